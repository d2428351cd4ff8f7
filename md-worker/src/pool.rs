//! The client side of a worker pool: boxes spread over endpoints, each either an in-process
//! back end or a remote `md-worker serve` reached over gRPC (`mscale.coupling.v1`).
//!
//! Every box is owned by exactly one endpoint; a step's work is split by owner, run on all
//! endpoints at once (one thread per endpoint), and the results are put back in the order of
//! the request. Since every box is computed independently and deterministically, the result
//! does not depend on how many endpoints there are or which kind they are.
//!
//! An endpoint that is lost mid-run (its worker killed, frozen past the call's deadline, or
//! declared lost by the orchestrator) is replaced without touching the others: the pool logs
//! every input it sends since the last checkpoint ([`crate::recovery`]), restores only the lost
//! endpoint's boxes from that checkpoint onto surviving endpoints of the same back end and
//! precision, replays their logged inputs in order, redoes the interrupted call for them and
//! goes on; the results are bitwise those of an uninterrupted run.

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
use crate::recovery::{AbortHandle, Baseline, CheckpointBoxes, InputLog, Recovery, StepDeadline};
use crate::reuse::{Classes, content_hash};
use crate::wire;
use mscale_proto::coupling::v1 as pb;
use std::sync::Arc;
use std::time::{Duration, Instant};

pub use crate::ids::{IdHasher, IdMap};
pub use crate::source::PotentialSource;

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
    /// Bound on the wall time of the following calls (remote endpoints; others ignore it).
    fn set_deadline(&mut self, _deadline: Duration) {}
    /// Aborts this endpoint's calls (remote endpoints).
    fn abort_handle(&self) -> Option<AbortHandle> {
        None
    }
    /// Whether the endpoint is gone with its boxes (transport failure, deadline passed,
    /// aborted, or its session unknown): its boxes must be rebuilt elsewhere. An error of an
    /// endpoint that still answers (a refused input) is not a loss.
    fn lost(&self) -> bool {
        false
    }
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
            let choice = crate::device::BackendChoice::named(&self.backend_name).with_threads(self.threads.clone());
            self.backend = Some(crate::device::build(&choice, pot, Some(potential))?);
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

/// Boxes spread over endpoints.
pub struct MdPool {
    endpoints: Vec<Box<dyn Endpoint>>,
    /// Every box: its endpoint, atoms and MD steps done (one lookup per box and step).
    boxes: IdMap<Held>,
    pub times: PoolTimes,
    /// Relative throughput of each endpoint (empty: equal); `open` spreads boxes by it.
    weights: Vec<f64>,
    /// Per endpoint: seconds in step calls and atom-steps done.
    load: Vec<(f64, f64)>,
    /// Per endpoint: false once lost (it holds no boxes and gets no calls).
    alive: Vec<bool>,
    /// Spec of every box, to open it again on another endpoint.
    specs: IdMap<BoxSpec>,
    potential: Option<PotentialSource>,
    /// Every input sent since the last checkpoint.
    log: InputLog,
    deadline: StepDeadline,
    /// Lost endpoints replaced so far.
    recoveries: Vec<Recovery>,
    on_loss: Option<LossHook>,
    /// The continuum step of the last step call (for a loss found by a snapshot).
    last_step: u64,
    /// Boxes that share their computation with bitwise identical ones ([`crate::reuse`]).
    classes: Classes,
}

/// What the pool keeps of one box.
#[derive(Debug, Clone, Copy)]
struct Held {
    /// Index of the endpoint that holds it.
    endpoint: usize,
    /// Atoms (from its spec), for the per-endpoint load.
    atoms: u64,
    /// MD steps it was really stepped in step calls (recovery replays not counted).
    done_steps: u64,
}

