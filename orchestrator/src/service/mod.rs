//! `mscale serve`: the job service (`mscale.orchestrator.v1`).
//!
//! Jobs are scenes submitted with the files they name; they are validated at submit with the
//! messages of `mscale check`, kept in the SQLite [`store::Store`] under the state directory, and run
//! side by side on disjoint sets of workers (`schedule`: by priority, then fair share between
//! users), each on its own thread with the same run driver as `mscale run` (so a job ends with
//! the digest `mscale run` gives). Jobs checkpoint at an interval; a job
//! that was running when the orchestrator died is resumed from its last checkpoint on restart.
//!
//! Layout of the state directory: `jobs.sqlite`, `token` (generated when no token file is
//! given), and `jobs/<id>/input/` (the scene and its files) and `jobs/<id>/run/` (the run
//! directory: outputs, checkpoints, summary.json).
//!
//! Workers (`md-worker serve --orchestrator URL`, or `--local-workers N` started here) register
//! and heartbeat ([`workers`]). A job's MD boxes are spread over the workers it was given (its
//! `--workers N`, or every free one, of one back end and precision) in proportion to their
//! throughput, or run in this process when the pool has none (one such job at a time). A worker that stops answering mid-job (killed, or past `--step-deadline`) is
//! declared lost and only its boxes are rebuilt on the job's surviving workers of the same back
//! end and precision: restored from the last checkpoint and sent again every input logged since
//! (`md_worker::recovery`), so the job ends with the digest of an uninterrupted run; with no
//! survivor it waits for a worker of its kind that another job releases and rolls back onto
//! it, and where the pool has no live worker of its kind left it fails naming the worker and
//! the step. A worker silent for longer than the
//! worker timeout is declared lost and a call in flight on it is aborted, with the same
//! recovery. Where replay is impossible (the input log outgrew its bound) the whole job rolls
//! back to its last checkpoint onto the survivors instead.
//!
//! `schedule`: the queue goes by priority, then fair share (a user with fewer jobs running
//! first), then submission; a job that cannot start holds back later jobs from what it waits
//! for, so a released worker goes to the first waiting job. No preemption.
//!
//! Watch events: every event of a job has a sequence number (1, 2, 3, ... with no gaps), given
//! in the store transaction that records it (the store keeps state changes, checkpoints and
//! worker changes for good and recent progress). Watchers replay what they missed from the
//! store and then follow a broadcast channel; one that lags is caught up from the store again,
//! so an event is never skipped. Progress is published at most every 100 ms.
//!
//! Security: calls carry `authorization: Bearer <token>`; the token names a user with a role
//! (`auth`: one admin token, or a users file read again on SIGHUP). A job belongs to its
//! submitter: only it or an admin may see, watch, fetch or cancel it (another user's job
//! answers as an unknown one); a worker token may only register and heartbeat. Tokens are
//! compared in constant time; per-user limits (jobs, upload bytes, snapshots) refuse a
//! submission naming the limit; requests are bounded in size; FetchResult cannot leave the job's
//! run directory; nothing runs through a shell. TLS (rustls) is served with `--tls-cert` and
//! `--tls-key`, and required to listen on anything but a loopback address.

//! The module's parts: [`api`] is the gRPC edge (decoding, encoding, [`JobError`] to
//! `tonic::Status`), `convert` the proto conversions; the domain core is `shared` (what the
//! calls, the runner and the monitor share), `jobs` (the runner and a job's life), `events`
//! (numbered events and watchers), `inputs` (submitted files), `fetch` (reads of run
//! directories), `auth` (tokens), [`store`] (SQLite) and [`workers`] (the worker pool).

pub mod api;
mod auth;
mod convert;
mod dashboard;
mod error;
mod events;
mod fetch;
mod http;
mod inputs;
mod jobs;
mod metrics;
mod ranks;
mod schedule;
mod shared;
pub mod store;
pub mod workers;

pub use auth::read_token;
pub use error::JobError;
pub use fetch::{FETCH_CHUNK, contained, run_files};
pub use inputs::for_each_string;

use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1::orchestrator_server::OrchestratorServer;
use shared::Core;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;
use store::Store;
use workers::Registry;

