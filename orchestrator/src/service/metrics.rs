//! Prometheus metrics of `mscale serve` (`GET /metrics` on `--http ADDR`, text format).
//!
//! Counted as things happen: per job its step, steps, steps per second and atom-steps (total
//! and per second), per worker its measured atom-steps per second in the running job, gRPC
//! call latencies by method (to the response head), recoveries of lost workers (`replay`: only
//! the lost worker's boxes were rebuilt; `rollback`: the whole job went back to a checkpoint),
//! and checkpoint sizes and write times. Read from the store at each scrape: jobs by state,
//! the queue length and workers by state.

use super::shared::{Core, lock};
use super::store::{JobState, WorkerState};
use md_worker::metrics::{FloatGauge, HistogramFamily, MethodLabels, latency_histogram, size_histogram};
use mscale_proto::orchestrator::v1 as pb;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;
use std::collections::HashMap;
use std::sync::Mutex;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub(crate) struct StateLabels {
    pub(crate) state: String,
}

/// `job_id`, not `job`: Prometheus's own `job` label names the scrape job.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub(crate) struct JobLabels {
    pub(crate) job_id: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub(crate) struct WorkerLabels {
    pub(crate) job_id: String,
    pub(crate) worker: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub(crate) struct KindLabels {
    pub(crate) kind: String,
}

/// What `mscale serve` counts.
pub(crate) struct Metrics {
    registry: Registry,
    jobs: Family<StateLabels, Gauge>,
    queue: Gauge,
    workers: Family<StateLabels, Gauge>,
    job_step: Family<JobLabels, Gauge>,
    job_steps: Family<JobLabels, Gauge>,
    job_steps_per_second: Family<JobLabels, FloatGauge>,
    job_atom_steps: Family<JobLabels, Counter>,
    job_atom_steps_per_second: Family<JobLabels, FloatGauge>,
    worker_atom_steps_per_second: Family<WorkerLabels, FloatGauge>,
    worker_atom_steps: Family<WorkerLabels, Counter>,
    pub(crate) rpc: HistogramFamily<MethodLabels>,
    recoveries: Family<KindLabels, Counter>,
    checkpoints: Family<JobLabels, Counter>,
    checkpoint_bytes: Family<JobLabels, Gauge>,
    checkpoint_size: Histogram,
    checkpoint_seconds: Histogram,
    /// Atom-steps already counted, per (job, endpoint) of the current attempt.
    seen: Mutex<HashMap<(String, usize), f64>>,
}

/// One sample of a running job (from its progress callback).
pub(crate) struct Sample<'a> {
    pub(crate) job: &'a str,
    pub(crate) step: u64,
    pub(crate) steps: u64,
    pub(crate) steps_per_second: f64,
    pub(crate) session_seconds: f64,
    /// The MD pool's load per endpoint this attempt (empty: no MD or its lock was busy).
    pub(crate) load: &'a [md_worker::pool::EndpointLoad],
    /// The job's workers as its events show them (empty: MD in the orchestrator's process).
    pub(crate) workers: &'a [pb::JobWorker],
}

impl Metrics {
    pub(crate) fn new() -> Metrics {
        let mut r = Registry::default();
        let m = Metrics {
            registry: Registry::default(),
            jobs: Family::default(),
            queue: Gauge::default(),
            workers: Family::default(),
            job_step: Family::default(),
            job_steps: Family::default(),
            job_steps_per_second: Family::default(),
            job_atom_steps: Family::default(),
            job_atom_steps_per_second: Family::default(),
            worker_atom_steps_per_second: Family::default(),
            worker_atom_steps: Family::default(),
            rpc: Family::new_with_constructor(latency_histogram),
            recoveries: Family::default(),
            checkpoints: Family::default(),
            checkpoint_bytes: Family::default(),
            checkpoint_size: size_histogram(),
            checkpoint_seconds: latency_histogram(),
            seen: Mutex::default(),
        };
        r.register("mscale_jobs", "Jobs in the store by state", m.jobs.clone());
        r.register("mscale_queue_length", "Jobs queued (waiting to run)", m.queue.clone());
        r.register("mscale_workers", "Registered workers by state", m.workers.clone());
        r.register("mscale_job_step", "The job's last completed step", m.job_step.clone());
        r.register("mscale_job_steps", "Steps the job runs in all", m.job_steps.clone());
        r.register("mscale_job_steps_per_second", "Steps per wall second of the job's current session", m.job_steps_per_second.clone());
        r.register("mscale_job_atom_steps", "MD atom-steps computed for the job", m.job_atom_steps.clone());
        r.register(
            "mscale_job_atom_steps_per_second",
            "MD atom-steps per wall second of the job's current attempt",
            m.job_atom_steps_per_second.clone(),
        );
        r.register(
            "mscale_worker_atom_steps_per_second",
            "MD atom-steps per second of a worker's step calls in the job (compute and transfer)",
            m.worker_atom_steps_per_second.clone(),
        );
        r.register("mscale_worker_atom_steps", "MD atom-steps a worker computed for the job", m.worker_atom_steps.clone());
        r.register("mscale_rpc_duration_seconds", "gRPC calls served, to the response head (s)", m.rpc.clone());
        r.register(
            "mscale_recoveries",
            "Recoveries from lost workers (replay: only its boxes; rollback: the whole job)",
            m.recoveries.clone(),
        );
        r.register("mscale_checkpoints", "Checkpoints written for the job", m.checkpoints.clone());
        r.register("mscale_checkpoint_bytes", "Size of the job's newest checkpoint (bytes)", m.checkpoint_bytes.clone());
        r.register("mscale_checkpoint_size_bytes", "Checkpoint sizes (bytes)", m.checkpoint_size.clone());
        r.register("mscale_checkpoint_write_seconds", "Time to encode and durably write one checkpoint (s)", m.checkpoint_seconds.clone());
        // Every kind is exposed from the start (at 0), so dashboards and alerts find them.
        for kind in ["replay", "rollback", "move"] {
            let _ = m.recoveries.get_or_create(&KindLabels { kind: kind.to_string() });
        }
        Metrics { registry: r, ..m }
    }

