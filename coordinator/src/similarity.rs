//! Similarity between a target observation set and a render (`model.md`, "Similarity"), and the
//! calibration of the threshold ε.
//!
//! Scores are computed from summed integer counts, so a render may arrive in pieces. Every
//! metric is "higher is better": the L2 metrics are negated sums of squares.

use clap::ValueEnum;
use scatterfarm_worker::CountMatrix;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The similarity metrics, by name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ValueEnum, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Metric {
    /// The paper's: the fraction of observations within ε of the target.
    #[default]
    WithinEpsilon,
    /// Minus the sum of squared differences.
    L2,
    /// Minus the sum of squared differences, each divided by the target's intensity
    /// (plus one photon's worth, so dark observations stay finite).
    L2InverseIntensity,
    /// Minus χ²: squared differences over the binomial variance of the difference, with the
    /// fraction pooled from target and render (so neither side's noise sets the weights, and
    /// darker candidates are not favoured).
    L2Pooled,
}

/// Why a score could not be computed.
#[derive(Debug, Error, PartialEq)]
pub enum SimilarityError {
    #[error("the render has {got} observations, the target {expected}")]
    Shape { expected: usize, got: usize },
    #[error("a render needs at least one photon per source")]
    NoPhotons,
    #[error("percentile must lie in [0, 100], got {0}")]
    Percentile(f64),
}

/// A target observation set: fractions `O[i][j]`, row-major, and the photons behind them.
#[derive(Debug, Clone)]
pub struct Target {
    pub values: Vec<f32>,
    /// Photons per source of the target (its effective sample size for captures).
    pub photons_per_source: u64,
}

/// A render's fraction in the target's precision.
#[inline]
fn fraction(count: u32, photons: u64) -> f32 {
    (f64::from(count) / photons as f64) as f32
}

/// The similarity of a render (`counts` over `photons_per_source` photons) to `target`.
pub fn score(
    metric: Metric,
    target: &Target,
    counts: &CountMatrix,
    photons_per_source: u64,
    epsilon: f64,
) -> Result<f64, SimilarityError> {
    if counts.counts.len() != target.values.len() {
        return Err(SimilarityError::Shape {
            expected: target.values.len(),
            got: counts.counts.len(),
        });
    }
    if photons_per_source == 0 {
        return Err(SimilarityError::NoPhotons);
    }
    let pairs = target
        .values
        .iter()
        .zip(&counts.counts)
        .map(|(&r, &c)| (r, fraction(c, photons_per_source)));
    Ok(match metric {
        Metric::WithinEpsilon => {
            let within = pairs
                .filter(|&(r, s)| r == s || (f64::from(r) - f64::from(s)).abs() < epsilon)
                .count();
            within as f64 / target.values.len().max(1) as f64
        }
        Metric::L2 => -pairs
            .map(|(r, s)| (f64::from(r) - f64::from(s)).powi(2))
            .sum::<f64>(),
        Metric::L2InverseIntensity => {
            let floor = 1.0 / target.photons_per_source.max(1) as f64;
            -pairs
                .map(|(r, s)| (f64::from(r) - f64::from(s)).powi(2) / (f64::from(r) + floor))
                .sum::<f64>()
        }
        Metric::L2Pooled => {
            // Var(R − S) = p(1 − p)(1/n_R + 1/n_S) for binomial fractions with a common p,
            // estimated from both; p is kept at least one photon's worth of the pooled sample.
            let (nr, ns) = (
                target.photons_per_source.max(1) as f64,
                photons_per_source as f64,
            );
            let scale = 1.0 / nr + 1.0 / ns;
            let floor = 1.0 / (nr + ns);
            -pairs
                .map(|(r, s)| {
                    let (r, s) = (f64::from(r), f64::from(s));
                    let p = ((r * nr + s * ns) / (nr + ns)).clamp(floor, 1.0 - floor);
                    (r - s).powi(2) / (p * (1.0 - p) * scale)
                })
                .sum::<f64>()
        }
    })
}

/// ε: the `percentile`-th percentile (nearest rank) of `|a − b|` over all observations.
pub fn epsilon(a: &[f32], b: &[f32], percentile: f64) -> Result<f64, SimilarityError> {
    if a.len() != b.len() {
        return Err(SimilarityError::Shape {
            expected: a.len(),
            got: b.len(),
        });
    }
    if !(0.0..=100.0).contains(&percentile) {
        return Err(SimilarityError::Percentile(percentile));
    }
    if a.is_empty() {
        return Ok(0.0);
    }
    let mut diffs: Vec<f64> = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).abs())
        .collect();
    // Nearest rank; the small slack keeps 99.9 % of 1000 at rank 999 despite rounding.
    let rank = ((percentile / 100.0) * diffs.len() as f64 - 1e-9).ceil() as usize;
    let index = rank.clamp(1, diffs.len()) - 1;
    let (_, value, _) = diffs.select_nth_unstable_by(index, f64::total_cmp);
    Ok(*value)
}

/// Fractions of a count matrix, as the target would store them.
pub fn fractions(counts: &CountMatrix, photons_per_source: u64) -> Vec<f32> {
    counts
        .counts
        .iter()
        .map(|&c| fraction(c, photons_per_source))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn counts(values: &[u32]) -> CountMatrix {
        CountMatrix {
            sources: 1,
            bins: values.len(),
            counts: values.to_vec(),
        }
    }

    #[test]
    fn within_epsilon_counts_close_and_exact_matches() {
        let target = Target {
            values: vec![0.5, 0.1, 0.0, 0.3],
            photons_per_source: 10,
        };
        // Render fractions: 0.5 (exact), 0.2 (0.1 off), 0.0 (exact), 0.9 (0.6 off).
        let c = counts(&[5, 2, 0, 9]);
        assert_eq!(
            score(Metric::WithinEpsilon, &target, &c, 10, 0.0).unwrap(),
            0.5
        );
        assert_eq!(
            score(Metric::WithinEpsilon, &target, &c, 10, 0.15).unwrap(),
            0.75
        );
        assert_eq!(
            score(Metric::WithinEpsilon, &target, &c, 10, 1.0).unwrap(),
            1.0
        );
        let l2 = score(Metric::L2, &target, &c, 10, 0.0).unwrap();
        assert!((l2 + 0.01 + 0.36).abs() < 1e-6, "{l2}");
        assert!(score(Metric::L2InverseIntensity, &target, &c, 10, 0.0).unwrap() < l2);
        assert!(score(Metric::L2, &target, &counts(&[1]), 10, 0.0).is_err());
    }

    #[test]
    fn epsilon_is_the_nearest_rank_percentile() {
        let a: Vec<f32> = (0..1000).map(|i| i as f32 / 1000.0).collect();
        let b = vec![0.0f32; 1000];
        assert!((epsilon(&a, &b, 99.9).unwrap() - 0.998).abs() < 1e-6);
        assert!((epsilon(&a, &b, 100.0).unwrap() - 0.999).abs() < 1e-6);
        assert!((epsilon(&a, &b, 50.0).unwrap() - 0.499).abs() < 1e-6);
        assert_eq!(epsilon(&b, &b, 99.9).unwrap(), 0.0);
        assert!(epsilon(&a, &b, 101.0).is_err());
    }
}
