//! `mscale`: run and check scenes (later: serve, submit, status, watch, cancel, fetch, report).

use clap::{Parser, Subcommand};
use orchestrator::loaded::Loaded;
use orchestrator::{exit, run};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "mscale", version, about = "Multiscale DDMP + MD simulations of materials under extreme deformation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a scene in this process (the embedded default).
    Run {
        /// Scene file (TOML); with --resume, the run directory's scene.resolved.toml by default.
        #[arg(required_unless_present = "resume")]
        scene: Option<PathBuf>,
        /// Run directory (default runs/<scene>-<timestamp>).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Override a scene field: --set dotted.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Running MD workers (`md-worker serve`) to use instead of in-process MD: HOST:PORT,...
        #[arg(long, value_delimiter = ',', value_name = "HOST:PORT,...")]
        workers: Vec<String>,
        /// Write a checkpoint every N steps into <out>/checkpoints (the two newest are kept).
        /// SIGINT/SIGTERM always write one and stop the run (exit code 1).
        #[arg(long, value_name = "N", default_value_t = 0)]
        checkpoint_every: u64,
        /// Continue the run in DIR from its newest good checkpoint.
        #[arg(long, value_name = "DIR", conflicts_with = "out")]
        resume: Option<PathBuf>,
        /// Bound on each call to a worker: `auto` (max(60 s, 10x the call's expected time at the
        /// worker's measured throughput)) or SECONDS. A worker past it is lost and its boxes are
        /// replayed on the other workers.
        #[arg(long, value_name = "auto|SECONDS", default_value = "auto", value_parser = md_worker::recovery::StepDeadline::parse)]
        step_deadline: md_worker::recovery::StepDeadline,
        /// Under `mpirun`/`srun` (feature `mpi`): share the grid's tiles out over the ranks again
        /// every N steps by the cost each rank measured (0: even blocks of tiles, never moved).
        /// The results do not depend on it.
        #[arg(long, value_name = "N", default_value_t = continuum::solver::DEFAULT_REBALANCE_EVERY)]
        rebalance_every: u64,
        /// Print the progress after every step as one JSON line on stdout (rank 0; the job
        /// service reads it from the runs it starts over MPI ranks).
        #[arg(long)]
        progress_json: bool,
        /// Stop as on SIGTERM (checkpoint after the current step, exit code 1) once this file
        /// exists (checked by rank 0 every 100 ms; every rank stops after the same step).
        #[arg(long, value_name = "FILE")]
        stop_file: Option<PathBuf>,
    },
    /// Run the job service (mscale.orchestrator.v1) with gRPC health and reflection.
    Serve {
        /// State directory: the job store (jobs.sqlite), job inputs and run directories.
        #[arg(long = "state", visible_alias = "state-dir", value_name = "DIR")]
        state: PathBuf,
        /// Address to listen on: a loopback address, or any with --tls-cert and --tls-key.
        #[arg(long, default_value = orchestrator::client::DEFAULT_SERVER)]
        listen: String,
        /// File holding the bearer token of mutating calls (default: one is generated into <state>/token).
        #[arg(long, value_name = "FILE")]
        token_file: Option<PathBuf>,
        /// Checkpoint interval (steps) of jobs that name none.
        #[arg(long, value_name = "N", default_value_t = orchestrator::service::DEFAULT_CHECKPOINT_EVERY)]
        checkpoint_every: u64,
        /// Serve over TLS with this PEM certificate chain (needs --tls-key; required off loopback).
        #[arg(long, value_name = "PEM", requires = "tls_key")]
        tls_cert: Option<PathBuf>,
        /// PEM private key of --tls-cert.
        #[arg(long, value_name = "PEM", requires = "tls_cert")]
        tls_key: Option<PathBuf>,
        /// Start N `md-worker serve` processes on this machine (the md-worker program next to
        /// this one) that join the pool; they are killed when the orchestrator exits.
        #[arg(long, value_name = "N", default_value_t = 0)]
        local_workers: usize,
        /// Declare a worker lost after this many seconds without a heartbeat.
        #[arg(long, value_name = "SECONDS", default_value_t = orchestrator::service::workers::DEFAULT_TIMEOUT_S)]
        worker_timeout: f64,
        /// Bound on each call to a worker: `auto` (max(60 s, 10x the call's expected time at the
        /// worker's measured throughput)) or SECONDS. A worker past it is lost and its boxes are
        /// replayed on the job's other workers.
        #[arg(long, value_name = "auto|SECONDS", default_value = "auto", value_parser = md_worker::recovery::StepDeadline::parse)]
        step_deadline: md_worker::recovery::StepDeadline,
        /// Serve the dashboard and Prometheus `/metrics` over HTTP on this address (HTTPS with
        /// --tls-cert; the same token). Prints `mscale serve: dashboard and metrics on URL`
        /// after the `listening on` line.
        #[arg(long, value_name = "ADDR")]
        http: Option<String>,
        #[command(flatten)]
        access: Access,
        /// The workers the state directory knows from an earlier run are gone (they ran in a
        /// batch allocation that ended): declare them lost at start, before any job resumes,
        /// instead of waiting out their heartbeat timeout.
        #[arg(long)]
        forget_workers: bool,
        /// Run jobs submitted with `--ranks N` (N > 1) as `MPIRUN -np N PATH run ...`: PATH is
        /// an `mscale` built with the cargo feature `mpi` (`cargo build --release -p
        /// orchestrator --features mpi`). Without it such jobs are refused.
        #[arg(long, value_name = "PATH")]
        mpi_mscale: Option<PathBuf>,
        /// The MPI launcher's words before `-np N`, split as a shell would (e.g. `mpirun
        /// --allow-run-as-root --oversubscribe`, or `srun --mpi=pmi2` inside an allocation).
        #[arg(long, value_name = "COMMAND", default_value = "mpirun", requires = "mpi_mscale")]
        mpirun: String,
    },
    /// List the workers registered with a running `mscale serve`; launch and release worker
    /// pools through Slurm.
    Workers {
        #[command(subcommand)]
        pools: Option<WorkersCommand>,
        #[command(flatten)]
        conn: Conn,
    },
    /// Drain a worker: it gets no new jobs and finishes what it holds.
    Drain {
        worker: String,
        #[command(flatten)]
        conn: Conn,
    },
    /// Submit a scene as a job to a running `mscale serve`; prints the job id.
    Submit {
        scene: PathBuf,
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Higher runs first.
        #[arg(long, default_value_t = 0)]
        priority: i32,
        /// Checkpoint interval in steps (0: the server's default).
        #[arg(long, value_name = "N", default_value_t = 0)]
        checkpoint_every: u64,
        /// Workers to run on: a number, or `all` (every worker free when the job starts). Jobs
        /// run side by side on disjoint sets of workers.
        #[arg(long, value_name = "N|all", default_value = "all", value_parser = parse_workers)]
        workers: u32,
        /// MPI ranks to run the job's continuum over (the orchestrator needs `serve
        /// --mpi-mscale`); 1 runs it in the orchestrator's process.
        #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=4096))]
        ranks: u32,
        #[command(flatten)]
        conn: Conn,
    },
    /// Show one job, or list every job.
    Status {
        job: Option<String>,
        #[command(flatten)]
        conn: Conn,
    },
    /// Follow a job with a progress bar; exit code 0 when it completed, 1 otherwise. Every
    /// event is numbered; a broken stream (the orchestrator restarted) is resumed where it broke.
    Watch {
        job: String,
        /// Print every event on stdout: `event SEQ KIND STATE step S/N MESSAGE`.
        #[arg(long)]
        events: bool,
        /// Keep reconnecting this long (s) after the stream broke before giving up (exit 1).
        #[arg(long, value_name = "SECONDS", default_value_t = 60.0)]
        reconnect_for: f64,
        #[command(flatten)]
        conn: Conn,
    },
    /// Cancel a job (a running one checkpoints first).
    Cancel {
        job: String,
        #[command(flatten)]
        conn: Conn,
    },
    /// Copy one file of a job's run directory (summary.json, snapshots/index.csv, ...) to
    /// `--out PATH`, or without FILE every file of it into the directory `--out DIR`.
    Fetch {
        job: String,
        file: Option<String>,
        #[arg(long, value_name = "PATH")]
        out: PathBuf,
        #[command(flatten)]
        conn: Conn,
    },
    /// Check that an orchestrator answers (gRPC health); exit code 0 when it serves.
    Health {
        #[command(flatten)]
        conn: Conn,
    },
    /// Reports over many runs of a scene.
    #[command(subcommand)]
    Report(ReportCommand),
    /// Validate a scene and print it with every default filled, and the size of the work.
    Check {
        scene: PathBuf,
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Also predict the MD atom-steps, memory and wall time from a throughput measured now.
        #[arg(long)]
        estimate: bool,
    },
}

