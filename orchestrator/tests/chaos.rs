//! The chaos benchmark (issue 21) across real processes on 127.0.0.1: one `mscale serve
//! --users` and W `md-worker serve --device null` workers (the null back end: no MD, zero
//! stress, its boxes' lengths checkpointed and restored like any back end's), J small MD jobs
//! (md-small with its size, length, an impact velocity, the workers it asks for and its
//! priority drawn from a seeded stream) submitted at once by three users, each followed by a
//! raw WatchJob stream of its owner.
//!
//! First the jobs run undisturbed (a fresh orchestrator and pool): their digests and the wall
//! time are the reference. Then the same jobs run on another fresh orchestrator and pool under
//! a fixed schedule (seeded, in fractions of the undisturbed wall time): workers killed with
//! SIGKILL (a new worker process joins in place of each), workers frozen with SIGSTOP for 0.5
//! to 5 s (past `--worker-timeout 3` some of them are declared lost, rejoin under a new id when
//! resumed), and one SIGKILL of the orchestrator, started again on the same store at the same
//! address.
//!
//! Checks: every job completes with its undisturbed digest; every watcher received its job's
//! events numbered 1, 2, ..., n with no gap, no repeat and none reported not retained, ending
//! with `completed` (it reconnects only when the stream breaks, with `after_sequence` = the
//! last number it received, and never repairs a gap); the store passes `PRAGMA
//! integrity_check`; the orchestrator's peak resident memory stays under 1 GiB. Prints one
//! JSON line: jobs per hour of both runs, the recovery overhead (chaos wall time over
//! undisturbed), the peak RSS, the disturbances made.
//!
//! `cargo test -p orchestrator --test chaos` runs the reduced variant (12 workers, 15 jobs);
//! the full one (64 workers, 100 jobs) is ignored by default:
//! `cargo build --profile test -p md-worker --bin md-worker && cargo test -p orchestrator
//! --test chaos -- --ignored --nocapture chaos_full` (figures in docs/chaos-benchmark.md).
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::Listening;
use orchestrator::client::{Client, Placement};
use serde_json::json;
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant};

const MD_SMALL: &str = "../tests/data/md-small.toml";
const USERS: [(&str, &str); 3] =
    [("alice", "alice-chaos-token-0123456789"), ("bob", "bob-chaos-token-0123456789"), ("carol", "carol-chaos-token-0123456789")];
const ROOT: &str = "root-chaos-token-0123456789";
const POOL: &str = "pool-chaos-token-0123456789";
/// Resident memory the orchestrator must stay under.
const RSS_BOUND_KB: u64 = 1 << 20;

/// A small deterministic stream (splitmix64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[derive(Clone, Copy)]
struct Params {
    workers: usize,
    jobs: usize,
    seed: u64,
    /// Workers killed, and frozen, during the chaos run.
    kills: usize,
    stops: usize,
    /// At most this many workers a job asks for.
    max_workers_per_job: u64,
    /// Minutes either run may take.
    limit_min: u64,
}

#[derive(Clone)]
struct JobSpec {
    sets: Vec<String>,
    workers: u32,
    priority: i32,
    user: usize,
}

fn job_specs(p: &Params) -> Vec<JobSpec> {
    let mut rng = Rng(p.seed);
    (0..p.jobs)
        .map(|k| {
            let cells = 6 + rng.below(11);
            let steps = 60 + rng.below(241);
            let v = 20 + rng.below(80);
            JobSpec {
                sets: vec![
                    format!("domain.cells=[{cells}]"),
                    format!("scheme.end_time={:e}", steps as f64 * 1e-14),
                    format!("bodies.right.velocity=[-{v}.0]"),
                ],
                workers: 1 + rng.below(p.max_workers_per_job) as u32,
                priority: rng.below(3) as i32,
                user: k % 3,
            }
        })
        .collect()
}

