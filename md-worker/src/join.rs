//! `md-worker serve --orchestrator URL`: joins the worker pool of an orchestrator
//! (`mscale serve`, `mscale.orchestrator.v1`). Once the worker serves, it registers (address,
//! device, back end and precision, cores, memory, throughput, coupling protocol version) and
//! heartbeats every few seconds. When the orchestrator declared it lost (NOT_FOUND) it
//! registers again, as a new worker; when it is drained it refuses new sessions. A refusal
//! that cannot change by retrying (another protocol version, a bad token) ends the worker.
//!
//! Throughput: measured at start, unless `--throughput` gives it: a short run of the back end
//! the worker serves with on a fixed workload (8 boxes of 108 Cu atoms, the u3 EAM potential
//! compiled in, 10 steps, the fastest of 3 repetitions after one warm-up). Only the ratios
//! between workers matter (boxes are spread in proportion to it); a GPU is underrated by a
//! workload this small, so give GPU workers `--throughput` from `md-worker bench`.

use crate::backend::{BoxResult, BoxSpec, BoxWork};
use crate::lattice::LatticeKind;
use crate::potential::Potential;
use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1 as pb;
use pb::orchestrator_client::OrchestratorClient;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use tonic::Code;

/// `md-worker serve` options for joining a pool.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct JoinArgs {
    /// Join the worker pool of this orchestrator (`mscale serve`), e.g. http://10.0.0.1:50100.
    #[arg(long, value_name = "URL")]
    pub orchestrator: Option<String>,
    /// HOST:PORT the orchestrator reaches this worker at (default: the --listen address,
    /// which then must not be a wildcard such as 0.0.0.0).
    #[arg(long, value_name = "HOST:PORT", requires = "orchestrator")]
    pub advertise: Option<String>,
    /// File holding the orchestrator's bearer token (default: the MSCALE_TOKEN variable).
    #[arg(long, value_name = "FILE", requires = "orchestrator")]
    pub token_file: Option<PathBuf>,
    /// Reach the orchestrator over TLS, trusting this PEM certificate authority.
    #[arg(long, value_name = "PEM", requires = "orchestrator")]
    pub ca_file: Option<PathBuf>,
    /// Present this PEM client certificate to the orchestrator (mutual TLS: `mscale serve
    /// --tls-client-ca`); needs --ca-file and --client-key.
    #[arg(long, value_name = "PEM", requires_all = ["ca_file", "client_key"])]
    pub client_cert: Option<PathBuf>,
    /// PEM private key of --client-cert.
    #[arg(long, value_name = "PEM", requires = "client_cert")]
    pub client_key: Option<PathBuf>,
    /// Seconds between heartbeats (at most a third of the orchestrator's worker timeout is used).
    #[arg(long, value_name = "SECONDS", default_value_t = 2.0)]
    pub heartbeat_every: f64,
    /// Advertise this MD throughput (atom-steps/s) instead of measuring it at start.
    #[arg(long, value_name = "ATOM_STEPS_PER_S")]
    pub throughput: Option<f64>,
}

/// Set while the orchestrator has this worker draining: `Open` of a new session is refused.
static DRAINING: AtomicBool = AtomicBool::new(false);

/// Whether this worker is draining (it takes no new sessions).
pub fn draining() -> bool {
    DRAINING.load(Ordering::SeqCst)
}

/// What the worker serves with, for its registration and throughput measurement.
pub struct WorkerKind {
    /// Back end of new sessions (`cpu`, `cuda`, ...).
    pub backend: String,
    pub precision: String,
    pub device: String,
    /// The cpu back end's thread pool (the global one when `None`).
    pub threads: Option<Arc<rayon::ThreadPool>>,
}

