//! `scatterfarm describe OBS.npy`: write the JSON sidecar of a captured matrix that has none.

use anyhow::{ensure, Context, Result};
use clap::Args;
use scatterfarm_job::observation::{self, Sidecar};
use scatterfarm_model::Geometry;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct DescribeArgs {
    /// The captured observation matrix (float32 NPY, [P·K, P·K]).
    pub observation: PathBuf,
    /// Side of the medium, mm.
    #[arg(long)]
    pub size_mm: f64,
    /// Boundary positions P.
    #[arg(long)]
    pub positions: u32,
    /// Directions per position K.
    #[arg(long)]
    pub directions: u32,
    /// Photons per source (for a capture: its effective sample size).
    #[arg(long)]
    pub photons: u64,
    /// Replace an existing sidecar.
    #[arg(long)]
    pub force: bool,
}

pub fn run(args: DescribeArgs) -> Result<()> {
    let geometry = Geometry::new(args.size_mm, 1, args.positions, args.directions)
        .context("invalid geometry")?;
    ensure!(args.photons > 0, "--photons must be at least 1");
    let sidecar = Sidecar::for_render(&geometry, args.photons);
    // The same checks as every read: header against the geometry, length, values.
    let bytes = observation::read_capped(
        &args.observation,
        observation::MAX_NPY_FILE_BYTES,
        "observation file",
    )?;
    observation::read_npy(&bytes, &args.observation, &sidecar)?;
    let path = observation::sidecar_path(&args.observation);
    ensure!(
        !path.exists() || args.force,
        "{} exists; pass --force to replace it",
        path.display()
    );
    let json = serde_json::to_vec_pretty(&sidecar)?;
    observation::write_atomically(&path, |w| Ok(w.write_all(&json)?))?;
    eprintln!("wrote {}", path.display());
    Ok(())
}
