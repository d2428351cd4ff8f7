//! CUDA back end (cargo feature `cuda`): batched EAM kernels through cudarc, compiled at run
//! time by NVRTC for the device's architecture (cached per architecture in the process).
//!
//! Design: one thread block per box, a box's atoms contiguous in flat arrays (the
//! [`crate::backend::Batch`] layout); one kernel launch runs a whole step call of every box
//! in the work list (energy addition, then for each MD step: half kick and drift, seed-mode
//! wrapping, the rebuild test, density, embedding, forces, half kick, affine remap), with
//! atom state resident on the device between calls. Per call only the work (velocity
//! gradient, steps, dt, energy) goes in and per-box energies, virial and kinetic tensors come
//! out; stresses are formed on the host. Neighbour lists are full lists built on the device
//! from all pairs and all periodic images within cut-off + skin (exact for boxes shorter than
//! twice the cut-off). Reductions are fixed-order trees, and no atomics are used, so results
//! are deterministic for a given device, build and precision (the only mode).
//!
//! The kernel source (`kernels.cu`) is also compiled as host C++ through `shim.h` (build.rs),
//! and [`ShimBackend`] runs it on the CPU through the same engine code: that is how the
//! kernels are tested without a GPU.
//!
//! Not on the device (yet): building and relaxing boxes in `open` (done by the CPU engine,
//! then uploaded), and the random velocities of energy added to a box at exactly 0 K (drawn
//! on the host, uploaded for that box only).

use crate::backend::{self, BoxResult, BoxState, BoxWork, Diagnostics, MdBackend, PointId, StressSampling};
use crate::error::MdError;
use crate::kernel::{self, BoxMeta, DeformMode};
use crate::lattice;
use crate::potential::{EamTables, Potential};
use crate::units::{BOLTZ, EV_PER_A3_TO_GPA, FTM2V, MVV2E};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::sync::Arc;

mod device;
pub use device::{CudaBackend, NvrtcOutput, driver_present, nvrtc_compile, nvrtc_present, unavailable_reason};

/// The kernel source, compiled by NVRTC at run time (and as host C++ by build.rs).
pub const KERNEL_SOURCE: &str = include_str!("kernels.cu");

/// Arithmetic of the force kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// Everything in f64.
    Double,
    /// Pair geometry, splines, densities and forces in f32; positions, velocities,
    /// integration, energies and stress in f64.
    Mixed,
}

// Layout constants shared with kernels.cu.
pub(crate) const MD_NT: u32 = 128;
const WD: usize = 12;
const WI: usize = 4;
const BOXD: usize = 32;
const BOXI: usize = 8;
const OUTD: usize = 24;
const OUTI: usize = 8;

/// Kernel arguments: the C struct `Params` of kernels.cu (pointers as 64-bit addresses).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Params {
    pub x: u64,
    pub v: u64,
    pub f: u64,
    pub xb: u64,
    pub img: u64,
    pub types: u64,
    pub rho: u64,
    pub fp: u64,
    pub vrand: u64,
    pub nlist: u64,
    pub nimg: u64,
    pub ncount: u64,
    pub off: u64,
    pub boxd: u64,
    pub boxi: u64,
    pub work_box: u64,
    pub work_d: u64,
    pub work_i: u64,
    pub out_d: u64,
    pub out_i: u64,
    pub frho64: u64,
    pub rhor64: u64,
    pub z2r64: u64,
    pub frho32: u64,
    pub rhor32: u64,
    pub z2r32: u64,
    pub type2rhor: u64,
    pub type2z2r: u64,
    pub masses: u64,
    pub rdr: f64,
    pub rdrho: f64,
    pub rhomax: f64,
    pub cutforcesq: f64,
    pub cutoff: f64,
    pub mvv2e: f64,
    pub ftm2v: f64,
    pub nelem: i32,
    pub nrho: i32,
    pub nr: i32,
    pub cap: i32,
    pub nwork: i32,
    pub pad: i32,
}

/// The potential's spline tables, flattened for upload (once per back end).
#[derive(Debug, Clone, Default)]
pub(crate) struct Tables {
    pub frho: Vec<f64>,
    pub rhor: Vec<f64>,
    pub z2r: Vec<f64>,
    pub type2rhor: Vec<i32>,
    pub type2z2r: Vec<i32>,
    pub masses: Vec<f64>,
    /// Scalars of Params (pointers left zero).
    pub scalars: Params,
}

