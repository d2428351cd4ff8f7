//! Physics and contract tests, written once and run for every back end.
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::{BoxResult, BoxSpec, BoxState, BoxWork, DeformMode, LatticeKind, MdBackend};

fn work(id: u64, g: [[f64; 3]; 3], steps: u64, de: f64) -> BoxWork {
    BoxWork { energy_to_add_ev: de, ..BoxWork::new(id, g, steps, 0.001) }
}

fn eval0(b: &mut Box<dyn MdBackend>, id: u64) -> BoxResult {
    let mut out = [BoxResult::default()];
    b.step(&[work(id, [[0.0; 3]; 3], 0, 0.0)], &mut out).unwrap();
    out[0]
}

/// Energy per atom and stress of a perfect fcc Cu box (0 K) with the Mishin potential.
fn fcc_state(backend: &str, a0: f64, cells: usize, strain: [f64; 3]) -> (f64, [f64; 6]) {
    let mut b = make_backend(backend, mishin());
    let mut s = BoxSpec::lattice(1, LatticeKind::Fcc, a0, [cells; 3]);
    s.strain = strain;
    b.open(&[s]).unwrap();
    let r = eval0(&mut b, 1);
    (r.potential_energy_ev / (4 * cells * cells * cells) as f64, r.stress_gpa)
}

fn mishin_lattice_constant_and_cohesive_energy(backend: &str) {
    let h = 0.005;
    let e: Vec<f64> = [-h, 0.0, h].iter().map(|d| fcc_state(backend, 3.615 + d, 3, [0.0; 3]).0).collect();
    // Parabola through three points: minimum position.
    let a_min = 3.615 + h * (e[0] - e[2]) / (2.0 * (e[0] - 2.0 * e[1] + e[2]));
    eprintln!("a0 = {a_min} A, E_coh = {} eV/atom", e[1]);
    assert!((a_min - 3.615).abs() < 1e-3, "lattice constant {a_min}");
    assert!((e[1] + 3.54).abs() < 2e-3, "cohesive energy {} eV/atom", e[1]);
    let (_, s) = fcc_state(backend, 3.615, 3, [0.0; 3]);
    assert!(s[0].abs() < 0.05 && (s[0] - s[1]).abs() < 1e-9 && s[3].abs() < 1e-9, "stress at a0 {s:?}");
}

fn box_smaller_than_twice_the_cutoff_sees_all_images(backend: &str) {
    // One fcc cell (3.615 A, 4 atoms) against 4x4x4 cells: same lattice, same energy per atom.
    let (e1, s1) = fcc_state(backend, 3.615, 1, [0.01, 0.0, -0.005]);
    let (e4, s4) = fcc_state(backend, 3.615, 4, [0.01, 0.0, -0.005]);
    assert!((e1 - e4).abs() < 1e-12 * e4.abs(), "{e1} vs {e4}");
    for c in 0..6 {
        assert!((s1[c] - s4[c]).abs() < 1e-9, "stress {c}: {} vs {}", s1[c], s4[c]);
    }
}

fn elastic_constants_c11_c12(backend: &str) {
    let eps = 1e-4;
    let (_, sp) = fcc_state(backend, 3.615, 3, [eps, 0.0, 0.0]);
    let (_, sm) = fcc_state(backend, 3.615, 3, [-eps, 0.0, 0.0]);
    // Engineering strain eps of the box; Cauchy stress, tension positive.
    let c11 = (sp[0] - sm[0]) / (2.0 * eps);
    let c12 = (sp[1] - sm[1]) / (2.0 * eps);
    eprintln!("C11 = {c11} GPa, C12 = {c12} GPa");
    assert!((c11 / 169.9 - 1.0).abs() < 0.005, "C11 = {c11} GPa (Mishin 2001: 169.9)");
    assert!((c12 / 122.6 - 1.0).abs() < 0.005, "C12 = {c12} GPa (Mishin 2001: 122.6)");
}

fn box_relaxes_to_zero_mean_stress(backend: &str) {
    let mut b = make_backend(backend, mishin());
    let mut s = BoxSpec::lattice(1, LatticeKind::Fcc, 3.66, [3; 3]);
    s.strain = [0.0, -0.02, 0.01];
    s.relax_box_blocks = 8;
    b.open(&[s]).unwrap();
    let r = eval0(&mut b, 1);
    let l = r.diagnostics.lengths_a;
    eprintln!("relaxed lengths {l:?}, stress {:?}", r.stress_gpa);
    for d in 0..3 {
        assert!(r.stress_gpa[d].abs() < 0.05, "stress {:?}", r.stress_gpa);
        assert!((l[d] / 3.0 - 3.615).abs() < 1e-3, "lattice constant {}", l[d] / 3.0);
    }
}

