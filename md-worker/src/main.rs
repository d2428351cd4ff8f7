//! `md-worker`: evaluate, run and benchmark EAM boxes from the command line.
//! Exit code 2 for bad input (with the message), 1 for other failures.

mod coupling_bench;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use md_worker::data::{DataFile, dump_frame};
use md_worker::kernel;
use md_worker::{BoxResult, BoxSpec, BoxWork, DeformMode, LatticeKind, MdBackend, MdError, Potential, backend_by_name};
use serde_json::json;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Parser)]
#[command(name = "md-worker", version, about = "MD engine for mscale: EAM boxes in LAMMPS metal units")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Host boxes for coordinators over gRPC (mscale.coupling.v1), with health and reflection.
    /// Prints `listening on ADDR` once ready (port 0 picks a free port).
    Serve {
        /// Address to listen on, e.g. 127.0.0.1:50051 or 0.0.0.0:50051.
        #[arg(long, default_value = "127.0.0.1:50051")]
        listen: String,
        /// auto, cpu or cuda (cuda needs the `cuda` feature and a device); `null` serves the
        /// null back end (no MD: zero stress, for coupling and orchestrator benchmarks and
        /// tests; needs --throughput).
        #[arg(long, default_value = "auto")]
        device: String,
        /// Worker threads for the cpu back end (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Serve Prometheus metrics (GET /metrics, text format) on this address; prints
        /// `metrics on ADDR` after the `listening on` line. Unauthenticated: bind it to a
        /// loopback or cluster-internal address.
        #[arg(long, value_name = "ADDR")]
        metrics: Option<String>,
        #[command(flatten)]
        join: md_worker::join::JoinArgs,
    },
    /// Energy, kinetic energy and virial stress of a LAMMPS data file (JSON on stdout).
    Eval {
        /// EAM potential file (.eam, .eam.alloy, .eam.fs).
        #[arg(long)]
        potential: PathBuf,
        /// LAMMPS data file (atom_style atomic).
        #[arg(long)]
        data: PathBuf,
        /// Write per-atom forces (id fx fy fz, eV/A) to this file.
        #[arg(long)]
        forces: Option<PathBuf>,
    },
    /// NVE run with an optional constant velocity gradient; one JSON line per --thermo steps.
    Run {
        #[arg(long)]
        potential: PathBuf,
        #[arg(long)]
        data: PathBuf,
        /// Number of steps.
        #[arg(long)]
        steps: u64,
        /// Time step (ps).
        #[arg(long)]
        dt: f64,
        /// Velocity gradient components in 1/ps, e.g. xx=0.01,yy=-0.005 (xy = dv_x/dy).
        #[arg(long, default_value = "")]
        velocity_gradient: String,
        /// Deformation mode: affine (LAMMPS fix deform remap x) or seed (thesis Ch. 5.2).
        #[arg(long, default_value = "affine")]
        remap: String,
        /// Print thermo every K steps.
        #[arg(long, default_value_t = 100)]
        thermo: u64,
        /// Write the final configuration as a LAMMPS data file.
        #[arg(long)]
        write_data: Option<PathBuf>,
        /// Write a LAMMPS dump (OVITO-readable) frame every --thermo steps.
        #[arg(long)]
        dump: Option<PathBuf>,
    },
    /// Direct MD of a bar: frozen end layers in x, periodic y/z, initial strain regions,
    /// slab stresses (reference x) as CSV every --every steps.
    Direct(md_worker::direct::DirectArgs),
    /// Coupling overhead alone: the round trip of one step's batch of POINTS boxes over WORKERS
    /// loopback workers running the null back end (no MD). Prints JSON with the median.
    BenchCoupling {
        #[arg(long, default_value_t = 20_000)]
        points: usize,
        #[arg(long, default_value_t = 4)]
        workers: usize,
        /// Steps timed (median reported; at least 5).
        #[arg(long, default_value_t = 20)]
        reps: usize,
    },
    /// Throughput of a back end on lattice boxes: atom-steps/s and ns/atom-step.
    Bench {
        #[arg(long)]
        potential: PathBuf,
        #[arg(long, default_value = "fcc")]
        lattice: String,
        /// Lattice constant (A).
        #[arg(long)]
        a0: f64,
        /// Cells per side.
        #[arg(long)]
        cells: usize,
        /// Number of boxes.
        #[arg(long, default_value_t = 1)]
        boxes: usize,
        /// Steps per repetition.
        #[arg(long, default_value_t = 100)]
        steps: u64,
        /// Threads (cpu back end).
        #[arg(long)]
        threads: Option<usize>,
        /// reference or cpu.
        #[arg(long, default_value = "cpu")]
        backend: String,
        /// Repetitions (median reported; at least 5).
        #[arg(long, default_value_t = 5)]
        reps: usize,
        /// auto, cpu or cuda (replaces --backend; cuda needs the `cuda` feature and a GPU,
        /// auto falls back to cpu with a warning).
        #[arg(long)]
        device: Option<String>,
        /// GPU arithmetic: double or mixed.
        #[arg(long, default_value = "double")]
        precision: String,
    },
}

