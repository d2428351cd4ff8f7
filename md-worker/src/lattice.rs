//! Lattice builders and deterministic random velocities.

use crate::error::MdError;
use crate::units::{BOLTZ, MVV2E};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha20Rng;
use serde::{Deserialize, Serialize};

/// Cubic lattices, conventional cell, orientation [100] [010] [001].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LatticeKind {
    /// Face-centred cubic, 4 atoms per cell.
    Fcc,
    /// Body-centred cubic, 2 atoms per cell.
    Bcc,
    /// Simple cubic, 1 atom per cell.
    Sc,
}

impl std::str::FromStr for LatticeKind {
    type Err = MdError;
    fn from_str(s: &str) -> Result<Self, MdError> {
        match s {
            "fcc" => Ok(LatticeKind::Fcc),
            "bcc" => Ok(LatticeKind::Bcc),
            "sc" => Ok(LatticeKind::Sc),
            _ => Err(MdError::invalid("lattice", format!("{s:?}; expected fcc, bcc or sc"))),
        }
    }
}

impl LatticeKind {
    fn basis(self) -> &'static [[f64; 3]] {
        match self {
            LatticeKind::Fcc => &[[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]],
            LatticeKind::Bcc => &[[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]],
            LatticeKind::Sc => &[[0.0, 0.0, 0.0]],
        }
    }
}

/// Positions of `cells` conventional cells of lattice constant `a0` (A), box [0, cells * a0).
pub fn build_lattice(kind: LatticeKind, a0: f64, cells: [usize; 3]) -> (Vec<[f64; 3]>, [f64; 3]) {
    let mut x = Vec::new();
    for i in 0..cells[0] {
        for j in 0..cells[1] {
            for k in 0..cells[2] {
                for b in kind.basis() {
                    x.push([(i as f64 + b[0]) * a0, (j as f64 + b[1]) * a0, (k as f64 + b[2]) * a0]);
                }
            }
        }
    }
    (x, [cells[0] as f64 * a0, cells[1] as f64 * a0, cells[2] as f64 * a0])
}

/// The generator for a (seed, point id, purpose, step) tuple: independent streams per box.
pub fn rng_for(seed: u64, point: u64, purpose: u64, step: u64) -> ChaCha20Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8..16].copy_from_slice(&point.to_le_bytes());
    key[16..24].copy_from_slice(&purpose.to_le_bytes());
    key[24..].copy_from_slice(&step.to_le_bytes());
    ChaCha20Rng::from_seed(key)
}

/// A standard normal deviate (Box-Muller, so the stream is ours and stable).
pub fn normal(rng: &mut ChaCha20Rng) -> f64 {
    let u1: f64 = 1.0 - rng.r#gen::<f64>(); // (0, 1]
    let u2: f64 = rng.r#gen::<f64>();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Maxwell velocities (A/ps) at exactly temperature `t` (K), zero total momentum.
pub fn maxwell_velocities(rng: &mut ChaCha20Rng, masses: &[f64], t: f64) -> Vec<[f64; 3]> {
    let n = masses.len();
    let mut v: Vec<[f64; 3]> = masses
        .iter()
        .map(|m| {
            let s = (BOLTZ * t / (m * MVV2E)).sqrt();
            [normal(rng) * s, normal(rng) * s, normal(rng) * s]
        })
        .collect();
    remove_momentum(&mut v, masses);
    let ke: f64 = 0.5 * MVV2E * v.iter().zip(masses).map(|(vi, m)| m * (vi[0] * vi[0] + vi[1] * vi[1] + vi[2] * vi[2])).sum::<f64>();
    let dof = (3 * n).saturating_sub(3) as f64;
    if ke > 0.0 && dof > 0.0 {
        let scale = (0.5 * dof * BOLTZ * t / ke).sqrt();
        for vi in &mut v {
            for c in vi.iter_mut() {
                *c *= scale;
            }
        }
    }
    v
}

/// Subtract the mass-weighted mean velocity.
pub fn remove_momentum(v: &mut [[f64; 3]], masses: &[f64]) {
    let mt: f64 = masses.iter().sum();
    let mut p = [0.0; 3];
    for (vi, m) in v.iter().zip(masses) {
        for d in 0..3 {
            p[d] += m * vi[d];
        }
    }
    for vi in v.iter_mut() {
        for d in 0..3 {
            vi[d] -= p[d] / mt;
        }
    }
}
