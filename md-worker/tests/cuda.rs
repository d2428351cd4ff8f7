//! CUDA back end without a GPU (feature `cuda`): the kernels compile cleanly with NVRTC for
//! sm_80 and sm_90, and the same kernel source, built as host C++ (`cuda-shim`), agrees with
//! the reference back end. The physics suite runs for `cuda-shim` and `cuda` in physics.rs.
#![cfg(feature = "cuda")]
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::cuda::{Precision, ShimBackend, nvrtc_compile, nvrtc_present};
use md_worker::{BoxResult, BoxSpec, BoxWork, DeformMode, LatticeKind, MdBackend, ReferenceBackend};

#[test]
#[cfg_attr(
    not(require_nvrtc),
    ignore = "needs NVRTC (libnvrtc.so): bash deploy/setup.sh nvrtc, export what it prints; runs with MSCALE_REQUIRE_NVRTC=1 (CI) or -- --ignored"
)]
fn kernels_compile_with_nvrtc_for_sm80_and_sm90_without_warnings() {
    assert!(nvrtc_present(), "NVRTC (libnvrtc.so) not found: run `bash deploy/setup.sh nvrtc` and export the LD_LIBRARY_PATH it prints");
    for arch in ["sm_80", "sm_90"] {
        let out = nvrtc_compile(arch, false).unwrap_or_else(|e| panic!("{e}"));
        assert!(out.log.trim().is_empty(), "NVRTC warnings for {arch}:\n{}", out.log);
        eprintln!("nvrtc {arch}: clean");
    }
    // What the back end loads at run time: PTX for the virtual architecture, with all entries.
    let ptx = nvrtc_compile("compute_90", true).unwrap().ptx.unwrap();
    for entry in ["md_steps_double", "md_steps_mixed", "build_lists"] {
        assert!(ptx.contains(&format!(".entry {entry}")), "PTX lacks {entry}");
    }
}

fn work(id: u64, g: [[f64; 3]; 3], steps: u64) -> BoxWork {
    BoxWork::new(id, g, steps, 0.001)
}

fn shim(p: Precision) -> Box<dyn MdBackend> {
    Box::new(ShimBackend::new(mishin(), p).unwrap())
}

fn run(b: &mut Box<dyn MdBackend>, spec: &BoxSpec, g: [[f64; 3]; 3], steps: u64) -> BoxResult {
    b.open(std::slice::from_ref(spec)).unwrap();
    let mut out = [BoxResult::default()];
    b.step(&[work(spec.id, g, steps)], &mut out).unwrap();
    out[0]
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// Relative differences (energy, stress against its largest component) of two results.
fn rel_diff(a: &BoxResult, b: &BoxResult) -> (f64, f64) {
    let de = (a.potential_energy_ev - b.potential_energy_ev).abs() / b.potential_energy_ev.abs();
    let ds = (0..6).map(|c| (a.stress_gpa[c] - b.stress_gpa[c]).abs()).fold(0.0, f64::max) / max_abs(&b.stress_gpa);
    (de, ds)
}

fn hot(id: u64, cells: usize, t: f64, mode: DeformMode) -> BoxSpec {
    let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [cells; 3]);
    s.temperature_k = t;
    s.seed = 7;
    s.mode = mode;
    s.strain = [0.01, -0.005, 0.0];
    s
}

#[test]
fn double_matches_reference_energy_forces_stress() {
    // A hot perturbed 256-atom box from the LAMMPS golden data, evaluated after 0 and 50 steps.
    let (spec, _) = spec_from_data(3, "cu256_hot.data");
    for steps in [0, 50] {
        let mut r = Box::new(ReferenceBackend::new(mishin())) as Box<dyn MdBackend>;
        let mut s = shim(Precision::Double);
        let g = [[0.02, 0.0, 0.0], [0.0, -0.01, 0.0], [0.0; 3]];
        let (a, b) = (run(&mut s, &spec, g, steps), run(&mut r, &spec, g, steps));
        let (de, ds) = rel_diff(&a, &b);
        let (fa, fb) = (s.snapshot(&[3]).unwrap().remove(0).f, r.snapshot(&[3]).unwrap().remove(0).f);
        let fmax = max_abs(&fb.iter().flatten().copied().collect::<Vec<_>>());
        let df = fa.iter().flatten().zip(fb.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max) / fmax;
        eprintln!("double, {steps} steps: energy {de:e}, stress {ds:e}, forces {df:e} (relative)");
        assert!(de < 1e-10 && ds < 1e-10 && df < 1e-10, "energy {de:e}, stress {ds:e}, forces {df:e}");
        assert!((a.kinetic_energy_ev - b.kinetic_energy_ev).abs() < 1e-10 * b.kinetic_energy_ev);
    }
}

