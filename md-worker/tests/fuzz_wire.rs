//! Fuzzing of every message `md-worker serve` decodes (see `mscale_testkit::fuzz`): Info,
//! HasPotential, Open, Step (the step batches, through the hand-written codec of
//! `mscale_proto::fast` and `wire::work_from_pb`), Snapshot, Restore (box states as JSON) and
//! Close, sent as raw bytes over gRPC to a real worker (the in-process loopback server on the
//! reference back end). Valid messages are mutated byte-wise (protobuf-aware) and, for the
//! box states, as JSON. No message may panic the server (a panic hook counts those of its
//! tasks), hang a call, or grow memory past the bound. Requests whose work is legitimately
//! large (more than 2,000 atoms, 50 relaxation steps, 10 MD steps or 16 boxes) have those
//! fields lowered before they are sent, so a run measures robustness, not MD throughput.
//! Each target runs a fixed number of mutations (MSCALE_FUZZ_ITERS or MSCALE_FUZZ_SECS change it).
#![allow(clippy::unwrap_used)]

use md_worker::server::Loopback;
use md_worker::{BoxWork, StressSampling, wire};
use mscale_proto::coupling::v1 as pb;
use mscale_testkit::fuzz::{Fuzzer, Rng, Rng64, class_of, mutate_bytes, mutate_json};
use prost::Message;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

static PANICS: AtomicU64 = AtomicU64::new(0);

fn corpus_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-corpus")
}

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

const METHODS: &[&str] = &["Info", "HasPotential", "Open", "Step", "Snapshot", "Restore", "Close"];

/// Sends raw bytes to `/mscale.coupling.v1.MdWorker/<method>`; Step sends the body (and a
/// second copy when `twice`) as a stream and reads the answers. Returns the outcome class and
/// the first answer.
async fn call(channel: tonic::transport::Channel, method: &str, body: Vec<u8>, twice: bool) -> (String, Vec<u8>) {
    let mut grpc = tonic::client::Grpc::new(channel).max_decoding_message_size(64 << 20);
    if let Err(e) = grpc.ready().await {
        return (format!("not ready: {e}"), Vec::new());
    }
    let path: tonic::codegen::http::uri::PathAndQuery = format!("/mscale.coupling.v1.MdWorker/{method}").parse().unwrap();
    let class = |s: &tonic::Status| class_of(&format!("{method} {:?} {}", s.code(), s.message()));
    if method == "Step" {
        let batches = if twice { vec![body.clone(), body] } else { vec![body] };
        let n = batches.len();
        match grpc.streaming(tonic::Request::new(tokio_stream::iter(batches)), path, Raw).await {
            Err(s) => (class(&s), Vec::new()),
            Ok(r) => {
                let mut stream = r.into_inner();
                let mut first = Vec::new();
                for k in 0..n {
                    match stream.message().await {
                        Ok(Some(m)) if k == 0 => first = m,
                        Ok(Some(_)) => {}
                        Ok(None) => break,
                        Err(s) => return (class(&s), first),
                    }
                }
                ("Step ok".into(), first)
            }
        }
    } else {
        match grpc.unary(tonic::Request::new(body), path, Raw).await {
            Ok(r) => (format!("{method} ok"), r.into_inner()),
            Err(s) => (class(&s), Vec::new()),
        }
    }
}

fn spec(id: u64, cells: u32, t: f64) -> pb::BoxSpec {
    pb::BoxSpec {
        point_id: id,
        lattice: "fcc".into(),
        lattice_constant: 3.615,
        cells: vec![cells; 3],
        strain: vec![0.01, 0.0, -0.01],
        temperature_k: t,
        seed: id,
        relax_steps: 3,
        relax_dt_ps: 0.001,
        relax_box_blocks: 1,
        deformation: "affine".into(),
        orientation: vec![],
    }
}

/// A step message of boxes `ids`, `steps` MD steps each (the coordinator's own encoding).
fn batch(session: u64, step: u64, ids: impl IntoIterator<Item = u64>, steps: u64) -> Vec<u8> {
    let work: Vec<BoxWork> = ids
        .into_iter()
        .map(|id| {
            let mut w = BoxWork::new(id, [[0.01, 0.0, 0.0], [0.0, -0.005, 0.0], [0.0; 3]], steps, 0.001);
            w.energy_to_add_ev = 0.01;
            w.stress_sampling = if id % 2 == 0 { StressSampling::Last } else { StressSampling::Average };
            w
        })
        .collect();
    wire::batch_to_pb(session, step, &work).encode_to_vec()
}

