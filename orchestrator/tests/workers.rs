//! The worker pool of `mscale serve` across real processes on 127.0.0.1: `md-worker serve
//! --orchestrator` processes (started by the test, or by `mscale serve --local-workers`)
//! register and heartbeat; a job's boxes are spread over them and it ends with the digest of
//! `mscale run` in one process, also when a worker is killed with SIGKILL mid-job or frozen
//! with SIGSTOP (past the step deadline, or past the heartbeat timeout): only the lost worker's
//! boxes are restored from the last checkpoint onto the survivor and their logged inputs
//! replayed; with no survivor the job fails naming the worker and the step. Another protocol version and a missing token are refused; a silent
//! worker is declared lost and comes back as a new worker; a drained worker takes no sessions.
//!
//! The md-worker program is the prebuilt one next to `mscale` (mscale_testkit::prebuilt: `cargo
//! test --workspace` builds it; alone, `cargo build --profile test -p md-worker --bin md-worker`).

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::{Listening, Proc, plain, text};
use orchestrator::client::Client;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

const MD_SMALL: &str = "../tests/data/md-small.toml";
const TOKEN: &str = "test-token-0123456789";
/// 16 points, 150 steps of md-small: long enough to kill a worker mid-job.
const LONGER: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=1.5e-12"];

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

/// The prebuilt md-worker program next to `mscale` (where `--local-workers` looks).
fn md_worker() -> PathBuf {
    let path = mscale_testkit::prebuilt("md-worker", "md-worker");
    assert_eq!(path.parent(), Path::new(bin()).parent(), "md-worker must lie next to mscale for --local-workers");
    path
}

struct Server {
    proc: Proc,
    addr: String,
}

impl Server {
    fn start(state: &Path, token_file: &Path, log: &Path, extra: &[&str]) -> Server {
        let mut cmd = Command::new(bin());
        cmd.args(["serve", "--state", state.to_str().unwrap(), "--listen", "127.0.0.1:0", "--token-file", token_file.to_str().unwrap()])
            .args(extra)
            .env("RUST_LOG", "info");
        let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(log));
        Server { proc, addr }
    }

    fn client(&self, token: bool) -> Client {
        Client::connect(&self.addr, token.then(|| TOKEN.to_string())).unwrap()
    }

    fn cli(&self, args: &[&str]) -> Output {
        Command::new(bin()).args(args).args(["--server", &self.addr]).env_remove("MSCALE_TOKEN").env("RUST_LOG", "warn").output().unwrap()
    }

    /// Waits until `n` workers are live; returns them.
    fn wait_live(&self, n: usize) -> Vec<pb::Worker> {
        let start = Instant::now();
        loop {
            let live: Vec<pb::Worker> =
                self.client(false).workers().unwrap().into_iter().filter(|w| w.state == pb::WorkerState::Live as i32).collect();
            if live.len() >= n {
                return live;
            }
            assert!(start.elapsed() < Duration::from_secs(120), "{} of {n} workers live after 120 s:\n{}", live.len(), self.proc.log());
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Submits md-small with overrides; returns the job id.
    fn submit(&self, token: &Path, sets: &[&str], checkpoint_every: u64) -> String {
        let every = checkpoint_every.to_string();
        let mut args = vec!["submit", MD_SMALL, "--token-file", token.to_str().unwrap(), "--checkpoint-every", &every];
        for s in sets {
            args.extend(["--set", s]);
        }
        let o = self.cli(&args);
        assert!(o.status.success(), "{}", text(&o));
        String::from_utf8_lossy(&o.stdout).trim().to_string()
    }
}

/// Starts `md-worker serve` joining `server` (1 thread, heartbeats every `heartbeat` s).
fn worker(server: &Server, token: &Path, log: &Path, heartbeat: &str) -> Proc {
    let mut cmd = Command::new(md_worker());
    cmd.args(["serve", "--listen", "127.0.0.1:0", "--device", "cpu", "--threads", "1", "--heartbeat-every", heartbeat])
        .args(["--orchestrator", &format!("http://{}", server.addr), "--token-file", token.to_str().unwrap()])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null());
    Proc::spawn_logged(&mut cmd, log)
}

fn setup() -> (tempfile::TempDir, PathBuf) {
    mscale_testkit::token_dir(TOKEN)
}

