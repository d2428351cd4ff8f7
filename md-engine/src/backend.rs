//! The back-end seam: [`MdBackend`] and its request/response types, the flat batch layout,
//! and the `reference` (serial) and `cpu` (rayon over boxes) back ends.
//!
//! Both back ends run the same per-box kernels ([`crate::kernel`]); they differ only in how
//! boxes are spread over threads and in the EAM kernel path (`reference`: scalar always;
//! `cpu`: [`crate::simd::selected`], AVX-512 where the CPU has it, which gives the scalar's
//! bits). Each box is integrated serially in a fixed order, so the result of a box is bitwise
//! the same whatever the thread count, the batch order, the path, or the back end
//! (`reference` and `cpu` agree bit for bit).

use crate::error::MdError;
use crate::kernel::{self, BoxMeta, BoxView, DeformMode, Deformation};
use crate::lattice::{self, LatticeKind};
use crate::neighbor::NeighborList;
use crate::potential::Potential;
use crate::simd::SimdPath;
use crate::units::BOLTZ;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Material point id: names a box everywhere.
pub type PointId = u64;

/// Where a box's atoms come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InitialAtoms {
    /// A perfect cubic lattice.
    Lattice {
        /// fcc, bcc or sc.
        kind: LatticeKind,
        /// Lattice constant (A).
        a0: f64,
        /// Cells along x, y, z (conventional cells for the cube orientation; otherwise
        /// oriented cells of `a0 |o_k|` along axis k).
        cells: [usize; 3],
        /// Crystal directions along x, y, z (default [100] [010] [001]).
        #[serde(default)]
        orient: crate::Orientation,
    },
    /// Given atoms (e.g. from a LAMMPS data file).
    Explicit {
        /// Lower corner (A).
        lo: [f64; 3],
        /// Box lengths (A).
        lengths: [f64; 3],
        /// Element index (0-based) per atom.
        types: Vec<u32>,
        /// Positions (A).
        x: Vec<[f64; 3]>,
        /// Velocities (A/ps); empty for zero.
        v: Vec<[f64; 3]>,
    },
}

/// How to build and prepare one box.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoxSpec {
    /// Material point id.
    pub id: PointId,
    /// Initial atoms.
    pub atoms: InitialAtoms,
    /// Initial engineering strain of box and positions along x, y, z.
    pub strain: [f64; 3],
    /// Target temperature (K). If > 0, velocities are drawn (thesis Ch. 6.2) from a Maxwell
    /// distribution at twice this temperature with zero total momentum, deterministically from
    /// (seed, id); if 0, explicit velocities are kept (lattices start at rest).
    pub temperature_k: f64,
    /// Random seed (combined with the id).
    pub seed: u64,
    /// NVE relaxation steps at zero strain rate after the velocities are set.
    pub relax_steps: u64,
    /// Time step of relaxation (ps).
    pub relax_dt_ps: f64,
    /// Blocks of 100 steps that rescale the box lengths towards zero mean normal stress
    /// (0: keep the box lengths).
    pub relax_box_blocks: u32,
    /// Deformation mode.
    pub mode: DeformMode,
    /// Neighbour skin (A).
    pub skin: f64,
}

impl BoxSpec {
    /// A lattice box with defaults: no strain, 0 K, no relaxation, affine mode, skin 1 A.
    pub fn lattice(id: PointId, kind: LatticeKind, a0: f64, cells: [usize; 3]) -> Self {
        BoxSpec {
            id,
            atoms: InitialAtoms::Lattice { kind, a0, cells, orient: crate::Orientation::CUBE },
            strain: [0.0; 3],
            temperature_k: 0.0,
            seed: 0,
            relax_steps: 0,
            relax_dt_ps: 0.001,
            relax_box_blocks: 0,
            mode: DeformMode::Affine,
            skin: 1.0,
        }
    }

    /// The same box with the crystal directions `o` along x, y, z (lattice boxes only).
    pub fn oriented(mut self, o: crate::Orientation) -> Self {
        if let InitialAtoms::Lattice { orient, .. } = &mut self.atoms {
            *orient = o;
        }
        self
    }
}

/// Which stress a step call returns (thesis Ch. 6-7: the seed's default is the stress at the
/// last MD step; the alternative averages over the continuum step). Chosen per call.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StressSampling {
    /// The virial stress after the last MD step of the call.
    #[default]
    Last,
    /// The mean of the virial stresses after each MD step of the call (steps 1..=n, summed in
    /// step order, then divided by n: deterministic). A call of one step gives exactly `Last`;
    /// a call of zero steps gives the current stress, as `Last` does. Energies and temperature
    /// are not averaged (see [`BoxResult`]).
    Average,
}

impl StressSampling {
    /// `last` or `average`.
    pub fn name(self) -> &'static str {
        match self {
            StressSampling::Last => "last",
            StressSampling::Average => "average",
        }
    }
}

impl std::str::FromStr for StressSampling {
    type Err = MdError;
    fn from_str(s: &str) -> Result<Self, MdError> {
        match s {
            "last" => Ok(StressSampling::Last),
            "average" => Ok(StressSampling::Average),
            other => Err(MdError::invalid("stress sampling", format!("{other:?}; expected last or average"))),
        }
    }
}

