//! Observation files (`docs/model.md`, "Observation files"): an `[P·K, P·K]` float32 NPY of
//! fractions `O[i][j]` and a JSON sidecar of the same name with a `.json` extension.
//!
//! Writes go to temporary files in the target directory and are renamed into place, so an
//! interrupted run never leaves a partial file under the requested name.

use anyhow::{bail, Context, Result};
use ndarray::Array2;
use ndarray_npy::{ReadNpyExt, WriteNpyExt};
use scatterfarm_model::{CountMatrix, Geometry};
use serde::{Deserialize, Serialize};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// The sidecar's `format` value.
pub const FORMAT: &str = "scatterfarm-observation/1";

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

/// Reads an observation file and its sidecar from disk.
pub fn read(path: &Path) -> Result<(Array2<f32>, Sidecar)> {
    let side = sidecar_path(path);
    let sidecar = std::fs::read(&side).with_context(|| {
        format!(
            "cannot read the sidecar {} of {} (write one with `scatterfarm describe`)",
            side.display(),
            path.display()
        )
    })?;
    let npy = std::fs::read(path).with_context(|| format!("cannot open {}", path.display()))?;
    read_bytes(&npy, &sidecar, path)
}

/// Parses an observation file from its bytes and its sidecar's; `path` names it in errors.
pub fn read_bytes(npy: &[u8], sidecar: &[u8], path: &Path) -> Result<(Array2<f32>, Sidecar)> {
    let side = sidecar_path(path);
    let sidecar: Sidecar =
        serde_json::from_slice(sidecar).with_context(|| format!("sidecar {}", side.display()))?;
    if sidecar.format != FORMAT {
        bail!(
            "{}: format is {:?}, expected {FORMAT:?}",
            side.display(),
            sidecar.format
        );
    }
    let data = Array2::<f32>::read_npy(npy)
        .with_context(|| format!("{} is not a 2-D float32 NPY", path.display()))?;
    let n = sidecar.sources();
    if data.shape() != [n, n] {
        bail!(
            "{}: shape {:?} does not match its sidecar ({} positions × {} directions = {n} sources)",
            path.display(),
            data.shape(),
            sidecar.positions,
            sidecar.directions
        );
    }
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
        let e = format!("{:#}", read(&path).unwrap_err());
        assert!(e.contains("does not match its sidecar"), "{e}");
    }
}
