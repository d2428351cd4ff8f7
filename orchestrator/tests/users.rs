//! Users of `mscale serve --users FILE` across real processes on 127.0.0.1: a job belongs to
//! its submitter, only the owner or an admin may get, watch, fetch or cancel it (another
//! user's job answers exactly as a job that does not exist), listing shows a user's own jobs
//! (an admin's: all), a worker token may only register and heartbeat; the dashboard and
//! `/metrics` check the same users; the users file is read again on SIGHUP; per-user limits
//! refuse a submission naming the limit.

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::{Listening, Proc, http_get, text};
use orchestrator::client::{Client, Refused};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;
use tonic::Code;

const SMALL: &str = "../tests/data/small.toml";
const MD_SMALL: &str = "../tests/data/md-small.toml";
const ALICE: &str = "alice-token-0123456789abcdef";
const BOB: &str = "bob-token-0123456789abcdef";
const ROOT: &str = "root-token-0123456789abcdef";
const WORKER: &str = "worker-token-0123456789abcdef";
const CAROL: &str = "carol-token-0123456789abcdef";

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

fn user(name: &str, role: &str, token: &str, extra: &str) -> String {
    format!("[[user]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken_sha256 = \"{}\"\n{extra}\n", hex(token))
}

fn hex(token: &str) -> String {
    Sha256::digest(token.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
}

struct Server {
    proc: Proc,
    addr: String,
    http: String,
    tmp: PathBuf,
}

impl Server {
    fn start(tmp: &Path, users: &Path, extra: &[&str]) -> Server {
        // A free port for the dashboard (its address is printed after the gRPC one, which
        // Listening reads alone).
        let http = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().to_string();
        let mut cmd = Command::new(bin());
        cmd.args(["serve", "--state", tmp.join("state").to_str().unwrap(), "--listen", "127.0.0.1:0", "--http", &http])
            .args(["--users", users.to_str().unwrap()])
            .args(extra)
            .env("RUST_LOG", "info");
        let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(&tmp.join("serve.log")));
        Server { proc, addr, http, tmp: tmp.to_path_buf() }
    }

    fn client(&self, token: Option<&str>) -> Client {
        Client::connect(&self.addr, token.map(str::to_string)).unwrap()
    }

    /// A client verb with the token `token` (written to a file).
    fn cli(&self, token: &str, args: &[&str]) -> Output {
        let f = self.tmp.join(format!("token-{}", &hex(token)[..8]));
        std::fs::write(&f, token).unwrap();
        Command::new(bin())
            .args(args)
            .args(["--server", &self.addr, "--token-file", f.to_str().unwrap()])
            .env_remove("MSCALE_TOKEN")
            .env("RUST_LOG", "warn")
            .output()
            .unwrap()
    }

    fn get(&self, path: &str, token: &str) -> mscale_testkit::HttpResponse {
        let auth = format!("Bearer {token}");
        http_get(&self.http, path, &[("Authorization", &auth)], Duration::from_secs(30)).unwrap()
    }
}

/// The status code of a refused call.
fn code<T: std::fmt::Debug>(r: anyhow::Result<T>) -> (Code, String) {
    let e = r.expect_err("the call was not refused");
    let s = e.chain().find_map(|c| c.downcast_ref::<Refused>()).unwrap_or_else(|| panic!("not a refusal: {e:#}"));
    (s.0.code(), s.0.message().to_string())
}

fn wait_final(c: &mut Client, id: &str) -> pb::Job {
    let mut last = None;
    mscale_testkit::wait_until(&format!("job {id} ends"), Duration::from_secs(120), || {
        let j = c.get(id).unwrap();
        let done = [pb::JobState::Completed, pb::JobState::Failed, pb::JobState::Cancelled].iter().any(|s| *s as i32 == j.state);
        last = Some(j);
        done
    });
    last.unwrap()
}

fn users_file(tmp: &Path, text: &str) -> PathBuf {
    let f = tmp.join("users.toml");
    std::fs::write(&f, text).unwrap();
    f
}

fn everyone() -> String {
    user("alice", "user", ALICE, "") + &user("bob", "user", BOB, "") + &user("root", "admin", ROOT, "") + &user("w", "worker", WORKER, "")
}

fn ids(jobs: Vec<pb::Job>) -> Vec<String> {
    jobs.into_iter().map(|j| j.id).collect()
}

