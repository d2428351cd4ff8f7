//! Direct MD (`md-worker direct`): a 2D impact sample ([`ImpactSpec`], [`Bar::impact`], Eulerian
//! x-y bins [`Bar::bin_stress`]), or a bar: one large fcc/bcc/sc box, periodic in y and z,
//! with walls in x made of frozen end layers, a prescribed initial engineering strain per
//! region along x, and the virial stress binned in slabs of the reference x position
//! (thesis Ch. 6.3: per-atom virial stress summed per slab over the slab volume). It is the
//! all-atom reference the coupled runs are checked against.
//!
//! x is made non-periodic by a vacuum gap wider than the neighbour radius on both sides of
//! the bar, so the periodic kernels of [`crate::kernel`] serve unchanged. Frozen atoms keep
//! their initial positions and zero velocity; they still exert forces.

use crate::error::MdError;
use crate::kernel::{self, BoxMeta, BoxView, DeformMode};
use crate::lattice::{self, LatticeKind};
use crate::neighbor::NeighborList;
use crate::potential::Potential;
use crate::units::{EV_PER_A3_TO_GPA, FTM2V, MVV2E};
use rayon::prelude::*;

/// Atoms per task of the bar's integration loops.
const CHUNK: usize = 4096;

/// A region [x0, x1) of the reference bar (A) with an initial engineering strain along x.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Start, reference x (A).
    pub x0: f64,
    /// End, reference x (A).
    pub x1: f64,
    /// Engineering strain along x (negative: compression).
    pub strain: f64,
}

impl std::str::FromStr for Region {
    type Err = MdError;
    /// `x0:x1:strain`, x in A of the reference bar.
    fn from_str(s: &str) -> Result<Self, MdError> {
        let bad = || MdError::invalid("region", format!("{s:?}; expected x0:x1:strain (A, A, engineering strain)"));
        let p: Vec<f64> = s.split(':').map(|t| t.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad())?;
        match p[..] {
            [x0, x1, strain] if x0 < x1 && strain > -1.0 && strain.is_finite() => Ok(Region { x0, x1, strain }),
            _ => Err(bad()),
        }
    }
}

/// A bar run.
#[derive(Debug, Clone, PartialEq)]
pub struct BarSpec {
    /// Lattice.
    pub kind: LatticeKind,
    /// Lattice constant (A).
    pub a0: f64,
    /// Cells along x, y, z (conventional cells, or oriented cells of a0 |o_k|).
    pub cells: [usize; 3],
    /// Crystal directions along x, y, z.
    pub orient: crate::Orientation,
    /// Thickness of each frozen end layer (A, reference x).
    pub wall_a: f64,
    /// Initial strain regions (later ones win where they overlap).
    pub regions: Vec<Region>,
    /// Initial temperature (K; Maxwell at twice this, as the boxes; 0: at rest).
    pub temperature_k: f64,
    /// Seed of the velocities.
    pub seed: u64,
    /// Slab width (A, reference x).
    pub slab_a: f64,
    /// Neighbour skin (A).
    pub skin: f64,
}

/// Stress of the slabs at one time.
#[derive(Debug, Clone, PartialEq)]
pub struct SlabStress {
    /// Time (ps).
    pub time_ps: f64,
    /// Slab centres, reference x (A).
    pub center_a: Vec<f64>,
    /// sxx, syy, szz per slab (GPa, tension positive).
    pub stress_gpa: Vec<[f64; 3]>,
}

/// The bar: atoms, reference positions, frozen flags.
pub struct Bar {
    pot: std::sync::Arc<Potential>,
    masses: Vec<f64>,
    meta: BoxMeta,
    types: Vec<u32>,
    x: Vec<[f64; 3]>,
    v: Vec<[f64; 3]>,
    f: Vec<[f64; 3]>,
    x_build: Vec<[f64; 3]>,
    img: Vec<[i32; 3]>,
    list: NeighborList,
    rho: Vec<f64>,
    fp: Vec<f64>,
    /// Reference (unstrained) x of every atom (A).
    pub x_ref: Vec<f64>,
    frozen: Vec<bool>,
    slab_a: f64,
    bar_len_ref: f64,
    /// Where y = 0 of the output lies in the box (A; 2D impact runs).
    y_origin: f64,
    time_ps: f64,
    /// The EAM kernel path (`MSCALE_MD_SIMD`, else `SimdPath::best()`; the same bits on all).
    simd: crate::simd::SimdPath,
}

