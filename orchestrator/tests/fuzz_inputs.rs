//! Fuzzing of what a user or a peer hands the orchestrator (see `mscale_testkit::fuzz`):
//! scene TOML with `--set` overrides (as `mscale check` and `mscale run` read them), checkpoint
//! files of MPM, MD-coupled and cell runs (bodies mutated with a valid checksum, then resumed
//! as `mscale run --resume` does), the users file of `mscale serve --users`, and every
//! protobuf message `mscale serve` decodes (raw bytes over gRPC to a real server, with each
//! role's token). No input may panic, hang or grow memory past the bound; every input that
//! once broke something is a named regression test below. Each target runs a fixed
//! number of mutations (MSCALE_FUZZ_ITERS or MSCALE_FUZZ_SECS change it); the corpora are in tests/fuzz-corpus/.
#![allow(clippy::unwrap_used)]

use mscale_proto::orchestrator::v1 as pb;
use mscale_testkit::fuzz::{Fuzzer, HOSTILE, Rng, Rng64, class_of, mutate_bytes, mutate_json, mutate_text, threads_of};
use mscale_testkit::{Listening, repo};
use orchestrator::loaded::Loaded;
use orchestrator::run::{Outcome, RunOptions};
use prost::Message;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

fn corpus_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-corpus")
}

/// A directory where scene files of `scenes/` and `tests/data/` find what they name
/// (`../md-worker/...` and `../../md-worker/...` both resolve): scenes go into `a/b/`.
fn scene_home() -> (tempfile::TempDir, PathBuf) {
    let t = tempfile::tempdir().unwrap();
    let r = repo();
    std::fs::create_dir_all(t.path().join("a/b")).unwrap();
    for d in [t.path().to_path_buf(), t.path().join("a")] {
        for name in ["md-worker", "tests", "scenes"] {
            std::os::unix::fs::symlink(r.join(name), d.join(name)).unwrap();
        }
    }
    let dir = t.path().join("a/b");
    (t, dir)
}

/// `--set` overrides travel inside the input as `#--set key=value` lines (TOML comments).
fn split_sets(text: &str) -> Vec<String> {
    text.lines().filter_map(|l| l.strip_prefix("#--set ")).map(str::to_string).collect()
}

/// Dotted keys of TOML text (tables and values), for `--set` mutations.
fn dotted_keys(text: &str) -> Vec<String> {
    fn walk(t: &dyn toml_edit::TableLike, prefix: &str, out: &mut Vec<String>) {
        for (k, item) in t.iter() {
            let key = if prefix.is_empty() { k.to_string() } else { format!("{prefix}.{k}") };
            out.push(key.clone());
            if let Some(sub) = item.as_table_like() {
                walk(sub, &key, out);
            }
        }
    }
    let mut out = Vec::new();
    if let Ok(doc) = text.parse::<toml_edit::DocumentMut>() {
        walk(doc.as_table(), "", &mut out);
    }
    out
}

fn mutate_scene(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    if rng.gen_bool(0.55) {
        return mutate_text(rng, parent, corpus);
    }
    let text = String::from_utf8_lossy(parent).into_owned();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let sets: Vec<usize> = lines.iter().enumerate().filter(|(_, l)| l.starts_with("#--set ")).map(|(i, _)| i).collect();
    if !sets.is_empty() && rng.gen_bool(0.2) {
        lines.remove(sets[rng.gen_range(0..sets.len())]);
    } else {
        let keys = dotted_keys(&text);
        let key = match rng.gen_range(0..10) {
            0 => ["", ".", "a..b", "scheme.", "=", "bodies.left.material.law.x", "output.dump_points[1]"][rng.gen_range(0..7)].to_string(),
            1 if !keys.is_empty() => format!("{}.extra", keys[rng.gen_range(0..keys.len())]),
            _ if !keys.is_empty() => keys[rng.gen_range(0..keys.len())].clone(),
            _ => "name".to_string(),
        };
        let value = match rng.gen_range(0..6) {
            0 => format!("{}", rng.gen_range(-3.0..3.0) * 10f64.powi(rng.gen_range(-20..20))),
            1 => format!("{}", rng.gen_range(0u64..100)),
            _ => HOSTILE[rng.gen_range(0..HOSTILE.len())].to_string(),
        };
        let eq = if rng.gen_bool(0.97) { "=" } else { "" };
        lines.insert(0, format!("#--set {key}{eq}{value}"));
    }
    (lines.join("\n") + "\n").into_bytes()
}

