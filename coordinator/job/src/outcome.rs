//! A reconstruction's outputs (`report.json`, `materials.npy`, `materials.json`,
//! `reconstruction.png`, `maps.png`) and the measures against a known truth.

use crate::observation::write_atomically;
use crate::picture;
use anyhow::{ensure, Context, Result};
use image::{Rgb, RgbImage};
use ndarray::Array2;
use ndarray_npy::WriteNpyExt;
use scatterfarm_model::{Material, MaterialTable, Scene};
use serde::Serialize;
use std::path::Path;

/// An assignment at `from` × `from` spread to `to` × `to` (each region fills its pixels).
pub fn upsample(assignment: &[u16], from: usize, to: usize) -> Vec<u16> {
    let f = to / from.max(1);
    (0..to * to)
        .map(|i| assignment[(i / to / f) * from + (i % to) / f])
        .collect()
}

/// The reconstruction's materials at the truth's resolution.
fn materials_at(
    assignment: &[u16],
    grid: usize,
    table: &MaterialTable,
    to: usize,
) -> Vec<Material> {
    let phys = table.physics();
    upsample(assignment, grid, to)
        .into_iter()
        .map(|i| phys[i as usize])
        .collect()
}

/// Fraction of the truth's pixels whose material equals the reconstruction's.
pub fn pixel_accuracy(
    assignment: &[u16],
    grid: usize,
    table: &MaterialTable,
    truth: &Scene,
) -> f64 {
    let n = truth.geometry.grid as usize;
    let recon = materials_at(assignment, grid, table, n);
    let same = recon
        .iter()
        .enumerate()
        .filter(|(i, m)| **m == truth.material_at(i / n, i % n))
        .count();
    same as f64 / (n * n) as f64
}

/// `Σ (Δσs² + Δσa² + Δg²)` over the truth's pixels, an opaque σa counting as 1 mm⁻¹.
pub fn material_sse(assignment: &[u16], grid: usize, table: &MaterialTable, truth: &Scene) -> f64 {
    let n = truth.geometry.grid as usize;
    let recon = materials_at(assignment, grid, table, n);
    recon
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let t = truth.material_at(i / n, i % n);
            (m.sigma_s - t.sigma_s).powi(2)
                + (m.sigma_a_for_error() - t.sigma_a_for_error()).powi(2)
                + (m.g - t.g).powi(2)
        })
        .sum()
}

/// Writes `materials.npy` (N×N `uint16`) and `materials.json` (the index → material table).
pub fn write_materials(
    dir: &Path,
    assignment: &[u16],
    grid: usize,
    table: &MaterialTable,
) -> Result<()> {
    let array = Array2::from_shape_vec((grid, grid), assignment.to_vec())
        .context("assignment is not grid × grid")?;
    write_atomically(&dir.join("materials.npy"), |w| Ok(array.write_npy(w)?))?;
    #[derive(Serialize)]
    struct Entry<'a> {
        index: usize,
        name: &'a str,
        #[serde(flatten)]
        material: Material,
    }
    let entries: Vec<Entry> = table
        .materials
        .iter()
        .enumerate()
        .map(|(index, m)| Entry {
            index,
            name: &m.name,
            material: m.material,
        })
        .collect();
    let json = serde_json::to_vec_pretty(&serde_json::json!({ "materials": entries }))?;
    write_atomically(&dir.join("materials.json"), |w| Ok(w.write_all(&json)?))
}

/// Writes any serializable report as pretty JSON.
pub fn write_json(path: &Path, value: &impl Serialize) -> Result<()> {
    let json = serde_json::to_vec_pretty(value)?;
    write_atomically(path, |w| Ok(w.write_all(&json)?))
}

/// `reconstruction.png`: truth | reconstruction | wrong pixels marked, or the reconstruction alone.
pub fn write_reconstruction_png(
    path: &Path,
    assignment: &[u16],
    grid: usize,
    table: &MaterialTable,
    truth: Option<&Scene>,
) -> Result<()> {
    let img = match truth {
        None => {
            let map = picture::material_map(assignment, grid, table, picture::cell_size(grid));
            picture::panels_with_legend(&[("reconstruction", map)], table)
        }
        Some(truth) => {
            let n = truth.geometry.grid as usize;
            // One legend for both: the search's table plus truth materials it lacks.
            let mut legend = table.clone();
            let truth_index: Vec<u16> = truth
                .table
                .materials
                .iter()
                .map(|m| {
                    match legend
                        .materials
                        .iter()
                        .position(|l| l.material == m.material)
                    {
                        Some(i) => i as u16,
                        None => legend.push(m.name.clone(), m.material),
                    }
                })
                .collect();
            let truth_map: Vec<u16> = truth
                .assignment
                .iter()
                .map(|&i| truth_index[i as usize])
                .collect();
            let recon = upsample(assignment, grid, n);
            let cell = picture::cell_size(n);
            let truth_img = picture::material_map(&truth_map, n, &legend, cell);
            let recon_img = picture::material_map(&recon, n, &legend, cell);
            let mut wrong = recon_img.clone();
            let phys = legend.physics();
            for (i, (&r, &t)) in recon.iter().zip(&truth_map).enumerate() {
                let (y0, x0) = ((i / n) as u32 * cell, (i % n) as u32 * cell);
                let bad = phys[r as usize] != phys[t as usize];
                for y in y0..y0 + cell {
                    for x in x0..x0 + cell {
                        let Rgb([cr, cg, cb]) = *wrong.get_pixel(x, y);
                        let px = if bad {
                            // A red cross over the wrong pixel.
                            let (dx, dy) = (x - x0, y - y0);
                            if dx == dy || dx + dy + 1 == cell || dx == 0 || dy == 0 {
                                Rgb([230, 0, 0])
                            } else {
                                Rgb([255, 160, 160])
                            }
                        } else {
                            Rgb([
                                (cr as u32 * 2 / 5 + 153) as u8,
                                (cg as u32 * 2 / 5 + 153) as u8,
                                (cb as u32 * 2 / 5 + 153) as u8,
                            ])
                        };
                        wrong.put_pixel(x, y, px);
                    }
                }
            }
            picture::panels_with_legend(
                &[
                    ("truth", truth_img),
                    ("reconstruction", recon_img),
                    ("wrong pixels", wrong),
                ],
                &legend,
            )
        }
    };
    picture::save_png(&img, path)
}

