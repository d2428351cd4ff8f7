//! The client verbs of `mscale` for a job service (`mscale serve`): submit, status, watch,
//! cancel, fetch, health. Each call blocks on a small tokio runtime; the token for mutating
//! calls comes from `--token-file` or `MSCALE_TOKEN`.

use crate::service::store::{JobState, WorkerState};
use crate::service::{MAX_MESSAGE, for_each_string, read_token};
use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1 as pb;
use pb::orchestrator_client::OrchestratorClient;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
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
        return read_token(f).map(Some);
    }
    Ok(std::env::var("MSCALE_TOKEN").ok().map(|t| t.trim().to_string()).filter(|t| !t.is_empty()))
}

pub use crate::exit::Refused;

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
            let mut config = tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(pem));
            if let Some((cert, key)) = CLIENT_IDENTITY.get() {
                let read = |p: &Path| std::fs::read(p).with_context(|| format!("cannot read {}", p.display()));
                config = config.identity(tonic::transport::Identity::from_pem(read(cert)?, read(key)?));
            }
            endpoint = endpoint.tls_config(config).context("bad TLS settings")?;
        }
        let channel = rt.block_on(endpoint.connect()).with_context(|| format!("cannot reach the orchestrator at {server}"))?;
        let inner = OrchestratorClient::new(channel.clone()).max_decoding_message_size(MAX_MESSAGE).max_encoding_message_size(MAX_MESSAGE);
        Ok(Client { rt, inner, channel, token, server: server.to_string() })
    }

    fn authorized<T>(&self, msg: T) -> Result<tonic::Request<T>> {
        let mut req = tonic::Request::new(msg);
        if let Some(t) = &self.token {
            req.metadata_mut()
                .insert("authorization", format!("Bearer {t}").parse().context("the token has characters a header cannot carry")?);
        }
        Ok(req)
    }

    /// Submits a scene with the files it names (every string value naming an existing file
    /// relative to the scene); returns the job id.
    pub fn submit(&mut self, scene_path: &Path, sets: &[String], priority: i32, checkpoint_every: u64) -> Result<String> {
        self.submit_for(scene_path, sets, priority, checkpoint_every, Placement::default())
    }

    /// [`Client::submit`] of a job placed as `how` says.
    pub fn submit_for(
        &mut self,
        scene_path: &Path,
        sets: &[String],
        priority: i32,
        checkpoint_every: u64,
        how: Placement,
    ) -> Result<String> {
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
            workers: how.workers,
            ranks: how.ranks,
        };
        let req = self.authorized(req)?;
        let r = self.rt.block_on(self.inner.submit_job(req)).map_err(Refused)?;
        Ok(r.into_inner().job_id)
    }

    pub fn get(&mut self, id: &str) -> Result<pb::Job> {
        let req = self.authorized(pb::GetJobRequest { job_id: id.into() })?;
        let r = self.rt.block_on(self.inner.get_job(req)).map_err(Refused)?;
        Ok(r.into_inner())
    }

    pub fn list(&mut self) -> Result<Vec<pb::Job>> {
        let req = self.authorized(pb::ListJobsRequest {})?;
        let r = self.rt.block_on(self.inner.list_jobs(req)).map_err(Refused)?;
        Ok(r.into_inner().jobs)
    }

    pub fn cancel(&mut self, id: &str) -> Result<pb::Job> {
        let req = self.authorized(pb::CancelJobRequest { job_id: id.into() })?;
        let r = self.rt.block_on(self.inner.cancel_job(req)).map_err(Refused)?;
        Ok(r.into_inner())
    }

    /// Follows a job to its end from its first event, calling `on` for every event; returns
    /// the last one. See [`Client::watch_from`].
    pub fn watch(&mut self, id: &str, on: impl FnMut(&pb::JobEvent)) -> Result<pb::JobEvent> {
        self.watch_from(id, WatchOptions::default(), on)
    }

    /// Follows a job to its end, calling `on` for every event after `opts.after_sequence` in
    /// sequence order, each once; returns the final one. The sequence numbers are checked to
    /// follow each other (a JOB_EVENT_KIND_NOT_RETAINED event stands for the ones the server no
    /// longer has, and is passed to `on`); when the stream breaks (the orchestrator stopped or
    /// restarted, the connection dropped) or shows a gap, the watch reconnects with
    /// `after_sequence` set to the last event received, for up to `opts.reconnect_for` after
    /// the last event that came.
    pub fn watch_from(&mut self, id: &str, opts: WatchOptions, mut on: impl FnMut(&pb::JobEvent)) -> Result<pb::JobEvent> {
        let mut inner = self.inner.clone();
        let server = self.server.clone();
        self.authorized(())?; // the token can travel in a header
        let token = self.token.clone();
        self.rt.block_on(async move {
            let mut after = opts.after_sequence;
            // Since when no event came, and why.
            let mut broken: Option<Instant> = None;
            let mut pause = Duration::from_millis(100);
            loop {
                let mut req = tonic::Request::new(pb::WatchJobRequest { job_id: id.into(), after_sequence: after });
                if let Some(v) = token.as_ref().and_then(|t| format!("Bearer {t}").parse().ok()) {
                    req.metadata_mut().insert("authorization", v);
                }
                let why = match inner.watch_job(req).await {
                    Err(s) if !retryable(&s) => return Err(Refused(s).into()),
                    Err(s) => Refused(s).to_string(),
                    Ok(r) => {
                        let mut stream = r.into_inner();
                        loop {
                            let ev = match stream.message().await {
                                Ok(Some(ev)) => ev,
                                Ok(None) => break "the stream ended before the job did".to_string(),
                                Err(s) if !retryable(&s) => return Err(Refused(s).into()),
                                Err(s) => break Refused(s).to_string(),
                            };
                            // An orchestrator that numbers no events (older, or a job stored
                            // before numbering): nothing to check.
                            if ev.sequence == 0 {
                                on(&ev);
                                if is_final(&ev) {
                                    return Ok(ev);
                                }
                                continue;
                            }
                            if ev.sequence <= after {
                                continue; // already had it (a replay overlapping what came live)
                            }
                            let not_retained = ev.kind == pb::JobEventKind::NotRetained as i32;
                            let first = if not_retained { ev.not_retained_from } else { ev.sequence };
                            if first != after + 1 {
                                break format!("event {first} came after event {after}");
                            }
                            after = ev.sequence;
                            (broken, pause) = (None, Duration::from_millis(100));
                            on(&ev);
                            if !not_retained && is_final(&ev) {
                                return Ok(ev);
                            }
                        }
                    }
                };
                let since = *broken.get_or_insert_with(|| {
                    tracing::warn!("the watch of job {id} at {server} broke after event {after} ({why}); reconnecting");
                    Instant::now()
                });
                if since.elapsed() >= opts.reconnect_for {
                    bail!(
                        "lost the watch of job {id} at {server} after event {after} ({why}) and could not resume it within {:.0} s",
                        opts.reconnect_for.as_secs_f64()
                    );
                }
                tokio::time::sleep(pause).await;
                pause = (pause * 2).min(Duration::from_secs(1));
            }
        })
    }

    /// Every file of a job's run directory into `out` (see [`RunWriter`]); returns the number
    /// of files and of bytes.
    pub fn fetch_run(&mut self, id: &str, out: &Path) -> Result<(usize, u64)> {
        let mut writer = RunWriter::new(out)?;
        let mut inner = self.inner.clone();
        let req = self.authorized(pb::FetchRunRequest { job_id: id.into(), chunk_bytes: 0 })?;
        self.rt.block_on(async move {
            let mut stream = inner.fetch_run(req).await.map_err(Refused)?.into_inner();
            while let Some(c) = stream.message().await.map_err(Refused).with_context(|| format!("fetch of job {id}"))? {
                writer.chunk(&c)?;
            }
            writer.finish()
        })
    }

    pub fn fetch(&mut self, id: &str, file: &str) -> Result<Vec<u8>> {
        let req = self.authorized(pb::FetchResultRequest { job_id: id.into(), path: file.into() })?;
        let r = self.rt.block_on(self.inner.fetch_result(req)).map_err(Refused)?.into_inner();
        let actual = hex::encode(Sha256::digest(&r.content));
        anyhow::ensure!(actual == r.sha256, "{file} arrived damaged: SHA-256 {actual}, sent as {}", r.sha256);
        Ok(r.content)
    }

    /// Registered workers, oldest registration first.
    pub fn workers(&mut self) -> Result<Vec<pb::Worker>> {
        let req = self.authorized(pb::ListWorkersRequest {})?;
        let r = self.rt.block_on(self.inner.list_workers(req)).map_err(Refused)?;
        Ok(r.into_inner().workers)
    }

    /// The worker gets no new jobs.
    pub fn drain(&mut self, worker: &str) -> Result<pb::Worker> {
        let req = self.authorized(pb::DrainWorkerRequest { worker_id: worker.into() })?;
        let r = self.rt.block_on(self.inner.drain_worker(req)).map_err(Refused)?;
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
            .map_err(Refused)?
            .into_inner();
        Ok(format!("{:?}", tonic_health::pb::health_check_response::ServingStatus::try_from(r.status).unwrap_or_default()).to_uppercase())
    }
}

