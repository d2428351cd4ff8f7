//! Threads inside one box (`md-worker direct`, large boxes): the single-element EAM force
//! evaluation split over rayon's current pool with a fixed partition and fixed-order sums, so
//! the result is bitwise the same for any thread count.
//!
//! Rows of the half list are cut into fixed blocks of [`ROWS`] atoms (atom index order, which
//! for a lattice-built box is spatial order). The serial kernels scatter into the neighbour
//! atom (`rho[j] += v`, `f[j] -= fd`), which threads cannot share; here each block writes
//! every pair's term at its list entry instead, and a second pass gathers each atom's
//! column terms through a column index of the list (entries naming the atom, in list order),
//! then adds the atom's own row sum. That is exactly the serial kernels' order of additions
//! for every density and force, so densities, forces and therefore trajectories are bitwise
//! those of the serial kernel (and the `reference` back end) on every SIMD path and for any
//! thread count. The energy and virial are summed per block in pair order and the blocks'
//! sums then in block order: the same for any thread count, but they may differ from the
//! serial kernel's single running sum by round-off (they do not feed back into the motion).
//!
//! Potentials of several elements and LJ take the serial kernel.

use crate::neighbor::NeighborList;
use crate::potential::EamTables;
use crate::simd::{self, SimdPath};
use rayon::prelude::*;
use std::cell::{Cell, RefCell};

/// Atoms per block of the fixed partition (independent of the thread count).
pub const ROWS: usize = 64;

thread_local! {
    static ON: Cell<bool> = const { Cell::new(false) };
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// Run `f` with `kernel::compute_forces` on this thread threaded inside the box over
/// rayon's current pool (restored after, also on panic). Results are bitwise the same for any
/// pool size (see the module doc).
pub fn with_box_threads<R>(f: impl FnOnce() -> R) -> R {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            ON.with(|c| c.set(self.0));
        }
    }
    let _restore = Restore(ON.with(|c| c.replace(true)));
    f()
}

/// Run `f` on a pool of `threads` threads (0: rayon's default, the number of CPUs) with the
/// force evaluations threaded inside the box ([`with_box_threads`]).
pub fn on_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> Result<R, crate::error::MdError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| crate::error::MdError::invalid("threads", format!("cannot start {threads} threads: {e}")))?;
    Ok(pool.install(|| with_box_threads(f)))
}

/// Whether `kernel::compute_forces` threads inside the box on this thread.
pub fn enabled() -> bool {
    ON.with(|c| c.get())
}

/// The threaded kernel's buffers, kept between evaluations (on the calling thread).
#[derive(Default)]
struct Scratch {
    /// Column index of the list it was built for (`NeighborList::generation`).
    generation: u64,
    col_start: Vec<u32>,
    cols: Vec<u32>,
    /// Per-block pair buffers.
    blocks: Vec<simd::Scratch>,
    /// Per list entry: density value, force.
    vcol: Vec<f64>,
    fcol: Vec<[f64; 3]>,
    /// Per atom: own row sums.
    rho_row: Vec<f64>,
    fi_row: Vec<[f64; 3]>,
    /// Per block: embedding energy, pair energy and virial.
    pe_embed: Vec<f64>,
    pair: Vec<(f64, [f64; 6])>,
}

/// The column index: for each atom j, the list entries naming j, ascending.
fn columns(list: &NeighborList, n: usize, col_start: &mut Vec<u32>, cols: &mut Vec<u32>) {
    col_start.clear();
    col_start.resize(n + 1, 0);
    for &j in &list.j {
        col_start[j as usize + 1] += 1;
    }
    for a in 0..n {
        col_start[a + 1] += col_start[a];
    }
    let mut fill = col_start[..n].to_vec();
    cols.clear();
    cols.resize(list.j.len(), 0);
    for (k, &j) in list.j.iter().enumerate() {
        cols[fill[j as usize] as usize] = k as u32;
        fill[j as usize] += 1;
    }
}

/// Split `v` into consecutive pieces of the given lengths.
fn pieces<T>(mut v: &mut [T], lens: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut out = Vec::new();
    for len in lens {
        let (a, b) = std::mem::take(&mut v).split_at_mut(len);
        out.push(a);
        v = b;
    }
    out
}

