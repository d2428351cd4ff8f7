//! Scalar diffusion carried by material points (continuum::diffusion): exact conservation,
//! the heat problems of the battery thesis (Table 6.1 in 1D, Table 6.2 in 2D), convergence at t = 0.25 (B 7.1.2),
//! and the corrected explicit bound on pre-strained bars.

use continuum::closure::LinearElastic;
use continuum::diffusion::{
    Configuration, Diffusion, DiffusivityLaw, DirichletMode, FaceCondition, explicit_bound, heat_series, heat_series_2d,
};
use continuum::shape::Stencil;
use continuum::solver::Viscosity;
use continuum::tensor::IDENTITY;
use continuum::{Face, Grid, Particles, SchemeKind, Simulation};

/// A bar on [0, 1] of `cells` cells with `ppc` points per cell at rest under a zero-stress
/// elastic law (the mechanics does nothing), carrying c = 0, F = diag(j, 1, 1).
fn bar(cells: usize, ppc: usize, j: f64) -> (Grid<1>, Particles<1>) {
    let h = 1.0 / cells as f64;
    let grid = Grid { origin: [0.0], h: [h], cells: [cells], faces: [(Face::Free, Face::Free)] };
    let mut pts = Particles::default();
    let mut f = IDENTITY;
    f[0][0] = j;
    let v0 = h / ppc as f64;
    for k in 0..cells * ppc {
        let x = (k as f64 + 0.5) * v0;
        pts.push(0, [x], [0.0], v0, v0, [0.5 * v0], f);
    }
    pts.with_fields(true, false);
    (grid, pts)
}

fn heat_sim(
    scheme: SchemeKind,
    cells: usize,
    ppc: usize,
    dt: f64,
    faces: (Option<FaceCondition>, Option<FaceCondition>),
    mode: DirichletMode,
    beta: f64,
) -> Simulation<1> {
    let (grid, pts) = bar(cells, ppc, 1.0);
    let law = LinearElastic { youngs_modulus: 1.0, poisson_ratio: 0.0, density0: 1.0 };
    let mut sim = Simulation::new(grid, pts, scheme, vec![Box::new(law)], Viscosity::None, dt).expect("builds");
    let mut d = Diffusion::new(1.0, [faces]);
    d.dirichlet = mode;
    d.flip = beta;
    sim.diffusion = Some(d);
    sim
}

/// RMS of (c_p - exact) over the points (B 6.97 with its square).
fn rms(sim: &Simulation<1>, exact: impl Fn(f64) -> f64) -> f64 {
    let p = &sim.points;
    (p.scalar.iter().zip(&p.x).map(|(c, x)| (c - exact(x[0])).powi(2)).sum::<f64>() / p.len() as f64).sqrt()
}

#[test]
fn content_changes_by_exactly_the_boundary_source() {
    let cases = [
        (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0)), DirichletMode::Rate, 1.0),
        (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0)), DirichletMode::Value, 1.0),
        (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0)), DirichletMode::Rate, 0.99),
        (Some(FaceCondition::Flux(0.7)), None, DirichletMode::Rate, 1.0),
        (Some(FaceCondition::Flux(0.7)), Some(FaceCondition::Dirichlet(0.2)), DirichletMode::Value, 0.9),
    ];
    for (k, (lo, hi, mode, beta)) in cases.into_iter().enumerate() {
        for scheme in [SchemeKind::Mpm, SchemeKind::Ugimp] {
            let mut sim = heat_sim(scheme, 20, 2, 1e-4, (lo, hi), mode, beta);
            let before = Diffusion::content(&sim.points);
            for _ in 0..500 {
                sim.step().expect("steps");
            }
            let d = sim.diffusion.as_ref().expect("diffusion");
            let change = Diffusion::content(&sim.points) - before;
            let scale = sim.points.scalar.iter().zip(&sim.points.volume0).map(|(c, v)| (c * v).abs()).sum::<f64>().max(1.0);
            assert!(change.abs() > 1e-3, "case {k}: something must flow in ({change})");
            assert!(
                (change - d.boundary_content).abs() < 1e-13 * scale,
                "case {k} {scheme:?}: change {change:e} vs source {:e}",
                d.boundary_content
            );
            if lo == Some(FaceCondition::Flux(0.7)) && hi.is_none() {
                // A pure flux face: exactly j t enters.
                assert!((change - 0.7 * sim.time).abs() < 1e-13, "{change} vs {}", 0.7 * sim.time);
            }
        }
    }
}

