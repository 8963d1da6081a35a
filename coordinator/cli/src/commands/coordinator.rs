//! `scatterfarm coordinator`: serve the farm — workers lease render tasks from it, clients
//! submit and follow jobs — keeping every job's progress in a data folder.

use super::connect::load_token;
use anyhow::{ensure, Context, Result};
use clap::Args;
use scatterfarm_coordinator::http;
use scatterfarm_coordinator::http_tls::WebTls;
use scatterfarm_coordinator::scheduler::Settings;
use scatterfarm_coordinator::server::{self, ServerConfig};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Debug, Clone, Args)]
pub struct CoordinatorArgs {
    /// The address to serve gRPC on (0.0.0.0:7070 to accept workers of other hosts).
    #[arg(long, default_value = "127.0.0.1:7070")]
    pub listen: SocketAddr,
    /// The data folder: job files, progress and results. A coordinator restarted on the same
    /// folder resumes every unfinished job.
    #[arg(long)]
    pub data: PathBuf,
    /// A file whose first line is the shared token clients and workers must send (else the
    /// SCATTERFARM_TOKEN variable; without either, no token is required).
    #[arg(long, env = "SCATTERFARM_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// PEM certificate (chain) to serve TLS with; needs --tls-key.
    #[arg(long, requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Tasks are sized so the leasing worker renders one in about this many seconds.
    #[arg(long, default_value_t = 2.0)]
    pub task_seconds: f64,
    /// How often workers must send heartbeats, in milliseconds; after 3 missed ones their
    /// tasks are leased again.
    #[arg(long, default_value_t = 2000)]
    pub heartbeat_ms: u64,
    /// The shortest lease, in seconds (a lease lasts the longer of this and 5 × the task's
    /// expected render time, plus twice the time the worker's results have taken to arrive
    /// beyond their render; an expired lease doubles that allowance).
    #[arg(long, default_value_t = 30.0)]
    pub lease_seconds: f64,
    /// Leases of one task before its job fails with a reason naming the task (a task whose
    /// lease expires, that a worker gives back or whose result is refused is leased again).
    #[arg(long, default_value_t = 8)]
    pub max_attempts: u32,
    /// Photons (all sources) one job may simulate before it fails saying so; a paper-scale
    /// reconstruction at 32 × 5 sources simulates about 10^9.
    #[arg(long, default_value_t = 1_000_000_000_000)]
    pub max_job_photons: u64,
    /// On SIGTERM, wait this long for leased tasks to come back before stopping.
    #[arg(long, default_value_t = 60.0)]
    pub drain_seconds: f64,
    /// Serve the status page (`/`) and Prometheus metrics (`/metrics`) on this address, e.g.
    /// 0.0.0.0:8080 (off unless given).
    /// With a token, every path of it needs the token: an `Authorization: Bearer` header (as
    /// Prometheus sends it) or a cookie a browser gets at `/login`. With --tls-cert/--tls-key
    /// it serves HTTPS with the same certificate and key (and plain HTTP requests are refused);
    /// without them it is plain HTTP: bind it to loopback, or put a TLS proxy in front, when the
    /// token must not cross a network.
    #[arg(long)]
    pub http: Option<SocketAddr>,
    /// Serve --http without asking for the token (anyone who reaches it sees every job).
    #[arg(long)]
    pub http_open: bool,
    /// Serve --http as plain HTTP even though gRPC has TLS, e.g. behind a proxy that terminates
    /// TLS for it (off loopback the coordinator warns that the token crosses the network in the
    /// clear).
    #[arg(long, requires = "http")]
    pub http_plaintext: bool,
    /// Write the coordinator's URL to this file once it listens (for scripts; with --listen
    /// on port 0 it holds the port chosen).
    #[arg(long)]
    pub address_file: Option<PathBuf>,
    /// Write the status page's URL to this file once it listens (with --http on port 0 it
    /// holds the port chosen); written before --address-file.
    #[arg(long, requires = "http")]
    pub http_address_file: Option<PathBuf>,
}