/// How [`Client::watch_from`] follows a job.
#[derive(Debug, Clone, Copy)]
pub struct WatchOptions {
    /// Only events after this sequence number (0: from the first).
    pub after_sequence: u64,
    /// How long to keep reconnecting after the stream broke and no event came.
    pub reconnect_for: Duration,
}

impl Default for WatchOptions {
    fn default() -> Self {
        WatchOptions { after_sequence: 0, reconnect_for: Duration::from_secs(60) }
    }
}

/// Whether a failed watch is worth reconnecting (the server or the connection went away),
/// as opposed to a refusal that retrying does not change.
fn retryable(s: &tonic::Status) -> bool {
    use tonic::Code::*;
    !matches!(s.code(), NotFound | InvalidArgument | OutOfRange | Unauthenticated | PermissionDenied | FailedPrecondition | Unimplemented)
}

/// `path` as sent by a server, if it is a plain relative path (no root, `..` or `.`), which
/// cannot lead out of the directory it is joined to.
pub fn safe_relative(path: &str) -> Result<PathBuf> {
    let p = Path::new(path);
    let ok = !path.is_empty() && !path.contains('\0') && p.components().all(|c| matches!(c, std::path::Component::Normal(_)));
    anyhow::ensure!(ok, "the orchestrator sent the file name {path:?}, which is not a plain relative path; refusing to write it");
    Ok(p.to_path_buf())
}

