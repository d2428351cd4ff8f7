//! The HTTP side across real processes on 127.0.0.1: `mscale serve --http` (Prometheus
//! `/metrics` and the dashboard) and `md-worker serve --metrics`, scraped during a real job on
//! a joined worker and checked against what the job did (steps, atom-steps, checkpoints, calls);
//! every metric the Grafana dashboard in deploy/ plots exists in these scrapes; the dashboard's
//! pages, server-sent events (numbered as `mscale watch` gets them), stress plot and result
//! links, and its token.
//!
//! md-worker is the prebuilt program (mscale_testkit::prebuilt: `cargo build --profile test -p
//! md-worker --bin md-worker` first when running this package's tests alone).

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::{HttpResponse, Proc, http_get, prometheus_samples};
use orchestrator::client::Client;
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

const MD_SMALL: &str = "../tests/data/md-small.toml";
const TOKEN: &str = "test-token-0123456789";
/// 16 points, 150 steps of md-small (10 MD steps of 32 atoms per point and step).
const LONGER: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=1.5e-12"];
const LIMIT: Duration = Duration::from_secs(30);

/// A process whose stdout lines are read one at a time (and kept open).
struct Announcing {
    proc: Proc,
    out: BufReader<ChildStdout>,
}

impl Announcing {
    fn start(cmd: &mut Command, log: &Path) -> Announcing {
        cmd.stdout(Stdio::piped());
        let mut proc = Proc::spawn_logged(cmd, log);
        let out = BufReader::new(proc.child.stdout.take().unwrap());
        Announcing { proc, out }
    }

    /// The rest of the next line, which must start with `prefix`.
    fn line(&mut self, prefix: &str) -> String {
        let mut line = String::new();
        self.out.read_line(&mut line).unwrap();
        match line.trim().strip_prefix(prefix) {
            Some(rest) => rest.to_string(),
            None => panic!("expected {prefix:?}..., got {line:?}; log: {}", self.proc.log()),
        }
    }
}

struct Cluster {
    _tmp: tempfile::TempDir,
    state: std::path::PathBuf,
    token_file: std::path::PathBuf,
    server: Announcing,
    grpc: String,
    http: String,
    _worker: Option<Announcing>,
    worker_metrics: Option<String>,
}

