//! Compiles the vendored Foxglove schemas (`foxglove/foxglove/*.proto`, MIT, see
//! `foxglove/README.md`) with the pure-Rust `protox` compiler, generates their prost types and
//! keeps the encoded `FileDescriptorSet` the Foxglove channels of a bag embed as their schema.
use prost::Message;
use std::path::PathBuf;

/// The Foxglove messages scancorr writes, and its own deviation summary; protox adds their
/// imports.
const ROOTS: [&str; 5] = [
    "foxglove/scancorr/deviation.proto",
    "foxglove/foxglove/PointCloud.proto",
    "foxglove/foxglove/SceneUpdate.proto",
    "foxglove/foxglove/Log.proto",
    "foxglove/foxglove/FrameTransform.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=foxglove");
    let fds = protox::compile(ROOTS, ["foxglove"])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("foxglove_descriptor.bin"), fds.encode_to_vec())?;
    prost_build::Config::new()
        .compile_well_known_types()
        .compile_fds(fds)?;
    Ok(())
}
