//! The `mscale` binary end to end: outputs of a run, exit codes, messages.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn mscale(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mscale")).args(args).current_dir(repo()).env("RUST_LOG", "warn").output().expect("run mscale")
}

fn small() -> String {
    repo().join("tests/data/small.toml").display().to_string()
}

fn text(o: &[u8]) -> String {
    String::from_utf8_lossy(o).into_owned()
}

fn summary(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).expect("summary.json")).expect("summary is JSON")
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).expect("dir").flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn run_writes_every_output() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let o = mscale(&["run", &small(), "--out", out.to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let s = summary(&out);
    assert_eq!(s["status"], "completed");
    assert_eq!(s["steps"], 25);
    for key in ["wall_seconds", "simulated_time_s", "time_breakdown_s", "provenance", "command_line", "state_digest", "conservation"] {
        assert!(!s[key].is_null(), "summary lacks {key}");
    }
    assert_eq!(s["conservation"]["mass_drift"], 0.0);
    assert!(s["conservation"]["momentum_drift"].as_f64().expect("number") < 1e-9, "{}", s["conservation"]);
    let e = &s["errors"];
    assert_eq!(e["reference"], "isothermal-riemann");
    let l1 = e["pressure_l1"].as_f64().expect("number");
    assert!(l1 > 0.0 && l1 < 0.2, "pressure L1 {l1}");
    assert_eq!(s["provenance"]["inputs"].as_object().expect("map").len(), 1);
    assert_eq!(s["state_digest"].as_str().expect("digest").len(), 64);

    let resolved = std::fs::read_to_string(out.join("scene.resolved.toml")).expect("resolved");
    assert!(resolved.contains("timestep = 0.004") && resolved.contains("viscosity_coefficient"), "{resolved}");

    let index = std::fs::read_to_string(out.join("snapshots/index.csv")).expect("index");
    let mut lines = index.lines();
    assert_eq!(lines.next(), Some("step,time,file"));
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), 4, "initial, two in between (snapshots = 2), final: {index}");
    for row in rows {
        let file = row.split(',').nth(2).expect("file column");
        assert!(out.join("snapshots").join(file).is_file(), "{file} listed but missing");
    }
    let csv = std::fs::read_to_string(out.join("particles_final.csv")).expect("final csv");
    let header = csv.lines().next().expect("header");
    assert_eq!(header, "id,x0,x,vx,mass,volume,density,pressure,sxx,syy,szz,sxy,sxz,syz");
    assert_eq!(csv.lines().count(), 1 + 50 * 4);
    assert!(!csv.contains("NaN") && !csv.contains("inf"));

    let pvd = std::fs::read_to_string(out.join("vtk/particles.pvd")).expect("pvd");
    assert_eq!(pvd.matches("<DataSet").count(), 4);
    let vtu = std::fs::read_to_string(out.join("vtk/particles_00000025.vtu")).expect("vtu");
    assert!(vtu.contains("NumberOfPoints=\"200\"") && vtu.contains("Name=\"pressure\""));
    for plot in ["pressure", "velocity", "density"] {
        let png = std::fs::read(out.join(format!("plots/{plot}.png"))).expect("png");
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    }
    // No temporary file is left behind by the atomic writes.
    let leftovers: Vec<_> =
        walk(&out).into_iter().filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().contains(".tmp"))).collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn same_scene_gives_the_same_digest_and_overrides_change_it() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = small();
    let digest = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut args = vec!["run", scene.as_str(), "--out", out.to_str().expect("utf8")];
        args.extend_from_slice(extra);
        let o = mscale(&args);
        assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
        summary(&out)["state_digest"].as_str().expect("digest").to_string()
    };
    let a = digest("a", &[]);
    let b = digest("b", &[]);
    let c = digest("c", &["--set", "bodies.left.density=1.2"]);
    assert_eq!(a, b);
    assert_ne!(a, c);
}