/// Writes the chunks of FetchRun under a directory: each file into a temporary file next to
/// its place, checked against its size and SHA-256 (read back after fsync), then renamed into
/// place; names that would leave the directory are refused.
pub struct RunWriter {
    root: PathBuf,
    current: Option<Partial>,
    seen: std::collections::HashSet<String>,
    files: usize,
    bytes: u64,
}

struct Partial {
    path: String,
    tmp: PathBuf,
    dest: PathBuf,
    file: std::fs::File,
    hasher: Sha256,
    written: u64,
}

impl RunWriter {
    pub fn new(out: &Path) -> Result<Self> {
        std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
        let root = out.canonicalize().with_context(|| format!("cannot resolve {}", out.display()))?;
        Ok(RunWriter { root, current: None, seen: Default::default(), files: 0, bytes: 0 })
    }

    /// Takes the next chunk.
    pub fn chunk(&mut self, c: &pb::FetchRunChunk) -> Result<()> {
        use std::io::Write;
        if let Some(p) = &self.current {
            anyhow::ensure!(p.path == c.path, "the orchestrator sent {} before the end of {}", c.path, p.path);
        } else {
            self.current = Some(self.open(&c.path)?);
        }
        let Some(p) = self.current.as_mut() else { unreachable!("opened above") };
        anyhow::ensure!(c.offset == p.written, "{}: a chunk at byte {} after {} bytes", c.path, c.offset, p.written);
        p.file.write_all(&c.data).with_context(|| format!("cannot write {}", p.tmp.display()))?;
        p.hasher.update(&c.data);
        p.written += c.data.len() as u64;
        if c.last {
            let p = self.current.take().unwrap_or_else(|| unreachable!("set above"));
            let (files, bytes) = (&mut self.files, &mut self.bytes);
            let result = (|| {
                anyhow::ensure!(c.size == p.written, "{}: {} bytes arrived, the orchestrator sent {}", c.path, p.written, c.size);
                let sent = hex::encode(p.hasher.clone().finalize());
                anyhow::ensure!(sent == c.sha256, "{} arrived damaged: SHA-256 {sent}, sent as {}", c.path, c.sha256);
                p.file.sync_all().with_context(|| format!("cannot write {}", p.tmp.display()))?;
                let on_disk =
                    hex::encode(Sha256::digest(std::fs::read(&p.tmp).with_context(|| format!("cannot read back {}", p.tmp.display()))?));
                anyhow::ensure!(on_disk == c.sha256, "{} reads back with SHA-256 {on_disk}, not {}", p.tmp.display(), c.sha256);
                crate::atomic::commit(&p.tmp, &p.dest)
            })();
            if result.is_err() {
                let _ = std::fs::remove_file(&p.tmp);
            }
            result?;
            *files += 1;
            *bytes += p.written;
        }
        Ok(())
    }