/// x after the initial strain: x' = integral_0^x (1 + e(s)) ds.
fn strained_x(x: f64, regions: &[Region]) -> f64 {
    // Piecewise: fine steps of the regions' ends suffice (strain is piecewise constant).
    let mut cuts: Vec<f64> = vec![0.0, x];
    for r in regions {
        for c in [r.x0, r.x1] {
            if c > 0.0 && c < x {
                cuts.push(c);
            }
        }
    }
    cuts.sort_by(f64::total_cmp);
    let strain_at = |s: f64| regions.iter().rev().find(|r| s >= r.x0 && s < r.x1).map_or(0.0, |r| r.strain);
    cuts.windows(2).map(|w| (w[1] - w[0]) * (1.0 + strain_at(0.5 * (w[0] + w[1])))).sum()
}

impl Bar {
    /// Build the bar, strain it, set velocities and the first forces.
    pub fn new(pot: std::sync::Arc<Potential>, s: &BarSpec) -> Result<Bar, MdError> {
        if s.cells.contains(&0) || !(s.a0 > 0.0) || !(s.slab_a > 0.0) || !(s.wall_a >= 0.0) || !(s.skin > 0.0) {
            return Err(MdError::invalid("bar", "needs cells >= 1, a0 > 0, slab > 0, wall >= 0, skin > 0"));
        }
        let (mut x, l) = lattice::build_oriented(s.kind, s.a0, s.cells, &s.orient)?;
        let n = x.len();
        let bar_len_ref = l[0];
        let rs = pot.cutoff() + s.skin;
        let x_ref: Vec<f64> = x.iter().map(|p| p[0]).collect();
        let gap = 2.0 * rs;
        let len = strained_x(bar_len_ref, &s.regions);
        for p in &mut x {
            p[0] = gap + strained_x(p[0], &s.regions);
        }
        let lengths = [len + 2.0 * gap, l[1], l[2]];
        let x_max = x_ref.iter().copied().fold(0.0, f64::max);
        let frozen: Vec<bool> = x_ref.iter().map(|&xr| xr < s.wall_a || xr > x_max - s.wall_a).collect();
        let mut v = vec![[0.0; 3]; n];
        if s.temperature_k > 0.0 {
            let m = vec![pot.mass(0); n];
            let mut rng = lattice::rng_for(s.seed, 0, 3, 0);
            v = lattice::maxwell_velocities(&mut rng, &m, 2.0 * s.temperature_k);
        }
        for (vi, fr) in v.iter_mut().zip(&frozen) {
            if *fr {
                *vi = [0.0; 3];
            }
        }
        let mut bar = Bar::assemble(pot, x, v, frozen, lengths, s.seed, s.skin)?;
        bar.x_ref = x_ref;
        bar.slab_a = s.slab_a;
        bar.bar_len_ref = bar_len_ref;
        Ok(bar)
    }

