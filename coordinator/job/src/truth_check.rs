//! Information or search? When a reconstruction of a synthesized target misses pixels, this
//! says which limits it: the truth and the map found are rendered on the same fresh photons and
//! their likelihoods compared (paired, `docs/model.md`, "Likelihood"). A truth that scores
//! clearly better than the map found means the search stopped short; a truth that does not
//! means the target's photons cannot tell the two apart.
//!
//! The truth's one-pixel neighbours sharpen that per pixel ([`Neighbours`]): one differential
//! render of the truth estimates every map that differs from it in one pixel, and each wrong
//! pixel of the map found is then either resolved (the truth beats the truth with that pixel
//! as the map has it by at least [`RESOLVED_Z`] paired standard errors: the target tells, the
//! search missed it) or not (information). The found map's own one-pixel changes
//! ([`Escapes`]) then say how the search missed: a map that no single pixel improves is a
//! local optimum that only larger moves leave.

use crate::plan::Plan;
use anyhow::{Context, Result};
use scatterfarm_model::differential::{change_is_reweightable, Change};
use scatterfarm_model::{Engine, EngineError, RenderItem};
use scatterfarm_search::driver::{render_differential, render_one, Scoring};
use scatterfarm_search::likelihood::{self, paired};
use scatterfarm_search::seeds::{self, Stream};
use serde::{Deserialize, Serialize};

/// A margin, in paired standard errors, from which the target is taken to tell two maps apart.
pub const RESOLVED_Z: f64 = 2.0;

/// At most this many bytes of change estimates per differential render of the neighbours.
const NEIGHBOUR_BYTES: usize = 128 << 20;

/// The truth against a map, on common photons.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthCheck {
    /// Photons per source of the renders.
    pub photons: u32,
    /// The truth's log-likelihood score minus the map's (positive: the truth fits better),
    /// and the paired standard error of that difference.
    pub margin: f64,
    pub std_error: f64,
    /// The truth's one-pixel neighbours, where the engine renders differentially.
    pub neighbours: Option<Neighbours>,
    /// The found map's one-pixel changes that beat it, where the engine renders
    /// differentially: none means the map is a local optimum of single-pixel changes (a
    /// search stopped there needs larger moves), some means it stopped early.
    #[serde(default)]
    pub escapes: Option<Escapes>,
}

/// The one-pixel changes of the map found, estimated from one differential render of it on
/// the check's photons.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Escapes {
    /// Changes estimated.
    pub estimated: usize,
    /// Changes that beat the map found by at least [`RESOLVED_Z`] paired standard errors.
    pub beating: usize,
    /// Of those, the changes that set a pixel to the truth's material.
    pub toward_truth: usize,
    /// The best change's margin in standard errors.
    pub best_z: Option<f64>,
}

/// The truth's one-pixel neighbours (each pixel set to each other material of the search's
/// table), estimated from one differential render of the truth on the check's photons.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Neighbours {
    /// Neighbours estimated.
    pub estimated: usize,
    /// Neighbours a render of the truth cannot estimate (out of an opaque pixel, or from a
    /// non-scattering pixel to a scattering material).
    pub not_estimated: usize,
    /// Estimated neighbours the truth does not beat by [`RESOLVED_Z`] standard errors.
    pub unresolved: usize,
    /// The map's wrong pixels, each with the truth's margin in standard errors over the truth
    /// with that one pixel as the map has it (`None`: not estimated).
    pub wrong: Vec<WrongPixel>,
}

/// One wrong pixel of the map found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WrongPixel {
    /// Row-major index, row 0 at the top.
    pub pixel: u32,
    pub z: Option<f64>,
}

impl Neighbours {
    /// Wrong pixels the target tells (z ≥ [`RESOLVED_Z`]): the search missed them.
    pub fn wrong_resolved(&self) -> usize {
        self.wrong
            .iter()
            .filter(|w| w.z.is_some_and(|z| z >= RESOLVED_Z))
            .count()
    }

    /// Wrong pixels the target does not tell (z < [`RESOLVED_Z`]): information.
    pub fn wrong_unresolved(&self) -> usize {
        self.wrong
            .iter()
            .filter(|w| w.z.is_some_and(|z| z < RESOLVED_Z))
            .count()
    }
}

impl TruthCheck {
    /// The margin in standard errors.
    pub fn z(&self) -> f64 {
        if self.std_error > 0.0 {
            self.margin / self.std_error
        } else {
            0.0
        }
    }
}

/// The truth as an assignment of the search's table, when the search grid is the truth's and
/// every true material is in the table.
pub fn truth_assignment(plan: &Plan) -> Option<Vec<u16>> {
    let truth = plan.truth.as_ref()?;
    let n = truth.geometry.grid as usize;
    if plan.search_geometry.grid as usize != n {
        return None;
    }
    let table = plan.search.materials();
    (0..n * n)
        .map(|i| {
            let m = truth.material_at(i / n, i % n);
            table.iter().position(|t| *t == m).map(|k| k as u16)
        })
        .collect()
}

/// Compares the truth with `found` on `photons` fresh photons per source; `None` when the
/// truth cannot be written in the search's table.
pub fn check(
    plan: &Plan,
    scoring: &Scoring,
    engine: &dyn Engine,
    found: &[u16],
    photons: u32,
) -> Result<Option<TruthCheck>> {
    let Some(truth) = truth_assignment(plan) else {
        return Ok(None);
    };
    let seed = seeds::derive(plan.config.seed, Stream::TruthCheck);
    let table = plan.search.materials();
    let score = |a: &[u16]| -> Result<likelihood::Deviance> {
        let counts = render_one(engine, scoring.geometry, &table, a.to_vec(), seed, photons)?;
        Ok(likelihood::deviance(
            &scoring.target,
            &counts,
            u64::from(photons),
        )?)
    };
    let (t, f) = (score(&truth)?, score(found)?);
    let (margin, std_error) = paired(&t.blocks, &f.blocks).context("too few observations")?;
    let probe = Probe {
        scoring,
        engine,
        table: &table,
        seed,
        photons,
    };
    let neighbours = neighbours(&probe, &truth, found, &t)?;
    let escapes = escapes(&probe, &truth, found, &f)?;
    Ok(Some(TruthCheck {
        photons,
        margin,
        std_error,
        neighbours,
        escapes,
    }))
}

