//! `mscale run`: one process runs the whole scene (the embedded default), with a progress bar
//! on a terminal and periodic log lines otherwise, and writes every output of a run directory.
//! It checkpoints at an interval and when asked to stop (a flag set by SIGINT/SIGTERM or by the
//! job service), and resumes from the newest good checkpoint of a run directory to the same
//! final state, bit for bit, as a run never stopped (see [`crate::checkpoint`]).

use crate::output::{self, Series};
use crate::scene::{LoadedScene, Material, Reference, Scene};
use crate::{checkpoint, setup};
use anyhow::{Context, Result};
use continuum::Simulation;
use continuum::exact::{IsothermalRiemann, PressureErrors, State};
use coupling::MdShared;
use serde_json::{Value, json};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How a run ended.
pub enum Outcome {
    Completed(Value),
    /// The solver stopped the run (divergence guard, closure failure); outputs so far are kept.
    Failed(Value, String),
    /// Stopped on request at the end of `step`; the state is in `checkpoint`.
    Cancelled {
        checkpoint: PathBuf,
        step: u64,
    },
}

/// Progress of a run after a step (for the job service's watch stream).
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct Progress {
    pub step: u64,
    pub steps: u64,
    /// Simulated time (s).
    pub time: f64,
    pub end_time: f64,
    /// Wall seconds since this session of the run started.
    pub elapsed_s: f64,
    /// Steps done in this session (for the ETA).
    pub session_steps: u64,
    /// |E - E0| / energy scale (as in summary.json).
    pub energy_drift: f64,
    /// Set on the last call (run over, whatever the outcome).
    pub done: bool,
}

/// Called after every step.
pub type ProgressFn = Arc<dyn Fn(&Progress) + Send + Sync>;

/// Given the run's MD state once its pool is open (the job service reads per-worker load).
pub type MdHook = Arc<dyn Fn(&Arc<Mutex<MdShared>>) + Send + Sync>;

pub struct RunOptions {
    pub out: PathBuf,
    pub command_line: Vec<String>,
    /// Draw a progress bar (otherwise log lines every 10 %).
    pub progress_bar: bool,
    /// MD workers (`host:port`); empty runs MD in this process.
    pub workers: Vec<String>,
    /// Write a checkpoint every this many steps (0: only when stopped on request).
    pub checkpoint_every: u64,
    /// Continue from the newest good checkpoint in `out` instead of starting afresh.
    pub resume: bool,
    /// Where a resume reads its checkpoint when not `out` (MPI ranks above 0 write into a
    /// scratch directory but resume from the run's).
    pub resume_from: Option<PathBuf>,
    /// When set (by a signal handler or the job service), the run checkpoints after the current
    /// step and returns [`Outcome::Cancelled`].
    pub cancel: Option<Arc<AtomicBool>>,
    pub progress: Option<ProgressFn>,
    /// Relative throughput of each of `workers` (empty: equal shares): boxes are spread in
    /// proportion to it. The results do not depend on it.
    pub worker_weights: Vec<f64>,
    pub md_hook: Option<MdHook>,
    /// Bound on each call to a remote worker; past it the worker is lost and its boxes are
    /// replayed on the others.
    pub step_deadline: md_worker::recovery::StepDeadline,
    /// Told of every worker lost mid-run once its boxes live on the survivors.
    pub on_worker_lost: Option<LossFn>,
    /// Over MPI ranks: steps between two shares of the tiles by measured cost (0: never;
    /// see `continuum::solver::LoadBalance`).
    pub rebalance_every: u64,
}

/// See [`RunOptions::on_worker_lost`].
pub type LossFn = Arc<dyn Fn(&md_worker::recovery::Recovery) + Send + Sync>;

impl RunOptions {
    pub fn new(out: PathBuf, command_line: Vec<String>) -> Self {
        RunOptions {
            out,
            command_line,
            progress_bar: std::io::stderr().is_terminal(),
            workers: Vec::new(),
            checkpoint_every: 0,
            resume: false,
            resume_from: None,
            cancel: None,
            progress: None,
            worker_weights: Vec::new(),
            md_hook: None,
            step_deadline: Default::default(),
            on_worker_lost: None,
            rebalance_every: continuum::solver::DEFAULT_REBALANCE_EVERY,
        }
    }
}

/// The MD pool of a scene with md bodies (one potential per run), or `None`.
fn md_shared(loaded: &LoadedScene, opts: &RunOptions) -> Result<Option<Arc<Mutex<MdShared>>>> {
    let (workers, weights) = (&opts.workers, &opts.worker_weights);
    let mut potentials = loaded.resolved.md_bodies().map(|(_, m)| m.potential.clone());
    let Some(first) = potentials.next() else { return Ok(None) };
    if let Some(other) = potentials.find(|p| *p != first) {
        anyhow::bail!("all md bodies of a run must share one potential; found {} and {}", first.display(), other.display());
    }
    let potential = md_worker::pool::PotentialSource::from_file(&first)?;
    // Over MPI continuum ranks (continuum/README.md "MPI") the MD closures are computed once,
    // by rank 0 (`Closure::computed_once`): rank 0 drives the pool (in-process or the
    // workers); the other ranks' closures are never called and stand over a `null` pool (no
    // atoms, no MD work, no connection), which still takes their checkpoints and resumes.
    if continuum::par::exchange().is_some_and(|e| e.size() > 1 && e.rank() > 0) {
        let pool = md_worker::pool::MdPool::new(vec![Box::new(md_worker::pool::InProcess::new("null", None))])?;
        return Ok(Some(Arc::new(Mutex::new(MdShared::new(pool, potential)))));
    }
    let mut pool = crate::md::pool(workers)?;
    if !weights.is_empty() {
        pool.set_weights(weights.to_vec())?;
    }
    pool.set_deadline(opts.step_deadline);
    let told = opts.on_worker_lost.clone();
    pool.set_loss_hook(Box::new(move |r: &md_worker::recovery::Recovery| {
        tracing::warn!("MD {r}");
        if let Some(f) = &told {
            f(r);
        }
    }));
    tracing::info!("MD on {}", pool.endpoint_names().join(", "));
    Ok(Some(Arc::new(Mutex::new(MdShared::new(pool, potential)))))
}

/// Default run directory: `runs/<scene>-<UTC timestamp>`.
pub fn default_out_dir(scene: &Scene) -> PathBuf {
    default_out_dir_named(&scene.name)
}

