//! The derived linear CFL bounds (continuum::stability) against the solver itself: a bar of
//! the linear law sigma = E (F - 1), a random perturbation of 1e-8 (no point leaves its cell),
//! run at 0.99 and 1.01 of the bound the analysis gives for that bar's waves. Below, the
//! perturbation stays bounded; above, it grows by orders of magnitude. Also a single wave's
//! frequency and growth per step against the eigenvalues of the analysis.

use continuum::Particles;
use continuum::closure::LinearPiola;
use continuum::grid::{Face, Grid};
use continuum::shape::SchemeKind;
use continuum::solver::{Simulation, TimeIntegrator, Viscosity};
use continuum::stability::{self, Layout, Symbol};
use continuum::tensor::IDENTITY;

const CELLS: usize = 16;

/// A bar of `CELLS` unit cells (rho = E = 1, so c = 1 and cfl = dt), `ppc` points per cell,
/// velocities `v(x)`.
fn bar(layout: Layout, integrator: TimeIntegrator, flip: f64, cfl: f64, v: impl Fn(usize, f64) -> f64) -> Simulation<1> {
    // The MLS velocity maps (impm, cpdi-improved) do not wrap around a periodic axis: a bar
    // with fixed ends, the perturbation in its interior cells.
    let periodic = !layout.scheme.maps_velocity_by_mls();
    let face = if periodic { Face::Periodic } else { Face::Fixed };
    let grid = Grid::<1> { origin: [0.0], h: [1.0], cells: [CELLS], faces: [(face.clone(), face)] };
    let n = layout.particles_per_cell;
    let mut pts = Particles::default();
    for c in 0..CELLS {
        for k in 0..n {
            let x = c as f64 + (k as f64 + 0.5) / n as f64;
            let vel = if periodic || (1..CELLS - 1).contains(&c) { v(c * n + k, x) } else { 0.0 };
            pts.push(0, [x], [vel], 1.0 / n as f64, 1.0 / n as f64, [0.5 / n as f64], IDENTITY);
        }
    }
    let law = LinearPiola { youngs_modulus: 1.0, poisson_ratio: 0.0, density0: 1.0 };
    let mut sim = Simulation::new(grid, pts, layout.scheme, vec![Box::new(law)], Viscosity::None, cfl)
        .expect("builds")
        .with_sub_points(layout.sub_points);
    sim.integrator = integrator;
    sim.flip_fraction = flip;
    sim
}

/// sqrt(sum_p m v^2 + V sigma^2 / E): the perturbation's size.
fn size(sim: &Simulation<1>) -> f64 {
    let p = &sim.points;
    (0..p.len()).map(|k| p.mass[k] * p.v[k][0].powi(2) + p.volume[k] * p.stress[k][0][0].powi(2)).sum::<f64>().sqrt()
}

