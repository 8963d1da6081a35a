//! The step logic against scripted scorers, seeding, and restoring from checkpoints.

use super::*;
use crate::refine::RefineConfig;
use scatterfarm_model::material::builtin_material;

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
        photons: Photons::uniform(100),
        early_step2: false,
        tie_z: 0.0,
        tiebreak: None,
        refine: None,
        coarse_levels: None,
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
        s.check_consistent().unwrap();
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
fn inconsistent_stored_states_are_refused() {
    let truth: Vec<u16> = vec![0, 1, 1, 0, 0, 2, 2, 1, 0, 0, 0, 1, 2, 0, 1, 0];
    let scorer = truth_scorer(&truth);
    let mut s = search(4, 2, 11, vec![0, 1, 2]);
    // Into level 1, where the state has maps, candidates and a region order.
    while s.progress().level < 1 {
        let scores: Vec<f64> = s.pending().iter().map(&scorer).collect();
        s.submit(&scores).unwrap();
    }
    let good: serde_json::Value = serde_json::to_value(&s).unwrap();
    let refused = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut v = good.clone();
        edit(&mut v);
        let restored: Search = serde_json::from_value(v).unwrap();
        restored.check_consistent().unwrap_err().to_string()
    };
    // A level count of billions (a fuzzed record made progress loop for minutes).
    let e = refused(&|v| v["state"]["level"] = u32::MAX.into());
    assert!(e.contains("level 4294967295 of 3"), "{e}");
    let e = refused(&|v| v["state"]["current"] = serde_json::json!([0, 1]));
    assert!(e.contains("maps of level 1"), "{e}");
    let e = refused(&|v| v["state"]["candidates"] = serde_json::json!([0, 9]));
    assert!(e.contains("candidates"), "{e}");
    let e = refused(&|v| v["pending"][0]["assignment"][0] = 7.into());
    assert!(e.contains("pending request"), "{e}");
    let e = refused(&|v| v["config"]["grid"] = 3.into());
    assert!(e.contains("grid 3"), "{e}");
    // A level of no photons (a fuzzed record made racing's first stage panic).
    let e = refused(&|v| v["config"]["photons"]["per_level"] = serde_json::json!([0, 2]));
    assert!(e.contains("at least one photon"), "{e}");
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
        photons: Photons::uniform(100),
        early_step2: false,
        tie_z: 0.0,
        tiebreak: None,
        refine: None,
        coarse_levels: None,
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
                photons: Photons::uniform(100),
                early_step2: false,
                tie_z: 0.0,
                tiebreak: None,
                refine: None,
                coarse_levels: None,
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
            photons: Photons::uniform(100),
            early_step2: false,
            tie_z: 0.0,
            tiebreak: None,
            refine: None,
            coarse_levels: None,
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

/// A search with every option given.
fn configured(grid: u32, permutations: u32, d: u16, seeding: Seeding, photons: Photons) -> Search {
    let names = ["moderate", "opaque", "mild"];
    Search::new(
        SearchConfig {
            grid,
            permutations,
            seed: 4,
            candidates: Candidates::Dictionary((0..d).collect()),
            seeding,
            photons,
            early_step2: false,
            tie_z: 0.0,
            tiebreak: None,
            refine: None,
            coarse_levels: None,
        },
        table(&names),
    )
    .unwrap()
}

fn racing(share: f64, z: f64, photons: u32) -> Photons {
    Photons {
        race: Some(Race { share, z }),
        ..Photons::uniform(photons)
    }
}

fn score(value: f64, std_error: f64) -> Score {
    Score {
        value,
        std_error,
        secondary: None,
        blocks: Vec::new(),
        changes: Vec::new(),
    }
}

#[test]
fn racing_drops_the_clearly_behind_and_renders_the_contenders_in_full() {
    let mut s = configured(2, 1, 3, Seeding::PerRequest, racing(0.25, 2.0, 100));
    let first = s.pending().to_vec();
    assert_eq!(first.len(), 3);
    assert!(
        first.iter().all(|r| r.photons == 25),
        "the first stage's share"
    );
    // Candidate 1 is 0.5 behind with a spread of 0.14: dropped; candidate 2 is not.
    s.submit_scores(&[score(1.0, 0.1), score(0.5, 0.1), score(0.95, 0.1)])
        .unwrap();
    let second = s.pending().to_vec();
    assert_eq!(second.len(), 2);
    for (r, c) in second.iter().zip([0, 2]) {
        assert_eq!(r.photons, 100);
        assert_eq!(r.assignment, first[c].assignment);
        assert_eq!(
            r.seed, first[c].seed,
            "the full render extends the first stage's"
        );
    }
    // The full budget decides, not the first stage.
    s.submit(&[0.8, 0.9]).unwrap();
    assert_eq!(s.levels()[0].assignment, first[2].assignment);
    assert_eq!(s.levels()[0].score, 0.9);
    assert_eq!(s.budgets(), vec![25, 100]);
}

