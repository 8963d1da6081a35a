//! Compiles `proto/` with protox (no system `protoc`) and generates the tonic services.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = ["proto/scatterfarm/v1/farm.proto"];
    for file in files {
        println!("cargo:rerun-if-changed={file}");
    }
    let descriptors = protox::compile(files, ["proto"])?;
    tonic_prost_build::configure()
        .bytes(".scatterfarm.v1.CountMatrix.counts_le_u32")
        .compile_fds(descriptors)?;
    Ok(())
}
