//! Physics checks of the step (issue 3, tests 6 and 7): conservation, determinism across
//! thread counts, symmetry, and convergence on the manufactured solution of Gong Ch. 4.7.
//! Kept small (a few thousand points, a few hundred steps) so the file runs in seconds with
//! the optimised test profile; the full ranges are `#[ignore]`d tests.

use continuum::closure::{IdealGasIsothermal, NeoHookean, lame};
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::{Closure, Face, Grid, Particles, SchemeKind, Simulation};
use std::f64::consts::PI;
use std::sync::Arc;

fn free<const D: usize>() -> [(Face, Face); D] {
    std::array::from_fn(|_| (Face::Free, Face::Free))
}

/// Points at the sub-centres of every cell of `grid` whose centre lies in [lo, hi).
fn points<const D: usize>(
    grid: &Grid<D>,
    lo: [f64; D],
    hi: [f64; D],
    ppc: usize,
    rho: f64,
    v: impl Fn(&[f64; D]) -> [f64; D],
) -> Particles<D> {
    let mut pts = Particles::default();
    let vol = grid.cell_volume() / ppc.pow(D as u32) as f64;
    let n: [usize; D] = std::array::from_fn(|a| grid.cells[a] * ppc);
    let total: usize = n.iter().product();
    for k in 0..total {
        let mut rem = k;
        let x: [f64; D] = std::array::from_fn(|a| {
            let i = rem % n[a];
            rem /= n[a];
            grid.origin[a] + (i as f64 + 0.5) * grid.h[a] / ppc as f64
        });
        if (0..D).all(|a| x[a] >= lo[a] && x[a] < hi[a]) {
            let half = std::array::from_fn(|a| 0.5 * grid.h[a] / ppc as f64);
            pts.push(0, x, v(&x), rho * vol, vol, half, Particles::<D>::identity());
        }
    }
    pts
}

fn neo() -> Box<dyn Closure> {
    Box::new(NeoHookean { youngs_modulus: 1e7, poisson_ratio: 0.3, density0: 1e3 })
}

fn momentum<const D: usize>(s: &Simulation<D>) -> ([f64; D], f64) {
    let t = s.totals();
    let scale = (0..s.points.len()).map(|p| s.points.mass[p] * s.points.v[p].iter().map(|v| v * v).sum::<f64>().sqrt()).sum::<f64>();
    (t.momentum, scale)
}

/// A 2D elastic block in the middle of a larger grid, free on every side, with a swirling
/// and compressing velocity field: forces reach empty nodes next to the free surface.
fn free_block_2d(scheme: SchemeKind, sub: usize) -> Simulation<2> {
    let grid = Grid::<2> { origin: [0.0; 2], h: [0.1; 2], cells: [16, 12], faces: free() };
    let pts = points(&grid, [0.4, 0.3], [1.2, 0.9], 2, 1e3, |x| [3.0 * (3.0 * x[1]).sin() + 0.5, -4.0 * (x[0] - 0.8)]);
    let c = ((lame(1e7, 0.3).0 + 2.0 * lame(1e7, 0.3).1) / 1e3).sqrt();
    Simulation::new(grid, pts, scheme, vec![neo()], Viscosity::None, 0.2 * 0.1 / c).expect("builds").with_sub_points(sub)
}

#[test]
fn mass_and_momentum_are_conserved_at_free_surfaces() {
    // Every PIC/FLIP blend: the PIC share interpolates nodal velocities, so it must see the
    // momentum the points mapped, not the small-mass average of the light surface nodes.
    let cases =
        [(SchemeKind::Ddmp, 1), (SchemeKind::DdmpSubpoints, 8), (SchemeKind::Cpdi2, 1), (SchemeKind::Ugimp, 1), (SchemeKind::Tlmpm, 1)];
    for ((scheme, sub), beta) in cases.into_iter().flat_map(|c| [1.0, 0.5, 0.0].map(|b| (c, b))) {
        let mut s = free_block_2d(scheme, sub);
        s.flip_fraction = beta;
        let (p0, scale) = momentum(&s);
        let m0 = s.totals().mass;
        for _ in 0..100 {
            s.step().unwrap_or_else(|e| panic!("{scheme:?}, flip {beta}: {e}"));
        }
        let (p1, _) = momentum(&s);
        for a in 0..2 {
            assert!(
                (p1[a] - p0[a]).abs() <= 1e-13 * scale,
                "{scheme:?}, flip {beta}: momentum[{a}] {} -> {} (scale {scale:e})",
                p0[a],
                p1[a]
            );
        }
        assert_eq!(s.totals().mass, m0);
        assert_eq!(s.wall_impulse, [0.0; 2]);
    }
}

