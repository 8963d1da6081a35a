//! Running a reconstruction in one process: rendering a [`Plan`]'s target and calibration, and
//! driving the [`Search`] state machine against an [`Engine`].
//!
//! The renders of a search step are rendered as one batch (all candidates at once), each with
//! the photons its request names, in chunks of one iteration's photons, then scored. A request
//! whose render identity (assignment, seed, photons) was already scored takes the cached score
//! instead of a new render (common random numbers make these frequent), and a racing
//! contender's full render extends its first-stage render instead of starting again.

use crate::engines::{render_in_chunks, render_range};
use crate::plan::{Plan, SetupCounts};
use crate::prefixes::{Prefixes, DEFAULT_BYTES};
use crate::search::{Score, Search, Secondary};
use crate::similarity::{self, Metric, Target};
use anyhow::{Context, Result};
use scatterfarm_worker::{CountMatrix, Engine, Geometry, Material, RenderItem};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

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
    /// The tiebreak's metric, scored beside the primary one when the search has a tiebreak.
    pub secondary: Option<Metric>,
    /// ε of every photons-per-source budget the search renders with.
    pub epsilons: BTreeMap<u32, f64>,
    /// Whether scores carry their standard errors (racing needs them; they cost a pass).
    pub with_errors: bool,
    /// Photons per source per chunk of an in-process render (one iteration's).
    pub chunk: u32,
}

impl Scoring {
    /// ε of renders with `photons` per source.
    pub fn epsilon(&self, photons: u32) -> Result<f64> {
        self.epsilons
            .get(&photons)
            .copied()
            .with_context(|| format!("no ε was calibrated for {photons} photons per source"))
    }

    /// The score of a render of `photons` per source.
    pub fn score(&self, counts: &CountMatrix, photons: u32) -> Result<Score> {
        let epsilon = self.epsilon(photons)?;
        let n = u64::from(photons);
        let value = similarity::score(self.metric, &self.target, counts, n, epsilon)?;
        let std_error = if self.with_errors {
            similarity::std_error(self.metric, &self.target, counts, n, epsilon)?
        } else {
            0.0
        };
        let secondary = match self.secondary {
            Some(metric) => Some(Secondary {
                value: similarity::score(metric, &self.target, counts, n, epsilon)?,
                std_error: similarity::std_error(metric, &self.target, counts, n, epsilon)?,
            }),
            None => None,
        };
        Ok(Score {
            value,
            std_error,
            secondary,
        })
    }
}

/// What the search consumed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Consumption {
    /// Render requests the search made (each answered by a render or by the cache).
    #[serde(default)]
    pub requests: u64,
    /// Distinct renders the search needed: requests whose identity had not been rendered.
    pub renders: u64,
    /// Photons those renders needed, over all sources: a racing contender's full render
    /// counts only the photons beyond its first stage.
    pub photons: u64,
    pub scatter_events: u64,
    /// Photons rendered again because a first-stage prefix had been forgotten (all sources).
    #[serde(default)]
    pub recomputed: u64,
    /// Batches of requests that needed at least one render: `renders / batches` is how many
    /// renders can run at once, on average.
    #[serde(default)]
    pub batches: u64,
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
    for (photons, epsilon) in &scoring.epsilons {
        tracing::info!(
            "ε = {epsilon:.6} at {photons} photons per source ({}th percentile)",
            plan.percentile
        );
    }
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
    let sources = scoring.geometry.sources() as u64;
    let mut used = Consumption::default();
    // Scores by (assignment, seed, photons): within one search level, engine, geometry and the
    // material table's entries are fixed, so this is the render's identity. Seeds never repeat
    // across levels, so the caches are cleared at each new level.
    let mut cache: HashMap<(Vec<u16>, u64, u32), Score> = HashMap::new();
    // Photons per source already consumed of each stream (for racing's accounting).
    let mut consumed: HashMap<(Vec<u16>, u64), u32> = HashMap::new();
    let mut prefixes = Prefixes::new(DEFAULT_BYTES);
    let mut cache_level = search.progress().level;
    while !search.is_finished() {
        let level = search.progress().level;
        if level != cache_level {
            cache.clear();
            consumed.clear();
            prefixes.clear();
            cache_level = level;
        }
        let full = search.config().photons.level(level);
        // The missing renders, grouped by the photon range they need.
        let mut missing: BTreeMap<(u32, u32), Vec<RenderItem>> = BTreeMap::new();
        for r in search.pending() {
            if cache.contains_key(&(r.assignment.clone(), r.seed, r.photons)) {
                continue;
            }
            let key = (r.assignment.clone(), r.seed);
            let start = prefixes.get(&key, r.photons).map_or(0, |(p, _)| p);
            let items = missing.entry((start, r.photons)).or_default();
            if !items
                .iter()
                .any(|m| m.seed == r.seed && m.assignment == r.assignment)
            {
                items.push(RenderItem {
                    assignment: r.assignment.clone(),
                    seed: r.seed,
                });
            }
        }
        let table = search.materials();
        if !missing.is_empty() {
            used.batches += 1;
        }
        for ((start, photons), items) in missing {
            let n_items = items.len() as u64;
            let rendered = render_range(
                engine,
                scoring.geometry,
                &table,
                &items,
                start..photons,
                scoring.chunk,
                &mut |n| on_photons(u64::from(n) * n_items * sources),
            )?;
            used.scatter_events += rendered.scatter_events;
            for (item, mut counts) in items.into_iter().zip(rendered.counts) {
                let key = (item.assignment, item.seed);
                if let Some((_, prefix)) = prefixes.get(&key, photons) {
                    counts.add(prefix)?;
                }
                cache.insert(
                    (key.0.clone(), key.1, photons),
                    scoring.score(&counts, photons)?,
                );
                let before = consumed.get(&key).copied().unwrap_or(0).min(photons);
                used.recomputed += u64::from(before - before.min(start)) * sources;
                used.renders += 1;
                used.photons += u64::from(photons - before) * sources;
                consumed.insert(key.clone(), before.max(photons));
                if photons < full {
                    prefixes.keep(key, photons, counts);
                }
            }
        }
        let scores = search
            .pending()
            .iter()
            .map(|r| {
                cache
                    .get(&(r.assignment.clone(), r.seed, r.photons))
                    .copied()
                    .context("a request's score is missing")
            })
            .collect::<Result<Vec<Score>>>()?;
        used.requests += scores.len() as u64;
        search.submit_scores(&scores)?;
        on_step(search, &used);
    }
    Ok(used)
}
