//! `mscale serve`: the job service (`mscale.orchestrator.v1`).
//!
//! Jobs are scenes submitted with the files they name; they are validated at submit with the
//! messages of `mscale check`, kept in the SQLite [`Store`] under the state directory, and run
//! one at a time, by priority, on a dedicated thread with the same run driver as `mscale run`
//! (so a job ends with the digest `mscale run` gives). Jobs checkpoint at an interval; a job
//! that was running when the orchestrator died is resumed from its last checkpoint on restart.
//!
//! Layout of the state directory: `jobs.sqlite`, `token` (generated when no token file is
//! given), and `jobs/<id>/input/` (the scene and its files) and `jobs/<id>/run/` (the run
//! directory: outputs, checkpoints, summary.json).
//!
//! Workers (`md-worker serve --orchestrator URL`, or `--local-workers N` started here) register
//! and heartbeat ([`crate::workers`]). A job's MD boxes are spread over the live workers of one
//! back end and precision in proportion to their throughput, or run in this process when there
//! are none. A worker that stops answering mid-job (killed, or past `--step-deadline`) is
//! declared lost and only its boxes are rebuilt on the job's surviving workers of the same back
//! end and precision: restored from the last checkpoint and sent again every input logged since
//! (`md_worker::recovery`), so the job ends with the digest of an uninterrupted run; with no
//! survivor the job fails naming the worker and the step. A worker silent for longer than the
//! worker timeout is declared lost and a call in flight on it is aborted, with the same
//! recovery. Where replay is impossible (the input log outgrew its bound) the whole job rolls
//! back to its last checkpoint onto the survivors instead.
//!
//! Watch events: every event of a job has a sequence number (1, 2, 3, ... with no gaps), given
//! in the store transaction that records it ([`Store`] keeps state changes, checkpoints and
//! worker changes for good and recent progress). Watchers replay what they missed from the
//! store and then follow a broadcast channel; one that lags is caught up from the store again,
//! so an event is never skipped. Progress is published at most every 100 ms.
//!
//! Security: mutating calls (SubmitJob, CancelJob, RegisterWorker, Heartbeat, DrainWorker)
//! need `authorization: Bearer <token>`,
//! compared in constant time; requests are bounded in size; FetchResult cannot leave the job's
//! run directory; nothing runs through a shell. TLS (rustls) is served with `--tls-cert` and
//! `--tls-key`, and required to listen on anything but a loopback address.

use crate::run::{self, Outcome, Progress, RunOptions};
use crate::scene;
use crate::store::{EventKind, EventRecord, JobRecord, JobState, Store, WorkerAd, WorkerRecord, WorkerState, now_unix};
use crate::workers::{self, Registry, WorkerError};
use coupling::MdShared;
use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1 as pb;
use pb::orchestrator_server::{Orchestrator, OrchestratorServer};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Component, Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use prost::Message;
use tokio::sync::{broadcast, watch};
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// Largest request or response message (bytes): scenes plus potential files, fetched files.
pub const MAX_MESSAGE: usize = 64 << 20;
/// Default checkpoint interval (steps) of jobs that name none.
pub const DEFAULT_CHECKPOINT_EVERY: u64 = 100;