#[test]
fn empty_node_forces_are_handed_on_not_dropped() {
    // DDMP's gradient reaches one node beyond the material: those nodes must end the force
    // pass with no force, and the total force must still vanish.
    let mut s = free_block_2d(SchemeKind::Ddmp, 1);
    for _ in 0..3 {
        s.step().expect("step");
    }
    let (m, f) = (s.node_mass(), s.node_force());
    let mut total = [0.0; 2];
    let mut scale = 0.0;
    for i in 0..m.len() {
        if m[i] == 0.0 {
            assert_eq!(f[i], [0.0; 2], "empty node {i} kept a force");
        }
        for a in 0..2 {
            total[a] += f[i][a];
            scale += f[i][a].abs();
        }
    }
    assert!(scale > 0.0);
    assert!(total.iter().all(|t| t.abs() <= 1e-12 * scale), "net force {total:?} of {scale:e}");
}

#[test]
fn wall_impulse_accounts_for_the_momentum_change() {
    // A 1D bar moving into a reflective wall, for every PIC/FLIP blend: the PIC share also
    // feels the wall through the projected mapped velocity, an impulse of its own.
    for beta in [1.0, 0.5, 0.0] {
        let grid = Grid::<1> { origin: [0.0], h: [0.01], cells: [100], faces: [(Face::Reflective, Face::Free)] };
        let pts = points(&grid, [0.0], [0.6], 4, 1e3, |_| [-20.0]);
        let mut s = Simulation::new(grid, pts, SchemeKind::Ddmp, vec![neo()], Viscosity::None, 0.2 * 0.01 / 117.0).expect("builds");
        s.flip_fraction = beta;
        let (p0, scale) = momentum(&s);
        for _ in 0..200 {
            s.step().expect("step");
        }
        let (p1, _) = momentum(&s);
        assert!(s.wall_impulse[0].abs() > 0.01 * scale, "flip {beta}: the wall did nothing");
        assert!(
            (p1[0] - p0[0] - s.wall_impulse[0]).abs() <= 1e-12 * scale.max(s.wall_impulse_magnitude),
            "flip {beta}: {} - {} != {}",
            p1[0],
            p0[0],
            s.wall_impulse[0]
        );
    }
}

/// A periodic 1D bar with a smooth standing wave (neo-Hookean, no viscosity).
fn periodic_wave(scheme: SchemeKind, sub: usize, dt_factor: f64) -> Simulation<1> {
    let grid = Grid::<1> { origin: [0.0], h: [1.0 / 64.0], cells: [64], faces: [(Face::Periodic, Face::Periodic)] };
    let pts = points(&grid, [0.0], [1.0], 2, 1e3, |x| [2.0 * (2.0 * PI * x[0]).sin() + 0.5]);
    let c = 117.0;
    Simulation::new(grid, pts, scheme, vec![neo()], Viscosity::None, dt_factor * grid_h() / c).expect("builds").with_sub_points(sub)
}

fn grid_h() -> f64 {
    1.0 / 64.0
}

#[test]
fn momentum_is_conserved_to_round_off_in_a_periodic_scene() {
    for (scheme, sub) in [(SchemeKind::Ddmp, 1), (SchemeKind::DdmpSubpoints, 4), (SchemeKind::Cpdi, 1), (SchemeKind::Mpm, 1)] {
        let mut s = periodic_wave(scheme, sub, 0.4);
        let (p0, scale) = momentum(&s);
        for _ in 0..300 {
            s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
        }
        let (p1, _) = momentum(&s);
        assert!((p1[0] - p0[0]).abs() <= 1e-13 * scale, "{scheme:?}: {} -> {}", p0[0], p1[0]);
    }
}

#[test]
fn energy_drift_falls_when_the_time_step_halves() {
    for (scheme, sub) in [(SchemeKind::Ddmp, 1), (SchemeKind::DdmpSubpoints, 4)] {
        let drift = |f: f64| {
            let mut s = periodic_wave(scheme, sub, f);
            let t_end = 0.004;
            while s.time < t_end - 1e-12 {
                s.step().expect("step");
            }
            (s.totals().energy() - s.initial.energy()).abs() / s.initial.energy()
        };
        let (d1, d2) = (drift(0.4), drift(0.2));
        assert!(d1 > 0.0 && d1 >= 1.8 * d2, "{scheme:?}: energy drift {d1:e} at dt, {d2:e} at dt/2");
    }
}

