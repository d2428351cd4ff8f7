//! Scene files: parsing, command-line overrides, validation and defaults.
//!
//! A scene is physics and numerics only (where it runs comes from the command line). It is read
//! in three stages: the TOML text is parsed into an editable document and `--set` overrides are
//! applied to it; the result is deserialised into typed structs (unknown keys, missing keys and
//! wrong types are refused there, with the line); then [`Scene::validate`] checks physics and
//! numerics, and fills every default, so `scene.resolved.toml` shows exactly what ran.
//! Every message names the file, the line (or the `--set` that put the value there), the key,
//! the value and what is allowed.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::path::PathBuf;

/// The scene-file schema this build reads.
pub const SCHEMA_VERSION: u32 = 1;

/// A problem with a scene: everything a user needs to find and fix it.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneError {
    pub file: String,
    /// Where the value came from: `line N` or `--set key=value`; empty when unknown.
    pub location: String,
    pub key: String,
    pub value: String,
    pub problem: String,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if !self.location.is_empty() {
            write!(f, ", {}", self.location)?;
        }
        if !self.key.is_empty() {
            write!(f, ": `{}`", self.key)?;
            if !self.value.is_empty() {
                write!(f, " = {}", self.value)?;
            }
        }
        write!(f, ": {}", self.problem)
    }
}

impl std::error::Error for SceneError {}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Scene-file schema version; this build reads 1.
    pub schema: u32,
    /// Name used for the run directory (default: the file's stem).
    #[serde(default)]
    pub name: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub description: String,
    pub domain: Domain,
    pub bodies: BTreeMap<String, Body>,
    pub scheme: Scheme,
    #[serde(default)]
    pub boundary: Boundary,
    #[serde(default)]
    pub output: Output,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<Reference>,
    /// Diffusion of the scalar field the points carry (concentration or temperature).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diffusion: Option<DiffusionSpec>,
}

/// `[diffusion]`: explicit diffusion of the points' scalar field (continuum::diffusion; in the
/// current configuration, or the reference one under `tlmpm`; the bodies that carry the field
/// start from their `lithiation.initial` or 0).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DiffusionSpec {
    /// Diffusivity K (m^2/s): k / (rho0 C) for heat, D for a concentration.
    pub diffusivity: f64,
    /// FLIP fraction beta of the point update (1: FLIP, 0: PIC; B 6.16).
    #[serde(default = "default_flip")]
    pub flip_fraction: f64,
    /// `rate` (the Dirichlet value reaches the points through the nodal rate, the default; it
    /// reproduces B Table 6.1) or `value` (on the nodal value only).
    #[serde(default)]
    pub dirichlet: DirichletSpec,
    /// How the diffusivity depends on the point: `{ kind = "pressure", alpha, beta, p_max }`
    /// (K exp(alpha c - beta p), p clamped to [-p_max, p_max], beta per Pa, p_max in Pa) or
    /// `{ kind = "cubic" }` (K (1 - c)^3); absent: constant.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub law: Option<DiffusivityLawSpec>,
    /// The bodies whose points carry and diffuse the field (absent: every body). The others
    /// hold their initial value and take no part; where they touch, no flux crosses (a
    /// substrate that takes no lithium).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bodies: Option<Vec<String>>,
    /// A flux j (content per unit area per second into the body: m/s for a normalised
    /// concentration) through the free surface of the diffusing bodies: battery thesis
    /// (7.16)-(7.18), the surface points and their areas found at t = 0 (a face is exposed
    /// where no point lies beyond it and the grid goes on), times the saturation factor
    /// clamp(1 + 0.25 ln(1 - c), 0, 1). Absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub surface_flux: Option<f64>,
    /// Face conditions: `{ value = c }` (Dirichlet) or `{ flux = j }` (into the body, per unit
    /// area per second); a face not given has no flux.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_min: Option<FaceBc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_max: Option<FaceBc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_min: Option<FaceBc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_max: Option<FaceBc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_min: Option<FaceBc>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_max: Option<FaceBc>,
}

/// `diffusion.law`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum DiffusivityLawSpec {
    Constant,
    Pressure { alpha: f64, beta: f64, p_max: f64 },
    Cubic,
}

fn default_flip() -> f64 {
    1.0
}

#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum DirichletSpec {
    #[default]
    Rate,
    Value,
}

