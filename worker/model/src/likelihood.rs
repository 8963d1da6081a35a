//! The likelihood of a render against a target (`docs/model.md`, "Likelihood"): the Poisson
//! two-sample deviance of a render's counts against the target's, split over interleaved
//! blocks so that two renders on common photons compare with a standard error. It lives in the
//! model because both ends score with it: the coordinator scores the renders it receives, and
//! a worker scores the changes of a differential render where their counts are (sending one
//! score per change, not a count matrix).
//!
//! Each observation `i` (a source and a bin) holds a target count `t` over `n_t` photons per
//! source and a render count `c` over `n_c`. Under the hypothesis that both come from one rate,
//! its maximum-likelihood estimate gives the expected counts `e_t = n_t (t + c) / (n_t + n_c)` and
//! `e_c = n_c (t + c) / (n_t + n_c)`, and the deviance
//! `D_i = 2 [t ln(t / e_t) + c ln(c / e_c)]` (`0 ln 0 = 0`) measures how far the two disagree,
//! honest about the noise of both sides: neither is taken as the truth. The score is `−Σ D_i`
//! (higher is better), so it orders candidates as the likelihood ratio does.
//!
//! A score keeps its deviance split over [`blocks`] interleaved blocks of observations
//! (observation `i` in block `i mod B`). Interleaving spreads every source and bin over all
//! blocks, so a change's signal is shared evenly by the blocks and their spread measures noise,
//! not where the signal sits.

use crate::differential::DifferentialOutput;
use crate::engine::CountMatrix;
use thiserror::Error;

/// The most blocks a score is split into.
pub const MAX_BLOCKS: usize = 256;

/// The number of blocks for `observations` observations.
pub fn blocks(observations: usize) -> usize {
    observations.clamp(1, MAX_BLOCKS)
}

/// A target observation set: fractions `O[i][j]`, row-major, and the photons behind them.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    pub values: Vec<f32>,
    /// Photons per source of the target (its effective sample size for captures).
    pub photons_per_source: u64,
}

/// Why a deviance cannot be computed.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum LikelihoodError {
    #[error("the render has {got} observations, the target {expected}")]
    Shape { expected: usize, got: usize },
    #[error("a render and its target need at least one photon per source")]
    NoPhotons,
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
) -> Result<Deviance, LikelihoodError> {
    if counts.counts.len() != target.values.len() {
        return Err(LikelihoodError::Shape {
            expected: target.values.len(),
            got: counts.counts.len(),
        });
    }
    if photons == 0 || target.photons_per_source == 0 {
        return Err(LikelihoodError::NoPhotons);
    }
    Ok(deviance_of(target, photons, |i| {
        f64::from(counts.counts[i])
    }))
}

/// The deviance of a change estimated by a differential render: its counts are the rendered
/// map's `counts` plus `delta` (`Σ (w − 1)` per observation; see [`crate::differential`]),
/// fractional and never below 0.
pub fn deviance_reweighted(
    target: &Target,
    counts: &CountMatrix,
    delta: &[f64],
    photons: u64,
) -> Result<Deviance, LikelihoodError> {
    if counts.counts.len() != target.values.len() || delta.len() != counts.counts.len() {
        return Err(LikelihoodError::Shape {
            expected: target.values.len(),
            got: delta.len().min(counts.counts.len()),
        });
    }
    if photons == 0 || target.photons_per_source == 0 {
        return Err(LikelihoodError::NoPhotons);
    }
    Ok(deviance_of(target, photons, |i| {
        (f64::from(counts.counts[i]) + delta[i]).max(0.0)
    }))
}

/// The deviance of every change a differential render of `photons` per source estimated, in
/// order; `None` for a change it did not estimate.
pub fn change_deviances(
    target: &Target,
    output: &DifferentialOutput,
    photons: u64,
) -> Result<Vec<Option<Deviance>>, LikelihoodError> {
    output
        .deltas
        .iter()
        .map(|delta| {
            delta
                .as_ref()
                .map(|d| deviance_reweighted(target, &output.counts, d, photons))
                .transpose()
        })
        .collect()
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

#[cfg(test)]
mod tests {
    use super::*;

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

    fn target() -> (Target, CountMatrix) {
        let counts = CountMatrix {
            sources: 2,
            bins: 3,
            counts: vec![5, 0, 9, 1, 2, 3],
        };
        let target = Target {
            values: vec![0.05, 0.01, 0.08, 0.0, 0.03, 0.02],
            photons_per_source: 100,
        };
        (target, counts)
    }

    #[test]
    fn a_zero_delta_scores_as_the_plain_render_and_shapes_are_checked() {
        let (target, counts) = target();
        let plain = deviance(&target, &counts, 100).unwrap();
        assert_eq!(plain.blocks.len(), 6);
        assert!((plain.blocks.iter().sum::<f64>() - plain.value).abs() < 1e-12);
        let same = deviance_reweighted(&target, &counts, &[0.0; 6], 100).unwrap();
        assert_eq!(same, plain);
        let moved =
            deviance_reweighted(&target, &counts, &[0.0, 1.0, -1.0, 0.0, 1.0, 0.0], 100).unwrap();
        assert_ne!(moved.value, plain.value);
        assert!(matches!(
            deviance_reweighted(&target, &counts, &[0.0; 5], 100),
            Err(LikelihoodError::Shape { .. })
        ));
        assert_eq!(
            deviance(&target, &counts, 0),
            Err(LikelihoodError::NoPhotons)
        );
        let output = DifferentialOutput {
            counts: counts.clone(),
            deltas: vec![None, Some(vec![0.0; 6])],
            scatter_events: 0,
        };
        let each = change_deviances(&target, &output, 100).unwrap();
        assert_eq!(each, vec![None, Some(plain)]);
    }
}
