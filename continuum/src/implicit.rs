//! The implicit trapezoidal step (Guilkey-Weiss; battery thesis Ch. 5): Newmark with
//! beta = 1/4, gamma = 1/2, solved by Newton on the nodal displacements of the step with the
//! stencil frozen (the points do not move inside Newton). See `continuum/docs/implicit.md` for
//! the derivation, the choices made where the thesis is silent and the errata it corrects.
//!
//! One step:
//! 1. Stencil at the start-of-step positions; lumped nodal mass m_i and velocity v_i^n; the
//!    internal force f^n = -sum_p V_p sigma_p . G_ip and a^n = (f^n + b^n) / m.
//! 2. Unknowns: the components of the nodal displacement u of nodes that carry mass and are not
//!    constrained by a boundary face (a constrained component takes u = dt/2 (v^n + v_wall)).
//! 3. Predictor u = alpha dt v^n (5.41); Newton on the residual (5.34)
//!    R(u) = m (4u/dt^2 - 4 v^n / dt - a^n) - f(u) - b^{n+1}
//!    with J du = -R, the Jacobian analytic (material tangent of the closure) or by coloured
//!    finite differences, the sparse LU of faer for the linear solves.
//! 4. f(u) is the virtual work of the trial state with the frozen stencil: with H_p = sum_i
//!    u_i (x) G_ip, F_p = (I + H_p) F_p^n, the closure's stress sigma_p(H_p) and the nominal
//!    stress of the start configuration P_p = det(I + H) sigma (I + H)^-T,
//!    f_i = -sum_p V_p^n P_p . G_ip (the thesis's (5.47)-(5.52) with V = det(F) V0 multiplies
//!    this by an extra det(I + H) in 1D; the form here is the exact weak form on the frozen map).
//! 5. Commit (5.53)-(5.59): a^{n+1} = 4u/dt^2 - 4v^n/dt - a^n, v^{n+1} = 2u/dt - v^n,
//!    v_p += sum S (v^{n+1} - v^n) (= dt/2 sum S (a^n + a^{n+1})), x_p += sum S u_i, and the trial
//!    F, volume and stress of the converged u.

use super::*;
use crate::closure::{ClosureBatch, Tangent, TangentIn};
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use std::ops::Range;
use std::time::Instant;

/// How the Newton Jacobian is formed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum JacobianKind {
    /// Assembled from the closures' material tangents ([`Closure::tangent`]).
    #[default]
    Analytic,
    /// Forward differences of the residual, columns grouped by a distance-2 colouring of the
    /// node graph so one Jacobian costs (colours x D) residuals whatever the grid size.
    FiniteDifference,
}

/// Options of the implicit integrator.
#[derive(Debug, Clone)]
pub struct ImplicitOptions {
    pub jacobian: JacobianKind,
    /// Predictor weight alpha of (5.41): u = alpha dt v^n (1: constant velocity).
    pub alpha: f64,
    /// Newton has converged when the last correction is at most this many cells (inf-norm)...
    pub displacement_tolerance: f64,
    /// ... or the residual is at most this fraction of the largest term it balances.
    pub residual_tolerance: f64,
    /// Newton iterations (linear solves) before the step is declared failed.
    pub max_iterations: usize,
    /// No point may move more than this many cells in one step (the stencil is frozen).
    pub max_motion_cells: f64,
    /// Adaptive steps (None: the fixed dt of the scene).
    pub adaptive: Option<Adaptive>,
}

impl Default for ImplicitOptions {
    fn default() -> Self {
        ImplicitOptions {
            jacobian: JacobianKind::Analytic,
            alpha: 1.0,
            displacement_tolerance: 1e-10,
            residual_tolerance: 1e-8,
            max_iterations: 20,
            max_motion_cells: 0.5,
            adaptive: None,
        }
    }
}

/// What the implicit integrator did so far (summary.json `implicit`; checkpoints carry it,
/// and a field absent from an older checkpoint reads as its default).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ImplicitStats {
    pub accepted_steps: u64,
    pub rejected_steps: u64,
    /// Of `rejected_steps` (adaptive steps only): the estimated local error above 1, the motion
    /// bound, Newton (or its residual) failing; the step whose attempt first hit the motion
    /// bound (0: none).
    pub rejected_for_error: u64,
    pub rejected_for_motion: u64,
    pub rejected_for_newton: u64,
    pub first_motion_rejection_step: u64,
    /// Newton iterations (linear solves) over all accepted steps.
    pub newton_iterations: u64,
    pub max_newton_iterations_per_step: usize,
    /// Residual evaluations (each a full pass of every point through its closure).
    pub residual_evaluations: u64,
    pub jacobians: u64,
    /// Symbolic LU factorisations (column ordering, elimination structure): one per change of
    /// the Jacobian's pattern; every other Newton iteration reuses the last one.
    pub symbolic_factorisations: u64,
    /// Residual inf-norms of the last step's Newton iterations.
    pub last_residual_history: Vec<f64>,
    /// Distance-2 colours of the last finite-difference Jacobian (0 when analytic).
    pub colours: usize,
    /// Unknowns of the last step.
    pub unknowns: usize,
    pub seconds_residual: f64,
    pub seconds_jacobian: f64,
    pub seconds_solve: f64,
    /// Of `seconds_solve`: the symbolic factorisations (the rest is numeric LU and solve).
    pub seconds_symbolic: f64,
    pub seconds_total: f64,
    /// Estimated local errors of the last step: max over the free dofs of |dt^2/12 (a^{n+1} - a^n)| (m)
    /// and, from the second step on, |dt/12 (a^{n+1} - 2 a^n + a^{n-1})| (m/s).
    pub last_error_u: f64,
    pub last_error_v: f64,
    /// Estimated local error of the deformation gradient of the last step: max over the points
    /// and components of |dt^2/12 sum_i (a_i^{n+1} - a_i^n) (x) G_ip F_p^n| (free dofs only).
    pub last_error_f: f64,
    /// Grid energy balance of the last step: dKE (free dofs) + stress work - constraint and body
    /// force work. The trapezoidal rule makes it vanish at R = 0, so it measures the Newton
    /// tolerance; `last_energy_scale` is the kinetic plus strain energy it is judged against.
    pub last_energy_defect: f64,
    pub last_energy_scale: f64,
    /// WRMS error norm of the last accepted step (0 without adaptive steps) and its dt (s).
    pub last_error_norm: f64,
    pub last_dt: f64,
}

/// Options, record and the nodal history the error estimates need.
#[derive(Debug, Clone, Default)]
pub struct Implicit {
    pub options: ImplicitOptions,
    pub stats: ImplicitStats,
    /// a^n of the previous step per node dof (for the velocity error estimate; empty before the
    /// first step), and its dt. Public so a checkpoint can carry them.
    pub prev_acc: Vec<f64>,
    pub prev_dt: f64,
    /// The symbolic LU of the last Jacobian pattern, kept while the pattern is unchanged.
    symbolic: Option<SymbolicCache>,
}

