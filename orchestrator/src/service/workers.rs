//! The MD worker pool of `mscale serve`: `md-worker serve --orchestrator URL` processes
//! register, heartbeat and may be drained; jobs' MD boxes are spread over the live ones in
//! proportion to their throughput.
//!
//! Main design decision: a registration is an identity. Every `RegisterWorker` gets a new id
//! and epoch (`w<epoch>`, the store's sequence number), also when the same process or address
//! comes back, and `lost` is final; so a worker that was declared lost and rejoins is a new,
//! empty worker, and a job's boxes are only ever put on a worker by opening them there
//! (restoring them from a checkpoint), never assumed to be still there.
//!
//! The registry is kept in memory and written through to the [`Store`] (one transaction per
//! state change); heartbeats only touch memory. After an orchestrator restart, registrations
//! that were live get one timeout's grace to heartbeat again.

use super::error::JobError;
use super::shared::{Core, lock};
use super::store::{Store, WorkerAd, WorkerRecord, WorkerState, now_unix};
use anyhow::{Context, Result};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Default time without a heartbeat after which a worker is declared lost (s).
pub const DEFAULT_TIMEOUT_S: f64 = 15.0;

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// FAILED_PRECONDITION.
    #[error("the worker speaks coupling protocol version {theirs}, this orchestrator speaks version {ours}")]
    Version { theirs: u32, ours: u32 },
    /// INVALID_ARGUMENT.
    #[error("{0}")]
    Invalid(String),
    /// NOT_FOUND: unknown, or declared lost (register again).
    #[error("{0}")]
    NotFound(String),
    /// INTERNAL.
    #[error(transparent)]
    Store(#[from] anyhow::Error),
}

/// One registration as the service shows it.
#[derive(Debug, Clone)]
pub struct WorkerView {
    pub record: WorkerRecord,
    /// Unix time of the last heartbeat this process saw (0: none).
    pub last_heartbeat: i64,
    /// The job whose boxes it holds now.
    pub job: Option<String>,
}

pub struct Registry {
    timeout: Duration,
    workers: BTreeMap<u64, WorkerRecord>,
    /// Last heartbeat (or registration, or this process's start for registrations it found).
    seen: HashMap<u64, (Instant, i64)>,
    busy: HashMap<u64, String>,
}

fn check_version(theirs: u32) -> Result<(), WorkerError> {
    let ours = mscale_proto::COUPLING_PROTOCOL_VERSION;
    if theirs != ours {
        return Err(WorkerError::Version { theirs, ours });
    }
    Ok(())
}

/// `host:port` with a port, nothing else.
fn check_address(a: &str) -> Result<(), WorkerError> {
    let bad = || WorkerError::Invalid(format!("address {a:?} is not HOST:PORT"));
    let (host, port) = a.rsplit_once(':').ok_or_else(bad)?;
    if host.is_empty() || port.parse::<u16>().map_or(true, |p| p == 0) || a.contains('/') || a.chars().any(char::is_whitespace) {
        return Err(bad());
    }
    Ok(())
}

impl Registry {
    /// The registrations in `store`; the live and draining ones get one timeout's grace.
    pub fn load(store: &Store, timeout: Duration) -> Result<Self> {
        let mut r = Registry { timeout, workers: BTreeMap::new(), seen: HashMap::new(), busy: HashMap::new() };
        for w in store.workers()? {
            if w.state != WorkerState::Lost {
                r.seen.insert(w.epoch, (Instant::now(), 0));
            }
            r.workers.insert(w.epoch, w);
        }
        Ok(r)
    }

    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// Accepts a worker (a new identity) or refuses it (another protocol version, bad values).
    pub fn register(&mut self, store: &mut Store, ad: WorkerAd) -> Result<WorkerRecord, WorkerError> {
        check_version(ad.protocol_version)?;
        check_address(&ad.address)?;
        if ad.backend.is_empty() || ad.precision.is_empty() {
            return Err(WorkerError::Invalid("backend and precision must be given".into()));
        }
        if !(ad.atom_steps_per_s.is_finite() && ad.atom_steps_per_s >= 0.0) {
            return Err(WorkerError::Invalid(format!("throughput {} atom-steps/s is not a non-negative number", ad.atom_steps_per_s)));
        }
        let (record, replaced) = store.register_worker(&ad)?;
        for id in replaced {
            if let Some(w) = self.workers.values_mut().find(|w| w.id == id) {
                tracing::warn!("worker {id} at {} is replaced by {}, a new registration at its address", w.ad.address, record.id);
                w.state = WorkerState::Lost;
                w.note = format!("replaced by {}, a new registration at its address", record.id);
            }
        }
        self.seen.insert(record.epoch, (Instant::now(), now_unix()));
        self.workers.insert(record.epoch, record.clone());
        Ok(record)
    }

