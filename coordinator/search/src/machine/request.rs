//! What the search asks for ([`RenderRequest`]) and what it is answered with ([`Score`]).

use super::Secondary;
use scatterfarm_model::Change;
use serde::{Deserialize, Serialize};

/// One render the search needs: the assignment, the seed and the photons to render it with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RenderRequest {
    /// The request's index in the search's deterministic order.
    pub index: u64,
    pub seed: u64,
    /// Photons per source.
    pub photons: u32,
    /// `grid²` indices into the search's table.
    pub assignment: Vec<u16>,
    /// A differential render (`docs/model.md`, "Differential renders"): the changes of
    /// `assignment` whose scores the same photons also estimate. Empty for a plain render.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<Change>,
}

/// A render's score and its standard error from the render's own Monte Carlo noise
/// (`similarity::score`); racing compares candidates with it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Score {
    pub value: f64,
    pub std_error: f64,
    /// The tiebreak's score of the same render, when the search has a [`Tiebreak`](super::Tiebreak).
    pub secondary: Option<Secondary>,
    /// The likelihood score split into interleaved blocks of observations
    /// ([`crate::likelihood`]): two renders on one seed are compared by their blocks' paired
    /// differences. Empty for the other metrics.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub blocks: Vec<f64>,
    /// A differential render's estimated scores of its request's changes, in order (`None`:
    /// the change could not be reweighted). Empty for a plain render.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<Option<ChangeScore>>,
}

/// The likelihood score of one change estimated by a differential render: its value and its
/// blocks, paired with the rendered map's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeScore {
    pub value: f64,
    pub blocks: Vec<f64>,
}

impl Score {
    /// A score known without error.
    pub fn exact(value: f64) -> Score {
        Score {
            value,
            std_error: 0.0,
            secondary: None,
            blocks: Vec::new(),
            changes: Vec::new(),
        }
    }

    /// The likelihood score of a render from its deviance, wherever that was computed (here,
    /// or by the worker that rendered it): the value and blocks as they are, the standard
    /// error the blocks' spread.
    pub fn of_deviance(d: scatterfarm_model::likelihood::Deviance) -> Score {
        Score {
            value: d.value,
            std_error: crate::likelihood::spread(&d.blocks),
            secondary: None,
            blocks: d.blocks,
            changes: Vec::new(),
        }
    }
}
