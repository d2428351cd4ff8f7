//! Weak isothermal shock tube (diagnostic): `cargo run --release -p continuum --example tube -- SCHEME PPC SUB [dump]`.
use continuum::closure::IdealGasIsothermal;
use continuum::exact::{pressure_errors, IsothermalRiemann, State};
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
    let mut sim = Simulation::new(grid, pts, scheme, vec![gas(), gas()], Viscosity::Linear { coefficient: 0.5 }, 0.1 / cells as f64).expect("tube").with_sub_points(sub);
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
    if a.get(4).map(|s| s == "dump").unwrap_or(false) {
        for k in 0..x.len() {
            println!("{:.6} {:.6} {:.6} {:.6}", sim.points.x0[k][0], x[k], (p[k] - 1.0) / jump, (rp.pressure(x[k], sim.time) - 1.0) / jump);
        }
    }
}
