//! The direct-MD reference of the Cu shock bar agrees with the single periodic box the coupled
//! run gives each point: the pre-compressed state's sigma_xx, sigma_yy at t = 0. The main job
//! (`scenes/cu-shock-1d.toml`) names that reference and models the bar it was computed for.

use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind, MdBackend, Potential, ReferenceBackend};
use mscale_tests::repo;
use std::sync::Arc;

fn box_stress(strain: f64) -> [f64; 6] {
    box_stress_of(strain, 2)
}

/// Stress (GPa) of a perfect fcc Mishin Cu box of `cells`^3 cells under `strain` along x.
fn box_stress_of(strain: f64, cells: usize) -> [f64; 6] {
    let pot = Arc::new(Potential::from_file(&repo().join("md-worker/potentials/Cu_mishin1.eam.alloy")).expect("potential"));
    let mut md = ReferenceBackend::new(pot);
    let mut spec = BoxSpec::lattice(0, LatticeKind::Fcc, 3.615, [cells, cells, cells]);
    spec.strain = [strain, 0.0, 0.0];
    md.open(&[spec]).expect("open");
    let mut out = [BoxResult::default()];
    md.step(&[BoxWork::new(0, [[0.0; 3]; 3], 0, 0.001)], &mut out).expect("step");
    out[0].stress_gpa
}

#[test]
fn direct_bar_matches_the_box_of_each_point() {
    check_boxes_against_the_direct_bar(box_stress(-0.05), box_stress(0.0));
}

/// Mean sigma_xx, sigma_yy of the direct bar at t = 0 in slabs well inside each region
/// (reference x in nm): compressed 10-45, relaxed 65-100; against the boxes' stresses.
fn check_boxes_against_the_direct_bar(compressed: [f64; 6], relaxed: [f64; 6]) {
    let text = std::fs::read_to_string(repo().join("tests/golden/cu-shock-1d/direct-bar.csv")).expect("golden");
    let rows: Vec<Vec<f64>> = text.lines().skip(1).map(|l| l.split(',').map(|v| v.parse().expect("number")).collect()).collect();
    let at0: Vec<&Vec<f64>> = rows.iter().filter(|r| r[0] == 0.0).collect();
    let mean = |lo: f64, hi: f64, c: usize| {
        let v: Vec<f64> = at0.iter().filter(|r| r[1] > lo && r[1] < hi).map(|r| r[c]).collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    for (c, k) in [(2usize, 0usize), (3, 1)] {
        let (direct_c, direct_r) = (mean(10.0, 45.0, c), mean(65.0, 100.0, c));
        assert!(
            (direct_c - compressed[k]).abs() < 0.01 * compressed[k].abs(),
            "compressed component {k}: direct {direct_c} vs box {}",
            compressed[k]
        );
        assert!((direct_r - relaxed[k]).abs() < 0.02, "relaxed component {k}: direct {direct_r} vs box {}", relaxed[k]);
    }
}

#[test]
fn the_main_job_names_the_0k_direct_bar_it_models() {
    use orchestrator::scene::{self, Material, Reference};
    let l = scene::load(&repo().join("scenes/cu-shock-1d.toml"), &[]).expect("scenes/cu-shock-1d.toml");
    let Some(Reference::DirectMd(r)) = &l.scene.reference else {
        panic!("the main job names no direct-md reference: {:?}", l.scene.reference)
    };
    let golden = repo().join("tests/golden/cu-shock-1d/direct-bar.csv").canonicalize().expect("golden");
    assert_eq!(r.profile, golden, "the main job must be scored against the 0 K bar");
    assert_eq!((r.component.as_str(), r.times_ps.as_slice()), ("sxx", [5.0, 10.0].as_slice()));
    // The direct bar is at 0 K (`md-worker direct` without --temperature): so is every body.
    for (name, b) in &l.scene.bodies {
        assert_eq!(b.temperature_k, 0.0, "body {name}");
    }
    // The bar of the direct run: 150 + 150 fcc cells of 3.615 A along x, the left half
    // pre-compressed by 5 % (`--region 0:542.25:-0.05`). In the reference coordinate the
    // scene's interface and far end lie where the direct bar's do (the grid puts the interface
    // on a cell boundary).
    let map = orchestrator::report::ReferenceMap::of(&l.scene).expect("map");
    let (c, rel) = (&l.scene.bodies["compressed"], &l.scene.bodies["relaxed"]);
    assert_eq!(c.initial_strain[0], -0.05);
    assert!((map.x_ref(c.max[0]) - 54.225e-9).abs() < 1e-15, "interface at X = {:e} m", map.x_ref(c.max[0]));
    assert!((map.x_ref(rel.max[0]) - 108.45e-9).abs() < 1e-15, "far end at X = {:e} m", map.x_ref(rel.max[0]));
    let h = l.scene.domain.cell_size[0];
    let k = c.max[0] / h;
    assert!((k - k.round()).abs() < 1e-6, "the interface {:e} m is not on a cell boundary (h = {h:e} m)", c.max[0]);
    // The scene's own boxes give the direct bar's initial stresses.
    let cells = |b: &scene::Body| match &b.material {
        Material::Md(m) => m.cells_per_side,
        other => panic!("the main job's bodies are md, not {}", other.law()),
    };
    check_boxes_against_the_direct_bar(box_stress_of(-0.05, cells(c)), box_stress_of(0.0, cells(rel)));
}
