//! Checkpoints of a run: everything needed to continue it bit for bit, in
//! `<run dir>/checkpoints/step-<step>.ckpt`.
//!
//! A checkpoint holds the complete continuum state (every array of the material points, time,
//! step, wall impulse, initial totals, counters), every MD box (`MdPool::snapshot`) with the
//! per-point state of the MD closure (pending energy), and what the run driver needs to write
//! the same outputs (snapshot index, running maxima). Main design decision: the file is one line
//! of header, `mscale-checkpoint 1 bytes=<n> sha256=<hex>`, and a JSON body whose f64 values
//! round-trip bit for bit (serde_json `float_roundtrip`); it is written atomically (temporary
//! file, fsync, rename, fsync of the directory) and the two newest are kept, so a checkpoint
//! cut short or damaged is detected by its checksum and the previous one is used instead.
//!
//! Restoring rebuilds the simulation from the scene as a fresh run does (grid, closures, MD
//! boxes opened) and then overwrites its state, so nothing private to the solver is saved:
//! the solver recomputes its scratch (stencils, nodal fields) from the points every step.

use anyhow::{Context, Result, bail, ensure};
use continuum::diagnostics::Totals;
use continuum::tensor::Mat3;
use continuum::{Particles, Simulation};
use coupling::{MdPointState, MdShared};
use md_worker::{BoxResult, BoxState};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// Version of the checkpoint format; a file of another version is refused.
pub const FORMAT_VERSION: u32 = 1;
const MAGIC: &str = "mscale-checkpoint";
/// Checkpoints kept in a run directory (the newest and the one before it).
pub const KEEP: usize = 2;

/// The saved state of a run at the end of a step.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Checkpoint {
    /// SHA-256 of the resolved scene (`Scene::to_toml`) the run was started with.
    pub scene_sha256: String,
    pub dimension: usize,
    pub step: u64,
    /// Simulated time (s).
    pub time: f64,
    /// Time step (s).
    pub dt: f64,
    pub closure_evaluations: u64,
    pub integration_point_updates: u64,
    /// N s (per unit cross-section in 1D), `dimension` components.
    pub wall_impulse: Vec<f64>,
    pub wall_impulse_magnitude: f64,
    pub initial: SavedTotals,
    pub points: SavedPoints,
    pub md: Option<SavedMd>,
    pub driver: DriverState,
    /// The implicit integrator's history and record (implicit runs only; absent in older
    /// checkpoints, which then resume without a^{n-1} and with the counts restarted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub implicit: Option<SavedImplicit>,
    /// tlmpm's moving mesh: the carried nodal velocity, node by node, `dimension` components
    /// each (empty for every other scheme, and before the moving mesh's first step).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub mesh_velocity: Vec<f64>,
}

/// What an implicit run carries past a checkpoint: a^n of the last step per nodal dof (the
/// velocity error estimate's a^{n-1} of the next step, which the adaptive step's error norm
/// reads), that step's dt, and the statistics summary.json reports.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedImplicit {
    pub prev_acc: Vec<f64>,
    pub prev_dt: f64,
    pub stats: continuum::solver::implicit::ImplicitStats,
}

/// [`Totals`] with the momentum as a vector.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedTotals {
    pub mass: f64,
    pub momentum: Vec<f64>,
    pub kinetic: f64,
    pub internal: f64,
}

/// Every array of [`Particles`], vectors of `D` and 3x3 tensors flattened row by row.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedPoints {
    pub x0: Vec<f64>,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub mass: Vec<f64>,
    pub volume0: Vec<f64>,
    pub volume: Vec<f64>,
    pub half_length: Vec<f64>,
    pub def_grad: Vec<f64>,
    pub vel_grad: Vec<f64>,
    pub stress: Vec<f64>,
    pub visc_pressure: Vec<f64>,
    pub visc_stress: Vec<f64>,
    pub domain0: Vec<f64>,
    pub corners: Vec<f64>,
    pub internal_energy: Vec<f64>,
    pub body: Vec<u32>,
    /// The optional fields (empty when the scene has none; absent in older checkpoints).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub scalar: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub scalar_rate: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub plastic_strain: Vec<f64>,
}

