//! The per-box kernels: forces, neighbour-list upkeep, one velocity-Verlet step with
//! deformation, thermodynamic measures. Every function here works on one box's slices and
//! runs serially in a fixed order, so a box's result never depends on how boxes are spread
//! over threads. A GPU back end implements the same functions over the same flat layout.

use crate::neighbor::{self, NeighborList};
use crate::potential::Potential;
use crate::simd::SimdPath;
use crate::units::{BOLTZ, EV_PER_A3_TO_GPA, FTM2V, MVV2E};
use serde::{Deserialize, Serialize};

/// How a velocity gradient deforms a box.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DeformMode {
    /// Box lengths follow L = L0 exp(L_dd t); atoms are remapped affinely every step
    /// (LAMMPS `fix deform ... trate ... remap x`). Diagonal gradients only.
    #[default]
    Affine,
    /// The thesis's scheme (Ch. 5.2): the gradient is made upper triangular by adding a
    /// rotation (5.20), box lengths grow as (5.7), atoms leaving the box re-enter through the
    /// opposite face (5.8) and get the velocity of the image they become, `L' * shift`.
    /// Off-diagonal terms act only through those image velocities.
    Seed,
}

/// Per-box scalars (everything of a box that is not per atom).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoxMeta {
    /// Material point id.
    pub id: u64,
    /// Lower box corner (A).
    pub lo: [f64; 3],
    /// Box lengths (A).
    pub l: [f64; 3],
    /// Box corner and lengths when the neighbour list was built.
    pub lo_build: [f64; 3],
    /// Box lengths when the neighbour list was built (A).
    pub l_build: [f64; 3],
    /// Deformation mode.
    pub mode: DeformMode,
    /// Random seed of the box (with the point id it seeds every random draw).
    pub seed: u64,
    /// Neighbour skin (A).
    pub skin: f64,
    /// MD steps done.
    pub step: u64,
    /// Potential energy at the last force evaluation (eV).
    pub pe: f64,
    /// Pair virial at the last force evaluation, sum of r_a f_b (eV), order xx yy zz xy xz yz.
    pub virial: [f64; 6],
    /// Neighbour-list builds so far.
    pub rebuilds: u64,
}

/// One box's per-atom data, borrowed from the flat batch arrays.
pub struct BoxView<'a> {
    /// Scalars.
    pub meta: &'a mut BoxMeta,
    /// Element index per atom.
    pub types: &'a [u32],
    /// Positions (A).
    pub x: &'a mut [[f64; 3]],
    /// Velocities (A/ps).
    pub v: &'a mut [[f64; 3]],
    /// Forces (eV/A).
    pub f: &'a mut [[f64; 3]],
    /// Positions when the list was built (wrapped).
    pub x_build: &'a mut [[f64; 3]],
    /// Box crossings since the list was built (seed mode).
    pub img: &'a mut [[i32; 3]],
    /// Neighbour list.
    pub list: &'a mut NeighborList,
}

/// Wrap positions into the box; returns nothing, resets image counters. Bounded for any
/// input: an atom within a few box lengths steps back one length at a time (the arithmetic
/// results have always had), a farther one in one `rem_euclid` (a coordinate such as 1e308
/// would never change by adding L, and stepping would hang); a non-finite one is left as it is
/// (the engine refuses it before, and the step guard stops a box that produces one).
fn wrap_all(x: &mut [[f64; 3]], img: &mut [[i32; 3]], lo: [f64; 3], l: [f64; 3]) {
    for (p, im) in x.iter_mut().zip(img.iter_mut()) {
        for d in 0..3 {
            let mut s = p[d];
            if (s - lo[d]).abs() <= 4.0 * l[d] {
                while s < lo[d] {
                    s += l[d];
                }
                while s >= lo[d] + l[d] {
                    s -= l[d];
                }
            } else if s.is_finite() {
                s = lo[d] + (s - lo[d]).rem_euclid(l[d]);
                if !(s >= lo[d] && s < lo[d] + l[d]) {
                    s = lo[d]; // round-off of the remainder
                }
            }
            p[d] = s;
            im[d] = 0;
        }
    }
}

/// Most kinetic energy one atom may reach before the step guard stops its box (eV): about
/// 10^6 K, or a copper atom at 17 km/s; no solid survives it, and a diverging box passes it
/// within a few steps of going wrong.
pub const MAX_ATOM_KINETIC_EV: f64 = 100.0;

