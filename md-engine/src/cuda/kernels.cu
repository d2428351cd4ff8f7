// mscale md-worker: batched EAM kernels, one thread block per box, a box's atoms contiguous.
//
// Written as phases separated by block barriers (FOR_THREADS ... END_THREADS), with no warp
// intrinsics and no thread-private variables living across a barrier (per-thread state that
// must survive a barrier lives in shared arrays indexed by the thread). Code between phases is
// block-uniform: every thread computes the same values from shared or constant data.
// Compiled two ways from this one source:
//   * by NVRTC for the device (the CUDA branch of the macros below);
//   * as host C++ through shim.h (MSCALE_HOST): blocks and threads become loops, each phase
//     runs for all threads before the next, shared memory is a local struct. The tests run
//     this host build against the reference back end.
// Reductions are fixed-order trees over thread slots, neighbour lists are full lists (each
// atom sums its own neighbours in list order), so no atomics are used: results are
// deterministic for a given device, build and precision.
// Precision: R = double (`double`) or R = float (`mixed`: spline arithmetic, densities, embedding
// derivatives and per-atom force sums in f32; distances, positions, velocities, integration,
// energies and stress in f64).

#ifdef MSCALE_HOST
#include "shim.h"
#else
#define DEVICE __device__
// MD_MIN_BLOCKS: the blocks per SM the compiler must fit (a register cap that survives into
// the PTX as .minnctapersm, unlike NVRTC's --maxrregcount, which the driver's JIT never sees);
// set for tuning runs through MSCALE_CUDA_NVRTC_OPTIONS="-DMD_MIN_BLOCKS=N".
#ifndef MD_MIN_BLOCKS
#define MD_MIN_BLOCKS 1
#endif
#define KERNEL_ENTRY(name) extern "C" __global__ void __launch_bounds__(MD_NT, MD_MIN_BLOCKS) name(const Params p)
#define BLOCK_INDEX ((int)blockIdx.x)
#define SHARED_DECL(T, v) __shared__ T v
// A phase: every thread of the block runs the body, then the block waits at a barrier.
#define FOR_THREADS(t) { const int t = (int)threadIdx.x; {
#define END_THREADS } } __syncthreads();
// After block-uniform code read shared data that a later phase overwrites.
#define UNIFORM_READ_DONE() __syncthreads();
#endif

#define MD_NT 128
#define WD 12   /* work doubles: g[9], dt, energy to add, spare */
#define WI 4    /* work ints: steps, energy mode (0 none, 1 scale, 2 random), stress average (0/1), spare */
#define BOXD 32 /* box doubles: lo 0, l 3, lo_build 6, l_build 9, skin 12, pe 13, virial 14..19 */
#define BOXI 8  /* box ints: step 0, rebuilds 1, mode 2 */
#define OUTD 24 /* out doubles: pe 0, virial 1..6, kin 7..12, lengths 13..15, shortfall 16,
                   sum over steps of -(kin + virial) / volume (eV/A^3) 17..22 (average only) */
#define OUTI 8  /* out ints: step 0, rebuilds 1, wraps 2, overflow (needed capacity) 3, energy not added 4 */
#define MODE_AFFINE 0
#define MODE_SEED 1

typedef long long i64;

struct Params {
    double* x;
    double* v;
    double* f;
    double* xb;
    int* img;
    const int* type;
    double* rho;
    double* fp;
    const double* vrand;
    int* nlist;
    int* nimg;
    int* ncount;
    const i64* off;
    double* boxd;
    i64* boxi;
    const int* work_box;
    const double* work_d;
    const i64* work_i;
    double* out_d;
    i64* out_i;
    const double* frho64;
    const double* rhor64;
    const double* z2r64;
    const float* frho32;
    const float* rhor32;
    const float* z2r32;
    const int* type2rhor;
    const int* type2z2r;
    const double* masses;
    double rdr, rdrho, rhomax, cutforcesq, cutoff, mvv2e, ftm2v;
    int nelem, nrho, nr, cap, nwork, pad;
};