/// The MD side: the closure's per-point state and every box.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedMd {
    /// The continuum step of the capture (the MD closures take their step from the solver's
    /// batch; kept so checkpoints stay readable both ways).
    pub step: u64,
    /// Indexed by global point index; `None` for points of non-MD bodies.
    pub points: Vec<Option<SavedMdPoint>>,
    /// Every box of the pool, by ascending id.
    pub boxes: Vec<BoxState>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedMdPoint {
    pub last: BoxResult,
    /// eV.
    pub pending_ev: f64,
    /// eV.
    pub added_ev: f64,
    /// The tolerance mode's state of the box (absent in checkpoints of runs without it).
    #[serde(default)]
    pub skip: coupling::Skip,
}

/// What the run driver carries from step to step.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct DriverState {
    pub max_kinetic: f64,
    pub max_abs_momentum: f64,
    /// Contents of `snapshots/index.csv` so far.
    pub snapshot_index: String,
    /// Entries of `vtk/particles.pvd` so far: (time in s, file).
    pub pvd: Vec<(f64, String)>,
    /// Seconds spent before this checkpoint (summed over earlier sessions of the run).
    pub wall_s: f64,
    pub setup_s: f64,
    pub continuum_s: f64,
    pub output_s: f64,
}

fn flat<const N: usize>(v: &[[f64; N]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

fn flat_mat(v: &[Mat3]) -> Vec<f64> {
    v.iter().flatten().flatten().copied().collect()
}

fn unflat<const N: usize>(name: &str, v: &[f64], n: usize) -> Result<Vec<[f64; N]>> {
    ensure!(v.len() == n * N, "checkpoint field {name} has {} values, expected {}", v.len(), n * N);
    Ok(v.chunks_exact(N).map(|c| std::array::from_fn(|a| c[a])).collect())
}

fn unflat_mat(name: &str, v: &[f64], n: usize) -> Result<Vec<Mat3>> {
    ensure!(v.len() == n * 9, "checkpoint field {name} has {} values, expected {}", v.len(), n * 9);
    Ok(v.chunks_exact(9).map(|c| std::array::from_fn(|i| std::array::from_fn(|j| c[3 * i + j]))).collect())
}

fn scalars(name: &str, v: &[f64], n: usize) -> Result<Vec<f64>> {
    ensure!(v.len() == n, "checkpoint field {name} has {} values, expected {n}", v.len());
    Ok(v.to_vec())
}

/// An optional per-point field: empty, or one value per point.
fn optional(name: &str, v: &[f64], n: usize) -> Result<Vec<f64>> {
    if v.is_empty() { Ok(Vec::new()) } else { scalars(name, v, n) }
}

impl SavedPoints {
    pub fn of<const D: usize>(p: &Particles<D>) -> Self {
        SavedPoints {
            x0: flat(&p.x0),
            x: flat(&p.x),
            v: flat(&p.v),
            mass: p.mass.clone(),
            volume0: p.volume0.clone(),
            volume: p.volume.clone(),
            half_length: flat(&p.half_length),
            def_grad: flat_mat(&p.def_grad),
            vel_grad: flat_mat(&p.vel_grad),
            stress: flat_mat(&p.stress),
            visc_pressure: p.visc_pressure.clone(),
            visc_stress: flat_mat(&p.visc_stress),
            domain0: flat_mat(&p.domain0),
            corners: flat(&p.corners),
            internal_energy: p.internal_energy.clone(),
            body: p.body.clone(),
            scalar: p.scalar.clone(),
            scalar_rate: p.scalar_rate.clone(),
            plastic_strain: p.plastic_strain.clone(),
        }
    }

    pub fn to_particles<const D: usize>(&self) -> Result<Particles<D>> {
        let n = self.mass.len();
        ensure!(self.body.len() == n, "checkpoint field body has {} values, expected {n}", self.body.len());
        Ok(Particles {
            x0: unflat("x0", &self.x0, n)?,
            x: unflat("x", &self.x, n)?,
            v: unflat("v", &self.v, n)?,
            mass: self.mass.clone(),
            volume0: scalars("volume0", &self.volume0, n)?,
            volume: scalars("volume", &self.volume, n)?,
            half_length: unflat("half_length", &self.half_length, n)?,
            def_grad: unflat_mat("def_grad", &self.def_grad, n)?,
            vel_grad: unflat_mat("vel_grad", &self.vel_grad, n)?,
            stress: unflat_mat("stress", &self.stress, n)?,
            visc_pressure: scalars("visc_pressure", &self.visc_pressure, n)?,
            visc_stress: unflat_mat("visc_stress", &self.visc_stress, n)?,
            domain0: unflat_mat("domain0", &self.domain0, n)?,
            corners: unflat("corners", &self.corners, n * (1 << D))?,
            internal_energy: scalars("internal_energy", &self.internal_energy, n)?,
            body: self.body.clone(),
            scalar: optional("scalar", &self.scalar, n)?,
            scalar_rate: optional("scalar_rate", &self.scalar_rate, n)?,
            plastic_strain: optional("plastic_strain", &self.plastic_strain, n)?,
        })
    }
}

/// SHA-256 of the resolved scene text, to refuse resuming a run with another scene.
pub fn scene_sha256(resolved_toml: &str) -> String {
    hex::encode(Sha256::digest(resolved_toml.as_bytes()))
}

impl Checkpoint {
    /// Captures a simulation (and its MD boxes) at the end of a step.
    pub fn capture<const D: usize>(
        sim: &Simulation<D>,
        scene_sha256: &str,
        md: Option<&mut MdShared>,
        driver: DriverState,
    ) -> Result<Self> {
        let md = match md {
            None => None,
            Some(m) => {
                let ids = m.pool.box_ids();
                let boxes = m.pool.snapshot(&ids).context("cannot snapshot the MD boxes")?;
                let points = m
                    .points
                    .iter()
                    .map(|p| {
                        p.as_ref().map(|s| SavedMdPoint { last: s.last, pending_ev: s.pending_ev, added_ev: s.added_ev, skip: s.skip })
                    })
                    .collect();
                Some(SavedMd { step: sim.step, points, boxes })
            }
        };
        let t = &sim.initial;
        Ok(Checkpoint {
            scene_sha256: scene_sha256.to_string(),
            dimension: D,
            step: sim.step,
            time: sim.time,
            dt: sim.dt,
            closure_evaluations: sim.closure_evaluations,
            integration_point_updates: sim.integration_point_updates,
            wall_impulse: sim.wall_impulse.to_vec(),
            wall_impulse_magnitude: sim.wall_impulse_magnitude,
            initial: SavedTotals { mass: t.mass, momentum: t.momentum.to_vec(), kinetic: t.kinetic, internal: t.internal },
            points: SavedPoints::of(&sim.points),
            md,
            driver,
            implicit: (sim.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal).then(|| SavedImplicit {
                prev_acc: sim.implicit.prev_acc.clone(),
                prev_dt: sim.implicit.prev_dt,
                stats: sim.implicit.stats.clone(),
            }),
            mesh_velocity: sim.mesh_velocity.iter().flatten().copied().collect(),
        })
    }

    /// Puts the saved state into a simulation freshly built from the same scene (and its MD
    /// boxes, opened from the same specs, into `md`).
    pub fn restore_into<const D: usize>(&self, sim: &mut Simulation<D>, md: Option<&mut MdShared>) -> Result<()> {
        ensure!(self.dimension == D, "the checkpoint is of a {}D run, the scene is {D}D", self.dimension);
        // Adaptive implicit steps carry their current dt in the checkpoint.
        let adaptive = sim.implicit.options.adaptive.is_some();
        ensure!(
            adaptive || self.dt.to_bits() == sim.dt.to_bits(),
            "the checkpoint's time step {:e} s differs from the scene's {:e} s",
            self.dt,
            sim.dt
        );
        let points = self.points.to_particles::<D>()?;
        ensure!(points.len() == sim.points.len(), "the checkpoint has {} material points, the scene {}", points.len(), sim.points.len());
        ensure!(points.body == sim.points.body, "the checkpoint's points belong to other bodies than the scene's");
        // A point's half-lengths are set by the scene and never change in a run: a checkpoint
        // whose half-lengths differ is not of this scene (a huge one made the uGIMP stencil
        // loop over 10^18 nodes: found by the checkpoint fuzzer).
        if let Some(p) =
            (0..points.len()).find(|&p| (0..D).any(|a| points.half_length[p][a].to_bits() != sim.points.half_length[p][a].to_bits()))
        {
            bail!(
                "checkpoint field half_length of point {p} is {:?}, the scene gives {:?}: the checkpoint is damaged or of another scene",
                points.half_length[p],
                sim.points.half_length[p]
            );
        }
        let vec_d = |name: &str, v: &[f64]| -> Result<[f64; D]> {
            ensure!(v.len() == D, "checkpoint field {name} has {} components, expected {D}", v.len());
            Ok(std::array::from_fn(|a| v[a]))
        };
        let initial = Totals {
            mass: self.initial.mass,
            momentum: vec_d("initial.momentum", &self.initial.momentum)?,
            kinetic: self.initial.kinetic,
            internal: self.initial.internal,
        };
        let wall_impulse = vec_d("wall_impulse", &self.wall_impulse)?;
        // Each step counts at most points x sub-points updates (the implicit step counts
        // points): a larger count is not a count this run could have made.
        let most = (self.step as u128) * (points.len() as u128) * (sim.sub_points.max(1) as u128);
        ensure!(
            u128::from(self.integration_point_updates) <= most,
            "checkpoint field integration_point_updates = {} exceeds {most}, the most {} steps of {} points can make",
            self.integration_point_updates,
            self.step,
            points.len()
        );
        match (md, &self.md) {
            (None, None) => {}
            (Some(m), Some(saved)) => {
                ensure!(
                    saved.points.len() == m.points.len(),
                    "the checkpoint has MD state for {} points, the scene {}",
                    saved.points.len(),
                    m.points.len()
                );
                m.pool.restore(saved.boxes.clone()).context("cannot restore the MD boxes")?;
                m.points = saved
                    .points
                    .iter()
                    .map(|p| {
                        p.as_ref().map(|s| MdPointState { last: s.last, pending_ev: s.pending_ev, added_ev: s.added_ev, skip: s.skip })
                    })
                    .collect();
            }
            (None, Some(_)) => bail!("the checkpoint has MD boxes but the scene has no md bodies"),
            (Some(_), None) => bail!("the scene has md bodies but the checkpoint has no MD boxes"),
        }
        let implicit = sim.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal;
        match (&self.implicit, implicit) {
            (Some(saved), true) => {
                let dofs = sim.grid.node_count() * D;
                ensure!(
                    saved.prev_acc.is_empty() || saved.prev_acc.len() == dofs,
                    "checkpoint field implicit.prev_acc has {} values, the grid has {dofs} nodal components",
                    saved.prev_acc.len()
                );
                ensure!(
                    saved.prev_dt.is_finite() && saved.prev_dt >= 0.0,
                    "checkpoint field implicit.prev_dt = {} is not a finite time step",
                    saved.prev_dt
                );
                sim.implicit.prev_acc = saved.prev_acc.clone();
                sim.implicit.prev_dt = saved.prev_dt;
                sim.implicit.stats = saved.stats.clone();
            }
            (None, true) => tracing::warn!(
                "the checkpoint predates the implicit integrator's saved state: the first step after the resume has no velocity error estimate (no a^(n-1)) and the implicit counts restart, so an adaptive run may take other steps than an uninterrupted one"
            ),
            (Some(_), false) => bail!("the checkpoint holds implicit-integrator state but the scene's integrator is explicit"),
            (None, false) => {}
        }
        let mv = &self.mesh_velocity;
        if sim.moving_mesh {
            let n = sim.grid.node_count();
            ensure!(
                mv.len() == n * D || (mv.is_empty() && self.step == 0),
                "checkpoint field mesh_velocity has {} values, the moving mesh of this scene needs {} ({n} nodes x {D}): the checkpoint is not of this scene's moving-mesh run",
                mv.len(),
                n * D
            );
            sim.mesh_velocity = mv.chunks_exact(D).map(|c| std::array::from_fn(|a| c[a])).collect();
        } else {
            ensure!(mv.is_empty(), "the checkpoint holds a moving mesh's nodal velocity but the scene's tlmpm_form is not \"moving-mesh\"");
        }
        sim.points = points;
        sim.time = self.time;
        sim.step = self.step;
        if adaptive {
            sim.dt = self.dt;
        }
        sim.closure_evaluations = self.closure_evaluations;
        sim.integration_point_updates = self.integration_point_updates;
        sim.wall_impulse = wall_impulse;
        sim.wall_impulse_magnitude = self.wall_impulse_magnitude;
        sim.initial = initial;
        Ok(())
    }
}

/// A flag raised by the first SIGINT or SIGTERM (the run then checkpoints and stops); a second
/// one of either ends the process at once.
pub fn stop_on_signals() -> std::io::Result<std::sync::Arc<std::sync::atomic::AtomicBool>> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    for sig in [SIGINT, SIGTERM] {
        // Registered first, so it sees the flag before this signal's own handler raises it.
        signal_hook::flag::register_conditional_shutdown(sig, 1, flag.clone())?;
        signal_hook::flag::register(sig, flag.clone())?;
    }
    Ok(flag)
}

/// The checkpoint directory of a run directory.
pub fn dir_of(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoints")
}

fn file_name(step: u64) -> String {
    format!("step-{step:012}.ckpt")
}

/// Checkpoint files of a run directory with their steps, newest first.
pub fn list(run_dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let dir = dir_of(run_dir);
    let mut out = Vec::new();
    let entries = match std::fs::read_dir(&dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e).with_context(|| format!("cannot list {}", dir.display())),
    };
    for e in entries {
        let e = e.with_context(|| format!("cannot list {}", dir.display()))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if let Some(step) = name.strip_prefix("step-").and_then(|s| s.strip_suffix(".ckpt")).and_then(|s| s.parse::<u64>().ok()) {
            out.push((step, e.path()));
        }
    }
    out.sort_by_key(|a| std::cmp::Reverse(a.0));
    Ok(out)
}

