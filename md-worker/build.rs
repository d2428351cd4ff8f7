//! The `require_*` cfgs of the tests from the CI variables `MSCALE_REQUIRE_*`: without them
//! the tests that need a GPU or NVRTC are ignored, with the reason (tests/cuda.rs,
//! tests/common); with them, an absent device or library fails those tests.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    for (var, cfg) in [("MSCALE_REQUIRE_NVRTC", "require_nvrtc"), ("MSCALE_REQUIRE_GPU", "require_gpu")] {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        println!("cargo::rerun-if-env-changed={var}");
        if std::env::var(var).is_ok_and(|v| v == "1") {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
}
