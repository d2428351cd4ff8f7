//! The continuum over MPI ranks (continuum's and orchestrator's cargo feature `mpi`, issue 14
//! stage 1): `mpirun -np N mscale run SCENE` gives the `state_digest` of the single-process run
//! for N = 1, 2, 3 (oversubscribed), on a 1D and a 2D scene and several gradient schemes.
//!
//! Needs an `mscale` built with `--features mpi` (`bash deploy/setup.sh mpi`, then
//! `cargo build -p orchestrator --features mpi --bin mscale`); set `MSCALE_MPI_MSCALE` to that
//! binary. The single-process reference is the same binary without `mpirun` (one rank: no tile
//! exchange is set, the plain code path), and for the schemes pinned in tests/golden/digests.toml
//! also that pinned digest of the default build. Without `MSCALE_REQUIRE_MPI=1` at build time
//! (tests/build.rs) these tests are ignored; with it (CI's mpi step) they run and fail when MPI
//! or the binary is missing. `MSCALE_MPIRUN` overrides the launcher (default `mpirun`).

use mscale_tests::repo;
use std::path::{Path, PathBuf};
use std::process::Command;

fn mpi_mscale() -> PathBuf {
    match std::env::var_os("MSCALE_MPI_MSCALE") {
        Some(p) if !p.is_empty() && Path::new(&p).is_file() => PathBuf::from(p),
        _ => panic!("MSCALE_MPI_MSCALE is unset or not a file: set it to an mscale built with --features mpi (see .ci/run)"),
    }
}

/// Runs `scene` with `set` into a fresh directory under `tmp`, over `ranks` MPI ranks (None: no
/// mpirun), and returns the state_digest of its summary.json.
fn digest(exe: &Path, tmp: &Path, scene: &str, set: &[String], ranks: Option<usize>) -> String {
    let out = tmp.join(format!("{}-{}-{}", scene.replace('/', "_"), set.join(",").replace(['/', '"', '='], "_"), ranks.unwrap_or(0)));
    let scene = repo().join(scene);
    let mut cmd = match ranks {
        Some(n) => {
            let mut c = Command::new(std::env::var("MSCALE_MPIRUN").unwrap_or_else(|_| "mpirun".into()));
            c.args(["--allow-run-as-root", "--oversubscribe", "-np", &n.to_string()]).arg(exe);
            c
        }
        None => Command::new(exe),
    };
    cmd.arg("run").arg(&scene).arg("--out").arg(&out);
    for s in set {
        cmd.args(["--set", s]);
    }
    cmd.current_dir(repo()).env("RUST_LOG", "warn").env("RAYON_NUM_THREADS", "1").env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    let o = cmd.output().expect("run mscale");
    assert_eq!(
        o.status.code(),
        Some(0),
        "{cmd:?}\nstdout: {}\nstderr: {}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary.json")).expect("json");
    assert_eq!(s["status"], "completed", "{s}");
    s["state_digest"].as_str().expect("state_digest").to_string()
}

/// `base`, then `method` ("name" or "name;key=value;..." with the method's own settings).
fn sets(base: &[&str], method: Option<&str>) -> Vec<String> {
    let mut v: Vec<String> = base.iter().map(|s| s.to_string()).collect();
    if let Some(m) = method {
        let mut parts = m.split(';');
        v.push(format!("scheme.method=\"{}\"", parts.next().expect("method")));
        v.extend(parts.map(str::to_string));
    }
    v
}

/// One scene: every scheme's digest over 1, 2 and 3 ranks equals the one-process digest, and
/// the scene's own scheme gives `pinned` (tests/golden/digests.toml). The other schemes run
/// with `extra` appended to `base` (a later `--set` wins).
fn same_digest_over_ranks(scene: &str, base: &[&str], methods: &[&str], extra: &[&str], pinned: &str) {
    let exe = mpi_mscale();
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut methods: Vec<Option<&str>> = methods.iter().map(|m| Some(*m)).collect();
    methods.insert(0, None);
    for m in methods {
        let mut set = sets(base, m);
        if m.is_some() {
            set.extend(extra.iter().map(|s| s.to_string()));
        }
        let one = digest(&exe, tmp.path(), scene, &set, None);
        if m.is_none() {
            assert_eq!(one, pinned, "{scene}: the mpi build's one-process digest differs from the pinned default-build digest");
        }
        for n in 1..=3 {
            let d = digest(&exe, tmp.path(), scene, &set, Some(n));
            assert_eq!(d, one, "{scene} {m:?}: mpirun -np {n} differs from the one-process run");
        }
        eprintln!("{scene} {}: one digest {one} over 1, 2, 3 ranks", m.unwrap_or("(scene's scheme)"));
    }
}

