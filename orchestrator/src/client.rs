//! The client verbs of `mscale` for a job service (`mscale serve`): submit, status, watch,
//! cancel, fetch, health. Each call blocks on a small tokio runtime; the token for mutating
//! calls comes from `--token-file` or `MSCALE_TOKEN`.

use crate::service::{MAX_MESSAGE, for_each_string};
use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1 as pb;
use pb::orchestrator_client::OrchestratorClient;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use tonic::transport::Channel;

/// Default address of `mscale serve` and of its clients.
pub const DEFAULT_SERVER: &str = "127.0.0.1:50100";

pub struct Client {
    rt: tokio::runtime::Runtime,
    inner: OrchestratorClient<Channel>,
    channel: Channel,
    token: Option<String>,
    server: String,
}

/// The token from `--token-file` or, without one, `MSCALE_TOKEN`.
pub fn token(token_file: Option<&Path>) -> Result<Option<String>> {
    if let Some(f) = token_file {
        return crate::service::read_token(f).map(Some);
    }
    Ok(std::env::var("MSCALE_TOKEN").ok().map(|t| t.trim().to_string()).filter(|t| !t.is_empty()))
}

fn status_text(s: &tonic::Status) -> String {
    format!("{} ({:?})", s.message(), s.code())
}

impl Client {
    /// Plain HTTP/2 (for loopback).
    pub fn connect(server: &str, token: Option<String>) -> Result<Self> {
        Self::connect_with(server, token, None)
    }

