//! The client side of a worker pool: boxes spread over endpoints, each either an in-process
//! back end or a remote `md-worker serve` reached over gRPC (`mscale.coupling.v1`).
//!
//! Every box is owned by exactly one endpoint; a step's work is split by owner, run on all
//! endpoints at once (one thread per endpoint), and the results are put back in the order of
//! the request. Since every box is computed independently and deterministically, the result
//! does not depend on how many endpoints there are or which kind they are.

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
use crate::potential::Potential;
use crate::wire;
use mscale_proto::coupling::v1 as pb;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

/// A potential file as shipped to workers: its name, bytes and SHA-256.
#[derive(Debug, Clone)]
pub struct PotentialSource {
    pub name: String,
    pub bytes: Arc<Vec<u8>>,
    pub sha256: String,
}

impl PotentialSource {
    pub fn from_file(path: &std::path::Path) -> Result<Self, MdError> {
        let bytes = std::fs::read(path).map_err(|e| MdError::Io { file: path.display().to_string(), source: e })?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(Self::from_bytes(name, bytes))
    }

    pub fn from_bytes(name: String, bytes: Vec<u8>) -> Self {
        let sha256 = hex::encode(Sha256::digest(&bytes));
        PotentialSource { name, bytes: Arc::new(bytes), sha256 }
    }

    /// Parses the potential (the format follows the file name).
    pub fn parse(&self) -> Result<Potential, MdError> {
        let text = std::str::from_utf8(&self.bytes).map_err(|_| MdError::Parse { file: self.name.clone(), line: 1, msg: "not a text file".into() })?;
        Potential::from_text(&self.name, text)
    }
}

/// One place boxes live.
pub trait Endpoint: Send {
    /// Name for messages (`in-process cpu`, `127.0.0.1:50051`).
    fn name(&self) -> String;
    fn open(&mut self, potential: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError>;
    /// Results in the order of `work`.
    fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError>;
    fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError>;
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError>;
    /// Back end and precision that hold the boxes (`cpu/double`).
    fn kind(&self) -> String;
}

/// An in-process back end, created on `open` from the potential.
pub struct InProcess {
    backend_name: String,
    backend: Option<Box<dyn MdBackend>>,
    threads: Option<Arc<rayon::ThreadPool>>,
}

impl InProcess {
    /// `backend`: `reference` or `cpu` (the rayon pool is the global one unless `threads` is given).
    pub fn new(backend: &str, threads: Option<Arc<rayon::ThreadPool>>) -> Self {
        InProcess { backend_name: backend.to_string(), backend: None, threads }
    }

    fn backend(&mut self) -> Result<&mut Box<dyn MdBackend>, MdError> {
        self.backend.as_mut().ok_or_else(|| MdError::invalid("pool", "step before open"))
    }
}

impl Endpoint for InProcess {
    fn name(&self) -> String {
        format!("in-process {}", self.backend_name)
    }
    fn open(&mut self, potential: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
        if self.backend.is_none() {
            let pot = Arc::new(potential.parse()?);
            self.backend = Some(match (self.backend_name.as_str(), &self.threads) {
                ("cpu", Some(pool)) => Box::new(crate::CpuBackend::with_pool(pot, pool.clone())),
                (name, _) => crate::backend_by_name(name, pot)?,
            });
        }
        self.backend()?.open(specs)
    }
    fn step(&mut self, _step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let mut out = vec![BoxResult::default(); work.len()];
        self.backend()?.step(work, &mut out)?;
        Ok(out)
    }
    fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        self.backend()?.snapshot(ids)
    }
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        self.backend()?.restore(states)
    }
    fn kind(&self) -> String {
        format!("{}/double", self.backend_name)
    }
}

/// Time spent in a pool's step calls.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct PoolTimes {
    /// Wall time of step calls (s).
    pub step_wall: f64,
    /// Largest compute time of an endpoint per call, summed (s).
    pub md_compute: f64,
    /// Step calls.
    pub calls: u64,
}