/// What the check renders with: the target's scoring, the engine and table, and the seed and
/// photons per source of its renders.
struct Probe<'a> {
    scoring: &'a Scoring,
    engine: &'a dyn Engine,
    table: &'a [scatterfarm_model::Material],
    seed: u64,
    photons: u32,
}

/// The truth's one-pixel neighbours against the truth (whose plain deviance on the probe's
/// seed and photons is `truth_score`); `None` when the engine does not render differentially.
fn neighbours(
    probe: &Probe,
    truth: &[u16],
    found: &[u16],
    truth_score: &likelihood::Deviance,
) -> Result<Option<Neighbours>> {
    let Some(one_pixel) =
        one_pixel_z(probe, truth, truth_score).context("the truth's neighbours")?
    else {
        return Ok(None);
    };
    let wrong = (0..truth.len())
        .filter(|&p| found.get(p).is_some_and(|&f| f != truth[p]))
        .map(|p| WrongPixel {
            pixel: p as u32,
            z: one_pixel.z.get(&(p as u32, found[p])).map(|z| -z),
        })
        .collect();
    // The truth's margin over each neighbour is minus the neighbour's over the truth.
    Ok(Some(Neighbours {
        estimated: one_pixel.z.len(),
        not_estimated: one_pixel.not_estimated,
        unresolved: one_pixel.z.values().filter(|&&z| -z < RESOLVED_Z).count(),
        wrong,
    }))
}

/// The found map's one-pixel changes against it (whose plain deviance is `found_score`):
/// those that beat it, and those of them that set a pixel to the truth's material.
fn escapes(
    probe: &Probe,
    truth: &[u16],
    found: &[u16],
    found_score: &likelihood::Deviance,
) -> Result<Option<Escapes>> {
    let Some(one_pixel) =
        one_pixel_z(probe, found, found_score).context("the found map's neighbours")?
    else {
        return Ok(None);
    };
    let beating = |threshold: f64| {
        one_pixel
            .z
            .iter()
            .filter(move |(_, &z)| z >= threshold)
            .map(|(&(p, d), _)| (p, d))
    };
    Ok(Some(Escapes {
        estimated: one_pixel.z.len(),
        beating: beating(RESOLVED_Z).count(),
        toward_truth: beating(RESOLVED_Z)
            .filter(|&(p, d)| truth.get(p as usize) == Some(&d))
            .count(),
        best_z: one_pixel
            .z
            .values()
            .copied()
            .fold(None, |best, z| match best {
                Some(b) if b >= z => Some(b),
                _ => Some(z),
            }),
    }))
}

/// Every one-pixel change of a map that a differential render of it estimates, with its
/// margin in paired standard errors over the map (positive: the change fits better).
struct OnePixel {
    z: std::collections::BTreeMap<(u32, u16), f64>,
    not_estimated: usize,
}

/// [`OnePixel`] of `map` (whose plain deviance on the probe's seed and photons is
/// `map_score`); `None` when the engine does not render differentially.
fn one_pixel_z(
    probe: &Probe,
    map: &[u16],
    map_score: &likelihood::Deviance,
) -> Result<Option<OnePixel>> {
    let Probe {
        scoring,
        engine,
        table,
        seed,
        photons,
    } = *probe;
    let materials = table.len() as u16;
    let all: Vec<Change> = (0..map.len() as u32)
        .flat_map(|p| {
            (0..materials)
                .filter(move |&d| d != map[p as usize])
                .map(move |d| Change {
                    pixels: vec![(p, d)],
                })
        })
        .collect();
    let (estimable, not_estimated): (Vec<Change>, Vec<Change>) = all
        .into_iter()
        .partition(|c| change_is_reweightable(table, map, c));
    let observations = scoring.target.values.len().max(1);
    let per_render = (NEIGHBOUR_BYTES / (observations * 8)).max(1);
    let item = RenderItem {
        assignment: map.to_vec(),
        seed,
    };
    let n = u64::from(photons);
    let mut z_of = std::collections::BTreeMap::new();
    for changes in estimable.chunks(per_render) {
        let output =
            match render_differential(engine, scoring, table, &item, photons, changes, &mut |_| {})
            {
                Ok(o) => o,
                Err(e)
                    if e.chain().any(|c| {
                        matches!(
                            c.downcast_ref::<EngineError>(),
                            Some(EngineError::Unsupported(_))
                        )
                    }) =>
                {
                    return Ok(None)
                }
                Err(e) => return Err(e),
            };
        for (change, delta) in changes.iter().zip(&output.deltas) {
            let Some(delta) = delta else { continue };
            let d = likelihood::deviance_reweighted(&scoring.target, &output.counts, delta, n)?;
            // The change's margin over the map (scores: higher fits better).
            if let Some((margin, se)) = paired(&d.blocks, &map_score.blocks) {
                let z = if se > 0.0 { margin / se } else { 0.0 };
                z_of.insert(change.pixels[0], z);
            }
        }
    }
    Ok(Some(OnePixel {
        z: z_of,
        not_estimated: not_estimated.len(),
    }))
}
