//! `scatterfarm worker`: runs this machine as a render farm worker. It opens the engine, connects
//! to the coordinator (retrying until it answers), registers, and renders the tasks it leases
//! until SIGTERM, Ctrl-C or SIGUSR1; then it finishes and returns the task in hand (a second
//! SIGTERM or Ctrl-C quits at once; SIGUSR1 never does). The work itself is
//! `scatterfarm_worker`; the signals are [`StopSignals`].

use super::connect::ConnectArgs;
use crate::engines::EngineArgs;
use anyhow::{Context, Result};
use clap::Args;
use scatterfarm_model::Engine;
use scatterfarm_worker::{self as agent, AgentConfig};
use std::sync::Arc;

/// Render tasks leased from a coordinator until SIGTERM, Ctrl-C or SIGUSR1 (then finish the task
/// in hand; a second SIGTERM or Ctrl-C quits at once).
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
    let endpoint = args.connect.endpoint()?;
    // The engine renders on its own threads; the runtime only waits on the network.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("scatterfarm-agent")
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    // Listen before the engine opens (seconds on a GPU), so a stop asked for meanwhile counts.
    let signals = {
        let _context = runtime.enter();
        StopSignals::listen()
    };
    let engine: Arc<dyn Engine> = Arc::from(args.engine.open()?);
    let config = AgentConfig {
        endpoint,
        name: args.name,
        photons_per_second: args.photons_per_second,
        max_tasks: None,
    };
    let summary = runtime.block_on(agent::run(config, engine, signals.first_stop()))?;
    tracing::info!(
        "worker stopped after {} tasks ({:.3e} photons)",
        summary.tasks_completed,
        summary.photons as f64
    );
    Ok(())
}

/// A signal that stops the worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    /// SIGTERM or Ctrl-C (SIGINT): the first asks the worker to finish, the second quits at once.
    Terminate,
    /// SIGUSR1: asks the worker to finish and never quits it. The Slurm batch script
    /// (`deploy/slurm`) forwards its own SIGTERM to the workers as SIGUSR1 through srun, and
    /// Slurm may signal the same workers directly: the two must count as one request.
    Finish,
}

/// The stop signals, listened for from the start. A signal we cannot listen for is logged and
/// left to its default action.
struct StopSignals {
    #[cfg(unix)]
    terminate: Option<tokio::signal::unix::Signal>,
    #[cfg(unix)]
    interrupt: Option<tokio::signal::unix::Signal>,
    #[cfg(unix)]
    finish: Option<tokio::signal::unix::Signal>,
}

impl StopSignals {
    /// Starts listening; needs a Tokio runtime context.
    fn listen() -> StopSignals {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            let open = |kind: SignalKind, name: &str| match signal(kind) {
                Ok(listener) => Some(listener),
                Err(e) => {
                    tracing::warn!(
                        "cannot listen for {name} ({e}): it will not stop the worker cleanly"
                    );
                    None
                }
            };
            StopSignals {
                terminate: open(SignalKind::terminate(), "SIGTERM"),
                interrupt: open(SignalKind::interrupt(), "SIGINT"),
                finish: open(SignalKind::user_defined1(), "SIGUSR1"),
            }
        }
        #[cfg(not(unix))]
        StopSignals {}
    }

    /// The next stop signal.
    async fn next(&mut self) -> Stop {
        #[cfg(unix)]
        {
            tokio::select! {
                _ = recv(&mut self.terminate) => Stop::Terminate,
                _ = recv(&mut self.interrupt) => Stop::Terminate,
                _ = recv(&mut self.finish) => Stop::Finish,
            }
        }
        #[cfg(not(unix))]
        {
            match tokio::signal::ctrl_c().await {
                Ok(()) => Stop::Terminate,
                Err(e) => {
                    tracing::warn!(
                        "cannot listen for Ctrl-C ({e}); the worker stops only when killed"
                    );
                    std::future::pending().await
                }
            }
        }
    }

    /// Resolves on the first stop signal; after it, a second SIGTERM or Ctrl-C exits the process
    /// at once (a task in hand is then lost to the coordinator until its lease expires). SIGUSR1
    /// never counts towards that second one, whichever order the two arrive in.
    async fn first_stop(mut self) {
        let first = self.next().await;
        tracing::debug!("stop signal: {first:?}");
        let mut terminated = first == Stop::Terminate;
        tokio::spawn(async move {
            loop {
                match self.next().await {
                    Stop::Finish => tracing::info!("SIGUSR1: already finishing"),
                    Stop::Terminate if !terminated => {
                        terminated = true;
                        tracing::info!("SIGTERM: already finishing");
                    }
                    Stop::Terminate => {
                        tracing::warn!(
                            "second signal: quitting without returning the task in hand"
                        );
                        std::process::exit(130);
                    }
                }
            }
        });
    }
}

/// The next delivery of a signal, or never when it is not listened for (or its driver is gone).
#[cfg(unix)]
async fn recv(listener: &mut Option<tokio::signal::unix::Signal>) {
    if let Some(listener) = listener {
        if listener.recv().await.is_some() {
            return;
        }
    }
    std::future::pending().await
}
