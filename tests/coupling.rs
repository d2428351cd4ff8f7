//! The coupled run across real processes: in-process MD and MD on `md-worker serve` processes
//! on loopback give bitwise the same result; a lost worker stops the run naming it.

use mscale_tests::{Worker, binary, repo};
use std::path::Path;
use std::process::Command;

fn mscale(args: &[&str]) -> std::process::Output {
    Command::new(binary("mscale", "orchestrator")).args(args).current_dir(repo()).env("RUST_LOG", "warn").output().expect("run mscale")
}

fn digest(dir: &Path) -> String {
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).expect("summary")).expect("json");
    assert_eq!(s["status"], "completed", "{s}");
    s["state_digest"].as_str().expect("digest").to_string()
}

#[test]
fn in_process_and_remote_workers_give_the_same_digest() {
    let scene = repo().join("tests/data/md-small.toml");
    let scene = scene.to_str().expect("utf8");
    let tmp = tempfile::tempdir().expect("tempdir");
    let run = |name: &str, workers: Option<String>| {
        let out = tmp.path().join(name);
        let mut args = vec!["run".to_string(), scene.to_string(), "--out".into(), out.display().to_string()];
        if let Some(w) = workers {
            args.push("--workers".into());
            args.push(w);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = mscale(&args);
        assert_eq!(o.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&o.stderr));
        out
    };
    let local = run("local", None);
    let (a, b) = (Worker::start(1), Worker::start(2));
    let one = run("one", Some(a.addr.clone()));
    let two = run("two", Some(format!("{},{}", a.addr, b.addr)));
    assert_eq!(digest(&local), digest(&one), "in-process vs one remote worker");
    assert_eq!(digest(&local), digest(&two), "in-process vs two remote workers");
    let csv = std::fs::read_to_string(two.join("particles_final.csv")).expect("csv");
    assert!(csv.lines().next().expect("header").ends_with("md_temperature_k,md_potential_ev,md_kinetic_ev,md_energy_added_ev"));
    let summary = std::fs::read_to_string(two.join("summary.json")).expect("summary");
    assert!(summary.contains(&a.addr) && summary.contains(&b.addr), "the provenance names the workers");
}

#[test]
fn an_unreachable_worker_is_named_and_the_run_fails() {
    let w = Worker::start(1);
    let addr = w.addr.clone();
    drop(w);
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = repo().join("tests/data/md-small.toml");
    let o = mscale(&["run", scene.to_str().expect("utf8"), "--out", tmp.path().join("x").to_str().expect("utf8"), "--workers", &addr]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(&format!("worker {addr}")), "{err}");
}

#[test]
fn a_worker_killed_mid_run_stops_the_run_naming_it_and_the_step() {
    let mut w = Worker::start(1);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("x");
    let scene = repo().join("tests/data/md-small.toml");
    // Long enough (thousands of steps) that the worker dies mid-run.
    let child = Command::new(binary("mscale", "orchestrator"))
        .args(["run", scene.to_str().expect("utf8"), "--out", out.to_str().expect("utf8"), "--workers", &w.addr, "--set", "scheme.end_time=1e-10"])
        .current_dir(repo())
        .env("RUST_LOG", "warn")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start mscale");
    std::thread::sleep(std::time::Duration::from_millis(1500));
    w.child.kill().expect("kill the worker");
    let o = child.wait_with_output().expect("wait");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(&format!("worker {}", w.addr)) && err.contains("continuum step"), "{err}");
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary")).expect("json");
    assert_eq!(s["status"], "failed");
}
