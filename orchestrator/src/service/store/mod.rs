//! The persistent job store of `mscale serve`: one SQLite file (`<state>/jobs.sqlite`,
//! compiled in with rusqlite's `bundled` feature). Every state change is one transaction and
//! appends a row to the job's history, so jobs and their history survive a restart; a job
//! found `running` when the store is opened was interrupted (the orchestrator died) and goes
//! back to the queue, to resume from its last checkpoint.
//!
//! Workers that joined the pool are kept here too (`workers`, `worker_history`): every
//! registration is a new row whose sequence number is the worker's epoch, so a worker that
//! rejoins is a new worker; `lost` is final.
//!
//! Every event a watcher can see (`events`) is numbered per job (1, 2, 3, ... with no gaps)
//! and written in the transaction of the change it reports, so the numbering and the state
//! changes survive a restart together. Old progress events are pruned (see
//! [`Store::set_progress_retention`]); state, checkpoint and worker events are kept.

use anyhow::{Context, Result};
use rusqlite::{Connection, OptionalExtension, params};
pub use schema::SCHEMA_VERSION;
use schema::migrations;
use std::path::Path;

mod schema;
mod workers;
pub use workers::{WorkerAd, WorkerRecord, WorkerState};

/// Where a job is in its life (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, strum::IntoStaticStr, strum::EnumString)]
#[strum(serialize_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Completed,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    pub fn parse(s: &str) -> Result<Self> {
        s.parse().map_err(|_| anyhow::anyhow!("unknown job state {s:?} in the store"))
    }

    pub fn is_final(self) -> bool {
        matches!(self, JobState::Completed | JobState::Failed | JobState::Cancelled)
    }
}

/// One job as stored.
#[derive(Debug, Clone)]
pub struct JobRecord {
    pub id: String,
    pub scene: String,
    pub state: JobState,
    pub priority: i32,
    /// `--set` overrides, in order.
    pub overrides: Vec<String>,
    pub checkpoint_every: u64,
    pub step: u64,
    pub steps: u64,
    /// s.
    pub sim_time: f64,
    pub error: String,
    pub state_digest: String,
    pub submitted: i64,
    pub started: i64,
    pub finished: i64,
    pub resumes: u32,
    /// The user who submitted it.
    pub owner: String,
    /// Workers it asked for (0: every free worker).
    pub workers: u32,
    /// MPI ranks its continuum runs over (1: in the orchestrator's process).
    pub ranks: u32,
}

/// What a job event reports (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, strum::IntoStaticStr, strum::EnumString)]
#[strum(serialize_all = "lowercase")]
pub enum EventKind {
    /// The job's state changed.
    State,
    Progress,
    /// A checkpoint was written at the event's step.
    Checkpoint,
    /// A worker was lost, or the job moved onto other workers.
    Workers,
}

impl EventKind {
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    pub fn parse(s: &str) -> Result<Self> {
        s.parse().map_err(|_| anyhow::anyhow!("unknown event kind {s:?} in the store"))
    }
}

/// One numbered event of a job, as stored.
#[derive(Debug, Clone)]
pub struct EventRecord {
    pub job_id: String,
    /// Per job: 1, 2, 3, ... with no gaps.
    pub seq: u64,
    pub kind: EventKind,
    /// Unix seconds.
    pub at: i64,
    /// The job's state, step, steps and simulated time (s) when it happened.
    pub state: JobState,
    pub step: u64,
    pub steps: u64,
    pub sim_time: f64,
    pub message: String,
    /// What the service adds (progress details, workers), encoded by it; empty when none.
    pub detail: Vec<u8>,
}

/// Progress events kept per job by default (older ones are pruned; other kinds are kept).
pub const RETAINED_PROGRESS_EVENTS: u64 = 10_000;

pub struct Store {
    db: Connection,
    retained_progress: u64,
}

pub fn now_unix() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0)
}

const COLUMNS: &str = "id, scene, state, priority, overrides, checkpoint_every, step, steps, sim_time, error, state_digest, submitted, started, finished, resumes, owner, workers, ranks";

fn record(r: &rusqlite::Row<'_>) -> rusqlite::Result<(JobRecord, String)> {
    let overrides: String = r.get(4)?;
    let state: String = r.get(2)?;
    Ok((
        JobRecord {
            id: r.get(0)?,
            scene: r.get(1)?,
            state: JobState::Queued,
            priority: r.get(3)?,
            overrides: serde_json::from_str(&overrides).unwrap_or_default(),
            checkpoint_every: r.get::<_, i64>(5)? as u64,
            step: r.get::<_, i64>(6)? as u64,
            steps: r.get::<_, i64>(7)? as u64,
            sim_time: r.get(8)?,
            error: r.get(9)?,
            state_digest: r.get(10)?,
            submitted: r.get(11)?,
            started: r.get(12)?,
            finished: r.get(13)?,
            resumes: r.get::<_, i64>(14)? as u32,
            owner: r.get(15)?,
            workers: r.get::<_, i64>(16)? as u32,
            ranks: r.get::<_, i64>(17)? as u32,
        },
        state,
    ))
}

