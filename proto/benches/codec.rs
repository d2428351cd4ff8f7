//! `cargo bench -p mscale-proto --bench codec`: prost's generated codec of the two
//! column-oriented `Step` messages (protocol 2), on one batch of 20,000 boxes each way. Prints
//! the message sizes and the medians of 31 runs of encode (into a reused buffer) and decode.
//! (Protocol 1's hand-written codec, src/fast.rs, was measured against these figures and
//! removed; README.md has both.)

#![allow(clippy::unwrap_used)] // a benchmark: a failed encode or decode is a bug to see at once

use mscale_proto::coupling::v1 as pb;
use mscale_proto::f64_column;
use prost::Message;
use std::hint::black_box;
use std::time::Instant;

const BOXES: u64 = 20_000;
const RUNS: usize = 31;

fn median(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// Median seconds of `f` over RUNS runs (after one warm-up).
fn time(mut f: impl FnMut()) -> f64 {
    f();
    median(
        (0..RUNS)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

fn main() {
    let ids = || (0..BOXES as usize).map(|i| i as u64);
    let batch = pb::StepBatch {
        session: 7,
        step: 123,
        point_id: ids().collect(),
        velocity_gradient: f64_column(ids().map(|i| std::array::from_fn::<f64, 9, _>(|k| (i as f64 + k as f64) * 1e-4 - 0.3))),
        steps: ids().map(|_| 10).collect(),
        dt_ps: f64_column(ids().map(|_| [0.001])),
        energy_to_add_ev: f64_column(ids().map(|i| [1e-3 * i as f64])),
        stress_sampling: ids().map(|_| 0).collect(),
    };
    let results = pb::StepResults {
        step: 123,
        compute_seconds: 0.5,
        point_id: ids().collect(),
        stress_gpa: f64_column(ids().map(|i| std::array::from_fn::<f64, 6, _>(|k| (i as f64) * 0.01 - k as f64))),
        potential_energy_ev: f64_column(ids().map(|i| [-3.5 * i as f64])),
        kinetic_energy_ev: f64_column(ids().map(|_| [0.04])),
        temperature_k: f64_column(ids().map(|i| [300.0 + i as f64])),
        lengths: f64_column(ids().map(|i| std::array::from_fn::<f64, 3, _>(|k| 18.0 + (i as f64 + k as f64) * 1e-6))),
        neighbor_rebuilds: ids().map(|_| 2).collect(),
        energy_shortfall_ev: f64_column(ids().map(|_| [0.0])),
        total_steps: ids().map(|i| 1000 + i).collect(),
        wraps: ids().map(|_| 3).collect(),
        stress_sampling: ids().map(|_| 0).collect(),
    };
    let (wb, rb) = (batch.encode_to_vec(), results.encode_to_vec());
    assert_eq!(pb::StepBatch::decode(&wb[..]).unwrap(), batch, "StepBatch does not survive a round trip");
    assert_eq!(pb::StepResults::decode(&rb[..]).unwrap(), results, "StepResults does not survive a round trip");
    let mut buf = Vec::with_capacity(wb.len().max(rb.len()));
    let mut enc = |m: &dyn Fn(&mut Vec<u8>)| {
        time(|| {
            buf.clear();
            m(&mut buf);
            black_box(&buf);
        })
    };
    let rows = [
        ("StepBatch", "encode", enc(&|b| batch.encode(b).unwrap())),
        ("StepResults", "encode", enc(&|b| results.encode(b).unwrap())),
        ("StepBatch", "decode", time(|| drop(black_box(pb::StepBatch::decode(&wb[..]).unwrap())))),
        ("StepResults", "decode", time(|| drop(black_box(pb::StepResults::decode(&rb[..]).unwrap())))),
    ];
    println!("{BOXES} boxes, medians of {RUNS} runs; StepBatch {} bytes, StepResults {} bytes", wb.len(), rb.len());
    println!("{:<12} {:<7} {:>10}", "message", "op", "prost_ms");
    for (m, op, t) in rows {
        println!("{m:<12} {op:<7} {:>10.3}", t * 1e3);
    }
}
