//! The MD worker: the pool of endpoints a coupled run steps its boxes through (in-process or
//! remote workers over gRPC, `mscale.coupling.v1`), the recovery of a lost worker's boxes,
//! the conversion between the engine's types and the wire, the worker's gRPC service
//! (`md-worker serve`), its registration with an orchestrator, MPI inside one worker, and the
//! `md-worker` program. The MD itself is the `md-engine` crate, re-exported here (its modules
//! and its main types), so `md_worker::X` paths keep working.

// Index loops over x, y, z read like the physics; `!(x > 0.0)` deliberately rejects NaN.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod device;
pub mod ids;
pub mod join;
pub mod metrics;
#[cfg(feature = "mpi")]
pub mod mpi;
pub mod null;
pub mod pool;
pub mod recovery;
pub mod reuse;
pub mod server;
pub mod source;
pub mod wire;

#[cfg(feature = "cuda")]
pub use md_engine::cuda;
pub use md_engine::{backend, data, direct, error, intra, kernel, lattice, neighbor, potential, simd, units};

pub use md_engine::{
    BoxResult, BoxSpec, BoxState, BoxWork, CpuBackend, DeformMode, Diagnostics, EamFormat, InitialAtoms, LatticeKind, LjCut, MdBackend,
    MdError, Orientation, PointId, Potential, ReferenceBackend, StressSampling,
};

pub use device::backend_by_name;

/// Cargo features this build was compiled with (programs report them in their provenance).
pub const FEATURES: &[&str] = &[
    #[cfg(feature = "cuda")]
    "cuda",
    #[cfg(feature = "mpi")]
    "mpi",
];
