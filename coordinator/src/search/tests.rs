//! The step logic against scripted scorers, seeding, and restoring from checkpoints.

use super::*;
use scatterfarm_worker::material::builtin_material;

fn table(names: &[&str]) -> MaterialTable {
    let mut t = MaterialTable::default();
    for n in names {
        t.push(*n, builtin_material(n).unwrap());
    }
    t
}

fn search(grid: u32, permutations: u32, seed: u64, dictionary: Vec<u16>) -> Search {
    let names = ["moderate", "opaque", "mild"];
    let config = SearchConfig {
        grid,
        permutations,
        seed,
        candidates: Candidates::Dictionary(dictionary),
        seeding: Seeding::PerRequest,
    };
    Search::new(config, table(&names)).unwrap()
}

/// Scores an assignment by how many pixels match `truth`, plus a small deterministic term from
/// the render seed (as Monte Carlo noise would).
fn truth_scorer(truth: &[u16]) -> impl Fn(&RenderRequest) -> f64 + '_ {
    move |r| {
        let hits = r
            .assignment
            .iter()
            .zip(truth)
            .filter(|(a, b)| a == b)
            .count() as f64;
        hits + (r.seed % 1000) as f64 * 1e-4
    }
}

fn run_to_end(s: &mut Search, score: &dyn Fn(&RenderRequest) -> f64) -> Vec<Vec<RenderRequest>> {
    let mut history = Vec::new();
    while !s.is_finished() {
        let pending = s.pending().to_vec();
        let scores: Vec<f64> = pending.iter().map(score).collect();
        history.push(pending);
        s.submit(&scores).unwrap();
    }
    history
}

#[test]
fn level_zero_renders_each_material_and_keeps_the_best_earliest_on_ties() {
    let mut s = search(2, 1, 1, vec![0, 1, 2]);
    assert_eq!(s.pending().len(), 3);
    assert_eq!(s.pending()[1].assignment, vec![1; 4]);
    s.submit(&[0.5, 0.7, 0.7]).unwrap();
    assert_eq!(s.levels()[0].assignment, vec![1; 4]);
    assert_eq!(s.levels()[0].score, 0.7);
}

#[test]
fn first_region_runs_no_step_two_and_later_regions_run_both() {
    let mut s = search(2, 1, 1, vec![0, 1]);
    s.submit(&[1.0, 0.0]).unwrap();
    // Level 1, i = 1: step 1 only, from M⁰ (all material 0).
    assert_eq!(s.pending().len(), 2);
    let r1 = s.pending()[0]
        .assignment
        .iter()
        .zip(&s.pending()[1].assignment)
        .position(|(a, b)| a != b)
        .unwrap();
    assert_eq!(s.pending()[1].assignment[r1], 1);
    s.submit(&[0.1, 0.9]).unwrap(); // π₁ ← material 1
                                    // i = 2: step 1 from M¹ (region π₁ = 1) and step 2 from M⁰.
    let p = s.pending().to_vec();
    assert_eq!(p.len(), 4);
    assert_eq!(p[0].assignment[r1], 1, "step 1 starts from M¹");
    assert_eq!(p[2].assignment[r1], 0, "step 2 starts from M⁰");
}

