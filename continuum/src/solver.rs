//! The explicit step (Dhakal, Ch. 3.1, steps 3-10) and the guard that stops a diverging run.
//!
//! Every per-point pass runs chunk-parallel (see [`crate::par`]) and every scatter to the grid
//! is reduced in a fixed chunk order, so a run gives bitwise the same state for any number of
//! threads.

use crate::closure::{Closure, ClosureError};
use crate::ddmp;
use crate::diagnostics::Totals;
use crate::grid::Grid;
use crate::par::{self, CHUNK, Scatter};
use crate::particles::Particles;
use crate::shape::{self, Block, OutsideGrid, SchemeKind, Stencil, StencilPart};
use crate::tensor::{self, Mat3};
use rayon::prelude::*;

mod corrected;
#[path = "implicit.rs"]
pub mod implicit;
mod impm;
mod nullspace;
mod ranks;
pub use ranks::{DEFAULT_REBALANCE_EVERY, LoadBalance};
mod tlmpm;
mod verlet;

pub use corrected::{GradientCorrection, NodeCorrection, correction_factors};
pub use nullspace::{NullspaceFilter, SVD_MAX_POINTS, global_svd_filter, local_filter};

/// Artificial viscosity added to the closure's stress in compression.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Viscosity {
    None,
    /// Linear form of Ch. 6.3: q = coefficient * rho * c * h * |tr D| when tr D < 0, as a
    /// pressure (the viscous stress is -q I).
    Linear {
        coefficient: f64,
    },
    /// Tensor form (7.8)-(7.10): q = sum_k rho l lambda_k (tau0 c_L c - c_q l lambda_k) g_k g_k^T
    /// over the negative eigenvalues lambda_k (eigenvectors g_k) of D, with
    /// tau0 = |tr L| / |L| (Frobenius norm) and l the mean current length of the point's domain.
    Tensor {
        linear: f64,
        quadratic: f64,
    },
}

/// Why a step (or the set-up of a simulation, step 0) failed. A closure's error is the
/// [`source`](std::error::Error::source) of [`SolverError::Closure`], not part of its message:
/// print the chain (`{:#}` of an `anyhow::Error`, or each source in turn) to see it whole.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SolverError {
    #[error("step {step}: {what}; likely cause: {cause}")]
    Diverged { step: u64, what: String, cause: &'static str },
    #[error("step {step}")]
    Closure {
        step: u64,
        #[source]
        source: ClosureError,
    },
}

/// How velocities and positions advance in time.
///
/// `Dhakal` is the cycle of Dhakal Ch. 3.1 that the issue specifies: v^L = v^n + dt a^n,
/// particle velocities by the increment (3.13), positions and the strain rate with the average
/// (v^n + v^L) / 2 (3.14), (4.10). Derived on one mode of frequency w (a^n = -w^2 x^n, the
/// stress of step n being consistent with x^n): x' = x + dt v - dt^2 w^2 x / 2, v' = v - dt w^2 x,
/// whose amplification matrix has determinant 1 + (w dt)^2 / 2 > 1. The amplitude grows by
/// T w^2 dt / 4 over a time T: first order in dt (Newmark with gamma = 0). Measured on the 2D
/// manufactured solution (h = 1/64, dt = 0.4 h/c, T = 0.02 s): velocity error 9.68e-4, exactly
/// the predicted 3.08 % of the velocity norm 0.0314; at a fixed Courant number the displacement
/// error then stops converging (a floor near 1 % of G, every scheme).
///
/// `Leapfrog` is the staggered update of Gong (4.24), used in her convergence studies:
/// particle velocities live at half steps, v^{n+1/2} = v^{n-1/2} + dt a^n, positions and the
/// strain rate use v^{n+1/2} alone, and the first step advances the velocity by dt / 2 (Gong's
/// v^{1/2} = (v^0 + v^1) / 2). Its amplification matrix has determinant 1 (symplectic, second
/// order). Particle velocities are then half a step behind positions and stresses.
///
/// `Usl` is the symplectic-Euler update-stress-last of the original MPM (battery thesis B 5.3,
/// Table 5.1 "traditional", FLIP form (3.60)-(3.61); notes A.7): v_i^{n+1} = v_i^n + dt a_i^n,
/// the strain rate and the positions with v_i^{n+1}. It is the leapfrog's update without the
/// half first step, so particle velocities are taken to belong to t^n: first order.
///
/// `Usf` is update-stress-first (Bardenhagen; notes A.7): the strain rate uses the mapped
/// velocity v_i^n before the momentum update, the deformation, volume and stress are updated
/// first and the forces come from the new stress; then v_i^{n+1} = v_i^n + dt a_i moves the
/// points (FLIP increment, positions with v_i^{n+1}).
///
/// Every one of them keeps the explicit bound c dt / h <= 1 (Gong 7.32) as the enforced
/// sufficient bound (notes F).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TimeIntegrator {
    #[default]
    Dhakal,
    Leapfrog,
    Usl,
    Usf,
    /// Stormer-Verlet (battery thesis Table 5.1; see `solver/verlet.rs`): half kick, drift,
    /// the linear-implicit F update solved, forces at the new positions, second half kick.
    /// Second order, velocities and positions at t^n; FLIP only.
    StormerVerlet,
    /// Guilkey-Weiss trapezoidal rule (Newmark beta = 1/4, gamma = 1/2) solved by Newton on
    /// the nodal displacements with the stencil frozen over the step; see [`implicit`].
    ImplicitTrapezoidal,
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
    /// Sub-points per point (`ddmp-subpoints`; 1 for every other scheme).
    pub sub_points: usize,
    /// Small-mass threshold m_eps of (7.5) (kg; per unit cross-section in 1D). Nodes at or
    /// below it hand their internal force to heavier neighbours and take their velocity from
    /// them; 0 turns the treatment off (empty nodes still hand on their force, (7.4)).
    pub small_mass: f64,
    /// DDMP nodal volumes V_j summed over the integration points instead of the exact grid
    /// integral (see [`crate::ddmp`]); off by default.
    pub ddmp_point_volumes: bool,
    /// Closure evaluations so far (points advanced), the measure of cost users compare. The
    /// counters saturate: a count (restored from a checkpoint, say) never stops a run.
    pub closure_evaluations: u64,
    /// Integration-point updates so far (points times sub-points per step).
    pub integration_point_updates: u64,
    /// Momentum added by boundary constraints since the start (N s, per unit cross-section in 1D).
    pub wall_impulse: [f64; D],
    /// Sum of the magnitudes of the wall impulses (the scale to judge momentum drift by).
    pub wall_impulse_magnitude: f64,
    pub initial: Totals<D>,
    /// Body force per unit mass (m/s^2) as a function of the point's initial position and the
    /// time (manufactured solutions); applied at the start-of-step time.
    pub body_force: Option<BodyForce<D>>,
    /// Time integration (default: the Ch. 3.1 cycle); see [`TimeIntegrator`].
    pub integrator: TimeIntegrator,
    /// PIC/FLIP blend beta in [0, 1] of the particle velocity update (B 5.24-5.26, notes A.6):
    /// v_p^{n+1} = beta (v_p^n + sum S_ip (v_i^L - v_i^n)) + (1 - beta) sum S_ip v_i^L.
    /// 1 (the default) is the FLIP increment (3.13), 0 is PIC.
    pub flip_fraction: f64,
    /// Prescribed rate of every point's scalar field (1/s; a uniform lithiation), empty for
    /// none. Used only when the points carry a scalar field ([`Particles::with_fields`]).
    pub prescribed_scalar_rate: Vec<f64>,
    /// Ramp time of the prescribed rate (s; 0: none, the rate applies from the start): the
    /// rate is scaled by [`crate::silicon::ramp_factor`] over each step.
    pub prescribed_ramp: f64,
    /// Diffusion of the scalar field (see [`crate::diffusion`]); none by default.
    pub diffusion: Option<crate::diffusion::Diffusion<D>>,
    /// Options and per-step record of the implicit integrator (unused by the explicit ones).
    pub implicit: implicit::Implicit,
    /// Corrected derivatives in the nodal force (see `solver/corrected.rs`); none by default.
    pub gradient_correction: GradientCorrection,
    /// Per node the gradient correction of the current stencil.
    node_correction: Vec<NodeCorrection<D>>,
    /// Nullspace filter on the point velocity gradient (see `solver/nullspace.rs`); none by
    /// default.
    pub nullspace_filter: NullspaceFilter,
    /// Under `tlmpm`: the moving-mesh form (battery thesis 6.25-6.28, 6.35), whose nodal
    /// velocity is carried from step to step in [`Simulation::mesh_velocity`] instead of
    /// re-mapped from the points (`solver/tlmpm.rs`). Off: total-Lagrangian MPM.
    pub moving_mesh: bool,
    /// The moving mesh's nodal velocity at the last half step (empty before its first step:
    /// then mapped from the points). Checkpoints carry it.
    pub mesh_velocity: Vec<[f64; D]>,
    stencil: Stencil<D>,
    node_mass: Vec<f64>,
    node_force: Vec<[f64; D]>,
    node_v: Vec<[f64; D]>,
    /// What the PIC share of `move_points` starts from (filled only for `flip_fraction` < 1,
    /// by whatever maps the step's nodal velocity, and used once): the mapped velocity with the
    /// boundary conditions but before the small-mass average (7.7), and the wall impulse of
    /// that projection.
    pic_base: Vec<[f64; D]>,
    pic_wall: ([f64; D], f64),
    node_v_lagrangian: Vec<[f64; D]>,
    body_ranges: Vec<std::ops::Range<usize>>,
    /// Per body (1D), point indices sorted by initial position, for the neighbour-gap guard.
    order_1d: Vec<Vec<usize>>,
    scatter: Scatter,
    /// The points of each slab tile, the fixed summation order of every scatter of the step
    /// (see [`crate::par`]).
    tiles: par::Tiles,
    /// Over MPI ranks with the per-point work split (see `solver/ranks.rs`): per point whether
    /// this rank computes it this step (the points of the tiles it owns). Empty: every point.
    owned: Vec<bool>,
    /// Which rank computes which tiles when the per-point work is split over MPI ranks, and
    /// how often that is chosen again from measured costs (see [`LoadBalance`]).
    pub balance: LoadBalance,
    /// After a split step: per point whether this rank computed it (`held`: its whole state is
    /// current here), and whether the other ranks' points are stale here (they are brought in
    /// by [`Simulation::share_all`], or by the migration of a point onto this rank's tiles;
    /// `solver/ranks.rs`). What the next step and the per-step figures read of every point
    /// came with the step's end instead: `split_wave_speed`, `step_sums` (in tile order) and
    /// `split_points` (the points each rank computed).
    held: Vec<bool>,
    foreign_stale: bool,
    split_wave_speed: f64,
    step_sums: Option<(Totals<D>, f64)>,
    split_points: Vec<usize>,
    /// Points sent whole to the rank that computes them next, summed over the steps (over MPI
    /// ranks; 0 on one process).
    pub migrated_points: u64,
    flat: Vec<f64>,
    sub_x: Vec<[f64; D]>,
    ddmp_field: Vec<f64>,
    /// Start-of-step stress, viscous stress and volume (reused buffers of step 8).
    old_stress: Vec<Mat3>,
    old_q: Vec<Mat3>,
    old_volume: Vec<f64>,
}