fn main() {
    let cli = Cli::parse();
    let res = match cli.cmd {
        Cmd::Serve { listen, device, threads, metrics, join } => serve(&listen, &device, threads, metrics.as_deref(), &join),
        Cmd::Eval { potential, data, forces } => eval(&potential, &data, forces),
        Cmd::Run { potential, data, steps, dt, velocity_gradient, remap, thermo, write_data, dump } => {
            run(&potential, &data, steps, dt, &velocity_gradient, &remap, thermo, write_data, dump)
        }
        Cmd::BenchCoupling { points, workers, reps } => bench_coupling(points, workers, reps),
        Cmd::Direct(a) => md_worker::direct::run_cli(&a).map_err(anyhow::Error::from),
        Cmd::Bench { potential, lattice, a0, cells, boxes, steps, threads, backend, reps, device, precision } => {
            bench(&potential, &lattice, a0, cells, boxes, steps, threads, &backend, reps, device.as_deref(), &precision)
        }
    };
    if let Err(e) = res {
        eprintln!("md-worker: error: {e:#}");
        // Bad input exits 2; a box whose MD diverged (an MD guard stopped it) exits 1.
        let input = e.chain().any(|c| {
            matches!(c.downcast_ref::<MdError>(), Some(m) if !matches!(m, MdError::Diverged { .. }))
                || c.downcast_ref::<InputError>().is_some()
        });
        std::process::exit(if input { 2 } else { 1 });
    }
}

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct InputError(String);

fn bad(msg: impl Into<String>) -> anyhow::Error {
    InputError(msg.into()).into()
}

/// A single box from a data file, ready to evaluate.
fn load(potential: &std::path::Path, data: &std::path::Path, mode: DeformMode) -> Result<(Arc<Potential>, DataFile, BoxSpec)> {
    let pot = Arc::new(Potential::from_file(potential)?);
    let d = DataFile::read(data)?;
    if let Some(t) = d.types.iter().find(|&&t| t as usize > pot.n_elements()) {
        return Err(bad(format!("{}: atom type {t}, but {} has {} element(s)", data.display(), potential.display(), pot.n_elements())));
    }
    let mut spec = d.box_spec(0);
    spec.mode = mode;
    Ok((pot, d, spec))
}

fn stress_json(s: &[f64; 6]) -> serde_json::Value {
    json!({"xx": s[0], "yy": s[1], "zz": s[2], "xy": s[3], "xz": s[4], "yz": s[5]})
}

fn masses(pot: &Potential) -> Vec<f64> {
    (0..pot.n_elements()).map(|e| pot.mass(e)).collect()
}

