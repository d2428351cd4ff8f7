//! The direct-MD reference of the Cu shock bar agrees with the single periodic box the coupled
//! run gives each point: the pre-compressed state's sigma_xx, sigma_yy at t = 0.

use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind, MdBackend, Potential, ReferenceBackend};
use mscale_tests::repo;
use std::sync::Arc;

fn box_stress(strain: f64) -> [f64; 6] {
    let pot = Arc::new(Potential::from_file(&repo().join("md-worker/potentials/Cu_mishin1.eam.alloy")).expect("potential"));
    let mut md = ReferenceBackend::new(pot);
    let mut spec = BoxSpec::lattice(0, LatticeKind::Fcc, 3.615, [2, 2, 2]);
    spec.strain = [strain, 0.0, 0.0];
    md.open(&[spec]).expect("open");
    let mut out = [BoxResult::default()];
    md.step(&[BoxWork::new(0, [[0.0; 3]; 3], 0, 0.001)], &mut out).expect("step");
    out[0].stress_gpa
}

#[test]
fn direct_bar_matches_the_box_of_each_point() {
    let text = std::fs::read_to_string(repo().join("tests/golden/cu-shock-1d/direct-bar.csv")).expect("golden");
    let rows: Vec<Vec<f64>> = text.lines().skip(1).map(|l| l.split(',').map(|v| v.parse().expect("number")).collect()).collect();
    let at0: Vec<&Vec<f64>> = rows.iter().filter(|r| r[0] == 0.0).collect();
    // Slabs well inside each region (reference x in nm): compressed 10-45, relaxed 65-100.
    let mean = |lo: f64, hi: f64, c: usize| {
        let v: Vec<f64> = at0.iter().filter(|r| r[1] > lo && r[1] < hi).map(|r| r[c]).collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let compressed = box_stress(-0.05);
    let relaxed = box_stress(0.0);
    for (c, k) in [(2usize, 0usize), (3, 1)] {
        let (direct_c, direct_r) = (mean(10.0, 45.0, c), mean(65.0, 100.0, c));
        assert!((direct_c - compressed[k]).abs() < 0.01 * compressed[k].abs(), "compressed component {k}: direct {direct_c} vs box {}", compressed[k]);
        assert!((direct_r - relaxed[k]).abs() < 0.02, "relaxed component {k}: direct {direct_r} vs box {}", relaxed[k]);
    }
}
