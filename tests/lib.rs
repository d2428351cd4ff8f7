//! Helpers shared by the integration tests (the process-spawning ones live in mscale-testkit,
//! shared with orchestrator/tests).

use std::path::PathBuf;

pub use mscale_testkit::{Listening, Proc, state_digest, summary, text, token_dir, wait_until};

/// Root of the repository.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `MSCALE_MPI_MSCALE`: an mscale built with `--features mpi` (CI's mpi step builds it), for the
/// tests that run the continuum over MPI ranks (mpirun or srun).
pub fn mpi_mscale() -> PathBuf {
    match std::env::var_os("MSCALE_MPI_MSCALE") {
        Some(p) if !p.is_empty() && std::path::Path::new(&p).is_file() => PathBuf::from(p),
        _ => panic!("MSCALE_MPI_MSCALE is unset or not a file: set it to an mscale built with --features mpi (see .ci/run)"),
    }
}

/// A small valid 1D scene (ideal-gas shock tube, 50 cells) to mutate in tests.
pub fn small_scene() -> String {
    std::fs::read_to_string(repo().join("tests/data/small.toml")).expect("tests/data/small.toml")
}

/// Path of a workspace binary (`mscale`, `md-worker`), prebuilt: never built here, refused
/// when missing or older than its sources, with the command that builds it
/// ([`mscale_testkit::prebuilt`]; `cargo test --workspace` builds every binary first).
pub fn binary(name: &str, package: &str) -> PathBuf {
    mscale_testkit::prebuilt(name, package)
}

/// A running `md-worker serve` (the prebuilt one) on a free loopback port with `threads`
/// threads, killed on drop.
pub fn worker(threads: usize) -> Listening {
    Listening::md_worker(&binary("md-worker", "md-worker"), threads)
}
