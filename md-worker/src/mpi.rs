//! MPI inside one worker (cargo feature `mpi`): under `mpirun -np N md-worker serve ...`, rank 0
//! serves gRPC as usual and spreads each session's boxes over the N ranks; the other ranks run
//! [`serve_rank`], a loop that executes rank 0's commands until it says shut down.
//!
//! - Rank 0's back end for a session is an [`MpiBackend`]. It gives every new box an owning rank
//!   ([`partition`]: contiguous, nearly equal blocks of the point ids of one open or restore call,
//!   deterministic), forwards open/step/snapshot/restore to the owners, computes its own share at
//!   the same time, and gathers the results back in the order of the request. Closing the
//!   session (dropping the back end) closes it on every rank.
//! - Every rank holds its boxes in the normal `cpu` back end, resident between calls. Since
//!   every box is computed independently by the same serial per-box kernels, results are bitwise
//!   those of one rank, whatever the number of ranks or threads.
//! - Commands and replies are the engine's own serde types ([`BoxSpec`], [`BoxWork`],
//!   [`BoxResult`], [`BoxState`]) forwarded whole, encoded with bincode (exact, NaN included),
//!   sent as byte messages in chunks of at most [`CHUNK`] bytes. Rank-side state is keyed by a
//!   session id of rank 0's choosing; a potential's bytes travel once per rank and are parsed
//!   once per rank.
//! - All MPI calls on rank 0 are made under one lock (MPI_THREAD_SERIALIZED): gRPC calls run on
//!   several threads, and one call's commands and replies are never interleaved with another's.
//! - Waiting ranks poll (`MPI_Improbe`) with a short sleep, so an idle or waiting rank does not
//!   spin a core that the computing ranks could use.

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
use crate::kernel::DeformMode;
use crate::potential::Potential;
use crate::source::PotentialSource;
use mpi::traits::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeSet, HashMap, HashSet};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

/// Largest MPI message (bytes); longer payloads go in several messages.
pub const CHUNK: usize = 1 << 30;
/// Rank 0 to the others.
const TAG_COMMAND: i32 = 11;
/// The others to rank 0.
const TAG_REPLY: i32 = 12;

/// The owning rank of each id of one open or restore call, in the order of `ids`: the ids,
/// sorted, cut into `ranks` contiguous blocks whose sizes differ by at most one (the first
/// blocks are the larger ones). Depends only on the set of ids, not on their order.
pub fn partition(ids: &[PointId], ranks: usize) -> Vec<usize> {
    let ranks = ranks.max(1);
    let mut order: Vec<usize> = (0..ids.len()).collect();
    order.sort_by_key(|&k| ids[k]);
    let n = ids.len();
    // `extra` blocks of base + 1 ids, then blocks of base ids.
    let (base, extra) = (n / ranks, n % ranks);
    let mut out = vec![0; n];
    for (j, &k) in order.iter().enumerate() {
        out[k] = if j < extra * (base + 1) { j / (base + 1) } else { extra + (j - extra * (base + 1)) / base.max(1) };
    }
    out
}

/// A command from rank 0.
#[derive(Debug, Serialize, Deserialize)]
enum Command {
    /// A new session on the potential named by its SHA-256; its bytes come along the first time
    /// the ranks see it.
    Begin {
        session: u64,
        potential_name: String,
        potential_sha256: String,
        potential: Option<Vec<u8>>,
    },
    Open {
        session: u64,
        specs: Vec<BoxSpec>,
    },
    Step {
        session: u64,
        work: Vec<BoxWork>,
    },
    Snapshot {
        session: u64,
        ids: Vec<PointId>,
    },
    Restore {
        session: u64,
        states: Vec<BoxState>,
    },
    /// No reply.
    Close {
        session: u64,
    },
    /// No reply: leave the loop.
    Shutdown,
}

