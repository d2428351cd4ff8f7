//! Turns a resolved scene into a running [`continuum::Simulation`]: grid, points, closures.
//! A scene gets only the parts it needs: constitutive-law scenes build no MD engine. Setup
//! consumes only the [`ResolvedScene`]: every value is typed and measured there.

use crate::scene::{Law, ResolvedBody, ResolvedScene};
use continuum::closure::{IdealGasIsothermal, LinearElastic, LinearPiola, NeoHookean};
use continuum::silicon::ChemoPlasticClosure;
use continuum::tensor::IDENTITY;
use continuum::{Closure, Grid, Particles, Simulation};
use coupling::{MdClosure, MdSettings, MdShared};
use std::sync::{Arc, Mutex};

/// Why a validated scene still cannot be built in this build.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error("body `{0}` uses the md closure, but no MD worker pool was given")]
    MdUnavailable(String),
    #[error("body `{body}`")]
    Md {
        body: String,
        #[source]
        source: continuum::closure::ClosureError,
    },
    #[error("body `{0}` has no material points: it is thinner than a particle spacing")]
    EmptyBody(String),
    #[error(transparent)]
    Solver(#[from] continuum::SolverError),
}

pub fn grid<const D: usize>(scene: &ResolvedScene) -> Grid<D> {
    Grid {
        origin: std::array::from_fn(|a| scene.origin[a]),
        h: std::array::from_fn(|a| scene.cell_size[a]),
        cells: std::array::from_fn(|a| scene.cells[a]),
        faces: std::array::from_fn(|a| scene.faces[a].clone()),
    }
}

fn closure(body: &ResolvedBody, points: std::ops::Range<usize>, md: Option<&Arc<Mutex<MdShared>>>) -> Result<Box<dyn Closure>, SetupError> {
    Ok(match &body.law {
        Law::IdealGasIsothermal { sound_speed } => Box::new(IdealGasIsothermal { sound_speed: *sound_speed }),
        Law::LinearElastic { youngs_modulus, poisson_ratio } => {
            Box::new(LinearElastic { youngs_modulus: *youngs_modulus, poisson_ratio: *poisson_ratio, density0: body.density })
        }
        Law::NeoHookean { youngs_modulus, poisson_ratio } => {
            Box::new(NeoHookean { youngs_modulus: *youngs_modulus, poisson_ratio: *poisson_ratio, density0: body.density })
        }
        Law::LinearPiola { youngs_modulus, poisson_ratio } => {
            Box::new(LinearPiola { youngs_modulus: *youngs_modulus, poisson_ratio: *poisson_ratio, density0: body.density })
        }
        Law::HypoelasticPlastic(law) => Box::new(ChemoPlasticClosure { law: *law }),
        Law::Md(m) => {
            let shared = md.ok_or_else(|| SetupError::MdUnavailable(body.name.clone()))?;
            let specs: Vec<_> = points.map(|p| crate::md::box_spec(p as u64, body, m)).collect();
            let settings = MdSettings {
                body: body.name.clone(),
                dt_ps: m.timestep_fs * 1e-3,
                energy_consistency: m.energy_consistency,
                wave_speed: m.lattice_properties.wave_speed,
                c11_gpa: m.lattice_properties.c11_gpa,
                stress_sampling: m.stress_sampling,
                reuse: m.reuse,
                viscous_heating: m.viscous_heating,
            };
            Box::new(
                MdClosure::open(shared.clone(), settings, &specs).map_err(|source| SetupError::Md { body: body.name.clone(), source })?,
            )
        }
    })
}

/// Material points of every body, `ppc` per axis per cell at the cell's sub-centres.
pub fn points<const D: usize>(scene: &ResolvedScene, grid: &Grid<D>) -> Result<Particles<D>, SetupError> {
    let ppc = scene.particles_per_cell;
    let mut pts = Particles::default();
    let per_cell = ppc.pow(D as u32);
    let volume = grid.cell_volume() / per_cell as f64;
    for (b, body) in scene.bodies.iter().enumerate() {
        let mut f0 = IDENTITY;
        for (a, row) in f0.iter_mut().enumerate() {
            row[a] = 1.0 + body.initial_strain[a];
        }
        let j0 = continuum::tensor::det(&f0);
        let half: [f64; D] = std::array::from_fn(|a| grid.h[a] / (2.0 * ppc as f64));
        let v: [f64; D] = std::array::from_fn(|a| body.velocity[a]);
        let before = pts.len();
        let region = (body.min.as_slice(), body.max.as_slice(), body.notch.as_ref());
        crate::scene::for_each_point::<D>(&scene.origin, &scene.cell_size, &scene.cells, ppc, region, |x| {
            // The geometry is the current (strained) configuration; mass follows the
            // reference density and the reference volume V / J0.
            pts.push(b as u32, x, v, body.density * volume / j0, volume / j0, half, f0);
        });
        if pts.len() == before {
            return Err(SetupError::EmptyBody(body.name.clone()));
        }
    }
    // The optional fields: a concentration when a body is lithiated, a plastic strain when a
    // law is plastic (scenes with neither allocate nothing).
    let scalar = scene.diffusion.is_some() || scene.bodies.iter().any(|b| b.lithiation.is_some());
    let plastic = scene.bodies.iter().any(|b| matches!(b.law, Law::HypoelasticPlastic(_)));
    pts.with_fields(scalar, plastic);
    if scalar {
        for (p, &b) in pts.body.clone().iter().enumerate() {
            pts.scalar[p] = scene.bodies[b as usize].lithiation.map_or(0.0, |l| l.0);
        }
    }
    Ok(pts)
}

