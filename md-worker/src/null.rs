//! A back end that does no MD: boxes are ids with fixed lengths, every step returns zero
//! stress. It measures what the coupling itself costs (batching, serialisation, transfer,
//! scheduling) without MD work in the way.

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
#[derive(Default)]
pub struct NullBackend {
    lengths: crate::pool::IdMap<[f64; 3]>,
}

impl MdBackend for NullBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
        for s in specs {
            let l = match &s.atoms {
                crate::InitialAtoms::Lattice { a0, cells, orient, .. } => std::array::from_fn(|k| a0 * orient.period(k) * cells[k] as f64 * (1.0 + s.strain[k])),
                crate::InitialAtoms::Explicit { lengths, .. } => *lengths,
            };
            self.lengths.insert(s.id, l);
        }
        Ok(())
    }
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        for (w, r) in work.iter().zip(out.iter_mut()) {
            let l = *self.lengths.get(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            *r = BoxResult::default();
            r.id = w.id;
            r.diagnostics.lengths_a = l;
            r.diagnostics.total_steps = w.steps;
            r.stress_sampling = w.stress_sampling;
        }
        Ok(())
    }
    fn snapshot(&self, _ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        Err(MdError::Unsupported("snapshots of the null back end".into()))
    }
    fn restore(&mut self, _states: Vec<BoxState>) -> Result<(), MdError> {
        Err(MdError::Unsupported("restoring the null back end".into()))
    }
    fn name(&self) -> &'static str {
        "null"
    }
}

/// Median wall time (s) of one step round trip of `points` boxes spread over `workers`
/// `md-worker serve` instances with the null back end on loopback, over `reps` steps.
pub fn coupling_round_trip(points: usize, workers: usize, reps: usize) -> Result<(f64, Vec<f64>), Box<dyn std::error::Error + Send + Sync>> {
    use crate::pool::{Endpoint, MdPool, PotentialSource, Remote};
    use std::sync::Arc;
    let server_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let mut addrs = Vec::new();
    for _ in 0..workers {
        let listener = server_rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        addrs.push(listener.local_addr()?.to_string());
        let opts = crate::server::ServeOptions { backend: "null".into(), threads: None, device: "none".into() };
        server_rt.spawn(async move {
            let _ = crate::server::serve(listener, opts, std::future::pending()).await;
        });
    }
    let client_rt = Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?);
    let endpoints = addrs.iter().map(|a| Remote::connect(a, client_rt.clone()).map(|r| Box::new(r) as Box<dyn Endpoint>)).collect::<Result<Vec<_>, _>>()?;
    let mut pool = MdPool::new(endpoints)?;
    let potential = PotentialSource::from_bytes("null.eam.alloy".into(), b"no potential is parsed by the null back end".to_vec());
    let specs: Vec<BoxSpec> = (0..points as u64).map(|id| BoxSpec::lattice(id, crate::LatticeKind::Fcc, 3.615, [5, 5, 5])).collect();
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