impl Command {
    fn wants_reply(&self) -> bool {
        !matches!(self, Command::Close { .. } | Command::Shutdown)
    }
}

/// A rank's answer to a command.
#[derive(Debug, Serialize, Deserialize)]
enum Reply {
    Done,
    Results(Vec<BoxResult>),
    States(Vec<BoxState>),
    Failed(RemoteError),
}

/// An [`MdError`] as it travels between ranks (the kinds that map to distinct gRPC codes keep
/// their kind).
#[derive(Debug, Serialize, Deserialize)]
enum RemoteError {
    Invalid {
        what: String,
        msg: String,
    },
    Parse {
        file: String,
        line: usize,
        msg: String,
    },
    Unsupported(String),
    UnknownBox(u64),
    Other(String),
    /// A box whose MD diverged on its rank: stays a diverged box (not a failed rank).
    Diverged {
        point: u64,
        msg: String,
    },
}

impl From<MdError> for RemoteError {
    fn from(e: MdError) -> Self {
        match e {
            MdError::Invalid { what, msg } => RemoteError::Invalid { what, msg },
            MdError::Parse { file, line, msg } => RemoteError::Parse { file, line, msg },
            MdError::Unsupported(m) => RemoteError::Unsupported(m),
            MdError::UnknownBox(id) => RemoteError::UnknownBox(id),
            MdError::Diverged { point, msg } => RemoteError::Diverged { point, msg },
            other => RemoteError::Other(other.to_string()),
        }
    }
}

impl RemoteError {
    fn into_md(self, rank: usize) -> MdError {
        match self {
            RemoteError::Invalid { what, msg } => MdError::Invalid { what, msg },
            RemoteError::Parse { file, line, msg } => MdError::Parse { file, line, msg },
            RemoteError::Unsupported(m) => MdError::Unsupported(m),
            RemoteError::UnknownBox(id) => MdError::UnknownBox(id),
            RemoteError::Other(msg) => rank_error(rank, msg),
            RemoteError::Diverged { point, msg } => MdError::Diverged { point, msg },
        }
    }
}

fn rank_error(rank: usize, msg: impl Into<String>) -> MdError {
    MdError::Worker { worker: format!("mpi rank {rank}"), msg: msg.into() }
}

/// The encoding of everything ranks exchange (bincode: exact, NaN and signed zeros included).
pub fn encode<T: Serialize>(v: &T) -> Vec<u8> {
    // Serialising plain data into memory cannot fail (no I/O, no unsized sequences); an error
    // here is a bug.
    bincode::serialize(v).unwrap_or_else(|e| panic!("mpi: cannot encode a message: {e}"))
}

/// Decodes what [`encode`] made; an error names the rank the bytes came from.
pub fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8], rank: usize) -> Result<T, MdError> {
    bincode::deserialize(bytes).map_err(|e| rank_error(rank, format!("undecodable message ({} bytes): {e}", bytes.len())))
}

/// Sends `bytes` to `rank`: a first message with the total length (8 bytes, little endian) and
/// up to [`CHUNK`] bytes, then further chunks.
fn send_bytes(world: &mpi::topology::SimpleCommunicator, rank: usize, tag: i32, bytes: &[u8]) {
    let dest = world.process_at_rank(rank as i32);
    let first = bytes.len().min(CHUNK);
    let mut head = Vec::with_capacity(8 + first);
    head.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
    head.extend_from_slice(&bytes[..first]);
    dest.send_with_tag(&head[..], tag);
    for c in bytes[first..].chunks(CHUNK) {
        dest.send_with_tag(c, tag);
    }
}

