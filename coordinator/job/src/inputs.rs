//! The input files of a reconstruction, held in memory by the name the parameters give them:
//! read from disk by `reconstruct` and `submit`, sent with a job, stored by the coordinator.
//! Each file's size is checked against its kind's cap before it is read; the same checks of
//! its contents run for files read here and files that arrive as bytes with a submission.

use crate::observation::{self, Sidecar};
use crate::scene_source::LoadedScene;
use crate::spec::JobSpec;
use anyhow::{bail, Context, Result};
use ndarray::Array2;
use scatterfarm_model::scene::MAX_SCENE_BYTES;
use scatterfarm_model::{builtin, Scene};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::Path;

/// File name (as the parameters write it) → contents.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Inputs {
    pub files: BTreeMap<String, Vec<u8>>,
}

fn key(path: &Path) -> String {
    path.to_string_lossy().into_owned()
}

impl Inputs {
    /// Reads every file `params` names; relative paths are taken against `base`.
    pub fn gather(params: &JobSpec, base: &Path) -> Result<Inputs> {
        let mut files = BTreeMap::new();
        if let Some(scene) = &params.scene {
            let path = base.join(scene);
            if path.is_file() {
                let bytes = observation::read_capped(&path, MAX_SCENE_BYTES, "scene file")
                    .with_context(|| format!("cannot read scene file {}", path.display()))?;
                files.insert(scene.clone(), bytes);
            } else if builtin::toml(scene).is_none() {
                let names: Vec<&str> = builtin::list().iter().map(|b| b.name).collect();
                bail!(
                    "no scene file at {} and no built-in scene named {scene:?} (built-in: {})",
                    path.display(),
                    names.join(", ")
                );
            }
        }
        for p in [&params.target, &params.calibration].into_iter().flatten() {
            for file in [p.clone(), observation::sidecar_path(p)] {
                let path = base.join(&file);
                let (limit, what) = if file == *p {
                    (observation::MAX_NPY_FILE_BYTES, "observation file")
                } else {
                    (observation::MAX_SIDECAR_BYTES, "observation sidecar")
                };
                let bytes = observation::read_capped(&path, limit, what).with_context(|| {
                    if file == *p {
                        format!("cannot read {}", path.display())
                    } else {
                        format!(
                            "cannot read the sidecar {} (write one with `scatterfarm describe`)",
                            path.display()
                        )
                    }
                })?;
                files.insert(key(&file), bytes);
            }
        }
        Ok(Inputs { files })
    }

    /// The scene `name` names: the file sent under that name, else a built-in scene.
    pub fn scene(&self, name: &str) -> Result<LoadedScene> {
        let text = match self.files.get(name) {
            Some(bytes) if bytes.len() as u64 > MAX_SCENE_BYTES => bail!(
                "scene file {name} is {} bytes, more than the {MAX_SCENE_BYTES} a scene file may have",
                bytes.len()
            ),
            Some(bytes) => String::from_utf8(bytes.clone())
                .with_context(|| format!("scene file {name} is not UTF-8 text"))?,
            None => builtin::toml(name).with_context(|| {
                let names: Vec<&str> = builtin::list().iter().map(|b| b.name).collect();
                format!(
                    "no scene file {name:?} and no built-in scene of that name (built-in: {})",
                    names.join(", ")
                )
            })?,
        };
        let scene = Scene::from_toml(&text).with_context(|| format!("scene {name}"))?;
        Ok(LoadedScene {
            scene,
            origin: name.to_string(),
            sha256: hex::encode(Sha256::digest(text.as_bytes())),
        })
    }

    /// The observation file `path` names, with its sidecar.
    pub fn observation(&self, path: &Path) -> Result<(Array2<f32>, Sidecar)> {
        let npy = self
            .files
            .get(&key(path))
            .with_context(|| format!("{} was not sent with the job", path.display()))?;
        let side_path = observation::sidecar_path(path);
        let side = self
            .files
            .get(&key(&side_path))
            .with_context(|| format!("{} was not sent with the job", side_path.display()))?;
        Ok(observation::read_bytes(npy, side, path)?)
    }
}
