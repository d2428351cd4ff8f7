//! A back end that does no MD: boxes are ids with fixed lengths, every step returns zero
//! stress. It measures what the coupling itself costs (batching, serialisation, transfer,
//! scheduling) without MD work in the way (`md-worker bench-coupling`, src/coupling_bench.rs).

use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
use crate::kernel::{BoxMeta, DeformMode};
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
    /// A box's whole state here is its lengths: a state without atoms carrying them, so
    /// checkpoints, and the restore of a lost worker's boxes, work as with any back end (the
    /// chaos test kills null workers mid-job, orchestrator/tests/chaos.rs).
    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        ids.iter()
            .map(|id| {
                let l = *self.lengths.get(id).ok_or(MdError::UnknownBox(*id))?;
                let meta = BoxMeta {
                    id: *id,
                    lo: [0.0; 3],
                    l,
                    lo_build: [0.0; 3],
                    l_build: l,
                    mode: DeformMode::default(),
                    seed: 0,
                    skin: 0.0,
                    step: 0,
                    pe: 0.0,
                    virial: [0.0; 6],
                    rebuilds: 0,
                };
                Ok(BoxState { meta, types: Vec::new(), x: Vec::new(), v: Vec::new(), f: Vec::new(), x_build: Vec::new(), img: Vec::new() })
            })
            .collect()
    }
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        for s in &states {
            if !s.meta.l.iter().all(|l| l.is_finite() && *l > 0.0) {
                return Err(MdError::invalid(
                    "box state",
                    format!("box {}: lengths {:?} are not positive and finite", s.meta.id, s.meta.l),
                ));
            }
        }
        for s in states {
            self.lengths.insert(s.meta.id, s.meta.l);
        }
        Ok(())
    }
    fn name(&self) -> &'static str {
        "null"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::BoxSpec;
    use crate::lattice::LatticeKind;

    /// The state of a box moves to another null back end and answers as before there; a
    /// state with non-finite lengths is refused.
    #[test]
    fn a_null_box_snapshot_restores_elsewhere_and_bad_lengths_are_refused() {
        let mut a = NullBackend::default();
        let mut s = BoxSpec::lattice(7, LatticeKind::Fcc, 3.615, [2, 3, 4]);
        s.strain = [0.01, 0.0, -0.02];
        a.open(&[s]).unwrap();
        let states = a.snapshot(&[7]).unwrap();
        assert!(a.snapshot(&[8]).is_err());
        let mut b = NullBackend::default();
        b.restore(states.clone()).unwrap();
        let work = [BoxWork::new(7, [[0.0; 3]; 3], 3, 0.001)];
        let (mut ra, mut rb) = ([BoxResult::default()], [BoxResult::default()]);
        a.step(&work, &mut ra).unwrap();
        b.step(&work, &mut rb).unwrap();
        assert_eq!(ra[0].diagnostics.lengths_a, rb[0].diagnostics.lengths_a);
        assert!((ra[0].diagnostics.lengths_a[0] - 3.615 * 2.0 * 1.01).abs() < 1e-12, "{:?}", ra[0].diagnostics.lengths_a);
        let mut bad = states;
        bad[0].meta.l[1] = f64::NAN;
        assert!(NullBackend::default().restore(bad).is_err());
    }
}