/// Hasher of point ids for the per-box maps of the step path: one multiply (Fibonacci
/// hashing). Point ids come from the coordinator itself, so SipHash's resistance to chosen
/// keys buys nothing here, and it was a visible part of a 20,000-box step's cost.
#[derive(Debug, Default, Clone, Copy)]
pub struct IdHasher(u64);

impl std::hash::Hasher for IdHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
    fn finish(&self) -> u64 {
        self.0 ^ (self.0 >> 32)
    }
}

/// A map keyed by point id with [`IdHasher`].
pub type IdMap<V> = HashMap<PointId, V, std::hash::BuildHasherDefault<IdHasher>>;

/// Boxes spread over endpoints.
pub struct MdPool {
    endpoints: Vec<Box<dyn Endpoint>>,
    owner: IdMap<usize>,
    pub times: PoolTimes,
    /// Relative throughput of each endpoint (empty: equal); `open` spreads boxes by it.
    weights: Vec<f64>,
    /// Atoms of each box (from its spec), for the per-endpoint load.
    atoms: IdMap<u64>,
    /// Per endpoint: seconds in step calls and atom-steps done.
    load: Vec<(f64, f64)>,
}

/// What one endpoint holds and has done.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EndpointLoad {
    pub name: String,
    pub boxes: usize,
    pub atoms: u64,
    /// Wall seconds of its step calls (compute and transfer).
    pub step_seconds: f64,
    pub atom_steps: f64,
}

/// Sizes of contiguous blocks of `n` boxes in proportion to `weights` (largest remainder,
/// ties to the lower index): deterministic for the same `n` and weights. Non-positive or
/// non-finite weights count as the mean of the others (1 when none is positive).
pub fn proportional_blocks(n: usize, weights: &[f64]) -> Vec<usize> {
    let good: Vec<f64> = weights.iter().copied().filter(|w| w.is_finite() && *w > 0.0).collect();
    let fill = if good.is_empty() { 1.0 } else { good.iter().sum::<f64>() / good.len() as f64 };
    let w: Vec<f64> = weights.iter().map(|&x| if x.is_finite() && x > 0.0 { x } else { fill }).collect();
    let total: f64 = w.iter().sum();
    let quota: Vec<f64> = w.iter().map(|x| n as f64 * x / total).collect();
    let mut sizes: Vec<usize> = quota.iter().map(|q| (q.floor() as usize).min(n)).collect();
    let mut order: Vec<usize> = (0..w.len()).collect();
    order.sort_by(|&a, &b| (quota[b] - quota[b].floor()).total_cmp(&(quota[a] - quota[a].floor())).then(a.cmp(&b)));
    let mut left = n.saturating_sub(sizes.iter().sum());
    for &e in order.iter().cycle().take(left.min(w.len() * 2)) {
        if left == 0 {
            break;
        }
        sizes[e] += 1;
        left -= 1;
    }
    sizes
}

fn spec_atoms(s: &BoxSpec) -> u64 {
    match &s.atoms {
        crate::InitialAtoms::Lattice { kind, cells, .. } => {
            let per_cell = match kind {
                crate::LatticeKind::Fcc => 4,
                crate::LatticeKind::Bcc => 2,
                crate::LatticeKind::Sc => 1,
            };
            per_cell * cells.iter().map(|&c| c as u64).product::<u64>()
        }
        crate::InitialAtoms::Explicit { types, .. } => types.len() as u64,
    }
}

impl MdPool {
    pub fn new(endpoints: Vec<Box<dyn Endpoint>>) -> Result<Self, MdError> {
        if endpoints.is_empty() {
            return Err(MdError::invalid("pool", "no endpoints"));
        }
        let load = vec![(0.0, 0.0); endpoints.len()];
        Ok(MdPool { endpoints, owner: IdMap::default(), times: PoolTimes::default(), weights: Vec::new(), atoms: IdMap::default(), load })
    }