    /// A system of atoms at `x` (inside [0, lengths), one element), velocities `v`, the frozen
    /// ones at rest, periodic box `lengths`, with its neighbour list and first forces. The 1D
    /// fields (`x_ref`, slabs) are left empty for the caller.
    fn assemble(
        pot: std::sync::Arc<Potential>,
        x: Vec<[f64; 3]>,
        v: Vec<[f64; 3]>,
        frozen: Vec<bool>,
        lengths: [f64; 3],
        seed: u64,
        skin: f64,
    ) -> Result<Bar, MdError> {
        let n = x.len();
        let masses: Vec<f64> = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
        let types = vec![0u32; n];
        let meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l: lengths,
            lo_build: [0.0; 3],
            l_build: lengths,
            mode: DeformMode::Affine,
            seed,
            skin,
            step: 0,
            pe: 0.0,
            virial: [0.0; 6],
            rebuilds: 0,
        };
        let mut bar = Bar {
            pot,
            masses,
            meta,
            types,
            x: x.clone(),
            v,
            f: vec![[0.0; 3]; n],
            x_build: x,
            img: vec![[0; 3]; n],
            list: NeighborList::default(),
            rho: Vec::new(),
            fp: Vec::new(),
            x_ref: Vec::new(),
            frozen,
            slab_a: 1.0,
            bar_len_ref: 0.0,
            y_origin: 0.0,
            time_ps: 0.0,
            simd: crate::simd::selected()?,
        };
        let pot = bar.pot.clone();
        let (mut rho, mut fp) = (std::mem::take(&mut bar.rho), std::mem::take(&mut bar.fp));
        let simd = bar.simd;
        {
            let mut b = bar.view();
            kernel::rebuild(&pot, &mut b);
            kernel::with_simd(simd, || kernel::compute_forces(&pot, &mut b, &mut rho, &mut fp));
        }
        bar.rho = rho;
        bar.fp = fp;
        Ok(bar)
    }

    fn view(&mut self) -> BoxView<'_> {
        BoxView {
            meta: &mut self.meta,
            types: &self.types,
            x: &mut self.x,
            v: &mut self.v,
            f: &mut self.f,
            x_build: &mut self.x_build,
            img: &mut self.img,
            list: &mut self.list,
        }
    }

    /// The MD step guard ([`kernel::check_box`]) on the bar as it is now: a diverged bar is
    /// [`MdError::Diverged`] with the diagnosis.
    pub fn check(&mut self) -> Result<(), MdError> {
        let (pot, masses) = (self.pot.clone(), self.masses.clone());
        kernel::check_box(&pot, &masses, &self.view())
    }

    /// Atoms in the bar.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether the bar has no atom.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Frozen atoms.
    pub fn frozen_count(&self) -> usize {
        self.frozen.iter().filter(|f| **f).count()
    }

    /// Potential and kinetic energy (eV).
    pub fn energy(&self) -> (f64, f64) {
        (self.meta.pe, kernel::total_kinetic(&self.types, &self.v, &self.masses))
    }

    /// Total momentum (amu A/ps).
    pub fn momentum(&self) -> [f64; 3] {
        let mut p = [0.0; 3];
        for (t, v) in self.types.iter().zip(&self.v) {
            for d in 0..3 {
                p[d] += self.masses[*t as usize] * v[d];
            }
        }
        p
    }

    /// Sum of the forces on the frozen atoms (eV/A): minus the wall's push on the moving ones,
    /// so the moving atoms' momentum changes by minus its time integral.
    pub fn frozen_force(&self) -> [f64; 3] {
        let mut f = [0.0; 3];
        for (fi, fr) in self.f.iter().zip(&self.frozen) {
            if *fr {
                for d in 0..3 {
                    f[d] += fi[d];
                }
            }
        }
        f
    }

    /// Time since the start (ps).
    pub fn time_ps(&self) -> f64 {
        self.time_ps
    }

    /// `steps` velocity-Verlet steps of `dt` ps; frozen atoms do not move.
    pub fn run(&mut self, steps: u64, dt: f64) {
        let dtf = 0.5 * dt * FTM2V;
        let pot = self.pot.clone();
        let dtfm: Vec<f64> = self.masses.iter().map(|m| dtf / m).collect();
        let (mut rho, mut fp) = (std::mem::take(&mut self.rho), std::mem::take(&mut self.fp));
        // Out of the bar while its view borrows the rest.
        let frozen = std::mem::take(&mut self.frozen);
        let simd = self.simd;
        // Velocity Verlet, atom by atom over the current pool (elementwise: the same bits for
        // any thread count). Frozen atoms are never integrated.
        let kick = |types: &[u32], v: &mut [[f64; 3]], f: &[[f64; 3]]| {
            v.par_chunks_mut(CHUNK).enumerate().for_each(|(k, vc)| {
                for (i, vi) in (k * CHUNK..).zip(vc) {
                    if !frozen[i] {
                        let h = dtfm[types[i] as usize];
                        for d in 0..3 {
                            vi[d] += h * f[i][d];
                        }
                    }
                }
            })
        };
        let drift = |x: &mut [[f64; 3]], v: &[[f64; 3]]| {
            x.par_chunks_mut(CHUNK).enumerate().for_each(|(k, xc)| {
                for (i, xi) in (k * CHUNK..).zip(xc) {
                    if !frozen[i] {
                        for d in 0..3 {
                            xi[d] += dt * v[i][d];
                        }
                    }
                }
            })
        };
        for _ in 0..steps {
            kick(&self.types, &mut self.v, &self.f);
            drift(&mut self.x, &self.v);
            let mut b = self.view();
            // Frozen atoms never move, and lie inside the box, so wrapping leaves them be.
            if kernel::needs_rebuild(&pot, &b) {
                kernel::rebuild(&pot, &mut b);
            }
            kernel::with_simd(simd, || kernel::compute_forces(&pot, &mut b, &mut rho, &mut fp));
            kick(b.types, b.v, b.f);
            b.meta.step += 1;
            self.time_ps += dt;
        }
        self.frozen = frozen;
        self.rho = rho;
        self.fp = fp;
    }

    /// Slab stresses now: per-atom virial (pair half-and-half) plus kinetic m v v, summed over
    /// the atoms whose reference x falls in each slab, over the slab's current volume (its
    /// current x extent from the centroids of the neighbouring slabs, times Ly Lz).
    pub fn slab_stress(&self) -> SlabStress {
        let view = BoxViewRef { bar: self };
        let w = view.virials();
        let nslab = ((self.bar_len_ref / self.slab_a).round() as usize).max(1);
        let width = self.bar_len_ref / nslab as f64;
        let mut sum = vec![[0.0f64; 3]; nslab];
        let mut cx = vec![(0.0f64, 0usize); nslab];
        for i in 0..self.x.len() {
            // Nudged so lattice planes on a slab boundary all go to the upper slab.
            let k = ((self.x_ref[i] / width + 1e-6).floor() as usize).min(nslab - 1);
            let m = self.masses[self.types[i] as usize] * MVV2E;
            for d in 0..3 {
                sum[k][d] += w[i][d] + m * self.v[i][d] * self.v[i][d];
            }
            cx[k].0 += self.x[i][0] + self.img[i][0] as f64 * self.meta.l[0];
            cx[k].1 += 1;
        }
        let c: Vec<f64> = cx.iter().map(|(s, n)| s / (*n).max(1) as f64).collect();
        let area = self.meta.l[1] * self.meta.l[2];
        let mut stress = Vec::with_capacity(nslab);
        for k in 0..nslab {
            let ext = if nslab == 1 {
                self.bar_len_ref
            } else if k == 0 {
                c[1] - c[0]
            } else if k == nslab - 1 {
                c[k] - c[k - 1]
            } else {
                0.5 * (c[k + 1] - c[k - 1])
            };
            let vol = ext * area;
            stress.push(std::array::from_fn(|d| -sum[k][d] / vol * EV_PER_A3_TO_GPA));
        }
        SlabStress { time_ps: self.time_ps, center_a: (0..nslab).map(|k| (k as f64 + 0.5) * width).collect(), stress_gpa: stress }
    }
}