pub struct ServeOptions {
    pub state_dir: PathBuf,
    pub listen: String,
    /// The bearer token mutating calls must carry.
    pub token: String,
    pub checkpoint_every: u64,
    /// PEM certificate chain and private key: serve over TLS (rustls).
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    /// `md-worker serve` processes to start on this machine (`--local-workers`).
    pub local_workers: usize,
    /// The token file local workers authenticate with.
    pub token_file: PathBuf,
    /// What local workers trust to reach a TLS orchestrator (the certificate file).
    pub local_ca: Option<PathBuf>,
    /// A worker without a heartbeat for this long is declared lost.
    pub worker_timeout: Duration,
    /// Bound on each call to a worker.
    pub step_deadline: md_worker::recovery::StepDeadline,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Compares two byte strings in time that depends only on their lengths.
pub fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Reads a token file (surrounding whitespace ignored); refuses an empty one.
pub fn read_token(path: &Path) -> Result<String> {
    let t = std::fs::read_to_string(path).with_context(|| format!("cannot read the token file {}", path.display()))?;
    let t = t.trim().to_string();
    anyhow::ensure!(!t.is_empty(), "the token file {} is empty", path.display());
    Ok(t)
}

/// What the service and the job runner share.
struct Core {
    store: Mutex<Store>,
    state_dir: PathBuf,
    token: String,
    checkpoint_every: u64,
    /// The event channels of jobs somebody watches (lock after `store`).
    live: Mutex<HashMap<String, LiveJob>>,
    /// The progress details (end time, ETA, drift, workers) of running jobs' latest progress
    /// event, encoded: state events carry them too.
    details: Mutex<HashMap<String, Vec<u8>>>,
    /// The running job and its flags.
    running: Mutex<Option<RunningJob>>,
    /// Registered workers (lock before `store` when both are needed).
    workers: Mutex<Registry>,
    /// Jobs wait (up to [`LOCAL_WORKERS_WAIT`]) until this many workers have registered: the
    /// local workers being started.
    expect_workers: usize,
    started: Instant,
    /// Raised when the orchestrator stops: the running job checkpoints and stays queued.
    stopping: AtomicBool,
    /// Tells open watch streams that the orchestrator stops (so shutdown need not wait for them).
    stop_watchers: watch::Sender<bool>,
    wake: (Mutex<bool>, Condvar),
    next_id: AtomicU64,
    step_deadline: md_worker::recovery::StepDeadline,
    /// Abort handles of the running job's workers, by address: a worker declared lost gets its
    /// calls aborted (its boxes are then replayed on the others).
    aborts: Mutex<HashMap<String, md_worker::recovery::AbortHandle>>,
}

/// The broadcast of a watched job's events.
struct LiveJob {
    tx: broadcast::Sender<Arc<pb::JobEvent>>,
    /// The newest sequence number sent on `tx`.
    published: u64,
}

/// Events a watcher may fall behind by before it is caught up from the store.
const WATCH_BACKLOG: usize = 256;
/// Events read from the store at a time when a watcher catches up.
const REPLAY_BATCH: usize = 512;
/// Largest chunk of FetchRun (bytes).
pub const FETCH_CHUNK: usize = 1 << 20;

/// How long jobs wait for `--local-workers` to register before running without them.
const LOCAL_WORKERS_WAIT: Duration = Duration::from_secs(60);
/// Times a job moves off lost workers before it fails.
const MAX_ROLLBACKS: u32 = 16;

/// The job on the runner thread.
struct RunningJob {
    id: String,
    /// Stops the run after its current step, with a checkpoint.
    stop: Arc<AtomicBool>,
    /// Set with `stop` by CancelJob.
    user_cancel: Arc<AtomicBool>,
    /// Set with `stop` when one of its workers is declared lost: it continues elsewhere.
    reassign: Arc<AtomicBool>,
    /// Epochs of the workers holding its boxes.
    workers: Vec<u64>,
}

fn pb_worker_state(s: WorkerState) -> pb::WorkerState {
    match s {
        WorkerState::Live => pb::WorkerState::Live,
        WorkerState::Draining => pb::WorkerState::Draining,
        WorkerState::Lost => pb::WorkerState::Lost,
    }
}

fn worker_to_pb(v: &workers::WorkerView) -> pb::Worker {
    let (w, ad) = (&v.record, &v.record.ad);
    pb::Worker {
        id: w.id.clone(),
        epoch: w.epoch,
        address: ad.address.clone(),
        device: ad.device.clone(),
        backend: ad.backend.clone(),
        precision: ad.precision.clone(),
        cores: ad.cores,
        memory_bytes: ad.memory_bytes,
        atom_steps_per_s: ad.atom_steps_per_s,
        throughput_source: ad.throughput_source.clone(),
        protocol_version: ad.protocol_version,
        state: pb_worker_state(w.state) as i32,
        registered_unix: w.registered,
        last_heartbeat_unix: v.last_heartbeat,
        note: w.note.clone(),
        job_id: v.job.clone().unwrap_or_default(),
    }
}

fn worker_status(e: WorkerError) -> Status {
    match &e {
        WorkerError::Version { .. } => Status::failed_precondition(e.to_string()),
        WorkerError::Invalid(_) => Status::invalid_argument(e.to_string()),
        WorkerError::NotFound(_) => Status::not_found(e.to_string()),
        WorkerError::Store(_) => Status::internal(e.to_string()),
    }
}

fn pb_state(s: JobState) -> pb::JobState {
    match s {
        JobState::Queued => pb::JobState::Queued,
        JobState::Running => pb::JobState::Running,
        JobState::Completed => pb::JobState::Completed,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

fn to_pb(j: &JobRecord) -> pb::Job {
    pb::Job {
        id: j.id.clone(),
        scene: j.scene.clone(),
        state: pb_state(j.state) as i32,
        priority: j.priority,
        step: j.step,
        steps: j.steps,
        sim_time_s: j.sim_time,
        error: j.error.clone(),
        state_digest: j.state_digest.clone(),
        submitted_unix: j.submitted,
        started_unix: j.started,
        finished_unix: j.finished,
        resumes: j.resumes,
    }
}

fn pb_event_kind(k: EventKind) -> pb::JobEventKind {
    match k {
        EventKind::State => pb::JobEventKind::State,
        EventKind::Progress => pb::JobEventKind::Progress,
        EventKind::Checkpoint => pb::JobEventKind::Checkpoint,
        EventKind::Workers => pb::JobEventKind::Workers,
    }
}

/// A stored event as watchers get it: the progress details it was stored with (end time, ETA,
/// drift, workers), the rest from the record.
fn event_of(e: &EventRecord) -> pb::JobEvent {
    let mut ev = pb::JobEvent::decode(e.detail.as_slice()).unwrap_or_else(|_| pb::JobEvent { eta_s: -1.0, ..Default::default() });
    if e.detail.is_empty() {
        ev.eta_s = -1.0;
    }
    ev.job_id = e.job_id.clone();
    ev.state = pb_state(e.state) as i32;
    ev.step = e.step;
    ev.steps = e.steps;
    ev.sim_time_s = e.sim_time;
    ev.percent = if e.steps > 0 { 100.0 * e.step as f64 / e.steps as f64 } else { 0.0 };
    ev.message = e.message.clone();
    ev.sequence = e.seq;
    ev.kind = pb_event_kind(e.kind) as i32;
    ev.at_unix = e.at;
    ev
}

/// The event that stands for events `from..=to` no longer retained.
fn not_retained(id: &str, from: u64, to: u64) -> pb::JobEvent {
    pb::JobEvent {
        job_id: id.to_string(),
        sequence: to,
        not_retained_from: from,
        kind: pb::JobEventKind::NotRetained as i32,
        eta_s: -1.0,
        message: format!("events {from} to {to} of job {id} are no longer retained (old progress events are pruned); they cannot be replayed"),
        ..Default::default()
    }
}

fn is_final(state: i32) -> bool {
    matches!(pb::JobState::try_from(state), Ok(pb::JobState::Completed | pb::JobState::Failed | pb::JobState::Cancelled))
}

impl Core {
    fn job_dir(&self, id: &str) -> PathBuf {
        self.state_dir.join("jobs").join(id)
    }

    fn get(&self, id: &str) -> Result<JobRecord, Status> {
        lock(&self.store).get(id).map_err(|e| Status::internal(format!("{e:#}")))?.ok_or_else(|| Status::not_found(format!("no job {id:?}")))
    }

    /// Subscribes to a job's events; returns the receiver and the newest sequence number at
    /// that moment (every later event comes through the receiver or, if it lags, the store).
    fn subscribe(&self, id: &str) -> Result<(broadcast::Receiver<Arc<pb::JobEvent>>, u64), Status> {
        let store = lock(&self.store);
        let last = store.last_sequence(id).map_err(|e| Status::internal(format!("{e:#}")))?;
        let mut live = lock(&self.live);
        let job = live.entry(id.to_string()).or_insert_with(|| LiveJob { tx: broadcast::channel(WATCH_BACKLOG).0, published: last });
        Ok((job.tx.subscribe(), last))
    }

    /// Drops a job's channel when its last watcher has gone.
    fn unsubscribe(&self, id: &str) {
        let mut live = lock(&self.live);
        if live.get(id).is_some_and(|j| j.tx.receiver_count() == 0) {
            live.remove(id);
        }
    }

    /// Sends the job's stored events its watchers have not been sent yet (after every change
    /// the store records); in sequence order, as the store lock is held throughout.
    fn publish_stored(&self, id: &str) {
        let store = lock(&self.store);
        let mut live = lock(&self.live);
        let Some(job) = live.get_mut(id) else { return }; // nobody watches: watchers read the store
        loop {
            let events = match store.events_after(id, job.published, REPLAY_BATCH) {
                Ok(e) => e,
                Err(e) => {
                    tracing::error!("job {id}: cannot read its events: {e:#}");
                    return;
                }
            };
            for e in &events {
                job.published = e.seq;
                // No receiver: the watcher is gone or about to subscribe (it reads the store).
                let _ = job.tx.send(Arc::new(event_of(e)));
            }
            if events.len() < REPLAY_BATCH {
                return;
            }
        }
    }

    /// Records a job's note (a worker change, a checkpoint) as an event and publishes it.
    fn note_event(&self, id: &str, kind: EventKind, text: &str) {
        let detail = lock(&self.details).get(id).cloned().unwrap_or_default();
        if let Err(e) = lock(&self.store).note_event(id, kind, text, &detail) {
            tracing::error!("job {id}: cannot record {text:?}: {e:#}");
        }
        self.publish_stored(id);
    }

    /// Whether jobs should still wait for `--local-workers` to register.
    fn waiting_for_local_workers(&self) -> bool {
        self.expect_workers > 0 && self.started.elapsed() < LOCAL_WORKERS_WAIT && lock(&self.workers).usable().len() < self.expect_workers
    }

    fn wake_runner(&self) {
        *lock(&self.wake.0) = true;
        self.wake.1.notify_all();
    }

    fn new_id(&self) -> String {
        let n = self.next_id.fetch_add(1, Ordering::SeqCst);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
        let h = Sha256::digest(format!("{nanos}-{}-{n}", std::process::id()).as_bytes());
        format!("j{}", &hex::encode(h)[..12])
    }
}

/// Runs queued jobs one at a time until the orchestrator stops.
fn runner(core: Arc<Core>) {
    loop {
        if core.stopping.load(Ordering::SeqCst) {
            return;
        }
        let next = if core.waiting_for_local_workers() {
            None
        } else {
            match lock(&core.store).next_queued() {
                Ok(n) => n,
                Err(e) => {
                    tracing::error!("job store: {e:#}");
                    None
                }
            }
        };
        match next {
            Some(job) => run_job(&core, job),
            None => {
                let mut woken = lock(&core.wake.0);
                if !*woken {
                    woken = core.wake.1.wait_timeout(woken, Duration::from_millis(500)).map(|r| r.0).unwrap_or_else(|p| p.into_inner().0);
                }
                *woken = false;
            }
        }
    }
}

/// Declares silent workers lost, every fraction of the timeout, until the orchestrator stops;
/// a call in flight on one is aborted (its boxes are replayed on the others), or where the job
/// has no abort handle for it, the job checkpoints and moves off it.
fn monitor(core: Arc<Core>) {
    let period = (lock(&core.workers).timeout() / 4).clamp(Duration::from_millis(50), Duration::from_millis(500));
    while !core.stopping.load(Ordering::SeqCst) {
        std::thread::sleep(period);
        let mut reg = lock(&core.workers);
        for (epoch, silent) in reg.expired() {
            let why = format!("no heartbeat for {:.1} s (the worker timeout is {:.1} s)", silent.as_secs_f64(), reg.timeout().as_secs_f64());
            match reg.declare_lost(&mut lock(&core.store), epoch, &why) {
                Ok(true) => {
                    let abort = reg.get(epoch).and_then(|w| lock(&core.aborts).get(&w.ad.address).cloned());
                    if let Some(h) = abort {
                        tracing::warn!("aborting the MD calls on the lost worker w{epoch}: its boxes are replayed on the job's other workers");
                        h.abort(&why);
                    } else if let Some(run) = lock(&core.running).as_ref().filter(|r| r.workers.contains(&epoch)) {
                        tracing::warn!("job {}: moves off the lost worker w{epoch} (checkpoint after this step)", run.id);
                        run.reassign.store(true, Ordering::SeqCst);
                        run.stop.store(true, Ordering::SeqCst);
                    }
                }
                Ok(false) => {}
                Err(e) => tracing::error!("cannot record worker w{epoch} as lost: {e:#}"),
            }
        }
    }
}

fn transition(core: &Core, id: &str, state: JobState, note: &str, digest: &str) {
    let detail = if state.is_final() { lock(&core.details).remove(id) } else { lock(&core.details).get(id).cloned() };
    if let Err(e) = lock(&core.store).transition_event(id, state, note, digest, &detail.unwrap_or_default()) {
        tracing::error!("job {id}: cannot record {}: {e:#}", state.as_str());
    }
    core.publish_stored(id);
}

/// How one attempt of a job on a set of workers ended.
enum Attempt {
    Done(Outcome),
    Error(anyhow::Error),
}

fn run_job(core: &Arc<Core>, job: JobRecord) {
    let id = job.id.clone();
    let flags = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)));
    *lock(&core.running) = Some(RunningJob { id: id.clone(), stop: flags.0.clone(), user_cancel: flags.1.clone(), reassign: flags.2.clone(), workers: Vec::new() });
    // A job cancelled between being picked and starting stays cancelled and is not run.
    match lock(&core.store).transition(&id, JobState::Running, if job.resumes > 0 { "resumed" } else { "started" }, "") {
        Ok(true) => {}
        Ok(false) => {
            *lock(&core.running) = None;
            return;
        }
        Err(e) => {
            tracing::error!("job {id}: cannot record running: {e:#}");
            *lock(&core.running) = None;
            // Not in a tight loop while the store fails.
            std::thread::sleep(Duration::from_secs(1));
            return;
        }
    }
    core.publish_stored(&id);
    let outcome = run_on_workers(core, &job, &flags.0, &flags.2);
    *lock(&core.running) = None;
    let stopping = core.stopping.load(Ordering::SeqCst);
    match outcome {
        Attempt::Done(Outcome::Completed(summary)) => {
            let digest = summary["state_digest"].as_str().unwrap_or_default().to_string();
            tracing::info!("job {id} completed, state_digest {digest}");
            transition(core, &id, JobState::Completed, "", &digest);
        }
        Attempt::Done(Outcome::Failed(_, why)) => {
            tracing::error!("job {id} failed: {why}");
            transition(core, &id, JobState::Failed, &why, "")
        }
        Attempt::Done(Outcome::Cancelled { checkpoint, step }) if stopping && !flags.1.load(Ordering::SeqCst) => {
            tracing::info!("job {id}: checkpointed at step {step} ({}) as the orchestrator stops", checkpoint.display());
            core.note_event(&id, EventKind::Checkpoint, &format!("checkpoint at step {step} as the orchestrator stops"));
            transition(core, &id, JobState::Queued, "the orchestrator stopped; resumes from its last checkpoint", "");
        }
        Attempt::Done(Outcome::Cancelled { step, .. }) => {
            core.note_event(&id, EventKind::Checkpoint, &format!("checkpoint at step {step} as the job is cancelled"));
            transition(core, &id, JobState::Cancelled, &format!("cancelled by a user after step {step}"), "")
        }
        Attempt::Error(e) => {
            tracing::error!("job {id} failed: {e:#}");
            transition(core, &id, JobState::Failed, &format!("{e:#}"), "")
        }
    }
}

