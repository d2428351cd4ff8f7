//! Direct MD of a bar (`md-worker direct`): one large fcc/bcc/sc box, periodic in y and z,
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
        let masses: Vec<f64> = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
        let types = vec![0u32; n];
        let mut v = vec![[0.0; 3]; n];
        if s.temperature_k > 0.0 {
            let m: Vec<f64> = types.iter().map(|t| masses[*t as usize]).collect();
            let mut rng = lattice::rng_for(s.seed, 0, 3, 0);
            v = lattice::maxwell_velocities(&mut rng, &m, 2.0 * s.temperature_k);
        }
        for (vi, fr) in v.iter_mut().zip(&frozen) {
            if *fr {
                *vi = [0.0; 3];
            }
        }
        let meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l: lengths,
            lo_build: [0.0; 3],
            l_build: lengths,
            mode: DeformMode::Affine,
            seed: s.seed,
            skin: s.skin,
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
            x_ref,
            frozen,
            slab_a: s.slab_a,
            bar_len_ref,
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

    /// `steps` velocity-Verlet steps of `dt` ps; frozen atoms do not move.
    pub fn run(&mut self, steps: u64, dt: f64) {
        let dtf = 0.5 * dt * FTM2V;
        let pot = self.pot.clone();
        let dtfm: Vec<f64> = self.masses.iter().map(|m| dtf / m).collect();
        let (mut rho, mut fp) = (std::mem::take(&mut self.rho), std::mem::take(&mut self.fp));
        // Out of the bar while its view borrows the rest.
        let frozen = std::mem::take(&mut self.frozen);
        let simd = self.simd;
        for _ in 0..steps {
            for i in 0..self.x.len() {
                if frozen[i] {
                    continue;
                }
                let h = dtfm[self.types[i] as usize];
                for d in 0..3 {
                    self.v[i][d] += h * self.f[i][d];
                    self.x[i][d] += dt * self.v[i][d];
                }
            }
            let mut b = self.view();
            // Frozen atoms never move, and lie inside the box, so wrapping leaves them be.
            if kernel::needs_rebuild(&pot, &b) {
                kernel::rebuild(&pot, &mut b);
            }
            kernel::with_simd(simd, || kernel::compute_forces(&pot, &mut b, &mut rho, &mut fp));
            for i in 0..b.x.len() {
                if frozen[i] {
                    continue;
                }
                let h = dtfm[b.types[i] as usize];
                for d in 0..3 {
                    b.v[i][d] += h * b.f[i][d];
                }
            }
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
    /// CSV output (time_ps, slab_center_nm, sxx, syy, szz in GPa, tension positive).
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// Threads inside the bar (0: one per CPU); results are bitwise the same for any count.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
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
        skin: 1.0,
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