#[test]
fn the_same_state_for_one_and_two_threads() {
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
        pool.install(|| {
            let mut s = free_block_2d(SchemeKind::DdmpSubpoints, 8);
            for _ in 0..20 {
                s.step().expect("step");
            }
            let p = &s.points;
            let mut bits: Vec<u64> = Vec::new();
            for k in 0..p.len() {
                bits.extend(p.x[k].iter().chain(&p.v[k]).chain([&p.volume[k], &p.internal_energy[k]]).map(|v| v.to_bits()));
                bits.extend(p.stress[k].iter().flatten().chain(p.def_grad[k].iter().flatten()).map(|v| v.to_bits()));
            }
            bits
        })
    };
    let (a, b) = (run(1), run(2));
    assert!(a.len() > 1000);
    assert!(a == b, "state differs between 1 and 2 threads");
}

#[test]
fn a_radial_pressure_pulse_stays_symmetric() {
    let n = 24;
    let grid = Grid::<2> {
        origin: [-1.0; 2],
        h: [2.0 / n as f64; 2],
        cells: [n; 2],
        faces: [(Face::Reflective, Face::Reflective), (Face::Reflective, Face::Reflective)],
    };
    let mut pts = points(&grid, [-1.0; 2], [1.0; 2], 2, 1.0, |_| [0.0; 2]);
    for p in 0..pts.len() {
        let r2 = pts.x[p][0].powi(2) + pts.x[p][1].powi(2);
        let rho = 1.0 + 0.5 * (-r2 / 0.05).exp();
        pts.mass[p] *= rho;
    }
    let gas: Box<dyn Closure> = Box::new(IdealGasIsothermal { sound_speed: 1.0 });
    let mut s =
        Simulation::new(grid, pts, SchemeKind::DdmpSubpoints, vec![gas], Viscosity::Linear { coefficient: 0.5 }, 0.2 * 2.0 / n as f64)
            .expect("builds")
            .with_sub_points(4);
    for _ in 0..60 {
        s.step().expect("step");
    }
    // Index points by their initial position; compare each with its mirror images.
    let pts = &s.points;
    let key = |x: [f64; 2]| ((x[0] * 1e6).round() as i64, (x[1] * 1e6).round() as i64);
    let map: std::collections::HashMap<_, _> = (0..pts.len()).map(|p| (key(pts.x0[p]), p)).collect();
    let mut worst: f64 = 0.0;
    let moved = (0..pts.len()).map(|p| pts.v[p][0].abs()).fold(0.0, f64::max);
    assert!(moved > 1e-3, "the pulse did not move anything");
    for p in 0..pts.len() {
        let (x, y) = (pts.x0[p][0], pts.x0[p][1]);
        for (q, sx, sy, swap) in [((y, x), 1.0, 1.0, true), ((-x, y), -1.0, 1.0, false), ((x, -y), 1.0, -1.0, false)] {
            let m = map[&key([q.0, q.1])];
            let dp = (pts.pressure(p) - pts.pressure(m)).abs();
            let (vx, vy) = if swap { (pts.v[m][1], pts.v[m][0]) } else { (sx * pts.v[m][0], sy * pts.v[m][1]) };
            worst = worst.max(dp).max((pts.v[p][0] - vx).abs()).max((pts.v[p][1] - vy).abs());
        }
    }
    assert!(worst <= 1e-12, "asymmetry {worst:e}");
}