fn hot_box(id: u64, cells: usize, t: f64, mode: DeformMode) -> BoxSpec {
    let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [cells; 3]);
    s.temperature_k = t;
    s.seed = 42;
    s.mode = mode;
    s
}

fn nve_energy_conservation(backend: &str) {
    let mut b = make_backend(backend, mishin());
    b.open(&[hot_box(1, 3, 300.0, DeformMode::Affine)]).unwrap();
    let r0 = eval0(&mut b, 1);
    let e0 = r0.potential_energy_ev + r0.kinetic_energy_ev;
    let mut out = [BoxResult::default()];
    let mut worst = 0.0f64;
    for _ in 0..10 {
        b.step(&[work(1, [[0.0; 3]; 3], 100, 0.0)], &mut out).unwrap();
        let e = out[0].potential_energy_ev + out[0].kinetic_energy_ev;
        worst = worst.max((e - e0).abs());
    }
    // 108 atoms, 1000 steps of 1 fs at ~600 K: drift and fluctuation well below 1e-4 eV/atom.
    eprintln!("max |E - E0| over 1000 steps: {worst:e} eV ({:e} eV/atom)", worst / 108.0);
    assert!(worst / 108.0 < 1e-4, "energy error {worst} eV over 1000 steps");
    assert!(out[0].temperature_k > 150.0 && out[0].temperature_k < 600.0, "T = {}", out[0].temperature_k);
}

fn momentum(st: &BoxState) -> [f64; 3] {
    let mut p = [0.0; 3];
    for v in &st.v {
        for d in 0..3 {
            p[d] += v[d];
        }
    }
    p
}

fn momentum_is_conserved(backend: &str) {
    let mut b = make_backend(backend, mishin());
    b.open(&[hot_box(1, 2, 500.0, DeformMode::Affine), hot_box(2, 2, 500.0, DeformMode::Seed)]).unwrap();
    let mut out = [BoxResult::default(); 2];
    let g = [[0.02, 0.0, 0.0], [0.0, -0.01, 0.0], [0.0, 0.0, 0.0]];
    b.step(&[work(1, g, 200, 0.0), work(2, [[0.0; 3]; 3], 200, 0.0)], &mut out).unwrap();
    for st in b.snapshot(&[1, 2]).unwrap() {
        let p = momentum(&st);
        assert!(p.iter().all(|c| c.abs() < 1e-10), "box {}: momentum {p:?}", st.meta.id);
    }
}

fn seed_mode_keeps_every_atom_once_in_the_box(backend: &str) {
    let mut b = make_backend(backend, mishin());
    b.open(&[hot_box(5, 2, 600.0, DeformMode::Seed)]).unwrap();
    let n0 = b.snapshot(&[5]).unwrap()[0].x.len();
    // Full gradient with lower-triangular parts: made upper triangular by (5.20).
    let g = [[0.05, 0.5, -0.3], [0.4, -0.02, 0.6], [0.2, -0.5, 0.01]];
    let mut out = [BoxResult::default()];
    let mut wraps = 0;
    for _ in 0..10 {
        b.step(&[work(5, g, 50, 0.0)], &mut out).unwrap();
        wraps += out[0].diagnostics.wraps;
        let st = b.snapshot(&[5]).unwrap().remove(0);
        assert_eq!(st.x.len(), n0);
        for (k, p) in st.x.iter().enumerate() {
            for d in 0..3 {
                assert!(p[d] >= st.meta.lo[d] && p[d] < st.meta.lo[d] + st.meta.l[d], "atom {k} outside the box: {p:?}");
            }
        }
        // No two atoms coincide modulo the box (each atom appears once).
        for i in 0..st.x.len() {
            for j in 0..i {
                let r2: f64 = (0..3)
                    .map(|d| {
                        let mut dx = st.x[i][d] - st.x[j][d];
                        dx -= (dx / st.meta.l[d]).round() * st.meta.l[d];
                        dx * dx
                    })
                    .sum();
                assert!(r2 > 1.0, "atoms {i} and {j} overlap");
            }
        }
    }
    assert!(wraps > 0, "the test never wrapped an atom");
    let l = out[0].diagnostics.lengths_a;
    let l0 = 2.0 * 3.615;
    // (5.7): L grows by (1 + g_xx dt) every step.
    assert!((l[0] / (l0 * (1.0f64 + 0.05 * 0.001).powi(500)) - 1.0).abs() < 1e-12, "{l:?}");
}