    /// Spreads the boxes of later `open` calls in proportion to these weights (one per
    /// endpoint, e.g. measured throughputs) instead of equally. The results do not depend on
    /// it: every box is computed independently.
    pub fn set_weights(&mut self, weights: Vec<f64>) -> Result<(), MdError> {
        if weights.len() != self.endpoints.len() {
            return Err(MdError::invalid("pool", format!("{} weights for {} endpoints", weights.len(), self.endpoints.len())));
        }
        self.weights = weights;
        Ok(())
    }

    /// Boxes, atoms and step time of each endpoint, in endpoint order.
    pub fn endpoint_load(&self) -> Vec<EndpointLoad> {
        let mut out: Vec<EndpointLoad> = self.endpoints.iter().zip(&self.load).map(|(e, l)| EndpointLoad { name: e.name(), step_seconds: l.0, atom_steps: l.1, ..Default::default() }).collect();
        for (id, &e) in &self.owner {
            out[e].boxes += 1;
            out[e].atoms += self.atoms.get(id).copied().unwrap_or(0);
        }
        out
    }

    pub fn endpoint_names(&self) -> Vec<String> {
        self.endpoints.iter().map(|e| e.name()).collect()
    }

    /// Back end kinds of the endpoints (`cpu/double`, ...).
    pub fn kinds(&self) -> Vec<String> {
        self.endpoints.iter().map(|e| e.kind()).collect()
    }

    /// Opens boxes, spread over the endpoints in contiguous, nearly equal blocks.
    pub fn open(&mut self, potential: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
        let n = self.endpoints.len();
        let dest: Vec<usize> = if self.weights.is_empty() {
            (0..specs.len()).map(|k| k * n / specs.len().max(1)).collect()
        } else {
            // Shares of all boxes opened so far and these, so that several `open` calls (one
            // per body) add up to one proportional partition.
            let mut have = vec![0usize; n];
            self.owner.values().for_each(|&e| have[e] += 1);
            let target = proportional_blocks(self.owner.len() + specs.len(), &self.weights);
            let mut need: Vec<usize> = target.iter().zip(&have).map(|(t, h)| t.saturating_sub(*h)).collect();
            let mut excess = need.iter().sum::<usize>() - specs.len();
            for x in need.iter_mut().rev() {
                let cut = excess.min(*x);
                *x -= cut;
                excess -= cut;
            }
            need.iter().enumerate().flat_map(|(e, &size)| std::iter::repeat_n(e, size)).collect()
        };
        let mut parts: Vec<Vec<BoxSpec>> = vec![Vec::new(); n];
        for (k, s) in specs.iter().enumerate() {
            if self.owner.contains_key(&s.id) {
                return Err(MdError::invalid("box spec", format!("point {} is opened twice", s.id)));
            }
            parts[dest[k]].push(s.clone());
        }
        let results = self.on_every_endpoint(parts, |ep, part| if part.is_empty() { Ok(()) } else { ep.open(potential, &part) });
        for (e, r) in results.into_iter().enumerate() {
            r.map_err(|err| lost(&*self.endpoints[e], "open", err))?;
        }
        for (k, s) in specs.iter().enumerate() {
            self.owner.insert(s.id, dest[k]);
            self.atoms.insert(s.id, spec_atoms(s));
        }
        Ok(())
    }