/// The 2D/3D manufactured solution U_a = G sin(pi X_a) sin(c pi t) of Gong (4.41)-(4.46),
/// neo-Hookean, E = 1e7 Pa, nu = 0.3, rho0 = 1e3, dt = 0.4 h / c, T = 0.02 s, rollers on
/// every face. Returns the L2 displacement and velocity errors sqrt(sum_p V0_p |e|^2) at the
/// end (the leapfrog's velocities are compared at t - dt / 2, where they live).
fn manufactured<const D: usize>(scheme: SchemeKind, cells: usize, g: f64, integrator: TimeIntegrator) -> (f64, f64) {
    let (e, nu, rho0) = (1e7, 0.3, 1e3);
    let (lambda, mu) = lame(e, nu);
    let c = (e / rho0).sqrt();
    let h = 1.0 / cells as f64;
    let grid =
        Grid::<D> { origin: [0.0; D], h: [h; D], cells: [cells; D], faces: std::array::from_fn(|_| (Face::Reflective, Face::Reflective)) };
    let pts = points(&grid, [0.0; D], [1.0; D], 2, rho0, |x| std::array::from_fn(|a| c * PI * g * (PI * x[a]).sin()));
    let dt = 0.4 * h / c;
    let mut s = Simulation::new(
        grid,
        pts,
        scheme,
        vec![Box::new(NeoHookean { youngs_modulus: e, poisson_ratio: nu, density0: rho0 })],
        Viscosity::None,
        dt,
    )
    .expect("builds");
    s.integrator = integrator;
    s.body_force = Some(Arc::new(move |x0: &[f64; D], t: f64| {
        let f: [f64; D] = std::array::from_fn(|a| 1.0 + PI * g * (PI * x0[a]).cos() * (c * PI * t).sin());
        let lnj = f.iter().map(|v| v.ln()).sum::<f64>();
        std::array::from_fn(|a| {
            let u = g * (PI * x0[a]).sin() * (c * PI * t).sin();
            PI * PI * u / rho0 * (lambda / (f[a] * f[a]) * (1.0 - lnj) + mu * (1.0 + 1.0 / (f[a] * f[a])) - e)
        })
    }));
    let steps = (0.02 / dt).round() as usize;
    for _ in 0..steps {
        s.step().unwrap_or_else(|err| panic!("{scheme:?} h = 1/{cells}: {err}"));
    }
    let t = s.time;
    let tv = if integrator == TimeIntegrator::Leapfrog { t - 0.5 * dt } else { t };
    let p = &s.points;
    let (mut eu, mut ev) = (0.0, 0.0);
    for k in 0..p.len() {
        for a in 0..D {
            let x0 = p.x0[k][a];
            eu += p.volume0[k] * (p.x[k][a] - x0 - g * (PI * x0).sin() * (c * PI * t).sin()).powi(2);
            ev += p.volume0[k] * (p.v[k][a] - c * PI * g * (PI * x0).sin() * (c * PI * tv).cos()).powi(2);
        }
    }
    (eu.sqrt(), ev.sqrt())
}

fn orders(errors: &[f64]) -> Vec<f64> {
    errors.windows(2).map(|w| (w[0] / w[1]).log2()).collect()
}

/// Why the default cycle cannot pass test 7 (see [`TimeIntegrator`]): on the manufactured
/// solution its velocity error after one period is the amplitude growth T w^2 dt / 4 of the
/// derived amplification matrix (w = c pi), times the velocity norm: within 5 % for cpdi2 and
/// 15 % for ddmp, whose spatial error is larger (measured at h = 1/32: 1.6 % and 9.7 %). The
/// leapfrog removes it (at least 5x smaller; measured 18x and 8.4x).
#[test]
fn the_default_cycle_is_first_order_in_time_and_the_leapfrog_is_not() {
    let cells = 32;
    let (c, t_end) = (1e2, 0.02);
    let dt = 0.4 / (cells as f64 * c);
    let w = c * PI;
    // Velocity norm sqrt(int (c pi G sin(pi X))^2 dX) per component, two components.
    let norm = c * PI * 1e-4 * (0.5f64 * 2.0).sqrt();
    let predicted = t_end * w * w * dt / 4.0 * norm;
    for (scheme, tolerance) in [(SchemeKind::Cpdi2, 0.05), (SchemeKind::Ddmp, 0.15)] {
        let (_, dhakal) = manufactured::<2>(scheme, cells, 1e-4, TimeIntegrator::Dhakal);
        let (_, leapfrog) = manufactured::<2>(scheme, cells, 1e-4, TimeIntegrator::Leapfrog);
        eprintln!("{scheme:?} h = 1/{cells}: velocity error {dhakal:.4e} (predicted {predicted:.4e}), leapfrog {leapfrog:.4e}");
        assert!((dhakal / predicted - 1.0).abs() <= tolerance, "{scheme:?}: velocity error {dhakal:e}, predicted {predicted:e}");
        assert!(leapfrog * 5.0 <= dhakal, "{scheme:?}: leapfrog velocity error {leapfrog:e} vs {dhakal:e}");
    }
}