/// Receives what [`send_bytes`] sent from `rank`, polling for the first message with a short
/// sleep between polls (an MPI blocking receive would spin a core).
fn receive_bytes(world: &mpi::topology::SimpleCommunicator, rank: usize, tag: i32) -> Result<Vec<u8>, MdError> {
    let src = world.process_at_rank(rank as i32);
    let mut pause = Duration::from_micros(20);
    let mut polls = 0u32;
    let first = loop {
        if let Some(m) = src.immediate_matched_probe_with_tag(tag) {
            break m.matched_receive_vec::<u8>().0;
        }
        polls += 1;
        if polls < 200 {
            std::thread::yield_now();
        } else {
            std::thread::sleep(pause);
            pause = (pause * 2).min(Duration::from_millis(1));
        }
    };
    if first.len() < 8 {
        return Err(rank_error(rank, format!("message of {} bytes has no length header", first.len())));
    }
    let total = u64::from_le_bytes(first[..8].try_into().unwrap_or([0; 8])) as usize;
    let mut bytes = first[8..].to_vec();
    while bytes.len() < total {
        let (c, _) = src.matched_probe_with_tag(tag).matched_receive_vec::<u8>();
        if c.is_empty() {
            return Err(rank_error(rank, "empty chunk"));
        }
        bytes.extend_from_slice(&c);
    }
    if bytes.len() != total {
        return Err(rank_error(rank, format!("message of {} bytes, header says {total}", bytes.len())));
    }
    Ok(bytes)
}

/// The replies of the ranks to one exchange, in rank order.
type Replies = Vec<(usize, Result<Reply, MdError>)>;

/// Rank 0's side of the communication, behind the one lock that serialises its MPI calls.
struct Hub {
    size: usize,
    /// SHA-256 of the potentials whose bytes the ranks have.
    shipped: HashSet<String>,
    next_session: u64,
    /// Shut down: no more commands.
    down: bool,
}

static HUB: Mutex<Option<Hub>> = Mutex::new(None);
/// Sessions dropped while the hub was busy: closed on the ranks by the next user of the hub
/// (a drop never waits for another session's step).
static PENDING_CLOSE: Mutex<Vec<u64>> = Mutex::new(Vec::new());

/// The hub, locked, with the pending closes sent.
fn hub() -> MutexGuard<'static, Option<Hub>> {
    let mut guard = HUB.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(h) = guard.as_mut() {
        h.flush_closes();
    }
    guard
}

impl Hub {
    fn world() -> mpi::topology::SimpleCommunicator {
        mpi::topology::SimpleCommunicator::world()
    }

    /// Sends each rank its command (ranks > 0), runs `local` meanwhile, then gathers the
    /// replies of the ranks that were sent a command expecting one, in rank order. Every reply
    /// is received even when something failed, so the next call starts clean.
    fn exchange<T>(
        &mut self,
        commands: Vec<(usize, Command)>,
        local: impl FnOnce() -> Result<T, MdError>,
    ) -> (Result<T, MdError>, Replies) {
        let world = Self::world();
        let mut waiting = Vec::new();
        for (rank, cmd) in commands {
            debug_assert!(rank > 0 && rank < self.size);
            send_bytes(&world, rank, TAG_COMMAND, &encode(&cmd));
            if cmd.wants_reply() {
                waiting.push(rank);
            }
        }
        // A panic in rank 0's share must not skip the replies below (the ranks would fall out
        // of step): it becomes this call's error.
        let mine = std::panic::catch_unwind(std::panic::AssertUnwindSafe(local)).unwrap_or_else(|p| {
            let what = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string())).unwrap_or_default();
            Err(rank_error(0, format!("panicked: {what}")))
        });
        let replies = waiting
            .into_iter()
            .map(|rank| {
                let r = receive_bytes(&world, rank, TAG_REPLY).and_then(|b| decode::<Reply>(&b, rank)).and_then(|r| match r {
                    Reply::Failed(e) => Err(e.into_md(rank)),
                    ok => Ok(ok),
                });
                (rank, r)
            })
            .collect();
        (mine, replies)
    }

    fn flush_closes(&mut self) {
        let pending = std::mem::take(&mut *PENDING_CLOSE.lock().unwrap_or_else(|p| p.into_inner()));
        if !self.down {
            for session in pending {
                self.tell_all(|| Command::Close { session });
            }
        }
    }

    fn tell_all(&mut self, cmd: impl Fn() -> Command) {
        let world = Self::world();
        for rank in 1..self.size {
            send_bytes(&world, rank, TAG_COMMAND, &encode(&cmd()));
        }
    }
}