/// Runs a job on the usable workers (in-process when there are none), moving it off workers
/// that are lost on the way: the run rolls back to its last checkpoint (from the start when
/// it has none) onto the surviving workers of the same back end and precision.
fn run_on_workers(core: &Arc<Core>, job: &JobRecord, stop: &Arc<AtomicBool>, reassign: &Arc<AtomicBool>) -> Attempt {
    let id = &job.id;
    let run_dir = core.job_dir(id).join("run");
    let loaded = match scene::load(&core.job_dir(id).join("input/scene.toml"), &job.overrides) {
        Ok(l) => l,
        Err(e) => return Attempt::Error(anyhow::anyhow!("{e}")),
    };
    // Once boxes lived on workers of one kind, they only move to workers of that kind.
    let mut kind: Option<String> = None;
    let mut rollbacks = 0;
    loop {
        let assigned = workers::choose(&lock(&core.workers).usable(), kind.as_deref());
        if let (Some(k), true) = (&kind, assigned.is_empty()) {
            return Attempt::Done(Outcome::Failed(serde_json::Value::Null, format!("no live worker of back end {k} is left to take the job's boxes")));
        }
        let epochs: Vec<u64> = assigned.iter().map(|w| w.epoch).collect();
        lock(&core.workers).set_busy(&epochs, id);
        if let Some(r) = lock(&core.running).as_mut() {
            r.workers = epochs.clone();
        }
        let last_step = Arc::new(AtomicU64::new(0));
        let result = match attempt(core, job, &loaded, &run_dir, &assigned, stop, &last_step) {
            Ok(o) => Attempt::Done(o),
            Err(e) => Attempt::Error(e),
        };
        lock(&core.workers).set_busy(&epochs, "");
        let step = last_step.load(Ordering::SeqCst);
        let why = match &result {
            Attempt::Done(Outcome::Cancelled { step, .. }) if reassign.load(Ordering::SeqCst) && !core.stopping.load(Ordering::SeqCst) && !is_user_cancel(core, id) => {
                reassign.store(false, Ordering::SeqCst);
                stop.store(false, Ordering::SeqCst);
                kind = assigned.first().map(WorkerRecord::kind);
                note(core, id, &format!("a worker was declared lost; checkpointed after step {step} and continues on the live workers"));
                continue;
            }
            Attempt::Done(Outcome::Failed(_, why)) if !assigned.is_empty() => why.clone(),
            Attempt::Error(e) if !assigned.is_empty() => format!("{e:#}"),
            _ => return result,
        };
        // Did it fail because workers are gone? (Not: an error of a worker that still answers.)
        let lost: Vec<&WorkerRecord> = assigned
            .iter()
            .filter(|w| {
                let gone = lock(&core.workers).get(w.epoch).is_none_or(|r| r.state == WorkerState::Lost);
                gone || !workers::answers(&w.ad.address, Duration::from_secs(3))
            })
            .collect();
        if lost.is_empty() {
            return result;
        }
        let at = step + 1;
        let names = lost.iter().map(|w| format!("{} at {}", w.id, w.ad.address)).collect::<Vec<_>>().join(", ");
        {
            let mut reg = lock(&core.workers);
            for w in &lost {
                if let Err(e) = reg.declare_lost(&mut lock(&core.store), w.epoch, &format!("stopped answering during step {at} of job {id}")) {
                    tracing::error!("cannot record worker {} as lost: {e:#}", w.id);
                }
            }
        }
        let k = assigned[0].kind();
        let survivors = workers::choose(&lock(&core.workers).usable(), Some(&k));
        if survivors.is_empty() {
            return Attempt::Done(Outcome::Failed(
                serde_json::Value::Null,
                format!("worker {names} was lost at step {at} ({why}); no live worker of back end {k} is left to restore its boxes onto"),
            ));
        }
        rollbacks += 1;
        if rollbacks > MAX_ROLLBACKS {
            return Attempt::Done(Outcome::Failed(serde_json::Value::Null, format!("worker {names} was lost at step {at}; the job lost workers {rollbacks} times and gives up")));
        }
        let from = crate::checkpoint::list(&run_dir).ok().and_then(|l| l.first().map(|c| c.0));
        let from = from.map_or("the start (no checkpoint yet)".to_string(), |s| format!("its checkpoint of step {s}"));
        let onto = survivors.iter().map(|w| w.id.as_str()).collect::<Vec<_>>().join(", ");
        note(core, id, &format!("worker {names} was lost at step {at}; rolled back to {from} onto {onto}"));
        tracing::warn!("job {id}: worker {names} was lost at step {at} ({why}); its boxes could not be replayed alone, so the whole job is rolling back to {from} onto {onto}");
        kind = Some(k);
    }
}

