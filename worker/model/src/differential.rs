//! Differential renders (`docs/model.md`, "Differential renders"): one render of a map `M` that
//! also estimates the counts of many changes of `M` from the same photons (perturbation Monte
//! Carlo). A detected photon's weight under a change is a known function of what it did inside
//! the changed pixels; [`reweightable`] says which material changes that function covers.
//!
//! The types here are what an engine speaks: the changes to estimate ([`Change`]) and what comes
//! back ([`DifferentialOutput`]): the plain counts of `M` (bit-identical to a plain render of
//! `M` with the same seed and photons) and, per change, the sum over detected photons of
//! `w − 1` in each (source, bin), so that a change's estimated counts are `counts + delta`.

use crate::engine::{CountMatrix, EngineError};
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
}