#[test]
fn double_matches_reference_for_small_boxes_seed_mode_and_energy_addition() {
    // 4 atoms (3.6 A, far below twice the cut-off): all images; seed mode with shear wraps.
    let shear = [[0.05, 0.5, -0.3], [0.4, -0.02, 0.6], [0.2, -0.5, 0.01]];
    let mut tiny = BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [1; 3]);
    tiny.strain = [0.01, 0.0, -0.005];
    let stretch = [[0.05, 0.0, 0.0], [0.0; 3], [0.0; 3]];
    let cases = [(tiny, stretch, 100u64), (hot(2, 2, 600.0, DeformMode::Seed), shear, 300)];
    for (spec, g, steps) in cases {
        let mut r = Box::new(ReferenceBackend::new(mishin())) as Box<dyn MdBackend>;
        let mut s = shim(Precision::Double);
        let (a, b) = (run(&mut s, &spec, g, steps), run(&mut r, &spec, g, steps));
        let (de, ds) = rel_diff(&a, &b);
        eprintln!(
            "box {}: {} wraps, {} rebuilds; energy {de:e}, stress {ds:e}",
            spec.id, a.diagnostics.wraps, a.diagnostics.neighbor_rebuilds
        );
        assert!(de < 1e-10 && ds < 1e-9, "box {}: energy {de:e}, stress {ds:e}", spec.id);
        assert_eq!(a.diagnostics.wraps, b.diagnostics.wraps);
        assert_eq!(a.diagnostics.lengths_a, b.diagnostics.lengths_a);
    }
    // Energy addition: scaling a hot box, random velocities for a box at 0 K, removal with shortfall.
    let mut r = Box::new(ReferenceBackend::new(mishin())) as Box<dyn MdBackend>;
    let mut s = shim(Precision::Double);
    let specs = [hot(5, 2, 300.0, DeformMode::Affine), BoxSpec::lattice(6, LatticeKind::Fcc, 3.615, [2; 3])];
    let mut outs = vec![];
    for b in [&mut s, &mut r] {
        b.open(&specs).unwrap();
        let mut out = [BoxResult::default(); 2];
        let w = |id, de| BoxWork { energy_to_add_ev: de, ..work(id, [[0.0; 3]; 3], 20) };
        b.step(&[w(5, 0.3), w(6, 0.5)], &mut out).unwrap();
        let first = out;
        b.step(&[w(5, -100.0), w(6, -0.1)], &mut out).unwrap();
        outs.push((first, out));
    }
    for k in 0..2 {
        for (a, b) in [(outs[0].0[k], outs[1].0[k]), (outs[0].1[k], outs[1].1[k])] {
            let dk = (a.kinetic_energy_ev - b.kinetic_energy_ev).abs();
            assert!(dk < 1e-10 && (a.potential_energy_ev - b.potential_energy_ev).abs() < 1e-9, "{a:?}\n{b:?}");
            assert!((a.diagnostics.energy_shortfall_ev - b.diagnostics.energy_shortfall_ev).abs() < 1e-10);
        }
    }
}

