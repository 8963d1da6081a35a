//! `scatterfarm worker`: runs this machine as a render farm worker. It opens the engine, connects
//! to the coordinator (retrying until it answers), registers, and renders the tasks it leases
//! until SIGTERM or Ctrl-C; then it finishes and returns the task in hand (a second Ctrl-C quits
//! at once). The work itself is `scatterfarm_worker::agent`.

use super::connect::ConnectArgs;
use crate::engines::EngineArgs;
use anyhow::{Context, Result};
use clap::Args;
use scatterfarm_worker::agent::{self, AgentConfig};
use scatterfarm_worker::Engine;
use std::sync::Arc;

/// Render tasks leased from a coordinator until SIGTERM or Ctrl-C.
#[derive(Debug, Clone, Args)]
pub struct WorkerArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    #[command(flatten)]
    pub engine: EngineArgs,
    /// The name in worker listings (default: HOST/ENGINE-ADAPTER).
    #[arg(long)]
    pub name: Option<String>,
    /// Announce this throughput instead of measuring the engine at start.
    #[arg(long, hide = true, value_parser = positive_rate)]
    pub photons_per_second: Option<f64>,
}

fn positive_rate(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a finite number > 0, got {text:?}")),
    }
}

pub fn run(args: WorkerArgs) -> Result<()> {
    let target = args.connect.target()?;
    let engine: Arc<dyn Engine> = Arc::from(args.engine.open()?);
    let config = AgentConfig {
        target,
        name: args.name,
        photons_per_second: args.photons_per_second,
        max_tasks: None,
    };
    // The engine renders on its own threads; the runtime only waits on the network.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("scatterfarm-agent")
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let summary = runtime.block_on(agent::run(config, engine, shutdown_signal()))?;
    tracing::info!(
        "worker stopped after {} tasks ({:.3e} photons)",
        summary.tasks_completed,
        summary.photons as f64
    );
    Ok(())
}

/// Resolves on the first SIGTERM or Ctrl-C; after that, another one exits the process at once.
async fn shutdown_signal() {
    first_signal().await;
    tokio::spawn(async {
        first_signal().await;
        tracing::warn!("second signal: quitting without returning the task in hand");
        std::process::exit(130);
    });
}

async fn first_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut terminate) => {
                tokio::select! {
                    r = tokio::signal::ctrl_c() => {
                        if let Err(e) = r {
                            tracing::warn!("cannot listen for Ctrl-C ({e}); SIGTERM stops the worker");
                            terminate.recv().await;
                        }
                    }
                    _ = terminate.recv() => {}
                }
                return;
            }
            Err(e) => {
                tracing::warn!("cannot listen for SIGTERM ({e}); only Ctrl-C stops the worker")
            }
        }
    }
    if let Err(e) = tokio::signal::ctrl_c().await {
        tracing::warn!("cannot listen for Ctrl-C ({e}); the worker stops only when killed");
        std::future::pending::<()>().await;
    }
}