/// A triangular notch cut into the far (y max) face of a 2D impact sample (A): apex at
/// (`apex_x`, `apex_y`), base on the sample's top face from `base_x0` to `base_x1`. An atom
/// lies in the notch (and is not created) when its lattice site is strictly inside the
/// triangle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Notch {
    pub apex_x: f64,
    pub apex_y: f64,
    pub base_x0: f64,
    pub base_x1: f64,
}

impl std::str::FromStr for Notch {
    type Err = MdError;
    /// `apex_x:apex_y:base_x0:base_x1` (A).
    fn from_str(s: &str) -> Result<Self, MdError> {
        let bad = || MdError::invalid("notch", format!("{s:?}; expected apex_x:apex_y:base_x0:base_x1 (A), base_x0 < apex_x < base_x1"));
        let p: Vec<f64> = s.split(':').map(|t| t.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad())?;
        match p[..] {
            [apex_x, apex_y, base_x0, base_x1] if base_x0 < apex_x && apex_x < base_x1 && p.iter().all(|v| v.is_finite()) => {
                Ok(Notch { apex_x, apex_y, base_x0, base_x1 })
            }
            _ => Err(bad()),
        }
    }
}

impl Notch {
    /// Whether (x, y) lies strictly inside the notch of a sample whose top face is `top`.
    pub fn contains(&self, x: f64, y: f64, top: f64) -> bool {
        if !(y > self.apex_y) || self.apex_y >= top {
            return false;
        }
        let f = (y - self.apex_y) / (top - self.apex_y);
        x > self.apex_x - f * (self.apex_x - self.base_x0) && x < self.apex_x + f * (self.base_x1 - self.apex_x)
    }
}

/// A 2D impact run (the notch jet): a sample of `cells` fcc/bcc/sc cells (x, y, z) at
/// y in [0, cells_y a0), periodic in x and z, moving at `velocity_y` onto a rigid block of
/// `block_cells` cells of the same crystal (frozen, at rest) below y = 0; the y faces are free
/// (a vacuum gap wider than the neighbour radius, so the periodic kernels serve unchanged).
#[derive(Debug, Clone, PartialEq)]
pub struct ImpactSpec {
    pub kind: LatticeKind,
    /// Lattice constant (A).
    pub a0: f64,
    /// Cells of the moving sample along x, y, z.
    pub cells: [usize; 3],
    /// Cells of the rigid block along y (below y = 0).
    pub block_cells: usize,
    /// Velocity of the sample along y (A/ps; negative: onto the block).
    pub velocity_y: f64,
    /// Notch in the sample's top face, if any.
    pub notch: Option<Notch>,
    /// Initial temperature (K; Maxwell at twice this about the sample's mean velocity, as the
    /// boxes; 0: no thermal motion).
    pub temperature_k: f64,
    pub seed: u64,
    /// Side of the square Eulerian x-y bins (A), from the origin.
    pub bin_a: f64,
    /// Neighbour skin (A).
    pub skin: f64,
    /// Vacuum above the sample's top face (A), besides the gap of twice the neighbour radius:
    /// room for the jet.
    pub headroom_a: f64,
}

