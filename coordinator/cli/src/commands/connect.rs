//! `--coordinator`, `--token-file` and `--tls-ca`: how every client command and worker reaches a
//! coordinator.

use anyhow::{Context, Result};
use clap::Args;
use scatterfarm_proto::channel::Endpoint;
use std::path::{Path, PathBuf};

/// The environment variable that may hold the shared token itself.
pub const TOKEN_ENV: &str = "SCATTERFARM_TOKEN";

/// Reads the token from `file`, else from `SCATTERFARM_TOKEN`; `None` when neither is given.
pub fn load_token(file: Option<&Path>) -> Result<Option<String>> {
    if let Some(path) = file {
        let token = scatterfarm_proto::auth::read_token_file(path)
            .with_context(|| format!("cannot read the token file {}", path.display()))?;
        return Ok(Some(token));
    }
    Ok(std::env::var(TOKEN_ENV)
        .ok()
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty()))
}

#[derive(Debug, Clone, Args)]
pub struct ConnectArgs {
    /// The coordinator's URL: http://HOST:PORT, or https://HOST:PORT when it serves TLS.
    #[arg(
        long,
        env = "SCATTERFARM_COORDINATOR",
        default_value = "http://127.0.0.1:7070"
    )]
    pub coordinator: String,
    /// A file whose first line is the shared token (else the SCATTERFARM_TOKEN variable).
    #[arg(long, env = "SCATTERFARM_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// PEM certificate of a private CA that signed the coordinator's certificate.
    #[arg(long)]
    pub tls_ca: Option<PathBuf>,
}

impl ConnectArgs {
    /// The validated coordinator endpoint.
    pub fn endpoint(&self) -> Result<Endpoint> {
        let ca_pem = self
            .tls_ca
            .as_ref()
            .map(|p| {
                std::fs::read(p).with_context(|| format!("cannot read --tls-ca {}", p.display()))
            })
            .transpose()?;
        anyhow::ensure!(
            ca_pem.is_none() || self.coordinator.starts_with("https://"),
            "--tls-ca needs an https:// coordinator URL, got {}",
            self.coordinator
        );
        Ok(Endpoint {
            url: self.coordinator.clone(),
            ca_pem,
            token: load_token(self.token_file.as_deref())?,
        })
    }
}