/// B Table 6.1: 1D, 20 cells, GIMP, 2 points per cell, K = 1, T(0) = 1, T(1) = 0, dt = 1e-5.
/// Prints both Dirichlet variants; asserts the thesis's orderings and, for beta = 1 with the
/// rate variant, the numbers within 25 %.
#[test]
fn heat_table_6_1() {
    let times = [500usize, 2500, 4500];
    let table = [(1.0, [0.0375, 0.0156, 0.0114]), (0.99, [0.0536, 0.0615, 0.0675])];
    let mut measured = Vec::new();
    for mode in [DirichletMode::Rate, DirichletMode::Value] {
        for (beta, printed) in table {
            let mut sim = heat_sim(
                SchemeKind::Ugimp,
                20,
                2,
                1e-5,
                (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0))),
                mode,
                beta,
            );
            let mut errs = Vec::new();
            for &n in &times {
                while (sim.step as usize) < n {
                    sim.step().expect("steps");
                }
                let t = sim.time;
                errs.push(rms(&sim, |x| heat_series(x, t, 1.0, 1.0, (0.0, 1.0, 0.0), 4000)));
            }
            eprintln!("{mode:?} beta = {beta}: RMS {errs:.4?} (thesis {printed:?})");
            measured.push((mode, beta, errs));
        }
    }
    // The rate variant reproduces the table (measured: 0.0375, 0.0156, 0.0114 and 0.0534,
    // 0.0613, 0.0674): assert it within 2 %, and the thesis's orderings.
    for (mode, beta, e) in &measured {
        if *mode == DirichletMode::Rate {
            let printed = table.iter().find(|t| t.0 == *beta).expect("row").1;
            for k in 0..3 {
                assert!(((e[k] - printed[k]) / printed[k]).abs() < 0.02, "beta = {beta}: {e:?} vs Table 6.1 {printed:?}");
            }
        }
    }
    let get = |m: DirichletMode, b: f64| measured.iter().find(|r| r.0 == m && r.1 == b).expect("run").2.clone();
    let (one, blend) = (get(DirichletMode::Rate, 1.0), get(DirichletMode::Rate, 0.99));
    assert!(one[0] > one[1] && one[1] > one[2], "beta = 1 errors fall with time: {one:?}");
    assert!((0..3).all(|k| blend[k] > one[k]), "beta = 0.99 above beta = 1: {blend:?} vs {one:?}");
    assert!(blend[0] < blend[1] && blend[1] < blend[2], "beta = 0.99 errors rise: {blend:?}");
    // The value variant leaves the outer layer of points behind: a flat error (B Table 6.2's
    // particle column, 0.224 in 2D) that does not fall with time.
    let value = get(DirichletMode::Value, 1.0);
    assert!(value.iter().all(|&e| e > 0.1) && value[2] > 0.95 * value[0], "value variant: flat boundary-layer error {value:?}");
}

/// B 7.1.2: c_t = c_xx on [0, 1], c(0) = 1, c(1) = 0, 2 points per cell, hats, rate Dirichlet,
/// dt = 0.25 h^2, at t = 0.25. Returns per h: (h, the thesis's RMS of the relative error
/// (7.14)-(7.15) over the points, the absolute RMS over the points, the absolute RMS at the
/// nodes).
fn convergence(hs: &[f64]) -> Vec<(f64, f64, f64, f64)> {
    hs.iter()
        .map(|&h| {
            let cells = (1.0 / h).round() as usize;
            let dt = 0.25 * h * h;
            let steps = (0.25 / dt).round() as usize;
            let faces = (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0)));
            let mut sim = heat_sim(SchemeKind::Mpm, cells, 2, dt, faces, DirichletMode::Rate, 1.0);
            for _ in 0..steps {
                sim.step().expect("steps");
            }
            let t = sim.time;
            let exact = |x: f64| heat_series(x, t, 1.0, 1.0, (0.0, 1.0, 0.0), 1000);
            let p = &sim.points;
            let (mut rel, mut abs) = (0.0, 0.0);
            for (c, x) in p.scalar.iter().zip(&p.x) {
                let e = exact(x[0]);
                rel += if e == 0.0 { 0.0 } else { ((e - c) / e).powi(2) };
                abs += (e - c).powi(2);
            }
            let d = sim.diffusion.as_ref().expect("diffusion");
            let nodes: f64 =
                d.node_value.iter().enumerate().map(|(i, c)| (c - exact(i as f64 * h)).powi(2)).sum::<f64>() / d.node_value.len() as f64;
            let n = p.len() as f64;
            (h, (rel / n).sqrt(), (abs / n).sqrt(), nodes.sqrt())
        })
        .collect()
}