/// `runs/<name>-<UTC timestamp>`.
pub fn default_out_dir_named(name: &str) -> PathBuf {
    let t = time::OffsetDateTime::now_utc();
    PathBuf::from("runs").join(format!(
        "{}-{:04}{:02}{:02}T{:02}{:02}{:02}Z",
        name,
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second()
    ))
}

pub fn run(loaded: &LoadedScene, opts: &RunOptions) -> Result<Outcome> {
    match loaded.scene.domain.dimension {
        1 => run_dim::<1>(loaded, opts),
        2 => run_dim::<2>(loaded, opts),
        _ => run_dim::<3>(loaded, opts),
    }
}

/// The exact solution a scene names, if any, as (solution, pressure jump in Pa).
fn reference(scene: &Scene) -> Option<(IsothermalRiemann, f64)> {
    let Some(Reference::IsothermalRiemann(r)) = scene.reference.as_ref() else { return None };
    let state = |name: &str| {
        let b = scene.bodies.get(name)?;
        let Material::IdealGasIsothermal(g) = &b.material else { return None };
        let j0: f64 = b.initial_strain.iter().map(|e| 1.0 + e).product();
        Some((State { density: b.density / j0, velocity: b.velocity[0] }, g.sound_speed, b.max[0]))
    };
    let (left, c, x0) = state(&r.left)?;
    let (right, _, _) = state(&r.right)?;
    Some((IsothermalRiemann::new(left, right, c, x0), c * c * (left.density - right.density).abs()))
}

/// The thin-film scorer of a scene with `[reference] solution = "thin-film-lithiation"`.
fn thin_film<const D: usize>(loaded: &LoadedScene, sim: &Simulation<D>) -> Option<crate::reference::ThinFilmError> {
    let Some(Reference::ThinFilmLithiation(r)) = &loaded.scene.reference else { return None };
    let index = loaded.resolved.bodies.iter().position(|b| b.name == r.body)?;
    let body = &loaded.resolved.bodies[index];
    let crate::scene::Law::HypoelasticPlastic(law) = &body.law else { return None };
    let points = sim.points.body_ranges().get(index)?.clone();
    Some(crate::reference::ThinFilmError::new(*law, points, body.lithiation.map_or(0.0, |l| l.0)))
}

/// The quasi-static check of a run with a scaled density or a lithiated body (None otherwise).
fn quasi_static(loaded: &LoadedScene) -> Option<crate::reference::QuasiStatic> {
    let r = &loaded.resolved;
    let lithiated = r.bodies.iter().any(|b| b.lithiation.is_some()) || r.diffusion.is_some();
    if r.density_scaling == 1.0 && !lithiated {
        return None;
    }
    use crate::scene::Law;
    let iso = |e: f64, nu: f64| (e / (3.0 * (1.0 - 2.0 * nu)), e / (2.0 * (1.0 + nu)));
    let moduli: Vec<Option<(f64, f64)>> = r
        .bodies
        .iter()
        .map(|b| match &b.law {
            Law::LinearElastic { youngs_modulus, poisson_ratio } | Law::NeoHookean { youngs_modulus, poisson_ratio } => {
                Some(iso(*youngs_modulus, *poisson_ratio))
            }
            Law::HypoelasticPlastic(m) => Some((m.bulk_modulus, m.shear_modulus)),
            _ => None,
        })
        .collect();
    // The transit of the largest body at the scaled density, and the process time: the run's
    // (a prescribed lithiation), or L^2 / D of the diffusion if that is longer.
    let mut transit: f64 = 0.0;
    let mut length: f64 = 0.0;
    for (b, m) in r.bodies.iter().zip(&moduli) {
        let Some((k, g)) = m else { continue };
        let l = b.min.iter().zip(&b.max).map(|(lo, hi)| hi - lo).fold(0.0, f64::max);
        length = length.max(l);
        transit = transit.max(l / ((k + 4.0 * g / 3.0) / b.density).sqrt());
    }
    let mut process = loaded.scene.scheme.end_time;
    if let Some(d) = &r.diffusion {
        process = process.max(length * length / d.diffusivity);
    }
    let mut qs = crate::reference::QuasiStatic::new(r.density_scaling, moduli, transit, process);
    // A ramped lithiation: the start-up ends 10 transits after the ramp.
    qs.score_after_s += r.bodies.iter().map(|b| b.lithiation_ramp).fold(0.0, f64::max);
    Some(qs)
}

