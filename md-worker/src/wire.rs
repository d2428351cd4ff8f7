//! Conversions between the generated `mscale.coupling.v1` types and the engine's domain types,
//! with every value checked at the edge: a non-finite or out-of-range value is refused naming
//! the point and the field (InvalidArgument on the server side).

use crate::backend::{BoxResult, BoxSpec, BoxWork, Diagnostics, InitialAtoms, StressSampling};
use crate::error::MdError;
use crate::kernel::DeformMode;
use crate::lattice::{LatticeKind, Orientation};
use mscale_proto::coupling::v1 as pb;

/// Largest gRPC message either side accepts (bytes).
pub const MAX_MESSAGE: usize = 64 << 20;
/// Boxes per step message; larger batches are chunked.
pub const MAX_BOXES_PER_MESSAGE: usize = 4096;
/// Most MD steps one box may be asked for in one call.
pub const MAX_STEPS_PER_CALL: u64 = 10_000_000;
/// HTTP/2 flow-control window per stream, both sides (bytes). The default 64 KiB would make a
/// 400 KB step message wait for several window updates (round trips) on its way.
pub const HTTP2_STREAM_WINDOW: u32 = 16 << 20;
/// HTTP/2 flow-control window per connection, both sides (bytes).
pub const HTTP2_CONNECTION_WINDOW: u32 = 32 << 20;
/// Largest HTTP/2 frame a worker accepts (bytes; the default is 16 KiB): fewer frames per batch.
pub const HTTP2_MAX_FRAME: u32 = 1 << 20;

/// `work` cut into the fewest messages of at most [`MAX_BOXES_PER_MESSAGE`] boxes, of nearly
/// equal sizes (in order).
pub fn chunks<T>(work: &[T]) -> impl Iterator<Item = &[T]> {
    let n = work.len().div_ceil(MAX_BOXES_PER_MESSAGE).max(1);
    work.chunks(work.len().div_ceil(n).max(1))
}

pub fn status_text(s: &tonic::Status) -> String {
    format!("{:?}: {}", s.code(), s.message())
}

fn invalid(point: u64, field: &str, msg: impl std::fmt::Display) -> MdError {
    MdError::invalid(format!("point {point} field `{field}`"), msg.to_string())
}

fn finite(point: u64, field: &str, v: f64) -> Result<f64, MdError> {
    if v.is_finite() { Ok(v) } else { Err(invalid(point, field, format!("{v} is not finite"))) }
}

pub fn spec_to_pb(s: &BoxSpec) -> pb::BoxSpec {
    let (lattice, a0, cells, orientation) = match &s.atoms {
        InitialAtoms::Lattice { kind, a0, cells, orient } => (
            match kind {
                LatticeKind::Fcc => "fcc",
                LatticeKind::Bcc => "bcc",
                LatticeKind::Sc => "sc",
            },
            *a0,
            cells.iter().map(|&c| c as u32).collect(),
            if *orient == Orientation::CUBE { Vec::new() } else { orient.0.iter().flatten().copied().collect() },
        ),
        // Explicit atoms do not travel: the server refuses an empty lattice name.
        InitialAtoms::Explicit { .. } => ("", 0.0, Vec::new(), Vec::new()),
    };
    pb::BoxSpec {
        point_id: s.id,
        lattice: lattice.into(),
        lattice_constant: a0,
        cells,
        strain: s.strain.to_vec(),
        temperature_k: s.temperature_k,
        seed: s.seed,
        relax_steps: s.relax_steps,
        relax_dt_ps: s.relax_dt_ps,
        relax_box_blocks: s.relax_box_blocks,
        deformation: match s.mode {
            DeformMode::Affine => "affine",
            DeformMode::Seed => "seed",
        }
        .into(),
        orientation,
    }
}

