//! The MD closure: every material point of a body owns a periodic MD box, deformed by the
//! point's velocity gradient each continuum step, whose virial stress becomes the point's stress
//! (Dhakal, Ch. 6-7). This is the one place where units cross between the continuum (SI) and
//! MD (LAMMPS `metal`: A, ps, eV, GPa).
//!
//! The whole body is one batch: every step ships the velocity gradients of all its points to
//! the [`MdPool`] at once (in-process back ends or remote workers), and the pool runs them in
//! parallel. Energy consistency (Ch. 7.2, eq. 7.11): the work the continuum does on a point
//! over a step, (sigma : D) V dt with the box's volume, minus the change of the box's energy
//! over that step, is added to the box as kinetic energy at the start of its next call.
//!
//! Stress sampling (Ch. 6-7): a point's stress is the box's virial stress after the last MD
//! step of the continuum step (`last`, the seed's default) or the mean over the step's MD steps
//! (`average`, computed by the worker after every MD step, in step order). With `average`, the
//! continuum work of the energy balance uses that mean (the step's own time average) instead
//! of the trapezoid of the stresses at the ends of the step.
//!
//! [`lattice`] measures what a scene needs of an md material before anything runs: the
//! lattice's density and longitudinal modulus from a strained unit cell.

pub mod lattice;
pub mod reuse;

pub use reuse::{Reuse, Skip};

use continuum::closure::{Closure, ClosureBatch, ClosureError};
use continuum::tensor::{self, Mat3};
use md_worker::pool::{IdMap, MdPool};
use md_worker::{BoxResult, BoxSpec, BoxWork, StressSampling};
use std::sync::{Arc, Mutex};

/// 1 GPa = 1e9 Pa.
pub const PA_PER_GPA: f64 = 1e9;
/// 1 ps = 1e-12 s.
pub const S_PER_PS: f64 = 1e-12;
/// 1 eV/A^3 in GPa: the MD engine's own constant (LAMMPS metal units), so the energy the
/// continuum hands to a box is measured the way the box measures its own energy.
pub const GPA_PER_EV_PER_A3: f64 = md_worker::units::EV_PER_A3_TO_GPA;

/// Velocity gradient in 1/ps from one in 1/s.
pub fn to_md_rate(l: &Mat3) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = l[i][j] * S_PER_PS;
        }
    }
    out
}

/// Cauchy stress in Pa from the MD's Voigt GPa (xx, yy, zz, xy, xz, yz).
pub fn from_md_stress(s: &[f64; 6]) -> Mat3 {
    let p = PA_PER_GPA;
    [[s[0] * p, s[3] * p, s[4] * p], [s[3] * p, s[1] * p, s[5] * p], [s[4] * p, s[5] * p, s[2] * p]]
}

/// Work (eV) done on a box of volume `volume_a3` (A^3) by stress `stress_gpa` (Voigt, GPa)
/// at rate of deformation `d` (1/ps) over `dt_ps`.
pub fn stress_work_ev(stress_gpa: &[f64; 6], d: &[[f64; 3]; 3], volume_a3: f64, dt_ps: f64) -> f64 {
    let s = stress_gpa;
    let power = s[0] * d[0][0] + s[1] * d[1][1] + s[2] * d[2][2] + 2.0 * (s[3] * d[0][1] + s[4] * d[0][2] + s[5] * d[1][2]);
    power * volume_a3 * dt_ps / GPA_PER_EV_PER_A3
}

/// Per-point MD outputs of the last step, for particle files and summaries.
#[derive(Debug, Clone, Default)]
pub struct MdPointState {
    pub last: BoxResult,
    /// Energy to add at the next call (eV).
    pub pending_ev: f64,
    /// Energy added so far (eV).
    pub added_ev: f64,
    /// What the tolerance mode keeps between the box's MD calls.
    pub skip: Skip,
}

/// The extremes the MD boxes of a run have seen (summary.json `md.diagnostics`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MdDiagnostics {
    /// Largest |D_ij| of a point of an md body over the run (1/s).
    pub max_strain_rate_per_s: f64,
    /// Smallest box length of an MD call's result over the potential's cut-off.
    pub min_box_length_over_cutoff: f64,
    /// Most neighbour-list builds of one box in one call.
    pub max_rebuilds_per_call: u64,
    /// Highest temperature an MD call's result reported (K), and its point: a box far hotter
    /// than the scene's shocked states (energy consistency and the viscous heat are added to
    /// the boxes) is a point to look at.
    pub max_temperature_k: f64,
    pub hottest_point: Option<usize>,
}

