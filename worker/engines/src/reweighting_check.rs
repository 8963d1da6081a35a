//! What both engines' differential tests share (test builds only): the scene they render, and
//! the check that reweighted counts of a change agree with direct renders of the changed map,
//! where the unchanged map's do not.

use scatterfarm_model::differential::{Change, DifferentialOutput};
use scatterfarm_model::engine::{Engine, RenderBatch};
use scatterfarm_model::material::builtin_material;
use scatterfarm_model::{CountMatrix, Geometry, Material, PhotonRange, RenderItem};

/// A 4×4 grid of 16 mm with 8 positions × 3 directions.
pub(crate) fn geometry() -> Geometry {
    Geometry::new(16.0, 4, 8, 3).unwrap()
}

/// `moderate`, `mild`, `back`, `uniform`, opaque, transmissive, and `moderate` with g 0.5.
pub(crate) fn table() -> Vec<Material> {
    ["moderate", "mild", "back", "uniform"]
        .iter()
        .map(|n| builtin_material(n).unwrap())
        .chain([
            Material::OPAQUE,
            Material::TRANSMISSIVE,
            // `moderate` with another g.
            Material::new(0.6, 0.01, 0.5).unwrap(),
        ])
        .collect()
}

/// A plain render by `engine` of `assignment` over [`geometry`] and [`table`]: photons
/// [0, `photons`) of seed `seed`.
pub(crate) fn plain(
    engine: &dyn Engine,
    assignment: &[u16],
    seed: u64,
    photons: u32,
) -> CountMatrix {
    let table = table();
    let items = [RenderItem {
        assignment: assignment.to_vec(),
        seed,
    }];
    engine
        .render(&RenderBatch {
            geometry: geometry(),
            table: &table,
            items: &items,
            photons: PhotonRange::first_n(photons),
        })
        .unwrap()
        .remove(0)
        .counts
}

/// A 2×2 block of `mild` in a `moderate` 4×4 grid, and one `back` pixel.
pub(crate) fn map() -> Vec<u16> {
    let mut a = vec![0u16; 16];
    for p in [5, 6, 9, 10] {
        a[p] = 1;
    }
    a[15] = 2;
    a
}

/// `assignment` with `change` made.
pub(crate) fn apply(assignment: &[u16], change: &Change) -> Vec<u16> {
    let mut a = assignment.to_vec();
    for &(p, d) in &change.pixels {
        a[p as usize] = d;
    }
    a
}

/// Per source: the sum of `row(source × bins + bin)` over the bins.
fn per_source(geometry: &Geometry, row: &dyn Fn(usize) -> f64) -> Vec<f64> {
    let bins = geometry.bins();
    (0..geometry.sources())
        .map(|s| (0..bins).map(|b| row(s * bins + b)).sum())
        .collect()
}

/// Per source: the mean over the runs and the variance of that mean.
fn moments(runs: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    let k = runs.len() as f64;
    (0..runs[0].len())
        .map(|s| {
            let mean = runs.iter().map(|r| r[s]).sum::<f64>() / k;
            let var = runs.iter().map(|r| (r[s] - mean).powi(2)).sum::<f64>() / (k - 1.0);
            (mean, var / k)
        })
        .unzip()
}

/// χ² over the sources between the means of `x` and of `y`.
fn chi2(x: &[Vec<f64>], y: &[Vec<f64>]) -> f64 {
    let (mx, vx) = moments(x);
    let (my, vy) = moments(y);
    (0..mx.len())
        .map(|s| (mx[s] - my[s]).powi(2) / (vx[s] + vy[s]).max(1e-9))
        .sum()
}

/// Asserts that, per change `k`, the per-source totals of `renders` (differential renders of
/// one map on several seeds) reweighted by their deltas agree with `direct[k]` (direct renders
/// of the changed map on as many other seeds), and that the unchanged totals are told apart.
pub(crate) fn assert_reweighting_agrees(
    geometry: &Geometry,
    renders: &[DifferentialOutput],
    direct: &[Vec<CountMatrix>],
) {
    let base: Vec<Vec<f64>> = renders
        .iter()
        .map(|r| per_source(geometry, &|i| f64::from(r.counts.counts[i])))
        .collect();
    let n = geometry.sources() as f64;
    for (k, direct) in direct.iter().enumerate() {
        let est: Vec<Vec<f64>> = renders
            .iter()
            .map(|r| {
                let delta = r.deltas[k].as_ref().expect("the change is reweightable");
                per_source(geometry, &|i| f64::from(r.counts.counts[i]) + delta[i])
            })
            .collect();
        let direct: Vec<Vec<f64>> = direct
            .iter()
            .map(|c| per_source(geometry, &|i| f64::from(c.counts[i])))
            .collect();
        let (agree, apart) = (chi2(&est, &direct), chi2(&base, &direct));
        // With four seeds a term is a squared t with 6 degrees of freedom: mean 1.5.
        assert!(
            agree < 3.0 * n,
            "change {k}: χ² {agree:.1} over {n} sources"
        );
        assert!(
            apart > 3.0 * agree && apart > 6.0 * n,
            "change {k}: the unchanged map is told apart (χ² {apart:.1}; reweighted {agree:.1})"
        );
    }
}
