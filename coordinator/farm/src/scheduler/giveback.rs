//! Pieces that come back without a result (their lease expired, their worker gave them back, or
//! their result was refused as malformed): each is leased again with the next attempt number,
//! up to [`Settings::max_attempts`](super::Settings::max_attempts); then the job fails with a
//! reason naming the piece, so a poison or impossible task cannot loop for ever.
//!
//! A lease that expires also halves the speed the coordinator assumes for its worker, so the
//! next lease of the same photons lasts twice as long: a medium far more expensive than the
//! worker's registration benchmark gets leases it can meet after a few attempts. It doubles
//! the worker's transfer allowance too (at least to the shortest lease), for a worker whose
//! renders are quick but whose results crawl up a slow link.

use super::{Lease, Scheduler};
use crate::work::Purpose;
use scatterfarm_job::plan::SetupKind;

/// Why a piece came back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Returned {
    Expired,
    GivenBack,
    Refused,
}

impl Returned {
    fn as_str(self) -> &'static str {
        match self {
            Returned::Expired => "its lease expired",
            Returned::GivenBack => "its worker gave it back",
            Returned::Refused => "its result was refused",
        }
    }
}

impl Scheduler {
    /// Hands `lease`'s piece back to its group, or fails its job when the piece has had its
    /// last attempt. `detail` says what happened, for the job's failure message.
    pub(super) fn piece_returned(&mut self, lease: Lease, why: Returned, detail: &str) {
        if why == Returned::Expired {
            let min_lease = self.settings.min_lease.as_secs_f64();
            if let Some(w) = self.workers.get_mut(&lease.worker) {
                w.lease_expired(min_lease);
            }
        }
        let max = self.settings.max_attempts;
        let store = self.store.clone();
        let Some(job) = self.jobs.get_mut(&lease.job) else {
            return;
        };
        let Some(group) = job.groups.iter_mut().find(|g| g.id == lease.group) else {
            return;
        };
        let p = lease.piece;
        if p.attempt < max {
            group.give_back(p);
            return;
        }
        let what = match group.purpose {
            Purpose::Search => "search".to_string(),
            Purpose::Setup(SetupKind::Target) => "target".to_string(),
            Purpose::Setup(SetupKind::CalibrationTarget) => "calibration target".to_string(),
            Purpose::Setup(SetupKind::CalibrationSearch { photons }) => {
                format!("calibration ({photons} photons)")
            }
        };
        let message = format!(
            "task {} (photons {}..{} per source of a {what} render of {} assignment(s)) was \
             leased {} times without a result; the last time {} ({detail}). Raise \
             --max-attempts, or look at the workers' logs for why it does not finish",
            p.task_id,
            p.first,
            u64::from(p.first) + u64::from(p.count),
            group.items.len(),
            p.attempt,
            why.as_str(),
        );
        let id = job.id.clone();
        if let Err(e) = job.fail(message, store.as_ref()) {
            job.pause(&e);
        }
        self.leases.retain(|_, l| l.job != id);
    }
}
