//! Time integration of the cell's index-1 DAE `M y' = f(y)` (M = diag(1, 1, 0) per cell) by
//! diffsol's variable-order BDF over a banded LU ([`crate::band`]; faer's sparse LU on request), with
//! - a Jacobian by finite differences over 15 column colours (the residual of a cell depends
//!   on cells i-2..=i+2 only), so one Jacobian costs 15 right-hand sides at any N;
//! - consistent initialisation: phi solved from the initial p, n (and diffsol's own algebraic
//!   solve at every (re)start);
//! - the threshold switches as root functions: at a root the step is cut back to it, the
//!   switch flips, and the integrator restarts from there (order 1), so no step straddles a
//!   discontinuity of the right-hand side;
//! - an explicit-Euler path that the scene validator only admits below its stability bound.

use crate::band::BandLu;
use crate::model::Model;
use crate::scene::LinearSolver;
use diffsol::matrix::sparsity::MatrixSparsity;
use diffsol::{
    BdfState, ConstantOp, FaerContext, FaerSparseLU, FaerSparseMat, FaerVec, LaLinearOp, LinearOp, Matrix, MatrixCommon, NonLinearOp,
    NonLinearOpJacobian, OdeBuilder, OdeEquations, OdeEquationsRef, OdeSolverMethod, OdeSolverState, OdeSolverStopReason, Op,
    ParameterisedOp, UnitCallable, Vector,
};
use diffsol_la::LinearSolver as LaLinearSolver;
use std::cell::{Cell, RefCell};
use std::time::Instant;

type M = FaerSparseMat<f64>;

/// The integrator's unit of time (s): diffsol's smallest step is f64::EPSILON in its own
/// unit, and the first steps of a cell are ~1e-18 s, so it integrates in picoseconds.
pub const T_UNIT: f64 = 1e-12;
type V = FaerVec<f64>;

thread_local! {
    /// Seconds in factorisations (set_linearisation minus the Jacobian inside it) and in
    /// triangular solves, of this thread's integrations.
    static LU_SETUP_S: Cell<f64> = const { Cell::new(0.0) };
    static LU_SOLVE_S: Cell<f64> = const { Cell::new(0.0) };
    static JAC_S: Cell<f64> = const { Cell::new(0.0) };
    /// The charge weights of this thread's integration ([`Model::invariants`]; empty: the
    /// banded LU's corrections are not made charge-exact).
    static CHARGE_WEIGHTS: RefCell<Vec<Vec<f64>>> = const { RefCell::new(Vec::new()) };
}

/// Sets the charge weights for the banded LU of this thread while alive; clears them after.
struct ChargeWeights;

impl ChargeWeights {
    fn set(w: Vec<Vec<f64>>) -> ChargeWeights {
        CHARGE_WEIGHTS.with(|c| *c.borrow_mut() = w);
        ChargeWeights
    }
}

impl Drop for ChargeWeights {
    fn drop(&mut self) {
        CHARGE_WEIGHTS.with(|c| c.borrow_mut().clear());
    }
}

/// The banded LU of [`crate::band`] as diffsol's linear solver, with charge-exact
/// corrections where the cell's invariants are set ([`Model::invariants`]: the inventories per
/// material and species; the text below speaks of the net charge, which is in their span).
///
/// Why: where `w^T A = w^T M` (w the charge weights), an exact solution x of `A x = b` has
/// `w^T M x = w^T b`. The LU's x is backward stable, `(A + E) x = b` with |E| ~ eps |L||U|,
/// so it misses that by `w^T E x`: at 1e5 cells the cation rows in the interfaces' Debye layers
/// carry entries ~c D p / (V_T dx^2) ~ 1e15 and the charge error of a correction is ~1e-6 of its
/// size. The cell's net charge sits on the Dirichlet contact (G[0] = Q eps0/e): the error lands
/// in the first cell's electrons as dQ/dx (tolerance 1e-9 /nm^3) and tilts the potential of
/// the whole cell, and Newton converged only linearly, at 0.05-0.7 per iteration (cell/README.md).
/// The fix: the charge defect `d = w^T b - w^T M x` is computed from its definition (no product
/// with A, so to round-off of the charges) and removed along `z = A^{-1} u`, u = the charge
/// weights times |A||x| (the backward error's bound, row by row): `x += (d / w^T z) z`. The
/// correction is where the LU's error came from; the charge of the result is right to round-off.
#[derive(Default)]
pub struct BandedLu {
    /// The linearisation (M - c J) as diffsol assembles it, in the pattern of the Jacobian.
    a: Option<M>,
    lu: BandLu,
    /// z = A^{-1} u and w^T z for the charge-exact corrections (None: not made).
    charge_dir: Option<Directions>,
    /// Scratch for a solve's right-hand side (no allocation per solve).
    rhs: Cell<Vec<f64>>,
}

impl LaLinearSolver<M> for BandedLu {
    fn set_linearisation<C: LaLinearOp<V = V, T = f64, M = M, C = FaerContext>>(&mut self, op: &C) {
        let a = self.a.as_mut().expect("set_sparsity before set_linearisation");
        op.matrix_inplace(a);
        let m = &a.inner()[0];
        self.lu.factor_csc(m.symbolic().col_ptr(), m.symbolic().row_idx(), m.val());
        self.prepare_charge_direction();
    }
    fn set_sparsity<C: LaLinearOp<V = V, T = f64, M = M, C = FaerContext>>(&mut self, op: &C) {
        let a = M::new_from_sparsity(op.nrows(), op.ncols(), op.sparsity(), *op.context());
        let m = &a.inner()[0];
        let (kl, ku) = BandLu::bandwidths(m.symbolic().col_ptr(), m.symbolic().row_idx());
        self.lu = BandLu::new(op.nrows(), kl, ku);
        self.a = Some(a);
    }
    fn solve_in_place(&self, b: &mut V) -> Result<(), diffsol::LaError> {
        if let Some(col) = self.lu.singular() {
            return Err(diffsol::LaError::Other(format!("the Newton matrix is singular (zero pivot in column {col})")));
        }
        CHARGE_WEIGHTS.with(|w| {
            let w = w.borrow();
            b.for_each_batch_host([], |b, [], _| {
                if let Some(dirs) = self.charge_dir.as_ref().filter(|_| w.first().is_some_and(|w0| w0.len() == b.len())) {
                    let mut rhs = self.rhs.take();
                    rhs.clear();
                    rhs.extend_from_slice(b);
                    self.lu.solve(b);
                    dirs.apply(&w, &rhs, b);
                    self.rhs.set(rhs);
                } else {
                    self.lu.solve(b);
                }
            });
        });
        Ok(())
    }
    fn solve_transpose_in_place(&self, b: &mut V) -> Result<(), diffsol::LaError> {
        if let Some(col) = self.lu.singular() {
            return Err(diffsol::LaError::Other(format!("the Newton matrix is singular (zero pivot in column {col})")));
        }
        b.for_each_batch_host([], |b, [], _| self.lu.solve_transpose(b));
        Ok(())
    }
}

impl BandedLu {
    /// After a factorisation: the correction directions for this thread's invariants.
    fn prepare_charge_direction(&mut self) {
        self.charge_dir = None;
        let Some(a) = self.a.as_ref() else { return };
        if self.lu.singular().is_some() {
            return;
        }
        let m = &a.inner()[0];
        let (col_ptr, row_idx, val) = (m.symbolic().col_ptr(), m.symbolic().row_idx(), m.val());
        self.charge_dir = CHARGE_WEIGHTS.with(|w| Directions::new(&w.borrow(), col_ptr, row_idx, val, &self.lu));
    }
}