/// Deterministic noise in [-1, 1].
fn noise(k: usize) -> f64 {
    let mut x = (k as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    x ^= x >> 31;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x ^= x >> 29;
    (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// Growth of a random perturbation over `steps` steps (largest size over the run / initial),
/// or infinity if the guard stopped the run.
fn growth(layout: Layout, integrator: TimeIntegrator, flip: f64, cfl: f64, steps: usize) -> f64 {
    let mut sim = bar(layout, integrator, flip, cfl, |k, _| 1e-8 * noise(k));
    let start = size(&sim);
    let mut largest: f64 = start;
    for _ in 0..steps {
        if sim.step().is_err() {
            return f64::INFINITY;
        }
        largest = largest.max(size(&sim));
    }
    largest / start
}

fn layouts() -> Vec<Layout> {
    let mut v = Vec::new();
    for scheme in [SchemeKind::Mpm, SchemeKind::Ugimp, SchemeKind::Cpgimp, SchemeKind::Cpdi, SchemeKind::Ddmp, SchemeKind::Impm] {
        for n in [1, 2] {
            if scheme == SchemeKind::Impm && n == 1 {
                // One point per cell: the quadratic MLS support of a cell centre holds too few
                // distinct points near the ends; IMPM is run with 2 and more.
                continue;
            }
            v.push(Layout { scheme, particles_per_cell: n, sub_points: 1 });
        }
    }
    v.push(Layout { scheme: SchemeKind::DdmpSubpoints, particles_per_cell: 2, sub_points: 4 });
    // The improved CPDI: the CPDI stencil with the MLS velocity map (2 points per cell, as the
    // MLS support needs near the ends).
    v.push(Layout { scheme: SchemeKind::CpdiImproved, particles_per_cell: 2, sub_points: 1 });
    v
}

fn integrators(scheme: SchemeKind) -> Vec<TimeIntegrator> {
    if scheme == SchemeKind::Impm {
        vec![TimeIntegrator::Leapfrog]
    } else {
        vec![TimeIntegrator::Usl, TimeIntegrator::Leapfrog, TimeIntegrator::Usf, TimeIntegrator::StormerVerlet]
    }
}

/// Every scheme with usl, leapfrog, usf and stormer-verlet (impm: leapfrog), FLIP and a 0.5 blend
/// (stormer-verlet: FLIP): bounded at
/// 0.99 of the bound, growing at 1.01 (impm, and cpdi-improved with usf: bounded at 0.99 of the
/// validator's cap of 1, below their interior bound, which is not sufficient at the bar's fixed
/// ends).
#[test]
fn every_explicit_combination_is_stable_below_its_derived_bound_and_grows_above() {
    let mut table = String::new();
    let mut failures = Vec::new();
    for layout in layouts() {
        for integrator in integrators(layout.scheme) {
            // Stormer-Verlet is FLIP only.
            let blends: &[f64] = if integrator == TimeIntegrator::StormerVerlet { &[1.0] } else { &[1.0, 0.5] };
            for &flip in blends {
                let waves =
                    if layout.scheme.maps_velocity_by_mls() { stability::all_waves() } else { stability::waves_of_periodic_bar(CELLS) };
                let syms = stability::symbols(layout, &waves).unwrap();
                let bound = stability::bound_of(integrator, flip, &syms).unwrap();
                // cpdi-improved with usf: the interior bound (1.96 FLIP, 1.82 at 0.5) is not
                // sufficient at the fixed bar's ends (measured growth 4.9e5 / 6.6e5 at 0.99 of
                // it); what the validator enforces there is its cap cfl <= 1, so the bar is run
                // below that cap.
                // IMPM likewise (its interior bound 1.18 at 2 points per cell).
                let end_modes =
                    layout.scheme == SchemeKind::Impm || (layout.scheme == SchemeKind::CpdiImproved && integrator == TimeIntegrator::Usf);
                let cap = if end_modes { 1.0 } else { f64::INFINITY };
                let below_at = 0.99 * bound.min(cap);
                let below = growth(layout, integrator, flip, below_at, 3000);
                let above = growth(layout, integrator, flip, 1.01 * bound, 3000);
                let line = format!(
                    "{} N={} x{} {:?} flip {flip}: bound {bound:.4}, growth {below:.3e} at cfl {below_at:.4}, {above:.3e} at 1.01 of the bound\n",
                    layout.scheme.name(),
                    layout.particles_per_cell,
                    layout.sub_points,
                    integrator
                );
                table.push_str(&line);
                // IMPM's bound is the interior analysis (MLS maps at a node far from the ends);
                // the fixed bar's end modes are less stable: measured growth 3.3e6 over 3000 steps
                // at 0.99 of it, so it is run below the cap.
                let bounded_below = below < 10.0;
                if !(bounded_below && above > 1e3) {
                    failures.push(line);
                }
            }
        }
    }
    println!("{table}");
    assert!(failures.is_empty(), "not bounded below / growing above the derived bound:\n{}", failures.concat());
}

/// `scheme.method = "tlmpm"` (the solver's total-Lagrangian step, leapfrog): its own derived
/// bound ([`stability::tlmpm_bound_of`]: sqrt 3 at 2 points per cell, FLIP), not the usl one,
/// at 1 and 2 points per cell, FLIP and a 0.5 blend: bounded at 0.99, growing at 1.01.
#[test]
fn tlmpm_is_stable_below_its_derived_bound_and_grows_above() {
    let mut failures = Vec::new();
    for n in [1, 2] {
        let layout = Layout { scheme: SchemeKind::Tlmpm, particles_per_cell: n, sub_points: 1 };
        for flip in [1.0, 0.5] {
            let syms = stability::symbols(layout, &stability::waves_of_periodic_bar(CELLS)).unwrap();
            let bound = stability::tlmpm_bound_of(flip, &syms).unwrap();
            let below = growth(layout, TimeIntegrator::Leapfrog, flip, 0.99 * bound, 3000);
            let above = growth(layout, TimeIntegrator::Leapfrog, flip, 1.01 * bound, 3000);
            let line = format!("tlmpm N={n} flip {flip}: bound {bound:.4}, growth {below:.3e} at 0.99, {above:.3e} at 1.01\n");
            print!("{line}");
            if n == 2 && flip == 1.0 {
                // Over every wave number (the 16-cell bar's waves miss sin^2(theta/2) = 2/3).
                let all = stability::tlmpm_bound_of(flip, &stability::symbols(layout, &stability::all_waves()).unwrap()).unwrap();
                assert!((all - 3f64.sqrt()).abs() < 1e-6 && bound >= all, "{line} (all waves {all})");
            }
            if !(below < 10.0 && above > 1e3) {
                failures.push(line);
            }
        }
    }
    assert!(failures.is_empty(), "not bounded below / growing above the derived bound:\n{}", failures.concat());
}

/// tlmpm's moving mesh (the nodal velocity carried): bounded at 0.99 of its derived bound (1 at
/// any number of points per cell: the leapfrog on the hats' stiffness) and growing at 1.01.
#[test]
fn the_moving_mesh_is_stable_below_its_derived_bound_and_grows_above() {
    let mut failures = Vec::new();
    for n in [1, 2, 3] {
        let layout = Layout { scheme: SchemeKind::Tlmpm, particles_per_cell: n, sub_points: 1 };
        let bound = stability::moving_mesh_bound(layout).unwrap().unwrap();
        let run = |cfl: f64| {
            let mut sim = bar(layout, TimeIntegrator::Leapfrog, 1.0, cfl, |k, _| 1e-8 * noise(k));
            sim.moving_mesh = true;
            let start = size(&sim);
            let mut largest: f64 = start;
            for _ in 0..3000 {
                if sim.step().is_err() {
                    return f64::INFINITY;
                }
                largest = largest.max(size(&sim));
            }
            largest / start
        };
        let (below, above) = (run(0.99 * bound), run(1.01 * bound));
        let line = format!("moving mesh N={n}: bound {bound:.4}, growth {below:.3e} at 0.99, {above:.3e} at 1.01\n");
        print!("{line}");
        if !((bound - 1.0).abs() < 1e-6 && below < 10.0 && above > 1e3) {
            failures.push(line);
        }
    }
    assert!(failures.is_empty(), "not bounded below / growing above the derived bound:\n{}", failures.concat());
}

/// One smooth wave (theta = 2 pi / CELLS) on an MPM bar: its per-step rotation (the frequency)
/// and modulus (growth) as measured match the eigenvalue of the analysis, for usl (neutral),
/// usf, and dhakal (growing at every dt: the first-order cycle).
#[test]
fn a_single_wave_turns_and_grows_as_the_analysis_says() {
    let layout = Layout { scheme: SchemeKind::Mpm, particles_per_cell: 2, sub_points: 1 };
    let theta = 2.0 * std::f64::consts::PI / CELLS as f64;
    let sym: Symbol = stability::symbols(layout, &[theta]).unwrap()[0];
    for integrator in [TimeIntegrator::Usl, TimeIntegrator::Usf, TimeIntegrator::Dhakal] {
        let cfl = 0.5;
        let lambda = stability::eigenvalues(&stability::amplification(integrator, 1.0, &sym, cfl));
        let l = lambda.iter().copied().max_by(|a, b| a.im.total_cmp(&b.im)).unwrap();
        let (omega_dt, modulus) = (l.im.atan2(l.re), l.norm());
        // A standing wave v = 1e-8 sin(theta x).
        let mut sim = bar(layout, integrator, 1.0, cfl, |_, x| 1e-8 * (theta * x).sin());
        let project = |sim: &Simulation<1>| {
            let p = &sim.points;
            let (mut a, mut b) = (0.0, 0.0);
            for k in 0..p.len() {
                a += p.mass[k] * p.v[k][0] * (theta * p.x0[k][0]).sin();
                b += p.volume[k] * p.stress[k][0][0] * (theta * p.x0[k][0]).cos();
            }
            (a, b)
        };
        let steps = 400;
        let mut series = Vec::new();
        for _ in 0..steps {
            sim.step().unwrap();
            series.push(project(&sim));
        }
        // The stress starts at zero and only ever changes by dt E G^T v^L, all of which the grid
        // sees (the velocity projection also holds the points' constant null-space part), so its
        // projection follows the eigenvalue pair alone: zero crossings give the frequency, the
        // peaks of successive half periods the modulus.
        let z: Vec<f64> = series.iter().map(|s| s.1).collect();
        let crossings: Vec<f64> =
            (1..steps).filter(|&k| z[k - 1].signum() != z[k].signum()).map(|k| (k - 1) as f64 + z[k - 1] / (z[k - 1] - z[k])).collect();
        assert!(crossings.len() >= 3, "{integrator:?}: {} crossings", crossings.len());
        let half_period = (crossings[crossings.len() - 1] - crossings[0]) / (crossings.len() - 1) as f64;
        let measured_omega_dt = std::f64::consts::PI / half_period;
        assert!(
            (measured_omega_dt - omega_dt).abs() < 2e-3 * omega_dt,
            "{integrator:?}: omega dt measured {measured_omega_dt}, analysis {omega_dt}"
        );
        // Growth: the amplitude of the velocity projection over the crossings' half periods.
        let peak = |from: f64, to: f64| z[from.ceil() as usize..to.floor() as usize].iter().map(|v| v.abs()).fold(0.0, f64::max);
        let k = crossings.len() - 1;
        let (first, last) = (peak(crossings[0], crossings[1]), peak(crossings[k - 1], crossings[k]));
        let measured = (last / first).powf(1.0 / (crossings[k - 1] - crossings[0]));
        assert!((measured - modulus).abs() < 1e-4, "{integrator:?}: growth per step measured {measured}, analysis {modulus}");
        println!(
            "{integrator:?}: omega dt {omega_dt:.6} (measured {measured_omega_dt:.6}), |lambda| {modulus:.6} (measured {measured:.6})"
        );
    }
}
