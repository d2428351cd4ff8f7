//! The closure seam: how a body's points get their stress.
//!
//! A closure evaluates a *batch* of points (all points of one body) at once from their
//! velocity gradients and the time step, so an MD closure can ship a whole step's work to its
//! workers in one go. Constitutive laws implement it directly. Stresses are Cauchy, in Pa,
//! tension positive.

use crate::par::CHUNK;
use crate::tensor::{self, IDENTITY, Mat3};
use rayon::prelude::*;

/// The points of one body, handed to its closure.
pub struct ClosureBatch<'a> {
    /// The continuum step this batch advances to (1 for the first step; 0 for `initialize`).
    pub step: u64,
    /// Global index of the first point of the batch (point `k` of the batch has id `first + k`).
    pub first: usize,
    /// Velocity gradient over the step, L_ij = dv_i/dx_j (1/s).
    pub vel_grad: &'a [Mat3],
    /// Deformation gradient at the end of the step.
    pub def_grad: &'a [Mat3],
    pub mass: &'a [f64],
    /// Current volume (end of the step).
    pub volume: &'a [f64],
    /// In: stress at the start of the step. Out: stress at the end (Pa, tension positive).
    pub stress: &'a mut [Mat3],
    /// Rate of the scalar field the points carry (normalised concentration per second) over
    /// the step; empty when the scene has none (every rate zero).
    pub scalar_rate: &'a [f64],
    /// Equivalent plastic strain, in and out (plastic laws); empty when no law of the scene is
    /// plastic.
    pub plastic_strain: &'a mut [f64],
    /// Artificial viscous stress of the previous step (Pa, tension positive; the solver
    /// computes this step's after the closures), for closures that take the viscous work as
    /// heat; empty where the integrator has none.
    pub visc_stress: &'a [Mat3],
}

/// One point of a batch, as a pointwise law reads it.
pub struct PointIn<'a> {
    /// Global point index.
    pub id: usize,
    pub vel_grad: &'a Mat3,
    pub def_grad: &'a Mat3,
    pub mass: f64,
    pub volume: f64,
}

impl ClosureBatch<'_> {
    /// Updates every point's stress with `f` (a law without state shared between points), in
    /// parallel over fixed chunks, so the result is the same for any thread count. On failure
    /// the error of the lowest point is returned.
    pub fn for_each_point<F>(self, f: F) -> Result<(), ClosureError>
    where
        F: Fn(PointIn<'_>, &mut Mat3) -> Result<(), ClosureError> + Sync,
    {
        let ClosureBatch { first, vel_grad, def_grad, mass, volume, stress, .. } = self;
        let failed = stress
            .par_chunks_mut(CHUNK)
            .enumerate()
            .filter_map(|(c, chunk)| {
                chunk
                    .iter_mut()
                    .enumerate()
                    .try_for_each(|(i, s)| {
                        let k = c * CHUNK + i;
                        f(PointIn { id: first + k, vel_grad: &vel_grad[k], def_grad: &def_grad[k], mass: mass[k], volume: volume[k] }, s)
                    })
                    .err()
                    .map(|e| (c, e))
            })
            .min_by_key(|(c, _)| *c);
        failed.map_or(Ok(()), |(_, e)| Err(e))
    }
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ClosureError {
    #[error(
        "point {point}: {law} closure produced a non-finite stress (J = {jacobian:e}); the time step is probably too large or the point was crushed"
    )]
    NonFinite { point: usize, law: &'static str, jacobian: f64 },
    #[error(
        "point {point}: {law} closure needs a positive volume ratio, got J = {jacobian:e} (the point was inverted: reduce the time step or add particles per cell)"
    )]
    Inverted { point: usize, law: &'static str, jacobian: f64 },
    /// The engine behind a closure failed (an MD pool, a worker, a box): what the closure was
    /// doing; the engine's own error is the source.
    #[error("{context}")]
    Engine {
        context: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    #[error("{0}")]
    Other(String),
}

/// The message of an error and its chain of sources, joined by `: ` (as `{:#}` of an
/// `anyhow::Error` prints it); a source whose message its parent's already ends with is not
/// repeated. How `mscale` prints a failure, and how a closure's failure crosses MPI ranks
/// (`solver/ranks.rs`), so every rank reports it in the same words.
pub fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let m = c.to_string();
        if !out.ends_with(&m) {
            out.push_str(": ");
            out.push_str(&m);
        }
        cause = c.source();
    }
    out
}