impl Default for MdDiagnostics {
    fn default() -> Self {
        MdDiagnostics {
            max_strain_rate_per_s: 0.0,
            min_box_length_over_cutoff: f64::INFINITY,
            max_rebuilds_per_call: 0,
            max_temperature_k: 0.0,
            hottest_point: None,
        }
    }
}

/// The MD cost of one md body.
#[derive(Debug, Clone, PartialEq)]
pub struct MdBodyStats {
    pub name: String,
    pub reuse: Reuse,
    /// Its points are `first..first + boxes`.
    pub first: usize,
    pub boxes: usize,
    pub atoms_per_box: u64,
    /// MD steps of each box at open (relaxation).
    pub relax_steps: u64,
    /// MD box-steps `off` would have done in step calls (every box every step).
    pub requested_md_steps: u64,
    /// MD box-steps the tolerance mode skipped.
    pub skipped_md_steps: u64,
}

/// What a run shares with its MD closures: the pool and the per-point outputs.
pub struct MdShared {
    pub pool: MdPool,
    /// The potential every MD body of the run uses.
    pub potential: md_worker::pool::PotentialSource,
    /// Indexed by global point index; `None` for points of non-MD bodies.
    pub points: Vec<Option<MdPointState>>,
    /// One per md body, in the order they were opened.
    pub bodies: Vec<MdBodyStats>,
    pub diagnostics: MdDiagnostics,
    /// The potential's cut-off (A).
    pub cutoff_a: f64,
    /// Work the closures of the current continuum step have registered (`prepare`), sent to
    /// the pool in one call by the first of them to be advanced.
    queue: Vec<BoxWork>,
    /// The continuum step of the queued work.
    queue_step: u64,
    /// Results of the last pool call not yet taken by their closures, by point id.
    results: IdMap<BoxResult>,
}

impl MdShared {
    pub fn new(pool: MdPool, potential: md_worker::pool::PotentialSource) -> Self {
        let cutoff_a = potential.parse().map_or(f64::NAN, |p| p.cutoff());
        MdShared {
            pool,
            potential,
            points: Vec::new(),
            bodies: Vec::new(),
            diagnostics: MdDiagnostics::default(),
            cutoff_a,
            queue: Vec::new(),
            queue_step: 0,
            results: IdMap::default(),
        }
    }

    /// Sends the queued work of every body in one pool call and keeps the results.
    fn flush(&mut self) -> Result<(), ClosureError> {
        let (step, work) = (self.queue_step, std::mem::take(&mut self.queue));
        if work.is_empty() {
            return Ok(());
        }
        let results = self
            .pool
            .step(step, &work)
            .map_err(|e| ClosureError::Engine { context: format!("MD at continuum step {step}"), source: Box::new(e) })?;
        self.results.extend(results.into_iter().map(|r| (r.id, r)));
        Ok(())
    }
}

/// Settings of one MD body.
#[derive(Debug, Clone)]
pub struct MdSettings {
    /// The body's name (for the cost report).
    pub body: String,
    /// MD time step (ps).
    pub dt_ps: f64,
    pub energy_consistency: bool,
    /// Longitudinal wave speed of the material at rest (m/s), for the CFL bound and viscosity.
    pub wave_speed: f64,
    /// Longitudinal modulus of the lattice at rest (GPa), the tolerance mode's bound of what
    /// its measured tangent does not cover.
    pub c11_gpa: f64,
    /// Stress at the last MD step of a continuum step, or averaged over its MD steps.
    pub stress_sampling: StressSampling,
    pub reuse: Reuse,
    /// Add the artificial viscosity's work on the point, q : D per unit volume (of the
    /// previous step's q), to its box as heat: the dissipation of a smeared shock, without
    /// which the boxes follow a quasi-isentrope instead of the Hugoniot (too cold and too soft
    /// behind a strong shock; see coupling/README.md).
    pub viscous_heating: bool,
}

/// What a point does this step: an MD call (its work's index) or a skip (tolerance mode) with
/// the predicted change of its stress and its strain since its last MD call.
#[derive(Debug, Clone, Copy)]
enum Plan {
    Call(usize),
    Skip { change: [f64; 6], strain: [f64; 6], heat_ev: f64 },
}

