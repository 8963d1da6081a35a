//! The scatterfarm gRPC protocol: all generated code lives in this crate.
//!
//! `v1` is the package `scatterfarm.v1` of `proto/scatterfarm/v1/farm.proto`. Every `bytes` field
//! is `bytes::Bytes`, so large count matrices are not copied on the way through.
//!
//! Beside the generated code, [`convert`] holds every conversion between the protocol's messages
//! and the model's types (both ends encode and check the same way), [`differential`] those of a
//! differential render's parts (changes, the job's target, the changes' scores), [`scored`]
//! those of a task whose worker scores its renders (the scores that come back instead of the
//! counts), [`auth`] the shared-token check both ends agree on, [`channel`] the client channel,
//! and [`v1::MAX_MESSAGE_BYTES`] the message size limit both ends raise tonic's default to.

pub mod auth;
pub mod channel;
pub mod convert;
pub mod differential;
pub mod scored;

/// Package `scatterfarm.v1`.
pub mod v1 {
    tonic::include_proto!("scatterfarm.v1");

    /// The protocol version this build speaks.
    pub const PROTOCOL: ProtocolVersion = ProtocolVersion { major: 1, minor: 3 };

    /// Messages up to this size are accepted and sent (a default-size count matrix is 5.3 MB;
    /// a task result carries one per assignment).
    pub const MAX_MESSAGE_BYTES: usize = 1 << 30;

    /// The encoded descriptor set of the package, for gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/scatterfarm_descriptor.bin"));
}