pub fn spec_from_pb(p: &pb::BoxSpec) -> Result<BoxSpec, MdError> {
    let id = p.point_id;
    let kind = match p.lattice.as_str() {
        "fcc" => LatticeKind::Fcc,
        "bcc" => LatticeKind::Bcc,
        "sc" => LatticeKind::Sc,
        other => return Err(invalid(id, "lattice", format!("{other:?}; expected fcc, bcc or sc"))),
    };
    let a0 = finite(id, "lattice_constant", p.lattice_constant)?;
    if a0 <= 0.0 {
        return Err(invalid(id, "lattice_constant", format!("{a0} A must be positive")));
    }
    if p.cells.len() != 3 || p.cells.iter().any(|&c| c == 0 || c > 64) {
        return Err(invalid(id, "cells", format!("{:?}; expected 3 values in 1..=64", p.cells)));
    }
    if p.strain.len() != 3 || p.strain.iter().any(|e| !(e.is_finite() && *e > -0.5 && *e < 1.0)) {
        return Err(invalid(id, "strain", format!("{:?}; expected 3 finite values in (-0.5, 1)", p.strain)));
    }
    if !(p.temperature_k.is_finite() && p.temperature_k >= 0.0) {
        return Err(invalid(id, "temperature_k", p.temperature_k));
    }
    if !(p.relax_dt_ps.is_finite() && p.relax_dt_ps > 0.0 && p.relax_dt_ps <= 0.01) {
        return Err(invalid(id, "relax_dt_ps", format!("{} ps; expected (0, 0.01]", p.relax_dt_ps)));
    }
    let mode = match p.deformation.as_str() {
        "affine" => DeformMode::Affine,
        "seed" => DeformMode::Seed,
        other => return Err(invalid(id, "deformation", format!("{other:?}; expected affine or seed"))),
    };
    let orient = match p.orientation.as_slice() {
        [] => Orientation::CUBE,
        o if o.len() == 9 => Orientation([[o[0], o[1], o[2]], [o[3], o[4], o[5]], [o[6], o[7], o[8]]]),
        o => return Err(invalid(id, "orientation", format!("{o:?}; expected 9 integers (x, y, z directions) or none"))),
    };
    orient.validate().map_err(|e| invalid(id, "orientation", e))?;
    let mut s = BoxSpec::lattice(id, kind, a0, [p.cells[0] as usize, p.cells[1] as usize, p.cells[2] as usize]).oriented(orient);
    s.strain = [p.strain[0], p.strain[1], p.strain[2]];
    s.temperature_k = p.temperature_k;
    s.seed = p.seed;
    s.relax_steps = p.relax_steps;
    s.relax_dt_ps = p.relax_dt_ps;
    s.relax_box_blocks = p.relax_box_blocks;
    s.mode = mode;
    Ok(s)
}

fn sampling_to_pb(s: StressSampling) -> i32 {
    match s {
        StressSampling::Last => pb::StressSampling::Last as i32,
        StressSampling::Average => pb::StressSampling::Average as i32,
    }
}

fn sampling_from_pb(point: u64, v: i32) -> Result<StressSampling, MdError> {
    match pb::StressSampling::try_from(v) {
        Ok(pb::StressSampling::Last) => Ok(StressSampling::Last),
        Ok(pb::StressSampling::Average) => Ok(StressSampling::Average),
        Err(_) => Err(invalid(point, "stress_sampling", format!("{v}; expected 0 (last) or 1 (average)"))),
    }
}

pub fn work_to_pb(w: &BoxWork) -> pb::WorkItem {
    let l = &w.velocity_gradient;
    pb::WorkItem {
        point_id: w.id,
        velocity_gradient: pb::Doubles::full([l[0][0], l[0][1], l[0][2], l[1][0], l[1][1], l[1][2], l[2][0], l[2][1], l[2][2]]),
        steps: w.steps,
        dt_ps: w.dt_ps,
        energy_to_add_ev: w.energy_to_add_ev,
        stress_sampling: sampling_to_pb(w.stress_sampling),
    }
}

