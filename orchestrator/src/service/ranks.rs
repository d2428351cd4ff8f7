//! Jobs whose continuum runs over MPI ranks (`mscale submit --ranks N`): the orchestrator
//! starts `MPIRUN -np N MSCALE run ...` (its `serve --mpi-mscale` and `--mpirun`) as a child
//! process for each attempt, with the job's scene, overrides, checkpoint interval, workers and
//! step deadline, and turns what the run reports into what an in-process run gives the job
//! runner:
//! - progress: `run --progress-json` prints rank 0's progress after every step as a JSON line,
//!   handed to the job's progress callback (events, metrics, checkpoint events) as it comes;
//! - cancel and stop: when the job's stop flag rises the orchestrator creates the run's
//!   `--stop-file`; rank 0 sees it within 100 ms and every rank stops after the same step with
//!   a checkpoint (continuum/README.md "MPI"), as on SIGTERM;
//! - resume: an attempt of a job with checkpoints runs `run --resume RUN_DIR` (a checkpoint
//!   of any rank count resumes on any other);
//! - the outcome: exit code 0 and the run directory's summary.json (completed), the newest
//!   checkpoint after a requested stop (cancelled), or the run's own message (failed; exit
//!   code 2, bad input, is an error of the attempt).
//!
//! The MD workers the job holds are given to the run (`--workers`; rank 0 drives them); a
//! worker lost mid-run is recovered from inside the run (its boxes replayed on the others),
//! and the orchestrator learns of it from its heartbeats, not from the run.

use crate::run::{Outcome, Progress, RunOptions};
use anyhow::{Context, Result, anyhow, bail};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How the orchestrator starts a job over MPI ranks (`mscale serve --mpi-mscale PATH
/// --mpirun COMMAND`).
#[derive(Debug, Clone)]
pub struct MpiLauncher {
    /// An `mscale` built with the cargo feature `mpi`.
    pub mscale: PathBuf,
    /// The launcher's words before `-np N`.
    pub mpirun: Vec<String>,
}

impl MpiLauncher {
    /// `mpirun` split as a shell would; `mscale` must be a file.
    pub fn new(mscale: PathBuf, mpirun: &str) -> Result<MpiLauncher> {
        let words = shlex::split(mpirun).filter(|w| !w.is_empty()).ok_or_else(|| {
            anyhow!("--mpirun {mpirun:?} is not a command (empty, or an unbalanced quote): give the launcher, e.g. --mpirun mpirun")
        })?;
        if !mscale.is_file() {
            bail!("--mpi-mscale {}: no such file (build one: cargo build --release -p orchestrator --features mpi)", mscale.display());
        }
        Ok(MpiLauncher { mscale, mpirun: words })
    }

    /// The command line, for the log.
    pub fn describe(&self) -> String {
        format!("{} -np N {} run ...", self.mpirun.join(" "), self.mscale.display())
    }

    /// The command of one attempt of a job's run over `ranks` ranks (see the module doc).
    fn command(&self, ranks: u32, scene: &Path, overrides: &[String], opts: &RunOptions, stop_file: &Path) -> Command {
        let mut cmd = Command::new(&self.mpirun[0]);
        cmd.args(&self.mpirun[1..]).arg("-np").arg(ranks.to_string()).arg(&self.mscale).arg("run");
        if opts.resume {
            cmd.arg("--resume").arg(&opts.out);
        } else {
            cmd.arg(scene).arg("--out").arg(&opts.out);
            for s in overrides {
                cmd.arg("--set").arg(s);
            }
        }
        cmd.arg("--checkpoint-every").arg(opts.checkpoint_every.to_string());
        cmd.arg("--step-deadline").arg(opts.step_deadline.to_string());
        cmd.arg("--rebalance-every").arg(opts.rebalance_every.to_string());
        if !opts.workers.is_empty() {
            cmd.arg("--workers").arg(opts.workers.join(","));
        }
        cmd.arg("--progress-json").arg("--stop-file").arg(stop_file);
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        cmd
    }
}

/// Lines of the run's standard error kept for a failure's message.
const STDERR_TAIL: usize = 20;

