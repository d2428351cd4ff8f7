//! The hypoelastic-plastic law with a chemical strain rate of the battery thesis (Ch. 7.3):
//! lithiated silicon. Written in the unrotated frame of the polar decomposition F = R U
//! ((7.26)-(7.29)): sigma_bar = R^T sigma R, d_bar = R^T d R with d = sym(L), the rate split
//! d_bar = d_bar^e + d_bar^p + eta c_dot I ((7.25), (7.33)), the elastic rate
//! 2 G dev(d^e) + 3 K vol(d^e) ((7.36)-(7.38)) and J2 plasticity with linear isotropic hardening,
//! sqrt(3/2 s:s) - (sigma_Y + H eps_p) <= 0 ((7.35) with the square root the print drops, and
//! the plastic modulus called H, not the print's "K"), by radial return:
//!
//! - trial s_tr = s^n + 2 G dev(de - eta dc I) and q_tr = sqrt(3/2 s_tr:s_tr), with
//!   de = dt d_bar the strain increment and dc the concentration change over the step;
//! - if q_tr > sigma_Y + H eps_p: d_eps_p = (q_tr - sigma_Y - H eps_p) / (3 G + H),
//!   s = s_tr (1 - 3 G d_eps_p / q_tr), eps_p += d_eps_p;
//! - p^{n+1} = p^n - K tr(de - eta dc I), then sigma = R sigma_bar R^T (7.39).
//!
//! A rigid rotation has d = 0, so it leaves sigma_bar unchanged: the law is objective by
//! construction. The exact answers the unit tests check are derived in continuum/README.md
//! ("Silicon lithiation").

use crate::closure::{Closure, ClosureBatch, ClosureError};
use crate::kinematics;
use crate::par::CHUNK;
use crate::tensor::{self, IDENTITY, Mat3, ZERO};
use rayon::prelude::*;

/// Parameters of the law (SI: Pa, kg/m^3). [`ChemoPlastic::SILICON`] holds the thesis's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChemoPlastic {
    /// Bulk modulus K (Pa).
    pub bulk_modulus: f64,
    /// Shear modulus G (Pa).
    pub shear_modulus: f64,
    /// Initial yield stress sigma_Y (Pa); infinite for an elastic law.
    pub yield_stress: f64,
    /// Linear isotropic hardening modulus H (Pa); 0 is perfect plasticity.
    pub hardening_modulus: f64,
    /// Chemical expansion coefficient eta of d^c = eta c_dot I (per unit normalised
    /// concentration).
    pub chemical_expansion: f64,
    /// Reference density (kg/m^3), for the wave speed of a body with no points yet.
    pub density0: f64,
}

impl ChemoPlastic {
    /// Lithiated silicon, battery thesis Ch. 7.3: K 67 GPa, G 31 GPa, sigma_Y 1.4 GPa,
    /// H 1.15 GPa, eta 0.56, rho 2330 kg/m^3.
    pub const SILICON: ChemoPlastic = ChemoPlastic {
        bulk_modulus: 67e9,
        shear_modulus: 31e9,
        yield_stress: 1.4e9,
        hardening_modulus: 1.15e9,
        chemical_expansion: 0.56,
        density0: 2330.0,
    };

    /// Young's modulus E = 9 K G / (3 K + G) (Pa).
    pub fn youngs_modulus(&self) -> f64 {
        9.0 * self.bulk_modulus * self.shear_modulus / (3.0 * self.bulk_modulus + self.shear_modulus)
    }

    /// Poisson's ratio (3 K - 2 G) / (2 (3 K + G)).
    pub fn poisson_ratio(&self) -> f64 {
        (3.0 * self.bulk_modulus - 2.0 * self.shear_modulus) / (2.0 * (3.0 * self.bulk_modulus + self.shear_modulus))
    }

    /// Biaxial modulus M = E / (1 - nu) (Pa): a film's in-plane stress per in-plane strain.
    pub fn biaxial_modulus(&self) -> f64 {
        self.youngs_modulus() / (1.0 - self.poisson_ratio())
    }

