//! What validation hands to setup: a [`ResolvedScene`], every value typed and every default
//! and measurement in place (the lattice of each md body measured once, the material points
//! of each body counted), so that setup compares no strings and falls back to nothing.

use super::{Notch, Shape};
use continuum::solver::{TimeIntegrator, Viscosity};
use continuum::{Face, SchemeKind};
use coupling::lattice::LatticeProperties;
use md_worker::{DeformMode, LatticeKind, Orientation, StressSampling};
use std::path::PathBuf;

/// A validated scene as setup consumes it.
#[derive(Debug, Clone)]
pub struct ResolvedScene {
    /// 1, 2 or 3.
    pub dimension: usize,
    /// Lower corner of the grid (m), one value per dimension.
    pub origin: Vec<f64>,
    /// Cell size per axis (m).
    pub cell_size: Vec<f64>,
    /// Cells per axis.
    pub cells: Vec<usize>,
    /// (lower, upper) face per axis, x, y, z (free beyond the dimension).
    pub faces: [(Face, Face); 3],
    pub scheme: SchemeKind,
    pub particles_per_cell: usize,
    pub sub_points: usize,
    pub viscosity: Viscosity,
    pub integrator: TimeIntegrator,
    /// PIC/FLIP blend in [0, 1] (1: FLIP).
    pub flip_fraction: f64,
    /// `scheme.gradient_correction` (explicit point-weight schemes only).
    pub gradient_correction: continuum::solver::GradientCorrection,
    /// `scheme.nullspace_filter` (explicit stencil schemes; global-svd 1D only).
    pub nullspace_filter: continuum::solver::NullspaceFilter,
    /// `scheme.tlmpm_form = "moving-mesh"` (tlmpm only).
    pub moving_mesh: bool,
    pub jacobian: continuum::solver::implicit::JacobianKind,
    /// Adaptive implicit steps (end time set), and the motion bound of a step in cells.
    pub adaptive: Option<continuum::solver::implicit::Adaptive>,
    pub max_motion_cells: f64,
    /// `scheme.density_scaling` (already applied to every body's density).
    pub density_scaling: f64,
    pub small_mass_fraction: f64,
    /// Time step (s).
    pub dt: f64,
    /// Steps to the end time.
    pub steps: u64,
    /// In name order (the order of the point ids).
    pub bodies: Vec<ResolvedBody>,
    /// `[reference] solution = "manufactured"`: the solution whose body force and initial
    /// velocity setup applies.
    pub manufactured: Option<continuum::exact::Manufactured>,
    /// `[reference] solution = "vibrating-bar"`: likewise.
    pub vibrating_bar: Option<continuum::exact::VibratingBar>,
    /// The scalar field's diffusion, if the scene has one.
    pub diffusion: Option<ResolvedDiffusion>,
}

/// `[diffusion]` as setup consumes it.
#[derive(Debug, Clone)]
pub struct ResolvedDiffusion {
    pub diffusivity: f64,
    pub law: continuum::diffusion::DiffusivityLaw,
    pub flip: f64,
    pub dirichlet: continuum::diffusion::DirichletMode,
    /// (min, max) face per axis, x, y, z.
    pub faces: [(Option<continuum::diffusion::FaceCondition>, Option<continuum::diffusion::FaceCondition>); 3],
    /// The corrected explicit bound J_min h0^2 / (2 d K) (s).
    pub bound: f64,
    /// Indices of the bodies that carry the field (empty: every body).
    pub bodies: Vec<usize>,
    /// The surface flux j into the diffusing bodies' exposed faces (0: none).
    pub surface_flux: f64,
}

/// One body: its region, initial state, closure and number of material points.
#[derive(Debug, Clone)]
pub struct ResolvedBody {
    pub name: String,
    /// Lower corner (m), one value per dimension.
    pub min: Vec<f64>,
    /// Upper corner (m).
    pub max: Vec<f64>,
    /// The notch cut into the `y_max` face of a notched block.
    pub notch: Option<Notch>,
    /// Reference density (kg/m^3).
    pub density: f64,
    /// Initial velocity (m/s), one value per dimension.
    pub velocity: Vec<f64>,
    /// Initial diagonal engineering strain (xx, yy, zz).
    pub initial_strain: [f64; 3],
    pub temperature_k: f64,
    pub law: Law,
    /// Material points of the body.
    pub points: usize,
    /// (initial concentration, uniform rate (1/s)) of a lithiated body.
    pub lithiation: Option<(f64, f64)>,
    /// Ramp time (s) of the lithiation rate (0: none).
    pub lithiation_ramp: f64,
}

/// A body's closure with its parameters.
#[derive(Debug, Clone)]
pub enum Law {
    IdealGasIsothermal { sound_speed: f64 },
    LinearElastic { youngs_modulus: f64, poisson_ratio: f64 },
    NeoHookean { youngs_modulus: f64, poisson_ratio: f64 },
    LinearPiola { youngs_modulus: f64, poisson_ratio: f64 },
    Md(Box<ResolvedMd>),
    HypoelasticPlastic(continuum::silicon::ChemoPlastic),
}

