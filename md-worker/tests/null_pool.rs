//! The coupling path without MD: `md-worker bench-coupling` runs a pool over loopback workers
//! serving the null back end, which answers every box, in order, with the lengths it was
//! opened with.

#[test]
fn loopback_pool_round_trips_every_box() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_md-worker"))
        .args(["bench-coupling", "--points", "300", "--workers", "3", "--reps", "5"])
        .output()
        .expect("run md-worker bench-coupling");
    assert!(out.status.success(), "bench-coupling failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON line");
    let times = v["all_ms"].as_array().expect("all_ms");
    let median = v["median_ms"].as_f64().expect("median_ms");
    assert_eq!(times.len(), 5);
    assert!(median > 0.0 && median.is_finite());
}
