//! What the integration tests share, one concern a module:
//!
//! - [`process`]: the `scatterfarm` command with a clean environment, short commands run to
//!   their end ([`process::Ran`]) and long-lived ones killed when dropped ([`process::Proc`]);
//! - [`scenes`]: the scene texts and job files the tests use;
//! - [`gating`]: tests that need something of the machine skip loudly, or fail under `CI=true`;
//! - [`net`]: free ports and files another process writes;
//! - [`tls`]: a CA and a server certificate made with rcgen;
//! - [`farm`]: a coordinator with its workers and data folder, and the client commands;
//! - [`reference`]: the farm's job reconstructed in one process, to compare against;
//! - [`rpc`]: gRPC clients speaking the protocol from the test, and fake workers' answers.

pub mod farm;
pub mod gating;
pub mod net;
pub mod process;
pub mod reference;
pub mod rpc;
pub mod scenes;
pub mod tls;