/// Issue test 7 in 2D over h = 1/8 ... 1/32, with the leapfrog (the full range, 1/64 and
/// 3D, is the ignored test below; figures in continuum/README.md).
#[test]
fn manufactured_solution_converges_at_second_order_in_2d() {
    for scheme in [SchemeKind::Ddmp, SchemeKind::Cpdi1, SchemeKind::Cpdi2] {
        let e: Vec<f64> = [8, 16, 32].iter().map(|&n| manufactured::<2>(scheme, n, 1e-4, TimeIntegrator::Leapfrog).0).collect();
        let o = orders(&e);
        eprintln!("2D {scheme:?}: errors {e:?} orders {o:?}");
        assert!(o.iter().all(|&v| v >= 1.8), "{scheme:?}: errors {e:?}, orders {o:?}");
    }
}

/// IMPM on Gong's 2D manufactured solution (his Figs 5.7-5.8; notes A.9 T3: displacement order
/// at least 1.8 at G = 0.1 over 1/8 ... 1/32), and at the small-strain amplitude 1e-4; its 3D
/// form on the cube at 1e-4 over 1/4 ... 1/16 is in the ignored full-range test. The improved
/// CPDI on both bases at G = 0.1 (measured 2.09 / 2.04 on either).
#[test]
fn impm_and_the_improved_cpdis_converge_at_second_order_in_2d() {
    let runs = [(SchemeKind::Impm, 0.1), (SchemeKind::Impm, 1e-4), (SchemeKind::CpdiImproved, 0.1), (SchemeKind::Cpdi1Improved, 0.1)];
    for (scheme, g) in runs {
        let e: Vec<f64> = [8, 16, 32].iter().map(|&n| manufactured::<2>(scheme, n, g, TimeIntegrator::Leapfrog).0).collect();
        let o = orders(&e);
        eprintln!("2D {scheme:?} G = {g}: errors {e:?} orders {o:?}");
        assert!(o.iter().all(|&v| v >= 1.8), "2D {scheme:?} G = {g}: errors {e:?}, orders {o:?}");
    }
}

#[test]
#[ignore = "heavy (h = 1/64 in 2D, h = 1/16 in 3D): run with --ignored; figures in continuum/README.md"]
fn manufactured_solution_converges_at_second_order_full_range() {
    for scheme in [SchemeKind::Ddmp, SchemeKind::Cpdi1, SchemeKind::Cpdi2, SchemeKind::Impm] {
        let e: Vec<f64> = [8, 16, 32, 64].iter().map(|&n| manufactured::<2>(scheme, n, 1e-4, TimeIntegrator::Leapfrog).0).collect();
        let o = orders(&e);
        eprintln!("2D {scheme:?}: errors {e:?} orders {o:?}");
        assert!(o.iter().all(|&v| v >= 1.8), "2D {scheme:?}: errors {e:?}, orders {o:?}");
        let e: Vec<f64> = [4, 8, 16].iter().map(|&n| manufactured::<3>(scheme, n, 1e-4, TimeIntegrator::Leapfrog).0).collect();
        let o = orders(&e);
        eprintln!("3D {scheme:?}: errors {e:?} orders {o:?}");
        // IMPM on 4^3 cells is short of its asymptotic range (measured orders 1.71, 1.98: the
        // quadratic MLS at the centres next to the rollers spans most of the cube).
        let first = if scheme == SchemeKind::Impm { 1.6 } else { 1.8 };
        assert!(o[0] >= first && o[1] >= 1.8, "3D {scheme:?}: errors {e:?}, orders {o:?}");
    }
}

/// Every scheme of the registry ([`SchemeKind::NAMES`]) defined in `dim` dimensions, with the
/// sub-points it runs with (4 for ddmp-subpoints, else 1).
fn registry(dim: usize) -> Vec<(SchemeKind, usize)> {
    let all: Vec<(SchemeKind, usize)> =
        SchemeKind::NAMES.iter().map(|&(_, k)| (k, if k == SchemeKind::DdmpSubpoints { 4 } else { 1 })).collect();
    assert_eq!(all.len(), 12, "the registry changed: check that every scheme is still covered");
    all.into_iter().filter(|(k, _)| k.supports_dimension(dim)).collect()
}