fn energy_added_as_thermal_kinetic_energy(backend: &str) {
    let mut b = make_backend(backend, mishin());
    b.open(&[hot_box(1, 2, 300.0, DeformMode::Affine), BoxSpec::lattice(2, LatticeKind::Fcc, 3.615, [2; 3])]).unwrap();
    let k0 = eval0(&mut b, 1).kinetic_energy_ev;
    let mut out = [BoxResult::default(); 2];
    b.step(&[work(1, [[0.0; 3]; 3], 0, 0.25), work(2, [[0.0; 3]; 3], 0, 0.5)], &mut out).unwrap();
    assert!((out[0].kinetic_energy_ev - (k0 + 0.25)).abs() < 1e-12, "{} vs {}", out[0].kinetic_energy_ev, k0 + 0.25);
    assert!((out[1].kinetic_energy_ev - 0.5).abs() < 1e-12, "0 K box: {}", out[1].kinetic_energy_ev);
    let p = momentum(&b.snapshot(&[2]).unwrap()[0]);
    assert!(p.iter().all(|c| c.abs() < 1e-10), "{p:?}");
    // Removing more than there is: clamp to zero and report the shortfall.
    b.step(&[work(1, [[0.0; 3]; 3], 0, -100.0), work(2, [[0.0; 3]; 3], 0, -0.2)], &mut out).unwrap();
    assert!(out[0].kinetic_energy_ev < 1e-30, "{}", out[0].kinetic_energy_ev);
    assert!((out[0].diagnostics.energy_shortfall_ev - (100.0 - k0 - 0.25)).abs() < 1e-9);
    assert!((out[1].kinetic_energy_ev - 0.3).abs() < 1e-12 && out[1].diagnostics.energy_shortfall_ev == 0.0);
}

fn bits(st: &BoxState) -> Vec<u64> {
    st.x.iter().chain(&st.v).chain(&st.f).flat_map(|p| p.iter().map(|c| c.to_bits())).collect()
}

fn run_batch(backend: &str, order: &[u64]) -> (Vec<BoxResult>, Vec<BoxState>) {
    let mut b = make_backend(backend, mishin());
    let specs: Vec<BoxSpec> =
        (0..4).map(|id| hot_box(id, 2, 400.0, if id % 2 == 0 { DeformMode::Seed } else { DeformMode::Affine })).collect();
    b.open(&specs).unwrap();
    let g = |id: u64| {
        if id.is_multiple_of(2) {
            [[0.01, 0.2, 0.0], [0.0, 0.0, 0.1], [0.0, 0.0, -0.01]]
        } else {
            [[0.03, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -0.01]]
        }
    };
    let w: Vec<BoxWork> = order.iter().map(|&id| work(id, g(id), 60, 0.01 * id as f64)).collect();
    let mut out = vec![BoxResult::default(); w.len()];
    b.step(&w, &mut out).unwrap();
    out.sort_by_key(|r| r.id);
    (out, b.snapshot(&[0, 1, 2, 3]).unwrap())
}

fn bitwise_same_for_any_thread_count_and_order(backend: &str) {
    let (r_ref, s_ref) = run_batch(backend, &[0, 1, 2, 3]);
    // GPU back ends are deterministic but not bitwise equal to the CPU: compare with themselves.
    let others: &[&str] = if backend.starts_with("cuda") { &[backend] } else { &["cpu1", "cpu2", "reference"] };
    for &other in others {
        let (r, s) = run_batch(other, &[3, 1, 0, 2]);
        for (a, b) in r_ref.iter().zip(&r) {
            assert_eq!(a.stress_gpa.map(f64::to_bits), b.stress_gpa.map(f64::to_bits), "{backend} vs {other}");
            assert_eq!(a.potential_energy_ev.to_bits(), b.potential_energy_ev.to_bits());
        }
        for (a, b) in s_ref.iter().zip(&s) {
            assert_eq!(bits(a), bits(b), "{backend} vs {other}: box {}", a.meta.id);
        }
    }
}