/// One box's work in a step call.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoxWork {
    /// Which box.
    pub id: PointId,
    /// Velocity gradient, `l[i][j] = dv_i / dx_j` (1/ps).
    pub velocity_gradient: [[f64; 3]; 3],
    /// MD steps to run.
    pub steps: u64,
    /// MD time step (ps).
    pub dt_ps: f64,
    /// Energy added as thermal kinetic energy before the steps (eV); negative removes.
    pub energy_to_add_ev: f64,
    /// Which stress the call returns (absent in older serialisations: `last`).
    #[serde(default)]
    pub stress_sampling: StressSampling,
}

impl BoxWork {
    /// Work without energy addition, returning the stress at the last step.
    pub fn new(id: PointId, velocity_gradient: [[f64; 3]; 3], steps: u64, dt_ps: f64) -> Self {
        BoxWork { id, velocity_gradient, steps, dt_ps, energy_to_add_ev: 0.0, stress_sampling: StressSampling::Last }
    }
}

/// Diagnostics of one box after a step call.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Diagnostics {
    /// MD steps done by this box in total.
    pub total_steps: u64,
    /// Box lengths now (A).
    pub lengths_a: [f64; 3],
    /// Energy that could not be removed because the kinetic energy reached zero (eV, >= 0).
    pub energy_shortfall_ev: f64,
    /// Neighbour-list builds so far.
    pub neighbor_rebuilds: u64,
    /// Atom wraps through a face in this call (seed mode).
    pub wraps: u64,
}

/// One box's result.
///
/// Energies and temperature are always those at the end of the call, whatever the stress
/// sampling: energy consistency (thesis eq. 7.11) balances the box's energy between the ends of
/// continuum steps, and an averaged kinetic energy would not be the energy the box has.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct BoxResult {
    /// Which box.
    pub id: PointId,
    /// Virial Cauchy stress (GPa, tension positive), order xx yy zz xy xz yz: at the last step,
    /// or the mean over the call's steps (see `stress_sampling`).
    pub stress_gpa: [f64; 6],
    /// Potential energy at the end of the call (eV).
    pub potential_energy_ev: f64,
    /// Kinetic energy about the box's mean velocity at the end of the call (eV).
    pub kinetic_energy_ev: f64,
    /// Temperature at the end of the call (K), 3N - 3 degrees of freedom.
    pub temperature_k: f64,
    /// How `stress_gpa` was sampled (echoes the work's choice; the pool checks it, so a worker
    /// that ignores the choice is caught rather than silently returning the last stress).
    #[serde(default)]
    pub stress_sampling: StressSampling,
    /// Diagnostics.
    pub diagnostics: Diagnostics,
}

/// Everything of one box, for checkpoints. Restoring it gives bitwise the same future.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoxState {
    /// Scalars (id, box, step count, ...).
    pub meta: BoxMeta,
    /// Element per atom.
    pub types: Vec<u32>,
    /// Positions (A).
    pub x: Vec<[f64; 3]>,
    /// Velocities (A/ps).
    pub v: Vec<[f64; 3]>,
    /// Forces (eV/A).
    pub f: Vec<[f64; 3]>,
    /// Positions at the last neighbour-list build.
    pub x_build: Vec<[f64; 3]>,
    /// Face crossings since the last build.
    pub img: Vec<[i32; 3]>,
}

/// The MD back-end interface (see DESIGN.md).
pub trait MdBackend: Send {
    /// Build, equilibrate and add boxes.
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError>;
    /// Advance the named boxes; `out[k]` receives the result of `work[k]`.
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError>;
    /// Copy out the state of the named boxes.
    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError>;
    /// Put boxes back (replacing boxes of the same id, adding the others).
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError>;
    /// Back-end name (`reference`, `cpu`, ...).
    fn name(&self) -> &'static str;
}

/// All boxes of a back end in flat structure-of-arrays form: atom arrays of all boxes
/// end to end, box `b` owning `offsets[b]..offsets[b + 1]`.
#[derive(Debug, Default)]
pub struct Batch {
    /// Per-box scalars.
    pub meta: Vec<BoxMeta>,
    /// Atom offsets, length boxes + 1.
    pub offsets: Vec<usize>,
    /// Element per atom.
    pub types: Vec<u32>,
    /// Positions (A).
    pub x: Vec<[f64; 3]>,
    /// Velocities (A/ps).
    pub v: Vec<[f64; 3]>,
    /// Forces (eV/A).
    pub f: Vec<[f64; 3]>,
    /// Positions at the last list build: empty, kept per call only ([`kernel::with_fresh_list`]).
    pub x_build: Vec<[f64; 3]>,
    /// Face crossings since the last build: empty, kept per call only.
    pub img: Vec<[i32; 3]>,
    /// Neighbour lists, one per box (released between calls).
    pub lists: Vec<NeighborList>,
}

fn split<'a, T>(mut s: &'a mut [T], offsets: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(offsets.len().saturating_sub(1));
    for w in offsets.windows(2) {
        let (a, b) = std::mem::take(&mut s).split_at_mut(w[1] - w[0]);
        out.push(a);
        s = b;
    }
    out
}

