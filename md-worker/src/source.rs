//! A potential file as it travels: to remote workers (by SHA-256, with its bytes the first
//! time) and to the ranks of the mpi back end.

use crate::error::MdError;
use crate::potential::Potential;
use sha2::{Digest, Sha256};
use std::sync::Arc;

/// A potential file as shipped to workers: its name, bytes and SHA-256.
#[derive(Debug, Clone)]
pub struct PotentialSource {
    pub name: String,
    pub bytes: Arc<Vec<u8>>,
    pub sha256: String,
}

impl PotentialSource {
    pub fn from_file(path: &std::path::Path) -> Result<Self, MdError> {
        let bytes = std::fs::read(path).map_err(|e| MdError::Io { file: path.display().to_string(), source: e })?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(Self::from_bytes(name, bytes))
    }

    pub fn from_bytes(name: String, bytes: Vec<u8>) -> Self {
        let sha256 = hex::encode(Sha256::digest(&bytes));
        PotentialSource { name, bytes: Arc::new(bytes), sha256 }
    }

    /// Parses the potential (the format follows the file name).
    pub fn parse(&self) -> Result<Potential, MdError> {
        let text = std::str::from_utf8(&self.bytes).map_err(|_| MdError::Parse {
            file: self.name.clone(),
            line: 1,
            msg: "not a text file".into(),
        })?;
        Potential::from_text(&self.name, text)
    }
}