/// Stresses of the Eulerian x-y bins at one time.
#[derive(Debug, Clone, PartialEq)]
pub struct BinStress {
    pub time_ps: f64,
    /// Bins along x and y (x fastest in `atoms` and `stress_gpa`).
    pub nx: usize,
    pub ny: usize,
    /// Bin side (A).
    pub bin_a: f64,
    /// Atoms (moving ones; the block lies below y = 0) per bin.
    pub atoms: Vec<usize>,
    /// Mass-weighted mean velocity per bin (A/ps), x and y.
    pub velocity: Vec<[f64; 2]>,
    /// sxx, syy, szz, sxy per bin (GPa, tension positive); 0 in an empty bin.
    pub stress_gpa: Vec<[f64; 4]>,
}

impl Bar {
    /// The 2D impact sample of `s` (see [`ImpactSpec`]) with its first forces.
    pub fn impact(pot: std::sync::Arc<Potential>, s: &ImpactSpec) -> Result<Bar, MdError> {
        if s.cells.contains(&0)
            || !(s.a0 > 0.0)
            || !(s.bin_a > 0.0)
            || !(s.skin > 0.0)
            || !(s.headroom_a >= 0.0)
            || !s.velocity_y.is_finite()
        {
            return Err(MdError::invalid("impact", "needs cells >= 1, a0 > 0, bin > 0, skin > 0, headroom >= 0 and a finite velocity"));
        }
        let ny = s.cells[1] + s.block_cells;
        let (sites, l) = lattice::build_oriented(s.kind, s.a0, [s.cells[0], ny, s.cells[2]], &crate::Orientation::CUBE)?;
        let block = s.block_cells as f64 * s.a0;
        let top = s.cells[1] as f64 * s.a0;
        let rs = pot.cutoff() + s.skin;
        let gap = 2.0 * rs;
        // Box y = output y + y_origin; the lowest block plane sits `gap` above the box's floor.
        let y_origin = gap + block;
        let tol = 1e-9 * s.a0;
        let mut x = Vec::with_capacity(sites.len());
        let mut frozen = Vec::with_capacity(sites.len());
        for p in sites {
            let y = p[1] - block;
            if s.notch.is_some_and(|n| n.contains(p[0], y, top)) {
                continue;
            }
            x.push([p[0], y + y_origin, p[2]]);
            frozen.push(y < -tol);
        }
        let moving: Vec<usize> = (0..x.len()).filter(|&i| !frozen[i]).collect();
        let mut v = vec![[0.0; 3]; x.len()];
        if s.temperature_k > 0.0 && !moving.is_empty() {
            let m = vec![pot.mass(0); moving.len()];
            let mut rng = lattice::rng_for(s.seed, 0, 3, 0);
            let vt = lattice::maxwell_velocities(&mut rng, &m, 2.0 * s.temperature_k);
            for (k, &i) in moving.iter().enumerate() {
                v[i] = vt[k];
            }
        }
        for &i in &moving {
            v[i][1] += s.velocity_y;
        }
        let lengths = [l[0], block + top + 2.0 * gap + s.headroom_a, l[2]];
        let mut bar = Bar::assemble(pot, x, v, frozen, lengths, s.seed, s.skin)?;
        bar.slab_a = s.bin_a;
        bar.y_origin = y_origin;
        Ok(bar)
    }