/// The step guard: after every step, every atom must be finite, within one box length of
/// the box (the engine wraps atoms long before that) and below [`MAX_ATOM_KINETIC_EV`], and
/// the box lengths finite and at least [`crate::neighbor::min_box_side`]. Read-only, so
/// results of valid runs are unchanged. The error names the point, the step and the atom.
pub fn check_box(pot: &Potential, masses: &[f64], b: &BoxView) -> Result<(), crate::error::MdError> {
    let m = &*b.meta;
    let fail = |msg: String| Err(crate::error::MdError::Diverged { point: m.id, msg: format!("at step {}: {msg}", m.step) });
    if let Some(msg) = collapsed(pot, m) {
        return fail(msg);
    }
    if !(m.pe.is_finite() && m.virial.iter().all(|w| w.is_finite())) {
        return fail(format!("the potential energy ({} eV) or the virial is not finite", m.pe));
    }
    for i in 0..b.x.len() {
        let (p, v, f) = (b.x[i], b.v[i], b.f[i]);
        if !(p.iter().chain(&v).chain(&f).all(|c| c.is_finite())) {
            return fail(format!(
                "atom {i} (index from 0) has a non-finite position {p:?}, velocity {v:?} or force {f:?}; use a smaller time step"
            ));
        }
        let ke = 0.5 * masses[b.types[i] as usize] * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * MVV2E;
        if !(ke <= MAX_ATOM_KINETIC_EV) {
            return fail(format!(
                "atom {i} (index from 0) has a kinetic energy of {ke:.6e} eV, above the bound {MAX_ATOM_KINETIC_EV} eV per atom (energy blow-up); use a smaller time step or check the input velocities and positions"
            ));
        }
        if let Some(d) = (0..3).find(|&d| !(p[d] >= m.lo[d] - m.l[d] && p[d] <= m.lo[d] + 2.0 * m.l[d])) {
            return fail(format!(
                "atom {i} (index from 0) is lost: {} = {} lies more than a box length outside [{}, {}]",
                ["x", "y", "z"][d],
                crate::error::show(p[d]),
                m.lo[d],
                m.lo[d] + m.l[d]
            ));
        }
    }
    Ok(())
}

/// Rebuild the neighbour list now (wraps atoms first).
pub fn rebuild(pot: &Potential, b: &mut BoxView) {
    wrap_all(b.x, b.img, b.meta.lo, b.meta.l);
    b.x_build.copy_from_slice(b.x);
    b.meta.lo_build = b.meta.lo;
    b.meta.l_build = b.meta.l;
    build_from_reference(pot, b);
}

/// Build the list from the stored reference positions (used again on restore, so a
/// restored box has exactly the list the original had).
pub fn build_from_reference(pot: &Potential, b: &mut BoxView) {
    neighbor::build(b.x_build, b.meta.lo_build, b.meta.l_build, pot.cutoff() + b.meta.skin, b.list);
    b.meta.rebuilds += 1;
}

/// Whether some pair outside the list may have come within the cut-off.
pub fn needs_rebuild(pot: &Potential, b: &BoxView) -> bool {
    let m = &*b.meta;
    let mut ratio = [0.0; 3];
    for d in 0..3 {
        ratio[d] = m.l[d] / m.l_build[d];
    }
    let min_ratio = ratio[0].min(ratio[1]).min(ratio[2]);
    let rc = pot.cutoff();
    let margin = min_ratio * (rc + m.skin) - rc;
    if margin <= 0.0 {
        return true;
    }
    let lim = 0.25 * margin * margin;
    for i in 0..b.x.len() {
        let mut d2 = 0.0;
        for d in 0..3 {
            let now = b.x[i][d] + b.img[i][d] as f64 * m.l[d];
            let reference = m.lo[d] + (b.x_build[i][d] - m.lo_build[d]) * ratio[d];
            d2 += (now - reference) * (now - reference);
        }
        if d2 > lim {
            return true;
        }
    }
    false
}

/// Per-thread scratch of the force kernel: unwrapped positions, image shifts, and the
/// in-cut-off pairs of the density pass (list index and distance) reused by the force pass.
#[derive(Default)]
struct ForceScratch {
    xu: Vec<[f64; 3]>,
    shift: Vec<[f64; 3]>,
    /// Pairs within the cut-off, row by row (`pair_end[i]` closes row i).
    pairs: Vec<Pair>,
    pair_end: Vec<u32>,
    /// The vector paths' buffers ([`crate::simd`]).
    simd: crate::simd::Scratch,
}

