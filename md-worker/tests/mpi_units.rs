//! Unit-level tests of `md_worker::mpi` (cargo feature `mpi`) that need no `mpirun`: how boxes
//! are spread over ranks, and the encoding ranks exchange. The multi-rank end-to-end checks are
//! in the workspace's tests/mpi.rs.

use md_worker::mpi::{decode, encode, partition};
use md_worker::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use std::sync::Arc;

fn blocks(ids: &[PointId], ranks: usize) -> Vec<Vec<PointId>> {
    let owner = partition(ids, ranks);
    let mut out = vec![Vec::new(); ranks];
    for (id, r) in ids.iter().zip(owner) {
        out[r].push(*id);
    }
    for b in &mut out {
        b.sort_unstable();
    }
    out
}

#[test]
fn partition_cuts_sorted_ids_into_contiguous_nearly_equal_blocks() {
    let ids: Vec<PointId> = vec![40, 3, 17, 8, 99, 23, 5];
    let b = blocks(&ids, 3);
    assert_eq!(b, vec![vec![3, 5, 8], vec![17, 23], vec![40, 99]]);
    // Sizes differ by at most one, larger blocks first, every id of block r below every id of
    // block r + 1 (contiguous in id order), for many sizes and rank counts.
    for n in 0..40u64 {
        for ranks in 1..9 {
            let ids: Vec<PointId> = (0..n).map(|i| 1000 - 7 * i).collect();
            let b = blocks(&ids, ranks);
            let sizes: Vec<usize> = b.iter().map(Vec::len).collect();
            assert_eq!(sizes.iter().sum::<usize>(), n as usize);
            let (lo, hi) = (sizes.iter().min().copied().unwrap_or(0), sizes.iter().max().copied().unwrap_or(0));
            assert!(hi - lo <= 1, "n {n} ranks {ranks}: {sizes:?}");
            assert!(sizes.windows(2).all(|w| w[0] >= w[1]), "larger blocks first: {sizes:?}");
            let nonempty: Vec<&Vec<PointId>> = b.iter().filter(|v| !v.is_empty()).collect();
            for w in nonempty.windows(2) {
                assert!(w[0].last() < w[1].first(), "contiguous: {b:?}");
            }
        }
    }
}

#[test]
fn partition_depends_only_on_the_set_of_ids() {
    let ids: Vec<PointId> = (0..25).map(|i| (i * 37) % 101).collect();
    let mut rev = ids.clone();
    rev.reverse();
    assert_eq!(blocks(&ids, 4), blocks(&rev, 4));
    assert_eq!(partition(&ids, 4), partition(&ids, 4));
    // One rank owns everything; more ranks than boxes leaves the last ranks empty.
    assert!(partition(&ids, 1).iter().all(|&r| r == 0));
    assert_eq!(partition(&[5, 1], 4), vec![1, 0]);
    assert!(partition(&[], 3).is_empty());
}

#[test]
fn work_and_results_survive_the_encoding_bit_for_bit() {
    // Built through serde so this keeps compiling when the work type gains fields with defaults.
    let work: BoxWork = serde_json::from_value(serde_json::json!({
        "id": 7, "velocity_gradient": [[1e-3, 0.0, 0.0], [0.0, -2.5e-4, 0.0], [0.0, 0.0, 0.1]],
        "steps": 250, "dt_ps": 0.001, "energy_to_add_ev": -0.012345678901234567
    }))
    .expect("work");
    let back: Vec<BoxWork> = decode(&encode(&vec![work; 3]), 1).expect("decode");
    assert_eq!(back, vec![work; 3]);
    let mut r = BoxResult { id: 9, potential_energy_ev: -3.54e3, ..Default::default() };
    // A blown-up box's NaN must arrive as NaN (JSON would turn it into null and fail).
    r.stress_gpa = [f64::NAN, -0.0, 1e-300, f64::INFINITY, 1.0 / 3.0, -7.25];
    let back: Vec<BoxResult> = decode(&encode(&vec![r]), 1).expect("decode");
    assert_eq!(back[0].stress_gpa.map(f64::to_bits), r.stress_gpa.map(f64::to_bits));
    assert_eq!(back[0].potential_energy_ev.to_bits(), r.potential_energy_ev.to_bits());
    assert_eq!(back[0].id, 9);
}

#[test]
fn box_states_and_specs_survive_the_encoding() {
    let pot = Arc::new(md_worker::Potential::LjCut(md_worker::LjCut { epsilon: 0.0104, sigma: 3.4, cutoff: 8.5, mass: 39.95 }));
    let mut spec = BoxSpec::lattice(11, md_worker::LatticeKind::Fcc, 5.26, [2, 2, 2]);
    spec.temperature_k = 40.0;
    spec.seed = 5;
    let mut b = md_worker::CpuBackend::new(pot);
    b.open(std::slice::from_ref(&spec)).expect("open");
    let states = b.snapshot(&[11]).expect("snapshot");
    let back: Vec<BoxState> = decode(&encode(&states), 1).expect("decode");
    assert_eq!(back, states);
    let back: Vec<BoxSpec> = decode(&encode(&vec![spec.clone()]), 0).expect("decode");
    assert_eq!(back, vec![spec]);
}

#[test]
fn garbled_messages_are_refused_naming_the_rank() {
    let e = decode::<Vec<BoxResult>>(&[1, 2, 3], 2).expect_err("garbage");
    assert!(e.to_string().contains("mpi rank 2"), "{e}");
}