#[test]
fn a_racing_search_with_exact_scores_matches_the_plain_one_on_the_full_budget() {
    // With a perfect scorer every wrong candidate is clearly behind: racing keeps only the
    // winners, and ends where the plain search ends.
    let truth: Vec<u16> = vec![0, 0, 1, 1, 0, 2, 2, 1, 0, 0, 0, 1, 2, 0, 0, 0];
    let hits = |r: &RenderRequest| {
        r.assignment
            .iter()
            .zip(&truth)
            .filter(|(a, b)| a == b)
            .count() as f64
    };
    let mut plain = configured(4, 2, 3, Seeding::PerLevel, Photons::uniform(100));
    let plain_history = run_to_end(&mut plain, &hits);
    let mut raced = configured(4, 2, 3, Seeding::PerLevel, racing(0.5, 3.0, 100));
    let mut raced_requests = 0;
    while !raced.is_finished() {
        let scores: Vec<Score> = raced
            .pending()
            .iter()
            .map(|r| score(hits(r), 0.01))
            .collect();
        raced_requests += scores.len();
        raced.submit_scores(&scores).unwrap();
    }
    assert_eq!(raced.result().unwrap().assignment, truth);
    assert_eq!(plain.result().unwrap().assignment, truth);
    let full_renders: usize = plain_history.iter().map(Vec::len).sum();
    // Every step: all candidates at the first stage, then the few contenders.
    assert!(
        raced_requests < 2 * full_renders,
        "{raced_requests} vs {full_renders}"
    );
}

#[test]
fn early_step_two_requests_every_m0_variant_up_front_and_steps_reuse_their_seeds() {
    let mut s = Search::new(
        SearchConfig {
            early_step2: true,
            ..configured(4, 1, 2, Seeding::PerRequest, Photons::uniform(100))
                .config()
                .clone()
        },
        table(&["moderate", "opaque", "mild"]),
    )
    .unwrap();
    s.submit(&[1.0, 0.0]).unwrap();
    // Level 1, permutation 0: the four regions × two candidates from M⁰, at once.
    let early = s.pending().to_vec();
    assert_eq!(early.len(), 8);
    let seeds: Vec<u64> = early.iter().map(|r| r.seed).collect();
    let mut distinct = seeds.clone();
    distinct.dedup();
    assert_eq!(distinct.len(), 8, "per-request seeds stay distinct");
    s.submit(&[0.0; 8]).unwrap();
    // i = 1: step 1 from M⁰ is the first region's variants: the same renders.
    let step1 = s.pending().to_vec();
    assert_eq!(step1.len(), 2);
    for (r, e) in step1.iter().zip(&early[0..2]) {
        assert_eq!((&r.assignment, r.seed), (&e.assignment, e.seed));
    }
    s.submit(&[0.1, 0.9]).unwrap();
    // i = 2: step 2's candidates are the second region's variants.
    let step = s.pending().to_vec();
    assert_eq!(step.len(), 4);
    for (r, e) in step[2..].iter().zip(&early[2..4]) {
        assert_eq!((&r.assignment, r.seed), (&e.assignment, e.seed));
    }
    // Step 1's are new renders with seeds of their own.
    assert!(step[..2].iter().all(|r| !seeds.contains(&r.seed)));
}