/// A pair within the cut-off found by the density pass.
#[derive(Clone, Copy)]
struct Pair {
    d: [f64; 3],
    r: f64,
    j: usize,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<ForceScratch> = std::cell::RefCell::new(ForceScratch::default());
    /// The EAM path [`compute_forces`] takes on this thread ([`with_simd`]); scalar unless set.
    static PATH: std::cell::Cell<SimdPath> = const { std::cell::Cell::new(SimdPath::Scalar) };
}

/// Run `f` with [`compute_forces`] on `path` on this thread (restored after, also on panic).
/// Every path gives bitwise the same results ([`crate::simd`]); only the speed differs. Code
/// outside such a call (the `reference` back end, tests) takes the scalar path.
///
/// # Panics
/// If this CPU does not run `path` ([`SimdPath::is_supported`]).
pub fn with_simd<R>(path: SimdPath, f: impl FnOnce() -> R) -> R {
    assert!(path.is_supported(), "simd path {path} is not supported by this CPU");
    struct Restore(SimdPath);
    impl Drop for Restore {
        fn drop(&mut self) {
            PATH.with(|p| p.set(self.0));
        }
    }
    let _restore = Restore(PATH.with(|p| p.replace(path)));
    f()
}

/// `f` on this thread's scratch of the vector paths (tests read its counters).
#[cfg(test)]
pub(crate) fn with_simd_scratch<R>(f: impl FnOnce(&crate::simd::Scratch) -> R) -> R {
    SCRATCH.with(|s| f(&s.borrow().simd))
}

/// The path [`compute_forces`] takes on this thread now.
pub fn simd_path() -> SimdPath {
    PATH.with(|p| p.get())
}

/// Make sure the box has a neighbour list (lists of idle boxes are released; rebuilding
/// from the stored reference positions gives exactly the list the box had).
fn ensure_list(pot: &Potential, b: &mut BoxView) {
    if !b.list.is_built(b.x.len()) {
        let rebuilds = b.meta.rebuilds;
        build_from_reference(pot, b);
        b.meta.rebuilds = rebuilds;
    }
}

/// Release a box's neighbour list (it is rebuilt, identically, when next needed).
pub fn release_list(b: &mut BoxView) {
    b.list.release();
}

/// Run `f` on the box with list-build reference positions and image counters held only for
/// the call: atoms are wrapped, the reference taken and the list built first, and the list
/// released after. Idle boxes so keep only types, positions, velocities and forces (76 bytes
/// per atom). Every call starts from a fresh list, so a box's trajectory depends on how its
/// steps are split into calls (at round-off level, deterministically), never on threads.
pub fn with_fresh_list<R>(pot: &Potential, b: &mut BoxView, f: impl FnOnce(&mut BoxView) -> R) -> R {
    let n = b.x.len();
    let (mut xb, mut img) = (vec![[0.0; 3]; n], vec![[0i32; 3]; n]);
    let mut v = BoxView {
        meta: &mut *b.meta,
        types: b.types,
        x: &mut *b.x,
        v: &mut *b.v,
        f: &mut *b.f,
        x_build: &mut xb,
        img: &mut img,
        list: &mut *b.list,
    };
    rebuild(pot, &mut v);
    let r = f(&mut v);
    v.list.release();
    r
}