/// Told of every lost endpoint once its boxes live on the survivors.
pub type LossHook = Box<dyn FnMut(&Recovery) + Send>;

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
        crate::InitialAtoms::Lattice { kind, cells, orient, .. } => {
            kind.atoms_per_cell(orient) * cells.iter().map(|&c| c as u64).product::<u64>()
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
        let alive = vec![true; endpoints.len()];
        Ok(MdPool {
            endpoints,
            boxes: IdMap::default(),
            times: PoolTimes::default(),
            weights: Vec::new(),
            load,
            alive,
            specs: IdMap::default(),
            potential: None,
            log: InputLog::default(),
            deadline: StepDeadline::default(),
            recoveries: Vec::new(),
            on_loss: None,
            last_step: 0,
            classes: Classes::default(),
        })
    }

    /// Deadline of remote calls (default [`StepDeadline::Auto`]).
    pub fn set_deadline(&mut self, deadline: StepDeadline) {
        self.deadline = deadline;
    }

    /// Bound of the input log (default [`crate::recovery::DEFAULT_LOG_LIMIT_BYTES`]).
    pub fn set_log_limit(&mut self, bytes: usize) {
        self.log.set_limit(bytes);
    }

    pub fn set_loss_hook(&mut self, hook: LossHook) {
        self.on_loss = Some(hook);
    }

    /// The boxes' states are those of the checkpoint written at the end of continuum step
    /// `step` (read back by `boxes` when an endpoint is lost): the input log starts afresh.
    pub fn mark_checkpoint(&mut self, step: u64, boxes: CheckpointBoxes) {
        self.log.restart(Baseline::Checkpoint { step, boxes });
    }

    /// Lost endpoints replaced so far.
    pub fn recoveries(&self) -> &[Recovery] {
        &self.recoveries
    }

    /// Memory of the input log (bytes).
    pub fn log_bytes(&self) -> usize {
        self.log.bytes()
    }

    /// Abort handles of the endpoints that have one, by endpoint name (the worker's address).
    pub fn abort_handles(&self) -> Vec<(String, AbortHandle)> {
        self.endpoints.iter().filter_map(|e| e.abort_handle().map(|h| (e.name(), h))).collect()
    }

    /// Deadline of a call of `atom_steps` on endpoint `e`.
    fn deadline_for(&self, e: usize, atom_steps: f64) -> Duration {
        let (secs, done) = self.load[e];
        self.deadline.for_work(atom_steps, (secs > 0.0 && done > 0.0).then(|| done / secs))
    }

    fn work_atom_steps(&self, work: &[BoxWork]) -> f64 {
        work.iter().map(|w| w.steps as f64 * self.atoms_of(w.id) as f64).sum()
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
        let mut out: Vec<EndpointLoad> = self
            .endpoints
            .iter()
            .zip(&self.load)
            .map(|(e, l)| EndpointLoad { name: e.name(), step_seconds: l.0, atom_steps: l.1, ..Default::default() })
            .collect();
        for b in self.boxes.values() {
            out[b.endpoint].boxes += 1;
            out[b.endpoint].atoms += b.atoms;
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
        if let Some(e) = self.alive.iter().position(|a| !a) {
            return Err(MdError::Worker {
                worker: self.endpoints[e].name(),
                msg: "was lost before every box was opened; the run must start again".into(),
            });
        }
        let dest: Vec<usize> = if self.weights.is_empty() {
            (0..specs.len()).map(|k| k * n / specs.len().max(1)).collect()
        } else {
            // Shares of all boxes opened so far and these, so that several `open` calls (one
            // per body) add up to one proportional partition.
            let mut have = vec![0usize; n];
            self.boxes.values().for_each(|b| have[b.endpoint] += 1);
            let target = proportional_blocks(self.boxes.len() + specs.len(), &self.weights);
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
            if self.boxes.contains_key(&s.id) {
                return Err(MdError::invalid("box spec", format!("point {} is opened twice", s.id)));
            }
            parts[dest[k]].push(s.clone());
        }
        for (e, part) in parts.iter().enumerate() {
            let d = self.deadline_for(e, part.iter().map(|s| spec_atoms(s) as f64 * (s.relax_steps + 1) as f64).sum());
            self.endpoints[e].set_deadline(d);
        }
        let results = self.on_every_endpoint(parts, |ep, part| if part.is_empty() { Ok(()) } else { ep.open(potential, &part) });
        for (e, r) in results.into_iter().enumerate() {
            r.map_err(|err| lost(&*self.endpoints[e], "open", err))?;
        }
        for (k, s) in specs.iter().enumerate() {
            self.boxes.insert(s.id, Held { endpoint: dest[k], atoms: spec_atoms(s), done_steps: 0 });
            self.specs.insert(s.id, s.clone());
        }
        self.potential = Some(potential.clone());
        Ok(())
    }

    /// Lets the named boxes share their computation with bitwise identical boxes (exact reuse,
    /// [`crate::reuse`]): boxes whose states have the same content hash now (point ids left out)
    /// form one class. Results stay bitwise those of stepping every box.
    pub fn enable_reuse(&mut self, ids: &[PointId]) -> Result<(), MdError> {
        let mut hashes = Vec::with_capacity(ids.len());
        // In chunks, so a large pool is not copied out at once.
        for chunk in ids.chunks(256) {
            for s in self.snapshot_physical(chunk)? {
                hashes.push((s.meta.id, content_hash(&s)?));
            }
        }
        self.classes.join(&hashes);
        Ok(())
    }

    /// Distinct box states among the boxes that take part in reuse (0 without reuse).
    pub fn reuse_classes(&self) -> usize {
        self.classes.class_count()
    }

    /// MD steps box `id` was really stepped by step calls (less than it was sent under reuse).
    pub fn md_steps_done(&self, id: PointId) -> u64 {
        self.boxes.get(&id).map_or(0, |b| b.done_steps)
    }

    /// The endpoint that holds box `id`.
    fn endpoint_of(&self, id: PointId) -> Result<usize, MdError> {
        self.boxes.get(&id).map(|b| b.endpoint).ok_or(MdError::UnknownBox(id))
    }

    /// Atoms of box `id` (0 if unknown).
    pub fn atoms_of(&self, id: PointId) -> u64 {
        self.boxes.get(&id).map_or(0, |b| b.atoms)
    }

    /// Gives each `(from, to)` box pair the state `from` has now.
    fn copy_boxes(&mut self, pairs: &[(PointId, PointId)]) -> Result<(), MdError> {
        if pairs.is_empty() {
            return Ok(());
        }
        let mut from: Vec<PointId> = pairs.iter().map(|p| p.0).collect();
        from.sort_unstable();
        from.dedup();
        let states = self.snapshot_physical(&from)?;
        let by_id: IdMap<&BoxState> = states.iter().map(|s| (s.meta.id, s)).collect();
        let copies = pairs
            .iter()
            .map(|(f, t)| {
                let mut s = (*by_id.get(f).ok_or(MdError::UnknownBox(*f))?).clone();
                s.meta.id = *t;
                Ok(s)
            })
            .collect::<Result<Vec<_>, MdError>>()?;
        self.restore_physical(copies)
    }

    /// Advances boxes; `out[k]` is the result of `work[k]`. An endpoint lost during the call is
    /// replaced: its boxes are rebuilt on the survivors (restored from the last checkpoint, the
    /// logged inputs replayed, this call redone), so the result is that of an uninterrupted run.
    /// Under reuse, one box per group of bitwise identical boxes with bitwise identical work is
    /// stepped, and its result goes to all of them; the input log keeps the work of every box,
    /// so a replay rebuilds each box on its own, to the same bits.
    pub fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let out = if self.classes.is_empty() {
            self.step_physical(step, work)?
        } else {
            let plan = self.classes.plan(work)?;
            self.last_step = step;
            self.copy_boxes(&plan.copies)?;
            let res = self.step_physical(step, &plan.physical)?;
            self.classes.apply(&plan);
            work.iter()
                .zip(&plan.source)
                .map(|(w, &k)| {
                    let mut r = res[k];
                    r.id = w.id;
                    r
                })
                .collect()
        };
        self.log.record(step, work);
        Ok(out)
    }

    /// [`MdPool::step`] of every box as named (no reuse), without logging the inputs; counts
    /// the MD steps done.
    fn step_physical(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let start = Instant::now();
        self.last_step = step;
        let n = self.endpoints.len();
        let each = work.len() / n + 1;
        let mut parts: Vec<Vec<BoxWork>> = (0..n).map(|_| Vec::with_capacity(each)).collect();
        let mut slot: Vec<Vec<usize>> = (0..n).map(|_| Vec::with_capacity(each)).collect();
        let mut atom_steps = vec![0.0; n];
        for (k, w) in work.iter().enumerate() {
            let b = self.boxes.get_mut(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            // Counted when sent: a step call that fails ends the run, and the recovery of a
            // lost endpoint below redoes the call without counting it again.
            b.done_steps += w.steps;
            parts[b.endpoint].push(*w);
            slot[b.endpoint].push(k);
            atom_steps[b.endpoint] += w.steps as f64 * b.atoms as f64;
        }
        for (e, &a) in atom_steps.iter().enumerate() {
            let d = self.deadline_for(e, a);
            self.endpoints[e].set_deadline(d);
        }
        let results = self.on_every_endpoint(parts, |ep, part| {
            let t = Instant::now();
            let r = if part.is_empty() { Ok(Vec::new()) } else { ep.step(step, &part) };
            r.map(|r| (r, t.elapsed().as_secs_f64()))
        });
        let mut out = vec![BoxResult::default(); work.len()];
        let mut slowest: f64 = 0.0;
        let mut failed = Vec::new();
        for (e, r) in results.into_iter().enumerate() {
            let (res, secs) = match r {
                Ok(r) => r,
                Err(err) if self.endpoints[e].lost() => {
                    failed.push((e, err.to_string()));
                    continue;
                }
                Err(err) => return Err(lost(&*self.endpoints[e], &format!("continuum step {step}"), err)),
            };
            slowest = slowest.max(secs);
            self.load[e].0 += secs;
            self.load[e].1 += atom_steps[e];
            // A worker that answers garbage (a non-finite value, other boxes than asked) is
            // faulty: it is dropped as a lost one is, and its boxes rebuilt elsewhere.
            if let Err(err) = place_results(&self.endpoints[e].name(), &slot[e], work, res, &mut out) {
                failed.push((e, format!("declared faulty: {err}")));
            }
        }
        if !failed.is_empty() {
            self.recover(step, failed, work, &mut out)?;
        }
        self.times.step_wall += start.elapsed().as_secs_f64();
        self.times.md_compute += slowest;
        self.times.calls += 1;
        Ok(out)
    }

    /// Rebuilds the boxes of the `lost` endpoints on the survivors of the same kind: each box is
    /// opened from its spec, restored from the log's baseline (the last checkpoint), sent every
    /// logged input in order, then its item of `work` (the interrupted call), whose result goes
    /// into `out`. Survivors' own boxes are not touched. A survivor lost on the way loses its
    /// boxes too, and they are rebuilt in the next round.
    fn recover(&mut self, step: u64, mut gone: Vec<(usize, String)>, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        let position: IdMap<usize> = work.iter().enumerate().map(|(k, w)| (w.id, k)).collect();
        while !gone.is_empty() {
            let names = gone.iter().map(|(e, _)| self.endpoints[*e].name()).collect::<Vec<_>>().join(", ");
            let kind = self.endpoints[gone[0].0].kind();
            let why = gone.iter().map(|(_, w)| w.as_str()).collect::<Vec<_>>().join("; ");
            for (e, _) in &gone {
                self.alive[*e] = false;
            }
            let mut boxes: Vec<Vec<PointId>> = vec![Vec::new(); self.endpoints.len()];
            for (id, b) in &self.boxes {
                if !self.alive[b.endpoint] {
                    boxes[b.endpoint].push(*id);
                }
            }
            let moved: Vec<PointId> = {
                let mut m: Vec<PointId> = boxes.iter().flatten().copied().collect();
                m.sort_unstable();
                m
            };
            let survivors: Vec<usize> = (0..self.endpoints.len())
                .filter(|&e| self.alive[e] && (self.endpoints[e].kind() == kind || self.endpoints[e].kind().is_empty()))
                .collect();
            if survivors.is_empty() {
                return Err(MdError::Worker {
                    worker: names,
                    msg: format!(
                        "was lost during continuum step {step} ({why}); no surviving worker of back end {kind} holds this run to restore its {} boxes onto",
                        moved.len()
                    ),
                });
            }
            if let Some(broken) = &self.log.broken {
                return Err(MdError::Worker {
                    worker: names,
                    msg: format!("was lost during continuum step {step} ({why}); its boxes cannot be replayed: {broken}"),
                });
            }
            let potential = self.potential.clone().ok_or_else(|| MdError::invalid("pool", "recovery before open"))?;
            let states = match &self.log.baseline {
                Baseline::Opened => None,
                Baseline::Checkpoint { boxes, step: at } => Some(boxes(&moved).map_err(|e| MdError::Worker {
                    worker: names.clone(),
                    msg: format!(
                        "was lost during continuum step {step} ({why}); cannot read its boxes from the checkpoint of step {at}: {e}"
                    ),
                })?),
            };
            // The moved boxes spread over the survivors by weight, in contiguous blocks.
            let weights: Vec<f64> = survivors.iter().map(|&e| self.weights.get(e).copied().unwrap_or(1.0)).collect();
            let sizes = proportional_blocks(moved.len(), &weights);
            let mut dest: IdMap<usize> = IdMap::default();
            let mut plans: Vec<Option<ReplayPlan>> = (0..self.endpoints.len()).map(|_| None).collect();
            let mut next = 0;
            for (&e, &size) in survivors.iter().zip(&sizes) {
                let ids = &moved[next..next + size];
                next += size;
                if ids.is_empty() {
                    continue;
                }
                ids.iter().for_each(|id| _ = dest.insert(*id, e));
                let mine = |w: &&BoxWork| ids.binary_search(&w.id).is_ok();
                let calls: Vec<(u64, Vec<BoxWork>, Duration)> = self
                    .log
                    .calls
                    .iter()
                    .map(|(s, ws)| {
                        let part: Vec<BoxWork> = ws.iter().filter(mine).copied().collect();
                        let d = self.deadline_for(e, self.work_atom_steps(&part));
                        (*s, part, d)
                    })
                    .filter(|c| !c.1.is_empty())
                    .collect();
                let current: Vec<BoxWork> = work.iter().filter(mine).copied().collect();
                let open_atoms =
                    ids.iter().map(|id| self.specs.get(id).map_or(0.0, |s| spec_atoms(s) as f64 * (s.relax_steps + 1) as f64)).sum();
                plans[e] = Some(ReplayPlan {
                    specs: ids.iter().map(|id| self.specs.get(id).cloned().ok_or(MdError::UnknownBox(*id))).collect::<Result<_, _>>()?,
                    states: states.as_ref().map(|all| all.iter().filter(|s| ids.binary_search(&s.meta.id).is_ok()).cloned().collect()),
                    calls,
                    current_deadline: self.deadline_for(e, self.work_atom_steps(&current)),
                    current,
                    open_deadline: self.deadline_for(e, open_atoms),
                    kind: kind.clone(),
                });
            }
            // The survivors take their boxes now, so a survivor lost below loses them too.
            for (id, &e) in &dest {
                if let Some(b) = self.boxes.get_mut(id) {
                    b.endpoint = e;
                }
            }
            let expect: Vec<Vec<usize>> = plans
                .iter()
                .map(|p| p.as_ref().map_or(Vec::new(), |p| p.current.iter().filter_map(|w| position.get(&w.id).copied()).collect()))
                .collect();
            let results = self.on_every_endpoint(plans, |ep, plan| match plan {
                None => Ok(Vec::new()),
                Some(plan) => replay(ep, &potential, plan, step),
            });
            let mut again = Vec::new();
            for (e, r) in results.into_iter().enumerate() {
                match r {
                    Ok(res) => {
                        if let Err(err) = place_results(&self.endpoints[e].name(), &expect[e], work, res, out) {
                            again.push((e, format!("declared faulty: {err}")));
                        }
                    }
                    Err(err) if self.endpoints[e].lost() => again.push((e, err.to_string())),
                    Err(err) => return Err(lost(&*self.endpoints[e], &format!("the replay of lost boxes at continuum step {step}"), err)),
                }
            }
            let onto_of = |ids: &[PointId]| {
                let mut v: Vec<String> = ids.iter().filter_map(|id| dest.get(id)).map(|&e| self.endpoints[e].name()).collect();
                v.dedup();
                v
            };
            for (e, w) in &gone {
                let mut ids = boxes[*e].clone();
                ids.sort_unstable();
                let (mut calls, mut box_steps, mut md_steps) = (0, 0, 0);
                for (_, ws) in &self.log.calls {
                    let mine: Vec<&BoxWork> = ws.iter().filter(|w| ids.binary_search(&w.id).is_ok()).collect();
                    calls += usize::from(!mine.is_empty());
                    box_steps += mine.len() as u64;
                    md_steps += mine.iter().map(|w| w.steps).sum::<u64>();
                }
                let r = Recovery {
                    worker: self.endpoints[*e].name(),
                    step,
                    why: w.clone(),
                    onto: onto_of(&ids),
                    boxes: ids,
                    baseline: self.log.baseline.describe(),
                    replayed_calls: calls,
                    replayed_box_steps: box_steps,
                    replayed_md_steps: md_steps,
                };
                if let Some(hook) = self.on_loss.as_mut() {
                    hook(&r);
                }
                self.recoveries.push(r);
            }
            gone = again;
        }
        Ok(())
    }

    /// States of the named boxes, in the order of `ids` (under reuse, a box's state is its
    /// representative's, under its own id).
    /// An endpoint found lost here is replaced first (its boxes rebuilt on the survivors).
    pub fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        if self.classes.is_empty() {
            return self.snapshot_physical(ids);
        }
        let mut reps: Vec<PointId> = ids.iter().map(|&id| self.classes.rep(id)).collect();
        reps.sort_unstable();
        reps.dedup();
        let states = self.snapshot_physical(&reps)?;
        let by_id: IdMap<&BoxState> = states.iter().map(|s| (s.meta.id, s)).collect();
        ids.iter()
            .map(|&id| {
                let mut s = (*by_id.get(&self.classes.rep(id)).ok_or(MdError::UnknownBox(id))?).clone();
                s.meta.id = id;
                Ok(s)
            })
            .collect()
    }

    /// The states the endpoints hold for the named boxes.
    fn snapshot_physical(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        let mut out = Vec::with_capacity(ids.len());
        let mut k = 0;
        while k < ids.len() {
            // Consecutive ids on one endpoint go in one call.
            let e = self.endpoint_of(ids[k])?;
            let mut end = k + 1;
            while end < ids.len() && self.boxes.get(&ids[end]).map(|b| b.endpoint) == Some(e) {
                end += 1;
            }
            let d = self.deadline_for(e, 0.0);
            self.endpoints[e].set_deadline(d);
            match self.endpoints[e].snapshot(&ids[k..end]) {
                Ok(states) => {
                    out.extend(states);
                    k = end;
                }
                Err(err) if self.endpoints[e].lost() => self.recover(self.last_step, vec![(e, err.to_string())], &[], &mut [])?,
                Err(err) => return Err(lost(&*self.endpoints[e], "snapshot", err)),
            }
        }
        Ok(out)
    }

    /// Puts saved box states back (a checkpoint): each state goes to the endpoint that owns its
    /// box, so the boxes must have been opened first (with the same specs). Refuses a state of
    /// a box this pool does not hold, before touching any endpoint.
    pub fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        if !self.classes.is_empty() {
            // Boxes whose state a restored box holds, and that are not restored themselves,
            // take that state first; the restored boxes that take part in reuse form classes by
            // the content of the states restored.
            let restored: IdMap<()> = states.iter().map(|s| (s.meta.id, ())).collect();
            let mut keep = Vec::new();
            for s in &states {
                if self.classes.rep(s.meta.id) == s.meta.id {
                    keep.extend(
                        self.classes.dependants(s.meta.id).into_iter().filter(|d| !restored.contains_key(d)).map(|d| (s.meta.id, d)),
                    );
                }
            }
            self.copy_boxes(&keep)?;
            for (_, d) in &keep {
                self.classes.detach(*d);
            }
            let mut hashes = Vec::new();
            for s in &states {
                if self.classes.contains(s.meta.id) {
                    hashes.push((s.meta.id, content_hash(s)?));
                }
            }
            self.restore_physical(states)?;
            self.classes.join(&hashes);
        } else {
            self.restore_physical(states)?;
        }
        // Until the caller names the checkpoint these states came from, a loss cannot be replayed.
        self.log.invalidate("the boxes were restored from states that name no checkpoint".into());
        Ok(())
    }

    /// Puts states into the endpoints that own their boxes.
    fn restore_physical(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        let mut parts: Vec<Vec<BoxState>> = vec![Vec::new(); self.endpoints.len()];
        for s in states {
            parts[self.endpoint_of(s.meta.id)?].push(s);
        }
        for e in 0..self.endpoints.len() {
            let d = self.deadline_for(e, 0.0);
            self.endpoints[e].set_deadline(d);
        }
        let results = self.on_every_endpoint(parts, |ep, part| if part.is_empty() { Ok(()) } else { ep.restore(part) });
        for (e, r) in results.into_iter().enumerate() {
            r.map_err(|err| lost(&*self.endpoints[e], "restore", err))?;
        }
        Ok(())
    }

    /// Ids of every box this pool holds, ascending.
    pub fn box_ids(&self) -> Vec<PointId> {
        let mut ids: Vec<PointId> = self.boxes.keys().copied().collect();
        ids.sort_unstable();
        ids
    }

    /// Runs `f` on every endpoint with its part, concurrently (one thread per endpoint).
    fn on_every_endpoint<P: Send, R: Send>(&mut self, parts: Vec<P>, f: impl Fn(&mut dyn Endpoint, P) -> R + Sync) -> Vec<R> {
        if self.endpoints.len() == 1 {
            return parts.into_iter().map(|p| f(&mut *self.endpoints[0], p)).collect();
        }
        std::thread::scope(|s| {
            let handles: Vec<_> = self
                .endpoints
                .iter_mut()
                .zip(parts)
                .map(|(ep, p)| {
                    let f = &f;
                    s.spawn(move || f(&mut **ep, p))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
        })
    }
}

/// What one survivor does to take over lost boxes.
struct ReplayPlan {
    specs: Vec<BoxSpec>,
    /// Their checkpoint states (`None`: the baseline is the boxes as opened).
    states: Option<Vec<BoxState>>,
    /// The logged calls, restricted to these boxes, each with its deadline.
    calls: Vec<(u64, Vec<BoxWork>, Duration)>,
    /// The interrupted call's work of these boxes.
    current: Vec<BoxWork>,
    current_deadline: Duration,
    open_deadline: Duration,
    /// The back end and precision the boxes lived on.
    kind: String,
}

/// Opens, restores and replays lost boxes on `ep`; returns the results of the interrupted call.
fn replay(ep: &mut dyn Endpoint, potential: &PotentialSource, plan: ReplayPlan, step: u64) -> Result<Vec<BoxResult>, MdError> {
    ep.set_deadline(plan.open_deadline);
    ep.open(potential, &plan.specs)?;
    if ep.kind() != plan.kind {
        return Err(MdError::Worker {
            worker: ep.name(),
            msg: format!("holds {} boxes, not {} like the lost worker: it cannot take over at continuum step {step}", ep.kind(), plan.kind),
        });
    }
    if let Some(states) = plan.states {
        ep.restore(states)?;
    }
    for (s, work, deadline) in &plan.calls {
        ep.set_deadline(*deadline);
        ep.step(*s, work)?;
    }
    if plan.current.is_empty() {
        return Ok(Vec::new());
    }
    ep.set_deadline(plan.current_deadline);
    ep.step(step, &plan.current)
}

/// Checks an endpoint's results of the items `slots` of `work` (count, ids, finite values,
/// stress sampling); returns them with their slots.
/// Checks an endpoint's answer to the boxes `work[k]`, k in `slots`, and moves result j into
/// `out[slots[j]]`; nothing is moved when any result is wrong.
fn place_results(name: &str, slots: &[usize], work: &[BoxWork], res: Vec<BoxResult>, out: &mut [BoxResult]) -> Result<(), MdError> {
    if res.len() != slots.len() {
        return Err(MdError::invalid("worker reply", format!("{name} returned {} results for {} boxes", res.len(), slots.len())));
    }
    for (&k, r) in slots.iter().zip(&res) {
        if r.id != work[k].id {
            return Err(MdError::invalid("worker reply", format!("{name} answered point {} for point {}", r.id, work[k].id)));
        }
        wire::check_result(r, name)?;
        if r.stress_sampling != work[k].stress_sampling {
            return Err(MdError::Worker {
                worker: name.to_string(),
                msg: format!(
                    "returned the `{}` stress of point {} when `{}` was asked (a worker that predates stress sampling?)",
                    r.stress_sampling.name(),
                    r.id,
                    work[k].stress_sampling.name()
                ),
            });
        }
    }
    for (&k, r) in slots.iter().zip(res) {
        out[k] = r;
    }
    Ok(())
}

fn lost(ep: &dyn Endpoint, when: &str, err: MdError) -> MdError {
    MdError::Worker { worker: ep.name(), msg: format!("failed during {when}: {err}") }
}

/// A remote worker over gRPC. Calls block on a shared tokio runtime, each bounded by a
/// deadline and by an [`AbortHandle`]; a call that fails at the transport, passes its
/// deadline, is aborted, or finds its session gone marks the endpoint lost.
pub struct Remote {
    addr: String,
    rt: Arc<tokio::runtime::Runtime>,
    client: pb::md_worker_client::MdWorkerClient<tonic::transport::Channel>,
    session: Option<u64>,
    kind: String,
    stream: Option<StepStream>,
    abort: AbortHandle,
    deadline: Duration,
    lost: bool,
}

struct StepStream {
    tx: tokio::sync::mpsc::Sender<pb::StepBatch>,
    rx: tonic::Streaming<pb::StepResults>,
}

/// How a remote call failed.
enum CallError {
    /// The worker is gone with its boxes (or cannot be waited for).
    Lost(String),
    /// The worker answered with an error (a refused input).
    Refused(String),
}

fn status_error(s: &tonic::Status) -> CallError {
    use tonic::Code;
    let text = wire::status_text(s);
    match s.code() {
        // Transport failures, and a session the worker no longer has (it restarted).
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded | Code::Aborted | Code::NotFound => {
            CallError::Lost(text)
        }
        _ => CallError::Refused(text),
    }
}

/// Runs `call` unless the endpoint is aborted or `deadline` passes first.
fn guarded<T>(
    rt: &tokio::runtime::Runtime,
    abort: &AbortHandle,
    deadline: Duration,
    what: &str,
    call: impl std::future::Future<Output = Result<T, CallError>>,
) -> Result<T, CallError> {
    if let Some(why) = abort.reason() {
        return Err(CallError::Lost(format!("declared lost before {what} ({why})")));
    }
    rt.block_on(async {
        tokio::select! {
            r = call => r,
            why = abort.aborted() => Err(CallError::Lost(format!("declared lost during {what} ({why})"))),
            _ = tokio::time::sleep(deadline) => Err(CallError::Lost(format!("no reply to {what} within its deadline of {:.1} s (--step-deadline)", deadline.as_secs_f64()))),
        }
    })
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
            Ok::<_, MdError>(
                pb::md_worker_client::MdWorkerClient::new(ch)
                    .max_decoding_message_size(wire::MAX_MESSAGE)
                    .max_encoding_message_size(wire::MAX_MESSAGE),
            )
        })?;
        let deadline = StepDeadline::AUTO_MIN;
        let remote = Remote {
            addr: addr.to_string(),
            rt,
            client,
            session: None,
            kind: String::new(),
            stream: None,
            abort: AbortHandle::default(),
            deadline,
            lost: false,
        };
        let mut c = remote.client.clone();
        let info =
            guarded(
                &remote.rt,
                &remote.abort,
                deadline,
                "info",
                async move { c.info(pb::InfoRequest {}).await.map_err(|s| status_error(&s)) },
            )
            .map_err(|e| {
                worker(match e {
                    CallError::Lost(m) | CallError::Refused(m) => m,
                })
            })?
            .into_inner();
        if info.protocol_version != mscale_proto::COUPLING_PROTOCOL_VERSION {
            return Err(worker(format!(
                "speaks coupling protocol {}, this build speaks {}",
                info.protocol_version,
                mscale_proto::COUPLING_PROTOCOL_VERSION
            )));
        }
        Ok(remote)
    }

    /// The error of a failed call; a loss marks the endpoint lost for good.
    fn failed(&mut self, e: CallError) -> MdError {
        let msg = match e {
            CallError::Lost(m) => {
                self.lost = true;
                self.stream = None;
                m
            }
            CallError::Refused(m) => m,
        };
        MdError::Worker { worker: self.addr.clone(), msg }
    }

    fn session(&self) -> Result<u64, MdError> {
        if self.lost {
            return Err(MdError::Worker { worker: self.addr.clone(), msg: "is lost".into() });
        }
        self.session.ok_or_else(|| MdError::invalid("pool", "step before open"))
    }

    /// A unary call, guarded.
    fn call<T, F>(
        &mut self,
        what: &str,
        f: impl FnOnce(pb::md_worker_client::MdWorkerClient<tonic::transport::Channel>) -> F,
    ) -> Result<T, MdError>
    where
        F: std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    {
        if self.lost {
            return Err(MdError::Worker { worker: self.addr.clone(), msg: "is lost".into() });
        }
        let fut = f(self.client.clone());
        match guarded(&self.rt, &self.abort, self.deadline, what, async move {
            fut.await.map(tonic::Response::into_inner).map_err(|s| status_error(&s))
        }) {
            Ok(r) => Ok(r),
            Err(e) => Err(self.failed(e)),
        }
    }
}