fn orders(e: &[(f64, f64, f64, f64)], pick: impl Fn(&(f64, f64, f64, f64)) -> f64) -> Vec<f64> {
    e.windows(2).map(|w| (pick(&w[0]) / pick(&w[1])).ln() / (w[0].0 / w[1].0).ln()).collect()
}

/// Measured (h = 0.1, 0.05, 0.02, 0.01): the thesis's relative RMS converges at order 0.5 only
/// (it reports O(h)): FLIP leaves an O(h) error on the points next to a Dirichlet face, and
/// at x = 1, where c vanishes, that is an O(1) relative error on a fraction h of the points.
/// The absolute error over the points converges at 1.5 (an O(h) error on O(1) points of N ~ 1/h)
/// and the nodes at 2 (the 3-point scheme the nodal update is for stationary hats); measured
/// orders 0.48-0.50, 1.50-1.51, 1.96-1.99. The assertions pin them.
#[test]
fn diffusion_converges_at_t_0_25() {
    let e = convergence(&[0.1, 0.05, 0.02, 0.01]);
    let (rel, abs, nodes) = (orders(&e, |r| r.1), orders(&e, |r| r.2), orders(&e, |r| r.3));
    eprintln!(
        "t = 0.25 errors (h, relative RMS, absolute RMS, nodes): {e:?}\norders: relative {rel:.3?}, absolute {abs:.3?}, nodes {nodes:.3?}"
    );
    assert!(rel.iter().all(|&o| (0.4..0.6).contains(&o)), "relative RMS order about 0.5: {rel:?}");
    assert!(abs.iter().all(|&o| o >= 1.4), "absolute RMS order about 1.5: {abs:?}");
    assert!(nodes.iter().all(|&o| o >= 1.9), "nodal RMS order about 2: {nodes:?}");
}

#[test]
#[ignore = "heavy: h down to 0.001 is 2000 points x 1e6 steps"]
fn diffusion_converges_at_t_0_25_full_range() {
    let e = convergence(&[0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001]);
    let (rel, abs, nodes) = (orders(&e, |r| r.1), orders(&e, |r| r.2), orders(&e, |r| r.3));
    eprintln!("t = 0.25 errors: {e:?}\norders: relative {rel:.3?}, absolute {abs:.3?}, nodes {nodes:.3?}");
    assert!(abs.iter().all(|&o| o >= 0.9), "absolute RMS order >= 0.9: {abs:?}");
}

/// C.3 corrected: a bar pre-strained to J, reference form, hats, 2 symmetric points per cell,
/// checkerboard noise on the nodes: it decays at 0.99 of J h0^2 / (2 K) and grows at 1.01.
#[test]
fn a_prestrained_bar_is_stable_below_the_corrected_bound_and_not_above() {
    for j in [0.5, 2.0] {
        let cells = 20;
        let h = 1.0 / cells as f64;
        let k = 1.0;
        let bound = explicit_bound(j * h, 1, k, j);
        assert!((bound - j * h * h / (2.0 * k)).abs() < 1e-15, "J h0^2 / 2K: {bound}");
        for (factor, grows) in [(0.99, false), (1.01, true)] {
            let (grid, mut pts) = bar(cells, 2, j);
            let mut d = Diffusion::new(k, [(None, None)]);
            d.configuration = Configuration::Reference;
            let noise: Vec<f64> = (0..=cells).map(|i| if i % 2 == 0 { 1e-3 } else { -1e-3 }).collect();
            d.set_node_values(noise);
            let dt = factor * j * h * h / (2.0 * k);
            for _ in 0..2000 {
                d.step(&grid, SchemeKind::Mpm, &Stencil::default(), &mut pts, dt).expect("on the grid");
            }
            let amp = d.node_value.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            eprintln!("J = {j}, dt = {factor} x bound: checkerboard amplitude 1e-3 -> {amp:e}");
            if grows {
                assert!(amp > 1e-2, "J = {j}: grows above the bound ({amp:e})");
            } else {
                assert!(amp < 1e-4, "J = {j}: decays below the bound ({amp:e})");
            }
        }
    }
}