/// Atom-steps per second of `kind`'s back end on the fixed workload described above.
pub fn measure_throughput(kind: &WorkerKind) -> Result<f64> {
    let pot = Arc::new(Potential::from_text("Cu_u3.eam", include_str!("../potentials/Cu_u3.eam"))?);
    // The worker's cuda back end, or (every other kind: cpu, mpi, null) the cpu back end on
    // its threads.
    let device = if kind.backend == "cuda" { "cuda" } else { "cpu" };
    let choice = crate::device::BackendChoice::on_device(device, &kind.precision).with_threads(kind.threads.clone());
    let mut b = crate::device::build(&choice, pot, None)?;
    let (boxes, steps) = (8u64, 10u64);
    let specs: Vec<BoxSpec> = (0..boxes)
        .map(|id| {
            let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [3, 3, 3]);
            s.temperature_k = 300.0;
            s.seed = 1;
            s
        })
        .collect();
    b.open(&specs)?;
    let work: Vec<BoxWork> = (0..boxes).map(|id| BoxWork::new(id, [[1e-3, 0.0, 0.0], [0.0; 3], [0.0; 3]], steps, 0.001)).collect();
    let mut out = vec![BoxResult::default(); boxes as usize];
    b.step(&work, &mut out)?;
    let mut best = f64::INFINITY;
    for _ in 0..3 {
        let t = Instant::now();
        b.step(&work, &mut out)?;
        best = best.min(t.elapsed().as_secs_f64());
    }
    Ok((boxes * 108 * steps) as f64 / best.max(1e-9))
}

fn memory_bytes() -> u64 {
    let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
    meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}

/// A running membership: fails (see [`Join::failed`]) when the orchestrator refuses the worker
/// for good.
pub struct Join {
    error: tokio::sync::watch::Receiver<Option<String>>,
}

impl Join {
    /// Starts registering and heartbeating (a task on the current tokio runtime). Without
    /// `--orchestrator` it does nothing and never fails.
    pub fn start(args: &JoinArgs, bound: SocketAddr, kind: WorkerKind) -> Result<Join> {
        let (tx, error) = tokio::sync::watch::channel(None);
        let Some(url) = args.orchestrator.clone() else { return Ok(Join { error }) };
        let address = match &args.advertise {
            Some(a) => a.clone(),
            None if bound.ip().is_unspecified() => bail!(
                "--listen {bound} is a wildcard address; give --advertise HOST:PORT, the address the orchestrator reaches this worker at"
            ),
            None => bound.to_string(),
        };
        let token = match &args.token_file {
            Some(f) => {
                std::fs::read_to_string(f).with_context(|| format!("cannot read the token file {}", f.display()))?.trim().to_string()
            }
            None => std::env::var("MSCALE_TOKEN").unwrap_or_default().trim().to_string(),
        };
        anyhow::ensure!(!token.is_empty(), "--orchestrator needs the orchestrator's token: --token-file FILE or MSCALE_TOKEN");
        anyhow::ensure!(
            args.heartbeat_every.is_finite() && args.heartbeat_every > 0.0,
            "--heartbeat-every {} must be a positive number of seconds",
            args.heartbeat_every
        );
        let read = |f: &PathBuf, what: &str| std::fs::read(f).with_context(|| format!("cannot read the {what} {}", f.display()));
        let identity = match (&args.client_cert, &args.client_key) {
            (Some(c), Some(k)) => Some((read(c, "client certificate")?, read(k, "client key")?)),
            _ => None,
        };
        let ca = args.ca_file.as_ref().map(|f| read(f, "CA file")).transpose()?.map(|ca| (ca, identity));
        let (configured, heartbeat) = (args.throughput, Duration::from_secs_f64(args.heartbeat_every));
        if let Some(t) = configured {
            anyhow::ensure!(t.is_finite() && t > 0.0, "--throughput {t} must be a positive number of atom-steps per second");
        }
        tokio::spawn(async move {
            let r = member(url.clone(), address, token, ca, configured, heartbeat, kind).await;
            if let Err(e) = r {
                tracing::error!("joining {url}: {e:#}");
                let _ = tx.send(Some(format!("{e:#}")));
            }
        });
        Ok(Join { error })
    }

    /// Resolves when the orchestrator refused this worker for good; never without one.
    pub async fn failed(&self) {
        let mut rx = self.error.clone();
        let _ = rx.wait_for(|e| e.is_some()).await;
        if rx.borrow().is_none() {
            std::future::pending::<()>().await;
        }
    }

    /// The refusal, if there was one.
    pub fn outcome(&self) -> Result<()> {
        match self.error.borrow().as_ref() {
            Some(e) => bail!("the orchestrator refused this worker: {e}"),
            None => Ok(()),
        }
    }
}

fn authorized<T>(token: &str, msg: T) -> Result<tonic::Request<T>> {
    let mut req = tonic::Request::new(msg);
    req.metadata_mut()
        .insert("authorization", format!("Bearer {token}").parse().context("the token has characters a header cannot carry")?);
    Ok(req)
}