impl Endpoint for Remote {
    fn name(&self) -> String {
        self.addr.clone()
    }

    fn open(&mut self, potential: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
        let pref = pb::PotentialRef { name: potential.name.clone(), sha256: potential.sha256.clone() };
        let p = pref.clone();
        let present = self.call("has-potential", |mut c| async move { c.has_potential(p).await })?.present;
        let req = pb::OpenRequest {
            protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
            potential: Some(pref),
            potential_bytes: if present { Vec::new() } else { potential.bytes.as_ref().clone() },
            boxes: specs.iter().map(wire::spec_to_pb).collect(),
            backend: String::new(),
            session: self.session.unwrap_or(0),
        };
        let resp = self.call("open", |mut c| async move { c.open(req).await })?;
        self.session = Some(resp.session);
        self.kind = format!("{}/{}", resp.backend, resp.precision);
        Ok(())
    }

    fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
        let session = self.session()?;
        if self.stream.is_none() {
            let (tx, rx) = tokio::sync::mpsc::channel(16);
            let out = tokio_stream::wrappers::ReceiverStream::new(rx);
            let resp = self.call("the opening of the step stream", |mut c| async move { c.step(out).await })?;
            self.stream = Some(StepStream { tx, rx: resp });
        }
        let addr = self.addr.clone();
        let mut stream = self.stream.take().ok_or_else(|| MdError::invalid("pool", "no step stream"))?;
        let chunks: Vec<&[BoxWork]> = wire::chunks(work).collect();
        let what = format!("continuum step {step}");
        let result = guarded(&self.rt, &self.abort, self.deadline, &what, async {
            for c in &chunks {
                let batch = wire::batch_to_pb(session, step, c);
                stream.tx.send(batch).await.map_err(|_| CallError::Lost(format!("the step stream to {addr} closed")))?;
            }
            let mut out = Vec::with_capacity(work.len());
            for _ in &chunks {
                match stream.rx.message().await {
                    Ok(Some(r)) => out.extend(wire::results_from_pb(&r).map_err(|e| CallError::Refused(e.to_string()))?),
                    Ok(None) => return Err(CallError::Lost(format!("{addr} closed the step stream"))),
                    Err(s) => return Err(status_error(&s)),
                }
            }
            Ok(out)
        });
        match result {
            Ok(out) => {
                self.stream = Some(stream);
                Ok(out)
            }
            // A stream with an error (or replies still in flight) is not used again.
            Err(e) => Err(self.failed(e)),
        }
    }

    fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        let req = pb::SnapshotRequest { session: self.session()?, point_ids: ids.to_vec() };
        let resp = self.call("snapshot", |mut c| async move { c.snapshot(req).await })?;
        resp.states.iter().map(|b| serde_json::from_slice(b).map_err(|e| MdError::invalid("box state", e.to_string()))).collect()
    }

    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        let states = states
            .iter()
            .map(|s| serde_json::to_vec(s).map_err(|e| MdError::invalid("box state", e.to_string())))
            .collect::<Result<_, _>>()?;
        let req = pb::RestoreRequest { session: self.session()?, states };
        self.call("restore", |mut c| async move { c.restore(req).await })?;
        Ok(())
    }

    fn kind(&self) -> String {
        self.kind.clone()
    }

    fn set_deadline(&mut self, deadline: Duration) {
        self.deadline = deadline;
    }

    fn abort_handle(&self) -> Option<AbortHandle> {
        Some(self.abort.clone())
    }

    fn lost(&self) -> bool {
        self.lost
    }
}