/// A diffusion face condition: exactly one of `value` and `flux`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FaceBc {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flux: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Domain {
    /// 1, 2 or 3.
    pub dimension: usize,
    /// Lower corner (m), one value per dimension.
    pub min: Vec<f64>,
    /// Upper corner (m).
    pub max: Vec<f64>,
    /// Cells per axis (give `cells` or `cell_size`).
    #[serde(default)]
    pub cells: Vec<usize>,
    /// Cell size per axis (m).
    #[serde(default)]
    pub cell_size: Vec<f64>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Shape {
    /// Axis-aligned box from `min` to `max`.
    Block,
    /// A block by another name (the usual word for 1D specimens).
    Bar,
    /// A block with a triangular notch cut into its `y_max` face (2D/3D).
    NotchedBlock,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Notch {
    /// x of the notch tip (m).
    pub center: f64,
    /// Opening of the notch at the surface (m).
    pub width: f64,
    /// Depth of the notch from the surface (m).
    pub depth: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Body {
    pub shape: Shape,
    /// Lower corner (m).
    pub min: Vec<f64>,
    /// Upper corner (m).
    pub max: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notch: Option<Notch>,
    /// Reference (unstrained) density (kg/m^3).
    pub density: f64,
    /// Initial velocity (m/s); default at rest.
    #[serde(default)]
    pub velocity: Vec<f64>,
    /// Initial engineering strain along x, y, z (diagonal); default none.
    #[serde(default)]
    pub initial_strain: Vec<f64>,
    /// Initial temperature (K); used by MD closures.
    #[serde(default = "default_temperature")]
    pub temperature_k: f64,
    pub material: Material,
    /// A normalised lithium concentration c = c_Li / c_max carried by the body's points
    /// (laws with a chemical strain read its rate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lithiation: Option<Lithiation>,
}

/// `[bodies.<name>.lithiation]`: the body's concentration field.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Lithiation {
    /// Initial normalised concentration, in [0, 1].
    #[serde(default)]
    pub initial: f64,
    /// Uniform prescribed rate dc/dt (1/s) over the whole run: every point of the body gains
    /// the same concentration (uniform lithiation); the concentration must stay within [0, 1]
    /// up to `scheme.end_time`.
    #[serde(default)]
    pub uniform_rate: f64,
    /// Ramp time (s) of the uniform rate: the rate rises as (1 - cos(pi t / T)) / 2 over
    /// [0, T] and is full after (`continuum::silicon::ramp_integral`), so the start launches
    /// no thickness mode; 0 (the default): the full rate from the first step. Every lithiated
    /// body of a scene has the same ramp.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ramp_time: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn default_temperature() -> f64 {
    300.0
}

/// A body's material closure: a constitutive law by name, or `md`.
// One per body, built once per run: the size of the md variant costs nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "law", rename_all = "kebab-case")]
pub enum Material {
    /// p = c^2 rho.
    IdealGasIsothermal(IdealGas),
    /// Linear elasticity in rate form (Jaumann).
    LinearElastic(Elastic),
    /// Compressible neo-Hookean.
    NeoHookean(Elastic),
    /// P = lambda tr(F - I) I + mu (F - I + (F - I)^T): linear in the displacement gradient,
    /// sigma = M (F - 1) in 1D (the vibrating bar's law; not frame-indifferent).
    LinearPiola(Elastic),
    /// A periodic MD box per material point.
    Md(MdMaterial),
    /// Hypoelastic-plastic law in the unrotated frame with a chemical strain rate eta c_dot I
    /// and J2 plasticity with linear hardening (battery thesis Ch. 7.3; lithiated silicon).
    HypoelasticPlastic(ChemoPlasticMaterial),
}

impl Material {
    pub fn law(&self) -> &'static str {
        match self {
            Material::IdealGasIsothermal(_) => "ideal-gas-isothermal",
            Material::LinearElastic(_) => "linear-elastic",
            Material::NeoHookean(_) => "neo-hookean",
            Material::LinearPiola(_) => "linear-piola",
            Material::Md(_) => "md",
            Material::HypoelasticPlastic(_) => "hypoelastic-plastic",
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct IdealGas {
    /// Isothermal sound speed (m/s).
    pub sound_speed: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Elastic {
    /// Young's modulus (Pa).
    pub youngs_modulus: f64,
    pub poisson_ratio: f64,
}

/// `law = "hypoelastic-plastic"`: every key defaults to lithiated silicon (Ch. 7.3).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ChemoPlasticMaterial {
    /// Bulk modulus K (Pa).
    #[serde(default = "si_bulk")]
    pub bulk_modulus: f64,
    /// Shear modulus G (Pa).
    #[serde(default = "si_shear")]
    pub shear_modulus: f64,
    /// Initial yield stress sigma_Y (Pa) of sqrt(3/2 s:s) <= sigma_Y + H eps_p.
    #[serde(default = "si_yield")]
    pub yield_stress: f64,
    /// Linear isotropic hardening modulus H (Pa); 0 is perfect plasticity.
    #[serde(default = "si_hardening")]
    pub hardening_modulus: f64,
    /// eta of the chemical strain rate eta c_dot I (per unit normalised concentration).
    #[serde(default = "si_eta")]
    pub chemical_expansion: f64,
}

fn si_bulk() -> f64 {
    continuum::silicon::ChemoPlastic::SILICON.bulk_modulus
}
fn si_shear() -> f64 {
    continuum::silicon::ChemoPlastic::SILICON.shear_modulus
}
fn si_yield() -> f64 {
    continuum::silicon::ChemoPlastic::SILICON.yield_stress
}
fn si_hardening() -> f64 {
    continuum::silicon::ChemoPlastic::SILICON.hardening_modulus
}
fn si_eta() -> f64 {
    continuum::silicon::ChemoPlastic::SILICON.chemical_expansion
}

impl ChemoPlasticMaterial {
    /// The law with the body's density.
    pub fn law(&self, density0: f64) -> continuum::silicon::ChemoPlastic {
        continuum::silicon::ChemoPlastic {
            bulk_modulus: self.bulk_modulus,
            shear_modulus: self.shear_modulus,
            yield_stress: self.yield_stress,
            hardening_modulus: self.hardening_modulus,
            chemical_expansion: self.chemical_expansion,
            density0,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MdMaterial {
    /// Potential file (LAMMPS eam, eam/alloy, eam/fs), relative to the scene file.
    pub potential: PathBuf,
    /// fcc, bcc or sc.
    #[serde(with = "names::named")]
    pub lattice: md_worker::LatticeKind,
    pub lattice_constant_angstrom: f64,
    /// Lattice cells per box side (4 atoms per fcc cell: 5 gives 500 atoms). With an
    /// orientation, cells of a0 |o_k| along axis k (LAMMPS's lattice spacings).
    pub cells_per_side: usize,
    /// Crystal directions along x, y, z (integer Miller indices, as LAMMPS `lattice ... orient`):
    /// mutually orthogonal and right-handed; default [100] [010] [001].
    #[serde(default = "default_orientation")]
    pub orientation: [[i32; 3]; 3],
    /// MD time step (fs).
    #[serde(default = "default_md_timestep")]
    pub timestep_fs: f64,
    /// `last` (stress after the last MD step of a continuum step) or `average` (the mean of the
    /// stresses after each MD step of the continuum step).
    #[serde(default, with = "names::named")]
    pub stress_sampling: md_worker::StressSampling,
    /// Add the continuum work missing from the box as kinetic energy (Ch. 7.2).
    #[serde(default = "default_true")]
    pub energy_consistency: bool,
    /// Give the artificial viscosity's work (q : D) to the boxes as heat: a shock's dissipation.
    /// Off by default (the shipped scenes' digests); on in `cu-notch-jet-2d-half`, where
    /// without it the boxes behind the ~170 GPa shock stay ~3000 K too cold and sigma_yy ~13 %
    /// too soft (coupling/README.md).
    #[serde(default)]
    pub viscous_heating: bool,
    /// `double` or `mixed`.
    #[serde(default = "default_precision", with = "names::named")]
    pub precision: MdPrecision,
    /// Seed of the initial velocities (combined with the point id).
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// MD steps at zero strain rate before the run (Ch. 6.2).
    #[serde(default = "default_relax_steps")]
    pub relax_steps: usize,
    /// Relax the box lengths to zero mean stress at temperature.
    #[serde(default)]
    pub relax_box: bool,
    /// How boxes follow the velocity gradient: `affine` (LAMMPS `fix deform ... remap x`,
    /// diagonal gradients only), `seed` (thesis Ch. 5.2, any gradient), or `auto` (affine in
    /// 1D, seed otherwise).
    #[serde(default = "default_deformation", with = "names::named")]
    pub deformation: Deformation,
    /// MD-call avoidance: `off` (the default: every box every step), `exact` (boxes with
    /// bitwise identical states and work are computed once; results bitwise those of `off`)
    /// or `{ tolerance = GPa, max_interval = continuum steps }` (a box is not stepped while its
    /// predicted stress change stays below the tolerance; see `coupling::reuse`).
    #[serde(default)]
    pub reuse: coupling::Reuse,
}

fn default_orientation() -> [[i32; 3]; 3] {
    md_worker::Orientation::CUBE.0
}

fn default_deformation() -> Deformation {
    Deformation::Auto
}

fn default_md_timestep() -> f64 {
    1.0
}
fn default_true() -> bool {
    true
}
fn default_precision() -> MdPrecision {
    MdPrecision::Double
}
fn default_seed() -> u64 {
    1
}
fn default_relax_steps() -> usize {
    1000
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Scheme {
    /// Gradient scheme: mpm, ugimp, cpgimp, cpdi (1D), cpdi1, cpdi2, ddmp, ddmp-subpoints.
    #[serde(with = "names::named")]
    pub method: continuum::SchemeKind,
    /// Particles per cell along each axis.
    pub particles_per_cell: usize,
    /// Sub-points per particle (ddmp-subpoints only).
    #[serde(default = "default_one")]
    pub sub_points: usize,
    /// none, linear (Ch. 6.3), tensor (7.8)-(7.10).
    #[serde(default = "default_viscosity", with = "names::named")]
    pub artificial_viscosity: ViscosityForm,
    /// Coefficient of the linear viscosity (0.5 in Ch. 6.3).
    #[serde(default = "default_viscosity_coefficient")]
    pub viscosity_coefficient: f64,
    /// c_L of the tensor viscosity (7.8) (1.5 in Ch. 7.2).
    #[serde(default = "default_tensor_c_l")]
    pub viscosity_c_l: f64,
    /// c_q of the tensor viscosity (7.8) (2.0 in Ch. 7.2).
    #[serde(default = "default_tensor_c_q")]
    pub viscosity_c_q: f64,
    /// c dt / h; give `cfl` or `timestep`.
    #[serde(default)]
    pub cfl: Option<f64>,
    /// Time step (s).
    #[serde(default)]
    pub timestep: Option<f64>,
    /// Simulated time at the end (s).
    pub end_time: f64,
    /// Small-mass node threshold as a fraction of the mean initial point mass.
    #[serde(default = "default_small_mass")]
    pub small_mass_fraction: f64,
    /// Time stepping: `dhakal` (the cycle of Ch. 3.1, eqs. 3.13-3.14; first order in time),
    /// `leapfrog` (staggered velocities, Gong eq. 4.24; second order: use it for convergence
    /// studies of smooth problems), `usl` (symplectic Euler, update stress last) or `usf`
    /// (update stress first).
    #[serde(default, with = "names::named")]
    pub integrator: continuum::solver::TimeIntegrator,
    /// PIC/FLIP blend of the particle velocity update, in [0, 1]: 1 (default) is FLIP, 0 PIC
    /// (battery thesis 5.24-5.26).
    #[serde(default = "default_flip_fraction")]
    pub flip_fraction: f64,
    /// Corrected derivatives in the nodal force (battery thesis 4.21-4.29; its RKPM-style
    /// extension in 2D/3D): `none` (default), `constant` (a constant stress gives no nodal
    /// force) or `linear` (a linear stress gives the exact nodal force); see continuum
    /// `solver/corrected.rs`. Written only when not none.
    #[serde(default, with = "names::named", skip_serializing_if = "is_no_correction")]
    pub gradient_correction: continuum::solver::GradientCorrection,
    /// Nullspace filter on the point velocity gradient (battery thesis 4.50-4.92): `none`
    /// (default), `local` (one more particle -> node -> particle cycle of the gradient, any
    /// dimension) or `global-svd` (projection onto the row space of the point-to-node map, 1D
    /// reference runs of at most 2000 points); see continuum `solver/nullspace.rs`. Written
    /// only when not none.
    #[serde(default, with = "names::named", skip_serializing_if = "is_no_filter")]
    pub nullspace_filter: continuum::solver::NullspaceFilter,
    /// Newton Jacobian of `implicit-trapezoidal`: `analytic` (the closures' material tangents)
    /// or `finite-difference` (coloured forward differences). Written only when not analytic.
    #[serde(default, with = "names::named", skip_serializing_if = "is_analytic")]
    pub jacobian: continuum::solver::implicit::JacobianKind,
    /// Adaptive steps of `implicit-trapezoidal` (absent: the fixed `cfl`/`timestep`, which
    /// is then the first step).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveSpec>,
    /// Every body's density is multiplied by this (mass scaling: the acoustic step grows by its
    /// square root); summary.json `quasi_static` reports whether the run stayed quasi-static.
    #[serde(default = "default_scaling", skip_serializing_if = "is_one")]
    pub density_scaling: f64,
    /// Under `tlmpm`: `total-lagrangian` (the default: the nodal velocity re-mapped from the
    /// points every step, 6.29-6.37) or `moving-mesh` (the nodal velocity carried, 6.25-6.28;
    /// FLIP only, bound c dt / h <= 1). Written only when not the default.
    #[serde(default, with = "names::named", skip_serializing_if = "is_total_lagrangian")]
    pub tlmpm_form: TlmpmForm,
}

/// `scheme.tlmpm_form`: which reference-configuration form `tlmpm` runs (continuum::tlmpm).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TlmpmForm {
    #[default]
    TotalLagrangian,
    MovingMesh,
}

fn is_total_lagrangian(f: &TlmpmForm) -> bool {
    *f == TlmpmForm::TotalLagrangian
}

/// `scheme.adaptive`: the local-error controlled step of the implicit integrator
/// (continuum/docs/implicit.md, "Adaptive step").
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AdaptiveSpec {
    /// Relative tolerance of the WRMS error norm of le_u and le_v.
    pub rtol: f64,
    /// Absolute tolerance of the nodal displacement (m).
    pub atol_displacement: f64,
    /// Absolute tolerance of the nodal velocity (m/s).
    pub atol_velocity: f64,
    /// Absolute tolerance of the deformation gradient (dimensionless): when given, the WRMS
    /// norm also takes le_F (every point's F components, weights 1/(rtol |F| + atol)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub atol_deformation: Option<f64>,
    /// dt_new = dt min(max_growth, max(min_shrink, safety err^-1/3)).
    #[serde(default = "default_safety")]
    pub safety: f64,
    #[serde(default = "default_max_growth")]
    pub max_growth: f64,
    #[serde(default = "default_min_shrink")]
    pub min_shrink: f64,
    /// Smallest and largest step (s); the run stops when a step would need less than dt_min.
    #[serde(default)]
    pub dt_min: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dt_max: Option<f64>,
    /// Rejected attempts of one step before the run stops.
    #[serde(default = "default_max_rejections")]
    pub max_rejections: usize,
    /// No point moves more than this many cells in one step (at most 0.5: the stencil is
    /// frozen over the step); the next step is capped at 0.9 of it.
    #[serde(default = "default_motion_cells")]
    pub max_motion_cells: f64,
}

fn default_safety() -> f64 {
    0.9
}
fn default_max_growth() -> f64 {
    2.0
}
fn default_min_shrink() -> f64 {
    0.2
}
fn default_max_rejections() -> usize {
    10
}
fn default_motion_cells() -> f64 {
    0.5
}
fn default_scaling() -> f64 {
    1.0
}
fn is_one(v: &f64) -> bool {
    *v == 1.0
}

fn default_flip_fraction() -> f64 {
    1.0
}

fn is_no_correction(c: &continuum::solver::GradientCorrection) -> bool {
    *c == continuum::solver::GradientCorrection::None
}

fn is_no_filter(f: &continuum::solver::NullspaceFilter) -> bool {
    *f == continuum::solver::NullspaceFilter::None
}

fn is_analytic(j: &continuum::solver::implicit::JacobianKind) -> bool {
    *j == continuum::solver::implicit::JacobianKind::Analytic
}

fn default_one() -> usize {
    1
}
fn default_viscosity() -> ViscosityForm {
    ViscosityForm::None
}
fn default_viscosity_coefficient() -> f64 {
    0.5
}
fn default_tensor_c_l() -> f64 {
    1.5
}
fn default_tensor_c_q() -> f64 {
    2.0
}
fn default_small_mass() -> f64 {
    0.04
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Boundary {
    #[serde(default)]
    pub x_min: FaceSpec,
    #[serde(default)]
    pub x_max: FaceSpec,
    #[serde(default)]
    pub y_min: FaceSpec,
    #[serde(default)]
    pub y_max: FaceSpec,
    #[serde(default)]
    pub z_min: FaceSpec,
    #[serde(default)]
    pub z_max: FaceSpec,
}

impl Boundary {
    pub fn faces(&self) -> [(&'static str, &FaceSpec); 6] {
        [
            ("x_min", &self.x_min),
            ("x_max", &self.x_max),
            ("y_min", &self.y_min),
            ("y_max", &self.y_max),
            ("z_min", &self.z_min),
            ("z_max", &self.z_max),
        ]
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// Number of snapshots over the run (besides the initial and final states).
    #[serde(default = "default_snapshots")]
    pub snapshots: usize,
    /// Particle CSV files.
    #[serde(default = "default_true")]
    pub particles: bool,
    /// VTK (.vtu + .pvd) files.
    #[serde(default = "default_true")]
    pub vtk: bool,
    /// PNG line profiles (1D).
    #[serde(default = "default_true")]
    pub plots: bool,
    /// Write a checkpoint every this many steps (0: none at an interval). A command line's
    /// `--checkpoint-every` (run, submit, serve) takes precedence.
    #[serde(default)]
    pub checkpoint_every_steps: u64,
    /// Material points (ids as in the particle files) whose MD boxes are written at every
    /// snapshot as LAMMPS text dump frames (`boxes/point-<id>.dump`, readable by OVITO). Points
    /// of md bodies only.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dump_points: Vec<u64>,
}

fn default_snapshots() -> usize {
    10
}

impl Default for Output {
    fn default() -> Self {
        Output {
            snapshots: default_snapshots(),
            particles: true,
            vtk: true,
            plots: true,
            checkpoint_every_steps: 0,
            dump_points: Vec::new(),
        }
    }
}

/// What a run's error is measured against (`[reference] solution = ...`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "solution", rename_all = "kebab-case")]
pub enum Reference {
    /// The exact solution of the isothermal Riemann problem of two ideal-gas bodies.
    IsothermalRiemann(RiemannReference),
    /// A direct-MD solution of the same problem, scored by the seed's eq. (7.12).
    DirectMd(DirectMdReference),
    /// Gong's manufactured solution (4.5)-(4.7) on the unit interval/square/cube: sets the body
    /// force and the initial velocity, and every run writes its L2 errors.
    Manufactured(ManufacturedReference),
    /// The derived in-plane stress path of a uniformly lithiated film on a rigid substrate
    /// (see [`continuum::exact::thin_film_stress`]).
    ThinFilmLithiation(ThinFilmReference),
    /// The Fourier series of 1D diffusion between two Dirichlet faces from a uniform initial
    /// value (B 6.95), scored by the RMS over the points (B 6.97 with its square).
    HeatSeries(HeatSeriesReference),
    /// The battery thesis's vibrating bar (B 4.7.1): u = A sin(2 pi X) sin(c pi t) with its
    /// body force, for one `linear-piola` body filling [0, 1] (see
    /// [`continuum::exact::VibratingBar`]); summary.json `errors` as for `manufactured`.
    VibratingBar(ManufacturedReference),
}

/// `solution = "heat-series"`: a 1D scene with `[diffusion]` values on both faces and every
/// body starting at `initial`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HeatSeriesReference {
    /// The uniform initial value.
    #[serde(default)]
    pub initial: f64,
}

/// `solution = "manufactured"`: U = G sin(pi X) sin(c pi t) per axis, c = sqrt(E / rho0), for the
/// scene's one neo-Hookean body filling the unit domain (see [`continuum::exact::Manufactured`]).
/// The reference sets the body force (`manufactured`) and the initial velocity
/// V = c pi G sin(pi X); summary.json `errors` gets the displacement, velocity and stress L2
/// errors at the end time.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ManufacturedReference {
    /// G (m): 1e-4 (small strain) or 0.1 (large deformation, strain pi G = 0.314).
    pub amplitude: f64,
}

/// `solution = "thin-film-lithiation"`: a 1D scene along the film normal (x; the in-plane
/// axes y and z are held by the 1D kinematics), the substrate at `x_min`, the top free.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ThinFilmReference {
    /// The film: a `hypoelastic-plastic` body with a uniform `lithiation`.
    pub body: String,
}

/// `solution = "isothermal-riemann"`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RiemannReference {
    /// Body on the left of the jump.
    pub left: String,
    /// Body on the right of the jump.
    pub right: String,
}

/// `solution = "direct-md"`: every run writes the eq. (7.12) error of `component` against the
/// profile at each of `times_ps` into summary.json `errors` (see [`crate::reference::score_run`]).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DirectMdReference {
    /// The binned CSV output of `md-worker direct --slab` (1D: `time_ps,slab_center_nm,
    /// sxx_gpa,...` in slabs of the reference coordinate), relative to the scene file.
    pub profile: PathBuf,
    /// Times (ps) to score at: each one a time of the profile and at most the end time. The
    /// run writes a snapshot at the step nearest to each.
    pub times_ps: Vec<f64>,
    /// Stress component scored: `sxx` (the shock direction of a 1D bar), `syy` or `szz`.
    #[serde(default = "default_component", with = "names::named")]
    pub component: Component,
}

fn default_component() -> Component {
    Component::Sxx
}

/// A scene read from a file, with where every value came from.
#[derive(Debug, Clone)]
pub struct LoadedScene {
    pub scene: Scene,
    pub path: PathBuf,
    /// The text after overrides (what was deserialised).
    pub text: String,
    /// Files the scene names, resolved relative to the scene file.
    pub files: Vec<PathBuf>,
    /// The time step that will be used (s).
    pub dt: f64,
    /// Number of steps to reach `end_time`.
    pub steps: u64,
    /// What setup consumes: typed values, measured lattices, point counts.
    pub resolved: ResolvedScene,
}

mod names;
mod parse;
mod resolve;
mod validate;

pub use names::{Component, Deformation, FaceName, FaceSpec, MdPrecision, SceneName, ViscosityForm};
pub(crate) use resolve::for_each_point;
pub use resolve::{Law, ResolvedBody, ResolvedDiffusion, ResolvedMd, ResolvedScene};

pub use parse::{apply_overrides, load, parse};
pub use validate::{CFL_LIMIT, MAX_ATOMS_PER_BOX};

impl crate::reference::ReferenceMap {
    /// The reference map of a 1D scene's bodies (see [`crate::reference::ReferenceMap`]).
    pub fn of(scene: &Scene) -> anyhow::Result<crate::reference::ReferenceMap> {
        if scene.domain.dimension != 1 {
            anyhow::bail!("--reference scores sigma_xx along a 1D bar; scene `{}` has dimension {}", scene.name, scene.domain.dimension);
        }
        let bodies = scene.bodies.values().map(|b| (b.min[0], b.max[0], 1.0 + b.initial_strain.first().copied().unwrap_or(0.0))).collect();
        crate::reference::ReferenceMap::from_bodies(&scene.name, bodies)
    }
}

impl Scene {
    /// Whether any body needs the MD engine.
    pub fn needs_md(&self) -> bool {
        self.bodies.values().any(|b| matches!(b.material, Material::Md(_)))
    }

    /// The resolved scene as TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# could not render the scene: {e}\n"))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use std::path::Path;

    const MD: &str = r#"schema = 1
[domain]
dimension = 2
min = [0.0, 0.0]
max = [1e-8, 1e-8]
cells = [2, 2]

[bodies.bar]
shape = "block"
min = [0.0, 0.0]
max = [1e-8, 1e-8]
density = 8939.0

[bodies.bar.material]
law = "md"
potential = "../md-worker/potentials/Cu_mishin1.eam.alloy"
lattice = "fcc"
lattice_constant_angstrom = 3.615
cells_per_side = 2

[scheme]
method = "mpm"
particles_per_cell = 1
cfl = 0.2
end_time = 1e-12
"#;

    fn err(text: &str, sets: &[&str]) -> String {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        parse("t.toml", text, &sets, &base, "t").map(|_| ()).unwrap_err().to_string()
    }

    #[test]
    fn an_unknown_name_inside_a_tagged_table_names_its_key_and_line() {
        let e = err(&MD.replace("lattice = \"fcc\"", "lattice = \"hcp\""), &[]);
        assert_eq!(e, "t.toml, line 17: `bodies.bar.material.lattice` = \"hcp\": allowed: \"fcc\", \"bcc\", \"sc\"");
        let e = err(MD, &["bodies.bar.material.deformation=sideways"]);
        assert!(
            e.starts_with("t.toml, --set bodies.bar.material.deformation=sideways: `bodies.bar.material.deformation` = \"sideways\""),
            "{e}"
        );
        let e = err(MD, &["bodies.bar.material.precision=\"mixed\""]);
        assert!(e.contains("`bodies.bar.material.precision` = \"mixed\": allowed: \"double\""), "{e}");
        // Affine is a known name, refused in 2D by validation with the same message.
        let e = err(MD, &["bodies.bar.material.deformation=affine"]);
        assert!(e.contains("`bodies.bar.material.deformation` = \"affine\": allowed: \"seed\" (any dimension)"), "{e}");
        let e = err(MD, &["scheme.integrator=euler"]);
        assert!(e.contains("--set scheme.integrator=euler: `scheme.integrator` = \"euler\": allowed: \"dhakal\""), "{e}");
        let e = err(MD, &["boundary.y_max={ piston = [1.0, 0.0], speed = 2 }"]);
        assert!(e.contains("unknown field `speed`"), "{e}");
    }

    #[test]
    fn the_manufactured_reference_sets_its_solution_and_refuses_what_it_cannot_hold() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let text = std::fs::read_to_string(base.join("mms-2d.toml")).unwrap();
        let sets: Vec<String> = vec!["domain.cells=[8,8]".into(), "reference.amplitude=1e-4".into()];
        let l = parse("mms-2d.toml", &text, &sets, &base, "mms-2d").unwrap();
        let m = l.resolved.manufactured.expect("manufactured");
        assert_eq!((m.amplitude, m.youngs_modulus, m.density0), (1e-4, 1e7, 1e3));
        // Gong's dt = 0.4 h / c with c = sqrt(E / rho0) = 100 m/s.
        assert!((l.dt - 0.4 / 8.0 / 100.0).abs() < 1e-12 * l.dt, "{}", l.dt);
        assert_eq!(l.steps, 40);
        let err = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse("mms-2d.toml", &text, &sets, &base, "mms-2d").map(|_| ()).unwrap_err().to_string()
        };
        assert!(err(&["reference.amplitude=0.5"]).contains("`reference.amplitude` = 0.5: the amplitude G (m) must be"));
        assert!(err(&["boundary.y_max=\"fixed\""]).contains("`boundary.y_max`"));
        assert!(err(&["bodies.bar.velocity=[1.0, 0.0]"]).contains("sets the initial velocity"));
        assert!(err(&["domain.max=[2.0, 1.0]", "bodies.bar.max=[2.0, 1.0]"]).contains("unit domain"));
        assert!(
            err(&["bodies.bar.material={ law = \"linear-elastic\", youngs_modulus = 1e7, poisson_ratio = 0.3 }"]).contains("neo-hookean")
        );
        assert!(err(&["scheme.cfl=0.95"]).contains("manufactured particle speed"), "{}", err(&["scheme.cfl=0.95"]));
        assert!(err(&["scheme.method=cpdi"]).contains("`scheme.method` = \"cpdi\": `cpdi` is the 1D CPDI"));
        let impm_2d: Vec<String> = vec!["scheme.method=impm".into()];
        assert_eq!(parse("mms-2d.toml", &text, &impm_2d, &base, "mms-2d").map(|l| l.resolved.scheme), Ok(continuum::SchemeKind::Impm));
        let text_1d = std::fs::read_to_string(base.join("mms-1d.toml")).unwrap();
        let one = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse("mms-1d.toml", &text_1d, &sets, &base, "mms-1d").map(|l| l.resolved.scheme)
        };
        assert_eq!(one(&["scheme.method=impm"]), Ok(continuum::SchemeKind::Impm));
        let e = one(&["scheme.method=impm", "scheme.integrator=usl"]).unwrap_err().to_string();
        assert!(e.contains("`scheme.integrator` = \"usl\": impm is Gong's staggered scheme"), "{e}");
        assert!(err(&["scheme.flip_fraction=1.5"]).contains("`scheme.flip_fraction` = 1.5: the PIC/FLIP blend must lie in [0, 1]"));
        for (name, want) in [("usl", continuum::solver::TimeIntegrator::Usl), ("usf", continuum::solver::TimeIntegrator::Usf)] {
            let sets = vec![format!("scheme.integrator={name}"), "scheme.flip_fraction=0.25".to_string()];
            let l = parse("mms-2d.toml", &text, &sets, &base, "mms-2d").unwrap();
            assert_eq!((l.resolved.integrator, l.resolved.flip_fraction), (want, 0.25));
        }
    }

    #[test]
    fn the_vibrating_bar_resolves_and_the_derived_cfl_bounds_are_enforced() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let text = std::fs::read_to_string(base.join("vibrating-bar-1d.toml")).unwrap();
        let parse_with = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse("vibrating-bar-1d.toml", &text, &sets, &base, "vibrating-bar-1d")
        };
        let l = parse_with(&[]).unwrap();
        let m = l.resolved.vibrating_bar.expect("vibrating bar");
        assert_eq!((m.amplitude, m.modulus, m.density0), (3e-3, 1e3, 1.0));
        assert_eq!((l.dt, l.steps), (1e-5, 20_000));
        assert!(l.resolved.manufactured.is_none());
        let err = |sets: &[&str]| parse_with(sets).map(|_| ()).unwrap_err().to_string();
        assert!(err(&["reference.amplitude=0.2"]).contains("`reference.amplitude` = 0.2: the amplitude A (m) must be"));
        assert!(err(&["boundary.x_max=\"roller\""]).contains("`boundary.x_max`"));
        assert!(
            err(&["bodies.bar.material={ law = \"neo-hookean\", youngs_modulus = 1e3, poisson_ratio = 0.0 }"]).contains("linear-piola")
        );
        assert!(parse_with(&["boundary.x_min=\"periodic\"", "boundary.x_max=\"periodic\""]).is_ok());
        // The derived bounds (continuum::stability): usl and leapfrog MPM at 1 point per cell
        // stop at 0.7071, usf and stormer-verlet do not (their bounds pass CFL_LIMIT = 1).
        let e = err(&["scheme.particles_per_cell=1", "scheme.timestep=2.3e-4"]);
        assert!(
            e.contains(
                "`scheme.timestep` = 0.00023: exceeds the linear stability bound c dt / h <= 0.7071 of `mpm` with integrator \"usl\""
            ),
            "{e}"
        );
        let e = err(&["scheme.particles_per_cell=1", "scheme.integrator=leapfrog", "scheme.timestep=2.3e-4"]);
        assert!(e.contains("bound c dt / h <= 0.7071 of `mpm` with integrator \"leapfrog\""), "{e}");
        for ok in ["usf", "stormer-verlet"] {
            let i = format!("scheme.integrator={ok}");
            assert!(parse_with(&["scheme.particles_per_cell=1", &i, "scheme.timestep=2.3e-4"]).is_ok(), "{ok}");
        }
        assert!(parse_with(&["scheme.particles_per_cell=1", "scheme.timestep=2.2e-4"]).is_ok());
        // Found by the scene fuzzer: E = 5e-324 halves to a zero shear modulus, so no wave
        // speed; the resolved scene's cfl was 0 and could not be read again. Refused up front.
        let e = err(&["bodies.bar.material.youngs_modulus=5e-324"]);
        assert!(e.contains("the largest wave speed plus body speed is 0e0 m/s, which sets no time step"), "{e}");
        // A tiny but representable speed whose CFL number underflows: refused by the time step.
        let e = err(&["bodies.bar.material.youngs_modulus=1e-300", "domain.max=[1e300]", "bodies.bar.max=[1e300]"]);
        assert!(e.contains("underflows to 0"), "{e}");
        let e = err(&["scheme.integrator=stormer-verlet", "scheme.flip_fraction=0.5"]);
        assert!(e.contains("`scheme.flip_fraction` = 0.5: the Stormer-Verlet step updates the point velocities by FLIP only"), "{e}");
    }

    /// tlmpm: its own derived bound (sqrt 3 at 2 points per cell, FLIP; 2 at 1), leapfrog only,
    /// and what it cannot run with refused naming the key.
    #[test]
    fn tlmpm_resolves_with_its_own_bound_and_refuses_what_it_cannot_run() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let parse_in = |file: &str, sets: &[&str]| {
            let text = std::fs::read_to_string(base.join(file)).unwrap();
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse(file, &text, &sets, &base, file.trim_end_matches(".toml")).map(|l| l.resolved.scheme)
        };
        let err = |file: &str, sets: &[&str]| parse_in(file, sets).unwrap_err().to_string();
        assert_eq!(parse_in("mms-1d-tlmpm.toml", &[]).unwrap(), continuum::SchemeKind::Tlmpm);
        // The vibrating bar (E = 1e3, rho = 1, h = 1/40: c = 31.6 m/s, A c pi = 0.30 m/s).
        let bar = ["scheme.method=\"tlmpm\"", "scheme.integrator=leapfrog"];
        let with = |extra: &[&'static str]| -> Vec<&'static str> { bar.iter().chain(extra).copied().collect() };
        assert!(parse_in("vibrating-bar-1d.toml", &with(&["scheme.timestep=5.3e-4"])).is_ok(), "1.70 of h / (c + |v|) is below sqrt 3");
        let e = err("vibrating-bar-1d.toml", &with(&["scheme.timestep=5.6e-4"]));
        assert!(e.contains("`scheme.timestep`") && e.contains("1.732 h / (c + |v|)"), "{e}");
        let e = err("mms-1d-tlmpm.toml", &["scheme.cfl=1.8"]);
        assert!(e.contains("`scheme.cfl` = 1.8: allowed: 0 < cfl <= 1.7320, the linear stability bound of tlmpm"), "{e}");
        assert!(parse_in("mms-1d-tlmpm.toml", &["scheme.cfl=1.1", "reference.amplitude=1e-4"]).is_ok());
        // 1 point per cell: the bound is 2.
        assert!(parse_in("mms-1d-tlmpm.toml", &["scheme.cfl=1.9", "reference.amplitude=1e-4", "scheme.particles_per_cell=1"]).is_ok());
        let e = err("mms-1d-tlmpm.toml", &["scheme.integrator=dhakal"]);
        assert!(e.contains("`scheme.integrator` = \"dhakal\": tlmpm keeps its velocities at half steps"), "{e}");
        for (key, set) in [
            ("scheme.nullspace_filter", "scheme.nullspace_filter=\"local\""),
            ("scheme.gradient_correction", "scheme.gradient_correction=\"linear\""),
        ] {
            let e = err("mms-1d-tlmpm.toml", &[set]);
            assert!(e.contains(&format!("`{key}`")) && e.contains("tlmpm"), "{e}");
        }
        // Diffusion runs under tlmpm in the reference form; a pre-strained body does not.
        assert!(parse_in("heat-1d.toml", &bar).is_ok());
        let e = err("heat-1d.toml", &with(&["bodies.bar.initial_strain=[0.1, 0.0, 0.0]"]));
        assert!(e.contains("`bodies.bar.initial_strain`") && e.contains("not supported under tlmpm"), "{e}");
        // The moving mesh: its own bound (1), FLIP only, tlmpm only.
        let mm = "scheme.tlmpm_form=\"moving-mesh\"";
        assert!(parse_in("mms-1d-tlmpm.toml", &[mm, "scheme.cfl=0.99", "reference.amplitude=1e-4"]).is_ok());
        let e = err("mms-1d-tlmpm.toml", &[mm, "scheme.cfl=1.1"]);
        assert!(e.contains("`scheme.cfl` = 1.1: allowed: 0 < cfl <= 1.0000, the linear stability bound of tlmpm's moving mesh"), "{e}");
        let e = err("mms-1d-tlmpm.toml", &[mm, "scheme.flip_fraction=0.5"]);
        assert!(e.contains("`scheme.flip_fraction` = 0.5: the moving mesh carries the nodal velocity"), "{e}");
        let e = err("mms-1d-tlmpm.toml", &[mm, "scheme.method=\"cpdi\"", "scheme.integrator=leapfrog"]);
        assert!(e.contains("`scheme.tlmpm_form` = \"moving-mesh\": the moving-mesh form is a form of tlmpm"), "{e}");
    }

    #[test]
    fn the_shipped_battery_scenes_resolve_and_the_diffusion_bound_is_named() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let read = |f: &str| std::fs::read_to_string(base.join(f)).unwrap();
        let heat = read("heat-1d.toml");
        let l = parse("heat-1d.toml", &heat, &[], &base, "heat-1d").unwrap();
        let d = l.resolved.diffusion.as_ref().unwrap();
        assert!((d.bound - 1.25e-3).abs() < 1e-15, "h^2 / (2 K) = 1.25e-3 s, got {}", d.bound);
        let sets = vec!["scheme.timestep=2e-3".to_string()];
        let e = parse("heat-1d.toml", &heat, &sets, &base, "heat-1d").map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("corrected explicit diffusion bound dt <= J_min h0^2 / (2 d K) = 1.250000e-3 s"), "{e}");
        // A pre-strained bar at J = 1.6 tightens it by 1.6 (h0 = h / J); one at J = 0.8 relaxes it.
        let sets = vec!["bodies.bar.initial_strain=[0.6, 0.0, 0.0]".to_string(), "scheme.timestep=1e-3".to_string()];
        let e = parse("heat-1d.toml", &heat, &sets, &base, "heat-1d").map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("= 7.812500e-4 s") && e.contains("J_max = 1.6"), "{e}");
        let sets = vec!["bodies.bar.initial_strain=[-0.2, 0.0, 0.0]".to_string(), "scheme.timestep=1.5e-3".to_string()];
        let l = parse("heat-1d.toml", &heat, &sets, &base, "heat-1d").unwrap();
        assert!((l.resolved.diffusion.as_ref().unwrap().bound - 1.5625e-3).abs() < 1e-15);
        // The 2D heat plate (Table 6.2): the 2D bound h^2 / (4 K); the series needs one value on
        // all four faces.
        let plate = read("heat-2d.toml");
        let l = parse("heat-2d.toml", &plate, &[], &base, "heat-2d").unwrap();
        assert!((l.resolved.diffusion.as_ref().unwrap().bound - 6.25e-4).abs() < 1e-15);
        let sets = vec!["diffusion.y_max={ value = 0.5 }".to_string()];
        let e = parse("heat-2d.toml", &plate, &sets, &base, "heat-2d").map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("reference.solution") && e.contains("the same value on all four faces"), "{e}");
        let film = read("si-thin-film.toml");
        let l = parse("si-thin-film.toml", &film, &[], &base, "si-thin-film").unwrap();
        let Law::HypoelasticPlastic(law) = &l.resolved.bodies[0].law else { panic!("the film's law") };
        assert_eq!(*law, continuum::silicon::ChemoPlastic::SILICON);
        assert_eq!(l.resolved.bodies[0].lithiation, Some((0.0, 1.0e7)));
        assert_eq!(l.resolved.bodies[0].lithiation_ramp, 0.0, "no ramp by default");
        // A ramp: the concentration reached is rate x (end - ramp / 2), so a rate that would
        // overshoot c = 1 without it can fit with it.
        let sets = vec!["bodies.film.lithiation.uniform_rate=6e7".to_string()];
        let e = parse("si-thin-film.toml", &film, &sets, &base, "si-thin-film").map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("lithiation.uniform_rate") && e.contains("reaches c = 1.2"), "{e}");
        let sets = vec!["bodies.film.lithiation.uniform_rate=6e7".to_string(), "bodies.film.lithiation.ramp_time=1.6e-8".to_string()];
        let l = parse("si-thin-film.toml", &film, &sets, &base, "si-thin-film").unwrap();
        assert_eq!(l.resolved.bodies[0].lithiation_ramp, 1.6e-8);
        let sets = vec!["bodies.film.lithiation.ramp_time=-1".to_string()];
        let e = parse("si-thin-film.toml", &film, &sets, &base, "si-thin-film").map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("bodies.film.lithiation.ramp_time") && e.contains("finite and >= 0"), "{e}");
    }

    #[test]
    fn a_resolved_scene_has_typed_values_measured_lattices_and_point_counts() {
        let sets: Vec<String> = vec!["scheme.particles_per_cell=2".into()];
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let l = parse("t.toml", MD, &sets, &base, "t").unwrap();
        let r = &l.resolved;
        assert_eq!((r.scheme, r.integrator, r.dt, r.steps), (continuum::SchemeKind::Mpm, Default::default(), l.dt, l.steps));
        let Material::Md(m) = &l.scene.bodies["bar"].material else { panic!("md") };
        assert_eq!(m.deformation, Deformation::Seed, "auto is seed in 2D, in the scene as it ran");
        let Law::Md(m) = &r.bodies[0].law else { panic!("md") };
        assert_eq!((m.deformation, m.atoms_per_box), (md_worker::DeformMode::Seed, 32));
        assert!((m.lattice_properties.density - 8939.0).abs() < 0.01 * 8939.0);
        // 2 x 2 cells, 2 x 2 points each.
        assert_eq!(r.point_counts(), [("bar".to_string(), 16)]);
    }

    const BAR: &str = r#"schema = 1