/// This process's place in the MPI job. Holds MPI initialised; on rank 0, dropping it tells the
/// other ranks to leave [`serve_rank`] before MPI is finalised.
pub struct MpiWorld {
    universe: Option<mpi::environment::Universe>,
    rank: usize,
    size: usize,
    local_size: usize,
}

/// Initialises MPI (once per process) with MPI_THREAD_SERIALIZED.
pub fn init() -> Result<MpiWorld, MdError> {
    let mpi_err = |msg: String| MdError::Worker { worker: "mpi".into(), msg };
    let (universe, level) =
        mpi::initialize_with_threading(mpi::Threading::Serialized).ok_or_else(|| mpi_err("MPI is already initialised".into()))?;
    if matches!(level, mpi::Threading::Single | mpi::Threading::Funneled) {
        return Err(mpi_err(format!("the MPI library offers only {level:?} threading; serving needs MPI_THREAD_SERIALIZED")));
    }
    let world = universe.world();
    let (rank, size) = (world.rank() as usize, world.size() as usize);
    let local_size = world.split_shared(rank as i32).size().max(1) as usize;
    if rank == 0 && size > 1 {
        *hub() = Some(Hub { size, shipped: HashSet::new(), next_session: 1, down: false });
    }
    Ok(MpiWorld { universe: Some(universe), rank, size, local_size })
}

impl MpiWorld {
    /// This process's rank in MPI_COMM_WORLD.
    pub fn rank(&self) -> usize {
        self.rank
    }
    /// Number of ranks.
    pub fn size(&self) -> usize {
        self.size
    }
    /// Ranks on this node (MPI_COMM_TYPE_SHARED), at least 1.
    pub fn ranks_on_this_node(&self) -> usize {
        self.local_size
    }
}

impl Drop for MpiWorld {
    fn drop(&mut self) {
        if self.rank == 0 && self.size > 1 {
            let mut guard = hub();
            if let Some(h) = guard.as_mut().filter(|h| !h.down) {
                h.tell_all(|| Command::Shutdown);
                h.down = true;
            }
        }
        drop(self.universe.take());
    }
}

/// Rank 0's back end for one session: boxes spread over the ranks (see the module docs).
pub struct MpiBackend {
    session: u64,
    size: usize,
    pot: Arc<Potential>,
    /// Rank 0's own boxes.
    local: Box<dyn MdBackend>,
    /// Owning rank and deformation mode of every box.
    owner: HashMap<PointId, (usize, DeformMode)>,
}

/// Every rank's own boxes: the `cpu` back end, as the registry builds it (`device::build`).
fn cpu_backend(pot: Arc<Potential>, threads: Option<Arc<rayon::ThreadPool>>) -> Box<dyn MdBackend> {
    Box::new(crate::CpuBackend::on(pot, threads))
}

/// Runs `f` on rank 0's hub, under its lock.
fn with_hub<T>(f: impl FnOnce(&mut Hub) -> Result<T, MdError>) -> Result<T, MdError> {
    let mut guard = hub();
    let h = guard.as_mut().filter(|h| !h.down).ok_or_else(|| rank_error(0, "the MPI job is shutting down"))?;
    f(h)
}

