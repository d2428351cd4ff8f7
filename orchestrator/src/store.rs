//! The persistent job store of `mscale serve`: one SQLite file (`<state>/jobs.sqlite`,
//! compiled in with rusqlite's `bundled` feature). Every state change is one transaction and
//! appends a row to the job's history, so jobs and their history survive a restart; a job
//! found `running` when the store is opened was interrupted (the orchestrator died) and goes
//! back to the queue, to resume from its last checkpoint.
//!
//! Workers that joined the pool are kept here too (`workers`, `worker_history`): every
//! registration is a new row whose sequence number is the worker's epoch, so a worker that
//! rejoins is a new worker; `lost` is final.

use anyhow::{Context, Result};
use rusqlite::{Connection, OptionalExtension, params};
use std::path::Path;

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobState {
    Queued,
    Running,
    Completed,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Completed => "completed",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "completed" => JobState::Completed,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            other => anyhow::bail!("unknown job state {other:?} in the store"),
        })
    }

    pub fn is_final(self) -> bool {
        matches!(self, JobState::Completed | JobState::Failed | JobState::Cancelled)
    }
}

/// Where a worker is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WorkerState {
    Live,
    Draining,
    Lost,
}

impl WorkerState {
    pub fn as_str(self) -> &'static str {
        match self {
            WorkerState::Live => "live",
            WorkerState::Draining => "draining",
            WorkerState::Lost => "lost",
        }
    }

    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "live" => WorkerState::Live,
            "draining" => WorkerState::Draining,
            "lost" => WorkerState::Lost,
            other => anyhow::bail!("unknown worker state {other:?} in the store"),
        })
    }
}

/// What a worker says about itself when it registers.
#[derive(Debug, Clone, Default)]
pub struct WorkerAd {
    /// `host:port` of its coupling service.
    pub address: String,
    pub device: String,
    /// Back end and precision of its boxes (`cpu`, `double`).
    pub backend: String,
    pub precision: String,
    pub cores: u32,
    pub memory_bytes: u64,
    /// MD throughput (atom-steps/s).
    pub atom_steps_per_s: f64,
    pub throughput_source: String,
    pub protocol_version: u32,
}

/// One registration of a worker as stored.
#[derive(Debug, Clone)]
pub struct WorkerRecord {
    /// `w<epoch>`.
    pub id: String,
    /// The registration's sequence number in this store (increases with every registration).
    pub epoch: u64,
    pub ad: WorkerAd,
    pub state: WorkerState,
    pub registered: i64,
    /// Why it was lost or drained.
    pub note: String,
}

impl WorkerRecord {
    /// Back end and precision (`cpu/double`): boxes move only between workers of one kind.
    pub fn kind(&self) -> String {
        format!("{}/{}", self.ad.backend, self.ad.precision)
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
}

pub struct Store {
    db: Connection,
}

pub fn now_unix() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0)
}