pub trait Closure: Send {
    /// Name as written in scene files.
    fn name(&self) -> &'static str;
    /// Largest longitudinal wave speed over the points (m/s), for the CFL time step. Over a
    /// union of points it must be the largest of its values over the parts (a maximum over
    /// points, or one value for all): over MPI ranks each rank gives it over its own runs of
    /// points and the step takes the largest (`solver/ranks.rs`).
    fn wave_speed(&self, mass: &[f64], volume: &[f64]) -> f64;
    /// Called for every body of a step before any body's `initialize` or `advance` of that
    /// step (same batch, same `dt`): closures that share a resource (the MD closures of several
    /// bodies share one worker pool) register their work here, and the first of them to be
    /// advanced sends all of it at once. The default does nothing.
    fn prepare(&mut self, _batch: &ClosureBatch<'_>, _dt: f64) -> Result<(), ClosureError> {
        Ok(())
    }
    /// Stress of the initial state (the points carry their initial deformation gradient).
    fn initialize(&mut self, batch: ClosureBatch<'_>) -> Result<(), ClosureError> {
        self.advance(batch, 0.0)
    }
    /// Advances every point of the batch over `dt` (s) and writes its stress.
    fn advance(&mut self, batch: ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError>;
    /// Whether `advance` is a pure function of the batch (start stress in `stress`, velocity
    /// gradient, deformation gradient, mass, volume) and `dt`, keeping no state between calls,
    /// so the implicit integrator may call it once per Newton residual and keep only the last
    /// call (the implicit-trapezoidal integrator). The default (false) is
    /// right for closures with history (MD boxes), which the implicit integrator refuses.
    fn repeatable(&self) -> bool {
        false
    }
    /// Whether the closure's work must be done once for all MPI ranks (a closure holding
    /// state no rank may duplicate: the MD closure's boxes, each computed once). Over more than
    /// one rank (continuum/README.md "MPI") only rank 0 calls `prepare`, `initialize` and
    /// `advance` of such a closure, over every point of its body, and the solver gives the
    /// other ranks the stresses (and plastic strains) it wrote; their copy of the closure is
    /// never called. One process: no effect. The default (false): every rank calls its own copy.
    fn computed_once(&self) -> bool {
        false
    }
    /// Whether [`Closure::tangent`] gives the material tangent (the analytic Jacobian of the
    /// implicit integrator needs it; without it only the finite-difference Jacobian works).
    fn has_tangent(&self) -> bool {
        false
    }
    /// Material tangent of one point: the derivative of the end-of-step Cauchy stress that
    /// `advance` returns with respect to the step's displacement gradient H = F F_n^-1 - I
    /// (so F = (I + H) F_n and the velocity gradient passed to `advance` is H / dt). `None`
    /// when the closure has no tangent.
    fn tangent(&self, _point: &TangentIn<'_>) -> Option<Tangent> {
        None
    }
}

/// d sigma_ij / d H_kl, indexed `[i][j][k][l]` (Pa).
pub type Tangent = [[[[f64; 3]; 3]; 3]; 3];

/// What a tangent may depend on, for one point.
pub struct TangentIn<'a> {
    /// Stress at the start of the step.
    pub start_stress: &'a Mat3,
    /// Deformation gradient at the start of the step, F_n.
    pub start_def_grad: &'a Mat3,
    /// The step's displacement gradient H (F = (I + H) F_n).
    pub increment: &'a Mat3,
    /// Deformation gradient at the end of the step.
    pub def_grad: &'a Mat3,
    /// Stress `advance` returned for this H.
    pub stress: &'a Mat3,
    pub mass: f64,
    /// Volume at the end of the step.
    pub volume: f64,
}

