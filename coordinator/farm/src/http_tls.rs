//! TLS for the web face: when gRPC serves TLS (`--tls-cert`/`--tls-key`), `--http` serves HTTPS
//! with the same certificate and key, so its token (bearer header or `/login` cookie) never
//! crosses the network in the clear.
//!
//! [`WebTls`] is the rustls configuration (the ring provider tonic's `tls-ring` already brings,
//! HTTP/1.1 by ALPN), made from the PEM files with errors that name the file. [`TlsListener`]
//! hands `axum::serve` connections whose handshake is done: handshakes run in their own tasks
//! (at most [`MAX_HANDSHAKES`] at once, each within [`HANDSHAKE_TIMEOUT`]), so a slow or silent
//! client never holds up the others; a client speaking plain HTTP to the port gets a plain
//! `400` saying to use `https://`, and nothing else.

use anyhow::{anyhow, bail, Context, Result};
use rustls::pki_types::pem::{self, PemObject};
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::io;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;

/// TLS handshakes in flight at once; connections beyond them are closed at once.
pub const MAX_HANDSHAKES: usize = 256;

/// The longest a client may take over its handshake (or, speaking plain HTTP, over reading the
/// refusal).
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The web face's TLS configuration, made from the certificate and key gRPC serves.
#[derive(Clone)]
pub struct WebTls(Arc<rustls::ServerConfig>);

impl std::fmt::Debug for WebTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("WebTls")
    }
}

impl WebTls {
    /// From a PEM certificate chain (`cert`, read from `cert_file`) and its PEM private key
    /// (`key`, from `key_file`: PKCS#8, PKCS#1 or SEC1). Every error names the file at fault.
    pub fn from_pem(cert: &[u8], cert_file: &Path, key: &[u8], key_file: &Path) -> Result<Self> {
        let chain = CertificateDer::pem_slice_iter(cert)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| anyhow!("{}", pem_error(&e)))
            .with_context(|| {
                format!(
                    "cannot parse the certificate file {} (--tls-cert)",
                    cert_file.display()
                )
            })?;
        if chain.is_empty() {
            bail!(
                "the certificate file {} (--tls-cert) holds no PEM certificate \
                 (-----BEGIN CERTIFICATE-----)",
                cert_file.display()
            );
        }
        let key = match PrivateKeyDer::from_pem_slice(key) {
            Ok(k) => k,
            Err(pem::Error::NoItemsFound) => bail!(
                "the key file {} (--tls-key) holds no PEM private key (-----BEGIN PRIVATE \
                 KEY-----, or an RSA or EC one)",
                key_file.display()
            ),
            Err(e) => bail!(
                "cannot parse the key file {} (--tls-key): {}",
                key_file.display(),
                pem_error(&e)
            ),
        };
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config = rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .context("the TLS provider offers no protocol version")?
            .with_no_client_auth()
            .with_single_cert(chain, key);
        let mut config = match config {
            Ok(c) => c,
            Err(rustls::Error::InconsistentKeys(_)) => bail!(
                "the key in {} (--tls-key) does not belong to the certificate in {} \
                 (--tls-cert)",
                key_file.display(),
                cert_file.display()
            ),
            Err(e) => bail!(
                "cannot serve TLS with the certificate {} and the key {}: {e}",
                cert_file.display(),
                key_file.display()
            ),
        };
        config.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(Self(Arc::new(config)))
    }
}

/// A PEM error in words (pki-types' own quote lines as byte lists).
fn pem_error(e: &pem::Error) -> String {
    match e {
        pem::Error::MissingSectionEnd { end_marker } => format!(
            "a section has no end line {:?}",
            String::from_utf8_lossy(end_marker)
        ),
        pem::Error::IllegalSectionStart { line } => format!(
            "a section starts with a malformed line {:?}",
            String::from_utf8_lossy(line)
        ),
        e => e.to_string(),
    }
}

/// What [`TlsListener`] hands on: a connection past its handshake, and its peer.
type Accepted = (TlsStream<TcpStream>, SocketAddr);

/// A TCP listener whose connections come out past their TLS handshake, for `axum::serve`.
/// Dropping it (as `axum::serve` does on graceful shutdown) stops its accept task, which closes
/// the port.
pub struct TlsListener {
    accepted: mpsc::Receiver<Accepted>,
    local: SocketAddr,
}

impl TlsListener {
    /// Accepts on `tcp` in a task of its own, with `tls`.
    pub fn new(tcp: TcpListener, tls: &WebTls) -> io::Result<Self> {
        let local = tcp.local_addr()?;
        let (tx, accepted) = mpsc::channel(64);
        tokio::spawn(accept_loop(tcp, TlsAcceptor::from(tls.0.clone()), tx));
        Ok(Self { accepted, local })
    }
}

impl axum::serve::Listener for TlsListener {
    type Io = TlsStream<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.accepted.recv().await {
            Some(accepted) => accepted,
            // The accept task never ends while this listener lives.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> io::Result<SocketAddr> {
        Ok(self.local)
    }
}

