//! One module per `scatterfarm` subcommand; each exposes its clap arguments and a `run`.

pub mod adapters;
pub mod bench;
pub mod connect;
pub mod describe;
pub mod reconstruct;
pub mod render;
pub mod scenes;
pub mod show;