struct Shared {
    double red[8][MD_NT];
    i64 wraps[MD_NT];
    double lo[3], l[3], lob[3], lb[3], nlo[3], nl[3], lstart[3], mid[3];
    double g[9];
    double vb[3];
    double wl[7];   /* pe and pair virial of the last force evaluation with energies */
    double acc[6];  /* average sampling: sum over steps of -(kin + virial) / volume */
    double dt, dtf, skin, lim, scale, shortfall, target, kin_sum;
    int n, off, mode, any, any2, overflow, no_energy, pad;
};

template <typename R> struct Tables {
    const R* frho;
    const R* rhor;
    const R* z2r;
};

DEVICE inline int unpack_image(int packed, int d) { return ((packed >> (10 * d)) & 1023) - 512; }

// The vector from neighbour image (j, n) to atom i: x_i - (x_j + n L), with face crossings.
DEVICE inline void pair_delta(const Params& p, const Shared& sh, int gi, int gj, int packed, double* dx) {
    for (int d = 0; d < 3; ++d) {
        const int shift = p.img[3 * gi + d] - p.img[3 * gj + d] - unpack_image(packed, d);
        dx[d] = p.x[3 * gi + d] - p.x[3 * gj + d] + (double)shift * sh.l[d];
    }
}

// LAMMPS pair_eam spline lookups (7 coefficients per knot: 0..2 derivative, 3..6 value).
// The knot index and the fraction come from r in f64 (in f32, r * rdr ~ 5000 would keep only
// ~1e-3 of the fraction); the spline arithmetic itself is in R.
template <typename R> DEVICE inline void r_index(const Params& p, double r, int* m, R* frac) {
    double q = r * p.rdr + 1.0;
    int k = (int)q;
    if (k > p.nr - 1) k = p.nr - 1;
    q = q - (double)k;
    *m = k;
    *frac = (R)(q < 1.0 ? q : 1.0);
}

template <typename R> DEVICE inline R density(const Params& p, const Tables<R>& tb, int ti, int tj, double r) {
    int m;
    R q;
    r_index<R>(p, r, &m, &q);
    const R* c = tb.rhor + ((i64)p.type2rhor[tj * p.nelem + ti] * (p.nr + 1) + m) * 7;
    return ((c[3] * q + c[4]) * q + c[5]) * q + c[6];
}

template <typename R> DEVICE inline R embed(const Params& p, const Tables<R>& tb, int e, R rho, R* phi_out) {
    R q = rho * (R)p.rdrho + (R)1;
    int m = (int)q;
    if (m > p.nrho - 1) m = p.nrho - 1;
    if (m < 1) m = 1;
    q = q - (R)m;
    if (q > (R)1) q = (R)1;
    const R* c = tb.frho + ((i64)e * (p.nrho + 1) + m) * 7;
    const R fprime = (c[0] * q + c[1]) * q + c[2];
    R phi = ((c[3] * q + c[4]) * q + c[5]) * q + c[6];
    if (rho > (R)p.rhomax) phi += fprime * (rho - (R)p.rhomax);
    *phi_out = phi;
    return fprime;
}

template <typename R>
DEVICE inline R pair_term(const Params& p, const Tables<R>& tb, int ti, int tj, double r, R fpi, R fpj, R* phi_out) {
    int m;
    R q;
    r_index<R>(p, r, &m, &q);
    const i64 stride = (i64)(p.nr + 1);
    const R* c = tb.rhor + ((i64)p.type2rhor[ti * p.nelem + tj] * stride + m) * 7;
    const R rhoip = (c[0] * q + c[1]) * q + c[2];
    c = tb.rhor + ((i64)p.type2rhor[tj * p.nelem + ti] * stride + m) * 7;
    const R rhojp = (c[0] * q + c[1]) * q + c[2];
    c = tb.z2r + ((i64)p.type2z2r[ti * p.nelem + tj] * stride + m) * 7;
    const R z2p = (c[0] * q + c[1]) * q + c[2];
    const R z2 = ((c[3] * q + c[4]) * q + c[5]) * q + c[6];
    const R recip = (R)(1.0 / r);
    const R phi = z2 * recip;
    const R phip = z2p * recip - phi * recip;
    *phi_out = phi;
    return fpi * rhojp + fpj * rhoip + phip;
}