/// Forces, potential energy and pair virial of one box. `rho`/`fp` are scratch.
pub fn compute_forces(pot: &Potential, b: &mut BoxView, rho: &mut Vec<f64>, fp: &mut Vec<f64>) {
    ensure_list(pot, b);
    SCRATCH.with(|s| {
        let s = &mut *s.borrow_mut();
        // Unwrapped positions and per-code shifts n * L: dx = xu_i - xu_j - shift[code].
        let l = b.meta.l;
        s.xu.clear();
        s.xu.extend(
            b.x.iter()
                .zip(b.img.iter())
                .map(|(p, im)| [p[0] + im[0] as f64 * l[0], p[1] + im[1] as f64 * l[1], p[2] + im[2] as f64 * l[2]]),
        );
        s.shift.clear();
        s.shift.extend(b.list.images.iter().map(|n| [n[0] as f64 * l[0], n[1] as f64 * l[1], n[2] as f64 * l[2]]));
        for f in b.f.iter_mut() {
            *f = [0.0; 3];
        }
        let (pe, w) = match pot {
            Potential::Eam(t) if t.masses.len() == 1 && crate::intra::enabled() => {
                crate::intra::eam_forces(simd_path(), t, b.list, &s.xu, &s.shift, b.meta.lo, l, b.meta.skin, b.f, rho, fp)
            }
            Potential::Eam(t) if t.masses.len() == 1 => match simd_path() {
                SimdPath::Scalar => eam_forces::<true>(t, b, s, rho, fp),
                path => crate::simd::eam_forces_one(
                    path,
                    t,
                    b.types,
                    b.list,
                    &s.xu,
                    &s.shift,
                    b.meta.lo,
                    l,
                    b.meta.skin,
                    b.f,
                    rho,
                    fp,
                    &mut s.simd,
                ),
            },
            Potential::Eam(t) => eam_forces::<false>(t, b, s, rho, fp),
            Potential::LjCut(lj) => lj_forces(lj, b, s),
        };
        b.meta.pe = pe;
        b.meta.virial = w;
    });
}

/// Cubic spline value at fraction `p` of row `c` (LAMMPS coefficient layout).
#[inline(always)]
fn spline_value(c: &[f64; 7], p: f64) -> f64 {
    ((c[3] * p + c[4]) * p + c[5]) * p + c[6]
}

/// Cubic spline derivative at fraction `p` of row `c`.
#[inline(always)]
fn spline_deriv(c: &[f64; 7], p: f64) -> f64 {
    (c[0] * p + c[1]) * p + c[2]
}

/// EAM: density pass over the half list (keeping the in-cut-off pairs and their r),
/// embedding pass, force pass over the kept pairs. `ONE`: single-element fast path.
fn eam_forces<const ONE: bool>(
    t: &crate::potential::EamTables,
    b: &mut BoxView,
    s: &mut ForceScratch,
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
) -> (f64, [f64; 6]) {
    let n = b.x.len();
    let ne = t.masses.len();
    let types = b.types;
    let list = &*b.list;
    let (xu, shift) = (&s.xu[..], &s.shift[..]);
    let cut2 = t.cutforcesq;
    let (rdr, nr) = (t.rdr, t.nr);
    // dens[tj * ne + ti]: density at an atom of element ti from one of element tj.
    let dens: Vec<&[[f64; 7]]> = (0..ne * ne).map(|k| &t.rhor[t.type2rhor[k / ne][k % ne]][..]).collect();
    let z2: Vec<&[[f64; 7]]> = (0..ne * ne).map(|k| &t.z2r[t.type2z2r[k / ne][k % ne]][..]).collect();
    // Spline row and fraction of r, as LAMMPS. Only called for 0 <= r < cut-off, so p is
    // finite and in [1, nr + 1]: the unchecked conversion cannot overflow.
    let index = |r: f64| {
        let p = r * rdr + 1.0;
        // SAFETY: p is finite and 1 <= p < 2^31 (r below the cut-off, rdr = 1/dr).
        let m = (unsafe { p.to_int_unchecked::<i32>() } as usize).min(nr - 1);
        (m, (p - m as f64).min(1.0))
    };
    rho.clear();
    rho.resize(n, 0.0);
    // Sized for every listed pair, filled by index (cheaper than push).
    s.pairs.clear();
    s.pairs.resize(list.len(), Pair { d: [0.0; 3], r: 0.0, j: 0 });
    s.pair_end.clear();
    let mut np = 0;
    for i in 0..n {
        let xi = xu[i];
        let ti = types[i] as usize;
        let mut rho_i = 0.0;
        let row = list.start[i] as usize..list.start[i + 1] as usize;
        let (js, codes) = (&list.j[row.clone()], &list.code[row]);
        for (&j, &c) in js.iter().zip(codes) {
            let (xj, sh) = (xu[j as usize], shift[c as usize]);
            let d = [xi[0] - xj[0] - sh[0], xi[1] - xj[1] - sh[1], xi[2] - xj[2] - sh[2]];
            let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if r2 < cut2 {
                let r = r2.sqrt();
                let j = j as usize;
                s.pairs[np] = Pair { d, r, j };
                np += 1;
                let (m, p) = index(r);
                if ONE {
                    let v = spline_value(&dens[0][m], p);
                    rho_i += v;
                    rho[j] += v;
                } else {
                    let tj = types[j] as usize;
                    rho_i += spline_value(&dens[tj * ne + ti][m], p);
                    rho[j] += spline_value(&dens[ti * ne + tj][m], p);
                }
            }
        }
        rho[i] += rho_i;
        s.pair_end.push(np as u32);
    }
    let mut pe = 0.0;
    fp.clear();
    fp.resize(n, 0.0);
    for i in 0..n {
        let (phi, d) = t.embed(types[i] as usize, rho[i]);
        fp[i] = d;
        pe += phi;
    }
    let mut w = [0.0f64; 6];
    let f = &mut *b.f;
    let mut q0 = 0;
    for i in 0..n {
        let ti = types[i] as usize;
        let fp_i = fp[i];
        let mut fi = [0.0; 3];
        let q1 = s.pair_end[i] as usize;
        for pr in &s.pairs[q0..q1] {
            let (d, r, j) = (pr.d, pr.r, pr.j);
            let (m, p) = index(r);
            let (rho_ip, rho_jp, c) = if ONE {
                let v = spline_deriv(&dens[0][m], p);
                (v, v, &z2[0][m])
            } else {
                let tj = types[j] as usize;
                // rho_ip: d rho_i(r)/dr of element i's density (as LAMMPS's rhoip).
                (spline_deriv(&dens[ti * ne + tj][m], p), spline_deriv(&dens[tj * ne + ti][m], p), &z2[ti * ne + tj][m])
            };
            let z2p = spline_deriv(c, p);
            let z2v = spline_value(c, p);
            let recip = 1.0 / r;
            let phi = z2v * recip;
            let phip = z2p * recip - phi * recip;
            let psip = fp_i * rho_jp + fp[j] * rho_ip + phip;
            let fpair = -psip * recip;
            pe += phi;
            let fd = [d[0] * fpair, d[1] * fpair, d[2] * fpair];
            fi[0] += fd[0];
            fi[1] += fd[1];
            fi[2] += fd[2];
            let fj = &mut f[j];
            fj[0] -= fd[0];
            fj[1] -= fd[1];
            fj[2] -= fd[2];
            w[0] += d[0] * fd[0];
            w[1] += d[1] * fd[1];
            w[2] += d[2] * fd[2];
            w[3] += d[0] * fd[1];
            w[4] += d[0] * fd[2];
            w[5] += d[1] * fd[2];
        }
        q0 = q1;
        let fo = &mut f[i];
        fo[0] += fi[0];
        fo[1] += fi[1];
        fo[2] += fi[2];
    }
    (pe, w)
}