fn is_user_cancel(core: &Core, id: &str) -> bool {
    lock(&core.running).as_ref().is_some_and(|r| r.id == id && r.user_cancel.load(Ordering::SeqCst))
}

fn note(core: &Core, id: &str, text: &str) {
    core.note_event(id, EventKind::Workers, text);
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
fn attempt(core: &Arc<Core>, job: &JobRecord, loaded: &scene::LoadedScene, run_dir: &Path, assigned: &[WorkerRecord], stop: &Arc<AtomicBool>, last_step: &Arc<AtomicU64>) -> Result<Outcome> {
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
        *lock(&core3.aborts) = lock(m).pool.abort_handles().into_iter().collect();
    }));
    opts.step_deadline = core.step_deadline;
    let (core4, id4, assigned4) = (core.clone(), id.clone(), assigned.to_vec());
    opts.on_worker_lost = Some(Arc::new(move |r: &md_worker::recovery::Recovery| {
        if let Some(w) = assigned4.iter().find(|w| w.ad.address == r.worker) {
            let mut reg = lock(&core4.workers);
            if let Err(e) = reg.declare_lost(&mut lock(&core4.store), w.epoch, &format!("stopped answering during step {} of job {id4}: {}", r.step, r.why)) {
                tracing::error!("cannot record worker {} as lost: {e:#}", w.id);
            }
        }
        note(&core4, &id4, &r.to_string());
    }));
    // The run writes a checkpoint after these steps (before it reports their progress).
    let every = if opts.checkpoint_every > 0 { opts.checkpoint_every } else { loaded.scene.output.checkpoint_every_steps };
    let (core2, id2, assigned2, last_step) = (core.clone(), id.clone(), assigned.to_vec(), last_step.clone());
    let last = Mutex::new(Instant::now() - Duration::from_secs(1));
    opts.progress = Some(Arc::new(move |p: &Progress| {
        last_step.store(p.step, Ordering::SeqCst);
        let checkpoint = !p.done && every > 0 && p.step % every == 0 && p.step < p.steps;
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
        let detail = pb::JobEvent {
            end_time_s: p.end_time,
            eta_s: if p.session_steps > 0 { (p.steps - p.step.min(p.steps)) as f64 / rate } else { -1.0 },
            energy_drift: p.energy_drift,
            workers,
            ..Default::default()
        }
        .encode_to_vec();
        lock(&core2.details).insert(id2.clone(), detail.clone());
        let (kind, message) = if checkpoint { (EventKind::Checkpoint, format!("checkpoint at step {}", p.step)) } else { (EventKind::Progress, String::new()) };
        if let Err(e) = lock(&core2.store).progress_event(&id2, kind, p.step, p.steps, p.time, &message, &detail) {
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
        let shares = assigned.iter().map(|w| format!("{} at {} ({:.3e} atom-steps/s)", w.id, w.ad.address, w.ad.atom_steps_per_s)).collect::<Vec<_>>().join(", ");
        tracing::info!("job {id}: on workers {shares}");
    }
    let outcome = run::run(loaded, &opts);
    lock(&core.aborts).clear();
    outcome
}

/// Applies `f` to every string value of a TOML document.
pub fn for_each_string(item: &mut toml_edit::Item, f: &mut dyn FnMut(&mut toml_edit::Value)) {
    fn value(v: &mut toml_edit::Value, f: &mut dyn FnMut(&mut toml_edit::Value)) {
        match v {
            toml_edit::Value::String(_) => f(v),
            toml_edit::Value::Array(a) => a.iter_mut().for_each(|v| value(v, f)),
            toml_edit::Value::InlineTable(t) => t.iter_mut().for_each(|(_, v)| value(v, f)),
            _ => {}
        }
    }
    match item {
        toml_edit::Item::Value(v) => value(v, f),
        toml_edit::Item::Table(t) => t.iter_mut().for_each(|(_, i)| for_each_string(i, f)),
        toml_edit::Item::ArrayOfTables(a) => a.iter_mut().for_each(|t| t.iter_mut().for_each(|(_, i)| for_each_string(i, f))),
        toml_edit::Item::None => {}
    }
}

/// A stored input file's name: a prefix of its hash and its base name, nothing else.
fn stored_name(f: &pb::InputFile) -> String {
    let base = Path::new(&f.name).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let base: String = base.chars().map(|c| if c.is_ascii_alphanumeric() || "._-".contains(c) { c } else { '_' }).collect();
    format!("{}-{base}", &f.sha256[..16.min(f.sha256.len())])
}

/// Writes a submitted job's inputs into `dir/input` (files checked against their SHA-256, the
/// scene's references to them rewritten) and validates the scene: the error text is the one
/// `mscale check` prints.
fn prepare_inputs(dir: &Path, req: &pb::SubmitJobRequest) -> Result<scene::LoadedScene, Status> {
    let input = dir.join("input");
    std::fs::create_dir_all(input.join("files")).map_err(|e| Status::internal(format!("cannot create {}: {e}", input.display())))?;
    let mut renames = HashMap::new();
    for f in &req.files {
        let actual = hex::encode(Sha256::digest(&f.content));
        if !constant_time_eq(actual.as_bytes(), f.sha256.to_ascii_lowercase().as_bytes()) {
            return Err(Status::invalid_argument(format!("file {:?}: its content hashes to {actual}, not the SHA-256 {} it was sent with", f.name, f.sha256)));
        }
        let name = format!("files/{}", stored_name(f));
        crate::output::write_atomic(&input.join(&name), &f.content).map_err(|e| Status::internal(format!("{e:#}")))?;
        renames.insert(f.name.clone(), name);
    }
    let mut doc: toml_edit::DocumentMut = match req.scene_text.parse() {
        Ok(d) => d,
        // Not TOML: store it as is, so the scene loader reports it with its own message.
        Err(_) => toml_edit::DocumentMut::new(),
    };
    let text = if doc.is_empty() && !req.scene_text.trim().is_empty() {
        req.scene_text.clone()
    } else {
        for_each_string(doc.as_item_mut(), &mut |v| {
            if let Some(new) = v.as_str().and_then(|s| renames.get(s)) {
                let decor = v.decor().clone();
                *v = toml_edit::Value::from(new.as_str());
                *v.decor_mut() = decor;
            }
        });
        doc.to_string()
    };
    let scene_path = input.join("scene.toml");
    crate::output::write_atomic(&scene_path, text.as_bytes()).map_err(|e| Status::internal(format!("{e:#}")))?;
    scene::load(&scene_path, &req.overrides).map_err(|mut e| {
        if !req.scene_file.is_empty() {
            e.file = req.scene_file.clone();
        }
        Status::invalid_argument(e.to_string())
    })
}

/// The service: decodes, calls the core, encodes.
pub struct JobService {
    core: Arc<Core>,
}

impl JobService {
    fn authorize<T>(&self, req: &Request<T>, call: &str) -> Result<(), Status> {
        let given = req.metadata().get("authorization").and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer ")).unwrap_or("");
        if given.is_empty() {
            return Err(Status::unauthenticated(format!("{call} needs a bearer token (mscale: --token-file FILE or MSCALE_TOKEN)")));
        }
        if !constant_time_eq(given.as_bytes(), self.core.token.as_bytes()) {
            return Err(Status::unauthenticated(format!("{call}: the bearer token is not this orchestrator's")));
        }
        Ok(())
    }
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, Status> + Send + 'static) -> Result<T, Status> {
    tokio::task::spawn_blocking(f).await.map_err(|e| Status::internal(format!("task failed: {e}")))?
}

type EventStream = Pin<Box<dyn Stream<Item = Result<pb::JobEvent, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::FetchRunChunk, Status>> + Send>>;
type EventSender = tokio::sync::mpsc::Sender<Result<pb::JobEvent, Status>>;

/// Sends a watcher the job's events from `next` on, in order and each once, until the final one:
/// first from the store, then from the job's channel; whenever the channel lags or shows a
/// gap, from the store again.
async fn follow(core: &Arc<Core>, id: &str, mut next: u64, mut rx: broadcast::Receiver<Arc<pb::JobEvent>>, stop: &mut watch::Receiver<bool>, tx: &EventSender) {
    let mut catch_up = true;
    loop {
        if catch_up {
            match replay(core, id, &mut next, tx).await {
                Ok(true) => return,
                Ok(false) => catch_up = false,
                Err(s) => {
                    let _ = tx.send(Err(s)).await;
                    return;
                }
            }
        }
        if *stop.borrow() {
            let _ = tx.send(Err(Status::unavailable("the orchestrator is stopping; the job resumes when it restarts"))).await;
            return;
        }
        tokio::select! {
            r = rx.recv() => match r {
                Ok(ev) if ev.sequence < next => {}
                Ok(ev) if ev.sequence == next => {
                    next += 1;
                    let last = is_final(ev.state);
                    if tx.send(Ok((*ev).clone())).await.is_err() || last {
                        return;
                    }
                }
                // Ahead of what this watcher has (it lagged, or the event was stored by a
                // path that does not publish): the store has the ones in between.
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => catch_up = true,
                Err(broadcast::error::RecvError::Closed) => {
                    let _ = replay(core, id, &mut next, tx).await;
                    return;
                }
            },
            _ = stop.changed() => {}
        }
    }
}

/// Sends the stored events from `next` on (a hole left by pruned progress events as one
/// JOB_EVENT_KIND_NOT_RETAINED event); true when the stream is over (the final event was sent,
/// or the watcher has gone).
async fn replay(core: &Arc<Core>, id: &str, next: &mut u64, tx: &EventSender) -> Result<bool, Status> {
    loop {
        let (c, job, after) = (core.clone(), id.to_string(), *next - 1);
        let events = blocking(move || lock(&c.store).events_after(&job, after, REPLAY_BATCH).map_err(|e| Status::internal(format!("job {job}: cannot read its events: {e:#}")))).await?;
        for e in &events {
            if e.seq > *next && tx.send(Ok(not_retained(id, *next, e.seq - 1))).await.is_err() {
                return Ok(true);
            }
            *next = e.seq + 1;
            if tx.send(Ok(event_of(e))).await.is_err() || e.state.is_final() {
                return Ok(true);
            }
        }
        if events.len() < REPLAY_BATCH {
            return Ok(false);
        }
    }
}

/// The regular files under `root` (relative, `/`-separated, sorted). Symbolic links and
/// anything else that is not a directory or a regular file are skipped, never followed.
pub fn run_files(root: &Path) -> std::io::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut dirs = vec![String::new()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(root.join(&dir))? {
            let entry = entry?;
            let Ok(name) = entry.file_name().into_string() else {
                tracing::warn!("fetch: skipping {} (its name is not UTF-8)", entry.path().display());
                continue;
            };
            let rel = if dir.is_empty() { name } else { format!("{dir}/{name}") };
            let ty = entry.file_type()?; // of the entry itself: links are not followed
            if ty.is_dir() {
                dirs.push(rel);
            } else if ty.is_file() {
                files.push(rel);
            } else {
                tracing::warn!("fetch: skipping {rel} in {} (not a regular file: links are not followed)", root.display());
            }
        }
    }
    files.sort();
    Ok(files)
}

/// Streams every regular file under `root` in chunks of at most `chunk` bytes, each file's
/// last chunk with its size and SHA-256. A file that vanished since the listing (a running
/// job's old checkpoint) is skipped.
fn send_run(root: &Path, chunk: usize, tx: &tokio::sync::mpsc::Sender<Result<pb::FetchRunChunk, Status>>) -> Result<(), Status> {
    use std::io::Read;
    use std::os::unix::fs::OpenOptionsExt;
    let io = |what: &str, e: std::io::Error| Status::internal(format!("{what}: {e}"));
    for rel in run_files(root).map_err(|e| io(&root.display().to_string(), e))? {
        let path = root.join(&rel);
        // A directory on the way swapped for a link since the listing must not lead out.
        if !path.canonicalize().is_ok_and(|p| p.starts_with(root)) {
            tracing::warn!("fetch: skipping {rel} (it no longer resolves inside {})", root.display());
            continue;
        }
        let mut f = match std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW).open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(io(&rel, e)),
        };
        let (mut hasher, mut offset, mut buf) = (Sha256::new(), 0u64, vec![0u8; chunk]);
        loop {
            let mut n = 0;
            while n < chunk {
                match f.read(&mut buf[n..]).map_err(|e| io(&rel, e))? {
                    0 => break,
                    k => n += k,
                }
            }
            hasher.update(&buf[..n]);
            let last = n < chunk;
            let size = offset + n as u64;
            let sha256 = if last { hex::encode(hasher.clone().finalize()) } else { String::new() };
            let msg = pb::FetchRunChunk { path: rel.clone(), offset, data: buf[..n].to_vec(), last, size: if last { size } else { 0 }, sha256 };
            if tx.blocking_send(Ok(msg)).is_err() {
                return Ok(()); // the client has gone
            }
            offset = size;
            if last {
                break;
            }
        }
    }
    Ok(())
}