// Fixed-order tree sum of sh.red[0..k][*] into sh.red[0..k][0].
DEVICE void block_sum(Shared& sh, int k) {
    for (int s = MD_NT / 2; s > 0; s >>= 1) {
        FOR_THREADS(t)
        if (t < s) {
            for (int c = 0; c < k; ++c) sh.red[c][t] += sh.red[c][t + s];
        }
        END_THREADS
    }
}

// Full neighbour list of every atom of the box from the build positions: all pairs and
// every periodic image within cutoff + skin, so boxes shorter than twice the cut-off are exact.
DEVICE void build_list(const Params& p, Shared& sh) {
    FOR_THREADS(t)
    const int n = sh.n, base = sh.off;
    const double rs = p.cutoff + sh.skin;
    const double rs2 = rs * rs;
    for (int i = t; i < n; i += MD_NT) {
        const int gi = base + i;
        int count = 0;
        for (int j = 0; j < n; ++j) {
            const int gj = base + j;
            double d0[3];
            int lo_n[3], hi_n[3];
            for (int d = 0; d < 3; ++d) {
                d0[d] = p.xb[3 * gj + d] - p.xb[3 * gi + d];
                lo_n[d] = (int)floor((-rs - d0[d]) / sh.lb[d]);
                hi_n[d] = (int)ceil((rs - d0[d]) / sh.lb[d]);
            }
            for (int a = lo_n[0]; a <= hi_n[0]; ++a) {
                for (int b = lo_n[1]; b <= hi_n[1]; ++b) {
                    for (int c = lo_n[2]; c <= hi_n[2]; ++c) {
                        if (j == i && a == 0 && b == 0 && c == 0) continue;
                        const double ex = p.xb[3 * gj + 0] + (double)a * sh.lb[0] - p.xb[3 * gi + 0];
                        const double ey = p.xb[3 * gj + 1] + (double)b * sh.lb[1] - p.xb[3 * gi + 1];
                        const double ez = p.xb[3 * gj + 2] + (double)c * sh.lb[2] - p.xb[3 * gi + 2];
                        if (ex * ex + ey * ey + ez * ez < rs2) {
                            if (count < p.cap) {
                                p.nlist[(i64)gi * p.cap + count] = j;
                                p.nimg[(i64)gi * p.cap + count] = (a + 512) | ((b + 512) << 10) | ((c + 512) << 20);
                            }
                            ++count;
                        }
                    }
                }
            }
        }
        p.ncount[gi] = count < p.cap ? count : p.cap;
        if (count > p.cap && count > sh.overflow) sh.overflow = count;  // plain op: any winner flags it
    }
    END_THREADS
}

// Forces, and (when `energies`) potential energy and pair virial into sh.red[0..7][0].
template <typename R> DEVICE void compute_forces(const Params& p, const Tables<R>& tb, Shared& sh, int energies) {
    FOR_THREADS(t)
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        const int ti = p.type[gi];
        R rho = (R)0;
        for (int c = 0; c < p.ncount[gi]; ++c) {
            const int gj = sh.off + p.nlist[(i64)gi * p.cap + c];
            double dx[3];
            pair_delta(p, sh, gi, gj, p.nimg[(i64)gi * p.cap + c], dx);
            const double r2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2];
            if (r2 < p.cutforcesq) rho += density<R>(p, tb, ti, p.type[gj], sqrt(r2));
        }
        p.rho[gi] = (double)rho;
    }
    END_THREADS
    FOR_THREADS(t)
    double pe = 0.0;
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        R phi;
        p.fp[gi] = (double)embed<R>(p, tb, p.type[gi], (R)p.rho[gi], &phi);
        pe += (double)phi;
    }
    sh.red[0][t] = pe;
    END_THREADS
    FOR_THREADS(t)
    double w[7] = {sh.red[0][t], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        const int ti = p.type[gi];
        const R fpi = (R)p.fp[gi];
        R fx = (R)0, fy = (R)0, fz = (R)0;
        for (int c = 0; c < p.ncount[gi]; ++c) {
            const int gj = sh.off + p.nlist[(i64)gi * p.cap + c];
            double dd[3];
            pair_delta(p, sh, gi, gj, p.nimg[(i64)gi * p.cap + c], dd);
            const R dx = (R)dd[0], dy = (R)dd[1], dz = (R)dd[2];
            const double r2 = dd[0] * dd[0] + dd[1] * dd[1] + dd[2] * dd[2];
            if (r2 < p.cutforcesq) {
                const double r = sqrt(r2);
                R phi;
                const R psip = pair_term<R>(p, tb, ti, p.type[gj], r, fpi, (R)p.fp[gj], &phi);
                const R fpair = -psip * (R)(1.0 / r);
                fx += dx * fpair;
                fy += dy * fpair;
                fz += dz * fpair;
                // Each pair is seen from both atoms: half of its energy and virial here.
                const double hf = 0.5 * (double)fpair;
                w[0] += 0.5 * (double)phi;
                w[1] += (double)dx * (double)dx * hf;
                w[2] += (double)dy * (double)dy * hf;
                w[3] += (double)dz * (double)dz * hf;
                w[4] += (double)dx * (double)dy * hf;
                w[5] += (double)dx * (double)dz * hf;
                w[6] += (double)dy * (double)dz * hf;
            }
        }
        p.f[3 * gi + 0] = (double)fx;
        p.f[3 * gi + 1] = (double)fy;
        p.f[3 * gi + 2] = (double)fz;
    }
    for (int c = 0; c < 7; ++c) sh.red[c][t] = w[c];
    END_THREADS
    if (energies) block_sum(sh, 7);
}

