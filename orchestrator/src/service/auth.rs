//! Bearer tokens: read from a file or generated into the state directory, and checked in
//! constant time on every mutating call.

use super::error::JobError;
use super::shared::Core;
use anyhow::{Context, Result};
use std::path::Path;

/// Compares two byte strings in time that depends only on their lengths (`subtle`).
pub(crate) fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    use subtle::ConstantTimeEq;
    a.ct_eq(b).into()
}

/// Reads a token file (surrounding whitespace ignored); refuses an empty one.
pub fn read_token(path: &Path) -> Result<String> {
    let t = std::fs::read_to_string(path).with_context(|| format!("cannot read the token file {}", path.display()))?;
    let t = t.trim().to_string();
    anyhow::ensure!(!t.is_empty(), "the token file {} is empty", path.display());
    Ok(t)
}

/// The token in `<state>/token`, generated (256 bits from the operating system, mode 0600)
/// when missing.
pub(crate) fn generated_token(state: &Path) -> Result<String> {
    let path = state.join("token");
    if path.exists() {
        return read_token(&path);
    }
    std::fs::create_dir_all(state).with_context(|| format!("cannot create {}", state.display()))?;
    let mut bytes = [0u8; 32];
    getrandom::fill(&mut bytes).map_err(|e| anyhow::anyhow!("cannot get random bytes from the operating system for a token: {e}"))?;
    let token = hex::encode(bytes);
    {
        use std::io::Write;
        use std::os::unix::fs::OpenOptionsExt;
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        f.write_all(token.as_bytes())?;
        f.sync_all()?;
    }
    tracing::info!("generated a bearer token in {} (pass it with --token-file)", path.display());
    Ok(token)
}

impl Core {
    /// Whether `given` (the bearer token of a `call`, empty when none) is this orchestrator's.
    pub(crate) fn authorize(&self, given: &str, call: &str) -> Result<(), JobError> {
        if given.is_empty() {
            return Err(JobError::NoToken { call: call.to_string() });
        }
        if !constant_time_eq(given.as_bytes(), self.token.as_bytes()) {
            return Err(JobError::WrongToken { call: call.to_string() });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_compare_whole() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
    }

    #[test]
    fn a_generated_token_is_kept_private_and_reused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        let t = generated_token(&state).unwrap();
        assert_eq!(t.len(), 64);
        assert!(t.chars().all(|c| c.is_ascii_hexdigit()));
        assert_eq!(std::fs::metadata(state.join("token")).unwrap().permissions().mode() & 0o777, 0o600);
        assert_eq!(generated_token(&state).unwrap(), t);
        assert_ne!(generated_token(&dir.path().join("other")).unwrap(), t);
    }
}
