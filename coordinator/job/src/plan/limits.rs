//! Cost limits, checked when a job is resolved (by `reconstruct` and by the coordinator's
//! submit, before anything is rendered or stored). Each refusal names what is too large, by how
//! much, and the limit:
//!
//! - **sources**: a render's counts are `sources × bins` u32s, and a worker returns the counts
//!   of every render of a task in one message (at most `MAX_MESSAGE_BYTES`, 1 GiB). At
//!   [`MAX_SOURCES`] one render's counts are 16 MiB, so a result of 64 renders still fits;
//! - **optical thickness**: a photon in a medium of optical thickness τ = σt · size scatters
//!   about τ² times before it leaves (diffusion), so a render's cost grows with τ²; materials
//!   past [`MAX_OPTICAL_THICKNESS`] would make renders that never finish in practice.
//!
//! The photon budget of a job on the farm is the coordinator's (`--max-job-photons`).

use anyhow::{ensure, Result};
use scatterfarm_model::{Geometry, MaterialTable};

/// The most sources (positions × directions) a job may have.
pub const MAX_SOURCES: usize = 2048;

/// The most optical thickness (σs + σa) · size a non-opaque material may have.
pub const MAX_OPTICAL_THICKNESS: f64 = 1000.0;

/// Refuses geometries whose results cannot be carried.
pub fn check_sources(what: &str, geometry: &Geometry) -> Result<()> {
    let sources = geometry.sources();
    let mib = (sources * geometry.bins() * 4) as f64 / f64::from(1u32 << 20);
    ensure!(
        sources <= MAX_SOURCES,
        "{what}: positions × directions = {} × {} = {sources} sources; one render's counts \
         would be {mib:.0} MiB, and a job may have at most {MAX_SOURCES} sources (16 MiB per \
         render, so a task's result of up to 64 renders fits in one message)",
        geometry.positions,
        geometry.directions
    );
    Ok(())
}

/// Refuses materials whose renders would not finish.
pub fn check_thickness(what: &str, table: &MaterialTable, size_mm: f64) -> Result<()> {
    for m in &table.materials {
        if m.material.is_opaque() {
            continue;
        }
        let tau = m.material.sigma_t() * size_mm;
        ensure!(
            tau <= MAX_OPTICAL_THICKNESS,
            "{what}: material {:?} (sigma_s {}, sigma_a {}) is {tau:.0} mean free paths thick \
             across the {size_mm} mm medium; the limit is {MAX_OPTICAL_THICKNESS:.0} (a photon \
             scatters about τ² times before it leaves, so renders past it do not finish): lower \
             sigma_s or the size, or make it opaque",
            m.name,
            m.material.sigma_s,
            m.material.sigma_a
        );
    }
    Ok(())
}