#[tonic::async_trait]
impl Orchestrator for JobService {
    async fn submit_job(&self, req: Request<pb::SubmitJobRequest>) -> Result<Response<pb::SubmitJobResponse>, Status> {
        self.authorize(&req, "SubmitJob")?;
        let req = req.into_inner();
        let core = self.core.clone();
        let id = blocking(move || {
            let id = core.new_id();
            let dir = core.job_dir(&id);
            let loaded = match prepare_inputs(&dir, &req) {
                Ok(l) => l,
                Err(s) => {
                    let _ = std::fs::remove_dir_all(&dir);
                    return Err(s);
                }
            };
            let job = JobRecord {
                id: id.clone(),
                scene: loaded.scene.name.clone(),
                state: JobState::Queued,
                priority: req.priority,
                overrides: req.overrides.clone(),
                checkpoint_every: req.checkpoint_every_steps,
                step: 0,
                steps: loaded.steps,
                sim_time: 0.0,
                error: String::new(),
                state_digest: String::new(),
                submitted: now_unix(),
                started: 0,
                finished: 0,
                resumes: 0,
            };
            lock(&core.store).insert(&job).map_err(|e| Status::internal(format!("{e:#}")))?;
            tracing::info!("job {id} queued: scene {} ({} steps), priority {}", job.scene, job.steps, job.priority);
            core.wake_runner();
            Ok(id)
        })
        .await?;
        Ok(Response::new(pb::SubmitJobResponse { job_id: id }))
    }