/// The MD closure of one body. The closures of all md bodies of a run share one [`MdShared`]:
/// each registers its points' work in `prepare`, and the first one advanced sends the work of
/// all of them to the pool in one call (one round trip per continuum step, whatever the number
/// of md bodies); each then takes its own results.
pub struct MdClosure {
    shared: Arc<Mutex<MdShared>>,
    settings: MdSettings,
    /// Index of this body in [`MdShared::bodies`].
    body: usize,
    /// This step's plan of the body's points (in batch order) and its work, once registered.
    registered: Option<(Vec<Plan>, Vec<BoxWork>)>,
}

impl MdClosure {
    /// Opens the boxes of a body whose points are `first..first + specs.len()`; `specs[k].id`
    /// must be `first + k`. Initial stresses come from the boxes after relaxation.
    pub fn open(shared: Arc<Mutex<MdShared>>, settings: MdSettings, specs: &[BoxSpec]) -> Result<Self, ClosureError> {
        let mut s = shared.lock().map_err(|_| ClosureError::Other("MD state poisoned".into()))?;
        let potential = s.potential.clone();
        let end = specs.iter().map(|b| b.id as usize + 1).max().unwrap_or(0);
        if s.points.len() < end {
            s.points.resize(end, None);
        }
        s.pool.open(&potential, specs).map_err(|e| ClosureError::Engine { context: "opening MD boxes".into(), source: Box::new(e) })?;
        if settings.reuse.exact_sharing() {
            let ids: Vec<u64> = specs.iter().map(|b| b.id).collect();
            s.pool
                .enable_reuse(&ids)
                .map_err(|e| ClosureError::Engine { context: "sharing identical MD boxes".into(), source: Box::new(e) })?;
        }
        let body = s.bodies.len();
        let first = specs.first().map_or(0, |b| b.id);
        let atoms_per_box = s.pool.atoms_of(first);
        s.bodies.push(MdBodyStats {
            name: settings.body.clone(),
            reuse: settings.reuse,
            first: first as usize,
            boxes: specs.len(),
            atoms_per_box,
            relax_steps: specs.first().map_or(0, |b| b.relax_steps),
            requested_md_steps: 0,
            skipped_md_steps: 0,
        });
        drop(s);
        Ok(MdClosure { shared, settings, body, registered: None })
    }

    fn lock(&self) -> Result<std::sync::MutexGuard<'_, MdShared>, ClosureError> {
        self.shared.lock().map_err(|_| ClosureError::Other("MD state poisoned".into()))
    }

    /// MD steps of a continuum step of `dt` seconds.
    fn md_steps(&self, dt: f64) -> u64 {
        (dt / S_PER_PS / self.settings.dt_ps).round() as u64
    }

    /// The plan and the work of every point of the batch over `dt` (s).
    fn plan_of(&self, shared: &MdShared, b: &ClosureBatch<'_>, dt: f64) -> (Vec<Plan>, Vec<BoxWork>) {
        let steps = self.md_steps(dt);
        let dt_md = self.settings.dt_ps;
        let mut plan = Vec::with_capacity(b.stress.len());
        let mut work = Vec::with_capacity(b.stress.len());
        for k in 0..b.stress.len() {
            let id = (b.first + k) as u64;
            let state = shared.points[b.first + k].as_ref();
            let l = to_md_rate(&b.vel_grad[k]);
            // The viscous work of this step on the box (eV): the previous step's q, this step's
            // rate, the box's volume now.
            let heat_ev = match (state, b.visc_stress.get(k)) {
                (Some(p), Some(q)) if self.settings.viscous_heating && steps > 0 => {
                    let volume: f64 = p.last.diagnostics.lengths_a.iter().product();
                    let q_gpa = [q[0][0], q[1][1], q[2][2], q[0][1], q[0][2], q[1][2]].map(|v| v / PA_PER_GPA);
                    stress_work_ev(&q_gpa, &tensor::sym(&l), volume, steps as f64 * dt_md).max(0.0)
                }
                _ => 0.0,
            };
            let mut w = BoxWork {
                id,
                velocity_gradient: l,
                steps,
                dt_ps: dt_md,
                energy_to_add_ev: if self.settings.energy_consistency && steps > 0 { state.map_or(0.0, |p| p.pending_ev) } else { 0.0 }
                    + heat_ev,
                stress_sampling: self.settings.stress_sampling,
            };
            if let (Reuse::Tolerance { tolerance_gpa, max_interval }, Some(p)) = (self.settings.reuse, state)
                && steps > 0
            {
                let inc = reuse::strain_increment(&l, steps as f64 * dt_md);
                let strain: [f64; 6] = std::array::from_fn(|c| p.skip.strain[c] + inc[c]);
                let (change, bound) = p.skip.predict(&strain, self.settings.c11_gpa);
                if bound < tolerance_gpa && p.skip.skipped < max_interval {
                    plan.push(Plan::Skip { change, strain, heat_ev });
                    continue;
                }
                // The skipped steps' heat goes in with the catch-up.
                w.energy_to_add_ev += p.skip.heat_ev;
                if p.skip.skipped > 0 {
                    // The catch-up: the deformation of every skipped step and this one's, in this
                    // step's MD steps (the box's clock stays behind by the skipped time).
                    w.velocity_gradient = std::array::from_fn(|i| std::array::from_fn(|j| p.skip.l_sum[i][j] + l[i][j]));
                }
            }
            plan.push(Plan::Call(work.len()));
            work.push(w);
        }
        (plan, work)
    }
}