/// Lennard-Jones (tests only): one pass over the half list.
fn lj_forces(lj: &crate::potential::LjCut, b: &mut BoxView, s: &ForceScratch) -> (f64, [f64; 6]) {
    let cut2 = lj.cutoff * lj.cutoff;
    let s6 = lj.sigma.powi(6);
    let (lj1, lj2) = (48.0 * lj.epsilon * s6 * s6, 24.0 * lj.epsilon * s6);
    let (lj3, lj4) = (4.0 * lj.epsilon * s6 * s6, 4.0 * lj.epsilon * s6);
    let list = &*b.list;
    let mut pe = 0.0;
    let mut w = [0.0f64; 6];
    for i in 0..b.x.len() {
        for k in list.start[i] as usize..list.start[i + 1] as usize {
            let j = list.j[k] as usize;
            let (xi, xj, sh) = (s.xu[i], s.xu[j], s.shift[list.code[k] as usize]);
            let d = [xi[0] - xj[0] - sh[0], xi[1] - xj[1] - sh[1], xi[2] - xj[2] - sh[2]];
            let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if r2 < cut2 {
                let r2inv = 1.0 / r2;
                let r6inv = r2inv * r2inv * r2inv;
                let fpair = r6inv * (lj1 * r6inv - lj2) * r2inv;
                pe += r6inv * (lj3 * r6inv - lj4);
                for c in 0..3 {
                    b.f[i][c] += d[c] * fpair;
                    b.f[j][c] -= d[c] * fpair;
                }
                w[0] += d[0] * d[0] * fpair;
                w[1] += d[1] * d[1] * fpair;
                w[2] += d[2] * d[2] * fpair;
                w[3] += d[0] * d[1] * fpair;
                w[4] += d[0] * d[2] * fpair;
                w[5] += d[1] * d[2] * fpair;
            }
        }
    }
    (pe, w)
}

