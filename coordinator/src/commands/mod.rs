//! One module per `scatterfarm` subcommand; each exposes its clap arguments and a `run`.

pub mod bench;
pub mod render;
pub mod scenes;
pub mod show;
