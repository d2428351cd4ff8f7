//! Replays the committed corpora of the coverage-guided fuzz targets (`fuzz/corpus/TARGET/`,
//! minimised with `afl-cmin` after the runs logged in fuzz/MEASUREMENTS.md) through the same
//! target bodies (`fuzz/src/lib.rs`, compiled here without AFL): no input may panic. Cheap: a
//! few hundred small inputs.
#![allow(clippy::unwrap_used)]

#[path = "../fuzz/src/lib.rs"]
#[allow(dead_code)]
mod targets;

use std::path::PathBuf;

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = mscale_testkit::repo().join("fuzz/corpus").join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files.into_iter().map(|f| (f.clone(), std::fs::read(&f).unwrap())).collect()
}

fn replay(target: &str) {
    let (_, body) = targets::TARGETS.iter().find(|(n, _)| *n == target).unwrap();
    let inputs = corpus(target);
    assert!(!inputs.is_empty(), "fuzz/corpus/{target} is empty");
    for (file, input) in &inputs {
        let r = std::panic::catch_unwind(|| body(input));
        assert!(r.is_ok(), "fuzz target {target}: {} panics", file.display());
    }
    eprintln!("{target}: {} inputs replayed, 0 panics", inputs.len());
}

#[test]
fn afl_corpus_scene() {
    replay("scene");
}

#[test]
fn afl_corpus_eam() {
    replay("eam");
}

#[test]
fn afl_corpus_lammps() {
    replay("lammps");
}

#[test]
fn afl_corpus_checkpoint() {
    replay("checkpoint");
}

#[test]
fn afl_corpus_users() {
    replay("users");
}

#[test]
fn afl_corpus_step() {
    replay("step");
}