impl CoordinatorArgs {
    /// The validated server configuration.
    pub fn config(&self) -> Result<ServerConfig> {
        ensure!(
            self.task_seconds > 0.0 && self.task_seconds.is_finite(),
            "--task-seconds must be positive"
        );
        ensure!(
            self.heartbeat_ms >= 10,
            "--heartbeat-ms must be at least 10"
        );
        ensure!(
            self.lease_seconds > 0.0 && self.lease_seconds.is_finite(),
            "--lease-seconds must be positive"
        );
        ensure!(
            (1..=1000).contains(&self.max_attempts),
            "--max-attempts must be between 1 and 1000"
        );
        ensure!(
            self.drain_seconds >= 0.0 && self.drain_seconds.is_finite(),
            "--drain-seconds must be >= 0"
        );
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(c), Some(k)) => Some((
                std::fs::read(c)
                    .with_context(|| format!("cannot read --tls-cert {}", c.display()))?,
                std::fs::read(k)
                    .with_context(|| format!("cannot read --tls-key {}", k.display()))?,
            )),
            _ => None,
        };
        Ok(ServerConfig {
            listen: self.listen,
            data: self.data.clone(),
            token: load_token(self.token_file.as_deref())?,
            tls,
            settings: Settings {
                task_seconds: self.task_seconds,
                heartbeat: Duration::from_millis(self.heartbeat_ms),
                missed_heartbeats: 3,
                min_lease: Duration::from_secs_f64(self.lease_seconds),
                max_attempts: self.max_attempts,
                max_job_photons: self.max_job_photons,
            },
            drain_timeout: Duration::from_secs_f64(self.drain_seconds),
        })
    }

    /// The web face's TLS, from `config`'s certificate and key (None without them, or with
    /// --http-plaintext). The certificate and key are parsed even without --http, so a bad file
    /// is named before gRPC starts.
    pub fn web_tls(&self, config: &ServerConfig) -> Result<Option<WebTls>> {
        let (Some((cert, key)), Some(cert_file), Some(key_file)) =
            (&config.tls, &self.tls_cert, &self.tls_key)
        else {
            return Ok(None);
        };
        let tls = WebTls::from_pem(cert, cert_file, key, key_file)?;
        Ok((!self.http_plaintext).then_some(tls))
    }
}

pub fn run(args: CoordinatorArgs) -> Result<()> {
    let config = args.config()?;
    let tls = config.tls.is_some();
    let web_token = if args.http_open {
        None
    } else {
        config.token.clone()
    };
    let web_tls = args.web_tls(&config)?;
    if let Some(addr) = args.http {
        if !addr.ip().is_loopback() {
            if web_token.is_none() {
                tracing::warn!(
                    "the status page on {addr} asks for no token: anyone who can reach it sees \
                     every job"
                );
            }
            if tls && web_tls.is_none() {
                tracing::warn!(
                    "the status page on {addr} is plain HTTP (--http-plaintext) while gRPC has \
                     TLS: its token and pages cross the network in the clear unless a TLS proxy \
                     in front of it is all that reaches it"
                );
            } else if !tls && web_token.is_some() {
                tracing::warn!(
                    "the status page on {addr} is plain HTTP: its token crosses the network in \
                     the clear (bind it to loopback, put a TLS proxy in front, or give the \
                     coordinator --tls-cert and --tls-key)"
                );
            }
        }
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?
        .block_on(async {
            let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
            tokio::spawn(async move {
                server::termination().await;
                let _ = stop_tx.send(true);
            });
            let (running, serving) = server::start(config, server::stopped(stop_rx.clone()))
                .await
                .map_err(|e| in_use(e, &args.data))?;
            let web = match args.http {
                Some(addr) => {
                    let scheme = if web_tls.is_some() { "https" } else { "http" };
                    let (bound, web) = http::start(
                        addr,
                        running.farm.clone(),
                        web_token,
                        web_tls,
                        server::stopped(stop_rx),
                    )
                    .await?;
                    tracing::info!("status page on {scheme}://{bound}/ (metrics on /metrics)");
                    if let Some(path) = &args.http_address_file {
                        scatterfarm_job::observation::write_atomically(path, |w| {
                            writeln!(w, "{scheme}://{bound}")?;
                            Ok(())
                        })?;
                    }
                    Some(tokio::spawn(web))
                }
                None => None,
            };
            let url = format!(
                "{}://{}",
                if tls { "https" } else { "http" },
                running.address
            );
            tracing::info!("coordinator listening on {url}");
            if let Some(path) = &args.address_file {
                scatterfarm_job::observation::write_atomically(path, |w| {
                    writeln!(w, "{url}")?;
                    Ok(())
                })?;
            }
            serving.await?;
            if let Some(web) = web {
                web.await??;
            }
            tracing::info!("coordinator stopped");
            Ok(())
        })
}

/// `e`, saying so when the data folder's store is locked by another process (sled's own error
/// is a lock that could not be acquired, with an errno).
fn in_use(e: anyhow::Error, data: &Path) -> anyhow::Error {
    let locked = std::fs::File::open(data.join("store").join("db"))
        .is_ok_and(|f| matches!(f.try_lock(), Err(std::fs::TryLockError::WouldBlock)));
    if locked {
        e.context(format!(
            "the data folder {} is in use by another coordinator (its store is locked): stop \
             that one first, or give this one another --data",
            data.display()
        ))
    } else {
        e
    }
}