/// The digest `mscale run` gives in one process.
fn run_digest(dir: &Path, sets: &[&str]) -> String {
    let mut args = vec!["run", MD_SMALL, "--out", dir.to_str().unwrap()];
    for s in sets {
        args.extend(["--set", s]);
    }
    let o = Command::new(bin()).args(&args).env("RUST_LOG", "warn").output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    mscale_testkit::state_digest(dir)
}

/// Follows a job to its end; returns every event.
fn watch(server: &Server, job: &str) -> Vec<pb::JobEvent> {
    let mut events = Vec::new();
    server.client(false).watch(job, |ev| events.push(ev.clone())).unwrap_or_else(|e| panic!("watch {job}: {e:#}\n{}", server.proc.log()));
    events
}

fn wait_for_checkpoint(state: &Path, job: &str) {
    let dir = state.join("jobs").join(job).join("run/checkpoints");
    let done =
        || std::fs::read_dir(&dir).map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".ckpt")).count()).unwrap_or(0);
    mscale_testkit::wait_until(&format!("a checkpoint of job {job}"), Duration::from_secs(120), || done() > 0);
}

fn answers(addr: &str) -> bool {
    std::net::TcpStream::connect_timeout(&addr.parse().unwrap(), Duration::from_millis(500)).is_ok()
}

#[test]
fn local_workers_take_a_job_spread_by_throughput_and_die_with_the_orchestrator() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let mut server = Server::start(&state, &token, &tmp.path().join("serve.log"), &["--local-workers", "2"]);
    let workers = server.wait_live(2);
    for w in &workers {
        assert!(w.atom_steps_per_s > 0.0 && w.throughput_source.starts_with("measured"), "{w:?}");
        assert_eq!(
            (w.backend.as_str(), w.precision.as_str(), w.protocol_version),
            ("cpu", "double", mscale_proto::COUPLING_PROTOCOL_VERSION)
        );
    }
    let job = server.submit(&token, &[], 0);
    let events = watch(&server, &job);
    let last = events.last().unwrap();
    assert_eq!(last.state, pb::JobState::Completed as i32, "{last:?}\n{}", server.proc.log());
    let j = server.client(false).get(&job).unwrap();
    assert_eq!(j.state_digest, run_digest(&tmp.path().join("straight"), &[]), "{}", server.proc.log());

    // The watch events said where the boxes were: all 6 points, spread over both workers in
    // proportion to the advertised throughput (largest remainder of 6 * t_k / sum t).
    let seen = events.iter().rev().find(|e| e.workers.len() == 2).unwrap_or_else(|| panic!("no event with the workers: {events:?}"));
    let boxes: Vec<u32> = seen.workers.iter().map(|w| w.boxes).collect();
    assert_eq!(boxes.iter().sum::<u32>(), 6, "{seen:?}");
    let weights: Vec<f64> = seen.workers.iter().map(|w| w.advertised_atom_steps_per_s).collect();
    let expected: Vec<u32> = md_worker::pool::proportional_blocks(6, &weights).into_iter().map(|b| b as u32).collect();
    assert_eq!(boxes, expected, "{seen:?}");
    assert!(
        seen.workers.iter().all(|w| w.state == pb::WorkerState::Live as i32 && (w.boxes == 0 || w.measured_atom_steps_per_s > 0.0)),
        "{seen:?}"
    );

    // SIGKILL of the orchestrator takes its local workers along (PR_SET_PDEATHSIG).
    server.proc.child.kill().unwrap();
    server.proc.child.wait().unwrap();
    let start = Instant::now();
    while workers.iter().any(|w| answers(&w.address)) {
        assert!(start.elapsed() < Duration::from_secs(10), "local workers outlived the orchestrator: {workers:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_worker_killed_mid_job_is_replaced_from_the_checkpoint_and_without_survivors_the_job_fails() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"), &[]);
    let a = worker(&server, &token, &tmp.path().join("a.log"), "1");
    let b = worker(&server, &token, &tmp.path().join("b.log"), "1");
    server.wait_live(2);

    let job = server.submit(&token, &LONGER, 10);
    wait_for_checkpoint(&state, &job);
    a.signal("-KILL");
    let events = watch(&server, &job);
    let last = events.last().unwrap();
    assert_eq!(last.state, pb::JobState::Completed as i32, "{last:?}\n{}", server.proc.log());
    let log = server.proc.log();
    let j = server.client(false).get(&job).unwrap();
    assert_eq!(j.state_digest, run_digest(&tmp.path().join("straight"), &LONGER), "{log}");
    let workers = server.client(false).workers().unwrap();
    let states: Vec<(String, i32)> = workers.iter().map(|w| (w.id.clone(), w.state)).collect();
    assert_eq!(states.iter().filter(|s| s.1 == pb::WorkerState::Lost as i32).count(), 1, "{states:?}");
    let lost = workers.iter().find(|w| w.state == pb::WorkerState::Lost as i32).unwrap();
    assert!(lost.note.contains("stopped answering during step"), "{lost:?}");
    // Only the killed worker's boxes were restored and replayed; the job was neither rolled
    // back nor resumed.
    assert!(!log.contains("rolling back") && !log.contains("resuming"), "{log}");
    let n = only_the_lost_boxes_were_replayed(&state, &job, &lost.address, &b);
    assert!(log.contains(&format!("its {n} boxes were restored from the checkpoint of step")), "{log}");
    // The last event shows every box on the survivor, none on the lost worker.
    let on = |addr: &str| last.workers.iter().find(|w| w.address == addr).unwrap_or_else(|| panic!("{last:?}"));
    assert_eq!((on(&lost.address).boxes, on(&lost.address).state), (0, pb::WorkerState::Lost as i32), "{last:?}");
    assert_eq!(last.workers.iter().map(|w| w.boxes).sum::<u32>(), 16, "{last:?}");

    // Now kill the survivor mid-job: nobody can take its boxes, the job fails naming it.
    let survivor = states.iter().find(|s| s.1 == pb::WorkerState::Live as i32).unwrap().0.clone();
    let job = server.submit(&token, &LONGER, 10);
    wait_for_checkpoint(&state, &job);
    b.signal("-KILL");
    let last = watch(&server, &job).pop().unwrap();
    assert_eq!(last.state, pb::JobState::Failed as i32, "{last:?}");
    let j = server.client(false).get(&job).unwrap();
    assert!(
        j.error.contains(&format!("worker {survivor} at"))
            && j.error.contains("was lost at step")
            && j.error.contains("no live worker of back end cpu/double"),
        "{}",
        j.error
    );
}