    /// One step in the unrotated frame from (sigma_bar, eps_p) with strain increment `de`
    /// (dt d_bar) and concentration change `dc`: (sigma_bar, eps_p) at the end of the step.
    pub fn update_unrotated(&self, sigma_bar: &Mat3, plastic_strain: f64, de: &Mat3, dc: f64) -> (Mat3, f64) {
        let (k, g, h) = (self.bulk_modulus, self.shear_modulus, self.hardening_modulus);
        // Mechanical part of the increment: the chemical strain eta dc I taken out.
        let mut e = *de;
        for (i, row) in e.iter_mut().enumerate() {
            row[i] -= self.chemical_expansion * dc;
        }
        let tr_e = tensor::trace(&e);
        let p_old = -tensor::trace(sigma_bar) / 3.0;
        let mut s = *sigma_bar;
        for (i, row) in s.iter_mut().enumerate() {
            row[i] += p_old;
        }
        // Trial deviator s_tr = s + 2 G dev(e).
        for i in 0..3 {
            for j in 0..3 {
                let dev = e[i][j] - if i == j { tr_e / 3.0 } else { 0.0 };
                s[i][j] += 2.0 * g * dev;
            }
        }
        let q_tr = (1.5 * tensor::ddot(&s, &s)).sqrt();
        let yield_now = self.yield_stress + h * plastic_strain;
        let mut eps_p = plastic_strain;
        if q_tr > yield_now {
            let d_eps = (q_tr - yield_now) / (3.0 * g + h);
            let scale = 1.0 - 3.0 * g * d_eps / q_tr;
            for v in s.iter_mut().flatten() {
                *v *= scale;
            }
            eps_p += d_eps;
        }
        let p = p_old - k * tr_e;
        for (i, row) in s.iter_mut().enumerate() {
            row[i] -= p;
        }
        (s, eps_p)
    }
}

/// The law as a closure. The concentration rate of each point comes from the batch
/// ([`ClosureBatch::scalar_rate`]: empty means none), the equivalent plastic strain lives in
/// [`ClosureBatch::plastic_strain`].
#[derive(Debug, Clone)]
pub struct ChemoPlasticClosure {
    pub law: ChemoPlastic,
}