/// summary.json `errors` of a `heat-series` reference: the RMS of the points' values against
/// the series at the end (B 6.95 in 1D, 6.98 in 2D; 6.97 with its square), and the same at the
/// nodes of the last step: over every node with capacity (`rms_nodes`) and over those off the
/// Dirichlet faces (`rms_interior_nodes`, the nodes the scheme computes; with `value`
/// Dirichlet the face nodes hold the exact value).
fn heat_series_errors<const D: usize>(loaded: &LoadedScene, sim: &Simulation<D>) -> Option<Value> {
    let Some(Reference::HeatSeries(r)) = &loaded.scene.reference else { return None };
    let d = loaded.resolved.diffusion.as_ref()?;
    let value = |f: Option<continuum::diffusion::FaceCondition>| match f {
        Some(continuum::diffusion::FaceCondition::Dirichlet(v)) => v,
        _ => 0.0,
    };
    let (lo, hi) = (sim.grid.origin, sim.grid.extent_max());
    let (cl, cr) = (value(d.faces[0].0), value(d.faces[0].1));
    // The validator allows 1D and 2D (D - 1 is axis 1 in 2D; the index stays in range for any D).
    let exact = |x: &[f64; D]| match D {
        1 => continuum::diffusion::heat_series(x[0] - lo[0], sim.time, hi[0] - lo[0], d.diffusivity, (r.initial, cl, cr), 4000),
        _ => continuum::diffusion::heat_series_2d(
            [x[0] - lo[0], x[D - 1] - lo[D - 1]],
            sim.time,
            [hi[0] - lo[0], hi[D - 1] - lo[D - 1]],
            d.diffusivity,
            (r.initial, cl),
            4001,
        ),
    };
    let pts = &sim.points;
    let rms =
        |pairs: Vec<([f64; D], f64)>| (pairs.iter().map(|(x, c)| (c - exact(x)).powi(2)).sum::<f64>() / pairs.len().max(1) as f64).sqrt();
    let particles = rms((0..pts.len()).map(|p| (pts.x[p], pts.scalar.get(p).copied().unwrap_or(f64::NAN))).collect());
    let on_face = |idx: [usize; D]| (0..D).any(|a| idx[a] == 0 || idx[a] == sim.grid.cells[a]);
    let nodes = |interior: bool| {
        sim.diffusion.as_ref().map(|df| {
            rms((0..df.node_value.len())
                .filter(|&i| df.node_capacity[i] > 0.0 && !(interior && on_face(sim.grid.unlinear(i))))
                .map(|i| (sim.grid.node_position(sim.grid.unlinear(i)), df.node_value[i]))
                .collect())
        })
    };
    let (all_nodes, interior_nodes) = (nodes(false), nodes(true));
    let num = |v: f64| if v.is_finite() { json!(v) } else { Value::Null };
    tracing::info!(
        "heat-series RMS at t = {:e} s: points {particles:.6}, nodes {:.6}, interior nodes {:.6}",
        sim.time,
        all_nodes.unwrap_or(f64::NAN),
        interior_nodes.unwrap_or(f64::NAN)
    );
    Some(json!({
        "reference": "heat-series",
        "measure": "sqrt(mean (c - c_exact)^2) at the end, c_exact the Fourier series (battery thesis 6.95 in 1D, 6.98 in 2D; 6.97 with its square)",
        "time_s": sim.time,
        "flip_fraction": d.flip,
        "dirichlet": format!("{:?}", d.dirichlet).to_lowercase(),
        "rms_points": num(particles),
        "rms_nodes": all_nodes.map(num),
        "rms_interior_nodes": interior_nodes.map(num),
        "content_change": sim.diffusion.as_ref().map(|df| num(df.active_content(pts) - df.initial_content)),
        "boundary_content": sim.diffusion.as_ref().map(|df| num(df.boundary_content)),
        "explicit_bound_s": d.bound,
    }))
}

/// summary.json `diffusion` of a run with `[diffusion]`: the content of the points that carry
/// the field against the boundary source (exact conservation: the content changes by exactly
/// what the faces and surfaces added; both counted from the start of this session, a resumed
/// run from its checkpoint), and the concentration range.
fn diffusion_json<const D: usize>(sim: &Simulation<D>) -> Option<Value> {
    let df = sim.diffusion.as_ref()?;
    let pts = &sim.points;
    let content = df.active_content(pts);
    let change = content - df.initial_content;
    let active: Vec<f64> = (0..pts.len()).filter(|&p| df.active.get(p).copied().unwrap_or(true)).map(|p| pts.scalar[p]).collect();
    let num = |v: f64| if v.is_finite() { json!(v) } else { Value::Null };
    Some(json!({
        "content": num(content),
        "initial_content": num(df.initial_content),
        "content_change": num(change),
        "boundary_content": num(df.boundary_content),
        "conservation_error": num(change - df.boundary_content),
        "relative_conservation_error": num((change - df.boundary_content) / df.boundary_content.abs().max(content.abs()).max(f64::MIN_POSITIVE)),
        "concentration_max": num(active.iter().cloned().fold(f64::NEG_INFINITY, f64::max)),
        "concentration_mean": num(active.iter().sum::<f64>() / active.len().max(1) as f64),
        "configuration": format!("{:?}", df.configuration).to_lowercase(),
    }))
}

struct Snapshots {
    index: String,
    pvd: Vec<(f64, String)>,
}

/// Per-point MD columns of the particle files (empty without MD).
fn md_columns(md: Option<&Arc<Mutex<MdShared>>>, n: usize) -> Vec<(&'static str, Vec<f64>)> {
    let Some(m) = md.and_then(|m| m.lock().ok()) else { return Vec::new() };
    let col = |f: &dyn Fn(&coupling::MdPointState) -> f64| {
        (0..n).map(|p| m.points.get(p).and_then(|s| s.as_ref()).map_or(f64::NAN, f)).collect::<Vec<_>>()
    };
    vec![
        ("md_temperature_k", col(&|s| s.last.temperature_k)),
        ("md_potential_ev", col(&|s| s.last.potential_energy_ev)),
        ("md_kinetic_ev", col(&|s| s.last.kinetic_energy_ev)),
        ("md_energy_added_ev", col(&|s| s.added_ev)),
    ]
}

/// The extra columns of the particle files: the optional fields, then the MD columns.
fn columns<const D: usize>(pts: &continuum::Particles<D>, md: Option<&Arc<Mutex<MdShared>>>) -> Vec<(&'static str, Vec<f64>)> {
    let mut cols = output::field_columns(pts);
    cols.extend(md_columns(md, pts.len()));
    cols
}

/// `output.dump_points`: one LAMMPS text dump frame per chosen box (atoms as the pool's
/// snapshot has them, in-process or remote) appended to `boxes/point-<id>.dump`; the frame's
/// timestep is the continuum step of the snapshot (as in `snapshots/index.csv`).
fn dump_boxes(md: &Arc<Mutex<MdShared>>, ids: &[u64], step: u64, dir: &Path) -> Result<()> {
    let states = {
        let mut m = md.lock().map_err(|_| anyhow::anyhow!("MD state poisoned"))?;
        m.pool.snapshot(ids).context("cannot snapshot the MD boxes to dump")?
    };
    for s in states {
        let atom_ids: Vec<u64> = (1..=s.x.len() as u64).collect();
        let types: Vec<u32> = s.types.iter().map(|t| t + 1).collect();
        let frame = md_worker::data::dump_frame(step, s.meta.lo, s.meta.l, &atom_ids, &types, &s.x, &s.v);
        output::append_dump_frame(&dir.join("boxes").join(format!("point-{}.dump", s.meta.id)), step, &frame)?;
    }
    Ok(())
}