impl Cluster {
    /// `mscale serve --http` and, with `worker`, one `md-worker serve --metrics` joined to it.
    fn start(worker: bool) -> Cluster {
        let (tmp, token_file) = mscale_testkit::token_dir(TOKEN);
        let state = tmp.path().join("state");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mscale"));
        cmd.args(["serve", "--state", state.to_str().unwrap(), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"])
            .args(["--token-file", token_file.to_str().unwrap(), "--checkpoint-every", "50"])
            .env("RUST_LOG", "info");
        let mut server = Announcing::start(&mut cmd, &tmp.path().join("serve.log"));
        let grpc = server.line("mscale serve: listening on ");
        let http = server.line("mscale serve: dashboard and metrics on http://");
        let (mut w, mut worker_metrics) = (None, None);
        if worker {
            let mut cmd = Command::new(mscale_testkit::prebuilt("md-worker", "md-worker"));
            cmd.args(["serve", "--listen", "127.0.0.1:0", "--threads", "1", "--metrics", "127.0.0.1:0"])
                .args(["--orchestrator", &format!("http://{grpc}"), "--token-file", token_file.to_str().unwrap()])
                .args(["--throughput", "1e7"])
                .env("RUST_LOG", "warn");
            let mut a = Announcing::start(&mut cmd, &tmp.path().join("worker.log"));
            a.line("listening on ");
            worker_metrics = Some(a.line("metrics on "));
            w = Some(a);
        }
        Cluster { _tmp: tmp, state, token_file, server, grpc, http, _worker: w, worker_metrics }
    }

    fn client(&self) -> Client {
        Client::connect(&self.grpc, Some(TOKEN.to_string())).unwrap()
    }

    fn get(&self, path: &str, headers: &[(&str, &str)]) -> HttpResponse {
        http_get(&self.http, path, headers, LIMIT).unwrap()
    }

    fn scrape(&self) -> Samples {
        let r = self.get("/metrics", &[("authorization", &format!("Bearer {TOKEN}"))]);
        assert_eq!(r.status, 200, "{}", r.text());
        assert!(r.header("content-type").unwrap().starts_with("text/plain"), "{:?}", r.headers);
        Samples(prometheus_samples(&r.text()))
    }

    fn scrape_worker(&self) -> Samples {
        let r = http_get(self.worker_metrics.as_ref().unwrap(), "/metrics", &[], LIMIT).unwrap();
        assert_eq!(r.status, 200, "{}", r.text());
        Samples(prometheus_samples(&r.text()))
    }

    fn submit(&self, sets: &[&str]) -> String {
        let o = Command::new(env!("CARGO_BIN_EXE_mscale"))
            .args(["submit", MD_SMALL, "--server", &self.grpc, "--token-file", self.token_file.to_str().unwrap()])
            .args(sets.iter().flat_map(|s| ["--set", s]))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", mscale_testkit::text(&o));
        String::from_utf8(o.stdout).unwrap().trim().to_string()
    }

    fn wait_live_worker(&self) {
        let start = Instant::now();
        while !self.client().workers().unwrap().iter().any(|w| w.state == pb::WorkerState::Live as i32) {
            assert!(start.elapsed() < Duration::from_secs(120), "no live worker; log: {}", self.server.proc.log());
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

struct Samples(Vec<(String, BTreeMap<String, String>, f64)>);

impl Samples {
    /// The value of the sample `name` whose labels include `labels`; panics when there is none.
    fn get(&self, name: &str, labels: &[(&str, &str)]) -> f64 {
        self.find(name, labels).unwrap_or_else(|| panic!("no sample {name}{labels:?} in the scrape: {:?}", self.names()))
    }

    fn find(&self, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
        self.0.iter().find(|(n, l, _)| n == name && labels.iter().all(|(k, v)| l.get(*k).is_some_and(|x| x == v))).map(|s| s.2)
    }

    fn names(&self) -> BTreeSet<String> {
        self.0.iter().map(|s| s.0.clone()).collect()
    }
}

/// Metric names in the PromQL expressions of deploy/grafana/*.json.
fn dashboard_metrics() -> BTreeSet<String> {
    let dir = mscale_testkit::repo().join("deploy/grafana");
    let mut names = BTreeSet::new();
    for f in std::fs::read_dir(&dir).unwrap().flatten().filter(|f| f.path().extension().is_some_and(|e| e == "json")) {
        let dash: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(f.path()).unwrap()).unwrap();
        for p in dash["panels"].as_array().unwrap() {
            for t in p["targets"].as_array().unwrap() {
                let expr = t["expr"].as_str().unwrap();
                for word in expr.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
                    if word.starts_with("mscale_") || word.starts_with("mdworker_") {
                        names.insert(word.to_string());
                    }
                }
            }
        }
    }
    assert!(names.len() > 10, "{names:?}");
    names
}

#[test]
fn metrics_follow_a_real_job_on_a_worker_and_match_what_it_did() {
    let c = Cluster::start(true);
    c.wait_live_worker();
    // Unauthenticated scrapes are refused, like every mutating gRPC call.
    assert_eq!(c.get("/metrics", &[]).status, 401);
    assert_eq!(c.get("/metrics", &[("authorization", "Bearer wrong")]).status, 401);
    let before = c.scrape();
    assert_eq!(before.get("mscale_workers", &[("state", "live")]), 1.0);
    assert_eq!(before.get("mscale_jobs", &[("state", "completed")]), 0.0);
    let id = c.submit(&LONGER);
    // Scraped while it runs.
    let start = Instant::now();
    let (mut seen_running, mut worker_mid) = (None, None);
    while seen_running.is_none() {
        assert!(start.elapsed() < Duration::from_secs(120), "never scraped the job running; log: {}", c.server.proc.log());
        let s = c.scrape();
        let step = s.find("mscale_job_step", &[("job_id", &id)]).unwrap_or(0.0);
        if s.get("mscale_jobs", &[("state", "running")]) == 1.0 && step > 0.0 && step < 150.0 {
            worker_mid = Some(c.scrape_worker().get("mdworker_step_batches_total", &[]));
            seen_running = Some((step, s.get("mscale_job_steps", &[("job_id", &id)]), s.get("mscale_queue_length", &[])));
        }
        std::thread::sleep(Duration::from_millis(30));
    }
    let (mid_step, steps, queue) = seen_running.unwrap();
    assert_eq!((steps, queue), (150.0, 0.0));
    assert!(worker_mid.unwrap() > 0.0, "the worker had computed no batch mid-job");
    let mut events = Vec::new();
    let last = c.client().watch(&id, |e| events.push(e.clone())).unwrap();
    assert_eq!(last.state, pb::JobState::Completed as i32, "{}", last.message);
    let job = c.client().get(&id).unwrap();
    let s = c.scrape();
    let w = c.scrape_worker();
    eprintln!("mid-job step {mid_step}; final scrapes:\n{:?}\n{:?}", s.names(), w.names());
    // Jobs, queue and workers as the store has them.
    assert_eq!(s.get("mscale_jobs", &[("state", "completed")]), 1.0);
    assert_eq!(s.get("mscale_jobs", &[("state", "running")]), 0.0);
    assert_eq!(s.get("mscale_queue_length", &[]), 0.0);
    assert_eq!(s.get("mscale_job_step", &[("job_id", &id)]), job.step as f64);
    assert_eq!(s.get("mscale_job_steps", &[("job_id", &id)]), job.steps as f64);
    // MD work: 16 boxes of 32 atoms, 10 MD steps each per continuum step (md-small.toml).
    let (points, atoms, md_steps) = (16.0, 32.0, 10.0);
    let box_steps = points * md_steps * job.steps as f64;
    assert_eq!(w.get("mdworker_box_steps_total", &[]), box_steps);
    assert_eq!(w.get("mdworker_atom_steps_total", &[]), box_steps * atoms);
    // At least one batch per continuum step (the scheme may also ask for stresses without MD
    // steps, e.g. at the start), each timed once.
    let batches = w.get("mdworker_step_batches_total", &[]);
    assert!(batches >= job.steps as f64, "{batches} batches for {} steps", job.steps);
    assert_eq!(w.get("mdworker_step_compute_seconds_count", &[]), batches);
    assert!(w.get("mdworker_compute_seconds_total", &[]) > 0.0);
    assert_eq!((w.get("mdworker_boxes", &[]), w.get("mdworker_atoms", &[])), (0.0, 0.0), "the job's session is closed");
    // The orchestrator's view of the same work, per job and per worker.
    let worker_id = &c.client().workers().unwrap()[0].id;
    assert_eq!(s.get("mscale_job_atom_steps_total", &[("job_id", &id)]), box_steps * atoms);
    assert_eq!(s.get("mscale_worker_atom_steps_total", &[("job_id", &id), ("worker", worker_id)]), box_steps * atoms);
    assert!(s.get("mscale_worker_atom_steps_per_second", &[("job_id", &id), ("worker", worker_id)]) > 0.0);
    assert!(s.get("mscale_job_atom_steps_per_second", &[("job_id", &id)]) > 0.0);
    // Checkpoints: as many as the job's checkpoint events; the newest one's size.
    let checkpoints = events.iter().filter(|e| e.kind == pb::JobEventKind::Checkpoint as i32).count() as f64;
    assert_eq!(checkpoints, 2.0, "steps 50 and 100 of 150");
    assert_eq!(s.get("mscale_checkpoints_total", &[("job_id", &id)]), checkpoints);
    assert_eq!(s.get("mscale_checkpoint_write_seconds_count", &[]), checkpoints);
    assert_eq!(w.get("mdworker_snapshot_seconds_count", &[]), checkpoints, "each checkpoint took the boxes from the worker");
    let newest = std::fs::read_dir(c.state.join("jobs").join(&id).join("run/checkpoints"))
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains("100"))
        .map(|e| e.metadata().unwrap().len())
        .next()
        .unwrap();
    assert_eq!(s.get("mscale_checkpoint_bytes", &[("job_id", &id)]), newest as f64);
    // No worker was lost.
    for kind in ["replay", "rollback", "move"] {
        assert_eq!(s.get("mscale_recoveries_total", &[("kind", kind)]), 0.0);
    }
    assert_eq!(w.get("mdworker_restores_total", &[]), 0.0);
    // Calls: the test's own (one submit, watch and get, the worker lists), the worker's
    // registration, at least one open on the worker.
    assert_eq!(s.get("mscale_rpc_duration_seconds_count", &[("method", "SubmitJob")]), 1.0);
    assert_eq!(s.get("mscale_rpc_duration_seconds_count", &[("method", "RegisterWorker")]), 1.0);
    assert_eq!(s.get("mscale_rpc_duration_seconds_count", &[("method", "WatchJob")]), 1.0);
    assert_eq!(s.get("mscale_rpc_duration_seconds_count", &[("method", "GetJob")]), 1.0);
    assert!(
        s.get("mscale_rpc_duration_seconds_count", &[("method", "ListWorkers")]) >= 1.0,
        "the test listed the workers before this scrape"
    );
    assert!(w.get("mdworker_rpc_duration_seconds_count", &[("method", "Open")]) >= 1.0);
    // Every metric the Grafana dashboard plots is in these scrapes.
    let scraped: BTreeSet<String> = s.names().union(&w.names()).cloned().collect();
    let missing: Vec<String> = dashboard_metrics().difference(&scraped).cloned().collect();
    assert!(missing.is_empty(), "deploy/grafana plots metrics no scrape has: {missing:?}");
}

/// The SSE body's events: (sequence, JSON data).
fn sse_events(body: &str) -> Vec<(u64, serde_json::Value)> {
    let mut out = Vec::new();
    for block in body.split("\n\n").filter(|b| b.contains("event: job")) {
        let id = block.lines().find_map(|l| l.strip_prefix("id: ")).unwrap().parse().unwrap();
        let data = block.lines().find_map(|l| l.strip_prefix("data: ")).unwrap();
        out.push((id, serde_json::from_str(data).unwrap()));
    }
    out
}

#[test]
fn the_dashboard_shows_jobs_streams_their_events_and_links_their_results() {
    let c = Cluster::start(false);
    let id = c.submit(&["scheme.end_time=1e-13"]);
    // The token: none is refused with a hint; ?token= sets the cookie the page then uses.
    let r = c.get("/", &[]);
    assert_eq!(r.status, 401);
    assert!(r.text().contains("?token="), "{}", r.text());
    let r = c.get(&format!("/?token={TOKEN}"), &[]);
    assert_eq!(r.status, 200, "{}", r.text());
    let cookie = r.header("set-cookie").unwrap().split(';').next().unwrap().to_string();
    assert_eq!(cookie, format!("mscale_token={TOKEN}"));
    assert!(r.text().contains(&format!("href=\"/jobs/{id}\"")), "{}", r.text());
    let auth = [("cookie", cookie.as_str())];
    // The events to the end, numbered as the gRPC watch numbers them.
    let r = c.get(&format!("/jobs/{id}/events"), &auth);
    assert_eq!((r.status, r.header("content-type")), (200, Some("text/event-stream")));
    let events = sse_events(&r.text());
    let mut grpc = Vec::new();
    c.client().watch(&id, |e| grpc.push(e.sequence)).unwrap();
    assert_eq!(events.iter().map(|e| e.0).collect::<Vec<_>>(), grpc);
    assert_eq!(grpc, (1..=grpc.len() as u64).collect::<Vec<_>>());
    let last = &events.last().unwrap().1;
    let job = c.client().get(&id).unwrap();
    assert_eq!((last["state"].as_str(), last["final"].as_bool()), (Some("completed"), Some(true)), "{last}");
    assert_eq!(last["step"].as_u64(), Some(job.steps));
    assert!(r.text().trim_end().ends_with("event: end\ndata: {}"), "{}", r.text());
    // A reconnecting browser (Last-Event-ID) gets only what it missed; after the end, the end.
    let r = c.get(&format!("/jobs/{id}/events"), &[auth[0], ("last-event-id", "2")]);
    assert_eq!(sse_events(&r.text()).first().map(|e| e.0), Some(3));
    let r = c.get(&format!("/jobs/{id}/events"), &[auth[0], ("last-event-id", &grpc.len().to_string())]);
    assert_eq!((sse_events(&r.text()).len(), r.text().contains("event: end")), (0, true));
    // The job page as the store has it, with links to every file of the run directory.
    let page = c.get(&format!("/jobs/{id}"), &auth).text();
    assert!(page.contains(&format!("<dd id=\"step\">{0} / {0}</dd>", job.steps)), "{page}");
    assert!(page.contains("class=\"state completed\">completed<"), "{page}");
    assert!(page.contains(&job.state_digest), "{page}");
    let run = c.state.join("jobs").join(&id).join("run");
    let files = orchestrator::service::run_files(&run.canonicalize().unwrap()).unwrap();
    assert!(page.contains(&format!("data-n=\"{}\"", files.len())), "{page}");
    for f in &files {
        assert!(page.contains(&format!("href=\"/jobs/{id}/files/{f}\"")), "no link to {f}");
    }
    let summary = c.get(&format!("/jobs/{id}/files/summary.json"), &auth);
    assert_eq!(summary.body, std::fs::read(run.join("summary.json")).unwrap());
    assert_eq!(c.get(&format!("/jobs/{id}/files/../../token"), &auth).status, 400);
    assert_eq!(c.get("/jobs/jnosuch", &auth).status, 404);
    // The stress plot: one vertex per point of the newest snapshot.
    let svg = c.get(&format!("/jobs/{id}/stress.svg"), &auth);
    assert_eq!(svg.header("content-type"), Some("image/svg+xml"));
    let points = mscale_testkit::summary(&run)["points"].as_u64().unwrap();
    assert!(svg.text().contains(&format!("data-points=\"{points}\"")), "{}", svg.text());
    assert!(svg.text().contains(&format!("at step {}", job.steps)), "{}", svg.text());
}

#[test]
fn http_off_loopback_needs_tls() {
    let (tmp, token_file) = mscale_testkit::token_dir(TOKEN);
    let o = Command::new(env!("CARGO_BIN_EXE_mscale"))
        .args(["serve", "--state", tmp.path().join("s").to_str().unwrap(), "--listen", "127.0.0.1:0", "--http", "0.0.0.0:0"])
        .args(["--token-file", token_file.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", mscale_testkit::text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--http on 0.0.0.0:0 without TLS"), "{}", mscale_testkit::text(&o));
}

#[test]
fn with_tls_the_http_port_serves_https_with_the_same_certificate() {
    let (tmp, token_file) = mscale_testkit::token_dir(TOKEN);
    let (ca, cert, key) = mscale_testkit::tls_certificates(tmp.path());
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mscale"));
    cmd.args(["serve", "--state", tmp.path().join("s").to_str().unwrap(), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"]).args([
        "--token-file",
        token_file.to_str().unwrap(),
        "--tls-cert",
        cert.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
    ]);
    let mut server = Announcing::start(&mut cmd, &tmp.path().join("serve.log"));
    server.line("mscale serve: listening on ");
    let url = server.line("mscale serve: dashboard and metrics on ");
    assert!(url.starts_with("https://127.0.0.1:"), "{url}");
    let curl =
        |args: &[&str]| Command::new("curl").args(["-sS", "--max-time", "20"]).args(args).output().expect("curl is needed for this test");
    let o = curl(&["--cacert", ca.to_str().unwrap(), "-H", &format!("Authorization: Bearer {TOKEN}"), &format!("{url}/metrics")]);
    assert!(o.status.success(), "{}", mscale_testkit::text(&o));
    let body = String::from_utf8_lossy(&o.stdout);
    assert!(body.contains("mscale_jobs{state=\"queued\"} 0"), "{body}");
    // Plain HTTP to it, or TLS trusting no authority, is not served.
    let plain = http_get(url.trim_start_matches("https://"), "/metrics", &[("authorization", &format!("Bearer {TOKEN}"))], LIMIT);
    assert!(plain.map_or(true, |r| r.status != 200), "plain HTTP was served on the TLS port");
    assert!(!curl(&[&format!("{url}/metrics")]).status.success(), "curl trusted the server without its authority");
}