/// The correction directions of the invariant-exact solves ([`BandedLu`]): for each invariant
/// weight w_k, `z_k = A^{-1} u_k` with u_k = w_k times the rows' sums of |A| (where the LU's
/// backward error, bounded by eps |A||x| row by row, lives), and the K x K matrix `w_a . z_b`.
pub(crate) struct Directions {
    z: Vec<Vec<f64>>,
    wz: Vec<f64>,
    /// The range of indices where each weight is nonzero.
    support: Vec<(usize, usize)>,
}

impl Directions {
    pub(crate) fn new(ws: &[Vec<f64>], col_ptr: &[usize], row_idx: &[usize], val: &[f64], lu: &BandLu) -> Option<Directions> {
        let n = col_ptr.len() - 1;
        if ws.is_empty() || ws.iter().any(|w| w.len() != n) {
            return None;
        }
        let mut rowabs = vec![0.0; n];
        for j in 0..n {
            for k in col_ptr[j]..col_ptr[j + 1] {
                rowabs[row_idx[k]] += val[k].abs();
            }
        }
        let mut z: Vec<Vec<f64>> = ws.iter().map(|w| w.iter().zip(&rowabs).map(|(a, b)| a * b).collect()).collect();
        // All K in one sweep over the factors (the solves are bound by reading them).
        lu.solve_many(&mut z.iter_mut().map(|z| z.as_mut_slice()).collect::<Vec<_>>());
        let wz = ws.iter().flat_map(|w| z.iter().map(move |z| w.iter().zip(z).map(|(a, b)| a * b).sum::<f64>())).collect::<Vec<f64>>();
        // Where each weight is nonzero (a material's cells): the defects' sums skip the rest.
        let support = ws
            .iter()
            .map(|w| {
                let first = w.iter().position(|v| *v != 0.0).unwrap_or(0);
                let end = w.iter().rposition(|v| *v != 0.0).map_or(first, |l| l + 1);
                (first, end)
            })
            .collect();
        wz.iter().all(|v| v.is_finite()).then_some(Directions { z, wz, support })
    }

    /// Moves the LU's solution x of `A x = b` so that `w_k^T M x = w_k^T b` for every k.
    pub(crate) fn apply(&self, ws: &[Vec<f64>], b: &[f64], x: &mut [f64]) {
        let k = ws.len();
        // M is the identity on the differential rows and 0 on the Poisson rows, where w = 0.
        // (Summed over each weight's support only: the terms outside are zeros.)
        let mut d: Vec<f64> = ws
            .iter()
            .zip(&self.support)
            .map(|(w, &(lo, hi))| w[lo..hi].iter().zip(b[lo..hi].iter().zip(&x[lo..hi])).map(|(wj, (bj, xj))| wj * (bj - xj)).sum())
            .collect();
        if d.iter().all(|v| *v == 0.0) || !d.iter().all(|v| v.is_finite()) {
            return;
        }
        // (w_a . z_b) s = d by Gaussian elimination with partial pivoting (K <= 6).
        let mut g = self.wz.clone();
        for c in 0..k {
            let p = (c..k).max_by(|&a, &b| g[a * k + c].abs().total_cmp(&g[b * k + c].abs())).unwrap_or(c);
            if g[p * k + c] == 0.0 {
                return;
            }
            for j in 0..k {
                g.swap(c * k + j, p * k + j);
            }
            d.swap(c, p);
            for r in c + 1..k {
                let f = g[r * k + c] / g[c * k + c];
                for j in c..k {
                    g[r * k + j] -= f * g[c * k + j];
                }
                d[r] -= f * d[c];
            }
        }
        let mut s = vec![0.0; k];
        for c in (0..k).rev() {
            let t: f64 = (c + 1..k).map(|j| g[c * k + j] * s[j]).sum();
            s[c] = (d[c] - t) / g[c * k + c];
        }
        if !s.iter().all(|v| v.is_finite()) {
            return;
        }
        // One pass over x (per entry, the same additions in the same order as K passes).
        for (j, xj) in x.iter_mut().enumerate() {
            for (sk, z) in s.iter().zip(&self.z) {
                *xj += sk * z[j];
            }
        }
    }
}

/// A linear solver, timed (factorisation without the Jacobian inside it; triangular solves).
#[derive(Default)]
pub struct TimedLu<L> {
    inner: L,
}

impl<L: LaLinearSolver<M>> LaLinearSolver<M> for TimedLu<L> {
    fn set_linearisation<C: LaLinearOp<V = V, T = f64, M = M, C = FaerContext>>(&mut self, op: &C) {
        let jac_before = JAC_S.with(|c| c.get());
        let t = Instant::now();
        self.inner.set_linearisation(op);
        let jac = JAC_S.with(|c| c.get()) - jac_before;
        LU_SETUP_S.with(|c| c.set(c.get() + t.elapsed().as_secs_f64() - jac));
    }
    fn set_sparsity<C: LaLinearOp<V = V, T = f64, M = M, C = FaerContext>>(&mut self, op: &C) {
        self.inner.set_sparsity(op);
    }
    fn solve_in_place(&self, b: &mut V) -> Result<(), diffsol::LaError> {
        let t = Instant::now();
        let r = self.inner.solve_in_place(b);
        LU_SOLVE_S.with(|c| c.set(c.get() + t.elapsed().as_secs_f64()));
        r
    }
    fn solve_transpose_in_place(&self, b: &mut V) -> Result<(), diffsol::LaError> {
        self.inner.solve_transpose_in_place(b)
    }
}

/// The equations as diffsol sees them.
pub struct CellEqn {
    pub model: Model,
    /// Switch state of each interface (constant within an integration segment).
    pub open: RefCell<Vec<bool>>,
    /// The state a segment starts from.
    pub y_start: RefCell<Vec<f64>>,
    jac_sparsity: <M as Matrix>::Sparsity,
    mass_sparsity: <M as Matrix>::Sparsity,
    /// CSC structure of the Jacobian pattern (columns in order, rows sorted).
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    ctx: FaerContext,
    pub rhs_calls: Cell<u64>,
    pub jac_evals: Cell<u64>,
    pub rhs_s: Cell<f64>,
}

fn pattern(n: usize) -> (Vec<usize>, Vec<usize>) {
    let s = Model::STENCIL;
    let mut col_ptr = vec![0];
    let mut row_idx = Vec::with_capacity(3 * n * 3 * (2 * s + 1));
    for j in 0..3 * n {
        let c = j / 3;
        for r in c.saturating_sub(s)..=(c + s).min(n - 1) {
            for v in 0..3 {
                row_idx.push(3 * r + v);
            }
        }
        col_ptr.push(row_idx.len());
    }
    (col_ptr, row_idx)
}