/// Accepts connections until the listener is dropped, each handshake in a task of its own.
async fn accept_loop(tcp: TcpListener, acceptor: TlsAcceptor, tx: mpsc::Sender<Accepted>) {
    let handshakes = Arc::new(Semaphore::new(MAX_HANDSHAKES));
    loop {
        let accepted = tokio::select! {
            accepted = tcp.accept() => accepted,
            () = tx.closed() => return,
        };
        let (stream, peer) = match accepted {
            Ok(c) => c,
            Err(e) if is_connection_error(&e) => continue,
            Err(e) => {
                // Out of file descriptors and the like: as axum does, wait before trying again.
                tracing::error!("the web face cannot accept a connection: {e}");
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        let Ok(permit) = handshakes.clone().try_acquire_owned() else {
            tracing::warn!(
                "closing the connection from {peer}: {MAX_HANDSHAKES} TLS handshakes are in \
                 flight"
            );
            continue;
        };
        let (acceptor, tx) = (acceptor.clone(), tx.clone());
        tokio::spawn(async move {
            let _permit = permit;
            match tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake(stream, &acceptor)).await {
                Ok(Ok(Some(tls))) => {
                    // Fails only when the server is shutting down: the connection is dropped.
                    let _ = tx.send((tls, peer)).await;
                }
                Ok(Ok(None)) => {}
                Ok(Err(e)) => tracing::debug!("TLS handshake with {peer} failed: {e}"),
                Err(_) => tracing::debug!(
                    "TLS handshake with {peer} took over {HANDSHAKE_TIMEOUT:?}: closed"
                ),
            }
        });
    }
}

/// Errors of one connection, not of the listener (axum's own list).
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

/// The first byte of every TLS connection: a handshake record.
const TLS_HANDSHAKE_RECORD: u8 = 0x16;

/// The TLS connection, or `None` when the client spoke plain HTTP (refused) or sent nothing.
async fn handshake(
    stream: TcpStream,
    acceptor: &TlsAcceptor,
) -> io::Result<Option<TlsStream<TcpStream>>> {
    let mut first = [0u8; 1];
    if stream.peek(&mut first).await? == 0 {
        return Ok(None);
    }
    if first[0] != TLS_HANDSHAKE_RECORD {
        refuse_plaintext(stream).await?;
        return Ok(None);
    }
    acceptor.accept(stream).await.map(Some)
}

/// The answer to a plain-HTTP request on the HTTPS port.
const PLAINTEXT_REFUSAL: &str =
    "this port serves HTTPS (the coordinator has --tls-cert): use https://, not http://\n";

/// Answers plain HTTP with a plain `400` and closes, reading what the client sent meanwhile (so
/// the close is no reset that could destroy the answer before the client reads it).
async fn refuse_plaintext(mut stream: TcpStream) -> io::Result<()> {
    let answer = format!(
        "HTTP/1.1 400 Bad Request\r\ncontent-type: text/plain; charset=utf-8\r\n\
         content-length: {}\r\nconnection: close\r\n\r\n{PLAINTEXT_REFUSAL}",
        PLAINTEXT_REFUSAL.len()
    );
    stream.write_all(answer.as_bytes()).await?;
    stream.shutdown().await?;
    let mut sink = [0u8; 4096];
    while stream.read(&mut sink).await? > 0 {}
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair() -> (String, String) {
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()])
            .unwrap()
            .self_signed(&key)
            .unwrap();
        (cert.pem(), key.serialize_pem())
    }

    fn err(cert: &str, key: &str) -> String {
        let e = WebTls::from_pem(
            cert.as_bytes(),
            Path::new("/etc/c.pem"),
            key.as_bytes(),
            Path::new("/etc/k.pem"),
        )
        .unwrap_err();
        format!("{e:#}")
    }

    #[test]
    fn a_certificate_and_its_key_make_a_configuration() {
        let (cert, key) = pair();
        let tls = WebTls::from_pem(
            cert.as_bytes(),
            Path::new("c.pem"),
            key.as_bytes(),
            Path::new("k.pem"),
        )
        .unwrap();
        assert_eq!(tls.0.alpn_protocols, vec![b"http/1.1".to_vec()]);
    }

    #[test]
    fn errors_name_the_file_at_fault() {
        let (cert, key) = pair();
        let (_, other_key) = pair();
        let e = err("not a certificate", &key);
        assert!(
            e.contains("/etc/c.pem") && e.contains("no PEM certificate"),
            "{e}"
        );
        let e = err(&cert, "");
        assert!(
            e.contains("/etc/k.pem") && e.contains("no PEM private key"),
            "{e}"
        );
        let e = err(&cert, &other_key);
        assert!(
            e.contains("/etc/k.pem") && e.contains("does not belong") && e.contains("/etc/c.pem"),
            "{e}"
        );
        let cut = &cert[..cert.len() - 30];
        let e = err(cut, &key);
        assert!(
            e.contains("/etc/c.pem") && e.contains("cannot parse"),
            "{e}"
        );
        let e = err(&cert, &cert);
        assert!(e.contains("/etc/k.pem"), "{e}");
    }
}
