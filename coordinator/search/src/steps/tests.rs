//! The step driver's bounded score cache: forgetting earlier stages' scores changes neither the
//! result nor what is counted, alone or restored from stored scores mid-run.

use super::*;
use crate::machine::{Candidates, ChangeScore, Photons, Race, SearchConfig, Seeding};
use crate::refine::{RefineConfig, Screen};
use scatterfarm_model::material::builtin_material;
use scatterfarm_model::MaterialTable;

const GRID: u32 = 4;

fn geometry() -> Geometry {
    Geometry::new(10.0, GRID, 4, 1).unwrap()
}

/// Racing levels with early step 2 and common random numbers per level, then a differential
/// refinement with one escalation: every kind of stage the search has.
fn fresh() -> Search {
    let mut table = MaterialTable::default();
    for n in ["moderate", "opaque", "mild"] {
        table.push(n, builtin_material(n).unwrap());
    }
    let refine = RefineConfig {
        photons: 200,
        confirm_photons: 400,
        z: 3.0,
        max_sweeps: 8,
        move_objects: true,
        screen: Screen::Differential,
        changes_per_render: 5,
        escalations: 1,
        recolour_regions: true,
        pixel_mm: 1.0,
        direct_photons: None,
        retest_z: None,
        swap_pixels: false,
        blocks: false,
        simplify_z: None,
        grow_objects: crate::refine::Growth::Off,
        grow_trial_z: None,
    };
    let config = SearchConfig {
        grid: GRID,
        permutations: 3,
        seed: 5,
        candidates: Candidates::Dictionary(vec![0, 1, 2]),
        seeding: Seeding::PerLevel,
        photons: Photons {
            per_level: vec![40, 80],
            race: Some(Race { share: 0.5, z: 1.0 }),
            rescore: Some(120),
        },
        early_step2: true,
        tie_z: 0.0,
        tiebreak: None,
        refine: Some(refine),
        coarse_levels: None,
    };
    Search::new(config, table).unwrap()
}

fn truth() -> Vec<u16> {
    let mut t = vec![0u16; (GRID * GRID) as usize];
    t[5] = 2;
    t[6] = 2;
    t[10] = 1;
    t
}

/// A likelihood-like score: minus the wrong pixels over 8 blocks, plus noise of the seed that
/// pairs on one seed cancel; a differential request's changes scored as their maps would be.
fn score(assignment: &[u16], seed: u64, photons: u32, changes: &[Change]) -> Score {
    let truth = truth();
    let blocks_of = |a: &[u16]| -> Vec<f64> {
        let wrong = a.iter().zip(&truth).filter(|(a, b)| a != b).count() as f64;
        (0..8)
            .map(|b| -wrong + (seed % 89) as f64 * 0.1 + f64::from(b) * 0.01)
            .collect()
    };
    let blocks = blocks_of(assignment);
    let changes = changes
        .iter()
        .map(|c| {
            let mut a = assignment.to_vec();
            for &(p, m) in &c.pixels {
                a[p as usize] = m;
            }
            let blocks = blocks_of(&a);
            Some(ChangeScore {
                value: blocks.iter().sum(),
                blocks,
            })
        })
        .collect();
    Score {
        value: blocks.iter().sum(),
        std_error: 0.5 + 40.0 / f64::from(photons),
        secondary: None,
        blocks,
        changes,
    }
}

/// What one run did: the result, what it counted, the scores it held at the end, the oldest
/// step it held a score of after a step moved on, against that stage's start (the worst
/// case), and every score it made (what a farm's store holds), in order.
struct Run {
    search: Search,
    used: Consumption,
    cached: usize,
    oldest_behind: u64,
    stored: Vec<NewScore>,
}