/// Mass-weighted mean velocity (A/ps).
pub fn mean_velocity(types: &[u32], v: &[[f64; 3]], masses: &[f64]) -> [f64; 3] {
    let mut p = [0.0; 3];
    let mut mt = 0.0;
    for (t, vi) in types.iter().zip(v) {
        let m = masses[*t as usize];
        mt += m;
        for d in 0..3 {
            p[d] += m * vi[d];
        }
    }
    if mt > 0.0 {
        for pd in &mut p {
            *pd /= mt;
        }
    }
    p
}

/// Kinetic tensor about the mean velocity, sum m (v - vbar)_a (v - vbar)_b (eV), order
/// xx yy zz xy xz yz.
pub fn kinetic_tensor(types: &[u32], v: &[[f64; 3]], masses: &[f64]) -> [f64; 6] {
    let vb = mean_velocity(types, v, masses);
    let mut k = [0.0; 6];
    for (t, vi) in types.iter().zip(v) {
        let m = masses[*t as usize] * MVV2E;
        let u = [vi[0] - vb[0], vi[1] - vb[1], vi[2] - vb[2]];
        k[0] += m * u[0] * u[0];
        k[1] += m * u[1] * u[1];
        k[2] += m * u[2] * u[2];
        k[3] += m * u[0] * u[1];
        k[4] += m * u[0] * u[2];
        k[5] += m * u[1] * u[2];
    }
    k
}

/// Total kinetic energy 0.5 sum m v^2 (eV), not relative to the mean (as LAMMPS `ke`).
pub fn total_kinetic(types: &[u32], v: &[[f64; 3]], masses: &[f64]) -> f64 {
    let mut s = 0.0;
    for (t, vi) in types.iter().zip(v) {
        s += masses[*t as usize] * (vi[0] * vi[0] + vi[1] * vi[1] + vi[2] * vi[2]);
    }
    0.5 * s * MVV2E
}

/// Virial Cauchy stress (thesis eq. 2.25; GPa, tension positive, order xx yy zz xy xz yz):
/// -(sum m (v - vbar)(v - vbar) + sum r f) / V.
pub fn virial_stress(meta: &BoxMeta, kin: &[f64; 6]) -> [f64; 6] {
    let vol = meta.l[0] * meta.l[1] * meta.l[2];
    let mut s = [0.0; 6];
    for c in 0..6 {
        s[c] = -(kin[c] + meta.virial[c]) / vol * EV_PER_A3_TO_GPA;
    }
    s
}

/// Temperature (K) from the kinetic tensor, with 3N - 3 degrees of freedom (as LAMMPS).
pub fn temperature(kin: &[f64; 6], n: usize) -> f64 {
    let dof = (3 * n).saturating_sub(3).max(1) as f64;
    (kin[0] + kin[1] + kin[2]) / (dof * BOLTZ)
}

/// Validated per-call deformation: the gradient used by the mode.
#[derive(Debug, Clone, Copy)]
pub struct Deformation {
    /// Affine: diagonal rates; seed: the upper-triangular gradient L' of (5.20).
    pub g: [[f64; 3]; 3],
}

impl Deformation {
    /// Gradient for `mode` from the velocity gradient `l` (1/ps, l[i][j] = dv_i/dx_j).
    pub fn new(mode: DeformMode, l: &[[f64; 3]; 3]) -> Self {
        match mode {
            DeformMode::Affine => Deformation { g: *l },
            DeformMode::Seed => {
                // (5.20): add the rotation that zeroes the lower triangle.
                let mut g = *l;
                for i in 0..3 {
                    for j in 0..i {
                        g[j][i] += l[i][j];
                        g[i][j] = 0.0;
                    }
                }
                Deformation { g }
            }
        }
    }
}

/// Run `steps` velocity-Verlet steps of `dt` ps on one box. Forces in `b.f` must be those
/// of the current positions. Returns the number of atom wraps (seed mode), or the step
/// guard's diagnosis ([`check_box`], [`crate::error::MdError::Diverged`]) of the first step
/// that went wrong (the box is then left as that step made it).
#[allow(clippy::too_many_arguments)]
pub fn run_steps(
    pot: &Potential,
    masses: &[f64],
    b: &mut BoxView,
    def: &Deformation,
    steps: u64,
    dt: f64,
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
) -> Result<u64, crate::error::MdError> {
    run_steps_with(pot, masses, b, def, steps, dt, rho, fp, |_| {})
}

