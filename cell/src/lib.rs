//! The 1D Poisson-Nernst-Planck full cell of the battery thesis's Ch. 8: a cell-centred
//! finite-volume discretisation ([`model`]), its scene ([`scene`]) and its implicit DAE
//! integration by diffsol's BDF ([`solver`]). See README.md for the equations as derived
//! here, the errata and the choices made where the thesis is silent.

pub mod band;
pub mod debye;
pub mod model;
pub mod scene;
pub mod solver;
pub mod units;

pub use model::Model;
pub use scene::{CellScene, CellSceneError};

/// SHA-256 over the step count, the time and the bits of every unknown.
pub fn state_digest(step: u64, t: f64, y: &[f64]) -> String {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(step.to_le_bytes());
    h.update(t.to_bits().to_le_bytes());
    for v in y {
        h.update(v.to_bits().to_le_bytes());
    }
    hex::encode(h.finalize())
}