impl ChemoPlasticClosure {
    /// One point over `dt`: the start-of-step stress `sigma` (overwritten), the velocity
    /// gradient `l`, the end-of-step deformation gradient `f` (the solver's F = (I + dt L) F_old),
    /// the concentration rate and the plastic strain (updated).
    pub fn advance_point(&self, sigma: &mut Mat3, eps_p: &mut f64, l: &Mat3, f: &Mat3, c_rate: f64, dt: f64) -> Result<(), &'static str> {
        let inc = tensor::add_scaled(&IDENTITY, l, dt);
        let inc_inv = tensor::inverse(&inc).ok_or("the step's deformation increment is singular")?;
        let f_old = tensor::mul(&inc_inv, f);
        let f_mid = tensor::add_scaled(&tensor::add_scaled(&ZERO, &f_old, 0.5), f, 0.5);
        let r_old = kinematics::rotation(&f_old).ok_or("no polar decomposition at the start of the step")?;
        let r_mid = kinematics::rotation(&f_mid).ok_or("no polar decomposition at mid-step")?;
        let r_new = kinematics::rotation(f).ok_or("no polar decomposition at the end of the step")?;
        let sigma_bar = tensor::mul(&tensor::transpose(&r_old), &tensor::mul(sigma, &r_old));
        let d = tensor::sym(l);
        let d_bar = tensor::mul(&tensor::transpose(&r_mid), &tensor::mul(&d, &r_mid));
        let (sb, ep) = self.law.update_unrotated(&sigma_bar, *eps_p, &tensor::add_scaled(&ZERO, &d_bar, dt), c_rate * dt);
        *sigma = tensor::mul(&r_new, &tensor::mul(&sb, &tensor::transpose(&r_new)));
        *eps_p = ep;
        Ok(())
    }

    fn run(&self, b: ClosureBatch<'_>, dt: f64, initial: bool) -> Result<(), ClosureError> {
        let law = self.name();
        let ClosureBatch { first, vel_grad, def_grad, stress, scalar_rate, plastic_strain, .. } = b;
        let n = stress.len();
        let mut scratch = Vec::new();
        let eps: &mut [f64] = if plastic_strain.len() == n {
            plastic_strain
        } else {
            scratch.resize(n, 0.0);
            &mut scratch
        };
        let failed = stress
            .par_chunks_mut(CHUNK)
            .zip(eps.par_chunks_mut(CHUNK))
            .enumerate()
            .filter_map(|(c, (ss, es))| {
                ss.iter_mut()
                    .zip(es.iter_mut())
                    .enumerate()
                    .try_for_each(|(i, (s, e))| {
                        let k = c * CHUNK + i;
                        let (id, f) = (first + k, &def_grad[k]);
                        let j = tensor::det(f);
                        if !(j > 0.0) {
                            return Err(ClosureError::Inverted { point: id, law, jacobian: j });
                        }
                        if initial {
                            // The initial state: the small-strain stress of U - I in the unrotated
                            // frame (zero for an undeformed point), returned to the yield surface.
                            let (r, u) = kinematics::polar(f).ok_or(ClosureError::Inverted { point: id, law, jacobian: j })?;
                            let (sb, ep) = self.law.update_unrotated(&ZERO, 0.0, &tensor::add_scaled(&u, &IDENTITY, -1.0), 0.0);
                            *s = tensor::mul(&r, &tensor::mul(&sb, &tensor::transpose(&r)));
                            *e = ep;
                        } else {
                            let rate = scalar_rate.get(k).copied().unwrap_or(0.0);
                            self.advance_point(s, e, &vel_grad[k], f, rate, dt)
                                .map_err(|why| ClosureError::Other(format!("point {id}: {law} closure: {why}")))?;
                        }
                        if !tensor::is_finite(s) {
                            return Err(ClosureError::NonFinite { point: id, law, jacobian: j });
                        }
                        Ok(())
                    })
                    .err()
                    .map(|e| (c, e))
            })
            .min_by_key(|(c, _)| *c);
        failed.map_or(Ok(()), |(_, e)| Err(e))
    }
}

impl Closure for ChemoPlasticClosure {
    fn name(&self) -> &'static str {
        "hypoelastic-plastic"
    }
    fn wave_speed(&self, mass: &[f64], volume: &[f64]) -> f64 {
        let rho_min = mass.iter().zip(volume).map(|(m, v)| m / v).fold(self.law.density0, f64::min);
        ((self.law.bulk_modulus + 4.0 * self.law.shear_modulus / 3.0) / rho_min).sqrt()
    }
    fn initialize(&mut self, batch: ClosureBatch<'_>) -> Result<(), ClosureError> {
        self.run(batch, 0.0, true)
    }
    fn advance(&mut self, batch: ClosureBatch<'_>, dt: f64) -> Result<(), ClosureError> {
        self.run(batch, dt, false)
    }
    /// The step is a pure function of the start stress, the batch's plastic strain (in and
    /// out), its F, L and concentration rate: Newton may call it per residual. No analytic
    /// tangent (radial return): the implicit integrator uses the finite-difference Jacobian.
    fn repeatable(&self) -> bool {
        true
    }
}

/// The ramped start of a prescribed lithiation rate (`[lithiation] ramp_time`): the rate is
/// r s(t) with s(t) = (1 - cos(pi t / T)) / 2 for t < T and 1 after (continuous with its first
/// derivative at both ends, so the start launches no step in the acceleration). Returns the
/// integral of s from 0 to `t`, so the concentration added by time t is r times it exactly:
/// t / 2 - T sin(pi t / T) / (2 pi) up to T, T / 2 + (t - T) after. `ramp <= 0`: no ramp (t).
pub fn ramp_integral(t: f64, ramp: f64) -> f64 {
    if ramp <= 0.0 {
        return t;
    }
    if t >= ramp {
        return 0.5 * ramp + (t - ramp);
    }
    let t = t.max(0.0);
    0.5 * t - ramp * (std::f64::consts::PI * t / ramp).sin() / (2.0 * std::f64::consts::PI)
}