fn rel_inverse(p: &TangentIn<'_>) -> Mat3 {
    tensor::inverse(&tensor::add_scaled(&IDENTITY, p.increment, 1.0)).unwrap_or(IDENTITY)
}

/// Isothermal ideal gas: p = c^2 rho.
#[derive(Debug, Clone)]
pub struct IdealGasIsothermal {
    /// Isothermal sound speed c (m/s).
    pub sound_speed: f64,
}

impl Closure for IdealGasIsothermal {
    fn name(&self) -> &'static str {
        "ideal-gas-isothermal"
    }
    fn wave_speed(&self, _: &[f64], _: &[f64]) -> f64 {
        self.sound_speed
    }
    fn advance(&mut self, b: ClosureBatch<'_>, _dt: f64) -> Result<(), ClosureError> {
        let (c2, law) = (self.sound_speed * self.sound_speed, self.name());
        b.for_each_point(|p, s| {
            let rho = p.mass / p.volume;
            if !(rho.is_finite() && rho > 0.0) {
                return Err(ClosureError::Inverted { point: p.id, law, jacobian: tensor::det(p.def_grad) });
            }
            *s = tensor::add_scaled(&tensor::ZERO, &IDENTITY, -c2 * rho);
            Ok(())
        })
    }
    fn repeatable(&self) -> bool {
        true
    }
    fn has_tangent(&self) -> bool {
        true
    }
    /// sigma = -c^2 m / V I with V = det(I + H) V_n: d sigma_ij / d H_kl = c^2 rho delta_ij (I + H)^-1_lk.
    fn tangent(&self, p: &TangentIn<'_>) -> Option<Tangent> {
        let fi = rel_inverse(p);
        let k = self.sound_speed * self.sound_speed * p.mass / p.volume;
        let mut t = [[[[0.0; 3]; 3]; 3]; 3];
        for (i, ti) in t.iter_mut().enumerate() {
            for (k_, tk) in ti[i].iter_mut().enumerate() {
                for (l, v) in tk.iter_mut().enumerate() {
                    *v = k * fi[l][k_];
                }
            }
        }
        Some(t)
    }
}

/// Lame constants from Young's modulus and Poisson's ratio.
pub fn lame(youngs: f64, poisson: f64) -> (f64, f64) {
    let lambda = youngs * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson));
    let mu = youngs / (2.0 * (1.0 + poisson));
    (lambda, mu)
}

/// Linear elasticity in rate form with the Jaumann rate: sigma' = lambda tr(D) I + 2 mu D.
#[derive(Debug, Clone)]
pub struct LinearElastic {
    pub youngs_modulus: f64,
    pub poisson_ratio: f64,
    pub density0: f64,
}

impl LinearElastic {
    fn stress_rate(&self, d: &Mat3) -> Mat3 {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let mut s = tensor::add_scaled(&tensor::ZERO, d, 2.0 * mu);
        let tr = tensor::trace(d);
        for (i, row) in s.iter_mut().enumerate() {
            row[i] += lambda * tr;
        }
        s
    }
}

