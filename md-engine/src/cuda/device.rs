//! The device side: library detection, NVRTC compilation (cached per architecture), device
//! buffers and launches through cudarc. cudarc panics when a library it needs is missing, so
//! nothing here touches cudarc before `is_culib_present()` said yes.

use super::{BOXD, BOXI, Exec, GpuEngine, Kernel, MD_NT, OUTD, OUTI, Packed, Params, Precision, Tables, Work, eam, locked, to_f32};
use crate::backend::{BoxResult, BoxSpec, BoxState, BoxWork, MdBackend, PointId};
use crate::error::MdError;
use crate::potential::Potential;
use cudarc::driver::{CudaContext, CudaFunction, CudaModule, CudaSlice, CudaStream, DevicePtr, DeviceRepr, LaunchConfig, PushKernelArg};
use cudarc::nvrtc::{Ptx, result as nvrtc};
use std::collections::BTreeMap;
use std::ffi::{CStr, CString, c_char};
use std::sync::{Arc, Mutex};

// SAFETY: Params is #[repr(C)], plain old data, and has the layout of the C struct (checked
// against the host build in the tests).
unsafe impl DeviceRepr for Params {}

/// Whether the CUDA driver library (libcuda) can be loaded.
pub fn driver_present() -> bool {
    // SAFETY: only tries to dlopen the library.
    unsafe { cudarc::driver::sys::is_culib_present() }
}

/// Whether NVRTC (libnvrtc) can be loaded.
pub fn nvrtc_present() -> bool {
    // SAFETY: only tries to dlopen the library.
    unsafe { cudarc::nvrtc::sys::is_culib_present() }
}

/// Why no CUDA device can be used here, or `None` if one can.
pub fn unavailable_reason() -> Option<String> {
    if !driver_present() {
        return Some("no CUDA driver (libcuda.so not found)".into());
    }
    if !nvrtc_present() {
        return Some("no NVRTC (libnvrtc.so not found; `bash deploy/setup.sh nvrtc` installs it)".into());
    }
    match CudaContext::device_count() {
        Ok(n) if n > 0 => None,
        Ok(_) => Some("the CUDA driver sees no device".into()),
        Err(e) => Some(format!("the CUDA driver failed to start: {e}")),
    }
}

/// What NVRTC made of the kernel source.
#[derive(Debug, Clone)]
pub struct NvrtcOutput {
    /// The PTX (when asked for; only virtual architectures `compute_XY` give PTX).
    pub ptx: Option<String>,
    /// NVRTC's log: warnings (empty when the source compiled cleanly).
    pub log: String,
}

fn c_text(v: &[c_char]) -> String {
    let bytes: Vec<u8> = v.iter().map(|&c| c as u8).take_while(|&b| b != 0).collect();
    String::from_utf8_lossy(&bytes).into_owned()
}

fn nvrtc_err(arch: &str, what: &str, e: impl std::fmt::Debug) -> MdError {
    MdError::Device(format!("nvrtc {what} for {arch}: {e:?}"))
}