/// |sum of the nodal masses - sum of the point masses| / sum of the point masses.
fn nodal_mass_error<const D: usize>(s: &Simulation<D>) -> f64 {
    let points = s.points.mass.iter().sum::<f64>();
    (s.node_mass().iter().sum::<f64>() - points).abs() / points
}

/// Runs `steps` steps; checks mass (the points' exactly, the nodes' to round-off at every
/// step) and returns the largest momentum change over the run relative to the momentum scale.
fn conservation<const D: usize>(mut s: Simulation<D>, steps: usize) -> f64 {
    let scheme = s.scheme;
    let (p0, scale) = momentum(&s);
    let m0 = s.totals().mass;
    let mut worst: f64 = 0.0;
    for step in 1..=steps {
        s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
        let e = nodal_mass_error(&s);
        assert!(e <= 1e-14, "{D}D {scheme:?}, step {step}: the nodes hold {e:e} more or less mass than the points");
        let (p, _) = momentum(&s);
        worst = (0..D).map(|a| (p[a] - p0[a]).abs() / scale).fold(worst, f64::max);
    }
    assert_eq!(s.totals().mass, m0, "{D}D {scheme:?}: point masses changed");
    assert_eq!(s.wall_impulse, [0.0; D], "{D}D {scheme:?}: a wall acted in a scene without walls");
    worst
}

/// Mass to round-off for every scheme of the registry, in 1D (a periodic bar, 300 steps) and
/// 2D (a block with free surfaces on every side, 100 steps), and momentum too: every scheme
/// conserves it (measured at most 1.3e-15 of the momentum scale in 1D, 1.9e-15 in 2D) except
/// `impm` (1D, a free bar: 4.6e-5 over 300 steps, notes A.2).
#[test]
fn every_scheme_conserves_mass_and_momentum_in_1d_and_2d() {
    for (scheme, sub) in registry(1) {
        if scheme.maps_velocity_by_mls() {
            // IMPM conserves the points' mass but not momentum (velocity map, quadrature mass):
            // a free bar, its drift measured (see mls_bar). cpdi-improved does conserve it (the
            // FLIP increments come from forces that sum to zero, whatever the mapped velocity).
            let mut s = mls_bar(scheme);
            let (p0, scale) = momentum(&s);
            let m0 = s.totals().mass;
            let mut worst: f64 = 0.0;
            for _ in 0..300 {
                s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
                worst = worst.max((momentum(&s).0[0] - p0[0]).abs() / scale);
            }
            assert_eq!(s.totals().mass, m0);
            eprintln!("1D {scheme:?}: momentum drift {worst:e} of the momentum scale (not conserved by the scheme)");
            // Measured 4.6e-5 (impm), 1.7e-15 (cpdi-improved) of the scale over 300 steps.
            let limit = if scheme == SchemeKind::Impm { 1e-3 } else { 1e-13 };
            assert!(worst <= limit, "1D {scheme:?}: momentum drift {worst:e} of the scale");
            continue;
        }
        let drift = conservation(periodic_wave(scheme, sub, 0.4), 300);
        eprintln!("1D {scheme:?}: momentum drift {drift:e} of the momentum scale");
        assert!(drift <= 1e-13, "1D {scheme:?}: momentum drift {drift:e} of the scale");
    }
    for (scheme, sub) in registry(2) {
        if scheme == SchemeKind::Impm {
            // The free block: the points' mass exactly; momentum drifts (velocity map and
            // quadrature mass, as in 1D; the free surfaces' cells add to it) and falls with h.
            let drift: Vec<f64> = [1, 2]
                .iter()
                .map(|&refine| {
                    let h = 0.1 / refine as f64;
                    let grid = Grid::<2> { origin: [0.0; 2], h: [h; 2], cells: [16 * refine, 12 * refine], faces: free() };
                    let pts = points(&grid, [0.4, 0.3], [1.2, 0.9], 2, 1e3, |x| [3.0 * (3.0 * x[1]).sin() + 0.5, -4.0 * (x[0] - 0.8)]);
                    let c = ((lame(1e7, 0.3).0 + 2.0 * lame(1e7, 0.3).1) / 1e3).sqrt();
                    let mut s = Simulation::new(grid, pts, scheme, vec![neo()], Viscosity::None, 0.2 * h / c).expect("builds");
                    s.integrator = TimeIntegrator::Leapfrog;
                    let (p0, scale) = momentum(&s);
                    let m0 = s.totals().mass;
                    let mut worst: f64 = 0.0;
                    for _ in 0..100 * refine {
                        s.step().unwrap_or_else(|e| panic!("2D {scheme:?}: {e}"));
                        let p = momentum(&s).0;
                        worst = (0..2).map(|a| (p[a] - p0[a]).abs() / scale).fold(worst, f64::max);
                    }
                    assert_eq!(s.totals().mass, m0);
                    worst
                })
                .collect();
            eprintln!("2D {scheme:?}: momentum drift {drift:?} of the momentum scale at h = 0.1, 0.05 (not conserved by the scheme)");
            assert!(drift[1] <= 0.5 * drift[0], "2D {scheme:?}: momentum drift {drift:?} of the scale does not fall with h");
            continue;
        }
        let drift = conservation(free_block_2d(scheme, sub), 100);
        eprintln!("2D {scheme:?}: momentum drift {drift:e} of the momentum scale");
        assert!(drift <= 1e-13, "2D {scheme:?}: momentum drift {drift:e} of the scale");
    }
}

