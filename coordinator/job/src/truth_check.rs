//! Information or search? When a reconstruction of a synthesized target misses pixels, this
//! says which limits it: the truth and the map found are rendered on the same fresh photons and
//! their likelihoods compared (paired, `docs/model.md`, "Likelihood"). A truth that scores
//! clearly better than the map found means the search stopped short; a truth that does not
//! means the target's photons cannot tell the two apart.

use crate::plan::Plan;
use anyhow::{Context, Result};
use scatterfarm_model::Engine;
use scatterfarm_search::driver::{render_one, Scoring};
use scatterfarm_search::likelihood::{self, paired};
use scatterfarm_search::seeds::{self, Stream};
use serde::{Deserialize, Serialize};

/// The truth against a map, on common photons.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthCheck {
    /// Photons per source of the two renders.
    pub photons: u32,
    /// The truth's log-likelihood score minus the map's (positive: the truth fits better),
    /// and the paired standard error of that difference.
    pub margin: f64,
    pub std_error: f64,
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
    Ok(Some(TruthCheck {
        photons,
        margin,
        std_error,
    }))
}
