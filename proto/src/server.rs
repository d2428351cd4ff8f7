//! The gRPC server set-up both of mscale's servers share (`mscale serve` and `md-worker
//! serve`): gRPC health (the service reported serving) and reflection of every mscale service
//! next to it, TCP_NODELAY on every accepted socket, HTTP/2 keep-alive, and the caller's
//! bounds ([`Settings`]). TLS, where a server offers it, is added by the caller
//! ([`tonic::transport::Server::tls_config`] on the builder), as is the message size limit of
//! its generated service type (`max_decoding_message_size`, `max_encoding_message_size`).

use std::convert::Infallible;
use std::time::Duration;
use tonic::body::BoxBody;
use tonic::codegen::Service;
use tonic::codegen::http::{Request, Response};
use tonic::server::NamedService;
use tonic::transport::Server;
use tonic::transport::server::{Router, TcpIncoming};

pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Interval of the HTTP/2 keep-alive pings both servers send.
pub const KEEPALIVE: Duration = Duration::from_secs(30);

/// What differs between the servers.
#[derive(Debug, Clone, Copy, Default)]
pub struct Settings {
    /// Bound on each call (None: none; the coupling's `Step` stream lasts as long as a run).
    pub timeout: Option<Duration>,
    /// HTTP/2 flow-control windows and largest frame (bytes; None: the defaults).
    pub stream_window: Option<u32>,
    pub connection_window: Option<u32>,
    pub max_frame: Option<u32>,
}

/// A server builder with `settings`, TCP_NODELAY and keep-alive.
pub fn builder(settings: &Settings) -> Server {
    let b = Server::builder()
        .tcp_nodelay(true)
        .http2_keepalive_interval(Some(KEEPALIVE))
        .initial_stream_window_size(settings.stream_window)
        .initial_connection_window_size(settings.connection_window)
        .max_frame_size(settings.max_frame);
    match settings.timeout {
        Some(t) => b.timeout(t),
        None => b,
    }
}

/// The connections accepted on an already bound listener, each with TCP_NODELAY: the builder's
/// setting covers only listeners tonic binds itself, and without it Nagle's algorithm and
/// delayed ACKs hold a small reply's last segment back by ~40 ms.
pub fn incoming(listener: tokio::net::TcpListener) -> Result<TcpIncoming, BoxError> {
    TcpIncoming::from_listener(listener, true, None)
}

/// `service` on `server`, with gRPC health (reporting `service` serving) and reflection.
pub async fn router<S>(server: &mut Server, service: S) -> Result<Router, BoxError>
where
    S: Service<Request<BoxBody>, Response = Response<BoxBody>, Error = Infallible> + NamedService + Clone + Send + 'static,
    S::Future: Send + 'static,
{
    let (mut health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<S>().await;
    let reflection =
        tonic_reflection::server::Builder::configure().register_encoded_file_descriptor_set(crate::FILE_DESCRIPTOR_SET).build_v1()?;
    Ok(server.add_service(health_service).add_service(reflection).add_service(service))
}
