//! The back-end registry: the one place that turns (name, device, precision, threads) into a
//! back end, for the pool's in-process endpoints, the worker's sessions, its throughput
//! measurement and the `md-worker` commands.
//!
//! Names: `reference`, `cpu`, `cuda` (double), `cuda-mixed`, `null` (no MD: the coupling's own
//! cost, `md-worker bench-coupling`) and, with the `mpi` feature, `mpi`. A device (`--device`:
//! `auto`, `cpu` or `cuda`) takes the place of the name: `cuda` needs the `cuda` cargo
//! feature, a CUDA driver, NVRTC and a device, and is an error (exit code 2 in the CLI) when
//! one is missing; `auto` takes the GPU when there is one and otherwise falls back to the
//! `cpu` back end, saying why in one warning ([`resolve_device`]). The engine's own back ends
//! are built by `md_engine::device`.

use crate::backend::{CpuBackend, MdBackend};
use crate::error::MdError;
use crate::potential::Potential;
use crate::source::PotentialSource;
use std::sync::Arc;

pub use md_engine::device::gpu_unavailable;

/// What a back end is asked for.
#[derive(Clone, Debug)]
pub struct BackendChoice {
    /// A back end name (see the module docs); ignored when `device` is given.
    pub name: String,
    /// `auto`, `cpu` or `cuda`, in place of the name.
    pub device: Option<String>,
    /// Arithmetic of a GPU back end: `double` or `mixed` (the CPU ones are always double).
    pub precision: String,
    /// The cpu back end's thread pool (rayon's global one when `None`).
    pub threads: Option<Arc<rayon::ThreadPool>>,
}

impl BackendChoice {
    /// The back end `name`, double precision, on rayon's global pool.
    pub fn named(name: &str) -> Self {
        BackendChoice { name: name.into(), device: None, precision: "double".into(), threads: None }
    }

    /// The back end of `device` (`auto`, `cpu`, `cuda`) in `precision`.
    pub fn on_device(device: &str, precision: &str) -> Self {
        BackendChoice { name: String::new(), device: Some(device.into()), precision: precision.into(), threads: None }
    }

    /// The same, with the cpu back end on `threads`.
    pub fn with_threads(mut self, threads: Option<Arc<rayon::ThreadPool>>) -> Self {
        self.threads = threads;
        self
    }
}

/// The device `auto`, `cpu` or `cuda` stands for here: `cuda` when it is usable (an error
/// naming what is missing when it was asked for), `cpu` for `auto` without a usable GPU, with
/// the one warning of that fallback.
pub fn resolve_device(device: &str) -> Result<&'static str, MdError> {
    match (device, gpu_unavailable()) {
        ("cpu", _) => Ok("cpu"),
        ("cuda" | "auto", None) => Ok("cuda"),
        ("cuda", Some(why)) => Err(MdError::Device(why)),
        ("auto", Some(why)) => {
            fall_back_to_cpu(&why);
            Ok("cpu")
        }
        (other, _) => Err(MdError::invalid("device", format!("{other:?}; expected auto, cpu or cuda"))),
    }
}

/// The one warning of the `auto` device without a usable GPU.
fn fall_back_to_cpu(why: &dyn std::fmt::Display) {
    tracing::warn!("device auto: no usable GPU ({why}); running on the cpu back end");
}

/// Builds the back end `choice` asks for, for boxes of `pot`. `source` (the potential's file
/// as received) is needed by the `mpi` back end only, which ships it to its ranks.
pub fn build(choice: &BackendChoice, pot: Arc<Potential>, source: Option<&PotentialSource>) -> Result<Box<dyn MdBackend>, MdError> {
    let cpu = |pot| -> Box<dyn MdBackend> { Box::new(CpuBackend::on(pot, choice.threads.clone())) };
    if let Some(device) = &choice.device {
        let precision = choice.precision.as_str();
        if !matches!(precision, "double" | "mixed") {
            return Err(MdError::invalid("precision", format!("{precision:?}; expected double or mixed")));
        }
        return match device.as_str() {
            "cpu" => Ok(cpu(pot)),
            "cuda" => md_engine::device::backend_for_device("cuda", precision, pot),
            "auto" => match md_engine::device::backend_for_device("cuda", precision, pot.clone()) {
                Ok(b) => Ok(b),
                Err(e) => {
                    fall_back_to_cpu(&e);
                    Ok(cpu(pot))
                }
            },
            _ => Err(MdError::invalid("device", format!("{device:?}; expected auto, cpu or cuda"))),
        };
    }
    match choice.name.as_str() {
        "cpu" => Ok(cpu(pot)),
        "null" => Ok(Box::new(crate::null::NullBackend::default())),
        #[cfg(feature = "mpi")]
        "mpi" => {
            let src = source.ok_or_else(|| MdError::invalid("potential", "the mpi back end needs the potential's bytes"))?;
            Ok(Box::new(crate::mpi::MpiBackend::new(src, pot, choice.threads.clone())?))
        }
        name => {
            let _ = source;
            md_engine::device::backend_by_name(name, pot)
        }
    }
}

/// The back end `name` (see the module docs) on rayon's global pool.
pub fn backend_by_name(name: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    build(&BackendChoice::named(name), pot, None)
}

/// Back end for a device name (`auto`, `cpu`, `cuda`) and a GPU precision (`double` or
/// `mixed`; ignored on the CPU, which is always double).
pub fn backend_for_device(device: &str, precision: &str, pot: Arc<Potential>) -> Result<Box<dyn MdBackend>, MdError> {
    build(&BackendChoice::on_device(device, precision), pot, None)
}