impl Tables {
    fn new(t: &EamTables) -> Self {
        let flat = |s: &[Vec<[f64; 7]>]| s.iter().flat_map(|sp| sp.iter().flat_map(|c| c.iter().copied())).collect::<Vec<f64>>();
        let idx = |m: &[Vec<usize>]| m.iter().flat_map(|r| r.iter().map(|&k| k as i32)).collect::<Vec<i32>>();
        let scalars = Params {
            rdr: t.rdr,
            rdrho: t.rdrho,
            rhomax: t.rhomax,
            cutforcesq: t.cutforcesq,
            cutoff: t.cutoff,
            mvv2e: MVV2E,
            ftm2v: FTM2V,
            nelem: t.masses.len() as i32,
            nrho: t.nrho as i32,
            nr: t.nr as i32,
            ..Default::default()
        };
        Tables {
            frho: flat(&t.frho),
            rhor: flat(&t.rhor),
            z2r: flat(&t.z2r),
            type2rhor: idx(&t.type2rhor),
            type2z2r: idx(&t.type2z2r),
            masses: t.masses.clone(),
            scalars,
        }
    }
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// Everything of all boxes in the flat device layout, on the host.
#[derive(Debug, Clone, Default)]
pub(crate) struct Packed {
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub f: Vec<f64>,
    pub xb: Vec<f64>,
    pub img: Vec<i32>,
    pub types: Vec<i32>,
    pub off: Vec<i64>,
    pub boxd: Vec<f64>,
    pub boxi: Vec<i64>,
}

/// One launch's work list.
#[derive(Debug, Clone, Default)]
pub(crate) struct Work {
    pub boxes: Vec<i32>,
    pub d: Vec<f64>,
    pub i: Vec<i64>,
}

/// Which kernel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kernel {
    Steps(Precision),
    BuildLists,
}

/// Where the kernels run: the device (cudarc) or the host twin (FFI), same memory layout.
pub(crate) trait Exec: Send {
    /// Replace all atom and box arrays (and size the scratch and neighbour arrays).
    fn upload(&mut self, p: &Packed, cap: usize) -> Result<(), MdError>;
    /// Copy out x, v, f, xb, img, boxd, boxi (types and offsets stay the host's).
    fn download(&self, into: &mut Packed) -> Result<(), MdError>;
    /// Write random velocities of atoms `start..start + v.len() / 3` (0 K energy addition).
    fn write_vrand(&mut self, start: usize, v: &[f64]) -> Result<(), MdError>;
    /// Run a kernel over the work list; returns (out_d, out_i).
    fn launch(&mut self, k: Kernel, w: &Work) -> Result<(Vec<f64>, Vec<i64>), MdError>;
}

/// The host twin of the kernels (kernels.cu compiled as C++ through shim.h).
mod host {
    use super::*;

    unsafe extern "C" {
        fn mscale_host_md_steps_double(p: *const Params, nblocks: i32);
        fn mscale_host_md_steps_mixed(p: *const Params, nblocks: i32);
        fn mscale_host_build_lists(p: *const Params, nblocks: i32);
        fn mscale_host_params_size() -> std::ffi::c_ulong;
    }

    /// Size of the C struct Params (layout check).
    pub fn params_size_c() -> usize {
        // SAFETY: a pure function of the compiled C code.
        unsafe { mscale_host_params_size() as usize }
    }

    pub struct HostExec {
        t: Tables,
        frho32: Vec<f32>,
        rhor32: Vec<f32>,
        z2r32: Vec<f32>,
        p: Packed,
        rho: Vec<f64>,
        fp: Vec<f64>,
        vrand: Vec<f64>,
        nlist: Vec<i32>,
        nimg: Vec<i32>,
        ncount: Vec<i32>,
        cap: usize,
    }

    impl HostExec {
        pub fn new(t: Tables) -> Self {
            HostExec {
                frho32: to_f32(&t.frho),
                rhor32: to_f32(&t.rhor),
                z2r32: to_f32(&t.z2r),
                t,
                p: Packed::default(),
                rho: vec![],
                fp: vec![],
                vrand: vec![],
                nlist: vec![],
                nimg: vec![],
                ncount: vec![],
                cap: 0,
            }
        }
    }

    fn a<T>(v: &[T]) -> u64 {
        v.as_ptr() as u64
    }

    fn m<T>(v: &mut [T]) -> u64 {
        v.as_mut_ptr() as u64
    }