/// Compile the kernel source with NVRTC for `arch` (e.g. `sm_90`, `compute_90`); errors carry
/// the log. Needs NVRTC ([`nvrtc_present`]).
pub fn nvrtc_compile(arch: &str, want_ptx: bool) -> Result<NvrtcOutput, MdError> {
    if !nvrtc_present() {
        return Err(MdError::Device("no NVRTC (libnvrtc.so not found)".into()));
    }
    let src = CString::new(super::KERNEL_SOURCE).map_err(|e| nvrtc_err(arch, "source", e))?;
    let name: &CStr = c"kernels.cu";
    let prog = nvrtc::create_program(&src, Some(name)).map_err(|e| nvrtc_err(arch, "create", e))?;
    // MSCALE_CUDA_NVRTC_OPTIONS: extra NVRTC options, split at whitespace (tuning runs, e.g.
    // `-DMD_MIN_BLOCKS=8`, see kernels.cu; md-worker/README.md "CUDA back end" has the effect).
    let extra = std::env::var("MSCALE_CUDA_NVRTC_OPTIONS").unwrap_or_default();
    let opts: Vec<String> = [format!("--gpu-architecture={arch}"), "--std=c++17".to_string()]
        .into_iter()
        .chain(extra.split_whitespace().map(str::to_string))
        .collect();
    // SAFETY: prog was just created and is destroyed once below; src and name outlive it.
    let res = unsafe { nvrtc::compile_program(prog, &opts) };
    // SAFETY: as above.
    let log = unsafe { nvrtc::get_program_log(prog) }.map(|l| c_text(&l)).unwrap_or_default();
    let ptx = match (&res, want_ptx) {
        // SAFETY: as above.
        (Ok(()), true) => Some(unsafe { nvrtc::get_ptx(prog) }.map(|p| c_text(&p)).map_err(|e| nvrtc_err(arch, "get ptx", e))),
        _ => None,
    };
    // SAFETY: as above; not used afterwards.
    let _ = unsafe { nvrtc::destroy_program(prog) };
    if let Err(e) = res {
        return Err(MdError::Device(format!("nvrtc failed to compile kernels.cu for {arch} ({e:?}):\n{log}")));
    }
    Ok(NvrtcOutput { ptx: ptx.transpose()?, log })
}

/// PTX of the kernels for a compute capability, compiled once per process.
fn ptx_for(cc: (i32, i32)) -> Result<String, MdError> {
    static CACHE: Mutex<BTreeMap<(i32, i32), String>> = Mutex::new(BTreeMap::new());
    let mut cache = locked(&CACHE);
    if let Some(p) = cache.get(&cc) {
        return Ok(p.clone());
    }
    let out = nvrtc_compile(&format!("compute_{}{}", cc.0, cc.1), true)?;
    let ptx = out.ptx.ok_or_else(|| MdError::Device("nvrtc gave no PTX".into()))?;
    cache.insert(cc, ptx.clone());
    Ok(ptx)
}

fn dev(e: cudarc::driver::DriverError) -> MdError {
    MdError::Device(e.to_string())
}

struct Bufs {
    x: CudaSlice<f64>,
    v: CudaSlice<f64>,
    f: CudaSlice<f64>,
    xb: CudaSlice<f64>,
    img: CudaSlice<i32>,
    types: CudaSlice<i32>,
    off: CudaSlice<i64>,
    boxd: CudaSlice<f64>,
    boxi: CudaSlice<i64>,
    rho: CudaSlice<f64>,
    fp: CudaSlice<f64>,
    vrand: CudaSlice<f64>,
    nlist: CudaSlice<i32>,
    nimg: CudaSlice<i32>,
    ncount: CudaSlice<i32>,
    cap: usize,
}

/// Tables on the device (uploaded once) and the batch's buffers.
struct DeviceExec {
    stream: Arc<CudaStream>,
    _module: Arc<CudaModule>,
    f_double: CudaFunction,
    f_mixed: CudaFunction,
    f_build: CudaFunction,
    frho64: CudaSlice<f64>,
    rhor64: CudaSlice<f64>,
    z2r64: CudaSlice<f64>,
    frho32: CudaSlice<f32>,
    rhor32: CudaSlice<f32>,
    z2r32: CudaSlice<f32>,
    type2rhor: CudaSlice<i32>,
    type2z2r: CudaSlice<i32>,
    masses: CudaSlice<f64>,
    scalars: Params,
    bufs: Option<Bufs>,
}

