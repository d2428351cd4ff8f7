//! `MSCALE_REQUIRE_MPI=1` (set by CI, which provides MPI): the MPI tests of tests/mpi.rs run
//! and fail when MPI is absent, instead of being ignored. `MSCALE_REQUIRE_BROWSER=1` (CI,
//! after `bash deploy/setup.sh browser`): likewise the headless-Chromium test of the dashboard.
//! `MSCALE_REQUIRE_SLURM=1` (CI, after `bash deploy/setup.sh slurm`): the Slurm tests of
//! tests/slurm.rs.

fn main() {
    for (var, cfg) in
        [("MSCALE_REQUIRE_MPI", "require_mpi"), ("MSCALE_REQUIRE_BROWSER", "require_browser"), ("MSCALE_REQUIRE_SLURM", "require_slurm")]
    {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        println!("cargo::rerun-if-env-changed={var}");
        if std::env::var(var).is_ok_and(|v| v == "1") {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
}