    /// Stresses of the Eulerian bins of side `slab_a` (the spec's bin) in the current x-y
    /// plane from the origin, over y from 0 to the box's top: per bin, minus the sum over its
    /// moving atoms of the per-atom virial (pair half and half) plus m (v - vbar)(v - vbar),
    /// vbar the bin's mass-weighted mean velocity, over the bin's volume (side^2 Lz). The
    /// frozen block (y < 0) is not binned; its pairs with the sample give the sample's atoms
    /// their halves.
    pub fn bin_stress(&self) -> BinStress {
        let w = BoxViewRef { bar: self }.virials();
        let (lx, lz, bin) = (self.meta.l[0], self.meta.l[2], self.slab_a);
        let nx = ((lx / bin).round() as usize).max(1);
        let bx = lx / nx as f64;
        let ny = (((self.meta.l[1] - self.y_origin) / bin).ceil() as usize).max(1);
        let m_amu: Vec<f64> = self.types.iter().map(|t| self.masses[*t as usize]).collect();
        let bin_of = |i: usize| -> Option<usize> {
            let xu = (self.x[i][0] + self.img[i][0] as f64 * lx).rem_euclid(lx);
            let y = self.x[i][1] + self.img[i][1] as f64 * self.meta.l[1] - self.y_origin;
            if self.frozen[i] || !(y >= 0.0) {
                return None;
            }
            // Nudged so lattice planes on a bin boundary (bins of whole cells) all go to the
            // upper bin, whatever the round-off of their coordinates.
            let (kx, ky) = (((xu / bx + 1e-6).floor() as usize).min(nx - 1), (y / bin + 1e-6).floor() as usize);
            (ky < ny).then_some(ky * nx + kx)
        };
        let nb = nx * ny;
        let mut atoms = vec![0usize; nb];
        let mut mom = vec![[0.0f64; 4]; nb]; // sum m v (3), sum m
        let bins: Vec<Option<usize>> = (0..self.x.len()).map(bin_of).collect();
        for (i, b) in bins.iter().enumerate() {
            if let Some(k) = *b {
                atoms[k] += 1;
                for d in 0..3 {
                    mom[k][d] += m_amu[i] * self.v[i][d];
                }
                mom[k][3] += m_amu[i];
            }
        }
        let vbar: Vec<[f64; 3]> = mom.iter().map(|m| if m[3] > 0.0 { [m[0] / m[3], m[1] / m[3], m[2] / m[3]] } else { [0.0; 3] }).collect();
        let mut sum = vec![[0.0f64; 4]; nb];
        for (i, b) in bins.iter().enumerate() {
            if let Some(k) = *b {
                let u: [f64; 3] = std::array::from_fn(|d| self.v[i][d] - vbar[k][d]);
                let m = m_amu[i] * MVV2E;
                sum[k][0] += w[i][0] + m * u[0] * u[0];
                sum[k][1] += w[i][1] + m * u[1] * u[1];
                sum[k][2] += w[i][2] + m * u[2] * u[2];
                sum[k][3] += w[i][3] + m * u[0] * u[1];
            }
        }
        let vol = bx * bin * lz;
        let stress_gpa = sum.iter().map(|s| std::array::from_fn(|c| -s[c] / vol * EV_PER_A3_TO_GPA + 0.0)).collect();
        BinStress { time_ps: self.time_ps, nx, ny, bin_a: bin, atoms, velocity: vbar.iter().map(|v| [v[0], v[1]]).collect(), stress_gpa }
    }
}

/// CSV header of the 2D bin output (`md-worker direct --dimension 2`).
pub const CSV_HEADER_2D: &str = "time_ps,bin_x_nm,bin_y_nm,atoms,vx_km_s,vy_km_s,sxx_gpa,syy_gpa,szz_gpa,sxy_gpa";

/// CSV rows of one 2D output: every bin, x fastest; bin centres in nm (tension positive).
pub fn csv_rows_2d(s: &BinStress) -> String {
    let mut out = String::new();
    for ky in 0..s.ny {
        for kx in 0..s.nx {
            let k = ky * s.nx + kx;
            let (st, v) = (s.stress_gpa[k], s.velocity[k]);
            out += &format!(
                "{},{},{},{},{},{},{},{},{},{}\n",
                s.time_ps,
                (kx as f64 + 0.5) * s.bin_a / 10.0,
                (ky as f64 + 0.5) * s.bin_a / 10.0,
                s.atoms[k],
                v[0] / 10.0,
                v[1] / 10.0,
                st[0],
                st[1],
                st[2],
                st[3]
            );
        }
    }
    out
}

/// Read-only access for the virial pass (the kernel takes a view of mutable slices).
struct BoxViewRef<'a> {
    bar: &'a Bar,
}

impl BoxViewRef<'_> {
    fn virials(&self) -> Vec<[f64; 6]> {
        let b = self.bar;
        let (mut meta, mut x, mut v, mut f, mut xb, mut img, mut list) =
            (b.meta.clone(), b.x.clone(), Vec::new(), Vec::new(), b.x_build.clone(), b.img.clone(), b.list.clone());
        let view =
            BoxView { meta: &mut meta, types: &b.types, x: &mut x, v: &mut v, f: &mut f, x_build: &mut xb, img: &mut img, list: &mut list };
        kernel::atom_virials(&b.pot, &view, &b.fp)
    }
}

/// CSV header of the slab output.
pub const CSV_HEADER: &str = "time_ps,slab_center_nm,sxx_gpa,syy_gpa,szz_gpa";