    async fn list_jobs(&self, _: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        let jobs = lock(&self.core.store).list().map_err(|e| Status::internal(format!("{e:#}")))?;
        Ok(Response::new(pb::ListJobsResponse { jobs: jobs.iter().map(to_pb).collect() }))
    }

    async fn get_job(&self, req: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        Ok(Response::new(to_pb(&self.core.get(&req.get_ref().job_id)?)))
    }

    type WatchJobStream = EventStream;

    async fn watch_job(&self, req: Request<pb::WatchJobRequest>) -> Result<Response<EventStream>, Status> {
        let pb::WatchJobRequest { job_id: id, after_sequence } = req.into_inner();
        let job = self.core.get(&id)?;
        let (rx, newest) = self.core.subscribe(&id)?;
        let (tx, out) = tokio::sync::mpsc::channel(16);
        if newest == 0 && job.state.is_final() {
            // A job of a store older than event numbers: its final state, unnumbered.
            drop(rx);
            self.core.unsubscribe(&id);
            let mut ev = event_of(&EventRecord { job_id: id.clone(), seq: 0, kind: EventKind::State, at: job.finished, state: job.state, step: job.step, steps: job.steps, sim_time: job.sim_time, message: job.error.clone(), detail: Vec::new() });
            ev.kind = pb::JobEventKind::Unspecified as i32;
            let _ = tx.send(Ok(ev)).await;
        } else if after_sequence > newest {
            drop(rx);
            self.core.unsubscribe(&id);
            return Err(Status::out_of_range(format!(
                "job {id} has events up to {newest}; after_sequence {after_sequence} is beyond them (is this the orchestrator, and state directory, the watch began with?)"
            )));
        } else {
            let (core, mut stop) = (self.core.clone(), self.core.stop_watchers.subscribe());
            tokio::spawn(async move {
                follow(&core, &id, after_sequence + 1, rx, &mut stop, &tx).await;
                core.unsubscribe(&id);
            });
        }
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(out))))
    }

    async fn cancel_job(&self, req: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        self.authorize(&req, "CancelJob")?;
        let id = req.into_inner().job_id;
        let job = self.core.get(&id)?;
        match job.state {
            JobState::Queued => transition(&self.core, &id, JobState::Cancelled, "cancelled by a user before it started", ""),
            JobState::Running => {
                if let Some(run) = lock(&self.core.running).as_ref().filter(|r| r.id == id) {
                    run.user_cancel.store(true, Ordering::SeqCst);
                    run.stop.store(true, Ordering::SeqCst);
                }
            }
            _ => return Err(Status::failed_precondition(format!("job {id} has already ended ({})", job.state.as_str()))),
        }
        Ok(Response::new(to_pb(&self.core.get(&id)?)))
    }

    async fn fetch_result(&self, req: Request<pb::FetchResultRequest>) -> Result<Response<pb::FetchResultResponse>, Status> {
        let req = req.into_inner();
        self.core.get(&req.job_id)?;
        let run_dir = self.core.job_dir(&req.job_id).join("run");
        let path = contained(&run_dir, &req.path)?;
        let len = std::fs::metadata(&path).map_err(|e| Status::not_found(format!("{}: {e}", req.path)))?.len();
        if len as usize > MAX_MESSAGE - 1024 {
            return Err(Status::resource_exhausted(format!("{} has {len} bytes, more than one message carries ({MAX_MESSAGE})", req.path)));
        }
        let content = std::fs::read(&path).map_err(|e| Status::not_found(format!("{}: {e}", req.path)))?;
        let sha256 = hex::encode(Sha256::digest(&content));
        Ok(Response::new(pb::FetchResultResponse { content, sha256 }))
    }

    type FetchRunStream = ChunkStream;

    async fn fetch_run(&self, req: Request<pb::FetchRunRequest>) -> Result<Response<ChunkStream>, Status> {
        let req = req.into_inner();
        self.core.get(&req.job_id)?;
        let root = self.core.job_dir(&req.job_id).join("run").canonicalize().map_err(|_| Status::not_found(format!("job {} has no run directory yet", req.job_id)))?;
        let chunk = if req.chunk_bytes == 0 { FETCH_CHUNK } else { (req.chunk_bytes as usize).min(FETCH_CHUNK) };
        let (tx, out) = tokio::sync::mpsc::channel(4);
        tokio::task::spawn_blocking(move || {
            if let Err(s) = send_run(&root, chunk, &tx) {
                let _ = tx.blocking_send(Err(s));
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(out))))
    }

    async fn register_worker(&self, req: Request<pb::RegisterWorkerRequest>) -> Result<Response<pb::RegisterWorkerResponse>, Status> {
        self.register(req).await
    }

    async fn heartbeat(&self, req: Request<pb::HeartbeatRequest>) -> Result<Response<pb::HeartbeatResponse>, Status> {
        self.authorize(&req, "Heartbeat")?;
        let r = req.into_inner();
        let drain = lock(&self.core.workers).heartbeat(&r.worker_id, r.epoch, r.protocol_version).map_err(worker_status)?;
        Ok(Response::new(pb::HeartbeatResponse { drain }))
    }

    async fn drain_worker(&self, req: Request<pb::DrainWorkerRequest>) -> Result<Response<pb::Worker>, Status> {
        self.authorize(&req, "DrainWorker")?;
        let id = req.into_inner().worker_id;
        let core = self.core.clone();
        let view = blocking(move || {
            let mut reg = lock(&core.workers);
            let w = reg.drain(&mut lock(&core.store), &id).map_err(worker_status)?;
            Ok(reg.list().into_iter().find(|v| v.record.epoch == w.epoch).ok_or_else(|| Status::internal("drained worker vanished"))?)
        })
        .await?;
        Ok(Response::new(worker_to_pb(&view)))
    }

    async fn list_workers(&self, _: Request<pb::ListWorkersRequest>) -> Result<Response<pb::ListWorkersResponse>, Status> {
        let workers = lock(&self.core.workers).list().iter().map(worker_to_pb).collect();
        Ok(Response::new(pb::ListWorkersResponse { workers }))
    }
}

