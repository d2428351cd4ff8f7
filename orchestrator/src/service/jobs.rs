//! The life of a job: the runner thread starts queued jobs side by side ([`schedule`]), each
//! on its own thread and its own workers (in this process when there are none, one at a time),
//! with the run driver of `mscale run`, moving it off workers that are lost on the way;
//! CancelJob stops it.

use super::convert::pb_worker_state;
use super::error::JobError;
use super::schedule::{self, Placement};
use super::shared::{Core, RunningJob, lock};
use super::store::{EventKind, JobRecord, JobState, WorkerRecord, WorkerState};
use super::workers;
use crate::loaded::Loaded;
use crate::run::{Outcome, Progress, RunOptions};
use anyhow::Result;
use coupling::MdShared;
use mscale_proto::orchestrator::v1 as pb;
use prost::Message;
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Times a job moves off lost workers before it fails.
const MAX_ROLLBACKS: u32 = 16;

/// Starts queued jobs side by side, each on its own thread and its own workers (see
/// [`schedule`]), until the orchestrator stops; then waits for the running ones to checkpoint.
pub(crate) fn runner(core: Arc<Core>) {
    let mut threads: Vec<std::thread::JoinHandle<()>> = Vec::new();
    // Whether a job's scene needs MD (read once per job).
    let mut needs_md: HashMap<String, bool> = HashMap::new();
    loop {
        threads.retain(|t| !t.is_finished());
        if core.stopping.load(Ordering::SeqCst) {
            break;
        }
        let next = if core.waiting_for_local_workers() {
            None
        } else {
            match next_placement(&core, &mut needs_md) {
                Ok(n) => n,
                Err(e) => {
                    tracing::error!("job store: {e:#}");
                    None
                }
            }
        };
        match next {
            Some((job, placement)) => {
                let core2 = core.clone();
                let name = format!("job-{}", job.id);
                needs_md.remove(&job.id);
                match std::thread::Builder::new().name(name).spawn(move || run_job(&core2, job, placement)) {
                    Ok(t) => threads.push(t),
                    Err(e) => tracing::error!("cannot start a job thread: {e}"),
                }
            }
            None => {
                let mut woken = lock(&core.wake.0);
                if !*woken {
                    woken = core.wake.1.wait_timeout(woken, Duration::from_millis(500)).map(|r| r.0).unwrap_or_else(|p| p.into_inner().0);
                }
                *woken = false;
            }
        }
    }
    for t in threads {
        let _ = t.join();
    }
}

