//! The CPU engine's differential render (`docs/model.md`, "Differential renders"): the plain
//! render of a map, traced with a per-pixel tally, and for every detected photon its weight
//! under each change of the map.
//!
//! A photon's path density under a material, for the part of the path inside one pixel, is
//! `exp(−σt·L) · Π σs·p(θ_k)` over its `n` scattering collisions there (analog absorption: a
//! collision scatters with probability σs/σt, and a detected photon was never absorbed), with
//! `L` its path length in the pixel and `p` the flatland HG density
//! `p_g(θ) = (1 − g²) / (2π (1 + g² − 2g cos θ))`. The weight of the photon under a change is the
//! product over the changed pixels of the ratio of these densities, new over old:
//!
//! `w = Π_pixels (σs_d/σs_m)^n · exp(−(σt_d − σt_m)·L) · Π_k p_d(θ_k)/p_m(θ_k)`,
//!
//! with two exact special cases: an opaque candidate gives weight 0 to every photon that
//! entered the pixel, and a non-scattering candidate gives weight 0 to a photon that collided
//! there and `exp(−(σt_d − σt_m)·L)` to one that crossed without a collision. Changes that open
//! paths the render never samples are not reweighted ([`change_is_reweightable`]).
//!
//! Counts of the map are those of a plain render (the same stream, the same fate per photon);
//! each change's result is `Σ (w − 1)` per (source, bin), tasks per source in fixed order, so a
//! seed fixes every number.

use crate::rng::PhotonStream;
use crate::transport::{trace_photon_tallied, Fate, Medium, Tally};
use rayon::prelude::*;
use scatterfarm_model::differential::{
    change_is_reweightable, differential_batch, Change, DifferentialOutput,
};
use scatterfarm_model::engine::{CountMatrix, EngineError};
use scatterfarm_model::{Geometry, Material, PhotonRange, RenderItem};

/// Most changes one differential render estimates.
pub const MAX_CHANGES: usize = 8192;

/// A photon's path in each pixel it touched: cells in the order first touched.
struct PathTally {
    /// Per cell: path length, scattering collisions, and per table material `Σ ln(1 + g² −
    /// 2g cos θ)` over the collisions.
    length: Vec<f64>,
    collisions: Vec<u32>,
    phase: Vec<f64>,
    touched: Vec<usize>,
    seen: Vec<bool>,
    /// `g` of each table material.
    g: Vec<f64>,
}

impl PathTally {
    fn new(cells: usize, table: &[Material]) -> PathTally {
        PathTally {
            length: vec![0.0; cells],
            collisions: vec![0; cells],
            phase: vec![0.0; cells * table.len()],
            touched: Vec::new(),
            seen: vec![false; cells],
            g: table.iter().map(|m| m.g).collect(),
        }
    }

    fn clear(&mut self) {
        let d = self.g.len();
        for &c in &self.touched {
            self.length[c] = 0.0;
            self.collisions[c] = 0;
            self.phase[c * d..(c + 1) * d].fill(0.0);
            self.seen[c] = false;
        }
        self.touched.clear();
    }

    #[inline]
    fn touch(&mut self, cell: usize) {
        if !self.seen[cell] {
            self.seen[cell] = true;
            self.touched.push(cell);
        }
    }
}

impl Tally for PathTally {
    const ACTIVE: bool = true;

    #[inline]
    fn length(&mut self, cell: usize, length: f64) {
        self.touch(cell);
        self.length[cell] += length;
    }

    #[inline]
    fn scatter(&mut self, cell: usize, cos: f64) {
        self.touch(cell);
        self.collisions[cell] += 1;
        let d = self.g.len();
        for (k, &g) in self.g.iter().enumerate() {
            self.phase[cell * d + k] += (1.0 + g * g - 2.0 * g * cos).ln();
        }
    }
}

/// One pixel of one change, as the weight needs it.
#[derive(Debug, Clone, Copy)]
struct Factor {
    change: usize,
    from: usize,
    to: usize,
}

/// Per material: what its weight factors need.
#[derive(Debug, Clone, Copy)]
struct Physics {
    sigma_t: f64,
    ln_sigma_s: f64,
    /// `ln(1 − g²)`.
    ln_norm: f64,
    scatters: bool,
    opaque: bool,
}