#[test]
fn under_md_reuse_a_worker_killed_mid_job_is_replayed_to_the_same_digest() {
    // The left body (0 K, alike boxes) shares its computation exactly, the right one (50 K)
    // skips boxes within a tolerance; `exact` alone gives the digest of `off`.
    let reuse: Vec<&str> = LONGER
        .iter()
        .copied()
        .chain(["bodies.left.material.reuse=\"exact\"", "bodies.right.material.reuse={ tolerance = 0.05, max_interval = 4 }"])
        .collect();
    let (tmp, token) = setup();
    let exact: Vec<&str> =
        LONGER.iter().copied().chain(["bodies.left.material.reuse=\"exact\"", "bodies.right.material.reuse=\"exact\""]).collect();
    assert_eq!(run_digest(&tmp.path().join("exact"), &exact), run_digest(&tmp.path().join("off"), &LONGER), "exact reuse changed the run");
    let straight = run_digest(&tmp.path().join("straight"), &reuse);
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(tmp.path().join("straight/summary.json")).unwrap()).unwrap();
    let md = &summary["md"];
    assert!(md["bodies"]["right"]["avoided_by_tolerance"].as_f64().unwrap() > 0.0, "{md}");

    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"), &[]);
    let a = worker(&server, &token, &tmp.path().join("a.log"), "1");
    let _b = worker(&server, &token, &tmp.path().join("b.log"), "1");
    server.wait_live(2);
    let job = server.submit(&token, &reuse, 10);
    wait_for_checkpoint(&state, &job);
    a.signal("-KILL");
    let last = watch(&server, &job).pop().unwrap();
    let log = server.proc.log();
    assert_eq!(last.state, pb::JobState::Completed as i32, "{last:?}\n{log}");
    assert_eq!(server.client(false).get(&job).unwrap().state_digest, straight, "{log}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join("jobs").join(&job).join("run/summary.json")).unwrap()).unwrap();
    assert_eq!(summary["md_recovery"]["lost_workers"], 1, "{}", summary["md_recovery"]);
    assert!(!log.contains("rolling back") && !log.contains("resuming"), "{log}");
}