#[test]
fn a_job_is_its_owners_and_every_refusal_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(tmp.path(), &users_file(tmp.path(), &everyone()), &[]);
    let (mut alice, mut bob, mut root) = (server.client(Some(ALICE)), server.client(Some(BOB)), server.client(Some(ROOT)));
    let a = alice.submit(Path::new(SMALL), &[], 0, 0).unwrap();
    let b = bob.submit(Path::new(SMALL), &[], 0, 0).unwrap();
    let ja = wait_final(&mut alice, &a);
    assert_eq!((ja.state, ja.owner.as_str()), (pb::JobState::Completed as i32, "alice"), "{ja:?}\n{}", server.proc.log());
    assert_eq!(wait_final(&mut bob, &b).owner, "bob");

    // Listing: one's own jobs; an admin sees every job.
    assert_eq!(ids(alice.list().unwrap()), vec![a.clone()]);
    assert_eq!(ids(bob.list().unwrap()), vec![b.clone()]);
    assert_eq!(ids(root.list().unwrap()), vec![a.clone(), b.clone()]);

    // Bob guessing Alice's job id gets exactly what an unknown id gets, for every call.
    let unknown = "j000000000000";
    let (c, m) = code(bob.get(&a));
    assert_eq!((c, m), (Code::NotFound, format!("no job {a:?}")));
    assert_eq!(code(bob.get(unknown)), (Code::NotFound, format!("no job {unknown:?}")));
    assert_eq!(code(bob.watch(&a, |_| {})).0, Code::NotFound);
    assert_eq!(code(bob.cancel(&a)), (Code::NotFound, format!("no job {a:?}")));
    assert_eq!(code(bob.fetch(&a, "summary.json")), (Code::NotFound, format!("no job {a:?}")));
    assert_eq!(code(bob.fetch_run(&a, &tmp.path().join("stolen"))).0, Code::NotFound);
    assert!(!tmp.path().join("stolen/summary.json").exists());
    // The CLI says the same.
    let o = server.cli(BOB, &["status", &a]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains(&format!("no job {a:?}")), "{}", text(&o));

    // The owner and an admin may.
    assert!(!alice.fetch(&a, "summary.json").unwrap().is_empty());
    assert_eq!(root.get(&b).unwrap().owner, "bob");
    assert!(!root.fetch(&b, "summary.json").unwrap().is_empty());
    let mut seen = 0;
    root.watch(&a, |_| seen += 1).unwrap();
    assert!(seen > 2);

    // Without a token or with an unknown one, nothing: with users, reads need a token too.
    let mut anon = server.client(None);
    let (c, m) = code(anon.list());
    assert!(c == Code::Unauthenticated && m.contains("ListJobs needs a bearer token"), "{c:?} {m}");
    assert_eq!(code(anon.get(&a)).0, Code::Unauthenticated);
    assert_eq!(code(anon.workers()).0, Code::Unauthenticated);
    let mut wrong = server.client(Some("alice-token-0123456789abcdeX"));
    let (c, m) = code(wrong.get(&a));
    assert!(c == Code::Unauthenticated && m.contains("not this orchestrator's"), "{c:?} {m}");

    // A worker token registers and heartbeats, and does nothing else.
    let mut w = server.client(Some(WORKER));
    for (what, r) in [
        ("SubmitJob", w.submit(Path::new(SMALL), &[], 0, 0).map(|_| ())),
        ("ListJobs", w.list().map(|_| ())),
        ("GetJob", w.get(&a).map(|_| ())),
        ("CancelJob", w.cancel(&a).map(|_| ())),
        ("FetchResult", w.fetch(&a, "summary.json").map(|_| ())),
        ("WatchJob", w.watch(&a, |_| {}).map(|_| ())),
        ("ListWorkers", w.workers().map(|_| ())),
        ("DrainWorker", w.drain("w1").map(|_| ())),
    ] {
        let (c, m) = code(r);
        assert_eq!(c, Code::PermissionDenied, "{what}: {m}");
        assert!(m.contains(what) && m.contains("user w (role worker)"), "{what}: {m}");
    }
    let ad = pb::RegisterWorkerRequest {
        address: "127.0.0.1:9".into(),
        device: "cpu".into(),
        backend: "cpu".into(),
        precision: "double".into(),
        atom_steps_per_s: 1.0,
        protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
        ..Default::default()
    };
    let reg = w.register_worker(ad.clone()).unwrap();
    let hb = pb::HeartbeatRequest { worker_id: reg.worker_id.clone(), epoch: reg.epoch, protocol_version: ad.protocol_version };
    w.heartbeat(hb.clone()).unwrap();
    // A user may neither register nor heartbeat a worker, nor drain one.
    let s = alice.register_worker(ad.clone()).unwrap_err();
    assert!(s.code() == Code::PermissionDenied && s.message().contains("RegisterWorker"), "{s:?}");
    let s = alice.heartbeat(hb).unwrap_err();
    assert_eq!(s.code(), Code::PermissionDenied, "{s:?}");
    let (c, m) = code(alice.drain(&reg.worker_id));
    assert!(c == Code::PermissionDenied && m.contains("needs an admin token"), "{c:?} {m}");
    assert_eq!(alice.workers().unwrap().len(), 1, "users may list the workers");
    assert_eq!(root.drain(&reg.worker_id).unwrap().state, pb::WorkerState::Draining as i32);

    // Cancelling: not another user's queued job, but one's own and, as an admin, anyone's.
    let long = ["domain.cells=[4000]".to_string()];
    let a2 = alice.submit(Path::new(SMALL), &long, 0, 0).unwrap();
    let a3 = alice.submit(Path::new(SMALL), &long, 0, 0).unwrap();
    assert_eq!(code(bob.cancel(&a3)).0, Code::NotFound);
    assert_ne!(alice.get(&a3).unwrap().state, pb::JobState::Cancelled as i32);
    root.cancel(&a3).unwrap();
    alice.cancel(&a2).unwrap();
    assert_eq!(wait_final(&mut alice, &a2).state, pb::JobState::Cancelled as i32);
    assert_eq!(wait_final(&mut alice, &a3).state, pb::JobState::Cancelled as i32);

    // The dashboard and /metrics check the same users.
    let page = server.get("/", ALICE);
    assert_eq!(page.status, 200, "{}", page.text());
    let html = page.text();
    assert!(html.contains(&a) && !html.contains(&b) && html.contains("<th>owner</th>") && html.contains(">alice</td>"), "{html}");
    let html = server.get("/", ROOT).text();
    assert!(html.contains(&a) && html.contains(&b) && html.contains(">bob</td>"), "{html}");
    assert_eq!(server.get(&format!("/jobs/{a}"), BOB).status, 404);
    assert_eq!(server.get(&format!("/jobs/{a}/files/summary.json"), BOB).status, 404);
    assert_eq!(server.get(&format!("/jobs/{a}/events"), BOB).status, 404);
    assert_eq!(server.get(&format!("/jobs/{a}/results"), BOB).status, 404);
    assert_eq!(server.get(&format!("/jobs/{a}"), ALICE).status, 200);
    assert_eq!(server.get(&format!("/jobs/{a}/files/summary.json"), ROOT).status, 200);
    assert_eq!(server.get("/", WORKER).status, 403);
    assert_eq!(server.get("/metrics", ALICE).status, 403);
    assert_eq!(server.get("/metrics", ROOT).status, 200);
    assert_eq!(server.get("/", "nobody").status, 401);
    assert_eq!(http_get(&server.http, "/", &[], Duration::from_secs(30)).unwrap().status, 401);
}

