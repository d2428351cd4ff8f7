//! Properties of an md material's lattice measured from the potential before anything runs:
//! its density and its longitudinal modulus along x from one (oriented) unit cell strained by
//! +/- 0.1 %, for the validation of a scene (density of the body) and the CFL bound.

use anyhow::Result;
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind, MdBackend, Orientation, Potential};
use std::path::Path;
use std::sync::Arc;

/// Atomic mass unit (kg).
const AMU_KG: f64 = 1.66053906660e-27;

/// Properties of a perfect lattice at 0 K for a potential.
#[derive(Debug, Clone, Copy)]
pub struct LatticeProperties {
    /// kg/m^3.
    pub density: f64,
    /// dsigma_xx/deps_xx under uniaxial strain (GPa).
    pub c11_gpa: f64,
    /// Longitudinal wave speed sqrt(C11 / rho) (m/s).
    pub wave_speed: f64,
    /// The vibration that bounds the MD time step ([`md_worker::Potential::vibration`]).
    pub vibration: Option<md_worker::potential::Vibration>,
}

fn lattice_name(kind: LatticeKind) -> &'static str {
    match kind {
        LatticeKind::Fcc => "fcc",
        LatticeKind::Bcc => "bcc",
        LatticeKind::Sc => "sc",
    }
}

fn atoms_per_cell(kind: LatticeKind) -> f64 {
    match kind {
        LatticeKind::Fcc => 4.0,
        LatticeKind::Bcc => 2.0,
        LatticeKind::Sc => 1.0,
    }
}

/// Reads the potential (refusing malformed or truncated files with their line) and measures
/// the density and the longitudinal modulus along x (C11 for the cube orientation) of the
/// lattice from the stress of one (oriented) cell strained by +/- 0.1 % along x.
pub fn lattice_properties(potential: &Path, kind: LatticeKind, a0: f64, orient: Orientation) -> Result<LatticeProperties> {
    let pot = Arc::new(Potential::from_file(potential)?);
    let density = atoms_per_cell(kind) * pot.mass(0) * AMU_KG / (a0 * 1e-10).powi(3);
    let vibration = pot.vibration();
    let eps = 1e-3;
    let mut md = md_worker::ReferenceBackend::new(pot);
    let specs: Vec<BoxSpec> = [eps, -eps]
        .iter()
        .enumerate()
        .map(|(k, e)| {
            let mut s = BoxSpec::lattice(k as u64, kind, a0, [1, 1, 1]).oriented(orient);
            s.strain = [*e, 0.0, 0.0];
            s
        })
        .collect();
    md.open(&specs)?;
    let work: Vec<BoxWork> = (0..2).map(|k| BoxWork::new(k, [[0.0; 3]; 3], 0, 0.001)).collect();
    let mut out = vec![BoxResult::default(); 2];
    md.step(&work, &mut out)?;
    // Tension positive: stretching (+eps) raises sigma_xx.
    let c11_gpa = (out[0].stress_gpa[0] - out[1].stress_gpa[0]) / (2.0 * eps);
    anyhow::ensure!(
        c11_gpa > 0.0 && c11_gpa.is_finite(),
        "the {} lattice at a0 = {a0} A is not stable under this potential (C11 = {c11_gpa} GPa)",
        lattice_name(kind)
    );
    Ok(LatticeProperties { density, c11_gpa, wave_speed: (c11_gpa * 1e9 / density).sqrt(), vibration })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn an_oriented_lattice_has_the_same_density_and_its_own_longitudinal_modulus() {
        let pot = Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials/Cu_mishin1.eam.alloy");
        let cube = lattice_properties(&pot, LatticeKind::Fcc, 3.615, Orientation::CUBE).unwrap();
        let x110 = lattice_properties(&pot, LatticeKind::Fcc, 3.615, Orientation([[1, 1, 0], [-1, 1, 0], [0, 0, 1]])).unwrap();
        assert!((cube.density - x110.density).abs() < 1e-9 * cube.density);
        // Mishin Cu: C11 169.9, C12 122.6, C44 76.2 GPa; along [110] (C11 + C12 + 2 C44) / 2 = 222.4.
        assert!((cube.c11_gpa / 169.9 - 1.0).abs() < 0.01, "C11 = {}", cube.c11_gpa);
        assert!((x110.c11_gpa / 222.4 - 1.0).abs() < 0.01, "C'11[110] = {}", x110.c11_gpa);
    }
}
