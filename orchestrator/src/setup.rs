//! Turns a validated scene into a running [`continuum::Simulation`]: grid, points, closures.
//! A scene gets only the parts it needs: constitutive-law scenes build no MD engine.

use crate::scene::{Body, FaceSpec, Material, Scene, Shape};
use continuum::closure::{IdealGasIsothermal, LinearElastic, NeoHookean};
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::tensor::IDENTITY;
use continuum::{Closure, Face, Grid, Particles, SchemeKind, Simulation};
use coupling::{MdClosure, MdSettings, MdShared};
use std::sync::{Arc, Mutex};

/// Why a validated scene still cannot be built in this build.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error("body `{0}` uses the md closure, but no MD worker pool was given")]
    MdUnavailable(String),
    #[error("body `{0}`: {1}")]
    Md(String, String),
    #[error("body `{0}` has no material points: it is thinner than a particle spacing")]
    EmptyBody(String),
    #[error(transparent)]
    Solver(#[from] continuum::SolverError),
}

fn face(spec: &FaceSpec) -> Face {
    match spec {
        FaceSpec::Named(n) => match n.as_str() {
            "fixed" => Face::Fixed,
            "reflective" | "roller" => Face::Reflective,
            "periodic" => Face::Periodic,
            _ => Face::Free,
        },
        FaceSpec::Piston { piston } => Face::Piston(piston.clone()),
    }
}

pub fn grid<const D: usize>(scene: &Scene) -> Grid<D> {
    let d = &scene.domain;
    let b = &scene.boundary;
    let pairs = [(&b.x_min, &b.x_max), (&b.y_min, &b.y_max), (&b.z_min, &b.z_max)];
    Grid {
        origin: std::array::from_fn(|a| d.min[a]),
        h: std::array::from_fn(|a| d.cell_size[a]),
        cells: std::array::from_fn(|a| d.cells[a]),
        faces: std::array::from_fn(|a| (face(pairs[a].0), face(pairs[a].1))),
    }
}

/// Whether a point lies in a body (half-open box, minus the notch).
fn inside<const D: usize>(body: &Body, x: &[f64; D]) -> bool {
    let in_box = (0..D).all(|a| x[a] >= body.min[a] && x[a] < body.max[a]);
    if !in_box {
        return false;
    }
    match (&body.shape, &body.notch) {
        (Shape::NotchedBlock, Some(n)) if D >= 2 => {
            // Triangle with its tip at (center, top - depth) opening to width at the top face.
            let below_top = body.max[1] - x[1];
            let half_width_here = 0.5 * n.width * (1.0 - below_top / n.depth);
            !(below_top < n.depth && (x[0] - n.center).abs() < half_width_here)
        }
        _ => true,
    }
}

fn closure(
    body: &Body,
    name: &str,
    points: std::ops::Range<usize>,
    md: Option<&Arc<Mutex<MdShared>>>,
) -> Result<Box<dyn Closure>, SetupError> {
    Ok(match &body.material {
        Material::IdealGasIsothermal(g) => Box::new(IdealGasIsothermal { sound_speed: g.sound_speed }),
        Material::LinearElastic(e) => {
            Box::new(LinearElastic { youngs_modulus: e.youngs_modulus, poisson_ratio: e.poisson_ratio, density0: body.density })
        }
        Material::NeoHookean(e) => {
            Box::new(NeoHookean { youngs_modulus: e.youngs_modulus, poisson_ratio: e.poisson_ratio, density0: body.density })
        }
        Material::Md(m) => {
            let shared = md.ok_or_else(|| SetupError::MdUnavailable(name.to_string()))?;
            let md_err = |e: String| SetupError::Md(name.to_string(), e);
            let specs = points
                .map(|p| crate::md::box_spec(p as u64, body, m))
                .collect::<anyhow::Result<Vec<_>>>()
                .map_err(|e| md_err(format!("{e:#}")))?;
            let props =
                crate::md::lattice_properties(&m.potential, &m.lattice, m.lattice_constant_angstrom, md_worker::Orientation(m.orientation))
                    .map_err(|e| md_err(format!("{e:#}")))?;
            let stress_sampling = m.stress_sampling.parse().map_err(|e: md_worker::MdError| md_err(e.to_string()))?;
            let settings = MdSettings {
                body: name.to_string(),
                dt_ps: m.timestep_fs * 1e-3,
                energy_consistency: m.energy_consistency,
                wave_speed: props.wave_speed,
                c11_gpa: props.c11_gpa,
                stress_sampling,
                reuse: m.reuse,
            };
            Box::new(MdClosure::open(shared.clone(), settings, &specs).map_err(|e| md_err(e.to_string()))?)
        }
    })
}