/// [`run_steps`], calling `after_step` on the box after every step (once the step is complete:
/// forces, velocities, box and positions all belong to the step's end, so a measure taken there
/// after the last step is the one taken after the call).
#[allow(clippy::too_many_arguments)]
pub fn run_steps_with(
    pot: &Potential,
    masses: &[f64],
    b: &mut BoxView,
    def: &Deformation,
    steps: u64,
    dt: f64,
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
    mut after_step: impl FnMut(&BoxView),
) -> Result<u64, crate::error::MdError> {
    let dtf = 0.5 * dt * FTM2V;
    let mode = b.meta.mode;
    let g = def.g;
    let rate = [g[0][0], g[1][1], g[2][2]];
    let l_start = b.meta.l;
    let mid: [f64; 3] = std::array::from_fn(|d| b.meta.lo[d] + 0.5 * b.meta.l[d]);
    let deforming = rate.iter().any(|r| *r != 0.0);
    let mut wraps = 0;
    for k in 1..=steps {
        for i in 0..b.x.len() {
            let dtfm = dtf / masses[b.types[i] as usize];
            for d in 0..3 {
                b.v[i][d] += dtfm * b.f[i][d];
                b.x[i][d] += dt * b.v[i][d];
            }
        }
        if mode == DeformMode::Seed {
            wraps += seed_box_and_wrap(b, &g, dt);
            // The box changed before the list check: a collapsed box must not reach the list.
            check_box_lengths(pot, b)?;
        }
        if needs_rebuild(pot, b) {
            rebuild(pot, b);
        }
        compute_forces(pot, b, rho, fp);
        for i in 0..b.x.len() {
            let dtfm = dtf / masses[b.types[i] as usize];
            for d in 0..3 {
                b.v[i][d] += dtfm * b.f[i][d];
            }
        }
        if mode == DeformMode::Affine && deforming {
            // LAMMPS fix deform (end_of_step): L = L0 exp(rate t) about the box centre,
            // atoms remapped through their fractional coordinates.
            let t = k as f64 * dt;
            let old_lo = b.meta.lo;
            let old_l = b.meta.l;
            for d in 0..3 {
                let ld = l_start[d] * (rate[d] * t).exp();
                b.meta.lo[d] = mid[d] - 0.5 * ld;
                b.meta.l[d] = ld;
            }
            for p in b.x.iter_mut() {
                for d in 0..3 {
                    let lamda = (1.0 / old_l[d]) * (p[d] - old_lo[d]);
                    p[d] = b.meta.l[d] * lamda + b.meta.lo[d];
                }
            }
        }
        b.meta.step += 1;
        check_box(pot, masses, b)?;
        after_step(b);
    }
    Ok(wraps)
}

/// Why the box's lengths stop it, if they do: not finite, or below the smallest side the
/// neighbour list can serve ([`crate::neighbor::min_box_side`]).
fn collapsed(pot: &Potential, m: &BoxMeta) -> Option<String> {
    let rs = pot.cutoff() + m.skin;
    let min_side = crate::neighbor::min_box_side(rs);
    (0..3).find(|&d| !(m.l[d].is_finite() && m.l[d] >= min_side)).map(|d| {
        format!(
            "box length {} A along {} is below {min_side} A (the neighbour radius {rs} A / 16): the box collapsed or blew up; use a smaller velocity gradient",
            m.l[d],
            ["x", "y", "z"][d]
        )
    })
}

/// The box-length part of [`check_box`] alone.
fn check_box_lengths(pot: &Potential, b: &BoxView) -> Result<(), crate::error::MdError> {
    match collapsed(pot, b.meta) {
        None => Ok(()),
        Some(msg) => Err(crate::error::MdError::Diverged { point: b.meta.id, msg: format!("at step {}: {msg}", b.meta.step + 1) }),
    }
}

