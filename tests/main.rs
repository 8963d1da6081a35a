//! The one integration-test binary: the `scatterfarm` command as a user and a farm run it, in
//! real processes on real files. Every module shares [`harness`]: the launcher, the scene texts
//! and job files, process guards with logs, ports, TLS certificates and the rules for tests that
//! need something of the machine (root, iproute2, Chromium, a GPU) and fail under `CI=true`.
//!
//! - [`cli`]: render, show, scenes, help and the quality bench;
//! - [`reconstruct`]: `scatterfarm reconstruct` end to end with the CPU engine;
//! - [`farm`]: coordinator, workers and clients across processes, and fake workers;
//! - [`faults`]: several jobs at once, cancel and delete in flight, SIGTERM, two coordinators
//!   on one data folder, results past their lease (one over a slowed link in a network
//!   namespace);
//! - [`status_page`]: the coordinator's status page in headless Chromium;
//! - [`deploy`]: `deploy/local-cluster.sh` in network namespaces.

mod harness;

mod cli;
mod deploy;
mod farm;
mod faults;
mod reconstruct;
mod status_page;