#[test]
fn step_two_winning_resets_to_m0_and_ties_go_to_step_two() {
    let mut s = search(2, 1, 1, vec![0, 1]);
    s.submit(&[1.0, 0.0]).unwrap();
    let r1 = {
        let p = s.pending();
        p[0].assignment
            .iter()
            .zip(&p[1].assignment)
            .position(|(a, b)| a != b)
            .unwrap()
    };
    s.submit(&[0.1, 0.9]).unwrap(); // M¹ has region π₁ = 1
    let p = s.pending().to_vec();
    let r2 = p[2]
        .assignment
        .iter()
        .zip(&p[3].assignment)
        .position(|(a, b)| a != b)
        .unwrap();
    // Step 2's material 1 wins: M² = M⁰ with π₂ ← 1, so π₁ is back to 0.
    s.submit(&[0.2, 0.3, 0.1, 0.8]).unwrap();
    let p = s.pending().to_vec();
    assert_eq!(
        p[0].assignment[r1], 0,
        "step 2's win reset π₁ to M⁰'s material"
    );
    assert_eq!(p[0].assignment[r2], 1);
    // A tie between the steps' bests goes to step 2 as well.
    let r3 = p[2]
        .assignment
        .iter()
        .zip(&p[3].assignment)
        .position(|(a, b)| a != b)
        .unwrap();
    s.submit(&[0.5, 0.4, 0.5, 0.1]).unwrap();
    let p = s.pending().to_vec();
    assert_eq!(p[0].assignment[r2], 0, "the tie went to step 2 (from M⁰)");
    assert_eq!(p[0].assignment[r3], 0);
}

#[test]
fn the_best_permutation_wins_and_ties_go_to_the_earlier() {
    for (finals, expected) in [
        ([0.3, 0.9, 0.5], 1u32),
        ([0.6, 0.6, 0.2], 0),
        ([0.1, 0.2, 0.3], 2),
    ] {
        let mut s = search(2, 3, 5, vec![0, 1]);
        s.submit(&[1.0, 0.0]).unwrap();
        for final_score in finals {
            // Four regions: the last step's winning score is the permutation's score.
            s.submit(&[0.1, 0.0]).unwrap();
            s.submit(&[0.1, 0.0, 0.0, 0.0]).unwrap();
            s.submit(&[0.1, 0.0, 0.0, 0.0]).unwrap();
            s.submit(&[final_score, 0.0, 0.0, 0.0]).unwrap();
        }
        assert!(s.is_finished());
        let result = s.result().unwrap();
        assert_eq!(result.permutation, expected, "{finals:?}");
        assert_eq!(result.score, finals[expected as usize]);
    }
}

#[test]
fn a_perfect_scorer_finds_the_truth() {
    let truth: Vec<u16> = vec![0, 0, 1, 1, 0, 2, 2, 1, 0, 0, 0, 1, 2, 0, 0, 0];
    let mut s = search(4, 2, 3, vec![0, 1, 2]);
    let history = run_to_end(&mut s, &truth_scorer(&truth));
    assert_eq!(s.result().unwrap().assignment, truth);
    // Level 0: 3; level 1: 2 × (3 + 3·6); level 2: 2 × (3 + 15·6).
    let renders: usize = history.iter().map(Vec::len).sum();
    assert_eq!(renders, 3 + 2 * (3 + 3 * 6) + 2 * (3 + 15 * 6));
    assert_eq!(s.progress().renders_total, renders as u64);
    // Request indices run 0, 1, 2, … and seeds follow them.
    for (n, r) in history.iter().flatten().enumerate() {
        assert_eq!(r.index, n as u64);
        assert_eq!(r.seed, seeds::derive(3, Stream::Render(n as u64)));
    }
}

#[test]
fn the_seed_fixes_the_permutations() {
    let orders = |seed| {
        let mut s = search(4, 3, seed, vec![0, 1]);
        let truth = vec![0u16; 16];
        let history = run_to_end(&mut s, &truth_scorer(&truth));
        history
            .into_iter()
            .flatten()
            .map(|r| r.assignment)
            .collect::<Vec<_>>()
    };
    assert_eq!(orders(7), orders(7));
    assert_ne!(orders(7), orders(8));
}

#[test]
fn restoring_at_every_step_boundary_ends_in_the_same_result() {
    let truth: Vec<u16> = vec![0, 1, 1, 0, 0, 2, 2, 1, 0, 0, 0, 1, 2, 0, 1, 0];
    let scorer = truth_scorer(&truth);
    let mut alone = search(4, 2, 11, vec![0, 1, 2]);
    let history = run_to_end(&mut alone, &scorer);

    let mut s = search(4, 2, 11, vec![0, 1, 2]);
    let mut replay = Vec::new();
    while !s.is_finished() {
        // Checkpoint and restore before every step.
        let json = serde_json::to_string(&s).unwrap();
        s = serde_json::from_str(&json).unwrap();
        let pending = s.pending().to_vec();
        let scores: Vec<f64> = pending.iter().map(&scorer).collect();
        replay.push(pending);
        s.submit(&scores).unwrap();
    }
    assert_eq!(replay, history);
    assert_eq!(s.result(), alone.result());
    assert_eq!(s.levels(), alone.levels());
}

