//! One module per `scatterfarm` subcommand (the farm's client commands share [`jobs`]); each
//! exposes its clap arguments and a `run`.

pub mod adapters;
pub mod bench;
pub mod bench_fuzz;
pub mod bench_tallies;
pub mod connect;
pub mod coordinator;
pub mod demo;
pub mod describe;
pub mod jobs;
pub mod reconstruct;
pub mod render;
pub mod scenes;
pub mod show;
pub mod worker;
