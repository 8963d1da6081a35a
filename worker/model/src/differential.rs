//! Differential renders (`docs/model.md`, "Differential renders"): one render of a map `M` that
//! also estimates the counts of many changes of `M` from the same photons (perturbation Monte
//! Carlo). A detected photon's weight under a change is a known function of what it did inside
//! the changed pixels; [`reweightable`] says which material changes that function covers.
//!
//! The types here are what an engine speaks: the changes to estimate ([`Change`]) and what comes
//! back ([`DifferentialOutput`]): the plain counts of `M` (bit-identical to a plain render of
//! `M` with the same seed and photons) and, per change, the sum over detected photons of
//! `w − 1` in each (source, bin), so that a change's estimated counts are `counts + delta`.

use crate::engine::{
    validate_batch, CountMatrix, Engine, EngineError, PhotonRange, RenderBatch, RenderItem,
};
use crate::geometry::Geometry;
use crate::material::Material;
use serde::{Deserialize, Serialize};

/// One change of a map: the pixels it sets (row-major indices, row 0 at the top) and their new
/// material indices.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Change {
    pub pixels: Vec<(u32, u16)>,
}

/// Whether a photon weight estimates a pixel going from `from` to `to` without bias: the paths
/// the change opens must already be sampled under `from`. Not covered: out of an opaque pixel
/// (no photon crosses it), from a non-scattering pixel to a scattering one (no photon collides
/// there), and a change of `g` to or from a phase function that is a delta (`|g| = 1`).
pub fn reweightable(from: &Material, to: &Material) -> bool {
    if from == to {
        return true;
    }
    if from.is_opaque() {
        return to.is_opaque();
    }
    if to.is_opaque() || to.sigma_s <= 0.0 {
        return true;
    }
    if from.sigma_s <= 0.0 {
        return false;
    }
    from.g == to.g || (from.g.abs() < 1.0 && to.g.abs() < 1.0)
}

/// How noisy a photon weight is for a pixel going from `from` to `to`, for a photon that
/// crosses the pixel (of side `pixel_mm`): the weight's second moment over its mean squared,
/// so `1` for an exact weight (no change, or an opaque `to`) and `∞` where the change is not
/// [`reweightable`]. Collisions in a pixel are taken as a Poisson count with mean
/// `σs_from · pixel_mm`, each multiplying the weight by `r · p_to(θ)/p_from(θ)` with
/// `r = σs_to/σs_from`, so the ratio is `exp(σs_from · pixel_mm · (r²·Q − 2r + 1))` with
/// `Q = ∫ p_to²/p_from dθ` (`docs/model.md`, "Differential renders"). An effective sample
/// size is the photons that cross the pixel divided by this.
pub fn weight_spread(from: &Material, to: &Material, pixel_mm: f64) -> f64 {
    if from == to || (to.is_opaque() && !from.is_opaque()) {
        return 1.0;
    }
    if !reweightable(from, to) {
        return f64::INFINITY;
    }
    if from.sigma_s <= 0.0 {
        // Non-scattering into non-scattering: only the crossing's attenuation changes.
        return 1.0;
    }
    let r = to.sigma_s / from.sigma_s;
    let q = if to.sigma_s > 0.0 && to.g != from.g {
        phase_second_moment(from.g, to.g)
    } else {
        1.0
    };
    (from.sigma_s * pixel_mm * (r * r * q - 2.0 * r + 1.0)).exp()
}

/// `∫ p_to(θ)² / p_from(θ) dθ` over the circle, for flatland Henyey-Greenstein densities
/// `p_g(θ) = (1 − g²) / (2π(1 + g² − 2g·cos θ))` with `|g| < 1` (midpoint rule, 1 024 points:
/// the integrand is smooth and periodic, so the rule converges geometrically).
fn phase_second_moment(from_g: f64, to_g: f64) -> f64 {
    let p = |g: f64, t: f64| {
        (1.0 - g * g) / (std::f64::consts::TAU * (1.0 + g * g - 2.0 * g * t.cos()))
    };
    const POINTS: usize = 1024;
    let h = std::f64::consts::TAU / POINTS as f64;
    (0..POINTS)
        .map(|i| {
            let t = -std::f64::consts::PI + (i as f64 + 0.5) * h;
            p(to_g, t).powi(2) / p(from_g, t)
        })
        .sum::<f64>()
        * h
}