/// `split`, or empty slices when `s` is not kept (per-call scratch).
fn split_or_empty<'a, T>(s: &'a mut [T], offsets: &[usize]) -> Vec<&'a mut [T]> {
    if s.is_empty() { offsets.windows(2).map(|_| <&mut [T]>::default()).collect() } else { split(s, offsets) }
}

impl Batch {
    fn from_states(pot: &Potential, states: Vec<BoxState>) -> Self {
        let mut b = Batch { offsets: vec![0], ..Default::default() };
        // Exact capacities: growth by doubling would leave up to half of each array unused.
        let n: usize = states.iter().map(|s| s.x.len()).sum();
        b.meta.reserve_exact(states.len());
        b.offsets.reserve_exact(states.len());
        b.lists.reserve_exact(states.len());
        b.types.reserve_exact(n);
        b.x.reserve_exact(n);
        b.v.reserve_exact(n);
        b.f.reserve_exact(n);
        for s in states {
            b.offsets.push(b.offsets.last().copied().unwrap_or(0) + s.x.len());
            b.meta.push(s.meta);
            b.types.extend(s.types);
            b.x.extend(s.x);
            b.v.extend(s.v);
            b.f.extend(s.f);
            // x_build and img are per-call scratch (kernel::with_fresh_list): not kept.
            b.lists.push(NeighborList::default());
        }
        // Neighbour lists are built lazily by the first force evaluation, from the stored
        // reference positions (so exactly the list the box had).
        let _ = pot;
        b
    }

    fn state(&self, k: usize) -> BoxState {
        let r = self.offsets[k]..self.offsets[k + 1];
        BoxState {
            meta: self.meta[k].clone(),
            types: self.types[r.clone()].to_vec(),
            x: self.x[r.clone()].to_vec(),
            v: self.v[r.clone()].to_vec(),
            f: self.f[r.clone()].to_vec(),
            x_build: self.x[r.clone()].to_vec(),
            img: vec![[0; 3]; r.len()],
        }
    }

    /// Mutable per-box views of the flat arrays.
    pub fn views(&mut self) -> Vec<BoxView<'_>> {
        let o = &self.offsets;
        let types = {
            let mut out = Vec::new();
            let mut s: &[u32] = &self.types;
            for w in o.windows(2) {
                let (a, b) = s.split_at(w[1] - w[0]);
                out.push(a);
                s = b;
            }
            out
        };
        let mut x = split(&mut self.x, o).into_iter();
        let mut v = split(&mut self.v, o).into_iter();
        let mut f = split(&mut self.f, o).into_iter();
        let mut xb = split_or_empty(&mut self.x_build, o).into_iter();
        let mut img = split_or_empty(&mut self.img, o).into_iter();
        self.meta
            .iter_mut()
            .zip(self.lists.iter_mut())
            .zip(types)
            .filter_map(|((meta, list), types)| {
                Some(BoxView { meta, types, x: x.next()?, v: v.next()?, f: f.next()?, x_build: xb.next()?, img: img.next()?, list })
            })
            .collect()
    }
}

/// The part shared by all host back ends: potential, batch, id index.
struct Engine {
    pot: Arc<Potential>,
    masses: Vec<f64>,
    batch: Batch,
    index: BTreeMap<PointId, usize>,
}

/// How boxes are spread over threads, and which EAM kernel path they take.
trait Spread: Sync {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R>;
    /// The kernel path ([`crate::simd`]; every path gives the same bits).
    fn simd(&self) -> Result<SimdPath, MdError>;
}

struct Serial;
impl Spread for Serial {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R> {
        jobs.into_iter().map(f).collect()
    }
    /// The oracle stays scalar.
    fn simd(&self) -> Result<SimdPath, MdError> {
        Ok(SimdPath::Scalar)
    }
}

struct Rayon(Option<Arc<rayon::ThreadPool>>);
impl Spread for Rayon {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R> {
        // collect() keeps the job order; each job is one box, computed serially.
        let run = || jobs.into_par_iter().map(&f).collect();
        match &self.0 {
            Some(pool) => pool.install(run),
            None => run(),
        }
    }
    /// `MSCALE_MD_SIMD`, else `SimdPath::best()` (AVX-512 where the CPU has it).
    fn simd(&self) -> Result<SimdPath, MdError> {
        crate::simd::selected()
    }
}

impl Engine {
    fn new(pot: Arc<Potential>) -> Self {
        let masses = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
        Engine { pot, masses, batch: Batch { offsets: vec![0], ..Default::default() }, index: BTreeMap::new() }
    }

    fn all_states(&self) -> Vec<BoxState> {
        (0..self.batch.meta.len()).map(|k| self.batch.state(k)).collect()
    }

    fn install(&mut self, mut states: Vec<BoxState>) {
        let mut all = self.all_states();
        for s in states.drain(..) {
            match self.index.get(&s.meta.id) {
                Some(&k) => all[k] = s,
                None => {
                    self.index.insert(s.meta.id, all.len());
                    all.push(s);
                }
            }
        }
        self.batch = Batch::from_states(&self.pot, all);
    }

