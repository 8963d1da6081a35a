//! What fixes a refinement ([`RefineConfig`]), how its sweeps score changes ([`Screen`]), the
//! limits the stage keeps to, and the configuration's checks.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// What fixes a refinement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineConfig {
    /// Photons per source of a sweep's renders.
    pub photons: u32,
    /// Photons per source of the confirmation renders.
    pub confirm_photons: u32,
    /// A change must beat the current map by more than this many paired standard errors.
    pub z: f64,
    /// The most sweeps.
    pub max_sweeps: u32,
    /// Whether sweeps also move whole objects by one pixel.
    pub move_objects: bool,
    /// How a sweep scores its changes: a direct render of each, or one differential render of
    /// the current map that estimates them all from its photons (changes it cannot reweight
    /// are rendered directly).
    #[serde(default)]
    pub screen: Screen,
    /// The most changes one differential render estimates (its memory is this many count
    /// matrices).
    #[serde(default = "default_changes_per_render")]
    pub changes_per_render: u32,
    /// How many times the stage may double its sweep and confirmation photons where it would
    /// otherwise end (a sweep with no candidate, or two stalls): more photons where the signal
    /// of the changes left is small.
    #[serde(default)]
    pub escalations: u32,
    /// Whether sweeps also try each connected region of two pixels or more (objects and the
    /// background alike) set wholly to each other candidate material: a region found in the
    /// right place with the wrong material is then one change, not one per pixel.
    #[serde(default)]
    pub recolour_regions: bool,
    /// The pixel's side in mm, for how noisy reweighting is
    /// ([`Refinement::with_spread`](super::Refinement::with_spread)).
    #[serde(default = "default_pixel_mm")]
    pub pixel_mm: f64,
    /// Photons per source of a differential sweep's direct renders (the changes it cannot
    /// reweight, such as a scattering pixel in a non-scattering background) and of the plain
    /// render of `M` they are paired with; `None`: the sweep's photons. Their signal is
    /// usually large (a pixel that starts or stops scattering), so fewer photons find them,
    /// and a sweep over a transmissive background no longer costs a full render per pixel.
    /// Escalations double it with the others.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direct_photons: Option<u32>,
    /// A sweep of a map swept before (after a stall, or escalated) renders directly only the
    /// changes whose paired z on that map's last sweep was above this; `None`: every change.
    /// A change that does not come close at `N` photons is expected to lose by √2 more
    /// standard errors at `2N` (the difference stays, its error shrinks), so re-rendering it
    /// is where an escalation's photons went. Changes a differential render estimates cost
    /// no photons of their own and are always tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retest_z: Option<f64>,
    /// Whether sweeps also swap each pair of neighbouring pixels (8-connected) of different
    /// materials: one object pixel moved to a neighbouring place, which keeps the object's size
    /// and so changes the counts far less than either pixel alone.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub swap_pixels: bool,
    /// Whether sweeps also set each 2 × 2 block, and each pair of neighbouring pixels side by
    /// side or one above the other, wholly to each candidate material (where two pixels or
    /// more change): an object's edge grown, shrunk or shifted two pixels at a time. Such a
    /// change moves the counts about twice as far as one pixel against about √2 times the
    /// noise, so it clears `z` where each of its pixels alone does not, and it leaves the
    /// local optima where one pixel alone cannot improve (an object found one pixel too thin
    /// and one pixel off). With them, each object's bounding box grown or shrunk by one row
    /// or column on each side.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub blocks: bool,
    /// Where the stage would end, a **simplification** round first: a sweep of every
    /// non-background pixel and region set to the background, in which a change is a
    /// candidate, and a confirmation's option wins, unless it loses to the current map by
    /// more than this many paired standard errors. What the target cannot tell from the
    /// background becomes the background (an opaque pixel deep inside a tunnel that no photon
    /// reaches); what it can stays. Rounds come after the last escalation, at its photons.
    /// After a round that changes the map, sweeps go on; after one that
    /// changes nothing, the stage goes on as without it; [`MAX_SIMPLIFICATIONS`] rounds at
    /// most.
    /// `None`: no simplification.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simplify_z: Option<f64>,
    /// Where the stage would end (before it escalates), a **growth** round first: each small
    /// object (a connected region of at most [`GROWTH_MAX_PIXELS`] pixels, not of the
    /// background) grown by its 8-connected neighbours and set wholly to each candidate
    /// material other than the background, and (an object of two pixels or more) its bounding
    /// box grown by one row or column on each side in turn and filled with its material (an
    /// object found with a corner or a side missing), each grown map rendered on its own at a
    /// [`GROWTH_FRACTION`]th of the sweep's photons. A small object of a strong material can
    /// stand in for a larger one of a weaker material (one opaque pixel for a 3 × 2 block of
    /// `uniform` on fig7f): no single pixel then improves the map, and the recolour of the
    /// grown object is too noisy for a differential render to estimate. A round that changes
    /// the map lets the sweeps go on from it (they trim what it grew too far). In a round that
    /// changes nothing, its best grown map is **tried** (`Trial`): the sweeps go on from it
    /// as from a confirmed map, and where they would end, the map they reached is rendered
    /// beside the round's start on a fresh seed at the confirmation photons; it stays if it
    /// beats the start by `z` paired standard errors, else the start comes back and the stage
    /// goes on as without the round. A grown map that fits worse than the stand-in (it grew
    /// into pixels the object lacks) can so still lead to the object. [`MAX_GROWTHS`] rounds
    /// at most, and none twice on one map. [`Growth::Auto`] runs them only where the stage
    /// starts from a one-material map; the stage resolves it when it starts.
    #[serde(default, skip_serializing_if = "Growth::is_off")]
    pub grow_objects: Growth,
    /// A growth round's best grown map is tried (`Trial`) only where its paired z against
    /// the current map is above this; below it, the round ends as one without a trial. `None`:
    /// every round whose grown maps all lose runs a trial.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grow_trial_z: Option<f64>,
}

