//! Seed streams (`docs/model.md`, "Seed streams"): every random stream of a job is derived from the
//! job's one seed by hashing it with a domain tag, so no two uses ever share a stream.
//!
//! The derivation is SHA-256 over a fixed prefix, the seed, the tag and an index, truncated to
//! 64 bits: stable across releases and platforms, so old checkpoints stay valid.

use sha2::{Digest, Sha256};

/// The uses a job's seed is put to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    /// The synthesized target render.
    Target,
    /// The calibration render made as the target is made.
    CalibrationTarget,
    /// The calibration render made as the search renders.
    CalibrationSearch,
    /// The search's own generator (permutations, random materials).
    Search,
    /// Render request `n` of the search, in its deterministic order.
    Render(u64),
    /// Every render of search level `ℓ` under common random numbers (`--search fast`).
    LevelRender(u32),
    /// The re-scoring of level `ℓ`'s finalists (a seed no search render of the level uses).
    Rescore(u32),
    /// Every render of refinement sweep `k` (the current map and each change of it).
    RefineSweep(u32),
    /// The confirmation renders after refinement sweep `k`.
    RefineConfirm(u32),
    /// The end of a growth trial after refinement sweep `k`: the map it reached and the map
    /// its round started from.
    RefineTrial(u32),
    /// The quality bench's check of a result against the truth, on photons no search render
    /// used.
    TruthCheck,
}

impl Stream {
    fn tag(&self) -> (&'static str, u64) {
        match self {
            Stream::Target => ("target", 0),
            Stream::CalibrationTarget => ("calibration-target", 0),
            Stream::CalibrationSearch => ("calibration-search", 0),
            Stream::Search => ("search", 0),
            Stream::Render(n) => ("render", *n),
            Stream::LevelRender(l) => ("render-level", u64::from(*l)),
            Stream::Rescore(l) => ("rescore", u64::from(*l)),
            Stream::RefineSweep(k) => ("refine-sweep", u64::from(*k)),
            Stream::RefineConfirm(k) => ("refine-confirm", u64::from(*k)),
            Stream::RefineTrial(k) => ("refine-trial", u64::from(*k)),
            Stream::TruthCheck => ("truth-check", 0),
        }
    }
}

/// The 64-bit seed of `stream` under the job seed `seed`.
pub fn derive(seed: u64, stream: Stream) -> u64 {
    let (tag, index) = stream.tag();
    let mut h = Sha256::new();
    h.update(b"scatterfarm-seed/1\0");
    h.update(seed.to_le_bytes());
    h.update(tag.as_bytes());
    h.update([0]);
    h.update(index.to_le_bytes());
    let digest = h.finalize();
    let mut bytes = [0u8; 8];
    bytes.copy_from_slice(&digest[..8]);
    u64::from_le_bytes(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_distinct_and_stable() {
        let all = [
            derive(1, Stream::Target),
            derive(1, Stream::CalibrationTarget),
            derive(1, Stream::CalibrationSearch),
            derive(1, Stream::Search),
            derive(1, Stream::Render(0)),
            derive(1, Stream::Render(1)),
            derive(1, Stream::LevelRender(0)),
            derive(1, Stream::LevelRender(1)),
            derive(1, Stream::Rescore(1)),
            derive(2, Stream::Target),
        ];
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
        assert_eq!(derive(1, Stream::Target), derive(1, Stream::Target));
    }
}
