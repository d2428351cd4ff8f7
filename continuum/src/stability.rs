//! Linear stability of the explicit steps on a uniform 1D bar: the CFL bound of every scheme,
//! integrator and PIC/FLIP blend, derived for the step this solver takes (issue 17; Gong
//! Ch. 7 re-derived, notes A.8 and F).
//!
//! **Model.** A bar at rest, sigma = E (F - 1) (or any law with constant tangent E), N points
//! per cell at the cell sub-centres (x = (c + (k - 1/2) / N) h), lumped nodal mass
//! m_L = rho h, amplitudes so small that no point moves (the stencil is frozen). The step maps
//! the point velocities v_p and stresses sigma_p linearly. Write S (node <- point weights),
//! G (their gradients) and V_p, m_p. The grid sees the points only through
//! v_i = m_L^-1 sum_p S_ip m_p v_p (the mapped velocity) and f_i = -sum_p V_p G_ip sigma_p, and
//! one step gives (a_i = f_i / m_L, v^L = v + dt a):
//! - the next mapped velocity v' = b v + dt R a, with R = m_L^-1 S M S^T (consistent over
//!   lumped mass: the FLIP increment dt S^T a seen back on the grid) and b = beta + (1 - beta) R
//!   for the blend beta (`flip_fraction`; PIC re-maps S^T v^L);
//! - the next force f' = f - dt K v*, K = E G V G^T, with v* the velocity the strain rate uses:
//!   v^L (usl, leapfrog), (v + v^L) / 2 (dhakal), v (usf, whose forces then come from the new
//!   stress).
//!
//! The point-space remainder (velocities and stresses the grid cannot see) does not move.
//! On a Bloch wave e^{i theta j} each operator is a number: r(theta) = R, w^2(theta) = K / m_L,
//! and with s = dt^2 w^2 and alpha = dt a the step is a 2 x 2 matrix on (v, alpha):
//! - usl / leapfrog: [[b, r], [-s, 1 - s]]
//! - dhakal: [[b, r], [-s, 1 - s/2]]
//! - usf: [[b - s r, r], [-s, 1]]
//! - stormer-verlet (FLIP): [[1 - r s/2, r (1 - s/4)], [-s, 1 - s/2]]
//!
//! (the leapfrog is the usl recurrence with velocities relabelled at half steps.) The bound is
//! the largest c dt / h at which no Bloch wave's spectral radius exceeds 1.
//!
//! **What it gives** (hats, FLIP; r = 1 - 4 a q, w^2 h^2 / c^2 = 4 q with q = sin^2(theta/2)
//! and a the mean of xi (1 - xi) over the points' cell coordinates xi):
//! - usl / leapfrog: CFL <= 1 / sqrt(1 + 4a) at theta = pi: **0.7071 for 1 point per cell,
//!   0.7559 for 2**. The sawtooth grid mode is invisible to the points (r = 0 at N = 1), so its
//!   velocity is rebuilt from zero every step and its stress obeys sigma' = (1 - 4 CFL^2) sigma:
//!   Gong's CFL <= 1 (7.32), derived with the grid velocity kept from step to step, does not hold
//!   for MPM that re-maps velocities from the points.
//! - usf: det = 1, stable while s r <= 4: CFL <= 2 (N = 1), sqrt(3) = 1.732 (N = 2).
//! - stormer-verlet: det = 1 - s (1 - r)/2, stable for s <= 4: CFL <= 1 at any N (the kicks
//!   on both ends of the step make the sawtooth's stress see the full velocity history).
//! - dhakal: det = 1 + s (r - 1/2) > 1 for the smooth waves at every dt (the first-order growth
//!   T w^2 dt / 4 of [`crate::solver::TimeIntegrator::Dhakal`]); its bound is where a real
//!   eigenvalue passes -1 (the sawtooth blows up by a factor per step instead of a slow drift):
//!   1 / (2 sqrt(a)) = 1 (N = 1), 1.1547 (N = 2).
//!
//! GIMP, CPDI and DDMP are analysed with their own stencil rows (built by the solver on a
//! periodic bar); IMPM with its MLS velocity map Phi (R = Phi S^T) and its one-point cell
//! quadrature of the MLS-reconstructed stress (K = E h D Q G^T), both at an interior node: for
//! IMPM that bound (1.18 at 2 points per cell) is **not sufficient** on a bar with fixed ends
//! (its end modes grow at 0.99 of it, tests/stability.rs), and it is above 1, so the validator's
//! CFL <= 1 stays IMPM's enforced bound, itself not shown sufficient. The analysis is 1D; in 2D and
//! 3D a plane wave along one axis is this 1D problem, so the bound is necessary there too (not
//! shown sufficient).

