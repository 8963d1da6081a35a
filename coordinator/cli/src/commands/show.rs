//! `scatterfarm show SCENE|OBS.npy --out PNG`: draw a material map or an observation matrix.

use anyhow::Result;
use clap::Args;
use scatterfarm_job::{observation, picture, scene_source};
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct ShowArgs {
    /// A scene file or built-in name (drawn as a material map), or an observation `.npy`
    /// (drawn as a log-scale heat map).
    pub input: String,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: ShowArgs) -> Result<()> {
    let path = Path::new(&args.input);
    let img = if path.extension().is_some_and(|e| e == "npy") && path.is_file() {
        let (obs, _) = observation::read(path)?;
        picture::observation_heat_map(&obs)
    } else {
        let loaded = scene_source::load(&args.input)?;
        let s = &loaded.scene;
        let grid = s.geometry.grid as usize;
        let map = picture::material_map(&s.assignment, grid, &s.table, picture::cell_size(grid));
        picture::panels_with_legend(&[(loaded.origin.as_str(), map)], &s.table)
    };
    picture::save_png(&img, &args.out)?;
    eprintln!("wrote {}", args.out.display());
    Ok(())
}
