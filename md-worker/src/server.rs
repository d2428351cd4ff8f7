//! `md-worker serve`: hosts boxes for coordinators over gRPC (`mscale.coupling.v1`).
//!
//! The service only decodes, calls an [`MdBackend`], and encodes. MD work runs on blocking
//! threads (and the back end's rayon pool), never on the tokio runtime, so health checks and
//! other calls are answered while a batch computes. Every server registers gRPC health
//! (NOT_SERVING until ready) and reflection.

use crate::backend::MdBackend;
use crate::error::MdError;
use crate::ids::IdMap;
use crate::metrics::{Timed, WorkerMetrics};
use crate::pool::PotentialSource;
use crate::potential::Potential;
use crate::wire;
use mscale_proto::coupling::v1 as pb;
use pb::md_worker_server::{MdWorker, MdWorkerServer};
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status};

type Shared<T> = Arc<Mutex<T>>;

/// What a worker serves with.
#[derive(Clone)]
pub struct ServeOptions {
    /// Back end for new sessions: `cpu` or `reference`.
    pub backend: String,
    /// Rayon pool for the `cpu` back end (global pool if `None`).
    pub threads: Option<Arc<rayon::ThreadPool>>,
    /// Device description reported by `Info`.
    pub device: String,
}

pub struct WorkerService {
    opts: ServeOptions,
    potentials: Shared<HashMap<String, Arc<Potential>>>,
    sessions: Shared<HashMap<u64, Shared<Box<dyn MdBackend>>>>,
    next_session: AtomicU64,
    /// What it counts (`--metrics`), and the atoms of every open box by session and point
    /// (one session lookup per batch, then the cheap point-id hash per box).
    metrics: Arc<WorkerMetrics>,
    atoms: Shared<HashMap<u64, IdMap<u64>>>,
    /// Potential files as received, by SHA-256: the `mpi` back end ships them to its ranks.
    #[cfg(feature = "mpi")]
    sources: Shared<HashMap<String, PotentialSource>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl WorkerService {
    pub fn new(opts: ServeOptions) -> Self {
        Self::with_metrics(opts, Arc::default())
    }

    /// A service that counts into `metrics`.
    pub fn with_metrics(opts: ServeOptions, metrics: Arc<WorkerMetrics>) -> Self {
        WorkerService {
            opts,
            potentials: Default::default(),
            sessions: Default::default(),
            next_session: AtomicU64::new(1),
            metrics,
            atoms: Default::default(),
            #[cfg(feature = "mpi")]
            sources: Default::default(),
        }
    }

    /// Records the atoms of boxes opened in `session`.
    fn opened(&self, session: u64, boxes: &[(crate::PointId, u64)]) {
        let mut atoms = lock(&self.atoms);
        if !boxes.is_empty() {
            atoms.entry(session).or_default().extend(boxes.iter().copied());
        }
        self.metrics.boxes.set(atoms.values().map(|s| s.len()).sum::<usize>() as i64);
        self.metrics.atoms.set(atoms.values().flat_map(|s| s.values()).sum::<u64>() as i64);
    }

    fn session(&self, id: u64) -> Result<Shared<Box<dyn MdBackend>>, Status> {
        lock(&self.sessions)
            .get(&id)
            .cloned()
            .ok_or_else(|| Status::not_found(format!("no session {id} on this worker (was it restarted?)")))
    }
}

/// Runs blocking MD work off the runtime.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, MdError> + Send + 'static) -> Result<T, Status> {
    tokio::task::spawn_blocking(f).await.map_err(|e| Status::internal(format!("worker task failed: {e}")))?.map_err(wire::status)
}

#[tonic::async_trait]
impl MdWorker for WorkerService {
    async fn info(&self, _: Request<pb::InfoRequest>) -> Result<Response<pb::InfoResponse>, Status> {
        Ok(Response::new(pb::InfoResponse {
            protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
            device: self.opts.device.clone(),
            cores: std::thread::available_parallelism().map(|n| n.get() as u32).unwrap_or(1),
            version: env!("CARGO_PKG_VERSION").into(),
        }))
    }

    async fn has_potential(&self, req: Request<pb::PotentialRef>) -> Result<Response<pb::HasPotentialResponse>, Status> {
        let present = lock(&self.potentials).contains_key(&req.get_ref().sha256);
        Ok(Response::new(pb::HasPotentialResponse { present }))
    }