/// A symbolic sparse LU and the CSC pattern it was computed for.
#[derive(Debug, Clone)]
struct SymbolicCache {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    lu: SymbolicLu<usize>,
}

/// What Newton returns: the converged displacement, its trial state and force, the record.
struct NewtonOut {
    u: Vec<f64>,
    trial: Trial,
    force: Vec<f64>,
    history: Vec<f64>,
    iterations: usize,
    residuals: u64,
    colours: usize,
    times: [f64; 3],
}

/// The outcome of one attempt at a step.
enum Attempt {
    Accepted {
        report: StepReport,
        err: f64,
        speed: f64,
    },
    /// The estimated local error (WRMS) exceeds 1 (adaptive steps only).
    Rejected {
        err: f64,
    },
    /// Newton failed, or (`motion`) the converged step would move a point past the motion
    /// bound; a smaller dt may succeed.
    Failed {
        error: SolverError,
        motion: bool,
    },
}

/// Adaptive time step (the thesis's future work 9.6.2, as proposed in the notes): WRMS norm of
/// le_u and le_v with weights 1/(rtol |y| + atol), accept at err <= 1,
/// dt_new = dt min(max_growth, max(min_shrink, safety err^-1/3)) (local error O(dt^3)), and a
/// cap so no point moves more than 0.9 x the motion bound in the next step.
#[derive(Debug, Clone)]
pub struct Adaptive {
    pub rtol: f64,
    /// Absolute tolerance of the nodal displacement (m).
    pub atol_u: f64,
    /// Absolute tolerance of the nodal velocity (m/s).
    pub atol_v: f64,
    /// Absolute tolerance of the deformation gradient (dimensionless); `None` leaves le_F out
    /// of the error norm.
    pub atol_f: Option<f64>,
    pub safety: f64,
    pub max_growth: f64,
    pub min_shrink: f64,
    pub dt_min: f64,
    pub dt_max: f64,
    /// Rejected attempts of one step before the run stops.
    pub max_rejections: usize,
    /// The end of the run (s): a step that would pass it is shortened to land on it.
    pub end_time: f64,
}

impl Adaptive {
    /// The notes' defaults (safety 0.9, growth at most 2, shrink at least 0.2) with the given
    /// tolerances and no dt bounds beyond positive and finite.
    pub fn new(rtol: f64, atol_u: f64, atol_v: f64) -> Self {
        Adaptive {
            rtol,
            atol_u,
            atol_v,
            atol_f: None,
            safety: 0.9,
            max_growth: 2.0,
            min_shrink: 0.2,
            dt_min: 0.0,
            dt_max: f64::INFINITY,
            max_rejections: 10,
            end_time: f64::INFINITY,
        }
    }
}

/// The trial state of every point for one displacement field.
#[derive(Default)]
struct Trial {
    h: Vec<Mat3>,
    l: Vec<Mat3>,
    f: Vec<Mat3>,
    vol: Vec<f64>,
    stress: Vec<Mat3>,
    /// Equivalent plastic strain of the trial (empty when the points carry none).
    plastic: Vec<f64>,
}

/// The frozen data of one step.
struct Frozen<'a, const D: usize> {
    st: &'a Stencil<D>,
    pts: &'a Particles<D>,
    ranges: &'a [Range<usize>],
    step: u64,
    dt: f64,
}

/// What one step freezes: unknowns, start-of-step nodal fields (all dofs, node * D + axis),
/// the node graph and the Jacobian's pattern.
struct Setup {
    step: u64,
    dt: f64,
    floor: f64,
    /// Free-dof index of every dof (FREE_NONE when constrained).
    index_of: Vec<usize>,
    /// Dof of every free index.
    free: Vec<usize>,
    mass: Vec<f64>,
    v0: Vec<f64>,
    /// Prescribed end-of-step velocity of the constrained dofs.
    v1_fixed: Vec<f64>,
    f0: Vec<f64>,
    b0: Vec<f64>,
    b1: Vec<f64>,
    a0: Vec<f64>,
    adj_ptr: Vec<usize>,
    adj: Vec<usize>,
    pattern: Pattern,
    ranges: Vec<Range<usize>>,
    /// The predictor.
    u0: Vec<f64>,
}

impl Setup {
    /// m (4u/dt^2 - 4 v^n/dt - a^n) of dof `g`.
    fn inertia(&self, u: &[f64], g: usize) -> f64 {
        let dt = self.dt;
        self.mass[g] * (4.0 * u[g] / (dt * dt) - 4.0 * self.v0[g] / dt - self.a0[g])
    }
}

/// Sparsity of the Jacobian over the free dofs (CSC, rows sorted).
struct Pattern {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
}

impl Pattern {
    #[inline]
    fn slot(&self, row: usize, col: usize) -> usize {
        let r = &self.row_idx[self.col_ptr[col]..self.col_ptr[col + 1]];
        self.col_ptr[col] + r.binary_search(&row).expect("entry in the pattern")
    }
}

const FREE_NONE: usize = usize::MAX;

fn nominal(h: &Mat3, sigma: &Mat3) -> Mat3 {
    let fr = tensor::add_scaled(&tensor::IDENTITY, h, 1.0);
    let j = tensor::det(&fr);
    let fi = tensor::inverse(&fr).unwrap_or(tensor::IDENTITY);
    let s = tensor::mul(sigma, &tensor::transpose(&fi));
    tensor::add_scaled(&tensor::ZERO, &s, j)
}

/// dP_ab / dH_kl of P = J_r sigma F_r^-T, F_r = I + H, from T = d sigma / dH:
/// J_r [ (F_r^-1)_lk S_ab + sum_c T_ackl (F_r^-1)_bc - S_al (F_r^-1)_bk ], S = sigma F_r^-T.
fn nominal_tangent(h: &Mat3, sigma: &Mat3, t: &Tangent) -> Tangent {
    let fr = tensor::add_scaled(&tensor::IDENTITY, h, 1.0);
    let j = tensor::det(&fr);
    let fi = tensor::inverse(&fr).unwrap_or(tensor::IDENTITY);
    let s = tensor::mul(sigma, &tensor::transpose(&fi));
    let mut a = [[[[0.0; 3]; 3]; 3]; 3];
    for (ia, aa) in a.iter_mut().enumerate() {
        for (b, ab) in aa.iter_mut().enumerate() {
            for (k, ak) in ab.iter_mut().enumerate() {
                for (l, v) in ak.iter_mut().enumerate() {
                    let tc: f64 = (0..3).map(|c| t[ia][c][k][l] * fi[b][c]).sum();
                    *v = j * (fi[l][k] * s[ia][b] + tc - s[ia][l] * fi[b][k]);
                }
            }
        }
    }
    a
}