/// The worker RPCs, off the trait impl to keep it to decoding and encoding.
impl JobService {
    async fn register(&self, req: Request<pb::RegisterWorkerRequest>) -> Result<Response<pb::RegisterWorkerResponse>, Status> {
        self.authorize(&req, "RegisterWorker")?;
        let r = req.into_inner();
        let ad = WorkerAd {
            address: r.address,
            device: r.device,
            backend: r.backend,
            precision: r.precision,
            cores: r.cores,
            memory_bytes: r.memory_bytes,
            atom_steps_per_s: r.atom_steps_per_s,
            throughput_source: r.throughput_source,
            protocol_version: r.protocol_version,
        };
        let core = self.core.clone();
        let (w, timeout) = blocking(move || {
            let mut reg = lock(&core.workers);
            let w = reg.register(&mut lock(&core.store), ad).map_err(worker_status)?;
            Ok((w, reg.timeout()))
        })
        .await?;
        tracing::info!("worker {} registered: {} ({}, {}/{}), {:.3e} atom-steps/s ({})", w.id, w.ad.address, w.ad.device, w.ad.backend, w.ad.precision, w.ad.atom_steps_per_s, w.ad.throughput_source);
        self.core.wake_runner();
        Ok(Response::new(pb::RegisterWorkerResponse { worker_id: w.id, epoch: w.epoch, timeout_s: timeout.as_secs_f64() }))
    }
}

/// `rel` inside `root`, refusing absolute paths, `..`, and links that lead out.
pub fn contained(root: &Path, rel: &str) -> Result<PathBuf, Status> {
    let refuse = || Status::invalid_argument(format!("{rel:?} is not a path inside the job's run directory"));
    let p = Path::new(rel);
    if rel.is_empty() || p.components().any(|c| !matches!(c, Component::Normal(_))) {
        return Err(refuse());
    }
    let root = root.canonicalize().map_err(|_| Status::not_found("the job has no run directory yet"))?;
    let full = root.join(p).canonicalize().map_err(|e| Status::not_found(format!("{rel}: {e}")))?;
    if !full.starts_with(&root) || !full.is_file() {
        return Err(refuse());
    }
    Ok(full)
}

