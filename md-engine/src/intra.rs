//! Threads inside one box (`md-worker direct`, large boxes): the single-element EAM force
//! evaluation split over rayon's current pool with a fixed partition and fixed-order sums, so
//! the result is bitwise the same for any thread count.
//!
//! Rows of the half list are cut into fixed blocks of [`ROWS`] atoms (atom index order, which
//! for a lattice-built box is spatial order). The serial kernels scatter into the neighbour
//! atom (`rho[j] += v`, `f[j] -= fd`), which threads cannot share; here each block scatters
//! into a window of its own: one slot per atom its rows name (its own rows first, then the
//! neighbours in order of first appearance), with the serial kernels' additions in the
//! serial order within the block. Each atom's density and force are then the sum of its
//! slots over the blocks that name it, in block order. The partition, the slots and every
//! order of addition depend on the list alone, so densities, forces, energy and virial and
//! therefore trajectories are bitwise the same for any thread count, on every SIMD path (the
//! per-pair arithmetic is the scalar's on each). They differ from the serial kernel's single
//! running sums by round-off. A window costs about (ROWS + the rows' neighbours beyond the
//! block) slots, a few per atom in spatial order (the 43,200-atom bar: 1.96 at 256 rows),
//! against one term per list entry (~43 per atom) of the column gather this replaced
//! (md-engine/README.md, the h15w log). Each block reads its own filtered copy of its rows
//! (`simd`'s inner list, as the box kernel does).
//!
//! Potentials of several elements and LJ take the serial kernel.

use crate::neighbor::NeighborList;
use crate::potential::EamTables;
use crate::simd::{self, SimdPath};
use rayon::prelude::*;
use std::cell::{Cell, RefCell};

/// Atoms per block of the fixed partition (independent of the thread count).
pub const ROWS: usize = 256;

thread_local! {
    static ON: Cell<bool> = const { Cell::new(false) };
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
    /// Per thread: atom -> window slot of the block it is working on.
    static MAP: RefCell<Vec<u32>> = const { RefCell::new(Vec::new()) };
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
    /// The windows of the list they were built for (`NeighborList::generation`).
    generation: u64,
    n: usize,
    /// The atom of each slot of the concatenated windows; block b's window is
    /// `win_start[b]..win_start[b + 1]` (its rows first, then its rows' neighbours).
    atoms: Vec<u32>,
    win_start: Vec<usize>,
    /// Per atom a: its positions in the concatenated windows, in block order
    /// (`pos[pos_start[a]..pos_start[a + 1]]`).
    pos_start: Vec<u32>,
    pos: Vec<u32>,
    /// Per-block pair buffers.
    blocks: Vec<simd::Scratch>,
    /// The concatenated windows: densities, forces.
    win_rho: Vec<f64>,
    win_f: Vec<[f64; 3]>,
    /// Per block: embedding energy, pair energy and virial.
    pe_embed: Vec<f64>,
    pair: Vec<(f64, [f64; 6])>,
}

