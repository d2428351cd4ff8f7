//! Manufactured solution (diagnostic): `cargo run --release -p continuum --example mms -- SCHEME D CELLS [G] [T] [ppc]`.
//! Prints the L2 displacement error sqrt(sum V0 |u - u_exact|^2) at time T (default 0.02 s).
use continuum::closure::{NeoHookean, lame};
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::{Face, Grid, Particles, SchemeKind, Simulation};
use std::f64::consts::PI;
use std::sync::Arc;

fn run<const D: usize>(scheme: SchemeKind, cells: usize, g: f64, t_end: f64, ppc: usize, cfl: f64, lf: bool) -> (f64, f64) {
    let (e, nu, rho0) = (1e7, 0.3, 1e3);
    let (lambda, mu) = lame(e, nu);
    let c = (e / rho0).sqrt();
    let h = 1.0 / cells as f64;
    let grid =
        Grid::<D> { origin: [0.0; D], h: [h; D], cells: [cells; D], faces: std::array::from_fn(|_| (Face::Reflective, Face::Reflective)) };
    let mut pts = Particles::default();
    let n = cells * ppc;
    let vol = h.powi(D as i32) / ppc.pow(D as u32) as f64;
    for k in 0..n.pow(D as u32) {
        let mut rem = k;
        let x: [f64; D] = std::array::from_fn(|_| {
            let i = rem % n;
            rem /= n;
            (i as f64 + 0.5) * h / ppc as f64
        });
        let v = std::array::from_fn(|a| c * PI * g * (PI * x[a]).sin());
        pts.push(0, x, v, rho0 * vol, vol, [0.5 * h / ppc as f64; D], Particles::<D>::identity());
    }
    let dt = cfl * h / c;
    let mut s = Simulation::new(
        grid,
        pts,
        scheme,
        vec![Box::new(NeoHookean { youngs_modulus: e, poisson_ratio: nu, density0: rho0 })],
        Viscosity::None,
        dt,
    )
    .expect("builds");
    if lf {
        s.integrator = TimeIntegrator::Leapfrog;
    }
    s.body_force = Some(Arc::new(move |x0: &[f64; D], t: f64| {
        let f: [f64; D] = std::array::from_fn(|a| 1.0 + PI * g * (PI * x0[a]).cos() * (c * PI * t).sin());
        let lnj = f.iter().map(|v| v.ln()).sum::<f64>();
        std::array::from_fn(|a| {
            let u = g * (PI * x0[a]).sin() * (c * PI * t).sin();
            PI * PI * u / rho0 * (lambda / (f[a] * f[a]) * (1.0 - lnj) + mu * (1.0 + 1.0 / (f[a] * f[a])) - e)
        })
    }));
    let steps = (t_end / dt).round() as usize;
    for _ in 0..steps {
        s.step().expect("step");
    }
    let t = s.time;
    let tv = if lf { t - 0.5 * dt } else { t };
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

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scheme = SchemeKind::from_name(&a[1]).expect("scheme");
    let d: usize = a[2].parse().expect("a number");
    let cells: usize = a[3].parse().expect("a number");
    let g: f64 = a.get(4).map(|s| s.parse().expect("a number")).unwrap_or(1e-4);
    let t: f64 = a.get(5).map(|s| s.parse().expect("a number")).unwrap_or(0.02);
    let ppc: usize = a.get(6).map(|s| s.parse().expect("a number")).unwrap_or(2);
    let lf = a.get(8).map(|s| s == "leapfrog").unwrap_or(false);
    let cfl: f64 = a.get(7).map(|s| s.parse().expect("a number")).unwrap_or(0.4);
    let (eu, ev) = match d {
        1 => run::<1>(scheme, cells, g, t, ppc, cfl, lf),
        2 => run::<2>(scheme, cells, g, t, ppc, cfl, lf),
        _ => run::<3>(scheme, cells, g, t, ppc, cfl, lf),
    };
    println!("{} {d}D h=1/{cells} G={g} T={t} ppc={ppc} cfl={cfl} leapfrog={lf}: displacement {eu:.4e} velocity {ev:.4e}", a[1]);
}