/// Runs the orchestrator until SIGINT/SIGTERM. Prints `mscale serve: listening on ADDR` on
/// stdout once it answers calls.
pub fn serve(opts: ServeOptions) -> Result<()> {
    let addr: SocketAddr = opts.listen.parse().with_context(|| format!("--listen {:?} is not an address like 127.0.0.1:50100", opts.listen))?;
    if !addr.ip().is_loopback() && opts.tls.is_none() {
        bail!("refusing to listen on {addr} without TLS: tokens must not cross a network in clear text; pass --tls-cert and --tls-key, or listen on a loopback address (127.0.0.1 or [::1])");
    }
    let mut store = Store::open(&opts.state_dir)?;
    for id in store.requeue_interrupted()? {
        tracing::info!("job {id} was running when the orchestrator stopped: queued again, resumes from its last checkpoint");
    }
    let registry = Registry::load(&store, opts.worker_timeout)?;
    let core = Arc::new(Core {
        workers: Mutex::new(registry),
        expect_workers: opts.local_workers,
        started: Instant::now(),
        store: Mutex::new(store),
        state_dir: opts.state_dir.clone(),
        token: opts.token,
        checkpoint_every: opts.checkpoint_every,
        live: Mutex::new(HashMap::new()),
        details: Mutex::new(HashMap::new()),
        running: Mutex::new(None),
        stopping: AtomicBool::new(false),
        stop_watchers: watch::channel(false).0,
        wake: (Mutex::new(false), Condvar::new()),
        next_id: AtomicU64::new(0),
        step_deadline: opts.step_deadline,
        aborts: Mutex::new(HashMap::new()),
    });
    let listener = std::net::TcpListener::bind(addr).with_context(|| format!("cannot listen on {addr}"))?;
    listener.set_nonblocking(true)?;
    let bound = listener.local_addr()?;
    // Started from this (the main) thread: they die with the process (see LocalWorkers), and
    // are killed when `_local` is dropped, after the runner stopped.
    let scheme = if opts.tls.is_some() { "https" } else { "http" };
    let _local = workers::LocalWorkers::start(opts.local_workers, &format!("{scheme}://{bound}"), &opts.token_file, opts.local_ca.as_deref(), &opts.state_dir.join("workers"))?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the gRPC runtime")?;
    let runner_core = core.clone();
    let runner_thread = std::thread::Builder::new().name("job-runner".into()).spawn(move || runner(runner_core)).context("cannot start the job runner")?;
    let monitor_core = core.clone();
    let monitor_thread = std::thread::Builder::new().name("worker-monitor".into()).spawn(move || monitor(monitor_core)).context("cannot start the worker monitor")?;
    let result = rt.block_on(async {
        let listener = tokio::net::TcpListener::from_std(listener)?;
        let (mut health, health_service) = tonic_health::server::health_reporter();
        health.set_not_serving::<OrchestratorServer<JobService>>().await;
        let reflection = tonic_reflection::server::Builder::configure().register_encoded_file_descriptor_set(mscale_proto::FILE_DESCRIPTOR_SET).build_v1().context("reflection")?;
        let service = OrchestratorServer::new(JobService { core: core.clone() }).max_decoding_message_size(MAX_MESSAGE).max_encoding_message_size(MAX_MESSAGE);
        health.set_serving::<OrchestratorServer<JobService>>().await;
        println!("mscale serve: listening on {bound}");
        use std::io::Write;
        let _ = std::io::stdout().flush();
        tracing::info!("state in {}", opts.state_dir.display());
        let shutdown = async {
            let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = async { match term.as_mut() { Some(t) => { t.recv().await; } None => std::future::pending::<()>().await } } => {}
            }
            tracing::info!("stopping: the running job checkpoints and resumes on the next start");
            stop(&core);
        };
        // Accepted sockets get TCP_NODELAY (the builder's setting covers only listeners tonic
        // binds itself): without it, delayed ACKs hold small replies back by ~40 ms.
        let incoming = tonic::transport::server::TcpIncoming::from_listener(listener, true, None).map_err(|e| anyhow::anyhow!("listening: {e}"))?;
        let mut builder = tonic::transport::Server::builder();
        if let Some((cert, key)) = &opts.tls {
            builder = builder.tls_config(tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(cert, key))).context("bad TLS certificate or key")?;
        }
        builder
            .timeout(Duration::from_secs(60))
            .http2_keepalive_interval(Some(Duration::from_secs(30)))
            .add_service(health_service)
            .add_service(reflection)
            .add_service(service)
            .serve_with_incoming_shutdown(incoming, shutdown)
            .await
            .context("serving")
    });
    stop(&core);
    let _ = runner_thread.join();
    let _ = monitor_thread.join();
    result
}

/// Stops the runner (the running job checkpoints and stays queued) and ends watch streams.
fn stop(core: &Core) {
    core.stopping.store(true, Ordering::SeqCst);
    if let Some(run) = lock(&core.running).as_ref() {
        run.stop.store(true, Ordering::SeqCst);
    }
    core.stop_watchers.send_replace(true);
    core.wake_runner();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fetch_paths_cannot_leave_the_run_directory() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        std::fs::create_dir_all(run.join("snapshots")).unwrap();
        std::fs::write(run.join("summary.json"), "{}").unwrap();
        std::fs::write(run.join("snapshots/index.csv"), "x").unwrap();
        std::fs::write(dir.path().join("secret"), "s").unwrap();
        std::os::unix::fs::symlink(dir.path().join("secret"), run.join("link")).unwrap();
        assert!(contained(&run, "summary.json").is_ok());
        assert!(contained(&run, "snapshots/index.csv").is_ok());
        for bad in ["../secret", "/etc/passwd", "snapshots/../../secret", "link", "", "snapshots", "./summary.json"] {
            assert!(contained(&run, bad).is_err(), "{bad} was let through");
        }
    }

    /// A core over a store in `dir`, with no workers and no runner.
    fn test_core(dir: &Path) -> Arc<Core> {
        let store = Store::open(dir).unwrap();
        let registry = Registry::load(&store, Duration::from_secs(15)).unwrap();
        Arc::new(Core {
            workers: Mutex::new(registry),
            expect_workers: 0,
            started: Instant::now(),
            store: Mutex::new(store),
            state_dir: dir.to_path_buf(),
            token: "t".into(),
            checkpoint_every: 0,
            live: Mutex::new(HashMap::new()),
            details: Mutex::new(HashMap::new()),
            running: Mutex::new(None),
            stopping: AtomicBool::new(false),
            stop_watchers: watch::channel(false).0,
            wake: (Mutex::new(false), Condvar::new()),
            next_id: AtomicU64::new(0),
            step_deadline: Default::default(),
            aborts: Mutex::new(HashMap::new()),
        })
    }

    #[test]
    fn a_watcher_that_falls_behind_is_caught_up_from_the_store() {
        let dir = tempfile::tempdir().unwrap();
        let core = test_core(dir.path());
        let job = JobRecord {
            id: "j1".into(),
            scene: "s".into(),
            state: JobState::Queued,
            priority: 0,
            overrides: Vec::new(),
            checkpoint_every: 0,
            step: 0,
            steps: 1000,
            sim_time: 0.0,
            error: String::new(),
            state_digest: String::new(),
            submitted: now_unix(),
            started: 0,
            finished: 0,
            resumes: 0,
        };
        lock(&core.store).insert(&job).unwrap();
        let published = WATCH_BACKLOG as u64 + 50;
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let (rx, newest) = core.subscribe("j1").unwrap();
            assert_eq!(newest, 1);
            let (tx, mut out) = tokio::sync::mpsc::channel(100_000);
            let (c, mut stop) = (core.clone(), core.stop_watchers.subscribe());
            let watcher = tokio::spawn(async move { follow(&c, "j1", 1, rx, &mut stop, &tx).await });
            // The stored event comes first (replayed); then the watcher waits on the channel.
            assert_eq!(out.recv().await.unwrap().unwrap().sequence, 1);
            // More events than the channel holds, published while the watcher cannot run (one
            // thread, no await): its receiver lags and loses the oldest.
            transition(&core, "j1", JobState::Running, "started", "");
            for k in 1..=published {
                lock(&core.store).progress_event("j1", EventKind::Progress, k, 1000, 0.0, "", &[]).unwrap();
                core.publish_stored("j1");
            }
            transition(&core, "j1", JobState::Completed, "", "digest");
            let mut seqs = vec![1];
            while let Some(ev) = out.recv().await {
                let ev = ev.unwrap();
                seqs.push(ev.sequence);
                if is_final(ev.state) {
                    break;
                }
            }
            assert_eq!(seqs, (1..=published + 3).collect::<Vec<_>>(), "the watcher skipped events");
            watcher.await.unwrap();
        });
        // The watcher has gone: its channel too.
        assert!(lock(&core.live).get("j1").is_some_and(|j| j.tx.receiver_count() == 0));
        core.unsubscribe("j1");
        assert!(lock(&core.live).is_empty());
    }

    #[test]
    fn tokens_compare_whole() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
    }
}
