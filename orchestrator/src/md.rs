//! What a scene with `md` bodies needs beyond the solver: properties of the lattice measured
//! from the potential (for validation and the CFL bound), box specs for the points, and the
//! worker pool (in-process or remote workers).

use crate::scene::{Body, MdMaterial};
use anyhow::{Context, Result};
use md_worker::pool::{Endpoint, InProcess, MdPool, Remote};
use md_worker::{BoxResult, BoxSpec, BoxWork, DeformMode, LatticeKind, MdBackend, Potential};
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
}

pub fn lattice_kind(name: &str) -> Result<LatticeKind> {
    Ok(match name {
        "fcc" => LatticeKind::Fcc,
        "bcc" => LatticeKind::Bcc,
        "sc" => LatticeKind::Sc,
        other => anyhow::bail!("unknown lattice {other:?}; expected fcc, bcc or sc"),
    })
}

fn atoms_per_cell(kind: LatticeKind) -> f64 {
    match kind {
        LatticeKind::Fcc => 4.0,
        LatticeKind::Bcc => 2.0,
        LatticeKind::Sc => 1.0,
    }
}

/// Reads the potential (refusing malformed or truncated files with their line) and measures
/// the density and C11 of the lattice from the stress of one cell strained by +/- 0.1 %.
pub fn lattice_properties(potential: &Path, lattice: &str, a0: f64) -> Result<LatticeProperties> {
    let pot = Arc::new(Potential::from_file(potential)?);
    let kind = lattice_kind(lattice)?;
    let density = atoms_per_cell(kind) * pot.mass(0) * AMU_KG / (a0 * 1e-10).powi(3);
    let eps = 1e-3;
    let mut md = md_worker::ReferenceBackend::new(pot);
    let specs: Vec<BoxSpec> = [eps, -eps]
        .iter()
        .enumerate()
        .map(|(k, e)| {
            let mut s = BoxSpec::lattice(k as u64, kind, a0, [1, 1, 1]);
            s.strain = [*e, 0.0, 0.0];
            s
        })
        .collect();
    md.open(&specs)?;
    let work: Vec<BoxWork> = (0..2).map(|k| BoxWork { id: k, velocity_gradient: [[0.0; 3]; 3], steps: 0, dt_ps: 0.001, energy_to_add_ev: 0.0 }).collect();
    let mut out = vec![BoxResult::default(); 2];
    md.step(&work, &mut out)?;
    // Tension positive: stretching (+eps) raises sigma_xx.
    let c11_gpa = (out[0].stress_gpa[0] - out[1].stress_gpa[0]) / (2.0 * eps);
    anyhow::ensure!(c11_gpa > 0.0 && c11_gpa.is_finite(), "the {lattice} lattice at a0 = {a0} A is not stable under this potential (C11 = {c11_gpa} GPa)");
    Ok(LatticeProperties { density, c11_gpa, wave_speed: (c11_gpa * 1e9 / density).sqrt() })
}

/// The box of one material point of an md body.
pub fn box_spec(id: u64, body: &Body, md: &MdMaterial) -> Result<BoxSpec> {
    let n = md.cells_per_side;
    let mut s = BoxSpec::lattice(id, lattice_kind(&md.lattice)?, md.lattice_constant_angstrom, [n, n, n]);
    s.strain = [body.initial_strain[0], body.initial_strain[1], body.initial_strain[2]];
    s.temperature_k = body.temperature_k;
    s.seed = md.seed;
    s.relax_steps = md.relax_steps as u64;
    s.relax_dt_ps = md.timestep_fs * 1e-3;
    s.relax_box_blocks = if md.relax_box { 10 } else { 0 };
    s.mode = if md.deformation == "affine" { DeformMode::Affine } else { DeformMode::Seed };
    Ok(s)
}

/// A pool over `workers` (`host:port`), or in-process on all cores when there are none.
pub fn pool(workers: &[String]) -> Result<MdPool> {
    let endpoints: Vec<Box<dyn Endpoint>> = if workers.is_empty() {
        vec![Box::new(InProcess::new("cpu", None))]
    } else {
        let rt = Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the gRPC runtime")?);
        workers.iter().map(|w| Remote::connect(w, rt.clone()).map(|r| Box::new(r) as Box<dyn Endpoint>).map_err(anyhow::Error::from)).collect::<Result<_>>()?
    };
    Ok(MdPool::new(endpoints)?)
}
