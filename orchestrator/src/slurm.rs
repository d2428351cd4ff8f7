//! Worker pools through Slurm, the way dask-jobqueue starts Dask workers: `mscale workers
//! launch --slurm` submits one sbatch job per pool (N workers, each an MPI job step of R ranks
//! with G GPUs), follows it through `squeue` (then `scontrol show job`, then `sacct`, whichever
//! still knows it), waits until its workers have registered with the orchestrator and prints
//! the Slurm job id, the pool's name from then on. `mscale workers release POOL` drains the
//! pool's workers (they take no new job), waits until none holds a job, and `scancel`s it;
//! `mscale workers pools` lists the pools Slurm runs. A pool whose Slurm job dies (scancel, a
//! time limit, a node failure) is what the orchestrator already handles: its workers stop
//! answering, are declared lost, and their boxes move to the other workers.
//!
//! A pool's workers are known by their address: worker k of a pool listens on port BASE + k
//! and advertises `NODE:BASE+k`, NODE being the node Slurm put it on. BASE (one range of
//! [`PORTS_PER_POOL`] ports per pool from [`FIRST_PORT`], or `--port-base`) and the worker
//! count are kept in the Slurm job's comment, so any later `mscale` finds them again.

use crate::client::Client;
use crate::exit;
use anyhow::{Context, Result, bail};
use mscale_proto::orchestrator::v1 as pb;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// Slurm job name of every pool.
pub const JOB_NAME: &str = "mscale-pool";
/// First port of the pools' ranges, and the size of each range. The ranges lie below Linux's
/// default ephemeral range (32768-60999, `/proc/sys/net/ipv4/ip_local_port_range`), where any
/// outgoing connection on a node may hold a port and a worker's listen would fail with
/// "Address already in use" (seen once in CI with the old base 52000): 24000 + 100 k, k < 87.
pub const FIRST_PORT: u16 = 24000;
/// The end (exclusive) of the default ranges: the start of the ephemeral range.
pub const LAST_PORT_END: u16 = 32768;
pub const PORTS_PER_POOL: u16 = 100;

/// What `mscale workers launch --slurm` asks Slurm for.
#[derive(Clone, Debug)]
pub struct PoolRequest {
    pub workers: u32,
    pub gpus_per_worker: u32,
    pub ranks_per_worker: u32,
    pub threads_per_rank: u32,
    pub partition: Option<String>,
    pub time: Option<String>,
    /// The md-worker program (on a path every node sees); default: the one next to `mscale`.
    pub worker_bin: Option<PathBuf>,
    /// `srun --mpi` plugin of the worker steps.
    pub mpi: String,
    pub port_base: Option<u16>,
    /// Where the batch script and the job's output go.
    pub dir: PathBuf,
    /// Wait this long for the pool's workers to register (the job may queue first).
    pub wait: Duration,
    /// More sbatch options, passed as they are (`--account=A`, `--qos=Q`, ...).
    pub sbatch_args: Vec<String>,
}

/// How the pool's workers and the launcher reach the orchestrator.
pub struct Orchestrator<'a> {
    pub server: &'a str,
    pub token_file: Option<&'a Path>,
    pub ca_file: Option<&'a Path>,
}

impl Orchestrator<'_> {
    fn client(&self) -> Result<Client> {
        Client::connect_with(self.server, crate::client::token(self.token_file)?, self.ca_file)
    }

    /// The URL the workers join (`--orchestrator`).
    fn url(&self) -> String {
        if self.server.contains("://") {
            self.server.to_string()
        } else if self.ca_file.is_some() {
            format!("https://{}", self.server)
        } else {
            format!("http://{}", self.server)
        }
    }
}

fn bad(msg: String) -> Result<i32> {
    eprintln!("mscale: {msg}");
    Ok(exit::BAD_INPUT)
}

/// A word for a bash script, single-quoted.
fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// Runs a Slurm command; its stdout, or an error naming it with its stderr.
fn slurm(program: &str, args: &[String]) -> Result<String> {
    let o = Command::new(program).args(args).output().with_context(|| {
        format!("cannot run {program}: is Slurm installed here? (a single-node cluster for tests: bash deploy/setup.sh slurm)")
    })?;
    if !o.status.success() {
        bail!("{program} {} failed: {}", args.join(" "), String::from_utf8_lossy(&o.stderr).trim());
    }
    Ok(String::from_utf8_lossy(&o.stdout).into_owned())
}