impl Closure for LinearElastic {
    fn name(&self) -> &'static str {
        "linear-elastic"
    }
    fn wave_speed(&self, mass: &[f64], volume: &[f64]) -> f64 {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let rho_min = mass.iter().zip(volume).map(|(m, v)| m / v).fold(self.density0, f64::min);
        ((lambda + 2.0 * mu) / rho_min).sqrt()
    }
    fn initialize(&mut self, b: ClosureBatch<'_>) -> Result<(), ClosureError> {
        // Small-strain stress of the initial strain F - I.
        b.for_each_point(|p, s| {
            *s = self.stress_rate(&tensor::sym(&tensor::add_scaled(p.def_grad, &IDENTITY, -1.0)));
            Ok(())
        })
    }
    fn advance(&mut self, b: ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError> {
        let law = self.name();
        b.for_each_point(|p, out| {
            let l = p.vel_grad;
            let d = tensor::sym(l);
            let w = tensor::add_scaled(l, &tensor::transpose(l), -1.0);
            let w = tensor::add_scaled(&tensor::ZERO, &w, 0.5);
            let s = *out;
            // Jaumann: sigma_dot = C:D + W sigma - sigma W.
            let rot = tensor::add_scaled(&tensor::mul(&w, &s), &tensor::mul(&s, &w), -1.0);
            let rate = tensor::add_scaled(&self.stress_rate(&d), &rot, 1.0);
            *out = tensor::add_scaled(&s, &rate, dt);
            if !tensor::is_finite(out) {
                return Err(ClosureError::NonFinite { point: p.id, law, jacobian: tensor::det(p.def_grad) });
            }
            Ok(())
        })
    }
    fn repeatable(&self) -> bool {
        true
    }
    fn has_tangent(&self) -> bool {
        true
    }
    /// `advance` with L = H / dt is sigma = sigma_n + C : sym(H) + W sigma_n - sigma_n W,
    /// W = skew(H): linear in H, so the tangent is C plus the Jaumann terms
    /// (delta_ik sigma_lj - delta_il sigma_kj - sigma_ik delta_jl + sigma_il delta_jk) / 2.
    fn tangent(&self, p: &TangentIn<'_>) -> Option<Tangent> {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let s = p.start_stress;
        let d = |a: usize, b: usize| if a == b { 1.0 } else { 0.0 };
        let mut t = [[[[0.0; 3]; 3]; 3]; 3];
        for (i, ti) in t.iter_mut().enumerate() {
            for (j, tj) in ti.iter_mut().enumerate() {
                for (k, tk) in tj.iter_mut().enumerate() {
                    for (l, v) in tk.iter_mut().enumerate() {
                        *v = lambda * d(i, j) * d(k, l)
                            + mu * (d(i, k) * d(j, l) + d(i, l) * d(j, k))
                            + 0.5 * (d(i, k) * s[l][j] - d(i, l) * s[k][j] - s[i][k] * d(j, l) + s[i][l] * d(j, k));
                    }
                }
            }
        }
        Some(t)
    }
}

/// Compressible neo-Hookean: sigma = mu/J (F F^T - I) + lambda ln(J)/J I.
#[derive(Debug, Clone)]
pub struct NeoHookean {
    pub youngs_modulus: f64,
    pub poisson_ratio: f64,
    pub density0: f64,
}

impl Closure for NeoHookean {
    fn name(&self) -> &'static str {
        "neo-hookean"
    }
    fn wave_speed(&self, mass: &[f64], volume: &[f64]) -> f64 {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let rho_min = mass.iter().zip(volume).map(|(m, v)| m / v).fold(self.density0, f64::min);
        ((lambda + 2.0 * mu) / rho_min).sqrt()
    }
    fn advance(&mut self, b: ClosureBatch<'_>, _dt: f64) -> Result<(), ClosureError> {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let law = self.name();
        b.for_each_point(|p, out| {
            let f = p.def_grad;
            let j = tensor::det(f);
            if !(j > 0.0) {
                return Err(ClosureError::Inverted { point: p.id, law, jacobian: j });
            }
            let bb = tensor::mul(f, &tensor::transpose(f));
            let mut s = tensor::add_scaled(&tensor::add_scaled(&bb, &IDENTITY, -1.0), &tensor::ZERO, 0.0);
            for row in s.iter_mut() {
                for v in row.iter_mut() {
                    *v *= mu / j;
                }
            }
            for (i, row) in s.iter_mut().enumerate() {
                row[i] += lambda * j.ln() / j;
            }
            *out = s;
            Ok(())
        })
    }
    fn repeatable(&self) -> bool {
        true
    }
    fn has_tangent(&self) -> bool {
        true
    }
    /// With F = (I + H) F_n, B = F F^T: d sigma_ij / d H_kl =
    /// [-mu/J (B - I)_ij + lambda (1 - ln J)/J delta_ij] (I + H)^-1_lk
    /// + mu/J (delta_ik (F F_n^T)_jl + (F F_n^T)_il delta_jk).
    fn tangent(&self, p: &TangentIn<'_>) -> Option<Tangent> {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let f = p.def_grad;
        let j = tensor::det(f);
        if !(j > 0.0) {
            return None;
        }
        let fi = rel_inverse(p);
        let b = tensor::mul(f, &tensor::transpose(f));
        let ffn = tensor::mul(f, &tensor::transpose(p.start_def_grad));
        let d = |a: usize, c: usize| if a == c { 1.0 } else { 0.0 };
        let mut t = [[[[0.0; 3]; 3]; 3]; 3];
        for (i, ti) in t.iter_mut().enumerate() {
            for (jj, tj) in ti.iter_mut().enumerate() {
                let vol = -mu / j * (b[i][jj] - d(i, jj)) + lambda * (1.0 - j.ln()) / j * d(i, jj);
                for (k, tk) in tj.iter_mut().enumerate() {
                    for (l, v) in tk.iter_mut().enumerate() {
                        *v = vol * fi[l][k] + mu / j * (d(i, k) * ffn[jj][l] + ffn[i][l] * d(jj, k));
                    }
                }
            }
        }
        Some(t)
    }
}

