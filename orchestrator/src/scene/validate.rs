//! Validation of a deserialised scene: physics and numerics checked, every default filled.

use super::parse::Locator;
use super::resolve::{Law, ResolvedBody, ResolvedDiffusion, ResolvedMd, ResolvedScene, count_points, region};
use super::*;
use continuum::solver::Viscosity;
use continuum::{Face, SchemeKind};
use coupling::lattice::LatticeProperties;
use md_worker::{DeformMode, Orientation};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// What validation measured of an md body's lattice.
type Measured = (LatticeProperties, u64);

/// Largest lattice constant an md material may have (A); real crystals of these lattices have 2-7.
const MAX_LATTICE_CONSTANT: f64 = 100.0;

fn finite_positive(loc: &Locator<'_>, key: &str, v: f64, what: &str) -> Result<(), SceneError> {
    if v.is_finite() && v > 0.0 { Ok(()) } else { Err(loc.err(key, v, format!("{what} must be a finite positive number"))) }
}

fn vec_str(v: &[f64]) -> String {
    format!("{v:?}")
}

/// Largest CFL number the explicit schemes are stable at (Gong, Ch. 7: c dt/h <= 1).
pub const CFL_LIMIT: f64 = 1.0;

/// Largest MD box a scene may ask for (atoms).
pub const MAX_ATOMS_PER_BOX: u64 = 256_000;

impl Scene {
    /// Checks physics and numerics; fills defaults (so that the scene renders as what runs).
    /// Returns the resolved scene and the files the scene names (resolved against `base`).
    pub(super) fn resolve(&mut self, loc: &Locator<'_>, base: &Path) -> Result<(ResolvedScene, Vec<PathBuf>), SceneError> {
        if self.schema != SCHEMA_VERSION {
            return Err(loc.err("schema", self.schema, format!("this build reads schema {SCHEMA_VERSION}")));
        }
        let dim = self.domain.dimension;
        if !(1..=3).contains(&dim) {
            return Err(loc.err("domain.dimension", dim, "allowed: 1, 2 or 3"));
        }
        self.validate_domain(loc)?;
        if self.bodies.is_empty() {
            return Err(loc.err("bodies", "{}", "a scene needs at least one body, e.g. [bodies.bar]"));
        }
        let scaling = self.scheme.density_scaling;
        if !(scaling.is_finite() && scaling >= 1.0) {
            return Err(loc.err("scheme.density_scaling", scaling, "the density scaling factor must be finite and at least 1"));
        }
        if scaling != 1.0
            && let Some((name, _)) =
                self.bodies.iter().find(|(_, b)| matches!(b.material, Material::Md(_) | Material::IdealGasIsothermal(_)))
        {
            return Err(loc.err(
                "scheme.density_scaling",
                scaling,
                format!("body `{name}`: density scaling is for solids whose stress does not depend on the density (an md body's density is its lattice's, a gas's pressure is c^2 rho)"),
            ));
        }
        let mut files = Vec::new();
        let mut max_speed: f64 = 0.0;
        let names: Vec<String> = self.bodies.keys().cloned().collect();
        let mut measured = BTreeMap::new();
        for name in names {
            let (speed, file, lattice) = self.validate_body(loc, &name, base)?;
            max_speed = max_speed.max(speed);
            files.extend(file);
            measured.extend(lattice.map(|m| (name, m)));
        }
        self.validate_boundary(loc)?;
        let user_timestep = self.scheme.timestep.is_some() && self.scheme.cfl.is_none();
        let (mut dt, mut steps) = self.validate_scheme(loc, max_speed)?;
        if let Some(md_step) = self.md_step(loc)? {
            (dt, steps) = self.fit_to_md_step(loc, dt, md_step, user_timestep, max_speed)?;
        }
        let diffusion = self.validate_diffusion(loc, dt, max_speed)?;
        files.extend(self.validate_reference(loc, base)?);
        self.validate_linear_bound(loc, user_timestep)?;
        let counts = self.point_counts();
        self.validate_dump_points(loc, &counts)?;
        let mut resolved = self.resolved(dt, steps, &counts, measured);
        resolved.diffusion = diffusion;
        Ok((resolved, files))
    }

    /// The linear CFL bound derived for the scheme, integrator and PIC/FLIP blend
    /// ([`continuum::stability`]): a time step above it is refused where it is tighter than
    /// `CFL_LIMIT` (usl and leapfrog re-map the velocity from the points, so the sawtooth grid
    /// mode limits MPM to 0.7071 at 1 point per cell). The 1D analysis bounds 2D and 3D scenes
    /// too (a plane wave along an axis is the 1D problem; cpdi1/cpdi2 are analysed as the 1D
    /// cpdi); it is necessary there, not shown sufficient.
    fn validate_linear_bound(&self, loc: &Locator<'_>, user_timestep: bool) -> Result<(), SceneError> {
        let s = &self.scheme;
        let Some(cfl) = s.cfl else { return Ok(()) };
        let scheme = match s.method {
            SchemeKind::Cpdi1 | SchemeKind::Cpdi2 => SchemeKind::Cpdi,
            SchemeKind::Cpdi1Improved => SchemeKind::CpdiImproved,
            k => k,
        };
        let layout = continuum::stability::Layout { scheme, particles_per_cell: s.particles_per_cell, sub_points: s.sub_points };
        let Ok(Some(bound)) = continuum::stability::cfl_bound(layout, s.integrator, s.flip_fraction) else { return Ok(()) };
        if bound >= CFL_LIMIT || cfl <= bound {
            return Ok(());
        }
        let why = format!(
            "exceeds the linear stability bound c dt / h <= {bound:.4} of `{}` with integrator \"{}\", {} points per cell and flip_fraction {} (derived in continuum::stability; cfl here {cfl:.4})",
            s.method.name(),
            s.integrator.scene_name(),
            s.particles_per_cell,
            s.flip_fraction
        );
        Err(if user_timestep {
            loc.err(
                "scheme.timestep",
                s.timestep.unwrap_or_default(),
                format!("{why}; use dt <= {:.6e} s", s.timestep.unwrap_or_default() * bound / cfl),
            )
        } else {
            loc.err("scheme.cfl", cfl, format!("{why}; use cfl <= {:.4}", (bound * 1e4).floor() / 1e4))
        })
    }

    /// The largest c dt / h an explicit step of this scene's scheme allows: tlmpm's derived
    /// bound, `CFL_LIMIT` for every other scheme.
    fn explicit_cfl_limit(&self) -> f64 {
        if self.scheme.method == SchemeKind::Tlmpm {
            tlmpm_bound(self.scheme.particles_per_cell, self.scheme.flip_fraction, self.scheme.tlmpm_form)
        } else {
            CFL_LIMIT
        }
    }

    /// `explicit_cfl_limit` times h / (c + |v|), as a message writes it.
    fn explicit_bound_form(&self) -> String {
        let limit = self.explicit_cfl_limit();
        if limit == CFL_LIMIT { "h / (c + |v|)".to_string() } else { format!("{limit} h / (c + |v|) (tlmpm's bound)") }
    }

    /// Material points per body (name order), counted without building them.
    fn point_counts(&self) -> Vec<(String, usize)> {
        let d = &self.domain;
        let ppc = self.scheme.particles_per_cell;
        self.bodies
            .iter()
            .map(|(name, b)| {
                let r = region(b.shape, &b.min, &b.max, b.notch.as_ref());
                (name.clone(), count_points(d.dimension, &d.min, &d.cell_size, &d.cells, ppc, r))
            })
            .collect()
    }

