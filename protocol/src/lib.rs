//! The wire contract between plants and controllers (protobuf via prost).
//!
//! Not written yet: see the service issue. The crate exists so the workspace has its final
//! shape from the start.