const COLUMNS: &str = "id, scene, state, priority, overrides, checkpoint_every, step, steps, sim_time, error, state_digest, submitted, started, finished, resumes";

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
        let db = Connection::open(&path).with_context(|| format!("cannot open the job store {}", path.display()))?;
        db.execute_batch(
            "PRAGMA journal_mode = WAL;
             PRAGMA synchronous = FULL;
             CREATE TABLE IF NOT EXISTS jobs (
                 seq INTEGER PRIMARY KEY AUTOINCREMENT,
                 id TEXT NOT NULL UNIQUE,
                 scene TEXT NOT NULL,
                 state TEXT NOT NULL,
                 priority INTEGER NOT NULL,
                 overrides TEXT NOT NULL,
                 checkpoint_every INTEGER NOT NULL,
                 step INTEGER NOT NULL DEFAULT 0,
                 steps INTEGER NOT NULL DEFAULT 0,
                 sim_time REAL NOT NULL DEFAULT 0,
                 error TEXT NOT NULL DEFAULT '',
                 state_digest TEXT NOT NULL DEFAULT '',
                 submitted INTEGER NOT NULL,
                 started INTEGER NOT NULL DEFAULT 0,
                 finished INTEGER NOT NULL DEFAULT 0,
                 resumes INTEGER NOT NULL DEFAULT 0
             );
             CREATE TABLE IF NOT EXISTS history (
                 job_id TEXT NOT NULL,
                 at INTEGER NOT NULL,
                 state TEXT NOT NULL,
                 note TEXT NOT NULL
             );
             CREATE TABLE IF NOT EXISTS workers (
                 epoch INTEGER PRIMARY KEY AUTOINCREMENT,
                 address TEXT NOT NULL,
                 device TEXT NOT NULL,
                 backend TEXT NOT NULL,
                 precision TEXT NOT NULL,
                 cores INTEGER NOT NULL,
                 memory_bytes INTEGER NOT NULL,
                 atom_steps_per_s REAL NOT NULL,
                 throughput_source TEXT NOT NULL,
                 protocol_version INTEGER NOT NULL,
                 state TEXT NOT NULL,
                 registered INTEGER NOT NULL,
                 note TEXT NOT NULL DEFAULT ''
             );
             CREATE TABLE IF NOT EXISTS worker_history (
                 epoch INTEGER NOT NULL,
                 at INTEGER NOT NULL,
                 state TEXT NOT NULL,
                 note TEXT NOT NULL
             );",
        )
        .with_context(|| format!("cannot set up the job store {}", path.display()))?;
        Ok(Store { db })
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
            tx.execute("INSERT INTO history VALUES (?1, ?2, 'queued', 'the orchestrator restarted; resumes from its last checkpoint')", params![id, now_unix()])?;
        }
        tx.commit()?;
        Ok(ids)
    }

    pub fn insert(&mut self, job: &JobRecord) -> Result<()> {
        let tx = self.db.transaction()?;
        tx.execute(
            "INSERT INTO jobs (id, scene, state, priority, overrides, checkpoint_every, steps, submitted) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
            params![job.id, job.scene, job.state.as_str(), job.priority, serde_json::to_string(&job.overrides)?, job.checkpoint_every as i64, job.steps as i64, job.submitted],
        )?;
        tx.execute("INSERT INTO history VALUES (?1, ?2, ?3, 'submitted')", params![job.id, job.submitted, job.state.as_str()])?;
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

    /// The queued job to run next: highest priority, then oldest.
    pub fn next_queued(&self) -> Result<Option<JobRecord>> {
        let r = self.db.query_row(&format!("SELECT {COLUMNS} FROM jobs WHERE state = 'queued' ORDER BY priority DESC, seq ASC LIMIT 1"), [], record).optional()?;
        r.map(finish_record).transpose()
    }

    /// Moves a job to `state` (one transaction, with a history row); `error` and `digest` are
    /// kept when empty. Returns false when the job was already in a final state.
    pub fn transition(&mut self, id: &str, state: JobState, note: &str, digest: &str) -> Result<bool> {
        let tx = self.db.transaction()?;
        let old: String = tx.query_row("SELECT state FROM jobs WHERE id = ?1", params![id], |r| r.get(0))?;
        if JobState::parse(&old)?.is_final() {
            return Ok(false);
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
        tx.commit()?;
        Ok(true)
    }

    /// Records progress (not a state change: no history row).
    pub fn progress(&mut self, id: &str, step: u64, steps: u64, sim_time: f64) -> Result<()> {
        self.db.execute("UPDATE jobs SET step = ?2, steps = ?3, sim_time = ?4 WHERE id = ?1", params![id, step as i64, steps as i64, sim_time])?;
        Ok(())
    }

    /// Records a new registration (one transaction). Live or draining registrations at the same
    /// address are declared lost first: the process behind them was replaced. Returns the new
    /// record and the ids of the replaced ones.
    pub fn register_worker(&mut self, ad: &WorkerAd) -> Result<(WorkerRecord, Vec<String>)> {
        let tx = self.db.transaction()?;
        let now = now_unix();
        let replaced: Vec<i64> = {
            let mut q = tx.prepare("SELECT epoch FROM workers WHERE address = ?1 AND state != 'lost' ORDER BY epoch")?;
            q.query_map(params![ad.address], |r| r.get(0))?.collect::<rusqlite::Result<_>>()?
        };
        tx.execute(
            "INSERT INTO workers (address, device, backend, precision, cores, memory_bytes, atom_steps_per_s, throughput_source, protocol_version, state, registered)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, 'live', ?10)",
            params![ad.address, ad.device, ad.backend, ad.precision, ad.cores, ad.memory_bytes as i64, ad.atom_steps_per_s, ad.throughput_source, ad.protocol_version, now],
        )?;
        let epoch = tx.last_insert_rowid();
        let note = format!("replaced by w{epoch}, a new registration at its address");
        for e in &replaced {
            tx.execute("UPDATE workers SET state = 'lost', note = ?2 WHERE epoch = ?1", params![e, note])?;
            tx.execute("INSERT INTO worker_history VALUES (?1, ?2, 'lost', ?3)", params![e, now, note])?;
        }
        tx.execute("INSERT INTO worker_history VALUES (?1, ?2, 'live', 'registered')", params![epoch, now])?;
        tx.commit()?;
        let record = WorkerRecord { id: format!("w{epoch}"), epoch: epoch as u64, ad: ad.clone(), state: WorkerState::Live, registered: now, note: String::new() };
        Ok((record, replaced.iter().map(|e| format!("w{e}")).collect()))
    }

    /// Moves a worker to `state` (one transaction, with a history row). Returns false when the
    /// worker is unknown or already lost (`lost` is final).
    pub fn set_worker_state(&mut self, epoch: u64, state: WorkerState, note: &str) -> Result<bool> {
        let tx = self.db.transaction()?;
        let old: Option<String> = tx.query_row("SELECT state FROM workers WHERE epoch = ?1", params![epoch as i64], |r| r.get(0)).optional()?;
        match old.as_deref().map(WorkerState::parse).transpose()? {
            None | Some(WorkerState::Lost) => return Ok(false),
            Some(old) if old == state => return Ok(true),
            Some(_) => {}
        }
        tx.execute("UPDATE workers SET state = ?2, note = ?3 WHERE epoch = ?1", params![epoch as i64, state.as_str(), note])?;
        tx.execute("INSERT INTO worker_history VALUES (?1, ?2, ?3, ?4)", params![epoch as i64, now_unix(), state.as_str(), note])?;
        tx.commit()?;
        Ok(true)
    }

    /// Every registration, oldest first.
    pub fn workers(&self) -> Result<Vec<WorkerRecord>> {
        let mut q = self.db.prepare(
            "SELECT epoch, address, device, backend, precision, cores, memory_bytes, atom_steps_per_s, throughput_source, protocol_version, state, registered, note FROM workers ORDER BY epoch",
        )?;
        let rows = q
            .query_map([], |r| {
                let epoch: i64 = r.get(0)?;
                let ad = WorkerAd {
                    address: r.get(1)?,
                    device: r.get(2)?,
                    backend: r.get(3)?,
                    precision: r.get(4)?,
                    cores: r.get(5)?,
                    memory_bytes: r.get::<_, i64>(6)? as u64,
                    atom_steps_per_s: r.get(7)?,
                    throughput_source: r.get(8)?,
                    protocol_version: r.get(9)?,
                };
                Ok((WorkerRecord { id: format!("w{epoch}"), epoch: epoch as u64, ad, state: WorkerState::Live, registered: r.get(11)?, note: r.get(12)? }, r.get::<_, String>(10)?))
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter().map(|(mut w, state)| WorkerState::parse(&state).map(|s| {
            w.state = s;
            w
        })).collect()
    }

    /// (Unix time, state, note) of every change of a worker, oldest first.
    pub fn worker_history(&self, epoch: u64) -> Result<Vec<(i64, String, String)>> {
        let mut q = self.db.prepare("SELECT at, state, note FROM worker_history WHERE epoch = ?1 ORDER BY rowid")?;
        let rows = q.query_map(params![epoch as i64], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?.collect::<rusqlite::Result<_>>()?;
        Ok(rows)
    }

    /// Adds a note to a job's history without changing its state (a lost worker, a rollback).
    pub fn note(&mut self, id: &str, note: &str) -> Result<()> {
        let tx = self.db.transaction()?;
        let state: String = tx.query_row("SELECT state FROM jobs WHERE id = ?1", params![id], |r| r.get(0))?;
        tx.execute("INSERT INTO history VALUES (?1, ?2, ?3, ?4)", params![id, now_unix(), state, note])?;
        tx.commit()?;
        Ok(())
    }

    /// (Unix time, state, note) of every change of a job, oldest first.
    pub fn history(&self, id: &str) -> Result<Vec<(i64, String, String)>> {
        let mut q = self.db.prepare("SELECT at, state, note FROM history WHERE job_id = ?1 ORDER BY rowid")?;
        let rows = q.query_map(params![id], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?.collect::<rusqlite::Result<_>>()?;
        Ok(rows)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(id: &str, priority: i32) -> JobRecord {
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
        }
    }

    #[test]
    fn priority_order_restart_and_history() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut s = Store::open(dir.path()).unwrap();
            s.insert(&job("a", 0)).unwrap();
            s.insert(&job("b", 5)).unwrap();
            s.insert(&job("c", 5)).unwrap();
            assert_eq!(s.next_queued().unwrap().unwrap().id, "b");
            assert!(s.transition("b", JobState::Running, "", "").unwrap());
            assert_eq!(s.next_queued().unwrap().unwrap().id, "c");
            assert!(s.transition("a", JobState::Cancelled, "cancelled by a user", "").unwrap());
            assert!(!s.transition("a", JobState::Running, "", "").unwrap(), "a final state is final");
        }
        // Reopened as after a crash: the running job is queued again, with a resume counted.
        let mut s = Store::open(dir.path()).unwrap();
        assert_eq!(s.requeue_interrupted().unwrap(), vec!["b".to_string()]);
        let b = s.get("b").unwrap().unwrap();
        assert_eq!((b.state, b.resumes, b.overrides.clone()), (JobState::Queued, 1, vec!["a.b=1".to_string()]));
        assert_eq!(s.get("a").unwrap().unwrap().state, JobState::Cancelled);
        let states: Vec<String> = s.history("b").unwrap().into_iter().map(|h| h.1).collect();
        assert_eq!(states, vec!["queued", "running", "queued"]);
    }

    #[test]
    fn workers_get_a_new_epoch_per_registration_and_lost_is_final() {
        let dir = tempfile::tempdir().unwrap();
        let ad = |addr: &str| WorkerAd { address: addr.into(), backend: "cpu".into(), precision: "double".into(), atom_steps_per_s: 1e6, protocol_version: 1, ..Default::default() };
        let mut s = Store::open(dir.path()).unwrap();
        let (a, replaced) = s.register_worker(&ad("127.0.0.1:1")).unwrap();
        assert!(replaced.is_empty());
        let (b, _) = s.register_worker(&ad("127.0.0.1:2")).unwrap();
        assert!(b.epoch > a.epoch && a.id != b.id);
        assert!(s.set_worker_state(a.epoch, WorkerState::Draining, "drained by a user").unwrap());
        // The same address again: a new worker; the old registration is lost for good.
        let (c, replaced) = s.register_worker(&ad("127.0.0.1:1")).unwrap();
        assert_eq!(replaced, vec![a.id.clone()]);
        assert!(c.epoch > b.epoch);
        assert!(!s.set_worker_state(a.epoch, WorkerState::Live, "").unwrap(), "lost is final");
        drop(s);
        let s = Store::open(dir.path()).unwrap();
        let states: Vec<(String, WorkerState)> = s.workers().unwrap().into_iter().map(|w| (w.id, w.state)).collect();
        assert_eq!(states, vec![(a.id.clone(), WorkerState::Lost), (b.id, WorkerState::Live), (c.id, WorkerState::Live)]);
        let h: Vec<String> = s.worker_history(a.epoch).unwrap().into_iter().map(|h| h.1).collect();
        assert_eq!(h, vec!["live", "draining", "lost"]);
    }
}