impl Physics {
    fn of(m: &Material) -> Physics {
        Physics {
            sigma_t: if m.is_opaque() { 0.0 } else { m.sigma_t() },
            ln_sigma_s: m.sigma_s.ln(),
            ln_norm: (1.0 - m.g * m.g).ln(),
            scatters: m.sigma_s > 0.0,
            opaque: m.is_opaque(),
        }
    }
}

/// The log-weight factor of a pixel going `from` → `to` for a photon with `length`, `n`
/// collisions and phase sums `phase` there; `None` for weight 0.
#[inline]
fn log_factor(
    physics: &[Physics],
    g: &[f64],
    f: Factor,
    length: f64,
    n: u32,
    phase: &[f64],
) -> Option<f64> {
    let (a, b) = (physics[f.from], physics[f.to]);
    if b.opaque {
        return None;
    }
    let path = -(b.sigma_t - a.sigma_t) * length;
    if !b.scatters {
        return (n == 0).then_some(path);
    }
    if n == 0 {
        return Some(path);
    }
    let nf = f64::from(n);
    let mut lw = path + nf * (b.ln_sigma_s - a.ln_sigma_s);
    if g[f.from] != g[f.to] {
        lw += nf * (b.ln_norm - a.ln_norm) - (phase[f.to] - phase[f.from]);
    }
    Some(lw)
}

/// 64-bit words of a bitset over `n` changes.
fn n_words(n: usize) -> usize {
    n.div_ceil(64)
}