impl<const D: usize> Frozen<'_, D> {
    /// The trial state of displacement `u` (all dofs, node * D + axis): H, F, volume, and the
    /// closures' stresses from the start-of-step stress.
    fn evaluate(&self, closures: &mut [Box<dyn Closure>], u: &[f64], t: &mut Trial) -> Result<(), SolverError> {
        let (st, pts, dt) = (self.st, self.pts, self.dt);
        let n = pts.len();
        t.h.resize(n, tensor::ZERO);
        t.l.resize(n, tensor::ZERO);
        t.f.resize(n, tensor::ZERO);
        t.vol.resize(n, 0.0);
        t.stress.resize(n, tensor::ZERO);
        let bad =
            t.h.par_iter_mut()
                .zip(t.l.par_iter_mut())
                .zip(t.f.par_iter_mut().zip(t.vol.par_iter_mut()).zip(t.stress.par_iter_mut()))
                .enumerate()
                .with_min_len(CHUNK)
                .filter_map(|(p, ((h, l), ((f, vol), s)))| {
                    let (nodes, _, grads) = st.row(p);
                    let mut hh = tensor::ZERO;
                    for (&i, g) in nodes.iter().zip(grads) {
                        for a in 0..D {
                            let ui = u[i * D + a];
                            for b in 0..D {
                                hh[a][b] += ui * g[b];
                            }
                        }
                    }
                    *h = hh;
                    *l = tensor::add_scaled(&tensor::ZERO, &hh, 1.0 / dt);
                    *f = tensor::mul(&tensor::add_scaled(&tensor::IDENTITY, &hh, 1.0), &pts.def_grad[p]);
                    let j = tensor::det(f);
                    *vol = pts.volume0[p] * j;
                    *s = pts.stress[p];
                    if j > 0.0 && j.is_finite() { None } else { Some((p, j)) }
                })
                .min_by_key(|b| b.0);
        // Every residual starts from the start-of-step plastic strain (the closure returns
        // the trial's, which the commit keeps).
        t.plastic.clear();
        t.plastic.extend_from_slice(&pts.plastic_strain);
        if let Some((p, j)) = bad {
            return Err(SolverError::Diverged {
                step: self.step,
                what: format!("a Newton iterate inverts particle {p} (J = {j:e})"),
                cause: "inverted point: the time step is too large for Newton from the predictor, or the point was crushed",
            });
        }
        for (b, r) in self.ranges.iter().enumerate() {
            let batch = ClosureBatch {
                step: self.step,
                first: r.start,
                vel_grad: &t.l[r.clone()],
                def_grad: &t.f[r.clone()],
                mass: &pts.mass[r.clone()],
                volume: &t.vol[r.clone()],
                stress: &mut t.stress[r.clone()],
                // The step's scalar rate (prescribed plus diffusion, advanced explicitly on
                // the frozen stencil before Newton) and the plastic state.
                scalar_rate: if pts.scalar_rate.is_empty() { &[] } else { &pts.scalar_rate[r.clone()] },
                plastic_strain: if t.plastic.is_empty() { &mut [] } else { &mut t.plastic[r.clone()] },
                visc_stress: &[],
            };
            closures[b].advance(batch, dt).map_err(|source| SolverError::Closure { step: self.step, source })?;
        }
        Ok(())
    }

    /// f_i = -sum_p V_p^n P_p . G_ip (all dofs).
    fn internal_force(&self, h: &[Mat3], stress: &[Mat3], scatter: &mut Scatter, out: &mut Vec<f64>) {
        let (st, pts) = (self.st, self.pts);
        scatter.run(
            pts.len(),
            out.len() / D,
            D,
            out,
            |r| st.span(r),
            |r, w| {
                for p in r {
                    let pn = nominal(&h[p], &stress[p]);
                    let vol = pts.volume[p];
                    let (nodes, _, grads) = st.row(p);
                    for (&i, g) in nodes.iter().zip(grads) {
                        let slot = w.slot(i);
                        for a in 0..D {
                            let mut f = 0.0;
                            for b in 0..D {
                                f += pn[a][b] * g[b];
                            }
                            slot[a] -= vol * f;
                        }
                    }
                }
            },
        );
    }
}

/// Greedy distance-2 colouring of the node graph `adj` (CSR), restricted to `active` nodes:
/// two nodes sharing a neighbour never share a colour, so their Jacobian columns touch
/// disjoint rows. Returns the colour of every node (usize::MAX for inactive ones) and the count.
fn colour_nodes(adj_ptr: &[usize], adj: &[usize], active: &[bool]) -> (Vec<usize>, usize) {
    let n = active.len();
    let mut colour = vec![usize::MAX; n];
    let mut stamp: Vec<usize> = Vec::new();
    let mut count = 0;
    for j in 0..n {
        if !active[j] {
            continue;
        }
        for &i in &adj[adj_ptr[j]..adj_ptr[j + 1]] {
            for &k in &adj[adj_ptr[i]..adj_ptr[i + 1]] {
                let c = colour[k];
                if c != usize::MAX {
                    if stamp.len() <= c {
                        stamp.resize(c + 1, usize::MAX);
                    }
                    stamp[c] = j;
                }
            }
        }
        let c = (0..).find(|&c| c >= stamp.len() || stamp[c] != j).expect("a free colour");
        colour[j] = c;
        count = count.max(c + 1);
    }
    (colour, count)
}

impl<const D: usize> Simulation<D> {
    /// Why this simulation cannot take implicit steps, if it cannot.
    pub fn implicit_unsupported(&self) -> Option<String> {
        if self.scheme.is_ddmp() {
            return Some(format!(
                "scheme `{}`: DDMP's gradient puts force on empty nodes, which the explicit cycle hands on (7.4); the implicit residual has no such redistribution (use mpm, ugimp, cpgimp, cpdi, cpdi1 or cpdi2)",
                self.scheme.name()
            ));
        }
        if self.viscosity != Viscosity::None {
            return Some(
                "artificial viscosity has no tangent in the implicit integrator: set scheme.artificial_viscosity = \"none\"".into(),
            );
        }
        for c in &self.closures {
            if !c.repeatable() {
                return Some(format!(
                    "closure `{}` keeps state between calls, so Newton cannot evaluate it repeatedly within a step (use an explicit integrator)",
                    c.name()
                ));
            }
            if self.implicit.options.jacobian == JacobianKind::Analytic && !c.has_tangent() {
                return Some(format!(
                    "closure `{}` gives no material tangent for the analytic Jacobian: use the finite-difference Jacobian",
                    c.name()
                ));
            }
        }
        None
    }