/// What a checkpoint file holds: an MPM run's [`Checkpoint`] or the cell run driver's,
/// in the same file format, directory and rotation.
pub trait Saved: Serialize + serde::de::DeserializeOwned {
    /// The step the state is at the end of (names the file).
    fn step(&self) -> u64;
}

impl Saved for Checkpoint {
    fn step(&self) -> u64 {
        self.step
    }
}

/// Encodes a checkpoint: header line with length and SHA-256 of the body, then the body.
pub fn encode<T: Saved>(ck: &T) -> Result<Vec<u8>> {
    let body = serde_json::to_vec(ck).context("cannot encode the checkpoint")?;
    let mut out = format!("{MAGIC} {FORMAT_VERSION} bytes={} sha256={}\n", body.len(), hex::encode(Sha256::digest(&body))).into_bytes();
    out.extend_from_slice(&body);
    Ok(out)
}

/// Decodes and verifies a checkpoint file's bytes.
pub fn decode<T: Saved>(bytes: &[u8]) -> Result<T> {
    let nl = bytes.iter().position(|&b| b == b'\n').context("no header line (the file is empty or cut short)")?;
    let header = std::str::from_utf8(&bytes[..nl]).context("the header is not text")?;
    let body = &bytes[nl + 1..];
    let mut words = header.split(' ');
    ensure!(words.next() == Some(MAGIC), "not an mscale checkpoint");
    let version: u32 = words.next().and_then(|v| v.parse().ok()).context("no format version in the header")?;
    ensure!(version == FORMAT_VERSION, "checkpoint format {version}, this build reads {FORMAT_VERSION}");
    let (mut len, mut sum) = (None, None);
    for w in words {
        if let Some(v) = w.strip_prefix("bytes=") {
            len = v.parse::<usize>().ok();
        } else if let Some(v) = w.strip_prefix("sha256=") {
            sum = Some(v.to_string());
        }
    }
    let (len, sum) = (len.context("no length in the header")?, sum.context("no checksum in the header")?);
    ensure!(body.len() == len, "the body has {} bytes, the header says {len} (truncated?)", body.len());
    let actual = hex::encode(Sha256::digest(body));
    ensure!(actual == sum, "checksum mismatch: the header says {sum}, the body hashes to {actual}");
    serde_json::from_slice(body).context("the checksum matches but the body does not decode")
}