    fn open(&mut self, path: &str) -> Result<Partial> {
        use std::os::unix::fs::OpenOptionsExt;
        let rel = safe_relative(path)?;
        anyhow::ensure!(self.seen.insert(path.to_string()), "the orchestrator sent {path} twice");
        let dest = self.root.join(&rel);
        let (Some(dir), Some(name)) = (dest.parent(), dest.file_name()) else { bail!("{path} names no file") };
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        // A directory on the way that is a link must not lead out of the destination.
        let real = dir.canonicalize().with_context(|| format!("cannot resolve {}", dir.display()))?;
        anyhow::ensure!(
            real.starts_with(&self.root),
            "{path} would be written to {}, outside {}; refusing",
            real.display(),
            self.root.display()
        );
        let tmp = real.join(format!(".{}.fetch-{}", name.to_string_lossy(), std::process::id()));
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        Ok(Partial { path: path.to_string(), tmp, dest: real.join(name), file, hasher: Sha256::new(), written: 0 })
    }

    /// Checks that no file was left unfinished; returns the number of files and of bytes.
    pub fn finish(mut self) -> Result<(usize, u64)> {
        if let Some(p) = self.current.take() {
            let _ = std::fs::remove_file(&p.tmp);
            bail!("the fetch ended in the middle of {} ({} bytes arrived)", p.path, p.written);
        }
        Ok((self.files, self.bytes))
    }
}

impl Drop for RunWriter {
    fn drop(&mut self) {
        if let Some(p) = self.current.take() {
            let _ = std::fs::remove_file(&p.tmp);
        }
    }
}

/// A job state's name (`queued`, ...; the job store's), `unknown` for none.
pub fn state_name(state: i32) -> &'static str {
    pb::JobState::try_from(state).ok().and_then(|s| JobState::try_from(s).ok()).map_or("unknown", JobState::as_str)
}

pub fn is_final(ev: &pb::JobEvent) -> bool {
    matches!(pb::JobState::try_from(ev.state), Ok(pb::JobState::Completed | pb::JobState::Failed | pb::JobState::Cancelled))
}

// ---- the verbs, as `mscale` runs them (each returns its exit code) ----

static CA_FILE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
static CLIENT_IDENTITY: std::sync::OnceLock<(PathBuf, PathBuf)> = std::sync::OnceLock::new();

/// Makes the client verbs present this PEM client certificate and key over TLS (mutual TLS,
/// `mscale serve --tls-client-ca`; `--client-cert`/`--client-key`).
pub fn use_client_identity(cert: PathBuf, key: PathBuf) {
    let _ = CLIENT_IDENTITY.set((cert, key));
}

/// Makes the client verbs connect over TLS, trusting this PEM certificate authority
/// (`--ca-file` or `MSCALE_CA_FILE`).
pub fn use_ca_file(path: PathBuf) {
    let _ = CA_FILE.set(path);
}

fn ca_file() -> Option<PathBuf> {
    CA_FILE.get().cloned()
}

/// Where a job runs: on how many workers, over how many MPI ranks.
#[derive(Debug, Clone, Copy)]
pub struct Placement {
    /// Workers (0: every one free when it starts).
    pub workers: u32,
    /// MPI ranks of its continuum (1: in the orchestrator's process).
    pub ranks: u32,
}

impl Default for Placement {
    fn default() -> Self {
        Placement { workers: 0, ranks: 1 }
    }
}

/// `mscale submit`.
pub fn submit(server: &str, token_file: Option<&Path>, scene: &Path, sets: &[String], priority: i32, checkpoint_every: u64) -> Result<i32> {
    submit_for(server, token_file, scene, sets, priority, checkpoint_every, Placement::default())
}

