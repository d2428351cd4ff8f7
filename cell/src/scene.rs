//! The typed scene of a cell run (`kind = "cell"`): parsing, validation and defaults.
//!
//! Same conventions as the MPM scenes of the orchestrator: unknown keys, missing keys and wrong
//! types are refused by serde with the line; [`CellScene::validate`] checks physics and
//! numerics and fills every default, so `scene.resolved.toml` shows exactly what ran. Every
//! message names the line (or the `--set` that put the value there), the key, the value and
//! what is allowed.

use crate::units::{CM2_PER_S, E_CHARGE, EPS0, K_B};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// The scene-file schema this build reads (the same number as the MPM scenes).
pub const SCHEMA_VERSION: u32 = 1;

/// Cation face states of the drift.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FaceState {
    /// MUSCL states with the van Leer limiter (8.65)-(8.67), upwinded by the drift velocity.
    VanLeer,
    /// The upwind cell's value (first order).
    Upwind,
    /// The mean of the two cells (what the thesis's no-limiter runs do; it oscillates once
    /// a cell's potential drop exceeds 2 kT/e).
    Central,
}

/// Time integration of a cell scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Integrator {
    /// diffsol's variable-order BDF with a mass matrix.
    Bdf,
    /// Refused unless timestep_s is below its stability bound.
    ExplicitEuler,
}

/// The linear solver of the BDF's Newton iterations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LinearSolver {
    /// LU with partial pivoting of the banded matrix (8 sub- and 8 super-diagonals): cost
    /// linear in the cells.
    Banded,
    /// faer's general sparse LU (fill-reducing ordering, supernodes).
    SparseLu,
}

/// How the BDF's Newton iteration writes the electron rows of the electrodes (the DAE and its
/// BDF solution are the same either way; cell/README.md "Electron rows").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ElectronRows {
    /// `n' = (F_n[i] - F_n[i+1]) / dx` with `F_n = sigma dphi/dx`: the electron rate is a
    /// difference of two nearly equal fluxes, each from a difference of potentials.
    Potential,
    /// The same row plus `sigma/(eps eps0/e)` times the cell's Poisson row (a constant row
    /// operation that leaves M, and so the BDF equations, unchanged): inside an electrode
    /// `n' = (p - n) / tau` (tau = eps eps0 / sigma), at its ends the face's excess flux
    /// `F_n - (sigma/eps) G` over dx, so no potential enters where n ~ 0.
    Field,
}

/// The interface switch at the threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Switch {
    Events,
    Ramp,
}

/// A problem with a cell scene. `location` is `line N`, `--set key=value` or empty.
#[derive(Debug, Clone, PartialEq)]
pub struct CellSceneError {
    pub location: String,
    pub key: String,
    pub value: String,
    pub problem: String,
}

impl fmt::Display for CellSceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if !self.location.is_empty() {
            write!(f, "{}", self.location)?;
        }
        if !self.key.is_empty() {
            if !self.location.is_empty() {
                write!(f, ": ")?;
            }
            write!(f, "`{}`", self.key)?;
            if !self.value.is_empty() {
                write!(f, " = {}", self.value)?;
            }
        }
        write!(f, ": {}", self.problem)
    }
}

