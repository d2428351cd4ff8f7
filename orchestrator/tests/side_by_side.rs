//! Jobs side by side across real processes on 127.0.0.1: `mscale serve` with `md-worker serve
//! --orchestrator` workers runs several jobs at once on disjoint sets of workers (`mscale
//! submit --workers N`), each ending with the digest of `mscale run` in one process, also when
//! a worker is killed mid-job (its job, left without workers, waits for one that another job
//! releases and resumes from its checkpoint); a high-priority job submitted while others run
//! gets the first worker a running job releases, ahead of jobs queued before it.

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::{Listening, Proc, text};
use orchestrator::client::{Client, Placement};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

const MD_SMALL: &str = "../tests/data/md-small.toml";
const TOKEN: &str = "test-token-0123456789";
/// 16 points, 150 steps of md-small.
const LONGER: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=1.5e-12"];
/// 12 points, 120 steps.
const OTHER: [&str; 2] = ["domain.cells=[12]", "scheme.end_time=1.2e-12"];
/// 6 points, 30 steps.
const SHORT: [&str; 1] = ["scheme.end_time=3e-13"];
/// 16 points, 300 steps (about a second): still running while jobs are queued behind it.
const FIRST: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=3e-12"];
/// 16 points, 30,000 steps (a minute or more): runs while the others come and go (cancelled
/// once they have started). At 3,000 steps it once ended first on a loaded machine, before the
/// urgent job was seen starting.
const LONGEST: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=3e-10"];

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

struct Server {
    proc: Proc,
    addr: String,
}

impl Server {
    fn start(state: &Path, token_file: &Path, log: &Path) -> Server {
        let mut cmd = Command::new(bin());
        cmd.args(["serve", "--state", state.to_str().unwrap(), "--listen", "127.0.0.1:0", "--token-file", token_file.to_str().unwrap()])
            .env("RUST_LOG", "info");
        let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(log));
        Server { proc, addr }
    }

    fn client(&self) -> Client {
        Client::connect(&self.addr, Some(TOKEN.to_string())).unwrap()
    }

    fn wait_live(&self, n: usize) {
        mscale_testkit::wait_until(&format!("{n} live workers"), Duration::from_secs(120), || {
            self.client().workers().unwrap().iter().filter(|w| w.state == pb::WorkerState::Live as i32).count() >= n
        });
    }

    fn submit(&self, sets: &[&str], priority: i32, workers: u32) -> String {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        self.client().submit_for(Path::new(MD_SMALL), &sets, priority, 10, Placement { workers, ranks: 1 }).unwrap()
    }

    fn job(&self, id: &str) -> pb::Job {
        self.client().get(id).unwrap()
    }

    /// Which job each live worker holds (worker id -> job id, "" for none).
    fn holders(&self) -> BTreeMap<String, String> {
        self.client().workers().unwrap().into_iter().filter(|w| w.state != pb::WorkerState::Lost as i32).map(|w| (w.id, w.job_id)).collect()
    }

    /// Follows a job to its end; returns its record.
    fn finish(&self, id: &str) -> pb::Job {
        self.client().watch(id, |_| {}).unwrap_or_else(|e| panic!("watch {id}: {e:#}\n{}", self.proc.log()));
        self.job(id)
    }
}

/// `md-worker serve` joining `server` with 1 thread, heartbeats every second.
fn worker(server: &Server, token: &Path, log: &Path) -> Proc {
    let mut cmd = Command::new(mscale_testkit::prebuilt("md-worker", "md-worker"));
    cmd.args(["serve", "--listen", "127.0.0.1:0", "--device", "cpu", "--threads", "1", "--heartbeat-every", "1"])
        .args(["--orchestrator", &format!("http://{}", server.addr), "--token-file", token.to_str().unwrap()])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null());
    Proc::spawn_logged(&mut cmd, log)
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

fn wait_for_checkpoint(state: &Path, job: &str) {
    let dir = state.join("jobs").join(job).join("run/checkpoints");
    let done =
        || std::fs::read_dir(&dir).map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".ckpt")).count()).unwrap_or(0);
    mscale_testkit::wait_until(&format!("a checkpoint of job {job}"), Duration::from_secs(180), || done() > 0);
}

fn setup() -> (tempfile::TempDir, PathBuf) {
    mscale_testkit::token_dir(TOKEN)
}

