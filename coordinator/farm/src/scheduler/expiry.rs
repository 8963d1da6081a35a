//! Expiry: leases past their deadline, or held by workers that stopped sending heartbeats, are
//! handed out again (see [`giveback`](super::giveback)), and those workers forgotten.

use super::giveback::Returned;
use super::Scheduler;
use std::time::Instant;

impl Scheduler {
    /// Hands out again the leases past their deadline or of workers that stopped sending
    /// heartbeats, and forgets those workers; restores the paused jobs that waited enough.
    pub fn sweep(&mut self, now: Instant) {
        self.restore_paused(now);
        let silent_after = self.settings.heartbeat * self.settings.missed_heartbeats;
        let mut gone = self.liveness.forget_silent(now, silent_after);
        // A worker the registry holds but liveness does not cannot be heard from again.
        gone.extend(
            self.workers
                .keys()
                .filter(|id| self.liveness.last_seen(id).is_none() && !gone.contains(id))
                .cloned()
                .collect::<Vec<_>>(),
        );
        for id in &gone {
            tracing::warn!(
                "worker {id} missed {} heartbeats: forgotten",
                self.settings.missed_heartbeats
            );
            self.workers.remove(id);
        }
        let expired: Vec<u64> = self
            .leases
            .iter()
            .filter(|(_, l)| now > l.deadline || !self.workers.contains_key(&l.worker))
            .map(|(&t, _)| t)
            .collect();
        for t in expired {
            if let Some(l) = self.leases.remove(&t) {
                tracing::warn!(
                    "task {t} attempt {} of job {} (worker {}) expired: leasing it again",
                    l.piece.attempt,
                    l.job,
                    l.worker
                );
                self.counters.leases_expired += 1;
                let detail = if self.workers.contains_key(&l.worker) {
                    format!("worker {} did not return it in time", l.worker)
                } else {
                    format!("worker {} stopped sending heartbeats", l.worker)
                };
                self.piece_returned(l, Returned::Expired, &detail);
            }
        }
    }
}