fn finish_record((mut j, state): (JobRecord, String)) -> Result<JobRecord> {
    j.state = JobState::parse(&state)?;
    Ok(j)
}

impl Store {
    /// Opens (creating if needed) the store in `state_dir`.
    pub fn open(state_dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(state_dir).with_context(|| format!("cannot create the state directory {}", state_dir.display()))?;
        let path = state_dir.join("jobs.sqlite");
        let mut db = Connection::open(&path).with_context(|| format!("cannot open the job store {}", path.display()))?;
        db.execute_batch("PRAGMA journal_mode = WAL; PRAGMA synchronous = FULL;")
            .with_context(|| format!("cannot set up the job store {}", path.display()))?;
        migrations()
            .to_latest(&mut db)
            .with_context(|| format!("cannot bring the job store {} to schema version {SCHEMA_VERSION}", path.display()))?;
        Ok(Store { db, retained_progress: RETAINED_PROGRESS_EVENTS })
    }

    /// Keep at most about `n` of each job's newest progress events (at least 1).
    pub fn set_progress_retention(&mut self, n: u64) {
        self.retained_progress = n.max(1);
    }

    /// Puts every job left `running` by a dead orchestrator back in the queue (one
    /// transaction); returns their ids.
    pub fn requeue_interrupted(&mut self) -> Result<Vec<String>> {
        let tx = self.db.transaction()?;
        let ids: Vec<String> = {
            let mut q = tx.prepare("SELECT id FROM jobs WHERE state = 'running' ORDER BY seq")?;
            q.query_map([], |r| r.get(0))?.collect::<rusqlite::Result<_>>()?
        };
        for id in &ids {
            tx.execute("UPDATE jobs SET state = 'queued', resumes = resumes + 1 WHERE id = ?1", params![id])?;
            let note = "the orchestrator restarted; resumes from its last checkpoint";
            tx.execute("INSERT INTO history VALUES (?1, ?2, 'queued', ?3)", params![id, now_unix(), note])?;
            append_event(&tx, id, EventKind::State, note, &[], 0)?;
        }
        tx.commit()?;
        Ok(ids)
    }

    pub fn insert(&mut self, job: &JobRecord) -> Result<()> {
        let tx = self.db.transaction()?;
        tx.execute(
            "INSERT INTO jobs (id, scene, state, priority, overrides, checkpoint_every, steps, submitted, owner, workers, ranks) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
            params![job.id, job.scene, job.state.as_str(), job.priority, serde_json::to_string(&job.overrides)?, job.checkpoint_every as i64, job.steps as i64, job.submitted, job.owner, job.workers as i64, job.ranks as i64],
        )?;
        tx.execute("INSERT INTO history VALUES (?1, ?2, ?3, 'submitted')", params![job.id, job.submitted, job.state.as_str()])?;
        append_event(&tx, &job.id, EventKind::State, "submitted", &[], 0)?;
        tx.commit()?;
        Ok(())
    }

    pub fn get(&self, id: &str) -> Result<Option<JobRecord>> {
        let r = self.db.query_row(&format!("SELECT {COLUMNS} FROM jobs WHERE id = ?1"), params![id], record).optional()?;
        r.map(finish_record).transpose()
    }

    /// Every job, oldest first.
    pub fn list(&self) -> Result<Vec<JobRecord>> {
        let mut q = self.db.prepare(&format!("SELECT {COLUMNS} FROM jobs ORDER BY seq"))?;
        let rows = q.query_map([], record)?.collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter().map(finish_record).collect()
    }

    /// The jobs of `owner`, oldest first.
    pub fn list_of(&self, owner: &str) -> Result<Vec<JobRecord>> {
        let mut q = self.db.prepare(&format!("SELECT {COLUMNS} FROM jobs WHERE owner = ?1 ORDER BY seq"))?;
        let rows = q.query_map(params![owner], record)?.collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter().map(finish_record).collect()
    }

    /// How many jobs of `owner` are queued or running.
    pub fn active_jobs(&self, owner: &str) -> Result<u64> {
        let n: i64 =
            self.db
                .query_row("SELECT COUNT(*) FROM jobs WHERE owner = ?1 AND state IN ('queued', 'running')", params![owner], |r| r.get(0))?;
        Ok(n as u64)
    }

