//! Conversions between the generated `mscale.coupling.v1` types and the engine's domain types,
//! with every value checked at the edge: a non-finite or out-of-range value is refused naming
//! the point and the field (InvalidArgument on the server side).

use crate::backend::{BoxResult, BoxSpec, BoxWork, Diagnostics, InitialAtoms, StressSampling};
use crate::error::MdError;
use crate::kernel::DeformMode;
use crate::lattice::{LatticeKind, Orientation};
use mscale_proto::coupling::v1 as pb;
use mscale_proto::{f64_at, f64_column};

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

/// One step message of `work` (column-oriented: one packed column per quantity).
pub fn batch_to_pb(session: u64, step: u64, work: &[BoxWork]) -> pb::StepBatch {
    pb::StepBatch {
        session,
        step,
        point_id: work.iter().map(|w| w.id).collect(),
        velocity_gradient: f64_column(work.iter().map(|w| std::array::from_fn::<f64, 9, _>(|j| w.velocity_gradient[j / 3][j % 3]))),
        steps: work.iter().map(|w| w.steps).collect(),
        dt_ps: f64_column(work.iter().map(|w| [w.dt_ps])),
        energy_to_add_ev: f64_column(work.iter().map(|w| [w.energy_to_add_ev])),
        stress_sampling: work.iter().map(|w| sampling_to_pb(w.stress_sampling)).collect(),
    }
}

/// Refuses a message whose column `name` does not hold `per_box` values for each of `boxes`.
fn column(name: &str, len: usize, boxes: usize, per_box: usize) -> Result<(), MdError> {
    if len == boxes * per_box {
        return Ok(());
    }
    let what = if per_box == 1 { String::new() } else { format!(" ({per_box} per box)") };
    Err(MdError::invalid(
        format!("step message column `{name}`"),
        format!("{len} values for {boxes} boxes; expected {}{what}", boxes * per_box),
    ))
}

/// The f64 column `name` (its bytes, read with [`f64_at`]), refused unless it holds
/// `per_box` values for each of `boxes`.
fn f64s<'a>(name: &str, bytes: &'a [u8], boxes: usize, per_box: usize) -> Result<F64s<'a>, MdError> {
    if !bytes.len().is_multiple_of(8) {
        return Err(MdError::invalid(
            format!("step message column `{name}`"),
            format!("{} bytes: not a whole number of 8-byte doubles", bytes.len()),
        ));
    }
    column(name, bytes.len() / 8, boxes, per_box)?;
    Ok(F64s(bytes))
}

/// A checked f64 column.
struct F64s<'a>(&'a [u8]);

impl F64s<'_> {
    fn at(&self, k: usize) -> f64 {
        f64_at(self.0, k)
    }
}

/// The work of a step message, every value checked (a bad one is refused naming the point
/// and the field, a column of the wrong length naming the column).
pub fn batch_from_pb(p: &pb::StepBatch) -> Result<Vec<BoxWork>, MdError> {
    let n = p.point_id.len();
    let velocity_gradient = f64s("velocity_gradient", &p.velocity_gradient, n, 9)?;
    column("steps", p.steps.len(), n, 1)?;
    let dt = f64s("dt_ps", &p.dt_ps, n, 1)?;
    let energy = f64s("energy_to_add_ev", &p.energy_to_add_ev, n, 1)?;
    column("stress_sampling", p.stress_sampling.len(), n, 1)?;
    (0..n)
        .map(|k| {
            let id = p.point_id[k];
            let mut l = [[0.0; 3]; 3];
            for j in 0..9 {
                l[j / 3][j % 3] = finite(id, "velocity_gradient", velocity_gradient.at(9 * k + j))?;
            }
            let (steps, dt_ps) = (p.steps[k], dt.at(k));
            if steps > MAX_STEPS_PER_CALL {
                return Err(invalid(id, "steps", format!("{steps} exceeds {MAX_STEPS_PER_CALL}")));
            }
            if !(dt_ps.is_finite() && dt_ps > 0.0 && dt_ps <= 0.01) {
                return Err(invalid(id, "dt_ps", format!("{dt_ps} ps; expected (0, 0.01]")));
            }
            Ok(BoxWork {
                id,
                velocity_gradient: l,
                steps,
                dt_ps,
                energy_to_add_ev: finite(id, "energy_to_add_ev", energy.at(k))?,
                stress_sampling: sampling_from_pb(id, p.stress_sampling[k])?,
            })
        })
        .collect()
}

/// The reply to one step message (column-oriented, as [`batch_to_pb`]).
pub fn results_to_pb(step: u64, results: &[BoxResult], compute_seconds: f64) -> pb::StepResults {
    pb::StepResults {
        step,
        compute_seconds,
        point_id: results.iter().map(|r| r.id).collect(),
        stress_gpa: f64_column(results.iter().map(|r| r.stress_gpa)),
        potential_energy_ev: f64_column(results.iter().map(|r| [r.potential_energy_ev])),
        kinetic_energy_ev: f64_column(results.iter().map(|r| [r.kinetic_energy_ev])),
        temperature_k: f64_column(results.iter().map(|r| [r.temperature_k])),
        lengths: f64_column(results.iter().map(|r| r.diagnostics.lengths_a)),
        neighbor_rebuilds: results.iter().map(|r| r.diagnostics.neighbor_rebuilds).collect(),
        energy_shortfall_ev: f64_column(results.iter().map(|r| [r.diagnostics.energy_shortfall_ev])),
        total_steps: results.iter().map(|r| r.diagnostics.total_steps).collect(),
        wraps: results.iter().map(|r| r.diagnostics.wraps).collect(),
        stress_sampling: results.iter().map(|r| sampling_to_pb(r.stress_sampling)).collect(),
    }
}

