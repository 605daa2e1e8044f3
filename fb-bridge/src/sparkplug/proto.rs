//! The Sparkplug B protobuf messages: [`Payload`], [`payload::Metric`] with its value
//! `oneof` [`payload::metric::Value`], and the [`DataType`] numbers. Generated at build
//! time (`fb-bridge/build.rs`) by `prost-build` from Eclipse Tahu's `sparkplug_b.proto`
//! (proto package `org.eclipse.tahu.protobuf`; EPL-2.0, see `fb-bridge/proto/README.md`).
//!
//! Metric fields hold the datatype as a `u32` (`Some(DataType::Int16 as u32)`);
//! `DataType::try_from(i32)` reads one back. proto2 `optional` fields are `Option`s.
//! Decoding (`prost::Message::decode`) refuses messages nested deeper than prost's
//! recursion limit (100), so a `Template` inside a `Template` ... cannot exhaust the stack.

// Generated code, not ours to restyle. clippy 1.95 finds nothing in it, but prost's output
// has tripped newly added lints before (doc comments copied from the .proto, derives), and
// a new clippy must not fail `-D warnings` on code nobody can edit. Only this module.
#![allow(clippy::all)]

include!(concat!(env!("OUT_DIR"), "/org.eclipse.tahu.protobuf.rs"));
