//! Weak isothermal shock tube (diagnostic): `cargo run --release -p continuum --example tube -- SCHEME PPC SUB [dump]`.
use continuum::closure::IdealGasIsothermal;
use continuum::exact::{IsothermalRiemann, State, pressure_errors};
use continuum::solver::Viscosity;
use continuum::{Closure, Face, Grid, Particles, SchemeKind, Simulation};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scheme = SchemeKind::from_name(&a[1]).expect("scheme");
    let ppc: usize = a[2].parse().expect("a number");
    let sub: usize = a[3].parse().expect("a number");
    let ratio: f64 = a.get(5).map(|s| s.parse().expect("a number")).unwrap_or(1.01);
    let cells = 500;
    let grid = Grid::<1> { origin: [0.0], h: [1.0 / cells as f64], cells: [cells], faces: [(Face::Reflective, Face::Reflective)] };
    let mut pts = Particles::default();
    let v = grid.h[0] / ppc as f64;
    for k in 0..cells * ppc {
        let x = (k as f64 + 0.5) * v;
        let (b, rho) = if x < 0.5 { (0, ratio) } else { (1, 1.0) };
        pts.push(b, [x], [0.0], rho * v, v, [0.5 * v], Particles::<1>::identity());
    }
    let gas = || -> Box<dyn Closure> { Box::new(IdealGasIsothermal { sound_speed: 1.0 }) };
    let mut sim = Simulation::new(grid, pts, scheme, vec![gas(), gas()], Viscosity::Linear { coefficient: 0.5 }, 0.1 / cells as f64)
        .expect("tube")
        .with_sub_points(sub);
    let steps = 1250;
    for _ in 0..steps {
        sim.step().expect("step");
    }
    let rp = IsothermalRiemann::new(State { density: ratio, velocity: 0.0 }, State { density: 1.0, velocity: 0.0 }, 1.0, 0.5);
    let x: Vec<f64> = sim.points.x.iter().map(|x| x[0]).collect();
    let p: Vec<f64> = (0..sim.points.len()).map(|k| sim.points.pressure(k)).collect();
    let jump = ratio - 1.0;
    let e = pressure_errors(&x, &p, |xk| rp.pressure(xk, sim.time), jump, 1.0 / cells as f64);
    println!("{} ppc {ppc} sub {sub}: L1 {:.4e} L2 {:.4e} spike {:.4e}", a[1], e.l1, e.l2, e.spike);
    // The DDMP-effective pressure at the points, sigma + sigma_A of (3.25) read at x_p:
    // alpha P_p + (1 - alpha) sum_j S_j(x_p) P_j with P_j = sum_q V_q P_q S_j(x_q) / V_j.
    let h = 1.0 / cells as f64;
    let shape = |x: f64| {
        let c = ((x / h).floor() as usize).min(cells - 1);
        let xi = x / h - c as f64;
        (c, [1.0 - xi, xi])
    };
    let mut pj = vec![0.0; cells + 1];
    for k in 0..x.len() {
        let (c, s) = shape(x[k]);
        for m in 0..2 {
            pj[c + m] += sim.points.volume[k] * p[k] * s[m];
        }
    }
    for (j, v) in pj.iter_mut().enumerate() {
        *v /= if j == 0 || j == cells { 0.5 * h } else { h };
    }
    let p_eff: Vec<f64> = (0..x.len())
        .map(|k| {
            let (c, s) = shape(x[k]);
            let alpha = 0.5 * (4.0 * s[0] * s[1]).powf(1.5);
            alpha * p[k] + (1.0 - alpha) * (s[0] * pj[c] + s[1] * pj[c + 1])
        })
        .collect();
    let e2 = pressure_errors(&x, &p_eff, |xk| rp.pressure(xk, sim.time), jump, 1.0 / cells as f64);
    println!("  DDMP-effective pressure (sigma + sigma_A at x_p): L1 {:.4e} L2 {:.4e} spike {:.4e}", e2.l1, e2.l2, e2.spike);
    if a.get(4).map(|s| s == "dump").unwrap_or(false) {
        for k in 0..x.len() {
            println!("{:.6} {:.6} {:.6} {:.6}", sim.points.x0[k][0], x[k], (p[k] - 1.0) / jump, (rp.pressure(x[k], sim.time) - 1.0) / jump);
        }
    }
}
