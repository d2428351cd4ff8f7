//! Prometheus metrics (`prometheus-client`, text exposition format) and the small HTTP server
//! both mscale programs expose them on: `md-worker serve --metrics ADDR` and `mscale serve
//! --http ADDR` (which also serves its dashboard there).
//!
//! A worker counts what it computed: step batches, box-steps and atom-steps, the compute
//! seconds of its batches (and their rate), sessions and boxes held, restores (a lost worker's
//! boxes replayed onto this one), snapshot sizes and times (what checkpoints fetch), and the
//! latency of every gRPC call up to its response head ([`Timed`]; for the `Step` stream,
//! that is when the stream opens: a batch's time is `mdworker_step_compute_seconds`).

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::task::{Context, Poll};
use std::time::Instant;
use tonic::codegen::Service;
use tonic::codegen::http;
use tonic::server::NamedService;

/// The content type of the text exposition format.
pub const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// A floating-point gauge.
pub type FloatGauge = Gauge<f64, AtomicU64>;
/// A floating-point counter.
pub type FloatCounter = Counter<f64, AtomicU64>;
/// A histogram family with one constructor for every label set.
pub type HistogramFamily<L> = Family<L, Histogram, fn() -> Histogram>;

/// Buckets of call latencies (s): 0.1 ms to ~3 min.
pub fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(1e-4, 3.0, 14))
}

/// Buckets of sizes (bytes): 1 KiB to ~4 GiB.
pub fn size_histogram() -> Histogram {
    Histogram::new(exponential_buckets(1024.0, 4.0, 12))
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct MethodLabels {
    pub method: String,
}

/// What `md-worker serve` counts.
pub struct WorkerMetrics {
    registry: Registry,
    pub rpc: HistogramFamily<MethodLabels>,
    pub step_batches: Counter,
    pub box_steps: Counter,
    pub atom_steps: Counter,
    pub compute_seconds: FloatCounter,
    pub step_compute: Histogram,
    pub atom_steps_per_second: FloatGauge,
    pub steps_per_second: FloatGauge,
    pub sessions: Gauge,
    pub boxes: Gauge,
    pub atoms: Gauge,
    pub restores: Counter,
    pub restored_boxes: Counter,
    pub snapshot_bytes: Histogram,
    pub snapshot_seconds: Histogram,
}

impl Default for WorkerMetrics {
    fn default() -> Self {
        Self::new()
    }
}

impl WorkerMetrics {
    pub fn new() -> Self {
        let mut r = Registry::default();
        let m = WorkerMetrics {
            rpc: Family::new_with_constructor(latency_histogram),
            step_batches: Counter::default(),
            box_steps: Counter::default(),
            atom_steps: Counter::default(),
            compute_seconds: FloatCounter::default(),
            step_compute: latency_histogram(),
            atom_steps_per_second: FloatGauge::default(),
            steps_per_second: FloatGauge::default(),
            sessions: Gauge::default(),
            boxes: Gauge::default(),
            atoms: Gauge::default(),
            restores: Counter::default(),
            restored_boxes: Counter::default(),
            snapshot_bytes: size_histogram(),
            snapshot_seconds: latency_histogram(),
            registry: Registry::default(),
        };
        r.register("mdworker_rpc_duration_seconds", "gRPC calls served, to the response head (s)", m.rpc.clone());
        r.register("mdworker_step_batches", "Step batches computed", m.step_batches.clone());
        r.register("mdworker_box_steps", "MD steps computed, summed over boxes", m.box_steps.clone());
        r.register("mdworker_atom_steps", "MD atom-steps computed", m.atom_steps.clone());
        r.register("mdworker_compute_seconds", "Wall seconds spent computing step batches", m.compute_seconds.clone());
        r.register("mdworker_step_compute_seconds", "Compute time of one step batch (s)", m.step_compute.clone());
        r.register("mdworker_atom_steps_per_second", "Atom-steps per second of the last step batch", m.atom_steps_per_second.clone());
        r.register("mdworker_steps_per_second", "Step batches per second of compute, last batch", m.steps_per_second.clone());
        r.register("mdworker_sessions", "Open sessions", m.sessions.clone());
        r.register("mdworker_boxes", "MD boxes held", m.boxes.clone());
        r.register("mdworker_atoms", "Atoms in the boxes held", m.atoms.clone());
        r.register("mdworker_restores", "Restore calls (boxes rebuilt on this worker from a checkpoint)", m.restores.clone());
        r.register("mdworker_restored_boxes", "Boxes restored onto this worker", m.restored_boxes.clone());
        r.register("mdworker_snapshot_bytes", "Encoded size of the boxes of one Snapshot call (bytes)", m.snapshot_bytes.clone());
        r.register("mdworker_snapshot_seconds", "Time to snapshot and encode boxes for a checkpoint (s)", m.snapshot_seconds.clone());
        WorkerMetrics { registry: r, ..m }
    }

    /// Counts one computed step batch: `steps_and_atoms` is (MD steps, atoms) of each box.
    pub fn batch(&self, steps_and_atoms: impl IntoIterator<Item = (u64, u64)>, seconds: f64) {
        let (mut box_steps, mut atom_steps) = (0u64, 0u64);
        for (steps, atoms) in steps_and_atoms {
            box_steps += steps;
            atom_steps += steps * atoms;
        }
        self.step_batches.inc();
        self.box_steps.inc_by(box_steps);
        self.atom_steps.inc_by(atom_steps);
        self.compute_seconds.inc_by(seconds);
        self.step_compute.observe(seconds);
        if seconds > 0.0 {
            self.atom_steps_per_second.set(atom_steps as f64 / seconds);
            self.steps_per_second.set(1.0 / seconds);
        }
    }

    /// The text exposition of every metric.
    pub fn render(&self) -> String {
        render(&self.registry)
    }
}

/// `registry` in the text exposition format.
pub fn render(registry: &Registry) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail.
    let _ = prometheus_client::encoding::text::encode(&mut out, registry);
    out
}

