//! Atomic, durable file writes: every file mscale writes under a final name goes through here.
//! The content is written to a temporary file in the same directory and synced, renamed over
//! the final name, and the directory is synced, so after a crash the name holds either the old
//! content or the whole new one, and a completed write survives a power loss.

use anyhow::{Context, Result};
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// The temporary file [`write`] uses for `path`: `.NAME.tmpPID` next to it.
pub fn temp_path(path: &Path) -> PathBuf {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    dir.join(format!(".{name}.tmp{}", std::process::id()))
}

/// Writes `bytes` to `path` atomically (creating its directory if needed): temporary file,
/// fsync, rename, fsync of the directory.
pub fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create directory {}", dir.display()))?;
    let tmp = temp_path(path);
    let written = (|| {
        let mut f = std::fs::File::create(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?;
        f.write_all(bytes).and_then(|_| f.sync_all()).with_context(|| format!("cannot write {}", tmp.display()))?;
        drop(f);
        commit(&tmp, path)
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Puts a temporary file, already written and synced, in place: rename onto `dest`, then
/// fsync of `dest`'s directory (the rename reaches the disk).
pub fn commit(tmp: &Path, dest: &Path) -> Result<()> {
    std::fs::rename(tmp, dest).with_context(|| format!("cannot rename {} to {}", tmp.display(), dest.display()))?;
    let dir = dest.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::File::open(dir).and_then(|d| d.sync_all()).with_context(|| format!("cannot sync {}", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_whole_files_and_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a/b/out.txt");
        write(&path, b"first").unwrap();
        write(&path, b"second").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("out.txt")]);
        // A write that cannot be put in place leaves the old content and no temporary file.
        std::fs::create_dir_all(dir.path().join("d/x")).unwrap();
        std::fs::write(dir.path().join("d/x/keep"), "k").unwrap();
        assert!(write(&dir.path().join("d/x"), b"y").is_err());
        assert!(!temp_path(&dir.path().join("d/x")).exists());
        assert!(dir.path().join("d/x/keep").exists());
    }
}