impl CellEqn {
    pub fn new(model: Model, y0: Vec<f64>, open: Vec<bool>) -> CellEqn {
        let n = model.n;
        let (col_ptr, row_idx) = pattern(n);
        let mut indices = Vec::with_capacity(row_idx.len());
        for j in 0..3 * n {
            for &r in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                indices.push((r, j));
            }
        }
        let jac_sparsity = <<M as Matrix>::Sparsity as MatrixSparsity<M>>::try_from_indices(3 * n, 3 * n, indices)
            .expect("the banded Jacobian pattern is valid");
        let mass: Vec<(usize, usize)> = (0..n).flat_map(|i| [(3 * i, 3 * i), (3 * i + 1, 3 * i + 1)]).collect();
        let mass_sparsity =
            <<M as Matrix>::Sparsity as MatrixSparsity<M>>::try_from_indices(3 * n, 3 * n, mass).expect("the mass pattern is valid");
        CellEqn {
            model,
            open: RefCell::new(open),
            y_start: RefCell::new(y0),
            jac_sparsity,
            mass_sparsity,
            col_ptr,
            row_idx,
            ctx: FaerContext::default(),
            rhs_calls: Cell::new(0),
            jac_evals: Cell::new(0),
            rhs_s: Cell::new(0.0),
        }
    }

    fn eval(&self, x: &[f64], out: &mut [f64]) {
        let t = Instant::now();
        self.model.newton_rhs(x, &self.open.borrow(), out);
        for i in 0..self.model.n {
            out[3 * i] *= T_UNIT;
            out[3 * i + 1] *= T_UNIT;
        }
        self.rhs_calls.set(self.rhs_calls.get().saturating_add(1));
        self.rhs_s.set(self.rhs_s.get() + t.elapsed().as_secs_f64());
    }

    /// The Jacobian's values in CSC order, by coloured forward differences.
    pub fn fd_jacobian(&self, x: &[f64], vals: &mut [f64]) {
        let t = Instant::now();
        let n3 = x.len();
        let mut f0 = vec![0.0; n3];
        self.eval(x, &mut f0);
        let cmax = (0..n3).filter(|j| j % 3 != 2).map(|j| x[j].abs()).fold(0.0, f64::max);
        let typical = [1e-6 * cmax.max(1.0), 1e-6 * cmax.max(1.0), self.model.vt];
        let sqrt_eps = f64::EPSILON.sqrt();
        let colours = 3 * (2 * Model::STENCIL + 1);
        let period = 2 * Model::STENCIL + 1;
        let mut xp = x.to_vec();
        let mut f1 = vec![0.0; n3];
        let mut h = vec![0.0; n3];
        for colour in 0..colours {
            let (cell0, var) = (colour / 3, colour % 3);
            let mut j = 3 * cell0 + var;
            while j < n3 {
                let hj = sqrt_eps * x[j].abs().max(typical[var]);
                // An exactly representable step.
                let xj = x[j] + hj;
                h[j] = xj - x[j];
                xp[j] = xj;
                j += 3 * period;
            }
            self.eval(&xp, &mut f1);
            let mut j = 3 * cell0 + var;
            while j < n3 {
                for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                    let r = self.row_idx[k];
                    vals[k] = (f1[r] - f0[r]) / h[j];
                }
                xp[j] = x[j];
                j += 3 * period;
            }
        }
        // The Poisson rows are linear: their entries exactly, so that a Newton iteration with
        // a current matrix satisfies them to round-off.
        for j in 0..n3 {
            let (c, var) = (j / 3, j % 3);
            for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                let r = self.row_idx[k];
                if r % 3 == 2 {
                    vals[k] = self.model.poisson_derivative(r / 3, c, var);
                }
            }
        }
        self.jac_evals.set(self.jac_evals.get().saturating_add(1));
        JAC_S.with(|c| c.set(c.get() + t.elapsed().as_secs_f64()));
    }
}

pub struct CellRhs<'a> {
    eqn: &'a CellEqn,
}
pub struct CellMass<'a> {
    eqn: &'a CellEqn,
}
pub struct CellInit<'a> {
    eqn: &'a CellEqn,
}
pub struct CellRoot<'a> {
    eqn: &'a CellEqn,
}

macro_rules! cell_op {
    ($name:ident, $nout:expr) => {
        impl Op for $name<'_> {
            type M = M;
            type V = V;
            type T = f64;
            type C = FaerContext;
            fn nstates(&self) -> usize {
                self.eqn.model.len()
            }
            fn nout(&self) -> usize {
                #[allow(clippy::redundant_closure_call)]
                ($nout)(self.eqn)
            }
            fn nparams(&self) -> usize {
                0
            }
            fn context(&self) -> &FaerContext {
                &self.eqn.ctx
            }
        }
    };
}

cell_op!(CellRhs, |e: &CellEqn| e.model.len());
cell_op!(CellMass, |e: &CellEqn| e.model.len());
cell_op!(CellInit, |e: &CellEqn| e.model.len());
cell_op!(CellRoot, |e: &CellEqn| e.model.interfaces.len());

impl NonLinearOp for CellRhs<'_> {
    fn call_inplace(&self, x: &V, _t: f64, y: &mut V) {
        y.for_each_batch_host([x], |y, [x], _| self.eqn.eval(x, y));
    }
}

impl NonLinearOpJacobian for CellRhs<'_> {
    fn jac_mul_inplace(&self, x: &V, _t: f64, v: &V, y: &mut V) {
        // A directional difference (diffsol uses the assembled matrix for its Newton solves).
        y.for_each_batch_host([x, v], |y, [x, v], _| {
            let vnorm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
            if vnorm == 0.0 {
                y.iter_mut().for_each(|a| *a = 0.0);
                return;
            }
            let xnorm = x.iter().map(|a| a * a).sum::<f64>().sqrt();
            let h = f64::EPSILON.sqrt() * (1.0 + xnorm) / vnorm;
            let xp: Vec<f64> = x.iter().zip(v).map(|(a, b)| a + h * b).collect();
            let mut f0 = vec![0.0; x.len()];
            self.eqn.eval(x, &mut f0);
            self.eqn.eval(&xp, y);
            for (a, b) in y.iter_mut().zip(&f0) {
                *a = (*a - b) / h;
            }
        });
    }
    fn jacobian_inplace(&self, x: &V, _t: f64, y: &mut M) {
        let xs = x.clone_as_vec();
        let vals = y.inner_mut()[0].val_mut();
        assert_eq!(vals.len(), self.eqn.row_idx.len(), "Jacobian pattern mismatch");
        self.eqn.fd_jacobian(&xs, vals);
    }
    fn jacobian_sparsity(&self) -> Option<<M as Matrix>::Sparsity> {
        Some(self.eqn.jac_sparsity.clone())
    }
}

impl LinearOp for CellMass<'_> {
    fn gemv_inplace(&self, x: &V, _t: f64, beta: f64, y: &mut V) {
        y.for_each_batch_host([x], |y, [x], _| {
            for (i, (yi, xi)) in y.iter_mut().zip(x).enumerate() {
                *yi = if i % 3 == 2 { beta * *yi } else { xi + beta * *yi };
            }
        });
    }
    fn matrix_inplace(&self, _t: f64, y: &mut M) {
        for v in y.inner_mut()[0].val_mut() {
            *v = 1.0;
        }
    }
    fn sparsity(&self) -> Option<<M as Matrix>::Sparsity> {
        Some(self.eqn.mass_sparsity.clone())
    }
}

impl ConstantOp for CellInit<'_> {
    fn call_inplace(&self, _t: f64, y: &mut V) {
        let start = self.eqn.y_start.borrow();
        y.for_each_batch_host([], |y, [], _| y.copy_from_slice(&start));
    }
}

impl NonLinearOp for CellRoot<'_> {
    fn call_inplace(&self, x: &V, _t: f64, y: &mut V) {
        y.for_each_batch_host([x], |y, [x], _| self.eqn.model.switch_functions(x, &self.eqn.open.borrow(), y));
    }
}

impl Op for CellEqn {
    type M = M;
    type V = V;
    type T = f64;
    type C = FaerContext;
    fn nstates(&self) -> usize {
        self.model.len()
    }
    fn nout(&self) -> usize {
        self.model.len()
    }
    fn nparams(&self) -> usize {
        0
    }
    fn context(&self) -> &FaerContext {
        &self.ctx
    }
}

impl<'a> OdeEquationsRef<'a> for CellEqn {
    type Rhs = CellRhs<'a>;
    type Mass = CellMass<'a>;
    type Init = CellInit<'a>;
    type Root = CellRoot<'a>;
    type Out = ParameterisedOp<'a, UnitCallable<M>>;
    type Reset = ParameterisedOp<'a, UnitCallable<M>>;
}