fn write_snapshot<const D: usize>(
    sim: &Simulation<D>,
    scene: &Scene,
    dir: &Path,
    snaps: &mut Snapshots,
    md: Option<&Arc<Mutex<MdShared>>>,
) -> Result<()> {
    let step = sim.step;
    if scene.output.particles {
        let file = format!("particles_{step:08}.csv");
        output::write_atomic(&dir.join("snapshots").join(&file), output::particles_csv(&sim.points, &columns(&sim.points, md)).as_bytes())?;
        snaps.index.push_str(&format!("{step},{:e},{file}\n", sim.time));
        output::write_atomic(&dir.join("snapshots/index.csv"), snaps.index.as_bytes())?;
    }
    if !scene.output.dump_points.is_empty()
        && let Some(md) = md
    {
        dump_boxes(md, &scene.output.dump_points, step, dir)?;
    }
    if scene.output.vtk {
        let file = format!("particles_{step:08}.vtu");
        output::write_atomic(&dir.join("vtk").join(&file), output::particles_vtu(&sim.points).as_bytes())?;
        snaps.pvd.push((sim.time, file));
        output::write_atomic(&dir.join("vtk/particles.pvd"), output::pvd(&snaps.pvd).as_bytes())?;
    }
    Ok(())
}

fn run_dim<const D: usize>(loaded: &LoadedScene, opts: &RunOptions) -> Result<Outcome> {
    let scene = &loaded.scene;
    let dir = &opts.out;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create the run directory {}", dir.display()))?;
    let resolved = scene.to_toml();
    let scene_sha = checkpoint::scene_sha256(&resolved);
    // A resumed run reads its checkpoint before anything in the directory is rewritten.
    let saved = if opts.resume {
        Some(checkpoint::load_latest::<checkpoint::Checkpoint>(opts.resume_from.as_deref().unwrap_or(dir))?)
    } else {
        None
    };
    if let Some((ck, path)) = &saved {
        anyhow::ensure!(
            ck.scene_sha256 == scene_sha,
            "the checkpoint {} was written for another scene (or other --set overrides) than the one given",
            path.display()
        );
    }
    output::write_atomic(&dir.join("scene.resolved.toml"), resolved.as_bytes())?;
    let wall = Instant::now();
    let md = md_shared(loaded, opts)?;
    if let (Some(hook), Some(m)) = (&opts.md_hook, &md) {
        hook(m);
    }
    let mut sim = setup::simulation::<D>(&loaded.resolved, md.as_ref())?;
    sim.balance.every = opts.rebalance_every;
    let mut before = checkpoint::DriverState::default();
    if let Some((ck, path)) = &saved {
        let mut guard = md.as_ref().map(|m| m.lock()).transpose().map_err(|_| anyhow::anyhow!("MD state poisoned"))?;
        ck.restore_into(&mut sim, guard.as_deref_mut()).with_context(|| format!("cannot resume from {}", path.display()))?;
        if let Some(m) = guard.as_deref_mut() {
            m.pool.mark_checkpoint(ck.step, checkpoint::boxes_of(path.clone()));
        }
        before = ck.driver.clone();
        tracing::info!("resuming {} at step {} (t = {:e} s) from {}", scene.name, ck.step, ck.time, path.display());
    }
    let setup_s = before.setup_s + wall.elapsed().as_secs_f64();
    // The MD of setup (relaxation, initial stresses) counts as setup, not as step time.
    if let Some(m) = &md
        && let Ok(mut m) = m.lock()
    {
        m.pool.times = Default::default();
    }
    tracing::info!(points = sim.points.len(), nodes = sim.grid.node_count(), steps = loaded.steps, dt = sim.dt, "running {}", scene.name);

    let every = (loaded.steps / scene.output.snapshots.max(1) as u64).max(1);
    // A direct-MD reference is scored from the snapshots: one lands on the step nearest to each
    // of its times.
    let reference_steps: Vec<u64> = match &scene.reference {
        Some(Reference::DirectMd(r)) => {
            r.times_ps.iter().map(|t| ((t * 1e-12 / loaded.dt).round().max(0.0) as u64).min(loaded.steps)).collect()
        }
        _ => Vec::new(),
    };
    let checkpoint_every = if opts.checkpoint_every > 0 { opts.checkpoint_every } else { scene.output.checkpoint_every_steps };
    let mut snaps = Snapshots { index: "step,time,file\n".into(), pvd: Vec::new() };
    let mut output_s = before.output_s;
    let (mut max_kinetic, mut max_abs_momentum) = (sim.initial.kinetic.abs(), sim.step_totals().1);
    if saved.is_some() {
        snaps = Snapshots { index: before.snapshot_index.clone(), pvd: before.pvd.clone() };
        (max_kinetic, max_abs_momentum) = (before.max_kinetic, before.max_abs_momentum);
    } else {
        let t = Instant::now();
        write_snapshot(&sim, scene, dir, &mut snaps, md.as_ref())?;
        output_s += t.elapsed().as_secs_f64();
    }

    let bar = progress_bar(opts.progress_bar, loaded.steps, scene.scheme.end_time);
    if let Some(b) = &bar {
        b.set_position(sim.step);
    }
    let mut continuum_s = before.continuum_s;
    let mut last_log = Instant::now();
    let mut failure = None;
    let (session_start, first_step) = (Instant::now(), sim.step);
    // Over MPI ranks (continuum/README.md "MPI") a stop asked of any rank stops all of them
    // after the same step (mpirun hands a signal to each rank at its own moment).
    let cancelled = || {
        let mine = opts.cancel.as_ref().is_some_and(|c| c.load(Ordering::SeqCst));
        match continuum::par::exchange().filter(|e| e.size() > 1) {
            Some(ex) => ex.all_gather_bytes(&[u8::from(mine)]).iter().any(|b| b.first() == Some(&1)),
            None => mine,
        }
    };
    let save = |sim: &Simulation<D>,
                snaps: &Snapshots,
                max_kinetic: f64,
                max_abs_momentum: f64,
                continuum_s: f64,
                output_s: f64|
     -> Result<PathBuf> {
        let driver = checkpoint::DriverState {
            max_kinetic,
            max_abs_momentum,
            snapshot_index: snaps.index.clone(),
            pvd: snaps.pvd.clone(),
            wall_s: before.wall_s + wall.elapsed().as_secs_f64(),
            setup_s,
            continuum_s,
            output_s,
        };
        let mut guard = md.as_ref().map(|m| m.lock()).transpose().map_err(|_| anyhow::anyhow!("MD state poisoned"))?;
        let ck = checkpoint::Checkpoint::capture(sim, &scene_sha, guard.as_deref_mut(), driver)?;
        let path = checkpoint::write(dir, &ck)?;
        // The input log of the MD boxes starts again from this checkpoint.
        if let Some(m) = guard.as_deref_mut() {
            m.pool.mark_checkpoint(sim.step, checkpoint::boxes_of(path.clone()));
        }
        tracing::debug!("checkpoint at step {} in {}", sim.step, path.display());
        Ok(path)
    };
    let mut film = thin_film(loaded, &sim);
    let mut quasi = quasi_static(loaded);
    // Adaptive implicit steps run to the end time (the step count is only the estimate of the
    // first dt); snapshots fall on the first step past each of the evenly spaced times.
    let adaptive = sim.implicit.options.adaptive.is_some();
    let end_time = scene.scheme.end_time;
    let snapshot_dt = end_time / scene.output.snapshots.max(1) as f64;
    let mut next_snapshot = (sim.time / snapshot_dt).floor() + 1.0;
    let running = |sim: &Simulation<D>| if adaptive { sim.time < end_time * (1.0 - 1e-12) } else { sim.step < loaded.steps };
    while running(&sim) {
        if cancelled() {
            if let Some(b) = &bar {
                b.abandon();
            }
            let t = Instant::now();
            sim.share_all();
            let path = save(&sim, &snaps, max_kinetic, max_abs_momentum, continuum_s, output_s + t.elapsed().as_secs_f64())?;
            report_progress(opts, &sim, loaded, session_start, first_step, max_kinetic, true);
            return Ok(Outcome::Cancelled { checkpoint: path, step: sim.step });
        }
        let t = Instant::now();
        let result = sim.step();
        continuum_s += t.elapsed().as_secs_f64();
        if let Err(e) = result {
            failure = Some(crate::exit::message(&e));
            break;
        }
        // Over MPI ranks (split steps) each rank holds the whole state of its own points only;
        // whatever reads more than positions, velocities and energies of every point shares it
        // first (every rank at the same step: `share_all` is a collective).
        if film.is_some() || quasi.is_some() {
            sim.share_all();
        }
        if let Some(f) = film.as_mut() {
            f.observe(&sim);
        }
        if let Some(q) = quasi.as_mut() {
            q.observe(&sim);
        }
        // Over MPI ranks the split step's end gathered these (other ranks' points are stale).
        let (totals, scale) = sim.step_totals();
        max_kinetic = max_kinetic.max(totals.kinetic);
        max_abs_momentum = max_abs_momentum.max(scale);
        let snapshot_due = if adaptive {
            let due = sim.time >= next_snapshot * snapshot_dt * (1.0 - 1e-12) && running(&sim);
            if due {
                next_snapshot = (sim.time / snapshot_dt * (1.0 + 1e-12)).floor() + 1.0;
            }
            due
        } else {
            (sim.step % every == 0 || reference_steps.contains(&sim.step)) && sim.step < loaded.steps
        };
        if snapshot_due {
            let t = Instant::now();
            sim.share_all();
            write_snapshot(&sim, scene, dir, &mut snaps, md.as_ref())?;
            output_s += t.elapsed().as_secs_f64();
        }
        if checkpoint_every > 0 && sim.step % checkpoint_every == 0 && sim.step < loaded.steps {
            let t = Instant::now();
            sim.share_all();
            save(&sim, &snaps, max_kinetic, max_abs_momentum, continuum_s, output_s)?;
            output_s += t.elapsed().as_secs_f64();
        }
        report_progress(opts, &sim, loaded, session_start, first_step, max_kinetic, false);
        match &bar {
            Some(b) => {
                if adaptive && sim.time > 0.0 {
                    // The length is the step count the run is heading for at the current pace.
                    b.set_length(sim.step.max((sim.step as f64 * end_time / sim.time).ceil() as u64));
                }
                b.set_position(sim.step);
                b.set_message(match sim.integrator {
                    continuum::solver::TimeIntegrator::ImplicitTrapezoidal => {
                        let st = &sim.implicit.stats;
                        format!(
                            "t = {:.4e} s  dt = {:.3e} s  Newton {} it/step  accepted {} rejected {}",
                            sim.time,
                            st.last_dt,
                            st.last_residual_history.len().saturating_sub(1),
                            st.accepted_steps,
                            st.rejected_steps
                        )
                    }
                    _ => format!("t = {:.4e} s", sim.time),
                });
            }
            None if last_log.elapsed() > Duration::from_secs(5) || sim.step == loaded.steps => {
                last_log = Instant::now();
                tracing::info!(
                    "step {}/{} ({:.0} % of the end time), t = {:.4e} s",
                    sim.step,
                    loaded.steps,
                    100.0 * sim.time / end_time,
                    sim.time
                );
            }
            None => {}
        }
    }
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let t = Instant::now();
    sim.share_all();
    if failure.is_none() {
        write_snapshot(&sim, scene, dir, &mut snaps, md.as_ref())?;
    }
    if scene.output.particles {
        output::write_atomic(
            &dir.join("particles_final.csv"),
            output::particles_csv(&sim.points, &columns(&sim.points, md.as_ref())).as_bytes(),
        )?;
    }
    let reference = reference(scene);
    let errors = reference.as_ref().map(|(rp, jump)| pressure_errors(&sim, rp, *jump));
    let direct = direct_md_errors(scene, dir, sim.time + 0.5 * sim.dt);
    if D == 1 && scene.output.plots {
        plot_profiles(&sim, reference.as_ref().map(|r| &r.0), dir)?;
    }
    output_s += t.elapsed().as_secs_f64();

    let times =
        SummaryTimes { wall: before.wall_s + wall.elapsed().as_secs_f64(), setup: setup_s, continuum: continuum_s, output: output_s };
    let direct_json = direct
        .as_ref()
        .map(|d| d.json.clone())
        .or_else(|| manufactured_errors(loaded, &sim))
        .or_else(|| vibrating_bar_errors(loaded, &sim))
        .or(film.as_ref().map(|f| f.json()))
        .or_else(|| heat_series_errors(loaded, &sim));
    if let Some(f) = &film {
        tracing::info!("{}", f.log_line());
    }
    let mut summary =
        summary(loaded, opts, &sim, times, max_kinetic, max_abs_momentum, errors, direct_json, failure.as_deref(), md.as_ref())?;
    if let Some(q) = &quasi {
        summary["quasi_static"] = q.json();
    }
    if let Some(d) = diffusion_json(&sim) {
        summary["diffusion"] = d;
    }
    output::write_atomic(&dir.join("summary.json"), serde_json::to_string_pretty(&summary)?.as_bytes())?;
    report_progress(opts, &sim, loaded, session_start, first_step, max_kinetic, true);
    if let Some(done) = summary["md"]["atom_steps_done"].as_f64() {
        let requested = summary["md"]["atom_steps_requested"].as_f64().unwrap_or(done);
        tracing::info!("MD atom-steps: {done:.3e} done of {requested:.3e} ({:.3e} avoided by reuse)", requested - done);
        let d = &summary["md"]["diagnostics"];
        if let (Some(t), Some(p)) = (d["max_box_temperature_k"].as_f64(), d["hottest_box_point"].as_u64()) {
            tracing::info!("hottest MD box: point {p} at {t:.0} K (summary.json md.diagnostics)");
        }
    }
    // The run's last log line: its error against the direct MD.
    match direct.map(|d| d.line) {
        Some(Ok(line)) => tracing::info!("{line}"),
        Some(Err(why)) => tracing::warn!("{why}"),
        None => {}
    }
    Ok(match failure {
        None => Outcome::Completed(summary),
        Some(e) => Outcome::Failed(summary, e),
    })
}