/// The mean of the ramp factor over the step [t, t + dt] (exact: the difference of
/// [`ramp_integral`]); 1 without a ramp or once it is over, bitwise.
pub fn ramp_factor(t: f64, dt: f64, ramp: f64) -> f64 {
    if ramp <= 0.0 || t >= ramp {
        return 1.0;
    }
    (ramp_integral(t + dt, ramp) - ramp_integral(t, ramp)) / dt
}

#[cfg(test)]
mod tests {

    use super::*;

    const SI: ChemoPlastic = ChemoPlastic::SILICON;

    fn diag(a: f64, b: f64, c: f64) -> Mat3 {
        [[a, 0.0, 0.0], [0.0, b, 0.0], [0.0, 0.0, c]]
    }

    #[test]
    fn the_derived_constants_of_silicon() {
        assert!((SI.youngs_modulus() / 1e9 - 80.5733).abs() < 1e-4, "{}", SI.youngs_modulus());
        assert!((SI.poisson_ratio() - 0.299569).abs() < 1e-6);
        assert!((SI.biaxial_modulus() / 1e9 - 115.03).abs() < 5e-3, "{}", SI.biaxial_modulus());
    }

    /// Free uniform lithiation: a point free to swell takes d = eta c_dot I, so its stress
    /// stays zero; with F integrated exactly (F = exp(eta c) I) J = exp(3 eta dc), and the
    /// solver's F <- (I + dt L) F approaches it at first order in the step.
    #[test]
    fn free_uniform_lithiation_is_stress_free_and_swells_by_exp_3_eta_dc() {
        let c = ChemoPlasticClosure { law: SI };
        let (dc_total, n) = (1.0, 20_000);
        let (dt, rate) = (1e-3, dc_total / (n as f64 * 1e-3));
        let l = diag(SI.chemical_expansion * rate, SI.chemical_expansion * rate, SI.chemical_expansion * rate);
        let (mut s, mut ep, mut f) = (ZERO, 0.0, IDENTITY);
        for _ in 0..n {
            f = tensor::mul(&tensor::add_scaled(&IDENTITY, &l, dt), &f);
            c.advance_point(&mut s, &mut ep, &l, &f, rate, dt).expect("regular");
            assert!(s.iter().flatten().all(|v| v.abs() < 1.0), "{s:?}");
        }
        assert_eq!(ep, 0.0);
        let exact = (3.0 * SI.chemical_expansion * dc_total).exp();
        assert!((exact - 5.366).abs() < 1e-3, "J(dc = 1) = {exact}");
        let j = tensor::det(&f);
        // (1 + x/n)^(3n) vs exp(3x): relative gap about 3 x^2 / (2 n).
        assert!(((j - exact) / exact).abs() < 2.0 * 3.0 * 0.56f64.powi(2) / (2.0 * n as f64), "J = {j}, exact {exact}");
    }

    /// Fully constrained: L = 0, so p = 3 K eta dc (112.56 GPa per unit c) and the deviator
    /// stays zero: no yield however large the pressure.
    #[test]
    fn fully_constrained_lithiation_builds_pure_pressure_3_k_eta_dc_without_yield() {
        let c = ChemoPlasticClosure { law: SI };
        let (mut s, mut ep) = (ZERO, 0.0);
        let (dt, rate) = (1e-3, 1.0);
        for _ in 0..500 {
            c.advance_point(&mut s, &mut ep, &ZERO, &IDENTITY, rate, dt).expect("regular");
        }
        let dc = 0.5;
        let p = -tensor::trace(&s) / 3.0;
        assert!((3.0 * SI.bulk_modulus * SI.chemical_expansion / 1e9 - 112.56).abs() < 1e-9);
        assert!(((p - 3.0 * SI.bulk_modulus * SI.chemical_expansion * dc) / p).abs() < 1e-12, "p = {p}");
        assert!(s[0][1] == 0.0 && (s[0][0] - s[2][2]).abs() < 1e-12 * p, "{s:?}");
        assert_eq!(ep, 0.0, "J2 ignores the pressure");
    }

