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
                tasks_completed: 0,
                renders_differentially: abilities.renders_differentially,
                scores_renders: abilities.scores_renders,
            },
        );
        self.liveness.add(&id, Instant::now());
        id
    }
}
