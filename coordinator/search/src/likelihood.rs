//! The likelihood score (`docs/model.md`, "Likelihood"): the Poisson two-sample deviance of a
//! render's counts against the target's ([`scatterfarm_model::likelihood`], where workers score
//! with it too), and paired comparisons of two renders made on the same photons (common random
//! numbers).
//!
//! Each observation `i` (a source and a bin) holds a target count `t` over `n_t` photons per
//! source and a render count `c` over `n_c`. Under the hypothesis that both come from one rate,
//! its maximum-likelihood estimate gives the expected counts `e_t = n_t (t + c) / (n_t + n_c)` and
//! `e_c = n_c (t + c) / (n_t + n_c)`, and the deviance
//! `D_i = 2 [t ln(t / e_t) + c ln(c / e_c)]` (`0 ln 0 = 0`) measures how far the two disagree,
//! honest about the noise of both sides: neither is taken as the truth. The score is `−Σ D_i`
//! (higher is better), so it orders candidates as the likelihood ratio does.
//!
//! A score also keeps its deviance split over [`blocks`] interleaved blocks of observations
//! (observation `i` in block `i mod B`). Two renders on the same seed differ in their blocks by
//! the material change plus the noise that the change lets through; [`paired`] turns the
//! blocks' differences into the difference of the scores and its standard error. Interleaving
//! spreads every source and bin over all blocks, so a change's signal is shared evenly by the
//! blocks and their spread measures noise, not where the signal sits.

use crate::similarity::SimilarityError;
use scatterfarm_model::likelihood::{self as model, LikelihoodError};
pub use scatterfarm_model::likelihood::{blocks, spread, term, Deviance, Target, MAX_BLOCKS};
use scatterfarm_model::CountMatrix;

impl From<LikelihoodError> for SimilarityError {
    fn from(e: LikelihoodError) -> SimilarityError {
        match e {
            LikelihoodError::Shape { expected, got } => SimilarityError::Shape { expected, got },
            LikelihoodError::NoPhotons => SimilarityError::NoPhotons,
        }
    }
}

/// The deviance of a render (`counts` over `photons` photons per source) against `target`
/// ([`scatterfarm_model::likelihood::deviance`]).
pub fn deviance(
    target: &Target,
    counts: &CountMatrix,
    photons: u64,
) -> Result<Deviance, SimilarityError> {
    Ok(model::deviance(target, counts, photons)?)
}

/// The deviance of a change estimated by a differential render
/// ([`scatterfarm_model::likelihood::deviance_reweighted`]).
pub fn deviance_reweighted(
    target: &Target,
    counts: &CountMatrix,
    delta: &[f64],
    photons: u64,
) -> Result<Deviance, SimilarityError> {
    Ok(model::deviance_reweighted(target, counts, delta, photons)?)
}

/// The difference `a − b` of two scores split into the same blocks, and its standard error
/// from the spread of the blocks' differences (`√B` times their standard deviation). `None`
/// when the blocks do not match or there are fewer than two.
pub fn paired(a: &[f64], b: &[f64]) -> Option<(f64, f64)> {
    if a.len() != b.len() || a.len() < 2 {
        return None;
    }
    let n = a.len() as f64;
    // Two passes over the differences, made again rather than kept: this runs for every pair
    // of candidates a step compares, and allocating dominated it.
    let diffs = || a.iter().zip(b).map(|(x, y)| x - y);
    let sum: f64 = diffs().sum();
    let mean = sum / n;
    let var = diffs().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0);
    Some((sum, (n * var).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_engines::CpuEngine;
    use scatterfarm_model::material::builtin_material;
    use scatterfarm_model::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};

    #[test]
    fn paired_differences_and_their_error() {
        assert!(paired(&[1.0], &[0.0]).is_none());
        assert!(paired(&[1.0, 2.0], &[0.0]).is_none());
        let (d, se) = paired(&[1.0, 1.0, 1.0], &[0.0, 0.0, 0.0]).unwrap();
        assert_eq!((d, se), (3.0, 0.0));
        let (d, se) = paired(&[2.0, 0.0], &[0.0, 0.0]).unwrap();
        assert_eq!(d, 2.0);
        assert!((se - 2.0).abs() < 1e-12, "{se}");
    }

    fn render(assignment: Vec<u16>, seed: u64, photons: u32) -> (Geometry, CountMatrix) {
        let geometry = Geometry {
            size_mm: 16.0,
            grid: 4,
            positions: 8,
            directions: 3,
        };
        let table = [
            builtin_material("moderate").unwrap(),
            builtin_material("opaque").unwrap(),
        ];
        let items = [RenderItem { assignment, seed }];
        let out = CpuEngine::new()
            .render(&RenderBatch {
                geometry,
                table: &table,
                items: &items,
                photons: PhotonRange {
                    first: 0,
                    count: photons,
                },
            })
            .unwrap();
        (geometry, out.into_iter().next().unwrap().counts)
    }

    fn as_target(counts: &CountMatrix, photons: u32) -> Target {
        Target {
            values: counts
                .counts
                .iter()
                .map(|&c| (f64::from(c) / f64::from(photons)) as f32)
                .collect(),
            photons_per_source: u64::from(photons),
        }
    }

    #[test]
    fn the_truth_scores_clearly_better_than_a_wrong_map_on_common_photons() {
        let truth: Vec<u16> = (0..16).map(|p| u16::from(p == 5 || p == 6)).collect();
        let (_, t) = render(truth.clone(), 99, 4000);
        let target = as_target(&t, 4000);
        let wrong = vec![0u16; 16];
        let (_, a) = render(truth, 7, 1000);
        let (_, b) = render(wrong, 7, 1000);
        let da = deviance(&target, &a, 1000).unwrap();
        let db = deviance(&target, &b, 1000).unwrap();
        assert!((da.blocks.iter().sum::<f64>() - da.value).abs() < 1e-6);
        let (diff, se) = paired(&da.blocks, &db.blocks).unwrap();
        assert!(diff > 0.0 && se > 0.0, "{diff} ± {se}");
        assert!(diff > 3.0 * se, "the truth wins by {diff} ± {se}");
    }

    #[test]
    fn a_render_against_its_own_kind_scores_near_its_degrees_of_freedom() {
        // Two independent renders of one map: the deviance is about one per observation with
        // counts (a χ² with that many degrees of freedom), not far from it.
        let map = vec![0u16; 16];
        let (_, t) = render(map.clone(), 1, 2000);
        let (_, c) = render(map, 2, 2000);
        let d = deviance(&as_target(&t, 2000), &c, 2000).unwrap();
        let nonzero = t
            .counts
            .iter()
            .zip(&c.counts)
            .filter(|(a, b)| **a + **b > 0)
            .count() as f64;
        let per = -d.value / nonzero;
        assert!((0.6..1.6).contains(&per), "deviance per observation {per}");
    }
}