    /// Keeps a registration alive; returns whether it is draining.
    pub fn heartbeat(&mut self, id: &str, epoch: u64, protocol_version: u32) -> Result<bool, WorkerError> {
        check_version(protocol_version)?;
        let w = self
            .workers
            .get(&epoch)
            .filter(|w| w.id == id)
            .ok_or_else(|| WorkerError::NotFound(format!("no worker {id} (epoch {epoch}) is registered here; register again")))?;
        match w.state {
            WorkerState::Lost => {
                Err(WorkerError::NotFound(format!("worker {id} was declared lost ({}); register again, as a new worker", w.note)))
            }
            state => {
                self.seen.insert(epoch, (Instant::now(), now_unix()));
                Ok(state == WorkerState::Draining)
            }
        }
    }

    /// The worker gets no new jobs.
    pub fn drain(&mut self, store: &mut Store, id: &str) -> Result<WorkerRecord, WorkerError> {
        let w = self.workers.values_mut().find(|w| w.id == id).ok_or_else(|| WorkerError::NotFound(format!("no worker {id}")))?;
        if w.state == WorkerState::Lost {
            return Err(WorkerError::NotFound(format!("worker {id} is lost ({})", w.note)));
        }
        store.set_worker_state(w.epoch, WorkerState::Draining, "drained by a user")?;
        w.state = WorkerState::Draining;
        w.note = "drained by a user".into();
        tracing::info!("worker {id} at {} is draining: no new jobs", w.ad.address);
        Ok(w.clone())
    }

    /// Declares a worker lost for good; false when it already was.
    pub fn declare_lost(&mut self, store: &mut Store, epoch: u64, why: &str) -> Result<bool> {
        Ok(!self.declare_all_lost(store, vec![(epoch, why.to_string())])?.is_empty())
    }

    /// Declares each `(epoch, why)` lost for good, in one store transaction (a monitor pass
    /// that finds hundreds silent writes to disk once, not once each, while it holds the
    /// registry). Returns the epochs that were not lost before.
    pub fn declare_all_lost(&mut self, store: &mut Store, lost: Vec<(u64, String)>) -> Result<Vec<u64>> {
        let lost: Vec<(u64, String)> =
            lost.into_iter().filter(|(e, _)| self.workers.get(e).is_some_and(|w| w.state != WorkerState::Lost)).collect();
        if lost.is_empty() {
            return Ok(Vec::new());
        }
        store.set_workers_state(&lost, WorkerState::Lost)?;
        let mut newly = Vec::with_capacity(lost.len());
        for (epoch, why) in lost {
            let w = self.workers.get_mut(&epoch).expect("kept above: registered");
            tracing::warn!("worker {} at {} is lost: {why}", w.id, w.ad.address);
            w.state = WorkerState::Lost;
            w.note = why;
            self.seen.remove(&epoch);
            newly.push(epoch);
        }
        Ok(newly)
    }

    /// Live or draining workers whose last heartbeat is older than the timeout.
    pub fn expired(&self) -> Vec<(u64, Duration)> {
        self.workers
            .values()
            .filter(|w| w.state != WorkerState::Lost)
            .filter_map(|w| self.seen.get(&w.epoch).map(|s| (w.epoch, s.0.elapsed())))
            .filter(|(_, silent)| *silent > self.timeout)
            .collect()
    }

    pub fn get(&self, epoch: u64) -> Option<&WorkerRecord> {
        self.workers.get(&epoch)
    }

