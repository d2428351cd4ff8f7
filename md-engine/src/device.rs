//! The engine's back ends by name (`reference`, `cpu`, `cuda`, `cuda-mixed`) and by device
//! (`cpu` or `cuda`). `cuda` needs the `cuda` cargo feature, a CUDA driver, NVRTC and a device,
//! and is an error naming what is missing. The one place programs build a back end through is
//! the worker's registry (`md_worker::device::build`): it adds thread pools, the `null` and
//! `mpi` back ends, and the choice of a device for the user (`auto`: the GPU when there is
//! one, otherwise the cpu back end with one warning).

use crate::backend::{CpuBackend, MdBackend, ReferenceBackend};
use crate::error::MdError;
use crate::potential::Potential;
use std::sync::Arc;

/// Back end for a device name (`cpu`, `cuda`) and a GPU precision (`double` or `mixed`;
/// ignored on the CPU, which is always double).
pub fn backend_for_device(device: &str, precision: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    if !matches!(precision, "double" | "mixed") {
        return Err(MdError::invalid("precision", format!("{precision:?}; expected double or mixed")));
    }
    match device {
        "cpu" => Ok(Box::new(CpuBackend::new(pot))),
        "cuda" => cuda(precision, pot),
        _ => Err(MdError::invalid("device", format!("{device:?}; expected cpu or cuda"))),
    }
}

/// A back end by name: `reference`, `cpu`, `cuda` (double) or `cuda-mixed` (the GPU ones fail
/// with [`MdError::Device`] when there is no usable GPU).
pub fn backend_by_name(name: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    match name {
        "reference" => Ok(Box::new(ReferenceBackend::new(pot))),
        "cpu" => Ok(Box::new(CpuBackend::new(pot))),
        "cuda" => backend_for_device("cuda", "double", pot),
        "cuda-mixed" => backend_for_device("cuda", "mixed", pot),
        _ => Err(MdError::invalid("back end", format!("{name:?}; expected reference, cpu, cuda or cuda-mixed"))),
    }
}

#[cfg(feature = "cuda")]
fn cuda(precision: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    use crate::cuda::{CudaBackend, Precision};
    let p = if precision == "mixed" { Precision::Mixed } else { Precision::Double };
    Ok(Box::new(CudaBackend::new(pot, p)?))
}

#[cfg(not(feature = "cuda"))]
fn cuda(_precision: &str, _pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    Err(MdError::Device("this md-worker was built without the `cuda` cargo feature".into()))
}

/// Why the GPU cannot be used here, or `None` when it can (checked without touching cudarc
/// beyond its library probes).
pub fn gpu_unavailable() -> Option<String> {
    #[cfg(feature = "cuda")]
    {
        crate::cuda::unavailable_reason()
    }
    #[cfg(not(feature = "cuda"))]
    {
        Some("this md-worker was built without the `cuda` cargo feature".into())
    }
}