impl OdeEquations for CellEqn {
    fn rhs(&self) -> CellRhs<'_> {
        CellRhs { eqn: self }
    }
    fn mass(&self) -> Option<CellMass<'_>> {
        Some(CellMass { eqn: self })
    }
    fn init(&self) -> CellInit<'_> {
        CellInit { eqn: self }
    }
    fn root(&self) -> Option<CellRoot<'_>> {
        if self.model.interfaces.is_empty() || self.model.ramp.is_some() { None } else { Some(CellRoot { eqn: self }) }
    }
    fn set_params(&mut self, _p: &V) {}
    fn get_params(&self, _p: &mut V) {}
}

/// Integration settings.
#[derive(Debug, Clone)]
pub struct Settings {
    pub rtol: f64,
    pub atol_concentration: f64,
    pub atol_potential: f64,
    pub end_time: f64,
    /// Times of the snapshots (sorted, within [0, end_time]).
    pub output_times: Vec<f64>,
    pub max_steps: u64,
    /// Some(dt): explicit Euler at this step (the validator has checked the bound).
    pub explicit_dt: Option<f64>,
    /// Continue from this restart point (a checkpoint) instead of the initial state.
    pub start: Option<Restart>,
    /// The BDF's linear solver.
    pub linear_solver: LinearSolver,
}

/// A point from which the integration continues bit for bit as the run that never stopped:
/// the BDF integrator restarts (order 1, fresh Jacobian and factorisation) at every output time
/// and at every switch, from exactly the state, switch states and first step saved here, and
/// nothing else carries over a restart. Explicit Euler has a restart point at every output
/// time. A checkpoint of a cell run is one of these.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Restart {
    /// Time (s).
    pub t: f64,
    pub y: Vec<f64>,
    pub open: Vec<bool>,
    /// First step of the next segment (integrator units, [`T_UNIT`]).
    pub h0: f64,
    /// Output times passed (the next segment stops at the following one).
    pub outputs_done: usize,
    /// The statistics and checks up to here.
    pub stats: Stats,
}

/// A state handed to the caller.
pub struct Snapshot<'a> {
    /// Accepted steps so far.
    pub step: u64,
    pub t: f64,
    pub y: &'a [f64],
    pub open: &'a [bool],
    /// A snapshot at one of the output times (false: an accepted step only).
    pub output: bool,
    /// Set where the integration restarts (see [`Restart`]): a checkpoint may be taken here.
    pub restart: Option<&'a Restart>,
    /// The run's counters so far (the times only at the end of [`integrate`]).
    pub stats: &'a Stats,
}

/// What the caller wants after a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    Continue,
    Stop,
}

/// Step statistics and checks of a run. The counters saturate: a count restored from a
/// checkpoint never stops a run.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Stats {
    pub steps: u64,
    pub error_test_failures: u64,
    pub newton_iterations: u64,
    pub newton_failures: u64,
    pub lu_setups: u64,
    pub jacobian_evaluations: u64,
    pub rhs_evaluations: u64,
    /// Switch flips (root events) and so integrator restarts.
    pub switch_events: u64,
    pub switch_log: Vec<(f64, usize, bool)>,
    /// Starts at infinity (saved as null).
    #[serde(with = "infinite_as_null")]
    pub min_step: f64,
    pub max_step: f64,
    pub t: f64,
    pub wall_s: f64,
    pub rhs_s: f64,
    pub jacobian_s: f64,
    pub lu_factor_s: f64,
    pub lu_solve_s: f64,
    /// Largest Poisson-row residual over accepted steps, relative to the largest sum of the
    /// magnitudes of a row's terms ([`Model::poisson_residual`]).
    pub max_poisson_residual: f64,
    /// Largest relative drifts of the cation and electron inventories over accepted steps.
    pub max_cation_drift: f64,
    pub max_electron_drift: f64,
    /// Largest |(eps0/e)(G0 - GN) - Q| over accepted steps, relative to the inventory
    /// sum (p + n) dx.
    pub max_gauss_error: f64,
    /// Starts at infinity (saved as null).
    #[serde(with = "infinite_as_null")]
    pub min_p: f64,
    pub stopped: bool,
}

/// +infinity, the start of a running minimum, as JSON's null (JSON has no infinity).
mod infinite_as_null {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() { s.serialize_some(v) } else { s.serialize_none() }
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    #[error("the integrator failed at t = {t:e} s after {steps} steps: {why}")]
    Integrator { t: f64, steps: u64, why: String },
    #[error("the state is not finite at t = {t:e} s after {steps} steps")]
    NotFinite { t: f64, steps: u64 },
    #[error("scheme.max_steps = {0} accepted steps reached before end_time_s")]
    MaxSteps(u64),
}

struct Monitor<'m> {
    model: &'m Model,
    cations0: f64,
    electrons0: f64,
}

impl Monitor<'_> {
    fn check(&self, y: &[f64], open: &[bool], stats: &mut Stats) -> bool {
        if !y.iter().all(|v| v.is_finite()) {
            return false;
        }
        let (r, scale) = self.model.poisson_residual(y, open);
        stats.max_poisson_residual = stats.max_poisson_residual.max(r / scale.max(f64::MIN_POSITIVE));
        let tot = self.model.totals(y);
        stats.max_cation_drift = stats.max_cation_drift.max((tot.cations - self.cations0).abs() / self.cations0.abs().max(1.0));
        stats.max_electron_drift = stats.max_electron_drift.max((tot.electrons - self.electrons0).abs() / self.electrons0.abs().max(1.0));
        let (lhs, q, _) = self.model.gauss(y, open);
        let inventory = tot.cations + tot.electrons + tot.anions;
        stats.max_gauss_error = stats.max_gauss_error.max((lhs - q).abs() / inventory.max(f64::MIN_POSITIVE));
        stats.min_p = stats.min_p.min(tot.min_p);
        true
    }
}

