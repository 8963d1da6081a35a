//! The shared token: how a client attaches it and how a server checks it.
//!
//! A token travels as gRPC metadata `authorization: Bearer TOKEN`. The server side compares in
//! constant time so a wrong token says nothing about the right one. A token file is read only up
//! to [`MAX_TOKEN_FILE_BYTES`], and its token must be one that a header can carry.

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

/// Whether `a` and `b` are equal, in a time that does not depend on where they differ.
pub fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
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

/// The largest token file read.
pub const MAX_TOKEN_FILE_BYTES: u64 = 64 * 1024;

/// Reads a token file: its first line, trimmed. Empty files are an error, and so is a file
/// larger than [`MAX_TOKEN_FILE_BYTES`] (checked before it is read, so a device or a huge file
/// is refused rather than read).
pub fn read_token_file(path: &std::path::Path) -> std::io::Result<String> {
    use std::io::Read;
    let file = std::fs::File::open(path)?;
    let mut bytes = Vec::new();
    file.take(MAX_TOKEN_FILE_BYTES + 1)
        .read_to_end(&mut bytes)?;
    parse_token_file(&bytes, path)
}

/// A token file's token from its bytes (`path` names it in errors): the first line, trimmed,
/// of visible ASCII characters and spaces (what a header value can carry).
pub fn parse_token_file(bytes: &[u8], path: &std::path::Path) -> std::io::Result<String> {
    let invalid = |message: String| std::io::Error::new(std::io::ErrorKind::InvalidData, message);
    if bytes.len() as u64 > MAX_TOKEN_FILE_BYTES {
        return Err(invalid(format!(
            "{} is larger than the {MAX_TOKEN_FILE_BYTES} bytes a token file may have",
            path.display()
        )));
    }
    let line = bytes.split(|&b| b == b'\n').next().unwrap_or(&[]);
    let text = std::str::from_utf8(line).map_err(|_| {
        invalid(format!(
            "{}: the token is not text (expected visible ASCII characters)",
            path.display()
        ))
    })?;
    let token = text.trim();
    if token.is_empty() {
        return Err(invalid(format!("{} holds no token", path.display())));
    }
    if let Some(c) = token.chars().find(|&c| !(c.is_ascii_graphic() || c == ' ')) {
        return Err(invalid(format!(
            "{}: the token holds {c:?}; expected visible ASCII characters only",
            path.display()
        )));
    }
    Ok(token.to_string())
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

    #[test]
    fn token_files_are_checked() {
        let p = std::path::Path::new("tok");
        assert_eq!(parse_token_file(b"  abc \r\nrest", p).unwrap(), "abc");
        for (bytes, expect) in [
            (&b"\n"[..], "holds no token"),
            (&b"a\x01b\n"[..], "visible ASCII"),
            (&b"\xff\xfe"[..], "not text"),
            (&b"caf\xc3\xa9"[..], "visible ASCII"),
        ] {
            let e = parse_token_file(bytes, p).unwrap_err().to_string();
            assert!(e.contains("tok") && e.contains(expect), "{e}");
        }
        let huge = vec![b'a'; MAX_TOKEN_FILE_BYTES as usize + 1];
        assert!(parse_token_file(&huge, p)
            .unwrap_err()
            .to_string()
            .contains("larger than"));
    }
}