use crate::closure::LinearPiola;
use crate::grid::{Face, Grid};
use crate::mls::{Basis, Empty, Mls, Weight};
use crate::particles::Particles;
use crate::shape::SchemeKind;
use crate::solver::{Simulation, TimeIntegrator, Viscosity};
use crate::tensor::IDENTITY;
use nalgebra::Complex;

type C64 = Complex<f64>;

/// The Bloch symbols of one wave number: r = consistent over lumped mass of the FLIP increment,
/// w2 = K / m_L in units of (c / h)^2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Symbol {
    pub theta: f64,
    pub r: C64,
    pub w2: C64,
}

/// A scheme's layout for the analysis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layout {
    pub scheme: SchemeKind,
    pub particles_per_cell: usize,
    pub sub_points: usize,
}

/// Cells of the model bar (periodic, or non-periodic for IMPM with the analysed cell in the middle).
const CELLS: usize = 16;

/// The symbols of `layout` at each wave number `thetas` (radians per cell).
pub fn symbols(layout: Layout, thetas: &[f64]) -> Result<Vec<Symbol>, String> {
    if layout.scheme == SchemeKind::Impm {
        return impm_symbols(layout.particles_per_cell, thetas);
    }
    let n = layout.particles_per_cell.max(1);
    let grid = Grid::<1> { origin: [0.0], h: [1.0], cells: [CELLS], faces: [(Face::Periodic, Face::Periodic)] };
    let pts = bar_points(n);
    let law = LinearPiola { youngs_modulus: 1.0, poisson_ratio: 0.0, density0: 1.0 };
    // cpdi-improved keeps the CPDI stencil and maps velocities by MLS (below).
    let mls_map = layout.scheme.is_cpdi_improved();
    // tlmpm's stencil is the hats at the reference positions: at rest, mpm's.
    let stencil_scheme = match layout.scheme {
        SchemeKind::CpdiImproved | SchemeKind::Cpdi1Improved => SchemeKind::Cpdi,
        SchemeKind::Tlmpm => SchemeKind::Mpm,
        k => k,
    };
    let phi = if mls_map {
        let x: Vec<[f64; 1]> = pts.x.clone();
        Some(
            Mls::<1>::new(Basis::Linear, Weight::CubicBSpline, [1.0])
                .table(&[[(CELLS / 2) as f64]], &x, Empty::Refuse, "node", |_| CELLS / 2)
                .map_err(|e| e.to_string())?,
        )
    } else {
        None
    };
    let mut sim = Simulation::new(grid, pts, stencil_scheme, vec![Box::new(law)], Viscosity::None, 1e-3)
        .map_err(|e| e.to_string())?
        .with_sub_points(layout.sub_points);
    sim.integrator = TimeIntegrator::Usl;
    // At rest and unstressed nothing moves: the step only builds the stencil.
    sim.step().map_err(|e| e.to_string())?;
    let st = sim.stencil();
    let first = CELLS / 2 * n;
    let offset = |i: usize| {
        let d = i as i64 - (CELLS / 2) as i64;
        let d = d.rem_euclid(CELLS as i64);
        if d >= CELLS as i64 / 2 { d - CELLS as i64 } else { d }
    };
    Ok(thetas
        .iter()
        .map(|&theta| {
            let (mut mc, mut k, mut ml) = (0.0, 0.0, 0.0);
            for p in first..first + n {
                let (nodes, weights, grads) = st.row(p);
                let (mut s, mut g) = (C64::new(0.0, 0.0), C64::new(0.0, 0.0));
                for ((&i, &w), gr) in nodes.iter().zip(weights).zip(grads) {
                    let e = C64::from_polar(1.0, theta * offset(i) as f64);
                    s += e * w;
                    g += e * gr[0];
                    ml += sim.points.mass[p] * w;
                }
                mc += sim.points.mass[p] * s.norm_sqr();
                k += sim.points.volume[p] * g.norm_sqr();
            }
            let r = match &phi {
                // R = Phi S^T: the MLS map of the FLIP increment's point values.
                Some(phi) => {
                    let (points, values) = phi.row(0);
                    points
                        .iter()
                        .zip(values)
                        .map(|(&p, &f)| {
                            let (nodes, weights, _) = st.row(p);
                            let s: C64 = nodes.iter().zip(weights).map(|(&i, &w)| C64::from_polar(1.0, theta * offset(i) as f64) * w).sum();
                            s * f
                        })
                        .sum()
                }
                None => C64::new(mc / ml, 0.0),
            };
            Symbol { theta, r, w2: C64::new(k / ml, 0.0) }
        })
        .collect())
}