/// Largest request or response message (bytes): scenes plus potential files, fetched files.
pub const MAX_MESSAGE: usize = 64 << 20;
/// Default checkpoint interval (steps) of jobs that name none.
pub const DEFAULT_CHECKPOINT_EVERY: u64 = 100;

pub struct ServeOptions {
    pub state_dir: PathBuf,
    pub listen: String,
    /// The single-token mode's token (the admin user); unused with `access.users_file`.
    pub token: String,
    /// Users and their limits.
    pub access: AccessOptions,
    pub checkpoint_every: u64,
    /// PEM certificate chain and private key: serve over TLS (rustls).
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    /// `md-worker serve` processes to start on this machine (`--local-workers`).
    pub local_workers: usize,
    /// The token file local workers authenticate with.
    pub token_file: PathBuf,
    /// What local workers trust to reach a TLS orchestrator (the certificate file).
    pub local_ca: Option<PathBuf>,
    /// The client identity (certificate, key files) local workers present under mutual TLS.
    pub local_identity: Option<(PathBuf, PathBuf)>,
    /// PEM authority client certificates must be signed by (mutual TLS).
    pub client_ca: Option<Vec<u8>>,
    /// A worker without a heartbeat for this long is declared lost.
    pub worker_timeout: Duration,
    /// Bound on each call to a worker.
    pub step_deadline: md_worker::recovery::StepDeadline,
    /// Where to serve the dashboard and `/metrics` (`--http`), over TLS when `tls` is set.
    pub http: Option<String>,
    /// Workers the store knows from an earlier run are lost at start (`--forget-workers`).
    pub forget_workers: bool,
    /// How jobs over MPI ranks are started (None: such jobs are refused).
    pub mpi: Option<MpiLauncher>,
}

/// Who may call `mscale serve`, and the per-user limits.
#[derive(Debug, Clone, Default)]
pub struct AccessOptions {
    /// The users file (`--users`): users, roles, token hashes; read again on SIGHUP. None: the
    /// single-token mode.
    pub users_file: Option<PathBuf>,
    /// Mutual TLS (`--tls-client-ca`): clients and workers must present a certificate signed
    /// by this PEM authority.
    pub client_ca: Option<PathBuf>,
    /// Limits of every user (`--max-jobs-per-user`, `--max-upload-bytes`, `--max-snapshots`)
    /// where the users file sets none.
    pub limits: auth::Limits,
}

pub use auth::{Limits, Role, parse_users};
pub use ranks::MpiLauncher;

/// The worker pool options of `mscale serve`.
#[derive(Debug, Clone)]
pub struct PoolOptions {
    /// `md-worker serve` processes to start here.
    pub local_workers: usize,
    /// Seconds without a heartbeat after which a worker is declared lost.
    pub worker_timeout_s: f64,
    /// Bound on each call to a worker (`--step-deadline`).
    pub step_deadline: md_worker::recovery::StepDeadline,
    /// `--forget-workers`: the workers of an earlier run are gone (a new Slurm allocation).
    pub forget_workers: bool,
    /// `--mpi-mscale`, `--mpirun`: how jobs submitted with `--ranks N` are started.
    pub mpi: Option<MpiLauncher>,
}