/// Checks the job's summary.json: one lost worker (at `lost_addr`), whose boxes (fewer than
/// all 16) alone were restored, on `survivor` (its log shows one restore, of exactly those),
/// and replayed from the checkpoint up to the step of the loss. Returns how many boxes.
fn only_the_lost_boxes_were_replayed(state: &Path, job: &str, lost_addr: &str, survivor: &Proc) -> usize {
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join("jobs").join(job).join("run/summary.json")).unwrap()).unwrap();
    let rec = &summary["md_recovery"];
    assert_eq!(rec["lost_workers"], 1, "{rec}");
    let ev = &rec["events"][0];
    assert_eq!(ev["worker"], lost_addr, "{rec}");
    let n = ev["boxes"].as_array().unwrap().len();
    assert!(n > 0 && n < 16 && rec["restored_boxes"] == n, "{rec}");
    // Each box is sent once per continuum step: from the checkpoint to the step of the loss.
    let step = ev["step"].as_u64().unwrap();
    let from: u64 = ev["baseline"].as_str().unwrap().strip_prefix("the checkpoint of step ").unwrap().parse().unwrap();
    let box_steps = ev["replayed_box_steps"].as_u64().unwrap();
    assert!(step > from && (n as u64 * (step - 1 - from)..=n as u64 * (step - from)).contains(&box_steps), "{rec}");
    assert_eq!(ev["replayed_md_steps"].as_u64().unwrap(), 10 * box_steps, "{rec}");
    let restores: Vec<String> = plain(&survivor.log()).lines().filter(|l| l.contains("restored boxes")).map(String::from).collect();
    assert_eq!(restores.len(), 1, "{restores:?}");
    assert!(restores[0].contains(&format!("boxes={n}")), "{restores:?}");
    n
}

#[test]
fn a_frozen_worker_is_lost_past_the_step_deadline_or_the_heartbeat_timeout_and_only_its_boxes_are_replayed() {
    let (tmp, token) = setup();
    let straight = run_digest(&tmp.path().join("straight"), &LONGER);
    // The step deadline (3 s) comes long before the heartbeat timeout (60 s), then the
    // heartbeat timeout (2 s) long before the automatic step deadline (at least 60 s).
    for (name, flags, why) in [
        ("deadline", ["--step-deadline", "3", "--worker-timeout", "60"], "within its deadline of 3.0 s"),
        ("heartbeat", ["--step-deadline", "auto", "--worker-timeout", "2"], "no heartbeat for"),
    ] {
        let state = tmp.path().join(name);
        let server = Server::start(&state, &token, &tmp.path().join(format!("{name}-serve.log")), &flags);
        let a = worker(&server, &token, &tmp.path().join(format!("{name}-a.log")), "0.5");
        let b = worker(&server, &token, &tmp.path().join(format!("{name}-b.log")), "0.5");
        server.wait_live(2);
        let job = server.submit(&token, &LONGER, 10);
        wait_for_checkpoint(&state, &job);
        a.signal("-STOP");
        let events = watch(&server, &job);
        a.signal("-CONT");
        let last = events.last().unwrap();
        let log = server.proc.log();
        assert_eq!(last.state, pb::JobState::Completed as i32, "{name}: {last:?}\n{log}");
        assert_eq!(server.client(false).get(&job).unwrap().state_digest, straight, "{name}: {log}");
        let workers = server.client(false).workers().unwrap();
        let lost: Vec<&pb::Worker> = workers.iter().filter(|w| w.state == pb::WorkerState::Lost as i32).collect();
        assert_eq!(lost.len(), 1, "{name}: {workers:?}");
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(state.join("jobs").join(&job).join("run/summary.json")).unwrap()).unwrap();
        assert!(summary["md_recovery"]["events"][0]["why"].as_str().unwrap().contains(why), "{name}: {}", summary["md_recovery"]);
        assert!(!log.contains("rolling back") && !log.contains("resuming"), "{name}: {log}");
        only_the_lost_boxes_were_replayed(&state, &job, &lost[0].address, &b);
        assert!(!a.log().contains("restored boxes"), "{name}: {}", a.log());
    }
}