/// Users and limits of `mscale serve`.
#[derive(clap::Args)]
struct Access {
    /// Users file (TOML, `[[user]]` tables of name, role admin|user|worker, token_sha256 and
    /// optional max_jobs, max_upload_bytes, max_snapshots); read again on SIGHUP. Instead of
    /// --token-file: every call then needs a user's token.
    #[arg(long, value_name = "FILE", conflicts_with = "token_file")]
    users: Option<PathBuf>,
    /// Jobs a user may have queued or running at once (default: no limit).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    max_jobs_per_user: Option<u64>,
    /// Bytes a job may upload: its scene and the files it names (default: no limit below the
    /// 64 MiB message bound).
    #[arg(long, value_name = "BYTES")]
    max_upload_bytes: Option<u64>,
    /// Snapshots a job may write (`output.snapshots`; default: no limit).
    #[arg(long, value_name = "N")]
    max_snapshots: Option<u64>,
    /// Mutual TLS: every client and worker must present a certificate signed by this PEM
    /// authority (needs --tls-cert and --tls-key; local workers present the server's own).
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_client_ca: Option<PathBuf>,
}

impl Access {
    fn options(self) -> orchestrator::service::AccessOptions {
        orchestrator::service::AccessOptions {
            users_file: self.users,
            client_ca: self.tls_client_ca,
            limits: orchestrator::service::Limits {
                max_jobs: self.max_jobs_per_user,
                max_upload_bytes: self.max_upload_bytes,
                max_snapshots: self.max_snapshots,
            },
        }
    }
}