/// CSV rows of one output (tension positive).
pub fn csv_rows(s: &SlabStress) -> String {
    let mut out = String::new();
    for (c, st) in s.center_a.iter().zip(&s.stress_gpa) {
        out += &format!("{},{},{},{},{}\n", s.time_ps, c / 10.0, st[0], st[1], st[2]);
    }
    out
}

/// `md-worker direct` options.
#[cfg(feature = "cli")]
#[derive(Debug, Clone, clap::Args)]
pub struct DirectArgs {
    /// EAM potential file.
    #[arg(long)]
    pub potential: std::path::PathBuf,
    /// fcc, bcc or sc.
    #[arg(long, default_value = "fcc")]
    pub lattice: String,
    /// Lattice constant (A).
    #[arg(long)]
    pub a0: f64,
    /// Cells along x, y, z, e.g. 300,5,5 (oriented cells with --orient).
    #[arg(long, value_delimiter = ',')]
    pub cells: Vec<usize>,
    /// Crystal directions along x, y, z as X/Y/Z, e.g. 1,1,0/-1,1,0/0,0,1 (LAMMPS `orient`).
    #[arg(long, default_value = "1,0,0/0,1,0/0,0,1")]
    pub orient: crate::Orientation,
    /// Thickness of each frozen end layer (A).
    #[arg(long, default_value_t = 10.0)]
    pub wall: f64,
    /// Initial strain region x0:x1:strain (reference A); repeat for several.
    #[arg(long = "region")]
    pub regions: Vec<Region>,
    /// Initial temperature (K).
    #[arg(long, default_value_t = 0.0)]
    pub temperature: f64,
    /// Velocity seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Steps.
    #[arg(long)]
    pub steps: u64,
    /// Time step (ps).
    #[arg(long, default_value_t = 0.001)]
    pub dt: f64,
    /// Write slab stresses every N steps.
    #[arg(long, default_value_t = 100)]
    pub every: u64,
    /// Slab width (reference A).
    #[arg(long, default_value_t = 10.0)]
    pub slab: f64,
    /// CSV output (time_ps, slab_center_nm, sxx, syy, szz in GPa, tension positive; in 2D
    /// time_ps, bin_x_nm, bin_y_nm, atoms, vx_km_s, vy_km_s, sxx, syy, szz, sxy), written and
    /// flushed at every output.
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// Threads inside the bar (0: one per CPU); results are bitwise the same for any count.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// 1: the bar (frozen end layers, slabs of reference x); 2: the impact sample (a rigid
    /// block below y = 0, free top face, notch, Eulerian x-y bins; --cells is the moving sample).
    #[arg(long, default_value_t = 1)]
    pub dimension: u8,
    /// 2D: cells of the rigid (frozen) block below y = 0.
    #[arg(long, default_value_t = 5)]
    pub block_cells: usize,
    /// 2D: velocity of the sample along y (km/s; negative: onto the block).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub velocity_y: f64,
    /// 2D: triangular notch in the top face, apex_x:apex_y:base_x0:base_x1 (A).
    #[arg(long)]
    pub notch: Option<Notch>,
    /// 2D: side of the Eulerian x-y bins (A).
    #[arg(long, default_value_t = 18.075)]
    pub bin: f64,
    /// 2D: vacuum above the sample besides the neighbour gap (A).
    #[arg(long, default_value_t = 100.0)]
    pub headroom: f64,
    /// Neighbour skin (A).
    #[arg(long, default_value_t = 1.0)]
    pub skin: f64,
}

/// Run `md-worker direct` (forces threaded inside the bar, [`crate::intra`]).
#[cfg(feature = "cli")]
pub fn run_cli(a: &DirectArgs) -> Result<(), MdError> {
    crate::intra::on_threads(a.threads, || run_cli_on(a))?
}