/// Whether every pixel of `change` of `assignment` over `table` is [`reweightable`].
pub fn change_is_reweightable(table: &[Material], assignment: &[u16], change: &Change) -> bool {
    change.pixels.iter().all(|&(p, d)| {
        let (Some(&m), Some(to)) = (assignment.get(p as usize), table.get(usize::from(d))) else {
            return false;
        };
        table
            .get(usize::from(m))
            .is_some_and(|from| reweightable(from, to))
    })
}

/// The one-item batch a differential render of `item` traces, once every engine's checks
/// pass: those of any batch ([`validate_batch`]) and of the changes ([`validate_changes`]).
pub fn differential_batch<'a>(
    geometry: Geometry,
    table: &'a [Material],
    item: &'a RenderItem,
    photons: PhotonRange,
    changes: &[Change],
    max_changes: usize,
) -> Result<RenderBatch<'a>, EngineError> {
    let batch = RenderBatch {
        geometry,
        table,
        items: std::slice::from_ref(item),
        photons,
    };
    validate_batch(&batch)?;
    validate_changes(&geometry, table, changes, max_changes)?;
    Ok(batch)
}

/// What every engine checks of a differential render's changes: at most `max` of them, every
/// pixel on the grid and every material in the table.
pub fn validate_changes(
    geometry: &Geometry,
    table: &[Material],
    changes: &[Change],
    max: usize,
) -> Result<(), EngineError> {
    if changes.len() > max {
        return Err(EngineError::Unsupported(format!(
            "{} changes in one differential render; at most {max}",
            changes.len()
        )));
    }
    let pixels = geometry.pixels();
    for (k, c) in changes.iter().enumerate() {
        for &(p, d) in &c.pixels {
            if p as usize >= pixels || usize::from(d) >= table.len() {
                return Err(EngineError::MaterialIndex {
                    item: k,
                    index: d,
                    table: table.len(),
                });
            }
        }
    }
    Ok(())
}

/// A differential render's result.
#[derive(Debug, Clone, PartialEq)]
pub struct DifferentialOutput {
    /// The plain counts of the rendered map.
    pub counts: CountMatrix,
    /// Per change, in order: `Σ (w − 1)` per (source, bin), row-major like `counts`; `None` for
    /// a change that is not [`change_is_reweightable`].
    pub deltas: Vec<Option<Vec<f64>>>,
    /// Scattering events along all paths.
    pub scatter_events: u64,
}

impl DifferentialOutput {
    /// Adds another partial render of the same map and changes (a later photon range).
    pub fn add(&mut self, other: &DifferentialOutput) -> Result<(), EngineError> {
        self.counts.add(&other.counts)?;
        if other.deltas.len() != self.deltas.len() {
            return Err(EngineError::ShapeMismatch {
                expected: (self.deltas.len(), self.counts.counts.len()),
                got: (other.deltas.len(), other.counts.counts.len()),
            });
        }
        for (a, b) in self.deltas.iter_mut().zip(&other.deltas) {
            match (a, b) {
                (Some(a), Some(b)) if a.len() == b.len() => {
                    for (x, y) in a.iter_mut().zip(b) {
                        *x += *y;
                    }
                }
                (None, None) => {}
                (a, b) => {
                    return Err(EngineError::ShapeMismatch {
                        expected: (1, a.as_ref().map_or(0, |v| v.len())),
                        got: (1, b.as_ref().map_or(0, |v| v.len())),
                    })
                }
            }
        }
        self.scatter_events += other.scatter_events;
        Ok(())
    }
}

/// Photons per source per chunk of a differential render, in process and on the farm alike. A
/// chunk's fixed cost is its delta arrays (changes × observations: allocated, zeroed, filled and
/// summed once per chunk), so chunks are large: with a sweep's 256 single-pixel changes of
/// fig7a at 32 × 5 sources, a render of 102 400 photons per source cost 5.3 plain renders in
/// chunks of 512 photons and 1.8 in chunks of 65 536 (`scatterfarm bench tallies`). Memory does
/// not grow with the chunk.
pub const CHUNK_PHOTONS: u32 = 65_536;

