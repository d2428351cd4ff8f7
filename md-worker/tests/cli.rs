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
    let out = md_worker(&["eval", "--potential", "potentials/Cu_u3.eam", "--data", "tests/golden/cu256_hot.data", "--forces", forces.to_str().unwrap()]);
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
        "run", "--potential", "potentials/Cu_mishin1.eam.alloy", "--data", "tests/golden/cu108_hot.data", "--steps", "20",
        "--dt", "0.001", "--thermo", "10", "--velocity-gradient", "xx=0.01,xy=0.02", "--remap", "seed", "--dump", dump.to_str().unwrap(),
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
    let out = md_worker(&["run", "--potential", "potentials/Cu_u3.eam", "--data", "tests/golden/cu108_hot.data", "--steps", "1", "--dt", "0.001", "--velocity-gradient", "xq=1"]);
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
        "direct", "--potential", "potentials/Cu_mishin1.eam.alloy", "--a0", "3.615", "--cells", "8,2,2", "--orient", "1,1,0/-1,1,0/0,0,1",
        "--region", "0:20:-0.02", "--steps", "4", "--dt", "0.001", "--every", "2", "--slab", "10.2", "--out", csv.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&csv).unwrap();
    let times: std::collections::BTreeSet<String> = text.lines().filter(|l| !l.starts_with('#') && !l.starts_with("time")).map(|l| l.split(',').next().unwrap().to_string()).collect();
    assert_eq!(times.len(), 3, "{text}");
    let out = md_worker(&["direct", "--potential", "potentials/Cu_mishin1.eam.alloy", "--a0", "3.615", "--cells", "8,2", "--steps", "1", "--out", csv.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--cells NX,NY,NZ"), "{}", String::from_utf8_lossy(&out.stderr));
}