    /// Workers that take new work, oldest registration first.
    pub fn usable(&self) -> Vec<WorkerRecord> {
        self.workers.values().filter(|w| w.state == WorkerState::Live).cloned().collect()
    }

    pub fn list(&self) -> Vec<WorkerView> {
        self.workers
            .values()
            .map(|w| WorkerView {
                record: w.clone(),
                last_heartbeat: self.seen.get(&w.epoch).map_or(0, |s| s.1),
                job: self.busy.get(&w.epoch).cloned(),
            })
            .collect()
    }

    /// Whether a worker holds a job's boxes.
    pub fn is_busy(&self, epoch: u64) -> bool {
        self.busy.contains_key(&epoch)
    }

    /// Clears every worker still marked as holding `job`'s boxes.
    pub fn release_job(&mut self, job: &str) {
        self.busy.retain(|_, j| j != job);
    }

    /// Marks workers as holding a job's boxes (an empty `job` clears them).
    pub fn set_busy(&mut self, epochs: &[u64], job: &str) {
        for e in epochs {
            if job.is_empty() {
                self.busy.remove(e);
            } else {
                self.busy.insert(*e, job.to_string());
            }
        }
    }
}

/// The workers a job runs on: the usable ones of one back end and precision (`kind`, or when
/// `None` the kind with the most throughput), oldest registration first. Empty: in-process.
pub fn choose(usable: &[WorkerRecord], kind: Option<&str>) -> Vec<WorkerRecord> {
    let kind = match kind {
        Some(k) => k.to_string(),
        None => {
            let mut totals: BTreeMap<String, f64> = BTreeMap::new();
            for w in usable {
                *totals.entry(w.kind()).or_default() += w.ad.atom_steps_per_s.max(0.0);
            }
            match totals.into_iter().max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0))) {
                Some((k, _)) => k,
                None => return Vec::new(),
            }
        }
    };
    usable.iter().filter(|w| w.kind() == kind).cloned().collect()
}

/// Whether a worker answers its coupling service's `Info` within `within`.
pub fn answers(address: &str, within: Duration) -> bool {
    use mscale_proto::coupling::v1 as cpb;
    let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return false };
    let url = if address.starts_with("http") { address.to_string() } else { format!("http://{address}") };
    rt.block_on(async {
        let call = async {
            let ch = tonic::transport::Endpoint::from_shared(url).ok()?.connect_timeout(within).connect().await.ok()?;
            cpb::md_worker_client::MdWorkerClient::new(ch).info(cpb::InfoRequest {}).await.ok()
        };
        matches!(tokio::time::timeout(within, call).await, Ok(Some(_)))
    })
}

/// `md-worker serve` processes started by `mscale serve --local-workers N`; killed when this
/// is dropped (the orchestrator exits), and by the kernel when the orchestrator dies
/// (PR_SET_PDEATHSIG).
pub struct LocalWorkers {
    children: Vec<Child>,
}

/// The `md-worker` program next to this one.
pub fn md_worker_program() -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot find this program's path")?;
    let p = exe.with_file_name("md-worker");
    anyhow::ensure!(
        p.is_file(),
        "--local-workers: there is no md-worker program next to {} (build it: cargo build -p md-worker)",
        exe.display()
    );
    Ok(p)
}

