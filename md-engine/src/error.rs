//! The crate's error type.

/// Everything that can go wrong in the MD engine. Messages are lowercase and name the
/// file, line, component or value at fault.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MdError {
    /// A file could not be read or written.
    #[error("cannot access {file}")]
    Io {
        /// The file.
        file: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A potential, data or other input file is malformed or truncated.
    #[error("{file}:{line}: {msg}")]
    Parse {
        /// The file.
        file: String,
        /// 1-based line number (the line after the last one for a truncated file).
        line: usize,
        /// What was expected and what was found.
        msg: String,
    },
    /// An input value is out of range or inconsistent.
    #[error("invalid {what}: {msg}")]
    Invalid {
        /// The component or field at fault.
        what: String,
        /// Why.
        msg: String,
    },
    /// A feature that this engine does not provide was requested.
    #[error("unsupported: {0}")]
    Unsupported(String),
    /// A remote worker failed, was lost, or sent a bad reply.
    #[error("worker {worker}: {msg}")]
    Worker {
        /// Address or name of the worker.
        worker: String,
        /// What happened.
        msg: String,
    },
    /// A GPU back end is unavailable (no driver, NVRTC or device) or a device call failed.
    #[error("cuda: {0}")]
    Device(String),
    /// A box's MD diverged (an MD guard stopped it): non-finite or runaway atoms, a collapsed
    /// box. The input was accepted, the integration failed; the message is the diagnosis.
    #[error("point {point}: MD diverged: {msg}")]
    Diverged {
        /// The box (material point id).
        point: u64,
        /// What the guard found and what to do.
        msg: String,
    },
    /// A request named a box that this back end does not hold.
    #[error("unknown box (point id {0})")]
    UnknownBox(u64),
}

/// A number for a message: plain when of moderate size, else in exponent form (1e308 rather
/// than 309 digits).
pub fn show(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e9).contains(&v.abs()) { format!("{v}") } else { format!("{v:e}") }
}

impl MdError {
    /// Shorthand for [`MdError::Invalid`].
    pub fn invalid(what: impl Into<String>, msg: impl Into<String>) -> Self {
        MdError::Invalid { what: what.into(), msg: msg.into() }
    }
}