/// Writes a checkpoint atomically (temporary file, fsync, rename, fsync of the directory) and
/// removes all but the [`KEEP`] newest. Returns its path.
pub fn write<T: Saved>(run_dir: &Path, ck: &T) -> Result<PathBuf> {
    let dir = dir_of(run_dir);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let path = dir.join(file_name(ck.step()));
    let tmp = crate::atomic::temp_path(&path);
    let start = std::time::Instant::now();
    // The rename reaches the disk (the directory is synced) before older checkpoints are removed.
    let bytes = encode(ck)?;
    crate::atomic::write(&path, &bytes)?;
    let written = Written { step: ck.step(), bytes: bytes.len() as u64, seconds: start.elapsed().as_secs_f64() };
    WRITTEN.lock().unwrap_or_else(|p| p.into_inner()).insert(run_dir.to_path_buf(), written);
    // Temporary files of writers that died (a killed orchestrator) are removed too.
    for e in std::fs::read_dir(&dir).with_context(|| format!("cannot list {}", dir.display()))?.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with(".step-") && name.contains(".tmp") && e.path() != tmp {
            let _ = std::fs::remove_file(e.path());
        }
    }
    for (_, old) in list(run_dir)?.into_iter().skip(KEEP) {
        if let Err(e) = std::fs::remove_file(&old) {
            tracing::warn!("cannot remove the old checkpoint {}: {e}", old.display());
        }
    }
    Ok(path)
}