/// `maps.png`: σs, σa and g of the reconstruction side by side (viridis, each on its own
/// range; opaque pixels are black in the σa map).
pub fn write_maps_png(
    path: &Path,
    assignment: &[u16],
    grid: usize,
    table: &MaterialTable,
) -> Result<()> {
    ensure!(
        assignment.len() == grid * grid,
        "assignment is not grid × grid"
    );
    let phys = table.physics();
    let cell = picture::cell_size(grid);
    let panel = |f: &dyn Fn(&Material) -> Option<f64>| -> (RgbImage, f64, f64) {
        let values: Vec<Option<f64>> = assignment.iter().map(|&i| f(&phys[i as usize])).collect();
        let lo = values
            .iter()
            .flatten()
            .cloned()
            .fold(f64::INFINITY, f64::min);
        let hi = values
            .iter()
            .flatten()
            .cloned()
            .fold(f64::NEG_INFINITY, f64::max);
        let span = if hi > lo { hi - lo } else { 1.0 };
        let mut img = RgbImage::new(grid as u32 * cell, grid as u32 * cell);
        for (i, v) in values.iter().enumerate() {
            let colour = match v {
                Some(v) => {
                    let c = colorous::VIRIDIS.eval_continuous(((v - lo) / span).clamp(0.0, 1.0));
                    Rgb([c.r, c.g, c.b])
                }
                None => Rgb([0, 0, 0]),
            };
            let (y0, x0) = ((i / grid) as u32 * cell, (i % grid) as u32 * cell);
            for y in y0..y0 + cell {
                for x in x0..x0 + cell {
                    img.put_pixel(x, y, colour);
                }
            }
        }
        (
            img,
            if lo.is_finite() { lo } else { 0.0 },
            if hi.is_finite() { hi } else { 0.0 },
        )
    };
    let (s, s_lo, s_hi) = panel(&|m| Some(m.sigma_s));
    let (a, a_lo, a_hi) = panel(&|m| (!m.is_opaque()).then_some(m.sigma_a));
    let (g, g_lo, g_hi) = panel(&|m| Some(m.g));
    let titles = [
        format!("sigma_s {s_lo:.3}..{s_hi:.3}"),
        format!("sigma_a {a_lo:.3}..{a_hi:.3}"),
        format!("g {g_lo:.2}..{g_hi:.2}"),
    ];
    let img = picture::panels_with_legend(
        &[
            (titles[0].as_str(), s),
            (titles[1].as_str(), a),
            (titles[2].as_str(), g),
        ],
        &MaterialTable::default(),
    );
    picture::save_png(&img, path)
}

/// Everything a reconstruction's outputs are made from.
pub struct Summary<'a> {
    pub config: &'a crate::report::Configuration,
    pub truth: Option<&'a Scene>,
    pub search: &'a scatterfarm_search::Search,
    /// The map to write (the final result, or the current best of a running search).
    pub assignment: &'a [u16],
    pub similarity: f64,
    /// ε of every budget (empty before calibration).
    pub epsilons: &'a std::collections::BTreeMap<u32, f64>,
    pub used: scatterfarm_search::driver::Consumption,
    /// Photons engines ran (all sources): search, target and calibration renders,
    /// recomputation included.
    pub photons_simulated: u64,
    pub wall_seconds: f64,
    pub engine: String,
    pub reproducible: bool,
}