/// `mscale serve`: reads the token (generating one into the state directory when no file is
/// given) and the TLS files, then serves until SIGINT/SIGTERM.
#[allow(clippy::too_many_arguments)] // one per group of `mscale serve` flags
pub fn serve_command(
    state: PathBuf,
    listen: String,
    token_file: Option<PathBuf>,
    checkpoint_every: u64,
    tls: Option<(PathBuf, PathBuf)>,
    pool: PoolOptions,
    http: Option<String>,
    access: AccessOptions,
) -> Result<i32> {
    anyhow::ensure!(
        pool.worker_timeout_s.is_finite() && pool.worker_timeout_s > 0.0,
        "--worker-timeout {} must be a positive number of seconds",
        pool.worker_timeout_s
    );
    if let (Some(_), Some(t)) = (&access.users_file, &token_file) {
        bail!(
            "--users and --token-file {} exclude each other: give the admin token a [[user]] with role = \"admin\" in the users file",
            t.display()
        );
    }
    // With users, local workers get a token of their own (a worker user), made at every start.
    let (token, token_file) = match (&access.users_file, token_file) {
        (Some(_), _) => (String::new(), state.join("local-worker-token")),
        (None, Some(f)) => (read_token(&f)?, f),
        (None, None) => (auth::generated_token(&state)?, state.join("token")),
    };
    let local_ca = tls.as_ref().map(|t| t.0.clone());
    if access.client_ca.is_some() && tls.is_none() {
        bail!("--tls-client-ca needs --tls-cert and --tls-key: mutual TLS is TLS");
    }
    let local_identity = access.client_ca.as_ref().and(tls.clone());
    let client_ca = match &access.client_ca {
        Some(p) => Some(std::fs::read(p).with_context(|| format!("cannot read --tls-client-ca {}", p.display()))?),
        None => None,
    };
    let tls = match tls {
        Some((cert, key)) => {
            let read = |p: &Path| std::fs::read(p).with_context(|| format!("cannot read {}", p.display()));
            Some((read(&cert)?, read(&key)?))
        }
        None => None,
    };
    serve(ServeOptions {
        state_dir: state,
        listen,
        token,
        access,
        checkpoint_every,
        tls,
        local_workers: pool.local_workers,
        token_file,
        local_ca,
        local_identity,
        client_ca,
        worker_timeout: Duration::from_secs_f64(pool.worker_timeout_s),
        step_deadline: pool.step_deadline,
        http,
        forget_workers: pool.forget_workers,
        mpi: pool.mpi,
    })?;
    Ok(crate::exit::OK)
}

