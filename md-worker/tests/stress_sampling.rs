//! Stress sampling (`BoxWork::stress_sampling`): `average` is the mean of the stresses after
//! each MD step of a call, `last` the stress after its last step; run for every back end.
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::{BoxResult, BoxSpec, BoxWork, DeformMode, LatticeKind, MdBackend, StressSampling};

/// A hot, strained 108-atom Cu box (thermal noise makes every step's stress different).
fn hot_box(mode: DeformMode) -> BoxSpec {
    let mut s = BoxSpec::lattice(3, LatticeKind::Fcc, 3.615, [3; 3]);
    s.temperature_k = 300.0;
    s.seed = 11;
    s.mode = mode;
    s.strain = [0.01, -0.005, 0.0];
    s
}

fn gradient(mode: DeformMode) -> [[f64; 3]; 3] {
    match mode {
        DeformMode::Affine => [[0.05, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0; 3]],
        // Seed mode takes shear too.
        DeformMode::Seed => [[0.05, 0.03, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.01]],
    }
}

/// A fresh back end holding the box (fresh so that every run starts from the same state).
fn opened(backend: &str, spec: &BoxSpec) -> Box<dyn MdBackend> {
    let mut b = make_backend(backend, mishin());
    b.open(std::slice::from_ref(spec)).unwrap();
    b
}

fn call(b: &mut Box<dyn MdBackend>, spec: &BoxSpec, steps: u64, sampling: StressSampling) -> BoxResult {
    let w = BoxWork { stress_sampling: sampling, ..BoxWork::new(spec.id, gradient(spec.mode), steps, 0.001) };
    let mut out = [BoxResult::default()];
    b.step(&[w], &mut out).unwrap();
    assert_eq!(out[0].stress_sampling, sampling, "the result echoes the sampling");
    out[0]
}

fn bits(s: &[f64; 6]) -> [u64; 6] {
    s.map(f64::to_bits)
}

fn one_step_and_zero_steps_average_equal_last(backend: &str) {
    for mode in [DeformMode::Affine, DeformMode::Seed] {
        let spec = hot_box(mode);
        for steps in [0, 1] {
            let last = call(&mut opened(backend, &spec), &spec, steps, StressSampling::Last);
            let avg = call(&mut opened(backend, &spec), &spec, steps, StressSampling::Average);
            assert_eq!(bits(&avg.stress_gpa), bits(&last.stress_gpa), "{mode:?}, {steps} step(s): {avg:?} vs {last:?}");
        }
    }
}

fn average_is_the_mean_of_the_per_step_stresses(backend: &str) {
    const N: u64 = 20;
    for mode in [DeformMode::Affine, DeformMode::Seed] {
        let spec = hot_box(mode);
        let avg = call(&mut opened(backend, &spec), &spec, N, StressSampling::Average);
        let last = call(&mut opened(backend, &spec), &spec, N, StressSampling::Last);
        // Sampling changes what is returned, not the trajectory: the end-of-call state is the same.
        assert_eq!(avg.potential_energy_ev.to_bits(), last.potential_energy_ev.to_bits(), "{mode:?}");
        assert_eq!(avg.kinetic_energy_ev.to_bits(), last.kinetic_energy_ev.to_bits(), "{mode:?}");
        assert_eq!(avg.temperature_k.to_bits(), last.temperature_k.to_bits(), "{mode:?}");
        assert_eq!(avg.diagnostics, last.diagnostics, "{mode:?}");
        // The same box stepped one MD step per call: the mean of its stresses, summed in order.
        // (Each call starts from a fresh neighbour list, so the trajectory agrees only to
        // round-off.)
        let mut b = opened(backend, &spec);
        let mut sum = [0.0; 6];
        let mut each = Vec::new();
        for _ in 0..N {
            let r = call(&mut b, &spec, 1, StressSampling::Last);
            each.push(r.stress_gpa);
            for c in 0..6 {
                sum[c] += r.stress_gpa[c];
            }
        }
        let mean = sum.map(|s| s / N as f64);
        let scale = mean.iter().fold(0.0f64, |m, s| m.max(s.abs()));
        let off = (0..6).map(|c| (avg.stress_gpa[c] - mean[c]).abs()).fold(0.0, f64::max);
        let from_last = (0..6).map(|c| (avg.stress_gpa[c] - last.stress_gpa[c]).abs()).fold(0.0, f64::max);
        let spread = (0..6)
            .map(|c| each.iter().map(|s| s[c]).fold(f64::NEG_INFINITY, f64::max) - each.iter().map(|s| s[c]).fold(f64::INFINITY, f64::min))
            .fold(0.0, f64::max);
        eprintln!(
            "{backend} {mode:?}: |average - mean of steps| = {off:e} GPa, |average - last| = {from_last:e} GPa, per-step spread {spread:e} GPa (scale {scale:e})"
        );
        assert!(off <= 1e-9 * scale, "{mode:?}: average {:?} vs per-step mean {mean:?}", avg.stress_gpa);
        assert!(from_last > 1e-4 * scale, "{mode:?}: the average of a deformed hot box should differ from the last stress");
        // The last stresses of both ways agree too (a check on the comparison itself).
        let last_off = (0..6).map(|c| (last.stress_gpa[c] - each[N as usize - 1][c]).abs()).fold(0.0, f64::max);
        assert!(last_off <= 1e-9 * scale, "{mode:?}: last {:?} vs {:?}", last.stress_gpa, each[N as usize - 1]);
    }
}

fn the_two_samplings_mix_in_one_batch(backend: &str) {
    // Two copies of the box in one call (distinct ids draw distinct velocities, so compare
    // each with its own single-box run).
    let (mut a, mut b) = (hot_box(DeformMode::Affine), hot_box(DeformMode::Affine));
    a.id = 1;
    b.id = 2;
    let mut both = make_backend(backend, mishin());
    both.open(&[a.clone(), b.clone()]).unwrap();
    let g = gradient(DeformMode::Affine);
    let work = [
        BoxWork { stress_sampling: StressSampling::Average, ..BoxWork::new(1, g, 10, 0.001) },
        BoxWork { stress_sampling: StressSampling::Last, ..BoxWork::new(2, g, 10, 0.001) },
    ];
    let mut out = [BoxResult::default(); 2];
    both.step(&work, &mut out).unwrap();
    let alone_a = call(&mut opened(backend, &a), &a, 10, StressSampling::Average);
    let alone_b = call(&mut opened(backend, &b), &b, 10, StressSampling::Last);
    assert_eq!(bits(&out[0].stress_gpa), bits(&alone_a.stress_gpa));
    assert_eq!(bits(&out[1].stress_gpa), bits(&alone_b.stress_gpa));
    assert_eq!((out[0].stress_sampling, out[1].stress_sampling), (StressSampling::Average, StressSampling::Last));
}

for_each_backend!(
    one_step_and_zero_steps_average_equal_last,
    average_is_the_mean_of_the_per_step_stresses,
    the_two_samplings_mix_in_one_batch
);

#[test]
fn reference_and_cpu_averages_agree_bit_for_bit() {
    let spec = hot_box(DeformMode::Seed);
    let r = call(&mut opened("reference", &spec), &spec, 15, StressSampling::Average);
    let c = call(&mut opened("cpu2", &spec), &spec, 15, StressSampling::Average);
    assert_eq!(bits(&r.stress_gpa), bits(&c.stress_gpa));
}
