//! The HTTP port of `mscale serve --http ADDR`: Prometheus metrics and the dashboard.
//!
//! Routes (every one needs the service's bearer token: `Authorization: Bearer T`, the cookie
//! `mscale_token` or `?token=T`, which answers with that cookie set so the page's own requests
//! carry it): `GET /metrics` (text exposition), `GET /` (the job list), `GET /jobs/ID` (a job's
//! page), `GET /jobs/ID/events` (its watch events as server-sent events, numbered as
//! `mscale watch` gets them; a reconnecting browser resumes after `Last-Event-ID`),
//! `GET /jobs/ID/stress.svg` (the newest snapshot's stress profile), `GET /jobs/ID/results`
//! (the run directory's files as links) and `GET /jobs/ID/files/PATH` (one of them). TLS, like
//! the gRPC port, with the server's certificate; off loopback only with TLS.

use super::auth::{Caller, Need};
use super::convert::is_final;
use super::dashboard;
use super::error::JobError;
use super::shared::Core;
use axum::body::{Body, Bytes};
use axum::extract::{Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use std::sync::Arc;

const COOKIE: &str = "mscale_token";

#[derive(Clone)]
struct Http {
    core: Arc<Core>,
    tls: bool,
}

/// The token a request carries, and whether it came in the query (then it is set as a cookie).
fn given_token(headers: &HeaderMap, query: Option<&str>) -> (String, bool) {
    if let Some(t) = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer ")) {
        return (t.trim().to_string(), false);
    }
    if let Some(t) = query.and_then(|q| q.split('&').find_map(|kv| kv.strip_prefix("token="))) {
        return (percent_decode(t), true);
    }
    let cookies = headers.get_all(header::COOKIE).iter().filter_map(|v| v.to_str().ok()).flat_map(|v| v.split(';'));
    for c in cookies {
        if let Some(t) = c.trim().strip_prefix(COOKIE).and_then(|r| r.strip_prefix('=')) {
            return (t.to_string(), false);
        }
    }
    (String::new(), false)
}

/// `%XX` and `+` of a query value (a malformed escape is kept as it is).
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = b
            .get(i + 1..i + 3)
            .filter(|h| h.iter().all(u8::is_ascii_hexdigit))
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        match (b[i], hex) {
            (b'%', Some(v)) => {
                out.push(v);
                i += 3;
                continue;
            }
            (b'+', _) => out.push(b' '),
            (c, _) => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn text(status: StatusCode, body: String) -> Response {
    (status, [(header::CONTENT_TYPE, "text/plain; charset=utf-8")], body).into_response()
}

fn error(e: JobError) -> Response {
    let status = match &e {
        JobError::NotFound(_) | JobError::NoRunDir(_) | JobError::Unreadable { .. } => StatusCode::NOT_FOUND,
        JobError::NotInRun(_) | JobError::BadFile { .. } | JobError::BadScene(_) | JobError::Ranks(_) => StatusCode::BAD_REQUEST,
        JobError::NoToken { .. } | JobError::WrongToken { .. } => StatusCode::UNAUTHORIZED,
        JobError::Forbidden { .. } => StatusCode::FORBIDDEN,
        JobError::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
        JobError::Stopping => StatusCode::SERVICE_UNAVAILABLE,
        JobError::BeyondEvents { .. } => StatusCode::RANGE_NOT_SATISFIABLE,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    };
    let hint = if status == StatusCode::UNAUTHORIZED {
        "\nopen the page with ?token=TOKEN once (it is then kept in a cookie), or send Authorization: Bearer TOKEN"
    } else {
        ""
    };
    text(status, format!("{}{hint}\n", e.chain()))
}

/// Checks the token of `req` (the same users as the gRPC port; a token is always needed here);
/// on success, who called and the cookie to set (when the token came in the query).
fn authorize(h: &Http, req: &Request, call: &str, need: Need) -> Result<(Caller, Option<HeaderValue>), Response> {
    let (token, from_query) = given_token(req.headers(), req.uri().query());
    if token.is_empty() {
        return Err(error(JobError::NoToken { call: call.to_string() }));
    }
    let caller = h.core.authorize(&token, call, need).map_err(error)?;
    if !from_query {
        return Ok((caller, None));
    }
    let secure = if h.tls { "; Secure" } else { "" };
    Ok((caller, HeaderValue::from_str(&format!("{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict{secure}")).ok()))
}

/// [`authorize`] for a page of job `id`: its owner or an admin (another user's job is not found).
fn authorize_job(h: &Http, req: &Request, call: &str, id: &str) -> Result<Option<HeaderValue>, Response> {
    let (caller, cookie) = authorize(h, req, call, Need::Read)?;
    h.core.owned(&caller, id).map_err(error)?;
    Ok(cookie)
}

/// `body` as HTML, with the cookie when there is one to set.
fn html(body: String, cookie: Option<HeaderValue>) -> Response {
    let mut r = ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], body).into_response();
    if let Some(c) = cookie {
        r.headers_mut().insert(header::SET_COOKIE, c);
    }
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, JobError> + Send + 'static) -> Result<T, Response> {
    match tokio::task::spawn_blocking(f).await {
        Ok(r) => r.map_err(error),
        Err(e) => Err(error(JobError::Task(e))),
    }
}