#[test]
fn mixed_stress_within_1e5_after_1000_cold_and_100_hot_steps() {
    // 500 Cu atoms (5x5x5 fcc): 0 K, strained and stretched for 1000 steps; 300 K for 100 steps.
    let mut cold = BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [5; 3]);
    cold.strain = [0.01, 0.0, -0.005];
    let g_cold = [[0.05, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0; 3]];
    let mut warm = hot(2, 5, 300.0, DeformMode::Affine);
    warm.relax_steps = 0;
    let g_hot = [[0.02, 0.0, 0.0], [0.0; 3], [0.0; 3]];
    for (spec, g, steps, tol) in [(cold, g_cold, 1000, 1e-5), (warm, g_hot, 100, 1e-5)] {
        let mut r = Box::new(ReferenceBackend::new(mishin())) as Box<dyn MdBackend>;
        let mut s = shim(Precision::Mixed);
        let (a, b) = (run(&mut s, &spec, g, steps), run(&mut r, &spec, g, steps));
        let (de, ds) = rel_diff(&a, &b);
        eprintln!(
            "mixed, box {} ({} steps, T = {:.1} K): stress {ds:e}, energy {de:e} relative; stress {:?} GPa",
            spec.id, steps, b.temperature_k, b.stress_gpa
        );
        assert!(ds < tol, "box {}: stress differs by {ds:e} relative", spec.id);
        assert!(de < tol, "box {}: energy differs by {de:e} relative", spec.id);
    }
}

#[test]
fn shim_is_deterministic_and_restores_bit_for_bit() {
    let spec = hot(4, 2, 500.0, DeformMode::Seed);
    let g = [[0.02, 0.1, 0.0], [0.0; 3], [0.0; 3]];
    let mut a = shim(Precision::Mixed);
    a.open(std::slice::from_ref(&spec)).unwrap();
    let mut out = [BoxResult::default()];
    a.step(&[work(4, g, 37)], &mut out).unwrap();
    let saved = serde_json::to_string(&a.snapshot(&[4]).unwrap()).unwrap();
    a.step(&[work(4, g, 60)], &mut out).unwrap();
    let mut b = shim(Precision::Mixed);
    b.restore(serde_json::from_str(&saved).unwrap()).unwrap();
    let mut out_b = [BoxResult::default()];
    b.step(&[work(4, g, 60)], &mut out_b).unwrap();
    assert_eq!(out[0].stress_gpa.map(f64::to_bits), out_b[0].stress_gpa.map(f64::to_bits));
    let bits = |st: &md_worker::BoxState| st.x.iter().chain(&st.v).flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.snapshot(&[4]).unwrap()[0]), bits(&b.snapshot(&[4]).unwrap()[0]));
}

#[test]
fn device_cuda_is_a_clear_error_and_auto_falls_back_without_a_gpu() {
    match md_worker::cuda::unavailable_reason() {
        Some(why) => {
            let e = md_worker::device::backend_for_device("cuda", "double", mishin()).err().unwrap();
            assert!(matches!(e, md_worker::MdError::Device(_)), "{e}");
            eprintln!("device cuda: {e} (no GPU here: {why})");
            let b = md_worker::device::backend_for_device("auto", "double", mishin()).unwrap();
            assert_eq!(b.name(), "cpu");
        }
        None => {
            let b = md_worker::device::backend_for_device("auto", "mixed", mishin()).unwrap();
            assert_eq!(b.name(), "cuda-mixed");
        }
    }
    assert!(md_worker::device::backend_for_device("tpu", "double", mishin()).is_err());
}

#[test]
fn a_box_that_blows_up_on_the_shim_is_stopped_naming_the_point() {
    // 1e5 eV added to a 32-atom box (3e3 eV per atom): the CPU back ends stop it at its first
    // step; the cuda back end checks once per call and stops it at the call's end.
    let mut b = shim(Precision::Double);
    b.open(&[BoxSpec::lattice(4, LatticeKind::Fcc, 3.615, [2, 2, 2])]).unwrap();
    let mut w = work(4, [[0.0; 3]; 3], 5);
    w.energy_to_add_ev = 1e5;
    let mut out = [BoxResult::default()];
    let e = b.step(&[w], &mut out).unwrap_err();
    assert!(matches!(e, md_worker::MdError::Diverged { point: 4, .. }), "{e}");
    assert!(e.to_string().contains("mean kinetic energy"), "{e}");
}
