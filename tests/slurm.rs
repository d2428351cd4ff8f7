//! Under a real Slurm: the sbatch files of deploy/slurm run on the single-node cluster of
//! `bash deploy/setup.sh slurm` (munged, slurmctld, slurmd on this machine).
//!
//! - `deploy/slurm/mscale-cluster.sbatch`, submitted with sbatch as it is (its #SBATCH lines
//!   are the allocation): the orchestrator as one job step, two worker pools as MPI job steps
//!   (`srun --mpi=pmix`), a scene submitted and watched to its end; the digest it fetched is
//!   the one `mscale run` gives in one process.
//! - A second allocation: one worker step is killed mid-job (`scancel --signal=KILL JOB.STEP`),
//!   and the job still ends with the undisturbed digest (the survivor takes the lost boxes).
//! - A third: `scancel` of the whole allocation mid-job (SIGTERM: the orchestrator
//!   checkpoints), then a new allocation of the same script on the same state directory
//!   (`MSCALE_JOB`), with more workers from `deploy/slurm/md-workers.sbatch` beside it,
//!   resumes the job to the undisturbed digest.
//!
//! Ignored unless `MSCALE_REQUIRE_SLURM=1` at build time (tests/build.rs); then they run and
//! fail when Slurm is missing. `MSCALE_MPI_WORKER` (an md-worker built with `--features mpi`)
//! makes the pools' md-worker that one, so each step is an MPI program under srun's PMIx.

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_tests::{binary, mpi_mscale, repo};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// One allocation at a time: the single-node cluster has few cores.
static CLUSTER: Mutex<()> = Mutex::new(());

const MD_SMALL: &str = "tests/data/md-small.toml";
/// 16 points, 1000 steps of md-small: long enough to act on the allocation mid-job (400 were
/// about a second since the MD got faster).
const LONGER: [&str; 2] = ["domain.cells=[16]", "scheme.end_time=1e-11"];

fn run(cmd: &mut Command) -> std::process::Output {
    cmd.output().unwrap_or_else(|e| panic!("cannot run {:?}: {e} (install Slurm: bash deploy/setup.sh slurm)", cmd.get_program()))
}

