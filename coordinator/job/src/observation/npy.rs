//! The NPY format, read without trusting it: the header parsed and checked (magic, version,
//! a capped length, dtype, order, a 2-D shape) before the data it describes is touched.

use super::*;

const MAGIC: &[u8] = b"\x93NUMPY";

/// An NPY header, parsed and checked: where the data starts and the array's shape.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyHeader {
    /// Bytes before the data: magic, version, header length and the header.
    pub data_offset: usize,
    /// The shape (always 2-D, row-major `<f4` data).
    pub shape: [u64; 2],
}

fn header_error(path: &Path, problem: impl Into<String>) -> ObservationError {
    ObservationError::Header {
        file: display(path),
        problem: problem.into(),
    }
}

/// Parses the NPY header at the start of `bytes`: magic, version 1.0, 2.0 or 3.0, a header of
/// at most [`MAX_HEADER_BYTES`], `descr` `'<f4'`, `fortran_order` `False` and a 2-D `shape`.
/// Reads nothing past the header and allocates nothing the header's numbers control.
pub fn parse_npy_header(bytes: &[u8], path: &Path) -> Result<NpyHeader, ObservationError> {
    if bytes.len() < 10 || !bytes.starts_with(MAGIC) {
        return Err(header_error(
            path,
            "expected the magic string \\x93NUMPY at the start",
        ));
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (length, offset) = match (major, minor) {
        (1, 0) => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        (2, 0) | (3, 0) => {
            let Some(b) = bytes.get(8..12) else {
                return Err(header_error(path, "the file ends inside the header length"));
            };
            let length = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let length = usize::try_from(length).unwrap_or(usize::MAX);
            (length, 12)
        }
        _ => {
            return Err(header_error(
                path,
                format!("format version {major}.{minor}, expected 1.0, 2.0 or 3.0"),
            ))
        }
    };
    if length > MAX_HEADER_BYTES {
        return Err(header_error(
            path,
            format!("a header of {length} bytes, expected at most {MAX_HEADER_BYTES}"),
        ));
    }
    let Some(header) = bytes.get(offset..offset + length) else {
        return Err(header_error(
            path,
            format!(
                "a header of {length} bytes, but the file ends after {}",
                bytes.len() - offset
            ),
        ));
    };
    let header =
        std::str::from_utf8(header).map_err(|_| header_error(path, "the header is not text"))?;
    let dict = parse_header_dict(header).map_err(|p| header_error(path, p))?;
    if dict.descr.as_deref() != Some("<f4") {
        return Err(header_error(
            path,
            format!(
                "dtype {}, expected '<f4' (little-endian float32)",
                dict.descr
                    .as_deref()
                    .map_or("missing".into(), |d| format!("{d:?}"))
            ),
        ));
    }
    match dict.fortran_order {
        Some(false) => {}
        Some(true) => {
            return Err(header_error(
                path,
                "Fortran order, expected C (row-major) order",
            ))
        }
        None => return Err(header_error(path, "no fortran_order, expected False")),
    }
    let shape = match dict.shape.as_deref() {
        Some([rows, columns]) => [*rows, *columns],
        Some(other) => {
            return Err(header_error(
                path,
                format!("a {}-D shape {other:?}, expected 2-D", other.len()),
            ))
        }
        None => return Err(header_error(path, "no shape, expected a 2-D shape")),
    };
    Ok(NpyHeader {
        data_offset: offset + length,
        shape,
    })
}

/// The keys of an NPY header dictionary.
#[derive(Default)]
struct HeaderDict {
    descr: Option<String>,
    fortran_order: Option<bool>,
    shape: Option<Vec<u64>>,
}

/// The most dimensions a header's shape may list (numpy's own limit is 64).
const MAX_DIMENSIONS: usize = 64;

/// Parses the Python dict literal of an NPY header: string keys `descr`, `fortran_order` and
/// `shape`, with a string, `True`/`False` and a tuple of whole numbers. No recursion, so no
/// nesting can exhaust the stack.
fn parse_header_dict(text: &str) -> Result<HeaderDict, String> {
    let mut s = Cursor {
        bytes: text.as_bytes(),
        at: 0,
    };
    let mut dict = HeaderDict::default();
    s.expect(b'{')?;
    loop {
        s.skip_space();
        if s.eat(b'}') {
            break;
        }
        let key = s.string()?;
        s.skip_space();
        s.expect(b':')?;
        s.skip_space();
        let duplicate = match key.as_str() {
            "descr" => dict.descr.replace(s.string()?).is_some(),
            "fortran_order" => dict.fortran_order.replace(s.boolean()?).is_some(),
            "shape" => dict.shape.replace(s.tuple()?).is_some(),
            other => {
                return Err(format!(
                    "unknown header key {other:?}, expected descr, fortran_order and shape"
                ))
            }
        };
        if duplicate {
            return Err(format!("the header key {key:?} appears twice"));
        }
        s.skip_space();
        if s.eat(b',') {
            continue;
        }
        s.skip_space();
        s.expect(b'}')?;
        break;
    }
    s.skip_space();
    if s.at != s.bytes.len() {
        return Err(format!("text after the header dictionary at byte {}", s.at));
    }
    Ok(dict)
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Cursor<'_> {
    fn skip_space(&mut self) {
        while self
            .bytes
            .get(self.at)
            .is_some_and(|b| b.is_ascii_whitespace())
        {
            self.at += 1;
        }
    }

    fn eat(&mut self, b: u8) -> bool {
        if self.bytes.get(self.at) == Some(&b) {
            self.at += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, b: u8) -> Result<(), String> {
        self.skip_space();
        if self.eat(b) {
            Ok(())
        } else {
            Err(format!(
                "expected '{}' at byte {} of the header",
                char::from(b),
                self.at
            ))
        }
    }

    fn string(&mut self) -> Result<String, String> {
        let quote = match self.bytes.get(self.at) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a quoted string at byte {}", self.at)),
        };
        let start = self.at + 1;
        let end = self.bytes[start..]
            .iter()
            .position(|&b| b == quote)
            .map(|p| start + p)
            .ok_or_else(|| format!("a string at byte {} is not closed", self.at))?;
        self.at = end + 1;
        Ok(String::from_utf8_lossy(&self.bytes[start..end]).into_owned())
    }

    fn boolean(&mut self) -> Result<bool, String> {
        for (word, value) in [(&b"True"[..], true), (&b"False"[..], false)] {
            if self.bytes[self.at..].starts_with(word) {
                self.at += word.len();
                return Ok(value);
            }
        }
        Err(format!("expected True or False at byte {}", self.at))
    }

    fn tuple(&mut self) -> Result<Vec<u64>, String> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        loop {
            self.skip_space();
            if self.eat(b')') {
                return Ok(dims);
            }
            let start = self.at;
            while self.bytes.get(self.at).is_some_and(u8::is_ascii_digit) {
                self.at += 1;
            }
            let digits = std::str::from_utf8(&self.bytes[start..self.at]).unwrap_or("");
            if digits.is_empty() {
                return Err(format!(
                    "expected a whole number at byte {start} of the shape"
                ));
            }
            let n: u64 = digits
                .parse()
                .map_err(|_| format!("the dimension {digits} is too large"))?;
            // Python 2 wrote longs with an L.
            self.eat(b'L');
            if dims.len() == MAX_DIMENSIONS {
                return Err(format!("more than {MAX_DIMENSIONS} dimensions"));
            }
            dims.push(n);
            self.skip_space();
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(dims);
            }
        }
    }
}

