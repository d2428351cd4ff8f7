//! The workers that joined the pool, as the store keeps them (`workers`, `worker_history`):
//! every registration is a new row whose sequence number is the worker's epoch.

use super::{Store, now_unix};
use anyhow::Result;
use rusqlite::{OptionalExtension, params};

/// Where a worker is in its life (stored as its lowercase name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, strum::IntoStaticStr, strum::EnumString)]
#[strum(serialize_all = "lowercase")]
pub enum WorkerState {
    Live,
    Draining,
    Lost,
}

impl WorkerState {
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    pub fn parse(s: &str) -> Result<Self> {
        s.parse().map_err(|_| anyhow::anyhow!("unknown worker state {s:?} in the store"))
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

impl Store {
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
        let record = WorkerRecord {
            id: format!("w{epoch}"),
            epoch: epoch as u64,
            ad: ad.clone(),
            state: WorkerState::Live,
            registered: now,
            note: String::new(),
        };
        Ok((record, replaced.iter().map(|e| format!("w{e}")).collect()))
    }

    /// Moves a worker to `state` (one transaction, with a history row). Returns false when the
    /// worker is unknown or already lost (`lost` is final).
    pub fn set_worker_state(&mut self, epoch: u64, state: WorkerState, note: &str) -> Result<bool> {
        Ok(self.set_workers_state(&[(epoch, note.to_string())], state)?[0])
    }

    /// Moves each `(epoch, note)` to `state` in one transaction (one write to disk however many
    /// there are). Returns, for each, whether it moved or was already there (false when the
    /// worker is unknown or already lost).
    pub fn set_workers_state(&mut self, moves: &[(u64, String)], state: WorkerState) -> Result<Vec<bool>> {
        let tx = self.db.transaction()?;
        let mut done = Vec::with_capacity(moves.len());
        for (epoch, note) in moves {
            let old: Option<String> =
                tx.query_row("SELECT state FROM workers WHERE epoch = ?1", params![*epoch as i64], |r| r.get(0)).optional()?;
            done.push(match old.as_deref().map(WorkerState::parse).transpose()? {
                None | Some(WorkerState::Lost) => false,
                Some(old) if old == state => true,
                Some(_) => {
                    tx.execute("UPDATE workers SET state = ?2, note = ?3 WHERE epoch = ?1", params![*epoch as i64, state.as_str(), note])?;
                    tx.execute(
                        "INSERT INTO worker_history VALUES (?1, ?2, ?3, ?4)",
                        params![*epoch as i64, now_unix(), state.as_str(), note],
                    )?;
                    true
                }
            });
        }
        tx.commit()?;
        Ok(done)
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
                Ok((
                    WorkerRecord {
                        id: format!("w{epoch}"),
                        epoch: epoch as u64,
                        ad,
                        state: WorkerState::Live,
                        registered: r.get(11)?,
                        note: r.get(12)?,
                    },
                    r.get::<_, String>(10)?,
                ))
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        rows.into_iter()
            .map(|(mut w, state)| {
                WorkerState::parse(&state).map(|s| {
                    w.state = s;
                    w
                })
            })
            .collect()
    }

    /// (Unix time, state, note) of every change of a worker, oldest first.
    pub fn worker_history(&self, epoch: u64) -> Result<Vec<(i64, String, String)>> {
        let mut q = self.db.prepare("SELECT at, state, note FROM worker_history WHERE epoch = ?1 ORDER BY rowid")?;
        let rows = q.query_map(params![epoch as i64], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?.collect::<rusqlite::Result<_>>()?;
        Ok(rows)
    }
}
