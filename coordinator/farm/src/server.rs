//! Serving a coordinator: the listening socket, TLS, the token check, gRPC health and
//! reflection, the lease sweeper, and a graceful drain when told to stop.

use super::scheduler::{Scheduler, Settings};
use super::service::{ClientApi, Farm, WorkerApi};
use super::store::SledStore;
use anyhow::{Context, Result};
use scatterfarm_proto::auth::RequireToken;
use scatterfarm_proto::v1::client_service_server::ClientServiceServer;
use scatterfarm_proto::v1::worker_service_server::WorkerServiceServer;
use scatterfarm_proto::v1::{FILE_DESCRIPTOR_SET, MAX_MESSAGE_BYTES};
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tonic::codec::CompressionEncoding;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Identity, Server, ServerTlsConfig};

/// How to run a coordinator.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    pub listen: SocketAddr,
    /// The data folder (created if missing).
    pub data: PathBuf,
    pub token: Option<String>,
    /// PEM certificate chain and private key: serve TLS.
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    pub settings: Settings,
    /// How long a drain waits for leased tasks to come back.
    pub drain_timeout: Duration,
}

/// A started coordinator: its address and shared state.
pub struct Running {
    pub address: SocketAddr,
    pub farm: Arc<Farm>,
}

/// Opens the data folder, binds the address, and returns the serving future (which ends after
/// `shutdown` resolves and the drain is done) with the bound address.
pub async fn start(
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(Running, impl Future<Output = Result<()>>)> {
    std::fs::create_dir_all(&config.data)
        .with_context(|| format!("cannot create the data folder {}", config.data.display()))?;
    let store = Arc::new(SledStore::open(&config.data)?);
    let scheduler = Scheduler::open(store, config.settings)?;
    let farm = Farm::new(scheduler);

    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("cannot listen on {}", config.listen))?;
    let address = listener.local_addr()?;

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<WorkerServiceServer<WorkerApi>>().await;
    health.set_serving::<ClientServiceServer<ClientApi>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("cannot build the reflection service")?;

    let auth = RequireToken::new(config.token.as_deref());
    if config.token.is_none() && !config.listen.ip().is_loopback() {
        tracing::warn!(
            "no token: anyone who can reach {} can submit jobs and lease work (give --token-file)",
            config.listen
        );
    }
    let workers = WorkerServiceServer::new(WorkerApi(farm.clone()))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES)
        .accept_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Zstd);
    let clients = ClientServiceServer::new(ClientApi(farm.clone()))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES)
        .accept_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Zstd);

    let mut builder = Server::builder();
    if let Some((cert, key)) = &config.tls {
        builder = builder
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))
            .context("the TLS certificate or key is not usable")?;
    }
    let router = builder
        .add_service(health_service)
        .add_service(reflection)
        .add_service(InterceptedService::new(workers, auth.clone()))
        .add_service(InterceptedService::new(clients, auth));

    // Leases past their deadline and silent workers are handled twice a second.
    let sweeper = {
        let farm = farm.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(500));
            loop {
                tick.tick().await;
                if farm
                    .locked_durable(|s| s.sweep(Instant::now()))
                    .await
                    .is_err()
                {
                    tracing::error!("the sweep failed");
                }
                farm.work.notify_waiters();
            }
        })
    };

    // On shutdown: stop handing out work, report not-serving, wait for leased tasks.
    let drained = {
        let farm = farm.clone();
        let timeout = config.drain_timeout;
        async move {
            shutdown.await;
            tracing::info!("draining: no new tasks; waiting for leased tasks to come back");
            farm.scheduler().draining = true;
            health
                .set_not_serving::<WorkerServiceServer<WorkerApi>>()
                .await;
            health
                .set_not_serving::<ClientServiceServer<ClientApi>>()
                .await;
            health
                .set_service_status("", tonic_health::ServingStatus::NotServing)
                .await;
            let until = Instant::now() + timeout;
            while !farm.scheduler().leases.is_empty() && Instant::now() < until {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            let left = farm.scheduler().leases.len();
            if left > 0 {
                tracing::warn!(
                    "{left} leased tasks did not come back; they are re-rendered on restart"
                );
            }
            if let Err(e) = farm.scheduler().store().flush() {
                tracing::error!("cannot flush the store: {e}");
            }
        }
    };

    let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
    let serving = async move {
        let r = router
            .serve_with_incoming_shutdown(incoming, drained)
            .await
            .context("the gRPC server failed");
        sweeper.abort();
        r
    };
    Ok((Running { address, farm }, serving))
}

/// Resolves once `rx` holds `true` (or its sender is gone).
pub async fn stopped(mut rx: tokio::sync::watch::Receiver<bool>) {
    let _ = rx.wait_for(|&s| s).await;
}

/// Resolves on SIGTERM or Ctrl-C.
pub async fn termination() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
