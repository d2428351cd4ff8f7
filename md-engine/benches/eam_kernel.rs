//! The EAM force kernel alone, every SIMD path this CPU runs, interleaved (A B C A B C ...):
//! ns per atom per force evaluation (one MD step's forces) on hot perturbed Mishin Cu boxes of
//! 108 and 500 atoms and a 32,000-atom box. Prints min and median over the rounds; the min is
//! the least disturbed figure on a shared machine. Times are the thread's CPU time.
//!   cargo bench -p md-engine --bench eam_kernel [-- ROUNDS]
//! MSCALE_MD_SIMD=PATH times one path, MSCALE_BENCH_CELLS=5 one box size (for profilers).
use md_engine::kernel::{self, BoxMeta, BoxView, DeformMode};
use md_engine::lattice::{self, LatticeKind};
use md_engine::neighbor::NeighborList;
use md_engine::potential::Potential;
use md_engine::simd::SimdPath;

/// CPU time of this thread (ns), from /proc/thread-self/schedstat: on a shared machine the
/// wall clock counts other processes' time slices too.
fn cpu_ns() -> f64 {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").unwrap_or_default();
    s.split_whitespace().next().and_then(|v| v.parse().ok()).unwrap_or(f64::NAN)
}

struct Box1 {
    meta: BoxMeta,
    types: Vec<u32>,
    x: Vec<[f64; 3]>,
    v: Vec<[f64; 3]>,
    f: Vec<[f64; 3]>,
    xb: Vec<[f64; 3]>,
    img: Vec<[i32; 3]>,
    list: NeighborList,
}

impl Box1 {
    fn new(pot: &Potential, cells: usize) -> Self {
        let (mut x, l) = lattice::build_oriented(LatticeKind::Fcc, 3.615, [cells; 3], &md_engine::Orientation::CUBE).expect("lattice");
        for (k, q) in x.iter_mut().enumerate() {
            for d in 0..3 {
                // ~0.1 A thermal-like displacements, deterministic.
                q[d] += 0.2 * (((k * 7 + d * 13) as f64 * 0.618_033_988_75).fract() - 0.5);
            }
        }
        let n = x.len();
        let meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l,
            lo_build: [0.0; 3],
            l_build: l,
            mode: DeformMode::Affine,
            seed: 0,
            skin: 1.0,
            step: 0,
            pe: 0.0,
            virial: [0.0; 6],
            rebuilds: 0,
        };
        let mut b = Box1 {
            meta,
            types: vec![0; n],
            x,
            v: vec![[0.0; 3]; n],
            f: vec![[0.0; 3]; n],
            xb: vec![[0.0; 3]; n],
            img: vec![[0; 3]; n],
            list: NeighborList::default(),
        };
        kernel::rebuild(pot, &mut b.view());
        b
    }
    fn view(&mut self) -> BoxView<'_> {
        BoxView {
            meta: &mut self.meta,
            types: &self.types,
            x: &mut self.x,
            v: &mut self.v,
            f: &mut self.f,
            x_build: &mut self.xb,
            img: &mut self.img,
            list: &mut self.list,
        }
    }
}

fn main() {
    let rounds: usize = std::env::args().skip(1).find_map(|a| a.parse().ok()).unwrap_or(7);
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials/Cu_mishin1.eam.alloy");
    let pot = Potential::from_file(&root).expect("potential");
    // MSCALE_MD_SIMD=PATH times that path alone (for profiling).
    let paths = match std::env::var(md_engine::simd::ENV) {
        Ok(v) => vec![SimdPath::parse(&v).expect("MSCALE_MD_SIMD")],
        Err(_) => SimdPath::supported(),
    };
    println!("paths: {paths:?}; load: {}", std::fs::read_to_string("/proc/loadavg").unwrap_or_default().trim());
    // MSCALE_BENCH_CELLS=5 (comma-separated) times those box sizes alone.
    let sizes: Vec<usize> = match std::env::var("MSCALE_BENCH_CELLS") {
        Ok(v) => v.split(',').map(|c| c.trim().parse().expect("MSCALE_BENCH_CELLS")).collect(),
        Err(_) => vec![3, 5, 20],
    };
    for cells in sizes {
        let mut b = Box1::new(&pot, cells);
        let n = b.x.len();
        let evals = (1_000_000 / n).max(10);
        let (mut rho, mut fp) = (Vec::new(), Vec::new());
        let mut t: Vec<Vec<f64>> = vec![Vec::new(); paths.len()];
        for _ in 0..rounds {
            for (k, &p) in paths.iter().enumerate() {
                let mut v = b.view();
                kernel::with_simd(p, || kernel::compute_forces(&pot, &mut v, &mut rho, &mut fp));
                let t0 = cpu_ns();
                for _ in 0..evals {
                    kernel::with_simd(p, || kernel::compute_forces(&pot, &mut v, &mut rho, &mut fp));
                }
                t[k].push((cpu_ns() - t0) / (evals * n) as f64);
            }
        }
        let pairs = b.list.len() as f64 / n as f64;
        for (k, p) in paths.iter().enumerate() {
            let mut s = t[k].clone();
            s.sort_by(f64::total_cmp);
            println!(
                "{n:>6} atoms ({pairs:.1} list entries/atom) {:>7}: min {:7.1} median {:7.1} ns/atom-force-eval",
                p.name(),
                s[0],
                s[s.len() / 2]
            );
        }
    }
}
