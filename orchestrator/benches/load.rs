//! Load benchmark of the job service (issue 7): one orchestrator (`mscale serve`, a real
//! process on 127.0.0.1), 64 lightweight workers (`md-worker`'s coupling service on the null
//! back end, which does no MD work, hosted in this process, each registered with the
//! orchestrator and heartbeating through `md_worker::join`, the code of `md-worker serve
//! --orchestrator`), and 10 jobs queued at
//! once, each followed by its own WatchJob stream.
//!
//! Checks: every job completes; no event is lost: each watch stream (a raw WatchJob stream
//! from `after_sequence` 0, no client-side repair) delivers its job's events numbered 1, 2,
//! 3, ... with no gap and none reported as not retained, from the first (submitted) to the
//! final one, with the state changes in order (queued, running, completed), progress never
//! going backwards, and the final event at the last step (progress is published at most every
//! 100 ms, so the number of steps that had an event of their own is reported, not required);
//! every job's boxes were spread over all the registered workers. Reports the scheduling overhead per step (everything but MD compute,
//! from each job's summary.json), the job set-up time and the hand-over between queued jobs,
//! as one JSON line.
//!
//!   cargo bench -p orchestrator --bench load [-- --workers 64 --jobs 10 --points 128 --steps 50]
//!
//! Exit code 0 when every check holds, 1 otherwise (the report says which).

use anyhow::{Context, Result, bail, ensure};
use mscale_proto::orchestrator::v1 as pb;
use orchestrator::client::Client;
use serde_json::json;
use std::collections::BTreeSet;
use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const TOKEN: &str = "load-bench-token-0123456789abcdef";

struct Args {
    workers: usize,
    jobs: usize,
    points: usize,
    steps: u64,
}

fn args() -> Result<Args> {
    let mut a = Args { workers: 64, jobs: 10, points: 128, steps: 50 };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let mut v = || it.next().with_context(|| format!("{k} needs a value"));
        match k.as_str() {
            "--workers" => a.workers = v()?.parse()?,
            "--jobs" => a.jobs = v()?.parse()?,
            "--points" => a.points = v()?.parse()?,
            "--steps" => a.steps = v()?.parse()?,
            "--bench" => {} // added by `cargo bench`
            other => bail!("unknown argument {other} (expected --workers N --jobs N --points N --steps N)"),
        }
    }
    ensure!(a.workers > 0 && a.jobs > 0 && a.points >= a.workers && a.steps > 0, "need workers, jobs, steps >= 1 and points >= workers");
    Ok(a)
}

