//! The user-facing side of mscale: scene files, runs and their outputs, and (later) the job
//! service. Main design decision: a scene is validated completely, with every default filled,
//! before anything is built, and then turned into exactly the parts it needs (a
//! constitutive-law scene builds no MD engine). The `mscale` binary is a thin layer over this
//! library, so tests drive the same code users do.

// A lock guard in a match or if-let scrutinee lives through the arms: the job service's threads
// take the registry, then the store, and a store guard held that way into code that takes the
// registry deadlocked (a cancelled job's start against DrainWorker). Bind the result first.
#![deny(clippy::significant_drop_in_scrutinee)]

pub mod atomic;
pub mod cell_run;
pub mod checkpoint;
pub mod client;
pub mod exit;
pub mod loaded;
pub mod md;
pub mod output;
pub mod reference;
pub mod report;
pub mod run;
pub mod scene;
pub mod service;
pub mod setup;
pub mod slurm;

/// Cargo features this binary was built with (reported in provenance): orchestrator has none
/// of its own; those of the MD engine it runs in-process (`cuda`, `mpi`).
pub const FEATURES: &[&str] = md_worker::FEATURES;