impl LocalWorkers {
    /// Starts `n` workers on 127.0.0.1 (free ports) that join the orchestrator at `url` with
    /// the token in `token_file`; each gets an equal share of the cores. No shell: the
    /// arguments go to the program as they are.
    pub fn start(
        n: usize,
        url: &str,
        token_file: &Path,
        ca_file: Option<&Path>,
        identity: Option<&(PathBuf, PathBuf)>,
        log_dir: &Path,
    ) -> Result<Self> {
        let mut workers = LocalWorkers { children: Vec::new() };
        if n == 0 {
            return Ok(workers);
        }
        let program = md_worker_program()?;
        std::fs::create_dir_all(log_dir).with_context(|| format!("cannot create {}", log_dir.display()))?;
        let cores = std::thread::available_parallelism().map(|c| c.get()).unwrap_or(1);
        let threads = (cores / n).max(1);
        for k in 0..n {
            let log_path = log_dir.join(format!("local-{k}.log"));
            let log = std::fs::File::create(&log_path).with_context(|| format!("cannot create {}", log_path.display()))?;
            let mut cmd = Command::new(&program);
            cmd.args([
                "serve",
                "--listen",
                "127.0.0.1:0",
                "--device",
                "cpu",
                "--threads",
                &threads.to_string(),
                "--orchestrator",
                url,
                "--token-file",
            ])
            .arg(token_file)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log);
            if let Some(ca) = ca_file {
                cmd.arg("--ca-file").arg(ca);
            }
            if let Some((cert, key)) = identity {
                cmd.arg("--client-cert").arg(cert).arg("--client-key").arg(key);
            }
            die_with_parent(&mut cmd);
            let child = cmd.spawn().with_context(|| format!("cannot start {}", program.display()))?;
            tracing::info!("started local worker {k} (pid {}, {threads} threads), log in {}", child.id(), log_path.display());
            workers.children.push(child);
        }
        Ok(workers)
    }

    pub fn pids(&self) -> Vec<u32> {
        self.children.iter().map(|c| c.id()).collect()
    }
}