/// Linear elasticity in the displacement gradient, written for the first Piola-Kirchhoff
/// stress: P = lambda tr(F - I) I + mu ((F - I) + (F - I)^T), sigma = P F^T / J. In 1D
/// (uniaxial strain, J = F) sigma = P = (lambda + 2 mu)(F - 1): with nu = 0 this is the battery
/// thesis's bar law sigma = P = E (F - 1) (B 4.93, rate E l F of (4.95)) and Gong's linearised
/// model (7.4). It is not frame-indifferent (a rigid rotation stresses it): meant for the
/// small-strain reference problems (the vibrating bar, the stability bound), not for general
/// scenes.
#[derive(Debug, Clone)]
pub struct LinearPiola {
    pub youngs_modulus: f64,
    pub poisson_ratio: f64,
    pub density0: f64,
}

impl LinearPiola {
    /// The first Piola-Kirchhoff stress of F (Pa).
    pub fn piola(&self, f: &Mat3) -> Mat3 {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let e = tensor::add_scaled(f, &IDENTITY, -1.0);
        let mut p = tensor::add_scaled(&tensor::add_scaled(&tensor::ZERO, &e, mu), &tensor::transpose(&e), mu);
        let tr = tensor::trace(&e);
        for (i, row) in p.iter_mut().enumerate() {
            row[i] += lambda * tr;
        }
        p
    }
}

