//! The harness of `md-worker bench-coupling`: what the coupling itself costs (batching,
//! serialisation, transfer, scheduling) with no MD in the way, through loopback workers that
//! serve the null back end (`md_worker::null`).

use md_worker::pool::{Endpoint, MdPool, PotentialSource, Remote};
use md_worker::{BoxSpec, BoxWork, LatticeKind};
use std::sync::Arc;

/// Median wall time (s) of one step round trip of `points` boxes spread over `workers`
/// `md-worker serve` instances with the null back end on loopback, over `reps` steps.
pub fn coupling_round_trip(
    points: usize,
    workers: usize,
    reps: usize,
) -> Result<(f64, Vec<f64>), Box<dyn std::error::Error + Send + Sync>> {
    let server_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let mut addrs = Vec::new();
    for _ in 0..workers {
        let listener = server_rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        addrs.push(listener.local_addr()?.to_string());
        let opts = md_worker::server::ServeOptions { backend: "null".into(), threads: None, device: "none".into() };
        server_rt.spawn(async move {
            let _ = md_worker::server::serve(listener, opts, std::future::pending()).await;
        });
    }
    let client_rt = Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?);
    let endpoints = addrs
        .iter()
        .map(|a| Remote::connect(a, client_rt.clone()).map(|r| Box::new(r) as Box<dyn Endpoint>))
        .collect::<Result<Vec<_>, _>>()?;
    let mut pool = MdPool::new(endpoints)?;
    let potential = PotentialSource::from_bytes("null.eam.alloy".into(), b"no potential is parsed by the null back end".to_vec());
    let specs: Vec<BoxSpec> = (0..points as u64).map(|id| BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [5, 5, 5])).collect();
    pool.open(&potential, &specs)?;
    let work: Vec<BoxWork> = (0..points as u64).map(|id| BoxWork::new(id, [[1e-3, 0.0, 0.0], [0.0; 3], [0.0; 3]], 250, 0.001)).collect();
    let mut times = Vec::new();
    for step in 0..reps as u64 + 1 {
        let t = std::time::Instant::now();
        pool.step(step, &work)?;
        if step > 0 {
            times.push(t.elapsed().as_secs_f64());
        }
    }
    let mut sorted = times.clone();
    sorted.sort_by(f64::total_cmp);
    Ok((sorted[sorted.len() / 2], times))
}
