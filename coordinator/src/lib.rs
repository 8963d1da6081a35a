//! The scatterfarm coordinator library: what the `scatterfarm` binary is built from.
//!
//! - [`scene_source`]: turns a command-line `SCENE` (a file or a built-in name) into a scene.
//! - [`observation`]: observation files (float32 NPY plus JSON sidecar), written atomically.
//! - [`picture`]: PNG drawings of material maps and observation matrices.
//! - [`engines`]: picking a render engine from `--engine`.
//! - [`commands`]: one module per subcommand.

pub mod commands;
pub mod engines;
pub mod observation;
pub mod picture;
pub mod scene_source;