/// `mscale submit --workers N --ranks R`.
pub fn submit_for(
    server: &str,
    token_file: Option<&Path>,
    scene: &Path,
    sets: &[String],
    priority: i32,
    checkpoint_every: u64,
    how: Placement,
) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    println!("{}", c.submit_for(scene, sets, priority, checkpoint_every, how)?);
    Ok(crate::exit::OK)
}

fn line(j: &pb::Job) -> String {
    let digest = if j.state_digest.is_empty() { String::new() } else { format!("  digest {}", j.state_digest) };
    let error = if j.error.is_empty() { String::new() } else { format!("  ({})", j.error) };
    format!(
        "{}  {:<9} {:<20} step {}  t = {:.4e} s  priority {}{}{}{}{digest}{error}",
        j.id,
        state_name(j.state),
        j.scene,
        step_of(j.step, j.steps),
        j.sim_time_s,
        j.priority,
        if j.resumes > 0 { format!("  resumed {}x", j.resumes) } else { String::new() },
        if j.owner.is_empty() { String::new() } else { format!("  owner {}", j.owner) },
        if j.ranks > 1 { format!("  {} MPI ranks", j.ranks) } else { String::new() }
    )
}

/// A worker state's name (`live`, `draining`, `lost`), `unknown` for none.
pub fn worker_state_name(state: i32) -> &'static str {
    pb::WorkerState::try_from(state).ok().and_then(|s| WorkerState::try_from(s).ok()).map_or("unknown", WorkerState::as_str)
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