/// The blocks' windows of `list` over `n` atoms (see the module doc).
fn windows(list: &NeighborList, n: usize, s: &mut Scratch) {
    let rows = |b: usize| b * ROWS..((b + 1) * ROWS).min(n);
    let nb = n.div_ceil(ROWS);
    // The block that last named each atom.
    let mut seen = vec![u32::MAX; n];
    let atoms = &mut s.atoms;
    atoms.clear();
    s.win_start.clear();
    s.win_start.push(0);
    for b in 0..nb {
        let r = rows(b);
        for i in r.clone() {
            seen[i] = b as u32;
            atoms.push(i as u32);
        }
        for &j in &list.j[list.start[r.start] as usize..list.start[r.end] as usize] {
            if seen[j as usize] != b as u32 {
                seen[j as usize] = b as u32;
                atoms.push(j);
            }
        }
        s.win_start.push(atoms.len());
    }
    // Positions ascend with the block, so each atom's come out in block order.
    s.pos_start.clear();
    s.pos_start.resize(n + 1, 0);
    for &a in atoms.iter() {
        s.pos_start[a as usize + 1] += 1;
    }
    for a in 0..n {
        s.pos_start[a + 1] += s.pos_start[a];
    }
    let mut fill = s.pos_start[..n].to_vec();
    let atoms = &s.atoms;
    s.pos.clear();
    s.pos.resize(atoms.len(), 0);
    for (p, &a) in atoms.iter().enumerate() {
        s.pos[fill[a as usize] as usize] = p as u32;
        fill[a as usize] += 1;
    }
    s.n = n;
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
    lo: [f64; 3],
    l: [f64; 3],
    skin: f64,
    f: &mut [[f64; 3]],
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
) -> (f64, [f64; 6]) {
    let n = xu.len();
    assert!(f.len() == n && list.is_built(n));
    let sh = simd::Shared::new(path, t, list, xu, shift, lo, l, skin);
    // A task stolen while this thread waits on its own passes could re-enter: it then gets
    // fresh buffers (same results: the windows and filtered lists are rebuilt).
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
    if list.generation == 0 || s.generation != list.generation || s.n != n {
        windows(list, n, s);
        s.generation = list.generation;
    }
    let nb = n.div_ceil(ROWS);
    let total = s.win_start[nb];
    s.blocks.resize_with(nb, Default::default);
    s.win_rho.resize(total, 0.0);
    s.win_f.resize(total, [0.0; 3]);
    s.pe_embed.resize(nb, 0.0);
    s.pair.resize(nb, (0.0, [0.0; 6]));
    let rows = |b: usize| b * ROWS..((b + 1) * ROWS).min(n);
    let (ws, atoms) = (&s.win_start, &s.atoms);
    // Pass 1: pairs, and each block's density sums into its window.
    {
        let win = pieces(&mut s.win_rho, (0..nb).map(|b| ws[b + 1] - ws[b]));
        s.blocks.par_iter_mut().zip(win).enumerate().for_each(|(b, (bs, w))| {
            MAP.with(|m| {
                let mut m = m.borrow_mut();
                m.resize(n, 0);
                simd::block_density(sh, rows(b), bs, &atoms[ws[b]..ws[b + 1]], &mut m, w);
            });
        });
    }
    // Pass 2: each atom's density (its slots in block order), embedding.
    rho.clear();
    rho.resize(n, 0.0);
    fp.clear();
    fp.resize(n, 0.0);
    {
        let (ps, pos, win) = (&s.pos_start, &s.pos, &s.win_rho);
        rho.par_chunks_mut(ROWS).zip(fp.par_chunks_mut(ROWS)).zip(s.pe_embed.par_iter_mut()).enumerate().for_each(|(b, ((rb, fb), pe))| {
            let mut e = 0.0;
            for (o, (r, d)) in rb.iter_mut().zip(fb.iter_mut()).enumerate() {
                let a = b * ROWS + o;
                let mut acc = 0.0;
                for &p in &pos[ps[a] as usize..ps[a + 1] as usize] {
                    acc += win[p as usize];
                }
                *r = acc;
                let (phi, dv) = t.embed(0, acc);
                *d = dv;
                e += phi;
            }
            *pe = e;
        });
    }
    // Pass 3: each block's force sums into its window, the blocks' energy and virial.
    {
        let win = pieces(&mut s.win_f, (0..nb).map(|b| ws[b + 1] - ws[b]));
        let fp = &fp[..];
        s.blocks.par_iter_mut().zip(win).zip(s.pair.par_iter_mut()).enumerate().for_each(|(b, ((bs, w), out))| {
            *out = simd::block_force(sh, rows(b), bs, fp, w);
        });
    }
    // Pass 4: each atom's force (its slots in block order).
    {
        let (ps, pos, win) = (&s.pos_start, &s.pos, &s.win_f);
        f.par_chunks_mut(ROWS).enumerate().for_each(|(b, fb)| {
            for (o, fo) in fb.iter_mut().enumerate() {
                let a = b * ROWS + o;
                let mut acc = [0.0f64; 3];
                for &p in &pos[ps[a] as usize..ps[a + 1] as usize] {
                    let w = win[p as usize];
                    acc[0] += w[0];
                    acc[1] += w[1];
                    acc[2] += w[2];
                }
                *fo = acc;
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
    fn any_thread_count_and_path_gives_the_same_bits_near_the_serial_trajectory() {
        let p = pot("Cu_mishin1.eam.alloy");
        // 4,000 atoms: 16 blocks, the last one short.
        let cells = [10, 10, 10];
        let serial = run_bits(&p, cells, SimdPath::Scalar, None, 30);
        let one = run_bits(&p, cells, SimdPath::Scalar, Some(1), 30);
        for path in SimdPath::supported() {
            for t in [1, 2, 3, 4] {
                let got = run_bits(&p, cells, path, Some(t), 30);
                assert!(got == one, "path {path}: {t} threads differ from the scalar path on 1 thread");
            }
        }
        // The blocks' windows sum in another order than the serial kernel's running sums:
        // round-off apart, and the same trajectory to 1e-9 A after 30 hot steps.
        let n = one.0.len() / 9;
        let worst =
            one.0[..3 * n].iter().zip(&serial.0[..3 * n]).map(|(a, b)| (f64::from_bits(*a) - f64::from_bits(*b)).abs()).fold(0.0, f64::max);
        assert!(worst > 0.0 && worst < 1e-9, "positions differ from the serial kernel's by {worst} A");
        for (a, b) in one.1.iter().zip(&serial.1) {
            let (a, b) = (f64::from_bits(*a), f64::from_bits(*b));
            assert!((a - b).abs() <= 1e-10 * b.abs().max(1.0), "{a} vs serial {b}");
        }
    }
}