    impl Exec for HostExec {
        fn upload(&mut self, p: &Packed, cap: usize) -> Result<(), MdError> {
            let n = p.types.len();
            self.p = p.clone();
            self.rho = vec![0.0; n];
            self.fp = vec![0.0; n];
            self.vrand = vec![0.0; 3 * n];
            self.nlist = vec![0; n * cap];
            self.nimg = vec![0; n * cap];
            self.ncount = vec![0; n];
            self.cap = cap;
            Ok(())
        }
        fn download(&self, into: &mut Packed) -> Result<(), MdError> {
            into.x.clone_from(&self.p.x);
            into.v.clone_from(&self.p.v);
            into.f.clone_from(&self.p.f);
            into.xb.clone_from(&self.p.xb);
            into.img.clone_from(&self.p.img);
            into.boxd.clone_from(&self.p.boxd);
            into.boxi.clone_from(&self.p.boxi);
            Ok(())
        }
        fn write_vrand(&mut self, start: usize, v: &[f64]) -> Result<(), MdError> {
            self.vrand[3 * start..3 * start + v.len()].copy_from_slice(v);
            Ok(())
        }
        fn launch(&mut self, k: Kernel, w: &Work) -> Result<(Vec<f64>, Vec<i64>), MdError> {
            let nw = w.boxes.len();
            let mut out_d = vec![0.0f64; nw * OUTD];
            let mut out_i = vec![0i64; nw * OUTI];
            if nw == 0 {
                return Ok((out_d, out_i));
            }
            let params = Params {
                x: m(&mut self.p.x),
                v: m(&mut self.p.v),
                f: m(&mut self.p.f),
                xb: m(&mut self.p.xb),
                img: m(&mut self.p.img),
                types: a(&self.p.types),
                rho: m(&mut self.rho),
                fp: m(&mut self.fp),
                vrand: a(&self.vrand),
                nlist: m(&mut self.nlist),
                nimg: m(&mut self.nimg),
                ncount: m(&mut self.ncount),
                off: a(&self.p.off),
                boxd: m(&mut self.p.boxd),
                boxi: m(&mut self.p.boxi),
                work_box: a(&w.boxes),
                work_d: a(&w.d),
                work_i: a(&w.i),
                out_d: m(&mut out_d),
                out_i: m(&mut out_i),
                frho64: a(&self.t.frho),
                rhor64: a(&self.t.rhor),
                z2r64: a(&self.t.z2r),
                frho32: a(&self.frho32),
                rhor32: a(&self.rhor32),
                z2r32: a(&self.z2r32),
                type2rhor: a(&self.t.type2rhor),
                type2z2r: a(&self.t.type2z2r),
                masses: a(&self.t.masses),
                cap: self.cap as i32,
                nwork: nw as i32,
                ..self.t.scalars
            };
            // SAFETY: every pointer refers to a live array of the size the kernels index
            // (atoms by offsets, lists by cap, work and outputs by nw); the C code writes only
            // through the pointers taken from mutable borrows.
            unsafe {
                match k {
                    Kernel::Steps(Precision::Double) => mscale_host_md_steps_double(&params, nw as i32),
                    Kernel::Steps(Precision::Mixed) => mscale_host_md_steps_mixed(&params, nw as i32),
                    Kernel::BuildLists => mscale_host_build_lists(&params, nw as i32),
                }
            }
            Ok((out_d, out_i))
        }
    }
}

pub use host::params_size_c;

/// Neighbour capacity per atom: twice the neighbours within cut-off + skin at the densest
/// box's number density (margin for compression), plus a floor for tiny boxes.
fn list_capacity(p: &Packed, cutoff: f64) -> usize {
    let mut cap = 64usize;
    for b in 0..p.off.len().saturating_sub(1) {
        let n = (p.off[b + 1] - p.off[b]) as f64;
        let bd = &p.boxd[b * BOXD..(b + 1) * BOXD];
        let vol = bd[3] * bd[4] * bd[5];
        let rs = cutoff + bd[12];
        let want = 2.0 * n / vol * 4.0 / 3.0 * std::f64::consts::PI * rs * rs * rs + 32.0;
        cap = cap.max(want.ceil() as usize);
    }
    cap
}

/// The engine shared by [`CudaBackend`] and [`ShimBackend`]: host bookkeeping (ids, types,
/// offsets, seeds, modes) around an [`Exec`] that holds the atoms.
pub(crate) struct GpuEngine<E: Exec> {
    pot: Arc<Potential>,
    masses: Vec<f64>,
    precision: Precision,
    exec: E,
    ids: Vec<PointId>,
    seeds: Vec<u64>,
    index: BTreeMap<PointId, usize>,
    /// Types and offsets as on the device; the other arrays of this copy are refreshed by
    /// downloads only when needed (snapshot, open, restore).
    host: Packed,
    /// Kinetic energy about the mean velocity at the end of the last call (eV).
    kinetic: Vec<f64>,
    cap: usize,
}

