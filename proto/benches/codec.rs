//! `cargo bench -p mscale-proto --bench codec`: the hand-written codecs of the Step messages
//! (src/fast.rs) against prost's derived codec of the same messages (the generated `BoxWork`
//! and `BoxResult` in a prost-derived batch: what `tonic-build` would generate without the
//! `extern_path` mapping), on one batch of 20,000 boxes each way. Prints medians of 31 runs of
//! encode (into a reused buffer) and decode, and checks that both write the same bytes.

#![allow(clippy::unwrap_used)] // a benchmark: a failed encode or decode is a bug to see at once

use mscale_proto::coupling::v1 as pb;
use mscale_proto::fast::{Doubles, ResultItem, StepBatch, StepResults, WorkItem};
use prost::Message;
use std::hint::black_box;
use std::time::Instant;

#[derive(Clone, PartialEq, prost::Message)]
struct ProstStepBatch {
    #[prost(uint64, tag = "1")]
    session: u64,
    #[prost(uint64, tag = "2")]
    step: u64,
    #[prost(message, repeated, tag = "3")]
    work: Vec<pb::BoxWork>,
}

#[derive(Clone, PartialEq, prost::Message)]
struct ProstStepResults {
    #[prost(uint64, tag = "1")]
    step: u64,
    #[prost(message, repeated, tag = "2")]
    results: Vec<pb::BoxResult>,
    #[prost(double, tag = "3")]
    compute_seconds: f64,
}

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
    let g = |i: u64| -> [f64; 9] { std::array::from_fn(|k| (i as f64 + k as f64) * 1e-4 - 0.3) };
    let fast_batch = StepBatch {
        session: 7,
        step: 123,
        work: (0..BOXES)
            .map(|i| WorkItem {
                point_id: i,
                velocity_gradient: Doubles::full(g(i)),
                steps: 10,
                dt_ps: 0.001,
                energy_to_add_ev: 1e-3 * i as f64,
                stress_sampling: 0,
            })
            .collect(),
    };
    let prost_batch = ProstStepBatch {
        session: 7,
        step: 123,
        work: (0..BOXES)
            .map(|i| pb::BoxWork {
                point_id: i,
                velocity_gradient: g(i).to_vec(),
                steps: 10,
                dt_ps: 0.001,
                energy_to_add_ev: 1e-3 * i as f64,
                stress_sampling: 0,
            })
            .collect(),
    };
    let s = |i: u64| -> [f64; 6] { std::array::from_fn(|k| (i as f64) * 0.01 - k as f64) };
    let l = |i: u64| -> [f64; 3] { std::array::from_fn(|k| 18.0 + (i as f64 + k as f64) * 1e-6) };
    let fast_results = StepResults {
        step: 123,
        compute_seconds: 0.5,
        results: (0..BOXES)
            .map(|i| ResultItem {
                point_id: i,
                stress_gpa: Doubles::full(s(i)),
                potential_energy_ev: -3.5 * i as f64,
                kinetic_energy_ev: 0.04,
                temperature_k: 300.0 + i as f64,
                lengths: Doubles::full(l(i)),
                neighbor_rebuilds: 2,
                energy_shortfall_ev: 0.0,
                total_steps: 1000 + i,
                wraps: 3,
                stress_sampling: 0,
            })
            .collect(),
    };
    let prost_results = ProstStepResults {
        step: 123,
        compute_seconds: 0.5,
        results: (0..BOXES)
            .map(|i| pb::BoxResult {
                point_id: i,
                stress_gpa: s(i).to_vec(),
                potential_energy_ev: -3.5 * i as f64,
                kinetic_energy_ev: 0.04,
                temperature_k: 300.0 + i as f64,
                lengths: l(i).to_vec(),
                neighbor_rebuilds: 2,
                energy_shortfall_ev: 0.0,
                total_steps: 1000 + i,
                wraps: 3,
                stress_sampling: 0,
            })
            .collect(),
    };
    let (wb, rb) = (fast_batch.encode_to_vec(), fast_results.encode_to_vec());
    assert_eq!(wb, prost_batch.encode_to_vec(), "StepBatch: the codecs write different bytes");
    assert_eq!(rb, prost_results.encode_to_vec(), "StepResults: the codecs write different bytes");
    let mut buf = Vec::with_capacity(wb.len().max(rb.len()));
    let mut enc = |m: &dyn Fn(&mut Vec<u8>)| {
        time(|| {
            buf.clear();
            m(&mut buf);
            black_box(&buf);
        })
    };
    let rows = [
        ("StepBatch", "encode", enc(&|b| fast_batch.encode(b).unwrap()), enc(&|b| prost_batch.encode(b).unwrap())),
        ("StepResults", "encode", enc(&|b| fast_results.encode(b).unwrap()), enc(&|b| prost_results.encode(b).unwrap())),
        (
            "StepBatch",
            "decode",
            time(|| {
                black_box(StepBatch::decode(&wb[..]).unwrap());
            }),
            time(|| {
                black_box(ProstStepBatch::decode(&wb[..]).unwrap());
            }),
        ),
        (
            "StepResults",
            "decode",
            time(|| {
                black_box(StepResults::decode(&rb[..]).unwrap());
            }),
            time(|| {
                black_box(ProstStepResults::decode(&rb[..]).unwrap());
            }),
        ),
    ];
    println!("{BOXES} boxes, medians of {RUNS} runs; StepBatch {} bytes, StepResults {} bytes", wb.len(), rb.len());
    println!("{:<12} {:<7} {:>10} {:>10} {:>8}", "message", "op", "fast_ms", "prost_ms", "prost/fast");
    for (m, op, f, p) in rows {
        println!("{m:<12} {op:<7} {:>10.3} {:>10.3} {:>8.2}", f * 1e3, p * 1e3, p / f);
    }
}
