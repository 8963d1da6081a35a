//! Lease sizing: a piece holds about [`Settings::task_seconds`] of the leasing worker's work, and
//! its lease lasts the longer of [`Settings::min_lease`] and five times the expected render time,
//! plus twice the time the worker's results take beyond their render (its uplink:
//! [`super::registry::WorkerEntry::transfer_seconds`]).

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

/// The longest lease.
const MAX_LEASE_SECONDS: f64 = 86_400.0;

/// How long a lease of `count` photons per source lasts, for a worker of `photons_per_second`
/// whose results take `transfer_seconds` beyond their render to arrive.
pub(super) fn lease_duration(
    settings: &Settings,
    count: u32,
    photons_per_second: f64,
    per_photon: f64,
    transfer_seconds: f64,
) -> Duration {
    let expected = count as f64 * per_photon / photons_per_second;
    let render = settings
        .min_lease
        .as_secs_f64()
        .max((expected * 5.0).min(MAX_LEASE_SECONDS));
    let transfer = if transfer_seconds.is_finite() {
        2.0 * transfer_seconds.max(0.0)
    } else {
        0.0
    };
    Duration::from_secs_f64((render + transfer).min(MAX_LEASE_SECONDS))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lease_covers_five_renders_and_two_uploads_within_a_day() {
        let settings = Settings {
            min_lease: Duration::from_secs(30),
            ..Settings::default()
        };
        let secs = |count, speed, transfer| {
            lease_duration(&settings, count, speed, 10.0, transfer).as_secs_f64()
        };
        // 1 000 × 10 photons at 100 per second: 100 s of render, leased for 500 s.
        assert_eq!(secs(1_000, 100.0, 0.0), 500.0);
        // A short render gets the shortest lease, plus twice the upload.
        assert_eq!(secs(1, 100.0, 0.0), 30.0);
        assert_eq!(secs(1, 100.0, 7.5), 45.0);
        assert_eq!(secs(1_000, 100.0, 50.0), 600.0);
        // Nonsense measurements add nothing; nothing lasts beyond a day.
        assert_eq!(secs(1, 100.0, -3.0), 30.0);
        assert_eq!(secs(1, 100.0, f64::NAN), 30.0);
        assert_eq!(secs(u32::MAX, 1.0, 1e9), MAX_LEASE_SECONDS);
    }
}