    /// The typed scene setup consumes, from a validated scene (every default filled).
    fn resolved(&self, dt: f64, steps: u64, counts: &[(String, usize)], mut measured: BTreeMap<String, Measured>) -> ResolvedScene {
        let face = |f: &FaceSpec| match f {
            FaceSpec::Named(FaceName::Free) => Face::Free,
            FaceSpec::Named(FaceName::Fixed) => Face::Fixed,
            FaceSpec::Named(FaceName::Reflective | FaceName::Roller) => Face::Reflective,
            FaceSpec::Named(FaceName::Periodic) => Face::Periodic,
            FaceSpec::Piston { piston } => Face::Piston(piston.clone()),
        };
        let b = &self.boundary;
        let s = &self.scheme;
        let bodies = self
            .bodies
            .iter()
            .zip(counts)
            .map(|((name, body), (_, points))| {
                let law = match &body.material {
                    Material::IdealGasIsothermal(g) => Law::IdealGasIsothermal { sound_speed: g.sound_speed },
                    Material::LinearElastic(e) => Law::LinearElastic { youngs_modulus: e.youngs_modulus, poisson_ratio: e.poisson_ratio },
                    Material::NeoHookean(e) => Law::NeoHookean { youngs_modulus: e.youngs_modulus, poisson_ratio: e.poisson_ratio },
                    Material::LinearPiola(e) => Law::LinearPiola { youngs_modulus: e.youngs_modulus, poisson_ratio: e.poisson_ratio },
                    Material::HypoelasticPlastic(m) => Law::HypoelasticPlastic(m.law(body.density * s.density_scaling)),
                    Material::Md(m) => {
                        let (lattice_properties, atoms_per_box) = measured.remove(name).expect("every md body is measured by validation");
                        Law::Md(Box::new(ResolvedMd {
                            potential: m.potential.clone(),
                            lattice: m.lattice,
                            lattice_constant_angstrom: m.lattice_constant_angstrom,
                            cells_per_side: m.cells_per_side,
                            orientation: Orientation(m.orientation),
                            timestep_fs: m.timestep_fs,
                            stress_sampling: m.stress_sampling,
                            energy_consistency: m.energy_consistency,
                            viscous_heating: m.viscous_heating,
                            seed: m.seed,
                            relax_steps: m.relax_steps,
                            relax_box: m.relax_box,
                            deformation: match m.deformation {
                                Deformation::Affine => DeformMode::Affine,
                                // `auto` is resolved by validation; seed is its non-1D choice.
                                Deformation::Seed | Deformation::Auto => DeformMode::Seed,
                            },
                            reuse: m.reuse,
                            lattice_properties,
                            atoms_per_box,
                        }))
                    }
                };
                ResolvedBody {
                    name: name.clone(),
                    min: body.min.clone(),
                    max: body.max.clone(),
                    notch: if body.shape == Shape::NotchedBlock { body.notch.clone() } else { None },
                    density: body.density * s.density_scaling,
                    velocity: body.velocity.clone(),
                    initial_strain: [body.initial_strain[0], body.initial_strain[1], body.initial_strain[2]],
                    temperature_k: body.temperature_k,
                    law,
                    points: *points,
                    lithiation: body.lithiation.as_ref().map(|l| (l.initial, l.uniform_rate)),
                    lithiation_ramp: body.lithiation.as_ref().map_or(0.0, |l| l.ramp_time),
                }
            })
            .collect();
        ResolvedScene {
            dimension: self.domain.dimension,
            origin: self.domain.min.clone(),
            cell_size: self.domain.cell_size.clone(),
            cells: self.domain.cells.clone(),
            faces: [(face(&b.x_min), face(&b.x_max)), (face(&b.y_min), face(&b.y_max)), (face(&b.z_min), face(&b.z_max))],
            scheme: s.method,
            particles_per_cell: s.particles_per_cell,
            sub_points: s.sub_points,
            viscosity: match s.artificial_viscosity {
                ViscosityForm::None => Viscosity::None,
                ViscosityForm::Linear => Viscosity::Linear { coefficient: s.viscosity_coefficient },
                ViscosityForm::Tensor => Viscosity::Tensor { linear: s.viscosity_c_l, quadratic: s.viscosity_c_q },
            },
            integrator: s.integrator,
            flip_fraction: s.flip_fraction,
            gradient_correction: s.gradient_correction,
            nullspace_filter: s.nullspace_filter,
            moving_mesh: s.tlmpm_form == super::TlmpmForm::MovingMesh,
            jacobian: s.jacobian,
            adaptive: s.adaptive.as_ref().map(|a| continuum::solver::implicit::Adaptive {
                rtol: a.rtol,
                atol_u: a.atol_displacement,
                atol_v: a.atol_velocity,
                atol_f: a.atol_deformation,
                safety: a.safety,
                max_growth: a.max_growth,
                min_shrink: a.min_shrink,
                dt_min: a.dt_min,
                dt_max: a.dt_max.unwrap_or(f64::INFINITY),
                max_rejections: a.max_rejections,
                end_time: s.end_time,
            }),
            max_motion_cells: s
                .adaptive
                .as_ref()
                .map_or(continuum::solver::implicit::ImplicitOptions::default().max_motion_cells, |a| a.max_motion_cells),
            density_scaling: s.density_scaling,
            small_mass_fraction: s.small_mass_fraction,
            dt,
            steps,
            bodies,
            manufactured: self.manufactured(),
            vibrating_bar: self.vibrating_bar(),
            diffusion: None,
        }
    }

    /// `[diffusion]`: its values, its faces, and the time step against the corrected explicit
    /// bound dt <= J_min h0^2 / (2 d K) (battery thesis (6.90) with its sign fixed, in d
    /// dimensions; h0 = h / J the reference length of a cell at the points' initial J).
    fn validate_diffusion(&self, loc: &Locator<'_>, dt: f64, max_speed: f64) -> Result<Option<ResolvedDiffusion>, SceneError> {
        use continuum::diffusion::{DirichletMode, FaceCondition};
        let Some(d) = &self.diffusion else { return Ok(None) };
        finite_positive(loc, "diffusion.diffusivity", d.diffusivity, "the diffusivity K (m^2/s)")?;
        if !(d.flip_fraction.is_finite() && (0.0..=1.0).contains(&d.flip_fraction)) {
            return Err(loc.err("diffusion.flip_fraction", d.flip_fraction, "the FLIP fraction must lie in [0, 1]"));
        }
        let dim = self.domain.dimension;
        let given = [&d.x_min, &d.x_max, &d.y_min, &d.y_max, &d.z_min, &d.z_max];
        let names = ["x_min", "x_max", "y_min", "y_max", "z_min", "z_max"];
        let mut faces = [(None, None); 3];
        for (k, f) in given.iter().enumerate() {
            let Some(f) = f else { continue };
            let key = format!("diffusion.{}", names[k]);
            if k / 2 >= dim {
                return Err(loc.err(&key, format!("{f:?}"), format!("a {dim}D scene has no such face")));
            }
            let cond = match (f.value, f.flux) {
                (Some(v), None) if v.is_finite() => FaceCondition::Dirichlet(v),
                (None, Some(j)) if j.is_finite() => FaceCondition::Flux(j),
                _ => {
                    return Err(loc.err(
                        &key,
                        format!("{f:?}"),
                        "give exactly one finite `value` (Dirichlet) or `flux` (into the body, per unit area per second)",
                    ));
                }
            };
            if k % 2 == 0 { faces[k / 2].0 = Some(cond) } else { faces[k / 2].1 = Some(cond) }
        }
        let law = match d.law {
            None | Some(DiffusivityLawSpec::Constant) => continuum::diffusion::DiffusivityLaw::Constant,
            Some(DiffusivityLawSpec::Cubic) => continuum::diffusion::DiffusivityLaw::Cubic,
            Some(DiffusivityLawSpec::Pressure { alpha, beta, p_max }) => {
                for (key, v, ok) in [("alpha", alpha, true), ("beta", beta, true), ("p_max", p_max, p_max >= 0.0)] {
                    if !(v.is_finite() && ok) {
                        return Err(loc.err(
                            &format!("diffusion.law.{key}"),
                            v,
                            "alpha (per unit c) and beta (per Pa) must be finite, p_max (Pa) finite and >= 0",
                        ));
                    }
                }
                continuum::diffusion::DiffusivityLaw::Pressure { alpha, beta, p_max }
            }
        };
        let h = self.domain.cell_size.iter().cloned().fold(f64::INFINITY, f64::min);
        let j_max = self.bodies.values().map(|b| b.initial_strain.iter().map(|e| 1.0 + e).product::<f64>()).fold(0.0f64, f64::max);
        // The bound at the largest diffusivity the law can reach (c in [0, 1], p clamped).
        let bound = continuum::diffusion::explicit_bound(h, dim, d.diffusivity * law.max_factor(), j_max);
        if dt > bound {
            // validate_scheme has filled both `cfl` and `timestep`: name the time step.
            let key = "scheme.timestep";
            let acoustic = CFL_LIMIT * h / max_speed.max(f64::MIN_POSITIVE);
            return Err(loc.err(
                key,
                format!("{dt:e} s"),
                format!(
                    "the time step exceeds the corrected explicit diffusion bound dt <= J_min h0^2 / (2 d K) = {bound:.6e} s (battery thesis (6.90) with its sign fixed; d = {dim}, K = {:e} m^2/s (the largest the diffusion law reaches), h0 = h / J with h = {h:e} m and J_max = {j_max}); the diffusion limit binds, {:.3e} times tighter than the acoustic limit {acoustic:.6e} s: give `scheme.timestep` <= {bound:.6e}",
                    d.diffusivity * law.max_factor(),
                    acoustic / bound
                ),
            ));
        }
        let dirichlet = match d.dirichlet {
            DirichletSpec::Rate => DirichletMode::Rate,
            DirichletSpec::Value => DirichletMode::Value,
        };
        let mut bodies = Vec::new();
        for name in d.bodies.iter().flatten() {
            match self.bodies.keys().position(|k| k == name) {
                Some(i) if !bodies.contains(&i) => bodies.push(i),
                Some(_) => return Err(loc.err("diffusion.bodies", name, "a body is named twice")),
                None => {
                    let known: Vec<&str> = self.bodies.keys().map(String::as_str).collect();
                    return Err(loc.err("diffusion.bodies", name, format!("no such body; the scene's bodies: {}", known.join(", "))));
                }
            }
        }
        if d.bodies.as_ref().is_some_and(|b| b.is_empty()) {
            return Err(loc.err("diffusion.bodies", "[]", "name at least one body (leave the key out for every body)"));
        }
        bodies.sort_unstable();
        let surface_flux = d.surface_flux.unwrap_or(0.0);
        if !(surface_flux.is_finite() && surface_flux >= 0.0) {
            return Err(loc.err(
                "diffusion.surface_flux",
                surface_flux,
                "the surface flux (content per unit area per second into the body) must be finite and >= 0",
            ));
        }
        Ok(Some(ResolvedDiffusion {
            diffusivity: d.diffusivity,
            law,
            flip: d.flip_fraction,
            dirichlet,
            faces,
            bound,
            bodies,
            surface_flux,
        }))
    }

