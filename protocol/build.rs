//! Compiles the protobuf schema with protox (pure Rust), so no system `protoc` is needed.
//! The compiled schema is also kept as a `FileDescriptorSet` ([`FILE_DESCRIPTOR_SET`] in the
//! crate): recordings embed it so that any protobuf tool decodes them without our sources.
use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let fds = protox::compile(["mfc/v1/mfc.proto"], ["proto"])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("mfc_descriptor_set.bin"), fds.encode_to_vec())?;
    // Serialize on every message, enum and oneof: operator tools print them as JSON.
    prost_build::Config::new()
        .type_attribute(".", "#[derive(serde::Serialize)]")
        .compile_fds(fds)?;
    Ok(())
}
