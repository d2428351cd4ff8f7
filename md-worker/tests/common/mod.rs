//! Shared helpers of md-worker's integration tests: golden-file reader, box builders and the
//! back-end list every physics test is instantiated for.
#![allow(dead_code, clippy::unwrap_used)]

use md_worker::data::DataFile;
use md_worker::{BoxSpec, CpuBackend, DeformMode, MdBackend, Potential, ReferenceBackend};
use std::path::PathBuf;
use std::sync::Arc;

pub fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn potential(name: &str) -> Arc<Potential> {
    Arc::new(Potential::from_file(&crate_dir().join("potentials").join(name)).unwrap())
}

pub fn mishin() -> Arc<Potential> {
    potential("Cu_mishin1.eam.alloy")
}

/// Back ends by name, for the instantiation macro.
pub fn make_backend(name: &str, pot: Arc<Potential>) -> Box<dyn MdBackend> {
    match name {
        "reference" => Box::new(ReferenceBackend::new(pot)),
        "cpu" => Box::new(CpuBackend::new(pot)),
        "cpu1" => {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            Box::new(CpuBackend::with_pool(pot, Arc::new(pool)))
        }
        "cpu2" => {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
            Box::new(CpuBackend::with_pool(pot, Arc::new(pool)))
        }
        #[cfg(feature = "cuda")]
        "cuda-shim" => Box::new(md_worker::cuda::ShimBackend::new(pot, md_worker::cuda::Precision::Double).unwrap()),
        "cuda" => md_worker::backend_by_name("cuda", pot).unwrap(),
        _ => panic!("unknown back end {name}"),
    }
}

/// Instantiate each listed generic test `fn name(backend: &str)` once per back end.
#[macro_export]
macro_rules! for_each_backend {
    ($($test:ident),* $(,)?) => {
        mod reference { $( #[test] fn $test() { super::$test("reference") } )* }
        mod cpu { $( #[test] fn $test() { super::$test("cpu") } )* }
        // The CUDA kernels run on the CPU through their host C++ twin (feature `cuda`).
        #[cfg(feature = "cuda")]
        mod cuda_shim { $( #[test] fn $test() { super::$test("cuda-shim") } )* }
        // On a GPU: ignored (with the reason) unless MSCALE_REQUIRE_GPU=1 at build time or
        // `-- --ignored`; then a missing GPU or feature fails the test.
        mod cuda { $( #[test]
        #[cfg_attr(not(require_gpu), ignore = "needs a CUDA GPU and --features cuda: runs with MSCALE_REQUIRE_GPU=1 or -- --ignored")]
        fn $test() {
            if let Some(why) = $crate::common::cuda_unavailable() {
                panic!("cuda::{}: the cuda back end cannot run here: {why}", stringify!($test));
            }
            super::$test("cuda")
        } )* }
    };
}

/// Why the `cuda` back end cannot run here (None: it can).
pub fn cuda_unavailable() -> Option<String> {
    #[cfg(feature = "cuda")]
    return md_worker::cuda::unavailable_reason();
    #[cfg(not(feature = "cuda"))]
    return Some("md-worker built without the `cuda` feature".into());
}

/// A LAMMPS golden file produced by scripts/make_golden.py.
pub struct Golden {
    pub potential: String,
    pub data: String,
    pub steps: u64,
    pub deform: String,
    /// step pe ke pxx pyy pzz pxy pxz pyz lx ly lz
    pub thermo: Vec<Vec<f64>>,
    /// id type x y z vx vy vz fx fy fz (final frame)
    pub atoms: Vec<Vec<f64>>,
}

pub fn golden(name: &str) -> Golden {
    let path = crate_dir().join("tests/golden").join(name);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.starts_with("# regenerate: "), "golden file without its regeneration command");
    let mut g = Golden { potential: String::new(), data: String::new(), steps: 0, deform: String::new(), thermo: vec![], atoms: vec![] };
    for line in text.lines() {
        let (key, rest) = line.split_once(' ').unwrap_or((line, ""));
        let nums = || rest.split_whitespace().map(|t| t.parse::<f64>().unwrap()).collect::<Vec<_>>();
        match key {
            "potential" => g.potential = rest.to_string(),
            "data" => g.data = rest.to_string(),
            "steps" => g.steps = rest.parse().unwrap(),
            "deform" => g.deform = rest.to_string(),
            "thermo" => g.thermo.push(nums()),
            "atom" => g.atoms.push(nums()),
            _ => {}
        }
    }
    g
}

/// A box spec holding exactly the atoms of a data file (velocities kept).
pub fn spec_from_data(id: u64, file: &str) -> (BoxSpec, DataFile) {
    let d = DataFile::read(&crate_dir().join("tests/golden").join(file)).unwrap();
    let mut s = d.box_spec(id);
    s.mode = DeformMode::Affine;
    (s, d)
}

/// LAMMPS pressure (bar) to our stress (GPa, tension positive).
pub fn bar_to_stress(p: f64) -> f64 {
    -p / 1e4
}

pub fn rel_close(a: f64, b: f64, scale: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * scale.abs().max(1e-300)
}