/// Runs the orchestrator until SIGINT/SIGTERM. Prints `mscale serve: listening on ADDR` on
/// stdout once it answers calls.
pub fn serve(opts: ServeOptions) -> Result<()> {
    let addr: SocketAddr =
        opts.listen.parse().with_context(|| format!("--listen {:?} is not an address like 127.0.0.1:50100", opts.listen))?;
    let http_addr: Option<SocketAddr> = match &opts.http {
        Some(h) => Some(h.parse().with_context(|| format!("--http {h:?} is not an address like 127.0.0.1:8080"))?),
        None => None,
    };
    if let Some(h) = http_addr.filter(|h| !h.ip().is_loopback() && opts.tls.is_none()) {
        bail!(
            "refusing to serve --http on {h} without TLS: the dashboard's token must not cross a network in clear text; pass --tls-cert and --tls-key (the HTTP port then serves HTTPS with them), or use a loopback address"
        );
    }
    if !addr.ip().is_loopback() && opts.tls.is_none() {
        bail!(
            "refusing to listen on {addr} without TLS: tokens must not cross a network in clear text; pass --tls-cert and --tls-key, or listen on a loopback address (127.0.0.1 or [::1])"
        );
    }
    let mut store = Store::open(&opts.state_dir)?;
    for id in store.requeue_interrupted()? {
        tracing::info!("job {id} was running when the orchestrator stopped: queued again, resumes from its last checkpoint");
    }
    let mut registry = Registry::load(&store, opts.worker_timeout)?;
    if opts.forget_workers {
        // Before any job resumes: a job must not be handed to workers that ended with the
        // allocation of the previous orchestrator.
        let known: Vec<u64> = registry.list().iter().map(|v| v.record.epoch).collect();
        for epoch in known {
            registry.declare_lost(&mut store, epoch, "from an earlier run of the orchestrator (--forget-workers)")?;
        }
    }
    let users = match &opts.access.users_file {
        Some(file) => {
            let token = auth::random_token()?;
            auth::write_private(&opts.token_file, &token)?;
            let local = auth::User::with_token("local-workers", Role::Worker, &token);
            let users = auth::Users::from_file(file, vec![local], opts.access.limits)?;
            tracing::info!("users from {} (read again on SIGHUP)", file.display());
            users
        }
        None => auth::Users::single(&opts.token, opts.access.limits),
    };
    if let Some(m) = &opts.mpi {
        tracing::info!("jobs over MPI ranks run as: {}", m.describe());
    }
    let core = Core::new(
        store,
        registry,
        opts.state_dir.clone(),
        users,
        opts.checkpoint_every,
        opts.local_workers,
        opts.step_deadline,
        opts.mpi.clone(),
    );
    let listener = std::net::TcpListener::bind(addr).with_context(|| format!("cannot listen on {addr}"))?;
    listener.set_nonblocking(true)?;
    let http_listener = match http_addr {
        Some(h) => {
            let l = std::net::TcpListener::bind(h).with_context(|| format!("cannot listen on --http {h}"))?;
            l.set_nonblocking(true)?;
            Some(l)
        }
        None => None,
    };
    let http_tls = opts.tls.as_ref().map(|(cert, key)| http::tls_acceptor(cert, key)).transpose()?;
    let bound = listener.local_addr()?;
    // Started from this (the main) thread: they die with the process (see LocalWorkers), and
    // are killed when `_local` is dropped, after the runner stopped.
    let scheme = if opts.tls.is_some() { "https" } else { "http" };
    let _local = workers::LocalWorkers::start(
        opts.local_workers,
        &format!("{scheme}://{bound}"),
        &opts.token_file,
        opts.local_ca.as_deref(),
        opts.local_identity.as_ref(),
        &opts.state_dir.join("workers"),
    )?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the gRPC runtime")?;
    let runner_core = core.clone();
    let runner_thread = std::thread::Builder::new()
        .name("job-runner".into())
        .spawn(move || jobs::runner(runner_core))
        .context("cannot start the job runner")?;
    let monitor_core = core.clone();
    let monitor_thread = std::thread::Builder::new()
        .name("worker-monitor".into())
        .spawn(move || workers::monitor(monitor_core))
        .context("cannot start the worker monitor")?;
    let result = rt.block_on(async {
        let listener = tokio::net::TcpListener::from_std(listener)?;
        let settings = mscale_proto::server::Settings { timeout: Some(Duration::from_secs(60)), ..Default::default() };
        let mut builder = mscale_proto::server::builder(&settings);
        if let Some((cert, key)) = &opts.tls {
            let mut config = tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(cert, key));
            if let Some(ca) = &opts.client_ca {
                config = config.client_ca_root(tonic::transport::Certificate::from_pem(ca)).client_auth_optional(false);
            }
            builder = builder.tls_config(config).context("bad TLS certificate or key")?;
        }
        let service = OrchestratorServer::new(api::JobService::new(core.clone()))
            .max_decoding_message_size(MAX_MESSAGE)
            .max_encoding_message_size(MAX_MESSAGE);
        let service = md_worker::metrics::Timed::new(service, core.metrics.rpc.clone());
        let router = mscale_proto::server::router(&mut builder, service)
            .await
            .map_err(|e| anyhow::anyhow!("cannot set up the gRPC services: {e}"))?;
        let incoming = mscale_proto::server::incoming(listener).map_err(|e| anyhow::anyhow!("listening: {e}"))?;
        println!("mscale serve: listening on {bound}");
        use std::io::Write;
        let _ = std::io::stdout().flush();
        if let Some(l) = http_listener {
            let l = tokio::net::TcpListener::from_std(l)?;
            let scheme = if http_tls.is_some() { "https" } else { "http" };
            // After the gRPC line, which scripts and tests read first; its reader may be gone.
            let _ = writeln!(std::io::stdout(), "mscale serve: dashboard and metrics on {scheme}://{}", l.local_addr()?);
            let _ = std::io::stdout().flush();
            let mut stop = core.stop_watchers.subscribe();
            let router = http::router(core.clone(), http_tls.is_some());
            tokio::spawn(md_worker::metrics::serve_http(l, router, http_tls.clone(), async move {
                let _ = stop.wait_for(|s| *s).await;
            }));
        }
        tracing::info!("state in {}", opts.state_dir.display());
        let mut hangup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).context("cannot catch SIGHUP")?;
        let reload_core = core.clone();
        tokio::spawn(async move {
            while hangup.recv().await.is_some() {
                let core = reload_core.clone();
                let _ = tokio::task::spawn_blocking(move || core.reload_users()).await;
            }
        });
        let shutdown = async {
            let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = async { match term.as_mut() { Some(t) => { t.recv().await; } None => std::future::pending::<()>().await } } => {}
            }
            tracing::info!("stopping: the running job checkpoints and resumes on the next start");
            core.stop();
        };
        router.serve_with_incoming_shutdown(incoming, shutdown).await.context("serving")
    });
    core.stop();
    let _ = runner_thread.join();
    let _ = monitor_thread.join();
    result
}