// Mass-weighted mean velocity into sh.vb, kinetic tensor about it into sh.red[0..6][0].
DEVICE void kinetic(const Params& p, Shared& sh) {
    FOR_THREADS(t)
    double s[4] = {0.0, 0.0, 0.0, 0.0};
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        const double m = p.masses[p.type[gi]];
        s[0] += m;
        for (int d = 0; d < 3; ++d) s[d + 1] += m * p.v[3 * gi + d];
    }
    for (int c = 0; c < 4; ++c) sh.red[c][t] = s[c];
    END_THREADS
    block_sum(sh, 4);
    FOR_THREADS(t)
    if (t == 0) {
        for (int d = 0; d < 3; ++d) sh.vb[d] = sh.red[0][0] > 0.0 ? sh.red[d + 1][0] / sh.red[0][0] : 0.0;
    }
    END_THREADS
    FOR_THREADS(t)
    double k[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        const double m = p.masses[p.type[gi]] * p.mvv2e;
        const double u0 = p.v[3 * gi] - sh.vb[0], u1 = p.v[3 * gi + 1] - sh.vb[1], u2 = p.v[3 * gi + 2] - sh.vb[2];
        k[0] += m * u0 * u0;
        k[1] += m * u1 * u1;
        k[2] += m * u2 * u2;
        k[3] += m * u0 * u1;
        k[4] += m * u0 * u2;
        k[5] += m * u1 * u2;
    }
    for (int c = 0; c < 6; ++c) sh.red[c][t] = k[c];
    END_THREADS
    block_sum(sh, 6);
}

// Wrap atoms into the box, take the build reference and rebuild the list.
DEVICE void rebuild(const Params& p, Shared& sh) {
    FOR_THREADS(t)
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        for (int d = 0; d < 3; ++d) {
            double s = p.x[3 * gi + d];
            while (s < sh.lo[d]) s += sh.l[d];
            while (s >= sh.lo[d] + sh.l[d]) s -= sh.l[d];
            p.x[3 * gi + d] = s;
            p.xb[3 * gi + d] = s;
            p.img[3 * gi + d] = 0;
        }
    }
    if (t == 0) {
        for (int d = 0; d < 3; ++d) {
            sh.lob[d] = sh.lo[d];
            sh.lb[d] = sh.l[d];
        }
    }
    END_THREADS
    build_list(p, sh);
}