/// Whether a refinement runs growth rounds ([`RefineConfig::grow_objects`]).
///
/// Stored as a boolean (`On`, `Off`) or the string `"auto"`, so a checkpoint or job record
/// written when growth was a boolean reads back unchanged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Growth {
    /// No growth rounds.
    #[default]
    Off,
    /// Growth rounds wherever the stage would end.
    On,
    /// Growth rounds where the stage starts from a one-material map (level 0's, as
    /// `coarse_levels = auto` leaves it on moderate backgrounds: the sweeps then build every
    /// object from single pixels, and a small object standing in for a larger one is the
    /// failure growth mends); none where the quad-tree levels built the objects. Resolved to
    /// `On` or `Off` when the stage starts ([`Growth::resolve`]).
    Auto,
}

impl Growth {
    /// `On` or `Off` for a stage that starts from `start`: [`Growth::Auto`] is `On` where
    /// every pixel of `start` is one material.
    pub fn resolve(self, start: &[u16]) -> Growth {
        match self {
            Growth::Auto => match start.split_first() {
                Some((first, rest)) if rest.iter().all(|m| m == first) => Growth::On,
                _ => Growth::Off,
            },
            fixed => fixed,
        }
    }

    /// Whether this (resolved) setting runs growth rounds; an unresolved `Auto` does not.
    pub fn is_on(self) -> bool {
        self == Growth::On
    }

    fn is_off(&self) -> bool {
        *self == Growth::Off
    }
}

impl fmt::Display for Growth {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Growth::Off => "false",
            Growth::On => "true",
            Growth::Auto => "auto",
        })
    }
}

/// Why a spelling is not a [`Growth`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("expected true, false or \"auto\", got {0:?}")]
pub struct ParseGrowthError(String);

impl FromStr for Growth {
    type Err = ParseGrowthError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "true" | "on" => Ok(Growth::On),
            "false" | "off" => Ok(Growth::Off),
            "auto" => Ok(Growth::Auto),
            _ => Err(ParseGrowthError(s.to_string())),
        }
    }
}

