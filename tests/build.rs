//! `MSCALE_REQUIRE_MPI=1` (set by CI, which provides MPI): the MPI tests of tests/mpi.rs run
//! and fail when MPI is absent, instead of being ignored.

fn main() {
    println!("cargo::rustc-check-cfg=cfg(require_mpi)");
    println!("cargo::rerun-if-env-changed=MSCALE_REQUIRE_MPI");
    if std::env::var("MSCALE_REQUIRE_MPI").is_ok_and(|v| v == "1") {
        println!("cargo::rustc-cfg=require_mpi");
    }
}