/// Writes `report.json`, `materials.npy`, `materials.json`, `reconstruction.png` and `maps.png`
/// into `out` (created if missing) and returns the report.
pub fn write_outputs(out: &Path, s: &Summary<'_>) -> Result<crate::report::Report> {
    use crate::report::{LevelReport, Report};
    let grid = s.config.grid as usize;
    let table = s.search.table();
    let measures = |a: &[u16]| {
        s.truth.map(|t| {
            (
                pixel_accuracy(a, grid, table, t),
                material_sse(a, grid, table, t),
            )
        })
    };
    let measures_of = |a: &[u16]| (a.len() == grid * grid).then(|| measures(a)).flatten();
    let levels = s
        .search
        .levels()
        .iter()
        .map(|l| {
            let m = measures(&l.assignment);
            LevelReport {
                level: l.level,
                similarity: l.score,
                pixel_accuracy: m.map(|m| m.0),
                material_sse: m.map(|m| m.1),
            }
        })
        .collect();
    let refinement = s
        .search
        .refinement()
        .map(|r| r.history())
        .unwrap_or_default()
        .iter()
        .map(|h| crate::report::SweepReport {
            sweep: h.sweep,
            tried: h.tried,
            reweighted: h.reweighted,
            candidates: h.candidates,
            changed: h.changed,
            similarity: h.score,
            pixel_accuracy: (h.map.len() == grid * grid)
                .then(|| measures(&h.map).map(|m| m.0))
                .flatten(),
            growth: h.growth,
            trial_kept: h.trial_kept,
            grown_z: h.grown_z,
        })
        .collect();
    let convergence = convergence(scatterfarm_search::convergence::curve(s.search), &|a| {
        measures_of(a).map(|m| m.0)
    });
    let m = measures(s.assignment);
    let report = Report {
        pixel_accuracy: m.map(|m| m.0),
        material_sse: m.map(|m| m.1),
        similarity: s.similarity,
        epsilon: s
            .epsilons
            .get(&s.search.config().photons.level(u32::MAX))
            .copied(),
        epsilons: s.epsilons.clone(),
        requests: s.used.requests,
        renders: s.used.renders,
        batches: s.used.batches,
        photons: s.used.photons,
        photons_simulated: s.photons_simulated,
        wall_seconds: s.wall_seconds,
        engine: s.engine.clone(),
        seed: s.config.seed,
        reproducible: s.reproducible,
        configuration: s.config.clone(),
        levels,
        refinement,
        convergence,
    };
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write_materials(out, s.assignment, grid, table)?;
    write_reconstruction_png(
        &out.join("reconstruction.png"),
        s.assignment,
        grid,
        table,
        s.truth,
    )?;
    write_maps_png(&out.join("maps.png"), s.assignment, grid, table)?;
    if let Some(img) = crate::convergence_plot::png(&report.convergence) {
        picture::save_png(&img, &out.join("convergence.png"))?;
    }
    write_json(&out.join("report.json"), &report)?;
    Ok(report)
}

/// The convergence curve `points` (of [`scatterfarm_search::convergence::curve`]) as the
/// report has it, each point's accuracy from `accuracy` (of its map).
pub fn convergence(
    points: Vec<scatterfarm_search::convergence::Point>,
    accuracy: &dyn Fn(&[u16]) -> Option<f64>,
) -> Vec<crate::report::ConvergenceReport> {
    use scatterfarm_search::convergence::Stage;
    points
        .into_iter()
        .map(|p| {
            let (stage, index) = match p.stage {
                Stage::Level(l) => ("level", l),
                Stage::Sweep(n) => ("sweep", n),
            };
            let spent = p.spent.unwrap_or(scatterfarm_search::convergence::Spent {
                requests: 0,
                renders: 0,
                photons: 0,
            });
            crate::report::ConvergenceReport {
                stage: stage.into(),
                index,
                requests: spent.requests,
                renders: spent.renders,
                photons: spent.photons,
                score: p.score,
                pixel_accuracy: accuracy(&p.map),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_model::builtin;

    #[test]
    fn measures_against_the_truth_at_its_resolution() {
        let truth = builtin::scene("fig7b").unwrap().unwrap();
        // A perfect reconstruction at full resolution.
        let perfect = pixel_accuracy(&truth.assignment, 16, &truth.table, &truth);
        assert_eq!(perfect, 1.0);
        assert_eq!(
            material_sse(&truth.assignment, 16, &truth.table, &truth),
            0.0
        );
        // All background at grid 1: accuracy is the background's share; each opaque pixel costs
        // Δσs² + Δσa² + Δg² with opaque σa = 1.
        let background = vec![0u16];
        let opaque_pixels = truth.assignment.iter().filter(|&&i| i == 1).count();
        let acc = pixel_accuracy(&background, 1, &truth.table, &truth);
        assert!((acc - (256 - opaque_pixels) as f64 / 256.0).abs() < 1e-12);
        let m = scatterfarm_model::material::builtin_material("moderate").unwrap();
        let per_pixel = m.sigma_s.powi(2) + (m.sigma_a - 1.0).powi(2) + m.g.powi(2);
        let sse = material_sse(&background, 1, &truth.table, &truth);
        assert!((sse - per_pixel * opaque_pixels as f64).abs() < 1e-9);
        assert_eq!(upsample(&[1, 2, 3, 4], 2, 4)[..8], [1, 1, 2, 2, 1, 1, 2, 2]);
    }
}
