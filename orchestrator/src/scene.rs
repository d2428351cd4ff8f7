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
use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::path::{Path, PathBuf};

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
    /// A periodic MD box per material point.
    Md(MdMaterial),
}

impl Material {
    pub fn law(&self) -> &'static str {
        match self {
            Material::IdealGasIsothermal(_) => "ideal-gas-isothermal",
            Material::LinearElastic(_) => "linear-elastic",
            Material::NeoHookean(_) => "neo-hookean",
            Material::Md(_) => "md",
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

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MdMaterial {
    /// Potential file (LAMMPS eam, eam/alloy, eam/fs), relative to the scene file.
    pub potential: PathBuf,
    /// fcc, bcc or sc.
    pub lattice: String,
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
    #[serde(default = "default_sampling")]
    pub stress_sampling: String,
    /// Add the continuum work missing from the box as kinetic energy (Ch. 7.2).
    #[serde(default = "default_true")]
    pub energy_consistency: bool,
    /// `double` or `mixed`.
    #[serde(default = "default_precision")]
    pub precision: String,
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
    #[serde(default = "default_deformation")]
    pub deformation: String,
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

fn default_deformation() -> String {
    "auto".into()
}

fn default_md_timestep() -> f64 {
    1.0
}
fn default_sampling() -> String {
    "last".into()
}
fn default_true() -> bool {
    true
}
fn default_precision() -> String {
    "double".into()
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
    pub method: String,
    /// Particles per cell along each axis.
    pub particles_per_cell: usize,
    /// Sub-points per particle (ddmp-subpoints only).
    #[serde(default = "default_one")]
    pub sub_points: usize,
    /// none, linear (Ch. 6.3), tensor (7.8)-(7.10).
    #[serde(default = "default_viscosity")]
    pub artificial_viscosity: String,
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
    /// Time stepping: `dhakal` (the cycle of Ch. 3.1, eqs. 3.13-3.14; first order in time) or
    /// `leapfrog` (staggered velocities, Gong eq. 4.24; second order: use it for convergence
    /// studies of smooth problems).
    #[serde(default = "default_integrator")]
    pub integrator: String,
}

fn default_integrator() -> String {
    "dhakal".into()
}

fn default_one() -> usize {
    1
}
fn default_viscosity() -> String {
    "none".into()
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

/// One face's condition: a name, or `{ piston = [vx, ...] }`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum FaceSpec {
    Named(String),
    Piston { piston: Vec<f64> },
}

impl Default for FaceSpec {
    fn default() -> Self {
        FaceSpec::Named("free".into())
    }
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
/// profile at each of `times_ps` into summary.json `errors` (see [`crate::report::score_run`]).
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
    #[serde(default = "default_component")]
    pub component: String,
}

fn default_component() -> String {
    "sxx".into()
}

/// Stress components a direct-MD reference can score (columns `<c>` of the particle files and
/// `<c>_gpa` of the profile).
pub const REFERENCE_COMPONENTS: [&str; 3] = ["sxx", "syy", "szz"];

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
}

struct Locator<'a> {
    file: String,
    text: &'a str,
    overrides: &'a BTreeMap<String, String>,
}

impl Locator<'_> {
    fn location(&self, key: &str) -> String {
        if let Some(v) = self.overrides.get(key) {
            return format!("--set {key}={v}");
        }
        // An element of an overridden array (`output.dump_points[1]`): the --set of the array.
        if let Some((array, _)) = key.split_once('[')
            && let Some(v) = self.overrides.get(array)
        {
            return format!("--set {array}={v}");
        }
        line_of(self.text, key).map(|l| format!("line {l}")).unwrap_or_default()
    }

    fn err(&self, key: &str, value: impl fmt::Display, problem: impl Into<String>) -> SceneError {
        SceneError {
            file: self.file.clone(),
            location: self.location(key),
            key: key.into(),
            value: value.to_string(),
            problem: problem.into(),
        }
    }
}