impl DeviceExec {
    fn new(t: Tables) -> Result<Self, MdError> {
        if let Some(why) = unavailable_reason() {
            return Err(MdError::Device(why));
        }
        let ctx = CudaContext::new(0).map_err(dev)?;
        let cc = ctx.compute_capability().map_err(dev)?;
        let module = ctx.load_module(Ptx::from_src(ptx_for(cc)?)).map_err(dev)?;
        let stream = ctx.default_stream();
        let up64 = |v: &[f64]| stream.clone_htod(v).map_err(dev);
        let up32 = |v: &[f32]| stream.clone_htod(v).map_err(dev);
        let upi = |v: &[i32]| stream.clone_htod(v).map_err(dev);
        Ok(DeviceExec {
            f_double: module.load_function("md_steps_double").map_err(dev)?,
            f_mixed: module.load_function("md_steps_mixed").map_err(dev)?,
            f_build: module.load_function("build_lists").map_err(dev)?,
            frho64: up64(&t.frho)?,
            rhor64: up64(&t.rhor)?,
            z2r64: up64(&t.z2r)?,
            frho32: up32(&to_f32(&t.frho))?,
            rhor32: up32(&to_f32(&t.rhor))?,
            z2r32: up32(&to_f32(&t.z2r))?,
            type2rhor: upi(&t.type2rhor)?,
            type2z2r: upi(&t.type2z2r)?,
            masses: up64(&t.masses)?,
            scalars: t.scalars,
            bufs: None,
            _module: module,
            stream,
        })
    }

    fn ptr<T>(&self, s: &CudaSlice<T>) -> u64 {
        // One stream only, so the event guard is not needed beyond this call.
        let (p, _guard) = s.device_ptr(&self.stream);
        p
    }
}

impl Exec for DeviceExec {
    fn upload(&mut self, p: &Packed, cap: usize) -> Result<(), MdError> {
        self.bufs = None;
        let n = p.types.len();
        if n == 0 {
            return Ok(());
        }
        let s = &self.stream;
        self.bufs = Some(Bufs {
            x: s.clone_htod(&p.x).map_err(dev)?,
            v: s.clone_htod(&p.v).map_err(dev)?,
            f: s.clone_htod(&p.f).map_err(dev)?,
            xb: s.clone_htod(&p.xb).map_err(dev)?,
            img: s.clone_htod(&p.img).map_err(dev)?,
            types: s.clone_htod(&p.types).map_err(dev)?,
            off: s.clone_htod(&p.off).map_err(dev)?,
            boxd: s.clone_htod(&p.boxd).map_err(dev)?,
            boxi: s.clone_htod(&p.boxi).map_err(dev)?,
            rho: s.alloc_zeros(n).map_err(dev)?,
            fp: s.alloc_zeros(n).map_err(dev)?,
            vrand: s.alloc_zeros(3 * n).map_err(dev)?,
            nlist: s.alloc_zeros(n * cap).map_err(dev)?,
            nimg: s.alloc_zeros(n * cap).map_err(dev)?,
            ncount: s.alloc_zeros(n).map_err(dev)?,
            cap,
        });
        Ok(())
    }

    fn download(&self, into: &mut Packed) -> Result<(), MdError> {
        let Some(b) = &self.bufs else { return Ok(()) };
        let s = &self.stream;
        into.x = s.clone_dtoh(&b.x).map_err(dev)?;
        into.v = s.clone_dtoh(&b.v).map_err(dev)?;
        into.f = s.clone_dtoh(&b.f).map_err(dev)?;
        into.xb = s.clone_dtoh(&b.xb).map_err(dev)?;
        into.img = s.clone_dtoh(&b.img).map_err(dev)?;
        into.boxd = s.clone_dtoh(&b.boxd).map_err(dev)?;
        into.boxi = s.clone_dtoh(&b.boxi).map_err(dev)?;
        s.synchronize().map_err(dev)
    }

    fn write_vrand(&mut self, start: usize, v: &[f64]) -> Result<(), MdError> {
        let Some(b) = &mut self.bufs else { return Ok(()) };
        let mut dst = b.vrand.slice_mut(3 * start..3 * start + v.len());
        self.stream.memcpy_htod(v, &mut dst).map_err(dev)
    }

