//! MPI inside a worker (md-worker's cargo feature `mpi`): `mpirun -np 2 md-worker serve` gives
//! bitwise the results of the in-process run.
//!
//! Needs an md-worker built with `--features mpi` and Open MPI's `mpirun` (`bash deploy/setup.sh
//! mpi`); set `MSCALE_MPI_WORKER` to that binary. Without `MSCALE_REQUIRE_MPI=1` at build time
//! (tests/build.rs) these tests are ignored, with the reason; with it (CI's last step sets both)
//! they run and fail when MPI or the worker is missing. `-- --ignored` runs them too.
//! `MSCALE_MPIRUN` overrides the launcher (default `mpirun`).

use md_worker::pool::{Endpoint, InProcess, MdPool, PotentialSource, Remote};
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind};
use mscale_tests::{Listening, binary, repo};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

/// The md-worker built with `--features mpi`; a failure when it is not there (these tests run
/// only when MPI is required or asked for).
fn mpi_worker() -> PathBuf {
    match std::env::var_os("MSCALE_MPI_WORKER") {
        Some(p) if !p.is_empty() && Path::new(&p).is_file() => PathBuf::from(p),
        Some(p) if !p.is_empty() => {
            panic!("MSCALE_MPI_WORKER={} is not a file (an md-worker built with --features mpi; see .ci/run)", Path::new(&p).display())
        }
        _ => {
            panic!("MSCALE_MPI_WORKER is unset: set it to an md-worker built with --features mpi (`bash deploy/setup.sh mpi`; see .ci/run)")
        }
    }
}

/// `mpirun -np RANKS md-worker serve` on a free loopback port; stopped (SIGTERM to mpirun, which
/// ends every rank) on drop.
fn mpi_serve(exe: &Path, ranks: usize) -> Listening {
    let launcher = std::env::var("MSCALE_MPIRUN").unwrap_or_else(|_| "mpirun".into());
    let mut cmd = Command::new(&launcher);
    cmd.args(["--allow-run-as-root", "--oversubscribe", "-np", &ranks.to_string()])
        .arg(exe)
        .args(["serve", "--listen", "127.0.0.1:0", "--threads", "1"])
        .env("RUST_LOG", "warn")
        // Containers often forbid the cross-memory attach of Open MPI's shared-memory transport.
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    let mut w = Listening::start(&mut cmd, "listening on ", None);
    w.proc.terminate_first = true;
    w
}

fn mscale(args: &[&str]) -> std::process::Output {
    Command::new(binary("mscale", "orchestrator")).args(args).current_dir(repo()).env("RUST_LOG", "warn").output().expect("run mscale")
}

fn summary(dir: &Path) -> serde_json::Value {
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).expect("summary")).expect("json");
    assert_eq!(s["status"], "completed", "{s}");
    s
}

#[test]
#[cfg_attr(
    not(require_mpi),
    ignore = "needs MPI: bash deploy/setup.sh mpi, MSCALE_MPI_WORKER=<md-worker built with --features mpi>; runs with MSCALE_REQUIRE_MPI=1 (CI) or -- --ignored"
)]
fn a_coupled_run_on_two_mpi_ranks_has_the_in_process_digest() {
    let exe = mpi_worker();
    let scene = repo().join("tests/data/md-small.toml");
    let scene = scene.to_str().expect("utf8");
    let tmp = tempfile::tempdir().expect("tempdir");
    let run = |name: &str, workers: Option<&str>| {
        let out = tmp.path().join(name);
        let out_s = out.display().to_string();
        let mut args = vec!["run", scene, "--out", &out_s];
        if let Some(w) = workers {
            args.extend(["--workers", w]);
        }
        let o = mscale(&args);
        assert_eq!(o.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&o.stderr));
        out
    };
    let local = run("local", None);
    let w = mpi_serve(&exe, 2);
    let mpi = run("mpi", Some(&w.addr));
    let (a, b) = (summary(&local), summary(&mpi));
    assert_eq!(a["state_digest"], b["state_digest"], "in-process vs md-worker on 2 MPI ranks");
    assert!(b.to_string().contains("mpi"), "the provenance names the mpi back end: {b}");
    // The particle CSV (MD outputs per point) agrees too.
    let csv = |d: &Path| std::fs::read_to_string(d.join("particles_final.csv")).expect("csv");
    assert_eq!(csv(&local), csv(&mpi));
}

fn specs() -> Vec<BoxSpec> {
    // Ids out of order and not contiguous; mixed temperatures, so boxes differ.
    [12u64, 3, 40, 7, 25, 1, 33]
        .iter()
        .map(|&id| {
            let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [2, 2, 2]);
            s.temperature_k = if id % 2 == 0 { 0.0 } else { 30.0 + id as f64 };
            s.seed = 11;
            s.strain = [-0.01 * (id % 3) as f64, 0.0, 0.0];
            s
        })
        .collect()
}