/// Issue 19: D(c, p) = D0 exp(alpha c - beta p) with p clamped to [-p_max, p_max], and
/// D0 (1 - c)^3. The factors at the thesis's silicon values, and a heat run under a uniform
/// pressure p0 (alpha = 0) that follows the series of K exp(-beta p0), not that of K.
#[test]
fn pressure_dependent_and_cubic_diffusivities() {
    let si = DiffusivityLaw::Pressure { alpha: 6.0, beta: 0.5e-9, p_max: 3e9 };
    assert!((si.factor(0.5, 1e9) - (3.0f64 - 0.5).exp()).abs() < 1e-12);
    assert_eq!(si.factor(0.2, 5e9), si.factor(0.2, 3e9), "clamped in compression");
    assert_eq!(si.factor(0.2, -5e9), si.factor(0.2, -3e9), "clamped in tension");
    assert!((si.max_factor() - 7.5f64.exp()).abs() < 1e-9);
    let cubic = DiffusivityLaw::Cubic;
    assert_eq!((cubic.factor(0.5, 0.0), cubic.factor(1.2, 0.0), cubic.factor(-0.1, 0.0)), (0.125, 0.0, 1.0));

    let (beta, p0) = (0.5, 1.0);
    let t_end = 0.02;
    let dt = 1e-5;
    let mut sim = heat_sim(
        SchemeKind::Ugimp,
        20,
        2,
        dt,
        (Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0))),
        DirichletMode::Rate,
        1.0,
    );
    // Fixed ends: the uniform stress then puts no force on a free node, nothing moves.
    sim.grid.faces = [(Face::Fixed, Face::Fixed)];
    sim.diffusion.as_mut().expect("diffusion").law = DiffusivityLaw::Pressure { alpha: 0.0, beta, p_max: 10.0 };
    let steps = (t_end / dt).round() as usize;
    for _ in 0..steps {
        for s in sim.points.stress.iter_mut() {
            *s = [[-p0, 0.0, 0.0], [0.0, -p0, 0.0], [0.0, 0.0, -p0]];
        }
        sim.step().expect("steps");
    }
    let k_eff = (-beta * p0).exp();
    let with = rms(&sim, |x| heat_series(x, sim.time, 1.0, k_eff, (0.0, 1.0, 0.0), 4000));
    let without = rms(&sim, |x| heat_series(x, sim.time, 1.0, 1.0, (0.0, 1.0, 0.0), 4000));
    eprintln!("pressure-dependent K: RMS against K exp(-beta p) {with:.4e}, against K {without:.4e}");
    assert!(with < 0.5 * without, "{with} vs {without}");
}

/// A unit square of `cells` x `cells` cells with 2 x 2 points per cell at rest (zero-stress
/// elastic law), c = 0, c = 1 on all four faces.
fn heat_sim_2d(scheme: SchemeKind, cells: usize, dt: f64, mode: DirichletMode, beta: f64) -> Simulation<2> {
    let h = 1.0 / cells as f64;
    let grid = Grid { origin: [0.0; 2], h: [h; 2], cells: [cells; 2], faces: [(Face::Free, Face::Free), (Face::Free, Face::Free)] };
    let mut pts = Particles::default();
    let q = 0.5 * h;
    for j in 0..2 * cells {
        for i in 0..2 * cells {
            let x = [(i as f64 + 0.5) * q, (j as f64 + 0.5) * q];
            pts.push(0, x, [0.0; 2], q * q, q * q, [0.5 * q; 2], IDENTITY);
        }
    }
    pts.with_fields(true, false);
    let law = LinearElastic { youngs_modulus: 1.0, poisson_ratio: 0.0, density0: 1.0 };
    let mut sim = Simulation::new(grid, pts, scheme, vec![Box::new(law)], Viscosity::None, dt).expect("builds");
    let one = Some(FaceCondition::Dirichlet(1.0));
    let mut d = Diffusion::new(1.0, [(one, one); 2]);
    d.dirichlet = mode;
    d.flip = beta;
    sim.diffusion = Some(d);
    sim
}