/// Codes that retrying does not change.
fn fatal(s: &tonic::Status) -> bool {
    matches!(s.code(), Code::FailedPrecondition | Code::Unauthenticated | Code::InvalidArgument | Code::PermissionDenied)
}

/// The authority to trust and the client identity (certificate, key) to present, PEM.
type TlsFiles = (Vec<u8>, Option<(Vec<u8>, Vec<u8>)>);

async fn connect(url: &str, tls: Option<&TlsFiles>) -> Result<OrchestratorClient<tonic::transport::Channel>> {
    let mut ep = tonic::transport::Endpoint::from_shared(url.to_string())
        .with_context(|| format!("bad orchestrator URL {url:?}"))?
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(10));
    if let Some((pem, identity)) = tls {
        let mut config = tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(pem));
        if let Some((cert, key)) = identity {
            config = config.identity(tonic::transport::Identity::from_pem(cert, key));
        }
        ep = ep.tls_config(config).context("bad TLS settings")?;
    }
    Ok(OrchestratorClient::new(ep.connect_lazy()))
}

/// Registers, heartbeats, registers again when declared lost; returns only on a refusal.
async fn member(
    url: String,
    address: String,
    token: String,
    ca: Option<TlsFiles>,
    configured: Option<f64>,
    heartbeat: Duration,
    kind: WorkerKind,
) -> Result<()> {
    let (atom_steps_per_s, source) = match configured {
        Some(t) => (t, "configured (--throughput)".to_string()),
        None => {
            let (threads, backend, precision) = (kind.threads.clone(), kind.backend.clone(), kind.precision.clone());
            let k = WorkerKind { backend, precision, device: String::new(), threads };
            let t = tokio::task::spawn_blocking(move || measure_throughput(&k)).await.context("throughput measurement")??;
            (t, "measured at start: 8 boxes of 108 Cu atoms (u3 EAM), 10 steps".to_string())
        }
    };
    tracing::info!("throughput {atom_steps_per_s:.3e} atom-steps/s ({source})");
    let mut client = connect(&url, ca.as_ref()).await?;
    let cores = kind.threads.as_ref().map_or_else(rayon::current_num_threads, |p| p.current_num_threads()) as u32;
    let register = pb::RegisterWorkerRequest {
        address: address.clone(),
        device: kind.device.clone(),
        backend: kind.backend.clone(),
        precision: kind.precision.clone(),
        cores,
        memory_bytes: memory_bytes(),
        atom_steps_per_s,
        throughput_source: source,
        protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
    };
    let mut warned = false;
    loop {
        let reg = match client.register_worker(authorized(&token, register.clone())?).await {
            Ok(r) => r.into_inner(),
            Err(s) if fatal(&s) => bail!("{} ({:?})", s.message(), s.code()),
            Err(s) => {
                if !warned {
                    tracing::warn!("cannot register with {url} yet ({}); retrying", s.message());
                    warned = true;
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        warned = false;
        DRAINING.store(false, Ordering::SeqCst);
        let every = heartbeat.min(Duration::from_secs_f64((reg.timeout_s / 3.0).max(0.05)));
        tracing::info!(
            "joined the pool of {url} as {} (epoch {}) at {address}; heartbeat every {:.2} s",
            reg.worker_id,
            reg.epoch,
            every.as_secs_f64()
        );
        loop {
            tokio::time::sleep(every).await;
            let hb = pb::HeartbeatRequest {
                worker_id: reg.worker_id.clone(),
                epoch: reg.epoch,
                protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
            };
            match client.heartbeat(authorized(&token, hb)?).await {
                Ok(r) => {
                    let drain = r.into_inner().drain;
                    if drain != DRAINING.swap(drain, Ordering::SeqCst) {
                        tracing::info!("{}", if drain { "draining: no new sessions" } else { "no longer draining" });
                    }
                    warned = false;
                }
                Err(s) if s.code() == Code::NotFound => {
                    tracing::warn!("{}; registering again", s.message());
                    break;
                }
                Err(s) if fatal(&s) => bail!("{} ({:?})", s.message(), s.code()),
                Err(s) => {
                    if !warned {
                        tracing::warn!("heartbeat to {url} failed ({}); retrying", s.message());
                        warned = true;
                    }
                }
            }
        }
    }
}