/// `--workers N|all` (all: 0).
fn parse_workers(s: &str) -> Result<u32, String> {
    if s == "all" {
        return Ok(0);
    }
    match s.parse::<u32>() {
        Ok(n) if n > 0 => Ok(n),
        _ => Err(format!("{s:?} is neither a number of workers (1 or more) nor `all`")),
    }
}

/// How a client verb reaches the orchestrator.
#[derive(clap::Args)]
struct Conn {
    /// Orchestrator address (HOST:PORT or http://HOST:PORT).
    #[arg(long, default_value = orchestrator::client::DEFAULT_SERVER)]
    server: String,
    /// File holding the bearer token (default: the MSCALE_TOKEN variable).
    #[arg(long, value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// Connect over TLS, trusting this PEM certificate authority.
    #[arg(long, value_name = "PEM", env = "MSCALE_CA_FILE")]
    ca_file: Option<PathBuf>,
    /// Present this PEM client certificate (mutual TLS: `serve --tls-client-ca`); needs
    /// --ca-file and --client-key.
    #[arg(long, value_name = "PEM", env = "MSCALE_CLIENT_CERT", requires_all = ["ca_file", "client_key"])]
    client_cert: Option<PathBuf>,
    /// PEM private key of --client-cert.
    #[arg(long, value_name = "PEM", env = "MSCALE_CLIENT_KEY", requires = "client_cert")]
    client_key: Option<PathBuf>,
}

impl Conn {
    /// Installs --ca-file for the client verb.
    fn ca(&self) -> anyhow::Result<()> {
        if let Some(ca) = &self.ca_file {
            orchestrator::client::use_ca_file(ca.clone());
        }
        if let (Some(c), Some(k)) = (&self.client_cert, &self.client_key) {
            orchestrator::client::use_client_identity(c.clone(), k.clone());
        }
        Ok(())
    }
}

#[derive(Subcommand)]
enum WorkersCommand {
    /// Submit a pool of md-workers as one sbatch job (each worker an MPI job step), follow it
    /// through squeue until its workers have registered with the orchestrator; prints the
    /// Slurm job id, the pool's name for `release`.
    Launch {
        /// Through Slurm (sbatch, squeue, scancel): the one launcher there is.
        #[arg(long, required = true)]
        slurm: bool,
        /// Workers in the pool.
        #[arg(long, value_name = "N")]
        workers: u32,
        /// GPUs per worker (its device is then cuda; 0: cpu).
        #[arg(long, value_name = "G", default_value_t = 0)]
        gpus_per_worker: u32,
        /// MPI ranks per worker (more than 1 needs an md-worker built with the feature `mpi`).
        #[arg(long, value_name = "R", default_value_t = 1)]
        ranks_per_worker: u32,
        /// CPUs (threads) per rank.
        #[arg(long, value_name = "T", default_value_t = 1)]
        threads_per_rank: u32,
        /// Slurm partition.
        #[arg(long, value_name = "P")]
        partition: Option<String>,
        /// Slurm time limit (sbatch --time: MINUTES, HH:MM:SS, D-HH:MM:SS).
        #[arg(long, value_name = "T")]
        time: Option<String>,
        /// srun --mpi plugin of the worker steps.
        #[arg(long, value_name = "PLUGIN", default_value = "pmix")]
        mpi: String,
        /// The md-worker program, on a path every node sees (default: the one next to mscale).
        #[arg(long, value_name = "PATH")]
        worker_bin: Option<PathBuf>,
        /// First port of the pool's workers (default: a range of its own from 24000, below the ephemeral ports).
        #[arg(long, value_name = "PORT")]
        port_base: Option<u16>,
        /// Directory of the batch script and the job's output (on a shared file system).
        #[arg(long, value_name = "DIR", default_value = "mscale-pools")]
        dir: PathBuf,
        /// Seconds to wait for the workers to register (the job may queue); then it is cancelled.
        #[arg(long, value_name = "SECONDS", default_value_t = 600.0)]
        wait: f64,
        /// One more sbatch option, as it is (repeatable): --sbatch-arg=--account=A
        #[arg(long = "sbatch-arg", value_name = "OPTION", allow_hyphen_values = true)]
        sbatch_args: Vec<String>,
        #[command(flatten)]
        conn: Conn,
    },
    /// Release a pool: drain its workers, wait until none holds a job, scancel its Slurm job.
    Release {
        /// The pool (the Slurm job id `launch` printed).
        pool: String,
        /// Seconds to wait for its workers to finish their jobs (0: cancel at once; their
        /// boxes move to other workers).
        #[arg(long, value_name = "SECONDS", default_value_t = 3600.0)]
        drain_for: f64,
        #[command(flatten)]
        conn: Conn,
    },
    /// List the pools Slurm runs or queues, with their live workers.
    Pools {
        #[command(flatten)]
        conn: Conn,
    },
}