/// N points per cell of unit width and density at the sub-centres of `CELLS` cells.
fn bar_points(n: usize) -> Particles<1> {
    let mut pts = Particles::default();
    for c in 0..CELLS {
        for k in 0..n {
            let x = c as f64 + (k as f64 + 0.5) / n as f64;
            pts.push(0, [x], [0.0], 1.0 / n as f64, 1.0 / n as f64, [0.5 / n as f64], IDENTITY);
        }
    }
    pts
}

/// IMPM (Gong 5.3; [`crate::solver`]'s `impm`): v_i = sum_p Phi_p(x_i) v_p (linear MLS, cubic
/// B-spline), sigma_c = sum_p Q_p(x_c) sigma_p (linear MLS, quadratic B-spline),
/// f_i = -sum_c dN_i/dx(x_c) sigma_c h, m_i = rho h, hats at the points for the FLIP increment
/// and the strain rate. Evaluated at a node in the middle of a long bar.
fn impm_symbols(ppc: usize, thetas: &[f64]) -> Result<Vec<Symbol>, String> {
    let n = ppc.max(1);
    let pts = bar_points(n);
    let mid = (CELLS / 2) as f64;
    let phi = Mls::<1>::new(Basis::Linear, Weight::CubicBSpline, [1.0])
        .table(&[[mid]], &pts.x, Empty::Refuse, "node", |_| CELLS / 2)
        .map_err(|e| e.to_string())?;
    let q = Mls::<1>::new(Basis::Linear, Weight::QuadraticBSpline, [1.0])
        .table(&[[mid - 0.5], [mid + 0.5]], &pts.x, Empty::Refuse, "cell centre", |k| CELLS / 2 - 1 + k)
        .map_err(|e| e.to_string())?;
    // Hat weight and gradient of a point at x: nodes floor(x), floor(x) + 1.
    let hat = |x: f64, theta: f64| {
        let (c, xi) = (x.floor(), x - x.floor());
        let e0 = C64::from_polar(1.0, theta * (c - mid));
        let e1 = C64::from_polar(1.0, theta * (c + 1.0 - mid));
        (e0 * (1.0 - xi) + e1 * xi, e1 - e0)
    };
    Ok(thetas
        .iter()
        .map(|&theta| {
            let (points, values) = phi.row(0);
            let r: C64 = points.iter().zip(values).map(|(&p, &f)| hat(pts.x[p][0], theta).0 * f).sum();
            let mut k = C64::new(0.0, 0.0);
            for (c, grad) in [(0, 1.0), (1, -1.0)] {
                let (points, values) = q.row(c);
                let g: C64 = points.iter().zip(values).map(|(&p, &f)| hat(pts.x[p][0], theta).1 * f).sum();
                k += g * grad;
            }
            Symbol { theta, r, w2: k }
        })
        .collect())
}

/// The one-step matrix on (v, dt a) of one Bloch wave at `cfl` (c dt / h).
pub fn amplification(integrator: TimeIntegrator, flip_fraction: f64, sym: &Symbol, cfl: f64) -> [[C64; 2]; 2] {
    let one = C64::new(1.0, 0.0);
    let s = sym.w2 * (cfl * cfl);
    let r = sym.r;
    let b = one * flip_fraction + r * (1.0 - flip_fraction);
    match integrator {
        TimeIntegrator::Dhakal => [[b, r], [-s, one - s * 0.5]],
        TimeIntegrator::Usf => [[b - s * r, r], [-s, one]],
        // FLIP only: v' = v + r (alpha + alpha') / 2.
        TimeIntegrator::StormerVerlet => [[one - r * s * 0.5, r * (one - s * 0.25)], [-s, one - s * 0.5]],
        _ => [[b, r], [-s, one - s]],
    }
}

/// The two eigenvalues of a 2 x 2 matrix.
pub fn eigenvalues(m: &[[C64; 2]; 2]) -> [C64; 2] {
    let tr = m[0][0] + m[1][1];
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    let disc = (tr * tr - det * 4.0).sqrt();
    [(tr + disc) * 0.5, (tr - disc) * 0.5]
}

