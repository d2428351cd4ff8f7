//! `md-worker direct`: a small bar with frozen end layers (40x3x3 fcc Cu cells).
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::direct::{Bar, BarSpec, Region};
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind};

fn bar(strain: f64) -> BarSpec {
    BarSpec {
        kind: LatticeKind::Fcc,
        a0: 3.615,
        cells: [40, 3, 3],
        orient: md_worker::Orientation::CUBE,
        wall_a: 8.0,
        regions: if strain != 0.0 { vec![Region { x0: -1.0, x1: 1e9, strain }] } else { vec![] },
        temperature_k: 0.0,
        seed: 1,
        slab_a: 3.615 * 4.0,
        skin: 1.0,
    }
}

/// Interior slabs: away from the frozen layers and the free ends by more than a cut-off.
fn interior(s: &md_worker::direct::SlabStress) -> Vec<[f64; 3]> {
    let len = 40.0 * 3.615;
    s.center_a.iter().zip(&s.stress_gpa).filter(|(c, _)| **c > 20.0 && **c < len - 20.0).map(|(_, st)| *st).collect()
}

fn box_stress(strain: f64) -> [f64; 6] {
    let mut b = make_backend("reference", mishin());
    let mut s = BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [3; 3]);
    s.strain = [strain, 0.0, 0.0];
    b.open(&[s]).unwrap();
    let mut out = [BoxResult::default()];
    b.step(&[BoxWork::new(1, [[0.0; 3]; 3], 0, 0.001)], &mut out).unwrap();
    out[0].stress_gpa
}

#[test]
fn unstrained_bar_has_no_interior_stress_and_keeps_its_energy() {
    let mut b = Bar::new(mishin(), &bar(0.0)).unwrap();
    assert_eq!(b.len(), 40 * 9 * 4);
    assert!(b.frozen_count() > 0);
    let (pe0, ke0) = b.energy();
    b.run(200, 0.002);
    let (pe, ke) = b.energy();
    let s = b.slab_stress();
    let inner = interior(&s);
    assert!(inner.len() >= 4, "{} interior slabs", inner.len());
    for st in &inner {
        // The box stress of perfect Cu at 3.615 A is ~0.01 GPa; the bar's interior matches.
        assert!(st.iter().all(|c| c.abs() < 0.05), "interior slab stress {st:?}");
    }
    let e_err = ((pe + ke) - (pe0 + ke0)).abs() / b.len() as f64;
    eprintln!("unstrained bar: interior {inner:?}, |dE| = {e_err:e} eV/atom");
    assert!(e_err < 1e-6, "energy changed by {e_err} eV/atom");
}

#[test]
fn uniformly_strained_bar_matches_the_single_box_stress() {
    for strain in [-0.02, 0.01] {
        let b = Bar::new(mishin(), &bar(strain)).unwrap();
        let want = box_stress(strain);
        for st in interior(&b.slab_stress()) {
            for d in 0..3 {
                assert!((st[d] - want[d]).abs() < 0.01 * want[0].abs().max(1.0), "strain {strain}: slab {st:?} vs box {want:?}");
            }
        }
    }
}

#[test]
fn pre_compressed_half_pushes_and_conserves_energy() {
    let mut spec = bar(0.0);
    spec.regions = vec![Region { x0: 0.0, x1: 20.0 * 3.615, strain: -0.03 }];
    let mut b = Bar::new(mishin(), &spec).unwrap();
    let s0 = b.slab_stress();
    // Compressed half in compression (negative), the other half unloaded at t = 0.
    let left: Vec<f64> = s0.center_a.iter().zip(&s0.stress_gpa).filter(|(c, _)| **c > 20.0 && **c < 60.0).map(|(_, s)| s[0]).collect();
    let right: Vec<f64> = s0.center_a.iter().zip(&s0.stress_gpa).filter(|(c, _)| **c > 90.0 && **c < 125.0).map(|(_, s)| s[0]).collect();
    assert!(left.iter().all(|s| *s < -3.0), "compressed half {left:?}");
    assert!(right.iter().all(|s| s.abs() < 0.5), "free half {right:?}");
    let (pe0, ke0) = b.energy();
    b.run(300, 0.001);
    let (pe, ke) = b.energy();
    let e_err = ((pe + ke) - (pe0 + ke0)).abs() / b.len() as f64;
    eprintln!("pre-compressed bar: |dE| = {e_err:e} eV/atom, KE {ke0} -> {ke} eV, momentum {:?}", b.momentum());
    assert!(e_err < 1e-4, "energy changed by {e_err} eV/atom");
    assert!(ke > ke0, "the released compression should turn into motion");
}

#[test]
fn bad_regions_are_refused() {
    assert!("0:10:-0.05".parse::<Region>().is_ok());
    for bad in ["10:0:0.1", "0:10", "a:b:c", "0:10:-1.5"] {
        let e = bad.parse::<Region>().unwrap_err().to_string();
        assert!(e.contains("x0:x1:strain"), "{bad}: {e}");
    }
}