/// The next queued job that can start now and where, marked as running there (its workers
/// busy, its entry in `core.running`); None when none can.
fn next_placement(core: &Arc<Core>, needs_md: &mut HashMap<String, bool>) -> Result<Option<(JobRecord, Placement)>> {
    let queued = lock(&core.store).queued()?;
    if queued.is_empty() {
        return Ok(None);
    }
    // Read before the locks: loading a scene takes a while.
    needs_md.retain(|id, _| queued.iter().any(|j| &j.id == id));
    for job in &queued {
        needs_md.entry(job.id.clone()).or_insert_with(|| {
            Loaded::load(&core.job_dir(&job.id).join("input/scene.toml"), &job.overrides).map_or(true, |l| l.needs_md())
        });
    }
    let mut reg = lock(&core.workers);
    let mut running = lock(&core.running);
    let mut per_owner: HashMap<String, usize> = HashMap::new();
    for r in running.values() {
        *per_owner.entry(r.owner.clone()).or_default() += 1;
    }
    let in_process_busy = running.values().any(|r| r.in_process);
    let usable = reg.usable();
    // Free workers, less those a running job waits for (it lost its own).
    let waiting: Vec<String> = running.values().filter_map(|r| lock(&r.waits_for).clone()).collect();
    let free: Vec<WorkerRecord> = usable.iter().filter(|w| !reg.is_busy(w.epoch) && !waiting.contains(&w.kind())).cloned().collect();
    let (mut workers_blocked, mut slot_blocked) = (false, false);
    // A job placed a moment ago is still `queued` in the store until its thread says otherwise.
    let queued: Vec<JobRecord> = queued.into_iter().filter(|j| !running.contains_key(&j.id)).collect();
    for job in schedule::order(queued, &per_owner) {
        let md = needs_md.get(&job.id).copied().unwrap_or(true);
        let needs = if md && !usable.is_empty() { schedule::Needs::Workers(job.workers) } else { schedule::Needs::InProcess };
        let placement = match needs {
            schedule::Needs::InProcess if !in_process_busy && !slot_blocked => Some(Placement::InProcess),
            schedule::Needs::InProcess => {
                slot_blocked = true;
                None
            }
            schedule::Needs::Workers(_) if workers_blocked => None,
            schedule::Needs::Workers(want) => {
                let p = schedule::pick(&free, &usable, want).map(Placement::Workers);
                workers_blocked |= p.is_none();
                p
            }
        };
        let Some(placement) = placement else { continue };
        let epochs: Vec<u64> = match &placement {
            Placement::Workers(ws) => ws.iter().map(|w| w.epoch).collect(),
            Placement::InProcess => Vec::new(),
        };
        reg.set_busy(&epochs, &job.id);
        running.insert(
            job.id.clone(),
            RunningJob {
                id: job.id.clone(),
                owner: job.owner.clone(),
                stop: Arc::new(AtomicBool::new(false)),
                user_cancel: Arc::new(AtomicBool::new(false)),
                reassign: Arc::new(AtomicBool::new(false)),
                workers: epochs,
                in_process: matches!(placement, Placement::InProcess),
                waits_for: Arc::new(Mutex::new(None)),
            },
        );
        return Ok(Some((job, placement)));
    }
    Ok(None)
}

/// How one attempt of a job on a set of workers ended.
enum Attempt {
    Done(Outcome),
    Error(anyhow::Error),
}

/// The flags of a running job (set up by [`next_placement`]).
fn flags_of(core: &Core, id: &str) -> Option<(Arc<AtomicBool>, Arc<AtomicBool>, Arc<AtomicBool>, Arc<Mutex<Option<String>>>)> {
    lock(&core.running).get(id).map(|r| (r.stop.clone(), r.user_cancel.clone(), r.reassign.clone(), r.waits_for.clone()))
}

/// A job's run ends: its workers are free, the scheduler looks again.
fn release(core: &Core, id: &str) {
    let run = lock(&core.running).remove(id);
    if let Some(run) = run {
        lock(&core.workers).set_busy(&run.workers, "");
    }
    lock(&core.workers).release_job(id);
    core.wake_runner();
}