/// A body force field b(X, t) (m/s^2) of the initial position X and time t (s).
pub type BodyForce<const D: usize> = std::sync::Arc<dyn Fn(&[f64; D], f64) -> [f64; D] + Send + Sync>;

/// Nodes lighter than this fraction of the lightest point carry no velocity of their own.
const EMPTY_NODE_FRACTION: f64 = 1e-12;
/// A node accelerating faster than this many c^2/h is treated as a blow-up.
const ACCELERATION_LIMIT: f64 = 1e3;
/// Largest gap between neighbouring points of one 1D body, in cells, before the guard calls it
/// a tension instability. The issue says two cells; DDMP's gradient reaches two cells on each
/// side of a node, and the 2 x 16 strong tube legitimately opens a 2.0-cell gap at the contact
/// in its first steps (the rarefaction expands the gas threefold), so the limit is three.
pub const GAP_LIMIT_CELLS: f64 = 3.0;
/// Default small-mass threshold as a fraction of the mean initial point mass (Ch. 7.2).
pub const DEFAULT_SMALL_MASS_FRACTION: f64 = 0.04;

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
        let order_1d = if D == 1 {
            body_ranges
                .iter()
                .map(|r| {
                    let mut o: Vec<usize> = r.clone().collect();
                    o.sort_by(|&a, &b| points.x0[a][0].total_cmp(&points.x0[b][0]));
                    o
                })
                .collect()
        } else {
            Vec::new()
        };
        let mean_mass = points.mass.iter().sum::<f64>() / points.len().max(1) as f64;
        let mut sim = Simulation {
            initial: Totals::default(),
            body_force: None,
            integrator: TimeIntegrator::Dhakal,
            flip_fraction: 1.0,
            prescribed_scalar_rate: Vec::new(),
            prescribed_ramp: 0.0,
            diffusion: None,
            implicit: implicit::Implicit::default(),
            gradient_correction: GradientCorrection::None,
            node_correction: Vec::new(),
            nullspace_filter: NullspaceFilter::None,
            moving_mesh: false,
            mesh_velocity: Vec::new(),
            grid,
            points,
            scheme,
            closures,
            viscosity,
            dt,
            time: 0.0,
            step: 0,
            sub_points: 1,
            ddmp_point_volumes: false,
            small_mass: DEFAULT_SMALL_MASS_FRACTION * mean_mass,
            closure_evaluations: 0,
            integration_point_updates: 0,
            wall_impulse: [0.0; D],
            wall_impulse_magnitude: 0.0,
            stencil: Stencil::default(),
            node_mass: vec![0.0; n],
            node_force: vec![[0.0; D]; n],
            node_v: vec![[0.0; D]; n],
            pic_base: Vec::new(),
            pic_wall: ([0.0; D], 0.0),
            node_v_lagrangian: vec![[0.0; D]; n],
            body_ranges,
            order_1d,
            scatter: Scatter::default(),
            tiles: par::Tiles::default(),
            owned: Vec::new(),
            balance: LoadBalance::default(),
            held: Vec::new(),
            foreign_stale: false,
            split_wave_speed: 0.0,
            step_sums: None,
            split_points: Vec::new(),
            migrated_points: 0,
            flat: Vec::new(),
            old_stress: Vec::new(),
            old_q: Vec::new(),
            old_volume: Vec::new(),
            sub_x: Vec::new(),
            ddmp_field: Vec::new(),
        };
        // Initialization is not counted as closure evaluations.
        let mut uncounted = 0;
        ranks::advance_all_closures(par::exchange(), &mut sim.points, &mut sim.closures, &sim.body_ranges, 0, None, &mut uncounted)?;
        sim.initial = sim.totals();
        Ok(sim)
    }

    /// Sets the number of sub-points per point (only `ddmp-subpoints` uses more than one).
    pub fn with_sub_points(mut self, n: usize) -> Self {
        self.sub_points = if self.scheme == SchemeKind::DdmpSubpoints { n.max(1) } else { 1 };
        self
    }

    /// Sets m_eps to `fraction` of the mean initial point mass.
    pub fn with_small_mass_fraction(mut self, fraction: f64) -> Self {
        let mean_mass = self.points.mass.iter().sum::<f64>() / self.points.len().max(1) as f64;
        self.small_mass = fraction * mean_mass;
        self
    }

    /// Largest wave speed over all bodies (m/s). After a split step over MPI ranks, the one its
    /// end gathered (the largest over the ranks' points: [`Closure::wave_speed`]).
    pub fn wave_speed(&self) -> f64 {
        if self.foreign_stale {
            return self.split_wave_speed;
        }
        self.body_ranges
            .iter()
            .zip(&self.closures)
            .map(|(r, c)| c.wave_speed(&self.points.mass[r.clone()], &self.points.volume[r.clone()]))
            .fold(0.0, f64::max)
    }

    /// Mass, momentum and energy now (every point current: over MPI ranks after
    /// [`Simulation::share_all`]).
    pub fn totals(&self) -> Totals<D> {
        Totals::of(&self.points)
    }

    /// Mass, momentum and energy after the last step, and its momentum scale (the sum of m |v|
    /// over the points), for the figures a run follows step by step (the largest kinetic
    /// energy and momentum, the energy drift of the progress reports). Where the step's
    /// per-point work can be split over MPI ranks ([`Simulation::splittable`]) summed tile by
    /// tile over the step's tiles, each in ascending point index, then in tile order (over
    /// ranks each rank sums its own tiles and the step's end gathers them), so every rank
    /// count gives the same bits; otherwise in point order, as [`Simulation::totals`].
    pub fn step_totals(&self) -> (Totals<D>, f64) {
        if let Some(s) = self.step_sums {
            return s;
        }
        if self.splittable() && self.tiles.count() > 0 {
            return in_tile_order((0..self.tiles.count()).map(|t| self.tile_sums(t)));
        }
        let scale = (0..self.points.len()).map(|p| crate::diagnostics::momentum_magnitude(&self.points, p)).sum();
        (Totals::of(&self.points), scale)
    }

    /// [`Simulation::step_totals`] of the points of tile `t`, in ascending index (tiles are
    /// added with [`in_tile_order`]).
    fn tile_sums(&self, t: usize) -> (Totals<D>, f64) {
        let (mut sums, mut scale) = (Totals::default(), 0.0);
        for &p in self.tiles.points(t) {
            sums.add_point(&self.points, p);
            scale += crate::diagnostics::momentum_magnitude(&self.points, p);
        }
        (sums, scale)
    }

    /// Lumped nodal masses of the last step (kg).
    pub fn node_mass(&self) -> &[f64] {
        &self.node_mass
    }

    /// Nodal internal forces of the last step after the small-mass redistribution (N).
    pub fn node_force(&self) -> &[[f64; D]] {
        &self.node_force
    }

    /// One explicit step.
    pub fn step(&mut self) -> Result<StepReport, SolverError> {
        if self.foreign_stale && self.split_ranks().is_none() {
            self.share_all();
        }
        self.owned.clear();
        self.step_sums = None;
        if self.scheme == SchemeKind::Tlmpm {
            return self.tlmpm_step();
        }
        if self.integrator == TimeIntegrator::ImplicitTrapezoidal {
            return self.implicit_step();
        }
        if self.integrator == TimeIntegrator::StormerVerlet {
            return self.verlet_step();
        }
        let step = self.step + 1;
        let dt = self.dt;
        let ranks = self.split_ranks();
        let clock = ranks.map(|ex| (std::time::Instant::now(), ex.stats().seconds));
        let built = self.build_stencil(ranks);
        ranks::agree(
            ranks,
            built.map_err(|o| {
                (o.point, stencil_error(step, &o, "time step too large or a domain sheared past its limit (use cpdi1 or ddmp)"))
            }),
        )?;
        self.correct_gradients(step)?;
        let c = self.wave_speed();
        if self.scheme == SchemeKind::Impm {
            self.impm_grid(step)?;
            self.lagrangian_update(step, c)?;
            self.velocity_gradients();
            self.filter_velocity_gradients(step)?;
            self.advance_scalar(step)?;
            self.deform_and_stress(step, c)?;
        } else if self.integrator == TimeIntegrator::Usf {
            self.map_velocities(step)?;
            // Update stress first: strain rate from the mapped v^n, then forces from the new stress.
            self.velocity_gradients();
            self.filter_velocity_gradients(step)?;
            self.advance_scalar(step)?;
            self.deform_and_stress(step, c)?;
            self.nodal_forces();
            self.lagrangian_update(step, c)?;
        } else {
            self.map_velocities(step)?;
            self.nodal_forces();
            self.lagrangian_update(step, c)?;
            self.velocity_gradients();
            self.filter_velocity_gradients(step)?;
            self.advance_scalar(step)?;
            self.deform_and_stress(step, c)?;
        }
        self.move_points();
        self.time += dt;
        self.step = step;
        self.integration_point_updates = self.integration_point_updates.saturating_add((self.points.len() * self.sub_points) as u64);
        match ranks {
            None => self.guard(step)?,
            Some(ex) => {
                // Each rank checks its own points, all agree on the lowest bad one, then the
                // step's end gathers the sums (in 1D also the positions the neighbour-gap check
                // reads, which then runs on all).
                ranks::agree(Some(ex), self.guard_points(step))?;
                self.finish_split(ex);
                if let Some((start, inside)) = clock {
                    let outside = start.elapsed().as_secs_f64() - (ex.stats().seconds - inside);
                    self.balance.record(outside, self.owned.iter().filter(|&&o| o).count());
                }
                self.guard_gaps(step)?;
            }
        }
        Ok(StepReport { step, time: self.time })
    }

    /// Fills the stencil for the scheme (DDMP: sub-points and the nodal integrals first). With
    /// `ranks` (the per-point work split over MPI ranks), only this rank's points get a row.
    fn build_stencil(&mut self, ranks: Option<&dyn par::TileExchange>) -> Result<(), OutsideGrid> {
        let n = self.points.len();
        let ns = self.sub_points.max(1);
        let (grid, x, held) = (&self.grid, &self.points.x, &self.held);
        let n_tiles = par::slab_tile_count(grid);
        match ranks {
            // After a split step only the points this rank computed are current here: they are
            // sorted into the tiles, those in other ranks' tiles sent to them, the points
            // entering this rank's tiles taken in (`migrate`).
            Some(ex) if self.foreign_stale => {
                self.tiles.assign_some(n_tiles, n, |p| held[p].then(|| par::slab_tile(grid, &x[p])));
                self.rebalance(ex);
                self.migrate(ex);
                par::owned_points(&self.tiles, ex.rank(), ex.size(), &mut self.owned);
            }
            // Every point current here (the first split step, or after `share_all`): from now
            // on only this rank's (a failure later in the step shares them as they stand).
            Some(ex) => {
                self.tiles.assign(n_tiles, n, |p| par::slab_tile(grid, &x[p]));
                self.rebalance(ex);
                par::owned_points(&self.tiles, ex.rank(), ex.size(), &mut self.owned);
                self.split_wave_speed = self.wave_speed();
                self.held.clone_from(&self.owned);
                self.foreign_stale = true;
            }
            None => {
                self.tiles.assign(n_tiles, n, |p| par::slab_tile(grid, &x[p]));
                self.owned.clear();
            }
        }
        if self.scheme.is_ddmp() {
            ddmp::place_all(&self.points, ns, &self.owned, &mut self.sub_x);
            if self.ddmp_point_volumes {
                ddmp::assemble_volumes(&self.grid, &self.points, &self.sub_x, ns, &self.tiles, &mut self.scatter, &mut self.ddmp_field);
            }
        }
        let ranges = par::chunk_ranges(n);
        self.stencil.parts.resize_with(ranges.len(), StencilPart::default);
        self.stencil.parts.truncate(ranges.len());
        let (grid, pts, scheme) = (&self.grid, &self.points, self.scheme);
        let (subs, field) = (&self.sub_x, if self.ddmp_point_volumes { Some(self.ddmp_field.as_slice()) } else { None });
        let owned = &self.owned;
        let results: Vec<Result<(), OutsideGrid>> = self
            .stencil
            .parts
            .par_iter_mut()
            .zip(ranges.into_par_iter())
            .map_init(Block::default, |block, (part, r)| {
                part.clear(r.start);
                for p in r {
                    if !owned.is_empty() && !owned[p] {
                        // Another rank's point: an empty row (no scatter of this rank reads it).
                        part.end_point();
                        continue;
                    }
                    match scheme {
                        SchemeKind::Mpm | SchemeKind::Ugimp | SchemeKind::Cpgimp => shape::gimp_row(scheme, grid, pts, p, part)?,
                        // IMPM moves its points with the hat functions at x_p^s (Gong 5.3 steps 5-6).
                        // TLMPM builds its stencil once, at X_p (`solver/tlmpm.rs`); hats here.
                        SchemeKind::Impm | SchemeKind::Tlmpm => shape::gimp_row(SchemeKind::Mpm, grid, pts, p, part)?,
                        SchemeKind::Cpdi | SchemeKind::Cpdi1 | SchemeKind::Cpdi2 => shape::cpdi_row(scheme, grid, pts, p, block, part)?,
                        SchemeKind::CpdiImproved | SchemeKind::Cpdi1Improved => {
                            shape::cpdi_row(impm::improved_cpdi_base::<D>(scheme), grid, pts, p, block, part)?
                        }
                        SchemeKind::Ddmp | SchemeKind::DdmpSubpoints => {
                            ddmp::ddmp_row(grid, pts, p, &subs[p * ns..(p + 1) * ns], field, block, part)?
                        }
                    }
                    part.end_point();
                }
                Ok(())
            })
            .collect();
        results.into_iter().collect()
    }

    /// Steps 3-4: lumped nodal mass and momentum, nodal velocity, small-mass velocities (7.7).
    fn map_to_grid(&mut self) {
        let (st, pts) = (&self.stencil, &self.points);
        self.scatter.run_tiled(
            &self.tiles,
            self.grid.node_count(),
            D + 1,
            &mut self.flat,
            |p| row_span(st, p),
            |tile, w| {
                for &p in tile {
                    let (nodes, weights, _) = st.row(p);
                    for (&i, &s) in nodes.iter().zip(weights) {
                        if s == 0.0 {
                            continue;
                        }
                        let slot = w.slot(i);
                        let m = s * pts.mass[p];
                        slot[0] += m;
                        for a in 0..D {
                            slot[1 + a] += m * pts.v[p][a];
                        }
                    }
                }
            },
        );
        let floor = self.empty_floor();
        let flat = &self.flat;
        self.node_mass.par_iter_mut().zip(self.node_v.par_iter_mut()).enumerate().for_each(|(i, (m, v))| {
            let f = &flat[i * (D + 1)..(i + 1) * (D + 1)];
            *m = f[0];
            *v = if f[0] > floor { std::array::from_fn(|a| f[1 + a] / f[0]) } else { [0.0; D] };
        });
        // The PIC share interpolates velocities, not increments: it must see the momentum the
        // points brought, not the small-mass average below.
        self.set_pic_base();
        if self.small_mass > 0.0 && self.node_mass.iter().any(|&m| m > floor && m <= self.small_mass) {
            // (7.7) read as an average: a light node takes the sqrt(m)-weighted mean velocity of
            // the nodes sharing a cell with it (itself included). Its lumped mass is kept, so the
            // FLIP update (3.13) still conserves momentum (and PIC reads `pic_base`).
            let (grid, mass, eps, old) = (&self.grid, &self.node_mass, self.small_mass, self.node_v.clone());
            self.node_v.par_iter_mut().enumerate().for_each(|(i, v)| {
                if !(mass[i] > floor && mass[i] <= eps) {
                    return;
                }
                let (mut sum, mut wsum) = ([0.0; D], 0.0);
                for_each_neighbour(grid, i, |j| {
                    let w = mass[j].max(0.0).sqrt();
                    wsum += w;
                    for a in 0..D {
                        sum[a] += w * old[j][a];
                    }
                });
                if wsum > 0.0 {
                    *v = std::array::from_fn(|a| sum[a] / wsum);
                }
            });
        }
        let mass = std::mem::take(&mut self.node_mass);
        self.grid.apply_boundaries(&mass, &mut self.node_v);
        self.node_mass = mass;
    }

    /// For a PIC share: `pic_base` = `node_v` with the boundary conditions, and their impulse.
    fn set_pic_base(&mut self) {
        if self.flip_fraction < 1.0 {
            self.pic_base.clone_from(&self.node_v);
            self.pic_wall = self.grid.apply_boundaries(&self.node_mass, &mut self.pic_base);
        }
    }

    fn empty_floor(&self) -> f64 {
        EMPTY_NODE_FRACTION * self.points.mass.iter().cloned().fold(f64::INFINITY, f64::min)
    }

    /// Step 5: f_i = -sum_p V_p (sigma_p + q_p) . G_ip, then the distribution (7.4)-(7.6).
    fn nodal_forces(&mut self) {
        let (st, pts, body, t) = (&self.stencil, &self.points, &self.body_force, self.time);
        let corr = if self.gradient_correction == GradientCorrection::None { None } else { Some(self.node_correction.as_slice()) };
        self.scatter.run_tiled(
            &self.tiles,
            self.grid.node_count(),
            D,
            &mut self.flat,
            |p| row_span(st, p),
            |tile, w| {
                for &p in tile {
                    let s = tensor::add_scaled(&pts.stress[p], &pts.visc_stress[p], 1.0);
                    let vol = pts.volume[p];
                    let b = body.as_ref().map(|f| f(&pts.x0[p], t));
                    let (nodes, weights, grads) = st.row(p);
                    for ((&i, g), &sw) in nodes.iter().zip(grads).zip(weights) {
                        // Corrected derivatives: G~_ip = A_i (G_ip - S_ip r_i).
                        let g = &match corr {
                            Some(c) => c[i].apply(g, sw),
                            None => *g,
                        };
                        let slot = w.slot(i);
                        if let Some(b) = b {
                            for a in 0..D {
                                slot[a] += sw * pts.mass[p] * b[a];
                            }
                        }
                        for a in 0..D {
                            let mut f = 0.0;
                            for b in 0..D {
                                f += s[a][b] * g[b];
                            }
                            slot[a] -= vol * f;
                        }
                    }
                }
            },
        );
        let flat = &self.flat;
        self.node_force.par_iter_mut().enumerate().for_each(|(i, f)| *f = std::array::from_fn(|a| flat[i * D + a]));
        let floor = self.empty_floor();
        // (7.4): forces on empty nodes go to the nodes sharing a cell, in proportion to sqrt(m).
        let empty_with_force = |m: &[f64], f: &[[f64; D]]| (0..m.len()).any(|i| m[i] <= floor && f[i].iter().any(|v| *v != 0.0));
        // Sub-points reach past the material, so a force can sit two nodes away from any mass:
        // repeat the hand-on (each pass moves it one node closer to the mass), a few times.
        for _ in 0..4 {
            if !empty_with_force(&self.node_mass, &self.node_force) {
                break;
            }
            self.node_force = distribute_empty(&self.grid, &self.node_mass, &self.node_force, floor);
        }
        // (7.5)-(7.6): the same for light nodes (m <= m_eps), which keep their own share.
        let eps = self.small_mass;
        if eps > 0.0 && self.node_mass.iter().any(|&m| m > floor && m <= eps) {
            self.node_force = distribute(&self.grid, &self.node_mass, &self.node_force, |m| m > floor && m <= eps);
        }
    }

    /// Step 6: Lagrangian nodal velocity, boundary conditions, wall impulse.
    fn lagrangian_update(&mut self, step: u64, c: f64) -> Result<(), SolverError> {
        let floor = self.empty_floor();
        let limit = ACCELERATION_LIMIT * c * c / self.grid.min_spacing();
        // The leapfrog's first step takes the velocity from t = 0 to t = dt / 2.
        let first_half = self.integrator == TimeIntegrator::Leapfrog && self.step == 0;
        let (mass, force, v) = (&self.node_mass, &self.node_force, &self.node_v);
        let dt = if first_half { 0.5 * self.dt } else { self.dt };
        let bad = self
            .node_v_lagrangian
            .par_iter_mut()
            .enumerate()
            .filter_map(|(i, vl)| {
                let m = mass[i];
                if m <= floor {
                    *vl = [0.0; D];
                    return None;
                }
                let mut bad = None;
                for a in 0..D {
                    let acc = force[i][a] / m;
                    if !(acc.abs() <= limit) && bad.is_none() {
                        bad = Some((i, a, acc));
                    }
                    vl[a] = v[i][a] + dt * acc;
                }
                bad
            })
            .min_by_key(|b| b.0);
        if let Some((i, a, acc)) = bad {
            return Err(SolverError::Diverged {
                step,
                what: format!(
                    "node {:?} acceleration {acc:e} m/s^2 along axis {a} exceeds {limit:e} (= {ACCELERATION_LIMIT} c^2/h)",
                    self.grid.unlinear(i)
                ),
                cause: "time step too large for the wave speed, or a tension instability (too few particles per cell)",
            });
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
        let (st, v, vl) = (&self.stencil, &self.node_v, &self.node_v_lagrangian);
        let old = self.old_velocity_weight();
        // USF: the start-of-step velocity alone (v^L is not computed yet).
        let first = self.integrator == TimeIntegrator::Usf;
        let owned = &self.owned;
        par::for_chunks_mut(&mut self.points.vel_grad, 1, |r, out| {
            for (k, p) in r.enumerate() {
                if !owned.is_empty() && !owned[p] {
                    continue;
                }
                let (nodes, _, grads) = st.row(p);
                let mut l: Mat3 = tensor::ZERO;
                for (&i, g) in nodes.iter().zip(grads) {
                    for a in 0..D {
                        let v_half = if first { v[i][a] } else { old * v[i][a] + (1.0 - old) * vl[i][a] };
                        for b in 0..D {
                            l[a][b] += v_half * g[b];
                        }
                    }
                }
                out[k] = l;
            }
        });
    }

    /// The scalar field the points carry (when they carry one): its rate over the step (the
    /// prescribed rate plus the diffusion's) and its value at the end of the step, before the
    /// closures read the rate.
    fn advance_scalar(&mut self, step: u64) -> Result<(), SolverError> {
        let pts = &mut self.points;
        if pts.scalar.is_empty() {
            return Ok(());
        }
        let (dt, given) = (self.dt, &self.prescribed_scalar_rate);
        let ramp = crate::silicon::ramp_factor(self.time, dt, self.prescribed_ramp);
        let given_at = |p: usize| given.get(p).map_or(0.0, |r| r * ramp); // r * 1.0 is r, bit for bit
        for p in 0..pts.scalar.len() {
            pts.scalar_rate[p] = given_at(p);
        }
        if let Some(d) = self.diffusion.as_mut() {
            // tlmpm's stencil is at X_p: its diffusion is the reference form on it.
            if self.scheme == SchemeKind::Tlmpm && d.configuration == crate::diffusion::Configuration::Current {
                d.configuration = crate::diffusion::Configuration::Lagrangian;
            }
            d.step(&self.grid, self.scheme, &self.stencil, pts, dt).map_err(|o| SolverError::Diverged {
                step,
                what: format!("particle {} lies outside the grid along axis {} at its reference position", o.point, o.axis),
                cause: "the reference-configuration diffusion needs every point's initial position on the grid",
            })?;
        }
        for p in 0..pts.scalar.len() {
            pts.scalar[p] += dt * given_at(p);
        }
        if let Some(p) = pts.scalar.iter().position(|c| !c.is_finite()) {
            return Err(SolverError::Diverged {
                step,
                what: format!("particle {p} has a non-finite concentration"),
                cause: "the time step exceeds the explicit diffusion bound J_min h0^2 / (2 d K)",
            });
        }
        Ok(())
    }

    /// Step 8: deformation gradient, volume, closure stress, artificial viscosity and the
    /// stress work (internal energy, midpoint rule).
    fn deform_and_stress(&mut self, step: u64, c: f64) -> Result<(), SolverError> {
        let dt = self.dt;
        let ranks = self.split_ranks().filter(|_| !self.owned.is_empty());
        let owned = &self.owned;
        let pts = &mut self.points;
        let n = pts.len();
        self.old_stress.resize(n, tensor::ZERO);
        self.old_q.resize(n, tensor::ZERO);
        self.old_volume.resize(n, 0.0);
        let (vel_grad, volume0, stress, visc) = (&pts.vel_grad, &pts.volume0, &pts.stress, &pts.visc_stress);
        let bad = pts
            .def_grad
            .par_iter_mut()
            .zip(pts.volume.par_iter_mut())
            .zip(self.old_stress.par_iter_mut().zip(self.old_q.par_iter_mut()).zip(self.old_volume.par_iter_mut()))
            .enumerate()
            .with_min_len(CHUNK)
            .filter_map(|(p, ((f, vol), ((old_s, old_q), old_vol)))| {
                if !owned.is_empty() && !owned[p] {
                    return None;
                }
                (*old_s, *old_q, *old_vol) = (stress[p], visc[p], *vol);
                let inc = tensor::add_scaled(&tensor::IDENTITY, &vel_grad[p], dt);
                *f = tensor::mul(&inc, f);
                let j = tensor::det(f);
                *vol = volume0[p] * j;
                if j > 0.0 { None } else { Some((p, j)) }
            })
            .min_by_key(|b| b.0);
        let bad = bad.map(|(p, j)| {
            let e = SolverError::Diverged {
                step,
                what: format!("particle {p} has a non-positive volume ratio J = {j:e}"),
                cause: "time step too large or the particle was crushed between its neighbours",
            };
            (p, e)
        });
        ranks::agree(ranks, bad.map_or(Ok(()), Err))?;
        if let Some(ex) = ranks {
            // The closures are pointwise (`split_ranks`): each run of this rank's points is a
            // batch of its own.
            let r = ranks::advance_owned_closures(
                pts,
                &mut self.closures,
                &self.body_ranges,
                owned,
                step,
                dt,
                &mut self.closure_evaluations,
                &mut self.balance,
            );
            ranks::agree(Some(ex), r)?;
        }
        // Every closure sees its batch first (`prepare`), so closures sharing a worker pool send
        // one call for all their bodies; then each is advanced (over MPI ranks, a closure
        // computed once runs on rank 0 and its stresses are given to every rank).
        if ranks.is_none() {
            ranks::advance_all_closures(
                par::exchange(),
                pts,
                &mut self.closures,
                &self.body_ranges,
                step,
                Some(dt),
                &mut self.closure_evaluations,
            )?;
        }
        let (old_stress, old_q, old_volume) = (&self.old_stress, &self.old_q, &self.old_volume);
        let h = self.grid.min_spacing();
        let viscosity = self.viscosity;
        // Taken out so the rest of the points can be read while these are written.
        let (mut visc_stress, mut visc_pressure, mut energy) =
            (std::mem::take(&mut pts.visc_stress), std::mem::take(&mut pts.visc_pressure), std::mem::take(&mut pts.internal_energy));
        let pts_ro: &Particles<D> = pts;
        let owned = &self.owned;
        visc_stress.par_iter_mut().zip(visc_pressure.par_iter_mut()).zip(energy.par_iter_mut()).enumerate().with_min_len(CHUNK).for_each(
            |(p, ((q_out, qp), e))| {
                if !owned.is_empty() && !owned[p] {
                    return;
                }
                let l = &pts_ro.vel_grad[p];
                let d = tensor::sym(l);
                let rho = pts_ro.density(p);
                let q = match viscosity {
                    Viscosity::None => tensor::ZERO,
                    Viscosity::Linear { coefficient } => {
                        let rate = tensor::trace(&d);
                        if rate < 0.0 {
                            tensor::add_scaled(&tensor::ZERO, &tensor::IDENTITY, -coefficient * rho * c * h * rate.abs())
                        } else {
                            tensor::ZERO
                        }
                    }
                    Viscosity::Tensor { linear, quadratic } => tensor_viscosity(pts_ro, p, &d, l, rho, c, linear, quadratic),
                };
                let mut mid = tensor::add_scaled(&old_stress[p], &pts_ro.stress[p], 1.0);
                mid = tensor::add_scaled(&mid, &old_q[p], 1.0);
                mid = tensor::add_scaled(&mid, &q, 1.0);
                let vol_mid = 0.5 * (old_volume[p] + pts_ro.volume[p]);
                *q_out = q;
                *qp = -tensor::trace(&q) / 3.0;
                *e += dt * vol_mid * 0.5 * tensor::ddot(&mid, &d);
            },
        );
        (pts.visc_stress, pts.visc_pressure, pts.internal_energy) = (visc_stress, visc_pressure, energy);
        Ok(())
    }

    /// Steps 9-10: v_p += sum S (v^L - v^n) (3.13), x_p += dt sum S (v^L + v^n)/2 (3.14);
    /// tracked corners move with the grid velocity at the corner (6.28).
    fn move_points(&mut self) {
        let old = self.old_velocity_weight();
        let beta = self.flip_fraction;
        let (st, dt, grid) = (&self.stencil, self.dt, &self.grid);
        // The PIC share starts from the mapped momentum (`pic_base`), so it carries exactly the
        // nodes' momentum plus the impulses; where nothing mapped one this step, from v^L.
        let base = std::mem::take(&mut self.pic_base);
        let pic_base = beta < 1.0 && base.len() == self.node_v.len();
        if pic_base {
            let (added, magnitude) = self.pic_wall;
            self.wall_impulse_magnitude += (1.0 - beta) * magnitude;
            for a in 0..D {
                self.wall_impulse[a] += (1.0 - beta) * added[a];
            }
        }
        let (nv, nvl) = (&self.node_v, &self.node_v_lagrangian);
        let pts = &mut self.points;
        let track = self.scheme.tracks_corners();
        let nc = 1usize << D;
        let owned = &self.owned;
        pts.v.par_chunks_mut(CHUNK).zip(pts.x.par_chunks_mut(CHUNK)).zip(pts.corners.par_chunks_mut(CHUNK * nc)).enumerate().for_each(
            |(c, ((vs, xs), cs))| {
                for k in 0..vs.len() {
                    let p = c * CHUNK + k;
                    if !owned.is_empty() && !owned[p] {
                        continue;
                    }
                    let (nodes, weights, _) = st.row(p);
                    let mut dv = [0.0; D];
                    let mut vbar = [0.0; D];
                    let mut pic = [0.0; D];
                    for (&i, &w) in nodes.iter().zip(weights) {
                        for a in 0..D {
                            dv[a] += w * (nvl[i][a] - nv[i][a]);
                            vbar[a] += w * ((1.0 - old) * nvl[i][a] + old * nv[i][a]);
                            // v^L + (base - v): v^L itself, bit for bit, wherever the
                            // small-mass average did not move v.
                            pic[a] += w * if pic_base { nvl[i][a] + (base[i][a] - nv[i][a]) } else { nvl[i][a] };
                        }
                    }
                    let before = xs[k];
                    for a in 0..D {
                        if beta == 1.0 {
                            vs[k][a] += dv[a];
                        } else {
                            vs[k][a] = beta * (vs[k][a] + dv[a]) + (1.0 - beta) * pic[a];
                        }
                        xs[k][a] += dt * vbar[a];
                    }
                    let moved = xs[k];
                    grid.wrap_position(&mut xs[k]);
                    let corners = &mut cs[k * nc..(k + 1) * nc];
                    for corner in corners.iter_mut() {
                        if track {
                            let sh = shape::cell_shape(grid, corner);
                            let mut u = [0.0; D];
                            for m in 0..nc {
                                if let Some(i) = shape::node_index(grid, &shape::cell_node(&sh.cell, m)) {
                                    for a in 0..D {
                                        u[a] += sh.s[m] * ((1.0 - old) * nvl[i][a] + old * nv[i][a]);
                                    }
                                }
                            }
                            for a in 0..D {
                                corner[a] += dt * u[a];
                            }
                        } else {
                            for a in 0..D {
                                corner[a] += moved[a] - before[a];
                            }
                        }
                        // Keep the corners with their point when it wraps around a periodic axis.
                        for a in 0..D {
                            corner[a] += xs[k][a] - moved[a];
                        }
                    }
                }
            },
        );
        // Used once: the next step maps its own (the buffer is kept).
        self.pic_base = base;
        self.pic_base.clear();
    }

    /// Stops a run that is going wrong, naming the particle, the quantity and the likely cause.
    fn guard(&self, step: u64) -> Result<(), SolverError> {
        self.guard_points(step).map_err(|(_, e)| e)?;
        self.guard_gaps(step)
    }

    /// The guard's per-point check (this rank's points when the work is split): the lowest
    /// point with a non-finite position, velocity or stress, with its error.
    fn guard_points(&self, step: u64) -> Result<(), (usize, SolverError)> {
        let (pts, owned) = (&self.points, &self.owned);
        let bad = (0..pts.len()).into_par_iter().with_min_len(CHUNK).find_first(|&p| {
            (owned.is_empty() || owned[p])
                && !(pts.x[p].iter().chain(&pts.v[p]).all(|v| v.is_finite()) && tensor::is_finite(&pts.stress[p]))
        });
        match bad {
            Some(p) => Err((
                p,
                SolverError::Diverged {
                    step,
                    what: format!("particle {p} has a non-finite position, velocity or stress"),
                    cause: "time step too large or a tension instability",
                },
            )),
            None => Ok(()),
        }
    }

    /// Whether the guard checks the gaps between neighbouring points ([`Simulation::guard_gaps`]).
    fn gap_guarded(&self) -> bool {
        D == 1 && !self.grid.periodic(0)
    }

    /// The guard's neighbour-gap check of 1D bodies (over every point).
    fn guard_gaps(&self, step: u64) -> Result<(), SolverError> {
        let pts = &self.points;
        if self.gap_guarded() {
            // Neighbours in one body must stay within GAP_LIMIT_CELLS cells of each other.
            let h = self.grid.h[0];
            for order in &self.order_1d {
                for w in order.windows(2) {
                    let gap = (pts.x[w[1]][0] - pts.x[w[0]][0]).abs();
                    if gap > GAP_LIMIT_CELLS * h {
                        return Err(SolverError::Diverged {
                            step,
                            what: format!("particles {} and {} of one body are {:.2} cells apart", w[0], w[1], gap / h),
                            cause: "tension instability: too few particles per cell (use sub-points or more particles per cell)",
                        });
                    }
                }
            }
        }
        Ok(())
    }

    /// Weight of the start-of-step nodal velocity in the velocity that moves the points and
    /// drives the strain rate: 1/2 for the Ch. 3.1 cycle (3.14), 0 for the leapfrog.
    fn old_velocity_weight(&self) -> f64 {
        match self.integrator {
            TimeIntegrator::Dhakal => 0.5,
            TimeIntegrator::Leapfrog | TimeIntegrator::Usl | TimeIntegrator::Usf | TimeIntegrator::StormerVerlet => 0.0,
            TimeIntegrator::ImplicitTrapezoidal => 0.5,
        }
    }

    /// The time the particle velocities belong to (s): the simulated time, or half a step
    /// before it for the leapfrog (staggered velocities).
    pub fn velocity_time(&self) -> f64 {
        match self.integrator {
            TimeIntegrator::Leapfrog if self.step > 0 => self.time - 0.5 * self.dt,
            _ => self.time,
        }
    }

    /// Stencil of the last step (for schemes and tests).
    pub fn stencil(&self) -> &Stencil<D> {
        &self.stencil
    }
}

