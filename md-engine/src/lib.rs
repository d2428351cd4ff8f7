//! MD engine: batches of small periodic EAM boxes deformed by a velocity gradient, returning
//! their virial stress. LAMMPS `metal` units throughout (A, ps, eV, amu; stress in GPa at the
//! edge, tension positive). Design decision: one set of serial per-box kernels
//! ([`kernel`]) over a flat structure-of-arrays batch with per-box offsets ([`backend::Batch`]);
//! back ends ([`backend::MdBackend`]) only decide how boxes are spread over threads or a device,
//! so every box's result is bitwise the same for any thread count, and EAM tables are splined
//! exactly as LAMMPS `pair_eam` does, so results agree with LAMMPS to round-off.
//!
//! This crate knows no network, process or command line: the worker pool, the gRPC service
//! and the `md-worker` program live in `md-worker`, on top of it. With the `cli` feature,
//! [`direct::DirectArgs`] derives `clap::Args` for `md-worker direct`.

// Index loops over x, y, z read like the physics; `!(x > 0.0)` deliberately rejects NaN.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod backend;
#[cfg(feature = "cuda")]
pub mod cuda;
pub mod data;
pub mod device;
pub mod direct;
pub mod error;
pub mod intra;
pub mod kernel;
pub mod lattice;
pub mod neighbor;
pub mod potential;
pub mod simd;
pub mod units;

pub use backend::{
    BoxResult, BoxSpec, BoxState, BoxWork, CpuBackend, Diagnostics, InitialAtoms, MdBackend, PointId, ReferenceBackend, StressSampling,
};
pub use device::backend_by_name;
pub use error::MdError;
pub use kernel::DeformMode;
pub use lattice::{LatticeKind, Orientation};
pub use potential::{EamFormat, LjCut, Potential};