fn work(ids: &[u64], rate: f64) -> Vec<BoxWork> {
    ids.iter()
        .map(|&id| {
            serde_json::from_value(serde_json::json!({
                "id": id, "velocity_gradient": [[rate * (1.0 + id as f64 / 50.0), 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
                "steps": 15, "dt_ps": 0.001, "energy_to_add_ev": if id % 3 == 0 { 0.01 } else { 0.0 }
            }))
            .expect("work")
        })
        .collect()
}

fn bits(r: &[BoxResult]) -> Vec<String> {
    r.iter()
        .map(|r| {
            format!(
                "{} {:?} {:x} {:x} {:x}",
                r.id,
                r.stress_gpa.map(f64::to_bits),
                r.potential_energy_ev.to_bits(),
                r.kinetic_energy_ev.to_bits(),
                r.temperature_k.to_bits()
            )
        })
        .collect()
}

/// Runs the same open / step / snapshot / restore / second open / step sequence on `ep`.
fn sequence(ep: Box<dyn Endpoint>) -> (Vec<Vec<String>>, Vec<md_worker::BoxState>, String) {
    let pot = PotentialSource::from_file(&repo().join("md-worker/potentials/Cu_mishin1.eam.alloy")).expect("potential");
    let mut pool = MdPool::new(vec![ep]).expect("pool");
    let all = specs();
    pool.open(&pot, &all[..5]).expect("open");
    let ids: Vec<u64> = all[..5].iter().map(|s| s.id).collect();
    let mut out = Vec::new();
    out.push(bits(&pool.step(1, &work(&ids, 1e-3)).expect("step 1")));
    let saved = pool.snapshot(&ids).expect("snapshot");
    out.push(bits(&pool.step(2, &work(&ids, -2e-3)).expect("step 2")));
    pool.restore(saved.clone()).expect("restore");
    // After restoring, step 2 again gives bitwise the same results.
    out.push(bits(&pool.step(3, &work(&ids, -2e-3)).expect("step 2 again")));
    // More boxes in the same session; a step in a shuffled order over all of them.
    pool.open(&pot, &all[5..]).expect("second open");
    let mut every: Vec<u64> = all.iter().map(|s| s.id).collect();
    every.reverse();
    out.push(bits(&pool.step(4, &work(&every, 5e-4)).expect("step all")));
    // A box nobody opened is refused, naming it.
    let err = pool.step(5, &work(&[999], 1e-3)).expect_err("unknown box").to_string();
    let final_states = pool.snapshot(&every).expect("final snapshot");
    (out, final_states, err)
}

#[test]
#[cfg_attr(
    not(require_mpi),
    ignore = "needs MPI: bash deploy/setup.sh mpi, MSCALE_MPI_WORKER=<md-worker built with --features mpi>; runs with MSCALE_REQUIRE_MPI=1 (CI) or -- --ignored"
)]
fn open_step_snapshot_restore_on_two_mpi_ranks_match_in_process_bit_for_bit() {
    let exe = mpi_worker();
    let w = mpi_serve(&exe, 2);
    let rt = Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().expect("runtime"));
    let (local, local_states, local_err) = sequence(Box::new(InProcess::new("cpu", None)));
    assert_eq!(local[1], local[2], "restore replays step 2 exactly (in-process)");
    // Two sessions at once on the same MPI worker (two coordinators): kept apart on every rank.
    let sessions: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..2)
            .map(|_| {
                let remote = Remote::connect(&w.addr, rt.clone()).expect("connect");
                s.spawn(move || sequence(Box::new(remote)))
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("session thread")).collect()
    });
    for (n, (mpi, mpi_states, mpi_err)) in sessions.iter().enumerate() {
        for (k, (a, b)) in local.iter().zip(mpi).enumerate() {
            assert_eq!(a, b, "session {n}, call {k}: in-process vs 2 MPI ranks");
        }
        assert_eq!(&local_states, mpi_states, "session {n}: box states after the sequence");
        assert!(local_err.contains("999") && mpi_err.contains("999"), "{local_err} / {mpi_err}");
    }
    // Info says how the worker computes.
    let info = rt
        .block_on(async {
            let mut c =
                mscale_proto::coupling::v1::md_worker_client::MdWorkerClient::connect(format!("http://{}", w.addr)).await.expect("connect");
            c.info(mscale_proto::coupling::v1::InfoRequest {}).await
        })
        .expect("info")
        .into_inner();
    assert!(info.device.contains("mpi 2 ranks x 1 threads"), "device {:?}", info.device);
}