/// The node window `lo..hi` point `p`'s row touches (`(0, 0)` for an empty row).
fn row_span<const D: usize>(st: &Stencil<D>, p: usize) -> (usize, usize) {
    let (nodes, _, _) = st.row(p);
    let (lo, hi) = nodes.iter().fold((usize::MAX, 0), |(lo, hi), &i| (lo.min(i), hi.max(i + 1)));
    if lo < hi { (lo, hi) } else { (0, 0) }
}

/// Calls `f` with every node sharing a cell with node `i` (itself included), each once.
fn for_each_neighbour<const D: usize>(grid: &Grid<D>, i: usize, mut f: impl FnMut(usize)) {
    let idx = grid.unlinear(i);
    let mut seen = [usize::MAX; 27];
    let mut count = 0;
    for o in 0..ddmp::neighbours(D) {
        let mut rem = o;
        let mut lin = Some(0usize);
        let n: [i64; D] = std::array::from_fn(|a| {
            let d = (rem % 3) as i64 - 1;
            rem /= 3;
            idx[a] as i64 + d
        });
        for a in (0..D).rev() {
            lin = match (lin, grid.wrap(a, n[a])) {
                (Some(l), Some(w)) => Some(l * grid.nodes_along(a) + w),
                _ => None,
            };
        }
        if let Some(j) = lin
            && !seen[..count].contains(&j)
        {
            seen[count] = j;
            count += 1;
            f(j);
        }
    }
}