fn report_progress<const D: usize>(
    opts: &RunOptions,
    sim: &Simulation<D>,
    loaded: &LoadedScene,
    session_start: Instant,
    first_step: u64,
    max_kinetic: f64,
    done: bool,
) {
    let Some(f) = &opts.progress else { return };
    let (init, now) = (sim.initial, sim.step_totals().0);
    let energy_scale = init.energy().abs().max(max_kinetic).max(f64::MIN_POSITIVE);
    f(&Progress {
        step: sim.step,
        steps: loaded.steps,
        time: sim.time,
        end_time: loaded.scene.scheme.end_time,
        elapsed_s: session_start.elapsed().as_secs_f64(),
        session_steps: sim.step - first_step,
        energy_drift: (now.energy() - init.energy()).abs() / energy_scale,
        done,
    });
}

pub(crate) fn progress_bar(enabled: bool, steps: u64, end_time: f64) -> Option<indicatif::ProgressBar> {
    if !enabled {
        return None;
    }
    let bar = indicatif::ProgressBar::new(steps);
    let style = indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:40} step {pos}/{len}  {msg}  ETA {eta}")
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(format!("t = 0 / {end_time:e} s"));
    Some(bar)
}

/// summary.json `errors` of a run against its scene's manufactured solution: the L2 errors of
/// displacement, velocity and stress at the time reached (a run stopped by the guard is scored
/// where it stopped, with `time_s` saying when).
fn manufactured_errors<const D: usize>(loaded: &LoadedScene, sim: &Simulation<D>) -> Option<Value> {
    let m = loaded.resolved.manufactured?;
    let e = m.errors(&sim.points, sim.time, sim.velocity_time());
    Some(json!({
        "reference": "manufactured",
        "amplitude": m.amplitude,
        "time_s": sim.time,
        "velocity_time_s": sim.velocity_time(),
        "measure": "sqrt(sum_p V0_p |q_p - q(X_p, t)|^2), one-point quadrature over the reference domains (Gong 4.40); stress over the in-plane components",
        "displacement_l2": finite_or_null(e.displacement_l2),
        "velocity_l2": finite_or_null(e.velocity_l2),
        "stress_l2": finite_or_null(e.stress_l2),
    }))
}