pub fn work_from_pb(p: &pb::WorkItem) -> Result<BoxWork, MdError> {
    let id = p.point_id;
    if p.velocity_gradient.len != 9 {
        return Err(invalid(id, "velocity_gradient", format!("{} values; expected 9 (row major, 1/ps)", p.velocity_gradient.len)));
    }
    let mut l = [[0.0; 3]; 3];
    for (k, v) in p.velocity_gradient.values.iter().enumerate() {
        l[k / 3][k % 3] = finite(id, "velocity_gradient", *v)?;
    }
    if p.steps > MAX_STEPS_PER_CALL {
        return Err(invalid(id, "steps", format!("{} exceeds {MAX_STEPS_PER_CALL}", p.steps)));
    }
    if !(p.dt_ps.is_finite() && p.dt_ps > 0.0 && p.dt_ps <= 0.01) {
        return Err(invalid(id, "dt_ps", format!("{} ps; expected (0, 0.01]", p.dt_ps)));
    }
    Ok(BoxWork {
        id,
        velocity_gradient: l,
        steps: p.steps,
        dt_ps: p.dt_ps,
        energy_to_add_ev: finite(id, "energy_to_add_ev", p.energy_to_add_ev)?,
        stress_sampling: sampling_from_pb(id, p.stress_sampling)?,
    })
}

pub fn result_to_pb(r: &BoxResult) -> pb::ResultItem {
    pb::ResultItem {
        point_id: r.id,
        stress_gpa: pb::Doubles::full(r.stress_gpa),
        potential_energy_ev: r.potential_energy_ev,
        kinetic_energy_ev: r.kinetic_energy_ev,
        temperature_k: r.temperature_k,
        lengths: pb::Doubles::full(r.diagnostics.lengths_a),
        neighbor_rebuilds: r.diagnostics.neighbor_rebuilds,
        energy_shortfall_ev: r.diagnostics.energy_shortfall_ev,
        total_steps: r.diagnostics.total_steps,
        wraps: r.diagnostics.wraps,
        stress_sampling: sampling_to_pb(r.stress_sampling),
    }
}

pub fn result_from_pb(p: &pb::ResultItem) -> Result<BoxResult, MdError> {
    let id = p.point_id;
    if p.stress_gpa.len != 6 || p.lengths.len != 3 {
        return Err(invalid(
            id,
            "stress_gpa",
            format!("{} stress and {} length values; expected 6 and 3", p.stress_gpa.len, p.lengths.len),
        ));
    }
    Ok(BoxResult {
        id,
        stress_gpa: p.stress_gpa.values,
        potential_energy_ev: p.potential_energy_ev,
        kinetic_energy_ev: p.kinetic_energy_ev,
        temperature_k: p.temperature_k,
        stress_sampling: sampling_from_pb(id, p.stress_sampling)?,
        diagnostics: Diagnostics {
            total_steps: p.total_steps,
            lengths_a: p.lengths.values,
            energy_shortfall_ev: p.energy_shortfall_ev,
            neighbor_rebuilds: p.neighbor_rebuilds,
            wraps: p.wraps,
        },
    })
}

/// Refuses a result with a non-finite value, naming the worker, the point and the field.
pub fn check_result(r: &BoxResult, worker: &str) -> Result<(), MdError> {
    let fields = [
        ("stress_gpa", r.stress_gpa.iter().all(|v| v.is_finite())),
        ("potential_energy_ev", r.potential_energy_ev.is_finite()),
        ("kinetic_energy_ev", r.kinetic_energy_ev.is_finite()),
        ("lengths", r.diagnostics.lengths_a.iter().all(|v| v.is_finite() && *v > 0.0)),
    ];
    for (field, ok) in fields {
        if !ok {
            return Err(MdError::Worker { worker: worker.into(), msg: format!("returned a non-finite `{field}` for point {}", r.id) });
        }
    }
    Ok(())
}

