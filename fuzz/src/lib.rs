//! The bodies of the coverage-guided fuzz targets (cargo-afl, `fuzz/src/bin/*.rs`, run by
//! `scripts/afl.sh TARGET SECONDS`): each takes arbitrary bytes, puts them through the parser a
//! user or a peer reaches and what follows it, and must return without a panic, a hang or
//! unbounded memory (AFL counts a panic as a crash: the binaries abort on one). Errors are
//! values and fine.
//!
//! The same file is compiled into the default workspace by `tests/afl_corpus.rs`, which
//! replays the committed corpora (`fuzz/corpus/TARGET/`) through these functions without AFL in
//! the normal test command.
//!
//! Targets: `scene` (scene TOML with `#--set key=value` lines as overrides, as `mscale check`
//! loads it, the resolved scene read back, a small scene without MD built and stepped),
//! `eam` (first byte: the format, funcfl `.eam`, setfl `.eam.alloy` or Finnis-Sinclair
//! `.eam.fs`; a potential that parses is put through its time-step bound and a small box),
//! `lammps` (a LAMMPS data file: parsed, written back and read again, a box built from it),
//! `checkpoint` (first byte: which scene, and whether the rest is the whole file or its body
//! given a matching header; resumed as `mscale run --resume`), `users` (the users/tokens file), `step` (first byte: the coupling
//! message, an OpenRequest, a StepBatch, a RestoreRequest's box states, or StepResults; prost
//! decode and `md_worker::wire`'s conversion, as the worker and the pool do).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The workspace root (this file is compiled in `fuzz/` and in `tests/`, one level down).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("inside the workspace").to_path_buf()
}

/// A directory where scene files find what they name (`../md-worker/...` and
/// `../../md-worker/...` both resolve): scenes go into `a/b/`. Made once per process.
fn scene_home() -> &'static Path {
    static HOME: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &HOME
        .get_or_init(|| {
            let t = tempfile::tempdir().expect("a temporary directory");
            let r = repo();
            std::fs::create_dir_all(t.path().join("a/b")).expect("mkdir");
            for d in [t.path().to_path_buf(), t.path().join("a")] {
                for name in ["md-worker", "tests", "scenes"] {
                    std::os::unix::fs::symlink(r.join(name), d.join(name)).expect("symlink");
                }
            }
            let dir = t.path().join("a/b");
            (t, dir)
        })
        .1
}

/// Scene TOML and `#--set` overrides, as `mscale check` (and `mscale run`'s start) take them.
pub fn scene(data: &[u8]) {
    use orchestrator::loaded::Loaded;
    let text = String::from_utf8_lossy(data);
    let sets: Vec<String> = text.lines().filter_map(|l| l.strip_prefix("#--set ")).map(str::to_string).collect();
    let dir = scene_home();
    let path = dir.join(format!("fuzz-{}.toml", std::process::id()));
    std::fs::write(&path, data).expect("write the scene");
    match Loaded::load(&path, &sets) {
        Err(e) => assert!(!e.problem.is_empty(), "a refusal without a problem: {e}"),
        Ok(Loaded::Cell(c)) => {
            let out = orchestrator::cell_run::check_text(&c);
            let work = out.split("\n# work\n").nth(1).unwrap_or_default();
            assert!(!work.contains("NaN"), "mscale check of a cell scene printed NaN:\n{out}");
        }
        Ok(Loaded::Mpm(l)) => {
            let (per_body, nodes) = orchestrator::setup::work_size(&l.resolved);
            let points: usize = per_body.iter().map(|(_, n)| n).sum();
            let resolved = l.scene.to_toml();
            std::fs::write(&path, &resolved).expect("write the resolved scene");
            match Loaded::load(&path, &[]) {
                Ok(Loaded::Mpm(again)) => {
                    assert_eq!(again.scene.to_toml(), resolved, "the resolved scene does not read back as itself")
                }
                Ok(Loaded::Cell(_)) => panic!("a resolved MPM scene reads back as a cell scene"),
                Err(e) => panic!("the resolved scene of a valid one is refused: {e}\n{resolved}"),
            }
            if !l.scene.needs_md() && points <= 1000 && nodes <= 5000 {
                let _ = match l.resolved.dimension {
                    1 => build_and_step::<1>(&l),
                    2 => build_and_step::<2>(&l),
                    _ => build_and_step::<3>(&l),
                };
            }
        }
    }
}

