//! `scatterfarm render SCENE --out OBS.npy`: the observation set of a scene, with its sidecar.

use crate::engines::EngineArgs;
use anyhow::{ensure, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use scatterfarm_job::observation::{self, Sidecar};
use scatterfarm_job::scene_source;
use scatterfarm_model::{CountMatrix, Engine, RenderItem, Scene};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// A scene file, or a built-in scene's name (see `scatterfarm scenes`).
    pub scene: String,
    /// Where to write the observation NPY; its sidecar goes beside it with a `.json` extension.
    #[arg(long)]
    pub out: PathBuf,
    /// Photons launched per source.
    #[arg(long, default_value_t = 51_200)]
    pub photons: u32,
    /// The render seed: the same seed and engine give identical counts.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub engine: EngineArgs,
}

/// Counts of one scene over photons `[0, photons)`, rendered in chunks so a progress bar can
/// follow (chunks add up exactly to a single render: batch additivity).
pub fn render_scene(
    engine: &dyn Engine,
    scene: &Scene,
    photons: u32,
    seed: u64,
    bar: &ProgressBar,
) -> Result<(CountMatrix, u64)> {
    let items = [RenderItem {
        assignment: scene.assignment.clone(),
        seed,
    }];
    let chunk = (photons / 100).max(256);
    let rendered = scatterfarm_search::chunks::render_in_chunks(
        engine,
        scene.geometry,
        &scene.table.physics(),
        &items,
        photons,
        chunk,
        &mut |n| bar.inc(u64::from(n)),
    )?;
    let counts = rendered
        .counts
        .into_iter()
        .next()
        .context("the engine returned no result")?;
    Ok((counts, rendered.scatter_events))
}

pub fn run(args: RenderArgs) -> Result<()> {
    ensure!(args.photons > 0, "--photons must be at least 1");
    let loaded = scene_source::load(&args.scene)?;
    let engine = args.engine.open()?;
    let fingerprint = engine.fingerprint();
    let geometry = loaded.scene.geometry;
    tracing::info!(scene = %loaded.origin, engine = %fingerprint, "rendering {} sources × {} photons", geometry.sources(), args.photons);

    let bar = ProgressBar::new(u64::from(args.photons));
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} rendering [{bar:40}] {pos}/{len} photons per source, {per_sec}, ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let (counts, _) = render_scene(
        engine.as_ref(),
        &loaded.scene,
        args.photons,
        args.seed,
        &bar,
    )?;
    bar.finish_and_clear();

    let launched = u64::from(args.photons) * geometry.sources() as u64;
    let exited = counts.total();
    let mut sidecar = Sidecar::for_render(&geometry, u64::from(args.photons));
    sidecar.seed = Some(args.seed);
    sidecar.engine = Some(fingerprint.key());
    sidecar.scene_sha256 = Some(loaded.sha256.clone());
    sidecar.scene = Some(loaded.origin.clone());
    sidecar.photons_exited = Some(exited);
    sidecar.photons_absorbed = Some(launched - exited);
    observation::write(
        &args.out,
        &observation::fractions(&counts, u64::from(args.photons)),
        &sidecar,
    )?;
    eprintln!(
        "wrote {} ({} × {} observations) and {}: {} of {} photons exited ({:.2} %), {} absorbed",
        args.out.display(),
        geometry.sources(),
        geometry.bins(),
        observation::sidecar_path(&args.out).display(),
        exited,
        launched,
        100.0 * exited as f64 / launched as f64,
        launched - exited
    );
    Ok(())
}