fn eam(pot: &Potential) -> Result<&EamTables, MdError> {
    match pot {
        Potential::Eam(t) => Ok(t),
        Potential::LjCut(_) => Err(MdError::Unsupported("the cuda back end implements EAM potentials only (not lj/cut)".into())),
    }
}

impl<E: Exec> GpuEngine<E> {
    pub(crate) fn new(pot: Arc<Potential>, precision: Precision, exec: E) -> Self {
        let masses = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
        GpuEngine {
            pot,
            masses,
            precision,
            exec,
            ids: vec![],
            seeds: vec![],
            index: BTreeMap::new(),
            host: Packed { off: vec![0], ..Default::default() },
            kinetic: vec![],
            cap: 0,
        }
    }

    fn states(&mut self) -> Result<Vec<BoxState>, MdError> {
        if self.ids.is_empty() {
            return Ok(vec![]);
        }
        self.exec.download(&mut self.host)?;
        Ok((0..self.ids.len()).map(|k| self.state(k)).collect())
    }

    fn state(&self, k: usize) -> BoxState {
        let p = &self.host;
        let (a, b) = (p.off[k] as usize, p.off[k + 1] as usize);
        let v3 = |v: &[f64]| v[3 * a..3 * b].chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<_>>();
        let bd = &p.boxd[k * BOXD..(k + 1) * BOXD];
        let bi = &p.boxi[k * BOXI..(k + 1) * BOXI];
        let t3 = |o: usize| [bd[o], bd[o + 1], bd[o + 2]];
        BoxState {
            meta: BoxMeta {
                id: self.ids[k],
                lo: t3(0),
                l: t3(3),
                lo_build: t3(6),
                l_build: t3(9),
                mode: if bi[2] == 1 { DeformMode::Seed } else { DeformMode::Affine },
                seed: self.seeds[k],
                skin: bd[12],
                step: bi[0] as u64,
                pe: bd[13],
                virial: [bd[14], bd[15], bd[16], bd[17], bd[18], bd[19]],
                rebuilds: bi[1] as u64,
            },
            types: p.types[a..b].iter().map(|&t| t as u32).collect(),
            x: v3(&p.x),
            v: v3(&p.v),
            f: v3(&p.f),
            x_build: v3(&p.xb),
            img: p.img[3 * a..3 * b].chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        }
    }

    /// Replace all boxes by `states` (in this order) and upload them.
    fn install(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        let mut p = Packed { off: vec![0], ..Default::default() };
        self.ids.clear();
        self.seeds.clear();
        self.index.clear();
        self.kinetic.clear();
        for (k, s) in states.into_iter().enumerate() {
            let kin = kernel::kinetic_tensor(&s.types, &s.v, &self.masses);
            self.kinetic.push(0.5 * (kin[0] + kin[1] + kin[2]));
            self.ids.push(s.meta.id);
            self.seeds.push(s.meta.seed);
            self.index.insert(s.meta.id, k);
            p.off.push(p.off[k] + s.x.len() as i64);
            p.types.extend(s.types.iter().map(|&t| t as i32));
            p.x.extend(s.x.iter().flatten());
            p.v.extend(s.v.iter().flatten());
            p.f.extend(s.f.iter().flatten());
            p.xb.extend(s.x_build.iter().flatten());
            p.img.extend(s.img.iter().flatten());
            let m = &s.meta;
            let mut bd = [0.0; BOXD];
            bd[0..3].copy_from_slice(&m.lo);
            bd[3..6].copy_from_slice(&m.l);
            bd[6..9].copy_from_slice(&m.lo_build);
            bd[9..12].copy_from_slice(&m.l_build);
            bd[12] = m.skin;
            bd[13] = m.pe;
            bd[14..20].copy_from_slice(&m.virial);
            p.boxd.extend(bd);
            let mut bi = [0i64; BOXI];
            bi[0] = m.step as i64;
            bi[1] = m.rebuilds as i64;
            bi[2] = if m.mode == DeformMode::Seed { 1 } else { 0 };
            p.boxi.extend(bi);
        }
        let t = eam(&self.pot)?;
        let mut cap = list_capacity(&p, t.cutoff);
        let nb = self.ids.len();
        let all = Work { boxes: (0..nb as i32).collect(), d: vec![0.0; nb * WD], i: vec![0; nb * WI] };
        // Lists from the stored build positions (a restored box gets exactly its old list).
        for _ in 0..3 {
            self.exec.upload(&p, cap)?;
            let (_, oi) = self.exec.launch(Kernel::BuildLists, &all)?;
            let need = (0..all.boxes.len()).map(|w| oi[w * OUTI + 3]).max().unwrap_or(0);
            if need == 0 {
                self.cap = cap;
                self.host = p;
                return Ok(());
            }
            cap = (need as usize) * 5 / 4 + 16;
        }
        Err(MdError::Unsupported(format!("neighbour lists need more than {cap} entries per atom")))
    }

