//! `md-worker direct --dimension 2`: small impact samples (a few nm of fcc Cu on a rigid block).
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::direct::{Bar, ImpactSpec, Notch};
use md_worker::units::FTM2V;
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind};

fn spec(a0: f64, cells: [usize; 3], velocity_y: f64, temperature_k: f64) -> ImpactSpec {
    ImpactSpec {
        kind: LatticeKind::Fcc,
        a0,
        cells,
        block_cells: 3,
        velocity_y,
        notch: None,
        temperature_k,
        seed: 7,
        bin_a: 4.0 * a0,
        skin: 1.0,
        headroom_a: 20.0,
    }
}

fn box_stress(a0: f64) -> [f64; 6] {
    let mut b = make_backend("reference", mishin());
    b.open(&[BoxSpec::lattice(1, LatticeKind::Fcc, a0, [3; 3])]).unwrap();
    let mut out = [BoxResult::default()];
    b.step(&[BoxWork::new(1, [[0.0; 3]; 3], 0, 0.001)], &mut out).unwrap();
    out[0].stress_gpa
}

/// A compressed lattice (a0 = 3.55 A, about -8 GPa) moving as one at -2.5 km/s: the bins far
/// from the free top face hold 4 x 4 x 4 cells each and their stress is the periodic box's
/// virial stress (the streaming velocity removed per bin: it would add rho v^2 ~ 6 GPa to syy).
#[test]
fn bins_of_a_uniform_sample_match_the_periodic_box_stress() {
    let a0 = 3.55;
    let b = Bar::impact(mishin(), &spec(a0, [8, 16, 4], -25.0, 0.0)).unwrap();
    assert_eq!(b.len(), 8 * (16 + 3) * 4 * 4);
    assert_eq!(b.frozen_count(), 8 * 3 * 4 * 4);
    let want = box_stress(a0);
    assert!(want[0] < -5.0, "the compressed box is in compression: {want:?}");
    let s = b.bin_stress();
    assert_eq!((s.nx, s.ny), (2, ((16.0 * a0 + 2.0 * (mishin().cutoff() + 1.0) + 20.0) / (4.0 * a0)).ceil() as usize));
    // Bins of y in [0, 8 a0): more than two cut-offs below the top face at 16 a0.
    for k in 0..2 * s.nx {
        assert_eq!(s.atoms[k], 256, "bin {k}");
        assert!((s.velocity[k][1] + 25.0).abs() < 1e-12, "bin {k} streams at {:?}", s.velocity[k]);
        let st = s.stress_gpa[k];
        for d in 0..3 {
            assert!((st[d] - want[d]).abs() < 1e-9 * want[0].abs(), "bin {k}: {st:?} vs box {want:?}");
        }
        assert!(st[3].abs() < 1e-9 * want[0].abs(), "bin {k}: sxy = {}", st[3]);
    }
    // Rows 2 and 3 hold the rest of the sample (y up to 16 a0: every plane in exactly one bin),
    // the rows above nothing.
    for k in 2 * s.nx..s.atoms.len() {
        assert_eq!(s.atoms[k], if k < 4 * s.nx { 256 } else { 0 }, "bin {k}");
    }
    assert_eq!(s.atoms.iter().sum::<usize>(), b.len() - b.frozen_count());
}

/// Copper at 10 K with a notch hits the block at 2.5 km/s: the total energy of the NVE run
/// holds, the moving atoms' y momentum changes by exactly the wall's impulse (the frozen atoms'
/// forces, velocity-Verlet's trapezoid), and after 0.4 ps the bins at the wall carry the
/// ~170 GPa shock while the bins ahead of it are still nearly unloaded.
#[test]
fn notched_sample_keeps_energy_and_takes_the_walls_impulse() {
    let a0 = 3.615;
    let mut s = spec(a0, [6, 20, 4], -25.0, 10.0);
    s.notch = Some(Notch { apex_x: 3.0 * a0, apex_y: 14.0 * a0, base_x0: 1.0 * a0, base_x1: 5.0 * a0 });
    let mut b = Bar::impact(mishin(), &s).unwrap();
    let full = 6 * 23 * 4 * 4;
    assert!(b.len() < full && b.len() > full - 6 * 4 * 4 * 4, "{} atoms: the notch removes a triangle", b.len());
    let (pe0, ke0) = b.energy();
    let p0 = b.momentum();
    let mut impulse = [0.0; 3];
    let dt = 0.001;
    for _ in 0..400 {
        let f0 = b.frozen_force();
        b.run(1, dt);
        let f1 = b.frozen_force();
        for d in 0..3 {
            impulse[d] += 0.5 * dt * (f0[d] + f1[d]) * FTM2V;
        }
    }
    b.check().unwrap();
    let (pe, ke) = b.energy();
    let p = b.momentum();
    let de = ((pe + ke) - (pe0 + ke0)).abs() / b.len() as f64;
    eprintln!("impact: dE = {de:e} eV/atom, p0 = {p0:?}, p = {p:?}, wall impulse = {impulse:?}");
    assert!(de < 2e-4, "energy changed by {de} eV/atom");
    assert!(p[1] - p0[1] > 0.2 * p0[1].abs(), "the wall did not push: {p0:?} -> {p:?}");
    for d in 0..3 {
        assert!(
            (p[d] - p0[d] + impulse[d]).abs() < 1e-8 * p0[1].abs(),
            "axis {d}: dp = {} but the wall gave {}",
            p[d] - p0[d],
            -impulse[d]
        );
    }
    let st = b.bin_stress();
    let syy = |ky: usize| (0..st.nx).map(|kx| st.stress_gpa[ky * st.nx + kx][1]).sum::<f64>() / st.nx as f64;
    // Front at about 0.4 ps * 5.2 nm/ps = 2.1 nm above the wall: bin 0 (0 to 1.45 nm) shocked,
    // bin 3 (4.3 to 5.8 nm) not yet.
    eprintln!("impact: syy by bin row {:?}", (0..st.ny).map(syy).collect::<Vec<_>>());
    assert!(syy(0) < -100.0 && syy(0) > -300.0, "wall bins: {} GPa", syy(0));
    assert!(syy(3).abs() < 15.0, "bins ahead of the front: {} GPa", syy(3));
}

#[test]
fn bad_notches_are_refused() {
    for bad in ["1:2:3", "5:1:6:7", "x:1:0:9", "5:1:0:4"] {
        let e = bad.parse::<Notch>().unwrap_err().to_string();
        assert!(e.contains("apex_x:apex_y:base_x0:base_x1"), "{bad}: {e}");
    }
    assert!("18:4:9:27".parse::<Notch>().is_ok());
    let mut s = spec(3.615, [4, 4, 4], -25.0, 0.0);
    s.bin_a = 0.0;
    assert!(Bar::impact(mishin(), &s).is_err());
}