/// Whether every wave is stable at `cfl`. For `dhakal` only a real eigenvalue below -1 counts
/// (its complex pairs grow at every dt; see the module notes).
fn stable(integrator: TimeIntegrator, flip_fraction: f64, syms: &[Symbol], cfl: f64) -> bool {
    stable_with(|sym, cfl| amplification(integrator, flip_fraction, sym, cfl), integrator == TimeIntegrator::Dhakal, syms, cfl)
}

fn stable_with(matrix: impl Fn(&Symbol, f64) -> [[C64; 2]; 2], real_only: bool, syms: &[Symbol], cfl: f64) -> bool {
    const TOL: f64 = 1e-9;
    syms.iter().all(|sym| {
        eigenvalues(&matrix(sym, cfl))
            .iter()
            .all(|l| if real_only { !(l.im.abs() <= 1e-12 && l.re < -1.0 - TOL) } else { l.norm() <= 1.0 + TOL })
    })
}

/// The largest CFL (c dt / h) at which every wave of `syms` is stable (up to 8; `None` if no
/// CFL is, which no scheme here gives).
pub fn bound_of(integrator: TimeIntegrator, flip_fraction: f64, syms: &[Symbol]) -> Option<f64> {
    largest_stable(|cfl| stable(integrator, flip_fraction, syms, cfl))
}

fn largest_stable(stable: impl Fn(f64) -> bool) -> Option<f64> {
    let step = 1e-3;
    let mut lo = 0.0;
    while lo < 8.0 {
        let hi = lo + step;
        if !stable(hi) {
            if lo == 0.0 {
                return None;
            }
            let (mut a, mut b) = (lo, hi);
            for _ in 0..50 {
                let m = 0.5 * (a + b);
                if stable(m) { a = m } else { b = m }
            }
            return Some(a);
        }
        lo = hi;
    }
    Some(8.0)
}

/// TLMPM's one-step matrix on (v, dt a) (`solver/tlmpm.rs`, leapfrog): the re-mapped velocity
/// v' = b v + r alpha (as for usl), but F, and so the next force, is updated with v' rather
/// than v^L: alpha' = alpha - s v'. So [[b, r], [-s b, 1 - s r]], b = beta + (1 - beta) r.
/// At beta = 1 the determinant is 1 and the bound is s r <= 4: hats at 2 points per cell
/// (r = 1 - 3 q / 4, s = 4 CFL^2 q) give CFL <= sqrt 3, as [`crate::tlmpm`] derives.
pub fn tlmpm_amplification(flip_fraction: f64, sym: &Symbol, cfl: f64) -> [[C64; 2]; 2] {
    let one = C64::new(1.0, 0.0);
    let s = sym.w2 * (cfl * cfl);
    let r = sym.r;
    let b = one * flip_fraction + r * (1.0 - flip_fraction);
    [[b, r], [-s * b, one - s * r]]
}

/// TLMPM's bound over the waves of `syms` (the symbols of its hats at the reference positions).
pub fn tlmpm_bound_of(flip_fraction: f64, syms: &[Symbol]) -> Option<f64> {
    largest_stable(|cfl| stable_with(|sym, cfl| tlmpm_amplification(flip_fraction, sym, cfl), false, syms, cfl))
}

/// The moving-mesh form's one-step matrix on (v, dt a) (`scheme.tlmpm_form = "moving-mesh"`):
/// the nodal velocity is carried, never re-mapped from the points, so the leapfrog acts on the
/// nodal dofs with the stiffness of the hats at X_p: [[1, 1], [-s, 1 - s]], bound s <= 4 (hats:
/// s = 4 CFL^2 q, CFL <= 1 at any number of points per cell, as [`crate::tlmpm`] derives).
pub fn moving_mesh_amplification(sym: &Symbol, cfl: f64) -> [[C64; 2]; 2] {
    let one = C64::new(1.0, 0.0);
    let s = sym.w2 * (cfl * cfl);
    [[one, one], [-s, one - s]]
}

/// The moving-mesh form's bound at `layout` (tlmpm's hats at the reference positions).
pub fn moving_mesh_bound(layout: Layout) -> Result<Option<f64>, String> {
    let syms = symbols(Layout { scheme: SchemeKind::Tlmpm, ..layout }, &all_waves())?;
    Ok(largest_stable(|cfl| stable_with(moving_mesh_amplification, false, &syms, cfl)))
}

/// Wave numbers 0 ..= pi (every wave of an infinite bar; the symbols are even in theta).
pub fn all_waves() -> Vec<f64> {
    (0..=1024).map(|k| std::f64::consts::PI * k as f64 / 1024.0).collect()
}