impl Serialize for Growth {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Growth::On => serializer.serialize_bool(true),
            Growth::Off => serializer.serialize_bool(false),
            Growth::Auto => serializer.serialize_str("auto"),
        }
    }
}

impl<'de> Deserialize<'de> for Growth {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        deserializer.deserialize_any(GrowthVisitor)
    }
}

/// Reads a [`Growth`] from a boolean or a word, with an error that says what was expected.
struct GrowthVisitor;

impl serde::de::Visitor<'_> for GrowthVisitor {
    type Value = Growth;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("true, false or \"auto\"")
    }

    fn visit_bool<E: serde::de::Error>(self, on: bool) -> Result<Growth, E> {
        Ok(if on { Growth::On } else { Growth::Off })
    }

    fn visit_str<E: serde::de::Error>(self, word: &str) -> Result<Growth, E> {
        word.parse().map_err(E::custom)
    }
}

/// The most simplification rounds one refinement runs ([`RefineConfig::simplify_z`]).
pub const MAX_SIMPLIFICATIONS: u32 = 3;

/// The most growth rounds one refinement runs ([`RefineConfig::grow_objects`]).
pub const MAX_GROWTHS: u32 = 4;

/// A growth round grows the objects of at most this many pixels.
pub const GROWTH_MAX_PIXELS: usize = 4;

/// A growth round's renders take this fraction of the sweep's photons (escalated): each is a
/// render of its own, and the changes it looks for move the counts as a whole object does.
pub const GROWTH_FRACTION: u32 = 4;

pub(super) fn is_zero(n: &u32) -> bool {
    *n == 0
}

fn default_pixel_mm() -> f64 {
    1.0
}

/// A differential sweep leaves out a recolour whose photon weights are noisier than this
/// ([`Refinement::spread_of`](super::Refinement::spread_of)): its estimate would rest on a few
/// photons and could never beat `z`, and a direct render of each would cost a full render apiece.
pub const MAX_SPREAD: f64 = 10.0;

fn default_changes_per_render() -> u32 {
    1024
}

/// How a refinement sweep scores its changes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Screen {
    /// A render of every changed map.
    #[default]
    Direct,
    /// One differential render of the current map (`docs/model.md`, "Differential renders").
    Differential,
}

impl Screen {
    pub const ALL: [Screen; 2] = [Screen::Direct, Screen::Differential];

    pub fn name(self) -> &'static str {
        match self {
            Screen::Direct => "direct",
            Screen::Differential => "differential",
        }
    }
}

impl RefineConfig {
    /// What is wrong with the configuration, if anything.
    pub fn problem(&self) -> Option<String> {
        if self.photons == 0 || self.confirm_photons == 0 || self.direct_photons == Some(0) {
            return Some("refinement renders need at least one photon per source".into());
        }
        if !(self.z.is_finite() && self.z >= 0.0) {
            return Some(format!("refinement z must be a number ≥ 0, got {}", self.z));
        }
        if self.max_sweeps == 0 {
            return Some("refinement needs at least one sweep".into());
        }
        if self.changes_per_render == 0 {
            return Some("a differential render needs room for at least one change".into());
        }
        if self
            .simplify_z
            .is_some_and(|z| !(z.is_finite() && z >= 0.0))
        {
            return Some(format!(
                "the refinement's simplification z must be a number ≥ 0, got {}",
                self.simplify_z.unwrap_or_default()
            ));
        }
        if self.grow_trial_z.is_some_and(f64::is_nan) {
            return Some(
                "the refinement's growth trial z must be a number (or -inf: every trial)".into(),
            );
        }
        if self.retest_z.is_some_and(f64::is_nan) {
            return Some(
                "the refinement's retest z must be a number (or -inf: every change)".into(),
            );
        }
        if !(self.pixel_mm.is_finite() && self.pixel_mm > 0.0) {
            return Some(format!(
                "the pixel size must be > 0 mm, got {}",
                self.pixel_mm
            ));
        }
        None
    }
}