/// Closes the session, so a long-lived worker does not keep the boxes of finished runs
/// (best effort, bounded to 2 s: the worker may be gone).
impl Drop for Remote {
    fn drop(&mut self) {
        let Some(session) = self.session else { return };
        self.stream = None;
        // A lost worker is gone or frozen: nothing to close, nothing to wait for.
        if self.lost {
            return;
        }
        // Not from inside an async context (block_on would panic there); the session then
        // stays until the worker exits.
        if tokio::runtime::Handle::try_current().is_ok() {
            return;
        }
        let mut client = self.client.clone();
        let _ = self.rt.block_on(async move {
            tokio::time::timeout(std::time::Duration::from_secs(2), client.close(pb::CloseRequest { session })).await
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// An in-process endpoint that is lost at its step call `fail_at` (1-based), and for good.
    struct Flaky {
        inner: InProcess,
        calls: u64,
        fail_at: u64,
        gone: bool,
        /// Steps sent to it (box-calls), to see that survivors' boxes are not replayed.
        box_calls: Arc<AtomicU64>,
    }

    impl Endpoint for Flaky {
        fn name(&self) -> String {
            format!("flaky-{}", self.fail_at)
        }
        fn open(&mut self, p: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
            self.inner.open(p, specs)
        }
        fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
            self.calls += 1;
            if self.gone || self.calls == self.fail_at {
                self.gone = true;
                return Err(MdError::Worker { worker: self.name(), msg: "connection reset".into() });
            }
            self.box_calls.fetch_add(work.len() as u64, Ordering::SeqCst);
            self.inner.step(step, work)
        }
        fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
            self.inner.snapshot(ids)
        }
        fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
            self.inner.restore(states)
        }
        fn kind(&self) -> String {
            self.inner.kind()
        }
        fn lost(&self) -> bool {
            self.gone
        }
    }