/// Lowers the work of a request that decodes to more than the bounds of the module doc; the
/// bytes are sent as they are otherwise.
fn bounded(method: &str, body: Vec<u8>, protected: u64) -> Vec<u8> {
    match method {
        "Open" => match pb::OpenRequest::decode(body.as_slice()) {
            Ok(mut r) => {
                let atoms: u64 =
                    r.boxes.iter().map(|b| b.cells.iter().fold(80u64, |n, &c| n.saturating_mul(c as u64))).fold(0u64, u64::saturating_add);
                let mut changed = false;
                if atoms > 2000 || r.boxes.len() > 16 {
                    r.boxes.truncate(16);
                    for b in &mut r.boxes {
                        for c in &mut b.cells {
                            *c = (*c).min(2);
                        }
                        b.orientation.clear();
                    }
                    changed = true;
                }
                for b in &mut r.boxes {
                    if b.relax_steps > 50 {
                        b.relax_steps = 50;
                        changed = true;
                    }
                }
                // Joining the protected session would grow it for good.
                if r.session == protected {
                    r.session = 0;
                    changed = true;
                }
                if changed { r.encode_to_vec() } else { body }
            }
            Err(_) => body,
        },
        "Step" => match pb::StepBatch::decode(body.as_slice()) {
            Ok(mut b) => {
                let big = b.point_id.len() > 16 || b.steps.iter().any(|&s| s > 10);
                if big {
                    // Every column cut to 16 boxes (a column of the wrong length stays wrong).
                    b.point_id.truncate(16);
                    b.velocity_gradient.truncate(16 * 9 * 8);
                    b.steps.truncate(16);
                    b.dt_ps.truncate(16 * 8);
                    b.energy_to_add_ev.truncate(16 * 8);
                    b.stress_sampling.truncate(16);
                    for s in &mut b.steps {
                        *s = (*s).min(10);
                    }
                    b.encode_to_vec()
                } else {
                    body
                }
            }
            Err(_) => body,
        },
        _ => body,
    }
}

/// Restore requests get JSON mutations of a box state half the time; everything else is
/// mutated byte-wise (the method byte rarely).
fn mutate_message(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let mut m = parent.first().copied().unwrap_or(0);
    let mut body = parent.get(1..).unwrap_or_default().to_vec();
    if rng.gen_range(0..25) == 0 {
        m = rng.gen_range(0..METHODS.len() as u8);
    } else if METHODS[m as usize % METHODS.len()] == "Restore"
        && rng.gen_bool(0.5)
        && let Ok(mut r) = pb::RestoreRequest::decode(body.as_slice())
        && !r.states.is_empty()
    {
        let k = rng.gen_range(0..r.states.len());
        if let Ok(mut v) = serde_json::from_slice::<serde_json::Value>(&r.states[k]) {
            for _ in 0..rng.gen_range(1..=3) {
                mutate_json(rng, &mut v);
            }
            r.states[k] = serde_json::to_vec(&v).unwrap();
            body = r.encode_to_vec();
        }
    } else {
        body = mutate_bytes(rng, &body, corpus);
    }
    let mut out = vec![m];
    out.extend(body);
    out
}