/// A Slurm job as far as Slurm still knows it.
#[derive(Clone, Debug, PartialEq)]
pub struct JobInfo {
    /// PENDING, RUNNING, COMPLETED, CANCELLED, FAILED, TIMEOUT, NODE_FAIL, ...
    pub state: String,
    /// Why it pends, or the nodes it runs on (squeue's %R).
    pub reason: String,
    pub nodes: Vec<String>,
    pub comment: String,
}

impl JobInfo {
    pub fn is_final(&self) -> bool {
        !["PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "SUSPENDED", "REQUEUED", "RESIZING"].iter().any(|s| self.state.starts_with(s))
    }
}

/// The job's state from squeue; once squeue has forgotten it, from `scontrol show job` (kept for
/// MinJobAge), then from `sacct` (where accounting is configured). None when no one knows it.
pub fn job_info(job: &str) -> Option<JobInfo> {
    let args: Vec<String> = ["-h", "-j", job, "-o", "%T|%R|%N|%k"].iter().map(|s| s.to_string()).collect();
    if let Ok(out) = slurm("squeue", &args)
        && let Some(line) = out.lines().next()
    {
        let f: Vec<&str> = line.splitn(4, '|').collect();
        if f.len() == 4 {
            return Some(JobInfo { state: f[0].into(), reason: f[1].into(), nodes: hostnames(f[2]), comment: f[3].into() });
        }
    }
    if let Ok(out) = slurm("scontrol", &["show".into(), "job".into(), job.into()]) {
        let field = |k: &str| out.split_whitespace().find_map(|w| w.strip_prefix(k)).unwrap_or("").to_string();
        let comment = out.lines().find_map(|l| l.trim().strip_prefix("Comment=")).unwrap_or("").to_string();
        if !field("JobState=").is_empty() {
            return Some(JobInfo { state: field("JobState="), reason: field("Reason="), nodes: hostnames(&field("NodeList=")), comment });
        }
    }
    let args: Vec<String> = ["-n", "-X", "-P", "-j", job, "-o", "State,NodeList,Comment"].iter().map(|s| s.to_string()).collect();
    let out = slurm("sacct", &args).ok()?;
    let f: Vec<&str> = out.lines().next()?.splitn(3, '|').collect();
    let state = f.first()?.split_whitespace().next()?.to_string();
    Some(JobInfo { state, reason: String::new(), nodes: hostnames(f.get(1).unwrap_or(&"")), comment: f.get(2).unwrap_or(&"").to_string() })
}

/// `scontrol show hostnames` of a node list (`vm`, `n[1-3]`); empty for none.
fn hostnames(list: &str) -> Vec<String> {
    let list = list.trim();
    if list.is_empty() || list == "(null)" || list.starts_with('(') {
        return Vec::new();
    }
    match slurm("scontrol", &["show".into(), "hostnames".into(), list.into()]) {
        Ok(out) => out.lines().map(|l| l.trim().to_string()).filter(|l| !l.is_empty()).collect(),
        Err(_) => vec![list.to_string()],
    }
}

/// `base=B workers=N` of a pool's comment.
fn parse_comment(comment: &str) -> Option<(u16, u32)> {
    let rest = comment.strip_prefix("mscale-pool ")?;
    let get = |k: &str| rest.split_whitespace().find_map(|w| w.strip_prefix(k));
    Some((get("base=")?.parse().ok()?, get("workers=")?.parse().ok()?))
}

/// The pools Slurm runs or queues: (job id, state, comment).
fn running_pools() -> Result<Vec<(String, JobInfo)>> {
    let args: Vec<String> = ["-h", "--name", JOB_NAME, "-o", "%i|%T|%R|%N|%k"].iter().map(|s| s.to_string()).collect();
    Ok(slurm("squeue", &args)?
        .lines()
        .filter_map(|l| {
            let f: Vec<&str> = l.splitn(5, '|').collect();
            (f.len() == 5).then(|| {
                (f[0].to_string(), JobInfo { state: f[1].into(), reason: f[2].into(), nodes: hostnames(f[3]), comment: f[4].into() })
            })
        })
        .collect())
}

/// The orchestrator's workers that belong to a pool: on one of its nodes, on its ports.
fn pool_workers(all: &[pb::Worker], nodes: &[String], base: u16, n: u32) -> Vec<pb::Worker> {
    all.iter()
        .filter(|w| {
            w.address.rsplit_once(':').is_some_and(|(host, port)| {
                nodes.iter().any(|n| n == host) && port.parse::<u32>().is_ok_and(|p| p >= base as u32 && p < base as u32 + n)
            })
        })
        .cloned()
        .collect()
}

fn is_live(w: &pb::Worker) -> bool {
    w.state == pb::WorkerState::Live as i32
}

/// The batch script of a pool: one srun step per worker.
pub fn batch_script(req: &PoolRequest, url: &str, worker_bin: &Path, token_file: &Path, ca_file: Option<&Path>, base: u16) -> String {
    let device = if req.gpus_per_worker > 0 { "cuda" } else { "cpu" };
    let gpus = if req.gpus_per_worker > 0 { format!(" --gpus={}", req.gpus_per_worker) } else { String::new() };
    let ca = ca_file.map(|c| format!(" --ca-file {}", quote(&c.display().to_string()))).unwrap_or_default();
    // The inner command runs under bash -c in each task, where $SLURMD_NODENAME is that task's node.
    let inner = format!(
        "exec \"$0\" serve --listen \"0.0.0.0:$1\" --device {device} --threads {threads} --orchestrator {url} --advertise \"$SLURMD_NODENAME:$1\" --token-file {token}{ca}",
        threads = req.threads_per_rank,
        url = quote(url),
        token = quote(&token_file.display().to_string()),
    );
    format!(
        r#"#!/usr/bin/env bash
# Written by `mscale workers launch --slurm`: {n} md-worker(s) of {r} rank(s) x {t} thread(s){g},
# joining {url}. Worker k is one MPI job step (srun --mpi={mpi}) on port {base} + k.
set -u
pids=()
for k in $(seq 0 {last}); do
  port=$(( {base} + k ))
  srun --nodes=1 --ntasks={r} --cpus-per-task={t}{gpus} --exact --mpi={mpi} --kill-on-bad-exit=1 --job-name="md-worker-$k" \
    bash -c {inner} {bin} "$port" &
  pids+=("$!")
done
wait "${{pids[@]}}"
"#,
        n = req.workers,
        r = req.ranks_per_worker,
        t = req.threads_per_rank,
        g = if req.gpus_per_worker > 0 { format!(" and {} GPU(s)", req.gpus_per_worker) } else { String::new() },
        mpi = quote(&req.mpi),
        last = req.workers - 1,
        inner = quote(&inner),
        bin = quote(&worker_bin.display().to_string()),
    )
}

/// `mscale workers launch --slurm`: submits the pool, follows it until its workers have
/// registered (exit 0, the Slurm job id on stdout), or until its job ended or `--wait` passed
/// (exit 1, the pool cancelled).
pub fn launch(orch: &Orchestrator, req: &PoolRequest) -> Result<i32> {
    if req.workers == 0 || req.ranks_per_worker == 0 || req.threads_per_rank == 0 {
        return bad(format!(
            "--workers {}, --ranks-per-worker {}, --threads-per-rank {}: each must be at least 1",
            req.workers, req.ranks_per_worker, req.threads_per_rank
        ));
    }
    if req.workers as u64 > PORTS_PER_POOL as u64 {
        return bad(format!("--workers {}: at most {PORTS_PER_POOL} workers per pool (launch more pools)", req.workers));
    }
    let Some(token_file) = orch.token_file else {
        return bad("--token-file is required with --slurm: the pool's workers read the orchestrator's token from that file (on a file system every node sees)".into());
    };
    let token_file = std::fs::canonicalize(token_file).with_context(|| format!("--token-file {}", token_file.display()))?;
    let ca_file = orch.ca_file.map(std::fs::canonicalize).transpose().context("--ca-file")?;
    let worker_bin = match &req.worker_bin {
        Some(b) => b.clone(),
        None => std::env::current_exe()?.with_file_name("md-worker"),
    };
    if !worker_bin.is_file() {
        return bad(format!("{}: no md-worker program there (give --worker-bin PATH, on a path every node sees)", worker_bin.display()));
    }
    let worker_bin = std::fs::canonicalize(&worker_bin)?;
    // The orchestrator answers before anything is queued.
    let mut client = orch.client()?;
    client.health().context("the orchestrator does not answer")?;
    let base = match req.port_base {
        Some(b) => b,
        None => {
            let used: Vec<u16> = running_pools()?.iter().filter_map(|(_, j)| parse_comment(&j.comment)).map(|(b, _)| b).collect();
            (FIRST_PORT..LAST_PORT_END - PORTS_PER_POOL + 1)
                .step_by(PORTS_PER_POOL as usize)
                .find(|b| !used.contains(b))
                .context("no free port range for another pool below the ephemeral ports: give --port-base")?
        }
    };
    std::fs::create_dir_all(&req.dir).with_context(|| format!("--dir {}", req.dir.display()))?;
    let dir = std::fs::canonicalize(&req.dir)?;
    let script = dir.join(format!("pool-{base}.sbatch"));
    std::fs::write(&script, batch_script(req, &orch.url(), &worker_bin, &token_file, ca_file.as_deref(), base))
        .with_context(|| format!("cannot write {}", script.display()))?;
    let mut args = vec![
        "--parsable".to_string(),
        format!("--job-name={JOB_NAME}"),
        format!("--comment=mscale-pool base={base} workers={}", req.workers),
        format!("--ntasks={}", req.workers * req.ranks_per_worker),
        format!("--cpus-per-task={}", req.threads_per_rank),
        format!("--output={}", dir.join("pool-%j.out").display()),
    ];
    if req.gpus_per_worker > 0 {
        args.push(format!("--gpus={}", req.gpus_per_worker * req.workers));
    }
    if let Some(p) = &req.partition {
        args.push(format!("--partition={p}"));
    }
    if let Some(t) = &req.time {
        args.push(format!("--time={t}"));
    }
    args.extend(req.sbatch_args.iter().cloned());
    args.push(script.display().to_string());
    let out = match slurm("sbatch", &args) {
        Ok(o) => o,
        // sbatch refuses what the cluster cannot give (a partition, a time, GPUs): the user's to fix.
        Err(e) if e.to_string().contains("failed:") => return bad(format!("{e:#}")),
        Err(e) => return Err(e),
    };
    let job = out.trim().split(';').next().unwrap_or("").to_string();
    anyhow::ensure!(!job.is_empty(), "sbatch printed no job id: {out:?}");
    eprintln!(
        "mscale: pool {job}: submitted {} worker(s) (ports {base}..{}), output {}",
        req.workers,
        base as u32 + req.workers - 1,
        dir.join(format!("pool-{job}.out")).display()
    );
    let start = Instant::now();
    let mut last = String::new();
    loop {
        let info = job_info(&job);
        let state = info.as_ref().map_or("UNKNOWN".to_string(), |i| i.state.clone());
        let seen = format!("{state} {}", info.as_ref().map_or("", |i| i.reason.as_str()));
        if seen != last {
            eprintln!("mscale: pool {job}: {}", seen.trim());
            last = seen;
        }
        match &info {
            Some(i) if i.is_final() => {
                let output = std::fs::read_to_string(dir.join(format!("pool-{job}.out"))).unwrap_or_default();
                let tail: Vec<&str> = output.lines().rev().take(15).collect::<Vec<_>>().into_iter().rev().collect();
                bail!("pool {job}: the Slurm job ended ({}) before its workers registered; its output ends:\n{}", i.state, tail.join("\n"));
            }
            Some(i) if i.state == "RUNNING" => {
                let all = client.workers()?;
                let mine = pool_workers(&all, &i.nodes, base, req.workers);
                let live: Vec<&pb::Worker> = mine.iter().filter(|w| is_live(w)).collect();
                if live.len() as u32 >= req.workers {
                    for w in &live {
                        eprintln!("mscale: pool {job}: worker {} live at {} ({})", w.id, w.address, w.device);
                    }
                    println!("{job}");
                    return Ok(exit::OK);
                }
            }
            _ => {}
        }
        if start.elapsed() > req.wait {
            let _ = slurm("scancel", std::slice::from_ref(&job));
            bail!("pool {job}: its workers did not register within {:?} ({last}); the pool was cancelled", req.wait);
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// `mscale workers release POOL`: drain the pool's workers, wait until none holds a job (at
/// most `drain_for`; 0: do not wait), scancel the Slurm job and wait until it ended.
pub fn release(orch: &Orchestrator, pool: &str, drain_for: Duration) -> Result<i32> {
    let Some(info) = job_info(pool) else {
        return bad(format!("pool {pool}: Slurm knows no such job (see `mscale workers pools`)"));
    };
    let Some((base, n)) = parse_comment(&info.comment) else {
        return bad(format!("Slurm job {pool} is not a pool of `mscale workers launch --slurm` (its comment is {:?})", info.comment));
    };
    if info.is_final() {
        eprintln!("mscale: pool {pool}: its Slurm job already ended ({})", info.state);
        return Ok(exit::OK);
    }
    let mut client = orch.client()?;
    let mine: Vec<pb::Worker> = pool_workers(&client.workers()?, &info.nodes, base, n).into_iter().filter(is_live).collect();
    for w in &mine {
        client.drain(&w.id).with_context(|| format!("draining worker {}", w.id))?;
        eprintln!("mscale: pool {pool}: worker {} at {} drained", w.id, w.address);
    }
    let start = Instant::now();
    loop {
        let busy: Vec<String> = pool_workers(&client.workers()?, &info.nodes, base, n)
            .into_iter()
            .filter(|w| !w.job_id.is_empty() && mine.iter().any(|m| m.id == w.id))
            .map(|w| format!("{} (job {})", w.id, w.job_id))
            .collect();
        if busy.is_empty() {
            break;
        }
        if start.elapsed() >= drain_for {
            eprintln!(
                "mscale: pool {pool}: {} still hold a job after {:?}; cancelling anyway (their boxes move to other workers)",
                busy.join(", "),
                drain_for
            );
            break;
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    slurm("scancel", &[pool.to_string()])?;
    let start = Instant::now();
    loop {
        match job_info(pool) {
            Some(i) if !i.is_final() => {}
            Some(i) => {
                eprintln!("mscale: pool {pool}: released ({})", i.state);
                return Ok(exit::OK);
            }
            None => {
                eprintln!("mscale: pool {pool}: released");
                return Ok(exit::OK);
            }
        }
        if start.elapsed() > Duration::from_secs(120) {
            bail!("pool {pool}: still not ended 120 s after scancel");
        }
        std::thread::sleep(Duration::from_millis(300));
    }
}

/// `mscale workers pools`: every pool Slurm runs or queues, with its live workers.
pub fn pools(orch: &Orchestrator) -> Result<i32> {
    let pools = running_pools()?;
    if pools.is_empty() {
        println!("no pools");
        return Ok(exit::OK);
    }
    let all = orch.client().and_then(|mut c| c.workers()).unwrap_or_default();
    for (job, info) in pools {
        let (base, n) = parse_comment(&info.comment).unwrap_or((0, 0));
        let live = pool_workers(&all, &info.nodes, base, n).iter().filter(|w| is_live(w)).count();
        println!("{job}  {:<10} {live}/{n} workers live  ports {base}..{}  {}", info.state, base as u32 + n.max(1) - 1, info.reason);
    }
    Ok(exit::OK)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pools_comment_and_its_workers_by_address() {
        assert_eq!(parse_comment("mscale-pool base=52100 workers=3"), Some((52100, 3)));
        assert_eq!(parse_comment("something else"), None);
        let w = |id: &str, addr: &str| pb::Worker { id: id.into(), address: addr.into(), ..Default::default() };
        let all = [w("a", "n1:52100"), w("b", "n2:52102"), w("c", "n1:52103"), w("d", "n3:52100"), w("e", "n1:52000")];
        let ids: Vec<String> = pool_workers(&all, &["n1".into(), "n2".into()], 52100, 3).into_iter().map(|w| w.id).collect();
        assert_eq!(ids, ["a", "b"]);
    }

    #[test]
    fn the_batch_script_quotes_what_it_is_given() {
        let req = PoolRequest {
            workers: 2,
            gpus_per_worker: 1,
            ranks_per_worker: 2,
            threads_per_rank: 3,
            partition: None,
            time: None,
            worker_bin: None,
            mpi: "pmi2".into(),
            port_base: None,
            dir: PathBuf::from("."),
            wait: Duration::from_secs(1),
            sbatch_args: vec![],
        };
        let s = batch_script(&req, "https://h:1", Path::new("/o'k/md-worker"), Path::new("/t"), None, 52000);
        assert!(s.contains("--ntasks=2 --cpus-per-task=3 --gpus=1 --exact --mpi='pmi2'"), "{s}");
        assert!(s.contains(r"'/o'\''k/md-worker'"), "{s}");
        assert!(s.contains("--device cuda --threads 3"), "{s}");
        let o = Command::new("bash").arg("-n").arg("/dev/stdin").stdin(std::process::Stdio::piped()).spawn().and_then(|mut c| {
            use std::io::Write;
            c.stdin.take().expect("stdin").write_all(s.as_bytes())?;
            c.wait()
        });
        assert!(o.expect("bash -n").success(), "{s}");
    }
}