/// EAM forces of a single-element potential, threaded inside the box: forces added to `f`
/// (zeroed by the caller), `rho`/`fp` filled; returns (energy, virial). `xu`/`shift` as in
/// `kernel::compute_forces`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn eam_forces(
    path: SimdPath,
    t: &EamTables,
    list: &NeighborList,
    xu: &[[f64; 3]],
    shift: &[[f64; 3]],
    l: [f64; 3],
    f: &mut [[f64; 3]],
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
) -> (f64, [f64; 6]) {
    let n = xu.len();
    assert!(f.len() == n && list.is_built(n));
    let sh = simd::Shared::new(path, t, list, xu, shift, l);
    // A task stolen while this thread waits on its own passes could re-enter: it then gets
    // fresh buffers (same results, only the column index is rebuilt).
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut s) => evaluate(&sh, t, list, f, rho, fp, &mut s),
        Err(_) => evaluate(&sh, t, list, f, rho, fp, &mut Scratch::default()),
    })
}

fn evaluate(
    sh: &simd::Shared,
    t: &EamTables,
    list: &NeighborList,
    f: &mut [[f64; 3]],
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
    s: &mut Scratch,
) -> (f64, [f64; 6]) {
    let n = f.len();
    {
        if list.generation == 0 || s.generation != list.generation || s.col_start.len() != n + 1 || s.cols.len() != list.len() {
            columns(list, n, &mut s.col_start, &mut s.cols);
            s.generation = list.generation;
        }
        let nb = n.div_ceil(ROWS);
        s.blocks.resize_with(nb, Default::default);
        s.vcol.resize(list.len(), 0.0);
        s.fcol.resize(list.len(), [0.0; 3]);
        s.rho_row.resize(n, 0.0);
        s.fi_row.resize(n, [0.0; 3]);
        s.pe_embed.resize(nb, 0.0);
        s.pair.resize(nb, (0.0, [0.0; 6]));
        let rows = |b: usize| b * ROWS..((b + 1) * ROWS).min(n);
        let entries = |b: usize| {
            let r = rows(b);
            (list.start[r.end] - list.start[r.start]) as usize
        };
        // Pass 1: pairs, densities at their entries, own row sums.
        {
            let vcol = pieces(&mut s.vcol, (0..nb).map(entries));
            s.blocks.par_iter_mut().zip(vcol).zip(s.rho_row.par_chunks_mut(ROWS)).enumerate().for_each(|(b, ((bs, vc), rr))| {
                simd::block_density(sh, rows(b), bs, vc, rr);
            });
        }
        // Pass 2: each atom's density (column terms in list order, then its row), embedding.
        rho.clear();
        rho.resize(n, 0.0);
        fp.clear();
        fp.resize(n, 0.0);
        {
            let (cs, cols, vcol, rr) = (&s.col_start, &s.cols, &s.vcol, &s.rho_row);
            rho.par_chunks_mut(ROWS).zip(fp.par_chunks_mut(ROWS)).zip(s.pe_embed.par_iter_mut()).enumerate().for_each(
                |(b, ((rb, fb), pe))| {
                    let mut e = 0.0;
                    for (o, (r, d)) in rb.iter_mut().zip(fb.iter_mut()).enumerate() {
                        let j = b * ROWS + o;
                        let mut acc = 0.0;
                        for &k in &cols[cs[j] as usize..cs[j + 1] as usize] {
                            acc += vcol[k as usize];
                        }
                        *r = acc + rr[j];
                        let (phi, dv) = t.embed(0, *r);
                        *d = dv;
                        e += phi;
                    }
                    *pe = e;
                },
            );
        }
        // Pass 3: forces at their entries, own row sums, the blocks' energy and virial.
        {
            let fcol = pieces(&mut s.fcol, (0..nb).map(entries));
            let fp = &fp[..];
            s.blocks.par_iter_mut().zip(fcol).zip(s.fi_row.par_chunks_mut(ROWS)).zip(s.pair.par_iter_mut()).enumerate().for_each(
                |(b, (((bs, fc), fr), out))| {
                    *out = simd::block_force(sh, rows(b), bs, fp, fc, fr);
                },
            );
        }
        // Pass 4: each atom's force (column terms subtracted in list order, then its row).
        {
            let (cs, cols, fcol, fr) = (&s.col_start, &s.cols, &s.fcol, &s.fi_row);
            f.par_chunks_mut(ROWS).enumerate().for_each(|(b, fb)| {
                for (o, fo) in fb.iter_mut().enumerate() {
                    let j = b * ROWS + o;
                    let mut acc = [0.0f64; 3];
                    for &k in &cols[cs[j] as usize..cs[j + 1] as usize] {
                        let fd = fcol[k as usize];
                        acc[0] -= fd[0];
                        acc[1] -= fd[1];
                        acc[2] -= fd[2];
                    }
                    *fo = [acc[0] + fr[j][0], acc[1] + fr[j][1], acc[2] + fr[j][2]];
                }
            });
        }
        // Fixed-order totals: embedding energies by block, then pair energies and virials.
        let mut pe = 0.0;
        for e in &s.pe_embed {
            pe += e;
        }
        let mut w = [0.0f64; 6];
        for (p, wb) in &s.pair {
            pe += p;
            for c in 0..6 {
                w[c] += wb[c];
            }
        }
        (pe, w)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::kernel::{self, BoxMeta, BoxView, DeformMode, Deformation};
    use crate::lattice::{self, LatticeKind};
    use crate::potential::Potential;

    fn pot(name: &str) -> Potential {
        Potential::from_file(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials").join(name)).unwrap()
    }

    /// A hot, perturbed, stretched fcc box run `steps` steps; the bits of x, v, f, and
    /// separately of the energy and virial. `threads`: None for the serial kernel.
    fn run_bits(p: &Potential, cells: [usize; 3], path: SimdPath, threads: Option<usize>, steps: u64) -> (Vec<u64>, Vec<u64>) {
        let (mut x, l) = lattice::build_oriented(LatticeKind::Fcc, 3.615, cells, &crate::Orientation::CUBE).unwrap();
        let n = x.len();
        for (k, q) in x.iter_mut().enumerate() {
            for d in 0..3 {
                q[d] += 0.3 * (((k * 7 + d * 13) as f64 * 0.618_033_988_75).fract() - 0.5);
            }
        }
        let mut meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l,
            lo_build: [0.0; 3],
            l_build: l,
            mode: DeformMode::Affine,
            seed: 0,
            skin: 1.0,
            step: 0,
            pe: 0.0,
            virial: [0.0; 6],
            rebuilds: 0,
        };
        let types = vec![0u32; n];
        let masses = [p.mass(0)];
        let mut rng = lattice::rng_for(5, 0, 3, 0);
        let mut v = lattice::maxwell_velocities(&mut rng, &vec![masses[0]; n], 1200.0);
        let (mut f, mut xb, mut img) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n], vec![[0i32; 3]; n]);
        let mut list = NeighborList::default();
        let mut b =
            BoxView { meta: &mut meta, types: &types, x: &mut x, v: &mut v, f: &mut f, x_build: &mut xb, img: &mut img, list: &mut list };
        let def = Deformation::new(DeformMode::Affine, &[[0.5, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]]);
        let (mut rho, mut fp) = (Vec::new(), Vec::new());
        let mut go = || {
            kernel::with_simd(path, || {
                kernel::rebuild(p, &mut b);
                kernel::compute_forces(p, &mut b, &mut rho, &mut fp);
                kernel::run_steps(p, &masses, &mut b, &def, steps, 0.002, &mut rho, &mut fp).unwrap();
            })
        };
        match threads {
            None => go(),
            Some(t) => on_threads(t, go).unwrap(),
        }
        assert!(b.meta.rebuilds > 1, "the run should rebuild its list");
        let state: Vec<u64> = b.x.iter().chain(b.v.iter()).chain(b.f.iter()).flatten().map(|c| c.to_bits()).collect();
        let mut sums = vec![b.meta.pe.to_bits()];
        sums.extend(b.meta.virial.map(f64::to_bits));
        (state, sums)
    }

    #[test]
    fn any_thread_count_gives_the_same_bits_and_the_serial_trajectory() {
        let p = pot("Cu_mishin1.eam.alloy");
        // 4,000 atoms: 63 blocks, the last one short.
        let cells = [10, 10, 10];
        for path in SimdPath::supported() {
            let serial = run_bits(&p, cells, SimdPath::Scalar, None, 30);
            let one = run_bits(&p, cells, path, Some(1), 30);
            assert!(one.0 == serial.0, "path {path}: 1 thread's trajectory differs from the serial kernel's");
            for t in [2, 3, 4] {
                let got = run_bits(&p, cells, path, Some(t), 30);
                assert!(got == one, "path {path}: {t} threads differ from 1 thread");
            }
            // The energy and virial are summed per block: round-off off the serial sums.
            for (a, b) in one.1.iter().zip(&serial.1) {
                let (a, b) = (f64::from_bits(*a), f64::from_bits(*b));
                assert!((a - b).abs() <= 1e-12 * b.abs().max(1.0), "path {path}: {a} vs serial {b}");
            }
        }
    }
}