async fn metrics(State(h): State<Http>, req: Request) -> Response {
    if let Err(r) = authorize(&h, &req, "metrics", Need::Admin) {
        return r;
    }
    let core = h.core.clone();
    match blocking(move || Ok(core.metrics.render(&core))).await {
        Ok(body) => ([(header::CONTENT_TYPE, md_worker::metrics::CONTENT_TYPE)], body).into_response(),
        Err(r) => r,
    }
}

async fn jobs(State(h): State<Http>, req: Request) -> Response {
    let (caller, cookie) = match authorize(&h, &req, "dashboard", Need::Read) {
        Ok(c) => c,
        Err(r) => return r,
    };
    let core = h.core.clone();
    match blocking(move || dashboard::job_list(&core, &caller)).await {
        Ok(page) => html(page, cookie),
        Err(r) => r,
    }
}

async fn job(State(h): State<Http>, Path(id): Path<String>, req: Request) -> Response {
    let cookie = match authorize_job(&h, &req, "dashboard", &id) {
        Ok(c) => c,
        Err(r) => return r,
    };
    let core = h.core.clone();
    match blocking(move || dashboard::job_page(&core, &id)).await {
        Ok(page) => html(page, cookie),
        Err(r) => r,
    }
}

async fn results(State(h): State<Http>, Path(id): Path<String>, req: Request) -> Response {
    if let Err(r) = authorize_job(&h, &req, "dashboard", &id) {
        return r;
    }
    let core = h.core.clone();
    match blocking(move || Ok(dashboard::results(&core, &id))).await {
        Ok(part) => html(part, None),
        Err(r) => r,
    }
}

async fn stress(State(h): State<Http>, Path(id): Path<String>, req: Request) -> Response {
    if let Err(r) = authorize_job(&h, &req, "dashboard", &id) {
        return r;
    }
    let core = h.core.clone();
    match blocking(move || dashboard::stress_svg(&core, &id)).await {
        Ok(svg) => ([(header::CONTENT_TYPE, "image/svg+xml"), (header::CACHE_CONTROL, "no-store")], svg).into_response(),
        Err(r) => r,
    }
}

async fn file(State(h): State<Http>, Path((id, path)): Path<(String, String)>, req: Request) -> Response {
    if let Err(r) = authorize_job(&h, &req, "FetchResult", &id) {
        return r;
    }
    let core = h.core.clone();
    let name = path.rsplit('/').next().unwrap_or("file").to_string();
    match blocking(move || core.fetch_result(&id, &path)).await {
        Ok((content, sha256)) => {
            let ty = if name.ends_with(".json") {
                "application/json"
            } else if name.ends_with(".csv") || name.ends_with(".toml") || name.ends_with(".log") || name.ends_with(".txt") {
                "text/plain; charset=utf-8"
            } else if name.ends_with(".png") {
                "image/png"
            } else {
                "application/octet-stream"
            };
            let mut r = ([(header::CONTENT_TYPE, ty)], content).into_response();
            if let Ok(v) = HeaderValue::from_str(&sha256) {
                r.headers_mut().insert("x-sha256", v);
            }
            r
        }
        Err(r) => r,
    }
}