    /// Every queued job in the order of the queue: highest priority, then oldest.
    pub fn queued(&self) -> Result<Vec<JobRecord>> {
        let mut q = self.db.prepare(&format!("SELECT {COLUMNS} FROM jobs WHERE state = 'queued' ORDER BY priority DESC, seq ASC"))?;
        let rows = q.query_map([], record)?.collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter().map(finish_record).collect()
    }

    /// The queued job to run next: highest priority, then oldest.
    pub fn next_queued(&self) -> Result<Option<JobRecord>> {
        let r = self
            .db
            .query_row(&format!("SELECT {COLUMNS} FROM jobs WHERE state = 'queued' ORDER BY priority DESC, seq ASC LIMIT 1"), [], record)
            .optional()?;
        r.map(finish_record).transpose()
    }

    /// Moves a job to `state` (one transaction, with a history row); `error` and `digest` are
    /// kept when empty. Returns false when the job was already in a final state.
    pub fn transition(&mut self, id: &str, state: JobState, note: &str, digest: &str) -> Result<bool> {
        Ok(self.transition_event(id, state, note, digest, &[])?.is_some())
    }

    /// [`Store::transition`] that also returns the numbered state event it stored (with
    /// `detail`, the service's encoding of what the job row does not hold); None when the job
    /// was already in a final state.
    pub fn transition_event(&mut self, id: &str, state: JobState, note: &str, digest: &str, detail: &[u8]) -> Result<Option<EventRecord>> {
        let tx = self.db.transaction()?;
        let old: String = tx.query_row("SELECT state FROM jobs WHERE id = ?1", params![id], |r| r.get(0))?;
        if JobState::parse(&old)?.is_final() {
            return Ok(None);
        }
        let now = now_unix();
        tx.execute("UPDATE jobs SET state = ?2 WHERE id = ?1", params![id, state.as_str()])?;
        if state == JobState::Running {
            tx.execute("UPDATE jobs SET started = ?2 WHERE id = ?1 AND started = 0", params![id, now])?;
        }
        if state.is_final() {
            tx.execute("UPDATE jobs SET finished = ?2, error = ?3 WHERE id = ?1", params![id, now, note])?;
        }
        if !digest.is_empty() {
            tx.execute("UPDATE jobs SET state_digest = ?2 WHERE id = ?1", params![id, digest])?;
        }
        tx.execute("INSERT INTO history VALUES (?1, ?2, ?3, ?4)", params![id, now, state.as_str(), note])?;
        let ev = append_event(&tx, id, EventKind::State, note, detail, 0)?;
        tx.commit()?;
        Ok(Some(ev))
    }

    /// Records progress (not a state change: no history row).
    pub fn progress(&mut self, id: &str, step: u64, steps: u64, sim_time: f64) -> Result<()> {
        self.db.execute(
            "UPDATE jobs SET step = ?2, steps = ?3, sim_time = ?4 WHERE id = ?1",
            params![id, step as i64, steps as i64, sim_time],
        )?;
        Ok(())
    }

    /// Records progress and its numbered event (`Progress` or `Checkpoint`) in one
    /// transaction; prunes the job's old progress events now and then.
    #[allow(clippy::too_many_arguments)] // one event's columns
    pub fn progress_event(
        &mut self,
        id: &str,
        kind: EventKind,
        step: u64,
        steps: u64,
        sim_time: f64,
        message: &str,
        detail: &[u8],
    ) -> Result<EventRecord> {
        let tx = self.db.transaction()?;
        tx.execute("UPDATE jobs SET step = ?2, steps = ?3, sim_time = ?4 WHERE id = ?1", params![id, step as i64, steps as i64, sim_time])?;
        let ev = append_event(&tx, id, kind, message, detail, self.retained_progress)?;
        tx.commit()?;
        Ok(ev)
    }

