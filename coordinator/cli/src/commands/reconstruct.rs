//! `scatterfarm reconstruct`: find the material map whose simulation matches a target, and write
//! the report, material map and pictures.
//!
//! Without `--data` it runs in this process against one engine. With `--data DIR` it runs the
//! farm's embedded path (a coordinator and a worker in this process, over gRPC on loopback) and
//! keeps its state in DIR, so an interrupted run resumes where it stood.

use crate::args::job::JobArgs;
use crate::engines::EngineArgs;
use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::outcome::{self, Summary};
use scatterfarm_job::plan::Plan;
use scatterfarm_job::report::Report;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_model::Engine;
use scatterfarm_search::driver::{self, Consumption};
use scatterfarm_search::Search;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Clone, Args)]
pub struct ReconstructArgs {
    #[command(flatten)]
    pub job: JobArgs,
    #[command(flatten)]
    pub engine: EngineArgs,
    /// The output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Keep the reconstruction's state in this folder (a coordinator data folder) and resume
    /// from it after an interruption.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// No progress bar and no progress logs: warnings and errors only (for scripts and
    /// benchmarks; RUST_LOG still chooses the logs where it is set).
    #[arg(long)]
    pub quiet: bool,
}

/// Reconstructs in this process with `engine` and writes the outputs into `out`.
pub fn run_in_process(
    params: &JobSpec,
    engine: &dyn Engine,
    out: &Path,
    quiet: bool,
) -> Result<Report> {
    Ok(run_checked(params, engine, out, quiet, None)?.0)
}

/// [`run_in_process`], then (with `check_photons`) the truth against the map found on fresh
/// photons (`scatterfarm_job::truth_check`): information or search.
pub fn run_checked(
    params: &JobSpec,
    engine: &dyn Engine,
    out: &Path,
    quiet: bool,
    check_photons: Option<u32>,
) -> Result<(Report, Option<scatterfarm_job::truth_check::TruthCheck>)> {
    let inputs = Inputs::gather(params, Path::new("."))?;
    let plan = Plan::resolve(params, &inputs)?;
    let scoring = scatterfarm_job::setup::prepare(&plan, engine)?;
    let mut search = plan.search.clone();
    let started = Instant::now();
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(search.progress().renders_total)
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} renders, ETA {eta} · {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    // Each level's and sweep's end is logged (a long run's progress in a log, as the
    // convergence curve will have it).
    let mut stages = 0usize;
    let grid = plan.config.grid as usize;
    let mut on_step = |s: &Search, used: &Consumption| {
        let ended = scatterfarm_search::convergence::stages_ended(s);
        if ended > stages {
            let curve = scatterfarm_search::convergence::curve(s);
            let levels = s.levels().len();
            for (i, p) in curve.iter().enumerate().skip(stages) {
                let stage = match p.stage {
                    scatterfarm_search::convergence::Stage::Level(l) => format!("level {l}"),
                    scatterfarm_search::convergence::Stage::Sweep(n) => {
                        // What kind of sweep it was, where it was not a plain one.
                        let record = s
                            .refinement()
                            .and_then(|r| r.history().get(i.saturating_sub(levels)));
                        let kind = match record {
                            Some(h) if h.trial_kept == Some(true) => {
                                " (a growth trial's end: its map kept)".to_string()
                            }
                            Some(h) if h.trial_kept == Some(false) => {
                                " (a growth trial's end: its map given back)".to_string()
                            }
                            Some(h) if h.growth => match h.grown_z {
                                Some(z) => format!(
                                    " (a growth round: no grown map won, the best at z {z:.1})"
                                ),
                                None => " (a growth round)".to_string(),
                            },
                            Some(h) if h.simplification => " (a simplification round)".to_string(),
                            _ => String::new(),
                        };
                        format!("sweep {n}{kind}")
                    }
                };
                let accuracy = plan
                    .truth
                    .as_ref()
                    .filter(|_| p.map.len() == grid * grid)
                    .map(|t| {
                        let a = outcome::pixel_accuracy(&p.map, grid, s.table(), t);
                        format!(", pixel accuracy {:.1} %", a * 100.0)
                    })
                    .unwrap_or_default();
                bar.suspend(|| {
                    tracing::info!(
                        "{stage} ended: score {:.4}{accuracy}; {} renders, {:.3} G photons so far",
                        p.score,
                        used.renders,
                        used.photons as f64 / 1e9
                    )
                });
            }
            stages = ended;
        }
        let pr = s.progress();
        bar.set_length(pr.renders_total);
        bar.set_position(pr.renders_done);
        let rate = used.photons as f64 / started.elapsed().as_secs_f64().max(1e-9);
        bar.set_message(format!(
            "{} · best {:.4} · {:.2} M photons/s",
            pr.stage(),
            pr.best_score.unwrap_or(f64::NAN),
            rate / 1e6
        ));
    };
    let (used, simulated) =
        driver::drive(&mut search, engine, &scoring, &mut on_step, &mut |_| {})?;
    bar.finish_and_clear();
    let result = search
        .result()
        .context("the search ended without a result")?
        .clone();
    let report = outcome::write_outputs(
        out,
        &Summary {
            config: &plan.config,
            truth: plan.truth.as_ref(),
            search: &search,
            assignment: &result.assignment,
            similarity: result.score,
            epsilons: &scoring.epsilons,
            used,
            photons_simulated: simulated + plan.setup_photons()?,
            wall_seconds: started.elapsed().as_secs_f64(),
            engine: engine.fingerprint().key(),
            reproducible: true,
        },
    )?;
    let check = match check_photons {
        Some(photons) => scatterfarm_job::truth_check::check(
            &plan,
            &scoring,
            engine,
            &result.assignment,
            photons,
        )?,
        None => None,
    };
    Ok((report, check))
}

pub fn run(args: ReconstructArgs) -> Result<()> {
    let spec = args.job.into_spec();
    let report = match &args.data {
        None => {
            // Every check that needs no engine runs before the adapter starts.
            let inputs = Inputs::gather(&spec, Path::new("."))?;
            let plan = Plan::resolve(&spec, &inputs)?;
            let engine = args.engine.open_for(&plan)?;
            run_in_process(&spec, engine.as_ref(), &args.out, args.quiet)?
        }
        Some(data) => crate::commands::demo::run_embedded(
            &spec,
            &args.engine,
            data,
            &args.out,
            args.quiet,
            None,
        )?,
    };
    let accuracy = report
        .pixel_accuracy
        .map(|a| format!(", pixel accuracy {:.1} %", a * 100.0))
        .unwrap_or_default();
    eprintln!(
        "similarity {:.4}{accuracy}; {} renders in {:.1} s; wrote report.json, materials.npy, materials.json, reconstruction.png, maps.png and convergence.png to {}",
        report.similarity,
        report.renders,
        report.wall_seconds,
        args.out.display()
    );
    Ok(())
}
