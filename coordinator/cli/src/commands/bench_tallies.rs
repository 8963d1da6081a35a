//! `scatterfarm bench tallies`: what a differential render costs beside a plain one (issue 19:
//! "a render with per-region tallies costs ≤ 3× a plain render of the same photons").
//!
//! On a scene's own map at its grid (32 positions × 5 directions by default), the engine
//! (`--engine`: the CPU engine by default, or the GPU engine) renders the same photons four ways,
//! each timed on its own:
//!
//! - `plain`: `Engine::render`, the map alone;
//! - `tallies`: `Engine::render_differential` with no changes (the per-pixel tallies alone);
//! - `one_change`: with one single-pixel change;
//! - `sweep`: with every single-pixel change to every other table material (a refinement
//!   sweep's singles: `N² × (D − 1)` changes), then every estimate scored against a target
//!   (`model::likelihood::change_deviances`, timed apart as `scoring`).
//!
//! Ratios are of wall seconds measured in this one run. `direct_over_sweep` is what rendering
//! each estimated change on its own would cost (that many plain renders) over the sweep's
//! render and scoring.

use crate::engines::{self, EngineChoice};
use anyhow::{ensure, Context, Result};
use clap::Args;
use cpu_time::ProcessTime;
use scatterfarm_model::differential::{Change, PhotonChunks};
use scatterfarm_model::likelihood::{change_deviances, Target};
use scatterfarm_model::{Geometry, PhotonRange, RenderBatch, RenderItem};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct TalliesBenchArgs {
    /// The scene (a built-in name or a scene file) whose map is rendered.
    #[arg(long, default_value = "fig7a")]
    pub scene: String,
    /// Boundary positions (divisible by 4).
    #[arg(long, default_value_t = 32)]
    pub positions: u32,
    /// Directions per position.
    #[arg(long, default_value_t = 5)]
    pub directions: u32,
    /// Photons per source of every render.
    #[arg(long, default_value_t = 4096)]
    pub photons: u32,
    /// Photons per source per chunk of a differential render (a reconstruction's is
    /// `model::differential::CHUNK_PHOTONS`).
    #[arg(long, default_value_t = scatterfarm_model::differential::CHUNK_PHOTONS)]
    pub chunk: u32,
    /// Which engine renders (both render differentially).
    #[arg(long, value_enum, default_value_t = EngineChoice::Cpu)]
    pub engine: EngineChoice,
    /// The GPU adapter: an index or part of a name (see `scatterfarm adapters`).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// One timed render.
#[derive(Debug, Clone, Serialize)]
pub struct Timed {
    pub changes: usize,
    pub wall_seconds: f64,
    pub cpu_seconds: f64,
    /// Its wall seconds over the plain render's.
    pub over_plain: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct TalliesBench {
    pub engine: String,
    pub scene: String,
    pub grid: u32,
    pub sources: usize,
    pub bins: usize,
    pub photons_per_source: u32,
    pub chunk: u32,
    pub plain: Timed,
    pub tallies: Timed,
    pub one_change: Timed,
    pub sweep: Timed,
    /// Of the sweep's changes, those the render estimated (the rest need direct renders).
    pub sweep_estimated: usize,
    pub scoring_seconds: f64,
    /// `sweep_estimated` plain renders over the sweep's render and scoring.
    pub direct_over_sweep: f64,
}

/// Times `f` in wall and process CPU seconds.
fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(T, f64, f64)> {
    let cpu = ProcessTime::now();
    let wall = Instant::now();
    let out = f()?;
    Ok((
        out,
        wall.elapsed().as_secs_f64(),
        cpu.elapsed().as_secs_f64(),
    ))
}

pub fn run(args: TalliesBenchArgs) -> Result<()> {
    ensure!(args.photons > 0, "--photons must be at least 1");
    ensure!(args.chunk > 0, "--chunk must be at least 1");
    let loaded = scatterfarm_job::scene_source::load(&args.scene)?;
    let scene = loaded.scene;
    let geometry = Geometry::new(
        scene.geometry.size_mm,
        scene.geometry.grid,
        args.positions,
        args.directions,
    )
    .context("--positions and --directions")?;
    let table: Vec<_> = scene.table.materials.iter().map(|m| m.material).collect();
    let engine = engines::open(args.engine, args.adapter.as_deref())?;
    // Measured whether or not the engine offers differential renders to jobs (a CPU device
    // renders them but does not offer them); one that cannot render them says so.
    let item = RenderItem {
        assignment: scene.assignment.clone(),
        seed: 1,
    };
    let sweep: Vec<Change> = (0..geometry.pixels())
        .flat_map(|p| {
            let here = item.assignment[p];
            (0..table.len() as u16)
                .filter(move |&d| d != here)
                .map(move |d| Change {
                    pixels: vec![(p as u32, d)],
                })
        })
        .collect();
    let chunks = PhotonChunks {
        photons: args.photons,
        chunk: args.chunk,
    };
    let differential = |changes: &[Change]| {
        timed(|| {
            Ok(scatterfarm_model::differential::render_in_chunks(
                engine.as_ref(),
                geometry,
                &table,
                &item,
                chunks,
                changes,
                &mut |_| {},
            )?)
        })
    };
    let plain_render = |seed: u64| {
        let items = [RenderItem {
            assignment: item.assignment.clone(),
            seed,
        }];
        timed(|| {
            Ok(engine.render(&RenderBatch {
                geometry,
                table: &table,
                items: &items,
                photons: PhotonRange {
                    first: 0,
                    count: args.photons,
                },
            })?)
        })
    };
    // Warm-up (thread pool), then the target: the same map on another seed.
    differential(&sweep[..1])?;
    let (target_out, _, _) = plain_render(2)?;
    let target_counts = &target_out[0].counts;
    let photons = f64::from(args.photons);
    let target = Target {
        values: target_counts
            .counts
            .iter()
            .map(|&c| (f64::from(c) / photons) as f32)
            .collect(),
        photons_per_source: u64::from(args.photons),
    };
    eprintln!(
        "bench tallies: {} at grid {}, {} sources, {} photons per source, {} single-pixel changes",
        args.scene,
        geometry.grid,
        geometry.sources(),
        args.photons,
        sweep.len()
    );
    let (_, plain_wall, plain_cpu) = plain_render(1)?;
    let row = |changes: usize, wall: f64, cpu: f64| Timed {
        changes,
        wall_seconds: wall,
        cpu_seconds: cpu,
        over_plain: wall / plain_wall,
    };
    let plain = row(0, plain_wall, plain_cpu);
    let (_, w, c) = differential(&[])?;
    let tallies = row(0, w, c);
    let (_, w, c) = differential(&sweep[..1])?;
    let one_change = row(1, w, c);
    let (output, w, c) = differential(&sweep)?;
    let sweep_row = row(sweep.len(), w, c);
    let (scores, scoring_seconds, _) =
        timed(|| Ok(change_deviances(&target, &output, u64::from(args.photons))?))?;
    let estimated = scores.iter().filter(|s| s.is_some()).count();
    let bench = TalliesBench {
        engine: engine.fingerprint().key(),
        scene: args.scene.clone(),
        grid: geometry.grid,
        sources: geometry.sources(),
        bins: geometry.bins(),
        photons_per_source: args.photons,
        chunk: args.chunk,
        direct_over_sweep: estimated as f64 * plain_wall
            / (sweep_row.wall_seconds + scoring_seconds),
        plain,
        tallies,
        one_change,
        sweep: sweep_row,
        sweep_estimated: estimated,
        scoring_seconds,
    };
    eprintln!(
        "plain {:.2} s; tallies {:.2}×, one change {:.2}×, {} changes {:.2}× (+{:.2} s scoring, {} \
         estimated): {:.0}× cheaper than rendering them",
        bench.plain.wall_seconds,
        bench.tallies.over_plain,
        bench.one_change.over_plain,
        bench.sweep.changes,
        bench.sweep.over_plain,
        bench.scoring_seconds,
        bench.sweep_estimated,
        bench.direct_over_sweep
    );
    super::bench::emit(&serde_json::to_value(&bench)?, args.out.as_deref())
}