/// The results of a reply (a column of the wrong length is refused naming the column; the
/// values are checked by [`check_result`], which names the worker).
pub fn results_from_pb(p: &pb::StepResults) -> Result<Vec<BoxResult>, MdError> {
    let n = p.point_id.len();
    let stress = f64s("stress_gpa", &p.stress_gpa, n, 6)?;
    let pe = f64s("potential_energy_ev", &p.potential_energy_ev, n, 1)?;
    let ke = f64s("kinetic_energy_ev", &p.kinetic_energy_ev, n, 1)?;
    let temperature = f64s("temperature_k", &p.temperature_k, n, 1)?;
    let lengths = f64s("lengths", &p.lengths, n, 3)?;
    column("neighbor_rebuilds", p.neighbor_rebuilds.len(), n, 1)?;
    let shortfall = f64s("energy_shortfall_ev", &p.energy_shortfall_ev, n, 1)?;
    column("total_steps", p.total_steps.len(), n, 1)?;
    column("wraps", p.wraps.len(), n, 1)?;
    column("stress_sampling", p.stress_sampling.len(), n, 1)?;
    (0..n)
        .map(|k| {
            let id = p.point_id[k];
            Ok(BoxResult {
                id,
                stress_gpa: std::array::from_fn(|j| stress.at(6 * k + j)),
                potential_energy_ev: pe.at(k),
                kinetic_energy_ev: ke.at(k),
                temperature_k: temperature.at(k),
                stress_sampling: sampling_from_pb(id, p.stress_sampling[k])?,
                diagnostics: Diagnostics {
                    total_steps: p.total_steps[k],
                    lengths_a: std::array::from_fn(|j| lengths.at(3 * k + j)),
                    energy_shortfall_ev: shortfall.at(k),
                    neighbor_rebuilds: p.neighbor_rebuilds[k],
                    wraps: p.wraps[k],
                },
            })
        })
        .collect()
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
    fn step_messages_round_trip_and_refuse_a_column_of_the_wrong_length() {
        use prost::Message;
        let mut work: Vec<BoxWork> =
            (0..3).map(|i| BoxWork::new(10 + i, [[0.1 * i as f64, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, -9.0]], 5 + i, 0.002)).collect();
        work[1].energy_to_add_ev = -0.25;
        work[2].stress_sampling = StressSampling::Average;
        let bytes = batch_to_pb(4, 17, &work).encode_to_vec();
        let back = pb::StepBatch::decode(&bytes[..]).unwrap();
        assert_eq!((back.session, back.step), (4, 17));
        assert_eq!(batch_from_pb(&back).unwrap(), work);
        let mut short = back.clone();
        short.velocity_gradient.truncate(26 * 8);
        let e = batch_from_pb(&short).unwrap_err().to_string();
        assert!(e.contains("column `velocity_gradient`") && e.contains("26 values for 3 boxes; expected 27 (9 per box)"), "{e}");
        short.velocity_gradient.pop();
        let e = batch_from_pb(&short).unwrap_err().to_string();
        assert!(e.contains("column `velocity_gradient`") && e.contains("207 bytes: not a whole number"), "{e}");
        let mut nan = back;
        nan.velocity_gradient[8 * (9 + 4)..8 * (9 + 5)].copy_from_slice(&f64::NAN.to_le_bytes());
        let e = batch_from_pb(&nan).unwrap_err().to_string();
        assert!(e.contains("point 11 field `velocity_gradient`") && e.contains("NaN"), "{e}");

        let results: Vec<BoxResult> = work
            .iter()
            .map(|w| BoxResult {
                id: w.id,
                stress_gpa: std::array::from_fn(|k| w.id as f64 - k as f64),
                potential_energy_ev: -3.5,
                kinetic_energy_ev: 0.04 * w.id as f64,
                temperature_k: 300.0,
                stress_sampling: w.stress_sampling,
                diagnostics: Diagnostics {
                    total_steps: w.steps,
                    lengths_a: [18.0, 18.5, w.id as f64],
                    energy_shortfall_ev: 0.0,
                    neighbor_rebuilds: 2,
                    wraps: 1,
                },
            })
            .collect();
        let bytes = results_to_pb(17, &results, 0.5).encode_to_vec();
        let back = pb::StepResults::decode(&bytes[..]).unwrap();
        assert_eq!((back.step, back.compute_seconds), (17, 0.5));
        assert_eq!(results_from_pb(&back).unwrap(), results);
        let mut long = back;
        long.wraps.push(0);
        let e = results_from_pb(&long).unwrap_err().to_string();
        assert!(e.contains("column `wraps`") && e.contains("4 values for 3 boxes; expected 3"), "{e}");
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