/// A 1D copper bar of `points` MD points (one 32-atom box each, never computed: the workers
/// run the null back end), `steps` continuum steps.
fn scene(dir: &Path, points: usize, steps: u64) -> Result<std::path::PathBuf> {
    let pot = Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials/Cu_mishin1.eam.alloy");
    std::fs::copy(&pot, dir.join("Cu_mishin1.eam.alloy")).with_context(|| format!("copy {}", pot.display()))?;
    let length = points as f64 * 2e-9;
    let dt = 10e-15;
    let text = format!(
        r#"schema = 1
name = "load"

[domain]
dimension = 1
min = [0.0]
max = [{length:e}]
cells = [{points}]

[bodies.bar]
shape = "bar"
min = [0.0]
max = [{length:e}]
density = 8935.1
temperature_k = 0.0
material = {{ law = "md", potential = "Cu_mishin1.eam.alloy", lattice = "fcc", lattice_constant_angstrom = 3.615, cells_per_side = 2, relax_steps = 0 }}

[scheme]
method = "ugimp"
particles_per_cell = 1
artificial_viscosity = "linear"
timestep = {dt:e}
end_time = {end:e}

[boundary]
x_min = "reflective"
x_max = "reflective"

[output]
snapshots = 1
vtk = false
plots = false
"#,
        end = dt * steps as f64
    );
    let path = dir.join("load.toml");
    std::fs::write(&path, text)?;
    Ok(path)
}

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_orchestrator(dir: &Path) -> Result<(Server, String)> {
    let token = dir.join("token");
    std::fs::write(&token, TOKEN)?;
    let log = std::fs::File::create(dir.join("serve.log"))?;
    let mut child = Command::new(env!("CARGO_BIN_EXE_mscale"))
        .args(["serve", "--state-dir"])
        .arg(dir.join("state"))
        .args(["--listen", "127.0.0.1:0", "--token-file"])
        .arg(&token)
        // The null back end keeps no state to snapshot: no interval checkpoints.
        .args(["--checkpoint-every", "1000000000"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .context("start mscale serve")?;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().context("stdout")?).read_line(&mut line)?;
    let addr = line.trim().rsplit(' ').next().unwrap_or("").to_string();
    ensure!(addr.contains(':'), "mscale serve said {line:?}; log: {}", std::fs::read_to_string(dir.join("serve.log")).unwrap_or_default());
    Ok((Server(child), addr))
}

/// `n` workers on the null back end, served by `rt`, each joining the orchestrator at `server`
/// exactly as `md-worker serve --orchestrator URL --token-file F --throughput T` does
/// (`md_worker::join`): registration, heartbeats, re-registration. Returns once the
/// orchestrator lists all of them live.
fn start_workers(rt: &tokio::runtime::Runtime, server: &str, token_file: &Path, n: usize) -> Result<Vec<md_worker::join::Join>> {
    let url = format!("http://{server}");
    rt.block_on(async {
        let mut joins = Vec::new();
        for _ in 0..n {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
            let bound = listener.local_addr()?;
            let opts = md_worker::server::ServeOptions { backend: "null".into(), threads: None, device: "null (load benchmark)".into() };
            tokio::spawn(async move {
                let _ = md_worker::server::serve(listener, opts, std::future::pending()).await;
            });
            let args = md_worker::join::JoinArgs {
                orchestrator: Some(url.clone()),
                token_file: Some(token_file.to_path_buf()),
                // Equal throughputs: the boxes should spread evenly.
                throughput: Some(1e9),
                heartbeat_every: 2.0,
                ..Default::default()
            };
            let kind = md_worker::join::WorkerKind {
                backend: "null".into(),
                precision: "double".into(),
                device: "null (load benchmark)".into(),
                threads: None,
            };
            joins.push(md_worker::join::Join::start(&args, bound, kind)?);
        }
        let mut client = pb::orchestrator_client::OrchestratorClient::connect(url.clone()).await?;
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let listed = client.list_workers(pb::ListWorkersRequest {}).await?.into_inner().workers;
            let live = listed.iter().filter(|w| w.state == pb::WorkerState::Live as i32).count();
            if live >= n {
                break;
            }
            for j in &joins {
                j.outcome()?;
            }
            ensure!(Instant::now() < deadline, "only {live} of {n} workers registered within 60 s");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        Ok(joins)
    })
}

/// What one watch stream saw.
#[derive(Default)]
struct Seen {
    /// (state, step) of every event.
    events: Vec<(i32, u64)>,
    /// Sequence number of every event, and how many events said others were not retained.
    sequences: Vec<u64>,
    not_retained: usize,
    steps: u64,
    /// Largest number of workers an event listed, and how many of them held boxes.
    workers: usize,
    workers_with_boxes: usize,
    error: Option<String>,
}

/// Follows one job on a raw WatchJob stream (what the service sends, not repaired by
/// `mscale watch`'s reconnection).
fn watch(server: String, job: String) -> Seen {
    let mut seen = Seen::default();
    let r: Result<()> = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(anyhow::Error::from).and_then(|rt| {
        rt.block_on(async {
            let mut c = pb::orchestrator_client::OrchestratorClient::connect(format!("http://{server}")).await?;
            let mut stream = c.watch_job(pb::WatchJobRequest { job_id: job.clone(), after_sequence: 0 }).await?.into_inner();
            while let Some(ev) = stream.message().await? {
                if ev.kind == pb::JobEventKind::NotRetained as i32 {
                    seen.not_retained += 1;
                    continue;
                }
                seen.sequences.push(ev.sequence);
                seen.events.push((ev.state, ev.step));
                seen.steps = seen.steps.max(ev.steps);
                if ev.workers.len() >= seen.workers {
                    seen.workers = ev.workers.len();
                    seen.workers_with_boxes = ev.workers.iter().filter(|w| w.boxes > 0).count();
                }
            }
            Ok(())
        })
    });
    if let Err(e) = r {
        seen.error = Some(format!("{e:#}"));
    }
    seen
}

fn state_name(s: i32) -> String {
    pb::JobState::try_from(s).map(|s| s.as_str_name().trim_start_matches("JOB_STATE_").to_lowercase()).unwrap_or_else(|_| s.to_string())
}

fn main() -> Result<()> {
    let a = args()?;
    let tmp = tempfile::tempdir()?;
    let scene = scene(tmp.path(), a.points, a.steps)?;
    let (_server, addr) = start_orchestrator(tmp.path())?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let t_reg = Instant::now();
    let ids = start_workers(&rt, &addr, &tmp.path().join("token"), a.workers)?;
    let registration_s = t_reg.elapsed().as_secs_f64();
    let mut client = Client::connect(&addr, Some(TOKEN.to_string()))?;

    // Queue every job at once, each with its watcher.
    let t0 = Instant::now();
    let mut jobs = Vec::new();
    let mut watchers = Vec::new();
    for _ in 0..a.jobs {
        let id = client.submit(&scene, &[], 0, 0)?;
        let (server, job) = (addr.clone(), id.clone());
        watchers.push(std::thread::spawn(move || watch(server, job)));
        jobs.push(id);
    }
    let seen: Vec<Seen> = watchers
        .into_iter()
        .map(|w| w.join().unwrap_or_else(|_| Seen { error: Some("watcher panicked".into()), ..Seen::default() }))
        .collect();
    let total_s = t0.elapsed().as_secs_f64();

    let mut problems = Vec::new();
    let mut per_job = Vec::new();
    let (mut step_overhead, mut coupling, mut setups, mut wall_total) = (Vec::new(), Vec::new(), Vec::new(), 0.0);
    for (id, s) in jobs.iter().zip(&seen) {
        if let Some(e) = &s.error {
            problems.push(format!("{id}: watch failed: {e}"));
        }
        let job = client.get(id)?;
        let state = state_name(job.state);
        if state != "completed" {
            problems.push(format!("{id}: ended {state}: {}", job.error));
        }
        // States never go back; the last one is the job's final state.
        let states: Vec<i32> = s.events.iter().map(|e| e.0).collect();
        if states.windows(2).any(|w| w[1] < w[0]) {
            problems.push(format!("{id}: states out of order: {:?}", states.iter().map(|s| state_name(*s)).collect::<Vec<_>>()));
        }
        if states.last().map(|s| state_name(*s)) != Some(state.clone()) {
            problems.push(format!("{id}: the watch stream did not end with the final state {state}"));
        }
        // Progress events are samples (the service publishes at most one every 100 ms and a
        // watcher sees the latest), so a step may have no event of its own; what must not go
        // missing is a state change, the final event, or progress going backwards.
        // Numbered 1, 2, 3, ... from the first event to the final one: nothing skipped.
        let contiguous = s.not_retained == 0 && !s.sequences.is_empty() && s.sequences.iter().zip(1u64..).all(|(q, k)| *q == k);
        if !contiguous {
            problems.push(format!(
                "{id}: events not numbered 1..n without a gap ({} reported not retained): {:?}",
                s.not_retained, s.sequences
            ));
        }
        let running = s.events.iter().any(|e| e.0 == pb::JobState::Running as i32);
        if !running {
            problems.push(format!("{id}: the watch stream never showed the job running"));
        }
        let steps_seen: Vec<u64> = s.events.iter().map(|e| e.1).collect();
        if steps_seen.windows(2).any(|w| w[1] < w[0]) {
            problems.push(format!("{id}: progress went backwards: {steps_seen:?}"));
        }
        if steps_seen.last().copied() != Some(s.steps) {
            problems.push(format!("{id}: the last event is at step {:?}, the job has {} steps", steps_seen.last(), s.steps));
        }
        let distinct: BTreeSet<u64> = steps_seen.iter().copied().filter(|k| *k > 0).collect();
        if s.workers_with_boxes < a.workers {
            problems.push(format!("{id}: boxes on {} of {} registered workers", s.workers_with_boxes, a.workers));
        }
        let summary: serde_json::Value =
            client.fetch(id, "summary.json").ok().and_then(|b| serde_json::from_slice(&b).ok()).unwrap_or_default();
        let steps_run = summary["steps"].as_f64().unwrap_or(0.0).max(1.0);
        let t = &summary["time_breakdown_s"];
        let wall = summary["wall_seconds"].as_f64().unwrap_or(f64::NAN);
        let (setup, md, output) =
            (t["setup"].as_f64().unwrap_or(0.0), t["md"].as_f64().unwrap_or(0.0), t["output"].as_f64().unwrap_or(0.0));
        let transfer = t["serialisation_transfer_idle"].as_f64().unwrap_or(f64::NAN);
        let step_ms = (wall - setup - output - md) / steps_run * 1e3;
        wall_total += wall;
        step_overhead.push(step_ms);
        coupling.push(transfer / steps_run * 1e3);
        setups.push(setup);
        per_job.push(json!({
            "job": id, "state": state, "events": s.events.len(), "first_sequence": s.sequences.first(), "last_sequence": s.sequences.last(), "contiguous": contiguous,
            "steps": s.steps, "steps_with_an_event": distinct.len(),
            "workers_with_boxes": s.workers_with_boxes, "wall_s": wall, "setup_s": setup,
            "step_overhead_ms": step_ms, "coupling_ms_per_step": transfer / steps_run * 1e3,
        }));
    }
    let median = |v: &[f64]| {
        let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let report = json!({
        "what": "load: one orchestrator, null-back-end workers, queued jobs, one watch stream per job",
        "workers": a.workers, "registered": ids.len(), "registration_s": registration_s,
        "jobs": a.jobs, "points_per_job": a.points, "steps_per_job": a.steps,
        "total_s": total_s,
        "jobs_completed": per_job.iter().filter(|j| j["state"] == "completed").count(),
        // Watch streams that got every event of their job, 1..n with no gap, to the final one.
        "watchers_contiguous": per_job.iter().filter(|j| j["contiguous"] == true).count(),
        "events_received": seen.iter().map(|s| s.sequences.len()).sum::<usize>(),
        // Per step, everything but MD compute (continuum + coupling), the workers doing no MD.
        "median_step_overhead_ms": median(&step_overhead),
        // Of which the round trip to the workers (serialisation, transfer, waiting).
        "median_coupling_ms_per_step": median(&coupling),
        // Opening a job's boxes on the workers (potential upload included).
        "median_job_setup_s": median(&setups),
        // Time between jobs: the queue hand-over, outside any job's run.
        "handover_s_per_job": (total_s - wall_total) / a.jobs as f64,
        "problems": problems,
        "per_job": per_job,
        "command": format!("cargo bench -p orchestrator --bench load -- --workers {} --jobs {} --points {} --steps {}", a.workers, a.jobs, a.points, a.steps),
    });
    println!("{report}");
    drop(rt);
    if !report["problems"].as_array().is_some_and(|p| p.is_empty()) {
        eprintln!(
            "load: {} problem(s):\n  {}",
            problems_len(&report),
            report["problems"].as_array().map(|p| p.iter().filter_map(|x| x.as_str()).collect::<Vec<_>>().join("\n  ")).unwrap_or_default()
        );
        std::process::exit(1);
    }
    Ok(())
}

fn problems_len(r: &serde_json::Value) -> usize {
    r["problems"].as_array().map_or(0, |p| p.len())
}
