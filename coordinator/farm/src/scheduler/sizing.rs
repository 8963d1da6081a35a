//! Lease sizing: a piece holds about [`Settings::task_seconds`] of the leasing worker's work, and
//! its lease lasts the longer of [`Settings::min_lease`] and five times the expected render time.

use super::Settings;
use crate::work::{Piece, RenderGroup};
use std::time::Duration;

/// Photons one photon index of `group`'s pieces launches, as [`max_photons`] sizes them:
/// sources × assignments (a group cut by renders: sources; at least 1).
pub(super) fn photons_per_launch(group: &RenderGroup) -> f64 {
    let renders = if group.is_cut_by_renders() {
        1
    } else {
        group.items.len()
    };
    (group.geometry.sources() * renders).max(1) as f64
}

/// Photons one photon index of `piece` of `group` launches: sources × the piece's renders.
pub(crate) fn piece_photons_per_launch(group: &RenderGroup, piece: &Piece) -> f64 {
    (group.geometry.sources() * piece.items_count as usize).max(1) as f64
}

/// The most photons per source a piece for a worker of `photons_per_second` holds.
pub(super) fn max_photons(settings: &Settings, photons_per_second: f64, per_photon: f64) -> u32 {
    (settings.task_seconds * photons_per_second / per_photon).clamp(1.0, f64::from(u32::MAX)) as u32
}

/// How long a lease of `count` photons per source lasts.
pub(super) fn lease_duration(
    settings: &Settings,
    count: u32,
    photons_per_second: f64,
    per_photon: f64,
) -> Duration {
    let expected = count as f64 * per_photon / photons_per_second;
    settings
        .min_lease
        .max(Duration::from_secs_f64((expected * 5.0).min(86_400.0)))
}
