//! The scatterfarm gRPC protocol: all generated code lives in this crate.
//!
//! `v1` is the package `scatterfarm.v1` of `proto/scatterfarm/v1/farm.proto`. Payloads that carry
//! count matrices are `bytes::Bytes`, so large results are not copied on the way through.

/// Package `scatterfarm.v1`.
pub mod v1 {
    tonic::include_proto!("scatterfarm.v1");

    /// The protocol version this build speaks.
    pub const PROTOCOL: ProtocolVersion = ProtocolVersion { major: 1, minor: 0 };
}