    /// With `ca` (a PEM file of the certificate authority to trust), over TLS.
    pub fn connect_with(server: &str, token: Option<String>, ca: Option<&Path>) -> Result<Self> {
        let scheme = if ca.is_some() { "https" } else { "http" };
        let url = if server.starts_with("http") { server.to_string() } else { format!("{scheme}://{server}") };
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().context("cannot start the gRPC runtime")?;
        let mut endpoint = tonic::transport::Endpoint::from_shared(url.clone())?.connect_timeout(std::time::Duration::from_secs(10));
        if let Some(ca) = ca {
            let pem = std::fs::read(ca).with_context(|| format!("cannot read the CA file {}", ca.display()))?;
            endpoint = endpoint.tls_config(tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(pem))).context("bad TLS settings")?;
        }
        let channel = rt.block_on(endpoint.connect()).with_context(|| format!("cannot reach the orchestrator at {server}"))?;
        let inner = OrchestratorClient::new(channel.clone()).max_decoding_message_size(MAX_MESSAGE).max_encoding_message_size(MAX_MESSAGE);
        Ok(Client { rt, inner, channel, token, server: server.to_string() })
    }

    fn authorized<T>(&self, msg: T) -> Result<tonic::Request<T>> {
        let mut req = tonic::Request::new(msg);
        if let Some(t) = &self.token {
            req.metadata_mut().insert("authorization", format!("Bearer {t}").parse().context("the token has characters a header cannot carry")?);
        }
        Ok(req)
    }

    /// Submits a scene with the files it names (every string value naming an existing file
    /// relative to the scene); returns the job id.
    pub fn submit(&mut self, scene_path: &Path, sets: &[String], priority: i32, checkpoint_every: u64) -> Result<String> {
        let text = std::fs::read_to_string(scene_path).with_context(|| format!("cannot read {}", scene_path.display()))?;
        let base = scene_path.parent().unwrap_or(Path::new("."));
        let mut files = Vec::new();
        if let Ok(mut doc) = text.parse::<toml_edit::DocumentMut>() {
            let mut names = Vec::new();
            for_each_string(doc.as_item_mut(), &mut |v| {
                if let Some(s) = v.as_str() {
                    names.push(s.to_string());
                }
            });
            names.sort();
            names.dedup();
            for name in names {
                let p: PathBuf = base.join(&name);
                if !name.is_empty() && p.is_file() {
                    let content = std::fs::read(&p).with_context(|| format!("cannot read {}", p.display()))?;
                    files.push(pb::InputFile { sha256: hex::encode(Sha256::digest(&content)), name, content });
                }
            }
        }
        let req = pb::SubmitJobRequest {
            scene_text: text,
            files,
            overrides: sets.to_vec(),
            priority,
            checkpoint_every_steps: checkpoint_every,
            scene_file: scene_path.display().to_string(),
        };
        let req = self.authorized(req)?;
        let r = self.rt.block_on(self.inner.submit_job(req)).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner().job_id)
    }

    pub fn get(&mut self, id: &str) -> Result<pb::Job> {
        let r = self.rt.block_on(self.inner.get_job(pb::GetJobRequest { job_id: id.into() })).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner())
    }

    pub fn list(&mut self) -> Result<Vec<pb::Job>> {
        let r = self.rt.block_on(self.inner.list_jobs(pb::ListJobsRequest {})).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner().jobs)
    }

    pub fn cancel(&mut self, id: &str) -> Result<pb::Job> {
        let req = self.authorized(pb::CancelJobRequest { job_id: id.into() })?;
        let r = self.rt.block_on(self.inner.cancel_job(req)).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner())
    }

    /// Follows a job to its end, calling `on` for every event; returns the last one.
    pub fn watch(&mut self, id: &str, mut on: impl FnMut(&pb::JobEvent)) -> Result<pb::JobEvent> {
        let mut inner = self.inner.clone();
        let server = self.server.clone();
        self.rt.block_on(async move {
            let mut stream = inner.watch_job(pb::WatchJobRequest { job_id: id.into() }).await.map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?.into_inner();
            let mut last = None;
            while let Some(ev) = stream.message().await.map_err(|s| anyhow::anyhow!("{}", status_text(&s)))? {
                on(&ev);
                last = Some(ev);
            }
            match last {
                Some(ev) if is_final(&ev) => Ok(ev),
                _ => bail!("the orchestrator at {server} closed the watch of job {id} before it ended"),
            }
        })
    }

    pub fn fetch(&mut self, id: &str, file: &str) -> Result<Vec<u8>> {
        let r = self.rt.block_on(self.inner.fetch_result(pb::FetchResultRequest { job_id: id.into(), path: file.into() })).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?.into_inner();
        let actual = hex::encode(Sha256::digest(&r.content));
        anyhow::ensure!(actual == r.sha256, "{file} arrived damaged: SHA-256 {actual}, sent as {}", r.sha256);
        Ok(r.content)
    }

    /// Registered workers, oldest registration first.
    pub fn workers(&mut self) -> Result<Vec<pb::Worker>> {
        let r = self.rt.block_on(self.inner.list_workers(pb::ListWorkersRequest {})).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner().workers)
    }

    /// The worker gets no new jobs.
    pub fn drain(&mut self, worker: &str) -> Result<pb::Worker> {
        let req = self.authorized(pb::DrainWorkerRequest { worker_id: worker.into() })?;
        let r = self.rt.block_on(self.inner.drain_worker(req)).map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?;
        Ok(r.into_inner())
    }

    /// Registers a worker (what `md-worker serve --orchestrator` does); the status on refusal.
    pub fn register_worker(&mut self, req: pb::RegisterWorkerRequest) -> Result<pb::RegisterWorkerResponse, tonic::Status> {
        let req = self.authorized(req).map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
        self.rt.block_on(self.inner.register_worker(req)).map(|r| r.into_inner())
    }

    /// One heartbeat of a registered worker; the status on refusal.
    pub fn heartbeat(&mut self, req: pb::HeartbeatRequest) -> Result<pb::HeartbeatResponse, tonic::Status> {
        let req = self.authorized(req).map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
        self.rt.block_on(self.inner.heartbeat(req)).map(|r| r.into_inner())
    }

    /// The gRPC health of the orchestrator service (`SERVING`, ...).
    pub fn health(&mut self) -> Result<String> {
        let mut h = tonic_health::pb::health_client::HealthClient::new(self.channel.clone());
        let r = self
            .rt
            .block_on(h.check(tonic_health::pb::HealthCheckRequest { service: "mscale.orchestrator.v1.Orchestrator".into() }))
            .map_err(|s| anyhow::anyhow!("{}", status_text(&s)))?
            .into_inner();
        Ok(format!("{:?}", tonic_health::pb::health_check_response::ServingStatus::try_from(r.status).unwrap_or_default()).to_uppercase())
    }
}

pub fn state_name(state: i32) -> &'static str {
    match pb::JobState::try_from(state) {
        Ok(pb::JobState::Queued) => "queued",
        Ok(pb::JobState::Running) => "running",
        Ok(pb::JobState::Completed) => "completed",
        Ok(pb::JobState::Failed) => "failed",
        Ok(pb::JobState::Cancelled) => "cancelled",
        _ => "unknown",
    }
}

