//! Rendering a plan's setup renders (target, calibration) in one process with any engine.

use crate::plan::{Plan, SetupCounts};
use anyhow::Result;
use scatterfarm_model::Engine;
use scatterfarm_search::driver::render_one;
use scatterfarm_search::Scoring;

/// Renders a plan's setup renders with `engine` and returns what the search scores against.
pub fn prepare(plan: &Plan, engine: &dyn Engine) -> Result<Scoring> {
    let mut counts = SetupCounts::default();
    for r in plan.setup_renders()? {
        tracing::info!(
            "rendering {:?}: {} sources × {} photons",
            r.kind,
            r.geometry.sources(),
            r.photons
        );
        let c = render_one(
            engine,
            r.geometry,
            &r.table,
            r.item.assignment.clone(),
            r.item.seed,
            r.photons,
        )?;
        counts.set(r.kind, c);
    }
    let scoring = plan.finish_setup(&counts)?;
    for (photons, epsilon) in &scoring.epsilons {
        tracing::info!(
            "ε = {epsilon:.6} at {photons} photons per source ({}th percentile)",
            plan.percentile
        );
    }
    Ok(scoring)
}