fn scene_seeds() -> Vec<Vec<u8>> {
    let r = repo();
    let mut seeds = Vec::new();
    for dir in [r.join("scenes"), r.join("tests/data")] {
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().flatten().map(|e| e.path()).collect();
        files.sort();
        for f in files.into_iter().filter(|f| f.extension().is_some_and(|e| e == "toml")) {
            seeds.push(std::fs::read(f).unwrap());
        }
    }
    seeds
}

/// What `mscale check` does with a scene (and, for a small one without MD, building it and
/// two steps, as `mscale run` starts): the outcome class.
fn check_scene(dir: &Path, input: &[u8]) -> String {
    let text = String::from_utf8_lossy(input);
    let sets = split_sets(&text);
    let path = dir.join("fuzz.toml");
    std::fs::write(&path, input).unwrap();
    match Loaded::load(&path, &sets) {
        Err(e) => {
            assert!(!e.problem.is_empty(), "a refusal without a problem: {e}");
            class_of(&format!("{}|{}", e.key, e.problem))
        }
        Ok(Loaded::Cell(c)) => {
            let out = orchestrator::cell_run::check_text(&c);
            let work = out.split("\n# work\n").nth(1).unwrap_or_default();
            assert!(!work.contains("NaN"), "mscale check of a cell scene printed NaN:\n{out}");
            "cell ok".into()
        }
        Ok(Loaded::Mpm(l)) => {
            let (per_body, nodes) = orchestrator::setup::work_size(&l.resolved);
            let points: usize = per_body.iter().map(|(_, n)| n).sum();
            // The resolved scene reads back as itself.
            let resolved = l.scene.to_toml();
            std::fs::write(&path, &resolved).unwrap();
            match Loaded::load(&path, &[]) {
                Ok(Loaded::Mpm(again)) => {
                    assert_eq!(again.scene.to_toml(), resolved, "the resolved scene does not read back as itself")
                }
                Ok(Loaded::Cell(_)) => panic!("a resolved MPM scene reads back as a cell scene"),
                Err(e) => panic!("the resolved scene of a valid one is refused: {e}\n{resolved}"),
            }
            if !l.scene.needs_md() && points <= 4000 && nodes <= 20_000 {
                let r = match l.resolved.dimension {
                    1 => build_and_step::<1>(&l),
                    2 => build_and_step::<2>(&l),
                    _ => build_and_step::<3>(&l),
                };
                return class_of(&format!("mpm {}", r.err().unwrap_or_default()));
            }
            "mpm ok (not built)".into()
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

#[test]
fn fuzz_scenes_and_set_overrides() {
    let (_t, dir) = scene_home();
    let mut f = Fuzzer::new("scene", &corpus_root(), scene_seeds(), 2_000);
    f.run(mutate_scene, |input| check_scene(&dir, input));
}

// --- checkpoints -------------------------------------------------------------------------

/// A checkpoint file of `body` (header with length and SHA-256, as checkpoint::encode writes).
fn with_header(body: &[u8]) -> Vec<u8> {
    let mut out = format!("mscale-checkpoint 1 bytes={} sha256={}\n", body.len(), hex::encode(Sha256::digest(body))).into_bytes();
    out.extend_from_slice(body);
    out
}

/// The scenes whose checkpoints are fuzzed, as (scene file, overrides): a plain 1D MPM run,
/// an MD-coupled one (6 boxes of 32 atoms, the small potential), and the PNP cell.
fn checkpoint_scenes() -> Vec<(PathBuf, Vec<String>)> {
    let r = repo();
    let u3 = r.join("md-worker/potentials/Cu_u3.eam");
    let u3 = u3.to_str().unwrap();
    vec![
        (r.join("tests/data/small.toml"), vec!["scheme.end_time=0.05".into(), "domain.cells=[20]".into()]),
        (
            r.join("tests/data/md-small.toml"),
            vec![format!("bodies.left.material.potential=\"{u3}\""), format!("bodies.right.material.potential=\"{u3}\"")],
        ),
        (r.join("scenes/pnp-debye.toml"), vec![]),
    ]
}

fn run_opts(out: &Path, resume: bool, every: u64) -> RunOptions {
    let mut o = RunOptions::new(out.to_path_buf(), vec!["fuzz".into()]);
    o.progress_bar = false;
    o.checkpoint_every = every;
    o.resume = resume;
    o
}

/// A checkpoint of each scene: the run goes to the end with a checkpoint every step; the
/// oldest checkpoint kept (the one before the last) is the seed. The input is the scene's
/// index byte followed by the checkpoint file.
fn checkpoint_seeds(scenes: &[(PathBuf, Vec<String>)], work: &Path) -> Vec<Vec<u8>> {
    let mut seeds = Vec::new();
    for (k, (scene, sets)) in scenes.iter().enumerate() {
        let loaded = Loaded::load(scene, sets).unwrap_or_else(|e| panic!("{}: {e}", scene.display()));
        let out = work.join(format!("seed-{k}"));
        let o = run_opts(&out, false, 1);
        match loaded.run(&o).unwrap() {
            Outcome::Completed(_) => {}
            Outcome::Failed(_, why) => panic!("{}: the seed run failed: {why}", scene.display()),
            Outcome::Cancelled { .. } => panic!("{}: the seed run was cancelled", scene.display()),
        }
        let all = orchestrator::checkpoint::list(&out).unwrap();
        assert!(!all.is_empty(), "{}: the seed run wrote no checkpoint", scene.display());
        let (_, path) = all.last().unwrap();
        let mut input = vec![k as u8];
        input.extend(std::fs::read(path).unwrap());
        seeds.push(input);
    }
    seeds
}

/// Mutates a checkpoint: mostly its JSON body (then the header is made to match, so the
/// mutation reaches the decoder and the restore), sometimes the raw bytes or the header.
fn mutate_checkpoint(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let (which, file) = (parent.first().copied().unwrap_or(0), parent.get(1..).unwrap_or_default());
    let body_at = file.iter().position(|&b| b == b'\n').map_or(file.len(), |p| p + 1);
    let mut out = vec![which];
    match rng.gen_range(0..10) {
        0 => out.extend(mutate_bytes(rng, file, corpus)),
        1 => {
            // The header only.
            let header = String::from_utf8_lossy(&file[..body_at]).into_owned();
            let m = mutate_text(rng, header.as_bytes(), corpus);
            out.extend(m);
            out.extend_from_slice(&file[body_at..]);
        }
        _ => match serde_json::from_slice::<serde_json::Value>(&file[body_at..]) {
            Ok(mut v) => {
                for _ in 0..rng.gen_range(1..=3) {
                    mutate_json(rng, &mut v);
                }
                out.extend(with_header(&serde_json::to_vec(&v).unwrap()));
            }
            Err(_) => {
                let body = mutate_bytes(rng, &file[body_at..], corpus);
                out.extend(with_header(&body));
            }
        },
    }
    out
}

/// Resumes the input's scene from the input's checkpoint (written as the only checkpoint of
/// a fresh run directory), as `mscale run --resume` does.
fn check_checkpoint(scenes: &[Loaded], work: &Path, input: &[u8]) -> String {
    let (which, file) = (input.first().copied().unwrap_or(0) as usize % scenes.len(), input.get(1..).unwrap_or_default());
    let out = work.join("resume");
    let _ = std::fs::remove_dir_all(&out);
    let ck = orchestrator::checkpoint::dir_of(&out);
    std::fs::create_dir_all(&ck).unwrap();
    std::fs::write(ck.join("step-000000000002.ckpt"), file).unwrap();
    match scenes[which].run(&run_opts(&out, true, 0)) {
        Ok(Outcome::Completed(_)) => format!("{which} completed"),
        Ok(Outcome::Failed(_, why)) => class_of(&format!("{which} failed {why}")),
        Ok(Outcome::Cancelled { .. }) => panic!("a resumed run was cancelled without a request"),
        Err(e) => {
            let m = format!("{e:#}");
            // The message of a damaged checkpoint names the file.
            class_of(&format!("{which} {}", m.replace(&out.display().to_string(), "RUN")))
        }
    }
}

#[test]
fn fuzz_checkpoint_files() {
    let work = tempfile::tempdir().unwrap();
    let scenes = checkpoint_scenes();
    let seeds = checkpoint_seeds(&scenes, work.path());
    let loaded: Vec<Loaded> = scenes.iter().map(|(s, sets)| Loaded::load(s, sets).unwrap()).collect();
    // The corpus keeps only small inputs: the seeds are made afresh on every run (the body
    // of a checkpoint holds this machine's paths and timings), mutations of them in memory.
    let mut f = Fuzzer::new("checkpoint", &corpus_root(), seeds, 4_000);
    f.run(mutate_checkpoint, |input| check_checkpoint(&loaded, work.path(), input));
}

// --- the users file ----------------------------------------------------------------------

fn users_seed() -> Vec<Vec<u8>> {
    let h = |t: &str| hex::encode(Sha256::digest(t.as_bytes()));
    vec![
        format!(
            "[[user]]\nname = \"alice\"\nrole = \"user\"\ntoken_sha256 = \"{}\"\nmax_jobs = 3\nmax_upload_bytes = 1000000\n\n\
             [[user]]\nname = \"root@site\"\nrole = \"admin\"\ntoken_sha256 = \"sha256:{}\"\n\n\
             [[user]]\nname = \"pool-1\"\nrole = \"worker\"\ntoken_sha256 = \"{}\"\nmax_snapshots = 10\n",
            h("a"),
            h("r").to_uppercase(),
            h("w")
        )
        .into_bytes(),
    ]
}

#[test]
fn fuzz_users_file() {
    let mut f = Fuzzer::new("users", &corpus_root(), users_seed(), 20_000);
    f.run(mutate_text, |input| {
        let text = String::from_utf8_lossy(input);
        match orchestrator::service::parse_users(&text, "users.toml") {
            Ok(users) => {
                assert!(!users.is_empty(), "a users file with no user was accepted");
                let names: std::collections::BTreeSet<&str> = users.iter().map(|u| u.name.as_str()).collect();
                assert_eq!(names.len(), users.len(), "a name given twice was accepted");
                format!("ok {}", users.len())
            }
            Err(e) => {
                let m = format!("{e:#}");
                assert!(m.contains("users.toml"), "a refusal that does not name the file: {m}");
                class_of(&m)
            }
        }
    });
}

// --- every message `mscale serve` decodes ------------------------------------------------

/// A codec of raw message bytes: what the fuzzer sends is exactly what the server decodes.
#[derive(Clone, Default)]
struct Raw;
struct RawEncoder;
struct RawDecoder;

impl tonic::codec::Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn encode(&mut self, item: Vec<u8>, dst: &mut tonic::codec::EncodeBuf<'_>) -> Result<(), tonic::Status> {
        use prost::bytes::BufMut;
        dst.put_slice(&item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawDecoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn decode(&mut self, src: &mut tonic::codec::DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
        use prost::bytes::Buf;
        let n = src.remaining();
        Ok(Some(src.copy_to_bytes(n).to_vec()))
    }
}

impl tonic::codec::Codec for Raw {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawEncoder;
    type Decoder = RawDecoder;
    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }
    fn decoder(&mut self) -> RawDecoder {
        RawDecoder
    }
}

const METHODS: &[(&str, bool)] = &[
    ("SubmitJob", false),
    ("ListJobs", false),
    ("GetJob", false),
    ("WatchJob", true),
    ("CancelJob", false),
    ("FetchResult", false),
    ("FetchRun", true),
    ("RegisterWorker", false),
    ("Heartbeat", false),
    ("DrainWorker", false),
    ("ListWorkers", false),
];
/// What `mscale` prints for a panic (its panic hook).
const PANIC: &str = "mscale: internal error";
const TOKENS: &[&str] = &["admin-token-0123456789", "alice-token-0123456789", "worker-token-0123456789", "", "not a token", "Bearer x"];

/// Sends raw bytes to `/mscale.orchestrator.v1.Orchestrator/<method>` with a token; a streamed
/// answer is read for up to two messages. Returns the outcome class (the status code and
/// message with numbers blanked, or "ok") and the answer's first message.
async fn call(channel: tonic::transport::Channel, method: &str, streamed: bool, token: &str, body: Vec<u8>) -> (String, Vec<u8>) {
    let mut grpc = tonic::client::Grpc::new(channel).max_decoding_message_size(64 << 20);
    if let Err(e) = grpc.ready().await {
        return (format!("not ready: {e}"), Vec::new());
    }
    let path: tonic::codegen::http::uri::PathAndQuery = format!("/mscale.orchestrator.v1.Orchestrator/{method}").parse().unwrap();
    let mut req = tonic::Request::new(body);
    if let Ok(v) = format!("Bearer {token}").parse() {
        req.metadata_mut().insert("authorization", v);
    }
    let class = |s: &tonic::Status| class_of(&format!("{method} {:?} {}", s.code(), s.message()));
    if streamed {
        match grpc.server_streaming(req, path, Raw).await {
            Err(s) => (class(&s), Vec::new()),
            Ok(r) => {
                let mut stream = r.into_inner();
                let mut first = Vec::new();
                for k in 0..2 {
                    match tokio::time::timeout(Duration::from_millis(300), stream.message()).await {
                        Ok(Ok(Some(m))) if k == 0 => first = m,
                        Ok(Ok(Some(_))) => {}
                        Ok(Ok(None)) | Err(_) => break,
                        Ok(Err(s)) => return (class(&s), first),
                    }
                }
                (format!("{method} ok"), first)
            }
        }
    } else {
        match grpc.unary(req, path, Raw).await {
            Ok(r) => (format!("{method} ok"), r.into_inner()),
            Err(s) => (class(&s), Vec::new()),
        }
    }
}

fn small_scene_submission(priority: i32) -> pb::SubmitJobRequest {
    let text = std::fs::read_to_string(repo().join("tests/data/small.toml")).unwrap();
    pb::SubmitJobRequest {
        scene_text: text,
        files: vec![],
        overrides: vec!["scheme.end_time=0.01".into()],
        priority,
        checkpoint_every_steps: 0,
        scene_file: "small.toml".into(),
        workers: 0,
        ranks: 1,
    }
}

/// Valid messages of every method (input: method byte, token byte, message bytes).
fn message_seeds(job: &str, worker_id: &str, epoch: u64) -> Vec<Vec<u8>> {
    let md = std::fs::read_to_string(repo().join("tests/data/md-small.toml")).unwrap();
    let u3 = std::fs::read(repo().join("md-worker/potentials/Cu_u3.eam")).unwrap();
    let md = md.replace("../../md-worker/potentials/Cu_mishin1.eam.alloy", "Cu_u3.eam");
    let md_sub = pb::SubmitJobRequest {
        scene_text: md,
        files: vec![pb::InputFile { name: "Cu_u3.eam".into(), sha256: hex::encode(Sha256::digest(&u3)), content: u3 }],
        overrides: vec![],
        priority: 0,
        checkpoint_every_steps: 1,
        scene_file: "md.toml".into(),
        workers: 1,
        ranks: 1,
    };
    let msgs: Vec<(u8, u8, Vec<u8>)> = vec![
        (0, 1, small_scene_submission(3).encode_to_vec()),
        (0, 0, md_sub.encode_to_vec()),
        (1, 1, pb::ListJobsRequest {}.encode_to_vec()),
        (2, 1, pb::GetJobRequest { job_id: job.into() }.encode_to_vec()),
        (3, 1, pb::WatchJobRequest { job_id: job.into(), after_sequence: 1 }.encode_to_vec()),
        (4, 0, pb::CancelJobRequest { job_id: job.into() }.encode_to_vec()),
        (5, 1, pb::FetchResultRequest { job_id: job.into(), path: "summary.json".into() }.encode_to_vec()),
        (5, 0, pb::FetchResultRequest { job_id: job.into(), path: "../../jobs.sqlite".into() }.encode_to_vec()),
        (6, 1, pb::FetchRunRequest { job_id: job.into(), chunk_bytes: 100 }.encode_to_vec()),
        (
            7,
            2,
            pb::RegisterWorkerRequest {
                address: "127.0.0.1:9".into(),
                device: "cpu".into(),
                backend: "cpu".into(),
                precision: "double".into(),
                cores: 2,
                memory_bytes: 1 << 30,
                atom_steps_per_s: 1e6,
                throughput_source: "configured".into(),
                protocol_version: 1,
            }
            .encode_to_vec(),
        ),
        (8, 2, pb::HeartbeatRequest { worker_id: worker_id.into(), epoch, protocol_version: 1 }.encode_to_vec()),
        (9, 0, pb::DrainWorkerRequest { worker_id: "w-none".into() }.encode_to_vec()),
        (10, 1, pb::ListWorkersRequest {}.encode_to_vec()),
    ];
    msgs.into_iter()
        .map(|(m, t, b)| {
            let mut v = vec![m, t];
            v.extend(b);
            v
        })
        .collect()
}

/// Mostly the message bytes; sometimes the method or the token.
fn mutate_message(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let (mut m, mut t) = (parent.first().copied().unwrap_or(0), parent.get(1).copied().unwrap_or(0));
    let mut body = parent.get(2..).unwrap_or_default().to_vec();
    match rng.gen_range(0..20) {
        0 => m = rng.gen_range(0..METHODS.len() as u8),
        1 => t = rng.gen_range(0..TOKENS.len() as u8),
        2 => body = corpus[rng.gen_range(0..corpus.len())].get(2..).unwrap_or_default().to_vec(),
        _ => body = mutate_bytes(rng, &body, corpus),
    }
    let mut out = vec![m, t];
    out.extend(body);
    out
}

fn users_file(dir: &Path) -> PathBuf {
    let h = |t: &str| hex::encode(Sha256::digest(t.as_bytes()));
    let text = format!(
        "[[user]]\nname = \"root\"\nrole = \"admin\"\ntoken_sha256 = \"{}\"\n\n[[user]]\nname = \"alice\"\nrole = \"user\"\ntoken_sha256 = \"{}\"\n\n[[user]]\nname = \"pool\"\nrole = \"worker\"\ntoken_sha256 = \"{}\"\n",
        h(TOKENS[0]),
        h(TOKENS[1]),
        h(TOKENS[2])
    );
    let f = dir.join("users.toml");
    std::fs::write(&f, text).unwrap();
    f
}

/// The last 40 lines of a log file.
fn tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

#[test]
fn fuzz_orchestrator_messages() {
    let tmp = tempfile::tempdir().unwrap();
    let users = users_file(tmp.path());
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mscale"));
    // Workers silent for 2 s are lost: registrations of the fuzzer do not pile up as live ones.
    cmd.args(["serve", "--state", tmp.path().join("state").to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .args(["--users", users.to_str().unwrap(), "--worker-timeout", "2", "--checkpoint-every", "5"])
        .env("RUST_LOG", "warn");
    let log = tmp.path().join("serve.log");
    let Listening { mut proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(&log));
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let channel = rt.block_on(tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect()).unwrap();
    // A job and a worker for the seeds to name.
    let (_, answer) = rt.block_on(call(channel.clone(), "SubmitJob", false, TOKENS[1], small_scene_submission(0).encode_to_vec()));
    let job = pb::SubmitJobResponse::decode(answer.as_slice()).unwrap().job_id;
    let (_, answer) = rt.block_on(call(channel.clone(), "RegisterWorker", false, TOKENS[2], {
        let mut s = message_seeds(&job, "", 0)[9].clone();
        s.drain(..2);
        s
    }));
    let reg = pb::RegisterWorkerResponse::decode(answer.as_slice()).unwrap();
    let mut f = Fuzzer::new("orchestrator-messages", &corpus_root(), message_seeds(&job, &reg.worker_id, reg.epoch), 8_000);
    f.watched_pid.store(proc.pid(), std::sync::atomic::Ordering::SeqCst);
    let (mut n, mut seen) = (0u64, 0u64);
    f.run(mutate_message, |input| {
        let (m, t) = (input[0] as usize % METHODS.len(), input[1] as usize % TOKENS.len());
        let (method, streamed) = METHODS[m];
        let body = input.get(2..).unwrap_or_default().to_vec();
        let (class, answer) = rt.block_on(async {
            match tokio::time::timeout(Duration::from_secs(30), call(channel.clone(), method, streamed, TOKENS[t], body)).await {
                Ok(r) => r,
                Err(_) => panic!(
                    "{method}: no answer within 30 s (a hang); the server's threads:\n{}\nits log ends:\n{}",
                    threads_of(proc.pid()),
                    tail(&log)
                ),
            }
        });
        // A job the fuzzer got submitted is cancelled at once (the queue stays short).
        if method == "SubmitJob"
            && let Ok(r) = pb::SubmitJobResponse::decode(answer.as_slice())
        {
            rt.block_on(call(channel.clone(), "CancelJob", false, TOKENS[0], pb::CancelJobRequest { job_id: r.job_id }.encode_to_vec()));
        }
        // What the server logged for this input: a panic fails it (with the input kept).
        let len = std::fs::metadata(&log).map_or(0, |m| m.len());
        if len != seen {
            let l = std::fs::read(&log).unwrap_or_default();
            let new = String::from_utf8_lossy(&l[(seen as usize).min(l.len())..]).into_owned();
            assert!(!new.contains(PANIC), "mscale serve panicked on a {method} message:\n{new}");
            seen = len;
        }
        n += 1;
        if n % 100 == 0 {
            assert!(proc.child.try_wait().unwrap().is_none(), "mscale serve exited; log:\n{}", std::fs::read_to_string(&log).unwrap());
        }
        class
    });
    // The server still answers, and never panicked.
    let (class, _) = rt.block_on(call(channel.clone(), "ListJobs", false, TOKENS[0], Vec::new()));
    assert_eq!(class, "ListJobs ok");
    assert!(proc.child.try_wait().unwrap().is_none(), "mscale serve exited");
    let l = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(!l.contains(PANIC), "mscale serve panicked; log:\n{l}");
}

// Inputs that broke the resume of a checkpoint, each found by fuzz_checkpoint_files.

/// The seed checkpoint of scene `k` of [`checkpoint_scenes`] as JSON, with the loaded scenes.
fn seed_json(k: usize, work: &Path) -> (serde_json::Value, Vec<Loaded>) {
    let scenes = checkpoint_scenes();
    let seeds = checkpoint_seeds(&scenes[k..=k], work);
    let file = &seeds[0][1..];
    let at = file.iter().position(|&b| b == b'\n').unwrap() + 1;
    let loaded = scenes.iter().map(|(s, sets)| Loaded::load(s, sets).unwrap()).collect();
    (serde_json::from_slice(&file[at..]).unwrap(), loaded)
}

fn resume_with(k: usize, v: &serde_json::Value, loaded: &[Loaded], work: &Path) -> String {
    let mut input = vec![k as u8];
    input.extend(with_header(&serde_json::to_vec(v).unwrap()));
    check_checkpoint(loaded, work, &input)
}

#[test]
fn a_cell_checkpoint_restarting_at_minus_9e18_s_is_refused_not_a_hang() {
    // Found by fuzz_checkpoint_files: restart.t = i64::MIN made the integrator start 9e18 s
    // before the end and run for ever.
    let work = tempfile::tempdir().unwrap();
    let (mut v, loaded) = seed_json(2, work.path());
    v["restart"]["t"] = serde_json::json!(i64::MIN);
    let r = resume_with(2, &v, &loaded, work.path());
    assert!(r.contains("cannot resume") && r.contains("lies outside the run's"), "{r}");
    let (mut v, _) = seed_json(2, work.path());
    v["restart"]["y"].as_array_mut().unwrap().pop();
    let r = resume_with(2, &v, &loaded, work.path());
    assert!(r.contains("its state has # values, the scene's model #"), "{r}");
}

#[test]
fn checkpoints_with_their_counters_at_u64_max_resume_or_are_refused_without_an_overflow() {
    // Found by fuzz_checkpoint_files: integration_point_updates and then closure_evaluations =
    // u64::MAX made the next step's counter overflow (a panic in a debug build). The first is
    // refused (no run of the checkpoint's steps and points makes that count); the closure
    // count saturates; a step count past the scene's steps ends the run at once.
    let work = tempfile::tempdir().unwrap();
    for k in 0..2 {
        let (seed, loaded) = seed_json(k, work.path());
        for field in ["integration_point_updates", "closure_evaluations", "step"] {
            let mut v = seed.clone();
            v[field] = serde_json::json!(u64::MAX);
            let r = resume_with(k, &v, &loaded, work.path());
            if field == "integration_point_updates" {
                assert!(r.contains("checkpoint field integration_point_updates = # exceeds"), "{field}: {r}");
            } else {
                assert!(!r.contains("panicked"), "{field}: {r}");
            }
        }
    }
    // The cell's step statistics (error_test_failures = u64::MAX overflowed the next step's).
    let (seed, loaded) = seed_json(2, work.path());
    let counters: Vec<String> =
        seed["restart"]["stats"].as_object().unwrap().iter().filter(|(_, x)| x.is_u64()).map(|(k, _)| k.clone()).collect();
    assert!(counters.len() >= 8, "{counters:?}");
    for c in &counters {
        let mut v = seed.clone();
        v["restart"]["stats"][c] = serde_json::json!(u64::MAX);
        let r = resume_with(2, &v, &loaded, work.path());
        assert!(!r.contains("panicked"), "{c}: {r}");
    }
}
