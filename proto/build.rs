//! Compiles `scancorr/v1/scancorr.proto` with the pure-Rust `protox` compiler (no system
//! `protoc`), generates the prost types and keeps the encoded `FileDescriptorSet`, which bag
//! files embed as their schema.
use prost::Message;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=scancorr/v1/scancorr.proto");
    let fds = protox::compile(["scancorr/v1/scancorr.proto"], ["."])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("scancorr_v1_descriptor.bin"), fds.encode_to_vec())?;
    prost_build::Config::new().compile_fds(fds)?;
    Ok(())
}