    /// Advances boxes; `out[k]` is the result of `work[k]`.
    pub fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let start = Instant::now();
        let n = self.endpoints.len();
        let each = work.len() / n + 1;
        let mut parts: Vec<Vec<BoxWork>> = (0..n).map(|_| Vec::with_capacity(each)).collect();
        let mut slot: Vec<Vec<usize>> = (0..n).map(|_| Vec::with_capacity(each)).collect();
        for (k, w) in work.iter().enumerate() {
            let e = *self.owner.get(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            parts[e].push(*w);
            slot[e].push(k);
        }
        let results = self.on_every_endpoint(parts, |ep, part| {
            let t = Instant::now();
            let r = if part.is_empty() { Ok(Vec::new()) } else { ep.step(step, &part) };
            r.map(|r| (r, t.elapsed().as_secs_f64()))
        });
        let mut out = vec![BoxResult::default(); work.len()];
        let mut slowest: f64 = 0.0;
        for (e, r) in results.into_iter().enumerate() {
            let (res, secs) = r.map_err(|err| lost(&*self.endpoints[e], &format!("continuum step {step}"), err))?;
            slowest = slowest.max(secs);
            self.load[e].0 += secs;
            self.load[e].1 += slot[e].iter().map(|&k| work[k].steps as f64 * self.atoms.get(&work[k].id).copied().unwrap_or(0) as f64).sum::<f64>();
            if res.len() != slot[e].len() {
                return Err(MdError::invalid("worker reply", format!("{} returned {} results for {} boxes", self.endpoints[e].name(), res.len(), slot[e].len())));
            }
            for (k, r) in slot[e].iter().zip(res) {
                if r.id != work[*k].id {
                    return Err(MdError::invalid("worker reply", format!("{} answered point {} for point {}", self.endpoints[e].name(), r.id, work[*k].id)));
                }
                wire::check_result(&r, &self.endpoints[e].name())?;
                if r.stress_sampling != work[*k].stress_sampling {
                    return Err(MdError::Worker {
                        worker: self.endpoints[e].name(),
                        msg: format!(
                            "returned the `{}` stress of point {} when `{}` was asked (a worker that predates stress sampling?)",
                            r.stress_sampling.name(),
                            r.id,
                            work[*k].stress_sampling.name()
                        ),
                    });
                }
                out[*k] = r;
            }
        }
        self.times.step_wall += start.elapsed().as_secs_f64();
        self.times.md_compute += slowest;
        self.times.calls += 1;
        Ok(out)
    }

    /// States of the named boxes, in the order of `ids`.
    pub fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        let mut out = Vec::with_capacity(ids.len());
        for id in ids {
            let e = *self.owner.get(id).ok_or(MdError::UnknownBox(*id))?;
            out.extend(self.endpoints[e].snapshot(&[*id])?);
        }
        Ok(out)
    }

    /// Puts saved box states back (a checkpoint): each state goes to the endpoint that owns its
    /// box, so the boxes must have been opened first (with the same specs). Refuses a state of
    /// a box this pool does not hold, before touching any endpoint.
    pub fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        let mut parts: Vec<Vec<BoxState>> = vec![Vec::new(); self.endpoints.len()];
        for s in states {
            let e = *self.owner.get(&s.meta.id).ok_or(MdError::UnknownBox(s.meta.id))?;
            parts[e].push(s);
        }
        let results = self.on_every_endpoint(parts, |ep, part| if part.is_empty() { Ok(()) } else { ep.restore(part) });
        for (e, r) in results.into_iter().enumerate() {
            r.map_err(|err| lost(&*self.endpoints[e], "restore", err))?;
        }
        Ok(())
    }

    /// Ids of every box this pool holds, ascending.
    pub fn box_ids(&self) -> Vec<PointId> {
        let mut ids: Vec<PointId> = self.owner.keys().copied().collect();
        ids.sort_unstable();
        ids
    }

    /// Runs `f` on every endpoint with its part, concurrently (one thread per endpoint).
    fn on_every_endpoint<P: Send, R: Send>(&mut self, parts: Vec<P>, f: impl Fn(&mut dyn Endpoint, P) -> R + Sync) -> Vec<R> {
        if self.endpoints.len() == 1 {
            return parts.into_iter().map(|p| f(&mut *self.endpoints[0], p)).collect();
        }
        std::thread::scope(|s| {
            let handles: Vec<_> = self.endpoints.iter_mut().zip(parts).map(|(ep, p)| {
                let f = &f;
                s.spawn(move || f(&mut **ep, p))
            }).collect();
            handles.into_iter().map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
        })
    }
}