/// The newest checkpoint this process wrote into a run directory: its step, size and the
/// time to encode and durably write it (the job service's metrics read it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Written {
    pub step: u64,
    pub bytes: u64,
    pub seconds: f64,
}

static WRITTEN: std::sync::Mutex<std::collections::BTreeMap<PathBuf, Written>> = std::sync::Mutex::new(std::collections::BTreeMap::new());

/// What [`write`] last wrote into `run_dir` in this process, if anything.
pub fn last_written(run_dir: &Path) -> Option<Written> {
    WRITTEN.lock().unwrap_or_else(|p| p.into_inner()).get(run_dir).copied()
}

/// Reads the named MD boxes from the checkpoint file `path` when called (a lost worker's boxes,
/// to replay them elsewhere): nothing is kept in memory meanwhile.
pub fn boxes_of(path: PathBuf) -> md_worker::recovery::CheckpointBoxes {
    std::sync::Arc::new(move |ids: &[u64]| {
        let ck = std::fs::read(&path)
            .map_err(anyhow::Error::from)
            .and_then(|b| decode::<Checkpoint>(&b))
            .map_err(|e| format!("{}: {e:#}", path.display()))?;
        let mut saved: std::collections::HashMap<u64, BoxState> =
            ck.md.map(|m| m.boxes).unwrap_or_default().into_iter().map(|b| (b.meta.id, b)).collect();
        ids.iter().map(|id| saved.remove(id).ok_or_else(|| format!("{} holds no box of point {id}", path.display()))).collect()
    })
}

