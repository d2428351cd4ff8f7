//! Resident memory of idle boxes: opening many 500-atom boxes (and stepping them once)
//! must cost at most 100 bytes per atom of resident memory. One test per binary, so the
//! process's RSS is this test's alone.
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind};

#[cfg(all(target_os = "linux", target_env = "gnu"))]
unsafe extern "C" {
    fn malloc_trim(pad: usize) -> i32;
}

/// Resident set size of this process (bytes), from /proc/self/statm, after handing freed heap
/// pages back to the system: what is measured is live memory, not glibc's per-thread arenas
/// still holding the temporaries of parallel box preparation (which made the figure swing
/// between 82 and 112 B/atom with the machine's load).
fn rss_bytes() -> Option<f64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free memory at the top of glibc's heaps and arenas.
    unsafe {
        malloc_trim(0);
    }
    let s = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: f64 = s.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096.0)
}

fn idle_box_memory(boxes: u64) -> (f64, f64) {
    let mut b = make_backend("cpu", mishin());
    let specs: Vec<BoxSpec> = (0..boxes)
        .map(|id| {
            let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [5; 3]);
            s.temperature_k = 300.0;
            s.seed = 3;
            s
        })
        .collect();
    let atoms = 500.0 * boxes as f64;
    // Warm up the allocator and the thread pool with one box first.
    b.open(&[BoxSpec::lattice(u64::MAX, LatticeKind::Fcc, 3.615, [5; 3])]).unwrap();
    let before = rss_bytes().unwrap();
    b.open(&specs).unwrap();
    let opened = rss_bytes().unwrap();
    let work: Vec<BoxWork> = (0..boxes).map(|id| BoxWork::new(id, [[1e-3, 0.0, 0.0], [0.0; 3], [0.0; 3]], 2, 0.001)).collect();
    let mut out = vec![BoxResult::default(); work.len()];
    b.step(&work, &mut out).unwrap();
    let stepped = rss_bytes().unwrap();
    ((opened - before) / atoms, (stepped - before) / atoms)
}

/// One million atoms in 2000 idle boxes (the thesis's scale; ~6 s): fixed costs (thread
/// pools, per-thread scratch, allocator) are then below a few bytes per atom.
#[test]
#[cfg_attr(not(target_os = "linux"), ignore = "reads the resident size from /proc/self/statm (Linux only)")]
fn one_million_idle_atoms_cost_at_most_100_bytes_each() {
    assert!(rss_bytes().is_some(), "no /proc/self/statm on this system");
    let (open, stepped) = idle_box_memory(2000);
    eprintln!("1,000,000 atoms in 2000 boxes: {open:.1} B/atom after open, {stepped:.1} B/atom after a step call");
    assert!(open <= 100.0 && stepped <= 100.0, "{open} / {stepped} bytes per atom");
}
