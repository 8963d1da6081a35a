//! What a differential render of the current map can estimate: the filled base of a map with
//! opaque pixels, which changes reweight from a map, and how noisy their photon weights are.

use super::*;

/// The filled base of a map ([`Refinement::filled_base`]): the map rendered, and the change
/// of it that gives back the map it was filled from.
#[derive(Debug, Clone)]
pub(super) struct Base {
    pub(super) map: Vec<u16>,
    pub(super) current: Change,
}

impl Base {
    /// The change of the base that gives `target`: its pixels that differ, in order.
    pub(super) fn change_to(&self, target: &[u16]) -> Change {
        Change {
            pixels: self
                .map
                .iter()
                .zip(target)
                .enumerate()
                .filter(|(_, (b, t))| b != t)
                .map(|(p, (_, &t))| (p as u32, t))
                .collect(),
        }
    }
}

impl Refinement {
    /// The filled base of the current map `M`: `M` with every opaque pixel (and every pixel
    /// nothing reweights out of) set to the background (`docs/model.md`, "The filled base").
    /// Nothing reweights out of an opaque pixel, so a differential render of `M` cannot
    /// estimate clearing one; a render of the base can estimate `M` (its opaque pixels back:
    /// weight 0 for every photon that entered them, exact) and every change of `M`, clearing
    /// included, on the same photons. `None` when `M` has no pixel to fill, or its background
    /// is opaque.
    pub(super) fn filled_base(&self) -> Option<Base> {
        let opaque = |m: u16| self.opaque.get(usize::from(m)).copied().unwrap_or(false);
        let reweights = |from: u16, to: u16| {
            self.reweightable
                .get(usize::from(from))
                .and_then(|row| row.get(usize::from(to)))
                .copied()
                .unwrap_or(false)
        };
        let background = self.background();
        if opaque(background) {
            return None;
        }
        // Opaque pixels, and any other whose material nothing reweights out of to the
        // background while the background reweights into it (a non-scattering pixel in a
        // scattering background: its crossings are reweighted, unbiased, noisier).
        let filled = |m: u16| {
            m != background
                && (opaque(m) || (!reweights(m, background) && reweights(background, m)))
        };
        let mut map = self.current.clone();
        let mut pixels = Vec::new();
        for (p, m) in map.iter_mut().enumerate() {
            if filled(*m) {
                pixels.push((p as u32, *m));
                *m = background;
            }
        }
        (!pixels.is_empty()).then_some(Base {
            map,
            current: Change { pixels },
        })
    }

    /// Whether every pixel of `change` can be reweighted from the current map.
    pub(super) fn can_reweight(&self, change: &Change) -> bool {
        self.can_reweight_on(&self.current, change)
    }

    /// Whether every pixel of `change` can be reweighted from `map`.
    pub(super) fn can_reweight_on(&self, map: &[u16], change: &Change) -> bool {
        change.pixels.iter().all(|&(p, d)| {
            let from = map[p as usize];
            self.reweightable
                .get(usize::from(from))
                .and_then(|row| row.get(usize::from(d)))
                .copied()
                .unwrap_or(false)
        })
    }

    /// Whether a differential sweep rendering `map` leaves `change` (of the current map `M`,
    /// written as `relative`, the same change of `map`) out: a recolour (several pixels set to
    /// one material) whose photon weights are too noisy to estimate
    /// ([`Refinement::spread_of`] above [`MAX_SPREAD`]), or that `map` cannot reweight. A
    /// direct render of each would cost a full render apiece; direct screening tries them all.
    pub(super) fn left_out(&self, change: &Change, map: &[u16], relative: &Change) -> bool {
        let recolour =
            change.pixels.len() >= 2 && change.pixels.iter().all(|&(_, d)| d == change.pixels[0].1);
        recolour
            && (!self.can_reweight_on(map, relative) || self.spread_of(map, relative) > MAX_SPREAD)
    }

    /// How noisy the photon weights of `change` of `map` are: 1 for a change of at most one
    /// inexact pixel (single pixels are always reweighted: rendering each directly is what
    /// differential screening saves), else the noisiest pixel's spread to the power √k for
    /// its `k` inexact pixels (a photon crossing a region of `k` pixels crosses about √k).
    pub fn spread_of(&self, map: &[u16], change: &Change) -> f64 {
        let spreads: Vec<f64> = change
            .pixels
            .iter()
            .map(|&(p, d)| {
                let from = map[p as usize];
                self.spread
                    .get(usize::from(from))
                    .and_then(|row| row.get(usize::from(d)))
                    .copied()
                    .unwrap_or(1.0)
            })
            .filter(|&s| s > 1.0)
            .collect();
        if spreads.len() <= 1 {
            return 1.0;
        }
        let worst = spreads.iter().copied().fold(1.0, f64::max);
        worst.powf((spreads.len() as f64).sqrt())
    }
}
