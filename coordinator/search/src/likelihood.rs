//! The likelihood score (`docs/model.md`, "Likelihood"): the Poisson two-sample deviance of a
//! render's counts against the target's, and paired comparisons of two renders made on the same
//! photons (common random numbers).
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

use crate::similarity::{SimilarityError, Target};
use scatterfarm_model::CountMatrix;

/// The most blocks a score is split into.
pub const MAX_BLOCKS: usize = 256;

/// The number of blocks for `observations` observations.
pub fn blocks(observations: usize) -> usize {
    observations.clamp(1, MAX_BLOCKS)
}

/// A render's deviance against the target: `value = −Σ D_i`, and the same sum per block.
#[derive(Debug, Clone, PartialEq)]
pub struct Deviance {
    pub value: f64,
    pub blocks: Vec<f64>,
}

/// `x ln(x / e)`, 0 at `x = 0`.
#[inline]
fn xlogx_over(x: f64, e: f64) -> f64 {
    if x > 0.0 {
        x * (x / e).ln()
    } else {
        0.0
    }
}

/// One observation's deviance: target count `t` over `nt` photons, render count `c` over `nc`.
#[inline]
pub fn term(t: f64, nt: f64, c: f64, nc: f64) -> f64 {
    let sum = t + c;
    if sum <= 0.0 {
        return 0.0;
    }
    let total = nt + nc;
    2.0 * (xlogx_over(t, nt * sum / total) + xlogx_over(c, nc * sum / total))
}

/// The deviance of a render (`counts` over `photons` photons per source) against `target`.
pub fn deviance(
    target: &Target,
    counts: &CountMatrix,
    photons: u64,
) -> Result<Deviance, SimilarityError> {
    if counts.counts.len() != target.values.len() {
        return Err(SimilarityError::Shape {
            expected: target.values.len(),
            got: counts.counts.len(),
        });
    }
    if photons == 0 || target.photons_per_source == 0 {
        return Err(SimilarityError::NoPhotons);
    }
    Ok(deviance_of(target, photons, |i| {
        f64::from(counts.counts[i])
    }))
}

/// The deviance of a change estimated by a differential render: its counts are the rendered
/// map's `counts` plus `delta` (`Σ (w − 1)` per observation; see
/// `scatterfarm_model::differential`), fractional and never below 0.
pub fn deviance_reweighted(
    target: &Target,
    counts: &CountMatrix,
    delta: &[f64],
    photons: u64,
) -> Result<Deviance, SimilarityError> {
    if counts.counts.len() != target.values.len() || delta.len() != counts.counts.len() {
        return Err(SimilarityError::Shape {
            expected: target.values.len(),
            got: delta.len().min(counts.counts.len()),
        });
    }
    if photons == 0 || target.photons_per_source == 0 {
        return Err(SimilarityError::NoPhotons);
    }
    Ok(deviance_of(target, photons, |i| {
        (f64::from(counts.counts[i]) + delta[i]).max(0.0)
    }))
}

/// The deviance of render counts `count(i)` over `photons` per source (shapes checked).
fn deviance_of(target: &Target, photons: u64, count: impl Fn(usize) -> f64) -> Deviance {
    let nt = target.photons_per_source as f64;
    let nc = photons as f64;
    let n = target.values.len();
    let b = blocks(n);
    let mut per_block = vec![0.0; b];
    for (i, &f) in target.values.iter().enumerate() {
        // The target's count: its fraction over its photons (a capture's may be fractional).
        let t = (f64::from(f) * nt).max(0.0);
        per_block[i % b] -= term(t, nt, count(i), nc);
    }
    Deviance {
        value: per_block.iter().sum(),
        blocks: per_block,
    }
}

/// The standard error of a score from its blocks' spread (`√B` times their standard deviation):
/// how much another render of the same map on other photons would differ, with the target
/// fixed. 0 with fewer than two blocks.
pub fn spread(blocks: &[f64]) -> f64 {
    if blocks.len() < 2 {
        return 0.0;
    }
    let n = blocks.len() as f64;
    let mean = blocks.iter().sum::<f64>() / n;
    let var = blocks.iter().map(|b| (b - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (n * var).sqrt()
}

/// The difference `a − b` of two scores split into the same blocks, and its standard error
/// from the spread of the blocks' differences (`√B` times their standard deviation). `None`
/// when the blocks do not match or there are fewer than two.
pub fn paired(a: &[f64], b: &[f64]) -> Option<(f64, f64)> {
    if a.len() != b.len() || a.len() < 2 {
        return None;
    }
    let n = a.len() as f64;
    let diffs: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let sum: f64 = diffs.iter().sum();
    let mean = sum / n;
    let var = diffs.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0);
    Some((sum, (n * var).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_engines::CpuEngine;
    use scatterfarm_model::material::builtin_material;
    use scatterfarm_model::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};

    #[test]
    fn a_term_is_zero_when_rates_agree_and_grows_as_they_part() {
        assert_eq!(term(0.0, 100.0, 0.0, 50.0), 0.0);
        assert!(term(10.0, 100.0, 5.0, 50.0).abs() < 1e-12);
        let near = term(10.0, 100.0, 6.0, 50.0);
        let far = term(10.0, 100.0, 12.0, 50.0);
        assert!(near > 0.0 && far > near, "{near} {far}");
        // Symmetric in the two samples.
        assert!((term(3.0, 40.0, 9.0, 70.0) - term(9.0, 70.0, 3.0, 40.0)).abs() < 1e-12);
        // A count seen on one side only still costs.
        assert!(term(0.0, 100.0, 4.0, 100.0) > 0.0);
    }

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