/// summary.json `errors` of a run against the vibrating bar: as [`manufactured_errors`]
/// (`reference` = "manufactured", so reports tabulate both alike; `solution` tells them apart).
fn vibrating_bar_errors<const D: usize>(loaded: &LoadedScene, sim: &Simulation<D>) -> Option<Value> {
    let m = loaded.resolved.vibrating_bar?;
    let e = m.errors(&sim.points, sim.time, sim.velocity_time());
    Some(json!({
        "reference": "manufactured",
        "solution": "vibrating-bar",
        "amplitude": m.amplitude,
        "time_s": sim.time,
        "velocity_time_s": sim.velocity_time(),
        "measure": "sqrt(sum_p V0_p |q_p - q(X_p, t)|^2), one-point quadrature over the reference domains (Gong 4.40); stress sigma_xx",
        "displacement_l2": finite_or_null(e.displacement_l2),
        "velocity_l2": finite_or_null(e.velocity_l2),
        "stress_l2": finite_or_null(e.stress_l2),
    }))
}

fn pressure_errors<const D: usize>(sim: &Simulation<D>, rp: &IsothermalRiemann, jump: f64) -> PressureErrors {
    let x: Vec<f64> = sim.points.x.iter().map(|x| x[0]).collect();
    let p: Vec<f64> = (0..sim.points.len()).map(|k| sim.points.pressure(k)).collect();
    continuum::exact::pressure_errors(&x, &p, |xk| rp.pressure(xk, sim.time), jump, sim.grid.h[0])
}

fn plot_profiles<const D: usize>(sim: &Simulation<D>, exact: Option<&IsothermalRiemann>, dir: &Path) -> Result<()> {
    let pts = &sim.points;
    let (x0, x1) = (sim.grid.origin[0], sim.grid.extent_max()[0]);
    let field = |f: &dyn Fn(usize) -> f64| (0..pts.len()).map(|k| (pts.x[k][0], f(k))).collect::<Vec<_>>();
    let exact_line = |f: &dyn Fn(State) -> f64| {
        exact.map(|rp| (0..=2000).map(|i| x0 + (x1 - x0) * i as f64 / 2000.0).map(|x| (x, f(rp.sample(x, sim.time)))).collect::<Vec<_>>())
    };
    let c2 = exact.map(|r| r.sound_speed * r.sound_speed).unwrap_or(0.0);
    let title = |q: &str| format!("{q} at t = {:.4e} s (step {})", sim.time, sim.step);
    let plots: [(&str, &str, Vec<(f64, f64)>, Option<Vec<(f64, f64)>>); 3] = [
        ("pressure", "pressure (Pa)", field(&|k| pts.pressure(k)), exact_line(&|s| c2 * s.density)),
        ("velocity", "velocity (m/s)", field(&|k| pts.v[k][0]), exact_line(&|s| s.velocity)),
        ("density", "density (kg/m^3)", field(&|k| pts.density(k)), exact_line(&|s| s.density)),
    ];
    for (name, ylabel, particles, exact) in plots {
        let mut series = vec![Series { label: "particles", points: particles, line: false }];
        if let Some(e) = exact {
            series.push(Series { label: "exact", points: e, line: true });
        }
        output::plot_profile(&dir.join("plots").join(format!("{name}.png")), &title(name), "x (m)", ylabel, &series)?;
    }
    Ok(())
}

