//! The search's random draws, written out so they are stable across `rand` releases: only the
//! ChaCha8 output words are taken from the library (a checkpoint must resume identically).

use rand_chacha::rand_core::RngCore;
use rand_chacha::ChaCha8Rng;
use scatterfarm_model::Material;
use serde::{Deserialize, Serialize};

/// A uniform number in [0, 1) from 53 random bits.
pub fn unit(rng: &mut ChaCha8Rng) -> f64 {
    (rng.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// A uniform integer in `0..n` (`n ≥ 1`), by rejection so there is no modulo bias.
pub fn below(rng: &mut ChaCha8Rng, n: u32) -> u32 {
    let n64 = u64::from(n.max(1));
    let zone = u64::MAX - (u64::MAX % n64);
    loop {
        let x = rng.next_u64();
        if x < zone {
            return (x % n64) as u32;
        }
    }
}

/// Fisher–Yates.
pub fn shuffle(rng: &mut ChaCha8Rng, items: &mut [u32]) {
    for i in (1..items.len()).rev() {
        let j = below(rng, i as u32 + 1) as usize;
        items.swap(i, j);
    }
}

/// Bounds of random materials (`docs/model.md`: default σs ∈ [0, 1], σa ∈ [0, 0.03], g ∈ [0, 1]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    pub sigma_s: (f64, f64),
    pub sigma_a: (f64, f64),
    pub g: (f64, f64),
}

impl Default for Bounds {
    fn default() -> Self {
        Bounds {
            sigma_s: (0.0, 1.0),
            sigma_a: (0.0, 0.03),
            g: (0.0, 1.0),
        }
    }
}

impl Bounds {
    /// A material drawn uniformly within the bounds.
    pub fn draw(&self, rng: &mut ChaCha8Rng) -> Material {
        let mut pick = |(lo, hi): (f64, f64)| lo + (hi - lo) * unit(rng);
        let sigma_s = pick(self.sigma_s);
        let sigma_a = pick(self.sigma_a);
        let g = pick(self.g);
        Material {
            sigma_s,
            sigma_a,
            g,
        }
    }
}