impl std::error::Error for CellSceneError {}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CellScene {
    pub schema: u32,
    /// Must be "cell".
    pub kind: String,
    #[serde(default)]
    pub name: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub description: String,
    pub grid: Grid,
    #[serde(default)]
    pub physics: Physics,
    /// Electrode at x = 0 (optional: an electrolyte alone has none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub anode: Option<Electrode>,
    pub electrolyte: Electrolyte,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cathode: Option<Electrode>,
    #[serde(default)]
    pub interface: Interface,
    #[serde(default)]
    pub boundary: CellBoundary,
    pub scheme: CellScheme,
    #[serde(default)]
    pub output: CellOutput,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Grid {
    /// Number of uniform cells over the whole cell (anode + electrolyte + cathode).
    pub cells: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Physics {
    /// Temperature (K); 300 in the thesis.
    #[serde(default = "default_temperature")]
    pub temperature_k: f64,
}

fn default_temperature() -> f64 {
    300.0
}

impl Default for Physics {
    fn default() -> Self {
        Physics { temperature_k: default_temperature() }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Electrode {
    pub width_nm: f64,
    /// Relative permittivity (10 in the thesis).
    pub eps_r: f64,
    /// Cation diffusivity (cm^2/s).
    pub d_p_cm2_per_s: f64,
    /// Electronic conductivity (S/m, SI). The thesis's printed S/cm values cannot be meant in SI
    /// (see the crate README); this is a free parameter.
    pub sigma_s_per_m: f64,
    /// Initial cation concentration (1/nm^3).
    pub p0_per_nm3: f64,
    /// Initial electron concentration (1/nm^3).
    pub n0_per_nm3: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Electrolyte {
    pub width_nm: f64,
    pub eps_r: f64,
    /// Cation diffusivity (cm^2/s).
    pub d_p_cm2_per_s: f64,
    /// Anion diffusivity (cm^2/s); 0: fixed anions (the thesis).
    #[serde(default)]
    pub d_n_cm2_per_s: f64,
    pub p0_per_nm3: f64,
    pub n0_per_nm3: f64,
}

/// The threshold law (8.23) for cations crossing an electrode/electrolyte face.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Interface {
    /// Reduction factor alpha of the interface flux (not given in the thesis).
    #[serde(default = "default_alpha")]
    pub alpha: f64,
    /// Overpotential threshold gamma_t (V): the face opens when |phi_j - phi_j+1| >= it.
    #[serde(default = "default_threshold")]
    pub threshold_v: f64,
    /// An open face closes again only below threshold_v - hysteresis_v (> 0: no chattering
    /// of the switch at the threshold; the thesis has none and steps at a fixed dt).
    #[serde(default = "default_hysteresis")]
    pub hysteresis_v: f64,
    /// "events": the thesis's switch, located as a root of |dphi| - threshold (with the
    /// hysteresis), the integrator restarting at every flip; "ramp": the flux factor rises
    /// linearly from 0 at threshold_v - ramp_width_v to 1 at threshold_v (a continuous
    /// regularisation whose limit ramp_width_v -> 0 is the sliding mode the events chatter
    /// about; no restarts).
    #[serde(default = "default_switch")]
    pub switch: Switch,
    #[serde(default = "default_ramp")]
    pub ramp_width_v: f64,
    /// Absent (the thesis): the switch compares the one-face jump |phi_j - phi_j+1| with the
    /// thresholds, so it opens at the field threshold_v / dx: the field, the charge stored at
    /// the interface when it opens and the time it opens all grow in proportion to the cell
    /// count (the full cell: 2.95e-3 s x cells / 1000), and the discharge that follows needs
    /// ever shorter steps. Set: the jump scaled to this width, |phi_j - phi_j+1| w / dx (the
    /// interface field times w, the drop over an interphase of width w), the same switch on
    /// every grid, equal to the thesis's where dx = w.
    #[serde(default)]
    pub threshold_width_nm: Option<f64>,
}

fn default_switch() -> Switch {
    Switch::Events
}
fn default_ramp() -> f64 {
    0.01
}

fn default_alpha() -> f64 {
    1.0
}
fn default_threshold() -> f64 {
    0.1
}
fn default_hysteresis() -> f64 {
    0.02
}

impl Default for Interface {
    fn default() -> Self {
        Interface {
            alpha: default_alpha(),
            threshold_v: default_threshold(),
            hysteresis_v: default_hysteresis(),
            switch: default_switch(),
            ramp_width_v: default_ramp(),
            threshold_width_nm: None,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CellBoundary {
    /// Electron current at both ends, positive left to right (mA/cm^2); 3 in the thesis.
    #[serde(default)]
    pub electron_current_ma_per_cm2: f64,
    /// Dirichlet potential at x = 0 (V).
    #[serde(default)]
    pub phi_left_v: f64,
    /// "insulating": no cation flux and zero field at the right end (the thesis's cell);
    /// "reservoir": phi = phi_right_v and p = the electrolyte's p0 at the right face (a bulk
    /// electrolyte beyond it: the Debye test).
    #[serde(default = "default_right")]
    pub right: String,
    #[serde(default)]
    pub phi_right_v: f64,
}

fn default_right() -> String {
    "insulating".into()
}

impl Default for CellBoundary {
    fn default() -> Self {
        CellBoundary { electron_current_ma_per_cm2: 0.0, phi_left_v: 0.0, right: default_right(), phi_right_v: 0.0 }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CellScheme {
    /// "bdf" (diffsol's variable-order BDF with a mass matrix; the default) or
    /// "explicit-euler" (refused unless timestep_s is below its stability bound).
    #[serde(default = "default_integrator")]
    pub integrator: Integrator,
    /// Cation face states of the drift: "van-leer" (8.65)-(8.67), "upwind" or "central".
    #[serde(default = "default_face_state")]
    pub face_state: FaceState,
    pub end_time_s: f64,
    #[serde(default = "default_rtol")]
    pub rtol: f64,
    /// Absolute tolerance on a concentration (1/nm^3), the same in every cell whatever the
    /// cell count. Either this or `atol_inventory_per_nm2`, not both; neither: 1e-9.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub atol_concentration: Option<f64>,
    /// Absolute tolerance on a cell's inventory, concentration x dx (1/nm^2): the
    /// concentration's tolerance is this / dx, so a refined grid is held to the same amounts
    /// per cell rather than to the same concentrations (which at 1e5 cells lies below what the
    /// Newton iteration can resolve in double precision; cell/README.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub atol_inventory_per_nm2: Option<f64>,
    #[serde(default = "default_atol_phi")]
    pub atol_potential_v: f64,
    /// Only for explicit-euler.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timestep_s: Option<f64>,
    /// Bound on accepted steps (the run fails past it).
    #[serde(default = "default_max_steps")]
    pub max_steps: u64,
    /// "banded" (the default) or "sparse-lu".
    #[serde(default = "default_linear_solver")]
    pub linear_solver: LinearSolver,
    /// The electrodes' electron rows in the Newton iteration: "potential" (the default) or
    /// "field" (cell/README.md "Electron rows": the same BDF solution, measured 8 % fewer
    /// steps at 1e5 cells, not the fix of the stall).
    #[serde(default = "default_electron_rows")]
    pub electron_rows: ElectronRows,
    /// Charge-exact Newton corrections (cell/README.md "Charge-exact linear solves"): after
    /// the banded LU, the correction is moved so that it changes the cell's net charge by
    /// exactly what the Newton system prescribes. Applies where the charge's rate does not
    /// depend on the state (an insulating right end), with the banded LU and the potential
    /// form of the electron rows; elsewhere it is a no-op. Default true.
    #[serde(default = "default_true")]
    pub charge_exact_solve: bool,
}

fn default_electron_rows() -> ElectronRows {
    ElectronRows::Potential
}

fn default_linear_solver() -> LinearSolver {
    LinearSolver::Banded
}

fn default_integrator() -> Integrator {
    Integrator::Bdf
}
fn default_face_state() -> FaceState {
    FaceState::VanLeer
}
fn default_rtol() -> f64 {
    1e-6
}
/// The concentrations' absolute tolerance when a scene sets neither key (1/nm^3).
pub const DEFAULT_ATOL_CONCENTRATION: f64 = 1e-9;
fn default_atol_phi() -> f64 {
    1e-9
}
fn default_max_steps() -> u64 {
    1_000_000
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CellOutput {
    /// Times (s) of the profiles (profiles/profile_<step>.csv); the final one is always written.
    #[serde(default)]
    pub times_s: Vec<f64>,
    /// PNG of each profile.
    #[serde(default = "default_true")]
    pub plots: bool,
}

fn default_true() -> bool {
    true
}

impl Default for CellOutput {
    fn default() -> Self {
        CellOutput { times_s: Vec::new(), plots: true }
    }
}

/// Where a value came from, for messages: the closure maps a dotted key to `line N`,
/// `--set key=value` or "".
pub type Locate<'a> = &'a dyn Fn(&str) -> String;

/// Line (1-based) of a dotted key in TOML text, if it is written there.
pub fn line_of(text: &str, key: &str) -> Option<usize> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut item = doc.as_item();
    let mut span = None;
    for part in key.split('.') {
        let table = item.as_table_like()?;
        let (k, next) = table.get_key_value(part)?;
        span = k.span().or(span);
        item = next;
    }
    let start = span?.start;
    Some(text[..start.min(text.len())].matches('\n').count() + 1)
}

/// The dotted key whose value (or key) holds byte `offset` of the text, for serde's errors
/// (an unknown name or a wrong type is reported at its value).
fn key_at(text: &str, offset: usize) -> Option<String> {
    fn walk(table: &dyn toml_edit::TableLike, prefix: &str, offset: usize) -> Option<String> {
        for (k, item) in table.iter() {
            let key = if prefix.is_empty() { k.to_string() } else { format!("{prefix}.{k}") };
            if let Some(inner) = item.as_table_like()
                && let Some(found) = walk(inner, &key, offset)
            {
                return Some(found);
            }
            let in_value = item.span().is_some_and(|r| r.contains(&offset));
            let in_key = table.get_key_value(k).and_then(|(k, _)| k.span()).is_some_and(|r| r.contains(&offset));
            if in_value || in_key {
                return Some(key);
            }
        }
        None
    }
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    walk(doc.as_table(), "", offset)
}

/// Whether TOML text is a cell scene (`kind = "cell"` at the top level).
pub fn is_cell_text(text: &str) -> bool {
    toml_edit::ImDocument::parse(text).ok().is_some_and(|d| d.get("kind").and_then(|k| k.as_str()) == Some("cell"))
}

/// Parses and validates cell-scene text (after the orchestrator's `--set` overrides);
/// `overrides` maps overridden keys to their values, for the locations of messages.
pub fn parse(text: &str, overrides: &BTreeMap<String, String>, default_name: &str) -> Result<CellScene, CellSceneError> {
    let mut scene: CellScene = toml::from_str(text).map_err(|e| {
        let location = e.span().map(|s| format!("line {}", text[..s.start.min(text.len())].matches('\n').count() + 1)).unwrap_or_default();
        let key = e.span().and_then(|s| key_at(text, s.start)).unwrap_or_default();
        let location = overrides.get(&key).map_or(location, |v| format!("--set {key}={v}"));
        CellSceneError { location, key, value: String::new(), problem: e.message().to_string() }
    })?;
    if scene.name.is_empty() {
        scene.name = default_name.to_string();
    }
    let locate = |key: &str| -> String {
        if let Some(v) = overrides.get(key) {
            return format!("--set {key}={v}");
        }
        line_of(text, key).map(|l| format!("line {l}")).unwrap_or_default()
    };
    scene.validate(&locate)?;
    Ok(scene)
}

fn err(locate: Locate<'_>, key: &str, value: impl fmt::Display, problem: impl Into<String>) -> CellSceneError {
    CellSceneError { location: locate(key), key: key.into(), value: value.to_string(), problem: problem.into() }
}

fn positive(locate: Locate<'_>, key: &str, v: f64) -> Result<(), CellSceneError> {
    if v.is_finite() && v > 0.0 { Ok(()) } else { Err(err(locate, key, v, "must be a finite positive number")) }
}

fn non_negative(locate: Locate<'_>, key: &str, v: f64) -> Result<(), CellSceneError> {
    if v.is_finite() && v >= 0.0 { Ok(()) } else { Err(err(locate, key, v, "must be a finite number >= 0")) }
}

fn finite(locate: Locate<'_>, key: &str, v: f64) -> Result<(), CellSceneError> {
    if v.is_finite() { Ok(()) } else { Err(err(locate, key, v, "must be a finite number")) }
}

/// Fewest and most cells a scene may ask for.
pub const MIN_CELLS: usize = 3;
pub const MAX_CELLS: usize = 1_000_000;

impl CellScene {
    /// The stiffest stable explicit-Euler step of a scene (s): per region the diffusion bound
    /// dx^2/(2D) and the dielectric relaxation time lambda^2/D = eps eps0 kT/(e^2 D c) combined as
    /// 1/(1/a + 1/b), and in an electrode also eps eps0/sigma.
    pub fn explicit_bound(&self) -> f64 {
        let scene = self;
        let dx = scene.length_nm() / scene.grid.cells as f64;
        let kt = K_B * scene.physics.temperature_k;
        let mut bound = f64::INFINITY;
        let mut region = |eps_r: f64, d: f64, c: f64, sigma_si: Option<f64>| {
            let mut rate = 2.0 * d / (dx * dx);
            if c > 0.0 {
                let lambda2 = eps_r * EPS0 * kt / (E_CHARGE * E_CHARGE * c);
                rate += d / lambda2;
            }
            if let Some(s) = sigma_si {
                // sigma/e per V nm s, over eps_r eps0 (C/(V nm)) times e: the relaxation rate (1/s).
                rate = rate.max(s / (eps_r * 8.854e-12));
            }
            if rate > 0.0 {
                bound = bound.min(1.0 / rate);
            }
        };
        let el = &scene.electrolyte;
        region(el.eps_r, (el.d_p_cm2_per_s.max(el.d_n_cm2_per_s)) * CM2_PER_S, el.p0_per_nm3.max(el.n0_per_nm3), None);
        for e in [&scene.anode, &scene.cathode].into_iter().flatten() {
            region(e.eps_r, e.d_p_cm2_per_s * CM2_PER_S, e.p0_per_nm3.max(e.n0_per_nm3), Some(e.sigma_s_per_m));
        }
        bound
    }

    /// Checks physics and numerics and fills defaults.
    pub fn validate(&mut self, locate: Locate<'_>) -> Result<(), CellSceneError> {
        if self.schema != SCHEMA_VERSION {
            return Err(err(locate, "schema", self.schema, format!("this build reads schema {SCHEMA_VERSION}")));
        }
        if self.kind != "cell" {
            return Err(err(locate, "kind", format!("{:?}", self.kind), "a cell scene has kind = \"cell\""));
        }
        if !(MIN_CELLS..=MAX_CELLS).contains(&self.grid.cells) {
            return Err(err(locate, "grid.cells", self.grid.cells, format!("allowed: {MIN_CELLS} to {MAX_CELLS}")));
        }
        positive(locate, "physics.temperature_k", self.physics.temperature_k)?;
        match (&self.anode, &self.cathode) {
            (Some(_), None) | (None, Some(_)) => {
                return Err(err(locate, "cathode", "", "give both electrodes ([anode] and [cathode]) or neither (an electrolyte alone)"));
            }
            _ => {}
        }
        for (name, e) in [("anode", &self.anode), ("cathode", &self.cathode)] {
            let Some(e) = e else { continue };
            positive(locate, &format!("{name}.width_nm"), e.width_nm)?;
            positive(locate, &format!("{name}.eps_r"), e.eps_r)?;
            positive(locate, &format!("{name}.d_p_cm2_per_s"), e.d_p_cm2_per_s)?;
            positive(locate, &format!("{name}.sigma_s_per_m"), e.sigma_s_per_m)?;
            non_negative(locate, &format!("{name}.p0_per_nm3"), e.p0_per_nm3)?;
            non_negative(locate, &format!("{name}.n0_per_nm3"), e.n0_per_nm3)?;
        }
        let el = &self.electrolyte;
        positive(locate, "electrolyte.width_nm", el.width_nm)?;
        positive(locate, "electrolyte.eps_r", el.eps_r)?;
        positive(locate, "electrolyte.d_p_cm2_per_s", el.d_p_cm2_per_s)?;
        non_negative(locate, "electrolyte.d_n_cm2_per_s", el.d_n_cm2_per_s)?;
        non_negative(locate, "electrolyte.p0_per_nm3", el.p0_per_nm3)?;
        non_negative(locate, "electrolyte.n0_per_nm3", el.n0_per_nm3)?;
        // Every region must hold at least one cell, and the cell edges must fall on the
        // region boundaries (the interface faces are faces of the grid).
        let dx = self.length_nm() / self.grid.cells as f64;
        for (name, w) in self.region_widths() {
            let k = w / dx;
            if k.round() < 1.0 || (k - k.round()).abs() > 1e-6 * k.max(1.0) {
                return Err(err(
                    locate,
                    "grid.cells",
                    self.grid.cells,
                    format!(
                        "the {name} ({w} nm) must hold a whole number (>= 1) of cells of {dx} nm; choose cells so that every region width is a multiple of the cell size"
                    ),
                ));
            }
        }
        let i = &self.interface;
        non_negative(locate, "interface.alpha", i.alpha)?;
        non_negative(locate, "interface.threshold_v", i.threshold_v)?;
        non_negative(locate, "interface.hysteresis_v", i.hysteresis_v)?;
        if i.hysteresis_v > i.threshold_v {
            return Err(err(
                locate,
                "interface.hysteresis_v",
                i.hysteresis_v,
                format!("must not exceed interface.threshold_v = {}", i.threshold_v),
            ));
        }
        positive(locate, "interface.ramp_width_v", i.ramp_width_v)?;
        if let Some(w) = i.threshold_width_nm {
            positive(locate, "interface.threshold_width_nm", w)?;
        }
        let b = &self.boundary;
        finite(locate, "boundary.electron_current_ma_per_cm2", b.electron_current_ma_per_cm2)?;
        finite(locate, "boundary.phi_left_v", b.phi_left_v)?;
        finite(locate, "boundary.phi_right_v", b.phi_right_v)?;
        if !["insulating", "reservoir"].contains(&b.right.as_str()) {
            return Err(err(locate, "boundary.right", format!("{:?}", b.right), "allowed: \"insulating\", \"reservoir\""));
        }
        if self.anode.is_some() && b.right == "reservoir" {
            return Err(err(
                locate,
                "boundary.right",
                "\"reservoir\"",
                "a reservoir closes an electrolyte alone; a full cell ends in its cathode (\"insulating\")",
            ));
        }
        if self.anode.is_none() && b.electron_current_ma_per_cm2 != 0.0 {
            return Err(err(
                locate,
                "boundary.electron_current_ma_per_cm2",
                b.electron_current_ma_per_cm2,
                "an electrolyte alone carries no electrons; set 0 or add [anode] and [cathode]",
            ));
        }
        let s = &self.scheme;
        positive(locate, "scheme.end_time_s", s.end_time_s)?;
        if !(s.rtol.is_finite() && s.rtol > 0.0 && s.rtol < 0.1) {
            return Err(err(locate, "scheme.rtol", s.rtol, "allowed: 0 < rtol < 0.1"));
        }
        match (s.atol_concentration, s.atol_inventory_per_nm2) {
            (Some(_), Some(a)) => {
                return Err(err(
                    locate,
                    "scheme.atol_inventory_per_nm2",
                    a,
                    "set either scheme.atol_concentration or scheme.atol_inventory_per_nm2, not both",
                ));
            }
            (Some(c), None) => positive(locate, "scheme.atol_concentration", c)?,
            (None, Some(a)) => positive(locate, "scheme.atol_inventory_per_nm2", a)?,
            (None, None) => {}
        }
        positive(locate, "scheme.atol_potential_v", s.atol_potential_v)?;
        if s.max_steps == 0 {
            return Err(err(locate, "scheme.max_steps", 0, "must be at least 1"));
        }
        match s.integrator {
            Integrator::Bdf => {
                if s.timestep_s.is_some() {
                    return Err(err(
                        locate,
                        "scheme.timestep_s",
                        s.timestep_s.unwrap_or(0.0),
                        "bdf chooses its own steps; remove timestep_s",
                    ));
                }
            }
            Integrator::ExplicitEuler => {
                let bound = self.explicit_bound();
                let Some(dt) = s.timestep_s else {
                    return Err(err(
                        locate,
                        "scheme.timestep_s",
                        "",
                        format!(
                            "explicit-euler needs timestep_s; it is stable only for dt <= {bound:.3e} s (diffusion dx^2/(2D) and dielectric relaxation eps eps0 kT/(e^2 D c)); use integrator = \"bdf\""
                        ),
                    ));
                };
                positive(locate, "scheme.timestep_s", dt)?;
                if dt > bound {
                    return Err(err(
                        locate,
                        "scheme.timestep_s",
                        dt,
                        format!(
                            "explicit Euler is unstable here: it needs dt <= {bound:.3e} s (diffusion dx^2/(2D) and dielectric relaxation eps eps0 kT/(e^2 D c), the stiffest region), that is {:.3e} steps to end_time_s; use integrator = \"bdf\"",
                            s.end_time_s / bound
                        ),
                    ));
                }
                let steps = (s.end_time_s / dt).ceil();
                if steps > s.max_steps as f64 {
                    return Err(err(
                        locate,
                        "scheme.timestep_s",
                        dt,
                        format!(
                            "{steps:.3e} explicit steps to end_time_s exceed scheme.max_steps = {}; use integrator = \"bdf\"",
                            s.max_steps
                        ),
                    ));
                }
            }
        }
        let mut times = self.output.times_s.clone();
        for (k, t) in times.iter().enumerate() {
            if !(t.is_finite() && *t >= 0.0 && *t <= s.end_time_s) {
                return Err(err(
                    locate,
                    "output.times_s",
                    format!("{:?}", self.output.times_s),
                    format!("entry {k} = {t}: times must lie in [0, end_time_s = {}]", s.end_time_s),
                ));
            }
        }
        times.sort_by(f64::total_cmp);
        times.dedup();
        self.output.times_s = times;
        Ok(())
    }

    /// (name, width nm) of each region from x = 0.
    pub fn region_widths(&self) -> Vec<(&'static str, f64)> {
        let mut v = Vec::new();
        if let Some(a) = &self.anode {
            v.push(("anode", a.width_nm));
        }
        v.push(("electrolyte", self.electrolyte.width_nm));
        if let Some(c) = &self.cathode {
            v.push(("cathode", c.width_nm));
        }
        v
    }

    /// The concentrations' absolute tolerance (1/nm^3) at this scene's cell size:
    /// `atol_concentration`, or `atol_inventory_per_nm2 / dx`.
    pub fn atol_concentration(&self) -> f64 {
        match (self.scheme.atol_concentration, self.scheme.atol_inventory_per_nm2) {
            (Some(c), _) => c,
            (None, Some(a)) => a / (self.length_nm() / self.grid.cells as f64),
            (None, None) => DEFAULT_ATOL_CONCENTRATION,
        }
    }

    pub fn length_nm(&self) -> f64 {
        self.region_widths().iter().map(|(_, w)| w).sum()
    }

    /// The scene with every default filled, as TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot serialise the scene: {e}\n"))
    }
}