/// RMS against the series at time t: (points, interior nodes), the nodes off the faces
/// (the value Dirichlet holds the face nodes at the exact value).
fn rms_2d(sim: &Simulation<2>) -> (f64, f64) {
    let t = sim.time;
    let exact = |x: [f64; 2]| heat_series_2d(x, t, [1.0; 2], 1.0, (0.0, 1.0), 401);
    let p = &sim.points;
    let points = (p.scalar.iter().zip(&p.x).map(|(c, x)| (c - exact(*x)).powi(2)).sum::<f64>() / p.len() as f64).sqrt();
    let d = sim.diffusion.as_ref().expect("diffusion");
    let cells = sim.grid.cells[0];
    let (mut sum, mut n) = (0.0, 0);
    for (i, c) in d.node_value.iter().enumerate() {
        let k = sim.grid.unlinear(i);
        if k.iter().all(|&k| k > 0 && k < cells) {
            sum += (c - exact(sim.grid.node_position(k))).powi(2);
            n += 1;
        }
    }
    (points, (sum / n as f64).sqrt())
}

/// B Table 6.2: 2D, 20 x 20 cells, 2 x 2 points per cell, K = 1, T0 = 0, T = 1 on all sides,
/// dt = 1e-5 (not the printed 0.005: 8x above the 2D bound). The `value` Dirichlet reproduces
/// the table (measured: points 0.22409, 0.22231, 0.22226 against the printed 0.22412, 0.22239,
/// 0.22229; interior nodes 0.0236, 0.0060, 0.0039 against 0.0212, 0.0072, 0.0046; beta =
/// 0.995 points 0.0303, 0.0513, 0.0585 against 0.0303, 0.0450, 0.0540); the `rate` one gives
/// points 0.068, 0.023, 0.013 at beta = 1 (no boundary layer). Asserted: the numbers within
/// 25 % and the thesis's orderings (beta = 1: the nodes beat the points, which carry a flat
/// boundary-layer error; beta = 0.995 removes that layer but over-diffuses: errors growing in
/// time, the centre hotter than the series).
#[test]
fn heat_table_6_2() {
    let times = [500usize, 2500, 4500];
    let printed_points = [(1.0, [0.22411582, 0.22238649, 0.22228594]), (0.995, [0.03027875, 0.04500869, 0.05400095])];
    let printed_nodes = [0.02122968, 0.00717621, 0.00455933];
    let mut measured = Vec::new();
    for (beta, printed) in printed_points {
        let mut sim = heat_sim_2d(SchemeKind::Ugimp, 20, 1e-5, DirichletMode::Value, beta);
        let mut errs = Vec::new();
        for &n in &times {
            while (sim.step as usize) < n {
                sim.step().expect("steps");
            }
            errs.push(rms_2d(&sim));
        }
        // The centre: the four points around (0.5, 0.5) against the series there.
        let t = sim.time;
        let centre: Vec<f64> = (0..sim.points.len())
            .filter(|&p| sim.points.x[p].iter().all(|x| (x - 0.5).abs() < 0.02))
            .map(|p| sim.points.scalar[p] - heat_series_2d(sim.points.x[p], t, [1.0; 2], 1.0, (0.0, 1.0), 401))
            .collect();
        eprintln!("beta = {beta}: (points, interior nodes) RMS {errs:.5?} (points printed {printed:?}); centre - series {centre:.3?}");
        for k in 0..3 {
            assert!(((errs[k].0 - printed[k]) / printed[k]).abs() < 0.25, "beta = {beta}, points: {errs:?} vs {printed:?}");
        }
        measured.push((beta, errs, centre));
    }
    let (one, blend) = (&measured[0], &measured[1]);
    for k in 0..3 {
        let nodes = one.1[k].1;
        assert!(((nodes - printed_nodes[k]) / printed_nodes[k]).abs() < 0.25, "beta = 1 nodes {:?} vs {printed_nodes:?}", one.1);
        assert!(nodes < 0.2 * one.1[k].0, "beta = 1: the nodes are the more accurate ({:?})", one.1);
        assert!(blend.1[k].0 < 0.5 * one.1[k].0, "beta = 0.995 removes the boundary layer: {:?} vs {:?}", blend.1, one.1);
    }
    assert!(one.1[0].0 < 1.01 * one.1[2].0 && one.1[2].0 <= one.1[0].0, "beta = 1 points: a flat layer error {:?}", one.1);
    assert!(one.1[0].1 > one.1[1].1 && one.1[1].1 > one.1[2].1, "beta = 1 nodes fall with time {:?}", one.1);
    assert!(blend.1[0].0 < blend.1[1].0 && blend.1[1].0 < blend.1[2].0, "beta = 0.995 errors grow {:?}", blend.1);
    assert!(blend.2.len() == 4 && blend.2.iter().all(|&e| e > 0.0), "beta = 0.995: a hotter centre {:?}", blend.2);
}