/// How many photons per source a chunked render traces, and how many per chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PhotonChunks {
    /// Photons per source in all: the render covers photons `[0, photons)`.
    pub photons: u32,
    /// Photons per source in each chunk (0 is taken as 1).
    pub chunk: u32,
}

/// Renders `item` differentially over photons `[0, photons)` in chunks of `chunk` photons per
/// source, summing the chunks' outputs in order, and calls `on_chunk` with each chunk's photons
/// per source. The coordinator's in-process driver and a farm worker both render this way, so
/// the same chunk size gives bit-identical counts and deltas wherever the render runs.
pub fn render_in_chunks(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    item: &RenderItem,
    photons: PhotonChunks,
    changes: &[Change],
    on_chunk: &mut dyn FnMut(u32),
) -> Result<DifferentialOutput, EngineError> {
    let PhotonChunks { photons, chunk } = photons;
    let chunk = chunk.max(1);
    let mut total: Option<DifferentialOutput> = None;
    let mut first = 0u32;
    while first < photons {
        let count = chunk.min(photons - first);
        let part = engine.render_differential(
            geometry,
            table,
            item,
            PhotonRange { first, count },
            changes,
        )?;
        match total.as_mut() {
            Some(t) => t.add(&part)?,
            None => total = Some(part),
        }
        on_chunk(count);
        first += count;
    }
    total.ok_or(EngineError::Unsupported(
        "a differential render of no photons".into(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::builtin_material;

    #[test]
    fn which_changes_reweight() {
        let m = |n| builtin_material(n).unwrap();
        assert!(reweightable(&m("moderate"), &m("mild")));
        assert!(reweightable(&m("moderate"), &m("back")));
        assert!(reweightable(&m("moderate"), &Material::OPAQUE));
        assert!(reweightable(&m("moderate"), &Material::TRANSMISSIVE));
        assert!(!reweightable(&Material::OPAQUE, &m("moderate")));
        assert!(!reweightable(&Material::OPAQUE, &Material::TRANSMISSIVE));
        assert!(!reweightable(&Material::TRANSMISSIVE, &m("mild")));
        assert!(reweightable(&Material::TRANSMISSIVE, &Material::OPAQUE));
        let delta = Material::new(0.5, 0.0, 1.0).unwrap();
        assert!(!reweightable(&m("mild"), &delta));
        assert!(reweightable(&delta, &Material::new(0.7, 0.1, 1.0).unwrap()));
        let table = [m("moderate"), Material::OPAQUE];
        let change = Change {
            pixels: vec![(0, 1), (1, 0)],
        };
        assert!(!change_is_reweightable(&table, &[0, 1], &change));
        assert!(change_is_reweightable(&table, &[0, 0], &change));
        assert!(!change_is_reweightable(&table, &[0], &change));
    }

    #[test]
    fn weight_spread_grows_with_the_change() {
        let m = |n| builtin_material(n).unwrap();
        let same = weight_spread(&m("moderate"), &m("moderate"), 1.0);
        assert_eq!(same, 1.0);
        assert_eq!(weight_spread(&m("moderate"), &Material::OPAQUE, 1.0), 1.0);
        assert!(weight_spread(&Material::OPAQUE, &m("moderate"), 1.0).is_infinite());
        // Similar materials give nearly exact weights; a forward to a backward phase function
        // gives weights whose spread is hundreds per crossing.
        let mild = weight_spread(&m("moderate"), &m("mild"), 1.0);
        let back = weight_spread(&m("moderate"), &m("back"), 1.0);
        assert!(mild > 1.0 && mild < 1.2, "{mild}");
        assert!(back > 100.0, "{back}");
        // A larger pixel holds more collisions.
        assert!(weight_spread(&m("moderate"), &m("back"), 2.0) > back);
        // The phase function's second moment of a density against itself is 1, and the
        // midpoint rule integrates a density to 1.
        assert!((phase_second_moment(0.3, 0.3) - 1.0).abs() < 1e-9);
    }
}