#[derive(Subcommand)]
enum ReportCommand {
    /// Run every combination of the sweeps; write report.csv and report.png (error against wall time).
    ErrorVsTime {
        scene: PathBuf,
        /// A parameter and its values: --sweep scheme.particles_per_cell=8,16,32 (repeatable);
        /// KEY1+KEY2=V1,... sets both keys to each value.
        #[arg(long = "sweep", value_name = "KEY=V1,V2,...", required = true)]
        sweep: Vec<orchestrator::report::Sweep>,
        /// Override applied to every run (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Report directory (default runs/<scene>-report).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Running MD workers to use instead of in-process MD: HOST:PORT,...
        #[arg(long, value_delimiter = ',', value_name = "HOST:PORT,...")]
        workers: Vec<String>,
        /// Direct-MD reference profile (`md-worker direct --slab` CSV) to score each run's
        /// sigma_xx against by the seed's eq. 7.12 (1D scenes).
        #[arg(long, value_name = "CSV", requires = "reference_times")]
        reference: Option<PathBuf>,
        /// Times (ps) to score at with --reference: 5,10.
        #[arg(long, value_delimiter = ',', value_name = "T1,T2,...", requires = "reference")]
        reference_times: Vec<f64>,
        /// The --sweep key whose runs are replicas (e.g. the MD seeds): replicas.csv gives the
        /// mean and spread over them per setting of the other sweeps.
        #[arg(long, value_name = "KEY")]
        replicas: Option<String>,
    },
    /// Score a finished run again against a direct-MD reference (eq. 7.12, the run's own code),
    /// from the snapshots it wrote: prints the log line and the summary.json `errors` it would
    /// have. The run's `scene.resolved.toml` with --set overrides names the reference, e.g.
    /// --set reference.times_ps=[5.0,10.0] --set reference.profile=\"direct.csv\".
    Score {
        run_dir: PathBuf,
        /// Override of the run's resolved scene (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Under `mpirun -np N` (feature `mpi`): MPI lives until the end of main (finalised on drop).
    // Only `mscale run` starts it: any other verb (`serve` above all, which starts MPI runs of
    // its own) stays out of MPI, so its children are not taken for a singleton's.
    #[cfg(feature = "mpi")]
    let _mpi = match matches!(cli.command, Command::Run { .. }).then(continuum::mpi::init).transpose() {
        Ok(m) => m,
        Err(e) => {
            eprintln!("mscale: cannot start MPI: {e}");
            return ExitCode::from(exit::RUN_FAILED as u8);
        }
    };
    // Ranks above 0 log warnings only (rank 0 speaks for the run).
    let filter = if mpi_ranks().0 > 0 { None } else { tracing_subscriber::EnvFilter::try_from_default_env().ok() };
    tracing_subscriber::fmt()
        // diffsol logs its statistics at info at the end of every integration segment (the
        // cell run restarts at every output time and switch): warnings only.
        .with_env_filter(filter.unwrap_or_else(|| if mpi_ranks().0 > 0 { "warn".into() } else { "info,diffsol=warn".into() }))
        .with_writer(std::io::stderr)
        .init();
    // A file-size limit (`ulimit -f`) or quota reached while writing a checkpoint or a snapshot
    // fails that write with EFBIG and the run ends with a message naming the file, instead of
    // SIGXFSZ killing the process silently.
    // SAFETY: setting a signal's disposition to SIG_IGN at start, before any thread exists.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
    // No panic reaches the user as a backtrace: report it as an internal error.
    std::panic::set_hook(Box::new(|info| {
        eprintln!("mscale: internal error (this is a bug, please report it): {info}");
    }));
    let code = std::panic::catch_unwind(|| dispatch(cli)).unwrap_or(exit::RUN_FAILED);
    ExitCode::from(code as u8)
}

/// (rank, ranks) of this process: those of the tile exchange that MPI sets over more than one
/// rank (feature `mpi`), (0, 1) otherwise.
fn mpi_ranks() -> (usize, usize) {
    continuum::par::exchange().map_or((0, 1), |e| (e.rank(), e.size()))
}

fn dispatch(cli: Cli) -> i32 {
    match cli.command {
        Command::Serve {
            state,
            listen,
            token_file,
            checkpoint_every,
            tls_cert,
            tls_key,
            local_workers,
            worker_timeout,
            step_deadline,
            http,
            access,
            forget_workers,
            mpi_mscale,
            mpirun,
        } => {
            let mpi = match mpi_mscale.map(|m| orchestrator::service::MpiLauncher::new(m, &mpirun)).transpose() {
                Ok(m) => m,
                Err(e) => return report(Err(e)),
            };
            let pool =
                orchestrator::service::PoolOptions { local_workers, worker_timeout_s: worker_timeout, step_deadline, forget_workers, mpi };
            report(orchestrator::service::serve_command(
                state,
                listen,
                token_file,
                checkpoint_every,
                tls_cert.zip(tls_key),
                pool,
                http,
                access.options(),
            ))
        }
        Command::Workers { pools: Some(command), .. } => workers_command(command),
        Command::Workers { pools: None, conn } => {
            report(conn.ca().and_then(|_| orchestrator::client::workers(&conn.server, conn.token_file.as_deref())))
        }
        Command::Drain { worker, conn } => {
            report(conn.ca().and_then(|_| orchestrator::client::drain(&conn.server, conn.token_file.as_deref(), &worker)))
        }
        Command::Submit { scene, set, priority, checkpoint_every, workers, ranks, conn } => report(conn.ca().and_then(|_| {
            let how = orchestrator::client::Placement { workers, ranks };
            orchestrator::client::submit_for(&conn.server, conn.token_file.as_deref(), &scene, &set, priority, checkpoint_every, how)
        })),
        Command::Status { job, conn } => {
            report(conn.ca().and_then(|_| orchestrator::client::status(&conn.server, conn.token_file.as_deref(), job.as_deref())))
        }
        Command::Watch { job, events, reconnect_for, conn } => report(conn.ca().and_then(|_| {
            anyhow::ensure!(
                reconnect_for.is_finite() && reconnect_for >= 0.0,
                "--reconnect-for {reconnect_for} must be a number of seconds >= 0"
            );
            orchestrator::client::watch(
                &conn.server,
                conn.token_file.as_deref(),
                &job,
                events,
                std::time::Duration::from_secs_f64(reconnect_for),
            )
        })),
        Command::Cancel { job, conn } => {
            report(conn.ca().and_then(|_| orchestrator::client::cancel(&conn.server, conn.token_file.as_deref(), &job)))
        }
        Command::Fetch { job, file, out, conn } => report(
            conn.ca().and_then(|_| orchestrator::client::fetch(&conn.server, conn.token_file.as_deref(), &job, file.as_deref(), &out)),
        ),
        Command::Health { conn } => report(conn.ca().and_then(|_| orchestrator::client::health(&conn.server, conn.token_file.as_deref()))),
        Command::Check { scene, set, estimate } => match Loaded::load(&scene, &set) {
            Ok(Loaded::Cell(loaded)) => {
                print!("{}", orchestrator::cell_run::check_text(&loaded));
                exit::OK
            }
            Ok(Loaded::Mpm(loaded)) => {
                print!("{}", loaded.scene.to_toml());
                println!("\n# work");
                let (per_body, nodes) = orchestrator::setup::work_size(&loaded.resolved);
                let points: usize = per_body.iter().map(|(_, n)| n).sum();
                println!("# points = {points}\n# grid_nodes = {nodes}\n# steps = {}\n# dt_s = {:e}", loaded.steps, loaded.dt);
                if estimate {
                    match orchestrator::md::estimate(&loaded) {
                        Ok(Some(e)) => {
                            let threads = rayon::current_num_threads();
                            println!(
                                "# md_points = {}\n# atoms = {}\n# atom_steps = {:.3e}\n# measured_ns_per_atom_step = {:.1} (cpu back end, {threads} threads, this machine)\n# memory_bytes = {:.3e} ({:.0} bytes/atom measured)\n# predicted_md_wall_seconds = {:.0}",
                                e.md_points, e.atoms, e.atom_steps, e.ns_per_atom_step, e.memory_bytes, e.bytes_per_atom, e.wall_seconds
                            );
                            let on: Vec<String> =
                                [4, 16, 64, 256].iter().map(|&n| format!("{n}: {:.0}", e.wall_seconds_on(n, threads))).collect();
                            println!(
                                "# predicted_md_wall_seconds_on_workers = {} (workers like this machine, {threads} threads each; a box is not split; transfers not included)",
                                on.join(", ")
                            );
                        }
                        Ok(None) => println!("# no md bodies: nothing to estimate beyond the continuum work above"),
                        Err(e) => {
                            eprintln!("mscale: estimate: {e:#}");
                            return exit::RUN_FAILED;
                        }
                    }
                }
                exit::OK
            }
            Err(e) => {
                eprintln!("mscale: {e}");
                exit::BAD_INPUT
            }
        },
        Command::Report(ReportCommand::Score { run_dir, set }) => {
            let scene = match orchestrator::scene::load(&run_dir.join("scene.resolved.toml"), &set) {
                Ok(l) => l.scene,
                Err(e) => {
                    eprintln!("mscale: {e}");
                    return exit::BAD_INPUT;
                }
            };
            match orchestrator::run::rescore(&scene, &run_dir) {
                Ok((json, line)) => {
                    println!("{line}");
                    println!("{}", serde_json::to_string_pretty(&json).unwrap_or_default());
                    exit::OK
                }
                Err(e) => {
                    eprintln!("mscale: {}: {e:#}", run_dir.display());
                    exit::BAD_INPUT
                }
            }
        }
        Command::Report(ReportCommand::ErrorVsTime { scene, sweep, set, out, .. }) if orchestrator::cell_run::is_cell_scene(&scene) => {
            let out = out.unwrap_or_else(|| orchestrator::report::default_out(&scene));
            match orchestrator::cell_run::error_vs_time(&scene, &set, &sweep, &out) {
                Ok(n) => {
                    println!("{n} runs; report in {}/report.csv and report.png", out.display());
                    exit::OK
                }
                Err(e @ orchestrator::report::ReportError::Scene(_)) => {
                    eprintln!("mscale: {e}");
                    exit::BAD_INPUT
                }
                Err(e) => {
                    eprintln!("mscale: {e}");
                    exit::RUN_FAILED
                }
            }
        }
        Command::Report(ReportCommand::ErrorVsTime { scene, sweep, set, out, workers, reference, reference_times, replicas }) => {
            let out = out.unwrap_or_else(|| orchestrator::report::default_out(&scene));
            let reference = match reference.map(|r| orchestrator::report::ReferenceSpec::load(&r, &reference_times)).transpose() {
                Ok(r) => r,
                Err(e) => {
                    eprintln!("mscale: {e:#}");
                    return exit::BAD_INPUT;
                }
            };
            match orchestrator::report::error_vs_time(&scene, &set, &sweep, &out, &workers, reference.as_ref(), replicas.as_deref()) {
                Ok(rows) => {
                    println!("{} runs; report in {}/report.csv and report.png", rows.len(), out.display());
                    exit::OK
                }
                Err(orchestrator::report::ReportError::Scene(e)) => {
                    eprintln!("mscale: {e}");
                    exit::BAD_INPUT
                }
                Err(e @ orchestrator::report::ReportError::Input(_)) => {
                    eprintln!("mscale: {e}");
                    exit::BAD_INPUT
                }
                Err(e) => {
                    eprintln!("mscale: {e}");
                    exit::RUN_FAILED
                }
            }
        }
        Command::Run { scene, out, set, workers, checkpoint_every, resume, step_deadline, rebalance_every, progress_json, stop_file } => {
            let scene = match (scene, &resume) {
                (Some(s), _) => s,
                (None, Some(dir)) => dir.join("scene.resolved.toml"),
                (None, None) => unreachable!("clap requires a scene without --resume"),
            };
            let loaded = match Loaded::load(&scene, &set) {
                Ok(l) => l,
                Err(e) => {
                    eprintln!("mscale: {e}");
                    return exit::BAD_INPUT;
                }
            };
            let out = resume.clone().or(out).unwrap_or_else(|| loaded.default_out_dir());
            // Over MPI ranks (continuum/README.md "MPI"): every rank steps the same replicated
            // state; rank 0 writes the outputs and speaks, the others write theirs into a
            // private scratch directory removed at the end.
            let (rank, _) = mpi_ranks();
            let scratch = (rank > 0).then(|| std::env::temp_dir().join(format!("mscale-rank{rank}-{}", std::process::id())));
            let out = scratch.clone().unwrap_or(out);
            let _scratch = ScratchDir(scratch);
            let mut opts = run::RunOptions::new(out.clone(), std::env::args().collect());
            // MD runs once, driven by rank 0 (`Closure::computed_once`): only rank 0 talks to
            // the workers; the other ranks' md closures stand over a `null` pool (run.rs).
            opts.workers = if rank == 0 { workers } else { Vec::new() };
            opts.checkpoint_every = checkpoint_every;
            opts.resume = resume.is_some();
            // Every rank resumes from the run's checkpoint (the state is the same on every rank
            // and for any rank count: a checkpoint of N ranks resumes on M).
            opts.resume_from = resume.clone();
            opts.step_deadline = step_deadline;
            opts.rebalance_every = rebalance_every;
            match orchestrator::checkpoint::stop_on_signals() {
                Ok(flag) => opts.cancel = Some(flag),
                Err(e) => eprintln!("mscale: warning: cannot handle SIGINT/SIGTERM, no checkpoint will be written on them: {e}"),
            }
            if rank == 0 {
                if let Some(file) = stop_file {
                    let flag = opts.cancel.get_or_insert_with(Default::default).clone();
                    std::thread::spawn(move || {
                        while !file.exists() {
                            std::thread::sleep(std::time::Duration::from_millis(100));
                        }
                        flag.store(true, std::sync::atomic::Ordering::SeqCst);
                    });
                }
                if progress_json {
                    opts.progress_bar = false;
                    opts.progress = Some(std::sync::Arc::new(|p: &run::Progress| {
                        use std::io::Write;
                        // A closed stdout ends nothing: the run goes on (its reader is gone).
                        let _ = writeln!(std::io::stdout().lock(), "{}", serde_json::json!(p));
                    }));
                }
            }
            if rank > 0 {
                // The same replicated state as rank 0: the same outcome, reported by rank 0.
                let outcome = run_on_pool(&loaded, &opts);
                exchange_stats(rank);
                let agreed = outcome.is_ok();
                let code = match outcome {
                    Ok(run::Outcome::Completed(_)) => exit::OK,
                    _ => exit::RUN_FAILED,
                };
                if agreed {
                    ranks_done();
                }
                return code;
            }
            let outcome = run_on_pool(&loaded, &opts);
            exchange_stats(rank);
            let agreed = outcome.is_ok();
            let code = match outcome {
                Ok(run::Outcome::Completed(summary)) => {
                    println!(
                        "completed {} steps in {:.2} s; outputs in {}",
                        summary["steps"],
                        summary["wall_seconds"].as_f64().unwrap_or(0.0),
                        out.display()
                    );
                    // (A direct-MD reference's errors are in the run's last log line.)
                    if let Some(e) = summary.get("errors").filter(|e| e["reference"] == "isothermal-riemann") {
                        println!(
                            "pressure error vs {}: L1 {:.4e}, L2 {:.4e}, spike {:.4e} (of the jump)",
                            e["reference"],
                            e["pressure_l1"].as_f64().unwrap_or(f64::NAN),
                            e["pressure_l2"].as_f64().unwrap_or(f64::NAN),
                            e["pressure_spike"].as_f64().unwrap_or(f64::NAN)
                        );
                    }
                    if let Some(e) = summary.get("errors").filter(|e| e["reference"] == "manufactured") {
                        println!(
                            "L2 error vs the manufactured solution (G = {}): displacement {:.4e}, velocity {:.4e}, stress {:.4e}",
                            e["amplitude"],
                            e["displacement_l2"].as_f64().unwrap_or(f64::NAN),
                            e["velocity_l2"].as_f64().unwrap_or(f64::NAN),
                            e["stress_l2"].as_f64().unwrap_or(f64::NAN)
                        );
                    }
                    exit::OK
                }
                Ok(run::Outcome::Cancelled { checkpoint, step }) => {
                    eprintln!(
                        "mscale: cancelled after step {step}; checkpoint {}\n(continue with: mscale run --resume {})",
                        checkpoint.display(),
                        out.display()
                    );
                    exit::RUN_FAILED
                }
                Ok(run::Outcome::Failed(_, why)) => {
                    eprintln!("mscale: the run failed: {why}\n(outputs so far are in {})", out.display());
                    exit::RUN_FAILED
                }
                Err(e) => report(Err(e)),
            };
            if agreed {
                ranks_done();
            }
            code
        }
    }
}

/// `mscale run`'s one run, on a worker thread of rayon's global pool (`rayon::scope` called
/// from outside the pool runs its closure there): a parallel loop too short to split then runs
/// inline on that thread instead of being handed to the pool and waited for (a futex wake and
/// sleep per loop). On the 40-point silicon film (50,000 leapfrog steps) 32.8 s -> 2.84 s on
/// one thread and 13.1 s -> 3.9 s on two, the same digest. Not for the job service, whose
/// concurrent jobs would then steal each other's whole runs while waiting inside a loop.
fn run_on_pool(loaded: &Loaded, opts: &run::RunOptions) -> anyhow::Result<run::Outcome> {
    rayon::scope(|_| loaded.run(opts))
}

/// Over MPI ranks, after an outcome every rank reached at the same step (completed, cancelled,
/// failed in an agreed phase): waits until every rank, rank 0 included, has written and printed
/// all it will, so a launcher that ends the job at the first non-zero exit (`srun
/// --kill-on-bad-exit`, mpirun) cannot cut rank 0's checkpoint or message short. A rank's own
/// error (`Err`: rank 0 unable to write its outputs, say) skips it: that rank exits and the
/// launcher stops the others.
fn ranks_done() {
    if let Some(ex) = continuum::par::exchange().filter(|e| e.size() > 1) {
        ex.all_gather_bytes(&[]);
    }
}

/// With `MSCALE_MPI_STATS` set, over more than one MPI rank: what this rank's collectives cost
/// (calls, bytes, seconds inside them), one line on stderr per rank.
fn exchange_stats(rank: usize) {
    if let Some(ex) = continuum::par::exchange().filter(|e| e.size() > 1 && std::env::var_os("MSCALE_MPI_STATS").is_some()) {
        let s = ex.stats();
        eprintln!(
            "mscale: rank {rank} of {}: {} collectives, {} bytes sent, {} bytes received, {:.3} s inside them",
            ex.size(),
            s.calls,
            s.bytes_sent,
            s.bytes_received,
            s.seconds
        );
    }
}

/// A rank's scratch output directory (ranks above 0 under MPI), removed on drop.
struct ScratchDir(Option<std::path::PathBuf>);

impl Drop for ScratchDir {
    fn drop(&mut self) {
        if let Some(d) = &self.0 {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// `mscale workers launch|release|pools` (orchestrator::slurm).
fn workers_command(command: WorkersCommand) -> i32 {
    use orchestrator::slurm;
    fn orch(c: &Conn) -> orchestrator::slurm::Orchestrator<'_> {
        orchestrator::slurm::Orchestrator { server: &c.server, token_file: c.token_file.as_deref(), ca_file: c.ca_file.as_deref() }
    }
    let seconds = |flag: &str, s: f64| {
        if s.is_finite() && s >= 0.0 {
            Ok(std::time::Duration::from_secs_f64(s))
        } else {
            eprintln!("mscale: --{flag} {s} must be a number of seconds >= 0");
            Err(exit::BAD_INPUT)
        }
    };
    match command {
        WorkersCommand::Launch {
            slurm: _,
            workers,
            gpus_per_worker,
            ranks_per_worker,
            threads_per_rank,
            partition,
            time,
            mpi,
            worker_bin,
            port_base,
            dir,
            wait,
            sbatch_args,
            conn,
        } => {
            let wait = match seconds("wait", wait) {
                Ok(w) => w,
                Err(code) => return code,
            };
            let req = slurm::PoolRequest {
                workers,
                gpus_per_worker,
                ranks_per_worker,
                threads_per_rank,
                partition,
                time,
                worker_bin,
                mpi,
                port_base,
                dir,
                wait,
                sbatch_args,
            };
            report(conn.ca().and_then(|_| slurm::launch(&orch(&conn), &req)))
        }
        WorkersCommand::Release { pool, drain_for, conn } => match seconds("drain-for", drain_for) {
            Ok(d) => report(conn.ca().and_then(|_| slurm::release(&orch(&conn), &pool, d))),
            Err(code) => code,
        },
        WorkersCommand::Pools { conn } => report(conn.ca().and_then(|_| slurm::pools(&orch(&conn)))),
    }
}

/// Exit code of a verb: its own, or with the error chain printed once, [`exit::code_of`] the
/// error (2 for bad input, 1 otherwise).
fn report(r: anyhow::Result<i32>) -> i32 {
    r.unwrap_or_else(|e| {
        eprintln!("mscale: {e:#}");
        exit::code_of(&e)
    })
}
