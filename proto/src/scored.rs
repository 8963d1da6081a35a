//! The scored parts of the protocol: a plain task whose worker scores its renders against the
//! job's target ([`scored_to_proto`], checked by [`check_scored`]), and the scores that come
//! back instead of the counts ([`render_scores_to_proto`], [`render_scores_from_proto`]). Like
//! [`crate::convert`], both ends encode and check here.

use crate::convert::ConvertError;
use crate::differential::target_to_proto;
use crate::v1;
use scatterfarm_model::likelihood::{Deviance, Target, MAX_BLOCKS};

/// The most render scores one result may carry (far more assignments than a task holds).
pub const MAX_RENDER_SCORES: usize = 1 << 16;

/// The wire form of a task's scored part, with `target` when the worker does not hold it.
pub fn scored_to_proto(target: Option<&Target>) -> v1::Scored {
    v1::Scored {
        target: target.map(target_to_proto),
    }
}

/// Checks a scored task: a plain task (not differential) whose renders start at photon 0, so
/// the worker scores complete renders.
pub fn check_scored(differential: bool, first: u32) -> Result<(), ConvertError> {
    if differential {
        return Err(ConvertError::Scored(
            "a differential task cannot also be scored as a plain one".into(),
        ));
    }
    if first != 0 {
        return Err(ConvertError::Scored(format!(
            "a scored task renders from photon 0, not {first}"
        )));
    }
    Ok(())
}

/// Every render's score as the wire carries it.
pub fn render_scores_to_proto(scores: &[Deviance]) -> Vec<v1::RenderScore> {
    scores
        .iter()
        .map(|d| v1::RenderScore {
            value: d.value,
            blocks: d.blocks.clone(),
        })
        .collect()
}

/// Every render's score from the wire: at most [`MAX_RENDER_SCORES`], each with at most
/// [`MAX_BLOCKS`] blocks, every number finite. Whether they fit the task (one per assignment,
/// the geometry's blocks) is the receiver's check.
pub fn render_scores_from_proto(scores: &[v1::RenderScore]) -> Result<Vec<Deviance>, ConvertError> {
    let bad = |why: String| ConvertError::RenderScores(why);
    if scores.len() > MAX_RENDER_SCORES {
        return Err(bad(format!(
            "{} scores, at most {MAX_RENDER_SCORES}",
            scores.len()
        )));
    }
    scores
        .iter()
        .enumerate()
        .map(|(k, s)| {
            if s.blocks.len() > MAX_BLOCKS {
                return Err(bad(format!(
                    "render {k}: {} blocks, at most {MAX_BLOCKS}",
                    s.blocks.len()
                )));
            }
            if !s.value.is_finite() || s.blocks.iter().any(|b| !b.is_finite()) {
                return Err(bad(format!("render {k}: a score that is not finite")));
            }
            Ok(Deviance {
                value: s.value,
                blocks: s.blocks.clone(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn render_scores_round_trip_and_bad_ones_are_refused() {
        let scores = vec![
            Deviance {
                value: -3.0,
                blocks: vec![-1.0, -2.0],
            },
            Deviance {
                value: -0.5,
                blocks: vec![-0.5, 0.0],
            },
        ];
        let wire = render_scores_to_proto(&scores);
        assert_eq!(render_scores_from_proto(&wire).unwrap(), scores);
        let mut nan = wire.clone();
        nan[0].value = f64::NAN;
        assert!(render_scores_from_proto(&nan)
            .unwrap_err()
            .to_string()
            .contains("render 0"));
        let mut inf = wire.clone();
        inf[1].blocks[1] = f64::NEG_INFINITY;
        assert!(render_scores_from_proto(&inf)
            .unwrap_err()
            .to_string()
            .contains("render 1"));
        let mut many = wire;
        many[1].blocks = vec![0.0; MAX_BLOCKS + 1];
        assert!(render_scores_from_proto(&many).is_err());
    }

    #[test]
    fn a_scored_task_is_plain_and_starts_at_photon_0() {
        assert!(check_scored(false, 0).is_ok());
        let e = check_scored(false, 10).unwrap_err().to_string();
        assert!(e.contains("from photon 0"), "{e}");
        let e = check_scored(true, 0).unwrap_err().to_string();
        assert!(e.contains("differential"), "{e}");
    }
}