    pub(crate) fn open(&mut self, specs: &[backend::BoxSpec]) -> Result<(), MdError> {
        eam(&self.pot)?;
        let mut seen = std::collections::BTreeSet::new();
        for s in specs {
            if !seen.insert(s.id) || self.index.contains_key(&s.id) {
                return Err(MdError::invalid("box spec", format!("point id {} given twice", s.id)));
            }
            backend::validate_spec(&self.pot, s)?;
        }
        let (pot, masses) = (&*self.pot, &self.masses);
        let new = specs.par_iter().map(|s| backend::prepare_box(pot, masses, s)).collect::<Result<Vec<_>, _>>()?;
        let mut all = self.states()?;
        all.extend(new);
        self.install(all)
    }

    pub(crate) fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        for s in &states {
            crate::backend::check_state(&self.pot, s)?;
        }
        let mut all = self.states()?;
        for s in states {
            match self.index.get(&s.meta.id) {
                Some(&k) => all[k] = s,
                None => all.push(s),
            }
        }
        self.install(all)
    }

    pub(crate) fn snapshot(&mut self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        let ks = ids.iter().map(|id| self.index.get(id).copied().ok_or(MdError::UnknownBox(*id))).collect::<Result<Vec<_>, _>>()?;
        self.exec.download(&mut self.host)?;
        Ok(ks.into_iter().map(|k| self.state(k)).collect())
    }

    pub(crate) fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        if work.len() != out.len() {
            return Err(MdError::invalid("step", format!("{} work items but {} result slots", work.len(), out.len())));
        }
        let mut seen = std::collections::BTreeSet::new();
        let mut w = Work::default();
        for item in work {
            let k = *self.index.get(&item.id).ok_or(MdError::UnknownBox(item.id))?;
            if !seen.insert(item.id) {
                return Err(MdError::invalid("box work", format!("point id {} appears twice in one step", item.id)));
            }
            let mode = if self.host.boxi[k * BOXI + 2] == 1 { DeformMode::Seed } else { DeformMode::Affine };
            backend::validate_work(&self.pot, item, mode)?;
            w.boxes.push(k as i32);
            let g = kernel::Deformation::new(mode, &item.velocity_gradient).g;
            w.d.extend(g.iter().flatten());
            w.d.extend([item.dt_ps, item.energy_to_add_ev, 0.0]);
            let de = item.energy_to_add_ev;
            let energy_mode = if de == 0.0 {
                0
            } else if self.kinetic[k] <= 0.0 && de > 0.0 {
                // At 0 K: random directions, deterministic from (seed, point id, step), as
                // the CPU engine draws them.
                self.exec.download(&mut self.host)?;
                let (a, b) = (self.host.off[k] as usize, self.host.off[k + 1] as usize);
                let step = self.host.boxi[k * BOXI] as u64;
                let mut rng = lattice::rng_for(self.seeds[k], item.id, 2, step);
                let m: Vec<f64> = self.host.types[a..b].iter().map(|&t| self.masses[t as usize]).collect();
                let dof = (3 * (b - a)).saturating_sub(3).max(1) as f64;
                let u = lattice::maxwell_velocities(&mut rng, &m, 2.0 * de / (dof * BOLTZ));
                let flat: Vec<f64> = u.iter().flatten().copied().collect();
                self.exec.write_vrand(a, &flat)?;
                2
            } else {
                1
            };
            let average = i64::from(item.stress_sampling == StressSampling::Average);
            w.i.extend([item.steps as i64, energy_mode, average, 0]);
        }
        let (od, oi) = self.exec.launch(Kernel::Steps(self.precision), &w)?;
        for (q, (item, o)) in work.iter().zip(out.iter_mut()).enumerate() {
            let k = w.boxes[q] as usize;
            let d = &od[q * OUTD..(q + 1) * OUTD];
            let i = &oi[q * OUTI..(q + 1) * OUTI];
            if i[3] > 0 {
                return Err(MdError::Unsupported(format!(
                    "point {}: an atom has {} neighbours within cut-off + skin, more than the {} the cuda back end allocated; \
                     the box's state is now undefined (restore it from a snapshot)",
                    item.id, i[3], self.cap
                )));
            }
            if i[4] != 0 {
                return Err(MdError::Unsupported(format!("point {}: energy added to a box at rest was not drawn", item.id)));
            }
            let kin: [f64; 6] = std::array::from_fn(|c| d[7 + c]);
            let vol = d[13] * d[14] * d[15];
            let n = (self.host.off[k + 1] - self.host.off[k]) as usize;
            self.kinetic[k] = 0.5 * (kin[0] + kin[1] + kin[2]);
            self.host.boxi[k * BOXI] = i[0];
            let stress_gpa = if item.stress_sampling == StressSampling::Average && item.steps > 0 {
                // The device's per-step sum, in step order: for one step exactly the line below.
                std::array::from_fn(|c| d[17 + c] / item.steps as f64 * EV_PER_A3_TO_GPA)
            } else {
                std::array::from_fn(|c| -(kin[c] + d[1 + c]) / vol * EV_PER_A3_TO_GPA)
            };
            // The MD guard, once per call here (the device loop has none per step): a box
            // that blew up is stopped with its diagnosis, as the CPU back ends stop it.
            let ke_atom = self.kinetic[k] / n.max(1) as f64;
            if !(d[0].is_finite()
                && stress_gpa.iter().all(|c| c.is_finite())
                && ke_atom <= kernel::MAX_ATOM_KINETIC_EV
                && [d[13], d[14], d[15]].iter().all(|l| l.is_finite() && *l > 0.0))
            {
                return Err(MdError::Diverged {
                    point: item.id,
                    msg: format!(
                        "after step {} (the cuda back end checks once per call): potential energy {} eV, mean kinetic energy {ke_atom:.6e} eV per atom \
                         (bound {} eV), box {:?} A; use a smaller time step or velocity gradient",
                        i[0],
                        d[0],
                        kernel::MAX_ATOM_KINETIC_EV,
                        [d[13], d[14], d[15]]
                    ),
                });
            }
            *o = BoxResult {
                id: item.id,
                stress_gpa,
                stress_sampling: item.stress_sampling,
                potential_energy_ev: d[0],
                kinetic_energy_ev: self.kinetic[k],
                temperature_k: kernel::temperature(&kin, n),
                diagnostics: Diagnostics {
                    total_steps: i[0] as u64,
                    lengths_a: [d[13], d[14], d[15]],
                    energy_shortfall_ev: d[16],
                    neighbor_rebuilds: i[1] as u64,
                    wraps: i[2] as u64,
                },
            };
        }
        Ok(())
    }
}