    /// One implicit trapezoidal step (module docs).
    /// Step set-up: stencil, grid mapping, unknowns, start-of-step forces, Jacobian pattern.
    fn implicit_setup(&mut self) -> Result<Setup, SolverError> {
        let step = self.step + 1;
        let dt = self.dt;
        if let Some(why) = self.implicit_unsupported() {
            return Err(SolverError::Diverged { step, what: why, cause: "a closure or option the implicit integrator cannot use" });
        }
        // (The implicit integrator refuses ddmp: only cpdi1 is suggested.)
        self.build_stencil(None)
            .map_err(|o| stencil_error(step, &o, "time step too large or a domain sheared past its limit (use cpdi1)"))?;
        // The scalar field (concentration) is advanced explicitly over the step on the frozen
        // stencil (prescribed rate plus diffusion, the diffusion step bounded by its explicit
        // limit); the closures read its rate in every residual.
        self.advance_scalar(step)?;
        // No small-mass velocity averaging (7.7): the nodal momentum is exactly that of the points.
        let eps = std::mem::replace(&mut self.small_mass, 0.0);
        self.map_to_grid();
        self.small_mass = eps;
        let nn = self.grid.node_count();
        let ndof = nn * D;
        let floor = self.empty_floor();

        // Constrained components: the boundary faces' prescribed velocities, and massless nodes.
        let mut wall = vec![[f64::NAN; D]; nn];
        self.grid.apply_boundaries(&self.node_mass, &mut wall);
        let mut index_of = vec![FREE_NONE; ndof];
        let mut free = Vec::new();
        let mut v1_fixed = vec![0.0; ndof];
        for i in 0..nn {
            for a in 0..D {
                let g = i * D + a;
                if self.node_mass[i] <= floor {
                    v1_fixed[g] = 0.0;
                } else if wall[i][a].is_nan() {
                    index_of[g] = free.len();
                    free.push(g);
                } else {
                    v1_fixed[g] = wall[i][a];
                }
            }
        }
        let mass: Vec<f64> = (0..ndof).map(|g| self.node_mass[g / D]).collect();
        let v0: Vec<f64> = (0..ndof).map(|g| if mass[g] > floor { self.node_v[g / D][g % D] } else { 0.0 }).collect();

        // Start-of-step force, body forces, a^n.
        let (t0, t1) = (self.time, self.time + dt);
        let b0 = self.nodal_body_force(t0);
        let b1 = self.nodal_body_force(t1);
        let ranges = self.body_ranges.clone();
        let mut f0 = vec![0.0; ndof];
        let zero_h = vec![tensor::ZERO; self.points.len()];
        Frozen { st: &self.stencil, pts: &self.points, ranges: &ranges, step, dt }.internal_force(
            &zero_h,
            &self.points.stress,
            &mut self.scatter,
            &mut f0,
        );
        let a0: Vec<f64> = (0..ndof).map(|g| if mass[g] > floor { (f0[g] + b0[g]) / mass[g] } else { 0.0 }).collect();

        // Node graph of the frozen stencil and the Jacobian's pattern over the free dofs.
        let (adj_ptr, adj) = node_graph(&self.stencil, self.points.len(), nn);
        let mut col_ptr = vec![0usize];
        let mut row_idx = Vec::new();
        for &g in &free {
            let j = g / D;
            for &i in &adj[adj_ptr[j]..adj_ptr[j + 1]] {
                for a in 0..D {
                    let r = index_of[i * D + a];
                    if r != FREE_NONE {
                        row_idx.push(r);
                    }
                }
            }
            col_ptr.push(row_idx.len());
        }
        let pattern = Pattern { col_ptr, row_idx };
        // Predictor (5.41) and the constrained components u = dt/2 (v^n + v_wall).
        let alpha = self.implicit.options.alpha;
        let u0: Vec<f64> =
            (0..ndof).map(|g| if index_of[g] != FREE_NONE { alpha * dt * v0[g] } else { 0.5 * dt * (v0[g] + v1_fixed[g]) }).collect();
        Ok(Setup { step, dt, floor, index_of, free, mass, v0, v1_fixed, f0, b0, b1, a0, adj_ptr, adj, pattern, ranges, u0 })
    }

    /// Nodal body force sum_p S_ip m_p b(X_p, t) (all dofs; zero without a body force).
    fn nodal_body_force(&mut self, t: f64) -> Vec<f64> {
        let mut out = vec![0.0; self.grid.node_count() * D];
        if let Some(bf) = self.body_force.clone() {
            let (st, pts) = (&self.stencil, &self.points);
            self.scatter.run(
                pts.len(),
                self.grid.node_count(),
                D,
                &mut out,
                |r| st.span(r),
                |r, w| {
                    for p in r {
                        let b = bf(&pts.x0[p], t);
                        let (nodes, weights, _) = st.row(p);
                        for (&i, &s) in nodes.iter().zip(weights) {
                            let slot = w.slot(i);
                            for a in 0..D {
                                slot[a] += s * pts.mass[p] * b[a];
                            }
                        }
                    }
                },
            );
        }
        out
    }

    /// The residual (5.34) over the free dofs at `u`, its scale (the largest sum of the
    /// magnitudes of the terms of one component), with the trial state and force left in
    /// `trial` and `force`.
    fn implicit_residual(&mut self, s: &Setup, u: &[f64], trial: &mut Trial, force: &mut Vec<f64>) -> Result<(Vec<f64>, f64), SolverError> {
        let fz = Frozen { st: &self.stencil, pts: &self.points, ranges: &s.ranges, step: s.step, dt: s.dt };
        fz.evaluate(&mut self.closures, u, trial)?;
        force.resize(u.len(), 0.0);
        fz.internal_force(&trial.h, &trial.stress, &mut self.scatter, force);
        let dt = s.dt;
        let mut scale: f64 = 0.0;
        let r = s
            .free
            .iter()
            .map(|&g| {
                let m = s.mass[g];
                let terms = (m * 4.0 * u[g] / (dt * dt)).abs()
                    + (m * 4.0 * s.v0[g] / dt).abs()
                    + (m * s.a0[g]).abs()
                    + force[g].abs()
                    + s.b1[g].abs();
                scale = scale.max(terms);
                s.inertia(u, g) - force[g] - s.b1[g]
            })
            .collect();
        Ok((r, scale))
    }