fn build_and_step<const D: usize>(l: &orchestrator::scene::LoadedScene) -> Result<(), String> {
    let mut sim = orchestrator::setup::simulation::<D>(&l.resolved, None).map_err(|e| format!("setup: {e}"))?;
    for _ in 0..2 {
        sim.step().map_err(|e| format!("step: {}", orchestrator::exit::message(&e)))?;
    }
    Ok(())
}

/// What the engine does with a potential that parsed: the time-step bound, and a small box
/// built, evaluated and stepped.
fn exercise_potential(pot: md_worker::Potential) {
    use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind, MdBackend, ReferenceBackend};
    let _ = pot.max_time_step();
    let mut b = ReferenceBackend::new(std::sync::Arc::new(pot));
    let mut s = BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [1, 1, 1]);
    s.temperature_k = 300.0;
    if b.open(&[s]).is_ok() {
        let mut out = [BoxResult::default()];
        let _ = b.step(&[BoxWork::new(1, [[0.01, 0.0, 0.0], [0.0; 3], [0.0; 3]], 3, 0.001)], &mut out);
    }
}

/// An EAM potential file; the first byte picks the format (by the file name's extension).
pub fn eam(data: &[u8]) {
    let Some((&which, rest)) = data.split_first() else { return };
    let name = ["fuzz.eam", "fuzz.eam.alloy", "fuzz.eam.fs"][which as usize % 3];
    if let Ok(pot) = md_worker::Potential::from_text(name, &String::from_utf8_lossy(rest)) {
        exercise_potential(pot);
    }
}

/// The small potential shipped with md-worker.
fn u3() -> &'static md_worker::Potential {
    static POT: OnceLock<md_worker::Potential> = OnceLock::new();
    POT.get_or_init(|| {
        let text = std::fs::read_to_string(repo().join("md-worker/potentials/Cu_u3.eam")).expect("Cu_u3.eam");
        md_worker::Potential::from_text("Cu_u3.eam", &text).expect("Cu_u3.eam parses")
    })
}

/// A LAMMPS data file, as `md-worker eval` and `run` read it.
pub fn lammps(data: &[u8]) {
    use md_worker::data::DataFile;
    let pot = u3();
    let Ok(d) = DataFile::parse(&String::from_utf8_lossy(data), "fuzz.data") else { return };
    let again = DataFile::parse(&d.to_text("again"), "again").unwrap_or_else(|e| panic!("written data does not read back: {e}"));
    assert_eq!((&again.ids, &again.x, &again.v), (&d.ids, &d.x, &d.v), "written data reads back to other atoms");
    if d.x.len() > 4000 {
        return;
    }
    let masses: Vec<f64> = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
    let s = d.box_spec(0);
    if let Ok(st) = md_worker::backend::prepare_box(pot, &masses, &s) {
        assert!(st.meta.pe.is_finite(), "a box was built with a non-finite energy");
    }
}

/// The scenes whose checkpoints are fuzzed (as orchestrator/tests/fuzz_inputs.rs): a plain 1D
/// MPM run, an MD-coupled one (6 boxes of 32 atoms, the small potential), and the PNP cell.
pub fn checkpoint_scenes() -> Vec<(PathBuf, Vec<String>)> {
    let r = repo();
    let u3 = r.join("md-worker/potentials/Cu_u3.eam");
    let u3 = u3.to_str().expect("a UTF-8 path");
    vec![
        (r.join("tests/data/small.toml"), vec!["scheme.end_time=0.05".into(), "domain.cells=[20]".into()]),
        (
            r.join("tests/data/md-small.toml"),
            vec![format!("bodies.left.material.potential=\"{u3}\""), format!("bodies.right.material.potential=\"{u3}\"")],
        ),
        (r.join("scenes/pnp-debye.toml"), vec![]),
    ]
}

/// Options of `mscale run` into `out` (no progress bar), resuming or not, with a checkpoint
/// every `every` steps (0: none).
pub fn run_opts(out: &Path, resume: bool, every: u64) -> orchestrator::run::RunOptions {
    let mut o = orchestrator::run::RunOptions::new(out.to_path_buf(), vec!["fuzz".into()]);
    o.progress_bar = false;
    o.checkpoint_every = every;
    o.resume = resume;
    o
}

