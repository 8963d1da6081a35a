//! `scatterfarm scenes [show NAME]`: list the built-in scenes, or print one as a scene file.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use scatterfarm_model::builtin;

#[derive(Debug, Args)]
pub struct ScenesArgs {
    #[command(subcommand)]
    pub action: Option<ScenesAction>,
}

#[derive(Debug, Subcommand)]
pub enum ScenesAction {
    /// Print a built-in scene as TOML (a starting point for your own scene files).
    Show {
        /// The built-in scene's name (see `scatterfarm scenes`).
        name: String,
    },
}

pub fn run(args: ScenesArgs) -> Result<()> {
    match args.action {
        None => {
            for info in builtin::list() {
                println!("{:<12} {}", info.name, info.description);
            }
            Ok(())
        }
        Some(ScenesAction::Show { name }) => match builtin::toml(&name) {
            Some(text) => {
                print!("{text}");
                Ok(())
            }
            None => {
                let names: Vec<&str> = builtin::list().iter().map(|b| b.name).collect();
                bail!(
                    "unknown built-in scene {name:?} (built-in: {})",
                    names.join(", ")
                )
            }
        },
    }
}
