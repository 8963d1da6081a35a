//! Pinning a job to one engine fingerprint, so that every render of it comes from the same
//! engine (or to any engine, for a job that opted out).

use super::Job;
use crate::store::Store;
use anyhow::Result;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_search::refine::Screen;
use scatterfarm_search::steps::Steps;

/// The pinned fingerprint of a job that opted out of pinning.
pub const ANY_ENGINE: &str = "any";

/// What a submitted job is pinned to before any worker leases it: [`ANY_ENGINE`] when it opted
/// out, the fingerprint its spec names, or nothing yet.
pub(super) fn initial_pin(params: &JobSpec) -> Option<String> {
    if params.any_engine {
        Some(ANY_ENGINE.to_string())
    } else {
        params.engine_fingerprint.clone()
    }
}

impl Job {
    /// Pins the job to `fingerprint` (the first worker to lease its tasks) and stores it.
    pub fn pin(&mut self, fingerprint: &str, store: &dyn Store) -> Result<()> {
        self.checkpoint.pinned = Some(fingerprint.to_string());
        self.steps = Some(Steps::new(self.plan.search_geometry, fingerprint, []));
        self.persist(store)
    }

    /// Whether a worker of `fingerprint` may render this job (pinning it if not yet pinned).
    pub fn accepts(&self, fingerprint: &str) -> bool {
        match self.checkpoint.pinned.as_deref() {
            None | Some(ANY_ENGINE) => true,
            Some(p) => p == fingerprint,
        }
    }

    /// Whether the job's refinement screens by differential renders, which only engines that
    /// render differentially can serve (the whole job is pinned to one engine).
    pub fn needs_differential(&self) -> bool {
        self.plan
            .search
            .config()
            .refine
            .as_ref()
            .is_some_and(|r| r.screen == Screen::Differential)
    }

    /// The engine named in reports.
    pub(super) fn engine_label(&self) -> String {
        self.checkpoint
            .pinned
            .clone()
            .unwrap_or_else(|| "not pinned yet".into())
    }

    /// Whether every render comes from one engine, so the result is reproducible.
    pub(super) fn reproducible(&self) -> bool {
        self.checkpoint.pinned.as_deref() != Some(ANY_ENGINE)
    }
}