/// The ranks (0 included) whose part of an open or restore succeeded, and the first error.
fn done_ranks(
    mine: Result<(), MdError>,
    replies: impl IntoIterator<Item = (usize, Result<Reply, MdError>)>,
) -> (HashSet<usize>, Option<MdError>) {
    let mut ok_ranks = HashSet::new();
    let mut first_err = None;
    match mine {
        Ok(()) => {
            ok_ranks.insert(0);
        }
        Err(e) => first_err = Some(e),
    }
    for (rank, r) in replies {
        match expect_done(rank, r) {
            Ok(()) => {
                ok_ranks.insert(rank);
            }
            Err(e) => {
                first_err.get_or_insert(e);
            }
        }
    }
    (ok_ranks, first_err)
}

fn expect_done(rank: usize, r: Result<Reply, MdError>) -> Result<(), MdError> {
    match r? {
        Reply::Done => Ok(()),
        other => Err(rank_error(rank, format!("unexpected reply {:?}", std::mem::discriminant(&other)))),
    }
}

impl MpiBackend {
    /// A session on rank 0 of a job of more than one rank: opens it on every rank (the
    /// potential's bytes travel the first time). `pot` is `source` parsed; rank 0's own boxes
    /// run on `threads` (rayon's global pool if `None`).
    pub fn new(source: &PotentialSource, pot: Arc<Potential>, threads: Option<Arc<rayon::ThreadPool>>) -> Result<Self, MdError> {
        let mut guard = hub();
        let h = guard
            .as_mut()
            .filter(|h| !h.down)
            .ok_or_else(|| MdError::invalid("back end", "mpi: not rank 0 of a running MPI job of more than one rank"))?;
        let session = h.next_session;
        h.next_session += 1;
        let ship = !h.shipped.contains(&source.sha256);
        let commands = (1..h.size)
            .map(|rank| {
                let cmd = Command::Begin {
                    session,
                    potential_name: source.name.clone(),
                    potential_sha256: source.sha256.clone(),
                    potential: ship.then(|| source.bytes.as_ref().clone()),
                };
                (rank, cmd)
            })
            .collect();
        let (_, replies) = h.exchange(commands, || Ok(()));
        let mut first_err = None;
        for (rank, r) in replies {
            if let Err(e) = expect_done(rank, r) {
                first_err.get_or_insert(e);
            }
        }
        if let Some(e) = first_err {
            h.tell_all(|| Command::Close { session });
            return Err(e);
        }
        h.shipped.insert(source.sha256.clone());
        let size = h.size;
        drop(guard);
        Ok(MpiBackend { session, size, local: cpu_backend(pot.clone(), threads), pot, owner: HashMap::new() })
    }

    /// The session id on the ranks.
    pub fn session(&self) -> u64 {
        self.session
    }

    /// Owning rank of a box.
    pub fn owner(&self, id: PointId) -> Option<usize> {
        self.owner.get(&id).map(|o| o.0)
    }

    /// Splits `items` by owning rank: per rank, the items and their positions in `items`.
    fn split<T>(&self, items: Vec<T>, mut rank_of: impl FnMut(&T) -> usize) -> (Vec<Vec<T>>, Vec<Vec<usize>>) {
        let mut parts: Vec<Vec<T>> = (0..self.size).map(|_| Vec::new()).collect();
        let mut slots: Vec<Vec<usize>> = vec![Vec::new(); self.size];
        for (k, it) in items.into_iter().enumerate() {
            let r = rank_of(&it);
            parts[r].push(it);
            slots[r].push(k);
        }
        (parts, slots)
    }
}

impl Drop for MpiBackend {
    fn drop(&mut self) {
        PENDING_CLOSE.lock().unwrap_or_else(|p| p.into_inner()).push(self.session);
        // Close now if the hub is free; otherwise its current user does.
        if let Ok(mut guard) = HUB.try_lock()
            && let Some(h) = guard.as_mut()
        {
            h.flush_closes();
        }
    }
}

