//! Generates the gRPC code with a vendored protoc (no system protoc needed).
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; prost-build reads PROTOC from the environment.
    unsafe { std::env::set_var("PROTOC", protoc) };
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_build::configure()
        .file_descriptor_set_path(out.join("mscale_descriptor.bin"))
        .compile_protos(&["mscale/coupling/v1/coupling.proto", "mscale/orchestrator/v1/orchestrator.proto"], &["."])?;
    println!("cargo:rerun-if-changed=mscale");
    Ok(())
}
