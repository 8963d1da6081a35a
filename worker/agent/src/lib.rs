//! The worker agent: the process side of a render farm worker. It connects to a coordinator over
//! gRPC, registers its engine, leases render tasks, renders them and returns the counts. It is
//! built from the model, the engines and the protocol only; the engines know nothing of gRPC,
//! and every message ⇄ model conversion is `scatterfarm_proto::convert`'s.
//!
//! - [`measure`]: the engine's photons per second, measured once at start.
//! - `session`: connecting and registering with backoff, the heartbeat task.
//! - `work`: the lease → render → complete loop; `cache`: job geometries.
//! - `retry`: backoff, the shutdown signal, classification of gRPC failures.
//!
//! Failures of the network are retried with exponential backoff (0.5 s doubling to 10 s) for as
//! long as the agent runs; a refused token or a refused registration (another protocol version)
//! ends it with an error. When the coordinator forgets the worker (it restarted), the agent
//! registers again with the same measurement. On shutdown it stops leasing, finishes and returns
//! the task it is rendering, and returns.

pub mod measure;

mod cache;
mod retry;
mod session;
mod work;

#[cfg(test)]
mod tests;

use scatterfarm_model::engine::{Engine, EngineError};
use scatterfarm_proto::channel::{ConnectError, Endpoint};
use scatterfarm_proto::convert::fingerprint_to_proto;
use scatterfarm_proto::v1;
use std::future::Future;
use std::sync::Arc;
use thiserror::Error;

/// What the agent needs besides its engine.
#[derive(Debug, Clone)]
pub struct AgentConfig {
    /// The coordinator.
    pub endpoint: Endpoint,
    /// The name in worker listings; `HOST/ENGINE-ADAPTER` when `None`.
    pub name: Option<String>,
    /// Announced as is instead of measuring the engine at start.
    pub photons_per_second: Option<f64>,
    /// Stop after this many tasks the coordinator accepted (for tests).
    pub max_tasks: Option<u64>,
}

/// What the agent did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AgentSummary {
    /// Tasks whose results the coordinator accepted.
    pub tasks_completed: u64,
    /// Photons launched in those tasks (sources × photons per source × assignments).
    pub photons: u64,
}

/// Why the agent stopped before it was asked to.
#[derive(Debug, Error)]
pub enum AgentError {
    #[error("the coordinator at {url} refused this worker's credentials: {message}")]
    Unauthenticated { url: String, message: String },
    #[error("the coordinator at {url} refused to register this worker: {message}")]
    Refused { url: String, message: String },
    /// A malformed URL, bad TLS settings or a token that cannot travel as a header.
    #[error(transparent)]
    Connect(ConnectError),
    #[error("cannot measure the engine: {0}")]
    Measure(#[source] EngineError),
    #[error("the engine panicked while it was measured: {0}")]
    MeasurePanicked(String),
    #[error("--photons-per-second must be a finite number > 0, got {0}")]
    PhotonsPerSecond(f64),
}

/// Runs the agent until `shutdown` resolves (then finishes the task in hand), `max_tasks` tasks
/// are done, or a fatal error.
pub async fn run(
    config: AgentConfig,
    engine: Arc<dyn Engine>,
    shutdown: impl Future<Output = ()>,
) -> Result<AgentSummary, AgentError> {
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let agent = start(config, engine, retry::Stop::new(stop_rx));
    tokio::pin!(agent);
    tokio::pin!(shutdown);
    tokio::select! {
        result = &mut agent => return result,
        () = &mut shutdown => {
            tracing::info!("shutting down: no more leases; finishing the task in hand");
            // The receiver lives in `agent`, which is still running.
            let _ = stop_tx.send(true);
        }
    }
    agent.await
}

async fn start(
    config: AgentConfig,
    engine: Arc<dyn Engine>,
    stop: retry::Stop,
) -> Result<AgentSummary, AgentError> {
    let fingerprint = engine.fingerprint();
    let photons_per_second = match config.photons_per_second {
        Some(p) if p.is_finite() && p > 0.0 => p,
        Some(p) => return Err(AgentError::PhotonsPerSecond(p)),
        None => {
            let measured = engine.clone();
            let rate =
                tokio::task::spawn_blocking(move || measure::photons_per_second(measured.as_ref()))
                    .await
                    .map_err(|e| AgentError::MeasurePanicked(e.to_string()))?
                    .map_err(AgentError::Measure)?;
            tracing::info!("engine {fingerprint}: {rate:.3e} photons/s measured");
            rate
        }
    };
    let name = config
        .name
        .clone()
        .unwrap_or_else(|| default_name(&fingerprint));
    let request = v1::RegisterRequest {
        protocol: Some(v1::PROTOCOL),
        fingerprint: Some(fingerprint_to_proto(&fingerprint)),
        photons_per_second,
        name,
        renders_differentially: engine.renders_differentially(),
        scores_renders: true,
    };
    let connector =
        session::Connector::new(config.endpoint, request, fingerprint.key(), stop.clone());
    work::Worker {
        engine,
        connector,
        stop,
        max_tasks: config.max_tasks,
    }
    .run()
    .await
}

/// `HOST/ENGINE-ADAPTER`, or `HOST/ENGINE` when the adapter is named as the engine (`cpu`).
pub fn default_name(fingerprint: &scatterfarm_model::engine::EngineFingerprint) -> String {
    let engine = if fingerprint.adapter == fingerprint.engine || fingerprint.adapter.is_empty() {
        fingerprint.engine.clone()
    } else {
        format!("{}-{}", fingerprint.engine, fingerprint.adapter)
    };
    format!("{}/{engine}", hostname())
}

/// This machine's host name, from the kernel or the environment.
fn hostname() -> String {
    ["/proc/sys/kernel/hostname", "/etc/hostname"]
        .iter()
        .filter_map(|path| std::fs::read_to_string(path).ok())
        .chain(
            ["HOSTNAME", "COMPUTERNAME"]
                .iter()
                .filter_map(|v| std::env::var(v).ok()),
        )
        .map(|name| name.trim().to_string())
        .find(|name| !name.is_empty())
        .unwrap_or_else(|| "unknown-host".to_string())
}