/// The newest checkpoint of a run directory that verifies; a damaged one is logged and the
/// previous one used.
pub fn load_latest<T: Saved>(run_dir: &Path) -> Result<(T, PathBuf)> {
    let all = list(run_dir)?;
    if all.is_empty() {
        bail!("{} has no checkpoint to resume from (looked in {})", run_dir.display(), dir_of(run_dir).display());
    }
    let mut why = Vec::new();
    for (_, path) in all {
        let r = std::fs::read(&path).map_err(anyhow::Error::from).and_then(|b| decode(&b));
        match r {
            Ok(ck) => {
                if !why.is_empty() {
                    tracing::warn!("resuming from the previous checkpoint {}", path.display());
                }
                return Ok((ck, path));
            }
            Err(e) => {
                tracing::warn!("checkpoint {} is damaged and is skipped: {e:#}", path.display());
                why.push(format!("{}: {e:#}", path.display()));
            }
        }
    }
    bail!("no usable checkpoint in {}: {}", dir_of(run_dir).display(), why.join("; "))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        let mut p = Particles::<2>::default();
        p.push(0, [0.1, 0.2], [1.0 / 3.0, -2.5e-300], 1.0, 0.5, [0.05, 0.05], Particles::<2>::identity());
        p.push(1, [0.3, 0.4], [f64::MIN_POSITIVE, 1e300], 2.0, 0.5, [0.05, 0.05], Particles::<2>::identity());
        p.stress[1][0][1] = std::f64::consts::PI;
        Checkpoint {
            scene_sha256: "s".into(),
            dimension: 2,
            step: 7,
            time: 0.1 + 0.2,
            dt: 1e-3 / 3.0,
            closure_evaluations: 14,
            integration_point_updates: 14,
            wall_impulse: vec![1.0 / 7.0, 0.0],
            wall_impulse_magnitude: 1.0 / 7.0,
            initial: SavedTotals { mass: 3.0, momentum: vec![0.1, 0.7], kinetic: 1.0 / 9.0, internal: 0.0 },
            points: SavedPoints::of(&p),
            md: None,
            driver: DriverState::default(),
            implicit: None,
            mesh_velocity: Vec::new(),
        }
    }

    #[test]
    fn every_f64_bit_round_trips() {
        let ck = sample();
        let back: Checkpoint = decode(&encode(&ck).unwrap()).unwrap();
        let (a, b) = (ck.points.to_particles::<2>().unwrap(), back.points.to_particles::<2>().unwrap());
        let bits = |p: &Particles<2>| -> Vec<u64> {
            p.v.iter().flatten().chain(p.stress.iter().flatten().flatten()).chain(&p.volume).map(|v| v.to_bits()).collect()
        };
        assert_eq!(bits(&a), bits(&b));
        assert_eq!(ck.time.to_bits(), back.time.to_bits());
        assert_eq!(ck.dt.to_bits(), back.dt.to_bits());
        assert_eq!(ck.wall_impulse[0].to_bits(), back.wall_impulse[0].to_bits());
    }

    #[test]
    fn damage_is_detected() {
        let bytes = encode(&sample()).unwrap();
        let truncated = &bytes[..bytes.len() - 10];
        assert!(format!("{:#}", decode::<Checkpoint>(truncated).unwrap_err()).contains("truncated"));
        let mut flipped = bytes.clone();
        let k = flipped.len() - 20;
        flipped[k] ^= 0x01;
        assert!(format!("{:#}", decode::<Checkpoint>(&flipped).unwrap_err()).contains("checksum mismatch"));
        assert!(decode::<Checkpoint>(b"").is_err());
    }

    #[test]
    fn keeps_two_and_falls_back_past_a_damaged_one() {
        let dir = tempfile::tempdir().unwrap();
        let mut ck = sample();
        for step in [3, 5, 9] {
            ck.step = step;
            write(dir.path(), &ck).unwrap();
        }
        let steps: Vec<u64> = list(dir.path()).unwrap().into_iter().map(|(s, _)| s).collect();
        assert_eq!(steps, vec![9, 5]);
        let newest = dir_of(dir.path()).join(file_name(9));
        let len = std::fs::metadata(&newest).unwrap().len();
        std::fs::OpenOptions::new().write(true).open(&newest).unwrap().set_len(len / 2).unwrap();
        let (back, path): (Checkpoint, _) = load_latest(dir.path()).unwrap();
        assert_eq!(back.step, 5);
        assert!(path.ends_with(file_name(5)));
    }
}