    fn launch(&mut self, k: Kernel, w: &Work) -> Result<(Vec<f64>, Vec<i64>), MdError> {
        let nw = w.boxes.len();
        let Some(b) = &self.bufs else { return Ok((vec![0.0; nw * OUTD], vec![0; nw * OUTI])) };
        if nw == 0 {
            return Ok((vec![], vec![]));
        }
        let s = &self.stream;
        let wb = s.clone_htod(&w.boxes).map_err(dev)?;
        let wd = s.clone_htod(&w.d).map_err(dev)?;
        let wi = s.clone_htod(&w.i).map_err(dev)?;
        let od = s.alloc_zeros::<f64>(nw * OUTD).map_err(dev)?;
        let oi = s.alloc_zeros::<i64>(nw * OUTI).map_err(dev)?;
        let params = Params {
            x: self.ptr(&b.x),
            v: self.ptr(&b.v),
            f: self.ptr(&b.f),
            xb: self.ptr(&b.xb),
            img: self.ptr(&b.img),
            types: self.ptr(&b.types),
            rho: self.ptr(&b.rho),
            fp: self.ptr(&b.fp),
            vrand: self.ptr(&b.vrand),
            nlist: self.ptr(&b.nlist),
            nimg: self.ptr(&b.nimg),
            ncount: self.ptr(&b.ncount),
            off: self.ptr(&b.off),
            boxd: self.ptr(&b.boxd),
            boxi: self.ptr(&b.boxi),
            work_box: self.ptr(&wb),
            work_d: self.ptr(&wd),
            work_i: self.ptr(&wi),
            out_d: self.ptr(&od),
            out_i: self.ptr(&oi),
            frho64: self.ptr(&self.frho64),
            rhor64: self.ptr(&self.rhor64),
            z2r64: self.ptr(&self.z2r64),
            frho32: self.ptr(&self.frho32),
            rhor32: self.ptr(&self.rhor32),
            z2r32: self.ptr(&self.z2r32),
            type2rhor: self.ptr(&self.type2rhor),
            type2z2r: self.ptr(&self.type2z2r),
            masses: self.ptr(&self.masses),
            cap: b.cap as i32,
            nwork: nw as i32,
            ..self.scalars
        };
        let f = match k {
            Kernel::Steps(Precision::Double) => &self.f_double,
            Kernel::Steps(Precision::Mixed) => &self.f_mixed,
            Kernel::BuildLists => &self.f_build,
        };
        let cfg = LaunchConfig { grid_dim: (nw as u32, 1, 1), block_dim: (MD_NT, 1, 1), shared_mem_bytes: 0 };
        // SAFETY: the kernel indexes only the arrays in params, each sized as on the host
        // twin (atoms by offsets, lists by cap, work and outputs by nw); all are alive until
        // the stream is synchronised below.
        unsafe { s.launch_builder(f).arg(&params).launch(cfg) }.map_err(dev)?;
        let out_d = s.clone_dtoh(&od).map_err(dev)?;
        let out_i = s.clone_dtoh(&oi).map_err(dev)?;
        s.synchronize().map_err(dev)?;
        Ok((out_d, out_i))
    }
}

/// The CUDA back end: boxes resident on GPU 0, kernels compiled by NVRTC at run time.
pub struct CudaBackend {
    engine: Mutex<GpuEngine<DeviceExec>>,
    name: &'static str,
}

impl CudaBackend {
    /// A back end on GPU 0, or an error naming what is missing (driver, NVRTC, device) or
    /// what failed (compilation, allocation). EAM potentials only.
    pub fn new(pot: Arc<Potential>, precision: Precision) -> Result<Self, MdError> {
        let t = Tables::new(eam(&pot)?);
        let exec = DeviceExec::new(t)?;
        let name = match precision {
            Precision::Double => "cuda",
            Precision::Mixed => "cuda-mixed",
        };
        Ok(CudaBackend { engine: Mutex::new(GpuEngine::new(pot, precision, exec)), name })
    }
}

impl MdBackend for CudaBackend {
    fn open(&mut self, specs: &[BoxSpec]) -> Result<(), MdError> {
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
        self.name
    }
}

// Layout constants are used by the engine; referenced here so a mismatch shows in one place.
const _: () = assert!(BOXD == 32 && BOXI == 8);
