//! The explicit step (Dhakal, Ch. 3.1, steps 3-10) and the guard that stops a diverging run.

use crate::closure::{Closure, ClosureBatch, ClosureError};
use crate::diagnostics::Totals;
use crate::grid::Grid;
use crate::particles::Particles;
use crate::shape::{self, SchemeKind, Stencil};
use crate::tensor::{self, Mat3};

/// Artificial viscosity added to the closure's stress in compression.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Viscosity {
    None,
    /// Linear form of Ch. 6.3: q = coefficient * rho * c * h * |tr D| when tr D < 0.
    Linear { coefficient: f64 },
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SolverError {
    #[error("step {step}: {what}; likely cause: {cause}")]
    Diverged { step: u64, what: String, cause: &'static str },
    #[error("step {step}: {source}")]
    Closure { step: u64, source: ClosureError },
}

/// What one step did, for progress reporting.
#[derive(Debug, Clone, Copy)]
pub struct StepReport {
    pub step: u64,
    pub time: f64,
}

/// A running simulation: all state is here and every step takes it explicitly.
pub struct Simulation<const D: usize> {
    pub grid: Grid<D>,
    pub points: Particles<D>,
    pub scheme: SchemeKind,
    /// One closure per body, in body order.
    pub closures: Vec<Box<dyn Closure>>,
    pub viscosity: Viscosity,
    /// Time step (s).
    pub dt: f64,
    pub time: f64,
    pub step: u64,
    /// Closure evaluations so far (points advanced), the measure of cost users compare.
    pub closure_evaluations: u64,
    /// Momentum added by boundary constraints since the start (N s, per unit cross-section in 1D).
    pub wall_impulse: [f64; D],
    /// Sum of the magnitudes of the wall impulses (the scale to judge momentum drift by).
    pub wall_impulse_magnitude: f64,
    pub initial: Totals<D>,
    stencil: Stencil<D>,
    node_mass: Vec<f64>,
    node_momentum: Vec<[f64; D]>,
    node_force: Vec<[f64; D]>,
    node_v: Vec<[f64; D]>,
    node_v_lagrangian: Vec<[f64; D]>,
    body_ranges: Vec<std::ops::Range<usize>>,
}

/// Nodes lighter than this fraction of the lightest point carry no velocity of their own.
const EMPTY_NODE_FRACTION: f64 = 1e-12;
/// A node accelerating faster than this many c^2/h is treated as a blow-up.
const ACCELERATION_LIMIT: f64 = 1e3;

impl<const D: usize> Simulation<D> {
    /// Builds the simulation and evaluates the initial stresses.
    pub fn new(
        grid: Grid<D>,
        points: Particles<D>,
        scheme: SchemeKind,
        closures: Vec<Box<dyn Closure>>,
        viscosity: Viscosity,
        dt: f64,
    ) -> Result<Self, SolverError> {
        let n = grid.node_count();
        let body_ranges = points.body_ranges();
        let mut sim = Simulation {
            initial: Totals::default(),
            grid,
            points,
            scheme,
            closures,
            viscosity,
            dt,
            time: 0.0,
            step: 0,
            closure_evaluations: 0,
            wall_impulse: [0.0; D],
            wall_impulse_magnitude: 0.0,
            stencil: Stencil::default(),
            node_mass: vec![0.0; n],
            node_momentum: vec![[0.0; D]; n],
            node_force: vec![[0.0; D]; n],
            node_v: vec![[0.0; D]; n],
            node_v_lagrangian: vec![[0.0; D]; n],
            body_ranges,
        };
        for (b, range) in sim.body_ranges.clone().into_iter().enumerate() {
            let pts = &mut sim.points;
            let batch = ClosureBatch {
                first: range.start,
                vel_grad: &pts.vel_grad[range.clone()],
                def_grad: &pts.def_grad[range.clone()],
                mass: &pts.mass[range.clone()],
                volume: &pts.volume[range.clone()],
                stress: &mut pts.stress[range.clone()],
            };
            sim.closures[b].initialize(batch).map_err(|source| SolverError::Closure { step: 0, source })?;
        }
        sim.initial = sim.totals();
        Ok(sim)
    }

    /// Largest wave speed over all bodies (m/s).
    pub fn wave_speed(&self) -> f64 {
        self.body_ranges
            .iter()
            .zip(&self.closures)
            .map(|(r, c)| c.wave_speed(&self.points.mass[r.clone()], &self.points.volume[r.clone()]))
            .fold(0.0, f64::max)
    }

    /// Mass, momentum and energy now.
    pub fn totals(&self) -> Totals<D> {
        Totals::of(&self.points)
    }

    /// One explicit step.
    pub fn step(&mut self) -> Result<StepReport, SolverError> {
        let step = self.step + 1;
        let dt = self.dt;
        shape::build(self.scheme, &self.grid, &self.points, &mut self.stencil).map_err(|o| SolverError::Diverged {
            step,
            what: format!("particle {} left the grid along axis {} (position {:e} m)", o.point, o.axis, o.position),
            cause: "the body moved past a non-periodic face: enlarge the domain or use a wall",
        })?;
        self.map_to_grid();
        self.nodal_forces();
        let c = self.wave_speed();
        self.lagrangian_update(step, c)?;
        self.velocity_gradients();
        self.deform_and_stress(step, c)?;
        self.move_points();
        self.time += dt;
        self.step = step;
        self.guard(step)?;
        Ok(StepReport { step, time: self.time })
    }

    /// Steps 3-4: lumped nodal mass and momentum, nodal velocity.
    fn map_to_grid(&mut self) {
        self.node_mass.iter_mut().for_each(|m| *m = 0.0);
        self.node_momentum.iter_mut().for_each(|m| *m = [0.0; D]);
        let (st, pts) = (&self.stencil, &self.points);
        for p in 0..pts.len() {
            for e in st.entries(p) {
                let (i, w) = (st.node[e], st.weight[e]);
                self.node_mass[i] += w * pts.mass[p];
                for a in 0..D {
                    self.node_momentum[i][a] += w * pts.mass[p] * pts.v[p][a];
                }
            }
        }
        let floor = EMPTY_NODE_FRACTION * pts.mass.iter().cloned().fold(f64::INFINITY, f64::min);
        for i in 0..self.node_mass.len() {
            let m = self.node_mass[i];
            self.node_v[i] = if m > floor { std::array::from_fn(|a| self.node_momentum[i][a] / m) } else { [0.0; D] };
        }
        let mass = std::mem::take(&mut self.node_mass);
        self.grid.apply_boundaries(&mass, &mut self.node_v);
        self.node_mass = mass;
    }

    /// Step 5: f_i = -sum_p V_p (sigma_p - q_p I) . G_ip.
    fn nodal_forces(&mut self) {
        self.node_force.iter_mut().for_each(|f| *f = [0.0; D]);
        let (st, pts) = (&self.stencil, &self.points);
        for p in 0..pts.len() {
            let mut s = pts.stress[p];
            for (a, row) in s.iter_mut().enumerate() {
                row[a] -= pts.visc_pressure[p];
            }
            let vol = pts.volume[p];
            for e in st.entries(p) {
                let (i, g) = (st.node[e], &st.grad[e]);
                for a in 0..D {
                    let mut f = 0.0;
                    for b in 0..D {
                        f += s[a][b] * g[b];
                    }
                    self.node_force[i][a] -= vol * f;
                }
            }
        }
    }

    /// Step 6: Lagrangian nodal velocity, boundary conditions, wall impulse.
    fn lagrangian_update(&mut self, step: u64, c: f64) -> Result<(), SolverError> {
        let floor = EMPTY_NODE_FRACTION * self.points.mass.iter().cloned().fold(f64::INFINITY, f64::min);
        let limit = ACCELERATION_LIMIT * c * c / self.grid.min_spacing();
        for i in 0..self.node_mass.len() {
            let m = self.node_mass[i];
            if m <= floor {
                self.node_v_lagrangian[i] = [0.0; D];
                continue;
            }
            for a in 0..D {
                let acc = self.node_force[i][a] / m;
                if !(acc.abs() <= limit) {
                    return Err(SolverError::Diverged {
                        step,
                        what: format!(
                            "node {:?} acceleration {acc:e} m/s^2 along axis {a} exceeds {limit:e} (= {ACCELERATION_LIMIT} c^2/h)",
                            self.grid.unlinear(i)
                        ),
                        cause: "time step too large for the wave speed, or a tension instability (too few particles per cell)",
                    });
                }
                self.node_v_lagrangian[i][a] = self.node_v[i][a] + self.dt * acc;
            }
        }
        let (added, magnitude) = self.grid.apply_boundaries(&self.node_mass, &mut self.node_v_lagrangian);
        self.wall_impulse_magnitude += magnitude;
        for a in 0..D {
            self.wall_impulse[a] += added[a];
        }
        Ok(())
    }

    /// Step 7 with the half-step nodal velocity (4.10): L_p = sum_i v_i^{n+1/2} (x) G_ip.
    fn velocity_gradients(&mut self) {
        let st = &self.stencil;
        for p in 0..self.points.len() {
            let mut l: Mat3 = tensor::ZERO;
            for e in st.entries(p) {
                let i = st.node[e];
                for a in 0..D {
                    let v_half = 0.5 * (self.node_v[i][a] + self.node_v_lagrangian[i][a]);
                    for b in 0..D {
                        l[a][b] += v_half * st.grad[e][b];
                    }
                }
            }
            self.points.vel_grad[p] = l;
        }
    }

    /// Step 8: deformation gradient, volume, closure stress, artificial viscosity and the
    /// stress work (internal energy, midpoint rule).
    fn deform_and_stress(&mut self, step: u64, c: f64) -> Result<(), SolverError> {
        let dt = self.dt;
        let pts = &mut self.points;
        let old_stress = pts.stress.clone();
        let old_q = pts.visc_pressure.clone();
        let old_volume = pts.volume.clone();
        for p in 0..pts.len() {
            let inc = tensor::add_scaled(&tensor::IDENTITY, &pts.vel_grad[p], dt);
            pts.def_grad[p] = tensor::mul(&inc, &pts.def_grad[p]);
            let j = tensor::det(&pts.def_grad[p]);
            pts.volume[p] = pts.volume0[p] * j;
            if !(j > 0.0) {
                return Err(SolverError::Diverged {
                    step,
                    what: format!("particle {p} has a non-positive volume ratio J = {j:e}"),
                    cause: "time step too large or the particle was crushed between its neighbours",
                });
            }
        }
        for (b, range) in self.body_ranges.iter().enumerate() {
            let batch = ClosureBatch {
                first: range.start,
                vel_grad: &pts.vel_grad[range.clone()],
                def_grad: &pts.def_grad[range.clone()],
                mass: &pts.mass[range.clone()],
                volume: &pts.volume[range.clone()],
                stress: &mut pts.stress[range.clone()],
            };
            self.closures[b].advance(batch, dt).map_err(|source| SolverError::Closure { step, source })?;
            self.closure_evaluations += range.len() as u64;
        }
        let h = self.grid.min_spacing();
        for p in 0..pts.len() {
            let d = tensor::sym(&pts.vel_grad[p]);
            let rate = tensor::trace(&d);
            pts.visc_pressure[p] = match self.viscosity {
                Viscosity::Linear { coefficient } if rate < 0.0 => coefficient * pts.density(p) * c * h * rate.abs(),
                _ => 0.0,
            };
            let mut mid = tensor::add_scaled(&old_stress[p], &pts.stress[p], 1.0);
            for (a, row) in mid.iter_mut().enumerate() {
                row[a] -= old_q[p] + pts.visc_pressure[p];
            }
            let vol_mid = 0.5 * (old_volume[p] + pts.volume[p]);
            pts.internal_energy[p] += dt * vol_mid * 0.5 * tensor::ddot(&mid, &d);
        }
        Ok(())
    }

    /// Steps 9-10: v_p += sum S (v^L - v^n) (3.13), x_p += dt sum S (v^L + v^n)/2 (3.14).
    fn move_points(&mut self) {
        let (st, dt) = (&self.stencil, self.dt);
        let pts = &mut self.points;
        for p in 0..pts.len() {
            let mut dv = [0.0; D];
            let mut vbar = [0.0; D];
            for e in st.entries(p) {
                let (i, w) = (st.node[e], st.weight[e]);
                for a in 0..D {
                    dv[a] += w * (self.node_v_lagrangian[i][a] - self.node_v[i][a]);
                    vbar[a] += w * 0.5 * (self.node_v_lagrangian[i][a] + self.node_v[i][a]);
                }
            }
            for a in 0..D {
                pts.v[p][a] += dv[a];
                pts.x[p][a] += dt * vbar[a];
            }
            self.grid.wrap_position(&mut pts.x[p]);
        }
    }

    /// Stops a run that is going wrong, naming the particle, the quantity and the likely cause.
    fn guard(&self, step: u64) -> Result<(), SolverError> {
        let pts = &self.points;
        for p in 0..pts.len() {
            let finite = pts.x[p].iter().chain(&pts.v[p]).all(|v| v.is_finite()) && tensor::is_finite(&pts.stress[p]);
            if !finite {
                return Err(SolverError::Diverged {
                    step,
                    what: format!("particle {p} has a non-finite position, velocity or stress"),
                    cause: "time step too large or a tension instability",
                });
            }
        }
        if D == 1 {
            // Neighbours in one body must stay within two cells of each other.
            let h = self.grid.h[0];
            for r in &self.body_ranges {
                let mut xs: Vec<(f64, usize)> = r.clone().map(|p| (pts.x0[p][0], p)).collect();
                xs.sort_by(|a, b| a.0.total_cmp(&b.0));
                for w in xs.windows(2) {
                    let gap = (pts.x[w[1].1][0] - pts.x[w[0].1][0]).abs();
                    if gap > 2.0 * h && !self.grid.periodic(0) {
                        return Err(SolverError::Diverged {
                            step,
                            what: format!("particles {} and {} of one body are {:.2} cells apart", w[0].1, w[1].1, gap / h),
                            cause: "tension instability: too few particles per cell (use sub-points or more particles per cell)",
                        });
                    }
                }
            }
        }
        Ok(())
    }

    /// Stencil entries of the last step (for schemes and tests).
    pub fn stencil(&self) -> &Stencil<D> {
        &self.stencil
    }
}
