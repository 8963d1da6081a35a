//! Tests of the GPU engine's differential render: its counts are a plain render's, a seed fixes
//! every bit however the work is cut, exact cases are exact, and reweighted estimates agree with
//! direct renders of the changed maps (χ² from the seeds' own spread, as the CPU engine's test).

use super::engine::Tuning;
use super::tests::engine_or_skip;
use super::GpuEngine;
use crate::reweighting_check::{self, apply, geometry, map, table};
use scatterfarm_model::differential::{Change, DifferentialOutput};
use scatterfarm_model::engine::{CountMatrix, Engine, EngineError, RenderBatch};
use scatterfarm_model::{PhotonRange, RenderItem};

fn item(assignment: &[u16], seed: u64) -> RenderItem {
    RenderItem {
        assignment: assignment.to_vec(),
        seed,
    }
}

fn plain(gpu: &GpuEngine, assignment: &[u16], seed: u64, photons: u32) -> CountMatrix {
    reweighting_check::plain(gpu, assignment, seed, photons)
}

fn differential(
    gpu: &GpuEngine,
    assignment: &[u16],
    seed: u64,
    photons: PhotonRange,
    changes: &[Change],
) -> DifferentialOutput {
    gpu.render_differential(
        geometry(),
        &table(),
        &item(assignment, seed),
        photons,
        changes,
    )
    .unwrap()
}

fn change(pixels: &[(u32, u16)]) -> Change {
    Change {
        pixels: pixels.to_vec(),
    }
}

#[test]
fn counts_are_a_plain_renders_and_a_seed_fixes_every_bit_however_the_work_is_cut() {
    let Some(mut gpu) = engine_or_skip() else {
        return;
    };
    assert_eq!(gpu.renders_differentially(), !gpu.adapter().is_cpu());
    let a = map();
    let changes = [
        change(&[(0, 1)]),
        change(&[(5, 0), (6, 0), (9, 0), (10, 0)]),
        change(&[(15, 6)]),
        change(&[(3, 4)]),
    ];
    let photons = PhotonRange {
        first: 3,
        count: 3000,
    };
    let reference = differential(&gpu, &a, 7, photons, &changes);
    let items = [item(&a, 7)];
    let direct = gpu
        .render(&RenderBatch {
            geometry: geometry(),
            table: &table(),
            items: &items,
            photons,
        })
        .unwrap()
        .remove(0);
    assert_eq!(reference.counts, direct.counts);
    assert_eq!(reference.scatter_events, direct.scatter_events);
    let moved: f64 = reference
        .deltas
        .iter()
        .flatten()
        .map(|d| d.iter().map(|x| x.abs()).sum::<f64>())
        .sum();
    assert!(moved > 100.0, "the changes move the counts: {moved}");
    let default = gpu.tuning.clone();
    let bins = geometry().bins() as u64;
    for tuning in [
        Tuning {
            per_invocation: Some(1),
            photons_per_dispatch: 500,
            ..default.clone()
        },
        Tuning {
            per_invocation: Some(1000),
            ..default.clone()
        },
        // Five sources per submission (the deltas of four changes, 8 bytes each).
        Tuning {
            max_buffer_bytes: 5 * 4 * bins * 8,
            per_invocation: Some(37),
            ..default.clone()
        },
    ] {
        gpu.tuning = tuning.clone();
        let got = differential(&gpu, &a, 7, photons, &changes);
        assert_eq!(
            got.counts, reference.counts,
            "counts change with {tuning:?}"
        );
        assert_eq!(got.scatter_events, reference.scatter_events);
        for (k, (x, y)) in got.deltas.iter().zip(&reference.deltas).enumerate() {
            let (x, y) = (x.as_ref().unwrap(), y.as_ref().unwrap());
            let apart: Vec<(usize, f64, f64)> = x
                .iter()
                .zip(y)
                .enumerate()
                .filter(|(_, (p, q))| p != q)
                .map(|(i, (p, q))| (i, *p, *q))
                .collect();
            assert!(
                apart.is_empty(),
                "change {k}'s estimates change with {tuning:?}: {} of {} apart, first {:?}",
                apart.len(),
                x.len(),
                &apart[..apart.len().min(5)]
            );
        }
    }
    gpu.tuning = default;
    let other = differential(&gpu, &a, 8, photons, &changes);
    assert_ne!(other.deltas, reference.deltas);
}

#[test]
fn an_opaque_candidate_matches_a_direct_render_on_the_same_seed() {
    let Some(gpu) = engine_or_skip() else { return };
    let a = map();
    let c = change(&[(6, 4)]);
    let d = differential(
        &gpu,
        &a,
        11,
        PhotonRange::first_n(4000),
        std::slice::from_ref(&c),
    );
    let direct = plain(&gpu, &apply(&a, &c), 11, 4000);
    let delta = d.deltas[0].as_ref().unwrap();
    let mut off = 0.0;
    for (i, x) in delta.iter().enumerate() {
        off += (f64::from(d.counts.counts[i]) + x - f64::from(direct.counts[i])).abs();
    }
    let changed: f64 = delta.iter().map(|x| x.abs()).sum();
    assert!(changed > 2000.0, "the change removes photons: {changed}");
    // Weight 0 for each photon that entered the pixel, exactly; only the blocks the change
    // reshapes may part a rare photon by f32 rounding.
    assert!(
        off <= 0.01 * changed,
        "{off} photons apart, of {changed} removed"
    );
}

#[test]
fn unsupported_changes_are_flagged_and_bad_ones_refused() {
    let Some(gpu) = engine_or_skip() else { return };
    let mut a = map();
    a[0] = 4; // opaque
    a[3] = 5; // transmissive
    let changes = [
        change(&[(0, 0)]),
        change(&[(3, 1)]),
        change(&[(3, 4)]),
        change(&[(1, 5)]),
    ];
    let d = differential(&gpu, &a, 1, PhotonRange::first_n(50), &changes);
    let flags: Vec<bool> = d.deltas.iter().map(Option::is_some).collect();
    assert_eq!(flags, [false, false, true, true]);
    let bad = gpu.render_differential(
        geometry(),
        &table(),
        &item(&a, 1),
        PhotonRange::first_n(10),
        &[change(&[(99, 0)])],
    );
    assert!(
        matches!(bad, Err(EngineError::MaterialIndex { .. })),
        "{bad:?}"
    );
}

/// σs, σa and g changes of a 2×2 block, of one pixel and of two: per source, the reweighted
/// totals over four seeds agree with direct GPU renders of the changed map on four other seeds,
/// where the unchanged map's totals do not.
#[test]
fn reweighted_counts_agree_with_direct_renders() {
    let Some(gpu) = engine_or_skip() else { return };
    let a = map();
    let photons = 10_000;
    let cases = [
        change(&[(5, 0), (6, 0), (9, 0), (10, 0)]),
        change(&[(0, 6)]),
        change(&[(15, 3), (14, 1)]),
    ];
    let seeds = [31u64, 32, 33, 34];
    let renders: Vec<DifferentialOutput> = seeds
        .iter()
        .map(|&s| differential(&gpu, &a, s, PhotonRange::first_n(photons), &cases))
        .collect();
    let direct: Vec<Vec<_>> = cases
        .iter()
        .map(|c| {
            let changed = apply(&a, c);
            seeds
                .iter()
                .map(|&s| plain(&gpu, &changed, s + 1000, photons))
                .collect()
        })
        .collect();
    crate::reweighting_check::assert_reweighting_agrees(&geometry(), &renders, &direct);
}