fn ok(cmd: &mut Command) -> String {
    let o = run(cmd);
    assert!(o.status.success(), "{:?} failed: {}", cmd, mscale_tests::text(&o));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The cluster answers and its node takes jobs.
fn cluster_up() {
    let state = ok(Command::new("sinfo").args(["-h", "-o", "%T"]));
    assert!(
        state.lines().any(|s| matches!(s.trim(), "idle" | "mixed" | "allocated")),
        "no Slurm node takes jobs (sinfo: {state:?}); start the cluster with bash deploy/setup.sh slurm"
    );
}

/// A port base with `n` free ports on every address, below the pools' default ranges (24000)
/// and below Linux's ephemeral range (32768-60999), where an outgoing connection could take
/// the port between this check and the worker's listen.
fn free_ports(n: u16) -> u16 {
    let seed = std::process::id() as u16 ^ (Instant::now().elapsed().subsec_nanos() as u16);
    for k in 0..200u16 {
        let base = 12000 + (seed.wrapping_add(k.wrapping_mul(97)) % 12000);
        if (0..n).all(|i| std::net::TcpListener::bind(("0.0.0.0", base + i)).is_ok()) {
            return base;
        }
    }
    panic!("no {n} free ports");
}

/// A test's directory: the binaries the sbatch scripts run (MSCALE_BIN), the orchestrator's
/// state, the job outputs.
struct Site {
    tmp: tempfile::TempDir,
    bin: PathBuf,
    state: PathBuf,
}

impl Site {
    fn new() -> Site {
        let tmp = tempfile::tempdir().unwrap();
        let bin = tmp.path().join("bin");
        std::fs::create_dir_all(&bin).unwrap();
        std::os::unix::fs::symlink(binary("mscale", "orchestrator"), bin.join("mscale")).unwrap();
        let worker = match std::env::var_os("MSCALE_MPI_WORKER").filter(|w| !w.is_empty()) {
            Some(w) => {
                assert!(Path::new(&w).is_file(), "MSCALE_MPI_WORKER={} is not a file", Path::new(&w).display());
                PathBuf::from(w)
            }
            None => binary("md-worker", "md-worker"),
        };
        std::os::unix::fs::symlink(worker, bin.join("md-worker")).unwrap();
        let state = tmp.path().join("state");
        Site { tmp, bin, state }
    }

    /// `sbatch --parsable [options] SCRIPT [args]` from the repository with the site's
    /// environment; returns the Slurm job id.
    fn sbatch(&self, options: &[&str], script: &str, args: &[&str], env: &[(&str, String)]) -> String {
        let out = self.tmp.path().join("slurm-%j.out");
        let mut cmd = Command::new("sbatch");
        cmd.arg("--parsable").arg(format!("--output={}", out.display())).args(options).arg(script).args(args).current_dir(repo());
        cmd.env("MSCALE_HOME", repo()).env("MSCALE_BIN", &self.bin).env("MSCALE_STATE", &self.state).env("RUST_LOG", "info");
        for (k, v) in env {
            cmd.env(k, v);
        }
        let id = ok(&mut cmd).trim().split(';').next().unwrap().to_string();
        assert!(id.chars().all(|c| c.is_ascii_digit()) && !id.is_empty(), "sbatch printed {id:?}");
        id
    }

    fn output(&self, job: &str) -> String {
        std::fs::read_to_string(self.tmp.path().join(format!("slurm-{job}.out"))).unwrap_or_default()
    }

    /// Waits for `needle` in the job's output; returns the output.
    fn wait_output(&self, job: &str, needle: &str, limit: Duration) -> String {
        let start = Instant::now();
        loop {
            let out = self.output(job);
            if out.contains(needle) {
                return out;
            }
            let state = job_state(job);
            assert!(
                start.elapsed() < limit && !is_final(&state),
                "Slurm job {job} ({state}): no {needle:?} in its output after {:?}:\n{out}",
                start.elapsed()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The mscale job id the cluster script submitted, once it has.
    fn mscale_job(&self, slurm_job: &str) -> String {
        let out = self.wait_output(slurm_job, " as job ", Duration::from_secs(240));
        let line = out.lines().find(|l| l.starts_with("mscale-cluster: submitted ")).unwrap();
        line.split(" as job ").nth(1).unwrap().split_whitespace().next().unwrap().to_string()
    }

    fn wait_for_checkpoint(&self, job: &str, slurm_job: &str) {
        let dir = self.state.join("jobs").join(job).join("run/checkpoints");
        let mut polls = 0u32;
        wait_for_ckpt(&dir, || {
            polls += 1;
            // The allocation ended (the job failed, say): no checkpoint will come.
            let ended = polls.is_multiple_of(50) && is_final(&job_state(slurm_job));
            ended.then(|| self.output(slurm_job))
        });
    }

    /// Waits for a checkpoint of a job of a local orchestrator.
    fn wait_for_checkpoint_local(&self, job: &str) {
        wait_for_ckpt(&self.state.join("jobs").join(job).join("run/checkpoints"), || None);
    }

    /// The state_digest of the summary the cluster script fetched for `job`.
    fn fetched_digest(&self, job: &str) -> String {
        mscale_tests::state_digest(&self.state.join("results").join(job))
    }
}

/// Waits for a checkpoint file in `dir`; `gone` says (with a log) when none can come any more.
fn wait_for_ckpt(dir: &Path, mut gone: impl FnMut() -> Option<String>) {
    let start = Instant::now();
    let count =
        || std::fs::read_dir(dir).map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".ckpt")).count()).unwrap_or(0);
    while count() == 0 {
        if let Some(log) = gone() {
            panic!("no checkpoint in {} and none will come:\n{log}", dir.display());
        }
        assert!(start.elapsed() < Duration::from_secs(240), "no checkpoint in {} after 240 s", dir.display());
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// `scontrol show job`'s JobState (`RUNNING`, `COMPLETED`, ...) and ExitCode, as `STATE exit E`.
fn job_state(job: &str) -> String {
    let o = run(Command::new("scontrol").args(["show", "job", job]));
    let text = String::from_utf8_lossy(&o.stdout);
    let field = |k: &str| text.split_whitespace().find_map(|w| w.strip_prefix(k)).unwrap_or("?").to_string();
    format!("{} exit {}", field("JobState="), field("ExitCode="))
}

fn is_final(state: &str) -> bool {
    !["PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "SUSPENDED"].iter().any(|s| state.starts_with(s))
}

/// Waits until the Slurm job has ended; returns its state.
fn wait_ended(job: &str, limit: Duration) -> String {
    let start = Instant::now();
    loop {
        let state = job_state(job);
        if is_final(&state) {
            return state;
        }
        assert!(start.elapsed() < limit, "Slurm job {job} still {state} after {limit:?}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// The running steps of a job: (STEPID, NAME).
fn steps(job: &str) -> Vec<(String, String)> {
    ok(Command::new("squeue").args(["-h", "-s", "-j", job, "-o", "%i %j"]))
        .lines()
        .filter_map(|l| l.split_once(' ').map(|(a, b)| (a.to_string(), b.trim().to_string())))
        .collect()
}

/// The digest `mscale run` gives in one process.
fn run_digest(dir: &Path, sets: &[&str]) -> String {
    let mut cmd = Command::new(binary("mscale", "orchestrator"));
    cmd.args(["run", MD_SMALL, "--out", dir.to_str().unwrap()]).current_dir(repo()).env("RUST_LOG", "warn");
    for s in sets {
        cmd.args(["--set", s]);
    }
    ok(&mut cmd);
    mscale_tests::state_digest(dir)
}

fn scene_args(sets: &[&'static str]) -> Vec<&'static str> {
    let mut args = vec![MD_SMALL];
    for s in sets {
        args.extend(["--set", s]);
    }
    args.extend(["--checkpoint-every", "10"]);
    args
}

fn ports(site: &Site) -> Vec<(&'static str, String)> {
    let _ = site;
    let base = free_ports(4);
    vec![("MSCALE_PORT", base.to_string()), ("MSCALE_WORKER_PORT", (base + 1).to_string())]
}

#[test]
#[cfg_attr(
    not(require_slurm),
    ignore = "needs a Slurm cluster: bash deploy/setup.sh slurm; runs with MSCALE_REQUIRE_SLURM=1 (CI) or -- --ignored"
)]
fn the_cluster_sbatch_runs_a_job_survives_a_killed_worker_step_and_resumes_after_scancel() {
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    cluster_up();
    let site = Site::new();
    let straight = run_digest(&site.tmp.path().join("straight"), &LONGER);
    let mut env = ports(&site);
    env.push(("MSCALE_POOLS_PER_NODE", "2".into()));
    let script = "deploy/slurm/mscale-cluster.sbatch";

    // 1. The script as it is: its #SBATCH lines, two pools, the scene to its end.
    let a = site.sbatch(&[], script, &scene_args(&LONGER), &env);
    let job = site.mscale_job(&a);
    let state = wait_ended(&a, Duration::from_secs(300));
    let out = site.output(&a);
    assert_eq!(state, "COMPLETED exit 0:0", "{out}");
    assert!(out.contains("mscale-cluster: 2 of 2 worker pools live"), "{out}");
    assert_eq!(site.fetched_digest(&job), straight, "{out}");

    // 2. One worker step killed mid-job: the other takes its boxes, the digest is the same.
    let b = site.sbatch(&[], script, &scene_args(&LONGER), &env);
    let job = site.mscale_job(&b);
    site.wait_for_checkpoint(&job, &b);
    let all = steps(&b);
    let (victim, name) = all.iter().find(|(_, n)| n.starts_with("md-worker-")).unwrap_or_else(|| panic!("no worker step: {all:?}")).clone();
    ok(Command::new("scancel").args(["--signal=KILL", &victim]));
    let start = Instant::now();
    while steps(&b).iter().any(|(s, _)| *s == victim) {
        assert!(start.elapsed() < Duration::from_secs(30), "step {victim} ({name}) outlived scancel --signal=KILL");
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(!is_final(&job_state(&b)), "the allocation ended with its worker step: {}", site.output(&b));
    let state = wait_ended(&b, Duration::from_secs(300));
    let out = site.output(&b);
    assert_eq!(state, "COMPLETED exit 0:0", "{out}");
    assert!(out.contains("boxes were restored from the checkpoint of step"), "the lost worker's boxes were not recovered:\n{out}");
    assert_eq!(site.fetched_digest(&job), straight, "{out}");

    // 3. scancel of the whole allocation mid-job: the orchestrator checkpoints on SIGTERM and
    // a new allocation on the same state resumes the job; a md-workers.sbatch pool joins it.
    let c = site.sbatch(&[], script, &scene_args(&LONGER), &env);
    let job = site.mscale_job(&c);
    site.wait_for_checkpoint(&job, &c);
    ok(Command::new("scancel").arg(&c));
    let state = wait_ended(&c, Duration::from_secs(60));
    assert!(state.starts_with("CANCELLED"), "{state}: {}", site.output(&c));
    assert!(!site.state.join("results").join(&job).exists(), "the job ended before scancel; make LONGER longer");
    let mut env = ports(&site);
    env.push(("MSCALE_JOB", job.clone()));
    // Its script waits for two live workers: its own pool and the md-workers.sbatch one.
    env.push(("MSCALE_MIN_WORKERS", "2".into()));
    let d = site.sbatch(&["--ntasks-per-node=1"], script, &[], &env);
    let out = site.wait_output(&d, "mscale serve: listening on", Duration::from_secs(240));
    let server = format!("https://{}:{}", hostname(), env[0].1);
    let ca = site.state.join(format!("tls-{d}/ca.crt"));
    let mut more = vec![
        ("MSCALE_ORCHESTRATOR", server.clone()),
        ("MSCALE_CA_FILE", ca.display().to_string()),
        ("MSCALE_TOKEN_FILE", site.state.join("token").display().to_string()),
    ];
    more.push(("MSCALE_WORKER_PORT", free_ports(2).to_string()));
    let e = site.sbatch(&["--ntasks-per-node=1"], "deploy/slurm/md-workers.sbatch", &[], &more);
    let state = wait_ended(&d, Duration::from_secs(300));
    let out = format!("{out}\n{}", site.output(&d));
    assert_eq!(state, "COMPLETED exit 0:0", "{out}");
    assert!(out.contains(&format!("watching job {job}")) && out.contains("resuming from its last checkpoint"), "{out}");
    assert!(out.contains("mscale-cluster: 2 of 2 worker pools live"), "the md-workers.sbatch pool did not join: {out}");
    assert_eq!(site.fetched_digest(&job), straight, "{out}");
    // The md-workers.sbatch pool ran (its health check and its worker's listening line).
    let workers = site.output(&e);
    ok(Command::new("scancel").arg(&e));
    wait_ended(&e, Duration::from_secs(60));
    assert!(workers.contains("SERVING") && workers.contains("listening on 0.0.0.0:"), "md-workers.sbatch:\n{workers}");
}

/// mms-2d on 16 x 24 cells (twelve slab tiles), long enough to scancel mid-run.
const MMS_OVER_RANKS: [&str; 6] = [
    "domain.cells=[16,24]",
    "scheme.end_time=0.4",
    "output.snapshots=0",
    "output.particles=false",
    "output.vtk=false",
    "output.plots=false",
];

#[test]
#[cfg_attr(
    not(require_slurm),
    ignore = "needs a Slurm cluster: bash deploy/setup.sh slurm; runs with MSCALE_REQUIRE_SLURM=1 (CI) or -- --ignored"
)]
fn the_continuum_over_srun_ranks_has_the_one_process_digest_and_resumes_on_another_rank_count() {
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    cluster_up();
    let site = Site::new();
    let bin = site.tmp.path().join("mpi-bin");
    std::fs::create_dir_all(&bin).unwrap();
    std::os::unix::fs::symlink(mpi_mscale(), bin.join("mscale")).unwrap();
    let env = [("MSCALE_BIN", bin.display().to_string()), ("RUST_LOG", "warn".to_string())];
    let mut args: Vec<&str> = vec![];
    for s in &MMS_OVER_RANKS {
        args.extend(["--set", s]);
    }
    // The one-process run (the same binary without srun: no exchange, the plain code path).
    let straight = site.tmp.path().join("straight");
    let mut cmd = Command::new(mpi_mscale());
    cmd.args(["run", "scenes/mms-2d.toml", "--out", straight.to_str().unwrap()]).args(&args).current_dir(repo()).env("RUST_LOG", "warn");
    ok(&mut cmd);
    let digest = mscale_tests::state_digest(&straight);
    let script = "deploy/slurm/mscale-run.sbatch";

    // 1. The script as it is (2 tasks): one job step of 2 ranks, the scene to its end.
    let dir = site.tmp.path().join("two");
    let mut a_args = vec!["scenes/mms-2d.toml", dir.to_str().unwrap()];
    a_args.extend(&args);
    let a = site.sbatch(&[], script, &a_args, &env);
    let state = wait_ended(&a, Duration::from_secs(300));
    let out = site.output(&a);
    assert_eq!(state, "COMPLETED exit 0:0", "{out}");
    assert!(out.contains("mscale-run: scenes/mms-2d.toml on 2 ranks"), "{out}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["ranks"]["ranks"], 2, "not split over 2 srun ranks: {summary}");
    assert_eq!(mscale_tests::state_digest(&dir), digest, "{out}");

    // 2. scancel mid-run (SIGTERM to both ranks: they stop after the same step, rank 0 writes a
    // checkpoint), then the same command on 3 tasks resumes it to the uninterrupted digest.
    let dir = site.tmp.path().join("cut");
    let mut b_args = vec!["scenes/mms-2d.toml", dir.to_str().unwrap(), "--checkpoint-every", "200"];
    b_args.extend(&args);
    let b = site.sbatch(&[], script, &b_args, &env);
    wait_for_ckpt(&dir.join("checkpoints"), || is_final(&job_state(&b)).then(|| site.output(&b)));
    ok(Command::new("scancel").arg(&b));
    let state = wait_ended(&b, Duration::from_secs(60));
    let out = site.output(&b);
    assert!(state.starts_with("CANCELLED") || state.starts_with("FAILED"), "{state}: {out}");
    assert!(!dir.join("summary.json").exists() || mscale_tests::state_digest(&dir) != digest, "the run ended before scancel: {out}");
    let c = site.sbatch(&["--ntasks=3", "--overcommit"], script, &b_args, &env);
    let state = wait_ended(&c, Duration::from_secs(300));
    let out = site.output(&c);
    assert_eq!(state, "COMPLETED exit 0:0", "{out}");
    assert!(out.contains("resuming") && out.contains("on 3 ranks"), "{out}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["ranks"]["ranks"], 3, "{summary}");
    assert_eq!(mscale_tests::state_digest(&dir), digest, "resumed on 3 srun ranks: {out}");
}

fn hostname() -> String {
    ok(Command::new("hostname").arg("-s")).trim().to_string()
}

/// `mscale serve` on loopback (the launched workers run on this machine too), 5 s heartbeat timeout.
fn local_orchestrator(site: &Site, token: &Path) -> mscale_tests::Listening {
    let mut cmd = Command::new(binary("mscale", "orchestrator"));
    cmd.args(["serve", "--state", site.state.to_str().unwrap(), "--listen", "127.0.0.1:0", "--token-file", token.to_str().unwrap()])
        .args(["--worker-timeout", "5"])
        .env("RUST_LOG", "info");
    mscale_tests::Listening::start(&mut cmd, "mscale serve: listening on ", Some(&site.tmp.path().join("serve.log")))
}

fn mscale(args: &[&str], server: &str, token: &Path) -> std::process::Output {
    run(Command::new(binary("mscale", "orchestrator"))
        .args(args)
        .args(["--server", server, "--token-file", token.to_str().unwrap()])
        .current_dir(repo())
        .env("RUST_LOG", "warn"))
}

#[test]
#[cfg_attr(
    not(require_slurm),
    ignore = "needs a Slurm cluster: bash deploy/setup.sh slurm; runs with MSCALE_REQUIRE_SLURM=1 (CI) or -- --ignored"
)]
fn pools_launched_through_slurm_run_a_job_survive_a_cancelled_pool_and_are_released() {
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    cluster_up();
    let site = Site::new();
    let straight = run_digest(&site.tmp.path().join("straight"), &LONGER);
    let token = site.tmp.path().join("token");
    std::fs::write(&token, "slurm-pool-token-0123456789\n").unwrap();
    let server = local_orchestrator(&site, &token);
    let addr = server.addr.clone();
    let pools_dir = site.tmp.path().join("pools");
    let pools_dir_s = pools_dir.display().to_string();
    let worker_bin = site.bin.join("md-worker").display().to_string();
    let partition = ok(Command::new("sinfo").args(["-h", "-o", "%P"])).lines().next().unwrap().trim().trim_end_matches('*').to_string();
    let launch = |extra: &[&str]| {
        let mut args =
            vec!["workers", "launch", "--slurm", "--workers", "1", "--time", "15", "--dir", &pools_dir_s, "--worker-bin", &worker_bin];
        args.extend(extra);
        let o = mscale(&args, &addr, &token);
        assert!(o.status.success(), "launch {extra:?}: {}\n{}", mscale_tests::text(&o), server.proc.log());
        let pool = String::from_utf8_lossy(&o.stdout).trim().to_string();
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(err.contains(&format!("pool {pool}: RUNNING")) && err.contains("live at "), "{err}");
        pool
    };

    // Refused before anything is queued: exit code 2, the value named.
    let o = mscale(&["workers", "launch", "--slurm", "--workers", "0"], &addr, &token);
    assert_eq!(o.status.code(), Some(2), "{}", mscale_tests::text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--workers 0"), "{}", mscale_tests::text(&o));
    let o = mscale(
        &["workers", "launch", "--slurm", "--workers", "1", "--partition", "no-such-partition", "--dir", &pools_dir_s],
        &addr,
        &token,
    );
    assert_eq!(o.status.code(), Some(2), "{}", mscale_tests::text(&o));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("no-such-partition") || String::from_utf8_lossy(&o.stderr).contains("partition"),
        "{}",
        mscale_tests::text(&o)
    );

    // Two pools of one worker each (the second on the named partition).
    let a = launch(&[]);
    let b = launch(&["--partition", &partition, "--ranks-per-worker", "1", "--threads-per-rank", "1"]);
    let listed = String::from_utf8_lossy(&mscale(&["workers", "pools"], &addr, &token).stdout).into_owned();
    for p in [&a, &b] {
        assert!(listed.lines().any(|l| l.starts_with(p.as_str()) && l.contains("RUNNING") && l.contains("1/1 workers live")), "{listed}");
    }

    // A job on both; pool a's Slurm job cancelled mid-job: its worker is lost, b takes its
    // boxes, and the job ends with the undisturbed digest.
    let client_job = {
        let mut args = vec!["submit", MD_SMALL, "--checkpoint-every", "10"];
        for s in LONGER {
            args.extend(["--set", s]);
        }
        let o = mscale(&args, &addr, &token);
        assert!(o.status.success(), "{}", mscale_tests::text(&o));
        String::from_utf8_lossy(&o.stdout).trim().to_string()
    };
    site.wait_for_checkpoint_local(&client_job);
    ok(Command::new("scancel").arg(&a));
    let o = mscale(&["watch", &client_job], &addr, &token);
    assert!(o.status.success(), "{}\n{}", mscale_tests::text(&o), server.proc.log());
    let log = server.proc.log();
    assert!(log.contains("boxes were restored from the checkpoint of step"), "{log}");
    let status = String::from_utf8_lossy(&mscale(&["status", &client_job], &addr, &token).stdout).into_owned();
    assert!(status.contains("completed") && status.contains(&format!("digest {straight}")), "{status}\n{log}");
    assert!(wait_ended(&a, Duration::from_secs(60)).starts_with("CANCELLED"));

    // Release b: drained, scancelled, gone from the pools.
    let o = mscale(&["workers", "release", &b], &addr, &token);
    assert!(o.status.success(), "{}", mscale_tests::text(&o));
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(err.contains("drained") && err.contains(&format!("pool {b}: released (CANCELLED")), "{err}");
    assert!(wait_ended(&b, Duration::from_secs(60)).starts_with("CANCELLED"));
    let listed = String::from_utf8_lossy(&mscale(&["workers", "pools"], &addr, &token).stdout).into_owned();
    assert!(!listed.contains(&b) && !listed.contains(&a), "{listed}");
    let workers = String::from_utf8_lossy(&mscale(&["workers"], &addr, &token).stdout).into_owned();
    assert!(
        !workers.lines().any(|l| l.split_whitespace().nth(1) == Some("live")),
        "a released or cancelled pool's worker is still live:\n{workers}"
    );
}
