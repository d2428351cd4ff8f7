//! A full disk while a run writes: a file-size limit (`ulimit -f` on the `mscale run` child)
//! that a checkpoint or a snapshot does not fit under makes the write fail with EFBIG (mscale
//! ignores SIGXFSZ, which would otherwise kill it without a word). The run must end with exit
//! code 1 and a message naming the file and the cause, leave no half-written file under a
//! final name and no temporary file, keep the previous checkpoint as it was, and resume from
//! it, without the limit, to the digest of an undisturbed run.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SMALL: &str = "../tests/data/small.toml";
/// 800 points, 80 steps, a snapshot every 40: checkpoints of about 300 kB, snapshots of 70 kB.
const SETS: [&str; 4] = ["--set", "domain.cells=[200]", "--set", "output.snapshots=2"];

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

fn mscale(args: &[&str]) -> Output {
    Command::new(bin()).args(args).env("RUST_LOG", "warn").output().unwrap()
}

/// `mscale ARGS` under `ulimit -f KB` (bash counts the limit in 1024-byte blocks).
fn mscale_limited(kb: u64, args: &[&str]) -> Output {
    let quoted: Vec<String> = args.iter().map(|a| format!("'{a}'")).collect();
    Command::new("bash")
        .args(["-c", &format!("ulimit -f {kb} && exec '{}' {}", bin(), quoted.join(" "))])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap()
}

fn ok(args: &[&str]) {
    let o = mscale(args);
    assert!(o.status.success(), "mscale {args:?}: {}", String::from_utf8_lossy(&o.stderr));
}

fn digest(dir: &Path) -> String {
    mscale_testkit::state_digest(dir)
}

/// Every file under `dir` with its bytes, relative names, sorted.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push((p.strip_prefix(root).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

fn checkpoints(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    files(&dir.join("checkpoints"))
}

/// A completed run with checkpoints, and its digest.
fn completed(tmp: &Path, name: &str, every: &str) -> (PathBuf, String) {
    let dir = tmp.join(name);
    ok(&[&["run", SMALL, "--out", dir.to_str().unwrap(), "--checkpoint-every", every][..], &SETS].concat());
    let d = digest(&dir);
    (dir, d)
}

/// The checks after a write that did not fit: exit code 1, the message, no temporary file, the
/// checkpoints as before, and a resume without the limit to the undisturbed digest.
fn failed_cleanly(o: &Output, dir: &Path, what: &str, before: &[(PathBuf, Vec<u8>)], reference: &str) {
    let log = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{log}");
    assert!(log.contains(what) && log.contains("File too large"), "the message names neither the file nor the cause: {log}");
    let all = files(dir);
    let temps: Vec<_> = all.iter().filter(|(p, _)| p.to_string_lossy().contains(".tmp")).map(|(p, _)| p.clone()).collect();
    assert!(temps.is_empty(), "temporary files left behind: {temps:?}");
    assert_eq!(checkpoints(dir), before, "the checkpoints changed");
    // Every snapshot under its final name is whole: as many lines as the first one, the last
    // one ended.
    let snaps: Vec<_> = all
        .iter()
        .filter(|(p, _)| p.starts_with("snapshots") && p.extension().is_some_and(|e| e == "csv") && !p.ends_with("index.csv"))
        .collect();
    let lines = |b: &[u8]| b.iter().filter(|&&c| c == b'\n').count();
    for (p, b) in &snaps {
        assert!(b.ends_with(b"\n") && lines(b) == lines(&snaps[0].1), "{} is cut short", p.display());
    }
    ok(&["run", "--resume", dir.to_str().unwrap()]);
    assert_eq!(digest(dir), reference, "the resumed run differs from the undisturbed one");
}

#[test]
fn a_checkpoint_that_does_not_fit_ends_the_run_cleanly_and_the_previous_one_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let (dir, reference) = completed(tmp.path(), "run", "20");
    let before = checkpoints(&dir);
    assert_eq!(before.len(), 2, "{:?}", before.iter().map(|c| &c.0).collect::<Vec<_>>());
    let ck = before.iter().map(|(_, b)| b.len() as u64).min().unwrap();
    // Room for the snapshots and everything else, not for a checkpoint.
    let limit = ck / 1024 / 2;
    std::fs::remove_file(dir.join("summary.json")).unwrap();
    let o = mscale_limited(limit, &["run", "--resume", dir.to_str().unwrap(), "--checkpoint-every", "1"]);
    failed_cleanly(&o, &dir, "checkpoints/.step-", &before, &reference);
}

#[test]
fn a_snapshot_that_does_not_fit_ends_the_run_cleanly_and_the_checkpoint_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    // Checkpoints at steps 30 and 60; resumed from 30, the snapshot of step 40 is the first
    // file written.
    let (dir, reference) = completed(tmp.path(), "run", "30");
    let newest = checkpoints(&dir).iter().map(|(p, _)| p.clone()).max().unwrap();
    std::fs::remove_file(dir.join("checkpoints").join(&newest)).unwrap();
    std::fs::remove_file(dir.join("summary.json")).unwrap();
    let before = checkpoints(&dir);
    assert_eq!(before.len(), 1);
    let o = mscale_limited(4, &["run", "--resume", dir.to_str().unwrap()]);
    failed_cleanly(&o, &dir, "snapshot", &before, &reference);
}