/// Scores a finished run again (`mscale report score RUN_DIR`): eq. 7.12 of the run in `dir`
/// against `scene`'s direct-MD reference (typically the run's own `scene.resolved.toml` with
/// `--set reference.profile=...` / `reference.times_ps=[...]`), from the snapshots the run
/// wrote, up to the time its summary.json says it reached. The same code as the run's own
/// score; the run directory is not changed. Returns summary.json-style `errors` and the log line.
pub fn rescore(scene: &Scene, dir: &Path) -> Result<(Value, String)> {
    let path = dir.join("summary.json");
    let summary: Value = serde_json::from_str(&std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?)
        .with_context(|| format!("{} is not JSON", path.display()))?;
    let reached = summary["simulated_time_s"]
        .as_f64()
        .ok_or_else(|| anyhow::anyhow!("{} has no simulated_time_s: not a finished run's summary", path.display()))?;
    // The run's last step lands within round-off of its end time.
    let score = direct_md_errors(scene, dir, reached * (1.0 + 1e-9))
        .ok_or_else(|| anyhow::anyhow!("the scene names no `[reference] solution = \"direct-md\"` to score against"))?;
    let line = score.line.map_err(|e| anyhow::anyhow!(e))?;
    Ok((score.json, line))
}

/// A run's score against its scene's direct-MD reference: summary.json `errors`, and the log
/// line (or why it could not be scored).
struct DirectScore {
    json: Value,
    line: Result<String, String>,
}

/// eq. 7.12 of the run in `dir` against the scene's direct-MD reference at each of its times
/// up to `reached` (s; a failed run leaves the later ones out), from the snapshots written.
fn direct_md_errors(scene: &Scene, dir: &Path, reached: f64) -> Option<DirectScore> {
    let Some(Reference::DirectMd(r)) = &scene.reference else { return None };
    let times: Vec<f64> = r.times_ps.iter().map(|t| t * 1e-12).filter(|t| *t <= reached).collect();
    // A 2D profile scores particles where they are; a 1D one maps them to the reference bar.
    let scored = crate::reference::DirectProfile::read_component(&r.profile, r.component.as_str())
        .and_then(|profile| {
            let map = if profile.is_2d() { None } else { Some(crate::reference::ReferenceMap::of(scene)?) };
            Ok((profile, map))
        })
        .and_then(|(profile, map)| {
            Ok((crate::reference::score_run(&profile, r.component.as_str(), &times, map.as_ref(), dir)?, profile.is_2d()))
        });
    Some(match scored {
        Ok((scores, two_d)) => {
            let mut json = crate::reference::direct_md_errors_json(&r.profile, r.component.as_str(), &scores, two_d);
            if times.len() < r.times_ps.len() {
                json["not_reached_ps"] = json!(r.times_ps.iter().filter(|t| **t * 1e-12 > reached).collect::<Vec<_>>());
            }
            let line = if scores.is_empty() {
                Err(format!("the run ended at t = {reached:e} s, before every time of its direct-MD reference: not scored"))
            } else {
                Ok(crate::reference::direct_md_log_line(r.component.as_str(), &scores))
            };
            DirectScore { json, line }
        }
        Err(e) => {
            let why = format!("cannot score the run against its direct-MD reference {}: {e:#}", r.profile.display());
            DirectScore {
                json: json!({"reference": "direct-md", "profile": r.profile.display().to_string(), "component": r.component.as_str(), "failure": why}),
                line: Err(why),
            }
        }
    })
}

/// summary.json `md`: MD atom-steps done and avoided per md body (relaxation included in
/// both: `requested` is what `reuse = "off"` would have done), and the extremes the boxes saw.
fn md_cost_json(m: &MdShared) -> Value {
    let mut total = (0.0, 0.0, 0.0, 0.0);
    let bodies: serde_json::Map<String, Value> = m
        .bodies
        .iter()
        .map(|b| {
            let atoms = b.atoms_per_box as f64;
            let relax = (b.boxes as u64 * b.relax_steps) as f64 * atoms;
            let done_steps: u64 = (b.first..b.first + b.boxes).map(|id| m.pool.md_steps_done(id as u64)).sum();
            let requested = relax + b.requested_md_steps as f64 * atoms;
            let done = relax + done_steps as f64 * atoms;
            let by_tolerance = b.skipped_md_steps as f64 * atoms;
            let by_sharing = requested - done - by_tolerance;
            total = (total.0 + requested, total.1 + done, total.2 + by_tolerance, total.3 + by_sharing);
            let json = json!({
                "reuse": b.reuse.describe(),
                "boxes": b.boxes,
                "atoms_per_box": b.atoms_per_box,
                "atom_steps_requested": requested,
                "atom_steps_done": done,
                "atom_steps_avoided": requested - done,
                "avoided_by_tolerance": by_tolerance,
                "avoided_by_exact_sharing": by_sharing,
            });
            (b.name.clone(), json)
        })
        .collect();
    let d = &m.diagnostics;
    json!({
        "atom_steps_requested": total.0,
        "atom_steps_done": total.1,
        "atom_steps_avoided": total.0 - total.1,
        "avoided_by_tolerance": total.2,
        "avoided_by_exact_sharing": total.3,
        // Pool round trips of the run's continuum steps (one per step for all md bodies).
        "pool_calls": m.pool.times.calls,
        "bodies": bodies,
        "diagnostics": {
            "max_strain_rate_per_s": finite_or_null(d.max_strain_rate_per_s),
            "min_box_length_over_cutoff": finite_or_null(d.min_box_length_over_cutoff),
            "cutoff_a": finite_or_null(m.cutoff_a),
            "max_neighbor_rebuilds_per_call": d.max_rebuilds_per_call,
            "max_box_temperature_k": finite_or_null(d.max_temperature_k),
            "hottest_box_point": d.hottest_point,
        },
    })
}

struct SummaryTimes {
    wall: f64,
    setup: f64,
    continuum: f64,
    output: f64,
}

