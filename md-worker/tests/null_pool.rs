//! The coupling path without MD: a pool over loopback workers running the null back end
//! answers every box, in order, with the lengths it was opened with.

#[test]
fn loopback_pool_round_trips_every_box() {
    let (median, times) = md_worker::null::coupling_round_trip(300, 3, 5).expect("round trip");
    assert_eq!(times.len(), 5);
    assert!(median > 0.0 && median.is_finite());
}