/// An md body's boxes: everything a box spec and the MD closure need.
#[derive(Debug, Clone)]
pub struct ResolvedMd {
    /// Absolute path of the potential file.
    pub potential: PathBuf,
    pub lattice: LatticeKind,
    pub lattice_constant_angstrom: f64,
    pub cells_per_side: usize,
    pub orientation: Orientation,
    /// MD time step (fs).
    pub timestep_fs: f64,
    pub stress_sampling: StressSampling,
    pub energy_consistency: bool,
    pub viscous_heating: bool,
    pub seed: u64,
    pub relax_steps: usize,
    pub relax_box: bool,
    pub deformation: DeformMode,
    pub reuse: coupling::Reuse,
    /// Measured once, by validation.
    pub lattice_properties: LatticeProperties,
    pub atoms_per_box: u64,
}

impl ResolvedScene {
    /// The md parameters of body `index`, if it is an md body.
    pub fn md(&self, index: usize) -> Option<&ResolvedMd> {
        match &self.bodies.get(index)?.law {
            Law::Md(m) => Some(m),
            _ => None,
        }
    }

    /// The md bodies with their parameters, in body order.
    pub fn md_bodies(&self) -> impl Iterator<Item = (&ResolvedBody, &ResolvedMd)> {
        self.bodies.iter().filter_map(|b| match &b.law {
            Law::Md(m) => Some((b, m.as_ref())),
            _ => None,
        })
    }

    /// Material points of every body, in body order (their ids run body after body).
    pub fn point_counts(&self) -> Vec<(String, usize)> {
        self.bodies.iter().map(|b| (b.name.clone(), b.points)).collect()
    }
}

/// Whether a point lies in a body's region (half-open box, minus the notch).
fn inside<const D: usize>(min: &[f64], max: &[f64], notch: Option<&Notch>, x: &[f64; D]) -> bool {
    let in_box = (0..D).all(|a| x[a] >= min[a] && x[a] < max[a]);
    if !in_box {
        return false;
    }
    match notch {
        Some(n) if D >= 2 => {
            // Triangle with its tip at (center, top - depth) opening to width at the top face.
            let below_top = max[1] - x[1];
            let half_width_here = 0.5 * n.width * (1.0 - below_top / n.depth);
            !(below_top < n.depth && (x[0] - n.center).abs() < half_width_here)
        }
        _ => true,
    }
}

/// Calls `f` with every material point position of a region, `ppc` per axis per cell at the
/// cells' sub-centres, x fastest (the order of the whole grid's sub-centres); only the
/// sub-centres near the region's box are visited.
pub(crate) fn for_each_point<const D: usize>(
    origin: &[f64],
    h: &[f64],
    cells: &[usize],
    ppc: usize,
    (min, max, notch): (&[f64], &[f64], Option<&Notch>),
    mut f: impl FnMut([f64; D]),
) {
    // Index ranges per axis, one sub-cell wider than the box on each side; `inside` decides.
    let range: [std::ops::Range<usize>; D] = std::array::from_fn(|a| {
        let n = cells[a] * ppc;
        let step = h[a] / ppc as f64;
        let lo = ((min[a] - origin[a]) / step - 0.5).floor() - 1.0;
        let hi = ((max[a] - origin[a]) / step - 0.5).ceil() + 2.0;
        let clamp = |v: f64| if v.is_finite() { v.clamp(0.0, n as f64) as usize } else { 0 };
        clamp(lo)..clamp(hi)
    });
    if range.iter().any(|r| r.is_empty()) {
        return;
    }
    let mut idx: [usize; D] = std::array::from_fn(|a| range[a].start);
    loop {
        let x: [f64; D] = std::array::from_fn(|a| origin[a] + (idx[a] as f64 + 0.5) * h[a] / ppc as f64);
        if inside(min, max, notch, &x) {
            f(x);
        }
        // Odometer, axis 0 fastest.
        let mut a = 0;
        loop {
            idx[a] += 1;
            if idx[a] < range[a].end {
                break;
            }
            idx[a] = range[a].start;
            a += 1;
            if a == D {
                return;
            }
        }
    }
}

/// The region of a body as [`for_each_point`] takes it (the notch only of a notched block).
pub(crate) fn region<'a>(
    shape: Shape,
    min: &'a [f64],
    max: &'a [f64],
    notch: Option<&'a Notch>,
) -> (&'a [f64], &'a [f64], Option<&'a Notch>) {
    (min, max, if shape == Shape::NotchedBlock { notch } else { None })
}

/// Material points of a region (without building them).
pub(crate) fn count_points(
    dim: usize,
    origin: &[f64],
    h: &[f64],
    cells: &[usize],
    ppc: usize,
    r: (&[f64], &[f64], Option<&Notch>),
) -> usize {
    let mut n = 0;
    match dim {
        1 => for_each_point::<1>(origin, h, cells, ppc, r, |_| n += 1),
        2 => for_each_point::<2>(origin, h, cells, ppc, r, |_| n += 1),
        _ => for_each_point::<3>(origin, h, cells, ppc, r, |_| n += 1),
    }
    n
}