/// A checkpoint file, resumed as `mscale run --resume` does (written as the only checkpoint of
/// a fresh run directory). The first byte picks the scene (its value modulo 3) and the form of
/// the rest: with its top bit set the rest is the whole file; without, the rest is the JSON
/// body and the header (length and SHA-256) is made to match, as `checkpoint::encode` writes
/// it, so that mutations reach the body's reader past the hash check.
pub fn checkpoint(data: &[u8]) {
    use orchestrator::loaded::Loaded;
    use orchestrator::run::Outcome;
    use sha2::{Digest, Sha256};
    static SCENES: OnceLock<(Vec<Loaded>, tempfile::TempDir)> = OnceLock::new();
    let (scenes, work) = SCENES.get_or_init(|| {
        let loaded = checkpoint_scenes().iter().map(|(s, sets)| Loaded::load(s, sets).expect("a checkpoint scene loads")).collect();
        (loaded, tempfile::tempdir().expect("a temporary directory"))
    });
    let Some((&which, rest)) = data.split_first() else { return };
    let file = if which & 0x80 != 0 {
        rest.to_vec()
    } else {
        let mut f = format!("mscale-checkpoint 1 bytes={} sha256={}\n", rest.len(), hex::encode(Sha256::digest(rest))).into_bytes();
        f.extend_from_slice(rest);
        f
    };
    let which = (which & 0x7f) as usize % scenes.len();
    let out = work.path().join("resume");
    let _ = std::fs::remove_dir_all(&out);
    let ck = orchestrator::checkpoint::dir_of(&out);
    std::fs::create_dir_all(&ck).expect("mkdir");
    std::fs::write(ck.join("step-000000000002.ckpt"), file).expect("write the checkpoint");
    if let Ok(Outcome::Cancelled { .. }) = scenes[which].run(&run_opts(&out, true, 0)) {
        panic!("a resumed run was cancelled without a request")
    }
}

/// The users (tokens) file of `mscale serve --users`.
pub fn users(data: &[u8]) {
    let _ = orchestrator::service::parse_users(&String::from_utf8_lossy(data), "users.toml");
}

/// A coupling message as a worker or the pool decodes it. The first byte picks it, numbered
/// as md-worker/tests/fuzz_wire.rs numbers the worker's methods (so its corpus seeds this
/// target): 2 an OpenRequest (each box spec converted, and back), 3 a StepBatch (the step
/// batch converted to work), 5 a RestoreRequest (each box state decoded from JSON, restored
/// into the reference back end and stepped once), any other a StepResults (the pool's side:
/// converted and checked as a worker's answer).
pub fn step(data: &[u8]) {
    use md_worker::wire;
    use md_worker::{BoxResult, BoxWork, MdBackend, ReferenceBackend};
    use mscale_proto::coupling::v1 as pb;
    use prost::Message;
    let Some((&which, bytes)) = data.split_first() else { return };
    match which % 7 {
        2 => {
            for s in pb::OpenRequest::decode(bytes).map(|o| o.boxes).unwrap_or_default() {
                if let Ok(spec) = wire::spec_from_pb(&s) {
                    let again = wire::spec_from_pb(&wire::spec_to_pb(&spec));
                    assert!(again.is_ok(), "a converted spec does not convert back: {again:?}");
                }
            }
        }
        3 => {
            if let Ok(b) = pb::StepBatch::decode(bytes) {
                let _ = wire::batch_from_pb(&b);
            }
        }
        5 => {
            for raw in pb::RestoreRequest::decode(bytes).map(|r| r.states).unwrap_or_default().iter().take(4) {
                let Ok(state) = serde_json::from_slice::<md_worker::backend::BoxState>(raw) else { continue };
                let id = state.meta.id;
                if state.x.len() > 4000 {
                    continue;
                }
                let mut b = ReferenceBackend::new(std::sync::Arc::new(u3().clone()));
                if b.restore(vec![state]).is_ok() {
                    let mut out = [BoxResult::default()];
                    let _ = b.step(&[BoxWork::new(id, [[0.0; 3]; 3], 1, 0.001)], &mut out);
                }
            }
        }
        _ => {
            let results = pb::StepResults::decode(bytes).ok().and_then(|r| wire::results_from_pb(&r).ok()).unwrap_or_default();
            for res in &results {
                let _ = wire::check_result(res, "fuzz");
            }
        }
    }
}

/// The targets by name.
pub const TARGETS: [(&str, fn(&[u8])); 6] =
    [("scene", scene), ("eam", eam), ("lammps", lammps), ("checkpoint", checkpoint), ("users", users), ("step", step)];
