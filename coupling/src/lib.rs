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

use continuum::closure::{Closure, ClosureBatch, ClosureError};
use continuum::tensor::{self, Mat3};
use md_worker::pool::MdPool;
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
}

/// What a run shares with its MD closures: the pool and the per-point outputs.
pub struct MdShared {
    pub pool: MdPool,
    /// The potential every MD body of the run uses.
    pub potential: md_worker::pool::PotentialSource,
    /// Indexed by global point index; `None` for points of non-MD bodies.
    pub points: Vec<Option<MdPointState>>,
    /// Continuum step counter (for replay logs and worker messages).
    pub step: u64,
}

/// Settings of one MD body.
#[derive(Debug, Clone)]
pub struct MdSettings {
    /// MD time step (ps).
    pub dt_ps: f64,
    pub energy_consistency: bool,
    /// Longitudinal wave speed of the material at rest (m/s), for the CFL bound and viscosity.
    pub wave_speed: f64,
    /// Stress at the last MD step of a continuum step, or averaged over its MD steps.
    pub stress_sampling: StressSampling,
}

pub struct MdClosure {
    shared: Arc<Mutex<MdShared>>,
    settings: MdSettings,
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
        drop(s);
        Ok(MdClosure { shared, settings })
    }
}

impl Closure for MdClosure {
    fn name(&self) -> &'static str {
        "md"
    }

    fn wave_speed(&self, _mass: &[f64], _volume: &[f64]) -> f64 {
        self.settings.wave_speed
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
        let steps = (dt / S_PER_PS / dt_md).round() as u64;
        let mut shared = self.shared.lock().map_err(|_| ClosureError::Other("MD state poisoned".into()))?;
        let step = shared.step;
        let work: Vec<BoxWork> = (0..b.stress.len())
            .map(|k| {
                let id = (b.first + k) as u64;
                let pending = shared.points[b.first + k].as_ref().map_or(0.0, |p| p.pending_ev);
                BoxWork {
                    id,
                    velocity_gradient: to_md_rate(&b.vel_grad[k]),
                    steps,
                    dt_ps: dt_md,
                    energy_to_add_ev: if self.settings.energy_consistency && steps > 0 { pending } else { 0.0 },
                    stress_sampling: self.settings.stress_sampling,
                }
            })
            .collect();
        let results = shared
            .pool
            .step(step, &work)
            .map_err(|e| ClosureError::Engine { context: format!("MD at continuum step {step}"), source: Box::new(e) })?;
        for (k, (w, r)) in work.iter().zip(results).enumerate() {
            let p = b.first + k;
            let sigma = from_md_stress(&r.stress_gpa);
            if !tensor::is_finite(&sigma) {
                return Err(ClosureError::NonFinite { point: p, law: "md", jacobian: tensor::det(&b.def_grad[k]) });
            }
            b.stress[k] = sigma;
            let state = shared.points[p].get_or_insert_with(Default::default);
            if steps > 0 {
                let d = tensor::sym(&w.velocity_gradient);
                let old_volume: f64 = state.last.diagnostics.lengths_a.iter().product();
                let new_volume: f64 = r.diagnostics.lengths_a.iter().product();
                // The stress over the step: the trapezoid of its ends, or (average sampling) the
                // step's own mean.
                let over_step: [f64; 6] = match w.stress_sampling {
                    StressSampling::Average => r.stress_gpa,
                    StressSampling::Last => std::array::from_fn(|c| 0.5 * (state.last.stress_gpa[c] + r.stress_gpa[c])),
                };
                let work_ev = stress_work_ev(&over_step, &d, 0.5 * (old_volume + new_volume), steps as f64 * dt_md);
                let energy = |x: &BoxResult| x.potential_energy_ev + x.kinetic_energy_ev;
                // What was really added: a removal larger than the box's kinetic energy falls short.
                let added = w.energy_to_add_ev + r.diagnostics.energy_shortfall_ev;
                let gained = energy(&r) - energy(&state.last) - added;
                state.added_ev += added;
                state.pending_ev = work_ev - gained;
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
