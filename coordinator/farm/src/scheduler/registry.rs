//! The registry of workers: who registered with which engine and speed (then measured on the
//! pieces each returns). When each was last heard from is [`super::liveness`]'s.

use super::Scheduler;
use scatterfarm_model::EngineFingerprint;
use std::time::Instant;

/// A registered worker.
#[derive(Debug, Clone)]
pub struct WorkerEntry {
    pub id: String,
    pub name: String,
    pub fingerprint: EngineFingerprint,
    /// The fingerprint's canonical key ([`EngineFingerprint::key`]), as jobs are pinned to it.
    pub fingerprint_key: String,
    pub photons_per_second: f64,
    /// How long its results take to arrive beyond their render (upload, queueing), as
    /// measured on its results, and doubled (at least to the shortest lease) when a lease of
    /// it expires: a worker on a slow uplink gets leases it can meet.
    pub transfer_seconds: f64,
    pub tasks_completed: u64,
    /// Whether its engine renders differentially (it is leased differential renders).
    pub renders_differentially: bool,
    /// Whether it scores plain renders against a job's target (protocol 1.3 and later): it is
    /// leased scored renders.
    pub scores_renders: bool,
}

/// What a worker says it can do beyond plain renders.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Abilities {
    /// Its engine renders differentially.
    pub renders_differentially: bool,
    /// It scores plain renders against a job's target.
    pub scores_renders: bool,
}

impl Abilities {
    /// A worker of this build: it scores renders, and renders differentially if its engine does.
    pub fn of_this_build(renders_differentially: bool) -> Abilities {
        Abilities {
            renders_differentially,
            scores_renders: true,
        }
    }
}

/// The weight of a new measurement in a worker's speed (an exponential moving average).
const SPEED_WEIGHT: f64 = 0.5;

impl WorkerEntry {
    /// Folds a returned piece into the worker's speed: `photons` (all sources and assignments)
    /// rendered in `seconds`. Measurements under a millisecond are noise and ignored.
    pub fn measured(&mut self, photons: f64, seconds: f64) {
        if !(seconds.is_finite() && seconds >= 1e-3 && photons.is_finite() && photons > 0.0) {
            return;
        }
        let speed = photons / seconds;
        self.photons_per_second =
            (1.0 - SPEED_WEIGHT) * self.photons_per_second + SPEED_WEIGHT * speed;
    }

    /// Folds a result that arrived `round_trip` seconds after its lease, `render` of them
    /// rendering, into the worker's transfer time.
    pub fn measured_transfer(&mut self, round_trip: f64, render: f64) {
        let transfer = round_trip - render.max(0.0);
        if !(transfer.is_finite() && round_trip.is_finite()) {
            return;
        }
        self.transfer_seconds =
            (1.0 - SPEED_WEIGHT) * self.transfer_seconds + SPEED_WEIGHT * transfer.max(0.0);
    }

    /// A lease of the worker expired: the speed assumed for it halves, and its transfer time
    /// doubles, at least to `min_lease` seconds (a result that never came may be one that
    /// could not upload in time), so its next lease lasts longer either way.
    pub fn lease_expired(&mut self, min_lease: f64) {
        self.photons_per_second = (self.photons_per_second / 2.0).max(1.0);
        self.transfer_seconds = (2.0 * self.transfer_seconds).max(min_lease).min(86_400.0);
    }
}

impl Scheduler {
    /// Registers a worker; returns its id.
    pub fn register(
        &mut self,
        name: String,
        fingerprint: EngineFingerprint,
        photons_per_second: f64,
        abilities: Abilities,
    ) -> String {
        let id = format!("w{:08x}-{}", self.boot, self.next_worker);
        self.next_worker += 1;
        let key = fingerprint.key();
        tracing::info!(
            "worker {id} ({name}) registered: {key}, {:.2} M photons/s",
            photons_per_second / 1e6
        );
        self.workers.insert(
            id.clone(),
            WorkerEntry {
                id: id.clone(),
                name,
                fingerprint,
                fingerprint_key: key,
                photons_per_second: if photons_per_second.is_finite() && photons_per_second > 0.0 {
                    photons_per_second
                } else {
                    1e5
                },
                transfer_seconds: 0.0,
                tasks_completed: 0,
                renders_differentially: abilities.renders_differentially,
                scores_renders: abilities.scores_renders,
            },
        );
        self.liveness.add(&id, Instant::now());
        id
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry() -> WorkerEntry {
        WorkerEntry {
            id: "w1".into(),
            name: "one".into(),
            fingerprint: EngineFingerprint {
                engine: "cpu".into(),
                adapter: "cpu".into(),
                driver: "test".into(),
                version: "1".into(),
            },
            fingerprint_key: String::new(),
            photons_per_second: 1e6,
            transfer_seconds: 0.0,
            tasks_completed: 0,
            renders_differentially: false,
            scores_renders: true,
        }
    }

    #[test]
    fn transfer_time_follows_results_and_grows_with_each_expired_lease() {
        let mut w = entry();
        // A result 9 s after its lease, 1 s of it rendering: 8 s on the way, half-weighted.
        w.measured_transfer(9.0, 1.0);
        assert_eq!(w.transfer_seconds, 4.0);
        w.measured_transfer(9.0, 1.0);
        assert_eq!(w.transfer_seconds, 6.0);
        // A render reported longer than the round trip (clocks apart) counts as no transfer.
        w.measured_transfer(1.0, 3.0);
        assert_eq!(w.transfer_seconds, 3.0);
        w.measured_transfer(f64::NAN, 1.0);
        assert_eq!(w.transfer_seconds, 3.0);
        // Expired leases: the speed halves, the transfer allowance doubles, at least to the
        // shortest lease.
        let mut w = entry();
        w.lease_expired(30.0);
        assert_eq!((w.photons_per_second, w.transfer_seconds), (5e5, 30.0));
        w.lease_expired(30.0);
        assert_eq!((w.photons_per_second, w.transfer_seconds), (2.5e5, 60.0));
    }
}