impl Closure for LinearPiola {
    fn name(&self) -> &'static str {
        "linear-piola"
    }
    /// The Lagrangian speed sqrt((lambda + 2 mu) / rho0) (dP/dF is constant) times the largest
    /// stretch J of the points (the Eulerian speed of a 1D wave is F c_L).
    fn wave_speed(&self, mass: &[f64], volume: &[f64]) -> f64 {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let j_max = mass.iter().zip(volume).map(|(m, v)| self.density0 * v / m).fold(1.0, f64::max);
        ((lambda + 2.0 * mu) / self.density0).sqrt() * j_max
    }
    fn advance(&mut self, b: ClosureBatch<'_>, _dt: f64) -> Result<(), ClosureError> {
        let law = self.name();
        b.for_each_point(|p, out| {
            let f = p.def_grad;
            let j = tensor::det(f);
            if !(j > 0.0) {
                return Err(ClosureError::Inverted { point: p.id, law, jacobian: j });
            }
            let s = tensor::mul(&self.piola(f), &tensor::transpose(f));
            *out = tensor::add_scaled(&tensor::ZERO, &s, 1.0 / j);
            Ok(())
        })
    }
    fn repeatable(&self) -> bool {
        true
    }
    fn has_tangent(&self) -> bool {
        true
    }
    /// With F = (I + H) F_n and sigma = P F^T / J: d sigma_ij / d H_kl =
    /// [lambda (F_n)_lk F_ji + mu (delta_ik (F F_n^T)_jl + (F_n)_li F_jk)
    ///  + delta_jk (P F_n^T)_il] / J - sigma_ij (I + H)^-1_lk.
    fn tangent(&self, p: &TangentIn<'_>) -> Option<Tangent> {
        let (lambda, mu) = lame(self.youngs_modulus, self.poisson_ratio);
        let (f, fnn) = (p.def_grad, p.start_def_grad);
        let j = tensor::det(f);
        if !(j > 0.0) {
            return None;
        }
        let fi = rel_inverse(p);
        let sigma = tensor::add_scaled(&tensor::ZERO, &tensor::mul(&self.piola(f), &tensor::transpose(f)), 1.0 / j);
        let ffn = tensor::mul(f, &tensor::transpose(fnn));
        let pfn = tensor::mul(&self.piola(f), &tensor::transpose(fnn));
        let d = |a: usize, c: usize| if a == c { 1.0 } else { 0.0 };
        let mut t = [[[[0.0; 3]; 3]; 3]; 3];
        for (i, ti) in t.iter_mut().enumerate() {
            for (jj, tj) in ti.iter_mut().enumerate() {
                for (k, tk) in tj.iter_mut().enumerate() {
                    for (l, v) in tk.iter_mut().enumerate() {
                        let dp = lambda * fnn[l][k] * f[jj][i] + mu * (d(i, k) * ffn[jj][l] + fnn[l][i] * f[jj][k]);
                        *v = (dp + d(jj, k) * pfn[i][l]) / j - sigma[i][jj] * fi[l][k];
                    }
                }
            }
        }
        Some(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stress_of(law: &LinearPiola, f: &Mat3) -> Mat3 {
        let mut p = law.piola(f);
        p = tensor::mul(&p, &tensor::transpose(f));
        tensor::add_scaled(&tensor::ZERO, &p, 1.0 / tensor::det(f))
    }

    #[test]
    fn linear_piola_is_the_bar_law_in_1d_and_its_tangent_matches_a_difference() {
        let law = LinearPiola { youngs_modulus: 1e3, poisson_ratio: 0.0, density0: 1.0 };
        let mut f = IDENTITY;
        f[0][0] = 1.02;
        // sigma = P = E (F - 1) along the bar (B 4.93).
        assert!((stress_of(&law, &f)[0][0] - 1e3 * 0.02).abs() < 1e-12);
        let law = LinearPiola { youngs_modulus: 2e3, poisson_ratio: 0.3, density0: 1.0 };
        let fnn = [[1.03, 0.02, -0.01], [0.01, 0.98, 0.03], [-0.02, 0.01, 1.01]];
        let h = [[0.01, -0.004, 0.002], [0.003, -0.006, 0.001], [0.002, 0.005, 0.004]];
        let f = tensor::mul(&tensor::add_scaled(&IDENTITY, &h, 1.0), &fnn);
        let s = stress_of(&law, &f);
        let t = law
            .tangent(&TangentIn {
                start_stress: &tensor::ZERO,
                start_def_grad: &fnn,
                increment: &h,
                def_grad: &f,
                stress: &s,
                mass: 1.0,
                volume: tensor::det(&f),
            })
            .unwrap();
        let eps = 1e-6;
        for k in 0..3 {
            for l in 0..3 {
                let mut hp = h;
                hp[k][l] += eps;
                let mut hm = h;
                hm[k][l] -= eps;
                let sp = stress_of(&law, &tensor::mul(&tensor::add_scaled(&IDENTITY, &hp, 1.0), &fnn));
                let sm = stress_of(&law, &tensor::mul(&tensor::add_scaled(&IDENTITY, &hm, 1.0), &fnn));
                for i in 0..3 {
                    for j in 0..3 {
                        let fd = (sp[i][j] - sm[i][j]) / (2.0 * eps);
                        assert!((t[i][j][k][l] - fd).abs() < 1e-5 * 2e3, "[{i}][{j}][{k}][{l}]: {} vs {fd}", t[i][j][k][l]);
                    }
                }
            }
        }
    }
}
