//! A job's pace in this coordinator run: photons per second and the estimated time left.

use super::Job;

impl Job {
    /// Photons (all sources) per second and the estimated seconds left, from this run's pace.
    pub fn pace(&self) -> (f64, Option<f64>) {
        let elapsed = self.session_started.elapsed().as_secs_f64().max(1e-6);
        let photons_per_second = self.session_photons as f64 / elapsed;
        let p = self.checkpoint.search.progress();
        let done_here = p.renders_done.saturating_sub(self.session_renders_start);
        let eta = if !self.is_active() {
            Some(0.0)
        } else if done_here > 0 {
            Some(elapsed / done_here as f64 * p.renders_total.saturating_sub(p.renders_done) as f64)
        } else {
            None
        };
        (photons_per_second, eta)
    }
}