/// Material points of every body, `ppc` per axis per cell at the cell's sub-centres.
pub fn points<const D: usize>(scene: &Scene, grid: &Grid<D>) -> Result<Particles<D>, SetupError> {
    let ppc = scene.scheme.particles_per_cell;
    let mut pts = Particles::default();
    let per_cell = ppc.pow(D as u32);
    let volume = grid.cell_volume() / per_cell as f64;
    for (b, (name, body)) in scene.bodies.iter().enumerate() {
        let mut f0 = IDENTITY;
        for (a, row) in f0.iter_mut().enumerate() {
            row[a] = 1.0 + body.initial_strain[a];
        }
        let j0 = continuum::tensor::det(&f0);
        let half: [f64; D] = std::array::from_fn(|a| grid.h[a] / (2.0 * ppc as f64));
        let before = pts.len();
        let total: usize = grid.cells.iter().product::<usize>() * per_cell;
        for k in 0..total {
            let mut rem = k;
            let x: [f64; D] = std::array::from_fn(|a| {
                let n = grid.cells[a] * ppc;
                let i = rem % n;
                rem /= n;
                grid.origin[a] + (i as f64 + 0.5) * grid.h[a] / ppc as f64
            });
            if inside(body, &x) {
                let v: [f64; D] = std::array::from_fn(|a| body.velocity[a]);
                // The geometry is the current (strained) configuration; mass follows the
                // reference density and the reference volume V / J0.
                pts.push(b as u32, x, v, body.density * volume / j0, volume / j0, half, f0);
            }
        }
        if pts.len() == before {
            return Err(SetupError::EmptyBody(name.clone()));
        }
    }
    Ok(pts)
}

/// Builds the simulation of a validated scene with time step `dt`.
pub fn simulation<const D: usize>(scene: &Scene, dt: f64, md: Option<&Arc<Mutex<MdShared>>>) -> Result<Simulation<D>, SetupError> {
    let grid = grid::<D>(scene);
    let points = points(scene, &grid)?;
    let ranges = points.body_ranges();
    let closures = scene.bodies.iter().zip(ranges).map(|((n, b), r)| closure(b, n, r, md)).collect::<Result<Vec<_>, _>>()?;
    let scheme = SchemeKind::from_name(&scene.scheme.method).unwrap_or(SchemeKind::Mpm);
    let viscosity = match scene.scheme.artificial_viscosity.as_str() {
        "linear" => Viscosity::Linear { coefficient: scene.scheme.viscosity_coefficient },
        "tensor" => Viscosity::Tensor { linear: scene.scheme.viscosity_c_l, quadratic: scene.scheme.viscosity_c_q },
        _ => Viscosity::None,
    };
    let mut sim = Simulation::new(grid, points, scheme, closures, viscosity, dt)?
        .with_sub_points(scene.scheme.sub_points)
        .with_small_mass_fraction(scene.scheme.small_mass_fraction);
    sim.integrator = if scene.scheme.integrator == "leapfrog" { TimeIntegrator::Leapfrog } else { TimeIntegrator::Dhakal };
    Ok(sim)
}

/// Size of a scene's work without building closures: (points per body in body order, grid nodes).
pub fn work_size(scene: &Scene) -> (Vec<(String, usize)>, usize) {
    fn size<const D: usize>(scene: &Scene) -> (Vec<(String, usize)>, usize) {
        let grid = grid::<D>(scene);
        let counts = match points::<D>(scene, &grid) {
            Ok(p) => p.body_ranges().iter().map(|r| r.len()).collect(),
            Err(_) => Vec::new(),
        };
        (scene.bodies.keys().cloned().zip(counts.into_iter().chain(std::iter::repeat(0))).collect(), grid.node_count())
    }
    match scene.domain.dimension {
        1 => size::<1>(scene),
        2 => size::<2>(scene),
        _ => size::<3>(scene),
    }
}