/// Line (1-based) of a dotted key in TOML text, if it is written there.
fn line_of(text: &str, key: &str) -> Option<usize> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut item = doc.as_item();
    let mut span = None;
    for part in key.split('.') {
        let (name, index) = match part.split_once('[') {
            Some((n, rest)) => (n, rest.trim_end_matches(']').parse::<usize>().ok()),
            None => (part, None),
        };
        let table = item.as_table_like()?;
        let (k, next) = table.get_key_value(name)?;
        span = k.span().or(span);
        item = next;
        if let Some(i) = index
            && let Some(v) = item.as_array().and_then(|a| a.get(i))
        {
            span = v.span().or(span);
        }
        if let Some(s) = item.span() {
            span = Some(span.map_or(s.clone(), |old: std::ops::Range<usize>| old.start.min(s.start)..s.end));
        }
    }
    let start = span?.start;
    Some(text[..start.min(text.len())].matches('\n').count() + 1)
}

/// Applies `key=value` overrides to TOML text. Values are read as TOML (`300`, `"fcc"`,
/// `[1.0, 2.0]`, `true`), and as a plain string when they are not valid TOML.
pub fn apply_overrides(file: &str, text: &str, sets: &[String]) -> Result<(String, BTreeMap<String, String>), SceneError> {
    let mut doc: toml_edit::DocumentMut = text.parse().map_err(|e: toml_edit::TomlError| SceneError {
        file: file.into(),
        location: String::new(),
        key: String::new(),
        value: String::new(),
        problem: format!("not valid TOML: {e}"),
    })?;
    let mut applied = BTreeMap::new();
    for set in sets {
        let bad = |problem: &str| SceneError {
            file: file.into(),
            location: format!("--set {set}"),
            key: String::new(),
            value: String::new(),
            problem: problem.into(),
        };
        let (key, raw) = set.split_once('=').ok_or_else(|| bad("expected --set dotted.key=value"))?;
        let key = key.trim();
        if key.is_empty() || key.split('.').any(str::is_empty) {
            return Err(bad("the key is empty or has an empty part; expected for example bodies.left.temperature_k=300"));
        }
        let value: toml_edit::Value = raw.trim().parse().unwrap_or_else(|_| toml_edit::Value::from(raw.trim()));
        let parts: Vec<&str> = key.split('.').collect();
        let mut table = doc.as_table_mut() as &mut dyn toml_edit::TableLike;
        for part in &parts[..parts.len() - 1] {
            if table.get(part).is_none() {
                table.insert(part, toml_edit::Item::Table(toml_edit::Table::new()));
            }
            table = table
                .get_mut(part)
                .and_then(|i| i.as_table_like_mut())
                .ok_or_else(|| bad(&format!("`{part}` is a value, not a table, so `{key}` cannot be set")))?;
        }
        table.insert(parts[parts.len() - 1], toml_edit::Item::Value(value));
        applied.insert(key.to_string(), raw.trim().to_string());
    }
    Ok((doc.to_string(), applied))
}

/// Reads, overrides, parses and validates a scene file.
pub fn load(path: &Path, sets: &[String]) -> Result<LoadedScene, SceneError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| SceneError {
        file: file.clone(),
        location: String::new(),
        key: String::new(),
        value: String::new(),
        problem: format!("cannot read the scene file: {e}"),
    })?;
    let default_name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into());
    parse(&file, &text, sets, path.parent().unwrap_or(Path::new(".")), &default_name)
}