/// The `sources × sources` float32 matrix in an NPY file's bytes (`path` names it in errors):
/// the header is checked against the expected shape and [`MAX_DATA_BYTES`], the length against
/// header plus data, and every value must be finite and `>= 0`, before and while it is copied.
pub fn read_npy(
    bytes: &[u8],
    path: &Path,
    sidecar: &Sidecar,
) -> Result<Array2<f32>, ObservationError> {
    let file = || display(path);
    let header = parse_npy_header(bytes, path)?;
    let n = sidecar.sources();
    if header.shape != [n as u64, n as u64] {
        return Err(ObservationError::Shape {
            file: file(),
            shape: header.shape.to_vec(),
            positions: sidecar.positions,
            directions: sidecar.directions,
            sources: n,
        });
    }
    let data_bytes = (n as u64)
        .checked_mul(n as u64)
        .and_then(|c| c.checked_mul(4))
        .unwrap_or(u64::MAX);
    if data_bytes > MAX_DATA_BYTES {
        return Err(ObservationError::DataTooLarge {
            file: file(),
            sources: n,
            bytes: data_bytes,
            limit: MAX_DATA_BYTES,
        });
    }
    let expected = header.data_offset as u64 + data_bytes;
    if bytes.len() as u64 != expected {
        return Err(ObservationError::Length {
            file: file(),
            bytes: bytes.len() as u64,
            expected,
            header: header.data_offset,
            sources: n,
        });
    }
    let mut values = Vec::with_capacity(n * n);
    for (i, c) in bytes[header.data_offset..].chunks_exact(4).enumerate() {
        let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        if !(v.is_finite() && v >= 0.0) {
            return Err(ObservationError::Value {
                file: file(),
                row: i / n,
                column: i % n,
                value: v,
            });
        }
        values.push(v);
    }
    Array2::from_shape_vec((n, n), values).map_err(|e| ObservationError::Header {
        file: file(),
        problem: e.to_string(),
    })
}