#[test]
fn rescoring_takes_the_best_finalist_on_a_fresh_seed_and_may_keep_the_parent() {
    let photons = Photons {
        rescore: Some(400),
        ..Photons::uniform(100)
    };
    let mut s = configured(2, 2, 2, Seeding::PerLevel, photons);
    s.submit(&[1.0, 0.0]).unwrap(); // level 0: all material 0
    let m0 = vec![0u16; 4];
    // Two permutations that each end with one region changed to material 1.
    for _ in 0..2 {
        s.submit(&[0.0, 5.0]).unwrap();
        for _ in 0..3 {
            s.submit(&[5.0, 0.0, 0.0, 0.0]).unwrap();
        }
    }
    let finalists = s.pending().to_vec();
    assert!(finalists.len() >= 2, "{finalists:?}");
    let seed = seeds::derive(4, Stream::Rescore(1));
    assert!(finalists.iter().all(|r| r.seed == seed && r.photons == 400));
    assert_eq!(
        finalists.last().unwrap().assignment,
        m0,
        "M⁰ is the last finalist"
    );
    // The fresh render says M⁰ is best: the level keeps its parent's map.
    let mut scores = vec![0.0; finalists.len()];
    *scores.last_mut().unwrap() = 1.0;
    s.submit(&scores).unwrap();
    assert!(s.is_finished());
    assert_eq!(s.result().unwrap().assignment, m0);
    assert_eq!(s.result().unwrap().permutation, 2);
    assert_eq!(s.result().unwrap().score, 1.0);
}

#[test]
fn per_level_budgets_set_each_levels_photons() {
    let photons = Photons {
        per_level: vec![10, 20, 30],
        ..Photons::default()
    };
    let mut s = configured(8, 1, 2, Seeding::PerLevel, photons);
    assert_eq!(s.budgets(), vec![10, 20, 30]);
    while !s.is_finished() {
        let level = s.progress().level;
        let expected = [10, 20, 30, 30][level as usize];
        assert!(s.pending().iter().all(|r| r.photons == expected));
        let scores: Vec<f64> = (0..s.pending().len()).map(|i| i as f64).collect();
        s.submit(&scores).unwrap();
    }
}

#[test]
fn every_option_at_once_restores_at_every_step_boundary() {
    let truth: Vec<u16> = vec![0, 1, 1, 0, 0, 2, 2, 1, 0, 0, 0, 1, 2, 0, 1, 0];
    let scorer = |r: &RenderRequest| {
        let hits = r
            .assignment
            .iter()
            .zip(&truth)
            .filter(|(a, b)| a == b)
            .count() as f64;
        score(
            hits + (r.seed % 7) as f64 * 0.1,
            0.5 + f64::from(r.photons) * 1e-3,
        )
    };
    let fresh = || {
        let photons = Photons {
            per_level: vec![40, 80],
            race: Some(Race { share: 0.5, z: 1.0 }),
            rescore: Some(200),
        };
        let config = SearchConfig {
            early_step2: true,
            ..configured(4, 3, 3, Seeding::PerLevel, photons)
                .config()
                .clone()
        };
        Search::new(config, table(&["moderate", "opaque", "mild"])).unwrap()
    };
    let mut alone = fresh();
    let mut history = Vec::new();
    while !alone.is_finished() {
        let pending = alone.pending().to_vec();
        let scores: Vec<Score> = pending.iter().map(scorer).collect();
        history.push(pending);
        alone.submit_scores(&scores).unwrap();
    }
    let mut s = fresh();
    let mut replay = Vec::new();
    while !s.is_finished() {
        s = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
        let pending = s.pending().to_vec();
        let scores: Vec<Score> = pending.iter().map(scorer).collect();
        replay.push(pending);
        s.submit_scores(&scores).unwrap();
    }
    assert_eq!(replay, history);
    assert_eq!(s.levels(), alone.levels());
}

#[test]
fn scores_within_tie_z_standard_errors_tie_as_in_the_paper() {
    let config = SearchConfig {
        tie_z: 2.0,
        ..configured(2, 1, 2, Seeding::PerLevel, Photons::uniform(100))
            .config()
            .clone()
    };
    let fresh = || Search::new(config.clone(), table(&["moderate", "opaque", "mild"])).unwrap();
    // 1.2 is 0.2 ahead of 1.0 with a spread of 0.14: within 2 spreads, a tie, which goes to
    // the earlier candidate.
    let mut s = fresh();
    s.submit_scores(&[score(1.0, 0.1), score(1.2, 0.1)])
        .unwrap();
    assert_eq!(s.levels()[0].assignment, vec![0; 4]);
    assert_eq!(s.levels()[0].score, 1.0);
    // 0.5 ahead: clearly better.
    let mut s = fresh();
    s.submit_scores(&[score(1.0, 0.1), score(1.5, 0.1)])
        .unwrap();
    assert_eq!(s.levels()[0].assignment, vec![1; 4]);
    // Between the steps a tie goes to step 2, even when step 1's best is a little higher.
    let first = s.pending().to_vec();
    s.submit_scores(&[score(2.0, 0.1), score(0.0, 0.1)])
        .unwrap(); // π₁ ← 0
    let r1 = first[0].assignment.iter().position(|&m| m == 0).unwrap();
    assert_eq!(s.pending().len(), 4);
    s.submit_scores(&[
        score(3.2, 0.1),
        score(0.0, 0.1),
        score(3.0, 0.1),
        score(0.0, 0.1),
    ])
    .unwrap();
    assert_eq!(
        s.pending()[0].assignment[r1],
        1,
        "step 2 won the tie: π₁ is back to M⁰'s material"
    );
}