fn eval(potential: &std::path::Path, data: &std::path::Path, forces: Option<PathBuf>) -> Result<()> {
    let (pot, d, spec) = load(potential, data, DeformMode::Affine)?;
    let m = masses(&pot);
    let st = md_worker::backend::prepare_box(&pot, &m, &spec)?;
    let ke = kernel::total_kinetic(&st.types, &st.v, &m);
    let kin = kernel::kinetic_tensor(&st.types, &st.v, &m);
    let stress = kernel::virial_stress(&st.meta, &kin);
    println!("{}", json!({"energy_ev": st.meta.pe, "kinetic_ev": ke, "stress_gpa": stress_json(&stress)}));
    if let Some(path) = forces {
        let mut s = String::from("# id fx fy fz (eV/A)\n");
        for (id, f) in d.ids.iter().zip(&st.f) {
            s += &format!("{id} {:e} {:e} {:e}\n", f[0], f[1], f[2]);
        }
        std::fs::write(&path, s).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

fn parse_gradient(s: &str) -> Result<[[f64; 3]; 3]> {
    let mut g = [[0.0; 3]; 3];
    for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (k, v) = part.split_once('=').ok_or_else(|| bad(format!("velocity gradient entry {part:?}: expected like xx=0.01")))?;
        let idx = |c: u8| match c {
            b'x' => Ok(0),
            b'y' => Ok(1),
            b'z' => Ok(2),
            _ => Err(bad(format!("velocity gradient component {k:?}: expected two of x, y, z"))),
        };
        let kb = k.as_bytes();
        if kb.len() != 2 {
            return Err(bad(format!("velocity gradient component {k:?}: expected two of x, y, z")));
        }
        let val: f64 = v.parse().map_err(|_| bad(format!("velocity gradient {k}: {v:?} is not a number (1/ps)")))?;
        g[idx(kb[0])?][idx(kb[1])?] = val;
    }
    Ok(g)
}

#[allow(clippy::too_many_arguments)]
fn run(
    potential: &std::path::Path,
    data: &std::path::Path,
    steps: u64,
    dt: f64,
    grad: &str,
    remap: &str,
    thermo: u64,
    write_data: Option<PathBuf>,
    dump: Option<PathBuf>,
) -> Result<()> {
    let mode = match remap {
        "affine" => DeformMode::Affine,
        "seed" => DeformMode::Seed,
        _ => bail!(bad(format!("--remap {remap:?}: expected affine or seed"))),
    };
    if !(dt > 0.0 && dt.is_finite()) {
        return Err(bad(format!("--dt {dt}: must be a positive time step in ps")));
    }
    if thermo == 0 {
        return Err(bad("--thermo must be at least 1"));
    }
    let g = parse_gradient(grad)?;
    let (pot, mut d, spec) = load(potential, data, mode)?;
    let mut backend = backend_by_name("reference", pot.clone())?;
    backend.open(&[spec])?;
    let mut dump_out = match &dump {
        Some(p) => Some(std::io::BufWriter::new(std::fs::File::create(p).with_context(|| format!("cannot create {}", p.display()))?)),
        None => None,
    };
    let m = masses(&pot);
    let mut done = 0;
    let mut emit = |backend: &mut Box<dyn MdBackend>, r: &BoxResult, done: u64| -> Result<()> {
        let st = backend.snapshot(&[0])?.remove(0);
        let ke = kernel::total_kinetic(&st.types, &st.v, &m);
        println!(
            "{}",
            json!({"step": done, "energy_ev": r.potential_energy_ev, "kinetic_ev": ke, "stress_gpa": stress_json(&r.stress_gpa)})
        );
        if let Some(w) = dump_out.as_mut() {
            let types: Vec<u32> = st.types.iter().map(|t| t + 1).collect();
            w.write_all(dump_frame(done, st.meta.lo, st.meta.l, &d.ids, &types, &st.x, &st.v).as_bytes())?;
        }
        Ok(())
    };
    let mut out = [BoxResult::default()];
    backend.step(&[BoxWork::new(0, g, 0, dt)], &mut out)?;
    emit(&mut backend, &out[0], 0)?;
    while done < steps {
        let n = thermo.min(steps - done);
        backend.step(&[BoxWork::new(0, g, n, dt)], &mut out)?;
        done += n;
        emit(&mut backend, &out[0], done)?;
    }
    if let Some(path) = write_data {
        let st = backend.snapshot(&[0])?.remove(0);
        d.lo = st.meta.lo;
        d.lengths = st.meta.l;
        d.x = st.x;
        d.v = st.v;
        d.masses = Some(m.clone());
        std::fs::write(&path, d.to_text(&format!("md-worker run, step {done}")))
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn bench(
    potential: &std::path::Path,
    lattice: &str,
    a0: f64,
    cells: usize,
    boxes: usize,
    steps: u64,
    threads: Option<usize>,
    backend: &str,
    reps: usize,
    device: Option<&str>,
    precision: &str,
) -> Result<()> {
    let kind: LatticeKind = lattice.parse()?;
    if cells == 0 || boxes == 0 || steps == 0 {
        return Err(bad("--cells, --boxes and --steps must be at least 1"));
    }
    let pot = Arc::new(Potential::from_file(potential)?);
    let pool = match threads {
        Some(0) => return Err(bad("--threads must be at least 1")),
        Some(t) => Some(Arc::new(rayon::ThreadPoolBuilder::new().num_threads(t).build()?)),
        None => None,
    };
    let choice = match device {
        Some(d) => md_worker::device::BackendChoice::on_device(d, precision),
        None => md_worker::device::BackendChoice::named(backend),
    };
    let mut b = md_worker::device::build(&choice.with_threads(pool), pot.clone(), None)?;
    let backend = b.name();
    let specs: Vec<BoxSpec> = (0..boxes as u64)
        .map(|id| {
            let mut s = BoxSpec::lattice(id, kind, a0, [cells; 3]);
            s.temperature_k = 300.0;
            s.seed = 1;
            s
        })
        .collect();
    b.open(&specs)?;
    let natoms = kind_atoms(kind) * cells * cells * cells * boxes;
    let work: Vec<BoxWork> =
        (0..boxes as u64).map(|id| BoxWork::new(id, [[1e-3, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], steps, 0.001)).collect();
    let mut out = vec![BoxResult::default(); boxes];
    let mut times = Vec::new();
    for _ in 0..reps.max(5) {
        let t0 = std::time::Instant::now();
        b.step(&work, &mut out)?;
        times.push(t0.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let med = times[times.len() / 2];
    let atom_steps = (natoms as u64 * steps) as f64;
    println!(
        "{}",
        json!({"backend": backend, "simd": match backend { "cpu" => md_worker::simd::selected()?.name(), "reference" => "scalar", _ => "none" }, "threads": if backend == "reference" { 1 } else { threads.unwrap_or_else(rayon::current_num_threads) }, "atoms": natoms, "boxes": boxes,
               "steps": steps, "repetitions": times.len(), "median_s": med,
               "atom_steps_per_s": atom_steps / med, "ns_per_atom_step": med / atom_steps * 1e9})
    );
    Ok(())
}

fn kind_atoms(k: LatticeKind) -> usize {
    match k {
        LatticeKind::Fcc => 4,
        LatticeKind::Bcc => 2,
        LatticeKind::Sc => 1,
    }
}

/// `md-worker serve`.
fn serve(listen: &str, device: &str, threads: Option<usize>, metrics: Option<&str>, join: &md_worker::join::JoinArgs) -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    // Under `mpirun -np N` (N > 1): rank 0 serves and spreads boxes over the ranks, the others
    // run rank 0's commands; every rank computes on the cpu back end (src/mpi.rs).
    #[cfg(feature = "mpi")]
    let mpi = md_worker::mpi::init()?;
    #[cfg(feature = "mpi")]
    let (ranks, threads) = (
        mpi.size(),
        threads.or_else(|| {
            (mpi.size() > 1).then(|| (std::thread::available_parallelism().map_or(1, |n| n.get()) / mpi.ranks_on_this_node()).max(1))
        }),
    );
    #[cfg(not(feature = "mpi"))]
    let ranks = 1;
    let device = match device {
        "cuda" if ranks > 1 => return Err(bad(format!("--device cuda: not under mpi ({ranks} ranks compute on the cpu back end)"))),
        "auto" if ranks > 1 => "cpu",
        d => d,
    };
    if device == "null" && join.throughput.is_none() {
        return Err(bad("--device null needs --throughput (the null back end does no MD whose throughput could be measured)"));
    }
    let backend = match device {
        "null" => Ok("null"),
        d => md_worker::device::resolve_device(d),
    };
    let backend = match backend {
        Ok(d) => d,
        Err(MdError::Device(why)) => return Err(bad(format!("--device {device}: {why}"))),
        Err(_) => return Err(bad(format!("--device {device:?}: expected auto, cpu or cuda"))),
    };
    let pool = match threads {
        Some(0) => return Err(bad("--threads must be at least 1")),
        Some(t) => Some(Arc::new(rayon::ThreadPoolBuilder::new().num_threads(t).build()?)),
        None => None,
    };
    #[cfg(feature = "mpi")]
    if mpi.rank() > 0 {
        return md_worker::mpi::serve_rank(&mpi, pool).map_err(Into::into);
    }
    let nthreads = threads.unwrap_or_else(rayon::current_num_threads);
    let (backend, device) = match backend {
        "cuda" => ("cuda", "cuda".to_string()),
        "null" => ("null", "null (no MD)".to_string()),
        _ if ranks > 1 => ("mpi", format!("cpu (mpi {ranks} ranks x {nthreads} threads)")),
        b => (b, format!("cpu ({nthreads} threads)")),
    };
    let kind =
        md_worker::join::WorkerKind { backend: backend.into(), precision: "double".into(), device: device.clone(), threads: pool.clone() };
    let opts = md_worker::server::ServeOptions { backend: backend.into(), threads: pool, device };
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    rt.block_on(async {
        let listener = tokio::net::TcpListener::bind(listen).await.map_err(|e| bad(format!("--listen {listen}: {e}")))?;
        let addr = listener.local_addr()?;
        println!("listening on {addr}");
        std::io::stdout().flush()?;
        let counters = Arc::new(md_worker::metrics::WorkerMetrics::new());
        if let Some(m) = metrics {
            let l = tokio::net::TcpListener::bind(m).await.map_err(|e| bad(format!("--metrics {m}: {e}")))?;
            // The reader of the first line may have gone: a closed stdout is no error here.
            let _ = writeln!(std::io::stdout(), "metrics on {}", l.local_addr()?);
            let _ = std::io::stdout().flush();
            tokio::spawn(md_worker::metrics::serve_http(l, md_worker::metrics::router(counters.clone()), None, std::future::pending()));
        }
        // With --orchestrator: register and heartbeat (src/join.rs); a refusal ends the worker.
        let joined = md_worker::join::Join::start(join, addr, kind).map_err(|e| bad(format!("{e:#}")))?;
        let shutdown = async {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = joined.failed() => {}
            }
        };
        md_worker::server::serve_with_metrics(listener, opts, counters, shutdown)
            .await
            .map_err(|e| anyhow::anyhow!("serving on {addr}: {e}"))?;
        joined.outcome()
    })
}

/// `md-worker bench-coupling`.
fn bench_coupling(points: usize, workers: usize, reps: usize) -> Result<()> {
    if points == 0 || workers == 0 || reps < 5 {
        return Err(bad("--points and --workers must be at least 1, --reps at least 5"));
    }
    let (median, times) = coupling_bench::coupling_round_trip(points, workers, reps).map_err(|e| anyhow::anyhow!("{e}"))?;
    println!(
        "{}",
        json!({
            "what": "round trip of one step batch, null back end (no MD), loopback gRPC",
            "points": points,
            "workers": workers,
            "median_ms": median * 1e3,
            "all_ms": times.iter().map(|t| t * 1e3).collect::<Vec<_>>(),
            "command": format!("md-worker bench-coupling --points {points} --workers {workers} --reps {reps}"),
        })
    );
    Ok(())
}