#[test]
fn unknown_materials_grow_the_table_and_keep_inherited_candidates() {
    let config = SearchConfig {
        grid: 2,
        permutations: 1,
        seed: 2,
        candidates: Candidates::Random {
            per_level: 3,
            bounds: Bounds::default(),
        },
        seeding: Seeding::PerRequest,
    };
    let mut s = Search::new(config, MaterialTable::default()).unwrap();
    assert_eq!(s.table().len(), 3);
    for m in s.materials() {
        assert!(
            (0.0..=1.0).contains(&m.sigma_s)
                && (0.0..=0.03).contains(&m.sigma_a)
                && (0.0..=1.0).contains(&m.g)
        );
    }
    s.submit(&[0.1, 0.5, 0.2]).unwrap();
    // Level 1: three new materials plus the one inherited from M⁰.
    assert_eq!(s.table().len(), 6);
    assert_eq!(s.pending().len(), 4);
    assert!(s
        .pending()
        .iter()
        .any(|r| r.assignment.iter().all(|&m| m == 1)));
}

#[test]
fn bad_configurations_and_submissions_are_refused() {
    let t = table(&["moderate"]);
    let bad = |grid, permutations, candidates| {
        Search::new(
            SearchConfig {
                grid,
                permutations,
                seed: 1,
                candidates,
                seeding: Seeding::PerRequest,
            },
            t.clone(),
        )
        .err()
    };
    assert_eq!(
        bad(3, 1, Candidates::Dictionary(vec![0])),
        Some(SearchError::Grid(3))
    );
    assert_eq!(
        bad(4, 0, Candidates::Dictionary(vec![0])),
        Some(SearchError::Permutations)
    );
    assert_eq!(
        bad(4, 1, Candidates::Dictionary(vec![])),
        Some(SearchError::EmptyDictionary)
    );
    assert_eq!(
        bad(4, 1, Candidates::Dictionary(vec![4])),
        Some(SearchError::DictionaryIndex(4))
    );
    let mut s = search(2, 1, 1, vec![0, 1]);
    assert_eq!(
        s.submit(&[1.0]),
        Err(SearchError::ScoreCount {
            expected: 2,
            got: 1
        })
    );
    assert!(matches!(
        s.submit(&[f64::NAN, 1.0]),
        Err(SearchError::ScoreNaN(_))
    ));
}

#[test]
fn per_level_seeding_shares_one_seed_per_level() {
    let mut s = Search::new(
        SearchConfig {
            grid: 4,
            permutations: 2,
            seed: 9,
            candidates: Candidates::Dictionary(vec![0, 1]),
            seeding: Seeding::PerLevel,
        },
        table(&["moderate", "opaque"]),
    )
    .unwrap();
    let mut seen: Vec<(u32, u64)> = Vec::new();
    while !s.is_finished() {
        let level = s.progress().level;
        let seeds: Vec<u64> = s.pending().iter().map(|r| r.seed).collect();
        assert!(seeds.iter().all(|&x| x == seeds[0]));
        assert_eq!(seeds[0], seeds::derive(9, Stream::LevelRender(level)));
        seen.push((level, seeds[0]));
        let scores: Vec<f64> = (0..seeds.len()).map(|i| i as f64).collect();
        s.submit(&scores).unwrap();
    }
    let mut levels: Vec<u64> = seen.iter().map(|&(_, x)| x).collect();
    levels.dedup();
    assert_eq!(levels.len(), 3, "one seed per level: {seen:?}");
}
