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

mod files;
mod npy;
mod sidecar;
#[cfg(test)]
mod tests;

pub use files::{read_capped, write_atomically};
pub use npy::{parse_npy_header, read_npy, NpyHeader};
pub use sidecar::Sidecar;

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
