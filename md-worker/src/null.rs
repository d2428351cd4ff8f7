//! A back end that does no MD: boxes are ids with fixed lengths, every step returns zero
//! stress. It measures what the coupling itself costs (batching, serialisation, transfer,
//! scheduling) without MD work in the way (`md-worker bench-coupling`, src/coupling_bench.rs).

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
#[derive(Default)]
pub struct NullBackend {
    lengths: crate::ids::IdMap<[f64; 3]>,
}

impl MdBackend for NullBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
        for s in specs {
            let l = match &s.atoms {
                crate::InitialAtoms::Lattice { a0, cells, orient, .. } => {
                    std::array::from_fn(|k| a0 * orient.period(k) * cells[k] as f64 * (1.0 + s.strain[k]))
                }
                crate::InitialAtoms::Explicit { lengths, .. } => *lengths,
            };
            self.lengths.insert(s.id, l);
        }
        Ok(())
    }
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        for (w, r) in work.iter().zip(out.iter_mut()) {
            let l = *self.lengths.get(&w.id).ok_or(MdError::UnknownBox(w.id))?;
            *r = BoxResult::default();
            r.id = w.id;
            r.diagnostics.lengths_a = l;
            r.diagnostics.total_steps = w.steps;
            r.stress_sampling = w.stress_sampling;
        }
        Ok(())
    }
    fn snapshot(&self, _ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        Err(MdError::Unsupported("snapshots of the null back end".into()))
    }
    fn restore(&mut self, _states: Vec<BoxState>) -> Result<(), MdError> {
        Err(MdError::Unsupported("restoring the null back end".into()))
    }
    fn name(&self) -> &'static str {
        "null"
    }
}