    fn validate_domain(&mut self, loc: &Locator<'_>) -> Result<(), SceneError> {
        let d = &mut self.domain;
        let dim = d.dimension;
        for (key, v) in [("domain.min", &d.min), ("domain.max", &d.max)] {
            if v.len() != dim {
                return Err(loc.err(key, vec_str(v), format!("needs {dim} value(s), one per dimension")));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(loc.err(key, vec_str(v), "values must be finite"));
            }
        }
        for a in 0..dim {
            if d.max[a] <= d.min[a] {
                return Err(loc.err(
                    "domain.max",
                    vec_str(&d.max),
                    format!("must exceed domain.min along every axis (axis {a}: {} <= {})", d.max[a], d.min[a]),
                ));
            }
        }
        match (d.cells.is_empty(), d.cell_size.is_empty()) {
            (false, false) => {
                // Both given (as in a resolved scene): they must agree.
                let agree = d.cells.len() == dim
                    && d.cell_size.len() == dim
                    && (0..dim).all(|a| ((d.max[a] - d.min[a]) / d.cells[a] as f64 - d.cell_size[a]).abs() <= 1e-9 * d.cell_size[a].abs());
                if !agree {
                    return Err(loc.err(
                        "domain.cell_size",
                        vec_str(&d.cell_size),
                        format!("disagrees with cells = {:?}; give `cells` or `cell_size`, not both", d.cells),
                    ));
                }
            }
            (true, true) => return Err(loc.err("domain", "", "missing `cells` (cells per axis) or `cell_size` (m per axis)")),
            (false, true) => {
                if d.cells.len() != dim || d.cells.contains(&0) {
                    return Err(loc.err("domain.cells", format!("{:?}", d.cells), format!("needs {dim} positive integer(s)")));
                }
            }
            (true, false) => {
                if d.cell_size.len() != dim || d.cell_size.iter().any(|h| !(h.is_finite() && *h > 0.0)) {
                    return Err(loc.err("domain.cell_size", vec_str(&d.cell_size), format!("needs {dim} positive length(s) in m")));
                }
                let mut cells = Vec::new();
                for a in 0..dim {
                    let n = (d.max[a] - d.min[a]) / d.cell_size[a];
                    if (n - n.round()).abs() > 1e-9 * n.max(1.0) {
                        return Err(loc.err(
                            "domain.cell_size",
                            vec_str(&d.cell_size),
                            format!(
                                "must divide the domain length along axis {a} ({} m) into a whole number of cells",
                                d.max[a] - d.min[a]
                            ),
                        ));
                    }
                    cells.push(n.round() as usize);
                }
                d.cells = cells;
            }
        }
        let total: f64 = d.cells.iter().map(|&c| c as f64 + 1.0).product();
        if total > 2e8 {
            return Err(loc.err("domain.cells", format!("{:?}", d.cells), "more than 2e8 grid nodes: this would not fit in memory"));
        }
        d.cell_size = (0..dim).map(|a| (d.max[a] - d.min[a]) / d.cells[a] as f64).collect();
        Ok(())
    }

    /// Returns the body's wave speed estimate (m/s), the file it names, if any, and what was
    /// measured of an md body's lattice.
    fn validate_body(
        &mut self,
        loc: &Locator<'_>,
        name: &str,
        base: &Path,
    ) -> Result<(f64, Option<PathBuf>, Option<Measured>), SceneError> {
        let dim = self.domain.dimension;
        let (dmin, dmax) = (self.domain.min.clone(), self.domain.max.clone());
        let ramps: Vec<(String, f64)> =
            self.bodies.iter().filter_map(|(n, o)| o.lithiation.as_ref().map(|l| (n.clone(), l.ramp_time))).collect();
        let Some(b) = self.bodies.get_mut(name) else { return Ok((0.0, None, None)) };
        let k = |f: &str| format!("bodies.{name}.{f}");
        for (f, v) in [("min", &b.min), ("max", &b.max)] {
            if v.len() != dim || v.iter().any(|x| !x.is_finite()) {
                return Err(loc.err(&k(f), vec_str(v), format!("needs {dim} finite value(s) (m)")));
            }
        }
        for a in 0..dim {
            if b.max[a] <= b.min[a] {
                return Err(loc.err(&k("max"), vec_str(&b.max), format!("must exceed `min` along every axis (axis {a})")));
            }
            if b.min[a] < dmin[a] - 1e-12 || b.max[a] > dmax[a] + 1e-12 {
                return Err(loc.err(
                    &k("max"),
                    format!("min {:?} max {:?}", b.min, b.max),
                    format!("the body must lie inside the domain {dmin:?} .. {dmax:?}"),
                ));
            }
        }
        match (b.shape, &b.notch) {
            (Shape::NotchedBlock, None) => {
                return Err(loc.err(&k("notch"), "", "a notched-block needs [bodies.NAME.notch] with center, width and depth (m)"));
            }
            (Shape::NotchedBlock, Some(n)) => {
                if dim < 2 {
                    return Err(loc.err(&k("shape"), "\"notched-block\"", "a notch needs a 2D or 3D domain"));
                }
                for (f, v) in [("width", n.width), ("depth", n.depth)] {
                    finite_positive(loc, &k(&format!("notch.{f}")), v, "the notch size")?;
                }
                if n.depth >= b.max[1] - b.min[1] {
                    return Err(loc.err(&k("notch.depth"), n.depth, "must be less than the body's height"));
                }
            }
            (_, Some(_)) => return Err(loc.err(&k("notch"), "", "only a notched-block has a notch")),
            _ => {}
        }
        finite_positive(loc, &k("density"), b.density, "density (kg/m^3)")?;
        if b.velocity.is_empty() {
            b.velocity = vec![0.0; dim];
        }
        if b.velocity.len() != dim || b.velocity.iter().any(|v| !v.is_finite()) {
            return Err(loc.err(&k("velocity"), vec_str(&b.velocity), format!("needs {dim} finite value(s) (m/s)")));
        }
        if b.initial_strain.is_empty() {
            b.initial_strain = vec![0.0; 3];
        }
        if b.initial_strain.len() > 3 || b.initial_strain.iter().any(|e| !(e.is_finite() && *e > -0.5 && *e < 1.0)) {
            return Err(loc.err(
                &k("initial_strain"),
                vec_str(&b.initial_strain),
                "up to 3 diagonal engineering strains (xx, yy, zz), each between -0.5 and 1",
            ));
        }
        b.initial_strain.resize(3, 0.0);
        if !(b.temperature_k.is_finite() && b.temperature_k >= 0.0) {
            return Err(loc.err(&k("temperature_k"), b.temperature_k, "temperature (K) must be finite and >= 0"));
        }
        let rho = b.density * self.scheme.density_scaling;
        if let Some(l) = &b.lithiation {
            if !(l.initial.is_finite() && (0.0..=1.0).contains(&l.initial)) {
                return Err(loc.err(&k("lithiation.initial"), l.initial, "the normalised concentration must lie in [0, 1]"));
            }
            if !(l.ramp_time.is_finite() && l.ramp_time >= 0.0) {
                return Err(loc.err(&k("lithiation.ramp_time"), l.ramp_time, "the ramp time (s) must be finite and >= 0 (0: no ramp)"));
            }
            if let Some((other, t)) = ramps.iter().find(|(_, t)| *t != l.ramp_time) {
                return Err(loc.err(
                    &k("lithiation.ramp_time"),
                    l.ramp_time,
                    format!("body `{other}` ramps its lithiation over {t:e} s; every lithiated body of a scene has the same ramp"),
                ));
            }
            let end = l.initial + l.uniform_rate * continuum::silicon::ramp_integral(self.scheme.end_time, l.ramp_time);
            if !(l.uniform_rate.is_finite() && (0.0..=1.0).contains(&end)) {
                return Err(loc.err(
                    &k("lithiation.uniform_rate"),
                    l.uniform_rate,
                    format!("reaches c = {end:e} at the end time {:e} s; the concentration must stay within [0, 1]", self.scheme.end_time),
                ));
            }
        }
        match &mut b.material {
            Material::IdealGasIsothermal(g) => {
                finite_positive(loc, &k("material.sound_speed"), g.sound_speed, "the sound speed (m/s)")?;
                Ok((g.sound_speed, None, None))
            }
            Material::LinearElastic(e) | Material::NeoHookean(e) | Material::LinearPiola(e) => {
                finite_positive(loc, &k("material.youngs_modulus"), e.youngs_modulus, "Young's modulus (Pa)")?;
                if !(e.poisson_ratio > -1.0 && e.poisson_ratio < 0.5) {
                    return Err(loc.err(&k("material.poisson_ratio"), e.poisson_ratio, "Poisson's ratio must lie in (-1, 0.5)"));
                }
                let (lambda, mu) = continuum::closure::lame(e.youngs_modulus, e.poisson_ratio);
                Ok((((lambda + 2.0 * mu) / rho).sqrt(), None, None))
            }
            Material::HypoelasticPlastic(m) => {
                finite_positive(loc, &k("material.bulk_modulus"), m.bulk_modulus, "the bulk modulus (Pa)")?;
                finite_positive(loc, &k("material.shear_modulus"), m.shear_modulus, "the shear modulus (Pa)")?;
                finite_positive(loc, &k("material.yield_stress"), m.yield_stress, "the yield stress (Pa)")?;
                if !(m.hardening_modulus.is_finite() && m.hardening_modulus >= 0.0) {
                    return Err(loc.err(
                        &k("material.hardening_modulus"),
                        m.hardening_modulus,
                        "the hardening modulus (Pa) must be finite and >= 0 (0: perfect plasticity)",
                    ));
                }
                if !m.chemical_expansion.is_finite() {
                    return Err(loc.err(&k("material.chemical_expansion"), m.chemical_expansion, "must be a finite number"));
                }
                Ok((((m.bulk_modulus + 4.0 * m.shear_modulus / 3.0) / rho).sqrt(), None, None))
            }
            Material::Md(md) => {
                let file = base.join(&md.potential);
                if !file.is_file() {
                    return Err(loc.err(
                        &k("material.potential"),
                        format!("{:?}", md.potential),
                        format!("no such file ({}); paths are relative to the scene file", file.display()),
                    ));
                }
                finite_positive(loc, &k("material.lattice_constant_angstrom"), md.lattice_constant_angstrom, "the lattice constant (A)")?;
                if md.lattice_constant_angstrom > MAX_LATTICE_CONSTANT {
                    return Err(loc.err(
                        &k("material.lattice_constant_angstrom"),
                        md_worker::error::show(md.lattice_constant_angstrom),
                        format!("the lattice constant must be at most {MAX_LATTICE_CONSTANT} A"),
                    ));
                }
                if !(1..=40).contains(&md.cells_per_side) {
                    return Err(loc.err(&k("material.cells_per_side"), md.cells_per_side, "allowed: 1 to 40 lattice cells per box side"));
                }
                if let Err(e) = md_worker::Orientation(md.orientation).validate() {
                    return Err(loc.err(&k("material.orientation"), format!("{:?}", md.orientation), e.to_string()));
                }
                let atoms = md.lattice.atoms_per_cell(&Orientation(md.orientation)) * (md.cells_per_side as u64).pow(3);
                if atoms > MAX_ATOMS_PER_BOX {
                    return Err(loc.err(
                        &k("material.cells_per_side"),
                        md.cells_per_side,
                        format!("{atoms} atoms per box; at most {MAX_ATOMS_PER_BOX} (fewer cells, or an orientation with smaller indices)"),
                    ));
                }
                if !(md.timestep_fs > 0.0 && md.timestep_fs <= 5.0) {
                    return Err(loc.err(&k("material.timestep_fs"), md.timestep_fs, "the MD time step must lie in (0, 5] fs"));
                }
                if let coupling::Reuse::Tolerance { tolerance_gpa, max_interval } = md.reuse {
                    if !(tolerance_gpa.is_finite() && tolerance_gpa >= 0.0) {
                        return Err(loc.err(
                            &k("material.reuse.tolerance"),
                            tolerance_gpa,
                            "the tolerance (GPa) must be a finite number >= 0 (0: never skip a box)",
                        ));
                    }
                    if !(1..=100_000).contains(&max_interval) {
                        return Err(loc.err(&k("material.reuse.max_interval"), max_interval, "allowed: 1 to 100000 continuum steps"));
                    }
                }
                if md.precision != MdPrecision::Double {
                    return Err(loc.err(&k("material.precision"), format!("{:?}", md.precision.scene_name()), MdPrecision::allowed()));
                }
                if md.deformation == Deformation::Auto {
                    md.deformation = if dim == 1 { Deformation::Affine } else { Deformation::Seed };
                }
                if md.deformation == Deformation::Affine && dim > 1 {
                    return Err(loc.err(&k("material.deformation"), format!("{:?}", md.deformation.scene_name()), Deformation::allowed()));
                }
                if md.relax_steps > 1_000_000 {
                    return Err(loc.err(&k("material.relax_steps"), md.relax_steps, "at most 1e6 relaxation steps"));
                }
                // From here on the path is absolute, so the resolved scene reads back anywhere.
                let file = file.canonicalize().unwrap_or(file);
                md.potential = file.clone();
                let props =
                    coupling::lattice::lattice_properties(&file, md.lattice, md.lattice_constant_angstrom, Orientation(md.orientation))
                        .map_err(|e| loc.err(&k("material.potential"), format!("{:?}", md.potential), format!("{e}")))?;
                if let Some(v) = props.vibration
                    && md.timestep_fs > v.max_dt_ps() * 1e3
                {
                    return Err(loc.err(&k("material.timestep_fs"), md.timestep_fs, format!("exceeds {:.3} fs, {v}", v.max_dt_ps() * 1e3)));
                }
                if (rho - props.density).abs() > 0.01 * props.density {
                    return Err(loc.err(
                        &k("density"),
                        rho,
                        format!(
                            "an md body's density must match its lattice: {:.1} kg/m^3 for {} at a0 = {} A",
                            props.density,
                            md.lattice.scene_name(),
                            md.lattice_constant_angstrom
                        ),
                    ));
                }
                Ok((props.wave_speed, Some(file), Some((props, atoms))))
            }
        }
    }