    /// Jacobian values on `s.pattern` at `u` (residual `r`, trial state `trial` of `u`), and
    /// the residual evaluations and colours it took.
    fn implicit_jacobian(
        &mut self,
        s: &Setup,
        kind: JacobianKind,
        u: &[f64],
        r: &[f64],
        trial: &Trial,
    ) -> Result<(Vec<f64>, u64, usize), SolverError> {
        let mut vals = vec![0.0; s.pattern.row_idx.len()];
        match kind {
            JacobianKind::Analytic => {
                let fz = Frozen { st: &self.stencil, pts: &self.points, ranges: &s.ranges, step: s.step, dt: s.dt };
                assemble_analytic(&fz, &self.closures, trial, &s.index_of, &s.pattern, &s.mass, &mut vals)?;
                Ok((vals, 0, 0))
            }
            JacobianKind::FiniteDifference => {
                let nn = s.index_of.len() / D;
                let active: Vec<bool> = (0..nn).map(|i| (0..D).any(|a| s.index_of[i * D + a] != FREE_NONE)).collect();
                let (colour, count) = colour_nodes(&s.adj_ptr, &s.adj, &active);
                let h_min = self.grid.min_spacing();
                let scale_u = s.free.iter().fold(0.0_f64, |m, &g| m.max(u[g].abs())).max(1e-8 * h_min);
                let sqrt_eps = f64::EPSILON.sqrt();
                let mut up = u.to_vec();
                let (mut tp, mut fp) = (Trial::default(), Vec::new());
                let mut residuals = 0;
                for c in 0..count {
                    for a in 0..D {
                        let cols: Vec<(usize, f64)> = s
                            .free
                            .iter()
                            .enumerate()
                            .filter(|(_, g)| **g % D == a && colour[**g / D] == c)
                            .map(|(col, &g)| {
                                up[g] = u[g] + sqrt_eps * u[g].abs().max(scale_u);
                                (col, up[g] - u[g])
                            })
                            .collect();
                        if cols.is_empty() {
                            continue;
                        }
                        let (rp, _) = self.implicit_residual(s, &up, &mut tp, &mut fp)?;
                        residuals += 1;
                        for &(col, e) in &cols {
                            for k in s.pattern.col_ptr[col]..s.pattern.col_ptr[col + 1] {
                                let row = s.pattern.row_idx[k];
                                vals[k] = (rp[row] - r[row]) / e;
                            }
                            up[s.free[col]] = u[s.free[col]];
                        }
                    }
                }
                Ok((vals, residuals, count))
            }
        }
    }

    /// The Newton Jacobian of the next step at its predictor, dense (row-major, free dofs in
    /// node-major order), and the residual evaluations it took: for tests and small systems.
    /// Leaves the state of the simulation as it was (only the stencil and nodal buffers change).
    pub fn implicit_jacobian_at_predictor(&mut self, kind: JacobianKind) -> Result<(usize, Vec<f64>, u64), SolverError> {
        let s = self.implicit_setup()?;
        let (mut trial, mut force) = (Trial::default(), Vec::new());
        let (r, _) = self.implicit_residual(&s, &s.u0, &mut trial, &mut force)?;
        let (vals, residuals, _) = self.implicit_jacobian(&s, kind, &s.u0, &r, &trial)?;
        let nf = s.free.len();
        let mut dense = vec![0.0; nf * nf];
        for col in 0..nf {
            for k in s.pattern.col_ptr[col]..s.pattern.col_ptr[col + 1] {
                dense[s.pattern.row_idx[k] * nf + col] = vals[k];
            }
        }
        Ok((nf, dense, residuals))
    }

    /// One implicit trapezoidal step (module docs). With [`ImplicitOptions::adaptive`], steps
    /// whose Newton fails, that would move a point past the motion bound, or whose estimated
    /// local error exceeds 1 in the WRMS norm are rejected and retried with a smaller dt; an
    /// accepted step sets the next dt from its error (and the motion cap).
    pub(super) fn implicit_step(&mut self) -> Result<StepReport, SolverError> {
        let mut rejections = 0;
        loop {
            // A rejected attempt must leave the scalar field and the diffusion as they were.
            let saved = (self.implicit.options.adaptive.is_some() && !self.points.scalar.is_empty())
                .then(|| (self.points.scalar.clone(), self.diffusion.clone()));
            if let Some(ad) = &self.implicit.options.adaptive {
                // Land on the end time: the last step is shortened, the proposal kept.
                let left = ad.end_time - self.time;
                if left > 0.0 && self.dt > left {
                    self.dt = left;
                }
            }
            let attempt = self.implicit_attempt()?;
            if !matches!(attempt, Attempt::Accepted { .. })
                && let Some((scalar, diffusion)) = saved
            {
                self.points.scalar = scalar;
                self.diffusion = diffusion;
            }
            let Some(ad) = self.implicit.options.adaptive.clone() else {
                return match attempt {
                    Attempt::Accepted { report, .. } => Ok(report),
                    Attempt::Failed { error, .. } => Err(error),
                    Attempt::Rejected { .. } => unreachable!("only adaptive steps are rejected on their error"),
                };
            };
            let factor = |err: f64| if err > 0.0 { ad.safety * err.powf(-1.0 / 3.0) } else { ad.max_growth };
            match attempt {
                Attempt::Accepted { report, err, speed } => {
                    let mut dt = self.dt * factor(err).clamp(ad.min_shrink, ad.max_growth);
                    if speed > 0.0 {
                        dt = dt.min(0.9 * self.implicit.options.max_motion_cells * self.grid.min_spacing() / speed);
                    }
                    self.dt = dt.clamp(ad.dt_min, ad.dt_max);
                    return Ok(report);
                }
                Attempt::Rejected { err } => {
                    self.implicit.stats.rejected_steps += 1;
                    self.implicit.stats.rejected_for_error += 1;
                    self.dt *= factor(err).clamp(ad.min_shrink, 0.9);
                    rejections += 1;
                    if self.dt < ad.dt_min || rejections > ad.max_rejections {
                        return Err(SolverError::Diverged {
                            step: self.step + 1,
                            what: format!(
                                "{rejections} rejected attempts, the last with local error {err:.3e} (WRMS), dt = {:e} s",
                                self.dt
                            ),
                            cause: "the error tolerance cannot be met above dt_min: loosen rtol/atol or lower dt_min",
                        });
                    }
                }
                Attempt::Failed { error, motion } => {
                    let st = &mut self.implicit.stats;
                    st.rejected_steps += 1;
                    if motion {
                        st.rejected_for_motion += 1;
                        if st.first_motion_rejection_step == 0 {
                            st.first_motion_rejection_step = self.step + 1;
                        }
                    } else {
                        st.rejected_for_newton += 1;
                    }
                    self.dt *= ad.min_shrink;
                    rejections += 1;
                    if self.dt < ad.dt_min || rejections > ad.max_rejections {
                        return Err(error);
                    }
                }
            }
        }
    }