/// Seed mode, after the drift: grow the box by (5.7) about its centre and wrap atoms back
/// (5.8), giving each wrapped atom the velocity of the image it becomes.
fn seed_box_and_wrap(b: &mut BoxView, g: &[[f64; 3]; 3], dt: f64) -> u64 {
    let mut wraps = 0;
    for d in 0..3 {
        let mid = b.meta.lo[d] + 0.5 * b.meta.l[d];
        b.meta.l[d] *= 1.0 + g[d][d] * dt;
        b.meta.lo[d] = mid - 0.5 * b.meta.l[d];
    }
    let (lo, l) = (b.meta.lo, b.meta.l);
    for i in 0..b.x.len() {
        let mut shift = [0.0; 3];
        for d in 0..3 {
            let n = ((b.x[i][d] - lo[d]) / l[d]).floor();
            if n != 0.0 {
                let mut s = b.x[i][d] - n * l[d];
                if s >= lo[d] + l[d] {
                    s = lo[d] + l[d] * (1.0 - f64::EPSILON); // round-off guard
                }
                if s < lo[d] {
                    s = lo[d];
                }
                shift[d] = s - b.x[i][d];
                b.x[i][d] = s;
                b.img[i][d] += n as i32;
                wraps += 1;
            }
        }
        if shift != [0.0; 3] {
            for a in 0..3 {
                b.v[i][a] += g[a][0] * shift[0] + g[a][1] * shift[1] + g[a][2] * shift[2];
            }
        }
    }
    wraps
}

/// Per-atom pair virials (eV), each pair's `d (x) f` split half and half between its two
/// atoms (thesis Ch. 6.3), order xx yy zz xy xz yz. `fp` is F'(rho) from the last
/// [`compute_forces`] (EAM; ignored for LJ). The list must be built.
pub fn atom_virials(pot: &Potential, b: &BoxView, fp: &[f64]) -> Vec<[f64; 6]> {
    let n = b.x.len();
    let l = b.meta.l;
    let list = &*b.list;
    let mut w = vec![[0.0f64; 6]; n];
    let xu: Vec<[f64; 3]> = (0..n).map(|i| std::array::from_fn(|d| b.x[i][d] + b.img[i][d] as f64 * l[d])).collect();
    for i in 0..n {
        for k in list.start[i] as usize..list.start[i + 1] as usize {
            let j = list.j[k] as usize;
            let im = list.images[list.code[k] as usize];
            let d: [f64; 3] = std::array::from_fn(|c| xu[i][c] - xu[j][c] - im[c] as f64 * l[c]);
            let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            let fpair = match pot {
                Potential::Eam(t) if r2 < t.cutforcesq => {
                    let r = r2.sqrt();
                    let (_, psip) = t.pair(b.types[i] as usize, b.types[j] as usize, r, fp[i], fp[j]);
                    -psip / r
                }
                Potential::LjCut(lj) if r2 < lj.cutoff * lj.cutoff => {
                    let s6 = lj.sigma.powi(6);
                    let r6inv = 1.0 / (r2 * r2 * r2);
                    r6inv * (48.0 * lj.epsilon * s6 * s6 * r6inv - 24.0 * lj.epsilon * s6) / r2
                }
                _ => continue,
            };
            let p = [d[0] * d[0], d[1] * d[1], d[2] * d[2], d[0] * d[1], d[0] * d[2], d[1] * d[2]];
            for c in 0..6 {
                let h = 0.5 * p[c] * fpair;
                w[i][c] += h;
                w[j][c] += h;
            }
        }
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrapping_is_bounded_for_absurd_coordinates_and_unchanged_for_near_ones() {
        let (lo, l) = ([0.0; 3], [10.8, 10.8, 10.8]);
        let mut img = vec![[5i32; 3]; 4];
        // 1e308 used to hang the stepping loop (1e308 - 10.8 == 1e308).
        let mut x = vec![
            [1e308, -1e308, 3.0],
            [-3.2 * 10.8 + 1.0, 2.0 * 10.8 + 0.5, 10.8],
            [f64::NAN, f64::INFINITY, -0.0],
            [1e12 + 0.25, 5.0, 5.0],
        ];
        wrap_all(&mut x, &mut img, lo, l);
        for p in [x[0], x[1], x[3]] {
            assert!(p.iter().all(|c| *c >= 0.0 && *c < 10.8), "{p:?}");
        }
        // Near atoms step by whole lengths, as before (bit for bit).
        assert_eq!(x[1], [-3.2 * 10.8 + 1.0 + 10.8 + 10.8 + 10.8 + 10.8, 2.0 * 10.8 + 0.5 - 10.8 - 10.8, 0.0]);
        // Non-finite coordinates are left for the guards (not looped on).
        assert!(x[2][0].is_nan() && x[2][1].is_infinite());
        assert!(img.iter().all(|i| *i == [0; 3]));
    }
}
