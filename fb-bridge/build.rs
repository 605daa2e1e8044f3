//! Generates `fb_bridge::sparkplug::proto` from the vendored Sparkplug B schema
//! (`proto/sparkplug_b.proto`, Eclipse Tahu, EPL-2.0; see `proto/README.md`).
//!
//! `protox` parses the .proto in Rust and hands `prost-build` the descriptor set, so no
//! `protoc` binary is needed: a fresh checkout builds with cargo alone. The output,
//! `$OUT_DIR/org.eclipse.tahu.protobuf.rs` (named after the proto package), is included by
//! `src/sparkplug/proto.rs`.

use std::error::Error;

fn main() -> Result<(), Box<dyn Error>> {
    const PROTO: &str = "proto/sparkplug_b.proto";
    println!("cargo:rerun-if-changed={PROTO}");
    println!("cargo:rerun-if-changed=build.rs");

    let descriptors = protox::compile([PROTO], ["proto"])?;
    // Defaults throughout: `bytes` fields as `Vec<u8>`, enums as Rust enums with the
    // message fields holding their `i32`/`u32` numbers, as proto2 `optional` gives them.
    prost_build::Config::new().compile_fds(descriptors)?;
    Ok(())
}