    fn validate_boundary(&self, loc: &Locator<'_>) -> Result<(), SceneError> {
        let dim = self.domain.dimension;
        for (i, (face, spec)) in self.boundary.faces().into_iter().enumerate() {
            let key = format!("boundary.{face}");
            let axis = i / 2;
            match spec {
                FaceSpec::Named(n) if axis >= dim && *n != FaceName::Free => {
                    return Err(loc.err(&key, format!("{:?}", n.scene_name()), format!("a {dim}D scene has no {face} face")));
                }
                FaceSpec::Piston { piston } if axis >= dim || piston.len() != dim || piston.iter().any(|v| !v.is_finite()) => {
                    return Err(loc.err(
                        &key,
                        vec_str(piston),
                        format!("a piston needs {dim} finite velocity value(s) (m/s) on an existing face"),
                    ));
                }
                _ => {}
            }
        }
        for (axis, (lo, hi)) in [
            (&self.boundary.x_min, &self.boundary.x_max),
            (&self.boundary.y_min, &self.boundary.y_max),
            (&self.boundary.z_min, &self.boundary.z_max),
        ]
        .into_iter()
        .enumerate()
        {
            let periodic = |f: &FaceSpec| matches!(f, FaceSpec::Named(FaceName::Periodic));
            if periodic(lo) != periodic(hi) {
                let face = ["x", "y", "z"][axis];
                return Err(loc.err(
                    &format!("boundary.{face}_max"),
                    face_debug(hi),
                    format!("periodic must be set on both {face}_min and {face}_max"),
                ));
            }
        }
        Ok(())
    }

