//! Running a reconstruction in one process: rendering a [`Plan`]'s target and calibration, and
//! driving the [`Search`] state machine against an [`Engine`].
//!
//! The renders of a search step are rendered as one batch (all candidates at once) over the
//! search's photon budget, in chunks of one iteration's photons, then scored. A request whose
//! render identity was already scored (the same assignment and seed: common random numbers make
//! these frequent) takes the cached score instead of a new render.

use crate::engines::render_in_chunks;
use crate::plan::{Plan, SetupCounts};
use crate::search::Search;
use crate::similarity::{self, Metric, Target};
use anyhow::{Context, Result};
use scatterfarm_worker::{CountMatrix, Engine, Geometry, Material, RenderItem};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// The photon budget of a search (`model.md`, "Budget").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Budget {
    pub iterations: u32,
    pub photons_per_iteration: u32,
}

impl Budget {
    /// Photons per source of every search render.
    pub fn photons_per_source(&self) -> Result<u32> {
        self.iterations
            .checked_mul(self.photons_per_iteration)
            .filter(|&p| p > 0)
            .context("iterations × photons per iteration must be between 1 and 2³²−1")
    }
}

/// What the search scores against.
#[derive(Debug, Clone)]
pub struct Scoring {
    /// The search's geometry: the target's boundary sampling at the search grid.
    pub geometry: Geometry,
    pub target: Target,
    pub metric: Metric,
    pub epsilon: f64,
    pub budget: Budget,
}

/// What the search consumed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Consumption {
    /// Render requests the search made (each answered by a render or by the cache).
    #[serde(default)]
    pub requests: u64,
    /// Distinct renders the search needed: requests whose identity had not been rendered.
    pub renders: u64,
    /// Photons launched by those renders, over all sources.
    pub photons: u64,
    pub scatter_events: u64,
}

/// Renders one homogeneous or heterogeneous assignment in full and returns its counts.
pub fn render_one(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    assignment: Vec<u16>,
    seed: u64,
    photons: u32,
) -> Result<CountMatrix> {
    let items = [RenderItem { assignment, seed }];
    let chunk = photons.clamp(1, 65_536);
    let rendered = render_in_chunks(engine, geometry, table, &items, photons, chunk, &mut |_| {})?;
    rendered
        .counts
        .into_iter()
        .next()
        .context("the engine returned no result")
}

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
    tracing::info!(
        "ε = {:.6} ({}th percentile)",
        scoring.epsilon,
        plan.percentile
    );
    Ok(scoring)
}

/// Runs the search to its end, calling `on_step` after every scored step and `on_photons`
/// as photons are rendered (photons per source × items).
pub fn drive(
    search: &mut Search,
    engine: &dyn Engine,
    scoring: &Scoring,
    on_step: &mut dyn FnMut(&Search, &Consumption),
    on_photons: &mut dyn FnMut(u64),
) -> Result<Consumption> {
    let photons = scoring.budget.photons_per_source()?;
    let sources = scoring.geometry.sources() as u64;
    let mut used = Consumption::default();
    // Scores by (assignment, seed): within one search, engine, geometry, photons and the
    // material table's entries are fixed, so this is the render's identity. Seeds never repeat
    // across levels, so the cache is cleared at each new level.
    let mut cache: HashMap<(Vec<u16>, u64), f64> = HashMap::new();
    let mut cache_level = search.progress().level;
    while !search.is_finished() {
        let level = search.progress().level;
        if level != cache_level {
            cache.clear();
            cache_level = level;
        }
        let mut missing: Vec<RenderItem> = Vec::new();
        for r in search.pending() {
            let key = (r.assignment.clone(), r.seed);
            if !cache.contains_key(&key)
                && !missing
                    .iter()
                    .any(|m| m.seed == r.seed && m.assignment == r.assignment)
            {
                missing.push(RenderItem {
                    assignment: r.assignment.clone(),
                    seed: r.seed,
                });
            }
        }
        if !missing.is_empty() {
            let table = search.materials();
            let n_items = missing.len() as u64;
            let rendered = render_in_chunks(
                engine,
                scoring.geometry,
                &table,
                &missing,
                photons,
                scoring.budget.photons_per_iteration.max(1),
                &mut |n| on_photons(u64::from(n) * n_items * sources),
            )?;
            for (item, c) in missing.into_iter().zip(&rendered.counts) {
                let s = similarity::score(
                    scoring.metric,
                    &scoring.target,
                    c,
                    u64::from(photons),
                    scoring.epsilon,
                )?;
                cache.insert((item.assignment, item.seed), s);
            }
            used.renders += n_items;
            used.photons += n_items * sources * u64::from(photons);
            used.scatter_events += rendered.scatter_events;
        }
        let scores = search
            .pending()
            .iter()
            .map(|r| {
                cache
                    .get(&(r.assignment.clone(), r.seed))
                    .copied()
                    .context("a request's score is missing")
            })
            .collect::<Result<Vec<f64>>>()?;
        used.requests += scores.len() as u64;
        search.submit(&scores)?;
        on_step(search, &used);
    }
    Ok(used)
}