#[test]
fn registration_needs_the_token_and_the_same_protocol_version() {
    let (tmp, token) = setup();
    let server = Server::start(&tmp.path().join("state"), &token, &tmp.path().join("serve.log"), &[]);
    let ours = mscale_proto::COUPLING_PROTOCOL_VERSION;
    let req = |version: u32| pb::RegisterWorkerRequest {
        address: "127.0.0.1:9".into(),
        device: "test".into(),
        backend: "cpu".into(),
        precision: "double".into(),
        cores: 1,
        memory_bytes: 1 << 30,
        atom_steps_per_s: 1e6,
        throughput_source: "configured".into(),
        protocol_version: version,
    };
    let e = server.client(false).register_worker(req(ours)).unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e:?}");
    assert!(e.message().contains("RegisterWorker needs a bearer token"), "{e:?}");
    let e = server.client(true).register_worker(req(ours + 1)).unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e:?}");
    assert!(
        e.message().contains(&format!("version {}", ours + 1)) && e.message().contains(&format!("version {ours}")),
        "both versions named: {e:?}"
    );
    let ok = server.client(true).register_worker(req(ours)).unwrap();
    let hb = |version: u32| pb::HeartbeatRequest { worker_id: ok.worker_id.clone(), epoch: ok.epoch, protocol_version: version };
    assert_eq!(server.client(false).heartbeat(hb(ours)).unwrap_err().code(), tonic::Code::Unauthenticated);
    assert_eq!(server.client(true).heartbeat(hb(ours + 1)).unwrap_err().code(), tonic::Code::FailedPrecondition);
    assert!(!server.client(true).heartbeat(hb(ours)).unwrap().drain);
    let o = server.cli(&["drain", &ok.worker_id]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("needs a bearer token"), "{}", text(&o));
    assert!(server.client(true).heartbeat(hb(ours)).is_ok());
    // A real worker with another token is refused and exits.
    let wrong = tmp.path().join("wrong");
    std::fs::write(&wrong, "not-the-token").unwrap();
    let o = Command::new(md_worker())
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--device",
            "cpu",
            "--threads",
            "1",
            "--throughput",
            "1e6",
            "--orchestrator",
            &format!("http://{}", server.addr),
            "--token-file",
            wrong.to_str().unwrap(),
        ])
        .stdout(Stdio::null())
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("the orchestrator refused this worker"), "{}", text(&o));
}

#[test]
fn a_silent_worker_is_lost_and_rejoins_as_a_new_worker_and_a_drained_one_takes_no_sessions() {
    let (tmp, token) = setup();
    let server = Server::start(&tmp.path().join("state"), &token, &tmp.path().join("serve.log"), &["--worker-timeout", "1.5"]);
    let w = worker(&server, &token, &tmp.path().join("w.log"), "0.2");
    let first = server.wait_live(1).remove(0);

    // Stopped (SIGSTOP): no heartbeats, declared lost after the timeout.
    w.signal("-STOP");
    let start = Instant::now();
    loop {
        let ws = server.client(false).workers().unwrap();
        if ws.iter().any(|x| x.id == first.id && x.state == pb::WorkerState::Lost as i32) {
            assert!(ws.iter().find(|x| x.id == first.id).unwrap().note.contains("no heartbeat for"), "{ws:?}");
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "not declared lost: {ws:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
    // Resumed: told it is lost, it registers again under a new identity.
    w.signal("-CONT");
    let again = server.wait_live(1).remove(0);
    assert!(again.epoch > first.epoch && again.id != first.id && again.address == first.address, "{first:?} {again:?}");
    assert!(w.log().contains("registering again"), "{}", w.log());

    // Drained: it says so at its next heartbeat and refuses new sessions; jobs run without it.
    let o = server.cli(&["drain", &again.id, "--token-file", token.to_str().unwrap()]);
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("draining"), "{}", text(&o));
    let start = Instant::now();
    while !w.log().contains("draining: no new sessions") {
        assert!(start.elapsed() < Duration::from_secs(30), "{}", w.log());
        std::thread::sleep(Duration::from_millis(50));
    }
    let rt = std::sync::Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap());
    let mut remote = md_worker::pool::Remote::connect(&again.address, rt).unwrap();
    let pot = md_worker::pool::PotentialSource::from_file(Path::new("../md-worker/potentials/Cu_u3.eam")).unwrap();
    let spec = md_worker::BoxSpec::lattice(0, md_worker::LatticeKind::Fcc, 3.615, [2, 2, 2]);
    let e = md_worker::pool::Endpoint::open(&mut remote, &pot, &[spec]).unwrap_err();
    assert!(e.to_string().contains("draining"), "{e}");
    let job = server.submit(&token, &[], 0);
    assert_eq!(watch(&server, &job).last().unwrap().state, pb::JobState::Completed as i32);
    assert!(server.proc.log().contains(&format!("job {job}: no live workers")), "{}", server.proc.log());
}
