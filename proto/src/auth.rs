//! The shared token: how a client attaches it and how a server checks it.
//!
//! A token travels as gRPC metadata `authorization: Bearer TOKEN`. The server side compares in
//! constant time so a wrong token says nothing about the right one.

use tonic::metadata::MetadataValue;
use tonic::{Request, Status};

/// The metadata key.
pub const HEADER: &str = "authorization";

/// Adds the token (if any) to every outgoing request.
#[derive(Debug, Clone, Default)]
pub struct AttachToken {
    value: Option<MetadataValue<tonic::metadata::Ascii>>,
}

impl AttachToken {
    /// `None` sends no token. Fails if the token cannot travel as a header value.
    pub fn new(token: Option<&str>) -> Result<Self, Status> {
        let value = token
            .map(|t| {
                format!("Bearer {t}")
                    .parse::<MetadataValue<_>>()
                    .map_err(|_| {
                        Status::invalid_argument("the token has characters a header cannot carry")
                    })
            })
            .transpose()?;
        Ok(AttachToken { value })
    }
}

impl tonic::service::Interceptor for AttachToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.value {
            request.metadata_mut().insert(HEADER, v.clone());
        }
        Ok(request)
    }
}

/// Refuses requests without the expected token (when one is configured).
#[derive(Debug, Clone, Default)]
pub struct RequireToken {
    expected: Option<Vec<u8>>,
}

impl RequireToken {
    /// `None` lets every request through.
    pub fn new(token: Option<&str>) -> Self {
        RequireToken {
            expected: token.map(|t| format!("Bearer {t}").into_bytes()),
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl tonic::service::Interceptor for RequireToken {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        match request.metadata().get(HEADER) {
            None => Err(Status::unauthenticated(
                "this coordinator requires a token: pass --token-file or set SCATTERFARM_TOKEN",
            )),
            Some(v) if constant_time_eq(v.as_bytes(), expected) => Ok(request),
            Some(_) => Err(Status::unauthenticated("wrong token")),
        }
    }
}

/// Reads a token file: its first line, trimmed. Empty files are an error.
pub fn read_token_file(path: &std::path::Path) -> std::io::Result<String> {
    let text = std::fs::read_to_string(path)?;
    let token = text.lines().next().unwrap_or("").trim().to_string();
    if token.is_empty() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{} holds no token", path.display()),
        ));
    }
    Ok(token)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::service::Interceptor;

    #[test]
    fn tokens_are_checked() {
        let mut attach = AttachToken::new(Some("s3cret")).unwrap();
        let mut require = RequireToken::new(Some("s3cret"));
        let req = attach.call(Request::new(())).unwrap();
        assert!(require.call(req).is_ok());
        let mut wrong = AttachToken::new(Some("nope")).unwrap();
        let err = require
            .call(wrong.call(Request::new(())).unwrap())
            .unwrap_err();
        assert_eq!(err.code(), tonic::Code::Unauthenticated);
        let err = require.call(Request::new(())).unwrap_err();
        assert!(err.message().contains("requires a token"));
        assert!(RequireToken::new(None).call(Request::new(())).is_ok());
    }
}
