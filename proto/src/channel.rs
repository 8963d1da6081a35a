//! Client connections to a coordinator: URL, optional private CA, token, message limits and
//! compression, the same for workers and the command line.

use crate::auth::AttachToken;
use crate::v1::client_service_client::ClientServiceClient;
use crate::v1::worker_service_client::WorkerServiceClient;
use crate::v1::MAX_MESSAGE_BYTES;
use std::time::Duration;
use tonic::codec::CompressionEncoding;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig};

/// Why a connection could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error("{url:?} is not a coordinator URL (expected http://HOST:PORT or https://HOST:PORT): {source}")]
    Url {
        url: String,
        source: tonic::transport::Error,
    },
    #[error("TLS settings for {url}: {source}")]
    Tls {
        url: String,
        source: tonic::transport::Error,
    },
    #[error("cannot reach the coordinator at {url}: {source}")]
    Unreachable {
        url: String,
        source: tonic::transport::Error,
    },
    #[error("{0}")]
    Token(tonic::Status),
}

/// Where and how to reach a coordinator.
#[derive(Debug, Clone)]
pub struct Endpoint {
    /// `http://HOST:PORT` or `https://HOST:PORT`.
    pub url: String,
    /// PEM of a private CA that signed the coordinator's certificate (https only).
    pub ca_pem: Option<Vec<u8>>,
    pub token: Option<String>,
}

/// A channel whose every request carries the token.
pub type Authed = InterceptedService<Channel, AttachToken>;

impl Endpoint {
    /// The tonic endpoint: the URL with timeouts, keep-alive and, for https, TLS.
    fn tonic_endpoint(&self) -> Result<tonic::transport::Endpoint, ConnectError> {
        let mut endpoint =
            tonic::transport::Endpoint::from_shared(self.url.clone()).map_err(|source| {
                ConnectError::Url {
                    url: self.url.clone(),
                    source,
                }
            })?;
        endpoint = endpoint
            .connect_timeout(Duration::from_secs(10))
            .tcp_nodelay(true)
            .http2_keep_alive_interval(Duration::from_secs(20))
            .keep_alive_while_idle(true);
        if self.url.starts_with("https://") {
            let mut tls = ClientTlsConfig::new().with_webpki_roots();
            if let Some(ca) = &self.ca_pem {
                tls = tls.ca_certificate(Certificate::from_pem(ca));
            }
            endpoint = endpoint
                .tls_config(tls)
                .map_err(|source| ConnectError::Tls {
                    url: self.url.clone(),
                    source,
                })?;
        }
        Ok(endpoint)
    }

    /// Connects now (fails if the coordinator is not reachable).
    pub async fn connect(&self) -> Result<Authed, ConnectError> {
        let channel =
            self.tonic_endpoint()?
                .connect()
                .await
                .map_err(|source| ConnectError::Unreachable {
                    url: self.url.clone(),
                    source,
                })?;
        let token = AttachToken::new(self.token.as_deref()).map_err(ConnectError::Token)?;
        Ok(InterceptedService::new(channel, token))
    }

    /// A worker-service client over `channel`, with raised limits and zstd both ways.
    pub fn worker_client(channel: Authed) -> WorkerServiceClient<Authed> {
        WorkerServiceClient::new(channel)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
            .send_compressed(CompressionEncoding::Zstd)
            .accept_compressed(CompressionEncoding::Zstd)
    }

    /// A client-service client over `channel`, with raised limits and zstd both ways.
    pub fn client_client(channel: Authed) -> ClientServiceClient<Authed> {
        ClientServiceClient::new(channel)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
            .send_compressed(CompressionEncoding::Zstd)
            .accept_compressed(CompressionEncoding::Zstd)
    }
}