fn run_job(core: &Arc<Core>, job: JobRecord, placement: Placement) {
    let id = job.id.clone();
    let Some(flags) = flags_of(core, &id) else { return };
    // A job cancelled between being picked and starting stays cancelled and is not run.
    // Bound first: a guard in the match's scrutinee would hold the store through the arms, and
    // `release` takes the registry (the order everywhere else is registry, then store): a job
    // cancelled right after placement deadlocked against a DrainWorker that way.
    let started = lock(&core.store).transition(&id, JobState::Running, if job.resumes > 0 { "resumed" } else { "started" }, "");
    match started {
        Ok(true) => {}
        Ok(false) => {
            release(core, &id);
            return;
        }
        Err(e) => {
            tracing::error!("job {id}: cannot record running: {e:#}");
            // Not in a tight loop while the store fails.
            std::thread::sleep(Duration::from_secs(1));
            release(core, &id);
            return;
        }
    }
    core.publish_stored(&id);
    let assigned = match placement {
        Placement::Workers(ws) => ws,
        Placement::InProcess => Vec::new(),
    };
    let outcome = run_on_workers(core, &job, assigned, &flags.0, &flags.2, &flags.3);
    let stopping = core.stopping.load(Ordering::SeqCst);
    let user_cancel = flags.1.load(Ordering::SeqCst);
    // Free the workers before the final event: a watcher that sees the job end finds them free.
    release(core, &id);
    match outcome {
        Attempt::Done(Outcome::Completed(summary)) => {
            let digest = summary["state_digest"].as_str().unwrap_or_default().to_string();
            tracing::info!("job {id} completed, state_digest {digest}");
            core.transition(&id, JobState::Completed, "", &digest);
        }
        // A scheduler stopping the allocation (scancel, a time limit) signals the orchestrator
        // and its workers at once: a job that failed for want of workers while the orchestrator
        // stops is queued again and resumes from its last checkpoint on the next start.
        Attempt::Done(Outcome::Failed(_, why)) if stopping && !flags.1.load(Ordering::SeqCst) => {
            tracing::warn!("job {id}: {why}, as the orchestrator stops; queued again, resumes from its last checkpoint");
            core.transition(&id, JobState::Queued, &format!("the orchestrator stopped ({why}); resumes from its last checkpoint"), "");
        }
        Attempt::Done(Outcome::Failed(_, why)) => {
            tracing::error!("job {id} failed: {why}");
            core.transition(&id, JobState::Failed, &why, "")
        }
        Attempt::Done(Outcome::Cancelled { checkpoint, step }) if stopping && !user_cancel => {
            tracing::info!("job {id}: checkpointed at step {step} ({}) as the orchestrator stops", checkpoint.display());
            core.note_event(&id, EventKind::Checkpoint, &format!("checkpoint at step {step} as the orchestrator stops"));
            core.transition(&id, JobState::Queued, "the orchestrator stopped; resumes from its last checkpoint", "");
        }
        Attempt::Done(Outcome::Cancelled { step, .. }) => {
            core.note_event(&id, EventKind::Checkpoint, &format!("checkpoint at step {step} as the job is cancelled"));
            core.transition(&id, JobState::Cancelled, &format!("cancelled by a user after step {step}"), "")
        }
        Attempt::Error(e) => {
            tracing::error!("job {id} failed: {e:#}");
            core.transition(&id, JobState::Failed, &format!("{e:#}"), "")
        }
    }
}

