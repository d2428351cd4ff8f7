//! With the `cuda` feature: compile the CUDA kernels (src/cuda/kernels.cu) as host C++
//! through src/cuda/shim.h, so tests can run the very same kernel source on the CPU.
//! Without it: nothing. (md-worker's build.rs gives its tests the `require_*` cfgs.)

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
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
