//! Checkpoints and exact resume of local runs (`mscale run --checkpoint-every`, SIGTERM,
//! `mscale run --resume`), through the real binary: a resumed run must end with the same
//! `state_digest` as one never stopped, also from the previous checkpoint when the newest one
//! is damaged.

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SMALL: &str = "../tests/data/small.toml";
const MD_SMALL: &str = "../tests/data/md-small.toml";

fn mscale(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mscale")).args(args).env("RUST_LOG", "warn").output().expect("cannot start mscale")
}

fn ok(args: &[&str]) -> Output {
    let out = mscale(args);
    assert!(out.status.success(), "mscale {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    out
}

fn summary(dir: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(dir.join("summary.json")).expect("no summary.json")).expect("bad summary.json")
}

fn checkpoints(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir.join("checkpoints"))
        .map(|r| r.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "ckpt")).collect())
        .unwrap_or_default();
    v.sort();
    v
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), t).unwrap();
        }
    }
}

/// The fields that must not depend on whether a run was stopped and resumed.
fn same_state(a: &Value, b: &Value) {
    assert_eq!(a["status"], "completed");
    assert_eq!(b["status"], "completed");
    for k in ["state_digest", "steps", "simulated_time_s", "closure_evaluations"] {
        assert_eq!(a[k], b[k], "{k} differs");
    }
    for k in ["energy_final", "energy_drift", "momentum_drift", "momentum_final", "wall_impulse"] {
        assert_eq!(a["conservation"][k], b["conservation"][k], "conservation.{k} differs");
    }
    // Implicit runs: the counts and the last step's estimates carry over the checkpoint too.
    if a.get("implicit").is_some() {
        for k in IMPLICIT_KEYS {
            assert_eq!(a["implicit"][k], b["implicit"][k], "implicit.{k} differs");
        }
    }
}

/// summary.json `implicit` keys that do not depend on a stop and resume (not the timings).
const IMPLICIT_KEYS: [&str; 11] = [
    "accepted_steps",
    "rejected_steps",
    "rejected_for_error",
    "newton_iterations",
    "residual_evaluations",
    "jacobians",
    "last_error_u",
    "last_error_v",
    "last_error_f",
    "last_error_norm",
    "last_dt",
];

