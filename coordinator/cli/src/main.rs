//! `scatterfarm`: render, draw and reconstruct scattering media, alone or as a farm.
//!
//! A thin binary: [`args`] holds flags shared by subcommands and maps them onto the
//! libraries' values; [`commands`] turns each subcommand's raw arguments into the libraries' values
//! and calls them; [`engines`] opens the engine `--engine` names. The work is done by the crates
//! it links: `scatterfarm-model`, `-engines`, `-search`, `-job`, `-coordinator` (the service),
//! `-worker` (the agent) and `-proto`.

mod args;
mod commands;
mod engines;

use crate::commands::{
    adapters, bench, coordinator, demo, describe, jobs, reconstruct, render, scenes, show, worker,
};
use anyhow::Result;
use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// Reconstructs what is inside a scattering medium from light measured at its boundary.
///
/// Logs go to stderr; set RUST_LOG (e.g. RUST_LOG=debug) for more.
#[derive(Debug, Parser)]
#[command(
    name = "scatterfarm",
    version,
    about = "Reconstructs what is inside a scattering medium from light measured at its boundary: alone, or as a render farm of a coordinator and GPU workers.",
    long_about = None
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Reconstruct a built-in scene with a coordinator and a worker in this process (start here).
    Demo(demo::DemoArgs),
    /// Render a scene's observation set (a P·K × P·K float32 NPY plus a JSON sidecar).
    Render(render::RenderArgs),
    /// Draw a scene's material map or an observation file as a PNG.
    Show(show::ShowArgs),
    /// List the built-in scenes, or print one as a scene file.
    Scenes(scenes::ScenesArgs),
    /// Reconstruct a medium's material map from a target observation set.
    Reconstruct(Box<reconstruct::ReconstructArgs>),
    /// Write the JSON sidecar of a captured observation matrix.
    Describe(describe::DescribeArgs),
    /// List the GPU adapters the GPU engine can use.
    Adapters(adapters::AdaptersArgs),
    /// Measure performance and write JSON.
    Bench(bench::BenchArgs),
    /// Serve the farm: workers lease render tasks, clients submit jobs.
    Coordinator(coordinator::CoordinatorArgs),
    /// Render tasks for a coordinator on this host's engine.
    Worker(worker::WorkerArgs),
    /// Submit a job file to a coordinator; prints the job id.
    Submit(jobs::SubmitArgs),
    /// Show a job's state and progress.
    Status(jobs::StatusArgs),
    /// Follow a job's progress until it ends.
    Watch(jobs::JobArgs),
    /// Fetch a job's outputs (its current best, marked partial, while it runs).
    Result(jobs::ResultArgs),
    /// Stop a job.
    Cancel(jobs::JobArgs),
    /// Remove a job and its results from the coordinator.
    Delete(jobs::JobArgs),
    /// List the coordinator's jobs.
    Jobs(jobs::ListArgs),
    /// List the workers registered with the coordinator.
    Workers(jobs::ListArgs),
}

impl Command {
    /// The log level where RUST_LOG names none: warnings only for a quiet reconstruction.
    fn default_log_level(&self) -> &'static str {
        match self {
            Command::Reconstruct(a) if a.quiet => "warn",
            _ => "info",
        }
    }
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let level = cli.command.default_log_level();
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(level)),
        )
        .with_writer(std::io::stderr)
        // Colours only on a terminal: logs sent to a file or a journal stay plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match cli.command {
        Command::Render(a) => render::run(a),
        Command::Show(a) => show::run(a),
        Command::Scenes(a) => scenes::run(a),
        Command::Reconstruct(a) => reconstruct::run(*a),
        Command::Describe(a) => describe::run(a),
        Command::Adapters(a) => adapters::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Coordinator(a) => coordinator::run(a),
        Command::Worker(a) => worker::run(a),
        Command::Submit(a) => jobs::run_submit(a),
        Command::Status(a) => jobs::run_status(a),
        Command::Watch(a) => jobs::run_watch(a),
        Command::Result(a) => jobs::run_result(a),
        Command::Cancel(a) => jobs::run_cancel(a),
        Command::Delete(a) => jobs::run_delete(a),
        Command::Jobs(a) => jobs::run_jobs(a),
        Command::Workers(a) => jobs::run_workers(a),
    }
}
