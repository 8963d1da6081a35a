//! `scatterfarm describe OBS.npy`: write the JSON sidecar of a captured matrix that has none.

use anyhow::{ensure, Context, Result};
use clap::Args;
use ndarray::Array2;
use ndarray_npy::ReadNpyExt;
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
    let file = std::fs::File::open(&args.observation)
        .with_context(|| format!("cannot open {}", args.observation.display()))?;
    let data = Array2::<f32>::read_npy(std::io::BufReader::new(file))
        .with_context(|| format!("{} is not a 2-D float32 NPY", args.observation.display()))?;
    let n = geometry.sources();
    ensure!(
        data.shape() == [n, n],
        "{} has shape {:?}; {} positions × {} directions needs [{n}, {n}]",
        args.observation.display(),
        data.shape(),
        args.positions,
        args.directions
    );
    let path = observation::sidecar_path(&args.observation);
    ensure!(
        !path.exists() || args.force,
        "{} exists; pass --force to replace it",
        path.display()
    );
    let sidecar = Sidecar::for_render(&geometry, args.photons);
    let json = serde_json::to_vec_pretty(&sidecar)?;
    observation::write_atomically(&path, |w| Ok(w.write_all(&json)?))?;
    eprintln!("wrote {}", path.display());
    Ok(())
}