/// `mscale watch JOB`: a progress bar on a terminal, a line per second otherwise; with
/// `events`, also every event as a line on stdout (`event SEQ KIND STATE step S/N MESSAGE`).
/// Reconnects for up to `reconnect_for` when the stream breaks.
pub fn watch(server: &str, token_file: Option<&Path>, job: &str, events: bool, reconnect_for: Duration) -> Result<i32> {
    use std::io::IsTerminal;
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let bar = std::io::stderr().is_terminal().then(|| {
        let b = indicatif::ProgressBar::new(1);
        b.set_style(
            indicatif::ProgressStyle::with_template("{spinner} {bar:40} step {pos}/{len}  {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    });
    let mut last_line = std::time::Instant::now() - std::time::Duration::from_secs(2);
    let opts = WatchOptions { after_sequence: 0, reconnect_for };
    let last = c.watch_from(job, opts, |ev| {
        if events {
            println!("{}", event_line(ev));
        }
        if ev.kind == pb::JobEventKind::NotRetained as i32 {
            eprintln!("mscale: {}", ev.message);
            return;
        }
        let eta = if ev.eta_s >= 0.0 { format!("ETA {:.0} s", ev.eta_s) } else { "ETA -".into() };
        let msg = format!(
            "{}  t = {:.4e} s  {:.1} %  energy drift {:.2e}  {eta}",
            state_name(ev.state),
            ev.sim_time_s,
            ev.percent,
            ev.energy_drift
        );
        match &bar {
            Some(b) => {
                if ev.steps > 0 {
                    b.set_length(ev.steps);
                    b.set_position(ev.step);
                } else {
                    // Steps not known in advance: per mille of the simulated time.
                    b.set_length(1000);
                    b.set_position((10.0 * ev.percent) as u64);
                }
                b.set_message(msg);
            }
            None if last_line.elapsed().as_secs_f64() >= 1.0 || is_final(ev) => {
                last_line = std::time::Instant::now();
                eprintln!("job {}: step {}  {msg}", ev.job_id, step_of(ev.step, ev.steps));
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

/// One event as `mscale watch --events` prints it.
pub fn event_line(ev: &pb::JobEvent) -> String {
    let kind = pb::JobEventKind::try_from(ev.kind)
        .map(|k| k.as_str_name().trim_start_matches("JOB_EVENT_KIND_").to_lowercase())
        .unwrap_or_else(|_| ev.kind.to_string());
    if ev.kind == pb::JobEventKind::NotRetained as i32 {
        return format!("event {}..{} {kind}  {}", ev.not_retained_from, ev.sequence, ev.message);
    }
    let msg = if ev.message.is_empty() { String::new() } else { format!("  {}", ev.message) };
    format!("event {} {kind} {} step {}{msg}", ev.sequence, state_name(ev.state), step_of(ev.step, ev.steps))
}

/// `step/steps`, or `step` alone where the steps are not known in advance (0: a cell run's
/// adaptive steps).
fn step_of(step: u64, steps: u64) -> String {
    if steps > 0 { format!("{step}/{steps}") } else { step.to_string() }
}

/// `mscale cancel JOB`.
pub fn cancel(server: &str, token_file: Option<&Path>, job: &str) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let j = c.cancel(job)?;
    println!("{}", line(&j));
    Ok(crate::exit::OK)
}

/// `mscale fetch JOB FILE --out PATH`, or without FILE the whole run directory into the
/// directory `--out DIR`.
pub fn fetch(server: &str, token_file: Option<&Path>, job: &str, file: Option<&str>, out: &Path) -> Result<i32> {
    let mut c = Client::connect_with(server, token(token_file)?, ca_file().as_deref())?;
    let Some(file) = file else {
        let (files, bytes) = c.fetch_run(job, out)?;
        println!("{files} files, {bytes} bytes into {}", out.display());
        return Ok(crate::exit::OK);
    };
    let bytes = c.fetch(job, file)?;
    crate::atomic::write(out, &bytes)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(path: &str, offset: u64, data: &[u8], last: bool) -> pb::FetchRunChunk {
        let sha256 = if last { hex::encode(Sha256::digest(data)) } else { String::new() };
        pb::FetchRunChunk {
            path: path.into(),
            offset,
            data: data.to_vec(),
            last,
            size: if last { offset + data.len() as u64 } else { 0 },
            sha256,
        }
    }

    #[test]
    fn fetched_files_stay_inside_the_destination() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        for bad in ["../escape", "/tmp/escape", "a/../../escape", "", "./x", "a/.."] {
            let mut w = RunWriter::new(&out).unwrap();
            let e = w.chunk(&chunk(bad, 0, b"x", true)).unwrap_err();
            assert!(format!("{e:#}").contains("not a plain relative path"), "{bad}: {e:#}");
        }
        assert!(!dir.path().join("escape").exists());
        // A directory inside DIR that is a link out of it is not written through.
        std::fs::create_dir_all(dir.path().join("elsewhere")).unwrap();
        std::os::unix::fs::symlink(dir.path().join("elsewhere"), out.join("link")).unwrap();
        let mut w = RunWriter::new(&out).unwrap();
        let e = w.chunk(&chunk("link/f", 0, b"x", true)).unwrap_err();
        assert!(format!("{e:#}").contains("outside"), "{e:#}");
        assert!(!dir.path().join("elsewhere/f").exists());
    }

    #[test]
    fn fetched_files_are_checked_and_written_whole() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = RunWriter::new(dir.path()).unwrap();
        let data: Vec<u8> = (0..2500u32).map(|k| (k % 251) as u8).collect();
        let mut c = chunk("snapshots/a.csv", 0, &data[..1000], false);
        w.chunk(&c).unwrap();
        c = chunk("snapshots/a.csv", 1000, &data[1000..], true);
        c.size = 2500;
        c.sha256 = hex::encode(Sha256::digest(&data));
        w.chunk(&c).unwrap();
        w.chunk(&chunk("empty", 0, b"", true)).unwrap();
        // A damaged file: refused, nothing left behind.
        let mut bad = chunk("summary.json", 0, b"{}", true);
        bad.sha256 = hex::encode(Sha256::digest(b"{ }"));
        assert!(format!("{:#}", w.chunk(&bad).unwrap_err()).contains("arrived damaged"));
        assert_eq!(w.finish().unwrap(), (2, 2500));
        assert_eq!(std::fs::read(dir.path().join("snapshots/a.csv")).unwrap(), data);
        assert!(!dir.path().join("summary.json").exists());
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .filter(|n| n.to_string_lossy().starts_with('.'))
            .collect();
        assert!(left.is_empty(), "temporary files left: {left:?}");
        // A stream cut in the middle of a file is an error, and leaves no partial file.
        let mut w = RunWriter::new(dir.path()).unwrap();
        w.chunk(&chunk("cut", 0, b"abc", false)).unwrap();
        assert!(w.finish().is_err());
        assert!(!dir.path().join("cut").exists());
    }
}