#[test]
fn the_users_file_is_read_again_on_sighup_and_a_broken_one_keeps_the_users_in_force() {
    let tmp = tempfile::tempdir().unwrap();
    let file = users_file(tmp.path(), &everyone());
    let server = Server::start(tmp.path(), &file, &[]);
    server.client(Some(BOB)).list().unwrap();
    // Bob leaves, Carol comes.
    std::fs::write(&file, user("alice", "user", ALICE, "") + &user("carol", "user", CAROL, "")).unwrap();
    server.proc.signal("-HUP");
    mscale_testkit::wait_until("carol's token works", Duration::from_secs(30), || server.client(Some(CAROL)).list().is_ok());
    assert_eq!(code(server.client(Some(BOB)).list()).0, Code::Unauthenticated);
    assert_eq!(code(server.client(Some(ROOT)).list()).0, Code::Unauthenticated);
    // A broken file: reported, and the users in force stay.
    std::fs::write(&file, "[[user]]\nname = \"x\"\n").unwrap();
    server.proc.signal("-HUP");
    mscale_testkit::wait_until("the refusal in the log", Duration::from_secs(30), || {
        server.proc.log().contains("the users in force are kept")
    });
    assert!(server.proc.log().contains("missing field `role`"), "{}", server.proc.log());
    server.client(Some(CAROL)).list().unwrap();
    server.client(Some(ALICE)).list().unwrap();
    // The server is still up and serving.
    assert!(server.client(Some(ALICE)).submit(Path::new(SMALL), &[], 0, 0).is_ok());
}