#[test]
fn fuzz_worker_messages() {
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        PANICS.fetch_add(1, Ordering::SeqCst);
        hook(info);
    }));
    let worker = Loopback::start("reference").unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let channel = rt.block_on(tonic::transport::Endpoint::from_shared(format!("http://{}", worker.addr)).unwrap().connect()).unwrap();
    let pot = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("potentials/Cu_u3.eam")).unwrap();
    let pref = pb::PotentialRef { name: "Cu_u3.eam".into(), sha256: hex::encode(Sha256::digest(&pot)) };
    let open = |boxes: Vec<pb::BoxSpec>, bytes: Vec<u8>, session: u64| pb::OpenRequest {
        protocol_version: mscale_proto::COUPLING_PROTOCOL_VERSION,
        potential: Some(pref.clone()),
        potential_bytes: bytes,
        boxes,
        backend: "reference".into(),
        session,
    };
    // The protected session the Step, Snapshot and Restore seeds name.
    let (class, answer) = rt.block_on(call(
        channel.clone(),
        "Open",
        open((1..=4).map(|i| spec(i, 1 + (i % 2) as u32, 100.0 * i as f64)).collect(), pot.clone(), 0).encode_to_vec(),
        false,
    ));
    assert_eq!(class, "Open ok");
    let session = pb::OpenResponse::decode(answer.as_slice()).unwrap().session;
    let (_, snap) =
        rt.block_on(call(channel.clone(), "Snapshot", pb::SnapshotRequest { session, point_ids: vec![1, 2] }.encode_to_vec(), false));
    let states = pb::SnapshotResponse::decode(snap.as_slice()).unwrap().states;
    let seeds: Vec<(u8, Vec<u8>)> = vec![
        (0, pb::InfoRequest {}.encode_to_vec()),
        (1, pref.encode_to_vec()),
        (2, open(vec![spec(10, 1, 0.0), spec(11, 2, 300.0)], vec![], 0).encode_to_vec()),
        (2, {
            let mut o = open(vec![spec(12, 1, 50.0)], vec![], 0);
            o.boxes[0].orientation = vec![1, 1, 0, -1, 1, 0, 0, 0, 1];
            o.boxes[0].deformation = "seed".into();
            o.encode_to_vec()
        }),
        (3, batch(session, 7, 1..=4, 2)),
        (4, pb::SnapshotRequest { session, point_ids: vec![1, 2, 3] }.encode_to_vec()),
        (5, pb::RestoreRequest { session, states: states.clone() }.encode_to_vec()),
        (6, pb::CloseRequest { session: session + 1000 }.encode_to_vec()),
    ];
    let seeds = seeds
        .into_iter()
        .map(|(m, b)| {
            let mut v = vec![m];
            v.extend(b);
            v
        })
        .collect();
    let mut f = Fuzzer::new("worker-messages", &corpus_root(), seeds, 10_000);
    let restore_protected = pb::RestoreRequest { session, states }.encode_to_vec();
    let mut n = 0u64;
    f.run(mutate_message, |input| {
        let method = METHODS[input[0] as usize % METHODS.len()];
        let mut body = bounded(method, input.get(1..).unwrap_or_default().to_vec(), session);
        // Closing the protected session is sent as closing a fresh one.
        if method == "Close" && pb::CloseRequest::decode(body.as_slice()).is_ok_and(|c| c.session == session) {
            let (_, a) = rt.block_on(call(channel.clone(), "Open", open(vec![spec(20, 1, 0.0)], vec![], 0).encode_to_vec(), false));
            let s = pb::OpenResponse::decode(a.as_slice()).map_or(0, |r| r.session);
            body = pb::CloseRequest { session: s }.encode_to_vec();
        }
        let twice = input.len() % 3 == 0;
        let (class, answer) = rt.block_on(async {
            match tokio::time::timeout(Duration::from_secs(30), call(channel.clone(), method, body, twice)).await {
                Ok(r) => r,
                Err(_) => panic!("{method}: no answer within 30 s (a hang)"),
            }
        });
        // Sessions the fuzzer opened are closed again, so the worker's memory stays bounded.
        if method == "Open"
            && let Ok(r) = pb::OpenResponse::decode(answer.as_slice())
            && r.session != session
        {
            rt.block_on(call(channel.clone(), "Close", pb::CloseRequest { session: r.session }.encode_to_vec(), false));
        }
        // A restore the worker accepted changed the protected boxes: they are put back.
        let mut class = class;
        if method == "Restore" && class == "Restore ok" {
            // What the accepted states step to: finite results or a refusal, never NaN.
            let (c, a) = rt.block_on(call(channel.clone(), "Step", batch(session, 1, 1..=4, 1), false));
            if let Ok(r) = pb::StepResults::decode(a.as_slice()) {
                let columns = [&r.stress_gpa, &r.lengths, &r.potential_energy_ev, &r.kinetic_energy_ev, &r.temperature_k];
                let mut all = columns.iter().flat_map(|c| mscale_proto::f64_values(c).expect("the worker's own column"));
                assert!(all.all(|v| v.is_finite()), "restored states stepped to non-finite results: {r:?}");
            }
            class = format!("{class} then {c}");
            let (c, _) = rt.block_on(call(channel.clone(), "Restore", restore_protected.clone(), false));
            assert_eq!(c, "Restore ok");
        }
        n += 1;
        assert_eq!(PANICS.load(Ordering::SeqCst), 0, "the worker panicked on a {method} message (see the log above)");
        class
    });
    // Still serving, with its protected session intact.
    let (class, _) = rt.block_on(call(channel.clone(), "Step", batch(session, 8, [1], 1), false));
    assert_eq!(class, "Step ok");
    assert_eq!(PANICS.load(Ordering::SeqCst), 0);
    assert!(n > 0);
}
