//! The coupled run across real processes: in-process MD and MD on `md-worker serve` processes
//! on loopback give bitwise the same result; a lost worker stops the run naming it.

use mscale_tests::{binary, repo, worker};
use std::path::Path;
use std::process::Command;

fn mscale(args: &[&str]) -> std::process::Output {
    Command::new(binary("mscale", "orchestrator")).args(args).current_dir(repo()).env("RUST_LOG", "warn").output().expect("run mscale")
}

fn digest(dir: &Path) -> String {
    mscale_tests::state_digest(dir)
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
    let (a, b) = (worker(1), worker(2));
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
    let w = worker(1);
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
    let mut w = worker(1);
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("x");
    let scene = repo().join("tests/data/md-small.toml");
    // Long enough (thousands of steps) that the worker dies mid-run.
    let child = Command::new(binary("mscale", "orchestrator"))
        .args([
            "run",
            scene.to_str().expect("utf8"),
            "--out",
            out.to_str().expect("utf8"),
            "--workers",
            &w.addr,
            "--set",
            "scheme.end_time=1e-10",
        ])
        .current_dir(repo())
        .env("RUST_LOG", "warn")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start mscale");
    std::thread::sleep(std::time::Duration::from_millis(1500));
    w.proc.child.kill().expect("kill the worker");
    let o = child.wait_with_output().expect("wait");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(&format!("worker {}", w.addr)) && err.contains("continuum step"), "{err}");
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary")).expect("json");
    assert_eq!(s["status"], "failed");
}

/// Runs the small coupled scene with `sets`, in-process or on `workers`; returns the run directory.
fn run_small(out: &Path, sets: &[&str], workers: Option<&str>) -> std::path::PathBuf {
    let scene = repo().join("tests/data/md-small.toml");
    let mut args = vec!["run", scene.to_str().expect("utf8"), "--out", out.to_str().expect("utf8")];
    for s in sets {
        args.extend(["--set", s]);
    }
    if let Some(w) = workers {
        args.extend(["--workers", w]);
    }
    let o = mscale(&args);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    out.to_path_buf()
}

#[test]
fn average_stress_sampling_runs_and_gives_the_same_digest_in_process_and_remote() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let avg = ["bodies.left.material.stress_sampling=average", "bodies.right.material.stress_sampling=average"];
    let local = run_small(&tmp.path().join("local"), &avg, None);
    let (a, b) = (worker(1), worker(2));
    let two = run_small(&tmp.path().join("two"), &avg, Some(&format!("{},{}", a.addr, b.addr)));
    assert_eq!(digest(&local), digest(&two), "average sampling: in-process vs two remote workers");
    let resolved = std::fs::read_to_string(local.join("scene.resolved.toml")).expect("resolved scene");
    assert!(resolved.contains("stress_sampling = \"average\""), "{resolved}");
    // The choice reaches the boxes: the stresses (and so the run) differ from `last`.
    let last = run_small(&tmp.path().join("last"), &[], None);
    assert_ne!(digest(&local), digest(&last), "average and last sampling gave the same run");
}

/// Dump frames of a file: (timestep, atom lines).
fn dump_frames(path: &Path) -> Vec<(u64, Vec<String>)> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut frames = Vec::new();
    let mut lines = text.lines().peekable();
    while let Some(l) = lines.next() {
        assert_eq!(l, "ITEM: TIMESTEP", "{}", path.display());
        let step: u64 = lines.next().expect("step").parse().expect("step number");
        assert_eq!(lines.next(), Some("ITEM: NUMBER OF ATOMS"));
        let n: usize = lines.next().expect("count").parse().expect("atom count");
        assert_eq!(lines.next(), Some("ITEM: BOX BOUNDS pp pp pp"));
        for _ in 0..3 {
            let b: Vec<f64> = lines.next().expect("bounds").split_whitespace().map(|v| v.parse().expect("bound")).collect();
            assert!(b.len() == 2 && b[1] > b[0], "bounds {b:?}");
        }
        assert_eq!(lines.next(), Some("ITEM: ATOMS id type x y z vx vy vz"));
        let atoms: Vec<String> = (0..n).map(|_| lines.next().expect("atom line").to_string()).collect();
        for a in &atoms {
            let v: Vec<f64> = a.split_whitespace().map(|v| v.parse().expect("number")).collect();
            assert!(v.len() == 8 && v.iter().all(|x| x.is_finite()), "{a}");
        }
        frames.push((step, atoms));
    }
    frames
}

#[test]
fn chosen_boxes_are_dumped_for_ovito_at_every_snapshot_in_process_and_remote() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let sets = ["output.dump_points=[4, 1]"];
    let local = run_small(&tmp.path().join("local"), &sets, None);
    let w = worker(1);
    let remote = run_small(&tmp.path().join("remote"), &sets, Some(&w.addr));
    let index = std::fs::read_to_string(local.join("snapshots/index.csv")).expect("index");
    let steps: Vec<u64> = index.lines().skip(1).map(|l| l.split(',').next().expect("step").parse().expect("step")).collect();
    assert!(steps.len() >= 2, "{index}");
    for id in [1, 4] {
        let file = format!("boxes/point-{id}.dump");
        let frames = dump_frames(&local.join(&file));
        assert_eq!(
            frames.iter().map(|f| f.0).collect::<Vec<_>>(),
            steps,
            "{file}: one frame per snapshot, stamped with its continuum step"
        );
        assert!(frames.iter().all(|f| f.1.len() == 32), "{file}: 2x2x2 fcc cells = 32 atoms");
        assert_ne!(frames[0].1, frames[frames.len() - 1].1, "{file}: the atoms moved");
        let same = std::fs::read(local.join(&file)).expect("local dump") == std::fs::read(remote.join(&file)).expect("remote dump");
        assert!(same, "{file}: in-process and remote dumps differ");
    }
    assert!(!local.join("boxes/point-0.dump").exists(), "only the chosen boxes are dumped");
}