#[test]
fn a_bad_users_file_or_one_with_a_token_file_is_refused_at_start() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = users_file(tmp.path(), &user("alice", "boss", ALICE, ""));
    let state = tmp.path().join("state");
    let o = Command::new(bin())
        .args(["serve", "--state", state.to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .args(["--users", bad.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("users.toml") && String::from_utf8_lossy(&o.stderr).contains("boss"),
        "{}",
        text(&o)
    );
    let o = Command::new(bin())
        .args(["serve", "--state", state.to_str().unwrap(), "--users", bad.to_str().unwrap(), "--token-file", bad.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--token-file"), "{}", text(&o));
}

#[test]
fn limits_refuse_a_submission_naming_the_limit() {
    let tmp = tempfile::tempdir().unwrap();
    let users =
        user("alice", "user", ALICE, "max_jobs = 1") + &user("bob", "user", BOB, "max_upload_bytes = 100000000\nmax_snapshots = 50");
    let server = Server::start(
        tmp.path(),
        &users_file(tmp.path(), &users),
        &["--max-upload-bytes", "3000", "--max-snapshots", "20", "--max-jobs-per-user", "5"],
    );
    let (mut alice, mut bob) = (server.client(Some(ALICE)), server.client(Some(BOB)));
    // Uploaded bytes: md-small brings its potential file, over the server's 3000 bytes.
    let (c, m) = code(alice.submit(Path::new(MD_SMALL), &[], 0, 0));
    assert!(c == Code::ResourceExhausted && m.contains("max_upload_bytes = 3000"), "{c:?} {m}");
    // Snapshots: over the server's 20 for Alice, within Bob's own 50.
    let (c, m) = code(alice.submit(Path::new(SMALL), &["output.snapshots=21".to_string()], 0, 0));
    assert!(c == Code::ResourceExhausted && m.contains("max_snapshots = 20") && m.contains("output.snapshots = 21"), "{c:?} {m}");
    // Jobs at once: Alice's own limit (1), over the server's 5.
    let long = ["domain.cells=[4000]".to_string()];
    let first = alice.submit(Path::new(SMALL), &long, 0, 0).unwrap();
    let (c, m) = code(alice.submit(Path::new(SMALL), &[], 0, 0));
    assert!(c == Code::ResourceExhausted && m.contains("user alice") && m.contains("max_jobs = 1"), "{c:?} {m}");
    let o = server.cli(ALICE, &["submit", SMALL]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("max_jobs = 1"), "{}", text(&o));
    bob.submit(Path::new(SMALL), &["output.snapshots=21".to_string()], 0, 0).unwrap();
    let (c, m) = code(bob.submit(Path::new(SMALL), &["output.snapshots=51".to_string()], 0, 0));
    assert!(c == Code::ResourceExhausted && m.contains("max_snapshots = 50"), "{c:?} {m}");
    // Bob's own upload limit lets md-small in.
    bob.submit(Path::new(MD_SMALL), &["scheme.end_time=2e-14".to_string()], 0, 0).unwrap();
    // Refused submissions left nothing behind.
    assert_eq!(ids(alice.list().unwrap()), vec![first.clone()]);
    assert_eq!(bob.list().unwrap().len(), 2);
    let jobs_dir = tmp.path().join("state/jobs");
    assert_eq!(std::fs::read_dir(&jobs_dir).unwrap().count(), 3);
    // Once Alice's job ends she may submit again.
    alice.cancel(&first).unwrap();
    wait_final(&mut alice, &first);
    alice.submit(Path::new(SMALL), &[], 0, 0).unwrap();
}
