//! The continuum over MPI ranks (cargo feature `mpi`): [`init`] starts MPI and sets the
//! process's tile exchange over the ranks of `MPI_COMM_WORLD` ([`par::set_exchange`]). With
//! it, every explicit scatter ([`crate::par::Scatter::run_tiled`]) is summed tile by tile on the
//! tiles' owners and the buffers all-gathered (stage 1 of issue 14), and the explicit step's
//! per-point work is split the same way, the updated points all-gathered in tile order and
//! failures agreed over the ranks (stage 2, `solver/ranks.rs`). The point state stays
//! replicated, so every rank ends each step with the single-process bits (README "MPI").

use crate::par::{self, ExchangeStats, TileExchange};
use mpi::traits::*;

/// `MPI_COMM_WORLD`, used from one thread at a time (the solver's; MPI is initialised at
/// `MPI_THREAD_SERIALIZED` or above).
struct World {
    comm: mpi::topology::SimpleCommunicator,
    rank: usize,
    size: usize,
    stats: std::sync::Mutex<ExchangeStats>,
}

// SAFETY: the communicator is a handle MPI lets any thread use once MPI runs at
// MPI_THREAD_SERIALIZED or above ([`init`] refuses less); the collectives of a scatter are
// called by the one thread stepping the simulation, never concurrently.
unsafe impl Send for World {}
// SAFETY: as above.
unsafe impl Sync for World {}

impl TileExchange for World {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.size
    }

    fn all_gather(&self, mine: &[f64]) -> Vec<Vec<f64>> {
        self.gather_varcount(mine, 0.0)
    }

    fn all_gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>> {
        // One leading byte per rank: an empty byte slice's pointer is the dangling 0x1, which
        // Open MPI reads as MPI_IN_PLACE (MPI_ERR_ARG).
        let mut sent = Vec::with_capacity(mine.len() + 1);
        sent.push(0u8);
        sent.extend_from_slice(mine);
        self.gather_varcount(&sent, 0u8).into_iter().map(|mut b| b.split_off(1)).collect()
    }

    fn stats(&self) -> ExchangeStats {
        *self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl World {
    /// `MPI_Allgatherv` of every rank's `mine` (the counts first), counted in [`ExchangeStats`].
    fn gather_varcount<T: Equivalence + Copy>(&self, mine: &[T], zero: T) -> Vec<Vec<T>> {
        let start = std::time::Instant::now();
        let n = i32::try_from(mine.len()).expect("a rank's exchange buffer exceeds 2^31 values");
        let mut counts = vec![0i32; self.size];
        self.comm.all_gather_into(&n, &mut counts[..]);
        let displs: Vec<i32> = counts.iter().scan(0i32, |acc, &c| Some(std::mem::replace(acc, *acc + c))).collect();
        let total: usize = counts.iter().map(|&c| c as usize).sum();
        let mut all = vec![zero; total];
        {
            let mut part = mpi::datatype::PartitionMut::new(&mut all[..], &counts[..], &displs[..]);
            self.comm.all_gather_varcount_into(mine, &mut part);
        }
        let size = std::mem::size_of::<T>() as u64;
        let mut st = self.stats.lock().unwrap_or_else(|e| e.into_inner());
        st.calls += 1;
        st.bytes_sent += mine.len() as u64 * size;
        st.bytes_received += (total - mine.len()) as u64 * size;
        st.seconds += start.elapsed().as_secs_f64();
        drop(st);
        counts.iter().zip(&displs).map(|(&c, &d)| all[d as usize..(d + c) as usize].to_vec()).collect()
    }
}

/// MPI while it lives (finalised on drop): this process's rank and the number of ranks.
pub struct Mpi {
    _universe: mpi::environment::Universe,
    /// This process's rank.
    pub rank: usize,
    /// The number of ranks.
    pub size: usize,
}

/// Starts MPI and, over more than one rank, spreads the tiles of every explicit scatter over
/// the ranks ([`par::set_exchange`]). `Err` when MPI is already initialised or its thread level
/// is below `MPI_THREAD_SERIALIZED`.
pub fn init() -> Result<Mpi, String> {
    let (universe, level) =
        mpi::initialize_with_threading(mpi::Threading::Serialized).ok_or_else(|| "MPI is already initialised".to_string())?;
    if matches!(level, mpi::Threading::Single | mpi::Threading::Funneled) {
        return Err(format!("the MPI library gives thread level {level:?}; the continuum needs Serialized or Multiple"));
    }
    let comm = universe.world();
    let (rank, size) = (comm.rank() as usize, comm.size() as usize);
    if size > 1 && par::set_exchange(Box::new(World { comm, rank, size, stats: Default::default() })).is_err() {
        return Err("a tile exchange is set already".into());
    }
    Ok(Mpi { _universe: universe, rank, size })
}