impl MdBackend for MpiBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
        // The checks of the cpu back end, here for all ranks at once, so a refused call opens
        // nothing anywhere (as on one rank).
        let mut seen = BTreeSet::new();
        for s in specs {
            if !seen.insert(s.id) || self.owner.contains_key(&s.id) {
                return Err(MdError::invalid("box spec", format!("point id {} given twice", s.id)));
            }
            crate::backend::validate_spec(&self.pot, s)?;
        }
        let ids: Vec<PointId> = specs.iter().map(|s| s.id).collect();
        let ranks = partition(&ids, self.size);
        let mut k = 0;
        let (mut parts, _) = self.split(specs.to_vec(), |_| {
            k += 1;
            ranks[k - 1]
        });
        let session = self.session;
        let mine = std::mem::take(&mut parts[0]);
        let commands: Vec<(usize, Command)> = parts
            .iter_mut()
            .enumerate()
            .skip(1)
            .filter(|(_, p)| !p.is_empty())
            .map(|(r, p)| (r, Command::Open { session, specs: std::mem::take(p) }))
            .collect();
        let local = &mut self.local;
        let (mine_result, replies) = with_hub(|h| Ok(h.exchange(commands, || if mine.is_empty() { Ok(()) } else { local.open(&mine) })))?;
        let (ok_ranks, first_err) = done_ranks(mine_result, replies);
        for (s, r) in specs.iter().zip(ranks) {
            if ok_ranks.contains(&r) {
                self.owner.insert(s.id, (r, s.mode));
            }
        }
        first_err.map_or(Ok(()), Err)
    }

    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        if work.len() != out.len() {
            return Err(MdError::invalid("step", format!("{} work items but {} result slots", work.len(), out.len())));
        }
        // All checks before any box moves, as on one rank.
        let mut seen = BTreeSet::new();
        for w in work {
            let (_, mode) = *self.owner.get(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            if !seen.insert(w.id) {
                return Err(MdError::invalid("box work", format!("point id {} appears twice in one step", w.id)));
            }
            crate::backend::validate_work(&self.pot, w, mode)?;
        }
        let owner = &self.owner;
        let (mut parts, slots) = self.split(work.to_vec(), |w| owner.get(&w.id).map_or(0, |o| o.0));
        let session = self.session;
        let mine = std::mem::take(&mut parts[0]);
        let commands: Vec<(usize, Command)> = parts
            .iter_mut()
            .enumerate()
            .skip(1)
            .filter(|(_, p)| !p.is_empty())
            .map(|(r, p)| (r, Command::Step { session, work: std::mem::take(p) }))
            .collect();
        let local = &mut self.local;
        let (mine_result, replies) = with_hub(|h| {
            Ok(h.exchange(commands, || {
                let mut o = vec![BoxResult::default(); mine.len()];
                if !mine.is_empty() {
                    local.step(&mine, &mut o)?;
                }
                Ok(o)
            }))
        })?;
        let mut first_err = None;
        match mine_result {
            Ok(res) => place(&slots[0], res, out, 0, work, &mut first_err),
            Err(e) => first_err = Some(e),
        }
        for (rank, r) in replies {
            match r {
                Ok(Reply::Results(res)) => place(&slots[rank], res, out, rank, work, &mut first_err),
                Ok(_) => {
                    first_err.get_or_insert(rank_error(rank, "unexpected reply to a step"));
                }
                Err(e) => {
                    first_err.get_or_insert(e);
                }
            }
        }
        first_err.map_or(Ok(()), Err)
    }

    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        for id in ids {
            if !self.owner.contains_key(id) {
                return Err(MdError::UnknownBox(*id));
            }
        }
        let owner = &self.owner;
        let (mut parts, slots) = self.split(ids.to_vec(), |id| owner.get(id).map_or(0, |o| o.0));
        let session = self.session;
        let mine = std::mem::take(&mut parts[0]);
        let commands: Vec<(usize, Command)> = parts
            .iter_mut()
            .enumerate()
            .skip(1)
            .filter(|(_, p)| !p.is_empty())
            .map(|(r, p)| (r, Command::Snapshot { session, ids: std::mem::take(p) }))
            .collect();
        let local = &self.local;
        let (mine_result, replies) =
            with_hub(|h| Ok(h.exchange(commands, || if mine.is_empty() { Ok(Vec::new()) } else { local.snapshot(&mine) })))?;
        let mut out: Vec<Option<BoxState>> = (0..ids.len()).map(|_| None).collect();
        let mut first_err = None;
        let mut put = |rank: usize, states: Vec<BoxState>, first_err: &mut Option<MdError>| {
            if states.len() != slots[rank].len() {
                first_err.get_or_insert(rank_error(rank, format!("{} states for {} boxes", states.len(), slots[rank].len())));
                return;
            }
            for (k, s) in slots[rank].iter().zip(states) {
                out[*k] = Some(s);
            }
        };
        match mine_result {
            Ok(s) => put(0, s, &mut first_err),
            Err(e) => first_err = Some(e),
        }
        for (rank, r) in replies {
            match r {
                Ok(Reply::States(s)) => put(rank, s, &mut first_err),
                Ok(_) => {
                    first_err.get_or_insert(rank_error(rank, "unexpected reply to a snapshot"));
                }
                Err(e) => {
                    first_err.get_or_insert(e);
                }
            }
        }
        if let Some(e) = first_err {
            return Err(e);
        }
        out.into_iter().zip(ids).map(|(s, id)| s.ok_or(MdError::UnknownBox(*id))).collect()
    }

    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        // Boxes this session holds go back to their rank; new ones are spread like an open.
        let new_ids: Vec<PointId> = {
            let mut seen = BTreeSet::new();
            states.iter().map(|s| s.meta.id).filter(|id| !self.owner.contains_key(id) && seen.insert(*id)).collect()
        };
        let new_ranks: HashMap<PointId, usize> = new_ids.iter().copied().zip(partition(&new_ids, self.size)).collect();
        let rank_of = |id: PointId| self.owner.get(&id).map(|o| o.0).or_else(|| new_ranks.get(&id).copied()).unwrap_or(0);
        let assigned: Vec<(PointId, usize, DeformMode)> = states.iter().map(|s| (s.meta.id, rank_of(s.meta.id), s.meta.mode)).collect();
        let (mut parts, _) = self.split(states, |s| rank_of(s.meta.id));
        let session = self.session;
        let mine = std::mem::take(&mut parts[0]);
        let commands: Vec<(usize, Command)> = parts
            .iter_mut()
            .enumerate()
            .skip(1)
            .filter(|(_, p)| !p.is_empty())
            .map(|(r, p)| (r, Command::Restore { session, states: std::mem::take(p) }))
            .collect();
        let local = &mut self.local;
        let (mine_result, replies) = with_hub(|h| Ok(h.exchange(commands, || if mine.is_empty() { Ok(()) } else { local.restore(mine) })))?;
        let (ok_ranks, first_err) = done_ranks(mine_result, replies);
        for (id, rank, mode) in assigned {
            if ok_ranks.contains(&rank) {
                self.owner.insert(id, (rank, mode));
            }
        }
        first_err.map_or(Ok(()), Err)
    }

    fn name(&self) -> &'static str {
        "mpi"
    }
}