fn snapshot_restore_replays_bit_for_bit(backend: &str) {
    let g = [[0.02, 0.1, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]];
    let mut a = make_backend(backend, mishin());
    a.open(&[hot_box(9, 2, 500.0, DeformMode::Seed)]).unwrap();
    let mut out = [BoxResult::default()];
    a.step(&[work(9, g, 37, 0.0)], &mut out).unwrap();
    let saved = serde_json::to_string(&a.snapshot(&[9]).unwrap()).unwrap();
    a.step(&[work(9, g, 80, 0.0)], &mut out).unwrap();
    let mut b = make_backend(backend, mishin());
    b.restore(serde_json::from_str(&saved).unwrap()).unwrap();
    let mut out_b = [BoxResult::default()];
    b.step(&[work(9, g, 80, 0.0)], &mut out_b).unwrap();
    assert_eq!(out[0].stress_gpa.map(f64::to_bits), out_b[0].stress_gpa.map(f64::to_bits));
    assert_eq!(bits(&a.snapshot(&[9]).unwrap()[0]), bits(&b.snapshot(&[9]).unwrap()[0]));
}

fn impossible_box_states_are_refused_on_restore(backend: &str) {
    // Found by fuzz_wire: a restored box length of 5e-324 A overflowed the neighbour-list build.
    let mut a = make_backend(backend, mishin());
    a.open(&[hot_box(4, 2, 300.0, DeformMode::Seed)]).unwrap();
    let good = a.snapshot(&[4]).unwrap().remove(0);
    type Spoil = fn(&mut BoxState);
    let cases: [(&str, Spoil, &str); 7] = [
        ("tiny box", |s| s.meta.l[0] = 5e-324, "box lengths"),
        ("NaN box at the build", |s| s.meta.l_build[2] = f64::NAN, "box lengths at the list build"),
        ("zero skin", |s| s.meta.skin = 0.0, "skin"),
        ("infinite corner", |s| s.meta.lo[1] = f64::INFINITY, "box corner"),
        ("NaN velocity", |s| s.v[3][0] = f64::NAN, "atom 3: velocity"),
        ("far atom", |s| s.x[1][2] = 1e300, "box lengths outside the box"),
        ("short array", |s| _ = s.f.pop(), "differ in length"),
    ];
    for (what, spoil, says) in cases {
        let mut s = good.clone();
        spoil(&mut s);
        let mut b = make_backend(backend, mishin());
        let e = b.restore(vec![s]).expect_err(what).to_string();
        assert!(e.contains("point id 4") && e.contains(says), "{what}: {e}");
    }
    make_backend(backend, mishin()).restore(vec![good]).unwrap();
}

fn bad_requests_are_refused(backend: &str) {
    let mut b = make_backend(backend, mishin());
    b.open(&[hot_box(1, 2, 0.0, DeformMode::Affine)]).unwrap();
    let mut out = [BoxResult::default()];
    let e = b.step(&[work(2, [[0.0; 3]; 3], 1, 0.0)], &mut out).unwrap_err().to_string();
    assert!(e.contains("unknown box"), "{e}");
    let e = b.step(&[work(1, [[0.0, 0.1, 0.0], [0.0; 3], [0.0; 3]], 1, 0.0)], &mut out).unwrap_err().to_string();
    assert!(e.contains("affine"), "{e}");
    let mut w = work(1, [[0.0; 3]; 3], 1, 0.0);
    w.dt_ps = -1.0;
    assert!(b.step(&[w], &mut out).is_err());
    assert!(b.open(&[hot_box(1, 2, 0.0, DeformMode::Affine)]).is_err(), "duplicate id accepted");
}

for_each_backend!(
    mishin_lattice_constant_and_cohesive_energy,
    box_smaller_than_twice_the_cutoff_sees_all_images,
    elastic_constants_c11_c12,
    nve_energy_conservation,
    momentum_is_conserved,
    seed_mode_keeps_every_atom_once_in_the_box,
    energy_added_as_thermal_kinetic_energy,
    bitwise_same_for_any_thread_count_and_order,
    snapshot_restore_replays_bit_for_bit,
    impossible_box_states_are_refused_on_restore,
    bad_requests_are_refused,
    box_relaxes_to_zero_mean_stress,
);