/// Runs `scene` once straight through and once with checkpoints; resumes a copy of the
/// checkpointed run from its newest checkpoint and another copy from the previous one (the
/// newest cut in half); all three end in the same state.
/// Returns the summary of the uninterrupted run.
fn resume_matches(scene: &str, sets: &[&str], every: &str) -> Value {
    let tmp = tempfile::tempdir().unwrap();
    let straight = tmp.path().join("straight");
    let with_sets = |mut a: Vec<String>| {
        for s in sets {
            a.push("--set".into());
            a.push(s.to_string());
        }
        a
    };
    let args = |dir: &Path, extra: &[&str]| {
        with_sets(["run", scene, "--out", dir.to_str().unwrap()].iter().chain(extra).map(|s| s.to_string()).collect())
    };
    let run = |a: Vec<String>| ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
    run(args(&straight, &[]));
    let reference = summary(&straight);
    assert!(checkpoints(&straight).is_empty(), "a run without --checkpoint-every wrote checkpoints");

    let ckpt = tmp.path().join("ckpt");
    run(args(&ckpt, &["--checkpoint-every", every]));
    same_state(&reference, &summary(&ckpt));
    let files = checkpoints(&ckpt);
    assert_eq!(files.len(), 2, "expected the two newest checkpoints, got {files:?}");

    // Resume from the newest checkpoint: the steps after it are run again.
    let resumed = tmp.path().join("resumed");
    copy_dir(&ckpt, &resumed);
    std::fs::remove_file(resumed.join("summary.json")).unwrap();
    let out = ok(&["run", "--resume", resumed.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("completed"), "{text}");
    same_state(&reference, &summary(&resumed));

    // Cut the newest checkpoint short: the previous one is used, and logged.
    let fallback = tmp.path().join("fallback");
    copy_dir(&ckpt, &fallback);
    std::fs::remove_file(fallback.join("summary.json")).unwrap();
    let newest = checkpoints(&fallback).pop().unwrap();
    let len = std::fs::metadata(&newest).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&newest).unwrap().set_len(len / 2).unwrap();
    let out = ok(&["run", "--resume", fallback.to_str().unwrap()]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(log.contains("damaged") && log.contains("previous checkpoint"), "the fallback is not logged: {log}");
    same_state(&reference, &summary(&fallback));
    reference
}

/// The provenance names the precision used and the cargo features compiled in.
fn provenance_is_truthful(s: &Value, precision: &str) {
    assert_eq!(s["provenance"]["precision"], precision, "{}", s["provenance"]);
    assert_eq!(s["provenance"]["features"], serde_json::json!(md_worker::FEATURES), "{}", s["provenance"]);
}

#[test]
fn constitutive_run_resumes_to_the_same_digest() {
    // 25 steps; checkpoints after steps 15 and 20 are kept.
    let s = resume_matches(SMALL, &[], "5");
    provenance_is_truthful(&s, "f64");
}

#[test]
fn md_run_resumes_to_the_same_digest() {
    // 5 steps of 6 boxes; checkpoints after steps 2 and 4.
    let s = resume_matches(MD_SMALL, &[], "2");
    provenance_is_truthful(&s, "continuum f64, md double");
}

/// Issue 18: an implicit run with adaptive steps resumes to the digest and the implicit counts
/// of an uninterrupted one (the checkpoint carries a^(n-1) and its dt, which the velocity error
/// estimate of the next step, hence the error norm and the next dt, read, and the statistics).
/// A checkpoint without that state (as written before it was saved) still loads, with a
/// warning, and its run then ends in another state.
#[test]
fn implicit_adaptive_run_resumes_to_the_same_digest() {
    let sets = [
        "scheme.integrator=\"implicit-trapezoidal\"",
        // le_v controls the step (atol_displacement = 1 m takes le_u out of the norm; le_F at
        // rtol |F| ~ 1e-3 is far below it), so the state a^(n-1) decides the steps after a resume.
        "scheme.adaptive={ rtol = 1e-3, atol_displacement = 1, atol_velocity = 1e-6, atol_deformation = 1e-6 }",
        "scheme.cfl=0.01",
        "reference.amplitude=1e-3",
        "output.snapshots=2",
        "output.plots=false",
    ];
    // 47 accepted steps (18 rejected); checkpoints after steps 30 and 40 are kept.
    let reference = resume_matches("../scenes/mms-1d.toml", &sets, "10");
    let im = &reference["implicit"];
    assert!(im["accepted_steps"].as_u64().unwrap() > 20, "{im}");
    assert!(im["last_error_f"].as_f64().unwrap() > 0.0, "le_F is reported: {im}");

    // The same resume from a checkpoint stripped of the implicit state.
    let tmp = tempfile::tempdir().unwrap();
    let (ckpt, old) = (tmp.path().join("ckpt"), tmp.path().join("old"));
    let mut args: Vec<&str> = vec!["run", "../scenes/mms-1d.toml", "--out", ckpt.to_str().unwrap(), "--checkpoint-every", "10"];
    for s in &sets {
        args.extend(["--set", s]);
    }
    ok(&args);
    copy_dir(&ckpt, &old);
    std::fs::remove_file(old.join("summary.json")).unwrap();
    let newest = checkpoints(&old).pop().unwrap();
    let mut ck: orchestrator::checkpoint::Checkpoint = orchestrator::checkpoint::decode(&std::fs::read(&newest).unwrap()).unwrap();
    assert!(ck.implicit.as_ref().is_some_and(|i| !i.prev_acc.is_empty()), "an implicit checkpoint carries a^(n-1)");
    ck.implicit = None;
    std::fs::write(&newest, orchestrator::checkpoint::encode(&ck).unwrap()).unwrap();
    let out = ok(&["run", "--resume", old.to_str().unwrap()]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(log.contains("predates the implicit integrator's saved state"), "{log}");
    let s = summary(&old);
    assert_eq!(s["status"], "completed");
    assert_ne!(s["state_digest"], reference["state_digest"], "without a^(n-1) the adaptive steps differ after the resume");
}

/// Starts `mscale ARGS` (a run into `dir` with checkpoints), sends SIGTERM once its first
/// checkpoint exists, and checks that it stopped mid-run with exit code 1 and told how to resume.
fn stop_with_sigterm(args: &[&str], dir: &Path) {
    let child =
        Command::new(env!("CARGO_BIN_EXE_mscale")).args(args).env("RUST_LOG", "warn").stderr(std::process::Stdio::piped()).spawn().unwrap();
    let start = std::time::Instant::now();
    while checkpoints(dir).is_empty() {
        assert!(start.elapsed().as_secs() < 60, "no checkpoint after 60 s");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let pid = child.id().to_string();
    assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
    let out = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(!dir.join("summary.json").exists(), "the run finished before SIGTERM arrived; make it longer");
    assert_eq!(out.status.code(), Some(1), "{log}");
    assert!(log.contains("cancelled after step") && log.contains("--resume"), "{log}");
}

#[test]
fn sigterm_checkpoints_and_the_run_resumes_to_the_same_digest() {
    let tmp = tempfile::tempdir().unwrap();
    // Long enough (1000 steps of 8000 points, a few seconds, a checkpoint every 100) that
    // SIGTERM lands mid-run.
    let sets = ["--set", "domain.cells=[2000]"];
    let straight = tmp.path().join("straight");
    ok(&[&["run", SMALL, "--out", straight.to_str().unwrap()][..], &sets].concat());
    let reference = summary(&straight);

    let stopped = tmp.path().join("stopped");
    stop_with_sigterm(&[&["run", SMALL, "--out", stopped.to_str().unwrap(), "--checkpoint-every", "100"][..], &sets].concat(), &stopped);
    ok(&["run", "--resume", stopped.to_str().unwrap()]);
    same_state(&reference, &summary(&stopped));
}

#[test]
fn resume_refuses_another_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("a");
    ok(&["run", SMALL, "--out", dir.to_str().unwrap(), "--checkpoint-every", "5"]);
    let out = mscale(&["run", SMALL, "--set", "scheme.cfl=0.1", "--resume", dir.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("another scene"), "{}", String::from_utf8_lossy(&out.stderr));
    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = mscale(&["run", SMALL, "--resume", empty.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("no checkpoint"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn md_run_on_a_remote_worker_resumes_on_a_fresh_worker_to_the_same_digest() {
    let tmp = tempfile::tempdir().unwrap();
    let local = tmp.path().join("local");
    ok(&["run", MD_SMALL, "--out", local.to_str().unwrap()]);
    let reference = summary(&local);

    // Boxes on a gRPC worker, checkpoints after steps 2 and 4 (snapshots over Snapshot).
    let remote = tmp.path().join("remote");
    {
        let w = md_worker::server::Loopback::start("cpu").unwrap();
        ok(&["run", MD_SMALL, "--out", remote.to_str().unwrap(), "--checkpoint-every", "2", "--workers", &w.addr]);
    }
    same_state(&reference, &summary(&remote));
    assert_eq!(checkpoints(&remote).len(), 2);

    // A new worker has none of the boxes: they are opened and restored over Restore.
    std::fs::remove_file(remote.join("summary.json")).unwrap();
    let w = md_worker::server::Loopback::start("cpu").unwrap();
    ok(&["run", "--resume", remote.to_str().unwrap(), "--workers", &w.addr]);
    same_state(&reference, &summary(&remote));
}

const CELL: &str = "../scenes/pnp-full-cell.toml";

/// The fields of a cell run's summary that must not depend on whether it was stopped.
fn same_cell_state(a: &Value, b: &Value) {
    assert_eq!(a["status"], "completed");
    assert_eq!(b["status"], "completed");
    for k in ["state_digest", "steps", "simulated_time_s", "totals", "conservation", "checks"] {
        assert_eq!(a[k], b[k], "{k} differs");
    }
    let counts = |s: &Value| {
        let mut c = s["step_statistics"].clone();
        c.as_object_mut().unwrap().remove("switches");
        c
    };
    assert_eq!(counts(a), counts(b), "step statistics differ");
}

#[test]
fn cell_run_resumes_to_the_same_digest() {
    // The full cell at 200 cells to 2 s: ~1200 steps, switches (integrator restarts) and five
    // output times; checkpoints at restart points after every 100 steps.
    let tmp = tempfile::tempdir().unwrap();
    let sets = ["--set", "grid.cells=200", "--set", "output.times_s=[0.0, 0.5, 1.0, 1.5, 2.0]"];
    let run = |dir: &Path, extra: &[&str]| ok(&[&["run", CELL, "--out", dir.to_str().unwrap()][..], &sets, extra].concat());
    let straight = tmp.path().join("straight");
    run(&straight, &[]);
    let reference = summary(&straight);
    assert!(checkpoints(&straight).is_empty(), "a run without --checkpoint-every wrote checkpoints");
    let ckpt = tmp.path().join("ckpt");
    run(&ckpt, &["--checkpoint-every", "100"]);
    same_cell_state(&reference, &summary(&ckpt));
    assert_eq!(checkpoints(&ckpt).len(), 2, "the two newest checkpoints are kept");

    let resumed = tmp.path().join("resumed");
    copy_dir(&ckpt, &resumed);
    std::fs::remove_file(resumed.join("summary.json")).unwrap();
    ok(&["run", "--resume", resumed.to_str().unwrap()]);
    same_cell_state(&reference, &summary(&resumed));
    let index = |d: &Path| std::fs::read_to_string(d.join("profiles/index.csv")).unwrap();
    assert_eq!(index(&resumed), index(&straight), "the profile index of the resumed run");

    // The newest checkpoint cut short: the previous one is used.
    let fallback = tmp.path().join("fallback");
    copy_dir(&ckpt, &fallback);
    std::fs::remove_file(fallback.join("summary.json")).unwrap();
    let newest = checkpoints(&fallback).pop().unwrap();
    let len = std::fs::metadata(&newest).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&newest).unwrap().set_len(len / 2).unwrap();
    let out = ok(&["run", "--resume", fallback.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("damaged"), "{}", String::from_utf8_lossy(&out.stderr));
    same_cell_state(&reference, &summary(&fallback));

    // Another scene (other overrides) is refused.
    let out = mscale(&["run", CELL, "--set", "grid.cells=300", "--resume", ckpt.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("another scene"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn sigterm_checkpoints_a_cell_run_and_it_resumes_to_the_same_digest() {
    // 3000 cells to 2 s (several seconds): SIGTERM after the first checkpoint lands mid-run.
    let tmp = tempfile::tempdir().unwrap();
    let sets = ["--set", "grid.cells=3000", "--set", "output.times_s=[0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0]"];
    let straight = tmp.path().join("straight");
    ok(&[&["run", CELL, "--out", straight.to_str().unwrap()][..], &sets].concat());
    let reference = summary(&straight);

    let stopped = tmp.path().join("stopped");
    stop_with_sigterm(&[&["run", CELL, "--out", stopped.to_str().unwrap(), "--checkpoint-every", "1"][..], &sets].concat(), &stopped);
    ok(&["run", "--resume", stopped.to_str().unwrap()]);
    same_cell_state(&reference, &summary(&stopped));
}

/// Issue 19: a tlmpm run resumes to the digest of an uninterrupted one (its reference stencil
/// and nodal masses are rebuilt from X_p to the same bits; the nodal velocity is re-mapped from
/// the points every step, so the points are all it carries). 1D and 2D.
#[test]
fn tlmpm_run_resumes_to_the_same_digest() {
    // 80 steps; checkpoints after steps 60 and 80 are kept.
    resume_matches("../scenes/mms-1d-tlmpm.toml", &["output.snapshots=2", "output.plots=false"], "20");
    // 8 x 8 cells, 40 steps; checkpoints after steps 30 and 40.
    resume_matches(
        "../scenes/mms-2d.toml",
        &["scheme.method=\"tlmpm\"", "domain.cells=[8,8]", "output.snapshots=2", "output.plots=false", "output.vtk=false"],
        "10",
    );
}

/// Issue 19: tlmpm's moving mesh resumes to the uninterrupted digest: its checkpoint carries the
/// nodal velocity (`mesh_velocity`), which is not re-mapped from the points. 1D and 2D.
#[test]
fn a_moving_mesh_run_resumes_to_the_same_digest() {
    let mm = "scheme.tlmpm_form=\"moving-mesh\"";
    resume_matches("../scenes/mms-1d-tlmpm.toml", &[mm, "output.snapshots=2", "output.plots=false"], "20");
    resume_matches(
        "../scenes/mms-2d.toml",
        &["scheme.method=\"tlmpm\"", mm, "domain.cells=[8,8]", "output.snapshots=2", "output.plots=false", "output.vtk=false"],
        "10",
    );
}

/// Issue 19: diffusion under tlmpm (the reference form on the reference stencil, nodal values
/// projected from the points every step) carries nothing but the points, so a resumed run
/// ends with the uninterrupted digest; so does the pillar (its surface points, their areas and
/// the diffusing bodies are found again from X_p at setup).
#[test]
fn diffusion_runs_resume_to_the_same_digest() {
    // heat-1d under tlmpm, 80 steps; checkpoints after steps 60 and 80.
    resume_matches(
        "../scenes/heat-1d.toml",
        &[
            "scheme.method=\"tlmpm\"",
            "scheme.integrator=\"leapfrog\"",
            "scheme.end_time=0.0008",
            "output.snapshots=2",
            "output.plots=false",
        ],
        "20",
    );
    // The pillar, 40 steps at the faster flux.
    resume_matches(
        "../scenes/si-pillar-2d.toml",
        &["diffusion.surface_flux=1e-8", "scheme.end_time=0.012", "output.snapshots=2", "output.vtk=false"],
        "10",
    );
}