fn lost(ep: &dyn Endpoint, when: &str, err: MdError) -> MdError {
    MdError::Worker { worker: ep.name(), msg: format!("failed during {when}: {err}") }
}

/// A remote worker over gRPC. Calls block on a shared tokio runtime.
pub struct Remote {
    addr: String,
    rt: Arc<tokio::runtime::Runtime>,
    client: pb::md_worker_client::MdWorkerClient<tonic::transport::Channel>,
    session: Option<u64>,
    kind: String,
    stream: Option<StepStream>,
}

struct StepStream {
    tx: tokio::sync::mpsc::Sender<pb::StepBatch>,
    rx: tonic::Streaming<pb::StepResults>,
}

impl Remote {
    /// Connects to `addr` (`host:port`) and checks the protocol version.
    pub fn connect(addr: &str, rt: Arc<tokio::runtime::Runtime>) -> Result<Self, MdError> {
        let url = if addr.starts_with("http") { addr.to_string() } else { format!("http://{addr}") };
        let worker = |msg: String| MdError::Worker { worker: addr.to_string(), msg };
        let client = rt.block_on(async {
            let ch = tonic::transport::Endpoint::from_shared(url.clone())
                .map_err(|e| worker(format!("bad address: {e}")))?
                .connect_timeout(std::time::Duration::from_secs(10))
                .tcp_nodelay(true)
                .initial_stream_window_size(wire::HTTP2_STREAM_WINDOW)
                .initial_connection_window_size(wire::HTTP2_CONNECTION_WINDOW)
                .connect()
                .await
                .map_err(|e| worker(format!("cannot connect: {e}")))?;
            Ok::<_, MdError>(pb::md_worker_client::MdWorkerClient::new(ch).max_decoding_message_size(wire::MAX_MESSAGE).max_encoding_message_size(wire::MAX_MESSAGE))
        })?;
        let mut remote = Remote { addr: addr.to_string(), rt, client, session: None, kind: String::new(), stream: None };
        let info = remote.rt.block_on(remote.client.info(pb::InfoRequest {})).map_err(|s| worker(wire::status_text(&s)))?.into_inner();
        if info.protocol_version != mscale_proto::COUPLING_PROTOCOL_VERSION {
            return Err(worker(format!("speaks coupling protocol {}, this build speaks {}", info.protocol_version, mscale_proto::COUPLING_PROTOCOL_VERSION)));
        }
        Ok(remote)
    }

    fn err(&self, s: tonic::Status) -> MdError {
        MdError::Worker { worker: self.addr.clone(), msg: wire::status_text(&s) }
    }

    fn session(&self) -> Result<u64, MdError> {
        self.session.ok_or_else(|| MdError::invalid("pool", "step before open"))
    }
}

impl Endpoint for Remote {
    fn name(&self) -> String {
        self.addr.clone()
    }

    fn open(&mut self, potential: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
        let pref = pb::PotentialRef { name: potential.name.clone(), sha256: potential.sha256.clone() };
        let present = self.rt.block_on(self.client.has_potential(pref.clone())).map_err(|s| self.err(s))?.into_inner().present;
        let req = pb::OpenRequest {
            protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
            potential: Some(pref),
            potential_bytes: if present { Vec::new() } else { potential.bytes.as_ref().clone() },
            boxes: specs.iter().map(wire::spec_to_pb).collect(),
            backend: String::new(),
            session: self.session.unwrap_or(0),
        };
        let resp = self.rt.block_on(self.client.open(req)).map_err(|s| self.err(s))?.into_inner();
        self.session = Some(resp.session);
        self.kind = format!("{}/{}", resp.backend, resp.precision);
        Ok(())
    }

    fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let session = self.session()?;
        if self.stream.is_none() {
            let (tx, rx) = tokio::sync::mpsc::channel(16);
            let out = tokio_stream::wrappers::ReceiverStream::new(rx);
            let mut client = self.client.clone();
            let resp = self.rt.block_on(client.step(out)).map_err(|s| self.err(s))?;
            self.stream = Some(StepStream { tx, rx: resp.into_inner() });
        }
        let addr = self.addr.clone();
        let stream = self.stream.as_mut().ok_or_else(|| MdError::invalid("pool", "no step stream"))?;
        let chunks: Vec<&[BoxWork]> = wire::chunks(work).collect();
        let result = self.rt.block_on(async {
            for c in &chunks {
                let batch = pb::StepBatch { session, step, work: c.iter().map(wire::work_to_pb).collect() };
                stream.tx.send(batch).await.map_err(|_| format!("the step stream to {addr} closed"))?;
            }
            let mut out = Vec::with_capacity(work.len());
            for _ in &chunks {
                match stream.rx.message().await {
                    Ok(Some(r)) => {
                        for res in r.results {
                            out.push(wire::result_from_pb(&res).map_err(|e| e.to_string())?);
                        }
                    }
                    Ok(None) => return Err(format!("{addr} closed the step stream")),
                    Err(s) => return Err(wire::status_text(&s)),
                }
            }
            Ok(out)
        });
        result.map_err(|msg| {
            self.stream = None;
            MdError::Worker { worker: self.addr.clone(), msg }
        })
    }

    fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        let req = pb::SnapshotRequest { session: self.session()?, point_ids: ids.to_vec() };
        let resp = self.rt.block_on(self.client.snapshot(req)).map_err(|s| self.err(s))?.into_inner();
        resp.states.iter().map(|b| serde_json::from_slice(b).map_err(|e| MdError::invalid("box state", e.to_string()))).collect()
    }

    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        let states = states.iter().map(|s| serde_json::to_vec(s).map_err(|e| MdError::invalid("box state", e.to_string()))).collect::<Result<_, _>>()?;
        let req = pb::RestoreRequest { session: self.session()?, states };
        self.rt.block_on(self.client.restore(req)).map_err(|s| self.err(s))?;
        Ok(())
    }

    fn kind(&self) -> String {
        self.kind.clone()
    }
}

/// Closes the session, so a long-lived worker does not keep the boxes of finished runs
/// (best effort, bounded to 2 s: the worker may be gone).
impl Drop for Remote {
    fn drop(&mut self) {
        let Some(session) = self.session else { return };
        self.stream = None;
        // Not from inside an async context (block_on would panic there); the session then
        // stays until the worker exits.
        if tokio::runtime::Handle::try_current().is_ok() {
            return;
        }
        let mut client = self.client.clone();
        let _ = self.rt.block_on(async move { tokio::time::timeout(std::time::Duration::from_secs(2), client.close(pb::CloseRequest { session })).await });
    }
}

#[cfg(test)]
mod tests {
    use super::proportional_blocks;

    #[test]
    fn blocks_follow_the_weights_and_cover_every_box() {
        assert_eq!(proportional_blocks(10, &[1.0, 1.0]), vec![5, 5]);
        assert_eq!(proportional_blocks(10, &[3.0, 1.0]), vec![8, 2]);
        assert_eq!(proportional_blocks(7, &[1.0, 1.0, 1.0]), vec![3, 2, 2]);
        assert_eq!(proportional_blocks(6, &[2.0, 0.0, f64::NAN]), vec![2, 2, 2]);
        assert_eq!(proportional_blocks(3, &[1e9, 1.0]), vec![3, 0]);
        assert_eq!(proportional_blocks(0, &[1.0, 2.0]), vec![0, 0]);
        for n in 0..50 {
            let w = [0.3, 1.7, 2.2, 0.01];
            assert_eq!(proportional_blocks(n, &w).iter().sum::<usize>(), n);
            assert_eq!(proportional_blocks(n, &w), proportional_blocks(n, &w));
        }
    }
}