fn hex(token: &str) -> String {
    Sha256::digest(token.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
}

fn users_file(dir: &Path) -> PathBuf {
    let entry = |name: &str, role: &str, token: &str| {
        format!("[[user]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken_sha256 = \"{}\"\n", hex(token))
    };
    let mut text = entry("root", "admin", ROOT) + &entry("pool", "worker", POOL);
    for (name, token) in USERS {
        text += &entry(name, "user", token);
    }
    let f = dir.join("users.toml");
    std::fs::write(&f, text).unwrap();
    f
}

fn start_server(state: &Path, users: &Path, log: &Path, listen: &str) -> Listening {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mscale"));
    cmd.args(["serve", "--state", state.to_str().unwrap(), "--listen", listen, "--users", users.to_str().unwrap()])
        .args(["--worker-timeout", "3", "--step-deadline", "5"])
        .env("RUST_LOG", "info");
    Listening::start(&mut cmd, "mscale serve: listening on ", Some(log))
}

/// `md-worker serve --device null` joining the orchestrator at `addr`; its listening address.
fn start_worker(addr: &str, token: &Path, log: &Path) -> Listening {
    let mut cmd = Command::new(mscale_testkit::prebuilt("md-worker", "md-worker"));
    cmd.args(["serve", "--listen", "127.0.0.1:0", "--device", "null", "--throughput", "1e9", "--heartbeat-every", "0.5"])
        .args(["--orchestrator", &format!("http://{addr}"), "--token-file", token.to_str().unwrap()])
        .env("RUST_LOG", "warn");
    Listening::start(&mut cmd, "listening on ", Some(log))
}

fn admin(addr: &str) -> Client {
    Client::connect(addr, Some(ROOT.to_string())).unwrap()
}

fn live_workers(addr: &str) -> Vec<pb::Worker> {
    Client::connect(addr, Some(ROOT.to_string()))
        .and_then(|mut c| c.workers())
        .map(|w| w.into_iter().filter(|w| w.state == pb::WorkerState::Live as i32).collect())
        .unwrap_or_default()
}

/// What one watcher received.
#[derive(Default, Debug)]
struct Seen {
    sequences: Vec<u64>,
    not_retained: usize,
    reconnects: usize,
    last_state: i32,
    /// Worker events that told of a lost worker; whether the job went back to the queue
    /// after running (the orchestrator's restart).
    losses: usize,
    requeued: bool,
    error: Option<String>,
}

/// Follows `job` on raw WatchJob streams from event 1 until its final event; reconnects only
/// when the stream breaks, asking for the events after the last one received, and keeps what
/// came as it came (no repair), for up to `limit`.
async fn follow(addr: String, token: &'static str, job: String, limit: Duration) -> Seen {
    let mut seen = Seen::default();
    let start = Instant::now();
    loop {
        if start.elapsed() > limit {
            seen.error = Some(format!("no final event within {limit:?}"));
            return seen;
        }
        let after = seen.sequences.last().copied().unwrap_or(0);
        let attempt = async {
            let mut c = pb::orchestrator_client::OrchestratorClient::connect(format!("http://{addr}")).await.map_err(|e| e.to_string())?;
            let mut req = tonic::Request::new(pb::WatchJobRequest { job_id: job.clone(), after_sequence: after });
            req.metadata_mut().insert("authorization", format!("Bearer {token}").parse().unwrap());
            let mut stream = c.watch_job(req).await.map_err(|s| s.to_string())?.into_inner();
            while let Some(ev) = stream.message().await.map_err(|s| s.to_string())? {
                if ev.kind == pb::JobEventKind::NotRetained as i32 {
                    seen.not_retained += 1;
                    continue;
                }
                seen.sequences.push(ev.sequence);
                if ev.kind == pb::JobEventKind::Workers as i32 && ev.message.contains("was lost") {
                    seen.losses += 1;
                }
                if ev.state == pb::JobState::Queued as i32 && seen.last_state == pb::JobState::Running as i32 {
                    seen.requeued = true;
                }
                seen.last_state = ev.state;
                if orchestrator::client::is_final(&ev) {
                    return Ok(true);
                }
            }
            Ok::<bool, String>(false)
        };
        match attempt.await {
            Ok(true) => return seen,
            Ok(false) | Err(_) => {
                seen.reconnects += 1;
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

/// The orchestrator's resident memory now and at its peak (kB), from /proc.
fn rss_kb(pid: u32) -> Option<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field =
        |name: &str| status.lines().find(|l| l.starts_with(name)).and_then(|l| l.split_whitespace().nth(1)).and_then(|v| v.parse().ok());
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

/// A thread recording the peak resident memory of the process whose pid is in `pid`.
struct RssWatch {
    stop: Arc<AtomicBool>,
    peak: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl RssWatch {
    fn start(pid: Arc<AtomicU32>) -> RssWatch {
        let (stop, peak) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
        let (s, p) = (stop.clone(), peak.clone());
        let thread = std::thread::spawn(move || {
            while !s.load(Ordering::SeqCst) {
                if let Some((_, hwm)) = rss_kb(pid.load(Ordering::SeqCst)) {
                    p.fetch_max(hwm, Ordering::SeqCst);
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        RssWatch { stop, peak, thread: Some(thread) }
    }
    fn finish(mut self) -> u64 {
        self.stop.store(true, Ordering::SeqCst);
        self.thread.take().unwrap().join().unwrap();
        self.peak.load(Ordering::SeqCst)
    }
}

/// What one run (undisturbed or chaos) gave.
struct RunResult {
    digests: Vec<String>,
    wall_s: f64,
    peak_rss_kb: u64,
    problems: Vec<String>,
    disturbances: BTreeMap<&'static str, usize>,
    reconnects: usize,
    events: usize,
    /// Worker losses the jobs' events told of, and jobs requeued by the restart.
    losses: usize,
    requeued: usize,
    integrity: String,
}

/// One run of `specs` on a fresh orchestrator and pool in `dir`; with `chaos`, under the
/// schedule drawn from `p.seed`, its times fractions of `chaos` (the undisturbed wall time).
fn run(dir: &Path, p: &Params, specs: &[JobSpec], chaos: Option<f64>) -> RunResult {
    std::fs::create_dir_all(dir).unwrap();
    let users = users_file(dir);
    let state = dir.join("state");
    let pool_token = dir.join("pool-token");
    std::fs::write(&pool_token, POOL).unwrap();
    let mut server = start_server(&state, &users, &dir.join("serve-1.log"), "127.0.0.1:0");
    let addr = server.addr.clone();
    let pid = Arc::new(AtomicU32::new(server.proc.pid()));
    let rss = RssWatch::start(pid.clone());
    let mut workers: Vec<Listening> = Vec::new();
    let mut spawned = 0;
    let mut new_worker = |workers: &mut Vec<Listening>| {
        spawned += 1;
        workers.push(start_worker(&addr, &pool_token, &dir.join(format!("w{spawned}.log"))));
    };
    for _ in 0..p.workers {
        new_worker(&mut workers);
    }
    mscale_testkit::wait_until(&format!("{} live workers", p.workers), Duration::from_secs(120), || live_workers(&addr).len() >= p.workers);

    let limit = Duration::from_secs(60 * p.limit_min);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let t0 = Instant::now();
    let mut ids = Vec::new();
    let mut watchers = Vec::new();
    for s in specs {
        let (_, token) = USERS[s.user];
        let id = Client::connect(&addr, Some(token.to_string()))
            .unwrap()
            .submit_for(Path::new(MD_SMALL), &s.sets, s.priority, 5, Placement { workers: s.workers, ranks: 1 })
            .unwrap();
        watchers.push(rt.spawn(follow(addr.clone(), token, id.clone(), limit)));
        ids.push(id);
    }

    // The disturbances, in order of their time (seconds after the submissions).
    let mut disturbances: BTreeMap<&'static str, usize> = BTreeMap::new();
    if let Some(undisturbed_s) = chaos {
        let mut rng = Rng(p.seed ^ 0xc4a0_5000);
        let mut plan: Vec<(f64, &'static str)> = Vec::new();
        for _ in 0..p.kills {
            plan.push(((0.05 + 0.85 * rng.unit()) * undisturbed_s, "worker SIGKILL"));
        }
        for _ in 0..p.stops {
            plan.push(((0.05 + 0.85 * rng.unit()) * undisturbed_s, "worker SIGSTOP"));
        }
        plan.push((0.4 * undisturbed_s, "orchestrator SIGKILL"));
        plan.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Frozen workers (by index) and when they resume.
        let mut frozen: Vec<(usize, Instant)> = Vec::new();
        let all_final = |ids: &[String]| {
            Client::connect(&addr, Some(ROOT.to_string()))
                .and_then(|mut c| c.list())
                .is_ok_and(|jobs| ids.iter().all(|id| jobs.iter().any(|j| &j.id == id && j.state >= pb::JobState::Completed as i32)))
        };
        for (at, what) in plan {
            while t0.elapsed().as_secs_f64() < at {
                frozen.retain(|(k, until)| {
                    let go = Instant::now() >= *until;
                    if go {
                        workers[*k].proc.signal("-CONT");
                    }
                    !go
                });
                std::thread::sleep(Duration::from_millis(20));
            }
            if what != "orchestrator SIGKILL" && all_final(&ids) {
                continue;
            }
            // A worker holding a job if there is one (by its address in ListWorkers).
            let busy: Vec<usize> = {
                let listed = live_workers(&addr);
                (0..workers.len())
                    .filter(|k| !frozen.iter().any(|(f, _)| f == k))
                    .filter(|k| listed.iter().any(|w| w.address == workers[*k].addr && !w.job_id.is_empty()))
                    .collect()
            };
            let pick = |rng: &mut Rng| {
                if busy.is_empty() { rng.below(workers.len() as u64) as usize } else { busy[rng.below(busy.len() as u64) as usize] }
            };
            match what {
                "worker SIGKILL" => {
                    let k = pick(&mut rng);
                    if frozen.iter().any(|(f, _)| *f == k) {
                        continue;
                    }
                    workers[k].proc.signal("-KILL");
                    workers.swap_remove(k);
                    // swap_remove moved the last worker to k: renumber a frozen one.
                    let last = workers.len();
                    for (f, _) in frozen.iter_mut() {
                        if *f == last {
                            *f = k;
                        }
                    }
                    new_worker(&mut workers);
                }
                "worker SIGSTOP" => {
                    let k = pick(&mut rng);
                    if frozen.iter().any(|(f, _)| *f == k) {
                        continue;
                    }
                    workers[k].proc.signal("-STOP");
                    frozen.push((k, Instant::now() + Duration::from_secs_f64(0.5 + 4.5 * rng.unit())));
                }
                _ => {
                    server.proc.signal("-KILL");
                    server.proc.wait_exit(Duration::from_secs(10)).expect("the orchestrator dies of SIGKILL");
                    std::thread::sleep(Duration::from_millis(300));
                    server = start_server(&state, &users, &dir.join("serve-2.log"), &addr);
                    pid.store(server.proc.pid(), Ordering::SeqCst);
                }
            }
            *disturbances.entry(what).or_default() += 1;
        }
        for (k, _) in frozen {
            workers[k].proc.signal("-CONT");
        }
    }

    let seen: Vec<Seen> = watchers.into_iter().map(|w| rt.block_on(w).unwrap()).collect();
    let wall_s = t0.elapsed().as_secs_f64();
    let mut problems = Vec::new();
    let mut digests = Vec::new();
    let jobs: BTreeMap<String, pb::Job> = admin(&addr).list().unwrap().into_iter().map(|j| (j.id.clone(), j)).collect();
    for (id, s) in ids.iter().zip(&seen) {
        let job = &jobs[id];
        if job.state != pb::JobState::Completed as i32 {
            problems.push(format!("{id}: ended {} ({})", orchestrator::client::state_name(job.state), job.error));
        }
        if let Some(e) = &s.error {
            problems.push(format!("{id}: watcher: {e}; received {:?}", s.sequences));
        }
        let contiguous = s.not_retained == 0 && !s.sequences.is_empty() && s.sequences.iter().zip(1u64..).all(|(q, k)| *q == k);
        if !contiguous || s.last_state != pb::JobState::Completed as i32 {
            problems.push(format!(
                "{id}: events not 1..n ending with completed ({} not retained, {} reconnects, last state {}): {:?}",
                s.not_retained,
                s.reconnects,
                orchestrator::client::state_name(s.last_state),
                s.sequences
            ));
        }
        digests.push(job.state_digest.clone());
    }
    // Stop the orchestrator cleanly, then check its store.
    let peak_rss_kb = rss.finish();
    server.proc.signal("-TERM");
    server.proc.wait_exit(Duration::from_secs(30));
    let db = rusqlite::Connection::open(state.join("jobs.sqlite")).unwrap();
    let integrity: String = db.query_row("PRAGMA integrity_check", [], |r| r.get(0)).unwrap();
    if integrity != "ok" {
        problems.push(format!("the store's integrity check says {integrity}"));
    }
    if !problems.is_empty() {
        let log = |n: u32| std::fs::read_to_string(dir.join(format!("serve-{n}.log"))).unwrap_or_default();
        let tail = |s: String| s.lines().rev().take(60).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
        eprintln!("orchestrator log (tail):\n{}\n--- after the restart:\n{}", tail(log(1)), tail(log(2)));
    }
    RunResult {
        digests,
        wall_s,
        peak_rss_kb,
        problems,
        disturbances,
        reconnects: seen.iter().map(|s| s.reconnects).sum(),
        events: seen.iter().map(|s| s.sequences.len()).sum(),
        losses: seen.iter().map(|s| s.losses).sum(),
        requeued: seen.iter().filter(|s| s.requeued).count(),
        integrity,
    }
}

fn chaos(p: Params) {
    let tmp = tempfile::tempdir().unwrap();
    let specs = job_specs(&p);
    let calm = run(&tmp.path().join("undisturbed"), &p, &specs, None);
    assert!(calm.problems.is_empty(), "the undisturbed run: {:#?}", calm.problems);
    let wild = run(&tmp.path().join("chaos"), &p, &specs, Some(calm.wall_s));
    let mut problems = wild.problems.clone();
    for (k, (a, b)) in calm.digests.iter().zip(&wild.digests).enumerate() {
        if a != b {
            problems.push(format!("job {k} ({:?}): digest {b:?} under chaos, {a:?} undisturbed", specs[k].sets));
        }
    }
    let per_hour = |r: &RunResult| p.jobs as f64 / r.wall_s * 3600.0;
    let report = json!({
        "what": "chaos benchmark: null-back-end md-worker processes, small MD jobs of three users, worker SIGKILL/SIGSTOP and one orchestrator SIGKILL",
        "workers": p.workers, "jobs": p.jobs, "seed": p.seed,
        "distinct_digests": calm.digests.iter().collect::<std::collections::BTreeSet<_>>().len(),
        "undisturbed_s": calm.wall_s, "chaos_s": wild.wall_s,
        "jobs_per_hour_undisturbed": per_hour(&calm), "jobs_per_hour_chaos": per_hour(&wild),
        "recovery_overhead": wild.wall_s / calm.wall_s - 1.0,
        "disturbances": wild.disturbances,
        "watch_events": wild.events, "watch_reconnects": wild.reconnects,
        "worker_losses_in_jobs": wild.losses, "jobs_requeued_by_the_restart": wild.requeued,
        "peak_rss_mib_undisturbed": calm.peak_rss_kb as f64 / 1024.0, "peak_rss_mib_chaos": wild.peak_rss_kb as f64 / 1024.0,
        "integrity_check": wild.integrity,
        "problems": problems,
    });
    println!("chaos: {report}");
    assert!(problems.is_empty(), "{report:#}");
    assert_eq!(wild.disturbances.get("orchestrator SIGKILL"), Some(&1), "{report}");
    assert!(wild.disturbances.get("worker SIGKILL").is_some_and(|n| *n > 0), "no worker was killed: {report}");
    // Not vacuous: jobs lost workers mid-run, and the restart found jobs running.
    assert!(wild.losses > 0 && wild.requeued > 0, "the chaos disturbed no job: {report}");
    assert!(calm.peak_rss_kb.max(wild.peak_rss_kb) < RSS_BOUND_KB, "peak RSS over {} MiB: {report}", RSS_BOUND_KB / 1024);
}

#[test]
fn chaos_reduced_12_workers_15_jobs() {
    chaos(Params { workers: 12, jobs: 15, seed: 21, kills: 4, stops: 3, max_workers_per_job: 3, limit_min: 3 });
}

#[test]
#[ignore = "heavy: 64 worker processes and 100 jobs, twice (about 95 s on the loaded 2-core dev machine); run with --ignored --nocapture chaos_full"]
fn chaos_full() {
    chaos(Params { workers: 64, jobs: 100, seed: 2021, kills: 24, stops: 16, max_workers_per_job: 8, limit_min: 30 });
}
