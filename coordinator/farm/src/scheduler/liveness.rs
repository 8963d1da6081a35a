//! When each registered worker was last heard from, behind its own small lock: a heartbeat
//! touches it without the scheduler's lock, so it never waits behind result handling,
//! checkpoints or scoring, and a busy coordinator does not forget workers that are alive.
//!
//! The registry ([`super::registry`]) adds a worker here when it registers; the sweep
//! ([`super::expiry`]) reads and forgets. Holding the lock is a hash-map operation, never more.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Instant;

/// Last contact per worker id.
#[derive(Debug, Default)]
pub struct Liveness {
    seen: Mutex<HashMap<String, Instant>>,
}

impl Liveness {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, Instant>> {
        // A panic while holding this lock cannot leave the map half changed.
        self.seen.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A worker just registered.
    pub fn add(&self, worker: &str, now: Instant) {
        self.map().insert(worker.to_owned(), now);
    }

    /// Contact from `worker` (a heartbeat, a lease or a result); false if it is not known (it
    /// was forgotten and must register again).
    pub fn touch(&self, worker: &str, now: Instant) -> bool {
        match self.map().get_mut(worker) {
            Some(t) => {
                *t = now.max(*t);
                true
            }
            None => false,
        }
    }

    /// When `worker` was last heard from.
    pub fn last_seen(&self, worker: &str) -> Option<Instant> {
        self.map().get(worker).copied()
    }

    /// The workers silent for longer than `silent_after` at `now`, removed.
    pub fn forget_silent(&self, now: Instant, silent_after: std::time::Duration) -> Vec<String> {
        let mut map = self.map();
        let gone: Vec<String> = map
            .iter()
            .filter(|(_, &t)| now.saturating_duration_since(t) > silent_after)
            .map(|(id, _)| id.clone())
            .collect();
        for id in &gone {
            map.remove(id);
        }
        gone
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn only_known_workers_are_touched_and_silent_ones_are_forgotten() {
        let live = Liveness::default();
        let t0 = Instant::now();
        assert!(!live.touch("w1", t0), "an unknown worker must register");
        live.add("w1", t0);
        live.add("w2", t0);
        assert!(live.touch("w2", t0 + Duration::from_secs(5)));
        let gone = live.forget_silent(t0 + Duration::from_secs(7), Duration::from_secs(6));
        assert_eq!(gone, vec!["w1".to_string()]);
        assert!(!live.touch("w1", t0 + Duration::from_secs(8)));
        assert_eq!(live.last_seen("w2"), Some(t0 + Duration::from_secs(5)));
    }

    #[test]
    fn a_late_touch_never_moves_the_time_back() {
        let live = Liveness::default();
        let t0 = Instant::now();
        live.add("w", t0 + Duration::from_secs(3));
        assert!(live.touch("w", t0));
        assert_eq!(live.last_seen("w"), Some(t0 + Duration::from_secs(3)));
    }
}
