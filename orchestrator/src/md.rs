//! What a scene with `md` bodies needs beyond the solver: properties of the lattice measured
//! from the potential (for validation and the CFL bound; measured in `coupling::lattice`),
//! box specs for the points, and the worker pool (in-process or remote workers).

use crate::scene::{ResolvedBody, ResolvedMd};
use anyhow::{Context, Result};
use md_worker::pool::{Endpoint, InProcess, MdPool, Remote};
use md_worker::{BoxResult, BoxSpec, BoxWork, DeformMode, MdBackend, Potential};
use std::sync::Arc;

pub use coupling::lattice::{LatticeProperties, lattice_properties};

/// The box of one material point of an md body.
pub fn box_spec(id: u64, body: &ResolvedBody, md: &ResolvedMd) -> BoxSpec {
    let n = md.cells_per_side;
    let mut s = BoxSpec::lattice(id, md.lattice, md.lattice_constant_angstrom, [n, n, n]).oriented(md.orientation);
    s.strain = body.initial_strain;
    s.temperature_k = body.temperature_k;
    s.seed = md.seed;
    s.relax_steps = md.relax_steps as u64;
    s.relax_dt_ps = md.timestep_fs * 1e-3;
    s.relax_box_blocks = if md.relax_box { 10 } else { 0 };
    s.mode = md.deformation;
    s
}

/// A pool over `workers` (`host:port`), or in-process on all cores when there are none.
pub fn pool(workers: &[String]) -> Result<MdPool> {
    let endpoints: Vec<Box<dyn Endpoint>> = if workers.is_empty() {
        vec![Box::new(InProcess::new("cpu", None))]
    } else {
        let rt = Arc::new(
            tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the gRPC runtime")?,
        );
        workers
            .iter()
            .map(|w| Remote::connect(w, rt.clone()).map(|r| Box::new(r) as Box<dyn Endpoint>).map_err(anyhow::Error::from))
            .collect::<Result<_>>()?
    };
    Ok(MdPool::new(endpoints)?)
}

/// Predicted size and cost of the MD part of a scene.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Estimate {
    pub md_points: usize,
    pub atoms: u64,
    /// MD steps per box over the run (relaxation included).
    pub md_steps_per_box: u64,
    pub atom_steps: f64,
    /// Measured on this machine with the in-process cpu back end, all cores.
    pub ns_per_atom_step: f64,
    pub bytes_per_atom: f64,
    pub memory_bytes: f64,
    pub wall_seconds: f64,
}

impl Estimate {
    /// Predicted MD wall time (s) on `workers` workers like this machine, each running its
    /// boxes on `threads` threads: the boxes spread in nearly equal blocks and a box is never
    /// split, so the busiest worker runs ceil(points / workers) boxes in rounds of `threads`.
    /// Transfers and the continuum's own time are not included.
    pub fn wall_seconds_on(&self, workers: usize, threads: usize) -> f64 {
        let (p, t) = (self.md_points.max(1), threads.max(1));
        let per_worker = p.div_ceil(workers.max(1));
        self.wall_seconds * (per_worker.div_ceil(t) * t) as f64 / p as f64
    }
}

fn resident_bytes() -> Option<f64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: f64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096.0)
}

/// Counts the MD work of a validated scene and measures this machine's throughput on boxes of
/// the scene's size (a few boxes, a short run), to predict atom-steps, memory and wall time.
pub fn estimate(loaded: &crate::scene::LoadedScene) -> Result<Option<Estimate>> {
    let mut atoms = 0u64;
    let mut atom_steps = 0f64;
    let mut md_steps_per_box = 0;
    let mut calibrate = None;
    let mut md_points = 0;
    for (body, m) in loaded.resolved.md_bodies() {
        let (per_box, n) = (m.atoms_per_box, body.points);
        let steps = loaded.steps * (loaded.dt / (m.timestep_fs * 1e-15)).round() as u64 + m.relax_steps as u64;
        md_points += n;
        atoms += per_box * n as u64;
        atom_steps += (per_box * n as u64) as f64 * steps as f64;
        md_steps_per_box = md_steps_per_box.max(steps);
        calibrate.get_or_insert((m, body));
    }
    let Some((m, body)) = calibrate else { return Ok(None) };
    let pot = Arc::new(Potential::from_file(&m.potential)?);
    let boxes = rayon::current_num_threads().max(1) * 2;
    let before = resident_bytes();
    let mut md = md_worker::CpuBackend::new(pot);
    let specs: Vec<BoxSpec> = (0..boxes as u64).map(|id| box_spec(id, body, m)).collect();
    md.open(&specs)?;
    let l = 1e-3 * if m.deformation == DeformMode::Affine { 1.0 } else { 0.5 };
    let work: Vec<BoxWork> =
        (0..boxes as u64).map(|id| BoxWork::new(id, [[-l, 0.0, 0.0], [0.0; 3], [0.0; 3]], 20, m.timestep_fs * 1e-3)).collect();
    let mut out = vec![BoxResult::default(); boxes];
    md.step(&work, &mut out)?;
    let t = std::time::Instant::now();
    md.step(&work, &mut out)?;
    let secs = t.elapsed().as_secs_f64();
    let atoms_per_box = atoms as f64 / md_points.max(1) as f64;
    let ns_per_atom_step = secs * 1e9 / (boxes as f64 * atoms_per_box * 20.0);
    let bytes_per_atom = match (before, resident_bytes()) {
        (Some(a), Some(b)) if b > a => (b - a) / (boxes as f64 * atoms_per_box),
        _ => f64::NAN,
    };
    Ok(Some(Estimate {
        md_points,
        atoms,
        md_steps_per_box,
        atom_steps,
        ns_per_atom_step,
        bytes_per_atom,
        memory_bytes: bytes_per_atom * atoms as f64,
        wall_seconds: atom_steps * ns_per_atom_step * 1e-9,
    }))
}

#[cfg(test)]
mod tests {
    use super::Estimate;

    #[test]
    fn the_wall_time_on_n_workers_counts_whole_boxes_per_thread() {
        let e = Estimate {
            md_points: 100,
            atoms: 10_800,
            md_steps_per_box: 1000,
            atom_steps: 1.08e7,
            ns_per_atom_step: 500.0,
            bytes_per_atom: 1500.0,
            memory_bytes: 1.62e7,
            wall_seconds: 100.0,
        };
        // One worker of 2 threads: the measured time itself.
        assert_eq!(e.wall_seconds_on(1, 2), 100.0);
        // 4 workers: 25 boxes each, 13 rounds of 2 threads = 26 box-times of the 100.
        assert_eq!(e.wall_seconds_on(4, 2), 26.0);
        // More workers than boxes: one box per worker still takes a round of 2 threads.
        assert_eq!(e.wall_seconds_on(1000, 2), 2.0);
    }
}