    /// Newton on the step's residual from the predictor.
    fn implicit_newton(&mut self, s: &Setup) -> Result<NewtonOut, SolverError> {
        let (step, _dt) = (s.step, s.dt);
        let h_min = self.grid.min_spacing();
        let nf = s.free.len();
        let opts = self.implicit.options.clone();
        let mut u = s.u0.clone();
        let (mut trial, mut force) = (Trial::default(), Vec::new());
        let mut history = Vec::new();
        let mut iterations = 0usize;
        let mut du_norm = f64::INFINITY;
        let (mut t_res, mut t_jac, mut t_solve) = (0.0, 0.0, 0.0);
        let mut residuals = 0u64;
        let mut colours = 0usize;
        loop {
            let clock = Instant::now();
            let (r, scale) = self.implicit_residual(s, &u, &mut trial, &mut force).map_err(|e| newton_error(e, &history))?;
            residuals += 1;
            t_res += clock.elapsed().as_secs_f64();
            let rnorm = r.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            history.push(rnorm);
            if !rnorm.is_finite() {
                return Err(SolverError::Diverged {
                    step,
                    what: format!("the Newton residual is not finite (residual history {})", show(&history)),
                    cause: "time step too large for Newton from the predictor",
                });
            }
            if nf == 0 || rnorm <= opts.residual_tolerance * scale || (iterations > 0 && du_norm <= opts.displacement_tolerance * h_min) {
                break;
            }
            if iterations >= opts.max_iterations {
                return Err(SolverError::Diverged {
                    step,
                    what: format!(
                        "Newton did not converge in {} iterations (residual inf-norm history {}, last correction {du_norm:.3e} m)",
                        opts.max_iterations,
                        show(&history)
                    ),
                    cause: if history.len() > 2 && history[history.len() - 1] > 0.5 * history[history.len() - 2] {
                        "the residual stopped falling: time step too large for Newton from the predictor, or an inconsistent (finite-difference) Jacobian"
                    } else {
                        "Newton converges too slowly: reduce the time step or raise max_iterations"
                    },
                });
            }
            let clock = Instant::now();
            let (vals, fd_residuals, c) =
                self.implicit_jacobian(s, opts.jacobian, &u, &r, &trial).map_err(|e| newton_error(e, &history))?;
            residuals += fd_residuals;
            colours = c;
            t_jac += clock.elapsed().as_secs_f64();
            // Linear solve J du = -R (sparse LU).
            let clock = Instant::now();
            let sym = SymbolicSparseColMatRef::new_checked(nf, nf, &s.pattern.col_ptr, None, &s.pattern.row_idx);
            let symbolic = self.implicit_symbolic(sym).map_err(|e| SolverError::Diverged {
                step,
                what: format!("the Newton Jacobian's pattern could not be analysed ({e:?}; residual history {})", show(&history)),
                cause: "out of memory for the sparse LU",
            })?;
            let lu = Lu::try_new_with_symbolic(symbolic, SparseColMatRef::new(sym, &vals)).map_err(|e| SolverError::Diverged {
                step,
                what: format!("the Newton Jacobian could not be factorised ({e:?}; residual history {})", show(&history)),
                cause: "a singular Jacobian: a node without stiffness or mass among the unknowns",
            })?;
            let rhs = faer::Col::<f64>::from_fn(nf, |k| -r[k]);
            let du = lu.solve(&rhs);
            t_solve += clock.elapsed().as_secs_f64();
            du_norm = 0.0;
            for (k, &g) in s.free.iter().enumerate() {
                u[g] += du[k];
                du_norm = du_norm.max(du[k].abs());
            }
            iterations += 1;
        }
        Ok(NewtonOut { u, trial, force, history, iterations, residuals, colours, times: [t_res, t_jac, t_solve] })
    }

    /// The symbolic LU of `sym`: the kept one when its pattern is the same (the numeric phase
    /// with the same symbolic factorisation is what `sp_lu` does, so the factors are bitwise
    /// those of a fresh `sp_lu`), else a new one, kept for the next iterations and steps.
    fn implicit_symbolic(&mut self, sym: SymbolicSparseColMatRef<'_, usize>) -> Result<SymbolicLu<usize>, faer::sparse::FaerError> {
        if let Some(c) = &self.implicit.symbolic
            && c.col_ptr.as_slice() == sym.col_ptr()
            && c.row_idx.as_slice() == sym.row_idx()
        {
            return Ok(c.lu.clone());
        }
        let clock = Instant::now();
        let lu = SymbolicLu::try_new(sym)?;
        self.implicit.stats.symbolic_factorisations += 1;
        self.implicit.stats.seconds_symbolic += clock.elapsed().as_secs_f64();
        self.implicit.symbolic = Some(SymbolicCache { col_ptr: sym.col_ptr().to_vec(), row_idx: sym.row_idx().to_vec(), lu: lu.clone() });
        Ok(lu)
    }

    /// The motion bound on the converged displacement: the stencil was frozen over the step, so
    /// no point may move more than `max_motion_cells` cells along any axis.
    fn implicit_motion(&self, step: u64, u: &[f64]) -> Result<(), SolverError> {
        let max_cells = self.implicit.options.max_motion_cells;
        let (st, pts, h) = (&self.stencil, &self.points, &self.grid.h);
        let motion = (0..pts.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|p| {
                let (nodes, weights, _) = st.row(p);
                let mut d = [0.0; D];
                for (&i, &w) in nodes.iter().zip(weights) {
                    for a in 0..D {
                        d[a] += w * u[i * D + a];
                    }
                }
                (0..D).map(|a| d[a].abs() / h[a]).fold(0.0, f64::max)
            })
            .collect::<Vec<f64>>();
        // Name the point that moves most (the first one past the bound is seldom the worst).
        let over = motion.iter().filter(|m| **m > max_cells).count();
        if over > 0 {
            let (p, cells) = motion.iter().copied().enumerate().fold((0, 0.0), |b, (p, m)| if m > b.1 { (p, m) } else { b });
            return Err(SolverError::Diverged {
                step,
                what: format!(
                    "particle {p} would move {cells:.3} cells in one implicit step (limit {}; {over} of {} points past it)",
                    max_cells,
                    motion.len()
                ),
                cause: "time step too large for the frozen stencil: reduce the time step so no point moves more than half a cell",
            });
        }
        Ok(())
    }