/// The CUDA kernels run on the CPU through their host C++ twin (kernels.cu + shim.h):
/// slow, single-threaded, for tests of the kernels without a GPU.
pub struct ShimBackend {
    engine: std::sync::Mutex<GpuEngine<host::HostExec>>,
}

impl ShimBackend {
    /// A host-twin back end of the given precision (EAM potentials only).
    pub fn new(pot: Arc<Potential>, precision: Precision) -> Result<Self, MdError> {
        let t = Tables::new(eam(&pot)?);
        Ok(ShimBackend { engine: std::sync::Mutex::new(GpuEngine::new(pot, precision, host::HostExec::new(t))) })
    }
}

pub(crate) fn locked<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl MdBackend for ShimBackend {
    fn open(&mut self, specs: &[backend::BoxSpec]) -> Result<(), MdError> {
        locked(&self.engine).open(specs)
    }
    fn step(&mut self, work: &[BoxWork], out: &mut [BoxResult]) -> Result<(), MdError> {
        locked(&self.engine).step(work, out)
    }
    fn snapshot(&self, ids: &[PointId]) -> Result<Vec<BoxState>, MdError> {
        locked(&self.engine).snapshot(ids)
    }
    fn restore(&mut self, states: Vec<BoxState>) -> Result<(), MdError> {
        locked(&self.engine).restore(states)
    }
    fn name(&self) -> &'static str {
        "cuda-shim"
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn params_layout_matches_the_c_struct() {
        assert_eq!(std::mem::size_of::<super::Params>(), super::params_size_c());
    }
}
