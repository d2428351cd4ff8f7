//! Reads of a job's run directory (FetchResult, FetchRun): never outside it, never through a
//! link.

use super::MAX_MESSAGE;
use super::error::JobError;
use super::shared::Core;
use sha2::{Digest, Sha256};
use std::path::{Component, Path, PathBuf};

/// Largest chunk of FetchRun (bytes).
pub const FETCH_CHUNK: usize = 1 << 20;

/// A piece of a file of the run directory; a file's last piece carries its size and SHA-256.
pub(crate) struct Chunk {
    pub(crate) path: String,
    pub(crate) offset: u64,
    pub(crate) data: Vec<u8>,
    pub(crate) last: bool,
    /// The file's size (last chunk only, else 0).
    pub(crate) size: u64,
    /// The file's SHA-256 (last chunk only, else empty).
    pub(crate) sha256: String,
}

/// `rel` inside `root`, refusing absolute paths, `..`, and links that lead out.
pub fn contained(root: &Path, rel: &str) -> Result<PathBuf, JobError> {
    let refuse = || JobError::NotInRun(rel.to_string());
    let p = Path::new(rel);
    if rel.is_empty() || p.components().any(|c| !matches!(c, Component::Normal(_))) {
        return Err(refuse());
    }
    let root = root.canonicalize().map_err(|source| JobError::Unreadable { path: root.display().to_string(), source })?;
    let full = root.join(p).canonicalize().map_err(|source| JobError::Unreadable { path: rel.to_string(), source })?;
    if !full.starts_with(&root) || !full.is_file() {
        return Err(refuse());
    }
    Ok(full)
}

/// The regular files under `root` (relative, `/`-separated, sorted). Symbolic links and
/// anything else that is not a directory or a regular file are skipped, never followed.
pub fn run_files(root: &Path) -> std::io::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut dirs = vec![String::new()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(root.join(&dir))? {
            let entry = entry?;
            let Ok(name) = entry.file_name().into_string() else {
                tracing::warn!("fetch: skipping {} (its name is not UTF-8)", entry.path().display());
                continue;
            };
            let rel = if dir.is_empty() { name } else { format!("{dir}/{name}") };
            let ty = entry.file_type()?; // of the entry itself: links are not followed
            if ty.is_dir() {
                dirs.push(rel);
            } else if ty.is_file() {
                files.push(rel);
            } else {
                tracing::warn!("fetch: skipping {rel} in {} (not a regular file: links are not followed)", root.display());
            }
        }
    }
    files.sort();
    Ok(files)
}

/// Passes every regular file under `root` to `send` in chunks of at most `chunk` bytes, each
/// file's last chunk with its size and SHA-256, until `send` says the receiver has gone. A
/// file that vanished since the listing (a running job's old checkpoint) is skipped.
pub(crate) fn send_run(root: &Path, chunk: usize, mut send: impl FnMut(Chunk) -> bool) -> Result<(), JobError> {
    use std::io::Read;
    use std::os::unix::fs::OpenOptionsExt;
    let io = |what: &str, source: std::io::Error| JobError::Io { what: what.to_string(), source };
    for rel in run_files(root).map_err(|e| io(&root.display().to_string(), e))? {
        let path = root.join(&rel);
        // A directory on the way swapped for a link since the listing must not lead out.
        if !path.canonicalize().is_ok_and(|p| p.starts_with(root)) {
            tracing::warn!("fetch: skipping {rel} (it no longer resolves inside {})", root.display());
            continue;
        }
        let mut f = match std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW).open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(io(&rel, e)),
        };
        let (mut hasher, mut offset, mut buf) = (Sha256::new(), 0u64, vec![0u8; chunk]);
        loop {
            let mut n = 0;
            while n < chunk {
                match f.read(&mut buf[n..]).map_err(|e| io(&rel, e))? {
                    0 => break,
                    k => n += k,
                }
            }
            hasher.update(&buf[..n]);
            let last = n < chunk;
            let size = offset + n as u64;
            let sha256 = if last { hex::encode(hasher.clone().finalize()) } else { String::new() };
            if !send(Chunk { path: rel.clone(), offset, data: buf[..n].to_vec(), last, size: if last { size } else { 0 }, sha256 }) {
                return Ok(()); // the client has gone
            }
            offset = size;
            if last {
                break;
            }
        }
    }
    Ok(())
}

impl Core {
    /// The job's run directory, resolved.
    pub(crate) fn run_root(&self, id: &str) -> Result<PathBuf, JobError> {
        self.get(id)?;
        self.job_dir(id).join("run").canonicalize().map_err(|_| JobError::NoRunDir(id.to_string()))
    }

    /// One file of the job's run directory and its SHA-256 (hex).
    pub(crate) fn fetch_result(&self, id: &str, rel: &str) -> Result<(Vec<u8>, String), JobError> {
        let path = contained(&self.run_root(id)?, rel)?;
        let unreadable = |source| JobError::Unreadable { path: rel.to_string(), source };
        let len = std::fs::metadata(&path).map_err(unreadable)?.len();
        if len as usize > MAX_MESSAGE - 1024 {
            return Err(JobError::TooLarge { path: rel.to_string(), len, limit: MAX_MESSAGE });
        }
        let content = std::fs::read(&path).map_err(unreadable)?;
        let sha256 = hex::encode(Sha256::digest(&content));
        Ok((content, sha256))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fetch_paths_cannot_leave_the_run_directory() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        std::fs::create_dir_all(run.join("snapshots")).unwrap();
        std::fs::write(run.join("summary.json"), "{}").unwrap();
        std::fs::write(run.join("snapshots/index.csv"), "x").unwrap();
        std::fs::write(dir.path().join("secret"), "s").unwrap();
        std::os::unix::fs::symlink(dir.path().join("secret"), run.join("link")).unwrap();
        assert!(contained(&run, "summary.json").is_ok());
        assert!(contained(&run, "snapshots/index.csv").is_ok());
        for bad in ["../secret", "/etc/passwd", "snapshots/../../secret", "link", "", "snapshots", "./summary.json"] {
            assert!(contained(&run, bad).is_err(), "{bad} was let through");
        }
    }
}