    fn open(&mut self, specs: &[BoxSpec], spread: &impl Spread) -> Result<(), MdError> {
        let mut seen = std::collections::BTreeSet::new();
        for s in specs {
            if !seen.insert(s.id) || self.index.contains_key(&s.id) {
                return Err(MdError::invalid("box spec", format!("point id {} given twice", s.id)));
            }
            validate_spec(&self.pot, s)?;
        }
        let pot = &*self.pot;
        let masses = &self.masses;
        let path = spread.simd()?;
        let states = spread.map(specs.iter().collect(), |s| kernel::with_simd(path, || prepare_box(pot, masses, s)));
        let states = states.into_iter().collect::<Result<Vec<_>, _>>()?;
        self.install(states);
        Ok(())
    }

    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult], spread: &impl Spread) -> Result<(), MdError> {
        if work.len() != out.len() {
            return Err(MdError::invalid("step", format!("{} work items but {} result slots", work.len(), out.len())));
        }
        let mut which = Vec::with_capacity(work.len());
        let mut seen = std::collections::BTreeSet::new();
        for w in work {
            let k = *self.index.get(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            if !seen.insert(w.id) {
                return Err(MdError::invalid("box work", format!("point id {} appears twice in one step", w.id)));
            }
            validate_work(&self.pot, w, self.batch.meta[k].mode)?;
            which.push(k);
        }
        let path = spread.simd()?;
        let pot = &*self.pot;
        let masses = &self.masses;
        let mut slots: Vec<Option<BoxView>> = self.batch.views().into_iter().map(Some).collect();
        let mut jobs = Vec::with_capacity(work.len());
        for ((w, o), k) in work.iter().zip(out.iter_mut()).zip(which) {
            let view = slots[k].take().ok_or(MdError::UnknownBox(w.id))?;
            jobs.push((view, w, o));
        }
        // Every box runs; the first diverged box (in work order) is the call's error.
        let done = spread.map(jobs, |(mut view, w, o)| kernel::with_simd(path, || advance_box(pot, masses, &mut view, w).map(|r| *o = r)));
        done.into_iter().collect()
    }

    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        ids.iter().map(|id| self.index.get(id).map(|&k| self.batch.state(k)).ok_or(MdError::UnknownBox(*id))).collect()
    }

    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        for s in &states {
            check_state(&self.pot, s)?;
        }
        self.install(states);
        Ok(())
    }
}

/// Refuses a box state (a snapshot handed back by a peer or read from a checkpoint) that no
/// run of this potential could have made: per-atom arrays of different lengths, an element
/// the potential lacks, a box corner, length, skin, position, velocity or force that is not
/// finite, a box shorter than the neighbour list can serve ([`crate::neighbor::min_box_side`]),
/// positions far outside the box, or a density past [`MAX_NUMBER_DENSITY`].
pub fn check_state(pot: &Potential, s: &BoxState) -> Result<(), MdError> {
    let m = &s.meta;
    let bad = |why: String| Err(MdError::invalid("box state", format!("point id {}: {why}", m.id)));
    let n = s.x.len();
    if [s.v.len(), s.f.len(), s.x_build.len(), s.img.len(), s.types.len()].iter().any(|&k| k != n) {
        return bad("per-atom arrays differ in length".into());
    }
    if let Some(t) = s.types.iter().find(|&&t| t as usize >= pot.n_elements()) {
        return bad(format!("element {t} not in the potential"));
    }
    if !(m.skin > 0.0 && m.skin.is_finite()) {
        return bad(format!("skin must be > 0 A, got {}", crate::error::show(m.skin)));
    }
    if !finite3(&m.lo) || !finite3(&m.lo_build) || !finite3(&m.virial) || !m.pe.is_finite() {
        return bad(format!("box corner {:?}, corner at the list build {:?}, energy and virial must be finite", m.lo, m.lo_build));
    }
    let min_side = crate::neighbor::min_box_side(pot.cutoff() + m.skin);
    for (name, l) in [("box lengths", m.l), ("box lengths at the list build", m.l_build)] {
        if let Some(d) = (0..3).find(|&d| !(l[d].is_finite() && l[d] >= min_side)) {
            return bad(format!(
                "{name} {l:?} A: {} A along {} is below the {min_side} A the neighbour radius needs (or not finite)",
                crate::error::show(l[d]),
                ["x", "y", "z"][d]
            ));
        }
    }
    let density = n as f64 / (m.l[0] * m.l[1] * m.l[2]);
    if !(density <= MAX_NUMBER_DENSITY) {
        return bad(format!("{n} atoms in a {:?} A box are {density:.3e} atoms/A^3; at most {MAX_NUMBER_DENSITY}", m.l));
    }
    for (name, a) in [("position", &s.x), ("position at the list build", &s.x_build), ("velocity", &s.v), ("force", &s.f)] {
        if let Some(i) = a.iter().position(|u| !finite3(&u[..])) {
            return bad(format!("atom {i}: {name} {:?} is not finite", a[i]));
        }
    }
    for (i, (x, xb)) in s.x.iter().zip(&s.x_build).enumerate() {
        for d in 0..3 {
            for (c, lo, l) in [(x[d], m.lo[d], m.l[d]), (xb[d], m.lo_build[d], m.l_build[d])] {
                let outside = lengths_outside(c, lo, l);
                if outside > MAX_BOX_LENGTHS_OUTSIDE {
                    return bad(format!("atom {i}: {} = {c} A lies {outside:.3e} box lengths outside the box", ["x", "y", "z"][d]));
                }
            }
        }
    }
    Ok(())
}