    async fn open(&self, req: Request<pb::OpenRequest>) -> Result<Response<pb::OpenResponse>, Status> {
        let req = req.into_inner();
        if req.protocol_version != mscale_proto::COUPLING_PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "coordinator speaks coupling protocol {}, this worker speaks {}",
                req.protocol_version,
                mscale_proto::COUPLING_PROTOCOL_VERSION
            )));
        }
        let pref = req.potential.ok_or_else(|| Status::invalid_argument("`potential` is missing"))?;
        let known = lock(&self.potentials).get(&pref.sha256).cloned();
        let pot = match known {
            Some(p) => p,
            None if req.potential_bytes.is_empty() => {
                return Err(Status::failed_precondition(format!(
                    "this worker lacks potential {} ({}); send its bytes",
                    pref.name, pref.sha256
                )));
            }
            None => {
                let src = PotentialSource::from_bytes(pref.name.clone(), req.potential_bytes);
                if src.sha256 != pref.sha256 {
                    return Err(Status::invalid_argument(format!(
                        "potential {}: bytes hash to {}, not {}",
                        pref.name, src.sha256, pref.sha256
                    )));
                }
                #[cfg(feature = "mpi")]
                lock(&self.sources).insert(pref.sha256.clone(), src.clone());
                let null = self.opts.backend == "null";
                let pot = Arc::new(
                    blocking(move || {
                        if null {
                            Ok(crate::Potential::LjCut(crate::LjCut { epsilon: 0.0, sigma: 1.0, cutoff: 1.0, mass: 1.0 }))
                        } else {
                            src.parse()
                        }
                    })
                    .await?,
                );
                lock(&self.potentials).insert(pref.sha256.clone(), pot.clone());
                pot
            }
        };
        let specs = req.boxes.iter().map(wire::spec_from_pb).collect::<Result<Vec<_>, _>>().map_err(wire::status)?;
        if req.session != 0 {
            let backend = self.session(req.session)?;
            let opened: Vec<_> = specs.iter().map(|s| (s.id, crate::metrics::spec_atoms(s))).collect();
            let name = blocking(move || {
                let mut b = lock(&backend);
                b.open(&specs)?;
                Ok(b.name().to_string())
            })
            .await?;
            self.opened(req.session, &opened);
            return Ok(Response::new(pb::OpenResponse { session: req.session, backend: name, precision: "double".into() }));
        }
        if crate::join::draining() {
            return Err(Status::unavailable("this worker is draining (its orchestrator drained it): it takes no new sessions"));
        }
        let name = if req.backend.is_empty() { self.opts.backend.clone() } else { req.backend.clone() };
        let threads = self.opts.threads.clone();
        let opened: Vec<_> = specs.iter().map(|s| (s.id, crate::metrics::spec_atoms(s))).collect();
        #[cfg(feature = "mpi")]
        let source = lock(&self.sources).get(&pref.sha256).cloned();
        let backend = blocking(move || {
            #[cfg(not(feature = "mpi"))]
            let source: Option<PotentialSource> = None;
            let choice = crate::device::BackendChoice::named(&name).with_threads(threads);
            let mut b = crate::device::build(&choice, pot, source.as_ref())?;
            b.open(&specs)?;
            Ok(b)
        })
        .await?;
        let backend_name = backend.name().to_string();
        let session = self.next_session.fetch_add(1, Ordering::Relaxed);
        lock(&self.sessions).insert(session, Arc::new(Mutex::new(backend)));
        self.opened(session, &opened);
        self.metrics.sessions.set(lock(&self.sessions).len() as i64);
        tracing::info!(session, boxes = req.boxes.len(), backend = %backend_name, "opened boxes");
        Ok(Response::new(pb::OpenResponse { session, backend: backend_name, precision: "double".into() }))
    }

    type StepStream = Pin<Box<dyn Stream<Item = Result<pb::StepResults, Status>> + Send + 'static>>;

    async fn step(&self, req: Request<tonic::Streaming<pb::StepBatch>>) -> Result<Response<Self::StepStream>, Status> {
        let mut inbound = req.into_inner();
        let sessions = self.sessions.clone();
        let (metrics, atoms) = (self.metrics.clone(), self.atoms.clone());
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            while let Some(batch) = inbound.next().await {
                let reply = async {
                    let batch = batch?;
                    let backend = lock(&sessions)
                        .get(&batch.session)
                        .cloned()
                        .ok_or_else(|| Status::not_found(format!("no session {}", batch.session)))?;
                    let work = wire::batch_from_pb(&batch).map_err(wire::status)?;
                    let sizes: Vec<(u64, u64)> = {
                        let atoms = lock(&atoms);
                        let of = atoms.get(&batch.session);
                        work.iter().map(|w| (w.steps, of.and_then(|a| a.get(&w.id)).copied().unwrap_or(0))).collect()
                    };
                    let (results, secs) = blocking(move || {
                        let t = std::time::Instant::now();
                        let mut out = vec![crate::BoxResult::default(); work.len()];
                        lock(&backend).step(&work, &mut out)?;
                        Ok((out, t.elapsed().as_secs_f64()))
                    })
                    .await?;
                    metrics.batch(sizes, secs);
                    Ok(wire::results_to_pb(batch.step, &results, secs))
                }
                .await;
                let failed = reply.is_err();
                if tx.send(reply).await.is_err() || failed {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn snapshot(&self, req: Request<pb::SnapshotRequest>) -> Result<Response<pb::SnapshotResponse>, Status> {
        let req = req.into_inner();
        let backend = self.session(req.session)?;
        let start = std::time::Instant::now();
        let states: Vec<Vec<u8>> = blocking(move || {
            let states = lock(&backend).snapshot(&req.point_ids)?;
            states.iter().map(|s| serde_json::to_vec(s).map_err(|e| MdError::invalid("box state", e.to_string()))).collect()
        })
        .await?;
        self.metrics.snapshot_seconds.observe(start.elapsed().as_secs_f64());
        self.metrics.snapshot_bytes.observe(states.iter().map(Vec::len).sum::<usize>() as f64);
        Ok(Response::new(pb::SnapshotResponse { states }))
    }

    async fn restore(&self, req: Request<pb::RestoreRequest>) -> Result<Response<pb::RestoreResponse>, Status> {
        let req = req.into_inner();
        let backend = self.session(req.session)?;
        let states = req
            .states
            .iter()
            .map(|b| serde_json::from_slice(b).map_err(|e| Status::invalid_argument(format!("box state: {e}"))))
            .collect::<Result<Vec<_>, _>>()?;
        tracing::info!(session = req.session, boxes = states.len(), "restored boxes");
        self.metrics.restores.inc();
        self.metrics.restored_boxes.inc_by(states.len() as u64);
        blocking(move || lock(&backend).restore(states)).await?;
        Ok(Response::new(pb::RestoreResponse {}))
    }

    async fn close(&self, req: Request<pb::CloseRequest>) -> Result<Response<pb::CloseResponse>, Status> {
        let session = req.get_ref().session;
        lock(&self.sessions).remove(&session);
        lock(&self.atoms).remove(&session);
        self.opened(session, &[]);
        self.metrics.sessions.set(lock(&self.sessions).len() as i64);
        Ok(Response::new(pb::CloseResponse {}))
    }
}

/// Serves on an already bound listener until `shutdown` resolves.
pub async fn serve(
    listener: tokio::net::TcpListener,
    opts: ServeOptions,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    serve_with_metrics(listener, opts, Arc::default(), shutdown).await
}

/// [`serve`], counting into `metrics` (which `md-worker serve --metrics` exposes).
pub async fn serve_with_metrics(
    listener: tokio::net::TcpListener,
    opts: ServeOptions,
    metrics: Arc<WorkerMetrics>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let rpc = metrics.rpc.clone();
    let service = MdWorkerServer::new(WorkerService::with_metrics(opts, metrics))
        .max_decoding_message_size(wire::MAX_MESSAGE)
        .max_encoding_message_size(wire::MAX_MESSAGE);
    let service = Timed::new(service, rpc);
    let settings = mscale_proto::server::Settings {
        timeout: None,
        stream_window: Some(wire::HTTP2_STREAM_WINDOW),
        connection_window: Some(wire::HTTP2_CONNECTION_WINDOW),
        max_frame: Some(wire::HTTP2_MAX_FRAME),
    };
    let router = mscale_proto::server::router(&mut mscale_proto::server::builder(&settings), service).await?;
    router.serve_with_incoming_shutdown(mscale_proto::server::incoming(listener)?, shutdown).await?;
    Ok(())
}

/// A worker served in this process on a free loopback port (its own tokio runtime on its own
/// thread), stopped and joined when dropped: for tests and tools that need a real gRPC worker
/// without a process.
pub struct Loopback {
    /// `127.0.0.1:PORT`.
    pub addr: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Loopback {
    /// Serves back end `backend` (a registry name: `reference`, `cpu`, `null`, ...) on rayon's
    /// global pool.
    pub fn start(backend: &str) -> std::io::Result<Loopback> {
        let opts = ServeOptions { backend: backend.into(), threads: None, device: "loopback".into() };
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
        let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        let addr = listener.local_addr()?.to_string();
        let (stop, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let served = rt.block_on(serve(listener, opts, async move {
                let _ = stop_rx.await;
            }));
            if let Err(e) = served {
                tracing::error!("loopback worker: {e}");
            }
        });
        Ok(Loopback { addr, stop: Some(stop), thread: Some(thread) })
    }
}

impl Drop for Loopback {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
