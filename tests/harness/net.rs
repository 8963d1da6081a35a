//! Loopback ports, files another process writes, and one-request HTTP and HTTPS clients.

use std::path::Path;
use std::time::{Duration, Instant};

/// The port of `url` (`scheme://host:port`, as `--address-file` and `--http-address-file`
/// write it).
pub fn port_of(url: &str) -> u16 {
    url.rsplit(':')
        .next()
        .and_then(|p| p.trim_end_matches('/').parse().ok())
        .unwrap_or_else(|| panic!("no port in {url:?}"))
}

/// The trimmed text of `path` once it is there and ends with a newline (within 60 s).
pub fn wait_for_file(path: &Path) -> String {
    let until = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(text) = std::fs::read_to_string(path) {
            if text.ends_with('\n') {
                return text.trim().to_string();
            }
        }
        assert!(Instant::now() < until, "{} never appeared", path.display());
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The trimmed text of `path` once `proc` has written it (within 60 s, else a failure with its
/// log); `None` if `proc` ended first, as a server does whose free port was taken meanwhile.
pub fn wait_for_file_from(path: &Path, proc: &mut crate::harness::process::Proc) -> Option<String> {
    let until = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(text) = std::fs::read_to_string(path) {
            if text.ends_with('\n') {
                return Some(text.trim().to_string());
            }
        }
        if !proc.running() {
            eprintln!(
                "`{}` ended before writing {}:\n{}",
                proc.what,
                path.display(),
                proc.log_text()
            );
            return None;
        }
        assert!(
            Instant::now() < until,
            "{} never appeared; `{}` logged:\n{}",
            path.display(),
            proc.what,
            proc.log_text()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A plain HTTP/1.1 response: status code, header lines and body.
pub struct HttpResponse {
    pub status: u16,
    pub headers: String,
    pub body: String,
}

/// Connects to `127.0.0.1:port`, retrying for up to 30 s while the server starts.
fn connect(port: u16) -> std::net::TcpStream {
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        match std::net::TcpStream::connect(("127.0.0.1", port)) {
            Ok(s) => return s,
            Err(e) => {
                assert!(Instant::now() < until, "cannot connect to port {port}: {e}");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

/// Sends one HTTP/1.1 request to `127.0.0.1:port` (the connection closed after it), retrying
/// the connection for up to 30 s while the server starts.
pub fn http(port: u16, method: &str, path: &str, headers: &[&str], body: &str) -> HttpResponse {
    exchange(connect(port), port, method, path, headers, body)
}

/// [`http`] over TLS: the server's certificate must be signed by `ca_pem` for `localhost`.
pub fn https(
    port: u16,
    ca_pem: &str,
    method: &str,
    path: &str,
    headers: &[&str],
    body: &str,
) -> HttpResponse {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, ServerName};
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_slice_iter(ca_pem.as_bytes()) {
        roots
            .add(cert.expect("the CA parses"))
            .expect("the CA is usable");
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .expect("TLS versions")
        .with_root_certificates(roots)
        .with_no_client_auth();
    let name = ServerName::try_from("localhost").expect("a server name");
    let conn =
        rustls::ClientConnection::new(std::sync::Arc::new(config), name).expect("a TLS client");
    let stream = rustls::StreamOwned::new(conn, connect(port));
    exchange(stream, port, method, path, headers, body)
}

/// One request on `stream`, read to its end.
fn exchange(
    mut stream: impl std::io::Read + std::io::Write,
    port: u16,
    method: &str,
    path: &str,
    headers: &[&str],
    body: &str,
) -> HttpResponse {
    let mut request = format!(
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for h in headers {
        request.push_str(h);
        request.push_str("\r\n");
    }
    request.push_str("\r\n");
    request.push_str(body);
    stream.write_all(request.as_bytes()).expect("request sent");
    stream.flush().expect("request sent");
    let mut raw = Vec::new();
    let mut chunk = [0u8; 8192];
    loop {
        match stream.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => raw.extend_from_slice(&chunk[..n]),
            // A TLS peer that closes without close_notify, after the whole response.
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !raw.is_empty() => break,
            Err(e) => panic!("response read: {e}"),
        }
    }
    let text = String::from_utf8_lossy(&raw).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {text:?}"));
    HttpResponse {
        status,
        headers: head.to_string(),
        body: body.to_string(),
    }
}