/// Atoms of a box spec (as the pool counts them).
pub fn spec_atoms(s: &crate::BoxSpec) -> u64 {
    match &s.atoms {
        crate::InitialAtoms::Lattice { kind, cells, orient, .. } => {
            kind.atoms_per_cell(orient) * cells.iter().map(|&c| c as u64).product::<u64>()
        }
        crate::InitialAtoms::Explicit { types, .. } => types.len() as u64,
    }
}

/// A gRPC service whose calls are timed (to the response head) into a histogram by method.
#[derive(Clone)]
pub struct Timed<S> {
    inner: S,
    rpc: HistogramFamily<MethodLabels>,
}

impl<S> Timed<S> {
    pub fn new(inner: S, rpc: HistogramFamily<MethodLabels>) -> Self {
        Timed { inner, rpc }
    }
}

impl<S: NamedService> NamedService for Timed<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B, R> Service<http::Request<B>> for Timed<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>, Error = Infallible>,
    S::Future: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Infallible>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        let method = req.uri().path().rsplit('/').next().unwrap_or_default().to_string();
        let (start, rpc, fut) = (Instant::now(), self.rpc.clone(), self.inner.call(req));
        Box::pin(async move {
            let r = fut.await;
            rpc.get_or_create(&MethodLabels { method }).observe(start.elapsed().as_secs_f64());
            r
        })
    }
}

/// Serves `router` over HTTP/1.1 (and HTTP/2) on `listener`, through TLS when `tls` is given,
/// until `shutdown` resolves. Connections are served on their own tasks.
pub async fn serve_http(
    listener: tokio::net::TcpListener,
    router: axum::Router,
    tls: Option<tokio_rustls::TlsAcceptor>,
    shutdown: impl Future<Output = ()>,
) {
    use hyper_util::rt::{TokioExecutor, TokioIo};
    use hyper_util::service::TowerToHyperService;
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(c) => c,
                Err(e) => {
                    tracing::warn!("http: accept: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => return,
        };
        let _ = stream.set_nodelay(true);
        let service = TowerToHyperService::new(router.clone());
        let tls = tls.clone();
        tokio::spawn(async move {
            let builder = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
            let served = match tls {
                Some(acceptor) => match acceptor.accept(stream).await {
                    Ok(s) => builder.serve_connection(TokioIo::new(s), service).await,
                    Err(e) => {
                        tracing::debug!("http: TLS handshake with {peer}: {e}");
                        return;
                    }
                },
                None => builder.serve_connection(TokioIo::new(stream), service).await,
            };
            if let Err(e) = served {
                tracing::debug!("http: connection from {peer}: {e}");
            }
        });
    }
}

/// The router of a worker's metrics port: `GET /metrics`.
pub fn router(metrics: Arc<WorkerMetrics>) -> axum::Router {
    axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let m = metrics.clone();
            async move { ([(http::header::CONTENT_TYPE, CONTENT_TYPE)], m.render()) }
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_is_counted_in_box_and_atom_steps() {
        let m = WorkerMetrics::new();
        m.batch([(10, 32), (10, 32), (5, 4)], 0.5);
        assert_eq!((m.step_batches.get(), m.box_steps.get(), m.atom_steps.get()), (1, 25, 660));
        assert_eq!(m.atom_steps_per_second.get(), 1320.0);
        let text = m.render();
        assert!(text.contains("mdworker_atom_steps_total 660"), "{text}");
        assert!(text.contains("mdworker_step_compute_seconds_count 1"), "{text}");
        assert!(text.ends_with("# EOF\n"), "{text}");
    }
}