/// Integrates the cell from its consistent initial state (or from `settings.start`) to
/// `settings.end_time`, calling `on_snapshot` at every accepted step (output = false), at every
/// output time and at every restart point.
pub fn integrate(
    model: &Model,
    settings: &Settings,
    on_snapshot: &mut dyn FnMut(&Snapshot<'_>) -> Control,
) -> Result<(Vec<f64>, Vec<bool>, Stats), SolveError> {
    LU_SETUP_S.with(|c| c.set(0.0));
    LU_SOLVE_S.with(|c| c.set(0.0));
    JAC_S.with(|c| c.set(0.0));
    let wall = Instant::now();
    let y0 = model.initial_state();
    let tot0 = model.totals(&y0);
    let monitor = Monitor { model, cations0: tot0.cations, electrons0: tot0.electrons };
    let mut outputs = settings.output_times.iter().copied().peekable();
    let start = match &settings.start {
        Some(r) => {
            for _ in 0..r.outputs_done {
                outputs.next();
            }
            let mut r = r.clone();
            r.stats.stopped = false;
            r
        }
        None => {
            let open0 = model.initial_open(&y0);
            let mut stats = Stats { min_step: f64::INFINITY, min_p: f64::INFINITY, ..Default::default() };
            let mut done = 0;
            // Snapshots at t = 0.
            while outputs.peek().is_some_and(|&t| t <= 0.0) {
                outputs.next();
                done += 1;
            }
            monitor.check(&y0, &open0, &mut stats);
            let r = Restart { t: 0.0, y: y0, open: open0, h0: 1e-3, outputs_done: done, stats };
            let snap = Snapshot { step: 0, t: 0.0, y: &r.y, open: &r.open, output: done > 0, restart: Some(&r), stats: &r.stats };
            if on_snapshot(&snap) == Control::Stop {
                let mut stats = r.stats.clone();
                stats.stopped = true;
                return Ok((r.y, r.open, stats));
            }
            r
        }
    };
    let mut stats = start.stats.clone();
    let result = match settings.explicit_dt {
        Some(dt) => explicit(model, settings, &monitor, start, dt, &mut outputs, &mut stats, on_snapshot),
        None => bdf(model, settings, &monitor, start, &mut outputs, &mut stats, on_snapshot),
    };
    // Times are of this session (a resumed run's earlier sessions are not added).
    stats.wall_s = wall.elapsed().as_secs_f64();
    stats.jacobian_s = JAC_S.with(|c| c.get());
    stats.lu_factor_s = LU_SETUP_S.with(|c| c.get());
    stats.lu_solve_s = LU_SOLVE_S.with(|c| c.get());
    if stats.min_step == f64::INFINITY {
        stats.min_step = 0.0;
    }
    result.map(|(y, open)| (y, open, stats))
}

#[allow(clippy::too_many_arguments)]
fn explicit(
    model: &Model,
    settings: &Settings,
    monitor: &Monitor<'_>,
    start: Restart,
    dt: f64,
    outputs: &mut std::iter::Peekable<impl Iterator<Item = f64>>,
    stats: &mut Stats,
    on_snapshot: &mut dyn FnMut(&Snapshot<'_>) -> Control,
) -> Result<(Vec<f64>, Vec<bool>), SolveError> {
    let Restart { mut t, mut y, mut open, mut outputs_done, .. } = start;
    let mut f = vec![0.0; y.len()];
    let mut g = vec![0.0; model.interfaces.len()];
    while t < settings.end_time {
        let target = outputs.peek().copied().unwrap_or(settings.end_time).min(settings.end_time);
        let h = dt.min(target - t);
        model.rhs(&y, &open, &mut f);
        stats.rhs_evaluations = stats.rhs_evaluations.saturating_add(1);
        for i in 0..model.n {
            y[3 * i] += h * f[3 * i];
            y[3 * i + 1] += h * f[3 * i + 1];
        }
        model.solve_poisson(&mut y);
        t = if target - t <= dt { target } else { t + h };
        stats.steps = stats.steps.saturating_add(1);
        stats.min_step = stats.min_step.min(h);
        stats.max_step = stats.max_step.max(h);
        stats.t = t;
        model.switch_functions(&y, &open, &mut g);
        for (k, gk) in g.iter().enumerate() {
            if *gk >= 0.0 && !open[k] || *gk < 0.0 && open[k] {
                open[k] = !open[k];
                stats.switch_events = stats.switch_events.saturating_add(1);
                stats.switch_log.push((t, k, open[k]));
            }
        }
        if !monitor.check(&y, &open, stats) {
            return Err(SolveError::NotFinite { t, steps: stats.steps });
        }
        if stats.steps > settings.max_steps {
            return Err(SolveError::MaxSteps(settings.max_steps));
        }
        let is_output = outputs.peek().is_some_and(|&o| t >= o);
        if is_output {
            outputs.next();
            outputs_done += 1;
        }
        // Explicit Euler continues from (t, y, open) alone: every output time is a restart point.
        let restart = (is_output && t < settings.end_time).then(|| Restart {
            t,
            y: y.clone(),
            open: open.clone(),
            h0: dt,
            outputs_done,
            stats: stats.clone(),
        });
        if on_snapshot(&Snapshot { step: stats.steps, t, y: &y, open: &open, output: is_output, restart: restart.as_ref(), stats })
            == Control::Stop
        {
            stats.stopped = true;
            break;
        }
    }
    Ok((y, open))
}

/// Flips every switch that is on the wrong side of its threshold in the state `y` (a closed
/// interface with |dphi| >= threshold, or an open one below threshold - hysteresis), except
/// `just_flipped` (the root the segment ended at, which sits on its threshold to rounding),
/// logging each as a switch event at `t`. Returns how many were flipped.
///
/// Why: the root finder restarts at every restart point from the switch functions' values
/// there and only reports sign changes, so a function that is already positive at a restart
/// is never reported: both interfaces reach the threshold in the same step (the electrolyte's
/// field is the same at both), and the one not reported stayed closed above its threshold.
pub(crate) fn reconcile_switches(
    model: &Model,
    y: &[f64],
    open: &mut [bool],
    just_flipped: Option<usize>,
    t: f64,
    stats: &mut Stats,
) -> usize {
    if model.ramp.is_some() || open.is_empty() {
        return 0;
    }
    let mut g = vec![0.0; open.len()];
    model.switch_functions(y, open, &mut g);
    let mut flipped = 0;
    for (k, gk) in g.iter().enumerate() {
        if Some(k) == just_flipped {
            continue;
        }
        if (*gk >= 0.0 && !open[k]) || (*gk < 0.0 && open[k]) {
            open[k] = !open[k];
            stats.switch_events = stats.switch_events.saturating_add(1);
            stats.switch_log.push((t, k, open[k]));
            flipped += 1;
        }
    }
    flipped
}

/// How an integration segment ended: at a switch (its root: time, state, interface) or at its
/// stop time; with the step size to restart from.
struct SegmentEnd {
    t: f64,
    y: Vec<f64>,
    switched: Option<usize>,
    h: f64,
}

/// One integration segment, from the problem's start (time `t_seg`, the integrator's local time
/// 0) to `next_stop` or the first switch, with the linear solver `L`. `y` follows the accepted
/// steps; `None` when the caller stopped it.
///
/// Each segment runs in its own time from 0 (the equations are autonomous), so the steps right
/// after a switch, ~1e-18 s at 1e5 cells, are not below the rounding of the absolute time
/// (ulp(0.295 s) = 5.6e-17 s: with the absolute time the 1e5-cell run's first switch, at
/// 0.2951 s, could not be stepped past, "step size is too small").
#[allow(clippy::too_many_arguments)]
fn segment<L: LaLinearSolver<M> + Default>(
    problem: &diffsol::OdeSolverProblem<CellEqn>,
    model: &Model,
    monitor: &Monitor<'_>,
    t_seg: f64,
    next_stop: f64,
    stats: &mut Stats,
    y: &mut Vec<f64>,
    on_snapshot: &mut dyn FnMut(&Snapshot<'_>) -> Control,
) -> Result<Option<SegmentEnd>, SolveError> {
    let fail = |t: f64, steps: u64, e: diffsol::DiffsolError| SolveError::Integrator { t, steps, why: e.to_string() };
    let t = t_seg;
    // The start is consistent by construction (phi from the exact Poisson solve), so
    // diffsol's own initial-condition Newton is not needed: dy = f(y) on the differential
    // rows, and phi' from the differentiated constraint (index 1: M phi' = -(e/eps0)(p' - n')),
    // so that the first predictor is consistent too.
    let mut state = BdfState::new(problem, 1).map_err(|e| fail(t, stats.steps, e))?;
    state.as_mut().dy.for_each_batch_host([], |dy, [], _| model.solve_poisson_derivative(dy));
    let mut solver = problem.bdf_solver::<TimedLu<L>>(state).map_err(|e| fail(t, stats.steps, e))?;
    solver.set_stop_time((next_stop - t_seg) / T_UNIT).map_err(|e| fail(t, stats.steps, e))?;
    let base = stats.clone();
    loop {
        let before_local = solver.state().t;
        let before = t_seg + before_local * T_UNIT;
        let reason = solver.step().map_err(|e| fail(before, stats.steps, e))?;
        let st = solver.get_statistics();
        stats.steps = base.steps.saturating_add(st.number_of_steps as u64);
        stats.error_test_failures = base.error_test_failures.saturating_add(st.number_of_error_test_failures as u64);
        stats.newton_iterations = base.newton_iterations.saturating_add(st.number_of_nonlinear_solver_iterations as u64);
        stats.newton_failures = base.newton_failures.saturating_add(st.number_of_nonlinear_solver_fails as u64);
        stats.lu_setups = base.lu_setups.saturating_add(st.number_of_linear_solver_setups as u64);
        if let OdeSolverStopReason::RootFound(tau_root, k) = reason {
            let t_root = t_seg + tau_root * T_UNIT;
            solver.state_mut_back(tau_root).map_err(|e| fail(t_root, stats.steps, e))?;
            let state = solver.state();
            // Which switch: the root function whose sign changed, as the root finder reports
            // it. (Not the one closest to zero: a latched-open interface's function is its
            // |dphi|, which may well be closer to zero than the one that crossed.)
            let yr = state.y.clone_as_vec();
            return Ok(Some(SegmentEnd { t: t_root, y: yr, switched: Some(k), h: state.h }));
        }
        let state = solver.state();
        // The stop time exactly where the segment reached it.
        let tn = if reason == OdeSolverStopReason::TstopReached { next_stop } else { t_seg + state.t * T_UNIT };
        let step = (state.t - before_local) * T_UNIT;
        stats.min_step = stats.min_step.min(step.abs());
        stats.max_step = stats.max_step.max(step.abs());
        stats.t = tn;
        *y = state.y.clone_as_vec();
        if !monitor.check(y, &problem.eqn.open.borrow(), stats) {
            return Err(SolveError::NotFinite { t: tn, steps: stats.steps });
        }
        if reason == OdeSolverStopReason::TstopReached {
            return Ok(Some(SegmentEnd { t: tn, y: std::mem::take(y), switched: None, h: state.h }));
        }
        let open = problem.eqn.open.borrow();
        if on_snapshot(&Snapshot { step: stats.steps, t: tn, y, open: &open, output: false, restart: None, stats }) == Control::Stop {
            return Ok(None);
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn bdf(
    model: &Model,
    settings: &Settings,
    monitor: &Monitor<'_>,
    start: Restart,
    outputs: &mut std::iter::Peekable<impl Iterator<Item = f64>>,
    stats: &mut Stats,
    on_snapshot: &mut dyn FnMut(&Snapshot<'_>) -> Control,
) -> Result<(Vec<f64>, Vec<bool>), SolveError> {
    let n = model.n;
    let atol: Vec<f64> = (0..3 * n).map(|j| if j % 3 == 2 { settings.atol_potential } else { settings.atol_concentration }).collect();
    let Restart { t: t_start, y: y_start, open: mut open_start, h0, mut outputs_done, .. } = start;
    // A restart point whose switch states disagree with its potentials (from a checkpoint
    // written before the check below existed) is put right before the first segment.
    reconcile_switches(model, &y_start, &mut open_start, None, t_start, stats);
    let eqn = CellEqn::new(model.clone(), y_start.clone(), open_start);
    // The counters carry on from the restart point (a resumed run reports the whole run's).
    eqn.rhs_calls.set(stats.rhs_evaluations);
    eqn.jac_evals.set(stats.jacobian_evaluations);
    eqn.rhs_s.set(stats.rhs_s);
    let fail = |t: f64, steps: u64, e: diffsol::DiffsolError| SolveError::Integrator { t, steps, why: e.to_string() };
    let mut problem = OdeBuilder::<M>::new()
        .rtol(settings.rtol)
        .atol(atol)
        .t0(0.0)
        .h0(h0)
        .build_from_eqn(eqn)
        .map_err(|e| fail(t_start, stats.steps, e))?;
    problem.ode_options.max_error_test_failures = 60;
    // Newton to well below the local error (default 0.2 of it): the Poisson rows, linear,
    // then hold to ~1e-12 of their terms.
    problem.ode_options.nonlinear_solver_tolerance = 1e-3;
    // A fresh Jacobian every 10 steps (diffsol's default 50). The Newton matrix is reused
    // across steps (modified Newton); with a Jacobian up to 50 steps old it contracts at only
    // 0.4-0.7 per iteration, and against the tolerance above every one of the Newton failures
    // of the 1e3-cell run to 2 s (18 in 999 steps) was diffsol's "will not converge in the
    // iterations left" at such a rate, cured by the fresh Jacobian of its retry
    // (`newton_failures_by_cause`, cell/README.md). A Jacobian costs 15 right-hand sides; with
    // 10 the failures fall to 1 (1e3 cells) and 21 of 51 (1e4), the Newton iterations by
    // 19-22 %, for ~30 % more factorisations.
    problem.ode_options.update_rhs_jacobian_after_steps = 10;
    let mut y = y_start;
    let mut t = t_start;
    let end = settings.end_time;
    let at = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1e-300);
    while t < end * (1.0 - 1e-12) {
        let remaining = settings.max_steps.saturating_sub(stats.steps);
        if remaining == 0 {
            return Err(SolveError::MaxSteps(settings.max_steps));
        }
        problem.ode_options.max_number_timesteps = remaining as usize;
        let next_stop = outputs.peek().copied().unwrap_or(end).min(end);
        // The inventories this segment conserves, for the banded LU's invariant-exact solves.
        let invariants = if settings.linear_solver == LinearSolver::Banded { model.invariants(&problem.eqn.open.borrow()) } else { vec![] };
        let _weights = ChargeWeights::set(invariants);
        // How the segment ended: at a switch (its root: time, state, interface) or at the stop
        // time; with the step size to restart from.
        let segment = match settings.linear_solver {
            LinearSolver::Banded => segment::<BandedLu>(&problem, model, monitor, t, next_stop, stats, &mut y, on_snapshot)?,
            LinearSolver::SparseLu => segment::<FaerSparseLU<f64>>(&problem, model, monitor, t, next_stop, stats, &mut y, on_snapshot)?,
        };
        stats.jacobian_evaluations = problem.eqn.jac_evals.get();
        stats.rhs_evaluations = problem.eqn.rhs_calls.get();
        stats.rhs_s = problem.eqn.rhs_s.get();
        let Some(SegmentEnd { t: t_end, y: y_end, switched, h }) = segment else {
            stats.stopped = true;
            break;
        };
        if let Some(k) = switched {
            let mut open = problem.eqn.open.borrow_mut();
            open[k] = !open[k];
            stats.switch_events = stats.switch_events.saturating_add(1);
            stats.switch_log.push((t_end, k, open[k]));
        }
        t = t_end;
        // A segment that reached its stop time, or a switch that landed on it to within
        // rounding, passes the output time there.
        let output = at(t, next_stop) && outputs.peek().is_some_and(|&o| at(o, next_stop));
        if output {
            outputs.next();
            outputs_done += 1;
        }
        if switched.is_none() && t >= end * (1.0 - 1e-12) {
            // The end: no restart, the state as the integrator left it.
            y = y_end;
            let open = problem.eqn.open.borrow();
            let snap = Snapshot { step: stats.steps, t, y: &y, open: &open, output, restart: None, stats };
            if on_snapshot(&snap) == Control::Stop {
                stats.stopped = true;
            }
            break;
        }
        // Restart (order 1) from the state projected onto the constraint (the Poisson rows are
        // linear, so this moves phi by no more than the solver's tolerance). Everything the
        // next segment depends on is in the restart point, so a run continued from it is bit
        // for bit the run that never stopped.
        let mut yr = y_end;
        model.solve_poisson(&mut yr);
        // An interface on the wrong side of its threshold at the restart is never found by
        // the root finder (it only sees sign changes): flip it here.
        reconcile_switches(model, &yr, &mut problem.eqn.open.borrow_mut(), switched, t, stats);
        let h0 = h.abs().max(1e-6);
        *problem.eqn.y_start.borrow_mut() = yr.clone();
        problem.h0 = h0;
        let open = problem.eqn.open.borrow().clone();
        let restart = Restart { t, y: yr, open, h0, outputs_done, stats: stats.clone() };
        let snap =
            Snapshot { step: stats.steps, t, y: &restart.y, open: &restart.open, output, restart: Some(&restart), stats: &restart.stats };
        let control = on_snapshot(&snap);
        y = restart.y;
        if control == Control::Stop {
            stats.stopped = true;
            break;
        }
    }
    stats.jacobian_evaluations = problem.eqn.jac_evals.get();
    stats.rhs_evaluations = problem.eqn.rhs_calls.get();
    stats.rhs_s = problem.eqn.rhs_s.get();
    let open = problem.eqn.open.borrow().clone();
    Ok((y, open))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CellBoundary, CellOutput, CellScene, CellScheme, Electrolyte, Grid, Interface, Physics};

    fn small_scene(cells: usize) -> CellScene {
        CellScene {
            schema: 1,
            kind: "cell".into(),
            name: "t".into(),
            description: String::new(),
            grid: Grid { cells },
            physics: Physics::default(),
            anode: None,
            electrolyte: Electrolyte {
                width_nm: 1.0,
                eps_r: 10.0,
                d_p_cm2_per_s: 1.7e-4,
                d_n_cm2_per_s: 0.0,
                p0_per_nm3: 6.0,
                n0_per_nm3: 6.0,
            },
            cathode: None,
            interface: Interface::default(),
            boundary: CellBoundary { phi_left_v: 1e-3, right: "reservoir".into(), ..Default::default() },
            scheme: CellScheme {
                integrator: crate::scene::Integrator::Bdf,
                face_state: crate::scene::FaceState::VanLeer,
                end_time_s: 1e-12,
                rtol: 1e-6,
                atol_concentration: Some(1e-9),
                atol_inventory_per_nm2: None,
                atol_potential_v: 1e-9,
                timestep_s: None,
                max_steps: 100_000,
                linear_solver: crate::scene::LinearSolver::Banded,
                electron_rows: crate::scene::ElectronRows::Field,
                charge_exact_solve: true,
            },
            output: CellOutput::default(),
        }
    }

    #[test]
    fn coloured_jacobian_matches_column_by_column_differences() {
        let model = Model::new(&small_scene(12));
        let mut y = model.initial_state();
        for (k, v) in y.iter_mut().enumerate() {
            *v += 1e-3 * ((k * 7919) % 13) as f64 / 13.0;
        }
        let eqn = CellEqn::new(model.clone(), y.clone(), vec![]);
        let mut vals = vec![0.0; eqn.row_idx.len()];
        eqn.fd_jacobian(&y, &mut vals);
        let n3 = y.len();
        let mut f0 = vec![0.0; n3];
        model.newton_rhs(&y, &[], &mut f0);
        let mut f1 = vec![0.0; n3];
        for j in 0..n3 {
            let h = 1e-7 * y[j].abs().max(1e-3);
            let mut yp = y.clone();
            yp[j] += h;
            model.newton_rhs(&yp, &[], &mut f1);
            let mut dense = vec![0.0; n3];
            for r in 0..n3 {
                dense[r] = (f1[r] - f0[r]) / h * if r % 3 == 2 { 1.0 } else { T_UNIT };
            }
            for k in eqn.col_ptr[j]..eqn.col_ptr[j + 1] {
                let r = eqn.row_idx[k];
                let scale = dense[r].abs().max(vals[k].abs()).max(1.0);
                assert!((vals[k] - dense[r]).abs() < 1e-2 * scale, "J[{r},{j}] = {} vs {}", vals[k], dense[r]);
                dense[r] = 0.0;
            }
            let outside = dense.iter().map(|v| v.abs()).fold(0.0, f64::max);
            assert!(outside < 1e-6, "column {j} has entries outside the pattern: {outside}");
        }
    }

    /// The field form of the electron rows is the potential form plus sigma/(k eps) times the
    /// cell's Poisson row, in every electrode cell (inside, at x = 0, at the interfaces and at
    /// the insulating end), at a state that does not satisfy the Poisson rows.
    #[test]
    fn field_electron_rows_are_the_potential_rows_plus_a_multiple_of_the_poisson_row() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/pnp-full-cell.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let mut scene = crate::scene::parse(&text, &std::collections::BTreeMap::new(), "t").unwrap();
        scene.grid.cells = 50;
        let mut model = Model::new(&scene);
        let mut y = model.initial_state();
        for (k, v) in y.iter_mut().enumerate() {
            *v += if k % 3 == 2 { 1e-2 } else { 1.0 } * ((k * 7919) % 13) as f64 / 13.0;
        }
        let open = vec![true; model.interfaces.len()];
        let mut f = vec![0.0; y.len()];
        model.rhs(&y, &open, &mut f);
        model.electron_rows = crate::scene::ElectronRows::Field;
        let mut g = vec![0.0; y.len()];
        model.newton_rhs(&y, &open, &mut g);
        let mut electrode = 0;
        for i in 0..model.n {
            assert_eq!(f[3 * i], g[3 * i]);
            assert_eq!(f[3 * i + 2], g[3 * i + 2]);
            if model.region[i].is_electrode() {
                electrode += 1;
                let mu = model.sigma[i] / (model.k_poisson * model.eps[i]);
                let want = f[3 * i + 1] + mu * f[3 * i + 2];
                let scale = f[3 * i + 1].abs() + (mu * f[3 * i + 2]).abs();
                assert!((g[3 * i + 1] - want).abs() <= 1e-12 * scale, "cell {i}: {} vs {want}", g[3 * i + 1]);
                assert!((g[3 * i + 1] - f[3 * i + 1]).abs() > 1e-6 * scale, "cell {i}: the row did not change");
            } else {
                assert_eq!(f[3 * i + 1], g[3 * i + 1]);
            }
        }
        assert_eq!(electrode, 20);
    }

    struct Logger;
    impl log::Log for Logger {
        fn enabled(&self, _: &log::Metadata<'_>) -> bool {
            true
        }
        fn log(&self, r: &log::Record<'_>) {
            if std::env::var("CELL_LOG").is_ok() {
                eprintln!("{} {}", r.level(), r.args());
            }
        }
        fn flush(&self) {}
    }

    #[test]
    fn integrates_a_short_debye_transient() {
        let _ = log::set_logger(&Logger).map(|()| log::set_max_level(log::LevelFilter::Trace));
        let s = small_scene(std::env::var("CELL_N").ok().and_then(|v| v.parse().ok()).unwrap_or(50));
        let model = Model::new(&s);
        let env = |k: &str, d: f64| std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d);
        let settings = Settings {
            rtol: env("CELL_RTOL", 1e-6),
            atol_concentration: env("CELL_ATOLC", 1e-9),
            atol_potential: env("CELL_ATOLP", 1e-9),
            end_time: 1e-12,
            output_times: vec![],
            max_steps: 100_000,
            explicit_dt: None,
            start: None,
            linear_solver: crate::scene::LinearSolver::Banded,
        };
        let (_y, _open, stats) = integrate(&model, &settings, &mut |_| Control::Continue).unwrap_or_else(|e| panic!("{e}"));
        assert!(stats.steps > 0);
    }
}

#[cfg(test)]
mod diagnosis {
    use super::*;
    use crate::band::BandLu;
    use std::collections::BTreeMap;

    fn env<T: std::str::FromStr>(k: &str, d: T) -> T {
        std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
    }

    /// One backward Euler step's system at y0 as the integrator builds it: M - c J (finite
    /// differences) in band LU, the cell's invariants and their charge-exact directions.
    struct Shifted {
        eqn: CellEqn,
        c: f64,
        lu: BandLu,
        ws: Vec<Vec<f64>>,
        dirs: Directions,
    }

    fn shifted(model: &Model, y0: &[f64], open: &[bool], h: f64) -> Shifted {
        let eqn = CellEqn::new(model.clone(), y0.to_vec(), open.to_vec());
        let c = h / T_UNIT;
        let n3 = y0.len();
        let mut vals = vec![0.0; eqn.row_idx.len()];
        eqn.fd_jacobian(y0, &mut vals);
        for j in 0..n3 {
            for k in eqn.col_ptr[j]..eqn.col_ptr[j + 1] {
                let r = eqn.row_idx[k];
                vals[k] = if r == j && r % 3 != 2 { 1.0 } else { 0.0 } - c * vals[k];
            }
        }
        let (kl, ku) = BandLu::bandwidths(&eqn.col_ptr, &eqn.row_idx);
        let mut lu = BandLu::new(n3, kl, ku);
        lu.factor_csc(&eqn.col_ptr, &eqn.row_idx, &vals);
        let ws = model.invariants(open);
        let dirs = Directions::new(&ws, &eqn.col_ptr, &eqn.row_idx, &vals, &lu).expect("a closed cell");
        Shifted { eqn, c, lu, ws, dirs }
    }

    /// Backward Euler from the state y0 with step h, solved by modified Newton (the Jacobian
    /// of y0) over the banded LU, with or without the charge-exact correction; returns the
    /// weighted RMS norms of the corrections (rtol 1e-6, atol 1e-9) and the charge defects of
    /// the LU's solutions (e/nm^2).
    fn newton(model: &Model, y0: &[f64], open: &[bool], h: f64, charge_exact: bool, its: usize) -> (Vec<f64>, Vec<f64>) {
        let Shifted { eqn, c, lu, ws, dirs } = shifted(model, y0, open, h);
        let n3 = y0.len();
        // The net charge: +dx on p, -dx on n.
        let w: Vec<f64> = (0..n3).map(|j| [model.dx, -model.dx, 0.0][j % 3]).collect();
        let weight: Vec<f64> = y0.iter().map(|v| 1e-6 * v.abs() + 1e-9).collect();
        let (mut norms, mut defects) = (vec![], vec![]);
        let mut y = y0.to_vec();
        let mut f = vec![0.0; n3];
        for _ in 0..its {
            eqn.eval(&y, &mut f);
            let b: Vec<f64> = (0..n3).map(|j| -if j % 3 != 2 { (y[j] - y0[j]) - c * f[j] } else { -c * f[j] }).collect();
            let mut x = b.clone();
            lu.solve(&mut x);
            let d: f64 = (0..n3).map(|j| w[j] * (b[j] - x[j])).sum();
            defects.push(d);
            if charge_exact {
                dirs.apply(&ws, &b, &mut x);
            }
            let mut sum = 0.0;
            for j in 0..n3 {
                y[j] += x[j];
                sum += (x[j] / weight[j]).powi(2);
            }
            norms.push((sum / n3 as f64).sqrt());
        }
        (norms, defects)
    }

    /// A restart point saved by `diagnose_from_a_restart_point` (validation.rs), env R: one
    /// backward Euler step of size H (s) by modified Newton; where the weighted correction sits.
    #[test]
    #[ignore = "diagnosis tool: needs a saved restart point (env R)"]
    fn newton_from_a_saved_restart_point() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/pnp-full-cell.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let mut scene = crate::scene::parse(&text, &BTreeMap::new(), "t").unwrap();
        scene.grid.cells = env("N", 100_000usize);
        let r: Restart = serde_json::from_slice(&std::fs::read(std::env::var("R").unwrap()).unwrap()).unwrap();
        let model = Model::new(&scene);
        let (res, scale) = model.poisson_residual(&r.y, &r.open);
        eprintln!("Poisson residual {res:e} of {scale:e}");
        let mut yp = r.y.clone();
        model.solve_poisson(&mut yp);
        let dphi = (0..model.n).map(|i| (yp[3 * i + 2] - r.y[3 * i + 2]).abs()).fold(0.0, f64::max);
        eprintln!("re-projection moves phi by {dphi:e} V; residual after it {:e}", model.poisson_residual(&yp, &r.open).0);
        let r = Restart { y: yp, ..r };
        for h in [env("H", 1e-20), 1e-24] {
            let y0 = &r.y;
            let Shifted { eqn, c, lu, ws, dirs } = shifted(&model, y0, &r.open, h);
            let n3 = y0.len();
            let weight: Vec<f64> = y0.iter().map(|v| 1e-6 * v.abs() + 1e-9).collect();
            let mut y = y0.to_vec();
            let mut f = vec![0.0; n3];
            for it in 0..4 {
                eqn.eval(&y, &mut f);
                let b: Vec<f64> = (0..n3).map(|j| -if j % 3 != 2 { (y[j] - y0[j]) - c * f[j] } else { -c * f[j] }).collect();
                let mut x = b.clone();
                lu.solve(&mut x);
                dirs.apply(&ws, &b, &mut x);
                for j in 0..n3 {
                    y[j] += x[j];
                }
                let mut worst: Vec<(f64, usize)> = (0..n3).map(|j| ((y[j] - y0[j]) / weight[j], j)).collect();
                let norm = (worst.iter().map(|w| w.0 * w.0).sum::<f64>() / n3 as f64).sqrt();
                worst.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
                let per_kind: Vec<f64> =
                    (0..3).map(|k| (worst.iter().filter(|w| w.1 % 3 == k).map(|w| w.0 * w.0).sum::<f64>() / n3 as f64).sqrt()).collect();
                eprintln!(
                    "h {h:e} it {it}: |y - y0| weighted RMS {norm:e} (p, n, phi: {per_kind:?}); worst {:?}",
                    &worst[..6].iter().map(|w| (w.0, w.1 / 3, w.1 % 3, y0[w.1], y[w.1])).collect::<Vec<_>>()
                );
            }
        }
    }

    /// The diagnosis of cell/README.md "1e5 cells: why the steps were small": at 1e5 cells the
    /// LU's corrections change the cell's charge, and Newton converges only linearly; the
    /// charge-exact correction restores fast convergence.
    #[test]
    #[ignore = "heavy: a 1e5-cell state (about a minute); run with --ignored --nocapture"]
    fn charge_exact_corrections_restore_newton_convergence_at_1e5_cells() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/pnp-full-cell.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let mut scene = crate::scene::parse(&text, &BTreeMap::new(), "t").unwrap();
        scene.grid.cells = env("N", 100_000usize);
        let t0: f64 = env("T0", 5e-4);
        let h: f64 = env("H", 2e-6);
        let model = Model::new(&scene);
        let settings = Settings {
            rtol: 1e-6,
            atol_concentration: 1e-9,
            atol_potential: 1e-9,
            end_time: t0,
            output_times: vec![],
            max_steps: 1_000_000,
            explicit_dt: None,
            start: None,
            linear_solver: LinearSolver::Banded,
        };
        let (y0, open, _) = integrate(&model, &settings, &mut |_| Control::Continue).unwrap();
        let (plain, plain_d) = newton(&model, &y0, &open, h, false, 4);
        let (exact, exact_d) = newton(&model, &y0, &open, h, true, 4);
        eprintln!("plain LU: corrections {plain:?}, charge defects {plain_d:?}");
        eprintln!("charge-exact: corrections {exact:?}, charge defects of the LU {exact_d:?}");
        assert!(exact[2] < 1e-4 * exact[0], "charge-exact corrections converge fast: {exact:?}");
        assert!(plain[2] > 1e-3 * plain[0], "plain LU corrections converge slowly at 1e5 cells: {plain:?}");
        assert!(plain_d[0].abs() > 1e-8, "the plain LU's first correction changes the charge: {plain_d:?}");
    }
}