impl Drop for LocalWorkers {
    fn drop(&mut self) {
        for c in &mut self.children {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The child gets SIGKILL when the thread that started it ends (the orchestrator's main
/// thread, so: when the orchestrator dies, also by SIGKILL).
#[cfg(target_os = "linux")]
fn die_with_parent(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

#[cfg(not(target_os = "linux"))]
fn die_with_parent(_: &mut Command) {}

/// Declares silent workers lost, every fraction of the timeout, until the orchestrator stops;
/// a call in flight on one is aborted (its boxes are replayed on the others), or where the job
/// has no abort handle for it, the job checkpoints and moves off it.
pub(crate) fn monitor(core: Arc<Core>) {
    let period = (lock(&core.workers).timeout() / 4).clamp(Duration::from_millis(50), Duration::from_millis(500));
    while !core.stopping.load(Ordering::SeqCst) {
        std::thread::sleep(period);
        let mut reg = lock(&core.workers);
        let timeout = reg.timeout().as_secs_f64();
        let silent: Vec<(u64, String)> = reg
            .expired()
            .into_iter()
            .map(|(epoch, silent)| {
                (epoch, format!("no heartbeat for {:.1} s (the worker timeout is {timeout:.1} s)", silent.as_secs_f64()))
            })
            .collect();
        let lost = reg.declare_all_lost(&mut lock(&core.store), silent);
        let lost = match lost {
            Ok(l) => l,
            Err(e) => {
                tracing::error!("cannot record silent workers as lost: {e:#}");
                continue;
            }
        };
        for epoch in lost {
            let abort = reg.get(epoch).and_then(|w| lock(&core.aborts).get(&w.ad.address).cloned());
            if let Some(h) = abort {
                tracing::warn!("aborting the MD calls on the lost worker w{epoch}: its boxes are replayed on the job's other workers");
                h.abort(&reg.get(epoch).map(|w| w.note.clone()).unwrap_or_default());
            } else if let Some(run) = lock(&core.running).values().find(|r| r.workers.contains(&epoch)) {
                tracing::warn!("job {}: moves off the lost worker w{epoch} (checkpoint after this step)", run.id);
                run.reassign.store(true, Ordering::SeqCst);
                run.stop.store(true, Ordering::SeqCst);
            }
        }
    }
}

impl Core {
    /// Registers a worker; returns its record and the heartbeat timeout it must keep.
    pub(crate) fn register_worker(&self, ad: WorkerAd) -> Result<(WorkerRecord, Duration), JobError> {
        let (w, timeout) = {
            let mut reg = lock(&self.workers);
            let w = reg.register(&mut lock(&self.store), ad)?;
            (w, reg.timeout())
        };
        tracing::info!(
            "worker {} registered: {} ({}, {}/{}), {:.3e} atom-steps/s ({})",
            w.id,
            w.ad.address,
            w.ad.device,
            w.ad.backend,
            w.ad.precision,
            w.ad.atom_steps_per_s,
            w.ad.throughput_source
        );
        self.wake_runner();
        Ok((w, timeout))
    }

    /// Drains a worker: it gets no new jobs.
    pub(crate) fn drain_worker(&self, id: &str) -> Result<WorkerView, JobError> {
        let mut reg = lock(&self.workers);
        let w = reg.drain(&mut lock(&self.store), id)?;
        Ok(reg.list().into_iter().find(|v| v.record.epoch == w.epoch).ok_or_else(|| anyhow::anyhow!("drained worker vanished"))?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ad(addr: &str, backend: &str, tp: f64) -> WorkerAd {
        WorkerAd {
            address: addr.into(),
            backend: backend.into(),
            precision: "double".into(),
            atom_steps_per_s: tp,
            protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
            ..Default::default()
        }
    }

    #[test]
    fn register_heartbeat_drain_lose() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        let mut r = Registry::load(&store, Duration::from_millis(200)).unwrap();
        let mut bad = ad("127.0.0.1:1", "cpu", 1.0);
        bad.protocol_version += 1;
        let e = r.register(&mut store, bad).unwrap_err();
        assert!(matches!(e, WorkerError::Version { .. }), "{e}");
        let msg = e.to_string();
        assert!(
            msg.contains(&format!("version {}", mscale_proto::COUPLING_PROTOCOL_VERSION + 1))
                && msg.contains(&format!("version {}", mscale_proto::COUPLING_PROTOCOL_VERSION)),
            "{msg}"
        );
        for a in ["nohost", ":1", "h:0", "h:x", "http://h:1"] {
            assert!(matches!(r.register(&mut store, ad(a, "cpu", 1.0)), Err(WorkerError::Invalid(_))), "{a}");
        }
        let a = r.register(&mut store, ad("127.0.0.1:1", "cpu", 2.0)).unwrap();
        let b = r.register(&mut store, ad("127.0.0.1:2", "cpu", 1.0)).unwrap();
        assert!(!r.heartbeat(&a.id, a.epoch, mscale_proto::COUPLING_PROTOCOL_VERSION).unwrap());
        assert!(matches!(r.heartbeat(&a.id, b.epoch, mscale_proto::COUPLING_PROTOCOL_VERSION), Err(WorkerError::NotFound(_))));
        r.drain(&mut store, &b.id).unwrap();
        assert!(r.heartbeat(&b.id, b.epoch, mscale_proto::COUPLING_PROTOCOL_VERSION).unwrap());
        assert_eq!(r.usable().iter().map(|w| w.id.clone()).collect::<Vec<_>>(), vec![a.id.clone()]);
        std::thread::sleep(Duration::from_millis(300));
        r.heartbeat(&a.id, a.epoch, mscale_proto::COUPLING_PROTOCOL_VERSION).unwrap();
        let expired: Vec<u64> = r.expired().into_iter().map(|e| e.0).collect();
        assert_eq!(expired, vec![b.epoch]);
        assert!(r.declare_lost(&mut store, b.epoch, "no heartbeat").unwrap());
        assert!(matches!(r.heartbeat(&b.id, b.epoch, mscale_proto::COUPLING_PROTOCOL_VERSION), Err(WorkerError::NotFound(_))));
        // Rejoining: a new identity.
        let b2 = r.register(&mut store, ad("127.0.0.1:2", "cpu", 1.0)).unwrap();
        assert!(b2.epoch > b.epoch && b2.id != b.id);
    }

    #[test]
    fn a_job_runs_on_one_kind_of_worker() {
        let w = |epoch: u64, backend: &str, tp: f64| WorkerRecord {
            id: format!("w{epoch}"),
            epoch,
            ad: ad(&format!("h:{epoch}"), backend, tp),
            state: WorkerState::Live,
            registered: 0,
            note: String::new(),
        };
        let all = vec![w(1, "cpu", 1.0), w(2, "cuda", 5.0), w(3, "cpu", 2.0)];
        assert_eq!(choose(&all, None).iter().map(|w| w.epoch).collect::<Vec<_>>(), vec![2]);
        assert_eq!(choose(&all, Some("cpu/double")).iter().map(|w| w.epoch).collect::<Vec<_>>(), vec![1, 3]);
        assert!(choose(&all, Some("cuda/mixed")).is_empty());
        assert!(choose(&[], None).is_empty());
    }
}
