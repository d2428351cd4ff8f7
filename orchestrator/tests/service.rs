//! The job service across real processes on 127.0.0.1: `mscale serve` and the client verbs
//! (`submit`, `watch`, `status`, `cancel`, `fetch`, `health`). A submitted job ends with the
//! `state_digest` of `mscale run`, also when the orchestrator is killed with SIGKILL mid-job
//! and restarted; unauthenticated and invalid submits are refused. Every watch gets the job's
//! events numbered 1, 2, 3, ... with no gap up to the final one, also across a restart of the
//! orchestrator (`mscale watch` reconnects); `mscale fetch JOB --out DIR` copies the whole run
//! directory and nothing outside it.

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_testkit::{Listening, Proc, text};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

const SMALL: &str = "../tests/data/small.toml";
const MD_SMALL: &str = "../tests/data/md-small.toml";
const TOKEN: &str = "test-token-0123456789";

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

struct Server {
    proc: Proc,
    addr: String,
}

impl Server {
    fn start(state: &Path, token_file: &Path, log: &Path) -> Server {
        Self::start_on(state, token_file, log, "127.0.0.1:0")
    }

    fn start_on(state: &Path, token_file: &Path, log: &Path, listen: &str) -> Server {
        let mut cmd = Command::new(bin());
        cmd.args([
            "serve",
            "--state",
            state.to_str().unwrap(),
            "--listen",
            listen,
            "--token-file",
            token_file.to_str().unwrap(),
            "--checkpoint-every",
            "100",
        ])
        .env("RUST_LOG", "info");
        let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(log));
        Server { proc, addr }
    }

    fn log(&self) -> String {
        self.proc.log()
    }

    /// Runs a client verb against this server.
    fn client(&self, args: &[&str]) -> Output {
        Command::new(bin()).args(args).args(["--server", &self.addr]).env_remove("MSCALE_TOKEN").env("RUST_LOG", "warn").output().unwrap()
    }
}

fn setup() -> (tempfile::TempDir, PathBuf) {
    mscale_testkit::token_dir(TOKEN)
}

/// The digest `mscale run` gives for a scene with overrides.
fn run_digest(dir: &Path, scene: &str, sets: &[&str]) -> String {
    let mut args = vec!["run", scene, "--out", dir.to_str().unwrap()];
    for s in sets {
        args.extend(["--set", s]);
    }
    let o = Command::new(bin()).args(&args).env("RUST_LOG", "warn").output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    mscale_testkit::state_digest(dir)
}

fn submit(server: &Server, token: &Path, scene: &str, sets: &[&str]) -> String {
    let mut args = vec!["submit", scene, "--token-file", token.to_str().unwrap()];
    for s in sets {
        args.extend(["--set", s]);
    }
    let o = server.client(&args);
    assert!(o.status.success(), "{}", text(&o));
    String::from_utf8_lossy(&o.stdout).trim().to_string()
}

/// Watches a job to its end through `mscale watch --events`; returns the exit code and the
/// status line, after checking that the events came numbered 1, 2, 3, ... to the final one
/// without a reconnection.
fn watch(server: &Server, job: &str) -> (i32, String) {
    let o = server.client(&["watch", job, "--events"]);
    assert!(!String::from_utf8_lossy(&o.stderr).contains("reconnecting"), "{}", text(&o));
    let (events, line) = contiguous_events(&o);
    assert!(!events.is_empty());
    (o.status.code().unwrap_or(-1), line)
}

/// One line of `mscale watch --events`: (sequence, kind, state, message).
type Event = (u64, String, String, String);

/// The events `mscale watch --events` printed, checked to be numbered 1, 2, 3, ... with no gap
/// (no event reported as not retained) and to end with the job's final state; and the status
/// line printed after them.
fn contiguous_events(o: &Output) -> (Vec<Event>, String) {
    let stdout = String::from_utf8_lossy(&o.stdout);
    let mut events = Vec::new();
    for l in stdout.lines().filter(|l| l.starts_with("event ")) {
        let f: Vec<&str> = l.splitn(7, ' ').collect();
        let seq = f[1]
            .parse::<u64>()
            .unwrap_or_else(|_| panic!("event line {l:?} has no plain sequence number (events not retained?): {}", text(o)));
        events.push((seq, f[2].to_string(), f[3].to_string(), f.get(6).map(|m| m.trim().to_string()).unwrap_or_default()));
    }
    let seqs: Vec<u64> = events.iter().map(|e| e.0).collect();
    assert_eq!(seqs, (1..=seqs.len() as u64).collect::<Vec<_>>(), "events not numbered 1..n without gaps: {}", text(o));
    let last = events.last().unwrap_or_else(|| panic!("no events: {}", text(o)));
    assert!(
        ["completed", "failed", "cancelled"].contains(&last.2.as_str()) && last.1 == "state",
        "the last event is not a final state: {last:?}"
    );
    assert_eq!((events[0].1.as_str(), events[0].2.as_str(), events[0].3.as_str()), ("state", "queued", "submitted"), "{}", text(o));
    let status = stdout.lines().rfind(|l| !l.starts_with("event ")).unwrap_or_default().to_string();
    (events, status)
}