/// Redistributes the forces of the nodes selected by `light` over the nodes sharing a cell
/// with them (themselves included), in proportion to sqrt(m): (7.4)-(7.5). The total force is
/// unchanged (the shares of each node sum to one), so momentum is conserved. A node whose
/// whole neighbourhood is massless keeps its force.
fn distribute<const D: usize>(grid: &Grid<D>, mass: &[f64], force: &[[f64; D]], light: impl Fn(f64) -> bool + Sync) -> Vec<[f64; D]> {
    // Only selected nodes with a force hand anything on: a zero force's shares add +-0 to a
    // sum that starts at +0 and so is never -0, which leaves it bit for bit as it was. So
    // the rest of the grid (most of it: the empty region far from the material, the bulk)
    // skips its neighbours.
    let hands_on = |l: usize| light(mass[l]) && force[l].iter().any(|v| *v != 0.0);
    let sqrt_sum: Vec<f64> = (0..mass.len())
        .into_par_iter()
        .map(|l| {
            if !hands_on(l) {
                return 0.0;
            }
            let mut s = 0.0;
            for_each_neighbour(grid, l, |j| s += mass[j].max(0.0).sqrt());
            s
        })
        .collect();
    // A node beside no such node keeps its own force (the loop below adds 1 x its force to
    // zero, which `0.0 + f` is, bit for bit).
    let mut near = vec![false; mass.len()];
    for l in (0..mass.len()).filter(|&l| hands_on(l)) {
        // Sharing a cell is symmetric: l is beside j exactly when j is beside l.
        for_each_neighbour(grid, l, |j| near[j] = true);
    }
    (0..mass.len())
        .into_par_iter()
        .map(|i| {
            if !near[i] {
                return std::array::from_fn(|a| 0.0 + force[i][a]);
            }
            let mut f = [0.0; D];
            let own = mass[i].max(0.0).sqrt();
            for_each_neighbour(grid, i, |l| {
                let share = if !light(mass[l]) {
                    if l == i { 1.0 } else { 0.0 }
                } else if sqrt_sum[l] > 0.0 {
                    own / sqrt_sum[l]
                } else if l == i {
                    1.0
                } else {
                    0.0
                };
                if share != 0.0 {
                    for a in 0..D {
                        f[a] += share * force[l][a];
                    }
                }
            });
            f
        })
        .collect()
}