// Whether some pair outside the list may have come within the cut-off (as the CPU engine).
DEVICE int needs_rebuild(const Params& p, Shared& sh) {
    FOR_THREADS(t)
    if (t == 0) {
        double mn = 0.0;
        for (int d = 0; d < 3; ++d) {
            const double ratio = sh.l[d] / sh.lb[d];
            mn = (d == 0 || ratio < mn) ? ratio : mn;
            sh.nl[d] = ratio;
        }
        const double margin = mn * (p.cutoff + sh.skin) - p.cutoff;
        sh.any = margin <= 0.0;
        sh.lim = 0.25 * margin * margin;
        sh.any2 = 0;
    }
    END_THREADS
    FOR_THREADS(t)
    if (!sh.any) {
        for (int i = t; i < sh.n; i += MD_NT) {
            const int gi = sh.off + i;
            double d2 = 0.0;
            for (int d = 0; d < 3; ++d) {
                const double now = p.x[3 * gi + d] + (double)p.img[3 * gi + d] * sh.l[d];
                const double ref = sh.lo[d] + (p.xb[3 * gi + d] - sh.lob[d]) * sh.nl[d];
                d2 += (now - ref) * (now - ref);
            }
            if (d2 > sh.lim) sh.any2 = 1;  // plain op: every writer writes 1
        }
    }
    END_THREADS
    const int r = sh.any || sh.any2;
    UNIFORM_READ_DONE()
    return r;
}

// Seed mode after the drift: grow the box by (5.7) about its centre, wrap atoms back (5.8)
// giving each wrapped atom the velocity of the image it becomes.
DEVICE void seed_box_and_wrap(const Params& p, Shared& sh) {
    FOR_THREADS(t)
    if (t == 0) {
        for (int d = 0; d < 3; ++d) {
            const double mid = sh.lo[d] + 0.5 * sh.l[d];
            sh.l[d] *= 1.0 + sh.g[4 * d] * sh.dt;
            sh.lo[d] = mid - 0.5 * sh.l[d];
        }
    }
    END_THREADS
    FOR_THREADS(t)
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        double shift[3] = {0.0, 0.0, 0.0};
        int moved = 0;
        for (int d = 0; d < 3; ++d) {
            const double xd = p.x[3 * gi + d];
            const double nf = floor((xd - sh.lo[d]) / sh.l[d]);
            if (nf != 0.0) {
                double s = xd - nf * sh.l[d];
                if (s >= sh.lo[d] + sh.l[d]) s = sh.lo[d] + sh.l[d] * (1.0 - 2.220446049250313e-16);
                if (s < sh.lo[d]) s = sh.lo[d];
                shift[d] = s - xd;
                p.x[3 * gi + d] = s;
                p.img[3 * gi + d] += (int)nf;
                sh.wraps[t] += 1;
                moved = 1;
            }
        }
        if (moved) {
            for (int a = 0; a < 3; ++a) {
                p.v[3 * gi + a] += sh.g[3 * a] * shift[0] + sh.g[3 * a + 1] * shift[1] + sh.g[3 * a + 2] * shift[2];
            }
        }
    }
    END_THREADS
}

// Thesis eq. 7.11: add `de` eV of kinetic energy about the mean velocity (scaled velocities,
// or at 0 K the host's random velocities in p.vrand).
DEVICE void add_energy(const Params& p, Shared& sh, double de, int mode) {
    kinetic(p, sh);
    FOR_THREADS(t)
    if (t == 0) {
        const double k = 0.5 * (sh.red[0][0] + sh.red[1][0] + sh.red[2][0]);
        double target = k + de;
        sh.shortfall = target < 0.0 ? -target : 0.0;
        target = target > 0.0 ? target : 0.0;
        sh.kin_sum = k;
        sh.target = target;
        sh.scale = k > 0.0 ? sqrt(target / k) : 0.0;
        sh.no_energy = (k <= 0.0 && target > 0.0 && mode != 2);
    }
    END_THREADS
    FOR_THREADS(t)
    for (int i = t; i < sh.n; i += MD_NT) {
        const int gi = sh.off + i;
        for (int d = 0; d < 3; ++d) {
            if (sh.kin_sum > 0.0) {
                p.v[3 * gi + d] = sh.vb[d] + sh.scale * (p.v[3 * gi + d] - sh.vb[d]);
            } else if (sh.target > 0.0 && mode == 2) {
                p.v[3 * gi + d] = sh.vb[d] + p.vrand[3 * gi + d];
            }
        }
    }
    END_THREADS
}

