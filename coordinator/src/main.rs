//! `scatterfarm`: render, draw and (in later versions) reconstruct scattering media.

use anyhow::Result;
use clap::{Parser, Subcommand};
use scatterfarm_coordinator::commands::{
    adapters, bench, describe, reconstruct, render, scenes, show,
};
use tracing_subscriber::EnvFilter;

/// Reconstructs what is inside a scattering medium from light measured at its boundary.
///
/// Logs go to stderr; set RUST_LOG (e.g. RUST_LOG=debug) for more.
#[derive(Debug, Parser)]
#[command(name = "scatterfarm", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
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
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Render(a) => render::run(a),
        Command::Show(a) => show::run(a),
        Command::Scenes(a) => scenes::run(a),
        Command::Reconstruct(a) => reconstruct::run(*a),
        Command::Describe(a) => describe::run(a),
        Command::Adapters(a) => adapters::run(a),
        Command::Bench(a) => bench::run(a),
    }
}
