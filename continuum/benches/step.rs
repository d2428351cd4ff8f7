//! Benchmark of the continuum step (issue 3, "Performance"). Run with
//! `CARGO_TARGET_DIR=... cargo bench -p continuum --bench step`; prints medians of 5 runs.

use continuum::closure::{IdealGasIsothermal, LinearElastic};
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::{Closure, Face, Grid, Particles, SchemeKind, Simulation};
use std::time::Instant;

/// The jet layout of Dhakal Ch. 7: 100 x 50 cells over 144 x 72 nm, 2 x 2 points per cell,
/// a 36 nm triangular notch in the top face, moving down at 2.5 km/s onto a fixed wall.
fn jet(sub: usize) -> Simulation<2> {
    let (lx, ly) = (144e-9, 72e-9);
    let grid = Grid::<2> {
        origin: [0.0; 2],
        h: [lx / 100.0, ly / 50.0],
        cells: [100, 50],
        faces: [(Face::Reflective, Face::Reflective), (Face::Fixed, Face::Free)],
    };
    let mut pts = Particles::default();
    let ppc = 2;
    let vol = grid.cell_volume() / 4.0;
    let rho = 8960.0;
    for j in 0..50 * ppc {
        for i in 0..100 * ppc {
            let x = [(i as f64 + 0.5) * grid.h[0] / ppc as f64, (j as f64 + 0.5) * grid.h[1] / ppc as f64];
            let below_top = ly - x[1];
            let half_width = 0.5 * 36e-9 * (1.0 - below_top / 36e-9);
            if below_top < 36e-9 && (x[0] - 0.5 * lx).abs() < half_width {
                continue;
            }
            pts.push(
                0,
                x,
                [0.0, -2500.0],
                rho * vol,
                vol,
                [0.5 * grid.h[0] / ppc as f64, 0.5 * grid.h[1] / ppc as f64],
                Particles::<2>::identity(),
            );
        }
    }
    let law: Box<dyn Closure> = Box::new(LinearElastic { youngs_modulus: 130e9, poisson_ratio: 0.34, density0: rho });
    let c = law.wave_speed(&pts.mass, &pts.volume);
    let dt = 0.2 * grid.h[1] / (c + 2500.0);
    Simulation::new(grid, pts, SchemeKind::DdmpSubpoints, vec![law], Viscosity::Tensor { linear: 1.5, quadratic: 2.0 }, dt)
        .expect("jet builds")
        .with_sub_points(sub)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn weak_tube(scheme: SchemeKind, ppc: usize, sub: usize) -> Simulation<1> {
    let cells = 500;
    let grid = Grid::<1> { origin: [0.0], h: [1.0 / cells as f64], cells: [cells], faces: [(Face::Reflective, Face::Reflective)] };
    let mut pts = Particles::default();
    let v = grid.h[0] / ppc as f64;
    for k in 0..cells * ppc {
        let x = (k as f64 + 0.5) * v;
        let (b, rho) = if x < 0.5 { (0, 1.01) } else { (1, 1.0) };
        pts.push(b, [x], [0.0], rho * v, v, [0.5 * v], Particles::<1>::identity());
    }
    let gas = || -> Box<dyn Closure> { Box::new(IdealGasIsothermal { sound_speed: 1.0 }) };
    Simulation::new(grid, pts, scheme, vec![gas(), gas()], Viscosity::Linear { coefficient: 0.5 }, 0.1 * v * ppc as f64)
        .expect("tube builds")
        .with_sub_points(sub)
}

fn main() {
    let runs = 5;
    let steps = 20;
    // 1- and 2-thread runs alternate, so a load that comes and goes on a shared machine hits
    // both alike; the speed-up is the ratio of the medians.
    let pools: Vec<_> = [1, 2].map(|n| (n, rayon::ThreadPoolBuilder::new().num_threads(n).build().expect("pool"))).into();
    let mut times = vec![Vec::new(); pools.len()];
    let mut points = 0;
    for _ in 0..runs {
        for ((_, pool), t) in pools.iter().zip(&mut times) {
            pool.install(|| {
                let mut sim = jet(8);
                sim.step().expect("warm-up step");
                points = sim.points.len();
                let t0 = Instant::now();
                for _ in 0..steps {
                    sim.step().expect("step");
                }
                t.push(t0.elapsed().as_secs_f64() / steps as f64);
            });
        }
    }
    let per_thread: Vec<f64> = times.into_iter().map(median).collect();
    for ((threads, _), t) in pools.iter().zip(&per_thread) {
        let rate = (points * 8) as f64 / t;
        println!(
            "jet 100x50 cells, {points} points x 8 sub-points, {threads} thread(s): {:.3} ms/step, {:.2e} sub-point updates/s ({:.2e} per thread)",
            t * 1e3,
            rate,
            rate / *threads as f64
        );
    }
    println!("speed-up on 2 threads: {:.2}x (median of {runs} interleaved runs of {steps} steps each)", per_thread[0] / per_thread[1]);
    // The weak shock tube (500 cells) under the 1D schemes whose cost users compare: DDMP with
    // sub-points, and the improved schemes of issue 17 (IMPM needs the leapfrog).
    let tubes = [
        ("ddmp 32 per cell", SchemeKind::Ddmp, 32, 1, TimeIntegrator::Dhakal),
        ("ddmp-subpoints 2 x 16", SchemeKind::DdmpSubpoints, 2, 16, TimeIntegrator::Dhakal),
        ("cpdi 2 per cell", SchemeKind::Cpdi, 2, 1, TimeIntegrator::Dhakal),
        ("cpdi-improved 2 per cell", SchemeKind::CpdiImproved, 2, 1, TimeIntegrator::Dhakal),
        ("impm 2 per cell, leapfrog", SchemeKind::Impm, 2, 1, TimeIntegrator::Leapfrog),
    ];
    for (name, scheme, ppc, sub, integrator) in tubes {
        let mut times = Vec::new();
        let mut updates = 0;
        for _ in 0..runs {
            let mut sim = weak_tube(scheme, ppc, sub);
            sim.integrator = integrator;
            updates = sim.points.len() * sub * 1250;
            let t0 = Instant::now();
            for _ in 0..1250 {
                sim.step().expect("tube step");
            }
            times.push(t0.elapsed().as_secs_f64());
        }
        let t = median(times);
        println!(
            "weak shock tube, {name}: {t:.3} s for 1250 steps, {:.2e} (sub-)point updates/s (median of {runs}, default thread pool)",
            updates as f64 / t
        );
    }
}