    /// One attempt at the step with the current dt.
    fn implicit_attempt(&mut self) -> Result<Attempt, SolverError> {
        let started = Instant::now();
        let s = self.implicit_setup()?;
        let (step, dt, floor) = (s.step, s.dt, s.floor);
        let ndof = s.index_of.len();
        let nf = s.free.len();
        let n = match self.implicit_newton(&s) {
            Ok(n) => n,
            Err(error) => return Ok(Attempt::Failed { error, motion: false }),
        };
        if let Err(e) = self.implicit_motion(step, &n.u) {
            return Ok(Attempt::Failed { error: e, motion: true });
        }
        let NewtonOut { u, trial, force, history, iterations, residuals, colours, times: [t_res, t_jac, t_solve] } = n;
        let Setup { index_of, mass, v0, v1_fixed, f0, b0, b1, a0, .. } = s;
        let mass_of = |g: usize| mass[g];
        // Commit.
        let a1: Vec<f64> = (0..ndof)
            .map(|g| {
                if index_of[g] != FREE_NONE {
                    4.0 * u[g] / (dt * dt) - 4.0 * v0[g] / dt - a0[g]
                } else if mass_of(g) > floor {
                    2.0 * (v1_fixed[g] - v0[g]) / dt - a0[g]
                } else {
                    0.0
                }
            })
            .collect();
        let v1: Vec<f64> = (0..ndof).map(|g| if index_of[g] != FREE_NONE { 2.0 * u[g] / dt - v0[g] } else { v1_fixed[g] }).collect();
        // Local error estimates: le_u = dt^2/12 (a^{n+1} - a^n) and le_v = dt^3/12 a'' with
        // a'' from the three accelerations (unequal steps: 2 [(a1 - a0)/dt - (a0 - a_prev)/dt_prev]
        // / (dt + dt_prev), which is (a1 - 2 a0 + a_prev)/dt^2 for equal ones).
        let (mut eu, mut ev) = (0.0_f64, 0.0_f64);
        let (mut wu, mut wv, mut speed) = (0.0_f64, 0.0_f64, 0.0_f64);
        let have_prev = self.implicit.prev_acc.len() == ndof;
        let dtp = self.implicit.prev_dt;
        let ad = self.implicit.options.adaptive.clone();
        for g in 0..ndof {
            if index_of[g] != FREE_NONE {
                let le_u = dt * dt / 12.0 * (a1[g] - a0[g]);
                eu = eu.max(le_u.abs());
                speed = speed.max(v1[g].abs());
                let le_v = if have_prev {
                    let add = 2.0 * ((a1[g] - a0[g]) / dt - (a0[g] - self.implicit.prev_acc[g]) / dtp) / (dt + dtp);
                    dt * dt * dt / 12.0 * add
                } else {
                    0.0
                };
                ev = ev.max(le_v.abs());
                if let Some(ad) = &ad {
                    wu += (le_u / (ad.rtol * u[g].abs() + ad.atol_u)).powi(2);
                    wv += (le_v / (ad.rtol * v1[g].abs() + ad.atol_v)).powi(2);
                }
            }
        }
        let mut err = (wu.max(wv) / nf.max(1) as f64).sqrt();
        // le_F,p = dt^2/12 sum_i (a_i^{n+1} - a_i^n) (x) G_ip F_p^n = le_H,p F_p^n on the frozen
        // stencil (the step's F^{n+1} = (I + sum_i u_i (x) G_ip) F^n is linear in the nodal u, whose
        // local error is le_u; constrained components carry none). Per point: the largest
        // component and the WRMS sum with weights 1/(rtol |F^{n+1}| + atol_F).
        let atol_f = ad.as_ref().and_then(|a| a.atol_f.map(|t| (a.rtol, t)));
        let per_point: Vec<(f64, f64)> = (0..self.points.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|p| {
                let (nodes, _, grads) = self.stencil.row(p);
                let mut le_h = tensor::ZERO;
                for (&i, g) in nodes.iter().zip(grads) {
                    for a in 0..D {
                        let k = i * D + a;
                        if index_of[k] == FREE_NONE {
                            continue;
                        }
                        let da = dt * dt / 12.0 * (a1[k] - a0[k]);
                        for b in 0..D {
                            le_h[a][b] += da * g[b];
                        }
                    }
                }
                let le_f = tensor::mul(&le_h, &self.points.def_grad[p]);
                let (mut m, mut w) = (0.0_f64, 0.0_f64);
                for a in 0..D {
                    for b in 0..D {
                        m = m.max(le_f[a][b].abs());
                        if let Some((rtol, atol)) = atol_f {
                            w += (le_f[a][b] / (rtol * trial.f[p][a][b].abs() + atol)).powi(2);
                        }
                    }
                }
                (m, w)
            })
            .collect();
        let ef = per_point.iter().fold(0.0_f64, |m, e| m.max(e.0));
        if atol_f.is_some() {
            // Summed in point order (the same for any thread count).
            let wf: f64 = per_point.iter().map(|e| e.1).sum();
            err = err.max((wf / (self.points.len() * D * D).max(1) as f64).sqrt());
        }
        if ad.is_some() && err > 1.0 {
            return Ok(Attempt::Rejected { err });
        }
        // Impulse the constraints added: m (v^{n+1} - v^n) - dt/2 (f^n + f^{n+1} + b^n + b^{n+1}).
        for g in 0..ndof {
            if index_of[g] == FREE_NONE && mass_of(g) > floor {
                let dp = mass_of(g) * (v1[g] - v0[g]) - 0.5 * dt * (f0[g] + force[g] + b0[g] + b1[g]);
                self.wall_impulse[g % D] += dp;
                self.wall_impulse_magnitude += dp.abs();
            }
        }
        self.implicit.prev_acc = a0;
        self.implicit.prev_dt = dt;
        let (mut defect, mut ke0) = (0.0, 0.0);
        for g in 0..ndof {
            if index_of[g] != FREE_NONE {
                let m = mass_of(g);
                defect += 0.5 * m * (v1[g] * v1[g] - v0[g] * v0[g]) - 0.5 * (b0[g] + b1[g]) * u[g];
                ke0 += 0.5 * m * v0[g] * v0[g];
            } else {
                defect += 0.5 * (f0[g] + force[g]) * u[g];
            }
        }
        let work = self.commit_points(&u, &v0, &v1, &trial);
        defect += work;
        for (p, vg) in self.points.vel_grad.iter_mut().enumerate() {
            *vg = trial.l[p];
        }
        self.closure_evaluations = self.closure_evaluations.saturating_add(residuals.saturating_mul(self.points.len() as u64));
        self.time += dt;
        self.step = step;
        self.integration_point_updates = self.integration_point_updates.saturating_add(self.points.len() as u64);
        let s = &mut self.implicit.stats;
        s.accepted_steps += 1;
        s.newton_iterations += iterations as u64;
        s.max_newton_iterations_per_step = s.max_newton_iterations_per_step.max(iterations);
        s.residual_evaluations += residuals;
        s.jacobians += iterations as u64;
        s.last_residual_history = history;
        s.colours = colours;
        s.unknowns = nf;
        s.seconds_residual += t_res;
        s.seconds_jacobian += t_jac;
        s.seconds_solve += t_solve;
        s.seconds_total += started.elapsed().as_secs_f64();
        s.last_error_u = eu;
        s.last_error_v = ev;
        s.last_error_f = ef;
        s.last_energy_defect = defect;
        s.last_energy_scale = ke0 + work.abs() + self.points.internal_energy.iter().map(|e| e.abs()).sum::<f64>();
        s.last_error_norm = err;
        s.last_dt = dt;
        self.guard(step)?;
        Ok(Attempt::Accepted { report: StepReport { step, time: self.time }, err, speed })
    }

