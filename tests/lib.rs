//! Helpers shared by the integration tests.

use std::path::PathBuf;

/// Root of the repository.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A small valid 1D scene (ideal-gas shock tube, 50 cells) to mutate in tests.
pub fn small_scene() -> String {
    std::fs::read_to_string(repo().join("tests/data/small.toml")).expect("tests/data/small.toml")
}