/// Parses and validates scene text; `base` resolves the files it names.
pub fn parse(file: &str, text: &str, sets: &[String], base: &Path, default_name: &str) -> Result<LoadedScene, SceneError> {
    let (text, overrides) = apply_overrides(file, text, sets)?;
    let mut scene: Scene = toml::from_str(&text).map_err(|e| {
        let location = e.span().map(|s| format!("line {}", text[..s.start.min(text.len())].matches('\n').count() + 1)).unwrap_or_default();
        let key = e.span().map(|s| text[s.clone()].trim().to_string()).unwrap_or_default();
        let key = if key.len() > 60 || key.contains('\n') { String::new() } else { key };
        SceneError { file: file.into(), location, key, value: String::new(), problem: e.message().to_string() }
    })?;
    if scene.name.is_empty() {
        scene.name = default_name.to_string();
    }
    let loc = Locator { file: file.into(), text: &text, overrides: &overrides };
    let (dt, steps, files) = scene.validate(&loc, base)?;
    Ok(LoadedScene { scene, path: PathBuf::from(file), text, files, dt, steps })
}

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
    /// Checks physics and numerics; fills defaults. Returns the time step, the step count and
    /// the files the scene names (resolved against `base`).
    fn validate(&mut self, loc: &Locator<'_>, base: &Path) -> Result<(f64, u64, Vec<PathBuf>), SceneError> {
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
        let mut files = Vec::new();
        let mut max_speed: f64 = 0.0;
        let names: Vec<String> = self.bodies.keys().cloned().collect();
        for name in names {
            let (speed, file) = self.validate_body(loc, &name, base)?;
            max_speed = max_speed.max(speed);
            files.extend(file);
        }
        self.validate_boundary(loc)?;
        let user_timestep = self.scheme.timestep.is_some() && self.scheme.cfl.is_none();
        let (mut dt, mut steps) = self.validate_scheme(loc, max_speed)?;
        if let Some(md_step) = self.md_step(loc)? {
            (dt, steps) = self.fit_to_md_step(loc, dt, md_step, user_timestep, max_speed)?;
        }
        files.extend(self.validate_reference(loc, base)?);
        self.validate_dump_points(loc)?;
        Ok((dt, steps, files))
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

    /// Returns the body's wave speed estimate (m/s) and the file it names, if any.
    fn validate_body(&mut self, loc: &Locator<'_>, name: &str, base: &Path) -> Result<(f64, Option<PathBuf>), SceneError> {
        let dim = self.domain.dimension;
        let (dmin, dmax) = (self.domain.min.clone(), self.domain.max.clone());
        let Some(b) = self.bodies.get_mut(name) else { return Ok((0.0, None)) };
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
        let rho = b.density;
        match &mut b.material {
            Material::IdealGasIsothermal(g) => {
                finite_positive(loc, &k("material.sound_speed"), g.sound_speed, "the sound speed (m/s)")?;
                Ok((g.sound_speed, None))
            }
            Material::LinearElastic(e) | Material::NeoHookean(e) => {
                finite_positive(loc, &k("material.youngs_modulus"), e.youngs_modulus, "Young's modulus (Pa)")?;
                if !(e.poisson_ratio > -1.0 && e.poisson_ratio < 0.5) {
                    return Err(loc.err(&k("material.poisson_ratio"), e.poisson_ratio, "Poisson's ratio must lie in (-1, 0.5)"));
                }
                let (lambda, mu) = continuum::closure::lame(e.youngs_modulus, e.poisson_ratio);
                Ok((((lambda + 2.0 * mu) / rho).sqrt(), None))
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
                if !["fcc", "bcc", "sc"].contains(&md.lattice.as_str()) {
                    return Err(loc.err(&k("material.lattice"), format!("{:?}", md.lattice), "allowed: \"fcc\", \"bcc\", \"sc\""));
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
                let atoms = crate::md::atoms_per_box(md)
                    .map_err(|e| loc.err(&k("material.lattice"), format!("{:?}", md.lattice), e.to_string()))?;
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
                if !["last", "average"].contains(&md.stress_sampling.as_str()) {
                    return Err(loc.err(&k("material.stress_sampling"), format!("{:?}", md.stress_sampling), "allowed: \"last\" (the stress after the last MD step of a continuum step, the seed's choice), \"average\" (the mean over the continuum step's MD steps)"));
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
                if md.precision != "double" {
                    return Err(loc.err(
                        &k("material.precision"),
                        format!("{:?}", md.precision),
                        "allowed: \"double\" (the CPU back ends compute in double; \"mixed\" belongs to the CUDA back end)",
                    ));
                }
                if md.deformation == "auto" {
                    md.deformation = if dim == 1 { "affine".into() } else { "seed".into() };
                }
                if !["affine", "seed"].contains(&md.deformation.as_str()) || (md.deformation == "affine" && dim > 1) {
                    return Err(loc.err(
                        &k("material.deformation"),
                        format!("{:?}", md.deformation),
                        "allowed: \"seed\" (any dimension), \"affine\" (1D only: it takes diagonal gradients), \"auto\"",
                    ));
                }
                if md.relax_steps > 1_000_000 {
                    return Err(loc.err(&k("material.relax_steps"), md.relax_steps, "at most 1e6 relaxation steps"));
                }
                // From here on the path is absolute, so the resolved scene reads back anywhere.
                let file = file.canonicalize().unwrap_or(file);
                md.potential = file.clone();
                let props =
                    crate::md::lattice_properties(&file, &md.lattice, md.lattice_constant_angstrom, md_worker::Orientation(md.orientation))
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
                            props.density, md.lattice, md.lattice_constant_angstrom
                        ),
                    ));
                }
                Ok((props.wave_speed, Some(file)))
            }
        }
    }

    fn validate_boundary(&self, loc: &Locator<'_>) -> Result<(), SceneError> {
        let dim = self.domain.dimension;
        let allowed = "allowed: \"free\", \"fixed\", \"reflective\", \"roller\", \"periodic\", or { piston = [velocity per axis, m/s] }";
        for (i, (face, spec)) in self.boundary.faces().into_iter().enumerate() {
            let key = format!("boundary.{face}");
            let axis = i / 2;
            match spec {
                FaceSpec::Named(n) if !["free", "fixed", "reflective", "roller", "periodic"].contains(&n.as_str()) => {
                    return Err(loc.err(&key, format!("{n:?}"), allowed));
                }
                FaceSpec::Named(n) if axis >= dim && n != "free" => {
                    return Err(loc.err(&key, format!("{n:?}"), format!("a {dim}D scene has no {face} face")));
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
            let periodic = |f: &FaceSpec| matches!(f, FaceSpec::Named(n) if n == "periodic");
            if periodic(lo) != periodic(hi) {
                let face = ["x", "y", "z"][axis];
                return Err(loc.err(
                    &format!("boundary.{face}_max"),
                    format!("{hi:?}"),
                    format!("periodic must be set on both {face}_min and {face}_max"),
                ));
            }
        }
        Ok(())
    }

    fn validate_scheme(&mut self, loc: &Locator<'_>, max_speed: f64) -> Result<(f64, u64), SceneError> {
        let dim = self.domain.dimension;
        let s = &mut self.scheme;
        let names: Vec<&str> = continuum::SchemeKind::NAMES.iter().map(|(n, _)| *n).collect();
        let Some(kind) = continuum::SchemeKind::from_name(&s.method) else {
            return Err(loc.err("scheme.method", format!("{:?}", s.method), format!("allowed: {}", names.join(", "))));
        };
        if !kind.supports_dimension(dim) {
            let ok: Vec<&str> = continuum::SchemeKind::NAMES.iter().filter(|(_, k)| k.supports_dimension(dim)).map(|(n, _)| *n).collect();
            return Err(loc.err(
                "scheme.method",
                format!("{:?}", s.method),
                format!("`{}` is the 1D CPDI; a {dim}D scene allows: {}", s.method, ok.join(", ")),
            ));
        }
        if !(1..=64).contains(&s.particles_per_cell) {
            return Err(loc.err("scheme.particles_per_cell", s.particles_per_cell, "allowed: 1 to 64 per axis"));
        }
        if kind == continuum::SchemeKind::DdmpSubpoints {
            if !(1..=64).contains(&s.sub_points) {
                return Err(loc.err("scheme.sub_points", s.sub_points, "allowed: 1 to 64 sub-points per particle"));
            }
        } else if s.sub_points != 1 {
            return Err(loc.err(
                "scheme.sub_points",
                s.sub_points,
                format!("sub-points need method \"ddmp-subpoints\"; `{}` uses 1", s.method),
            ));
        }
        if !["dhakal", "leapfrog"].contains(&s.integrator.as_str()) {
            return Err(loc.err("scheme.integrator", format!("{:?}", s.integrator), "allowed: \"dhakal\" (Ch. 3.1 cycle), \"leapfrog\""));
        }
        if !["none", "linear", "tensor"].contains(&s.artificial_viscosity.as_str()) {
            return Err(loc.err(
                "scheme.artificial_viscosity",
                format!("{:?}", s.artificial_viscosity),
                "allowed: \"none\", \"linear\", \"tensor\"",
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
        if !(s.small_mass_fraction.is_finite() && (0.0..1.0).contains(&s.small_mass_fraction)) {
            return Err(loc.err("scheme.small_mass_fraction", s.small_mass_fraction, "must lie in [0, 1)"));
        }
        finite_positive(loc, "scheme.end_time", s.end_time, "the end time (s)")?;
        let h = self.domain.cell_size.iter().cloned().fold(f64::INFINITY, f64::min);
        let speed = max_speed + self.bodies.values().flat_map(|b| b.velocity.iter()).fold(0.0_f64, |m, v| m.max(v.abs()));
        let bound = CFL_LIMIT * h / speed;
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
                if !(c > 0.0 && c <= CFL_LIMIT) {
                    return Err(loc.err("scheme.cfl", c, format!("allowed: 0 < cfl <= {CFL_LIMIT} (explicit stability bound)")));
                }
                dt
            }
            (None, None) => return Err(loc.err("scheme", "", "missing `cfl` (c dt / h, at most 1) or `timestep` (s)")),
            (Some(c), None) => {
                if !(c > 0.0 && c <= CFL_LIMIT) {
                    return Err(loc.err("scheme.cfl", c, format!("allowed: 0 < cfl <= {CFL_LIMIT} (explicit stability bound)")));
                }
                c * h / speed
            }
            (None, Some(dt)) => {
                finite_positive(loc, "scheme.timestep", dt, "the time step (s)")?;
                if dt > bound {
                    return Err(loc.err("scheme.timestep", dt, format!("exceeds the stability bound h / (c + |v|) = {bound:.6e} s (h = {h:e} m, c + |v| = {speed:e} m/s); use a smaller time step or `cfl`")));
                }
                dt
            }
        };
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
        if self.domain.dimension != 1 {
            return Err(loc.err(
                "reference.solution",
                "\"direct-md\"",
                format!("scores 1D scenes only (the slabs of a 1D `md-worker direct --slab` run); this scene has dimension {}: the 2D form (Eulerian bins) is not implemented yet", self.domain.dimension),
            ));
        }
        if !REFERENCE_COMPONENTS.contains(&r.component.as_str()) {
            return Err(loc.err(
                "reference.component",
                format!("{:?}", r.component),
                format!(
                    "allowed: {} (sxx: the shock direction of a 1D bar)",
                    REFERENCE_COMPONENTS.iter().map(|c| format!("\"{c}\"")).collect::<Vec<_>>().join(", ")
                ),
            ));
        }
        let file = base.join(&r.profile);
        let profile = crate::report::DirectProfile::read_component(&file, &r.component).map_err(|e| {
            loc.err(
                "reference.profile",
                format!("{:?}", r.profile),
                format!("{e:#}; the profile is the CSV of `md-worker direct --slab`, its path relative to the scene file"),
            )
        })?;
        if r.times_ps.is_empty() {
            return Err(loc.err("reference.times_ps", "[]", "give at least one time (ps) to score at, e.g. [5.0, 10.0]"));
        }
        let (first, last) = profile.time_range();
        for (k, &t) in r.times_ps.iter().enumerate() {
            let key = format!("reference.times_ps[{k}]");
            if !t.is_finite() || t * 1e-12 < first - crate::report::TIME_TOLERANCE_S || t * 1e-12 > last + crate::report::TIME_TOLERANCE_S {
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
            if profile.at(t * 1e-12).is_none() {
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
        if let Err(e) = crate::report::ReferenceMap::of(self) {
            return Err(loc.err("reference.solution", "\"direct-md\"", format!("{e:#}")));
        }
        Ok(file.canonicalize().unwrap_or(file))
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

    /// `output.dump_points`: each id must name a material point of an md body, once.
    fn validate_dump_points(&self, loc: &Locator<'_>) -> Result<(), SceneError> {
        let ids = &self.output.dump_points;
        if ids.is_empty() {
            return Ok(());
        }
        // Point ids run body after body (in name order), as in the particle files.
        let (counts, _) = crate::setup::work_size(self);
        let mut ranges = Vec::new();
        let mut first = 0u64;
        for (name, n) in counts {
            ranges.push((name, first..first + n as u64));
            first += n as u64;
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

    /// Whether any body needs the MD engine.
    pub fn needs_md(&self) -> bool {
        self.bodies.values().any(|b| matches!(b.material, Material::Md(_)))
    }

    /// The resolved scene as TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# could not render the scene: {e}\n"))
    }
}