impl Closure for MdClosure {
    fn name(&self) -> &'static str {
        "md"
    }

    fn wave_speed(&self, _mass: &[f64], _volume: &[f64]) -> f64 {
        self.settings.wave_speed
    }

    /// Each box is computed once: over MPI continuum ranks only rank 0 drives the pool (the
    /// other ranks' closures stand over a `null` pool and are never called).
    fn computed_once(&self) -> bool {
        true
    }

    fn prepare(&mut self, b: &ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError> {
        let mut shared = self.lock()?;
        let (plan, work) = self.plan_of(&shared, b, dt);
        if !shared.queue.is_empty() && shared.queue_step != b.step {
            return Err(ClosureError::Other(format!(
                "MD work of continuum step {} queued while that of step {} was never sent",
                b.step, shared.queue_step
            )));
        }
        shared.queue_step = b.step;
        shared.queue.extend_from_slice(&work);
        drop(shared);
        self.registered = Some((plan, work));
        Ok(())
    }

    fn initialize(&mut self, b: ClosureBatch<'_>) -> Result<(), ClosureError> {
        // Zero MD steps: measure the relaxed boxes.
        self.call(b, 0.0)
    }

    fn advance(&mut self, b: ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError> {
        self.call(b, dt)
    }
}

impl MdClosure {
    fn call(&mut self, b: ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError> {
        let dt_md = self.settings.dt_ps;
        let steps = self.md_steps(dt);
        let shared_arc = self.shared.clone();
        let mut guard = shared_arc.lock().map_err(|_| ClosureError::Other("MD state poisoned".into()))?;
        let shared = &mut *guard;
        // Not prepared (a caller that skips `prepare`): this body's work goes alone.
        let (plan, work) = match self.registered.take() {
            Some(r) => r,
            None => {
                let (plan, work) = self.plan_of(shared, &b, dt);
                shared.queue_step = b.step;
                shared.queue.extend_from_slice(&work);
                (plan, work)
            }
        };
        if work.iter().any(|w| !shared.results.contains_key(&w.id)) {
            shared.flush()?;
        }
        let tolerance = match self.settings.reuse {
            Reuse::Tolerance { tolerance_gpa, .. } => Some(tolerance_gpa),
            _ => None,
        };
        let (c11, cutoff) = (self.settings.c11_gpa, shared.cutoff_a);
        let diag = &mut shared.diagnostics;
        let stats = &mut shared.bodies[self.body];
        if steps > 0 {
            stats.requested_md_steps += steps * b.stress.len() as u64;
        }
        for (k, item) in plan.iter().enumerate() {
            let p = b.first + k;
            let l = to_md_rate(&b.vel_grad[k]);
            let d = tensor::sym(&l);
            diag.max_strain_rate_per_s = d.iter().flatten().fold(diag.max_strain_rate_per_s, |m, v| m.max(v.abs() / S_PER_PS));
            let state = shared.points[p].get_or_insert_with(Default::default);
            let step_ps = steps as f64 * dt_md;
            let volume: f64 = state.last.diagnostics.lengths_a.iter().product();
            let w = match *item {
                Plan::Skip { change, strain, heat_ev } => {
                    let reported: [f64; 6] = std::array::from_fn(|c| state.last.stress_gpa[c] + change[c]);
                    let sigma = from_md_stress(&reported);
                    if !tensor::is_finite(&sigma) {
                        return Err(ClosureError::NonFinite { point: p, law: "md", jacobian: tensor::det(&b.def_grad[k]) });
                    }
                    b.stress[k] = sigma;
                    let over_step: [f64; 6] = std::array::from_fn(|c| 0.5 * (state.skip.reported_gpa[c] + reported[c]));
                    let skip = &mut state.skip;
                    skip.work_ev += stress_work_ev(&over_step, &d, volume, step_ps);
                    skip.heat_ev += heat_ev;
                    skip.skipped += 1;
                    for i in 0..3 {
                        for j in 0..3 {
                            skip.l_sum[i][j] += l[i][j];
                        }
                    }
                    skip.strain = strain;
                    skip.reported_gpa = reported;
                    stats.skipped_md_steps += steps;
                    continue;
                }
                Plan::Call(i) => work[i],
            };
            let r = shared.results.remove(&w.id).ok_or_else(|| ClosureError::Other(format!("MD: no result for point {p}")))?;
            let sigma = from_md_stress(&r.stress_gpa);
            if !tensor::is_finite(&sigma) {
                return Err(ClosureError::NonFinite { point: p, law: "md", jacobian: tensor::det(&b.def_grad[k]) });
            }
            b.stress[k] = sigma;
            diag.min_box_length_over_cutoff =
                r.diagnostics.lengths_a.iter().fold(diag.min_box_length_over_cutoff, |m, x| m.min(x / cutoff));
            diag.max_rebuilds_per_call =
                diag.max_rebuilds_per_call.max(r.diagnostics.neighbor_rebuilds.saturating_sub(state.last.diagnostics.neighbor_rebuilds));
            if r.temperature_k > diag.max_temperature_k {
                (diag.max_temperature_k, diag.hottest_point) = (r.temperature_k, Some(p));
            }
            if steps > 0 {
                // This continuum step's part of the call: its own rate (a catch-up's earlier
                // steps were accounted for while the box was skipped).
                let old_volume: f64 = volume;
                let new_volume: f64 = r.diagnostics.lengths_a.iter().product();
                let before = if tolerance.is_some() { state.skip.reported_gpa } else { state.last.stress_gpa };
                // The stress over the step: the trapezoid of its ends, or (average sampling) the
                // step's own mean.
                let over_step: [f64; 6] = match w.stress_sampling {
                    StressSampling::Average => r.stress_gpa,
                    StressSampling::Last => std::array::from_fn(|c| 0.5 * (before[c] + r.stress_gpa[c])),
                };
                let step_work = stress_work_ev(&over_step, &d, 0.5 * (old_volume + new_volume), step_ps);
                let work_ev = if state.skip.skipped > 0 { state.skip.work_ev + step_work } else { step_work };
                let energy = |x: &BoxResult| x.potential_energy_ev + x.kinetic_energy_ev;
                // What was really added: a removal larger than the box's kinetic energy falls short.
                let added = w.energy_to_add_ev + r.diagnostics.energy_shortfall_ev;
                let gained = energy(&r) - energy(&state.last) - added;
                state.added_ev += added;
                state.pending_ev = work_ev - gained;
            }
            if let Some(tol) = tolerance {
                let inc = reuse::strain_increment(&l, step_ps);
                let strain: [f64; 6] = std::array::from_fn(|c| state.skip.strain[c] + inc[c]);
                let ds: [f64; 6] = std::array::from_fn(|c| r.stress_gpa[c] - state.last.stress_gpa[c]);
                let secant = state.skip.secant;
                state.skip = Skip { reported_gpa: r.stress_gpa, secant, ..Default::default() };
                if steps > 0 {
                    state.skip.measured(ds, strain, c11, tol);
                }
            }
            state.last = r;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_conversions_round_trip() {
        // 1 GPa on 1 A^3 over a strain of 1 is 1e-21 J = 6.2415e-3 eV (LAMMPS's constants are
        // rounded to about 1e-7).
        let w = stress_work_ev(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], &[[1.0, 0.0, 0.0], [0.0; 3], [0.0; 3]], 1.0, 1.0);
        assert!((w - 1e-21 / 1.602176634e-19).abs() < 1e-6 * w);
        // Shear counts twice (xy and yx).
        let ws = stress_work_ev(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], &[[0.0, 0.5, 0.0], [0.5, 0.0, 0.0], [0.0; 3]], 1.0, 1.0);
        assert!((ws - w).abs() < 1e-15);
        let l = to_md_rate(&[[1e9, 0.0, 0.0], [0.0; 3], [0.0; 3]]);
        assert!((l[0][0] - 1e-3).abs() < 1e-18);
        let s = from_md_stress(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(s[0][1], 4e9);
        assert_eq!(s[2][1], 6e9);
    }
}
