//! Time per explicit step, per implicit step and per Newton iteration on one 2D grid (issue 18's
//! measurement): `cargo run --release -p continuum --example implicit_timing -- [cells] [steps]`.
//! A neo-Hookean block of cells x cells cells, 2 x 2 points per cell, free faces, a swirling
//! velocity; explicit leapfrog at CFL 0.5, implicit at CFL 5 (analytic Jacobian).

use continuum::closure::NeoHookean;
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::{Face, Grid, Particles, SchemeKind, Simulation};
use std::time::Instant;

fn block(cells: usize, cfl: f64, integrator: TimeIntegrator) -> Simulation<2> {
    let h = 1.0 / cells as f64;
    let grid =
        Grid::<2> { origin: [0.0; 2], h: [h; 2], cells: [cells + 4; 2], faces: [(Face::Free, Face::Free), (Face::Free, Face::Free)] };
    let mut pts = Particles::default();
    let n = 2 * cells;
    let vol = h * h / 4.0;
    for k in 0..n * n {
        let x = [2.0 * h + (k % n) as f64 * h / 2.0 + h / 4.0, 2.0 * h + (k / n) as f64 * h / 2.0 + h / 4.0];
        let v = [0.5 * (3.0 * x[1]).sin(), -0.5 * (x[0] - 0.5)];
        pts.push(0, x, v, 1e3 * vol, vol, [h / 4.0; 2], Particles::<2>::identity());
    }
    let law = NeoHookean { youngs_modulus: 1e7, poisson_ratio: 0.3, density0: 1e3 };
    let c = ((continuum::closure::lame(1e7, 0.3).0 + 2.0 * continuum::closure::lame(1e7, 0.3).1) / 1e3).sqrt();
    let mut s = Simulation::new(grid, pts, SchemeKind::Mpm, vec![Box::new(law)], Viscosity::None, cfl * h / c).expect("builds");
    s.integrator = integrator;
    s
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let cells: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(64);
    let steps: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(5);
    let mut e = block(cells, 0.5, TimeIntegrator::Leapfrog);
    let t = Instant::now();
    for _ in 0..steps {
        e.step().expect("explicit step");
    }
    let explicit = t.elapsed().as_secs_f64() / steps as f64;
    let mut i = block(cells, 5.0, TimeIntegrator::ImplicitTrapezoidal);
    let t = Instant::now();
    for _ in 0..steps {
        i.step().expect("implicit step");
    }
    let implicit = t.elapsed().as_secs_f64() / steps as f64;
    let st = &i.implicit.stats;
    let per_iteration = st.seconds_total / st.newton_iterations.max(1) as f64;
    println!(
        "{} points, {} unknowns: explicit step {explicit:.4e} s; implicit step {implicit:.4e} s ({:.2} Newton iterations; per iteration {per_iteration:.4e} s: residual {:.1} %, Jacobian {:.1} %, LU solve {:.1} %)",
        i.points.len(),
        st.unknowns,
        st.newton_iterations as f64 / st.accepted_steps as f64,
        100.0 * st.seconds_residual / st.seconds_total,
        100.0 * st.seconds_jacobian / st.seconds_total,
        100.0 * st.seconds_solve / st.seconds_total
    );
    println!("crossover: implicit wins when its dt exceeds {:.1} explicit steps", implicit / explicit);
}