    /// Records a running job's progress.
    pub(crate) fn sample(&self, s: &Sample) {
        let job = JobLabels { job_id: s.job.to_string() };
        self.job_step.get_or_create(&job).set(s.step as i64);
        self.job_steps.get_or_create(&job).set(s.steps as i64);
        self.job_steps_per_second.get_or_create(&job).set(s.steps_per_second);
        let mut seen = lock(&self.seen);
        let mut attempt_total = 0.0;
        for (k, l) in s.load.iter().enumerate() {
            attempt_total += l.atom_steps;
            let before = seen.insert((s.job.to_string(), k), l.atom_steps).unwrap_or(0.0);
            let new = (l.atom_steps - before).max(0.0).round() as u64;
            let worker = s.workers.get(k).map_or_else(|| l.name.clone(), |w| w.worker_id.clone());
            let labels = WorkerLabels { job_id: s.job.to_string(), worker };
            self.job_atom_steps.get_or_create(&job).inc_by(new);
            self.worker_atom_steps.get_or_create(&labels).inc_by(new);
            if l.step_seconds > 0.0 {
                self.worker_atom_steps_per_second.get_or_create(&labels).set(l.atom_steps / l.step_seconds);
            }
        }
        if s.session_seconds > 0.0 && !s.load.is_empty() {
            self.job_atom_steps_per_second.get_or_create(&job).set(attempt_total / s.session_seconds);
        }
    }

    /// A new attempt of a job starts (a new MD pool, whose load counts from zero).
    pub(crate) fn new_attempt(&self, job: &str) {
        lock(&self.seen).retain(|k, _| k.0 != job);
    }

    /// The job's final sample was taken: its per-worker rates stay, its bookkeeping goes.
    pub(crate) fn job_over(&self, job: &str) {
        self.new_attempt(job);
        self.job_steps_per_second.get_or_create(&JobLabels { job_id: job.to_string() }).set(0.0);
    }

    /// A lost worker was recovered from (`replay` or `rollback`).
    pub(crate) fn recovery(&self, kind: &str) {
        self.recoveries.get_or_create(&KindLabels { kind: kind.to_string() }).inc();
    }

    /// A checkpoint of `job` was written: `bytes` in `seconds`.
    pub(crate) fn checkpoint(&self, job: &str, bytes: u64, seconds: f64) {
        let l = JobLabels { job_id: job.to_string() };
        self.checkpoints.get_or_create(&l).inc();
        self.checkpoint_bytes.get_or_create(&l).set(bytes as i64);
        self.checkpoint_size.observe(bytes as f64);
        self.checkpoint_seconds.observe(seconds);
    }

    /// The text exposition, with jobs and workers by state read now.
    pub(crate) fn render(&self, core: &Core) -> String {
        let jobs = lock(&core.store).list();
        match jobs {
            Ok(jobs) => {
                for s in [JobState::Queued, JobState::Running, JobState::Completed, JobState::Failed, JobState::Cancelled] {
                    let n = jobs.iter().filter(|j| j.state == s).count();
                    self.jobs.get_or_create(&StateLabels { state: s.as_str().to_string() }).set(n as i64);
                }
                self.queue.set(jobs.iter().filter(|j| j.state == JobState::Queued).count() as i64);
            }
            Err(e) => tracing::warn!("metrics: cannot list the jobs: {e:#}"),
        }
        let workers = lock(&core.workers).list();
        for s in [WorkerState::Live, WorkerState::Draining, WorkerState::Lost] {
            let n = workers.iter().filter(|w| w.record.state == s).count();
            self.workers.get_or_create(&StateLabels { state: s.as_str().to_string() }).set(n as i64);
        }
        md_worker::metrics::render(&self.registry)
    }
}
