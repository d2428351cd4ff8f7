//! Reference-configuration MPM in 1D (continuum::tlmpm; battery thesis 6.1, wave2 notes C.1):
//! a standing mode's frequency against the derived dispersion relation to round-off, the
//! stability bounds (moving mesh k <= 1, TLMPM at beta = 1 k <= sqrt 3), and the manufactured
//! solution at G = 0.1 converging at second order (no point ever crosses a cell).

use continuum::exact::Manufactured;
use continuum::tlmpm::{Bar, Form, Law1d, dispersion};

const TLMPM: Form = Form::Total { flip: 1.0 };

/// A fixed-end bar of `cells` cells, 2 points per cell, rho0 = E = 1 (c = 1), dt = k h.
fn unit_bar(form: Form, cells: usize, k: f64) -> Bar {
    let h = 1.0 / cells as f64;
    Bar::new(1.0, cells, 2, 1.0, Law1d::Linear { modulus: 1.0 }, form, k * h)
}

/// The mode m's coefficient of the nodal displacement (sum u_i sin(m pi X_i)).
fn project(bar: &Bar, m: usize) -> f64 {
    bar.node_u.iter().enumerate().map(|(i, u)| u * (m as f64 * std::f64::consts::PI * i as f64 * bar.h).sin()).sum()
}

/// A standing mode u = A sin(m pi X), at rest: its coefficient obeys
/// u^{n+1} + u^{n-1} = 2 cos(w dt) u^n; the least-squares cos(w dt) over 400 steps equals the
/// derived one (sin(w dt/2) = k sin(theta/2), times sqrt(1 - 3/4 sin^2(theta/2)) for TLMPM at
/// beta = 1) to round-off, for several modes and k.
#[test]
fn a_standing_mode_follows_the_derived_dispersion_relation_to_round_off() {
    let cells = 16;
    for form in [Form::MovingMesh, TLMPM] {
        for (m, k) in [(1, 0.5), (3, 0.9), (7, 1.0), (12, 0.3), (15, 1.0)] {
            let mut bar = unit_bar(form, cells, k);
            bar.set_displacement(|x| 1e-3 * (m as f64 * std::f64::consts::PI * x).sin());
            let mut u = vec![project(&bar, m)];
            for _ in 0..400 {
                bar.step().expect("stable");
                u.push(project(&bar, m));
            }
            let (num, den) = (1..u.len() - 1).fold((0.0, 0.0), |(a, b), n| (a + u[n] * (u[n + 1] + u[n - 1]), b + 2.0 * u[n] * u[n]));
            let measured = num / den;
            let theta = m as f64 * std::f64::consts::PI / cells as f64;
            let derived = dispersion(form, k, theta);
            eprintln!("{form:?} m = {m} k = {k}: cos(w dt) measured {measured:.16}, derived {derived:.16}");
            assert!((measured - derived).abs() < 1e-12, "{form:?} m = {m} k = {k}: {measured} vs {derived}");
            // And the mode stays a mode: no other mode is excited.
            let other = project(&bar, if m == 1 { 2 } else { m - 1 });
            assert!(other.abs() < 1e-12 * u[0].abs(), "{form:?}: mode {m} leaks {other:e}");
        }
    }
}

/// Random nodal noise on a fixed-end 16-cell bar, 3000 steps: bounded at the bound (moving
/// mesh k = 1, TLMPM beta = 1 at 0.99 sqrt 3), growing by more than 1e3 at 1.01 x the bound.
#[test]
fn reference_mpm_is_stable_at_its_bound_and_grows_above_it() {
    let cells = 16;
    let mut seed = 0x9e3779b97f4a7c15u64;
    let noise: Vec<f64> = (0..=cells)
        .map(|i| {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            if i == 0 || i == cells { 0.0 } else { 1e-8 * ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) }
        })
        .collect();
    for (form, bound) in [(Form::MovingMesh, 1.0), (TLMPM, 3f64.sqrt())] {
        for (factor, grows) in [(if form == Form::MovingMesh { 1.0 } else { 0.99 }, false), (1.01, true)] {
            let mut bar = unit_bar(form, cells, factor * bound);
            bar.set_displacement(|x| noise[(x * cells as f64).round() as usize]);
            let mut amp: f64 = 0.0;
            for _ in 0..3000 {
                if bar.step().is_err() {
                    amp = f64::INFINITY;
                    break;
                }
                amp = amp.max(bar.node_u.iter().fold(0.0f64, |a, u| a.max(u.abs())));
            }
            eprintln!("{form:?} at {factor} x {bound:.4}: largest nodal displacement {amp:e} (noise 5e-9)");
            if grows {
                assert!(amp > 1e-5, "{form:?}: grows above the bound ({amp:e})");
            } else {
                assert!(amp < 1e-7, "{form:?}: bounded at the bound ({amp:e})");
            }
        }
    }
    // The derived bounds: the discrete modes theta = m pi / 16 at the bound stay in [-1, 1].
    for m in 1..cells {
        let theta = m as f64 * std::f64::consts::PI / cells as f64;
        assert!(dispersion(Form::MovingMesh, 1.0, theta) >= -1.0 && dispersion(TLMPM, 3f64.sqrt(), theta) >= -1.0);
    }
}