/// Every regular file under `dir`, relative, with its content.
fn files_under(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let t = e.file_type().unwrap();
            if t.is_dir() {
                stack.push(e.path());
            } else if t.is_file() {
                out.insert(e.path().strip_prefix(dir).unwrap().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap());
            }
        }
    }
    out
}

fn digest_of(status_line: &str) -> String {
    status_line
        .split("digest ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .unwrap_or_else(|| panic!("no digest in {status_line:?}"))
        .to_string()
}

#[test]
fn submitted_jobs_end_with_the_digest_of_mscale_run() {
    let (tmp, token) = setup();
    let server = Server::start(&tmp.path().join("state"), &token, &tmp.path().join("serve.log"));
    let h = server.client(&["health"]);
    assert!(h.status.success() && String::from_utf8_lossy(&h.stdout).contains("SERVING"), "{}", text(&h));

    for (scene, sets) in [(SMALL, vec!["scheme.cfl=0.1"]), (MD_SMALL, vec![])] {
        let job = submit(&server, &token, scene, &sets);
        let (code, line) = watch(&server, &job);
        assert_eq!(code, 0, "{line}\n{}", server.log());
        assert!(line.contains("completed"), "{line}");
        let expected = run_digest(&tmp.path().join(format!("run-{job}")), scene, &sets);
        assert_eq!(digest_of(&line), expected, "job {job} of {scene}");

        // The summary comes back through FetchResult, checked against its SHA-256.
        let out = tmp.path().join(format!("{job}.json"));
        let f = server.client(&["fetch", &job, "summary.json", "--out", out.to_str().unwrap()]);
        assert!(f.status.success(), "{}", text(&f));
        let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
        assert_eq!(s["state_digest"].as_str().unwrap(), expected);
        for bad in ["../input/scene.toml", "/etc/passwd"] {
            let f = server.client(&["fetch", &job, bad, "--out", tmp.path().join("x").to_str().unwrap()]);
            assert!(!f.status.success() && String::from_utf8_lossy(&f.stderr).contains("not a path inside"), "{bad}: {}", text(&f));
        }

        // The whole run directory: every file, byte for byte; a link planted in it that leads
        // out of the job's directory is not followed.
        let run = tmp.path().join("state/jobs").join(&job).join("run");
        std::os::unix::fs::symlink("../input/scene.toml", run.join("escape.toml")).unwrap();
        std::os::unix::fs::symlink("/etc", run.join("etc")).unwrap();
        let dir = tmp.path().join(format!("{job}-run"));
        let f = server.client(&["fetch", &job, "--out", dir.to_str().unwrap()]);
        assert!(f.status.success(), "{}", text(&f));
        let (sent, got) = (files_under(&run), files_under(&dir));
        assert!(sent.contains_key("summary.json") && sent.contains_key("snapshots/index.csv") && sent.len() > 3, "{:?}", sent.keys());
        assert_eq!(sent.keys().collect::<Vec<_>>(), got.keys().collect::<Vec<_>>());
        assert!(sent == got, "fetched files differ from the run directory's");
        assert!(!dir.join("escape.toml").exists() && !dir.join("etc").exists(), "a link out of the run directory was followed");
        assert!(String::from_utf8_lossy(&f.stdout).contains(&format!("{} files", sent.len())), "{}", text(&f));
    }

    // Watching again from a sequence number gets the events after it, the same ones; beyond
    // the newest is refused.
    let job =
        String::from_utf8_lossy(&server.client(&["status"]).stdout).lines().next().unwrap().split_whitespace().next().unwrap().to_string();
    let mut c = orchestrator::client::Client::connect(&server.addr, None).unwrap();
    let mut all = Vec::new();
    let last = c.watch(&job, |e| all.push(e.clone())).unwrap();
    assert_eq!(last.sequence, all.len() as u64);
    let mut tail = Vec::new();
    let opts = orchestrator::client::WatchOptions { after_sequence: 3, reconnect_for: Duration::from_secs(5) };
    c.watch_from(&job, opts, |e| tail.push(e.clone())).unwrap();
    assert_eq!(tail, all[3..]);
    let opts = orchestrator::client::WatchOptions { after_sequence: last.sequence + 1, ..opts };
    let e = c.watch_from(&job, opts, |_| {}).unwrap_err();
    assert!(format!("{e:#}").contains("is beyond them") && format!("{e:#}").contains("OutOfRange"), "{e:#}");
    let st = server.client(&["status"]);
    assert_eq!(String::from_utf8_lossy(&st.stdout).matches("completed").count(), 2, "{}", text(&st));
}

#[test]
fn a_cell_scene_runs_as_a_job_with_the_digest_of_mscale_run() {
    // A cell scene (kind = "cell") goes through the same submit, watch and fetch as an MPM
    // scene; it needs no worker. Stopped orchestrators resume it from its restart points.
    let (tmp, token) = setup();
    let server = Server::start(&tmp.path().join("state"), &token, &tmp.path().join("serve.log"));
    let (scene, sets) = ("../scenes/pnp-full-cell.toml", ["grid.cells=200"]);
    let job = submit(&server, &token, scene, &sets);
    let (code, line) = watch(&server, &job);
    assert_eq!(code, 0, "{line}\n{}", server.log());
    assert!(line.contains("completed"), "{line}");
    let expected = run_digest(&tmp.path().join("cell-run"), scene, &sets);
    assert_eq!(digest_of(&line), expected, "{line}");
    let out = tmp.path().join("cell.json");
    let f = server.client(&["fetch", &job, "summary.json", "--out", out.to_str().unwrap()]);
    assert!(f.status.success(), "{}", text(&f));
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!((s["kind"].as_str(), s["state_digest"].as_str()), (Some("cell"), Some(expected.as_str())));
}

#[test]
fn unauthenticated_and_invalid_submits_are_refused() {
    let (tmp, token) = setup();
    let server = Server::start(&tmp.path().join("state"), &token, &tmp.path().join("serve.log"));
    let o = server.client(&["submit", SMALL]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("needs a bearer token"), "{}", text(&o));
    let wrong = tmp.path().join("wrong");
    std::fs::write(&wrong, "test-token-0123456780").unwrap();
    let o = server.client(&["submit", SMALL, "--token-file", wrong.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("Unauthenticated"), "{}", text(&o));
    let o = server.client(&["cancel", "jnope"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("needs a bearer token"), "{}", text(&o));

    // A bad scene: refused at submit with the message `mscale check` prints.
    let bad = tmp.path().join("bad.toml");
    let scene = std::fs::read_to_string(SMALL).unwrap().replace("particles_per_cell = 4", "particles_per_cell = 0");
    std::fs::write(&bad, scene).unwrap();
    let check = Command::new(bin()).args(["check", bad.to_str().unwrap()]).output().unwrap();
    let expected = String::from_utf8_lossy(&check.stderr).trim().trim_start_matches("mscale: ").to_string();
    assert!(!check.status.success() && expected.contains("particles_per_cell"), "{expected}");
    let o = server.client(&["submit", bad.to_str().unwrap(), "--token-file", token.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains(&expected), "expected {expected:?} in {}", text(&o));
    // A bad override too.
    let o = server.client(&["submit", SMALL, "--set", "scheme.cfl=-1", "--token-file", token.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("scheme.cfl"), "{}", text(&o));
    // MPI ranks from an orchestrator that cannot start them (no --mpi-mscale), and 0 ranks.
    let o = server.client(&["submit", SMALL, "--ranks", "2", "--token-file", token.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("asks for 2 MPI ranks") && String::from_utf8_lossy(&o.stderr).contains("--mpi-mscale"),
        "{}",
        text(&o)
    );
    let o = server.client(&["submit", SMALL, "--ranks", "0", "--token-file", token.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));

    let st = server.client(&["status"]);
    assert!(String::from_utf8_lossy(&st.stdout).contains("no jobs"), "refused submits left jobs: {}", text(&st));
}

/// 1000 steps of 8000 points, a checkpoint every 100: a few seconds.
const LONG: [&str; 1] = ["domain.cells=[2000]"];

fn wait_for_checkpoint(state: &Path, job: &str) {
    let dir = state.join("jobs").join(job).join("run/checkpoints");
    let start = Instant::now();
    // Only finished checkpoints count, not the temporary file of one being written.
    let done =
        || std::fs::read_dir(&dir).map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".ckpt")).count()).unwrap_or(0);
    while done() == 0 {
        assert!(start.elapsed() < Duration::from_secs(120), "no checkpoint of job {job} after 120 s");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn a_job_survives_the_orchestrator_killed_mid_run() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let mut server = Server::start(&state, &token, &tmp.path().join("serve1.log"));
    let job = submit(&server, &token, SMALL, &LONG);
    wait_for_checkpoint(&state, &job);
    server.proc.child.kill().unwrap(); // SIGKILL
    server.proc.child.wait().unwrap();
    assert!(!state.join("jobs").join(&job).join("run/summary.json").exists(), "the job ended before the kill; make it longer");

    let server = Server::start(&state, &token, &tmp.path().join("serve2.log"));
    let o = server.client(&["watch", &job, "--events"]);
    let (events, line) = contiguous_events(&o);
    assert_eq!(o.status.code(), Some(0), "{line}\n{}", server.log());
    assert!(line.contains("resumed 1x"), "{line}");
    // Every state change and checkpoint before the kill is there, then the restart.
    let states: Vec<(&str, &str)> = events.iter().filter(|e| e.1 == "state").map(|e| (e.2.as_str(), e.3.as_str())).collect();
    assert_eq!(
        states[..3],
        [("queued", "submitted"), ("running", "started"), ("queued", "the orchestrator restarted; resumes from its last checkpoint")],
        "{states:?}"
    );
    assert_eq!(states[3..], [("running", "resumed"), ("completed", "")], "{states:?}");
    assert!(events.iter().any(|e| e.1 == "checkpoint"), "no checkpoint event: {events:?}");
    assert!(server.log().contains("resuming small at step"), "the job did not resume from a checkpoint:\n{}", server.log());
    assert_eq!(digest_of(&line), run_digest(&tmp.path().join("straight"), SMALL, &LONG));
}

#[test]
fn a_cancelled_job_ends_cancelled_and_watch_says_so() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"));
    let job = submit(&server, &token, SMALL, &LONG);
    wait_for_checkpoint(&state, &job);
    let o = server.client(&["cancel", &job, "--token-file", token.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = server.client(&["watch", &job, "--events"]);
    let (events, line) = contiguous_events(&o);
    assert_eq!(o.status.code(), Some(1), "{line}");
    assert!(line.contains("cancelled") && line.contains("cancelled by a user after step"), "{line}");
    let n = events.len();
    assert!(events[n - 2].1 == "checkpoint" && events[n - 2].3.contains("as the job is cancelled"), "{:?}", &events[n - 2..]);
}

#[test]
fn a_hundred_concurrent_status_calls_are_answered_while_a_job_runs() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"));
    let job = submit(&server, &token, SMALL, &LONG);
    wait_for_checkpoint(&state, &job);
    let threads: Vec<_> = (0..100)
        .map(|_| {
            let (addr, job) = (server.addr.clone(), job.clone());
            std::thread::spawn(move || {
                let mut c = orchestrator::client::Client::connect(&addr, None).expect("connect");
                let t = Instant::now();
                let j = c.get(&job).expect("GetJob");
                (t.elapsed(), j.state)
            })
        })
        .collect();
    let mut latencies: Vec<Duration> = threads.into_iter().map(|t| t.join().expect("a status call failed")).map(|(d, _)| d).collect();
    latencies.sort();
    assert_eq!(latencies.len(), 100);
    let p99 = latencies[98];
    eprintln!("100 concurrent GetJob calls during a run: median {:?}, p99 {:?}, max {:?}", latencies[49], p99, latencies[99]);
    // Answered while the job computes (it runs off the gRPC runtime): generous bound for a
    // loaded 2-core machine.
    assert!(p99 < Duration::from_secs(5), "p99 {p99:?}");
    let (code, _) = watch(&server, &job);
    assert_eq!(code, 0);
}

/// `mscale watch JOB --events` in the background, once it has received its first event.
struct Watcher {
    child: Child,
    out: BufReader<std::process::ChildStdout>,
    first: String,
}

impl Watcher {
    fn start(server: &Server, job: &str, extra: &[&str]) -> Watcher {
        let mut child = Command::new(bin())
            .args(["watch", job, "--events", "--server", &server.addr])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut out = BufReader::new(child.stdout.take().unwrap());
        let mut first = String::new();
        out.read_line(&mut first).unwrap();
        assert!(first.starts_with("event 1 "), "the watcher's first line: {first:?}");
        Watcher { child, out, first }
    }

    /// Waits for it to exit; all it printed.
    fn finish(mut self) -> Output {
        use std::io::Read;
        let mut rest = String::new();
        self.out.read_to_string(&mut rest).unwrap();
        let o = self.child.wait_with_output().unwrap();
        Output { status: o.status, stdout: format!("{}{rest}", self.first).into_bytes(), stderr: o.stderr }
    }
}

#[test]
fn sigterm_stops_the_orchestrator_with_a_checkpoint_and_the_job_resumes() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let mut server = Server::start(&state, &token, &tmp.path().join("serve1.log"));
    let job = submit(&server, &token, SMALL, &LONG);
    wait_for_checkpoint(&state, &job);
    // A watcher must not hold the shutdown up; it reconnects to the orchestrator started again
    // at the same address and follows the job to its end, missing nothing. One that may wait
    // only 0.3 s gives up.
    let watcher = Watcher::start(&server, &job, &[]);
    let quitter = Watcher::start(&server, &job, &["--reconnect-for", "0.3"]);
    server.proc.signal("-TERM");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = server.proc.child.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "mscale serve did not stop within 30 s of SIGTERM:\n{}", server.log());
        std::thread::sleep(Duration::from_millis(20));
    };
    let quit = quitter.finish();
    assert_eq!(quit.status.code(), Some(1), "{}", text(&quit));
    assert!(String::from_utf8_lossy(&quit.stderr).contains("could not resume it within"), "{}", text(&quit));
    assert!(status.success(), "{}", server.log());
    assert!(!state.join("jobs").join(&job).join("run/summary.json").exists(), "the job ended before SIGTERM; make it longer");
    assert!(server.log().contains("as the orchestrator stops"), "{}", server.log());

    let addr = server.addr.clone();
    drop(server);
    let server = Server::start_on(&state, &token, &tmp.path().join("serve2.log"), &addr);
    let watch_out = watcher.finish();
    let (events, line) = contiguous_events(&watch_out);
    assert_eq!(watch_out.status.code(), Some(0), "{}\n{}", text(&watch_out), server.log());
    assert!(String::from_utf8_lossy(&watch_out.stderr).contains("reconnecting"), "{}", text(&watch_out));
    assert!(events.iter().any(|e| e.3 == "the orchestrator stopped; resumes from its last checkpoint"), "{events:?}");
    assert!(server.log().contains("resuming small at step"), "{}", server.log());
    assert_eq!(digest_of(&line), run_digest(&tmp.path().join("straight"), SMALL, &LONG));
}

#[test]
fn a_non_loopback_listen_address_is_refused_without_tls() {
    let (tmp, token) = setup();
    let o = Command::new(bin())
        .args([
            "serve",
            "--state",
            tmp.path().join("state").to_str().unwrap(),
            "--listen",
            "0.0.0.0:0",
            "--token-file",
            token.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("refusing to listen on 0.0.0.0:0 without TLS"), "{}", text(&o));
}

#[test]
fn tls_serves_clients_that_trust_its_authority() {
    let (tmp, token) = setup();
    let (ca, cert, key) = mscale_testkit::tls_certificates(tmp.path());
    let log = tmp.path().join("serve.log");
    let mut cmd = Command::new(bin());
    cmd.args([
        "serve",
        "--state",
        tmp.path().join("state").to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--token-file",
        token.to_str().unwrap(),
    ])
    .args(["--tls-cert", cert.to_str().unwrap(), "--tls-key", key.to_str().unwrap()]);
    let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(&log));
    let server = Server { proc, addr };
    let with_ca = |args: &[&str]| server.client(&[args, &["--ca-file", ca.to_str().unwrap()]].concat());
    let h = with_ca(&["health"]);
    assert!(h.status.success() && String::from_utf8_lossy(&h.stdout).contains("SERVING"), "{}", text(&h));
    let job = String::from_utf8_lossy(&with_ca(&["submit", SMALL, "--token-file", token.to_str().unwrap()]).stdout).trim().to_string();
    let w = with_ca(&["watch", &job]);
    assert_eq!(w.status.code(), Some(0), "{}", text(&w));
    // Without the authority (plain HTTP/2, or TLS trusting nothing) the server is not reached.
    let plain = server.client(&["health"]);
    assert!(!plain.status.success(), "a plain client talked to the TLS server: {}", text(&plain));
    let other_ca = tmp.path().join("other");
    std::fs::create_dir_all(&other_ca).unwrap();
    let (other, _, _) = mscale_testkit::tls_certificates(&other_ca);
    let wrong = server.client(&["health", "--ca-file", other.to_str().unwrap()]);
    assert!(!wrong.status.success(), "a client trusting another authority connected: {}", text(&wrong));
}