    fn validate_scheme(&mut self, loc: &Locator<'_>, max_speed: f64) -> Result<(f64, u64), SceneError> {
        let dim = self.domain.dimension;
        let s = &mut self.scheme;
        let kind = s.method;
        if !kind.supports_dimension(dim) {
            let ok: Vec<&str> = SchemeKind::NAMES.iter().filter(|(_, k)| k.supports_dimension(dim)).map(|(n, _)| *n).collect();
            return Err(loc.err(
                "scheme.method",
                format!("{:?}", kind.name()),
                if kind == SchemeKind::Cpdi {
                    format!("`{}` is the 1D CPDI; a {dim}D scene allows: {}", kind.name(), ok.join(", "))
                } else if kind == SchemeKind::Cpdi1Improved {
                    format!(
                        "`{}` chooses cpdi1 as the base of the improved CPDI in 2D and 3D; in 1D `cpdi-improved` is the improved 1D CPDI; a {dim}D scene allows: {}",
                        kind.name(),
                        ok.join(", ")
                    )
                } else {
                    format!("`{}` is not defined in {dim}D in this build; a {dim}D scene allows: {}", kind.name(), ok.join(", "))
                },
            ));
        }
        if kind == SchemeKind::Impm {
            if s.integrator != continuum::solver::TimeIntegrator::Leapfrog {
                return Err(loc.err(
                    "scheme.integrator",
                    format!("{:?}", s.integrator.scene_name()),
                    "impm is Gong's staggered scheme (Ch. 5.3): set scheme.integrator = \"leapfrog\"",
                ));
            }
            if let Some((face, _)) = self.boundary.faces().into_iter().find(|(_, f)| matches!(f, FaceSpec::Named(FaceName::Periodic))) {
                return Err(loc.err(
                    &format!("boundary.{face}"),
                    "\"periodic\"",
                    "impm's MLS reconstruction does not wrap around a periodic axis in this build",
                ));
            }
        }
        if kind == SchemeKind::Tlmpm {
            if s.integrator != continuum::solver::TimeIntegrator::Leapfrog {
                return Err(loc.err(
                    "scheme.integrator",
                    format!("{:?}", s.integrator.scene_name()),
                    "tlmpm keeps its velocities at half steps (the first step kicks by dt / 2, battery thesis 6.1): set scheme.integrator = \"leapfrog\"",
                ));
            }
            // tlmpm takes the points' initial positions as X_p, where F = I: a body strained
            // at t = 0 would have its forces (V0 P G0) and its reference diffusivity
            // (K J C^-1) taken against the strained positions as if unstrained.
            if let Some((name, b)) = self.bodies.iter().find(|(_, b)| b.initial_strain.iter().any(|e| *e != 0.0)) {
                return Err(loc.err(
                    &format!("bodies.{name}.initial_strain"),
                    vec_str(&b.initial_strain),
                    "tlmpm takes the initial positions as the reference configuration (F = I there); a pre-strained body is not supported under tlmpm",
                ));
            }
        }
        if s.tlmpm_form == super::TlmpmForm::MovingMesh {
            if kind != SchemeKind::Tlmpm {
                return Err(loc.err(
                    "scheme.tlmpm_form",
                    "\"moving-mesh\"",
                    format!(
                        "the moving-mesh form is a form of tlmpm (set scheme.method = \"tlmpm\"); `{}` has no reference mesh",
                        kind.name()
                    ),
                ));
            }
            if s.flip_fraction != 1.0 {
                return Err(loc.err(
                    "scheme.flip_fraction",
                    s.flip_fraction,
                    "the moving mesh carries the nodal velocity and updates the points by FLIP only (battery thesis 6.25-6.28): leave flip_fraction at 1",
                ));
            }
        }
        if kind.is_cpdi_improved()
            && let Some((face, _)) = self.boundary.faces().into_iter().find(|(_, f)| matches!(f, FaceSpec::Named(FaceName::Periodic)))
        {
            return Err(loc.err(
                &format!("boundary.{face}"),
                "\"periodic\"",
                format!("{}'s MLS velocity map does not wrap around a periodic axis in this build", kind.name()),
            ));
        }
        if !(1..=64).contains(&s.particles_per_cell) {
            return Err(loc.err("scheme.particles_per_cell", s.particles_per_cell, "allowed: 1 to 64 per axis"));
        }
        if kind == SchemeKind::DdmpSubpoints {
            if !(1..=64).contains(&s.sub_points) {
                return Err(loc.err("scheme.sub_points", s.sub_points, "allowed: 1 to 64 sub-points per particle"));
            }
        } else if s.sub_points != 1 {
            return Err(loc.err(
                "scheme.sub_points",
                s.sub_points,
                format!("sub-points need method \"ddmp-subpoints\"; `{}` uses 1", kind.name()),
            ));
        }
        if !(s.viscosity_coefficient.is_finite() && s.viscosity_coefficient >= 0.0) {
            return Err(loc.err("scheme.viscosity_coefficient", s.viscosity_coefficient, "must be finite and >= 0"));
        }
        for (key, v) in [("scheme.viscosity_c_l", s.viscosity_c_l), ("scheme.viscosity_c_q", s.viscosity_c_q)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(loc.err(key, v, "must be finite and >= 0"));
            }
        }
        if !(s.flip_fraction.is_finite() && (0.0..=1.0).contains(&s.flip_fraction)) {
            return Err(loc.err("scheme.flip_fraction", s.flip_fraction, "the PIC/FLIP blend must lie in [0, 1] (1: FLIP, 0: PIC)"));
        }
        if s.integrator == continuum::solver::TimeIntegrator::StormerVerlet && s.flip_fraction != 1.0 {
            return Err(loc.err(
                "scheme.flip_fraction",
                s.flip_fraction,
                "the Stormer-Verlet step updates the point velocities by FLIP only (its two half kicks): leave flip_fraction at 1",
            ));
        }
        if s.gradient_correction != continuum::solver::GradientCorrection::None {
            let name = format!("{:?}", s.gradient_correction.scene_name());
            let why = if kind == SchemeKind::Tlmpm {
                Some("tlmpm's forces use the reference gradients G0 of hats at X_p, exact for its stencil; corrected derivatives apply to mpm, ugimp, cpgimp, cpdi, cpdi1, cpdi2".to_string())
            } else if !matches!(
                kind,
                SchemeKind::Mpm | SchemeKind::Ugimp | SchemeKind::Cpgimp | SchemeKind::Cpdi | SchemeKind::Cpdi1 | SchemeKind::Cpdi2
            ) {
                Some(format!(
                    "`{}` has its own gradient (DDMP's reconstruction or an MLS map); corrected derivatives apply to mpm, ugimp, cpgimp, cpdi, cpdi1, cpdi2",
                    kind.name()
                ))
            } else if s.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal {
                Some("the implicit integrator assembles its own forces and tangents: use an explicit integrator or \"none\"".to_string())
            } else {
                None
            };
            if let Some(why) = why {
                return Err(loc.err("scheme.gradient_correction", name, why));
            }
        }
        if s.nullspace_filter != continuum::solver::NullspaceFilter::None {
            use continuum::solver::NullspaceFilter;
            let name = format!("{:?}", s.nullspace_filter.scene_name());
            let points = self.domain.cells.iter().product::<usize>().saturating_mul(s.particles_per_cell.saturating_pow(dim as u32));
            let why = if kind == SchemeKind::Tlmpm {
                Some("tlmpm updates F from the re-mapped nodal velocity and never forms the filtered velocity gradient; the filters apply to mpm, ugimp, cpgimp, cpdi, cpdi1, cpdi2, ddmp, ddmp-subpoints".to_string())
            } else if kind.maps_velocity_by_mls() {
                Some(format!(
                    "`{}` maps velocities to the nodes by MLS, whose nullspace these filters do not address; the filters apply to mpm, ugimp, cpgimp, cpdi, cpdi1, cpdi2, ddmp, ddmp-subpoints",
                    kind.name()
                ))
            } else if s.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal {
                Some("the implicit integrator computes its velocity gradients inside the Newton iteration: use an explicit integrator or \"none\"".to_string())
            } else if s.nullspace_filter == NullspaceFilter::GlobalSvd && dim != 1 {
                Some(format!(
                    "the global SVD filter is for 1D reference runs (battery thesis 4.73, O(points^3) a step); a {dim}D scene allows \"none\" or \"local\""
                ))
            } else if s.nullspace_filter == NullspaceFilter::GlobalSvd && points > continuum::solver::SVD_MAX_POINTS {
                Some(format!(
                    "the global SVD filter takes at most {} points (one dense SVD a step); domain.cells x particles_per_cell = {points}: use \"local\"",
                    continuum::solver::SVD_MAX_POINTS
                ))
            } else {
                None
            };
            if let Some(why) = why {
                return Err(loc.err("scheme.nullspace_filter", name, why));
            }
        }
        if !(s.small_mass_fraction.is_finite() && (0.0..1.0).contains(&s.small_mass_fraction)) {
            return Err(loc.err("scheme.small_mass_fraction", s.small_mass_fraction, "must lie in [0, 1)"));
        }
        finite_positive(loc, "scheme.end_time", s.end_time, "the end time (s)")?;
        let h = self.domain.cell_size.iter().cloned().fold(f64::INFINITY, f64::min);
        let speed = max_speed + self.bodies.values().flat_map(|b| b.velocity.iter()).fold(0.0_f64, |m, v| m.max(v.abs()));
        if !(speed > 0.0 && speed.is_finite()) {
            // A modulus at the bottom of the denormals halves to 0 in the Lame constants.
            return Err(loc.err(
                "bodies",
                "",
                format!("the largest wave speed plus body speed is {speed:e} m/s, which sets no time step; check the materials' moduli and densities"),
            ));
        }
        let implicit = s.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal;
        if implicit {
            implicit_supported(loc, kind, s.artificial_viscosity, &self.bodies)?;
            if s.jacobian == continuum::solver::implicit::JacobianKind::Analytic
                && let Some((name, _)) = self.bodies.iter().find(|(_, b)| matches!(b.material, Material::HypoelasticPlastic(_)))
            {
                return Err(loc.err(
                    "scheme.jacobian",
                    "\"analytic\"",
                    format!("body `{name}`: the hypoelastic-plastic law (radial return) gives no analytic tangent; use scheme.jacobian = \"finite-difference\""),
                ));
            }
        }
        // The implicit integrator has no CFL bound (its bound is on motion per step, below);
        // tlmpm's is its own derived one (sqrt 3 at 2 points per cell, FLIP).
        let tlmpm = (kind == SchemeKind::Tlmpm).then(|| tlmpm_bound(s.particles_per_cell, s.flip_fraction, s.tlmpm_form));
        let cfl_limit = if implicit { f64::INFINITY } else { tlmpm.unwrap_or(CFL_LIMIT) };
        let bound = cfl_limit * h / speed;
        let cfl_message = |implicit: bool| match tlmpm {
            Some(b) if s.tlmpm_form == super::TlmpmForm::MovingMesh => format!(
                "allowed: 0 < cfl <= {b:.4}, the linear stability bound of tlmpm's moving mesh (derived in continuum::stability: the leapfrog on the carried nodal velocity with the hats' stiffness)"
            ),
            Some(b) => format!(
                "allowed: 0 < cfl <= {b:.4}, the linear stability bound of tlmpm at {} points per cell and flip_fraction {} (derived in continuum::stability: the F update sees the re-mapped velocity)",
                s.particles_per_cell, s.flip_fraction
            ),
            None => cfl_message(implicit),
        };
        let dt = match (s.cfl, s.timestep) {
            (Some(c), Some(dt)) => {
                // Both given (as in a resolved scene): they must agree.
                if (c - dt * speed / h).abs() > 1e-9 * c.abs() {
                    return Err(loc.err(
                        "scheme.timestep",
                        dt,
                        format!("disagrees with cfl = {c} (which gives {:e} s); give `cfl` or `timestep`, not both", c * h / speed),
                    ));
                }
                if !(c > 0.0 && c <= cfl_limit) {
                    return Err(loc.err("scheme.cfl", c, cfl_message(implicit)));
                }
                dt
            }
            (None, None) => return Err(loc.err("scheme", "", "missing `cfl` (c dt / h, at most 1) or `timestep` (s)")),
            (Some(c), None) => {
                if !(c.is_finite() && c > 0.0 && c <= cfl_limit) {
                    return Err(loc.err("scheme.cfl", c, cfl_message(implicit)));
                }
                c * h / speed
            }
            (None, Some(dt)) => {
                finite_positive(loc, "scheme.timestep", dt, "the time step (s)")?;
                if dt > bound {
                    let form = if tlmpm.is_some() { format!("tlmpm's {cfl_limit} h / (c + |v|)") } else { "h / (c + |v|)".to_string() };
                    return Err(loc.err("scheme.timestep", dt, format!("exceeds the stability bound {form} = {bound:.6e} s (h = {h:e} m, c + |v| = {speed:e} m/s); use a smaller time step or `cfl`")));
                }
                // The resolved scene carries cfl = c dt / h, which must be positive to be read
                // again: a wave speed that small (a denormal modulus) cannot be stepped.
                if !(dt * speed / h > 0.0) {
                    return Err(loc.err(
                        "scheme.timestep",
                        dt,
                        format!("gives a CFL number c dt / h that underflows to 0 (h = {h:e} m, c + |v| = {speed:e} m/s): the materials' wave speed is too small to step; check their moduli and densities"),
                    ));
                }
                dt
            }
        };
        let motion_cells = match &s.adaptive {
            Some(a) if !implicit => {
                return Err(loc.err(
                    "scheme.adaptive",
                    format!("{{ rtol = {} }}", a.rtol),
                    "adaptive steps need scheme.integrator = \"implicit-trapezoidal\"",
                ));
            }
            Some(a) => {
                validate_adaptive(loc, a)?;
                a.max_motion_cells
            }
            None => continuum::solver::implicit::ImplicitOptions::default().max_motion_cells,
        };
        let moving = self.bodies.values().flat_map(|b| b.velocity.iter()).fold(0.0_f64, |m, v| m.max(v.abs()));
        if implicit && moving * dt > motion_cells * h {
            return Err(loc.err(
                "scheme.timestep",
                dt,
                format!(
                    "moves points {:.3} cells per step at the initial body speed {moving:e} m/s; the implicit step freezes the stencil, so at most {} (use dt <= {:.6e} s)",
                    moving * dt / h,
                    motion_cells,
                    motion_cells * h / moving
                ),
            ));
        }
        let steps = (s.end_time / dt - 1e-9).ceil().max(1.0);
        if steps > 1e9 {
            return Err(loc.err("scheme.end_time", s.end_time, format!("needs {steps:e} steps of {dt:e} s; more than 1e9 steps")));
        }
        s.cfl = Some(dt * speed / h);
        s.timestep = Some(dt);
        Ok((dt, steps as u64))
    }

    /// Returns the file a direct-MD reference names (made absolute in the scene).
    fn validate_reference(&mut self, loc: &Locator<'_>, base: &Path) -> Result<Option<PathBuf>, SceneError> {
        match self.reference.clone() {
            None => Ok(None),
            Some(Reference::IsothermalRiemann(r)) => self.validate_riemann(loc, &r).map(|_| None),
            Some(Reference::Manufactured(r)) => self.validate_manufactured(loc, &r).map(|_| None),
            Some(Reference::VibratingBar(r)) => self.validate_vibrating_bar(loc, &r).map(|_| None),
            Some(Reference::ThinFilmLithiation(r)) => self.validate_thin_film(loc, &r).map(|_| None),
            Some(Reference::HeatSeries(_)) => {
                let value = |f: &Option<FaceBc>| f.as_ref().and_then(|f| f.value);
                let ok = match (self.domain.dimension, self.diffusion.as_ref()) {
                    (1, Some(d)) => value(&d.x_min).is_some() && value(&d.x_max).is_some(),
                    (2, Some(d)) => {
                        let v = value(&d.x_min);
                        v.is_some() && [&d.x_max, &d.y_min, &d.y_max].iter().all(|f| value(f) == v)
                    }
                    _ => false,
                };
                if ok {
                    Ok(None)
                } else {
                    Err(loc.err(
                        "reference.solution",
                        "\"heat-series\"",
                        "needs a 1D scene with [diffusion] x_min = { value = .. } and x_max = { value = .. }, or a 2D scene \
                         with the same value on all four faces (x_min, x_max, y_min, y_max = { value = c1 })",
                    ))
                }
            }
            Some(Reference::DirectMd(r)) => {
                let file = self.validate_direct_md(loc, &r, base)?;
                self.reference = Some(Reference::DirectMd(DirectMdReference { profile: file.clone(), ..r }));
                Ok(Some(file))
            }
        }
    }

    /// A direct-MD profile: readable, with the component's column, a frame at every time (each
    /// within the profile's range and the run), a 1D scene whose bodies map onto one bar, and
    /// particle snapshots to score. Returns the profile's absolute path.
    fn validate_direct_md(&self, loc: &Locator<'_>, r: &DirectMdReference, base: &Path) -> Result<PathBuf, SceneError> {
        let file = base.join(&r.profile);
        let profile = crate::reference::DirectProfile::read_component(&file, r.component.as_str()).map_err(|e| {
            loc.err(
                "reference.profile",
                format!("{:?}", r.profile),
                format!("{e:#}; the profile is the CSV of `md-worker direct` (1D slabs or 2D bins), its path relative to the scene file"),
            )
        })?;
        let profile_dim = if profile.is_2d() { 2 } else { 1 };
        if self.domain.dimension != profile_dim {
            return Err(loc.err(
                "reference.profile",
                format!("{:?}", r.profile),
                format!(
                    "is a {profile_dim}D profile ({}); this scene has dimension {}: a 1D scene needs the slabs of `md-worker direct`, a 2D one the bins of `md-worker direct --dimension 2`",
                    if profile_dim == 2 { "Eulerian x-y bins" } else { "slabs" },
                    self.domain.dimension
                ),
            ));
        }
        if profile.is_2d() && profile.bulk_atoms() == 0 {
            return Err(loc.err(
                "reference.profile",
                format!("{:?}", r.profile),
                "its first frame has no occupied bin: no bulk bin to scale the 80 % mask",
            ));
        }
        if r.times_ps.is_empty() {
            return Err(loc.err("reference.times_ps", "[]", "give at least one time (ps) to score at, e.g. [5.0, 10.0]"));
        }
        let (first, last) = profile.time_range();
        for (k, &t) in r.times_ps.iter().enumerate() {
            let key = format!("reference.times_ps[{k}]");
            if !t.is_finite()
                || t * 1e-12 < first - crate::reference::TIME_TOLERANCE_S
                || t * 1e-12 > last + crate::reference::TIME_TOLERANCE_S
            {
                return Err(loc.err(
                    &key,
                    t,
                    format!(
                        "outside the profile's range {} to {} ps ({})",
                        (first * 1e15).round() / 1e3,
                        (last * 1e15).round() / 1e3,
                        file.display()
                    ),
                ));
            }
            if !profile.has_frame(t * 1e-12) {
                return Err(loc.err(&key, t, format!("the profile has no frame at t = {t} ps (it has {} ps)", profile.times_ps())));
            }
            if t * 1e-12 > self.scheme.end_time * (1.0 + 1e-9) {
                return Err(loc.err(&key, t, format!("after the end time {} ps of the run", self.scheme.end_time * 1e12)));
            }
        }
        if !self.output.particles {
            return Err(loc.err(
                "output.particles",
                "false",
                "a direct-md reference scores the particle snapshots: needs output.particles = true",
            ));
        }
        if !profile.is_2d()
            && let Err(e) = crate::reference::ReferenceMap::of(self)
        {
            return Err(loc.err("reference.solution", "\"direct-md\"", format!("{e:#}")));
        }
        Ok(file.canonicalize().unwrap_or(file))
    }

    /// The manufactured solution of a validated scene's `[reference]`, if it names one.
    fn manufactured(&self) -> Option<continuum::exact::Manufactured> {
        let Some(Reference::Manufactured(r)) = &self.reference else { return None };
        let body = self.bodies.values().next()?;
        let Material::NeoHookean(e) = &body.material else { return None };
        Some(continuum::exact::Manufactured {
            amplitude: r.amplitude,
            youngs_modulus: e.youngs_modulus,
            poisson_ratio: e.poisson_ratio,
            density0: body.density,
        })
    }

    /// The vibrating bar of a validated scene's `[reference]`, if it names one.
    fn vibrating_bar(&self) -> Option<continuum::exact::VibratingBar> {
        let Some(Reference::VibratingBar(r)) = &self.reference else { return None };
        let body = self.bodies.values().next()?;
        let Material::LinearPiola(e) = &body.material else { return None };
        let (lambda, mu) = continuum::closure::lame(e.youngs_modulus, e.poisson_ratio);
        Some(continuum::exact::VibratingBar { amplitude: r.amplitude, modulus: lambda + 2.0 * mu, density0: body.density })
    }

    /// The vibrating bar holds for one `linear-piola` body filling [0, 1] in 1D, at rest and
    /// unstrained as given (the reference sets the velocity), with fixed or periodic ends (u = 0
    /// at X = 0 and 1, and the mode is periodic); |2 pi A| < 1 keeps F positive; the time step
    /// stays within the explicit bound with the particle speed A c pi added.
    fn validate_vibrating_bar(&self, loc: &Locator<'_>, r: &ManufacturedReference) -> Result<(), SceneError> {
        let a = r.amplitude;
        if !(a.is_finite() && a != 0.0 && 2.0 * std::f64::consts::PI * a.abs() < 1.0) {
            return Err(loc.err(
                "reference.amplitude",
                a,
                "the amplitude A (m) must be finite, nonzero and below 1/(2 pi) = 0.159 (the stretch 1 + 2 pi A cos(2 pi X) sin(c pi t) must stay positive)",
            ));
        }
        if self.domain.dimension != 1 {
            return Err(loc.err(
                "reference.solution",
                "\"vibrating-bar\"",
                format!("the vibrating bar is 1D; this scene has dimension {}", self.domain.dimension),
            ));
        }
        if self.domain.min[0].abs() > 1e-12 || (self.domain.max[0] - 1.0).abs() > 1e-12 {
            return Err(loc.err(
                "domain.max",
                vec_str(&self.domain.max),
                "the vibrating bar is defined on [0, 1]: domain.min = [0.0], domain.max = [1.0]",
            ));
        }
        let mut names = self.bodies.keys();
        let (Some(name), None) = (names.next(), names.next()) else {
            return Err(loc.err(
                "bodies",
                self.bodies.keys().cloned().collect::<Vec<_>>().join(", "),
                "the vibrating bar needs exactly one body (linear-piola, filling [0, 1])",
            ));
        };
        let b = &self.bodies[name];
        let k = |f: &str| format!("bodies.{name}.{f}");
        let Material::LinearPiola(_) = &b.material else {
            return Err(loc.err(
                &k("material.law"),
                format!("{:?}", b.material.law()),
                "the vibrating bar's body force is that of the linear law sigma = M (F - 1): law = \"linear-piola\"",
            ));
        };
        if b.min[0].abs() > 1e-12 || (b.max[0] - 1.0).abs() > 1e-12 {
            return Err(loc.err(&k("max"), format!("min {:?} max {:?}", b.min, b.max), "the body must fill [0, 1]"));
        }
        if b.velocity.iter().any(|v| *v != 0.0) {
            return Err(loc.err(
                &k("velocity"),
                vec_str(&b.velocity),
                "the reference sets the initial velocity A c pi sin(2 pi X): leave `velocity` out",
            ));
        }
        if b.initial_strain.iter().any(|e| *e != 0.0) {
            return Err(loc.err(&k("initial_strain"), vec_str(&b.initial_strain), "the vibrating bar starts unstrained: leave it out"));
        }
        for (face, spec) in self.boundary.faces().into_iter().take(2) {
            if !matches!(spec, FaceSpec::Named(FaceName::Fixed | FaceName::Periodic)) {
                return Err(loc.err(
                    &format!("boundary.{face}"),
                    face_debug(spec),
                    "the vibrating bar has u = 0 at X = 0 and 1: \"fixed\" (or \"periodic\" on both ends)",
                ));
            }
        }
        if let (Some(dt), Some(m)) = (self.scheme.timestep, self.vibrating_bar()) {
            let h = self.domain.cell_size[0];
            let speed = m.speed() + m.max_speed();
            if dt * speed / h > self.explicit_cfl_limit() {
                return Err(loc.err(
                    "scheme.timestep",
                    dt,
                    format!(
                        "with the bar's particle speed A c pi = {:e} m/s, dt exceeds the bound {} = {:e} s",
                        m.max_speed(),
                        self.explicit_bound_form(),
                        self.explicit_cfl_limit() * h / speed
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Gong's manufactured solution holds for one neo-Hookean body filling the unit domain,
    /// at rest and unstrained as given (the reference sets the velocity), with rollers on every
    /// face (the tangential velocity at a wall is not zero in 2D and 3D); its amplitude keeps
    /// F = 1 + pi G cos(pi X) sin(c pi t) positive; an explicit time step stays within the
    /// explicit bound with the solution's particle speed c pi G added to the wave speed (the
    /// scene's `cfl` counts the wave speed only, so dt = 0.4 h / c of Gong is a fixed `cfl`).
    /// The implicit integrator has no such bound: its motion per step is checked by the solver
    /// on the converged displacement of every step (c pi G dt, the constant-velocity predictor's
    /// motion, overstates an oscillation's by 1 + (w dt / 2)^2, so it is no bound to refuse on).
    fn validate_manufactured(&self, loc: &Locator<'_>, r: &ManufacturedReference) -> Result<(), SceneError> {
        let g = r.amplitude;
        if !(g.is_finite() && g != 0.0 && std::f64::consts::PI * g.abs() < 1.0) {
            return Err(loc.err(
                "reference.amplitude",
                g,
                "the amplitude G (m) must be finite, nonzero and below 1/pi = 0.318 (the stretch 1 + pi G cos(pi X) sin(c pi t) must stay positive)",
            ));
        }
        let dim = self.domain.dimension;
        let unit = |min: &[f64], max: &[f64]| (0..dim).all(|a| min[a].abs() <= 1e-12 && (max[a] - 1.0).abs() <= 1e-12);
        if !unit(&self.domain.min, &self.domain.max) {
            return Err(loc.err(
                "domain.max",
                vec_str(&self.domain.max),
                format!(
                    "the manufactured solution is defined on the unit domain: domain.min = {:?}, domain.max = {:?}",
                    vec![0.0; dim],
                    vec![1.0; dim]
                ),
            ));
        }
        let mut names = self.bodies.keys();
        let (Some(name), None) = (names.next(), names.next()) else {
            return Err(loc.err(
                "bodies",
                self.bodies.keys().cloned().collect::<Vec<_>>().join(", "),
                "the manufactured solution needs exactly one body (neo-hookean, filling the domain)",
            ));
        };
        let b = &self.bodies[name];
        let k = |f: &str| format!("bodies.{name}.{f}");
        let Material::NeoHookean(_) = &b.material else {
            return Err(loc.err(
                &k("material.law"),
                format!("{:?}", b.material.law()),
                "the manufactured solution's body force is that of the neo-hookean law: law = \"neo-hookean\"",
            ));
        };
        if !unit(&b.min, &b.max) {
            return Err(loc.err(&k("max"), format!("min {:?} max {:?}", b.min, b.max), "the body must fill the unit domain"));
        }
        if b.velocity.iter().any(|v| *v != 0.0) {
            return Err(loc.err(
                &k("velocity"),
                vec_str(&b.velocity),
                "the manufactured reference sets the initial velocity c pi G sin(pi X): leave `velocity` out",
            ));
        }
        if b.initial_strain.iter().any(|e| *e != 0.0) {
            return Err(loc.err(
                &k("initial_strain"),
                vec_str(&b.initial_strain),
                "the manufactured solution starts unstrained: leave it out",
            ));
        }
        for (i, (face, spec)) in self.boundary.faces().into_iter().enumerate() {
            if i / 2 < dim && !matches!(spec, FaceSpec::Named(FaceName::Reflective | FaceName::Roller)) {
                return Err(loc.err(
                    &format!("boundary.{face}"),
                    face_debug(spec),
                    "the manufactured solution has zero normal and free tangential velocity on every face: \"roller\" (or \"reflective\")",
                ));
            }
        }
        let explicit = self.scheme.integrator != continuum::solver::TimeIntegrator::ImplicitTrapezoidal;
        if let (true, Some(dt), Some(m)) = (explicit, self.scheme.timestep, self.manufactured()) {
            let h = self.domain.cell_size.iter().cloned().fold(f64::INFINITY, f64::min);
            let (lambda, mu) = continuum::closure::lame(m.youngs_modulus, m.poisson_ratio);
            let speed = ((lambda + 2.0 * mu) / m.density0).sqrt() + m.max_speed();
            if dt * speed / h > self.explicit_cfl_limit() {
                return Err(loc.err(
                    "scheme.cfl",
                    self.scheme.cfl.unwrap_or_default(),
                    format!(
                        "with the manufactured particle speed c pi G = {:e} m/s, dt = {dt:e} s exceeds the bound {} = {:e} s",
                        m.max_speed(),
                        self.explicit_bound_form(),
                        self.explicit_cfl_limit() * h / speed
                    ),
                ));
            }
        }
        Ok(())
    }

    fn validate_riemann(&self, loc: &Locator<'_>, r: &RiemannReference) -> Result<(), SceneError> {
        if self.domain.dimension != 1 {
            return Err(loc.err("reference.solution", "\"isothermal-riemann\"", "needs a 1D scene"));
        }
        let mut speeds = BTreeSet::new();
        for (key, name) in [("reference.left", &r.left), ("reference.right", &r.right)] {
            match self.bodies.get(name).map(|b| &b.material) {
                None => {
                    return Err(loc.err(
                        key,
                        format!("{name:?}"),
                        format!("no such body; bodies: {}", self.bodies.keys().cloned().collect::<Vec<_>>().join(", ")),
                    ));
                }
                Some(Material::IdealGasIsothermal(g)) => {
                    speeds.insert(g.sound_speed.to_bits());
                }
                Some(m) => {
                    return Err(loc.err(
                        key,
                        format!("{name:?}"),
                        format!("the isothermal Riemann solution needs ideal-gas-isothermal bodies, this one is {}", m.law()),
                    ));
                }
            }
        }
        if speeds.len() != 1 {
            return Err(loc.err("reference.right", format!("{:?}", r.right), "both bodies must have the same sound speed"));
        }
        Ok(())
    }

    /// A thin-film reference: a 1D scene, the film a uniformly lithiated `hypoelastic-plastic`
    /// body, the substrate face `x_min` holding it (fixed or reflective).
    fn validate_thin_film(&self, loc: &Locator<'_>, r: &ThinFilmReference) -> Result<(), SceneError> {
        if self.domain.dimension != 1 {
            return Err(loc.err(
                "reference.solution",
                "\"thin-film-lithiation\"",
                format!(
                    "needs a 1D scene along the film normal (the in-plane axes are held by the 1D kinematics); this one has dimension {}",
                    self.domain.dimension
                ),
            ));
        }
        let Some(b) = self.bodies.get(&r.body) else {
            return Err(loc.err(
                "reference.body",
                format!("{:?}", r.body),
                format!("no such body; bodies: {}", self.bodies.keys().cloned().collect::<Vec<_>>().join(", ")),
            ));
        };
        if !matches!(b.material, Material::HypoelasticPlastic(_)) || b.lithiation.is_none() {
            return Err(loc.err(
                "reference.body",
                format!("{:?}", r.body),
                format!(
                    "the thin-film solution needs a hypoelastic-plastic body with a [lithiation]; this one is {}{}",
                    b.material.law(),
                    if b.lithiation.is_none() { " without lithiation" } else { "" }
                ),
            ));
        }
        if !matches!(self.boundary.x_min, FaceSpec::Named(FaceName::Fixed | FaceName::Reflective | FaceName::Roller)) {
            return Err(loc.err(
                "boundary.x_min",
                face_debug(&self.boundary.x_min),
                "the substrate face of a thin film must be fixed (or reflective)",
            ));
        }
        Ok(())
    }

    /// `output.dump_points`: each id must name a material point of an md body, once.
    fn validate_dump_points(&self, loc: &Locator<'_>, counts: &[(String, usize)]) -> Result<(), SceneError> {
        let ids = &self.output.dump_points;
        if ids.is_empty() {
            return Ok(());
        }
        // Point ids run body after body (in name order), as in the particle files.
        let mut ranges = Vec::new();
        let mut first = 0u64;
        for (name, n) in counts {
            ranges.push((name.clone(), first..first + *n as u64));
            first += *n as u64;
        }
        let md_ranges: Vec<String> = ranges
            .iter()
            .filter(|(name, r)| !r.is_empty() && matches!(self.bodies[name].material, Material::Md(_)))
            .map(|(name, r)| format!("{}..={} (body `{name}`)", r.start, r.end - 1))
            .collect();
        let md_ids =
            if md_ranges.is_empty() { "the scene has no md body".to_string() } else { format!("md points: {}", md_ranges.join(", ")) };
        let mut seen = BTreeSet::new();
        for (k, &id) in ids.iter().enumerate() {
            let key = format!("output.dump_points[{k}]");
            let Some((name, _)) = ranges.iter().find(|(_, r)| r.contains(&id)) else {
                return Err(loc.err(
                    &key,
                    id,
                    format!(
                        "no such material point: the scene has {first} material points (ids 0..={}); {md_ids}",
                        first.saturating_sub(1)
                    ),
                ));
            };
            let body = &self.bodies[name];
            if !matches!(body.material, Material::Md(_)) {
                return Err(loc.err(
                    &key,
                    id,
                    format!("point {id} belongs to body `{name}` (law {}), which has no MD box; {md_ids}", body.material.law()),
                ));
            }
            if !seen.insert(id) {
                return Err(loc.err(&key, id, "listed twice"));
            }
        }
        Ok(())
    }

    /// The MD time step (s) shared by every md body, if there are any.
    fn md_step(&self, loc: &Locator<'_>) -> Result<Option<f64>, SceneError> {
        let mut step: Option<(String, f64)> = None;
        for (name, b) in &self.bodies {
            if let Material::Md(m) = &b.material {
                match &step {
                    Some((first, fs)) if *fs != m.timestep_fs => {
                        return Err(loc.err(
                            &format!("bodies.{name}.material.timestep_fs"),
                            m.timestep_fs,
                            format!("every md body must use the same MD time step; body `{first}` uses {fs} fs"),
                        ));
                    }
                    Some(_) => {}
                    None => step = Some((name.clone(), m.timestep_fs)),
                }
            }
        }
        Ok(step.map(|(_, fs)| fs * 1e-15))
    }

    /// A continuum step is a whole number of MD steps: a step from `cfl` is rounded down to
    /// one; a given `timestep` must be one.
    fn fit_to_md_step(
        &mut self,
        loc: &Locator<'_>,
        dt: f64,
        md_step: f64,
        user_timestep: bool,
        speed: f64,
    ) -> Result<(f64, u64), SceneError> {
        let n = dt / md_step;
        let whole = (n + 1e-9).floor();
        if whole < 1.0 {
            return Err(loc.err("scheme.timestep", dt, format!("the continuum step is shorter than one MD step ({md_step:e} s)")));
        }
        if user_timestep && (n - n.round()).abs() > 1e-6 * n {
            return Err(loc.err(
                "scheme.timestep",
                dt,
                format!("must be a whole number of MD steps ({md_step:e} s); e.g. {:e} s", whole * md_step),
            ));
        }
        let dt = if user_timestep { n.round() * md_step } else { whole * md_step };
        let h = self.domain.cell_size.iter().cloned().fold(f64::INFINITY, f64::min);
        // The same speed as the CFL number of `validate_scheme`: wave speed plus body speed.
        let speed = speed + self.bodies.values().flat_map(|b| b.velocity.iter()).fold(0.0_f64, |m, v| m.max(v.abs()));
        let steps = (self.scheme.end_time / dt - 1e-9).ceil().max(1.0) as u64;
        self.scheme.timestep = Some(dt);
        self.scheme.cfl = Some(dt * speed / h);
        Ok((dt, steps))
    }
}

/// A face as messages have always shown it (`Named("reflective")`, `Piston { piston: [..] }`).
fn face_debug(f: &FaceSpec) -> String {
    match f {
        FaceSpec::Named(n) => format!("Named({:?})", n.scene_name()),
        FaceSpec::Piston { piston } => format!("Piston {{ piston: {piston:?} }}"),
    }
}

/// `scheme.adaptive`: every tolerance and factor in its range.
fn validate_adaptive(loc: &Locator<'_>, a: &crate::scene::AdaptiveSpec) -> Result<(), SceneError> {
    let check = |key: &str, v: f64, ok: bool, what: &str| {
        if ok && v.is_finite() { Ok(()) } else { Err(loc.err(&format!("scheme.adaptive.{key}"), v, what)) }
    };
    check("rtol", a.rtol, a.rtol > 0.0, "the relative tolerance must be finite and positive")?;
    check(
        "atol_displacement",
        a.atol_displacement,
        a.atol_displacement > 0.0,
        "the absolute displacement tolerance (m) must be finite and positive",
    )?;
    check("atol_velocity", a.atol_velocity, a.atol_velocity > 0.0, "the absolute velocity tolerance (m/s) must be finite and positive")?;
    if let Some(t) = a.atol_deformation {
        check("atol_deformation", t, t > 0.0, "the absolute deformation-gradient tolerance must be finite and positive (or absent)")?;
    }
    check("safety", a.safety, a.safety > 0.0 && a.safety <= 1.0, "the safety factor must lie in (0, 1]")?;
    check("max_growth", a.max_growth, a.max_growth >= 1.0, "the largest growth of a step must be finite and at least 1")?;
    check("min_shrink", a.min_shrink, a.min_shrink > 0.0 && a.min_shrink < 1.0, "the smallest shrink factor must lie in (0, 1)")?;
    check("dt_min", a.dt_min, a.dt_min >= 0.0, "the smallest step (s) must be finite and >= 0")?;
    if let Some(m) = a.dt_max {
        check("dt_max", m, m > 0.0 && m >= a.dt_min, "the largest step (s) must be finite, positive and at least dt_min")?;
    }
    check(
        "max_motion_cells",
        a.max_motion_cells,
        a.max_motion_cells > 0.0 && a.max_motion_cells <= 0.5,
        "the motion bound must lie in (0, 0.5] cells (the stencil is frozen over a step)",
    )?;
    if a.max_rejections == 0 {
        return Err(loc.err("scheme.adaptive.max_rejections", 0, "must be at least 1"));
    }
    Ok(())
}

/// TLMPM's derived linear bound (c dt / h) at `ppc` points per cell and the blend `flip`, rounded
/// down to 4 digits (the hats at rest are a valid layout, so the analysis always gives one).
fn tlmpm_bound(ppc: usize, flip: f64, form: super::TlmpmForm) -> f64 {
    let layout = continuum::stability::Layout { scheme: SchemeKind::Tlmpm, particles_per_cell: ppc, sub_points: 1 };
    let b = match form {
        super::TlmpmForm::TotalLagrangian => continuum::stability::cfl_bound(layout, continuum::solver::TimeIntegrator::Leapfrog, flip),
        super::TlmpmForm::MovingMesh => continuum::stability::moving_mesh_bound(layout),
    };
    (b.ok().flatten().unwrap_or(CFL_LIMIT) * 1e4).floor() / 1e4
}

fn cfl_message(implicit: bool) -> String {
    if implicit {
        "must be a finite positive number (the implicit integrator has no CFL bound, only one on motion per step)".into()
    } else {
        format!("allowed: 0 < cfl <= {CFL_LIMIT} (explicit stability bound)")
    }
}

/// What `scheme.integrator = "implicit-trapezoidal"` cannot run with: DDMP (its force on empty
/// nodes is handed on by the explicit cycle only), artificial viscosity (no tangent) and md
/// bodies (their boxes keep state, so Newton cannot evaluate them more than once a step).
fn implicit_supported(
    loc: &Locator<'_>,
    kind: SchemeKind,
    viscosity: ViscosityForm,
    bodies: &BTreeMap<String, Body>,
) -> Result<(), SceneError> {
    let why = if kind.is_ddmp() {
        Some(format!(
            "needs a method whose force stays on nodes with mass: mpm, ugimp, cpgimp, cpdi, cpdi1 or cpdi2 (`{}` hands force on from empty nodes, which the implicit residual does not)",
            kind.name()
        ))
    } else if viscosity != ViscosityForm::None {
        Some("needs scheme.artificial_viscosity = \"none\" (the viscosity has no tangent for Newton)".to_string())
    } else {
        bodies.iter().find(|(_, b)| matches!(b.material, Material::Md(_))).map(|(name, _)| {
            format!("body `{name}` is an md body: its boxes keep state between calls, so Newton cannot evaluate them repeatedly (use dhakal or leapfrog)")
        })
    };
    match why {
        Some(w) => Err(loc.err("scheme.integrator", "\"implicit-trapezoidal\"", w)),
        None => Ok(()),
    }
}