/// How many box lengths `c` lies outside `[lo, lo + l)` (negative inside); written so that it
/// cannot overflow for any finite `c`.
fn lengths_outside(c: f64, lo: f64, l: f64) -> f64 {
    if c < lo { (lo - c) / l } else { (c - lo) / l - 1.0 }
}

fn finite3(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// Positions of given atoms may lie at most this many box lengths outside the box (they are
/// wrapped in); farther ones are refused as absurd. LAMMPS image flags unwrap positions by
/// whole box lengths, so a data file of a long run can hold atoms a few lengths out.
pub const MAX_BOX_LENGTHS_OUTSIDE: f64 = 100.0;

/// Most atoms per cubic angstrom a box may hold (copper has 0.085; the densest solids 0.18).
/// A denser box would have neighbour lists beyond any memory.
pub const MAX_NUMBER_DENSITY: f64 = 1.0;

/// Most engineering strain one MD step may apply along any component (`|L_ij| dt`).
pub const MAX_STRAIN_PER_STEP: f64 = 0.05;

/// Most a box may stretch or shrink in one step call: a factor of 2 either way per axis.
pub const MAX_STRETCH_PER_CALL: f64 = 2.0;

pub fn validate_spec(pot: &Potential, s: &BoxSpec) -> Result<(), MdError> {
    let bad = |msg: String| Err(MdError::invalid(format!("box spec of point {}", s.id), msg));
    // Box lengths before the strain, and atom count.
    let (lengths0, natoms, source) = match &s.atoms {
        InitialAtoms::Lattice { kind, a0, cells, orient } => {
            if !(a0.is_finite() && *a0 > 0.0) || cells.contains(&0) {
                return bad(format!("lattice needs a0 > 0 and cells >= 1, got a0 = {a0}, cells = {cells:?}"));
            }
            orient.validate()?;
            let n = kind.atoms_per_cell(orient) as f64 * cells.iter().map(|&c| c as f64).product::<f64>();
            (
                std::array::from_fn::<f64, 3, _>(|k| cells[k] as f64 * a0 * orient.period(k)),
                n,
                format!("lattice constant {} A, {cells:?} cells", crate::error::show(*a0)),
            )
        }
        InitialAtoms::Explicit { lo, lengths, types, x, v } => {
            if lengths.iter().any(|l| !(l.is_finite() && *l > 0.0)) {
                return bad(format!("box lengths must be positive, got {lengths:?}"));
            }
            if types.len() != x.len() || !(v.is_empty() || v.len() == x.len()) || x.is_empty() {
                return bad(format!("{} types, {} positions, {} velocities", types.len(), x.len(), v.len()));
            }
            if let Some(t) = types.iter().find(|&&t| t as usize >= pot.n_elements()) {
                return bad(format!("element index {t}, but the potential has {} element(s)", pot.n_elements()));
            }
            if !finite3(lo) {
                return bad(format!("box lower corner must be finite, got {lo:?}"));
            }
            for (i, p) in x.iter().enumerate() {
                for d in 0..3 {
                    let (c, l) = (p[d], lengths[d]);
                    let axis = ["x", "y", "z"][d];
                    if !c.is_finite() {
                        return bad(format!("atom {i} (0-based, in id order): {axis} = {c} is not a finite position"));
                    }
                    let outside = lengths_outside(c, lo[d], l);
                    if outside > MAX_BOX_LENGTHS_OUTSIDE {
                        return bad(format!(
                            "atom {i} (0-based, in id order): {axis} = {} A lies {outside:.3e} box lengths outside the box [{}, {}] along {axis}; \
                             at most {MAX_BOX_LENGTHS_OUTSIDE} are wrapped in",
                            crate::error::show(c),
                            lo[d],
                            lo[d] + l
                        ));
                    }
                }
            }
            if let Some((i, u)) = v.iter().enumerate().find(|(_, u)| !finite3(&u[..])) {
                return bad(format!("atom {i} (0-based, in id order): velocity {u:?} is not finite"));
            }
            (*lengths, x.len() as f64, format!("box lengths {lengths:?} A"))
        }
    };
    if !finite3(&s.strain) || s.strain.iter().any(|e| *e <= -1.0) {
        return bad(format!("strain must be finite and > -1, got {:?}", s.strain));
    }
    if !(s.skin > 0.0 && s.skin.is_finite()) {
        return bad(format!("skin must be > 0 A, got {}", s.skin));
    }
    let lengths: [f64; 3] = std::array::from_fn(|d| lengths0[d] * (1.0 + s.strain[d]));
    let rs = pot.cutoff() + s.skin;
    let min_side = crate::neighbor::min_box_side(rs);
    if let Some(d) = (0..3).find(|&d| !(lengths[d].is_finite() && lengths[d] >= min_side)) {
        return bad(format!(
            "the strained box is {} A long along {} ({source}, strain {:?}); the neighbour radius {rs} A (cut-off + skin) needs at least {min_side} A",
            crate::error::show(lengths[d]),
            ["x", "y", "z"][d],
            s.strain
        ));
    }
    let density = natoms / (lengths[0] * lengths[1] * lengths[2]);
    if !(density <= MAX_NUMBER_DENSITY) {
        return bad(format!(
            "{natoms} atoms in a {lengths:?} A box ({source}) are {density:.3e} atoms/A^3; at most {MAX_NUMBER_DENSITY} (copper has 0.085)"
        ));
    }
    if !(s.temperature_k >= 0.0 && s.temperature_k.is_finite()) {
        return bad(format!("temperature must be >= 0 K, got {}", s.temperature_k));
    }
    if (s.relax_steps > 0 || s.relax_box_blocks > 0) && !(s.relax_dt_ps > 0.0 && s.relax_dt_ps.is_finite()) {
        return bad(format!("relaxation time step must be > 0 ps, got {}", s.relax_dt_ps));
    }
    if s.relax_steps > 0 || s.relax_box_blocks > 0 {
        check_time_step(pot, s.relax_dt_ps)
            .map_err(|m| MdError::invalid(format!("box spec of point {}", s.id), format!("relaxation {m}")))?;
    }
    Ok(())
}

/// `Err(why)` when `dt` exceeds the potential's bound ([`Potential::max_time_step`]).
fn check_time_step(pot: &Potential, dt: f64) -> Result<(), String> {
    match pot.vibration() {
        Some(vib) if dt > vib.max_dt_ps() => {
            Err(format!("time step {} ps exceeds {:.6} ps, {vib}; use a smaller time step", crate::error::show(dt), vib.max_dt_ps()))
        }
        _ => Ok(()),
    }
}

pub fn validate_work(pot: &Potential, w: &BoxWork, mode: DeformMode) -> Result<(), MdError> {
    let what = || format!("box work of point {}", w.id);
    if !(w.dt_ps > 0.0 && w.dt_ps.is_finite()) && w.steps > 0 {
        return Err(MdError::invalid(what(), format!("time step must be > 0 ps, got {}", w.dt_ps)));
    }
    if !w.velocity_gradient.iter().all(|r| finite3(r)) || !w.energy_to_add_ev.is_finite() {
        return Err(MdError::invalid(what(), "velocity gradient and energy must be finite"));
    }
    // Also for a call of zero steps (with a time step of zero nothing is refused): a caller
    // that asks for the stress first (as `md-worker run` does) is told before any output.
    {
        check_time_step(pot, w.dt_ps).map_err(|m| MdError::invalid(what(), m))?;
        let l = &w.velocity_gradient;
        let name = |i: usize, j: usize| format!("{}{}", ["x", "y", "z"][i], ["x", "y", "z"][j]);
        for i in 0..3 {
            for j in 0..3 {
                let per_step = (l[i][j] * w.dt_ps).abs();
                if per_step > MAX_STRAIN_PER_STEP {
                    return Err(MdError::invalid(
                        what(),
                        format!(
                            "velocity gradient {} = {} 1/ps strains the box by {per_step:.3e} per step of {} ps; at most {MAX_STRAIN_PER_STEP} \
                             (|L_ij| dt), or the box inverts and the neighbour list cannot follow",
                            name(i, j),
                            crate::error::show(l[i][j]),
                            w.dt_ps
                        ),
                    ));
                }
            }
            // Stretch of axis i over the call: exp(L_ii t) (affine) or (1 + L_ii dt)^steps (seed).
            let ln_stretch = match mode {
                DeformMode::Affine => l[i][i] * w.dt_ps * w.steps as f64,
                DeformMode::Seed => (l[i][i] * w.dt_ps).ln_1p() * w.steps as f64,
            };
            if ln_stretch.abs() > MAX_STRETCH_PER_CALL.ln() {
                return Err(MdError::invalid(
                    what(),
                    format!(
                        "velocity gradient {} = {} 1/ps over {} steps of {} ps would scale the box by {:.3e}; \
                         at most a factor {MAX_STRETCH_PER_CALL} either way per call (fewer steps per call or a smaller gradient)",
                        name(i, i),
                        crate::error::show(l[i][i]),
                        w.steps,
                        w.dt_ps,
                        ln_stretch.exp()
                    ),
                ));
            }
        }
    }
    if mode == DeformMode::Affine {
        let l = &w.velocity_gradient;
        if (0..3).any(|i| (0..3).any(|j| i != j && l[i][j] != 0.0)) {
            return Err(MdError::Unsupported(format!(
                "point {}: affine mode keeps boxes orthogonal and takes diagonal velocity gradients only; \
                 use seed mode for shear",
                w.id
            )));
        }
    }
    Ok(())
}

/// Build one box from its spec: atoms, strain, velocities, forces, relaxation.
pub fn prepare_box(pot: &Potential, masses: &[f64], s: &BoxSpec) -> Result<BoxState, MdError> {
    // Every caller gets the checks (the CLI's `eval` builds boxes with this alone).
    validate_spec(pot, s)?;
    let (lo, mut l, types, mut x, mut v) = match &s.atoms {
        InitialAtoms::Lattice { kind, a0, cells, orient } => {
            let (x, l) = lattice::build_oriented(*kind, *a0, *cells, orient)?;
            let n = x.len();
            ([0.0; 3], l, vec![0u32; n], x, vec![[0.0; 3]; n])
        }
        InitialAtoms::Explicit { lo, lengths, types, x, v } => {
            let v = if v.is_empty() { vec![[0.0; 3]; x.len()] } else { v.clone() };
            (*lo, *lengths, types.clone(), x.clone(), v)
        }
    };
    for d in 0..3 {
        l[d] *= 1.0 + s.strain[d];
        for p in &mut x {
            p[d] = lo[d] + (p[d] - lo[d]) * (1.0 + s.strain[d]);
        }
    }
    let n = x.len();
    if s.temperature_k > 0.0 {
        let m: Vec<f64> = types.iter().map(|t| masses[*t as usize]).collect();
        let mut rng = lattice::rng_for(s.seed, s.id, 1, 0);
        v = lattice::maxwell_velocities(&mut rng, &m, 2.0 * s.temperature_k);
    }
    let meta = BoxMeta {
        id: s.id,
        lo,
        l,
        lo_build: lo,
        l_build: l,
        mode: s.mode,
        seed: s.seed,
        skin: s.skin,
        step: 0,
        pe: 0.0,
        virial: [0.0; 6],
        rebuilds: 0,
    };
    let state = BoxState { meta, types, x: x.clone(), v, f: vec![[0.0; 3]; n], x_build: x, img: vec![[0; 3]; n] };
    let mut batch = Batch { offsets: vec![0], ..Default::default() };
    batch.offsets.push(n);
    batch.meta.push(state.meta);
    batch.types = state.types;
    batch.x = state.x;
    batch.v = state.v;
    batch.f = state.f;
    batch.lists.push(NeighborList::default());
    {
        let mut views = batch.views();
        let b = views.first_mut().ok_or_else(|| MdError::invalid("box spec", "no atoms"))?;
        let (mut rho, mut fp) = (Vec::new(), Vec::new());
        kernel::with_fresh_list(pot, b, |b| {
            kernel::compute_forces(pot, b, &mut rho, &mut fp);
            if !b.meta.pe.is_finite() || b.f.iter().any(|f| !finite3(f)) {
                return Err(MdError::invalid(
                    format!("box spec of point {}", s.id),
                    format!("the energy of the initial atoms is {} eV (or a force is not finite): atoms overlap", b.meta.pe),
                ));
            }
            let still = Deformation::new(s.mode, &[[0.0; 3]; 3]);
            kernel::run_steps(pot, masses, b, &still, s.relax_steps, s.relax_dt_ps, &mut rho, &mut fp)?;
            relax_box_lengths(pot, masses, b, s, &mut rho, &mut fp)
        })?;
    }
    Ok(batch.state(0))
}

/// Rescale box lengths towards zero mean normal stress, in blocks of 100 NVE steps.
fn relax_box_lengths(
    pot: &Potential,
    masses: &[f64],
    b: &mut BoxView,
    s: &BoxSpec,
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
) -> Result<(), MdError> {
    const BLOCK: u64 = 100;
    // Assumed stiffnesses of the volumetric (C11 + 2 C12; Cu 415 GPa) and deviatoric
    // (C11 - C12; Cu 47 GPa) modes, set a little above cubic metals' values so the update
    // converges without overshooting.
    const VOLUMETRIC_GPA: f64 = 450.0;
    const DEVIATORIC_GPA: f64 = 60.0;
    let still = Deformation::new(s.mode, &[[0.0; 3]; 3]);
    for _ in 0..s.relax_box_blocks {
        let mut mean = [0.0; 3];
        for _ in 0..BLOCK / 10 {
            kernel::run_steps(pot, masses, b, &still, 10, s.relax_dt_ps, rho, fp)?;
            let st = kernel::virial_stress(b.meta, &kernel::kinetic_tensor(b.types, b.v, masses));
            for d in 0..3 {
                mean[d] += st[d] / (BLOCK / 10) as f64;
            }
        }
        let old_l = b.meta.l;
        let old_lo = b.meta.lo;
        let hydro = (mean[0] + mean[1] + mean[2]) / 3.0;
        for d in 0..3 {
            // Tension (positive) means the box is too long: shrink it.
            let strain = hydro / VOLUMETRIC_GPA + (mean[d] - hydro) / DEVIATORIC_GPA;
            let factor = (1.0 - strain).clamp(0.98, 1.02);
            let mid = old_lo[d] + 0.5 * old_l[d];
            b.meta.l[d] = old_l[d] * factor;
            b.meta.lo[d] = mid - 0.5 * b.meta.l[d];
        }
        for p in b.x.iter_mut() {
            for d in 0..3 {
                p[d] = b.meta.lo[d] + (p[d] - old_lo[d]) * (b.meta.l[d] / old_l[d]);
            }
        }
        kernel::rebuild(pot, b);
        kernel::compute_forces(pot, b, rho, fp);
    }
    Ok(())
}

/// Energy addition (thesis eq. 7.11) and the MD steps of one box; its result.
fn advance_box(pot: &Potential, masses: &[f64], b: &mut BoxView, w: &BoxWork) -> Result<BoxResult, MdError> {
    let shortfall = add_thermal_energy(masses, b, w.energy_to_add_ev);
    let def = Deformation::new(b.meta.mode, &w.velocity_gradient);
    let (mut rho, mut fp) = (Vec::new(), Vec::new());
    let average = w.stress_sampling == StressSampling::Average;
    // Sum of the stresses after each step, in step order (average sampling only).
    let mut sum: Option<[f64; 6]> = None;
    let sample = |b: &BoxView| {
        if average {
            let s = kernel::virial_stress(b.meta, &kernel::kinetic_tensor(b.types, b.v, masses));
            match &mut sum {
                None => sum = Some(s),
                Some(a) => (0..6).for_each(|c| a[c] += s[c]),
            }
        }
    };
    // Idle boxes keep no neighbour list nor build reference (memory: see kernel::with_fresh_list).
    let wraps =
        kernel::with_fresh_list(pot, b, |b| kernel::run_steps_with(pot, masses, b, &def, w.steps, w.dt_ps, &mut rho, &mut fp, sample))?;
    let mut r = measure(masses, b);
    if let Some(a) = sum {
        // The last sample is exactly `measure`'s stress, so one step gives `Last` bit for bit.
        r.stress_gpa = a.map(|x| x / w.steps as f64);
    }
    r.stress_sampling = w.stress_sampling;
    r.diagnostics.energy_shortfall_ev = shortfall;
    r.diagnostics.wraps = wraps;
    Ok(r)
}

/// Stress, energies and temperature of a box as it is now.
pub fn measure(masses: &[f64], b: &BoxView) -> BoxResult {
    let kin = kernel::kinetic_tensor(b.types, b.v, masses);
    BoxResult {
        id: b.meta.id,
        stress_gpa: kernel::virial_stress(b.meta, &kin),
        potential_energy_ev: b.meta.pe,
        kinetic_energy_ev: 0.5 * (kin[0] + kin[1] + kin[2]),
        temperature_k: kernel::temperature(&kin, b.x.len()),
        stress_sampling: StressSampling::Last,
        diagnostics: Diagnostics {
            total_steps: b.meta.step,
            lengths_a: b.meta.l,
            energy_shortfall_ev: 0.0,
            neighbor_rebuilds: b.meta.rebuilds,
            wraps: 0,
        },
    }
}

/// Add `de` eV of kinetic energy about the mean velocity; returns the shortfall (eV) when
/// removing more than there is.
fn add_thermal_energy(masses: &[f64], b: &mut BoxView, de: f64) -> f64 {
    if de == 0.0 {
        return 0.0;
    }
    let vb = kernel::mean_velocity(b.types, b.v, masses);
    let kin = kernel::kinetic_tensor(b.types, b.v, masses);
    let k = 0.5 * (kin[0] + kin[1] + kin[2]);
    let target = k + de;
    let shortfall = (-target).max(0.0);
    let target = target.max(0.0);
    if k > 0.0 {
        let s = (target / k).sqrt();
        for vi in b.v.iter_mut() {
            for d in 0..3 {
                vi[d] = vb[d] + s * (vi[d] - vb[d]);
            }
        }
    } else if target > 0.0 {
        // At 0 K: random directions, deterministic from (seed, point id, step).
        let mut rng = lattice::rng_for(b.meta.seed, b.meta.id, 2, b.meta.step);
        let m: Vec<f64> = b.types.iter().map(|t| masses[*t as usize]).collect();
        let dof = (3 * b.x.len()).saturating_sub(3).max(1) as f64;
        let t = 2.0 * target / (dof * BOLTZ);
        let u = lattice::maxwell_velocities(&mut rng, &m, t);
        for (vi, ui) in b.v.iter_mut().zip(u) {
            for d in 0..3 {
                vi[d] = vb[d] + ui[d];
            }
        }
    }
    shortfall
}

/// Serial, double-precision back end: the oracle.
pub struct ReferenceBackend {
    engine: Engine,
}

impl ReferenceBackend {
    /// A back end for boxes of potential `pot`.
    pub fn new(pot: Arc<Potential>) -> Self {
        ReferenceBackend { engine: Engine::new(pot) }
    }
}

impl MdBackend for ReferenceBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
        self.engine.open(specs, &Serial)
    }
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        self.engine.step(work, out, &Serial)
    }
    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        self.engine.snapshot(ids)
    }
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        self.engine.restore(states)
    }
    fn name(&self) -> &'static str {
        "reference"
    }
}

/// Multi-threaded back end: boxes spread over a rayon pool (the global one unless a pool
/// is given). Bitwise the same results as `reference` for any thread count.
pub struct CpuBackend {
    engine: Engine,
    spread: Rayon,
}

impl CpuBackend {
    /// A back end on rayon's global pool.
    pub fn new(pot: Arc<Potential>) -> Self {
        CpuBackend { engine: Engine::new(pot), spread: Rayon(None) }
    }
    /// A back end on the given pool.
    pub fn with_pool(pot: Arc<Potential>, pool: Arc<rayon::ThreadPool>) -> Self {
        Self::on(pot, Some(pool))
    }
    /// A back end on `threads`, or on rayon's global pool for `None`.
    pub fn on(pot: Arc<Potential>, threads: Option<Arc<rayon::ThreadPool>>) -> Self {
        CpuBackend { engine: Engine::new(pot), spread: Rayon(threads) }
    }
}

impl MdBackend for CpuBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
        self.engine.open(specs, &self.spread)
    }
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        self.engine.step(work, out, &self.spread)
    }
    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        self.engine.snapshot(ids)
    }
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        self.engine.restore(states)
    }
    fn name(&self) -> &'static str {
        "cpu"
    }
}