    /// (5.53)-(5.59): points take the converged trial state; velocities by the nodal increment,
    /// positions by the nodal displacement, tracked corners by the displacement at the corner,
    /// stress work by the trapezoid V^n (P^n + P^{n+1})/2 : H (so the grid energy balance of
    /// the step is exact at convergence).
    /// Returns the stress work of the step (J, summed over the points).
    fn commit_points(&mut self, u: &[f64], v0: &[f64], v1: &[f64], trial: &Trial) -> f64 {
        let (st, grid) = (&self.stencil, &self.grid);
        let pts = &mut self.points;
        let track = self.scheme.tracks_corners();
        let nc = 1usize << D;
        let mut total = 0.0;
        for p in 0..pts.len() {
            let (nodes, weights, _) = st.row(p);
            let (mut dv, mut dx) = ([0.0; D], [0.0; D]);
            for (&i, &w) in nodes.iter().zip(weights) {
                for a in 0..D {
                    dv[a] += w * (v1[i * D + a] - v0[i * D + a]);
                    dx[a] += w * u[i * D + a];
                }
            }
            let before = pts.x[p];
            for a in 0..D {
                pts.v[p][a] += dv[a];
                pts.x[p][a] += dx[a];
            }
            let moved = pts.x[p];
            grid.wrap_position(&mut pts.x[p]);
            for corner in pts.corners[p * nc..(p + 1) * nc].iter_mut() {
                if track {
                    let sh = shape::cell_shape(grid, corner);
                    let mut d = [0.0; D];
                    for m in 0..nc {
                        if let Some(i) = shape::node_index(grid, &shape::cell_node(&sh.cell, m)) {
                            for a in 0..D {
                                d[a] += sh.s[m] * u[i * D + a];
                            }
                        }
                    }
                    for a in 0..D {
                        corner[a] += d[a];
                    }
                } else {
                    for a in 0..D {
                        corner[a] += moved[a] - before[a];
                    }
                }
                for a in 0..D {
                    corner[a] += pts.x[p][a] - moved[a];
                }
            }
            let p0 = pts.stress[p];
            let p1 = nominal(&trial.h[p], &trial.stress[p]);
            let mid = tensor::add_scaled(&p0, &p1, 1.0);
            let work = pts.volume[p] * 0.5 * tensor::ddot(&mid, &trial.h[p]);
            pts.internal_energy[p] += work;
            total += work;
            if !trial.plastic.is_empty() {
                pts.plastic_strain[p] = trial.plastic[p];
            }
            pts.def_grad[p] = trial.f[p];
            pts.volume[p] = trial.vol[p];
            pts.stress[p] = trial.stress[p];
            pts.visc_stress[p] = tensor::ZERO;
            pts.visc_pressure[p] = 0.0;
        }
        total
    }
}

/// A residual history as `[1.234e5, ...]`.
fn show(history: &[f64]) -> String {
    format!("[{}]", history.iter().map(|r| format!("{r:.3e}")).collect::<Vec<_>>().join(", "))
}

/// Adds the Newton history to an error from inside the iteration.
fn newton_error(e: SolverError, history: &[f64]) -> SolverError {
    match e {
        SolverError::Diverged { step, what, cause } => {
            SolverError::Diverged { step, what: format!("{what} (Newton residual history {})", show(history)), cause }
        }
        other => other,
    }
}

/// Node adjacency of the stencil (nodes sharing a point), CSR with sorted rows.
fn node_graph<const D: usize>(st: &Stencil<D>, n_points: usize, n_nodes: usize) -> (Vec<usize>, Vec<usize>) {
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for p in 0..n_points {
        let (nodes, _, _) = st.row(p);
        for &i in nodes {
            for &j in nodes {
                pairs.push((i, j));
            }
        }
    }
    pairs.par_sort_unstable();
    pairs.dedup();
    let mut ptr = vec![0usize; n_nodes + 1];
    for &(i, _) in &pairs {
        ptr[i + 1] += 1;
    }
    for i in 0..n_nodes {
        ptr[i + 1] += ptr[i];
    }
    (ptr, pairs.into_iter().map(|(_, j)| j).collect())
}

/// J = 4 M / dt^2 + sum_p V_p^n G_ip . A_p . G_jp, A = dP/dH from the closures' tangents.
fn assemble_analytic<const D: usize>(
    fz: &Frozen<'_, D>,
    closures: &[Box<dyn Closure>],
    trial: &Trial,
    index_of: &[usize],
    pattern: &Pattern,
    dof_mass: &[f64],
    vals: &mut [f64],
) -> Result<(), SolverError> {
    let pts = fz.pts;
    for (b, r) in fz.ranges.iter().enumerate() {
        let closure = &closures[b];
        for p in r.clone() {
            let input = TangentIn {
                start_stress: &pts.stress[p],
                start_def_grad: &pts.def_grad[p],
                increment: &trial.h[p],
                def_grad: &trial.f[p],
                stress: &trial.stress[p],
                mass: pts.mass[p],
                volume: trial.vol[p],
            };
            let Some(t) = closure.tangent(&input) else {
                return Err(SolverError::Diverged {
                    step: fz.step,
                    what: format!("closure `{}` gave no tangent for particle {p}", closure.name()),
                    cause: "a closure without a tangent (or an inverted point): use the finite-difference Jacobian",
                });
            };
            let a = nominal_tangent(&trial.h[p], &trial.stress[p], &t);
            let vol = pts.volume[p];
            let (nodes, _, grads) = fz.st.row(p);
            for (&i, gi) in nodes.iter().zip(grads) {
                for (&j, gj) in nodes.iter().zip(grads) {
                    for ra in 0..D {
                        let row = index_of[i * D + ra];
                        if row == FREE_NONE {
                            continue;
                        }
                        for ck in 0..D {
                            let col = index_of[j * D + ck];
                            if col == FREE_NONE {
                                continue;
                            }
                            let mut k = 0.0;
                            for bb in 0..D {
                                for l in 0..D {
                                    k += a[ra][bb][ck][l] * gi[bb] * gj[l];
                                }
                            }
                            vals[pattern.slot(row, col)] += vol * k;
                        }
                    }
                }
            }
        }
    }
    // Inertia on the diagonal.
    let dt = fz.dt;
    for (g, &col) in index_of.iter().enumerate() {
        if col != FREE_NONE {
            vals[pattern.slot(col, col)] += 4.0 * dof_mass[g] / (dt * dt);
        }
    }
    Ok(())
}