[domain]
dimension = 1
min = [0.0]
max = [1.0]
cells = [50]

[bodies.bar]
shape = "bar"
min = [0.0]
max = [1.0]
density = 1.0
velocity = [0.01]
material = { law = "linear-elastic", youngs_modulus = 1e4, poisson_ratio = 0.0 }

[scheme]
method = "mpm"
particles_per_cell = 2
cfl = 0.5
end_time = 0.1

[boundary]
x_min = "fixed"
x_max = "fixed"
"#;

    /// Issue 18: no CFL bound for the implicit integrator, a bound on motion per step instead,
    /// and the set-ups it cannot run refused at `scheme.integrator`.
    #[test]
    fn the_implicit_integrator_has_a_motion_bound_not_a_cfl_bound() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let ok = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse("t.toml", BAR, &sets, &base, "t").map_err(|e| e.to_string())
        };
        let e = err(BAR, &["scheme.cfl=50"]);
        assert!(e.contains("`scheme.cfl` = 50: allowed: 0 < cfl <= 1 (explicit stability bound)"), "{e}");
        let l = ok(&["scheme.cfl=50", "scheme.integrator=\"implicit-trapezoidal\""]).expect("cfl 50 is fine implicitly");
        assert_eq!(l.resolved.integrator, continuum::solver::TimeIntegrator::ImplicitTrapezoidal);
        assert!((l.dt - 50.0 * 0.02 / 100.01).abs() < 1e-9 * l.dt, "{}", l.dt);
        let l = ok(&["scheme.cfl=5", "scheme.integrator=\"implicit-trapezoidal\"", "scheme.jacobian=\"finite-difference\""]).expect("fd");
        assert_eq!(l.resolved.jacobian, continuum::solver::implicit::JacobianKind::FiniteDifference);
        // 1 m/s at dt = 0.5 s moves points 25 cells.
        let e = err(BAR, &["scheme.integrator=\"implicit-trapezoidal\"", "bodies.bar.velocity=[1.0]", "scheme.cfl=5000"]);
        assert!(
            e.contains("`scheme.timestep`") && e.contains("cells per step at the initial body speed 1e0 m/s") && e.contains("at most 0.5"),
            "{e}"
        );
        let e = err(BAR, &["scheme.integrator=\"implicit-trapezoidal\"", "scheme.method=\"ddmp\""]);
        assert!(e.contains("`scheme.integrator` = \"implicit-trapezoidal\": needs a method whose force stays on nodes with mass"), "{e}");
        let e = err(BAR, &["scheme.integrator=\"implicit-trapezoidal\"", "scheme.artificial_viscosity=\"linear\""]);
        assert!(e.contains("needs scheme.artificial_viscosity = \"none\""), "{e}");
        let e = err(MD, &["scheme.integrator=\"implicit-trapezoidal\""]);
        assert!(e.contains("body `bar` is an md body"), "{e}");
        let e = err(BAR, &["scheme.jacobian=\"exact\""]);
        assert!(e.contains("`scheme.jacobian` = \"exact\": allowed: \"analytic\", \"finite-difference\""), "{e}");
    }

    /// `scheme.adaptive` (issue 18) and `scheme.density_scaling` (issue 19): resolved into the
    /// integrator's options and the bodies' densities, every bad value named.
    #[test]
    fn adaptive_steps_and_density_scaling_are_scene_keys() {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let ok = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            parse("t.toml", BAR, &sets, &base, "t").map_err(|e| e.to_string())
        };
        let imp = "scheme.integrator=\"implicit-trapezoidal\"";
        let ad = "scheme.adaptive={ rtol = 1e-3, atol_displacement = 1e-9, atol_velocity = 1e-6, safety = 0.8, max_motion_cells = 0.25 }";
        let l = ok(&[imp, ad]).expect("adaptive");
        let a = l.resolved.adaptive.clone().expect("resolved");
        assert_eq!((a.rtol, a.safety, a.max_growth, a.end_time), (1e-3, 0.8, 2.0, l.scene.scheme.end_time));
        assert_eq!(l.resolved.max_motion_cells, 0.25);
        let e = err(BAR, &[ad]);
        assert!(e.contains("`scheme.adaptive`") && e.contains("adaptive steps need scheme.integrator = \"implicit-trapezoidal\""), "{e}");
        let e = err(BAR, &[imp, "scheme.adaptive={ rtol = -1, atol_displacement = 1e-9, atol_velocity = 1e-6 }"]);
        assert!(e.contains("`scheme.adaptive.rtol` = -1"), "{e}");
        let e = err(BAR, &[imp, "scheme.adaptive={ rtol = 1e-3, atol_displacement = 1e-9, atol_velocity = 1e-6, max_motion_cells = 0.8 }"]);
        assert!(e.contains("`scheme.adaptive.max_motion_cells` = 0.8: the motion bound must lie in (0, 0.5]"), "{e}");
        let e = err(BAR, &[imp, "scheme.adaptive={ rtol = 1e-3 }"]);
        assert!(e.contains("atol_displacement"), "{e}");
        let l = ok(&["scheme.density_scaling=100"]).expect("scaled");
        assert_eq!(l.resolved.bodies[0].density, 100.0 * l.scene.bodies["bar"].density);
        assert_eq!(l.resolved.density_scaling, 100.0);
        // The acoustic step grows by sqrt(100) (c = 100 -> 10 m/s, plus the body's 0.01 m/s).
        let plain = ok(&[]).expect("plain");
        assert!((l.dt / plain.dt - 100.01 / 10.01).abs() < 1e-9, "{} vs {}", l.dt, plain.dt);
        let e = err(BAR, &["scheme.density_scaling=0.5"]);
        assert!(e.contains("`scheme.density_scaling` = 0.5: the density scaling factor must be finite and at least 1"), "{e}");
        let e = err(MD, &["scheme.density_scaling=10"]);
        assert!(e.contains("body `bar`: density scaling is for solids"), "{e}");
    }
}
