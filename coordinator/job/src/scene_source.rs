//! A command-line `SCENE` argument: an existing file is that file, otherwise a built-in name.

use anyhow::{bail, Context, Result};
use scatterfarm_model::{builtin, Scene};
use sha2::{Digest, Sha256};
use std::path::Path;

/// A loaded scene and where it came from.
#[derive(Debug, Clone)]
pub struct LoadedScene {
    pub scene: Scene,
    /// The file path or the built-in name, as given.
    pub origin: String,
    /// SHA-256 of the scene's TOML text.
    pub sha256: String,
}

/// Loads `arg`: a file if one exists at that path, else a built-in scene.
pub fn load(arg: &str) -> Result<LoadedScene> {
    let path = Path::new(arg);
    let text = if path.is_file() {
        let bytes = crate::observation::read_capped(
            path,
            scatterfarm_model::scene::MAX_SCENE_BYTES,
            "scene file",
        )
        .with_context(|| format!("cannot read scene file {arg}"))?;
        String::from_utf8(bytes).with_context(|| format!("scene file {arg} is not UTF-8 text"))?
    } else if let Some(text) = builtin::toml(arg) {
        text
    } else {
        let names: Vec<&str> = builtin::list().iter().map(|b| b.name).collect();
        bail!(
            "no scene file at {arg:?} and no built-in scene of that name (built-in: {})",
            names.join(", ")
        );
    };
    let scene = Scene::from_toml(&text).with_context(|| format!("scene {arg}"))?;
    let sha256 = hex::encode(Sha256::digest(text.as_bytes()));
    Ok(LoadedScene {
        scene,
        origin: arg.to_string(),
        sha256,
    })
}