    /// An endpoint that answers garbage at its call `at`: a NaN stress (`nan`) or the result
    /// of another box (otherwise), as a broken worker or a corrupted reply would.
    struct Garbage {
        inner: InProcess,
        calls: u64,
        at: u64,
        nan: bool,
    }

    impl Endpoint for Garbage {
        fn name(&self) -> String {
            format!("garbage-{}", self.at)
        }
        fn open(&mut self, p: &PotentialSource, specs: &[BoxSpec]) -> Result<(), MdError> {
            self.inner.open(p, specs)
        }
        fn step(&mut self, step: u64, work: &[BoxWork]) -> Result<Vec<BoxResult>, MdError> {
            self.calls += 1;
            let mut r = self.inner.step(step, work)?;
            if self.calls >= self.at {
                if self.nan {
                    r[0].stress_gpa[1] = f64::NAN;
                } else {
                    r[0].id += 1000;
                }
            }
            Ok(r)
        }
        fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
            self.inner.snapshot(ids)
        }
        fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
            self.inner.restore(states)
        }
        fn kind(&self) -> String {
            self.inner.kind()
        }
    }

    #[test]
    fn a_worker_answering_nan_or_other_boxes_is_declared_faulty_and_its_boxes_recovered() {
        let (straight, _, _) = run(&[0, 0, 0], None);
        let straight = straight.unwrap();
        for nan in [true, false] {
            let (mut eps, _): (Vec<_>, Vec<_>) = [u64::MAX, u64::MAX].iter().map(|&f| flaky(f)).unzip();
            eps.insert(1, Box::new(Garbage { inner: InProcess::new("reference", None), calls: 0, at: 4, nan }));
            let mut pool = MdPool::new(eps).unwrap();
            let pot =
                PotentialSource::from_file(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/potentials/Cu_u3.eam"))).unwrap();
            pool.open(&pot, &specs_of_run()).unwrap();
            let mut out = Vec::new();
            for step in 1..=STEPS {
                out.push(format!("{:?}", pool.step(step, &work_of(step)).unwrap()));
            }
            let states = pool.snapshot(&pool.box_ids()).unwrap();
            assert_eq!((out, serde_json::to_string(&states).unwrap()), straight, "nan = {nan}");
            let rec = pool.recoveries();
            assert_eq!(rec.len(), 1, "{rec:?}");
            assert_eq!((rec[0].worker.as_str(), rec[0].step, rec[0].boxes.clone()), ("garbage-4", 4, vec![2, 3]), "{rec:?}");
            let why = if nan { "returned a non-finite `stress_gpa` for point 2" } else { "answered point 1002 for point 2" };
            assert!(rec[0].why.starts_with("declared faulty") && rec[0].why.contains(why), "{rec:?}");
            assert_eq!(pool.endpoint_load().iter().map(|l| l.boxes).collect::<Vec<_>>(), vec![3, 0, 3]);
        }
    }

    fn flaky(fail_at: u64) -> (Box<dyn Endpoint>, Arc<AtomicU64>) {
        let c = Arc::new(AtomicU64::new(0));
        (Box::new(Flaky { inner: InProcess::new("reference", None), calls: 0, fail_at, gone: false, box_calls: c.clone() }), c)
    }

    const STEPS: u64 = 6;

    /// The 6 boxes of [`run`].
    fn specs_of_run() -> Vec<BoxSpec> {
        (0..6)
            .map(|id| {
                let mut s = BoxSpec::lattice(id, crate::LatticeKind::Fcc, 3.615, [2, 2, 2]);
                s.temperature_k = 50.0 + id as f64;
                s.seed = 7;
                s
            })
            .collect()
    }

    /// The work of call `step` of [`run`].
    fn work_of(step: u64) -> Vec<BoxWork> {
        (0..6)
            .map(|id| {
                let mut w = BoxWork::new(id, [[1e-3 * step as f64, 0.0, 0.0], [0.0, -5e-4, 0.0], [0.0; 3]], 3, 0.001);
                w.energy_to_add_ev = 1e-3 * id as f64;
                w.stress_sampling = if id % 2 == 0 { crate::StressSampling::Average } else { crate::StressSampling::Last };
                w
            })
            .collect()
    }

    /// Runs 6 boxes for 6 calls (a checkpoint after call `checkpoint`, if any) on endpoints
    /// lost at their call `fail_at` (0: never); returns every result and the final states.
    fn run(fail_at: &[u64], checkpoint: Option<u64>) -> (Result<(Vec<String>, String), MdError>, MdPool, Vec<Arc<AtomicU64>>) {
        let (eps, counters): (Vec<_>, Vec<_>) = fail_at.iter().map(|&f| flaky(if f == 0 { u64::MAX } else { f })).unzip();
        let mut pool = MdPool::new(eps).unwrap();
        let pot = PotentialSource::from_file(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/potentials/Cu_u3.eam"))).unwrap();
        pool.open(&pot, &specs_of_run()).unwrap();
        let mut out = Vec::new();
        let r = (|| {
            for step in 1..=STEPS {
                out.push(format!("{:?}", pool.step(step, &work_of(step))?));
                if checkpoint == Some(step) {
                    let saved = pool.snapshot(&pool.box_ids())?;
                    pool.mark_checkpoint(
                        step,
                        Arc::new(move |ids: &[PointId]| Ok(saved.iter().filter(|s| ids.contains(&s.meta.id)).cloned().collect())),
                    );
                }
            }
            let states = pool.snapshot(&pool.box_ids())?;
            Ok((out, serde_json::to_string(&states).unwrap()))
        })();
        (r, pool, counters)
    }

    #[test]
    fn a_lost_endpoint_is_replayed_onto_the_survivors_bit_for_bit() {
        let (straight, _, _) = run(&[0, 0, 0], None);
        let straight = straight.unwrap();
        // Lost at its 5th call, after a checkpoint at call 3: only its boxes (2 and 3) are
        // restored and replay call 4, then redo call 5.
        let (r, pool, counters) = run(&[0, 5, 0], Some(3));
        assert_eq!(r.unwrap(), straight);
        let rec = pool.recoveries();
        assert_eq!(rec.len(), 1, "{rec:?}");
        assert_eq!((rec[0].worker.as_str(), rec[0].step, rec[0].boxes.clone()), ("flaky-5", 5, vec![2, 3]), "{rec:?}");
        assert_eq!((rec[0].replayed_calls, rec[0].replayed_box_steps, rec[0].replayed_md_steps), (1, 2, 6), "{rec:?}");
        assert_eq!(rec[0].baseline, "the checkpoint of step 3");
        // Survivors: their own 2 boxes x 6 calls, and each took one lost box: 1 replayed + 2 calls (5, 6).
        assert_eq!(counters[0].load(Ordering::SeqCst), 2 * STEPS + 3);
        assert_eq!(counters[2].load(Ordering::SeqCst), 2 * STEPS + 3);
        assert_eq!(pool.endpoint_load().iter().map(|l| l.boxes).collect::<Vec<_>>(), vec![3, 0, 3]);

        // No checkpoint yet: the boxes are opened again and every call replayed.
        let (r, pool, _) = run(&[2, 0, 0], None);
        assert_eq!(r.unwrap(), straight);
        let rec = &pool.recoveries()[0];
        assert_eq!((rec.boxes.clone(), rec.replayed_calls, rec.replayed_box_steps), (vec![0, 1], 1, 2), "{rec:?}");
        assert!(rec.baseline.contains("as opened"), "{rec:?}");

        // Two losses, one of them a survivor of the first.
        let (r, pool, _) = run(&[4, 0, 6], Some(2));
        assert_eq!(r.unwrap(), straight);
        assert_eq!(pool.recoveries().len(), 2);
        assert_eq!(pool.endpoint_load().iter().map(|l| l.boxes).collect::<Vec<_>>(), vec![0, 6, 0]);
    }

    #[test]
    fn without_survivors_or_with_an_overflowed_log_the_loss_is_an_error() {
        let (r, _, _) = run(&[3], Some(1));
        let e = r.unwrap_err().to_string();
        assert!(
            e.contains("flaky-3")
                && e.contains("lost during continuum step 3")
                && e.contains("no surviving worker of back end reference/double"),
            "{e}"
        );

        let (eps, _): (Vec<_>, Vec<_>) = [u64::MAX, 2].iter().map(|&f| flaky(f)).unzip();
        let mut pool = MdPool::new(eps).unwrap();
        pool.set_log_limit(10);
        let pot = PotentialSource::from_file(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/potentials/Cu_u3.eam"))).unwrap();
        pool.open(
            &pot,
            &[
                BoxSpec::lattice(0, crate::LatticeKind::Fcc, 3.615, [2, 2, 2]),
                BoxSpec::lattice(1, crate::LatticeKind::Fcc, 3.615, [2, 2, 2]),
            ],
        )
        .unwrap();
        let work = [BoxWork::new(0, [[0.0; 3]; 3], 1, 0.001), BoxWork::new(1, [[0.0; 3]; 3], 1, 0.001)];
        pool.step(1, &work).unwrap();
        let e = pool.step(2, &work).unwrap_err().to_string();
        assert!(e.contains("cannot be replayed") && e.contains("outgrew its bound"), "{e}");
    }

    /// 6 boxes, ids 0-3 bitwise alike (0 K, the same strain), 4-5 alike among themselves, for
    /// 6 calls whose work splits, regroups, leaves boxes out (as the tolerance mode does, then
    /// catches them up with a longer call) and adds energy; with or without reuse, on endpoints
    /// lost at their call `fail_at` (0: never), a checkpoint after call `checkpoint`.
    fn run_shared(reuse: bool, fail_at: &[u64], checkpoint: Option<u64>) -> (Vec<String>, String, MdPool) {
        let (eps, _): (Vec<_>, Vec<_>) = fail_at.iter().map(|&f| flaky(if f == 0 { u64::MAX } else { f })).unzip();
        let mut pool = MdPool::new(eps).unwrap();
        let pot = PotentialSource::from_file(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/potentials/Cu_u3.eam"))).unwrap();
        let specs: Vec<BoxSpec> = (0..6)
            .map(|id| {
                let mut s = BoxSpec::lattice(id, crate::LatticeKind::Fcc, 3.615, [2, 2, 2]);
                s.strain = if id < 4 { [-0.02, 0.0, 0.0] } else { [0.01, 0.0, 0.0] };
                s.seed = 7;
                s
            })
            .collect();
        pool.open(&pot, &specs).unwrap();
        if reuse {
            pool.enable_reuse(&pool.box_ids()).unwrap();
            assert_eq!(pool.reuse_classes(), 2);
        }
        let mut out = Vec::new();
        for step in 1..=STEPS {
            let l = |a: f64| [[a, 0.0, 0.0], [0.0; 3], [0.0; 3]];
            let mut work: Vec<BoxWork> = (0..6).map(|id| BoxWork::new(id, l(1e-3), 3, 0.001)).collect();
            match step {
                // Ids 2 and 3 split off; 4 and 5 too.
                2 => {
                    work[2].velocity_gradient = l(-1e-3);
                    work[3].velocity_gradient = l(-1e-3);
                    work[5].velocity_gradient = l(2e-3);
                }
                // Id 1 and id 3 left out (skipped); the others as they were.
                3 => {
                    work.retain(|w| w.id != 1 && w.id != 3);
                }
                // Id 1 catches up (two calls' steps); id 0 gets energy (never shared).
                4 => {
                    work[1].steps = 6;
                    work[0].energy_to_add_ev = 1e-3;
                }
                _ => {}
            }
            let res = pool.step(step, &work).unwrap();
            out.push(format!("{res:?}"));
            if checkpoint == Some(step) {
                let saved = pool.snapshot(&pool.box_ids()).unwrap();
                pool.mark_checkpoint(
                    step,
                    Arc::new(move |ids: &[PointId]| Ok(saved.iter().filter(|s| ids.contains(&s.meta.id)).cloned().collect())),
                );
            }
        }
        let states = pool.snapshot(&pool.box_ids()).unwrap();
        (out, serde_json::to_string(&states).unwrap(), pool)
    }

    #[test]
    fn exact_reuse_is_bitwise_stepping_every_box_and_replays_the_same() {
        let (plain, plain_states, plain_pool) = run_shared(false, &[0], None);
        let (shared, shared_states, pool) = run_shared(true, &[0], None);
        assert_eq!(shared, plain);
        assert_eq!(shared_states, plain_states);
        let done = |p: &MdPool| (0..6).map(|id| p.md_steps_done(id)).sum::<u64>();
        // Plain: 6 boxes x 6 calls x 3 steps, less 2 left out at call 3, plus id 1's 3 more at 4.
        assert_eq!(done(&plain_pool), 6 * 6 * 3 - 2 * 3 + 3);
        // Shared: call 1 steps 2 boxes (two classes), calls 2-3 four (0-1, 2-3, 4, 5; the
        // left-out ids take their representative's state), call 4 all six (id 0's energy, id 1's
        // catch-up, and ids 2 and 3 no longer one class), as do 5 and 6 (classes do not merge
        // again): 3 x (2 + 4 + 4 + 5 + 6 + 6) + 6.
        assert_eq!(done(&pool), 3 * (2 + 4 + 4 + 5 + 6 + 6) + 6);
        // Endpoints lost mid-run (no checkpoint, and after one) rebuild their boxes to the bits.
        for (fail, ck) in [(vec![0, 3, 0], None), (vec![5, 0], Some(2)), (vec![0, 0, 4], Some(3))] {
            let (r, states, pool) = run_shared(true, &fail, ck);
            assert_eq!(r, plain, "{fail:?} {ck:?}");
            assert_eq!(states, plain_states, "{fail:?} {ck:?}");
            assert_eq!(pool.recoveries().len(), 1);
        }
        // A restore (a resumed run) keeps every box's state, shared or not.
        let (_, _, mut pool) = run_shared(true, &[0, 0], None);
        let states = pool.snapshot(&pool.box_ids()).unwrap();
        pool.restore(states.clone()).unwrap();
        assert_eq!(pool.snapshot(&pool.box_ids()).unwrap(), states);
        pool.restore(states[..2].to_vec()).unwrap();
        assert_eq!(pool.snapshot(&pool.box_ids()).unwrap(), states);
    }

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