#[test]
fn three_jobs_on_four_workers_end_with_their_digests_when_a_worker_is_killed() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"));
    let workers: Vec<Proc> = (0..4).map(|k| worker(&server, &token, &tmp.path().join(format!("w{k}.log")))).collect();
    server.wait_live(4);
    let pids: BTreeMap<String, u32> = {
        // Which process is which worker: their logs say ("joined the pool of URL as wN").
        let mut m = BTreeMap::new();
        mscale_testkit::wait_until("every worker logged its id", Duration::from_secs(30), || {
            m.clear();
            for (k, p) in workers.iter().enumerate() {
                let log = mscale_testkit::plain(&std::fs::read_to_string(tmp.path().join(format!("w{k}.log"))).unwrap_or_default());
                let joined = log.split("joined the pool of ").nth(1).and_then(|r| r.split(" as ").nth(1));
                if let Some(id) = joined.and_then(|r| r.split(|c: char| !c.is_alphanumeric()).next()) {
                    m.insert(id.to_string(), p.pid());
                }
            }
            m.len() == 4
        });
        m
    };

    let j1 = server.submit(&LONGER, 0, 1);
    let j2 = server.submit(&OTHER, 0, 1);
    let j3 = server.submit(&LONGER, 0, 2);
    // All three run at once, on disjoint workers: 1, 1 and 2 of the 4. (A job holds its
    // workers a moment before its state says running: wait for both.)
    let mut held = BTreeMap::new();
    mscale_testkit::wait_until("three jobs running on 1, 1 and 2 workers", Duration::from_secs(120), || {
        held = server.holders();
        let count = |j: &str| held.values().filter(|h| h.as_str() == j).count();
        (count(&j1), count(&j2), count(&j3)) == (1, 1, 2)
            && [&j1, &j2, &j3].iter().all(|j| server.job(j).state == pb::JobState::Running as i32)
    });
    for j in [&j1, &j2, &j3] {
        assert_eq!(server.job(j).state, pb::JobState::Running as i32, "{held:?}\n{}", server.proc.log());
    }
    // Kill j1's only worker after j1's first checkpoint.
    wait_for_checkpoint(&state, &j1);
    let victim = held.iter().find(|(_, j)| **j == j1).map(|(w, _)| w.clone()).unwrap();
    let k = workers.iter().position(|p| p.pid() == pids[&victim]).unwrap();
    workers[k].signal("-KILL");

    let (a, b, c) = (server.finish(&j1), server.finish(&j2), server.finish(&j3));
    let log = server.proc.log();
    for j in [&a, &b, &c] {
        assert_eq!(j.state, pb::JobState::Completed as i32, "{j:?}\n{log}");
    }
    let longer = run_digest(&tmp.path().join("longer"), &LONGER);
    assert_eq!((a.state_digest.as_str(), c.state_digest.as_str()), (longer.as_str(), longer.as_str()), "{log}");
    assert_eq!(b.state_digest, run_digest(&tmp.path().join("other"), &OTHER), "{log}");
    // j1 lost its only worker, waited for one the others released and rolled back onto it.
    let mut notes = Vec::new();
    server.client().watch(&j1, |e| notes.push(e.message.clone())).unwrap();
    assert!(
        notes.iter().any(|m| m.contains(&format!("worker {victim} at")) && m.contains("rolled back to its checkpoint of step")),
        "{notes:?}"
    );
    assert!(notes.iter().any(|m| m.contains("it waits for a worker of back end cpu/double")), "{notes:?}");
    // The others were not disturbed.
    assert!(!log.contains(&format!("job {j2}: worker")) && !log.contains(&format!("job {j3}: worker")), "{log}");
}

#[test]
fn a_high_priority_job_gets_the_first_worker_a_running_job_releases() {
    let (tmp, token) = setup();
    let state = tmp.path().join("state");
    let server = Server::start(&state, &token, &tmp.path().join("serve.log"));
    let _workers: Vec<Proc> = (0..2).map(|k| worker(&server, &token, &tmp.path().join(format!("w{k}.log")))).collect();
    server.wait_live(2);
    // (The first job was once SHORT itself; since the MD got faster it could end before the
    // queued jobs were submitted, and the ordinary one then started at once.)
    let short = server.submit(&FIRST, 0, 1);
    let long = server.submit(&LONGEST, 0, 1);
    mscale_testkit::wait_until("both running", Duration::from_secs(120), || {
        [&short, &long].iter().all(|j| server.job(j).state == pb::JobState::Running as i32)
    });
    // Queued while both workers are taken: first an ordinary job, then an urgent one.
    let low = server.submit(&SHORT, 0, 1);
    let high = server.submit(&SHORT, 5, 1);
    assert_eq!(server.job(&low).state, pb::JobState::Queued as i32);
    // The urgent job starts when the short one ends, while the long one still runs, and the
    // ordinary job still waits.
    let mut seen = None;
    mscale_testkit::wait_until("the urgent job starts", Duration::from_secs(180), || {
        let jobs: BTreeMap<String, pb::Job> = server.client().list().unwrap().into_iter().map(|j| (j.id.clone(), j)).collect();
        let state = |j: &str| jobs[j].state;
        assert_ne!(state(&low), pb::JobState::Running as i32, "the ordinary job overtook the urgent one\n{}", server.proc.log());
        let started = state(&high) != pb::JobState::Queued as i32;
        if started {
            seen = Some(jobs);
        }
        started
    });
    let jobs = seen.unwrap();
    // The short job has released its worker: it is completed, or has run its last step and is
    // still being finished (its outputs written) when the urgent job is listed as started.
    let (s, done) = (&jobs[&short], pb::JobState::Completed as i32);
    assert!(s.state == done || (s.state == pb::JobState::Running as i32 && s.step == s.steps), "{jobs:?}");
    mscale_testkit::wait_until("the short job completes", Duration::from_secs(60), || server.job(&short).state == done);
    assert_eq!(jobs[&long].state, pb::JobState::Running as i32, "{jobs:?}");
    assert_eq!(jobs[&low].state, pb::JobState::Queued as i32, "{jobs:?}");
    // No preemption: the long job kept its worker; cancel it now, the ordinary job follows.
    server.client().cancel(&long).unwrap();
    let (first, digest) = (run_digest(&tmp.path().join("first"), &FIRST), run_digest(&tmp.path().join("short"), &SHORT));
    for (j, d) in [(&short, &first), (&high, &digest), (&low, &digest)] {
        let done = server.finish(j);
        assert_eq!((done.state, done.state_digest.as_str()), (pb::JobState::Completed as i32, d.as_str()), "{done:?}");
    }
    assert_eq!(server.finish(&long).state, pb::JobState::Cancelled as i32);
    let log = mscale_testkit::plain(&server.proc.log());
    let at = |j: &str| log.find(&format!("job {j}: on workers")).unwrap_or_else(|| panic!("job {j} never ran on workers\n{log}"));
    assert!(at(&short) < at(&high) && at(&high) < at(&low), "{log}");
}