fn finite_or_null(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

#[allow(clippy::too_many_arguments)]
fn summary<const D: usize>(
    loaded: &LoadedScene,
    opts: &RunOptions,
    sim: &Simulation<D>,
    times: SummaryTimes,
    max_kinetic: f64,
    momentum_scale: f64,
    errors: Option<PressureErrors>,
    direct_errors: Option<Value>,
    failure: Option<&str>,
    md: Option<&Arc<Mutex<MdShared>>>,
) -> Result<Value> {
    let md = md.and_then(|m| m.lock().ok());
    let pool_times = md.as_ref().map(|m| m.pool.times).unwrap_or_default();
    let backend = match &md {
        Some(m) => format!("md: {} on {}", m.pool.kinds().join(", "), m.pool.endpoint_names().join(", ")),
        None => "none (constitutive laws only)".into(),
    };
    // The continuum is f64 throughout; MD boxes in the precision their back ends report.
    let precision = match &md {
        Some(m) => {
            let mut md_precisions: Vec<String> = m.pool.kinds().iter().map(|k| k.rsplit('/').next().unwrap_or(k).to_string()).collect();
            md_precisions.sort();
            md_precisions.dedup();
            format!("continuum f64, md {}", md_precisions.join(", "))
        }
        None => "f64".into(),
    };
    let scene = &loaded.scene;
    let (init, now) = (sim.initial, sim.totals());
    let energy_scale = init.energy().abs().max(max_kinetic).max(f64::MIN_POSITIVE);
    let momentum_drift = (0..D).map(|a| (now.momentum[a] - init.momentum[a] - sim.wall_impulse[a]).abs()).fold(0.0, f64::max)
        / momentum_scale.max(sim.wall_impulse_magnitude).max(f64::MIN_POSITIVE);
    let mut inputs = serde_json::Map::new();
    inputs.insert(loaded.path.display().to_string(), json!(output::sha256_file(&loaded.path)?));
    for f in &loaded.files {
        inputs.insert(f.display().to_string(), json!(output::sha256_file(f)?));
    }
    let mut out = json!({
        "status": if failure.is_some() { "failed" } else { "completed" },
        "error": failure,
        "scene": scene.name,
        "dimension": D,
        "method": scene.scheme.method.name(),
        "wall_seconds": times.wall,
        "steps": sim.step,
        "simulated_time_s": sim.time,
        "dt_s": sim.dt,
        "points": sim.points.len(),
        "grid_nodes": sim.grid.node_count(),
        "closure_evaluations": sim.closure_evaluations,
        "conservation": {
            "mass_initial": init.mass,
            "mass_final": now.mass,
            "mass_drift": finite_or_null((now.mass - init.mass).abs() / init.mass),
            "momentum_initial": init.momentum.to_vec(),
            "momentum_final": now.momentum.iter().map(|v| finite_or_null(*v)).collect::<Vec<_>>(),
            "wall_impulse": sim.wall_impulse.to_vec(),
            "momentum_drift": finite_or_null(momentum_drift),
            "energy_initial": init.energy(),
            "energy_final": finite_or_null(now.energy()),
            "energy_drift": finite_or_null((now.energy() - init.energy()).abs() / energy_scale),
        },
        "time_breakdown_s": {
            "setup": times.setup,
            "continuum": times.continuum - pool_times.step_wall,
            "md": pool_times.md_compute,
            "serialisation_transfer_idle": pool_times.step_wall - pool_times.md_compute,
            "output": times.output,
        },
        "errors": errors.map(|e| json!({
            "reference": "isothermal-riemann",
            "pressure_l1": finite_or_null(e.l1),
            "pressure_l2": finite_or_null(e.l2),
            "pressure_spike": finite_or_null(e.spike),
        })).or(direct_errors),
        "provenance": {
            "program": "mscale",
            "version": env!("CARGO_PKG_VERSION"),
            "commit": option_env!("MSCALE_COMMIT").unwrap_or("unknown"),
            "features": crate::FEATURES,
            // The EAM kernel path of this process's cpu back end (MSCALE_MD_SIMD or the CPU's
            // widest; every path gives the same bits): scalar, avx2 or avx512.
            "md_simd": md_worker::simd::selected_name(),
            "backend": backend,
            "precision": precision,
            "inputs": inputs,
        },
        "command_line": opts.command_line,
        "state_digest": output::state_digest(&sim.points, sim.step, sim.time),
        "md": md.as_ref().map(|m| md_cost_json(m)),
        "md_recovery": md.as_ref().map(|m| {
            let r = m.pool.recoveries();
            json!({
                "lost_workers": r.len(),
                "restored_boxes": r.iter().map(|x| x.boxes.len()).sum::<usize>(),
                "replayed_box_steps": r.iter().map(|x| x.replayed_box_steps).sum::<u64>(),
                "replayed_md_steps": r.iter().map(|x| x.replayed_md_steps).sum::<u64>(),
                "events": r,
            })
        }),
    });
    // Implicit runs only (other summaries keep their keys): Newton iterations per step,
    // accepted and rejected steps, timings.
    if sim.integrator == continuum::solver::TimeIntegrator::ImplicitTrapezoidal {
        let st = &sim.implicit.stats;
        let mut v = serde_json::to_value(st)?;
        v["jacobian"] = json!(format!("{:?}", sim.implicit.options.jacobian));
        v["newton_iterations_per_step"] = json!(st.newton_iterations as f64 / st.accepted_steps.max(1) as f64);
        v["seconds_per_newton_iteration"] = json!(st.seconds_total / st.newton_iterations.max(1) as f64);
        v["seconds_per_step"] = json!(st.seconds_total / st.accepted_steps.max(1) as f64);
        out["implicit"] = v;
    }
    // Over MPI ranks only: how the tiles were shared out (the last step's split; with the
    // per-point work replicated, as in coupled scenes, only the scatters follow it).
    if let Some(e) = continuum::par::exchange().filter(|e| e.size() > 1) {
        let (cuts, points) = sim.tile_split(e.size());
        out["ranks"] = json!({
            "ranks": e.size(),
            "rebalance_every": sim.balance.every,
            "rebalances": sim.balance.rebalances,
            "tile_cuts": cuts,
            "points_per_rank": points,
            "migrated_points": sim.migrated_points,
        });
    }
    Ok(out)
}
