//! How many quad-tree levels the coarse stage runs ([`CoarseLevels`]), and the rule that
//! decides it after level 0 when the search is told to decide (`docs/model.md`, "Refinement",
//! "Where it starts").

use crate::refine::{RefineConfig, Screen};
use scatterfarm_model::differential::reweightable;
use scatterfarm_model::Material;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// The quad-tree levels the coarse stage runs, from level 0.
///
/// Stored as a number (`Count`) or the string `"auto"`, so a checkpoint or job record written
/// when only numbers were known reads back unchanged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoarseLevels {
    /// Levels `0 … n−1`; the refinement (or the result) starts from level `n−1`'s map.
    Count(u32),
    /// Level 0 only where the refinement can build the objects itself from its one-material
    /// map (`refines_from_level_zero`), else every level.
    Auto,
}

impl fmt::Display for CoarseLevels {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CoarseLevels::Count(n) => write!(f, "{n}"),
            CoarseLevels::Auto => f.write_str("auto"),
        }
    }
}

/// Why a spelling is not a [`CoarseLevels`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("expected a level count (1, 2, …) or \"auto\", got {0:?}")]
pub struct ParseCoarseLevelsError(String);

impl FromStr for CoarseLevels {
    type Err = ParseCoarseLevelsError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "auto" => Ok(CoarseLevels::Auto),
            t => t
                .parse()
                .map(CoarseLevels::Count)
                .map_err(|_| ParseCoarseLevelsError(s.to_string())),
        }
    }
}

impl Serialize for CoarseLevels {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            CoarseLevels::Count(n) => serializer.serialize_u32(*n),
            CoarseLevels::Auto => serializer.serialize_str("auto"),
        }
    }
}

impl<'de> Deserialize<'de> for CoarseLevels {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        deserializer.deserialize_any(CoarseLevelsVisitor)
    }
}

/// Reads [`CoarseLevels`] from a number or a word, with an error that says what was expected.
struct CoarseLevelsVisitor;

impl serde::de::Visitor<'_> for CoarseLevelsVisitor {
    type Value = CoarseLevels;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a level count (1, 2, …) or \"auto\"")
    }

    fn visit_u64<E: serde::de::Error>(self, n: u64) -> Result<CoarseLevels, E> {
        u32::try_from(n)
            .map(CoarseLevels::Count)
            .map_err(|_| E::invalid_value(serde::de::Unexpected::Unsigned(n), &self))
    }

    fn visit_i64<E: serde::de::Error>(self, n: i64) -> Result<CoarseLevels, E> {
        u64::try_from(n)
            .map_err(|_| E::invalid_value(serde::de::Unexpected::Signed(n), &self))
            .and_then(|n| self.visit_u64(n))
    }

    fn visit_str<E: serde::de::Error>(self, word: &str) -> Result<CoarseLevels, E> {
        word.parse().map_err(E::custom)
    }
}

/// Whether the refinement should start from level 0's one-material map rather than from the
/// finest level's: it screens differentially, and every candidate is a change it can reweight
/// out of that material, so each sweep scores all of them from one render and builds the
/// objects itself. (Out of a non-scattering or opaque material most changes are direct
/// renders, and the quad-tree levels build the objects far more cheaply.) `level_zero` is
/// level 0's map, `physics` the table it indexes, `candidates` the materials the refinement
/// tries.
pub fn refines_from_level_zero(
    refine: Option<&RefineConfig>,
    level_zero: &[u16],
    physics: &[Material],
    candidates: &[u16],
) -> bool {
    let Some(refine) = refine else {
        return false;
    };
    if refine.screen != Screen::Differential {
        return false;
    }
    let Some(&first) = level_zero.first() else {
        return false;
    };
    if level_zero.iter().any(|&m| m != first) {
        return false;
    }
    let Some(from) = physics.get(usize::from(first)) else {
        return false;
    };
    if from.is_opaque() || from.sigma_s <= 0.0 {
        return false;
    }
    candidates.iter().all(|&c| {
        physics
            .get(usize::from(c))
            .is_some_and(|to| reweightable(from, to))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_auto_read_back_from_their_stored_and_written_forms() {
        for (text, value) in [
            ("1", CoarseLevels::Count(1)),
            ("5", CoarseLevels::Count(5)),
            ("auto", CoarseLevels::Auto),
        ] {
            assert_eq!(text.parse::<CoarseLevels>(), Ok(value));
            assert_eq!(value.to_string(), text);
            let json = serde_json::to_string(&value).unwrap();
            assert_eq!(serde_json::from_str::<CoarseLevels>(&json).unwrap(), value);
        }
        // A checkpoint of the numbers-only days holds a bare number.
        assert_eq!(
            serde_json::from_str::<CoarseLevels>("3").unwrap(),
            CoarseLevels::Count(3)
        );
        assert!("all".parse::<CoarseLevels>().is_err());
        assert!("-1".parse::<CoarseLevels>().is_err());
        assert!(serde_json::from_str::<CoarseLevels>("\"sometimes\"").is_err());
    }
}