/// A likelihood-like score with blocks: minus the wrong pixels (worth 8 each, spread evenly
/// over 8 blocks), plus seed noise that is the same for every map of one seed (so pairs cancel
/// it), as common random numbers make it.
/// A differential request's changes are scored as their own maps would be.
fn blocked(truth: &[u16], r: &RenderRequest) -> Score {
    let blocks_of = |a: &[u16]| -> Vec<f64> {
        let wrong = a.iter().zip(truth).filter(|(a, b)| a != b).count() as f64;
        (0..8)
            .map(|b| -wrong + (r.seed % 89) as f64 * 0.1 + f64::from(b) * 0.01)
            .collect()
    };
    let blocks = blocks_of(&r.assignment);
    let changes = r
        .changes
        .iter()
        .map(|c| {
            let mut a = r.assignment.clone();
            for &(p, m) in &c.pixels {
                a[p as usize] = m;
            }
            let blocks = blocks_of(&a);
            Some(crate::machine::ChangeScore {
                value: blocks.iter().sum(),
                blocks,
            })
        })
        .collect();
    Score {
        value: blocks.iter().sum(),
        std_error: 0.0,
        secondary: None,
        blocks,
        changes,
    }
}

#[test]
fn refinement_runs_after_the_levels_and_resumes_from_a_checkpoint() {
    refinement_runs_and_resumes(crate::refine::Screen::Direct, None, 3);
}

#[test]
fn differential_refinement_runs_after_the_levels_and_resumes_from_a_checkpoint() {
    refinement_runs_and_resumes(crate::refine::Screen::Differential, None, 3);
}

#[test]
fn a_coarse_stage_cut_to_level_zero_refines_from_the_one_material_map() {
    refinement_runs_and_resumes(
        crate::refine::Screen::Differential,
        Some(CoarseLevels::Count(1)),
        1,
    );
}

#[test]
fn an_automatic_coarse_stage_refines_from_a_scattering_one_material_map_when_sweeps_reweight() {
    // Level 0 picks `moderate`, out of which every candidate reweights.
    refinement_runs_and_resumes(
        crate::refine::Screen::Differential,
        Some(CoarseLevels::Auto),
        1,
    );
}

#[test]
fn an_automatic_coarse_stage_runs_every_level_when_sweeps_render_each_change() {
    refinement_runs_and_resumes(crate::refine::Screen::Direct, Some(CoarseLevels::Auto), 3);
}

#[test]
fn an_automatic_coarse_stage_runs_every_level_from_a_non_scattering_one_material_map() {
    // A transmissive background with a moderate and an opaque pixel: level 0 picks
    // `transmissive`, out of which a change to `moderate` cannot be reweighted.
    let mut config = search(4, 1, 3, vec![0, 1, 2]).config().clone();
    config.seeding = Seeding::PerLevel;
    config.coarse_levels = Some(CoarseLevels::Auto);
    config.refine = Some(RefineConfig {
        max_sweeps: 2,
        ..small_refinement(crate::refine::Screen::Differential)
    });
    let mut s = Search::new(config, table(&["transmissive", "moderate", "opaque"])).unwrap();
    let mut truth = vec![0u16; 16];
    truth[5] = 1;
    truth[10] = 2;
    while !s.is_finished() {
        let scores: Vec<Score> = s.pending().iter().map(|r| blocked(&truth, r)).collect();
        s.submit_scores(&scores).unwrap();
    }
    let levels = s.levels();
    assert_eq!(levels.len(), 3, "every level ran");
    assert!(levels[0].assignment.iter().all(|&m| m == 0));
    assert!(
        s.refinement().is_some(),
        "the refinement ran after the levels"
    );
}

