//! Driving the [`Search`] state machine against an [`Engine`] in one process, and what a search
//! scores against ([`Scoring`]) and consumes ([`Consumption`]).
//!
//! The renders of a search step are rendered as one batch (all candidates at once), each with
//! the photons its request names, in chunks of one iteration's photons, then scored. A request
//! whose render identity (assignment, seed, photons) was already scored takes the cached score
//! instead of a new render (common random numbers make these frequent), and a racing
//! contender's full render extends its first-stage render instead of starting again.

use crate::chunks::{render_in_chunks, render_range};
use crate::likelihood;
use crate::machine::{ChangeScore, Score, Search, Secondary};
use crate::similarity::{self, Metric, Target};
use crate::steps::{Next, Steps};
use anyhow::{Context, Result};
use scatterfarm_model::{CountMatrix, DifferentialOutput, Engine, Geometry, Material, RenderItem};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The photon budget of a search (`docs/model.md`, "Budget").
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
    /// Whether renders are scored by the likelihood alone (metric deviance, no tiebreak): a
    /// score then depends on the render's counts and the target only, so it can be made where
    /// the counts are ([`Score::of_deviance`]).
    pub fn is_likelihood(&self) -> bool {
        self.metric == Metric::Deviance && self.secondary.is_none()
    }

    /// ε of renders with `photons` per source.
    pub fn epsilon(&self, photons: u32) -> Result<f64> {
        self.epsilons
            .get(&photons)
            .copied()
            .with_context(|| format!("no ε was calibrated for {photons} photons per source"))
    }

    /// The score of a render of `photons` per source.
    pub fn score(&self, counts: &CountMatrix, photons: u32) -> Result<Score> {
        let n = u64::from(photons);
        if self.is_likelihood() {
            return Ok(Score::of_deviance(likelihood::deviance(
                &self.target,
                counts,
                n,
            )?));
        }
        let epsilon = self.epsilon(photons)?;
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
            blocks: Vec::new(),
            changes: Vec::new(),
        })
    }
}

impl Scoring {
    /// The score of a differential render: the rendered map's, with the estimated score of
    /// every change it reweighted (the likelihood only: paired blocks are what compare them).
    pub fn score_differential(&self, output: &DifferentialOutput, photons: u32) -> Result<Score> {
        let changes = scatterfarm_model::likelihood::change_deviances(
            &self.target,
            output,
            u64::from(photons),
        )?
        .into_iter()
        .map(|d| {
            d.map(|d| ChangeScore {
                value: d.value,
                blocks: d.blocks,
            })
        })
        .collect();
        self.score_with_changes(&output.counts, photons, changes)
    }

    /// The score of a differential render whose changes were scored where it was rendered (a
    /// farm worker): the rendered map's counts scored here, with the changes' scores as given.
    pub fn score_with_changes(
        &self,
        counts: &CountMatrix,
        photons: u32,
        changes: Vec<Option<ChangeScore>>,
    ) -> Result<Score> {
        anyhow::ensure!(
            self.is_likelihood(),
            "differential renders are scored by the likelihood (metric deviance, no tiebreak)"
        );
        let mut score = self.score(counts, photons)?;
        score.changes = changes;
        Ok(score)
    }
}

/// What the search consumed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Consumption {
    /// Render requests the search made (each answered by a render or by the cache).
    pub requests: u64,
    /// Distinct renders the search needed: requests whose identity had not been rendered.
    pub renders: u64,
    /// Photons those renders needed, over all sources: a racing contender's full render
    /// counts only the photons beyond its first stage.
    pub photons: u64,
    pub scatter_events: u64,
    /// Batches of requests that needed at least one render: `renders / batches` is how many
    /// renders can run at once, on average.
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

/// Runs the search to its end in this process with `engine`, through the one step driver
/// ([`Steps`]), calling `on_step` after every submitted step and `on_photons` as photons are
/// rendered (photons per source × items). Returns what the search consumed and the photons the
/// engine simulated (all sources).
pub fn drive(
    search: &mut Search,
    engine: &dyn Engine,
    scoring: &Scoring,
    on_step: &mut dyn FnMut(&Search, &Consumption),
    on_photons: &mut dyn FnMut(u64),
) -> Result<(Consumption, u64)> {
    let sources = scoring.geometry.sources() as u64;
    let fingerprint = engine.fingerprint().to_string();
    let mut steps = Steps::new(scoring.geometry, &fingerprint, []);
    let mut used = Consumption::default();
    let mut simulated = 0u64;
    loop {
        match steps.next(search, &mut used)? {
            Next::Finished => return Ok((used, simulated)),
            Next::Submitted => on_step(search, &used),
            Next::Render(groups) => {
                let table = search.materials();
                for group in groups {
                    if !group.changes.is_empty() {
                        let item = group
                            .items
                            .first()
                            .context("a differential group without its render")?;
                        let output = render_differential(
                            engine,
                            scoring,
                            &table,
                            &item.item,
                            group.photons,
                            &group.changes,
                            on_photons,
                        )?;
                        used.scatter_events += output.scatter_events;
                        simulated += u64::from(group.photons) * sources;
                        steps.complete_differential(
                            search,
                            scoring,
                            group.photons,
                            item,
                            &output,
                        )?;
                        continue;
                    }
                    let items: Vec<RenderItem> =
                        group.items.iter().map(|i| i.item.clone()).collect();
                    let n_items = items.len() as u64;
                    let rendered = render_range(
                        engine,
                        scoring.geometry,
                        &table,
                        &items,
                        group.start..group.photons,
                        scoring.chunk,
                        &mut |n| on_photons(u64::from(n) * n_items * sources),
                    )?;
                    used.scatter_events += rendered.scatter_events;
                    simulated += u64::from(group.photons - group.start) * n_items * sources;
                    let mut counts = rendered.counts;
                    for (total, prefix) in counts.iter_mut().zip(&group.prefixes) {
                        total.add(prefix)?;
                    }
                    steps.complete(search, scoring, group.photons, &group.items, counts)?;
                }
            }
        }
    }
}

/// Renders `item` differentially over photons `[0, photons)`, in chunks of
/// [`scatterfarm_model::differential::CHUNK_PHOTONS`]
/// ([`scatterfarm_model::differential::render_in_chunks`], as a farm worker does).
pub fn render_differential(
    engine: &dyn Engine,
    scoring: &Scoring,
    table: &[Material],
    item: &RenderItem,
    photons: u32,
    changes: &[scatterfarm_model::Change],
    on_photons: &mut dyn FnMut(u64),
) -> Result<DifferentialOutput> {
    let sources = scoring.geometry.sources() as u64;
    scatterfarm_model::differential::render_in_chunks(
        engine,
        scoring.geometry,
        table,
        item,
        scatterfarm_model::differential::PhotonChunks {
            photons,
            chunk: scatterfarm_model::differential::CHUNK_PHOTONS,
        },
        changes,
        &mut |count| on_photons(u64::from(count) * sources),
    )
    .context("a differential render (refine_screen = \"differential\")")
}
