//! Golden state digests: every scene shipped in scenes/ (and the test scenes of tests/data),
//! shortened to a few steps by `--set`, run through `mscale run`, must end with the
//! `state_digest` recorded in tests/golden/digests.toml. Any change to the results of a
//! shipped scene shows there: the test names the scene, the expected and the found digest.
//!
//! `mscale` is the prebuilt binary (mscale_testkit::prebuilt: `cargo test --workspace` builds
//! it; alone, `cargo build --profile test -p orchestrator --bin mscale` first).
//!
//! Regenerate (after a change of results that is meant and explained):
//! `MSCALE_BLESS=1 cargo test -p mscale-tests --test golden_digests` rewrites the digests and
//! step counts of the file's entries (their scenes and overrides are kept).

use mscale_testkit::{prebuilt, repo, summary};
use std::path::Path;
use std::process::Command;

const FILE: &str = "tests/golden/digests.toml";

/// The header of the golden file, written back by the bless mode.
const HEADER: &str = "\
# Golden state digests of every scene shipped in scenes/ (and the test scenes in tests/data),
# each shortened to a few steps by `--set`. Any change to the results of a shipped scene
# changes its digest here; tests/golden_digests.rs compares every entry.
# An entry is `mscale run <file> --set <each of set> --out DIR`, digest = summary.json's
# state_digest after `steps` steps.
# regenerate: MSCALE_BLESS=1 cargo test -p mscale-tests --test golden_digests
# (rewrites digests and steps; add a new scene as an entry with `file` and `set`, then bless)
# One digest per scene holds on every MD kernel path (MSCALE_MD_SIMD=scalar|avx2|avx512): the
# paths give bitwise the same results (md-engine/src/simd.rs), so an MD digest does not depend on
# the CPU. The cell scenes' (scenes/pnp-*.toml) may: faer's sparse LU picks its SIMD kernels at
# run time, so on another CPU type re-bless them and say so.
";

#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    file: String,
    set: Vec<String>,
    #[serde(default)]
    steps: u64,
    #[serde(default)]
    state_digest: String,
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Golden {
    scene: Vec<Entry>,
}

/// Runs one entry; returns (steps, state_digest).
fn run(entry: &Entry, out: &Path) -> Result<(u64, String), String> {
    let mut cmd = Command::new(prebuilt("mscale", "orchestrator"));
    cmd.args(["run", &entry.file, "--out"]).arg(out).current_dir(repo()).env("RUST_LOG", "warn");
    for s in &entry.set {
        cmd.args(["--set", s]);
    }
    let o = cmd.output().map_err(|e| format!("cannot start mscale: {e}"))?;
    if !o.status.success() {
        return Err(format!("mscale run exited with {:?}: {}", o.status.code(), String::from_utf8_lossy(&o.stderr)));
    }
    let s = summary(out);
    if s["status"] != "completed" {
        return Err(format!("status {} in summary.json", s["status"]));
    }
    let digest = s["state_digest"].as_str().ok_or("summary.json has no state_digest")?.to_string();
    Ok((s["steps"].as_u64().ok_or("summary.json has no steps")?, digest))
}

fn write(entries: &[Entry]) -> String {
    let mut text = HEADER.to_string();
    for e in entries {
        let set: Vec<String> = e.set.iter().map(|s| format!("{s:?}")).collect();
        text.push_str(&format!(
            "\n[[scene]]\nfile = {:?}\nset = [{}]\nsteps = {}\nstate_digest = {:?}\n",
            e.file,
            set.join(", "),
            e.steps,
            e.state_digest
        ));
    }
    text
}

#[test]
fn every_shipped_scene_has_its_golden_digest() {
    let path = repo().join(FILE);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(text.contains("# regenerate: "), "{FILE} lacks its regeneration command");
    let golden: Golden = toml::from_str(&text).unwrap_or_else(|e| panic!("{FILE}: {e}"));

    // Every scene in scenes/ has exactly one entry; every entry names an existing scene.
    let mut shipped: Vec<String> = std::fs::read_dir(repo().join("scenes"))
        .expect("scenes/")
        .flatten()
        .map(|e| format!("scenes/{}", e.file_name().to_string_lossy()))
        .filter(|n| n.ends_with(".toml"))
        .collect();
    shipped.sort();
    assert!(!shipped.is_empty(), "no scenes in scenes/");
    for s in &shipped {
        let n = golden.scene.iter().filter(|e| &e.file == s).count();
        assert_eq!(
            n, 1,
            "{s}: {n} entries in {FILE}; add one ([[scene]] with `file` and a short-run `set`), then bless: MSCALE_BLESS=1 cargo test -p mscale-tests --test golden_digests"
        );
    }
    for e in &golden.scene {
        assert!(repo().join(&e.file).is_file(), "{FILE} names {}, which does not exist", e.file);
    }

    let bless = std::env::var("MSCALE_BLESS").is_ok_and(|v| v == "1");
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut found = golden.scene.clone();
    let mut failures = Vec::new();
    for (k, e) in golden.scene.iter().enumerate() {
        let start = std::time::Instant::now();
        let command = format!("mscale run {} --set {} --out DIR", e.file, e.set.join(" --set "));
        match run(e, &tmp.path().join(k.to_string())) {
            Ok((steps, digest)) => {
                eprintln!("{}: {steps} steps, {digest} ({:.1} s)", e.file, start.elapsed().as_secs_f64());
                if (steps, digest.as_str()) != (e.steps, e.state_digest.as_str()) {
                    failures.push(format!(
                        "{}: expected {} ({} steps), found {digest} ({steps} steps)\n    {command}",
                        e.file, e.state_digest, e.steps
                    ));
                }
                found[k].steps = steps;
                found[k].state_digest = digest;
            }
            Err(why) => failures.push(format!("{}: the run failed: {why}\n    {command}", e.file)),
        }
    }
    if bless {
        assert!(failures.iter().all(|f| !f.contains("the run failed")), "cannot bless, runs failed:\n{}", failures.join("\n"));
        std::fs::write(&path, write(&found)).expect("write the golden file");
        eprintln!("blessed {FILE}: {} entries, {} changed", found.len(), failures.len());
        for f in &failures {
            eprintln!("  {f}");
        }
        return;
    }
    assert!(
        failures.is_empty(),
        "{} of {} golden digests differ (a change to results; if it is meant, explain it and bless: MSCALE_BLESS=1 cargo test -p mscale-tests --test golden_digests):\n{}",
        failures.len(),
        golden.scene.len(),
        failures.join("\n")
    );
}
