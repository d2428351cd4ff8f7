//! With the `cuda` feature: compile the CUDA kernels (src/cuda/kernels.cu) as host C++
//! through src/cuda/shim.h, so tests can run the very same kernel source on the CPU.
//! Without it: nothing. Always: the `require_*` cfgs of the tests from `MSCALE_REQUIRE_*`.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    // CI variables that turn an absent device or library into a failure (tests/cuda.rs,
    // tests/common): without them the tests that need it are ignored, with the reason.
    for (var, cfg) in [("MSCALE_REQUIRE_NVRTC", "require_nvrtc"), ("MSCALE_REQUIRE_GPU", "require_gpu")] {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        println!("cargo::rerun-if-env-changed={var}");
        if std::env::var(var).is_ok_and(|v| v == "1") {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
    #[cfg(feature = "cuda")]
    {
        println!("cargo:rerun-if-changed=src/cuda/kernels.cu");
        println!("cargo:rerun-if-changed=src/cuda/shim.h");
        cc::Build::new()
            .cpp(true)
            .file("src/cuda/kernels.cu")
            .define("MSCALE_HOST", None)
            .include("src/cuda")
            .flag_if_supported("-std=c++17")
            .flag_if_supported("-xc++")
            // Keep a*b+c as two roundings, as the reference back end does.
            .flag_if_supported("-ffp-contract=off")
            .opt_level(2)
            .warnings(true)
            .compile("mscale_md_kernels_host");
    }
}
