//! Observation files (`docs/model.md`, "Observation files"): an `[P·K, P·K]` float32 NPY of
//! fractions `O[i][j]` and a JSON sidecar of the same name with a `.json` extension.
//!
//! Reading trusts nothing in either file: the sidecar is checked key by key (a valid geometry,
//! at least one photon), then the NPY header is parsed here (magic, version, a capped header
//! length, dtype `<f4`, C order, a 2-D shape) and checked against the sidecar's `P·K × P·K`
//! and [`MAX_DATA_BYTES`] before anything the file's size claims is allocated; the file's length
//! must be exactly header plus data, and every value a finite number `>= 0`. Every error names
//! the file, and the key, row and column, or header field at fault.
//!
//! Writes go to temporary files in the target directory and are renamed into place, so an
//! interrupted run never leaves a partial file under the requested name.

use anyhow::{Context, Result};
use ndarray::Array2;
use ndarray_npy::WriteNpyExt;
use scatterfarm_model::{CountMatrix, Geometry};
use serde::{de::DeserializeOwned, Deserialize, Serialize};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The sidecar's `format` value.
pub const FORMAT: &str = "scatterfarm-observation/1";

/// The most data bytes an observation may hold (a 16 384 × 16 384 float32 matrix, what one
/// message can carry).
pub const MAX_DATA_BYTES: u64 = 1 << 30;
/// The longest NPY header read (numpy's own reader stops at 10 000 bytes).
pub const MAX_HEADER_BYTES: usize = 16 * 1024;
/// The largest sidecar read.
pub const MAX_SIDECAR_BYTES: u64 = 1 << 20;
/// The largest NPY file read: the longest header and the most data.
pub const MAX_NPY_FILE_BYTES: u64 = MAX_DATA_BYTES + 12 + MAX_HEADER_BYTES as u64;

const MAGIC: &[u8] = b"\x93NUMPY";

/// What is wrong with an observation file or its sidecar; each names the file.
#[derive(Debug, Error)]
pub enum ObservationError {
    #[error("cannot read {file}: {source}")]
    Read {
        file: String,
        source: std::io::Error,
    },
    #[error(
        "cannot read the sidecar {file} of {npy} (write one with `scatterfarm describe`): {source}"
    )]
    ReadSidecar {
        file: String,
        npy: String,
        source: std::io::Error,
    },
    #[error("{file} is {bytes} bytes, more than the {limit} bytes an {what} may have")]
    FileTooLarge {
        file: String,
        what: &'static str,
        bytes: u64,
        limit: u64,
    },
    #[error("{file}: not a float32 NPY as expected: {problem}")]
    Header { file: String, problem: String },
    #[error(
        "{file}: shape {shape:?} does not match its geometry: {positions} positions × \
         {directions} directions = {sources} sources needs [{sources}, {sources}]"
    )]
    Shape {
        file: String,
        shape: Vec<u64>,
        positions: u32,
        directions: u32,
        sources: usize,
    },
    #[error(
        "{file}: {sources} × {sources} float32 values are {bytes} bytes, more than the \
         {limit} bytes an observation may hold"
    )]
    DataTooLarge {
        file: String,
        sources: usize,
        bytes: u64,
        limit: u64,
    },
    #[error(
        "{file} is {bytes} bytes, expected {expected} (a {header}-byte header and {sources} × \
         {sources} float32 values)"
    )]
    Length {
        file: String,
        bytes: u64,
        expected: u64,
        header: usize,
        sources: usize,
    },
    #[error(
        "{file}: the value at row {row}, column {column} is {value}; expected a finite number >= 0"
    )]
    Value {
        file: String,
        row: usize,
        column: usize,
        value: f32,
    },
    #[error("sidecar {file}: not a JSON object: {detail}")]
    SidecarJson { file: String, detail: String },
    #[error("sidecar {file}: key `{key}`: expected {expected}{detail}")]
    SidecarKey {
        file: String,
        key: &'static str,
        expected: &'static str,
        /// What was found instead, with a leading separator (empty for a missing key).
        detail: String,
    },
}

fn display(path: &Path) -> String {
    path.display().to_string()
}

/// The JSON sidecar of an observation file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sidecar {
    pub format: String,
    pub size_mm: f64,
    pub positions: u32,
    pub directions: u32,
    /// Photons launched per source (for captures: the effective sample size).
    pub photons_per_source: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub engine: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_sha256: Option<String>,
    /// The scene file or built-in name the observation was rendered from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// Photons that left the medium, over all sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_exited: Option<u64>,
    /// Photons absorbed, over all sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_absorbed: Option<u64>,
}