/// The waves of a periodic bar of `cells` cells: theta = 2 pi j / cells.
pub fn waves_of_periodic_bar(cells: usize) -> Vec<f64> {
    (0..=cells / 2).map(|j| 2.0 * std::f64::consts::PI * j as f64 / cells as f64).collect()
}

/// The CFL bound of a combination on an infinite bar (every wave number).
pub fn cfl_bound(layout: Layout, integrator: TimeIntegrator, flip_fraction: f64) -> Result<Option<f64>, String> {
    if integrator == TimeIntegrator::ImplicitTrapezoidal {
        return Ok(None);
    }
    let syms = symbols(layout, &all_waves())?;
    if layout.scheme == SchemeKind::Tlmpm {
        return Ok(tlmpm_bound_of(flip_fraction, &syms));
    }
    Ok(bound_of(integrator, flip_fraction, &syms))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(scheme: SchemeKind, n: usize) -> Layout {
        Layout { scheme, particles_per_cell: n, sub_points: 1 }
    }

    /// The hat symbols against their closed forms r = 1 - 4 a q, w^2 = 4 q, and the closed-form
    /// bounds of the module notes.
    #[test]
    fn the_mpm_symbols_and_bounds_are_the_closed_forms() {
        for (n, a) in [(1usize, 0.25), (2, 3.0 / 16.0), (4, 11.0 / 64.0)] {
            let syms = symbols(layout(SchemeKind::Mpm, n), &all_waves()).unwrap();
            for s in &syms {
                let q = (s.theta / 2.0).sin().powi(2);
                assert!((s.r.re - (1.0 - 4.0 * a * q)).abs() < 1e-12 && (s.w2.re - 4.0 * q).abs() < 1e-12, "N = {n}: {s:?}");
            }
            let mm = moving_mesh_bound(layout(SchemeKind::Tlmpm, n)).unwrap().unwrap();
            assert!((mm - 1.0).abs() < 1e-6, "N = {n}: moving mesh {mm}");
            let usl = bound_of(TimeIntegrator::Usl, 1.0, &syms).unwrap();
            assert!((usl - 1.0 / (1.0 + 4.0 * a).sqrt()).abs() < 1e-6, "N = {n}: usl {usl}");
            let dhakal = bound_of(TimeIntegrator::Dhakal, 1.0, &syms).unwrap();
            assert!((dhakal - 1.0 / (2.0 * a.sqrt())).abs() < 1e-6, "N = {n}: dhakal {dhakal}");
            // usf: s r <= 4 with s = 4 CFL^2 q: CFL^2 <= 1 / max_q q (1 - 4 a q).
            let qm = (1.0 / (8.0 * a)).min(1.0);
            let usf = bound_of(TimeIntegrator::Usf, 1.0, &syms).unwrap();
            assert!((usf - 1.0 / (qm * (1.0 - 4.0 * a * qm)).sqrt()).abs() < 2e-3, "N = {n}: usf {usf}");
        }
    }

    /// TLMPM at beta = 1: s r <= 4, CFL^2 <= 1 / max_q q (1 - 4 a q), the usf form: sqrt 3 at 2
    /// points per cell ([`crate::tlmpm`]'s derivation), 2 at 1; through `cfl_bound` as well.
    #[test]
    fn the_tlmpm_bound_is_the_closed_form() {
        for (n, a) in [(1usize, 0.25f64), (2, 3.0 / 16.0), (4, 11.0 / 64.0)] {
            let qm = (1.0 / (8.0 * a)).min(1.0);
            let closed = 1.0 / (qm * (1.0 - 4.0 * a * qm)).sqrt();
            let b = cfl_bound(layout(SchemeKind::Tlmpm, n), TimeIntegrator::Leapfrog, 1.0).unwrap().unwrap();
            assert!((b - closed).abs() < 2e-3, "N = {n}: tlmpm {b} vs {closed}");
        }
        let b2 = cfl_bound(layout(SchemeKind::Tlmpm, 2), TimeIntegrator::Leapfrog, 1.0).unwrap().unwrap();
        assert!((b2 - 3f64.sqrt()).abs() < 2e-3, "{b2}");
        // PIC re-maps the FLIP increment away: still bounded, and no looser than FLIP here.
        let pic = cfl_bound(layout(SchemeKind::Tlmpm, 2), TimeIntegrator::Leapfrog, 0.0).unwrap().unwrap();
        eprintln!("tlmpm 2 ppc: FLIP {b2:.4}, PIC {pic:.4}");
        assert!(pic > 0.5 && pic <= b2 + 1e-6, "PIC {pic}");
    }
}