    /// Up to `limit` retained events of a job with a sequence number above `after`, in order.
    /// Pruned progress events leave holes in the numbering, which the caller reports.
    pub fn events_after(&self, id: &str, after: u64, limit: usize) -> Result<Vec<EventRecord>> {
        let mut q = self.db.prepare_cached(
            "SELECT job_id, seq, kind, at, state, step, steps, sim_time, message, detail FROM events WHERE job_id = ?1 AND seq > ?2 ORDER BY seq LIMIT ?3",
        )?;
        let rows = q
            .query_map(params![id, after as i64, limit as i64], |r| {
                Ok((
                    EventRecord {
                        job_id: r.get(0)?,
                        seq: r.get::<_, i64>(1)? as u64,
                        kind: EventKind::State,
                        at: r.get(3)?,
                        state: JobState::Queued,
                        step: r.get::<_, i64>(5)? as u64,
                        steps: r.get::<_, i64>(6)? as u64,
                        sim_time: r.get(7)?,
                        message: r.get(8)?,
                        detail: r.get(9)?,
                    },
                    r.get::<_, String>(2)?,
                    r.get::<_, String>(4)?,
                ))
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter()
            .map(|(mut e, kind, state)| {
                e.kind = EventKind::parse(&kind)?;
                e.state = JobState::parse(&state)?;
                Ok(e)
            })
            .collect()
    }

    /// The sequence number of a job's newest event (0: none).
    pub fn last_sequence(&self, id: &str) -> Result<u64> {
        let n: i64 = self.db.query_row("SELECT COALESCE(MAX(seq), 0) FROM events WHERE job_id = ?1", params![id], |r| r.get(0))?;
        Ok(n as u64)
    }

    /// Adds a note to a job's history without changing its state (a lost worker, a rollback).
    pub fn note(&mut self, id: &str, note: &str) -> Result<()> {
        self.note_event(id, EventKind::Workers, note, &[]).map(|_| ())
    }

    /// [`Store::note`] with its numbered event of `kind`, in one transaction.
    pub fn note_event(&mut self, id: &str, kind: EventKind, note: &str, detail: &[u8]) -> Result<EventRecord> {
        let tx = self.db.transaction()?;
        let state: String = tx.query_row("SELECT state FROM jobs WHERE id = ?1", params![id], |r| r.get(0))?;
        tx.execute("INSERT INTO history VALUES (?1, ?2, ?3, ?4)", params![id, now_unix(), state, note])?;
        let ev = append_event(&tx, id, kind, note, detail, 0)?;
        tx.commit()?;
        Ok(ev)
    }

    /// (Unix time, state, note) of every change of a job, oldest first.
    pub fn history(&self, id: &str) -> Result<Vec<(i64, String, String)>> {
        let mut q = self.db.prepare("SELECT at, state, note FROM history WHERE job_id = ?1 ORDER BY rowid")?;
        let rows = q.query_map(params![id], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?.collect::<rusqlite::Result<_>>()?;
        Ok(rows)
    }
}

/// Appends a job's next numbered event inside `tx`, from the job row as `tx` sees it. With
/// `retain_progress` > 0, every 256th event prunes the job's progress events older than that
/// many sequence numbers (never the newest event).
fn append_event(
    tx: &rusqlite::Transaction<'_>,
    id: &str,
    kind: EventKind,
    message: &str,
    detail: &[u8],
    retain_progress: u64,
) -> Result<EventRecord> {
    let (state, step, steps, sim_time): (String, i64, i64, f64) =
        tx.query_row("SELECT state, step, steps, sim_time FROM jobs WHERE id = ?1", params![id], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
        })?;
    let last: i64 = tx.query_row("SELECT COALESCE(MAX(seq), 0) FROM events WHERE job_id = ?1", params![id], |r| r.get(0))?;
    let seq = last + 1;
    let at = now_unix();
    tx.execute(
        "INSERT INTO events (job_id, seq, kind, at, state, step, steps, sim_time, message, detail) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
        params![id, seq, kind.as_str(), at, state, step, steps, sim_time, message, detail],
    )?;
    if retain_progress > 0 && seq % 256 == 0 && seq as u64 > retain_progress {
        tx.execute("DELETE FROM events WHERE job_id = ?1 AND kind = 'progress' AND seq <= ?2", params![id, seq - retain_progress as i64])?;
    }
    let state = JobState::parse(&state)?;
    Ok(EventRecord {
        job_id: id.to_string(),
        seq: seq as u64,
        kind,
        at,
        state,
        step: step as u64,
        steps: steps as u64,
        sim_time,
        message: message.to_string(),
        detail: detail.to_vec(),
    })
}

/// A job as the store's tests and the service's tests insert it.
#[cfg(test)]
pub(crate) fn test_job(id: &str, priority: i32) -> JobRecord {
    JobRecord {
        id: id.into(),
        scene: "s".into(),
        state: JobState::Queued,
        priority,
        overrides: vec!["a.b=1".into()],
        checkpoint_every: 10,
        step: 0,
        steps: 100,
        sim_time: 0.0,
        error: String::new(),
        state_digest: String::new(),
        submitted: now_unix(),
        started: 0,
        finished: 0,
        resumes: 0,
        owner: "admin".into(),
        workers: 0,
        ranks: 1,
    }
}

#[cfg(test)]
mod tests;