impl Sidecar {
    /// A sidecar for a render of `geometry` with `photons_per_source` photons.
    pub fn for_render(geometry: &Geometry, photons_per_source: u64) -> Self {
        Sidecar {
            format: FORMAT.into(),
            size_mm: geometry.size_mm,
            positions: geometry.positions,
            directions: geometry.directions,
            photons_per_source,
            seed: None,
            engine: None,
            scene_sha256: None,
            scene: None,
            photons_exited: None,
            photons_absorbed: None,
        }
    }

    /// Number of sources (and bins) `P·K`.
    pub fn sources(&self) -> usize {
        (self.positions as usize) * (self.directions as usize)
    }

    /// Parses and checks a sidecar's bytes key by key; `path` (the sidecar's) names it in errors.
    pub fn from_json(bytes: &[u8], path: &Path) -> Result<Sidecar, ObservationError> {
        let file = display(path);
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| ObservationError::SidecarJson {
                file: file.clone(),
                detail: e.to_string(),
            })?;
        let serde_json::Value::Object(object) = value else {
            return Err(ObservationError::SidecarJson {
                file,
                detail: format!("found {}", json_type(&value)),
            });
        };
        let key_error = |key: &'static str, expected: &'static str, detail: String| {
            ObservationError::SidecarKey {
                file: file.clone(),
                key,
                expected,
                detail,
            }
        };
        // A key's value as `T`; `None` when absent (or null).
        fn field<T: DeserializeOwned>(
            object: &serde_json::Map<String, serde_json::Value>,
            key: &'static str,
            expected: &'static str,
            error: &dyn Fn(&'static str, &'static str, String) -> ObservationError,
        ) -> Result<Option<T>, ObservationError> {
            match object.get(key) {
                None | Some(serde_json::Value::Null) => Ok(None),
                Some(v) => T::deserialize(v)
                    .map(Some)
                    .map_err(|_| error(key, expected, format!(", got {}", short(v)))),
            }
        }
        fn required<T>(
            v: Option<T>,
            key: &'static str,
            expected: &'static str,
            error: &dyn Fn(&'static str, &'static str, String) -> ObservationError,
        ) -> Result<T, ObservationError> {
            v.ok_or_else(|| error(key, expected, ", but it is missing".into()))
        }
        let e = &key_error;
        let format: String = required(
            field(&object, "format", "a string", e)?,
            "format",
            "a string",
            e,
        )?;
        if format != FORMAT {
            return Err(e(
                "format",
                "\"scatterfarm-observation/1\"",
                format!(", got {format:?}"),
            ));
        }
        const SIZE: &str = "a finite number of mm > 0";
        let size_mm: f64 = required(field(&object, "size_mm", SIZE, e)?, "size_mm", SIZE, e)?;
        if !(size_mm.is_finite() && size_mm > 0.0) {
            return Err(e("size_mm", SIZE, format!(", got {size_mm}")));
        }
        const POSITIONS: &str = "a whole number > 0 divisible by 4";
        let positions: u32 = required(
            field(&object, "positions", POSITIONS, e)?,
            "positions",
            POSITIONS,
            e,
        )?;
        if positions == 0 || !positions.is_multiple_of(4) {
            return Err(e("positions", POSITIONS, format!(", got {positions}")));
        }
        const DIRECTIONS: &str = "a whole number >= 1";
        let directions: u32 = required(
            field(&object, "directions", DIRECTIONS, e)?,
            "directions",
            DIRECTIONS,
            e,
        )?;
        if directions == 0 {
            return Err(e("directions", DIRECTIONS, format!(", got {directions}")));
        }
        let geometry = Geometry {
            size_mm,
            grid: 1,
            positions,
            directions,
        };
        if let Err(g) = geometry.validate() {
            return Err(e(
                "directions",
                "positions × directions within the geometry's limit",
                format!(": {g}"),
            ));
        }
        const PHOTONS: &str = "a whole number >= 1";
        let photons_per_source: u64 = required(
            field(&object, "photons_per_source", PHOTONS, e)?,
            "photons_per_source",
            PHOTONS,
            e,
        )?;
        if photons_per_source == 0 {
            return Err(e("photons_per_source", PHOTONS, ", got 0".into()));
        }
        const WHOLE: &str = "a whole number >= 0";
        const TEXT: &str = "a string";
        Ok(Sidecar {
            format,
            size_mm,
            positions,
            directions,
            photons_per_source,
            seed: field(&object, "seed", WHOLE, e)?,
            engine: field(&object, "engine", TEXT, e)?,
            scene_sha256: field(&object, "scene_sha256", TEXT, e)?,
            scene: field(&object, "scene", TEXT, e)?,
            photons_exited: field(&object, "photons_exited", WHOLE, e)?,
            photons_absorbed: field(&object, "photons_absorbed", WHOLE, e)?,
        })
    }
}