pub fn is_final(ev: &pb::JobEvent) -> bool {
    matches!(pb::JobState::try_from(ev.state), Ok(pb::JobState::Completed | pb::JobState::Failed | pb::JobState::Cancelled))
}

// ---- the verbs, as `mscale` runs them (each returns its exit code) ----

/// The worker pool options of `mscale serve`.
#[derive(Debug, Clone, Copy)]
pub struct PoolOptions {
    /// `md-worker serve` processes to start here.
    pub local_workers: usize,
    /// Seconds without a heartbeat after which a worker is declared lost.
    pub worker_timeout_s: f64,
}

/// `mscale serve`.
pub fn serve(state: PathBuf, listen: String, token_file: Option<PathBuf>, checkpoint_every: u64, tls: Option<(PathBuf, PathBuf)>, pool: PoolOptions) -> Result<i32> {
    anyhow::ensure!(pool.worker_timeout_s.is_finite() && pool.worker_timeout_s > 0.0, "--worker-timeout {} must be a positive number of seconds", pool.worker_timeout_s);
    let token = match &token_file {
        Some(f) => crate::service::read_token(f)?,
        None => generated_token(&state)?,
    };
    let token_file = token_file.unwrap_or_else(|| state.join("token"));
    let local_ca = tls.as_ref().map(|t| t.0.clone());
    let tls = match tls {
        Some((cert, key)) => {
            let read = |p: &Path| std::fs::read(p).with_context(|| format!("cannot read {}", p.display()));
            Some((read(&cert)?, read(&key)?))
        }
        None => None,
    };
    crate::service::serve(crate::service::ServeOptions {
        state_dir: state,
        listen,
        token,
        checkpoint_every,
        tls,
        local_workers: pool.local_workers,
        token_file,
        local_ca,
        worker_timeout: std::time::Duration::from_secs_f64(pool.worker_timeout_s),
    })?;
    Ok(crate::exit::OK)
}

/// The token in `<state>/token`, generated (256 bits from the OS, mode 0600) when missing.
fn generated_token(state: &Path) -> Result<String> {
    use std::io::Read;
    let path = state.join("token");
    if path.exists() {
        return crate::service::read_token(&path);
    }
    std::fs::create_dir_all(state).with_context(|| format!("cannot create {}", state.display()))?;
    let mut bytes = [0u8; 32];
    std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut bytes)).context("cannot read /dev/urandom for a token")?;
    let token = hex::encode(bytes);
    {
        use std::io::Write;
        use std::os::unix::fs::OpenOptionsExt;
        let mut f = std::fs::OpenOptions::new().write(true).create_new(true).mode(0o600).open(&path).with_context(|| format!("cannot create {}", path.display()))?;
        f.write_all(token.as_bytes())?;
        f.sync_all()?;
    }
    tracing::info!("generated a bearer token in {} (pass it with --token-file)", path.display());
    Ok(token)
}

static CA_FILE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

/// Makes the client verbs connect over TLS, trusting this PEM certificate authority
/// (`--ca-file` or `MSCALE_CA_FILE`).
pub fn use_ca_file(path: PathBuf) {
    let _ = CA_FILE.set(path);
}

fn ca_file() -> Option<PathBuf> {
    CA_FILE.get().cloned()
}

/// `mscale submit`.
pub fn submit(server: &str, token_file: Option<&Path>, scene: &Path, sets: &[String], priority: i32, checkpoint_every: u64) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    match c.submit(scene, sets, priority, checkpoint_every) {
        Ok(id) => {
            println!("{id}");
            Ok(crate::exit::OK)
        }
        Err(e) if e.to_string().contains("InvalidArgument") => {
            eprintln!("mscale: {e:#}");
            Ok(crate::exit::BAD_INPUT)
        }
        Err(e) => Err(e),
    }
}

fn line(j: &pb::Job) -> String {
    let digest = if j.state_digest.is_empty() { String::new() } else { format!("  digest {}", j.state_digest) };
    let error = if j.error.is_empty() { String::new() } else { format!("  ({})", j.error) };
    format!("{}  {:<9} {:<20} step {}/{}  t = {:.4e} s  priority {}{}{digest}{error}", j.id, state_name(j.state), j.scene, j.step, j.steps, j.sim_time_s, j.priority, if j.resumes > 0 { format!("  resumed {}x", j.resumes) } else { String::new() })
}