/// Workers of `kind` to replace the job's lost ones when none of its own survived: free ones
/// at once, else it waits until a running job releases one. None when no live worker of
/// `kind` is left in the pool (nothing to wait for), or the job is stopped while it waits.
fn replacements(
    core: &Core,
    id: &str,
    kind: &str,
    n: usize,
    stop: &AtomicBool,
    waits_for: &Mutex<Option<String>>,
) -> Option<Vec<WorkerRecord>> {
    let mut told = false;
    loop {
        {
            let mut reg = lock(&core.workers);
            let usable: Vec<WorkerRecord> = reg.usable().into_iter().filter(|w| w.kind() == kind).collect();
            if usable.is_empty() {
                *lock(waits_for) = None;
                return None;
            }
            let free: Vec<WorkerRecord> = usable.iter().filter(|w| !reg.is_busy(w.epoch)).take(n.max(1)).cloned().collect();
            if !free.is_empty() {
                let epochs: Vec<u64> = free.iter().map(|w| w.epoch).collect();
                reg.set_busy(&epochs, id);
                if let Some(r) = lock(&core.running).get_mut(id) {
                    r.workers.extend(&epochs);
                }
                *lock(waits_for) = None;
                return Some(free);
            }
        }
        if !told {
            *lock(waits_for) = Some(kind.to_string());
            core.note(id, &format!("none of the job's workers is left; it waits for a worker of back end {kind} to be free"));
            told = true;
        }
        if stop.load(Ordering::SeqCst) || core.stopping.load(Ordering::SeqCst) {
            *lock(waits_for) = None;
            return None;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Runs a job on `assigned` (in-process when empty), moving it off workers that are lost on
/// the way: the run rolls back to its last checkpoint (from the start when it has none) onto
/// its surviving workers, or when none survived, onto replacements of the same back end and
/// precision (waiting for one to be free).
fn run_on_workers(
    core: &Arc<Core>,
    job: &JobRecord,
    mut assigned: Vec<WorkerRecord>,
    stop: &Arc<AtomicBool>,
    reassign: &Arc<AtomicBool>,
    waits_for: &Mutex<Option<String>>,
) -> Attempt {
    let id = &job.id;
    let run_dir = core.job_dir(id).join("run");
    let loaded = match Loaded::load(&core.job_dir(id).join("input/scene.toml"), &job.overrides) {
        Ok(l) => l,
        Err(e) => return Attempt::Error(anyhow::anyhow!("{e}")),
    };
    let mut rollbacks = 0;
    loop {
        let last_step = Arc::new(AtomicU64::new(0));
        let result = match attempt(core, job, &loaded, &run_dir, &assigned, stop, &last_step) {
            Ok(o) => Attempt::Done(o),
            Err(e) => Attempt::Error(e),
        };
        let step = last_step.load(Ordering::SeqCst);
        let live = |w: &WorkerRecord| lock(&core.workers).get(w.epoch).is_some_and(|r| r.state != WorkerState::Lost);
        let why = match &result {
            Attempt::Done(Outcome::Cancelled { step, .. })
                if reassign.load(Ordering::SeqCst) && !core.stopping.load(Ordering::SeqCst) && !is_user_cancel(core, id) =>
            {
                reassign.store(false, Ordering::SeqCst);
                stop.store(false, Ordering::SeqCst);
                let kind = assigned[0].kind();
                let before = assigned.len();
                assigned.retain(|w| live(w));
                if assigned.is_empty() {
                    match replacements(core, id, &kind, before, stop, waits_for) {
                        Some(r) => assigned = r,
                        // (Every worker lost at once is also what SIGTERM to a whole allocation
                        // looks like: when the orchestrator is stopping, the job is requeued.)
                        None if stop.load(Ordering::SeqCst) || core.stopping.load(Ordering::SeqCst) => return result,
                        None => {
                            return Attempt::Done(Outcome::Failed(
                                serde_json::Value::Null,
                                format!("no live worker of back end {kind} is left to take the job's boxes"),
                            ));
                        }
                    }
                }
                core.note(id, &format!("a worker was declared lost; checkpointed after step {step} and continues on the live workers"));
                core.metrics.recovery("move");
                continue;
            }
            Attempt::Done(Outcome::Failed(_, why)) if !assigned.is_empty() => why.clone(),
            Attempt::Error(e) if !assigned.is_empty() => format!("{e:#}"),
            _ => return result,
        };
        // Did it fail because workers are gone? (Not: an error of a worker that still answers.)
        let lost: Vec<WorkerRecord> =
            assigned.iter().filter(|w| !live(w) || !workers::answers(&w.ad.address, Duration::from_secs(3))).cloned().collect();
        if lost.is_empty() {
            return result;
        }
        let at = step + 1;
        let names = lost.iter().map(|w| format!("{} at {}", w.id, w.ad.address)).collect::<Vec<_>>().join(", ");
        {
            let why = format!("stopped answering during step {at} of job {id}");
            let mut reg = lock(&core.workers);
            let declared = reg.declare_all_lost(&mut lock(&core.store), lost.iter().map(|w| (w.epoch, why.clone())).collect());
            if let Err(e) = declared {
                tracing::error!("cannot record the workers {names} as lost: {e:#}");
            }
        }
        let k = assigned[0].kind();
        let before = assigned.len();
        assigned.retain(|w| !lost.iter().any(|l| l.epoch == w.epoch) && live(w));
        if assigned.is_empty() {
            match replacements(core, id, &k, before, stop, waits_for) {
                Some(r) => assigned = r,
                None if stop.load(Ordering::SeqCst) && !core.stopping.load(Ordering::SeqCst) => {
                    let step = crate::checkpoint::list(&run_dir).ok().and_then(|l| l.first().map(|c| c.0)).unwrap_or(0);
                    return Attempt::Done(Outcome::Cancelled { checkpoint: run_dir.join("checkpoints"), step });
                }
                None => {
                    return Attempt::Done(Outcome::Failed(
                        serde_json::Value::Null,
                        format!(
                            "worker {names} was lost at step {at} ({why}); no live worker of back end {k} is left to restore its boxes onto"
                        ),
                    ));
                }
            }
        }
        rollbacks += 1;
        if rollbacks > MAX_ROLLBACKS {
            return Attempt::Done(Outcome::Failed(
                serde_json::Value::Null,
                format!("worker {names} was lost at step {at}; the job lost workers {rollbacks} times and gives up"),
            ));
        }
        let from = crate::checkpoint::list(&run_dir).ok().and_then(|l| l.first().map(|c| c.0));
        let from = from.map_or("the start (no checkpoint yet)".to_string(), |s| format!("its checkpoint of step {s}"));
        let onto = assigned.iter().map(|w| w.id.as_str()).collect::<Vec<_>>().join(", ");
        core.note(id, &format!("worker {names} was lost at step {at}; rolled back to {from} onto {onto}"));
        core.metrics.recovery("rollback");
        tracing::warn!(
            "job {id}: worker {names} was lost at step {at} ({why}); its boxes could not be replayed alone, so the whole job is rolling back to {from} onto {onto}"
        );
    }
}

fn is_user_cancel(core: &Core, id: &str) -> bool {
    lock(&core.running).get(id).is_some_and(|r| r.user_cancel.load(Ordering::SeqCst))
}

/// The job's workers as a watch event shows them, with their load in this attempt.
fn job_workers(core: &Core, assigned: &[WorkerRecord], md: Option<&Arc<Mutex<MdShared>>>) -> Vec<pb::JobWorker> {
    let load = md.and_then(|m| m.try_lock().ok().map(|m| m.pool.endpoint_load())).unwrap_or_default();
    let reg = lock(&core.workers);
    assigned
        .iter()
        .enumerate()
        .map(|(k, w)| {
            let l = load.get(k).cloned().unwrap_or_default();
            pb::JobWorker {
                worker_id: w.id.clone(),
                address: w.ad.address.clone(),
                state: pb_worker_state(reg.get(w.epoch).map_or(WorkerState::Lost, |r| r.state)) as i32,
                boxes: l.boxes as u32,
                advertised_atom_steps_per_s: w.ad.atom_steps_per_s,
                measured_atom_steps_per_s: if l.step_seconds > 0.0 { l.atom_steps / l.step_seconds } else { 0.0 },
            }
        })
        .collect()
}

/// One run of a job on `assigned` (in-process when empty), from its newest checkpoint if any.
fn attempt(
    core: &Arc<Core>,
    job: &JobRecord,
    loaded: &Loaded,
    run_dir: &Path,
    assigned: &[WorkerRecord],
    stop: &Arc<AtomicBool>,
    last_step: &Arc<AtomicU64>,
) -> Result<Outcome> {
    let id = job.id.clone();
    let mut opts = RunOptions::new(run_dir.to_path_buf(), vec!["mscale".into(), "serve".into(), format!("job {id}")]);
    opts.progress_bar = false;
    opts.checkpoint_every = if job.checkpoint_every > 0 { job.checkpoint_every } else { core.checkpoint_every };
    opts.resume = !crate::checkpoint::list(run_dir)?.is_empty();
    opts.cancel = Some(stop.clone());
    opts.workers = assigned.iter().map(|w| w.ad.address.clone()).collect();
    opts.worker_weights = assigned.iter().map(|w| w.ad.atom_steps_per_s).collect();
    let md_slot: Arc<Mutex<Option<Arc<Mutex<MdShared>>>>> = Arc::default();
    let slot = md_slot.clone();
    let core3 = core.clone();
    opts.md_hook = Some(Arc::new(move |m: &Arc<Mutex<MdShared>>| {
        *lock(&slot) = Some(m.clone());
        // Keyed by address: the jobs' workers are disjoint.
        lock(&core3.aborts).extend(lock(m).pool.abort_handles());
    }));
    opts.step_deadline = core.step_deadline;
    let (core4, id4, assigned4) = (core.clone(), id.clone(), assigned.to_vec());
    opts.on_worker_lost = Some(Arc::new(move |r: &md_worker::recovery::Recovery| {
        if let Some(w) = assigned4.iter().find(|w| w.ad.address == r.worker) {
            let why = if r.why.starts_with("declared faulty") {
                format!("answered garbage during step {} of job {id4}: {}", r.step, r.why)
            } else {
                format!("stopped answering during step {} of job {id4}: {}", r.step, r.why)
            };
            let mut reg = lock(&core4.workers);
            let declared = reg.declare_lost(&mut lock(&core4.store), w.epoch, &why);
            if let Err(e) = declared {
                tracing::error!("cannot record worker {} as lost: {e:#}", w.id);
            }
        }
        core4.note(&id4, &r.to_string());
        core4.metrics.recovery("replay");
    }));
    // The run writes a checkpoint after these steps (before it reports their progress).
    let every = if opts.checkpoint_every > 0 { opts.checkpoint_every } else { loaded.checkpoint_every_steps() };
    let (core2, id2, assigned2, last_step) = (core.clone(), id.clone(), assigned.to_vec(), last_step.clone());
    let run_dir2 = run_dir.to_path_buf();
    core.metrics.new_attempt(&id);
    let last = Mutex::new(Instant::now() - Duration::from_secs(1));
    opts.progress = Some(Arc::new(move |p: &Progress| {
        last_step.store(p.step, Ordering::SeqCst);
        let checkpoint = !p.done && every > 0 && p.step.is_multiple_of(every) && p.step < p.steps;
        let mut last = lock(&last);
        let now = Instant::now();
        // Progress is sampled (at most one event per 100 ms); checkpoints and the last step
        // always get their event.
        if !p.done && !checkpoint && now.duration_since(*last) < Duration::from_millis(100) {
            return;
        }
        *last = now;
        let rate = p.session_steps as f64 / p.elapsed_s.max(1e-9);
        let workers = if assigned2.is_empty() { Vec::new() } else { job_workers(&core2, &assigned2, lock(&md_slot).as_ref()) };
        let load = lock(&md_slot).as_ref().and_then(|m| m.try_lock().ok().map(|m| m.pool.endpoint_load())).unwrap_or_default();
        core2.metrics.sample(&super::metrics::Sample {
            job: &id2,
            step: p.step,
            steps: p.steps,
            steps_per_second: rate,
            session_seconds: p.elapsed_s,
            load: &load,
            workers: &workers,
        });
        if let Some(w) = crate::checkpoint::last_written(&run_dir2).filter(|w| checkpoint && w.step == p.step) {
            core2.metrics.checkpoint(&id2, w.bytes, w.seconds);
        }
        if p.done {
            core2.metrics.job_over(&id2);
        }
        let detail = pb::JobEvent {
            end_time_s: p.end_time,
            // (-1: unknown; a cell run's adaptive steps have no count to go.)
            eta_s: if p.session_steps > 0 && p.steps > 0 { (p.steps - p.step.min(p.steps)) as f64 / rate } else { -1.0 },
            energy_drift: p.energy_drift,
            workers,
            ..Default::default()
        }
        .encode_to_vec();
        lock(&core2.details).insert(id2.clone(), detail.clone());
        let (kind, message) = if checkpoint {
            (EventKind::Checkpoint, format!("checkpoint at step {}", p.step))
        } else {
            (EventKind::Progress, String::new())
        };
        let recorded = lock(&core2.store).progress_event(&id2, kind, p.step, p.steps, p.time, &message, &detail);
        if let Err(e) = recorded {
            tracing::warn!("job {id2}: cannot record progress: {e:#}");
        }
        core2.publish_stored(&id2);
    }));
    if opts.resume {
        tracing::info!("job {id}: resuming from its last checkpoint");
    }
    if assigned.is_empty() {
        tracing::info!("job {id}: no live workers; MD (if any) runs in this process");
    } else {
        let shares = assigned
            .iter()
            .map(|w| format!("{} at {} ({:.3e} atom-steps/s)", w.id, w.ad.address, w.ad.atom_steps_per_s))
            .collect::<Vec<_>>()
            .join(", ");
        tracing::info!("job {id}: on workers {shares}");
    }
    // The job on a rayon pool of its own: its stepping thread is a worker of that pool, so a
    // parallel loop too short to split runs inline on it instead of a futex hand-off to the pool
    // per loop (10x on small scenes; see `mscale run`'s run_on_pool), and a job waiting inside a
    // loop can only take up its own tasks, never another job's run. Same results on any pool.
    let outcome = if job.ranks > 1 {
        match &core.mpi {
            Some(m) => super::ranks::run(m, job.ranks, &core.job_dir(&id).join("input/scene.toml"), &job.overrides, &opts),
            None => Err(anyhow::anyhow!(
                "the job asks for {} MPI ranks, but this orchestrator was started without --mpi-mscale: restart it with one",
                job.ranks
            )),
        }
    } else {
        match rayon::ThreadPoolBuilder::new().thread_name(|k| format!("job-{k}")).build() {
            Ok(pool) => pool.install(|| loaded.run(&opts)),
            Err(e) => {
                tracing::warn!("job {id}: cannot start its thread pool ({e}); running on the shared one");
                loaded.run(&opts)
            }
        }
    };
    lock(&core.aborts).retain(|addr, _| !assigned.iter().any(|w| &w.ad.address == addr));
    outcome
}

impl Core {
    /// Cancels a job: a queued one at once, a running one after its current step (with a
    /// checkpoint). Returns the job as it is now.
    pub(crate) fn cancel(&self, id: &str) -> Result<JobRecord, JobError> {
        let job = self.get(id)?;
        match job.state {
            JobState::Queued => self.transition(id, JobState::Cancelled, "cancelled by a user before it started", ""),
            JobState::Running => {
                if let Some(run) = lock(&self.running).get(id) {
                    run.user_cancel.store(true, Ordering::SeqCst);
                    run.stop.store(true, Ordering::SeqCst);
                }
            }
            state => return Err(JobError::Ended { id: id.to_string(), state }),
        }
        self.get(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::store::test_job;

    #[test]
    fn a_job_cancelled_before_it_starts_frees_the_store_before_it_takes_the_registry() {
        // Found by fuzz_orchestrator_messages (SubmitJob, then CancelJob at once, and a
        // DrainWorker): the job's thread held the store while waiting for the registry, and
        // DrainWorker held the registry while waiting for the store.
        let dir = tempfile::tempdir().unwrap();
        let core = Core::for_test(dir.path());
        lock(&core.store).insert(&test_job("j1", 0)).unwrap();
        assert!(lock(&core.store).transition("j1", JobState::Cancelled, "cancelled by a user before it started", "").unwrap());
        lock(&core.running).insert(
            "j1".into(),
            RunningJob {
                id: "j1".into(),
                owner: "t".into(),
                stop: Arc::default(),
                user_cancel: Arc::default(),
                reassign: Arc::default(),
                workers: Vec::new(),
                in_process: true,
                waits_for: Arc::default(),
            },
        );
        let job = lock(&core.store).get("j1").unwrap().unwrap();
        // The registry held (as DrainWorker holds it) while the job's thread starts and finds
        // the job cancelled.
        let registry = lock(&core.workers);
        let t = std::thread::spawn({
            let core = core.clone();
            move || run_job(&core, job, Placement::InProcess)
        });
        std::thread::sleep(Duration::from_millis(200));
        // DrainWorker's next lock: the store must be free.
        let t0 = Instant::now();
        let free = loop {
            if core.store.try_lock().is_ok() {
                break true;
            }
            if t0.elapsed() > Duration::from_secs(2) {
                break false;
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        drop(registry);
        t.join().unwrap();
        assert!(free, "the job's thread held the store while it waited for the registry");
        assert!(lock(&core.running).is_empty(), "the cancelled job was released");
        assert_eq!(lock(&core.store).get("j1").unwrap().unwrap().state, JobState::Cancelled);
    }
}
