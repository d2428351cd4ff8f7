//! Where MD runs: `auto`, `cpu` or `cuda` (the `--device` option). `cuda` needs the `cuda`
//! cargo feature, a CUDA driver, NVRTC and a device, and is an error (exit code 2 in the CLI)
//! when one is missing; `auto` takes the GPU when there is one and otherwise falls back to the
//! `cpu` back end, saying why in one warning. The back ends themselves are the engine's
//! (`md_engine::device`).

use crate::backend::{CpuBackend, MdBackend};
use crate::error::MdError;
use crate::potential::Potential;
use std::sync::Arc;

pub use md_engine::device::gpu_unavailable;

/// Back end for a device name (`auto`, `cpu`, `cuda`) and a GPU precision (`double` or
/// `mixed`; ignored on the CPU, which is always double).
pub fn backend_for_device(device: &str, precision: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    if !matches!(precision, "double" | "mixed") {
        return Err(MdError::invalid("precision", format!("{precision:?}; expected double or mixed")));
    }
    match device {
        "cpu" | "cuda" => md_engine::device::backend_for_device(device, precision, pot),
        "auto" => match md_engine::device::backend_for_device("cuda", precision, pot.clone()) {
            Ok(b) => Ok(b),
            Err(e) => {
                tracing::warn!("device auto: no usable GPU ({e}); running on the cpu back end");
                Ok(Box::new(CpuBackend::new(pot)))
            }
        },
        _ => Err(MdError::invalid("device", format!("{device:?}; expected auto, cpu or cuda"))),
    }
}