/// The gRPC status of an engine error: InvalidArgument for bad input, NotFound for an unknown
/// box, Unimplemented for an unsupported request, Internal for a diverged box and otherwise. (A function, not a
/// `From` impl: both types belong to other crates.)
pub fn status(e: MdError) -> tonic::Status {
    match e {
        MdError::Invalid { .. } | MdError::Parse { .. } => tonic::Status::invalid_argument(e.to_string()),
        MdError::UnknownBox(_) => tonic::Status::not_found(e.to_string()),
        MdError::Unsupported(_) => tonic::Status::unimplemented(e.to_string()),
        // Internal, not a loss: the pool must not recover the box on another worker, where
        // the same box diverges the same way; the message names the point.
        MdError::Diverged { .. } => tonic::Status::internal(e.to_string()),
        _ => tonic::Status::internal(e.to_string()),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::pool::{Endpoint, PotentialSource, Remote};
    use std::sync::Arc;

    fn cu() -> PotentialSource {
        PotentialSource::from_file(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/potentials/Cu_mishin1.eam.alloy"))).unwrap()
    }

    #[test]
    fn hostile_values_over_the_wire_are_refused_or_stopped_naming_the_point() {
        let w = crate::server::Loopback::start("reference").unwrap();
        let rt = Arc::new(tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap());
        let mut remote = Remote::connect(&w.addr, rt).unwrap();
        // A lattice constant that gives a box below the neighbour list's reach.
        let tiny = BoxSpec::lattice(9, LatticeKind::Fcc, 1e-300, [1, 1, 1]);
        let e = remote.open(&cu(), &[tiny]).unwrap_err().to_string();
        assert!(e.contains("InvalidArgument") && e.contains("point 9") && e.contains("1e-300"), "{e}");
        let specs: Vec<BoxSpec> = [3, 5].iter().map(|&id| BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [2, 2, 2])).collect();
        remote.open(&cu(), &specs).unwrap();
        // A velocity gradient of 1e6 1/ps: refused before any box moves.
        let mut l = [[0.0; 3]; 3];
        l[0][0] = 1e6;
        let e = remote.step(1, &[BoxWork::new(3, l, 10, 0.001), BoxWork::new(5, [[0.0; 3]; 3], 10, 0.001)]).unwrap_err().to_string();
        assert!(e.contains("InvalidArgument") && e.contains("point 3") && e.contains("xx = 1000000 1/ps"), "{e}");
        // A 5 ps time step: refused at the wire's edge, naming the point and the field.
        let e = remote.step(1, &[BoxWork::new(3, [[0.0; 3]; 3], 10, 5.0)]).unwrap_err().to_string();
        assert!(e.contains("InvalidArgument") && e.contains("point 3 field `dt_ps`") && e.contains("5 ps"), "{e}");
        // 1e5 eV added to box 5 (about 3e3 eV per atom): the MD guard stops it at its first
        // step, and the worker's error names the point.
        let mut hot = BoxWork::new(5, [[0.0; 3]; 3], 10, 0.001);
        hot.energy_to_add_ev = 1e5;
        let e = remote.step(2, &[BoxWork::new(3, [[0.0; 3]; 3], 10, 0.001), hot]).unwrap_err().to_string();
        assert!(e.contains("Internal") && e.contains("point 5: MD diverged: at step 1") && e.contains("kinetic energy"), "{e}");
    }

    #[test]
    fn a_diverged_box_is_an_internal_status_not_a_loss() {
        let s = status(MdError::Diverged { point: 7, msg: "x".into() });
        assert_eq!(s.code(), tonic::Code::Internal);
        assert!(s.message().contains("point 7: MD diverged"));
        let s = status(MdError::invalid("box work of point 7", "velocity gradient xx = 1000000 1/ps"));
        assert_eq!(s.code(), tonic::Code::InvalidArgument);
    }
}