/// (7.4) for empty nodes, extended so force moves towards mass even when no neighbour has any:
/// an empty node with no massive neighbour passes its force in equal shares to its neighbours one
/// node nearer the material (graph distance over nodes sharing a cell), level by level from the
/// farthest, and the nodes beside the material then hand it on by (7.4). Total force is kept:
/// no force is left on a massless node, whose velocity is not updated (a DDMP row of a stretched
/// point reaches nodes two or more cells from any mass). Where no force is that far out (nearly
/// always) this is (7.4) alone, bit for bit.
fn distribute_empty<const D: usize>(grid: &Grid<D>, mass: &[f64], force: &[[f64; D]], floor: f64) -> Vec<[f64; D]> {
    let light = |m: f64| m <= floor;
    let first = distribute(grid, mass, force, light);
    // Nodes whose neighbourhood is massless kept their force.
    let near_mass_of = |i: usize| {
        // A node with mass is beside itself.
        let mut any = !light(mass[i]);
        if !any {
            for_each_neighbour(grid, i, |j| any |= !light(mass[j]));
        }
        any
    };
    let holds = |l: usize| light(mass[l]) && first[l].iter().any(|v| *v != 0.0);
    if !(0..mass.len()).into_par_iter().any(|l| holds(l) && !near_mass_of(l)) {
        return first;
    }
    // Distance of every node from the material (0 on massive nodes), breadth first.
    let mut dist = vec![u32::MAX; mass.len()];
    let mut queue: std::collections::VecDeque<usize> = (0..mass.len()).filter(|&i| !light(mass[i])).collect();
    for &i in &queue {
        dist[i] = 0;
    }
    while let Some(i) = queue.pop_front() {
        for_each_neighbour(grid, i, |j| {
            if dist[j] == u32::MAX {
                dist[j] = dist[i] + 1;
                queue.push_back(j);
            }
        });
    }
    let far = (0..mass.len()).filter(|&l| holds(l) && dist[l] != u32::MAX).map(|l| dist[l]).max().unwrap_or(0);
    let mut f = first;
    for d in (2..=far).rev() {
        let receivers: Vec<usize> = (0..mass.len())
            .into_par_iter()
            .map(|l| {
                let mut n = 0;
                if dist[l] == d {
                    for_each_neighbour(grid, l, |j| n += usize::from(dist[j] == d - 1));
                }
                n
            })
            .collect();
        let passes = |l: usize| dist[l] == d && receivers[l] > 0;
        f = (0..mass.len())
            .into_par_iter()
            .map(|i| {
                let mut fi = if passes(i) { [0.0; D] } else { f[i] };
                if dist[i] == d - 1 {
                    for_each_neighbour(grid, i, |l| {
                        if passes(l) {
                            for a in 0..D {
                                fi[a] += f[l][a] / receivers[l] as f64;
                            }
                        }
                    });
                }
                fi
            })
            .collect();
    }
    distribute(grid, mass, &f, light)
}