/// Builds the simulation of a resolved scene.
pub fn simulation<const D: usize>(scene: &ResolvedScene, md: Option<&Arc<Mutex<MdShared>>>) -> Result<Simulation<D>, SetupError> {
    let grid = grid::<D>(scene);
    let mut points = points(scene, &grid)?;
    if let Some(m) = scene.manufactured {
        // The manufactured solution's initial velocity V = c pi G sin(pi X).
        for (v, x0) in points.v.iter_mut().zip(&points.x0) {
            *v = std::array::from_fn(|a| m.velocity(x0[a], 0.0));
        }
    }
    if let Some(m) = scene.vibrating_bar {
        // The bar's initial velocity A c pi sin(2 pi X).
        for (v, x0) in points.v.iter_mut().zip(&points.x0) {
            v[0] = m.velocity(x0[0], 0.0);
        }
    }
    let ranges = points.body_ranges();
    let closures = scene.bodies.iter().zip(ranges).map(|(b, r)| closure(b, r, md)).collect::<Result<Vec<_>, _>>()?;
    let mut sim = Simulation::new(grid, points, scene.scheme, closures, scene.viscosity, scene.dt)?
        .with_sub_points(scene.sub_points)
        .with_small_mass_fraction(scene.small_mass_fraction);
    sim.integrator = scene.integrator;
    sim.flip_fraction = scene.flip_fraction;
    sim.gradient_correction = scene.gradient_correction;
    sim.nullspace_filter = scene.nullspace_filter;
    sim.moving_mesh = scene.moving_mesh;
    if let Some(m) = scene.manufactured {
        sim.body_force = Some(Arc::new(move |x0: &[f64; D], t: f64| m.body_force(x0, t)));
    }
    if let Some(m) = scene.vibrating_bar {
        sim.body_force = Some(Arc::new(move |x0: &[f64; D], t: f64| m.body_force(x0, t)));
    }
    if let Some(d) = &scene.diffusion {
        let mut diffusion = continuum::diffusion::Diffusion::<D>::new(d.diffusivity, std::array::from_fn(|a| d.faces[a]));
        diffusion.flip = d.flip;
        diffusion.law = d.law;
        diffusion.dirichlet = d.dirichlet;
        if scene.scheme == continuum::SchemeKind::Tlmpm {
            diffusion.configuration = continuum::diffusion::Configuration::Lagrangian;
        }
        if !d.bodies.is_empty() {
            diffusion.active = sim.points.body.iter().map(|b| d.bodies.contains(&(*b as usize))).collect();
        }
        if d.surface_flux > 0.0 {
            let include = if diffusion.active.is_empty() { vec![true; sim.points.len()] } else { diffusion.active.clone() };
            let areas = continuum::diffusion::exposed_areas(&sim.grid, &sim.points, &include);
            diffusion.surface_source = areas.iter().map(|a| d.surface_flux * a).collect();
        }
        sim.diffusion = Some(diffusion);
    }
    if !sim.points.scalar.is_empty() {
        let body = sim.points.body.clone();
        sim.prescribed_scalar_rate = body.iter().map(|&b| scene.bodies[b as usize].lithiation.map_or(0.0, |l| l.1)).collect();
        // One ramp for the scene (the validator makes every lithiated body's the same).
        sim.prescribed_ramp = scene.bodies.iter().map(|b| b.lithiation_ramp).fold(0.0, f64::max);
    }
    sim.implicit.options.jacobian = scene.jacobian;
    sim.implicit.options.adaptive = scene.adaptive.clone();
    sim.implicit.options.max_motion_cells = scene.max_motion_cells;
    Ok(sim)
}

/// Size of a scene's work without building anything: (points per body in body order, grid nodes).
pub fn work_size(scene: &ResolvedScene) -> (Vec<(String, usize)>, usize) {
    let nodes = match scene.dimension {
        1 => grid::<1>(scene).node_count(),
        2 => grid::<2>(scene).node_count(),
        _ => grid::<3>(scene).node_count(),
    };
    (scene.point_counts(), nodes)
}