#[test]
#[cfg_attr(
    not(require_mpi),
    ignore = "needs MPI: bash deploy/setup.sh mpi, MSCALE_MPI_MSCALE=<mscale built with --features mpi>; runs with MSCALE_REQUIRE_MPI=1 (CI) or -- --ignored"
)]
fn a_1d_shock_tube_has_one_digest_over_1_2_3_ranks() {
    // tests/golden/digests.toml's shock-tube-weak entry (ddmp-subpoints, 10 steps).
    same_digest_over_ranks(
        "scenes/shock-tube-weak.toml",
        &["scheme.end_time=2e-3", "output.snapshots=0", "output.particles=false", "output.vtk=false", "output.plots=false"],
        &["mpm", "ugimp", "cpgimp", "cpdi", "cpdi1", "cpdi2", "ddmp", "impm;scheme.integrator=\"leapfrog\"", "cpdi-improved"],
        // The scene's 16 sub-points are ddmp-subpoints' only.
        &["scheme.sub_points=1"],
        "be47117a901fadf612bc199660357700bbb301ce431937378c343839156a694b",
    );
}

#[test]
#[cfg_attr(
    not(require_mpi),
    ignore = "needs MPI: bash deploy/setup.sh mpi, MSCALE_MPI_MSCALE=<mscale built with --features mpi>; runs with MSCALE_REQUIRE_MPI=1 (CI) or -- --ignored"
)]
fn a_2d_manufactured_solution_has_one_digest_over_1_2_3_ranks() {
    // tests/golden/digests.toml's mms-2d entry (cpdi1, 8 x 8 cells, 4 steps).
    same_digest_over_ranks(
        "scenes/mms-2d.toml",
        &[
            "scheme.end_time=0.002",
            "domain.cells=[8,8]",
            "output.snapshots=0",
            "output.particles=false",
            "output.vtk=false",
            "output.plots=false",
        ],
        &["mpm", "cpgimp", "cpdi2", "cpdi-improved", "ddmp", "ddmp-subpoints;scheme.sub_points=4"],
        // 12 rows: three slab tiles of 4 rows, one per rank at N = 3 (8 rows are two tiles).
        &["domain.cells=[8,12]"],
        "6c5ece78afd33a6fc6db7853845043f4d2891cea7005bad174bf50a5ae9b8f32",
    );
}

#[test]
#[cfg_attr(
    not(require_mpi),
    ignore = "needs MPI: bash deploy/setup.sh mpi, MSCALE_MPI_MSCALE=<mscale built with --features mpi>; runs with MSCALE_REQUIRE_MPI=1 (CI) or -- --ignored"
)]
fn a_point_leaving_the_grid_stops_every_rank_with_one_message() {
    // mms-2d under ugimp on 8 x 12 cells: a point leaves the grid at step 3 (the one-process run
    // fails the same way). Over 3 ranks every rank stops there (no rank hangs in a collective),
    // mpirun exits 1 and the message is printed once, by rank 0.
    let exe = mpi_mscale();
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = repo().join("scenes/mms-2d.toml");
    let set = [
        "scheme.end_time=0.002",
        "domain.cells=[8,12]",
        "output.snapshots=0",
        "output.particles=false",
        "output.vtk=false",
        "output.plots=false",
        "scheme.method=\"ugimp\"",
    ];
    let run = |ranks: Option<usize>| {
        let mut cmd = match ranks {
            Some(n) => {
                let mut c = Command::new(std::env::var("MSCALE_MPIRUN").unwrap_or_else(|_| "mpirun".into()));
                c.args(["--allow-run-as-root", "--oversubscribe", "-np", &n.to_string()]).arg(&exe);
                c
            }
            None => Command::new(&exe),
        };
        cmd.arg("run").arg(&scene).arg("--out").arg(tmp.path().join(format!("fail-{}", ranks.unwrap_or(0))));
        for s in set {
            cmd.args(["--set", s]);
        }
        cmd.current_dir(repo())
            .env("RUST_LOG", "warn")
            .env("RAYON_NUM_THREADS", "1")
            .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
        let o = cmd.output().expect("run mscale");
        (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (code1, err1) = run(None);
    assert_eq!(code1, Some(1), "{err1}");
    let (code3, err3) = run(Some(3));
    assert_eq!(code3, Some(1), "{err3}");
    let line = |e: &str| e.lines().filter(|l| l.contains("the run failed: step 3: particle")).map(str::to_string).collect::<Vec<_>>();
    assert_eq!(line(&err1).len(), 1, "{err1}");
    assert_eq!(line(&err3), line(&err1), "3 ranks: {err3}");
}