/// The sum of per-tile [`Simulation::step_totals`] terms, added in the order given (tile order).
fn in_tile_order<const D: usize>(tiles: impl Iterator<Item = (Totals<D>, f64)>) -> (Totals<D>, f64) {
    tiles.fold((Totals::default(), 0.0), |(mut a, m), (t, tm)| {
        a.add(&t);
        (a, m + tm)
    })
}

/// The tensor artificial viscosity (7.8)-(7.10) of point `p`.
#[allow(clippy::too_many_arguments)]
fn tensor_viscosity<const D: usize>(pts: &Particles<D>, p: usize, d: &Mat3, l: &Mat3, rho: f64, c: f64, c_l: f64, c_q: f64) -> Mat3 {
    let (lambda, g) = tensor::sym_eigen(d);
    if lambda.iter().all(|&v| v >= 0.0) {
        return tensor::ZERO;
    }
    let norm = tensor::ddot(l, l).sqrt();
    let tau0 = if norm > 0.0 { tensor::trace(l).abs() / norm } else { 0.0 };
    let len = (0..D).map(|a| 2.0 * pts.half_vector(p, a).iter().map(|v| v * v).sum::<f64>().sqrt()).sum::<f64>() / D as f64;
    let mut q = tensor::ZERO;
    for k in 0..3 {
        let lk = lambda[k];
        if lk >= 0.0 {
            continue;
        }
        let coef = rho * len * lk * (tau0 * c_l * c - c_q * len * lk);
        for i in 0..3 {
            for j in 0..3 {
                q[i][j] += coef * g[i][k] * g[j][k];
            }
        }
    }
    q
}

