//! Energies, forces, stresses and trajectories against LAMMPS (29 Sep 2021) golden data in
//! tests/golden (regenerate: bash md-worker/scripts/make_golden.sh). Run for every back end.
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::{BoxResult, BoxWork};

fn check_eval(backend: &str, case: &str) {
    let g = golden(case);
    let pot = potential(&g.potential);
    let (spec, _) = spec_from_data(7, &g.data);
    let mut b = make_backend(backend, pot);
    b.open(&[spec]).unwrap();
    let mut out = [BoxResult::default()];
    let work = BoxWork::new(7, [[0.0; 3]; 3], 0, 0.001);
    b.step(&[work], &mut out).unwrap();
    let r = out[0];
    let t = &g.thermo[0];
    assert!(rel_close(r.potential_energy_ev, t[1], t[1], 1e-9), "{case}: pe {} vs lammps {}", r.potential_energy_ev, t[1]);
    assert!(rel_close(r.kinetic_energy_ev, t[2], t[2], 1e-9), "{case}: ke {} vs lammps {}", r.kinetic_energy_ev, t[2]);
    let want: Vec<f64> = t[3..9].iter().map(|p| bar_to_stress(*p)).collect();
    let smax = want.iter().fold(0.0f64, |m, s| m.max(s.abs()));
    for c in 0..6 {
        assert!(rel_close(r.stress_gpa[c], want[c], smax, 1e-9), "{case}: stress[{c}] {} vs lammps {}", r.stress_gpa[c], want[c]);
    }
    let st = b.snapshot(&[7]).unwrap().remove(0);
    let fmax = g.atoms.iter().flat_map(|a| a[8..11].to_vec()).fold(0.0f64, |m, f| m.max(f.abs()));
    let mut worst = 0.0f64;
    for (k, a) in g.atoms.iter().enumerate() {
        for d in 0..3 {
            worst = worst.max((st.f[k][d] - a[8 + d]).abs() / fmax);
        }
    }
    eprintln!("{case}: pe rel err {:e}, worst force err {worst:e} of max force", (r.potential_energy_ev - t[1]).abs() / t[1].abs());
    assert!(worst < 1e-9, "{case}: worst force error {worst:e} of max force {fmax}");
}

fn check_trajectory(backend: &str, case: &str) {
    let g = golden(case);
    let pot = potential(&g.potential);
    let (spec, data) = spec_from_data(3, &g.data);
    let mut grad = [[0.0; 3]; 3];
    if g.deform != "none" {
        let w: Vec<&str> = g.deform.split_whitespace().collect();
        for c in w.chunks(3) {
            assert_eq!(c[1], "trate");
            let d = (c[0].as_bytes()[0] - b'x') as usize;
            grad[d][d] = c[2].parse().unwrap();
        }
    }
    let mut b = make_backend(backend, pot);
    b.open(&[spec]).unwrap();
    let every = (g.thermo[1][0] - g.thermo[0][0]) as u64;
    let mut out = [BoxResult::default()];
    for t in &g.thermo[1..] {
        let work = BoxWork::new(3, grad, every, 0.001);
        b.step(&[work], &mut out).unwrap();
        let r = out[0];
        let step = t[0];
        assert!(rel_close(r.potential_energy_ev, t[1], t[1], 1e-6), "{case} step {step}: pe {} vs {}", r.potential_energy_ev, t[1]);
        assert!(rel_close(r.kinetic_energy_ev, t[2], t[2], 1e-6), "{case} step {step}: ke {} vs {}", r.kinetic_energy_ev, t[2]);
        let want: Vec<f64> = t[3..9].iter().map(|p| bar_to_stress(*p)).collect();
        let smax = want.iter().fold(0.0f64, |m, s| m.max(s.abs()));
        for c in 0..6 {
            assert!(rel_close(r.stress_gpa[c], want[c], smax, 1e-6), "{case} step {step}: stress[{c}] {} vs {}", r.stress_gpa[c], want[c]);
        }
        if t[0] == g.thermo.last().unwrap()[0] {
            let e = (0..6).map(|c| (r.stress_gpa[c] - want[c]).abs() / smax).fold(0.0f64, f64::max);
            eprintln!("{case} step {step}: pe rel err {:e}, stress rel err {e:e}", (r.potential_energy_ev - t[1]).abs() / t[1].abs());
        }
        for d in 0..3 {
            assert!(rel_close(r.diagnostics.lengths_a[d], t[9 + d], t[9 + d], 1e-12), "{case}: box length {d}");
        }
    }
    // Final positions (modulo the box) and velocities.
    let st = b.snapshot(&[3]).unwrap().remove(0);
    let l = st.meta.l;
    let vmax = g.atoms.iter().flat_map(|a| a[5..8].to_vec()).fold(0.0f64, |m, v| m.max(v.abs()));
    for (k, a) in g.atoms.iter().enumerate() {
        assert_eq!(a[0] as u64, data.ids[k]);
        for d in 0..3 {
            let mut dx = st.x[k][d] - a[2 + d];
            dx -= (dx / l[d]).round() * l[d];
            assert!(dx.abs() < 1e-6, "{case}: atom {} position {d} off by {dx:e}", a[0]);
            assert!((st.v[k][d] - a[5 + d]).abs() < 1e-6 * vmax, "{case}: atom {} velocity", a[0]);
        }
    }
}

fn eval_mishin(backend: &str) {
    for c in ["cu108_hot", "cu256_strained", "cu256_hot"] {
        check_eval(backend, &format!("eval_mishin_{c}.golden"));
    }
}

fn eval_funcfl_u3(backend: &str) {
    for c in ["cu108_hot", "cu256_strained", "cu256_hot"] {
        check_eval(backend, &format!("eval_u3_{c}.golden"));
    }
}

fn nve_trajectory_300_steps(backend: &str) {
    check_trajectory(backend, "nve_mishin_cu108_hot.golden");
    check_trajectory(backend, "nve_u3_cu108_hot.golden");
}

fn affine_deformation_trajectory_300_steps(backend: &str) {
    check_trajectory(backend, "affine_mishin_cu256_strained.golden");
    check_trajectory(backend, "affine_u3_cu256_strained.golden");
}

for_each_backend!(eval_mishin, eval_funcfl_u3, nve_trajectory_300_steps, affine_deformation_trajectory_300_steps);
