//! Conversions between the service's domain types and `mscale.orchestrator.v1`.

use super::fetch::Chunk;
use super::inputs::{InputFile, Submission};
use super::store::{EventKind, EventRecord, JobRecord, JobState, WorkerAd, WorkerState};
use super::workers::WorkerView;
use mscale_proto::orchestrator::v1 as pb;
use prost::Message;

pub(crate) fn pb_worker_state(s: WorkerState) -> pb::WorkerState {
    match s {
        WorkerState::Live => pb::WorkerState::Live,
        WorkerState::Draining => pb::WorkerState::Draining,
        WorkerState::Lost => pb::WorkerState::Lost,
    }
}

impl TryFrom<pb::WorkerState> for WorkerState {
    type Error = pb::WorkerState;
    fn try_from(s: pb::WorkerState) -> Result<Self, pb::WorkerState> {
        match s {
            pb::WorkerState::Live => Ok(WorkerState::Live),
            pb::WorkerState::Draining => Ok(WorkerState::Draining),
            pb::WorkerState::Lost => Ok(WorkerState::Lost),
            other => Err(other),
        }
    }
}

pub(crate) fn worker_to_pb(v: &WorkerView) -> pb::Worker {
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

impl From<pb::RegisterWorkerRequest> for WorkerAd {
    fn from(r: pb::RegisterWorkerRequest) -> Self {
        WorkerAd {
            address: r.address,
            device: r.device,
            backend: r.backend,
            precision: r.precision,
            cores: r.cores,
            memory_bytes: r.memory_bytes,
            atom_steps_per_s: r.atom_steps_per_s,
            throughput_source: r.throughput_source,
            protocol_version: r.protocol_version,
        }
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

impl TryFrom<pb::JobState> for JobState {
    type Error = pb::JobState;
    fn try_from(s: pb::JobState) -> Result<Self, pb::JobState> {
        match s {
            pb::JobState::Queued => Ok(JobState::Queued),
            pb::JobState::Running => Ok(JobState::Running),
            pb::JobState::Completed => Ok(JobState::Completed),
            pb::JobState::Failed => Ok(JobState::Failed),
            pb::JobState::Cancelled => Ok(JobState::Cancelled),
            other => Err(other),
        }
    }
}

pub(crate) fn job_to_pb(j: &JobRecord) -> pb::Job {
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
        owner: j.owner.clone(),
        workers: j.workers,
        ranks: j.ranks,
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
pub(crate) fn event_of(e: &EventRecord) -> pb::JobEvent {
    let mut ev = pb::JobEvent::decode(e.detail.as_slice()).unwrap_or_else(|_| pb::JobEvent { eta_s: -1.0, ..Default::default() });
    if e.detail.is_empty() {
        ev.eta_s = -1.0;
    }
    ev.job_id = e.job_id.clone();
    ev.state = pb_state(e.state) as i32;
    ev.step = e.step;
    ev.steps = e.steps;
    ev.sim_time_s = e.sim_time;
    // A run whose steps are not known in advance (a cell run's adaptive steps): by time.
    ev.percent = if e.steps > 0 {
        100.0 * e.step as f64 / e.steps as f64
    } else if ev.end_time_s > 0.0 {
        (100.0 * e.sim_time / ev.end_time_s).clamp(0.0, 100.0)
    } else {
        0.0
    };
    ev.message = e.message.clone();
    ev.sequence = e.seq;
    ev.kind = pb_event_kind(e.kind) as i32;
    ev.at_unix = e.at;
    ev
}

/// The event that stands for events `from..=to` no longer retained.
pub(crate) fn not_retained(id: &str, from: u64, to: u64) -> pb::JobEvent {
    pb::JobEvent {
        job_id: id.to_string(),
        sequence: to,
        not_retained_from: from,
        kind: pb::JobEventKind::NotRetained as i32,
        eta_s: -1.0,
        message: format!(
            "events {from} to {to} of job {id} are no longer retained (old progress events are pruned); they cannot be replayed"
        ),
        ..Default::default()
    }
}

/// Whether a `pb::JobState` value is a final state.
pub(crate) fn is_final(state: i32) -> bool {
    matches!(pb::JobState::try_from(state), Ok(pb::JobState::Completed | pb::JobState::Failed | pb::JobState::Cancelled))
}

impl From<pb::SubmitJobRequest> for Submission {
    fn from(r: pb::SubmitJobRequest) -> Self {
        Submission {
            scene_text: r.scene_text,
            files: r.files.into_iter().map(|f| InputFile { name: f.name, sha256: f.sha256, content: f.content }).collect(),
            overrides: r.overrides,
            priority: r.priority,
            checkpoint_every: r.checkpoint_every_steps,
            scene_file: r.scene_file,
            workers: r.workers,
            ranks: r.ranks,
        }
    }
}

impl From<Chunk> for pb::FetchRunChunk {
    fn from(c: Chunk) -> Self {
        pb::FetchRunChunk { path: c.path, offset: c.offset, data: c.data, last: c.last, size: c.size, sha256: c.sha256 }
    }
}