/// The guard's error for a stencil that could not be built at `step`: a point outside the grid
/// or a CPDI domain turned inside out (`inverted_cause`: the likely cause then, with the schemes
/// the integrator can offer instead).
pub(crate) fn stencil_error(step: u64, o: &OutsideGrid, inverted_cause: &'static str) -> SolverError {
    if o.inverted {
        SolverError::Diverged {
            step,
            what: format!("the domain of particle {} turned inside out (non-positive corner Jacobian)", o.point),
            cause: inverted_cause,
        }
    } else {
        SolverError::Diverged {
            step,
            what: format!("particle {} left the grid along axis {} (position {:e} m)", o.point, o.axis, o.position),
            cause: "the body moved past a non-periodic face: enlarge the domain or use a wall",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Face;

    /// A force on a massless node three nodes from the only mass (a DDMP row of a stretched
    /// point reaches that far) ends on the mass, whole: none is left on a massless node.
    #[test]
    fn force_far_from_the_material_reaches_it_whole() {
        let free = || (Face::Free, Face::Free);
        let grid = Grid::<2> { origin: [0.0; 2], h: [1.0; 2], cells: [6, 4], faces: [free(), free()] };
        let n = grid.node_count();
        let (floor, at) = (1e-12, |i: usize, j: usize| grid.linear([i, j]));
        let mut mass = vec![0.0; n];
        mass[at(1, 1)] = 2.0;
        mass[at(1, 2)] = 0.5;
        let mut force = vec![[0.0; 2]; n];
        force[at(4, 3)] = [3.0, -1.5];
        force[at(5, 4)] = [0.25, 0.5];
        force[at(1, 1)] = [-1.0, 1.0];
        let total = |f: &[[f64; 2]]| f.iter().fold([0.0; 2], |s, v| [s[0] + v[0], s[1] + v[1]]);
        let out = distribute_empty(&grid, &mass, &force, floor);
        let (before, after) = (total(&force), total(&out));
        for a in 0..2 {
            assert!((before[a] - after[a]).abs() < 1e-14, "{before:?} -> {after:?}");
        }
        for i in (0..n).filter(|&i| mass[i] <= floor) {
            assert_eq!(out[i], [0.0; 2], "force left on massless node {:?}", grid.unlinear(i));
        }
        // Nothing that far: (7.4) alone, bit for bit.
        force[at(4, 3)] = [0.0; 2];
        force[at(5, 4)] = [0.0; 2];
        force[at(2, 2)] = [0.5, 0.5];
        assert_eq!(distribute_empty(&grid, &mass, &force, floor), distribute(&grid, &mass, &force, |m| m <= floor));
    }
}