/// Gong's manufactured solution (scenes/mms-1d.toml's: E = 1e7, nu = 0.3, rho0 = 1e3,
/// G = 0.1, rollers, T = 0.02 s, dt = 0.4 h / c, 2 points per cell) with the neo-Hookean law
/// in PK1 form: L2 errors at T over h = 1/8 ... 1/64.
fn mms(form: Form, cells: usize) -> [f64; 3] {
    let m = Manufactured { amplitude: 0.1, youngs_modulus: 1e7, poisson_ratio: 0.3, density0: 1e3 };
    let (lambda, mu) = continuum::closure::lame(m.youngs_modulus, m.poisson_ratio);
    let h = 1.0 / cells as f64;
    let dt = 0.4 * h / m.speed();
    let steps = (0.02 / dt).round() as usize;
    let mut bar = Bar::new(1.0, cells, 2, m.density0, Law1d::NeoHookean { lambda, mu }, form, dt);
    bar.set_velocity(|x| m.velocity(x, 0.0));
    bar.body_force = Some(Box::new(move |x, t| m.body_force(&[x], t)[0]));
    for _ in 0..steps {
        bar.step().expect("no inversion");
    }
    let (t, tv) = (bar.time, bar.time - 0.5 * dt);
    let (mut eu, mut ev, mut es) = (0.0, 0.0, 0.0);
    for p in 0..bar.x0.len() {
        let (x0, v0) = (bar.x0[p], bar.volume0[p]);
        eu += v0 * (bar.x[p] - x0 - m.displacement(x0, t)).powi(2);
        ev += v0 * (bar.v[p] - m.velocity(x0, tv)).powi(2);
        es += v0 * (bar.piola[p] - m.stress(&[x0], t)[0][0]).powi(2);
    }
    [eu.sqrt(), ev.sqrt(), es.sqrt()]
}

/// Measured orders (displacement, velocity, stress), 1/8 -> 1/16 -> 1/32 -> 1/64:
/// moving mesh 2.00 / 1.77 / 2.03, 2.00 / 1.93 / 2.01, 2.00 / 1.97 / 2.00; TLMPM (FLIP)
/// 2.03 / 1.63 / 2.10, 2.01 / 1.90 / 2.03, 2.00 / 1.97 / 2.01; TLMPM PIC 0.90-0.98 (first order).
#[test]
fn the_manufactured_solution_at_g_0_1_converges_at_second_order() {
    let mut all = Vec::new();
    for form in [Form::MovingMesh, TLMPM, Form::Total { flip: 0.0 }] {
        let e: Vec<[f64; 3]> = [8, 16, 32, 64].iter().map(|&n| mms(form, n)).collect();
        let orders: Vec<[f64; 3]> = e.windows(2).map(|w| std::array::from_fn(|q| (w[0][q] / w[1][q]).log2())).collect();
        eprintln!("{form:?} G = 0.1: errors (u, v, P) {e:?}\n  orders {orders:.3?}");
        all.push((form, orders));
    }
    for (form, orders) in all {
        if form == (Form::Total { flip: 0.0 }) {
            // PIC: the re-map's O(h) dissipation every step makes it first order.
            assert!(orders.iter().all(|o| o.iter().all(|&o| (0.8..1.1).contains(&o))), "PIC: first order {orders:?}");
            continue;
        }
        // Displacement and stress second order from the start; the velocity reaches it (1.63 /
        // 1.77 on the coarsest pair, 1.97 on the finest).
        assert!(orders.iter().all(|o| o[0] >= 1.95 && o[2] >= 1.95), "{form:?}: second order {orders:?}");
        assert!(orders.iter().all(|o| o[1] >= 1.6) && orders[2][1] >= 1.95, "{form:?}: velocity {orders:?}");
    }
}