/// The test bar of the MLS velocity maps (IMPM and cpdi-improved have no periodic axis): a free
/// neo-Hookean bar on [0.1, 1.1] m in a grid on [0, 1.2] m of 384 cells, 2 points per cell,
/// v = 2 sin(2 pi x) + 0.5 m/s, leapfrog.
fn mls_bar(scheme: SchemeKind) -> Simulation<1> {
    let grid = Grid::<1> { origin: [0.0], h: [1.2 / 384.0], cells: [384], faces: [(Face::Free, Face::Free)] };
    let pts = points(&grid, [0.1], [1.1], 2, 1e3, |x| [2.0 * (2.0 * PI * x[0]).sin() + 0.5]);
    let mut s = Simulation::new(grid, pts, scheme, vec![neo()], Viscosity::None, 0.4 * 1.2 / 384.0 / 117.0).expect("builds");
    s.integrator = TimeIntegrator::Leapfrog;
    s
}

/// Bits of the whole point state.
fn state_bits<const D: usize>(s: &Simulation<D>) -> Vec<u64> {
    let p = &s.points;
    let mut bits: Vec<u64> = Vec::new();
    for k in 0..p.len() {
        bits.extend(p.x[k].iter().chain(&p.v[k]).chain([&p.volume[k], &p.internal_energy[k], &p.visc_pressure[k]]).map(|v| v.to_bits()));
        bits.extend(p.stress[k].iter().flatten().chain(p.def_grad[k].iter().flatten()).map(|v| v.to_bits()));
    }
    bits
}

#[test]
fn every_scheme_gives_the_same_state_on_one_and_two_threads_in_1d_and_2d() {
    let on = |threads: usize, f: &(dyn Fn() -> Vec<u64> + Sync)| {
        rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool").install(f)
    };
    for (scheme, sub) in registry(1) {
        if scheme.maps_velocity_by_mls() {
            let run = || {
                let mut s = mls_bar(scheme);
                for _ in 0..30 {
                    s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
                }
                assert!(s.points.len() > 2 * continuum::par::CHUNK);
                state_bits(&s)
            };
            assert!(on(1, &run) == on(2, &run), "1D {scheme:?}: state differs between 1 and 2 threads");
            continue;
        }
        // A bar longer than one parallel chunk of points.
        let run = || {
            let grid = Grid::<1> { origin: [0.0], h: [1.0 / 320.0], cells: [320], faces: [(Face::Periodic, Face::Periodic)] };
            let pts = points(&grid, [0.0], [1.0], 2, 1e3, |x| [2.0 * (2.0 * PI * x[0]).sin() + 0.5]);
            let mut s = Simulation::new(grid, pts, scheme, vec![neo()], Viscosity::Linear { coefficient: 0.5 }, 0.4 / 320.0 / 117.0)
                .expect("builds")
                .with_sub_points(sub);
            for _ in 0..30 {
                s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
            }
            assert!(s.points.len() > 2 * continuum::par::CHUNK);
            state_bits(&s)
        };
        assert!(on(1, &run) == on(2, &run), "1D {scheme:?}: state differs between 1 and 2 threads");
    }
    for (scheme, sub) in registry(2) {
        let run = || {
            let mut s = free_block_2d(scheme, sub);
            // impm and tlmpm as scenes can run them (the validator requires the leapfrog).
            if matches!(scheme, SchemeKind::Impm | SchemeKind::Tlmpm) {
                s.integrator = TimeIntegrator::Leapfrog;
            }
            for _ in 0..20 {
                s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
            }
            state_bits(&s)
        };
        let (a, b) = (on(1, &run), on(2, &run));
        assert!(a.len() > 1000);
        assert!(a == b, "2D {scheme:?}: state differs between 1 and 2 threads");
    }
}