/// Renders `item` differentially: see the module documentation.
pub(super) fn render_differential(
    geometry: Geometry,
    table: &[Material],
    item: &RenderItem,
    photons: PhotonRange,
    changes: &[Change],
) -> Result<DifferentialOutput, EngineError> {
    differential_batch(geometry, table, item, photons, changes, MAX_CHANGES)?;
    let pixels = geometry.pixels();
    let medium = Medium::new(geometry, table, &item.assignment);
    let supported: Vec<bool> = changes
        .iter()
        .map(|c| change_is_reweightable(table, &item.assignment, c))
        .collect();
    let physics: Vec<Physics> = table.iter().map(Physics::of).collect();
    // Per cell, the factors of the changes that touch it; the changes that make it opaque
    // (weight 0 for a photon that entered it) as a bitset instead, since a filled base's
    // changes nearly all make the same cells opaque (`docs/model.md`, "The filled base").
    let words = n_words(changes.len());
    let mut by_cell: Vec<Vec<Factor>> = vec![Vec::new(); pixels];
    let mut opaque_by_cell: Vec<Vec<u64>> = vec![Vec::new(); pixels];
    for (k, c) in changes.iter().enumerate() {
        if !supported[k] {
            continue;
        }
        for &(p, d) in &c.pixels {
            let from = usize::from(item.assignment[p as usize]);
            let to = usize::from(d);
            if from == to {
                continue;
            }
            let cell = medium.cell_of_pixel(p as usize);
            if physics[to].opaque {
                let mask = &mut opaque_by_cell[cell];
                if mask.is_empty() {
                    mask.resize(words, 0);
                }
                mask[k / 64] |= 1 << (k % 64);
            } else {
                by_cell[cell].push(Factor {
                    change: k,
                    from,
                    to,
                });
            }
        }
    }
    let g: Vec<f64> = table.iter().map(|m| m.g).collect();
    let sources = geometry.sources();
    let bins = geometry.bins();
    let n_changes = changes.len();
    let rays: Vec<_> = (0..sources).map(|i| geometry.source_ray(i)).collect();
    let d = table.len();
    // One task per source: its row of counts, its rows of every change's deltas (change-major).
    let rows: Vec<(Vec<u32>, Vec<f64>, u64)> = (0..sources)
        .into_par_iter()
        .map(|source| {
            let mut counts = vec![0u32; bins];
            let mut deltas = vec![0.0f64; n_changes * bins];
            let mut tally = PathTally::new(pixels, table);
            let mut log_w = vec![0.0f64; n_changes];
            let mut zero = vec![false; n_changes];
            let mut hit: Vec<usize> = Vec::new();
            let mut hit_seen = vec![false; n_changes];
            let mut opaque_hit = vec![0u64; words];
            let mut scatters = 0u64;
            for photon in u64::from(photons.first)..photons.end() {
                tally.clear();
                let mut rng = PhotonStream::new(item.seed, source as u32, photon as u32);
                let trace = trace_photon_tallied(&medium, &rays[source], &mut rng, &mut tally);
                scatters += u64::from(trace.scatters);
                let Fate::Exited(bin) = trace.fate else {
                    continue;
                };
                counts[bin] += 1;
                let mut entered_opaque = false;
                for &cell in &tally.touched {
                    let mask = &opaque_by_cell[cell];
                    if !mask.is_empty() {
                        entered_opaque = true;
                        for (h, m) in opaque_hit.iter_mut().zip(mask) {
                            *h |= m;
                        }
                    }
                    let (length, n) = (tally.length[cell], tally.collisions[cell]);
                    let phase = &tally.phase[cell * d..(cell + 1) * d];
                    for &f in &by_cell[cell] {
                        if !hit_seen[f.change] {
                            hit_seen[f.change] = true;
                            hit.push(f.change);
                        }
                        match log_factor(&physics, &g, f, length, n, phase) {
                            Some(lw) => log_w[f.change] += lw,
                            None => zero[f.change] = true,
                        }
                    }
                }
                // Changes that made a cell the photon entered opaque: weight 0.
                if entered_opaque {
                    for (i, h) in opaque_hit.iter_mut().enumerate() {
                        let mut bits = std::mem::take(h);
                        while bits != 0 {
                            let k = i * 64 + bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            zero[k] = true;
                            if !hit_seen[k] {
                                hit_seen[k] = true;
                                hit.push(k);
                            }
                        }
                    }
                }
                for &k in &hit {
                    let w = if zero[k] { 0.0 } else { log_w[k].exp() };
                    deltas[k * bins + bin] += w - 1.0;
                    log_w[k] = 0.0;
                    zero[k] = false;
                    hit_seen[k] = false;
                }
                hit.clear();
            }
            (counts, deltas, scatters)
        })
        .collect();
    let mut counts = CountMatrix::zeros(sources, bins);
    let mut deltas: Vec<Option<Vec<f64>>> = supported
        .iter()
        .map(|&s| s.then(|| vec![0.0; sources * bins]))
        .collect();
    let mut scatter_events = 0;
    for (source, (row, row_deltas, s)) in rows.into_iter().enumerate() {
        counts.counts[source * bins..(source + 1) * bins].copy_from_slice(&row);
        for (k, delta) in deltas.iter_mut().enumerate() {
            if let Some(delta) = delta {
                delta[source * bins..(source + 1) * bins]
                    .copy_from_slice(&row_deltas[k * bins..(k + 1) * bins]);
            }
        }
        scatter_events += s;
    }
    Ok(DifferentialOutput {
        counts,
        deltas,
        scatter_events,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reweighting_check::{self, apply, geometry, map, table};
    use crate::CpuEngine;
    use scatterfarm_model::Engine;

    fn plain(assignment: &[u16], seed: u64, photons: u32) -> CountMatrix {
        reweighting_check::plain(&CpuEngine::new(), assignment, seed, photons)
    }

    fn differential(
        assignment: &[u16],
        seed: u64,
        photons: u32,
        changes: &[Change],
    ) -> DifferentialOutput {
        CpuEngine::new()
            .render_differential(
                geometry(),
                &table(),
                &RenderItem {
                    assignment: assignment.to_vec(),
                    seed,
                },
                PhotonRange::first_n(photons),
                changes,
            )
            .unwrap()
    }

    #[test]
    fn the_rendered_map_counts_equal_a_plain_render_bit_for_bit() {
        let a = map();
        let changes = [Change {
            pixels: vec![(0, 1)],
        }];
        let d = differential(&a, 3, 500, &changes);
        assert_eq!(d.counts, plain(&a, 3, 500));
        // Split photon ranges add up to the whole.
        let item = RenderItem {
            assignment: a.clone(),
            seed: 3,
        };
        let engine = CpuEngine::new();
        let part = |first, count| {
            engine
                .render_differential(
                    geometry(),
                    &table(),
                    &item,
                    PhotonRange { first, count },
                    &changes,
                )
                .unwrap()
        };
        let mut halves = part(0, 200);
        halves.add(&part(200, 300)).unwrap();
        assert_eq!(halves.counts, d.counts);
        let (x, y) = (
            halves.deltas[0].as_ref().unwrap(),
            d.deltas[0].as_ref().unwrap(),
        );
        assert!(x.iter().zip(y).all(|(p, q)| (p - q).abs() < 1e-9));
    }

    #[test]
    fn an_opaque_candidate_is_exact() {
        // Photons that never enter the pixel follow the same stream in both maps; those that
        // enter it are absorbed by the opaque one. Only the homogeneous-block shortcut, which
        // the change reshapes, may part a rare photon by rounding.
        let a = map();
        let change = Change {
            pixels: vec![(6, 4)],
        };
        let d = differential(&a, 11, 2000, std::slice::from_ref(&change));
        let direct = plain(&apply(&a, &change), 11, 2000);
        let delta = d.deltas[0].as_ref().unwrap();
        let mut off = 0.0;
        for (i, x) in delta.iter().enumerate() {
            let est = f64::from(d.counts.counts[i]) + x;
            off += (est - f64::from(direct.counts[i])).abs();
        }
        let changed: f64 = delta.iter().map(|x| x.abs()).sum();
        assert!(changed > 1000.0, "the change removes photons: {changed}");
        assert!(
            off <= 1e-3 * direct.total() as f64,
            "{off} photons apart of {}",
            direct.total()
        );
    }

    #[test]
    fn unsupported_changes_are_flagged() {
        let mut a = map();
        a[0] = 4; // opaque
        a[3] = 5; // transmissive
        let changes = [
            Change {
                pixels: vec![(0, 0)],
            },
            Change {
                pixels: vec![(3, 1)],
            },
            Change {
                pixels: vec![(3, 4)],
            },
            Change {
                pixels: vec![(1, 5)],
            },
        ];
        let d = differential(&a, 1, 50, &changes);
        let flags: Vec<bool> = d.deltas.iter().map(Option::is_some).collect();
        assert_eq!(flags, [false, false, true, true]);
        let bad = CpuEngine::new().render_differential(
            geometry(),
            &table(),
            &RenderItem {
                assignment: a,
                seed: 1,
            },
            PhotonRange::first_n(10),
            &[Change {
                pixels: vec![(99, 0)],
            }],
        );
        assert!(bad.is_err());
    }

    /// σs, σa and g changes of one pixel, of two and of a 2×2 block: per source, the
    /// reweighted totals over four seeds agree with direct renders of the changed map on four
    /// other seeds (χ² about one per source, from the seeds' own spread), where the unchanged
    /// map's totals do not.
    #[test]
    fn reweighted_counts_agree_with_direct_renders() {
        let a = map();
        let photons = 10_000;
        let cases = [
            // σs, σa and g: mild → moderate (0.5 → 0.6, 0.03 → 0.01, g 0.6 → 0.75), 2×2.
            Change {
                pixels: vec![(5, 0), (6, 0), (9, 0), (10, 0)],
            },
            // g alone: 0.75 → 0.5 on one pixel.
            Change {
                pixels: vec![(0, 6)],
            },
            // Two pixels at once: back → uniform and moderate → mild.
            Change {
                pixels: vec![(15, 3), (14, 1)],
            },
        ];
        let seeds = [31u64, 32, 33, 34];
        let renders: Vec<DifferentialOutput> = seeds
            .iter()
            .map(|&s| differential(&a, s, photons, &cases))
            .collect();
        let direct: Vec<Vec<_>> = cases
            .iter()
            .map(|change| {
                let changed = apply(&a, change);
                seeds
                    .iter()
                    .map(|&s| plain(&changed, s + 1000, photons))
                    .collect()
            })
            .collect();
        crate::reweighting_check::assert_reweighting_agrees(&geometry(), &renders, &direct);
    }
}
