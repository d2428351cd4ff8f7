//! The closed forms of the Debye-screening test: an electrolyte with fixed anions n0 and mobile
//! cations in equilibrium with a bulk at phi = 0, held at phi(0) = phi_s.
//!
//! Zero cation flux gives p = n0 exp(-phi/V_T) (V_T = kT/e), so Poisson reads
//! phi'' = (e n0/(eps_r eps0)) (1 - exp(-phi/V_T)). Linearised: phi = phi_s exp(-x/lambda),
//! lambda^2 = eps_r eps0 kT/(e^2 n0). Exactly (first integral, u = phi/V_T,
//! F(u) = u + e^-u - 1): x(u) = lambda [ln(u_s/u) + int_u^u_s (1/sqrt(2F(w)) - 1/w) dw],
//! whose integrand is smooth (-> 1/6 at w -> 0), so 5-point Gauss-Legendre is exact to
//! round-off for u_s << 1; phi(x) follows by Newton on x(u).

use crate::model::{E_CHARGE, EPS0, K_B};

/// The Debye length (nm) of concentration n0 (1/nm^3).
pub fn debye_length(eps_r: f64, temperature_k: f64, n0: f64) -> f64 {
    (eps_r * EPS0 * K_B * temperature_k / (E_CHARGE * E_CHARGE * n0)).sqrt()
}

/// F(w) = w + exp(-w) - 1, by its series where the direct form cancels.
fn f_of(w: f64) -> f64 {
    if w.abs() < 1e-2 {
        let w2 = w * w;
        w2 * (0.5 - w / 6.0 + w2 / 24.0 - w2 * w / 120.0 + w2 * w2 / 720.0)
    } else {
        w + (-w).exp() - 1.0
    }
}

fn correction(w: f64) -> f64 {
    1.0 / (2.0 * f_of(w)).sqrt() - 1.0 / w
}

const GL5: [(f64, f64); 5] = [
    (0.0, 0.568_888_888_888_888_9),
    (-0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (-0.906_179_845_938_664, 0.236_926_885_056_189_1),
    (0.906_179_845_938_664, 0.236_926_885_056_189_1),
];

/// The exact (nonlinear) screening profile.
#[derive(Debug, Clone, Copy)]
pub struct Screening {
    pub lambda: f64,
    pub vt: f64,
    pub phi_s: f64,
}

impl Screening {
    pub fn new(eps_r: f64, temperature_k: f64, n0: f64, phi_s: f64) -> Screening {
        assert!(phi_s > 0.0, "the closed form here is for phi_s > 0");
        Screening { lambda: debye_length(eps_r, temperature_k, n0), vt: K_B * temperature_k / E_CHARGE, phi_s }
    }

    /// x (nm) at which phi = u V_T.
    fn x_of_u(&self, u: f64) -> f64 {
        let us = self.phi_s / self.vt;
        let (mid, half) = (0.5 * (us + u), 0.5 * (us - u));
        let integral: f64 = GL5.iter().map(|(z, w)| w * correction(mid + half * z)).sum::<f64>() * half;
        self.lambda * ((us / u).ln() + integral)
    }

    /// The exact phi (V) at x (nm).
    pub fn phi(&self, x: f64) -> f64 {
        let mut u = self.linear(x) / self.vt;
        for _ in 0..30 {
            let g = self.x_of_u(u) - x;
            let dg = -self.lambda / (2.0 * f_of(u)).sqrt();
            // Newton in ln u: u' = u - g/dg, kept positive.
            let next = u - g / dg;
            let next = if next > 0.0 { next } else { 0.5 * u };
            if (next - u).abs() <= 1e-15 * u {
                u = next;
                break;
            }
            u = next;
        }
        u * self.vt
    }

    /// The linearised phi (V) at x (nm).
    pub fn linear(&self, x: f64) -> f64 {
        self.phi_s * (-x / self.lambda).exp()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lambda_is_the_notes_value() {
        let l = debye_length(10.0, 300.0, 6.0);
        assert!((l - 0.0488).abs() < 5e-5, "lambda = {l}");
    }

    #[test]
    fn exact_profile_solves_the_poisson_boltzmann_equation() {
        let s = Screening::new(10.0, 300.0, 6.0, 1e-3);
        assert!((s.phi(0.0) - 1e-3).abs() < 1e-15);
        // phi'' = (lambda^-2 V_T)(1 - exp(-phi/V_T)) by central differences.
        for &x in &[0.01, 0.05, 0.1, 0.2] {
            let h = 1e-4;
            let d2 = (s.phi(x + h) - 2.0 * s.phi(x) + s.phi(x - h)) / (h * h);
            let want = s.vt / (s.lambda * s.lambda) * (1.0 - (-s.phi(x) / s.vt).exp());
            assert!((d2 - want).abs() < 1e-5 * want.abs(), "x = {x}: {d2} vs {want}");
        }
        // Close to the linear form (u_s = 0.039).
        let dev = (0..100).map(|k| (s.phi(k as f64 * 0.005) - s.linear(k as f64 * 0.005)).abs()).fold(0.0, f64::max);
        assert!(dev < 0.02 * 1e-3 && dev > 1e-7, "nonlinear deviation {dev}");
    }
}