DEVICE void load_box(const Params& p, Shared& sh, int b) {
    FOR_THREADS(t)
    if (t == 0) {
        const double* bd = p.boxd + (i64)b * BOXD;
        for (int d = 0; d < 3; ++d) {
            sh.lo[d] = bd[d];
            sh.l[d] = bd[3 + d];
            sh.lob[d] = bd[6 + d];
            sh.lb[d] = bd[9 + d];
        }
        sh.skin = bd[12];
        sh.n = (int)(p.off[b + 1] - p.off[b]);
        sh.off = (int)p.off[b];
        sh.mode = (int)p.boxi[(i64)b * BOXI + 2];
        sh.overflow = 0;
        sh.no_energy = 0;
        sh.shortfall = 0.0;
    }
    sh.wraps[t] = 0;
    END_THREADS
}

// Build the lists of the listed boxes from their stored build positions (after an upload).
DEVICE void build_lists_block(const Params& p, int w) {
    SHARED_DECL(Shared, sh);
    const int b = p.work_box[w];
    load_box(p, sh, b);
    build_list(p, sh);
    FOR_THREADS(t)
    if (t == 0) p.out_i[(i64)w * OUTI + 3] = sh.overflow;
    END_THREADS
}

// Energy addition and `steps` velocity-Verlet steps with deformation of one box.
template <typename R> DEVICE void md_steps_block(const Params& p, const Tables<R>& tb, int w) {
    SHARED_DECL(Shared, sh);
    const int b = p.work_box[w];
    const double* wd = p.work_d + (i64)w * WD;
    const i64 steps = p.work_i[(i64)w * WI];
    const int energy_mode = (int)p.work_i[(i64)w * WI + 1];
    const int average = (int)p.work_i[(i64)w * WI + 2];
    load_box(p, sh, b);
    FOR_THREADS(t)
    if (t == 0) {
        for (int c = 0; c < 9; ++c) sh.g[c] = wd[c];
        sh.dt = wd[9];
        sh.dtf = 0.5 * wd[9] * p.ftm2v;
        for (int d = 0; d < 3; ++d) {
            sh.lstart[d] = sh.l[d];
            sh.mid[d] = sh.lo[d] + 0.5 * sh.l[d];
        }
    }
    END_THREADS
    const int mode = sh.mode;
    const int deforming = sh.g[0] != 0.0 || sh.g[4] != 0.0 || sh.g[8] != 0.0;
    if (energy_mode != 0) add_energy(p, sh, wd[10], energy_mode);
    i64 rebuilds = 0;
    for (i64 k = 1; k <= steps; ++k) {
        FOR_THREADS(t)
        for (int i = t; i < sh.n; i += MD_NT) {
            const int gi = sh.off + i;
            const double dtfm = sh.dtf / p.masses[p.type[gi]];
            for (int d = 0; d < 3; ++d) {
                p.v[3 * gi + d] += dtfm * p.f[3 * gi + d];
                p.x[3 * gi + d] += sh.dt * p.v[3 * gi + d];
            }
        }
        END_THREADS
        if (mode == MODE_SEED) seed_box_and_wrap(p, sh);
        if (needs_rebuild(p, sh)) {
            rebuild(p, sh);
            ++rebuilds;
        }
        const int energies = k == steps || average;
        compute_forces<R>(p, tb, sh, energies);
        if (energies) {
            FOR_THREADS(t)
            if (t == 0) {
                for (int c = 0; c < 7; ++c) sh.wl[c] = sh.red[c][0];
            }
            END_THREADS
        }
        FOR_THREADS(t)
        for (int i = t; i < sh.n; i += MD_NT) {
            const int gi = sh.off + i;
            const double dtfm = sh.dtf / p.masses[p.type[gi]];
            for (int d = 0; d < 3; ++d) p.v[3 * gi + d] += dtfm * p.f[3 * gi + d];
        }
        END_THREADS
        if (mode == MODE_AFFINE && deforming) {
            // LAMMPS fix deform (end_of_step): L = L0 exp(rate t) about the centre, atoms
            // remapped through their fractional coordinates.
            FOR_THREADS(t)
            if (t == 0) {
                const double time = (double)k * sh.dt;
                for (int d = 0; d < 3; ++d) {
                    const double ld = sh.lstart[d] * exp(sh.g[4 * d] * time);
                    sh.nlo[d] = sh.mid[d] - 0.5 * ld;
                    sh.nl[d] = ld;
                }
            }
            END_THREADS
            FOR_THREADS(t)
            for (int i = t; i < sh.n; i += MD_NT) {
                const int gi = sh.off + i;
                for (int d = 0; d < 3; ++d) {
                    const double lamda = (1.0 / sh.l[d]) * (p.x[3 * gi + d] - sh.lo[d]);
                    p.x[3 * gi + d] = sh.nl[d] * lamda + sh.nlo[d];
                }
            }
            END_THREADS
            FOR_THREADS(t)
            if (t == 0) {
                for (int d = 0; d < 3; ++d) {
                    sh.lo[d] = sh.nlo[d];
                    sh.l[d] = sh.nl[d];
                }
            }
            END_THREADS
        }
        if (average) {
            // The step's stress (before the GPa factor, applied on the host), summed in step
            // order; the same arithmetic as the host's end-of-call stress, so one step gives
            // exactly the last stress.
            kinetic(p, sh);
            FOR_THREADS(t)
            if (t == 0) {
                const double vol = sh.l[0] * sh.l[1] * sh.l[2];
                for (int c = 0; c < 6; ++c) {
                    const double s = -(sh.red[c][0] + sh.wl[1 + c]) / vol;
                    sh.acc[c] = k == 1 ? s : sh.acc[c] + s;
                }
            }
            END_THREADS
        }
    }
    // Energies of the last force evaluation (sh.red after compute_forces) go to the box.
    FOR_THREADS(t)
    if (t == 0) {
        double* bd = p.boxd + (i64)b * BOXD;
        i64* bi = p.boxi + (i64)b * BOXI;
        if (steps > 0) {
            for (int c = 0; c < 7; ++c) bd[13 + c] = sh.wl[c];
        }
        for (int d = 0; d < 3; ++d) {
            bd[d] = sh.lo[d];
            bd[3 + d] = sh.l[d];
            bd[6 + d] = sh.lob[d];
            bd[9 + d] = sh.lb[d];
        }
        bi[0] += steps;
        bi[1] += rebuilds;
        i64 wraps = 0;
        for (int s = 0; s < MD_NT; ++s) wraps += sh.wraps[s];
        i64* oi = p.out_i + (i64)w * OUTI;
        oi[0] = bi[0];
        oi[1] = bi[1];
        oi[2] = wraps;
        oi[3] = sh.overflow;
        oi[4] = sh.no_energy;
        double* od = p.out_d + (i64)w * OUTD;
        for (int c = 0; c < 7; ++c) od[c] = bd[13 + c];
        for (int d = 0; d < 3; ++d) od[13 + d] = sh.l[d];
        od[16] = sh.shortfall;
        for (int c = 0; c < 6; ++c) od[17 + c] = (average && steps > 0) ? sh.acc[c] : 0.0;
    }
    END_THREADS
    kinetic(p, sh);
    FOR_THREADS(t)
    if (t == 0) {
        double* od = p.out_d + (i64)w * OUTD;
        for (int c = 0; c < 6; ++c) od[7 + c] = sh.red[c][0];
    }
    END_THREADS
}

DEVICE inline Tables<double> tables64(const Params& p) {
    Tables<double> tb = {p.frho64, p.rhor64, p.z2r64};
    return tb;
}

DEVICE inline Tables<float> tables32(const Params& p) {
    Tables<float> tb = {p.frho32, p.rhor32, p.z2r32};
    return tb;
}

KERNEL_ENTRY(md_steps_double) { md_steps_block<double>(p, tables64(p), BLOCK_INDEX); }

KERNEL_ENTRY(md_steps_mixed) { md_steps_block<float>(p, tables32(p), BLOCK_INDEX); }

KERNEL_ENTRY(build_lists) { build_lists_block(p, BLOCK_INDEX); }

#ifdef MSCALE_HOST
// Lets the Rust side check that its copy of Params has the same layout.
extern "C" unsigned long mscale_host_params_size() { return (unsigned long)sizeof(Params); }
#endif