/// Puts one rank's results into their slots of `out`, checking count and ids.
fn place(slots: &[usize], res: Vec<BoxResult>, out: &mut [BoxResult], rank: usize, work: &[BoxWork], first_err: &mut Option<MdError>) {
    if res.len() != slots.len() {
        first_err.get_or_insert(rank_error(rank, format!("{} results for {} boxes", res.len(), slots.len())));
        return;
    }
    for (k, r) in slots.iter().zip(res) {
        if r.id != work[*k].id {
            first_err.get_or_insert(rank_error(rank, format!("answered point {} for point {}", r.id, work[*k].id)));
            return;
        }
        out[*k] = r;
    }
}

/// The loop of a rank other than 0: runs rank 0's commands on this rank's boxes until told to
/// shut down. Boxes run on `threads` (rayon's global pool if `None`).
pub fn serve_rank(world: &MpiWorld, threads: Option<Arc<rayon::ThreadPool>>) -> Result<(), MdError> {
    let me = world.rank;
    let comm = mpi::topology::SimpleCommunicator::world();
    let mut potentials: HashMap<String, Arc<Potential>> = HashMap::new();
    let mut sessions: HashMap<u64, Box<dyn MdBackend>> = HashMap::new();
    loop {
        let bytes = receive_bytes(&comm, 0, TAG_COMMAND)?;
        let cmd: Command = match decode(&bytes, 0) {
            Ok(c) => c,
            Err(e) => {
                // Without the command we cannot tell whether rank 0 waits for a reply: the two
                // sides would fall out of step. Stop the job.
                eprintln!("md-worker: mpi rank {me}: {e}; aborting the MPI job");
                comm.abort(3);
            }
        };
        let wants_reply = cmd.wants_reply();
        let reply: Result<Reply, MdError> = match cmd {
            Command::Shutdown => return Ok(()),
            Command::Close { session } => {
                sessions.remove(&session);
                continue;
            }
            Command::Begin { session, potential_name, potential_sha256, potential } => (|| {
                if let Some(bytes) = potential {
                    let src = PotentialSource::from_bytes(potential_name.clone(), bytes);
                    if src.sha256 != potential_sha256 {
                        return Err(rank_error(
                            me,
                            format!("potential {potential_name}: bytes hash to {}, not {potential_sha256}", src.sha256),
                        ));
                    }
                    potentials.insert(potential_sha256.clone(), Arc::new(src.parse()?));
                }
                let pot = potentials
                    .get(&potential_sha256)
                    .cloned()
                    .ok_or_else(|| rank_error(me, format!("potential {potential_name} ({potential_sha256}) never arrived")))?;
                sessions.insert(session, cpu_backend(pot, threads.clone()));
                Ok(Reply::Done)
            })(),
            Command::Open { session, specs } => match sessions.get_mut(&session) {
                Some(b) => b.open(&specs).map(|()| Reply::Done),
                None => Err(rank_error(me, format!("no session {session} on this rank"))),
            },
            Command::Step { session, work } => match sessions.get_mut(&session) {
                Some(b) => {
                    let mut out = vec![BoxResult::default(); work.len()];
                    b.step(&work, &mut out).map(|()| Reply::Results(out))
                }
                None => Err(rank_error(me, format!("no session {session} on this rank"))),
            },
            Command::Snapshot { session, ids } => match sessions.get(&session) {
                Some(b) => b.snapshot(&ids).map(Reply::States),
                None => Err(rank_error(me, format!("no session {session} on this rank"))),
            },
            Command::Restore { session, states } => match sessions.get_mut(&session) {
                Some(b) => b.restore(states).map(|()| Reply::Done),
                None => Err(rank_error(me, format!("no session {session} on this rank"))),
            },
        };
        if wants_reply {
            let reply = reply.unwrap_or_else(|e| Reply::Failed(e.into()));
            send_bytes(&comm, 0, TAG_REPLY, &encode(&reply));
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_diverged_box_on_another_rank_stays_a_diverged_box_naming_its_point() {
        let e = RemoteError::from(MdError::Diverged { point: 3, msg: "at step 1: atom 0 (index from 0) has a kinetic energy".into() });
        let back: RemoteError = bincode::deserialize(&bincode::serialize(&e).unwrap()).unwrap();
        let e = back.into_md(1);
        assert!(matches!(e, MdError::Diverged { point: 3, .. }), "{e}");
        assert!(e.to_string().starts_with("point 3: MD diverged: at step 1"), "{e}");
    }
}
