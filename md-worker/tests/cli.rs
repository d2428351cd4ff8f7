//! The `md-worker` binary: eval against LAMMPS golden values, run output, bad input exits 2.
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use std::process::Command;

fn md_worker(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_md-worker")).args(args).current_dir(crate_dir()).output().unwrap()
}

#[test]
fn eval_matches_lammps_and_writes_forces() {
    let dir = tempfile::tempdir().unwrap();
    let forces = dir.path().join("f.txt");
    let out = md_worker(&[
        "eval",
        "--potential",
        "potentials/Cu_u3.eam",
        "--data",
        "tests/golden/cu256_hot.data",
        "--forces",
        forces.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let g = golden("eval_u3_cu256_hot.golden");
    let e = v["energy_ev"].as_f64().unwrap();
    assert!(rel_close(e, g.thermo[0][1], g.thermo[0][1], 1e-9), "{e}");
    let sxx = v["stress_gpa"]["xx"].as_f64().unwrap();
    assert!(rel_close(sxx, bar_to_stress(g.thermo[0][3]), sxx, 1e-9), "{sxx}");
    let f = std::fs::read_to_string(&forces).unwrap();
    assert_eq!(f.lines().filter(|l| !l.starts_with('#')).count(), 256);
}

#[test]
fn run_prints_one_line_per_thermo_interval_and_dumps() {
    let dir = tempfile::tempdir().unwrap();
    let dump = dir.path().join("d.dump");
    let out = md_worker(&[
        "run",
        "--potential",
        "potentials/Cu_mishin1.eam.alloy",
        "--data",
        "tests/golden/cu108_hot.data",
        "--steps",
        "20",
        "--dt",
        "0.001",
        "--thermo",
        "10",
        "--velocity-gradient",
        "xx=0.01,xy=0.02",
        "--remap",
        "seed",
        "--dump",
        dump.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.iter().map(|l| l["step"].as_u64().unwrap()).collect::<Vec<_>>(), vec![0, 10, 20]);
    let d = std::fs::read_to_string(&dump).unwrap();
    assert_eq!(d.matches("ITEM: TIMESTEP").count(), 3);
}

#[test]
fn bad_input_exits_2_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let trunc = dir.path().join("trunc.eam");
    let text = std::fs::read_to_string(crate_dir().join("potentials/Cu_u3.eam")).unwrap();
    std::fs::write(&trunc, &text[..2000]).unwrap();
    let out = md_worker(&["eval", "--potential", trunc.to_str().unwrap(), "--data", "tests/golden/cu108_hot.data"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("trunc.eam:") && err.contains("F(rho)"), "{err}");
    let out = md_worker(&[
        "run",
        "--potential",
        "potentials/Cu_u3.eam",
        "--data",
        "tests/golden/cu108_hot.data",
        "--steps",
        "1",
        "--dt",
        "0.001",
        "--velocity-gradient",
        "xq=1",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let out = md_worker(&["eval", "--potential", "potentials/Cu_u3.eam", "--data", "no-such.data"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such.data"));
}

#[test]
fn direct_takes_the_documented_comma_lists_and_writes_slab_stresses() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("bar.csv");
    // The form of tests/golden/cu-shock-1d/README.md, on a small oriented bar.
    let out = md_worker(&[
        "direct",
        "--potential",
        "potentials/Cu_mishin1.eam.alloy",
        "--a0",
        "3.615",
        "--cells",
        "8,2,2",
        "--orient",
        "1,1,0/-1,1,0/0,0,1",
        "--region",
        "0:20:-0.02",
        "--steps",
        "4",
        "--dt",
        "0.001",
        "--every",
        "2",
        "--slab",
        "10.2",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&csv).unwrap();
    let times: std::collections::BTreeSet<String> =
        text.lines().filter(|l| !l.starts_with('#') && !l.starts_with("time")).map(|l| l.split(',').next().unwrap().to_string()).collect();
    assert_eq!(times.len(), 3, "{text}");
    let out = md_worker(&[
        "direct",
        "--potential",
        "potentials/Cu_mishin1.eam.alloy",
        "--a0",
        "3.615",
        "--cells",
        "8,2",
        "--steps",
        "1",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--cells NX,NY,NZ"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// `md_worker` with a time limit: a hang fails the test instead of stalling it.
fn md_worker_within(secs: u64, args: &[&str]) -> std::process::Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_md-worker"))
        .args(args)
        .current_dir(crate_dir())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed().as_secs() > secs {
            child.kill().unwrap();
            panic!("md-worker {args:?} still running after {secs} s");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// cu108_hot.data with the x coordinate of atom 1 replaced by `x`, in `dir`.
fn data_with_atom1_x(dir: &std::path::Path, x: &str) -> String {
    let text = std::fs::read_to_string(crate_dir().join("tests/golden/cu108_hot.data")).unwrap();
    let line = text.lines().find(|l| l.starts_with("1 1 ")).unwrap();
    let mut w: Vec<&str> = line.split_whitespace().collect();
    w[2] = x;
    let path = dir.join(format!("atom1_x_{x}.data"));
    std::fs::write(&path, text.replacen(line, &w.join(" "), 1)).unwrap();
    path.to_str().unwrap().to_string()
}

fn stderr_of(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).to_string()
}

#[test]
fn eval_of_an_atom_at_x_1e308_is_refused_not_a_hang() {
    let dir = tempfile::tempdir().unwrap();
    let data = data_with_atom1_x(dir.path(), "1e308");
    let out = md_worker_within(60, &["eval", "--potential", "potentials/Cu_u3.eam", "--data", &data]);
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("atom 1") && err.contains("x = 1e308") && err.contains("box lengths outside"), "{err}");
    assert!(err.contains(&format!("{data}:16")), "names the file and line: {err}");
    assert!(out.stdout.is_empty(), "no energy printed");
}

#[test]
fn eval_of_an_atom_at_x_nan_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for bad in ["NaN", "nan", "inf", "-inf"] {
        let data = data_with_atom1_x(dir.path(), bad);
        let out = md_worker_within(60, &["eval", "--potential", "potentials/Cu_u3.eam", "--data", &data]);
        let err = stderr_of(&out);
        assert_eq!(out.status.code(), Some(2), "{bad}: {err}");
        assert!(err.contains("x of atom 1") && err.contains("is not a finite number"), "{bad}: {err}");
        assert!(out.stdout.is_empty(), "{bad}: no energy printed");
    }
}

#[test]
fn eval_wraps_an_atom_a_few_box_lengths_out_to_the_same_energy() {
    // Atom 1 moved by +3 box lengths (10.8 A each): bounded, so wrapped in, same energy.
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(crate_dir().join("tests/golden/cu108_hot.data")).unwrap();
    let line = text.lines().find(|l| l.starts_with("1 1 ")).unwrap();
    let x: f64 = line.split_whitespace().nth(2).unwrap().parse().unwrap();
    let data = data_with_atom1_x(dir.path(), &format!("{:e}", x + 3.0 * 10.8));
    let e = |data: &str| {
        let out = md_worker_within(60, &["eval", "--potential", "potentials/Cu_u3.eam", "--data", data]);
        assert!(out.status.success(), "{}", stderr_of(&out));
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        v["energy_ev"].as_f64().unwrap()
    };
    let (moved, orig) = (e(&data), e("tests/golden/cu108_hot.data"));
    assert!((moved - orig).abs() < 1e-9 * orig.abs(), "{moved} vs {orig}");
}

#[test]
fn run_with_a_5_ps_time_step_is_refused_naming_the_bound() {
    let out = md_worker_within(
        60,
        &["run", "--potential", "potentials/Cu_mishin1.eam.alloy", "--data", "tests/golden/cu108_hot.data", "--steps", "100", "--dt", "5"],
    );
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("time step 5 ps exceeds") && err.contains("vibration period") && err.contains("point 0"), "{err}");
    assert!(out.stdout.is_empty(), "nothing run: {}", String::from_utf8_lossy(&out.stdout));
}

#[test]
fn run_with_a_velocity_gradient_of_1e6_is_refused() {
    for remap in ["affine", "seed"] {
        let out = md_worker_within(
            60,
            &[
                "run",
                "--potential",
                "potentials/Cu_mishin1.eam.alloy",
                "--data",
                "tests/golden/cu108_hot.data",
                "--steps",
                "10",
                "--dt",
                "0.001",
                "--velocity-gradient",
                "xx=1e6",
                "--remap",
                remap,
            ],
        );
        let err = stderr_of(&out);
        assert_eq!(out.status.code(), Some(2), "{remap}: {err}");
        assert!(err.contains("velocity gradient xx = 1000000 1/ps") && err.contains("point 0"), "{remap}: {err}");
    }
    // Under the per-step bound but a box stretched by e^5 in one call of 1000 steps.
    let out = md_worker_within(
        60,
        &[
            "run",
            "--potential",
            "potentials/Cu_mishin1.eam.alloy",
            "--data",
            "tests/golden/cu108_hot.data",
            "--steps",
            "1000",
            "--dt",
            "0.001",
            "--velocity-gradient",
            "yy=-5",
            "--thermo",
            "1000",
        ],
    );
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("yy = -5 1/ps over 1000 steps") && err.contains("factor 2"), "{err}");
}

#[test]
fn run_of_a_runaway_atom_is_stopped_by_the_md_guard_with_exit_1() {
    // Atom 5 given 3000 A/ps (300 km/s, 2.9e4 eV): input the parser accepts, a box the MD
    // guard stops at its first step with the diagnosis.
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(crate_dir().join("tests/golden/cu108_hot.data")).unwrap();
    let (head, vels) = text.split_at(text.find("Velocities").unwrap());
    let line = vels.lines().find(|l| l.starts_with("5 ")).unwrap();
    let data = dir.path().join("runaway.data");
    std::fs::write(&data, format!("{head}{}", vels.replacen(line, "5 3000 0 0", 1))).unwrap();
    let out = md_worker_within(
        60,
        &["run", "--potential", "potentials/Cu_mishin1.eam.alloy", "--data", data.to_str().unwrap(), "--steps", "10", "--dt", "0.001"],
    );
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("point 0: MD diverged: at step 1: atom 4 (index from 0) has a kinetic energy of") && err.contains("energy blow-up"),
        "{err}"
    );
}

#[test]
fn eval_of_two_atoms_at_one_place_is_refused() {
    // Atom 1 put on atom 2: an infinite energy, refused as input rather than printed.
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(crate_dir().join("tests/golden/cu108_hot.data")).unwrap();
    let l1 = text.lines().find(|l| l.starts_with("1 1 ")).unwrap();
    let l2 = text.lines().find(|l| l.starts_with("2 1 ")).unwrap();
    let data = dir.path().join("overlap.data");
    std::fs::write(&data, text.replacen(l1, &l2.replacen("2 1 ", "1 1 ", 1), 1)).unwrap();
    let out = md_worker_within(60, &["eval", "--potential", "potentials/Cu_u3.eam", "--data", data.to_str().unwrap()]);
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("point 0") && err.contains("atoms overlap"), "{err}");
    assert!(out.stdout.is_empty());
}

#[test]
fn direct_gives_the_same_bytes_for_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    // 32 x 3 x 3 cells (1,152 atoms, 5 blocks of the threaded kernel, the last one short), hot,
    // pre-compressed.
    let run = |threads: &str| {
        let csv = dir.path().join(format!("bar-{threads}.csv"));
        let out = md_worker(&[
            "direct",
            "--potential",
            "potentials/Cu_mishin1.eam.alloy",
            "--a0",
            "3.615",
            "--cells",
            "32,3,3",
            "--region",
            "0:57.84:-0.03",
            "--temperature",
            "300",
            "--steps",
            "40",
            "--every",
            "20",
            "--slab",
            "7.23",
            "--threads",
            threads,
            "--out",
            csv.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        (std::fs::read(&csv).unwrap(), out.stderr)
    };
    let one = run("1");
    assert!(one.0.len() > 200, "{}", String::from_utf8_lossy(&one.0));
    for t in ["2", "3"] {
        let got = run(t);
        assert!(got == one, "--threads {t} differs from --threads 1");
    }
}

#[test]
fn serve_on_the_null_device_needs_a_throughput() {
    let out = md_worker_within(60, &["serve", "--listen", "127.0.0.1:0", "--device", "null"]);
    let err = stderr_of(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--device null needs --throughput"), "{err}");
}