    /// The out-of-plane strain increment that keeps sigma_zz = 0 (and, with `uniaxial`,
    /// sigma_yy = 0 too, by symmetry d_yy = d_zz) over one step: sigma_zz is piecewise linear
    /// in it, so the secant method lands on the root in a few iterations.
    fn free_faces(law: &ChemoPlastic, s: &Mat3, ep: f64, dxx: f64, dc: f64, uniaxial: bool) -> (Mat3, f64) {
        let at = |dz: f64| {
            let de = if uniaxial { diag(dxx, dz, dz) } else { diag(dxx, dxx, dz) };
            law.update_unrotated(s, ep, &de, dc)
        };
        let (mut a, mut b) = (0.0, 1e-4);
        let (mut fa, mut fb) = (at(a).0[2][2], at(b).0[2][2]);
        for _ in 0..50 {
            if fb.abs() < 1e-6 {
                break;
            }
            let c = b - fb * (b - a) / (fb - fa);
            (a, fa) = (b, fb);
            b = c;
            fb = at(b).0[2][2];
        }
        assert!(fb.abs() < 1e-6, "no free-face strain: sigma_zz = {fb}");
        at(b)
    }

    /// A film on a rigid substrate: in-plane strain zero, sigma_zz = 0. The in-plane stress
    /// follows -M eta dc to yield at dc = sigma_Y / (M eta) = 0.021733, then stays at
    /// -sigma_Y (perfect plasticity) or falls with slope -H M eta / (H + M / 2) = -1.2628 GPa
    /// per unit c (linear hardening).
    #[test]
    fn a_film_on_a_rigid_substrate_follows_the_derived_stress_path() {
        for hardening in [0.0, SI.hardening_modulus] {
            let law = ChemoPlastic { hardening_modulus: hardening, ..SI };
            let (m, eta) = (law.biaxial_modulus(), law.chemical_expansion);
            let yield_dc = law.yield_stress / (m * eta);
            assert!((yield_dc - 0.021733).abs() < 1e-6, "{yield_dc}");
            let slope = -hardening * m * eta / (hardening + m / 2.0);
            if hardening > 0.0 {
                assert!((slope / 1e9 + 1.2628).abs() < 1e-4, "{slope}");
            }
            let (mut s, mut ep, ddc) = (ZERO, 0.0, 1e-5);
            let mut first_yield = None;
            for k in 1..=20_000 {
                let dc = k as f64 * ddc;
                (s, ep) = free_faces(&law, &s, ep, 0.0, ddc, false);
                if first_yield.is_none() && ep > 0.0 {
                    first_yield = Some(dc);
                }
                let exact = if dc <= yield_dc { -m * eta * dc } else { -law.yield_stress + slope * (dc - yield_dc) };
                assert!((s[0][0] - exact).abs() < 1e-3 * law.yield_stress, "H = {hardening}, dc = {dc}: {} vs {exact}", s[0][0]);
                assert!((s[1][1] - s[0][0]).abs() < 1e-9 * law.yield_stress);
            }
            let y = first_yield.expect("the film yields by dc = 0.2");
            assert!((y - yield_dc).abs() <= ddc, "yield at {y}, derived {yield_dc}");
        }
    }