/// One attempt of a job's run over `ranks` MPI ranks: the run's outcome, as `Loaded::run`
/// gives it in-process (`opts` as the job runner set them; its hooks of the MD pool are not
/// called: the pool lives in the child).
pub(crate) fn run(launcher: &MpiLauncher, ranks: u32, scene: &Path, overrides: &[String], opts: &RunOptions) -> Result<Outcome> {
    std::fs::create_dir_all(&opts.out).with_context(|| format!("cannot create {}", opts.out.display()))?;
    // Beside the run directory (not in it: a fetch of the run gets the run's files only).
    let stop_file = opts.out.with_file_name("stop-request");
    match std::fs::remove_file(&stop_file) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(e).with_context(|| format!("cannot remove the stale {}", stop_file.display()));
        }
        _ => {}
    }
    let mut cmd = launcher.command(ranks, scene, overrides, opts, &stop_file);
    tracing::info!("starting {cmd:?}");
    let mut child = cmd.spawn().with_context(|| format!("cannot start the MPI launcher {:?}", launcher.mpirun[0]))?;
    let stdout = child.stdout.take().context("the run's standard output is not piped")?;
    let stderr = child.stderr.take().context("the run's standard error is not piped")?;
    let tail: Arc<Mutex<Vec<String>>> = Arc::default();
    let tail2 = tail.clone();
    let errors = std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
            tracing::info!("(ranks) {line}");
            let mut t = super::shared::lock(&tail2);
            t.push(line);
            if t.len() > STDERR_TAIL {
                t.remove(0);
            }
        }
    });
    // The job's stop flag becomes the run's stop file.
    let exited = Arc::new(AtomicBool::new(false));
    let (exited2, cancel, stop2) = (exited.clone(), opts.cancel.clone(), stop_file.clone());
    let stopper = std::thread::spawn(move || {
        while !exited2.load(Ordering::SeqCst) {
            if cancel.as_ref().is_some_and(|c| c.load(Ordering::SeqCst)) {
                if let Err(e) = std::fs::write(&stop2, b"stop\n") {
                    tracing::error!("cannot write {} to stop the run: {e}", stop2.display());
                }
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    });
    let mut last: Option<Progress> = None;
    for line in BufReader::new(stdout).lines().map_while(|l| l.ok()) {
        match serde_json::from_str::<Progress>(&line) {
            Ok(p) => {
                if let Some(f) = &opts.progress {
                    f(&p);
                }
                last = Some(p);
            }
            Err(_) => tracing::info!("(ranks) {line}"),
        }
    }
    let status = child.wait().context("cannot wait for the MPI run")?;
    exited.store(true, Ordering::SeqCst);
    let _ = stopper.join();
    let _ = errors.join();
    let _ = std::fs::remove_file(&stop_file);
    // A run that died without its last progress report still ends the job's progress.
    if let (Some(p), Some(f)) = (last.filter(|p| !p.done), &opts.progress) {
        f(&Progress { done: true, ..p });
    }
    let tail = super::shared::lock(&tail).join("\n");
    let summary = || -> Result<serde_json::Value> {
        let path = opts.out.join("summary.json");
        let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
        serde_json::from_str(&text).with_context(|| format!("{} is not JSON", path.display()))
    };
    let stop_requested = opts.cancel.as_ref().is_some_and(|c| c.load(Ordering::SeqCst));
    match status.code() {
        Some(crate::exit::OK) => Ok(Outcome::Completed(summary()?)),
        Some(crate::exit::BAD_INPUT) => bail!("the run over {ranks} MPI ranks refused its input: {tail}"),
        _ if stop_requested => match crate::checkpoint::list(&opts.out)?.into_iter().next() {
            Some((step, checkpoint)) => Ok(Outcome::Cancelled { checkpoint, step }),
            None => bail!("the run over {ranks} MPI ranks was stopped but left no checkpoint ({status}): {tail}"),
        },
        _ => {
            let why = tail
                .lines()
                .find_map(|l| l.strip_prefix("mscale: the run failed: "))
                .map(str::to_string)
                .unwrap_or_else(|| format!("the run over {ranks} MPI ranks ended with {status}: {tail}"));
            Ok(Outcome::Failed(summary().unwrap_or(serde_json::Value::Null), why))
        }
    }
}