#[test]
fn dump_points_must_name_points_of_md_bodies() {
    use orchestrator::scene;
    let md_small = repo().join("tests/data/md-small.toml");
    let err = |path: &Path, sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        scene::load(path, &sets).expect_err("must be refused").to_string()
    };
    let e = err(&md_small, &["output.dump_points=[2, 6]"]);
    for part in [
        "md-small.toml",
        "--set output.dump_points=[2, 6]",
        "`output.dump_points[1]` = 6",
        "no such material point",
        "ids 0..=5",
        "0..=2 (body `left`)",
        "3..=5 (body `right`)",
    ] {
        assert!(e.contains(part), "{e:?} lacks {part:?}");
    }
    let e = err(&md_small, &["output.dump_points=[3, 3]"]);
    assert!(e.contains("`output.dump_points[1]` = 3") && e.contains("listed twice"), "{e}");
    // In the file: the line is named. A gas body has no boxes.
    let tmp = tempfile::tempdir().expect("tempdir");
    let gas = tmp.path().join("gas.toml");
    let text = mscale_tests::small_scene();
    assert!(text.contains("[output]\n"), "test bug: the small scene has no [output] table");
    std::fs::write(&gas, text.replacen("[output]\n", "[output]\ndump_points = [0]\n", 1)).expect("write");
    let e = err(&gas, &[]);
    assert!(
        e.contains("gas.toml, line ")
            && e.contains("`output.dump_points[0]` = 0")
            && e.contains("which has no MD box")
            && e.contains("the scene has no md body"),
        "{e}"
    );
    assert!(scene::load(&md_small, &["output.dump_points=[0, 5]".to_string()]).is_ok());
}

#[test]
fn two_md_bodies_make_one_pool_call_per_step_and_exact_reuse_changes_no_bit() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let off = run_small(&tmp.path().join("off"), &[], None);
    let s = mscale_tests::summary(&off);
    assert_eq!(s["steps"], 5, "{s}");
    assert_eq!(s["md"]["pool_calls"], 5, "one call per continuum step for both bodies: {}", s["md"]);
    let d = &s["md"]["diagnostics"];
    assert!(d["max_strain_rate_per_s"].as_f64().expect("strain rate") > 0.0, "{d}");
    let ratio = d["min_box_length_over_cutoff"].as_f64().expect("box length");
    assert!(ratio > 1.0 && ratio < 2.0, "2x2x2-cell boxes of Cu (7.2 A) over Mishin's 5.5 A cut-off: {d}");
    assert!(d["max_neighbor_rebuilds_per_call"].as_u64().is_some(), "{d}");
    // The hottest box over the run is at least as hot as the hottest box at its end.
    let csv = std::fs::read_to_string(off.join("particles_final.csv")).expect("csv");
    let col = csv.lines().next().expect("header").split(',').position(|c| c == "md_temperature_k").expect("column");
    let at_end = csv.lines().skip(1).map(|l| l.split(',').nth(col).expect("cell").parse::<f64>().expect("number")).fold(0.0, f64::max);
    let hottest = d["max_box_temperature_k"].as_f64().expect("temperature");
    assert!(at_end > 0.0 && hottest >= at_end, "hottest {hottest} K, {at_end} K at the end: {d}");
    assert!(d["hottest_box_point"].as_u64().expect("point") < s["points"].as_u64().expect("points"), "{d}");
    assert_eq!(s["md"]["atom_steps_avoided"], 0.0, "{}", s["md"]);
    let exact = ["bodies.left.material.reuse=\"exact\"", "bodies.right.material.reuse=\"exact\""];
    let ex = run_small(&tmp.path().join("exact"), &exact, None);
    assert_eq!(digest(&ex), digest(&off), "exact reuse changed the run");
    let s = mscale_tests::summary(&ex);
    // The books add up. (Here the boxes' work differs from the first step on: walls, the 50 K
    // body and signed zeros of the velocity gradients; the pool's unit test shows the sharing.)
    for body in ["left", "right"] {
        let b = &s["md"]["bodies"][body];
        let f = |k: &str| b[k].as_f64().expect("number");
        assert_eq!(f("atom_steps_done") + f("atom_steps_avoided"), f("atom_steps_requested"), "{b}");
        assert_eq!(f("avoided_by_tolerance"), 0.0, "{b}");
    }
    assert!(std::fs::read_to_string(ex.join("scene.resolved.toml")).expect("resolved").contains("reuse = \"exact\""));
    // The tolerance mode skips boxes, and runs to the end; a zero tolerance never skips.
    let tol = ["bodies.left.material.reuse={ tolerance = 0.0 }", "bodies.right.material.reuse={ tolerance = 0.0 }"];
    assert_eq!(digest(&run_small(&tmp.path().join("tol0"), &tol, None)), digest(&off), "a zero tolerance skipped a box");
    let tol = ["bodies.left.material.reuse={ tolerance = 0.5, max_interval = 3 }", "bodies.right.material.reuse={ tolerance = 0.5 }"];
    let t = mscale_tests::summary(&run_small(&tmp.path().join("tol"), &tol, None));
    assert_eq!(t["status"], "completed", "{t}");
    assert!(t["md"]["avoided_by_tolerance"].as_f64().expect("avoided") > 0.0, "{}", t["md"]);
}