#[cfg(feature = "cli")]
fn run_cli_on(a: &DirectArgs) -> Result<(), MdError> {
    let kind: LatticeKind = a.lattice.parse()?;
    if a.cells.len() != 3 || !(a.dt > 0.0 && a.dt.is_finite()) || a.every == 0 {
        return Err(MdError::invalid("direct", "needs --cells NX,NY,NZ, --dt > 0 and --every >= 1"));
    }
    let pot = std::sync::Arc::new(Potential::from_file(&a.potential)?);
    if let Some(vib) = pot.vibration()
        && a.dt > vib.max_dt_ps()
    {
        return Err(MdError::invalid(
            "direct --dt",
            format!("time step {} ps exceeds {:.6} ps, {vib}; use a smaller time step", a.dt, vib.max_dt_ps()),
        ));
    }
    if a.dimension == 2 {
        return run_cli_2d(a, kind, pot);
    }
    if a.dimension != 1 {
        return Err(MdError::invalid("direct --dimension", format!("{}; expected 1 (the bar) or 2 (the impact sample)", a.dimension)));
    }
    let spec = BarSpec {
        kind,
        a0: a.a0,
        cells: [a.cells[0], a.cells[1], a.cells[2]],
        orient: a.orient,
        wall_a: a.wall,
        regions: a.regions.clone(),
        temperature_k: a.temperature,
        seed: a.seed,
        slab_a: a.slab,
        skin: a.skin,
    };
    let mut bar = Bar::new(pot, &spec)?;
    let io = |e: std::io::Error| MdError::Io { file: a.out.display().to_string(), source: e };
    let mut out = std::io::BufWriter::new(std::fs::File::create(&a.out).map_err(io)?);
    use std::io::Write;
    writeln!(out, "{CSV_HEADER}").map_err(io)?;
    out.write_all(csv_rows(&bar.slab_stress()).as_bytes()).map_err(io)?;
    let mut done = 0;
    while done < a.steps {
        let k = a.every.min(a.steps - done);
        bar.run(k, a.dt);
        bar.check()?;
        done += k;
        out.write_all(csv_rows(&bar.slab_stress()).as_bytes()).map_err(io)?;
    }
    out.flush().map_err(io)?;
    let (pe, ke) = bar.energy();
    eprintln!("direct: {} atoms ({} frozen), {done} steps, E = {:.6} eV", bar.len(), bar.frozen_count(), pe + ke);
    Ok(())
}

/// `md-worker direct --dimension 2`: the impact sample, bins every `--every` steps (each
/// written and flushed as it comes, so a stopped run leaves its snapshots), a progress line
/// per output on stderr (time, energy, momentum, wall time per atom-step).
#[cfg(feature = "cli")]
fn run_cli_2d(a: &DirectArgs, kind: LatticeKind, pot: std::sync::Arc<Potential>) -> Result<(), MdError> {
    if !a.regions.is_empty() {
        return Err(MdError::invalid("direct --region", "is for the 1D bar; the 2D impact sample has no strain regions"));
    }
    let spec = ImpactSpec {
        kind,
        a0: a.a0,
        cells: [a.cells[0], a.cells[1], a.cells[2]],
        block_cells: a.block_cells,
        velocity_y: a.velocity_y * 10.0,
        notch: a.notch,
        temperature_k: a.temperature,
        seed: a.seed,
        bin_a: a.bin,
        skin: a.skin,
        headroom_a: a.headroom,
    };
    let t0 = std::time::Instant::now();
    let mut bar = Bar::impact(pot, &spec)?;
    let io = |e: std::io::Error| MdError::Io { file: a.out.display().to_string(), source: e };
    let mut out = std::io::BufWriter::new(std::fs::File::create(&a.out).map_err(io)?);
    use std::io::Write;
    writeln!(out, "{CSV_HEADER_2D}").map_err(io)?;
    out.write_all(csv_rows_2d(&bar.bin_stress()).as_bytes()).map_err(io)?;
    out.flush().map_err(io)?;
    let report = |bar: &Bar, done: u64, secs: f64| {
        let (pe, ke) = bar.energy();
        let p = bar.momentum();
        let per = if done > 0 { secs / (done as f64 * bar.len() as f64) * 1e9 } else { 0.0 };
        eprintln!(
            "direct 2d: t = {:.3} ps, step {done}, E = {:.6} eV (pe {:.6}, ke {:.6}), p = [{:.6e}, {:.6e}, {:.6e}] amu A/ps, {} rebuilds, {:.1} s, {per:.1} ns/atom-step",
            bar.time_ps,
            pe + ke,
            pe,
            ke,
            p[0],
            p[1],
            p[2],
            bar.meta.rebuilds,
            secs
        );
    };
    eprintln!("direct 2d: {} atoms ({} frozen), box {:?} A, {} steps of {} ps", bar.len(), bar.frozen_count(), bar.meta.l, a.steps, a.dt);
    report(&bar, 0, 0.0);
    let start = std::time::Instant::now();
    let mut done = 0;
    while done < a.steps {
        let k = a.every.min(a.steps - done);
        bar.run(k, a.dt);
        bar.check()?;
        done += k;
        out.write_all(csv_rows_2d(&bar.bin_stress()).as_bytes()).map_err(io)?;
        out.flush().map_err(io)?;
        report(&bar, done, start.elapsed().as_secs_f64());
    }
    eprintln!("direct 2d: done in {:.1} s (setup {:.1} s)", t0.elapsed().as_secs_f64(), (t0.elapsed() - start.elapsed()).as_secs_f64());
    Ok(())
}