/// Drives `search` through `steps` to the end with the scripted scorer, stopping after
/// `stop_after` submitted steps when given.
fn drive(
    mut search: Search,
    mut steps: Steps,
    mut used: Consumption,
    stop_after: Option<usize>,
) -> Run {
    let mut stored = Vec::new();
    let mut oldest_behind = 0;
    let mut submitted = 0;
    loop {
        match steps.next(&mut search, &mut used).unwrap() {
            Next::Finished => break,
            Next::Submitted => {
                submitted += 1;
                if stop_after == Some(submitted) {
                    break;
                }
            }
            Next::Render(groups) => {
                for g in groups {
                    if !g.changes.is_empty() {
                        let item = &g.items[0];
                        let s = score(&item.item.assignment, item.item.seed, g.photons, &g.changes);
                        stored.extend(steps.keep_differential(&search, g.photons, item, s));
                        continue;
                    }
                    let scores: Vec<Score> = g
                        .items
                        .iter()
                        .map(|i| score(&i.item.assignment, i.item.seed, g.photons, &[]))
                        .collect();
                    let g_ = geometry();
                    let counts = vec![CountMatrix::zeros(g_.sources(), g_.bins()); g.items.len()];
                    stored.extend(
                        steps
                            .keep(&search, g.photons, &g.items, counts, scores)
                            .unwrap(),
                    );
                }
            }
        }
        if let Some(oldest) = steps.scores.values().map(|(_, step)| *step).min() {
            oldest_behind = oldest_behind.max(search.stage_start().saturating_sub(oldest));
        }
    }
    Run {
        search,
        used,
        cached: steps.cached(),
        oldest_behind,
        stored,
    }
}

fn steps_knowing(stored: &[NewScore]) -> Steps {
    Steps::new(
        geometry(),
        "test-engine",
        stored.iter().map(|(id, s, step)| (*id, (s.clone(), *step))),
    )
}

#[test]
fn forgetting_earlier_stages_changes_nothing_counted_and_bounds_the_cache() {
    let bounded = drive(fresh(), steps_knowing(&[]), Consumption::default(), None);
    let mut every = steps_knowing(&[]);
    every.keep_every_stage();
    let unbounded = drive(fresh(), every, Consumption::default(), None);
    assert!(bounded.search.is_finished());
    assert_eq!(bounded.search.result(), unbounded.search.result());
    assert_eq!(bounded.search.result().unwrap().assignment, truth());
    assert_eq!(
        bounded.used, unbounded.used,
        "no forgotten score was needed again"
    );
    assert!(
        bounded.used.requests > bounded.used.renders,
        "the cache answered requests: {:?}",
        bounded.used
    );
    let stages = bounded.search.refinement().unwrap().history().len() + 2;
    assert!(
        stages >= 4,
        "levels and several sweeps ran: {stages} stages"
    );
    assert_eq!(
        bounded.oldest_behind, 0,
        "no score of an earlier stage is held once a step of the next one is answered"
    );
    assert!(unbounded.oldest_behind > 0);
    assert!(
        bounded.cached * 2 < unbounded.cached,
        "the cache ended with {} scores, against {} kept",
        bounded.cached,
        unbounded.cached
    );
}

#[test]
fn a_driver_restored_from_every_stored_score_counts_what_one_left_alone_does() {
    let alone = drive(fresh(), steps_knowing(&[]), Consumption::default(), None);
    let steps_total = {
        let mut n = 0;
        let mut probe = drive(fresh(), steps_knowing(&[]), Consumption::default(), Some(1));
        while !probe.search.is_finished() {
            n += 1;
            probe = drive(
                probe.search,
                steps_knowing(&probe.stored),
                probe.used,
                Some(1),
            );
        }
        n
    };
    assert!(steps_total > 10, "{steps_total} steps");
    // A checkpoint every few steps; the store holds the scores of a few steps after it (the
    // coordinator stops between its last checkpoint and later results), as a farm's does.
    for checkpoint_at in [1, steps_total / 3, steps_total / 2, steps_total - 2] {
        let before = drive(
            fresh(),
            steps_knowing(&[]),
            Consumption::default(),
            Some(checkpoint_at),
        );
        let checkpoint: Search =
            serde_json::from_str(&serde_json::to_string(&before.search).unwrap()).unwrap();
        let ahead = drive(
            before.search,
            steps_knowing(&before.stored),
            before.used,
            Some(3),
        );
        let mut stored = before.stored;
        stored.extend(ahead.stored);
        let restored = drive(checkpoint, steps_knowing(&stored), before.used, None);
        assert_eq!(restored.search.result(), alone.search.result());
        assert_eq!(
            restored.used, alone.used,
            "restored after step {checkpoint_at}"
        );
    }
}
