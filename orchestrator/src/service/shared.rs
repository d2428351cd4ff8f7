//! What the service's calls, the job runner and the worker monitor share: [`Core`].

use super::auth::Users;
use super::error::JobError;
use super::events::LiveJob;
use super::store::{JobRecord, Store};
use super::workers::Registry;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// How long jobs wait for `--local-workers` to register before running without them.
const LOCAL_WORKERS_WAIT: Duration = Duration::from_secs(60);

pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

pub(crate) fn read<T>(m: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    m.read().unwrap_or_else(|p| p.into_inner())
}

pub(crate) fn write<T>(m: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    m.write().unwrap_or_else(|p| p.into_inner())
}

/// What the service and the job runner share.
pub(crate) struct Core {
    pub(crate) store: Mutex<Store>,
    pub(crate) state_dir: PathBuf,
    /// Who may call (read again on SIGHUP).
    pub(crate) users: RwLock<Users>,
    pub(crate) checkpoint_every: u64,
    /// The event channels of jobs somebody watches (lock after `store`).
    pub(crate) live: Mutex<HashMap<String, LiveJob>>,
    /// The progress details (end time, ETA, drift, workers) of running jobs' latest progress
    /// event, encoded: state events carry them too.
    pub(crate) details: Mutex<HashMap<String, Vec<u8>>>,
    /// The running jobs and their flags, by id (lock after `workers`, before `store`).
    pub(crate) running: Mutex<HashMap<String, RunningJob>>,
    /// Registered workers (lock before `store` when both are needed).
    pub(crate) workers: Mutex<Registry>,
    /// Jobs wait (up to [`LOCAL_WORKERS_WAIT`]) until this many workers have registered: the
    /// local workers being started.
    expect_workers: usize,
    started: Instant,
    /// Raised when the orchestrator stops: the running job checkpoints and stays queued.
    pub(crate) stopping: AtomicBool,
    /// Tells open watch streams that the orchestrator stops (so shutdown need not wait for them).
    pub(crate) stop_watchers: watch::Sender<bool>,
    pub(crate) wake: (Mutex<bool>, Condvar),
    next_id: AtomicU64,
    pub(crate) step_deadline: md_worker::recovery::StepDeadline,
    /// Abort handles of the running job's workers, by address: a worker declared lost gets its
    /// calls aborted (its boxes are then replayed on the others).
    pub(crate) aborts: Mutex<HashMap<String, md_worker::recovery::AbortHandle>>,
    /// How jobs over MPI ranks are started (`serve --mpi-mscale`; None: they are refused).
    pub(crate) mpi: Option<super::MpiLauncher>,
    /// What `/metrics` exposes.
    pub(crate) metrics: super::metrics::Metrics,
}

/// A running job (each on its own thread).
pub(crate) struct RunningJob {
    pub(crate) id: String,
    pub(crate) owner: String,
    /// Stops the run after its current step, with a checkpoint.
    pub(crate) stop: Arc<AtomicBool>,
    /// Set with `stop` by CancelJob.
    pub(crate) user_cancel: Arc<AtomicBool>,
    /// Set with `stop` when one of its workers is declared lost: it continues elsewhere.
    pub(crate) reassign: Arc<AtomicBool>,
    /// Epochs of the workers holding its boxes.
    pub(crate) workers: Vec<u64>,
    /// It runs in this process (the one in-process slot).
    pub(crate) in_process: bool,
    /// The worker kind it waits for, having lost all of its workers (free ones of the kind go
    /// to it before queued jobs).
    pub(crate) waits_for: Arc<Mutex<Option<String>>>,
}

impl Core {
    /// A core over `store` and `registry`, with no job running; `expect_workers` is the number
    /// of local workers jobs wait for.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        store: Store,
        registry: Registry,
        state_dir: PathBuf,
        users: Users,
        checkpoint_every: u64,
        expect_workers: usize,
        step_deadline: md_worker::recovery::StepDeadline,
        mpi: Option<super::MpiLauncher>,
    ) -> Arc<Core> {
        Arc::new(Core {
            store: Mutex::new(store),
            state_dir,
            users: RwLock::new(users),
            checkpoint_every,
            live: Mutex::new(HashMap::new()),
            details: Mutex::new(HashMap::new()),
            running: Mutex::new(HashMap::new()),
            workers: Mutex::new(registry),
            expect_workers,
            started: Instant::now(),
            stopping: AtomicBool::new(false),
            stop_watchers: watch::channel(false).0,
            wake: (Mutex::new(false), Condvar::new()),
            next_id: AtomicU64::new(0),
            step_deadline,
            aborts: Mutex::new(HashMap::new()),
            metrics: super::metrics::Metrics::new(),
            mpi,
        })
    }

    pub(crate) fn job_dir(&self, id: &str) -> PathBuf {
        self.state_dir.join("jobs").join(id)
    }

    pub(crate) fn get(&self, id: &str) -> Result<JobRecord, JobError> {
        lock(&self.store).get(id)?.ok_or_else(|| JobError::NotFound(id.to_string()))
    }

    /// The job, when `caller` may see it: its owner or an admin. Another user's job answers
    /// as a job that does not exist, so ids cannot be probed.
    pub(crate) fn owned(&self, caller: &super::auth::Caller, id: &str) -> Result<JobRecord, JobError> {
        let job = self.get(id)?;
        if caller.is_admin() || job.owner == caller.user {
            Ok(job)
        } else {
            tracing::info!("user {} asked for job {id} of another user: answered as unknown", caller.user);
            Err(JobError::NotFound(id.to_string()))
        }
    }

    /// A core over a fresh store in `dir`, one user (token "t"), no workers, for unit tests.
    #[cfg(test)]
    pub(crate) fn for_test(dir: &std::path::Path) -> Arc<Core> {
        let store = Store::open(dir).unwrap();
        let registry = Registry::load(&store, std::time::Duration::from_secs(15)).unwrap();
        Core::new(store, registry, dir.to_path_buf(), Users::single("t", Default::default()), 0, 0, Default::default(), None)
    }

    /// The jobs `caller` sees, oldest first: its own, or every job for an admin.
    pub(crate) fn jobs_of(&self, caller: &super::auth::Caller) -> Result<Vec<JobRecord>, JobError> {
        let store = lock(&self.store);
        Ok(if caller.is_admin() { store.list()? } else { store.list_of(&caller.user)? })
    }

    /// Whether jobs should still wait for `--local-workers` to register.
    pub(crate) fn waiting_for_local_workers(&self) -> bool {
        self.expect_workers > 0 && self.started.elapsed() < LOCAL_WORKERS_WAIT && lock(&self.workers).usable().len() < self.expect_workers
    }

    pub(crate) fn wake_runner(&self) {
        *lock(&self.wake.0) = true;
        self.wake.1.notify_all();
    }

    pub(crate) fn new_id(&self) -> String {
        let n = self.next_id.fetch_add(1, Ordering::SeqCst);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
        let h = Sha256::digest(format!("{nanos}-{}-{n}", std::process::id()).as_bytes());
        format!("j{}", &hex::encode(h)[..12])
    }

    /// Stops the runner (the running job checkpoints and stays queued) and ends watch streams.
    pub(crate) fn stop(&self) {
        self.stopping.store(true, Ordering::SeqCst);
        for run in lock(&self.running).values() {
            run.stop.store(true, Ordering::SeqCst);
        }
        self.stop_watchers.send_replace(true);
        self.wake_runner();
    }
}