/// Server-sent events: the job's watch events after `Last-Event-ID` (or `?after=N`), each as
/// `id: SEQ`, `event: job`, `data: JSON`; an error as `event: failure`; the stream ends after
/// the final event.
async fn events(State(h): State<Http>, Path(id): Path<String>, req: Request) -> Response {
    if let Err(r) = authorize_job(&h, &req, "dashboard", &id) {
        return r;
    }
    let query_after = req.uri().query().and_then(|q| q.split('&').find_map(|kv| kv.strip_prefix("after="))).and_then(|v| v.parse().ok());
    let header_after = req.headers().get("last-event-id").and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse().ok());
    let after: u64 = header_after.or(query_after).unwrap_or(0);
    let core = h.core.clone();
    let id2 = id.clone();
    // The job and its newest event: a browser reconnecting after the final event gets an end.
    let (job, newest) = match blocking(move || Ok((core.get(&id2)?, super::shared::lock(&core.store).last_sequence(&id2)?))).await {
        Ok(x) => x,
        Err(r) => return r,
    };
    let sse = |s: String| -> Result<Bytes, std::convert::Infallible> { Ok(Bytes::from(s)) };
    if job.state.is_final() && after >= newest {
        let end = futures_end(sse("event: end\ndata: {}\n\n".into()));
        return sse_response(Body::from_stream(end));
    }
    let rx = match h.core.watch(&id, after) {
        Ok(rx) => rx,
        Err(e) => return error(e),
    };
    let stream = tokio_stream::StreamExt::map(tokio_stream::wrappers::ReceiverStream::new(rx), move |r| match r {
        Ok(ev) => {
            let last = is_final(ev.state);
            let mut s = format!("id: {}\nevent: job\ndata: {}\n\n", ev.sequence, dashboard::event_json(&ev));
            if last {
                s.push_str("event: end\ndata: {}\n\n");
            }
            sse(s)
        }
        Err(e) => sse(format!("event: failure\ndata: {}\n\n", serde_json::json!({ "message": e.chain() }))),
    });
    sse_response(Body::from_stream(stream))
}

fn futures_end(item: Result<Bytes, std::convert::Infallible>) -> impl tokio_stream::Stream<Item = Result<Bytes, std::convert::Infallible>> {
    tokio_stream::iter([item])
}

fn sse_response(body: Body) -> Response {
    let mut r = Response::new(body);
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("text/event-stream"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

/// The router of the HTTP port.
pub(crate) fn router(core: Arc<Core>, tls: bool) -> axum::Router {
    axum::Router::new()
        .route("/", get(jobs))
        .route("/metrics", get(metrics))
        .route("/jobs/:id", get(job))
        .route("/jobs/:id/events", get(events))
        .route("/jobs/:id/stress.svg", get(stress))
        .route("/jobs/:id/results", get(results))
        .route("/jobs/:id/files/*path", get(file))
        .fallback(|| async { text(StatusCode::NOT_FOUND, "no such page (try / or /metrics)\n".into()) })
        .with_state(Http { core, tls })
}

/// A TLS acceptor for the HTTP port from the PEM certificate chain and key of the gRPC port.
pub(crate) fn tls_acceptor(cert: &[u8], key: &[u8]) -> anyhow::Result<tokio_rustls::TlsAcceptor> {
    use anyhow::Context;
    let certs = rustls_pemfile::certs(&mut &cert[..]).collect::<Result<Vec<_>, _>>().context("bad TLS certificate (PEM)")?;
    let key = rustls_pemfile::private_key(&mut &key[..]).context("bad TLS key (PEM)")?.context("no private key in the TLS key file")?;
    let provider = Arc::new(tokio_rustls::rustls::crypto::ring::default_provider());
    let mut config = tokio_rustls::rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("TLS protocol versions")?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .context("bad TLS certificate or key")?;
    config.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_come_from_the_header_the_query_or_the_cookie() {
        let mut h = HeaderMap::new();
        assert_eq!(given_token(&h, None), (String::new(), false));
        assert_eq!(given_token(&h, Some("a=1&token=ab%2Bc+d")), ("ab+c d".to_string(), true));
        h.insert(header::COOKIE, HeaderValue::from_static("x=1; mscale_token=tok"));
        assert_eq!(given_token(&h, None), ("tok".to_string(), false));
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Bearer bearer"));
        assert_eq!(given_token(&h, Some("token=q")), ("bearer".to_string(), false));
        assert_eq!(percent_decode("%zz%4"), "%zz%4");
    }
}