    /// A single point in uniaxial stress: after yield the tangent d sigma / d eps is
    /// E H / (E + H) = 1.134 GPa.
    #[test]
    fn the_uniaxial_tangent_after_yield_is_e_h_over_e_plus_h() {
        let e_mod = SI.youngs_modulus();
        let tangent = e_mod * SI.hardening_modulus / (e_mod + SI.hardening_modulus);
        assert!((tangent / 1e9 - 1.1338).abs() < 1e-4, "{tangent}");
        let (mut s, mut ep, de) = (ZERO, 0.0, 1e-6);
        let mut path = Vec::new();
        for k in 1..=40_000 {
            (s, ep) = free_faces(&SI, &s, ep, de, 0.0, true);
            path.push((k as f64 * de, s[0][0]));
        }
        let yield_strain = SI.yield_stress / e_mod;
        assert!(ep > 0.0 && path.last().expect("steps").0 > 2.0 * yield_strain);
        let (a, b) = (path[30_000], path[39_999]);
        let measured = (b.1 - a.1) / (b.0 - a.0);
        assert!(((measured - tangent) / tangent).abs() < 1e-6, "tangent {measured} vs {tangent}");
        // Elastic part: E exactly.
        assert!(((path[99].1 / path[99].0 - e_mod) / e_mod).abs() < 1e-9);
    }

    /// A rigid rotation (L = W skew) of a pre-stressed, plastically strained point: the
    /// unrotated stress R^T sigma R and the plastic strain do not change.
    #[test]
    fn a_rigid_rotation_leaves_the_unrotated_stress_unchanged() {
        let c = ChemoPlasticClosure { law: SI };
        // Inside the yield surface (q = 0.94 GPa < sigma_Y + H eps_p), so the step is elastic.
        let sigma_bar: Mat3 = [[-0.6e9, 0.15e9, 0.05e9], [0.15e9, 0.2e9, -0.1e9], [0.05e9, -0.1e9, 0.35e9]];
        let (mut s, mut ep) = (sigma_bar, 0.01);
        let w = 2.0; // rad/s about an oblique axis
        let axis = [1.0 / 3f64.sqrt(); 3];
        let l: Mat3 = [[0.0, -w * axis[2], w * axis[1]], [w * axis[2], 0.0, -w * axis[0]], [-w * axis[1], w * axis[0], 0.0]];
        let (mut f, dt) = (IDENTITY, 1e-3);
        for _ in 0..1000 {
            f = tensor::mul(&tensor::add_scaled(&IDENTITY, &l, dt), &f);
            c.advance_point(&mut s, &mut ep, &l, &f, 0.0, dt).expect("regular");
        }
        let r = kinematics::rotation(&f).expect("regular");
        let back = tensor::mul(&tensor::transpose(&r), &tensor::mul(&s, &r));
        for i in 0..3 {
            for j in 0..3 {
                assert!((back[i][j] - sigma_bar[i][j]).abs() < 1e-6 * 1e9, "{back:?}");
            }
        }
        assert_eq!(ep, 0.01);
        // The stress itself did rotate (by about 2 rad).
        assert!((s[0][0] - sigma_bar[0][0]).abs() > 0.05e9, "{s:?}");
    }

    #[test]
    fn the_ramp_integrates_to_the_rate_times_its_integral() {
        let ramp = 2.0;
        assert_eq!(ramp_factor(0.3, 0.1, 0.0), 1.0);
        assert_eq!(ramp_factor(2.0, 0.1, ramp), 1.0);
        assert_eq!(ramp_integral(1.7, 0.0), 1.7);
        // Summed step factors reproduce the integral at any step size.
        let dt = 0.013;
        let (mut t, mut sum) = (0.0, 0.0);
        for _ in 0..300 {
            sum += dt * ramp_factor(t, dt, ramp);
            t += dt;
        }
        assert!((sum - ramp_integral(t, ramp)).abs() < 1e-12, "{sum} vs {}", ramp_integral(t, ramp));
        assert!((ramp_integral(ramp, ramp) - 1.0).abs() < 1e-15 && (ramp_integral(3.0, ramp) - 2.0).abs() < 1e-15);
        // s(t) = (1 - cos(pi t / T)) / 2: midpoint 1/2, slope 0 at both ends.
        let s = |t: f64| (ramp_integral(t + 1e-6, ramp) - ramp_integral(t - 1e-6, ramp)) / 2e-6;
        assert!((s(1.0) - 0.5).abs() < 1e-9 && s(1e-3).abs() < 1e-5 && (s(ramp - 1e-3) - 1.0).abs() < 1e-5);
    }
}
