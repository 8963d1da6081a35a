//! Command-line arguments shared by several subcommands, and their mapping onto the libraries'
//! validated values.
//!
//! - [`job`]: `reconstruct`'s job flags, mapped onto a job spec.
//! - [`choice`]: flags that choose a library value by name.

pub mod choice;
pub mod job;
