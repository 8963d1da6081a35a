//! The scatterfarm coordinator: a service that owns every reconstruction's search state, cuts it
//! into render tasks for workers over gRPC, scores what comes back, and keeps its progress in a
//! store. It renders nothing itself and links no engine.
//!
//! - [`store`]: the durable state behind a small trait (sled on disk with a schema version; in
//!   memory with injected faults, for tests).
//! - [`work`]: render groups cut into photon-range pieces, with partial counts summed.
//! - [`job`]: one job, one file per concern: record, durable progress, pinning, planning
//!   through the search's step driver, setup completion, outputs, pace.
//! - [`scheduler`]: the [`scheduler::Scheduler`]: jobs, the worker registry and leases, one file
//!   per concern (client requests, registry, leasing, lease sizing, result checks, expiry,
//!   attempt caps, strikes, restoring paused and listing damaged jobs).
//! - [`service`]: the [`service::Farm`] both services share, and the `WorkerService` and
//!   `ClientService` gRPC implementations (one file each); every message ⇄ model conversion is
//!   `scatterfarm_proto::convert`'s.
//! - [`status`]: the job-status view clients, the CLI and the status page share, with the one
//!   name of each job state.
//! - [`server`]: serving them with TLS, token, health, reflection and a graceful drain.
//! - [`http`]: the web face: Prometheus metrics and a status page.
//! - [`http_auth`]: the web face's token check (bearer header or a cookie set at `/login`).
//! - [`http_tls`]: the web face over HTTPS with gRPC's certificate and key.

pub mod http;
pub mod http_auth;
pub mod http_tls;
pub mod job;
pub mod scheduler;
pub mod server;
pub mod service;
pub mod status;
pub mod store;
pub mod work;

/// A number that differs between processes (ids of different coordinator runs must differ; they
/// need not be unpredictable).
pub(crate) fn nonce() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    h.write_u32(std::process::id());
    h.finish() as u32
}