#[test]
fn check_prints_the_resolved_scene_and_the_work() {
    let o = mscale(&["check", &small(), "--set", "scheme.particles_per_cell=2"]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let s = text(&o.stdout);
    assert!(s.contains("particles_per_cell = 2"), "{s}");
    assert!(s.contains("# points = 100") && s.contains("# grid_nodes = 51") && s.contains("# steps = 25"), "{s}");
}

#[test]
fn bad_input_exits_2_with_a_message_and_no_panic() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bad = tmp.path().join("bad.toml");
    std::fs::write(&bad, std::fs::read_to_string(small()).expect("small").replace("cfl = 0.2", "cfl = 3.0")).expect("write");
    for args in [vec!["run", bad.to_str().expect("utf8")], vec!["check", bad.to_str().expect("utf8")]] {
        let o = mscale(&args);
        assert_eq!(o.status.code(), Some(2));
        let err = text(&o.stderr);
        assert!(err.contains("bad.toml, line 28: `scheme.cfl` = 3"), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let o = mscale(&["run", "no/such/scene.toml"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o.stderr).contains("cannot read the scene file"));
    let o = mscale(&["frobnicate"]);
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn a_run_stopped_by_the_guard_exits_1_and_keeps_its_outputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    // The right body flies out through a free face: the guard stops the run.
    let o = mscale(&[
        "run",
        &small(),
        "--out",
        out.to_str().expect("utf8"),
        "--set",
        "boundary.x_max=\"free\"",
        "--set",
        "bodies.right.velocity=[30.0]",
        "--set",
        "scheme.end_time=1.0",
    ]);
    assert_eq!(o.status.code(), Some(1), "stderr: {}", text(&o.stderr));
    let err = text(&o.stderr);
    assert!(err.contains("left the grid along axis 0") && err.contains("likely cause"), "{err}");
    let s = summary(&out);
    assert_eq!(s["status"], "failed");
    assert!(s["error"].as_str().expect("error").contains("left the grid"));
    assert!(out.join("particles_final.csv").is_file());
    assert!(out.join("snapshots/index.csv").is_file());
}

#[test]
fn report_error_vs_time_runs_every_combination() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("rep");
    let o = mscale(&[
        "report",
        "error-vs-time",
        &small(),
        "--sweep",
        "scheme.method=mpm,ugimp",
        "--sweep",
        "scheme.particles_per_cell=2,4",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("report.csv")).expect("report.csv");
    let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
    assert_eq!(rows[0][..5], ["scheme.method", "scheme.particles_per_cell", "method", "status", "pressure_l1"]);
    assert_eq!(rows.len(), 5);
    let combos: Vec<(&str, &str)> = rows[1..].iter().map(|r| (r[0], r[1])).collect();
    assert_eq!(combos, [("mpm", "2"), ("mpm", "4"), ("ugimp", "2"), ("ugimp", "4")]);
    for r in &rows[1..] {
        assert_eq!(r[3], "completed");
        let l1: f64 = r[4].parse().expect("l1");
        assert!(l1 > 0.0);
        let evaluations: u64 = r[10].parse().expect("evaluations");
        let ppc: u64 = r[1].parse().expect("ppc");
        assert_eq!(evaluations, 25 * 50 * ppc, "closure evaluations = steps x points");
    }
    assert_eq!(&std::fs::read(out.join("report.png")).expect("png")[..4], b"\x89PNG");
    // A bad sweep value is refused before anything runs.
    let o = mscale(&["report", "error-vs-time", &small(), "--sweep", "scheme.cfl=0.5,7", "--out", out.join("bad").to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o.stderr).contains("`scheme.cfl` = 7"), "{}", text(&o.stderr));
    assert!(!out.join("bad").exists());
}

/// The full cell's refinement report: phi and the cumulative charge (eps0/e times the field)
/// fall monotonically against the finest run; p - n is reported but, next to the interfaces,
/// does not converge (the electrons' surface charge sits in one cell: cell/README.md).
#[test]
fn report_error_vs_time_of_the_full_cell_scores_phi_and_the_cumulative_charge() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("rep");
    let scene = repo().join("scenes/pnp-full-cell.toml");
    let o = mscale(&[
        "report",
        "error-vs-time",
        scene.to_str().expect("utf8"),
        "--set",
        "scheme.end_time_s=0.01",
        "--set",
        "output.times_s=[0.0, 0.01]",
        "--sweep",
        "grid.cells=50,100,200,400",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("report.csv")).expect("report.csv");
    let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
    assert_eq!(rows[0][5..], ["phi_l2_error_v", "charge_l2_error_e_per_nm3", "cumulative_charge_l2_error_e_per_nm2"]);
    assert_eq!(rows.len(), 5);
    assert_eq!(rows[4][5..], ["reference", "reference", "reference"]);
    let column = |c: usize| -> Vec<f64> { rows[1..4].iter().map(|r| r[c].parse().expect("number")).collect() };
    for (name, c) in [("phi", 5), ("cumulative charge", 7)] {
        let e = column(c);
        assert!(e.windows(2).all(|w| w[1] < w[0]) && e[2] > 0.0, "{name} errors fall: {e:?}");
    }
    assert!(column(6).iter().all(|e| e.is_finite() && *e > 0.0));
}

#[test]
fn report_error_vs_time_scores_a_heat_series_per_scheme_and_flip_fraction() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("rep");
    let scene = repo().join("scenes/heat-1d.toml");
    let o = mscale(&[
        "report",
        "error-vs-time",
        scene.to_str().expect("utf8"),
        "--set",
        "scheme.end_time=0.005",
        "--sweep",
        "scheme.method=mpm,ugimp",
        "--sweep",
        "diffusion.flip_fraction=1,0.99",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("report.csv")).expect("report.csv");
    let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
    let col = |name: &str| rows[0].iter().position(|c| *c == name).unwrap_or_else(|| panic!("no column {name} in {:?}", rows[0]));
    assert_eq!(rows.len(), 5);
    let num = |r: &[&str], name: &str| -> f64 { r[col(name)].parse().unwrap_or_else(|_| panic!("{name} of {r:?}")) };
    for r in &rows[1..] {
        assert_eq!(r[col("status")], "completed");
        assert_eq!(num(r, "flip_fraction"), num(r, "diffusion.flip_fraction"));
        assert_eq!(r[col("dirichlet")], "rate");
        assert!((num(r, "end_time") - 0.005).abs() < 1e-12, "{r:?}");
        for q in ["rms_points", "rms_nodes", "rms_interior_nodes"] {
            let e = num(r, q);
            assert!(e > 0.0 && e < 0.5, "{q} = {e} in {r:?}");
        }
    }
    // Table 6.1's first row (GIMP, t = 0.005): beta = 1 gives 0.0375 at the points, beta = 0.99
    // more (0.0534): the report carries the thesis's columns.
    let ugimp_1 = rows.iter().find(|r| r[0] == "ugimp" && r[1] == "1").expect("ugimp beta 1");
    let ugimp_99 = rows.iter().find(|r| r[0] == "ugimp" && r[1] == "0.99").expect("ugimp beta 0.99");
    assert!((num(ugimp_1, "rms_points") - 0.0375).abs() < 5e-4, "{ugimp_1:?}");
    assert!((num(ugimp_99, "rms_points") - 0.0534).abs() < 5e-4, "{ugimp_99:?}");
    assert_eq!(&std::fs::read(out.join("report.png")).expect("png")[..4], b"\x89PNG");
}

/// IMPM's MLS density and stress at the cell centres need at least two distinct points in a
/// centre's support: on the strong tube the density-1 gas spreads to one point per 1.5 cells
/// next to the contact, and the run stops naming that cell centre, its position and the
/// remedy (continuum/docs/error-vs-time: stopped at step 34-39 at every resolution).
#[test]
fn impm_on_the_strong_tube_is_stopped_naming_the_cell_centre() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = repo().join("scenes/shock-tube-strong.toml");
    let o = mscale(&[
        "run",
        scene.to_str().expect("utf8"),
        "--set",
        "scheme.method=impm",
        "--set",
        "scheme.integrator=leapfrog",
        "--set",
        "scheme.sub_points=1",
        "--set",
        "domain.cells=[125]",
        "--out",
        tmp.path().join("run").to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(1), "stderr: {}", text(&o.stderr));
    let err = text(&o.stderr);
    for want in ["the moment matrix at cell centre ", "(x = [", "is singular: 1 point(s) in its support", "Use more particles per cell"] {
        assert!(err.contains(want), "{want:?} not in {err}");
    }
    assert_eq!(summary(&tmp.path().join("run"))["status"], "failed");
}

#[test]
fn report_scores_against_a_direct_md_reference() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("rep");
    let scene = repo().join("scenes/cu-shock-1d-elastic.toml");
    let reference = repo().join("tests/golden/cu-shock-1d/direct-bar.csv");
    let (scene, reference) = (scene.to_str().expect("utf8"), reference.to_str().expect("utf8"));
    let args = |extra: &[&str], dir: &str| -> Vec<String> {
        // The twin as this test was written for: dhakal, the interface at 51.11 nm.
        let pinned =
            ["--set", "scheme.integrator=dhakal", "--set", "bodies.compressed.max=[51.11e-9]", "--set", "bodies.relaxed.min=[51.11e-9]"];
        let mut a: Vec<String> = ["report", "error-vs-time", scene, "--set", "scheme.timestep=0.05e-12", "--sweep", "domain.cells=[60]"]
            .iter()
            .chain(&pinned)
            .map(|s| s.to_string())
            .collect();
        a.extend(extra.iter().map(|s| s.to_string()));
        a.extend(["--out".to_string(), out.join(dir).to_str().expect("utf8").to_string()]);
        a
    };
    let run = |extra: &[&str], dir: &str| {
        let a = args(extra, dir);
        mscale(&a.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let o = run(&["--reference", reference, "--reference-times", "5,10"], "ok");
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("ok/report.csv")).expect("report.csv");
    let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
    let col = |name: &str| rows[0].iter().position(|c| *c == name).unwrap_or_else(|| panic!("no column {name} in {:?}", rows[0]));
    let e5: f64 = rows[1][col("sxx_error_5ps")].parse().expect("e5");
    let e10: f64 = rows[1][col("sxx_error_10ps")].parse().expect("e10");
    // The linear elastic twin at 60 cells: 14.99 % and 19.20 % (scripts/compare_direct.py
    // gives the same on this run directory).
    assert!((e5 - 0.1499).abs() < 2e-3 && (e10 - 0.1920).abs() < 2e-3, "{e5} {e10}");
    assert_eq!(rows[1][col("scored_points")], "58");
    assert_eq!(rows[1][col("md_atom_steps")], "0e0");
    let index = std::fs::read_to_string(out.join("ok/runs/000/snapshots/index.csv")).expect("index");
    assert_eq!(index.lines().count(), 4, "snapshots at 0, 5 and 10 ps: {index}");
    // Refused before anything runs, with the reason.
    for (extra, needle) in [
        (vec!["--reference", reference, "--reference-times", "7.25"], "no rows at t = 7.25 ps"),
        (
            vec!["--reference", reference, "--reference-times", "5", "--set", "scheme.timestep=0.3e-12"],
            "not a whole number of continuum steps",
        ),
        (vec!["--reference", reference, "--reference-times", "10", "--set", "scheme.end_time=8e-12"], "after the end time"),
        (vec!["--reference", "/nonexistent.csv", "--reference-times", "5"], "/nonexistent.csv"),
        (vec!["--reference-times", "5"], "--reference"),
    ] {
        let o = run(&extra, "bad");
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {}", text(&o.stderr));
        assert!(text(&o.stderr).contains(needle), "{extra:?}: {}", text(&o.stderr));
        assert!(!out.join("bad").exists());
    }
}

#[test]
fn a_run_with_a_direct_md_reference_scores_itself() {
    // The elastic twin at the settings of `report_scores_against_a_direct_md_reference` (60
    // cells, dhakal, 0.05 ps, the interface at 51.11 nm): `mscale run` writes the same eq. 7.12
    // errors into summary.json (one implementation) and prints them in its last log line.
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let scene = repo().join("scenes/cu-shock-1d-elastic.toml");
    let sets = [
        "domain.cells=[60]",
        "scheme.timestep=0.05e-12",
        "scheme.integrator=dhakal",
        "bodies.compressed.max=[51.11e-9]",
        "bodies.relaxed.min=[51.11e-9]",
        // Snapshots every 66 steps: 5 and 10 ps (steps 100 and 200) are not among them, the run
        // adds them.
        "output.snapshots=3",
        "output.vtk=false",
        "output.plots=false",
    ];
    let mut args: Vec<String> =
        vec!["run".into(), scene.to_str().expect("utf8").into(), "--out".into(), out.to_str().expect("utf8").into()];
    for s in sets {
        args.extend(["--set".to_string(), s.to_string()]);
    }
    let o =
        Command::new(env!("CARGO_BIN_EXE_mscale")).args(&args).current_dir(repo()).env("RUST_LOG", "info").output().expect("run mscale");
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let s = summary(&out);
    let e = &s["errors"];
    assert_eq!(e["reference"], "direct-md", "{e}");
    assert_eq!(e["component"], "sxx");
    assert!(e["profile"].as_str().expect("profile").ends_with("tests/golden/cu-shock-1d/direct-bar.csv"), "{e}");
    let (e5, e10) = (e["sxx_error_5ps"].as_f64().expect("5 ps"), e["sxx_error_10ps"].as_f64().expect("10 ps"));
    assert!((e5 - 0.1499).abs() < 2e-3 && (e10 - 0.1920).abs() < 2e-3, "{e5} {e10}");
    let times = e["times"].as_array().expect("times");
    assert_eq!(times.len(), 2);
    for (t, step) in [(5.0, 100), (10.0, 200)] {
        let row = times.iter().find(|r| r["time_ps"] == t).unwrap_or_else(|| panic!("no score at {t} ps: {e}"));
        assert_eq!(row["snapshot_step"], step, "{row}");
        assert_eq!(row["snapshot_time_ps"], t, "{row}");
        assert_eq!(row["points"], 58, "{row}");
    }
    let index = std::fs::read_to_string(out.join("snapshots/index.csv")).expect("index");
    let steps: Vec<&str> = index.lines().skip(1).map(|l| l.split(',').next().expect("step")).collect();
    assert_eq!(steps, ["0", "66", "100", "132", "198", "200"], "{index}");
    assert!(!text(&o.stdout).contains("NaN") && !text(&o.stdout).contains("pressure error"), "{}", text(&o.stdout));
    // The last log line carries the errors.
    let log = text(&o.stderr);
    let last = log.lines().last().expect("a log line");
    assert!(
        last.contains("eq. 7.12 error of sxx against direct MD")
            && last.contains(&format!("{:.2} % at 5 ps", 100.0 * e5))
            && last.contains(&format!("{:.2} % at 10 ps", 100.0 * e10)),
        "{last}"
    );
    // The resolved scene reads back with its reference (the profile made absolute).
    let o = mscale(&["check", out.join("scene.resolved.toml").to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains("solution = \"direct-md\""), "{}", text(&o.stdout));
    // `mscale report score` scores the finished run again by the same code: the same errors, and
    // a time the run never reached (or the reference lacks) is refused by name.
    let run_dir = out.to_str().expect("utf8");
    let o = mscale(&["report", "score", run_dir]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    let printed = text(&o.stdout);
    assert!(printed.lines().next().expect("a line").contains(&format!("{:.2} % at 5 ps", 100.0 * e5)), "{printed}");
    let again: serde_json::Value = serde_json::from_str(printed.split_once('\n').expect("json").1).expect("json");
    assert_eq!(again["sxx_error_10ps"], e["sxx_error_10ps"], "{again}");
    let o = mscale(&["report", "score", run_dir, "--set", "reference.times_ps=[5.0]"]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    assert!(!text(&o.stdout).contains("10 ps"), "{}", text(&o.stdout));
    let o = mscale(&["report", "score", run_dir, "--set", "reference.times_ps=[5.0,20.0]"]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o.stdout));
    assert!(text(&o.stderr).contains("reference.times_ps"), "{}", text(&o.stderr));
}

/// Issue 18: an implicit run past the explicit CFL bound reports Newton iterations per step and
/// accepted/rejected steps in summary.json; a set-up it cannot run exits 2 naming the key.
#[test]
fn an_implicit_run_reports_its_newton_iterations() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let implicit = "scheme.integrator=\"implicit-trapezoidal\"";
    let o = mscale(&[
        "run",
        &small(),
        "--out",
        out.to_str().expect("utf8"),
        "--set",
        implicit,
        "--set",
        "scheme.artificial_viscosity=\"none\"",
        "--set",
        "scheme.cfl=2.0",
    ]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    let s = summary(&out);
    let st = &s["implicit"];
    assert_eq!(st["accepted_steps"], s["steps"], "{st}");
    assert_eq!(st["rejected_steps"], 0);
    let per_step = st["newton_iterations_per_step"].as_f64().expect("iterations per step");
    assert!((1.0..=5.0).contains(&per_step), "{st}");
    assert!(st["seconds_per_newton_iteration"].as_f64().expect("timing") > 0.0);
    assert!(s["conservation"]["mass_drift"].as_f64().expect("mass") < 1e-12);
    // Explicit runs keep their summary keys.
    let o = mscale(&["run", &small(), "--out", tmp.path().join("explicit").to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", text(&o.stderr));
    assert!(summary(&tmp.path().join("explicit")).get("implicit").is_none());
    let o = mscale(&["check", &small(), "--set", implicit]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o.stderr).contains("needs scheme.artificial_viscosity = \"none\""), "{}", text(&o.stderr));
}