/// The weak isothermal shock tube of `scenes/shock-tube-weak.toml` (density 1.01 | 1, c = 1,
/// walls at both ends, 2 points per cell, linear viscosity 0.5, dt = 0.1 h/c, leapfrog) to
/// t = 0.25: the energy change (kinetic plus the points' stress work), the volume the points
/// gained over the box's length, and the largest kinetic energy.
fn weak_tube(scheme: SchemeKind, cells: usize) -> (f64, f64, f64) {
    let h = 1.0 / cells as f64;
    let grid = Grid::<1> { origin: [0.0], h: [h], cells: [cells], faces: [(Face::Reflective, Face::Reflective)] };
    let mut pts = points(&grid, [0.0], [1.0], 2, 1.0, |_| [0.0]);
    for p in 0..pts.len() {
        if pts.x[p][0] < 0.5 {
            pts.mass[p] *= 1.01;
        }
    }
    let gas: Box<dyn Closure> = Box::new(IdealGasIsothermal { sound_speed: 1.0 });
    let mut s = Simulation::new(grid, pts, scheme, vec![gas], Viscosity::Linear { coefficient: 0.5 }, 0.1 * h).expect("builds");
    s.integrator = TimeIntegrator::Leapfrog;
    let e0 = s.totals().energy();
    let mut ke: f64 = 0.0;
    for _ in 0..(0.25 / (0.1 * h)).round() as usize {
        s.step().unwrap_or_else(|e| panic!("{scheme:?}: {e}"));
        ke = ke.max(s.totals().kinetic);
    }
    (s.totals().energy() - e0, s.points.volume.iter().sum::<f64>() - 1.0, ke)
}

/// Why `impm` loses about the largest kinetic energy on the weak tube at every resolution
/// (`energy_drift` 0.99-1.01, continuum/docs/error-vs-time): Gong's step updates F_p with the hat
/// gradient at the point (notes A.2 step 6), sum_p V_p L_p, while the grid forces (which make
/// the kinetic energy) integrate the stress at the cell centres over the cells. The point sum
/// telescopes to the walls' zero velocity only where each cell's points fill exactly h; after
/// the gas has expanded or compressed, without a cell crossing, a cell's points fill h times
/// the volume ratio, so the points' total volume drifts by O(strain x velocity x time),
/// independent of h, and the gas's stored energy drops by the pressure times that volume. In
/// the acoustic limit that is of the order of the kinetic energy itself. cpdi's domain-integrated
/// gradient telescopes: its points keep the box's volume to round-off.
#[test]
fn impm_loses_the_pressure_times_the_volume_its_points_gain() {
    let (de_c, dv_c, ke_c) = weak_tube(SchemeKind::Cpdi, 125);
    eprintln!("cpdi 125 cells: energy change {de_c:e}, points' volume gained {dv_c:e}, largest kinetic {ke_c:e}");
    assert!(dv_c.abs() <= 1e-12, "cpdi: the points' volume drifted by {dv_c:e}");
    assert!(de_c.abs() <= 0.05 * ke_c, "cpdi: energy change {de_c:e} against the largest kinetic energy {ke_c:e}");
    let mut gained = Vec::new();
    for cells in [125, 250] {
        let (de, dv, ke) = weak_tube(SchemeKind::Impm, cells);
        eprintln!("impm {cells} cells: energy change {de:e}, points' volume gained {dv:e}, largest kinetic {ke:e}");
        // The loss is the mean pressure (1.005) times the volume gained, up to the leapfrog's
        // own share (cpdi's, a few per cent of the kinetic energy).
        assert!(de < -0.5 * ke, "impm {cells}: energy change {de:e} against the largest kinetic energy {ke:e}");
        assert!((de + 1.005 * dv).abs() <= 0.1 * de.abs(), "impm {cells}: energy change {de:e}, pressure x volume {:e}", 1.005 * dv);
        gained.push(dv);
    }
    let ratio = gained[1] / gained[0];
    assert!((0.8..=1.25).contains(&ratio), "impm: the volume gained should not shrink with h: {gained:?}");
}