pub fn worker_state_name(state: i32) -> &'static str {
    match pb::WorkerState::try_from(state) {
        Ok(pb::WorkerState::Live) => "live",
        Ok(pb::WorkerState::Draining) => "draining",
        Ok(pb::WorkerState::Lost) => "lost",
        _ => "unknown",
    }
}

fn worker_line(w: &pb::Worker) -> String {
    let job = if w.job_id.is_empty() { String::new() } else { format!("  job {}", w.job_id) };
    let note = if w.note.is_empty() { String::new() } else { format!("  ({})", w.note) };
    format!(
        "{}  {:<8} {:<21} {}/{}  {}  {} cores  {:.3e} atom-steps/s ({}){job}{note}",
        w.id,
        worker_state_name(w.state),
        w.address,
        w.backend,
        w.precision,
        w.device,
        w.cores,
        w.atom_steps_per_s,
        w.throughput_source
    )
}

/// `mscale workers`: the registered workers.
pub fn workers(server: &str, token_file: Option<&Path>) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let ws = c.workers()?;
    if ws.is_empty() {
        println!("no workers");
    }
    for w in ws {
        println!("{}", worker_line(&w));
    }
    Ok(crate::exit::OK)
}

/// `mscale drain WORKER`.
pub fn drain(server: &str, token_file: Option<&Path>, worker: &str) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    println!("{}", worker_line(&c.drain(worker)?));
    Ok(crate::exit::OK)
}

/// `mscale status [JOB]`.
pub fn status(server: &str, token_file: Option<&Path>, job: Option<&str>) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    match job {
        Some(id) => println!("{}", line(&c.get(id)?)),
        None => {
            let jobs = c.list()?;
            if jobs.is_empty() {
                println!("no jobs");
            }
            for j in jobs {
                println!("{}", line(&j));
            }
        }
    }
    Ok(crate::exit::OK)
}

/// `mscale watch JOB`: a progress bar on a terminal, a line per second otherwise.
pub fn watch(server: &str, token_file: Option<&Path>, job: &str) -> Result<i32> {
    use std::io::IsTerminal;
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let bar = std::io::stderr().is_terminal().then(|| {
        let b = indicatif::ProgressBar::new(1);
        b.set_style(indicatif::ProgressStyle::with_template("{spinner} {bar:40} step {pos}/{len}  {msg}").unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()));
        b
    });
    let mut last_line = std::time::Instant::now() - std::time::Duration::from_secs(2);
    let last = c.watch(job, |ev| {
        let eta = if ev.eta_s >= 0.0 { format!("ETA {:.0} s", ev.eta_s) } else { "ETA -".into() };
        let msg = format!("{}  t = {:.4e} s  {:.1} %  energy drift {:.2e}  {eta}", state_name(ev.state), ev.sim_time_s, ev.percent, ev.energy_drift);
        match &bar {
            Some(b) => {
                b.set_length(ev.steps.max(1));
                b.set_position(ev.step);
                b.set_message(msg);
            }
            None if last_line.elapsed().as_secs_f64() >= 1.0 || is_final(ev) => {
                last_line = std::time::Instant::now();
                eprintln!("job {}: step {}/{}  {msg}", ev.job_id, ev.step, ev.steps);
            }
            None => {}
        }
    })?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let j = c.get(job)?;
    println!("{}", line(&j));
    Ok(if pb::JobState::try_from(last.state) == Ok(pb::JobState::Completed) { crate::exit::OK } else { crate::exit::RUN_FAILED })
}

/// `mscale cancel JOB`.
pub fn cancel(server: &str, token_file: Option<&Path>, job: &str) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let j = c.cancel(job)?;
    println!("{}", line(&j));
    Ok(crate::exit::OK)
}

/// `mscale fetch JOB FILE --out PATH`.
pub fn fetch(server: &str, token_file: Option<&Path>, job: &str, file: &str, out: &Path) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let bytes = c.fetch(job, file)?;
    crate::output::write_atomic(out, &bytes)?;
    println!("{} bytes into {}", bytes.len(), out.display());
    Ok(crate::exit::OK)
}

/// `mscale health`.
pub fn health(server: &str, token_file: Option<&Path>) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let s = c.health()?;
    println!("{s}");
    Ok(if s == "SERVING" { crate::exit::OK } else { crate::exit::RUN_FAILED })
}