#[test]
fn a_coarse_stage_of_no_levels_or_more_than_the_grid_has_is_refused() {
    for (n, refused) in [(0, true), (1, false), (3, false), (4, true)] {
        let mut config = search(4, 1, 1, vec![0, 1]).config().clone();
        config.coarse_levels = Some(CoarseLevels::Count(n));
        let got = Search::new(config, table(&["moderate", "opaque"]));
        assert_eq!(
            got.err(),
            refused.then_some(SearchError::CoarseLevels {
                got: n,
                most: 3,
                grid: 4
            }),
            "{n} levels"
        );
    }
}

/// A refinement of small budgets that screens with `screen`.
fn small_refinement(screen: crate::refine::Screen) -> RefineConfig {
    RefineConfig {
        photons: 200,
        confirm_photons: 400,
        z: 3.0,
        max_sweeps: 6,
        move_objects: true,
        screen,
        changes_per_render: 7,
        escalations: 0,
        recolour_regions: true,
        pixel_mm: 1.0,
        direct_photons: None,
        retest_z: None,
        swap_pixels: false,
        blocks: false,
        simplify_z: None,
        grow_objects: crate::refine::Growth::Off,
        grow_trial_z: None,
    }
}

/// Runs a refinement after `coarse_levels` to the truth, checkpointing it once during
/// refinement, and checks that `levels` coarse levels ran.
fn refinement_runs_and_resumes(
    screen: crate::refine::Screen,
    coarse_levels: Option<CoarseLevels>,
    levels: usize,
) {
    let names = ["moderate", "opaque", "mild"];
    let config = SearchConfig {
        grid: 4,
        permutations: 1,
        seed: 3,
        candidates: Candidates::Dictionary(vec![0, 1, 2]),
        seeding: Seeding::PerLevel,
        photons: Photons::uniform(100),
        early_step2: true,
        tie_z: 0.0,
        tiebreak: None,
        refine: Some(small_refinement(screen)),
        coarse_levels,
    };
    let mut s = Search::new(config, table(&names)).unwrap();
    assert!(s.budgets().contains(&200) && s.budgets().contains(&400));
    let mut truth = vec![0u16; 16];
    truth[5] = 2;
    truth[10] = 1;
    let mut refining = 0;
    let mut restored_at = None;
    while !s.is_finished() {
        let scores: Vec<Score> = s.pending().iter().map(|r| blocked(&truth, r)).collect();
        let progress = s.progress();
        assert_eq!(progress.refining, s.refinement().is_some());
        assert_eq!(progress.sweeps, 6);
        if s.refinement().is_some() {
            assert!(
                progress.stage().starts_with("refinement · sweep ") && progress.sweep < 6,
                "{progress:?}"
            );
            refining += 1;
            assert!(s
                .pending()
                .iter()
                .all(|r| r.photons == 200 || r.photons == 400));
            // A checkpoint taken during refinement ends the same.
            if restored_at.is_none() {
                let json = serde_json::to_string(&s).unwrap();
                let mut copy: Search = serde_json::from_str(&json).unwrap();
                let mut c = copy.clone();
                while !c.is_finished() {
                    let sc: Vec<Score> = c.pending().iter().map(|r| blocked(&truth, r)).collect();
                    c.submit_scores(&sc).unwrap();
                }
                restored_at = Some(c.result().unwrap().assignment.clone());
                copy.submit_scores(&scores).unwrap();
            }
        }
        s.submit_scores(&scores).unwrap();
    }
    assert!(refining >= 1, "the refinement ran");
    let done = s.progress();
    assert_eq!(
        done.sweep as usize,
        s.refinement().unwrap().history().len(),
        "every sweep ended"
    );
    let result = s.result().unwrap();
    assert_eq!(result.assignment, truth);
    assert_eq!(result.level, 2, "the refined map is of the grid's pixels");
    assert_eq!(restored_at.as_ref(), Some(&truth));
    let ran = s.levels();
    assert_eq!(ran.len(), levels);
    if levels == 1 {
        let start = &ran[0].assignment;
        assert!(start.iter().all(|&m| m == start[0]), "{start:?}");
    }
    let history = s.refinement().unwrap().history();
    assert_eq!(history.last().map(|h| h.candidates), Some(0));
    let reweighted: u32 = history.iter().map(|h| h.reweighted).sum();
    match screen {
        crate::refine::Screen::Direct => assert_eq!(reweighted, 0),
        crate::refine::Screen::Differential => assert!(reweighted > 0),
    }
}