/// A bar on the reference interval [0, 1] (`cells` cells, 2 points per cell) with F = diag(j),
/// both grid faces fixed (a uniform stress then moves nothing: the interior nodes' forces
/// cancel), under `scheme`, heated from x = 0 (c = 1) against c = 0 at x = 1 (rate Dirichlet).
fn heat_bar(scheme: SchemeKind, j: f64, dt: f64) -> Simulation<1> {
    let (mut grid, pts) = bar(20, 2, j);
    grid.faces = [(Face::Fixed, Face::Fixed)];
    let law = LinearElastic { youngs_modulus: 1.0, poisson_ratio: 0.0, density0: 1.0 };
    let mut sim = Simulation::new(grid, pts, scheme, vec![Box::new(law)], Viscosity::None, dt).expect("builds");
    sim.diffusion = Some(Diffusion::new(1.0, [(Some(FaceCondition::Dirichlet(1.0)), Some(FaceCondition::Dirichlet(0.0)))]));
    sim
}

/// Issue 19: diffusion under `tlmpm` is the reference form on its stencil at X_p
/// (`Configuration::Lagrangian`: K0 = K J C^-1, V0, nodal values projected every step).
/// - At F = I with the points at rest it is the current form on the same hats: the mpm run's
///   values to round-off, and Table 6.1's beta = 1 error at t = 0.005.
/// - On a bar pre-stretched to J = 0.5, 1.5 and 2 (a bar of length J in space), c_t = (K / J) c_XX in
///   X (K0 = K / J in 1D), so J steps of dt J give the unstretched run's values to round-off; with
///   K instead of K0 (or V instead of V0) the runs differ by a factor J (or J^2) in time.
/// - The content changes by exactly the Dirichlet nodes' source.
#[test]
fn tlmpm_diffusion_is_the_reference_form() {
    let dt = 1e-5;
    let steps = 500;
    let run = |scheme: SchemeKind, j: f64| {
        let mut sim = heat_bar(scheme, j, dt * j);
        for _ in 0..steps {
            sim.step().expect("steps");
        }
        sim
    };
    let current = run(SchemeKind::Mpm, 1.0);
    let tl = run(SchemeKind::Tlmpm, 1.0);
    let d = tl.diffusion.as_ref().unwrap();
    assert_eq!(d.configuration, Configuration::Lagrangian, "tlmpm switches its diffusion to the reference form");
    let moved = tl.points.x.iter().zip(&tl.points.x0).fold(0.0f64, |m, (x, x0)| m.max((x[0] - x0[0]).abs()));
    assert!(moved < 1e-15, "the bar stays at rest: {moved:e}");
    let diff =
        |a: &Simulation<1>, b: &Simulation<1>| a.points.scalar.iter().zip(&b.points.scalar).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    let e = diff(&current, &tl);
    eprintln!("tlmpm vs mpm at F = I: max |dc| = {e:e}");
    assert!(e < 1e-13, "tlmpm at F = I is the current form: {e:e}");
    let t = tl.time;
    let err = rms(&tl, |x| heat_series(x, t, 1.0, 1.0, (0.0, 1.0, 0.0), 4000));
    eprintln!("tlmpm RMS at t = {t}: {err:.5} (Table 6.1, beta = 1: 0.0375)");
    assert!((err - 0.0375).abs() < 0.25 * 0.0375, "{err}");
    let drift = d.active_content(&tl.points) - d.initial_content - d.boundary_content;
    assert!(drift.abs() < 1e-13 * d.boundary_content.abs(), "content {drift:e} off the boundary source {:e}", d.boundary_content);
    assert!(d.boundary_content > 0.01, "heat entered: {}", d.boundary_content);
    for j in [0.5, 1.5, 2.0] {
        let stretched = run(SchemeKind::Tlmpm, j);
        let e = diff(&stretched, &tl);
        eprintln!("J = {j}: {steps} steps of {:e} s against J = 1: max |dc| = {e:e}", dt * j);
        assert!(e < 1e-12, "J = {j}: c_t = (K / J) c_XX: {e:e}");
        // The series of the stretched bar (length J in space, diffusivity J K on c per
        // reference volume: time scale J / K) is the same: the physics, not only the scaling.
        let t = stretched.time;
        let err = rms(&stretched, |x| heat_series(x, t, 1.0, 1.0 / j, (0.0, 1.0, 0.0), 4000));
        assert!((err - 0.0375).abs() < 0.25 * 0.0375, "J = {j}: {err}");
    }
}