fn json_type(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

/// A JSON value for an error message: numbers and short strings as they are, else its type.
fn short(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Number(n) => n.to_string(),
        serde_json::Value::Bool(b) => b.to_string(),
        serde_json::Value::String(s) if s.len() <= 64 => format!("{s:?}"),
        other => json_type(other).to_string(),
    }
}

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

/// Reads a whole file of at most `limit` bytes (its size is checked before reading).
pub fn read_capped(
    path: &Path,
    limit: u64,
    what: &'static str,
) -> Result<Vec<u8>, ObservationError> {
    let read_error = |source| ObservationError::Read {
        file: display(path),
        source,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let bytes = file.metadata().map_err(read_error)?.len();
    if bytes > limit {
        return Err(ObservationError::FileTooLarge {
            file: display(path),
            what,
            bytes,
            limit,
        });
    }
    let mut out = Vec::with_capacity(usize::try_from(bytes).unwrap_or(0));
    // `take` bounds a file that grows while it is read.
    std::io::Read::read_to_end(&mut std::io::Read::take(file, limit + 1), &mut out)
        .map_err(read_error)?;
    if out.len() as u64 > limit {
        return Err(ObservationError::FileTooLarge {
            file: display(path),
            what,
            bytes: out.len() as u64,
            limit,
        });
    }
    Ok(out)
}

/// The sidecar path of an observation file: same name, `.json` extension.
pub fn sidecar_path(npy: &Path) -> PathBuf {
    npy.with_extension("json")
}

/// Counts divided by the photons launched per source.
pub fn fractions(counts: &CountMatrix, photons_per_source: u64) -> Array2<f32> {
    let scale = 1.0 / photons_per_source.max(1) as f64;
    Array2::from_shape_fn((counts.sources, counts.bins), |(i, j)| {
        (f64::from(counts.counts[i * counts.bins + j]) * scale) as f32
    })
}

/// Writes `data` to `path` atomically: a temporary file beside it, then a rename.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create directory {}", dir.display()))?;
    let mut tmp = tempfile::Builder::new()
        .prefix(".scatterfarm-")
        .suffix(".tmp")
        .tempfile_in(&dir)
        .with_context(|| format!("cannot create a temporary file in {}", dir.display()))?;
    {
        let mut w = BufWriter::new(tmp.as_file_mut());
        write(&mut w)?;
        w.flush()
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    tmp.as_file()
        .sync_all()
        .with_context(|| format!("cannot sync {}", path.display()))?;
    tmp.persist(path)
        .with_context(|| format!("cannot move the finished file to {}", path.display()))?;
    Ok(())
}

/// Writes the observation and its sidecar (sidecar first, so a present NPY always has one).
pub fn write(path: &Path, observation: &Array2<f32>, sidecar: &Sidecar) -> Result<()> {
    let json = serde_json::to_vec_pretty(sidecar)?;
    write_atomically(&sidecar_path(path), |w| Ok(w.write_all(&json)?))?;
    write_atomically(path, |w| {
        observation
            .write_npy(w)
            .with_context(|| format!("cannot write NPY {}", path.display()))
    })
}

/// Reads an observation file and its sidecar from disk (each size-checked before it is read).
pub fn read(path: &Path) -> Result<(Array2<f32>, Sidecar), ObservationError> {
    let side = sidecar_path(path);
    let sidecar =
        read_capped(&side, MAX_SIDECAR_BYTES, "observation sidecar").map_err(|e| match e {
            ObservationError::Read { file, source } => ObservationError::ReadSidecar {
                file,
                npy: display(path),
                source,
            },
            other => other,
        })?;
    let npy = read_capped(path, MAX_NPY_FILE_BYTES, "observation file")?;
    read_bytes(&npy, &sidecar, path)
}

/// Parses an observation file from its bytes and its sidecar's; `path` names it in errors.
/// The sidecar is checked first, so the NPY header is checked against its geometry.
pub fn read_bytes(
    npy: &[u8],
    sidecar: &[u8],
    path: &Path,
) -> Result<(Array2<f32>, Sidecar), ObservationError> {
    let sidecar = Sidecar::from_json(sidecar, &sidecar_path(path))?;
    let data = read_npy(npy, path, &sidecar)?;
    Ok((data, sidecar))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_atomic_names() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obs.npy");
        let geo = Geometry::new(16.0, 4, 8, 1).unwrap();
        let mut counts = CountMatrix::zeros(8, 8);
        counts.counts[3] = 5;
        let obs = fractions(&counts, 10);
        let mut side = Sidecar::for_render(&geo, 10);
        side.seed = Some(3);
        write(&path, &obs, &side).unwrap();
        let (back, back_side) = read(&path).unwrap();
        assert_eq!(back[[0, 3]], 0.5);
        assert_eq!(back_side, side);
        // Only the two files remain: no temporary left behind.
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 2, "{names:?}");
    }

    #[test]
    fn mismatched_shape_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obs.npy");
        let geo = Geometry::new(16.0, 4, 8, 1).unwrap();
        write(&path, &Array2::zeros((4, 4)), &Sidecar::for_render(&geo, 1)).unwrap();
        let e = read(&path).unwrap_err().to_string();
        assert!(
            e.contains("does not match its geometry") && e.contains("obs.npy"),
            "{e}"
        );
    }

    /// An NPY file's bytes: a version 1.0 header of `dict`, then `data`.
    fn npy(dict: &str, data: &[u8]) -> Vec<u8> {
        let mut header = dict.to_string();
        while !(10 + header.len() + 1).is_multiple_of(64) {
            header.push(' ');
        }
        header.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn sidecar(positions: u32, directions: u32) -> Vec<u8> {
        let geo = Geometry::new(16.0, 1, positions, directions).unwrap();
        serde_json::to_vec(&Sidecar::for_render(&geo, 100)).unwrap()
    }

    fn floats(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    const GOOD: &str = "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4), }";

    fn refusal(npy_bytes: &[u8], side: &[u8]) -> String {
        match read_bytes(npy_bytes, side, Path::new("evil.npy")) {
            Ok(_) => panic!("accepted"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn a_huge_claimed_shape_is_refused_before_allocating() {
        // The file: 100 bytes claiming (2³⁰, 2³⁰) float32.
        let evil = npy(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1073741824, 1073741824), }",
            &[],
        );
        let e = refusal(&evil, &sidecar(4, 1));
        assert!(
            e.contains("evil.npy")
                && e.contains("[1073741824, 1073741824]")
                && e.contains("needs [4, 4]"),
            "{e}"
        );
        // Matching the sidecar is not enough: the data cap holds too.
        let big = npy(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (65536, 65536), }",
            &[],
        );
        let e = refusal(&big, &sidecar(65536, 1));
        assert!(e.contains("more than the 1073741824 bytes"), "{e}");
        // And so does the length: header plus data exactly.
        let e = refusal(&npy(GOOD, &floats(&[0.0; 15])), &sidecar(4, 1));
        assert!(e.contains("is 188 bytes, expected 192"), "{e}");
        let e = refusal(&npy(GOOD, &floats(&[0.0; 17])), &sidecar(4, 1));
        assert!(e.contains("expected 192"), "{e}");
    }

    #[test]
    fn header_fields_are_checked() {
        let side = sidecar(4, 1);
        let data = floats(&[0.0; 16]);
        for (dict, expect) in [
            (
                "{'descr': '<f8', 'fortran_order': False, 'shape': (4, 4), }",
                "'<f4'",
            ),
            (
                "{'descr': '>f4', 'fortran_order': False, 'shape': (4, 4), }",
                "'<f4'",
            ),
            (
                "{'descr': '<f4', 'fortran_order': True, 'shape': (4, 4), }",
                "C (row-major)",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (16,), }",
                "expected 2-D",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4, 1), }",
                "expected 2-D",
            ),
            ("{'descr': '<f4', 'fortran_order': False, }", "no shape"),
            ("{'descr': '<f4', 'shape': (4, 4), }", "fortran_order"),
            (
                "{'descr': '<f4', 'descr': '<f4', 'fortran_order': False, 'shape': (4, 4)}",
                "twice",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4), 'x': 1}",
                "unknown header key",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999999999999, 4)}",
                "too large",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4)",
                "expected '}'",
            ),
        ] {
            let e = refusal(&npy(dict, &data), &side);
            assert!(e.contains("evil.npy") && e.contains(expect), "{dict}: {e}");
        }
        let mut bad = npy(GOOD, &data);
        bad[0] = b'X';
        assert!(refusal(&bad, &side).contains("magic"));
        let mut bad = npy(GOOD, &data);
        bad[6] = 4;
        assert!(refusal(&bad, &side).contains("version 4.0"));
        // A huge header length (version 2: 32 bits) is refused before it is read.
        let mut bad = b"\x93NUMPY\x02\x00".to_vec();
        bad.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = refusal(&bad, &side);
        assert!(
            e.contains("4294967295 bytes, expected at most 16384"),
            "{e}"
        );
        // A header longer than the file.
        let good = npy(GOOD, &data);
        assert!(refusal(&good[..40], &side).contains("the file ends after"));
        assert!(refusal(&good[..9], &side).contains("magic"));
        // Version 2 and 3 headers and a Python-2 long are read.
        let mut v2 = b"\x93NUMPY\x03\x00".to_vec();
        let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (4L, 4L), }\n";
        v2.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        v2.extend_from_slice(dict.as_bytes());
        v2.extend_from_slice(&data);
        assert!(read_bytes(&v2, &side, Path::new("v3.npy")).is_ok());
    }

    #[test]
    fn bad_values_are_refused_with_their_index() {
        let side = sidecar(4, 1);
        for (bad, shown) in [(f32::NAN, "NaN"), (f32::INFINITY, "inf"), (-0.5, "-0.5")] {
            let mut values = [0.25; 16];
            values[2 * 4 + 3] = bad;
            let e = refusal(&npy(GOOD, &floats(&values)), &side);
            assert!(
                e.contains("evil.npy") && e.contains("row 2, column 3") && e.contains(shown),
                "{e}"
            );
        }
        let (data, _) =
            read_bytes(&npy(GOOD, &floats(&[0.25; 16])), &side, Path::new("ok.npy")).unwrap();
        assert_eq!(data[[3, 3]], 0.25);
    }

    #[test]
    fn sidecar_errors_name_the_file_and_key() {
        let data = npy(GOOD, &floats(&[0.0; 16]));
        let good: serde_json::Value = serde_json::from_slice(&sidecar(4, 1)).unwrap();
        let with = |key: &str, v: serde_json::Value| {
            let mut s = good.clone();
            match v {
                serde_json::Value::Null => {
                    s.as_object_mut().unwrap().remove(key);
                }
                v => {
                    s[key] = v;
                }
            }
            serde_json::to_vec(&s).unwrap()
        };
        use serde_json::json;
        for (key, v, expect) in [
            ("positions", json!("4"), "got \"4\""),
            ("positions", json!(6), "divisible by 4"),
            ("positions", json!(-4), "got -4"),
            ("positions", serde_json::Value::Null, "missing"),
            ("directions", json!(0), ">= 1"),
            ("directions", json!(100000), "65536"),
            ("size_mm", json!(0), "> 0"),
            ("photons_per_source", json!(0), ">= 1"),
            ("format", json!("other"), "scatterfarm-observation/1"),
            ("seed", json!(1.5), "whole number"),
            ("engine", json!([1]), "got an array"),
        ] {
            let e = refusal(&data, &with(key, v));
            assert!(
                e.contains("evil.json") && e.contains(&format!("`{key}`")) && e.contains(expect),
                "{key}: {e}"
            );
        }
        let e = refusal(&data, b"{\"format\": ");
        assert!(e.contains("evil.json") && e.contains("EOF"), "{e}");
        let e = refusal(&data, b"[1, 2]");
        assert!(e.contains("evil.json") && e.contains("an array"), "{e}");
    }

    #[test]
    fn oversized_files_are_refused_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.json");
        let f = std::fs::File::create(&path).unwrap();
        f.set_len(MAX_SIDECAR_BYTES + 1).unwrap();
        let e = read_capped(&path, MAX_SIDECAR_BYTES, "observation sidecar")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("big.json") && e.contains("more than the 1048576 bytes"),
            "{e}"
        );
    }
}
