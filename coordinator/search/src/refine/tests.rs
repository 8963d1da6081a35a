//! The refinement stage's tests: sweeps, confirmations, growth, trials and simplification on
//! small grids with exact or synthetic scores.

use super::moves::grown_boxes;
use super::*;

/// A refinement over materials 0 and 1 (job seed 1), knowing nothing of reweighting.
fn two_materials(config: RefineConfig, grid: u32, start: Vec<u16>) -> Refinement {
    Refinement::new(config, grid, vec![0, 1], 1, start, Vec::new(), Vec::new())
}

fn config() -> RefineConfig {
    RefineConfig {
        photons: 100,
        confirm_photons: 200,
        z: 2.0,
        max_sweeps: 5,
        move_objects: true,
        screen: Screen::Direct,
        changes_per_render: 1024,
        escalations: 0,
        recolour_regions: false,
        pixel_mm: 1.0,
        direct_photons: None,
        retest_z: None,
        swap_pixels: false,
        blocks: false,
        simplify_z: None,
        grow_objects: Growth::Off,
        grow_trial_z: None,
    }
}

/// Scores from a known truth: each block is minus the number of wrong pixels, plus noise
/// that pairs cancel (the same per seed and photons for every map; fewer photons score
/// higher, as a deviance does, so a render paired with one of other photons misleads).
fn score_of(truth: &[u16], map: &[u16], seed: u64, photons: u32) -> (f64, Vec<f64>) {
    let wrong = truth.iter().zip(map).filter(|(a, b)| a != b).count() as f64;
    let blocks: Vec<f64> = (0..8)
        .map(|b| {
            -wrong / 8.0 + ((seed % 97) as f64) * 0.01 + f64::from(b) * 0.001
                - f64::from(photons) * 0.01
        })
        .collect();
    (blocks.iter().sum(), blocks)
}

fn run(truth: &[u16], start: Vec<u16>, materials: Vec<u16>) -> Refinement {
    run_with(config(), truth, start, materials, Vec::new(), Vec::new())
}

/// A score's value and blocks.
type Scored = (f64, Vec<f64>);

/// Runs a refinement against [`score_of`]; a differential request's changes are scored as
/// a direct render of each would be.
fn run_with(
    config: RefineConfig,
    truth: &[u16],
    start: Vec<u16>,
    materials: Vec<u16>,
    reweightable: Vec<Vec<bool>>,
    opaque: Vec<bool>,
) -> Refinement {
    let score = |a: &[u16], seed: u64, photons: u32| score_of(truth, a, seed, photons);
    run_scored(config, start, materials, reweightable, opaque, &score)
}

/// [`run_with`] against any scores of a 4 × 4 map (its assignment, seed and photons).
fn run_scored(
    config: RefineConfig,
    start: Vec<u16>,
    materials: Vec<u16>,
    reweightable: Vec<Vec<bool>>,
    opaque: Vec<bool>,
    score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
) -> Refinement {
    run_traced(
        config,
        start,
        materials,
        reweightable,
        opaque,
        score_of,
        &mut |_| {},
    )
}

/// [`run_scored`], handing each step's state to `on_step` before its scores.
fn run_traced(
    config: RefineConfig,
    start: Vec<u16>,
    materials: Vec<u16>,
    reweightable: Vec<Vec<bool>>,
    opaque: Vec<bool>,
    score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
    on_step: &mut dyn FnMut(&Refinement),
) -> Refinement {
    let r = Refinement::new(config, 4, materials, 1, start, reweightable, opaque);
    drive(r, score_of, on_step)
}

/// Runs `r` to its end against `score_of`, handing each step's state to `on_step`.
fn drive(
    mut r: Refinement,
    score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
    on_step: &mut dyn FnMut(&Refinement),
) -> Refinement {
    let mut steps = 0;
    while !r.is_finished() {
        on_step(&r);
        let scored: Vec<(Scored, Vec<Option<ChangeScore>>)> = r
            .pending()
            .iter()
            .map(|q| {
                let changes = q
                    .changes
                    .iter()
                    .map(|c| {
                        let mut a = q.assignment.clone();
                        for &(p, m) in &c.pixels {
                            a[p as usize] = m;
                        }
                        let (value, blocks) = score_of(&a, q.seed, q.photons);
                        Some(ChangeScore { value, blocks })
                    })
                    .collect();
                (score_of(&q.assignment, q.seed, q.photons), changes)
            })
            .collect();
        let scores: Vec<BlockScore> = scored
            .iter()
            .map(|((v, b), c)| BlockScore {
                value: *v,
                blocks: b,
                changes: c,
            })
            .collect();
        r.submit(&scores).unwrap();
        steps += 1;
        assert!(steps < 50, "the refinement ends");
    }
    r
}

#[test]
fn growth_rounds_replace_a_strong_pixel_standing_in_for_a_weak_block() {
    // Each pixel grown outside the block costs less than the strong pixel: the grown map
    // wins outright.
    let start = stand_in_start();
    let run = |grow_objects| run_stand_in(0.2, grow_objects, 12, &mut |_| {});
    // Without growth rounds the start is where the stage ends.
    let kept = run(Growth::Off);
    assert_eq!(kept.current().0, &start[..]);
    assert!(kept.history().iter().all(|h| !h.growth));
    // With them, the strong pixel's neighbourhood becomes the weak material, and the
    // sweeps after it trim what grew outside the block: the truth.
    let grown = run(Growth::On);
    assert_eq!(
        grown.current().0,
        &stand_in_truth()[..],
        "{:?}",
        grown.history()
    );
    let rounds: Vec<&SweepRecord> = grown.history().iter().filter(|h| h.growth).collect();
    assert!(rounds.first().is_some_and(|h| h.changed == 9), "{rounds:?}");
    // It won outright: no trial (a later round on the truth tries, and loses, one).
    assert!(rounds[0].trial_kept.is_none(), "{rounds:?}");
    // A round that changes nothing is not run again on its map.
    assert!(rounds.len() <= MAX_GROWTHS as usize);
    assert!(grown.is_finished());
    // The rounds' state survives a checkpoint (the scores only to JSON's float precision).
    let json = serde_json::to_string(&grown).unwrap();
    let back: Refinement = serde_json::from_str(&json).unwrap();
    assert_eq!((back.growths, &back.grown), (grown.growths, &grown.grown));
    assert_eq!(back.history().len(), grown.history().len());
    assert!(back
        .history()
        .iter()
        .zip(grown.history())
        .all(|(a, b)| a.growth == b.growth));
}

#[test]
fn auto_growth_runs_only_from_a_one_material_start() {
    // The stand-in start holds two materials: `auto` is off there, and the stage ends on
    // the stand-in as without growth.
    let auto = run_stand_in(0.2, Growth::Auto, 12, &mut |_| {});
    assert_eq!(auto.config().grow_objects, Growth::Off);
    assert_eq!(auto.current().0, &stand_in_start()[..]);
    assert!(auto.history().iter().all(|h| !h.growth));
    // From a one-material map it is on, and stays resolved through a checkpoint.
    let config = RefineConfig {
        grow_objects: Growth::Auto,
        ..config()
    };
    let level_zero = two_materials(config, 4, vec![0; 16]);
    assert_eq!(level_zero.config().grow_objects, Growth::On);
    let json = serde_json::to_string(&level_zero).unwrap();
    let back: Refinement = serde_json::from_str(&json).unwrap();
    assert_eq!(back.config().grow_objects, Growth::On);
    assert_eq!(Growth::Auto.resolve(&[]), Growth::Off);
}

#[test]
fn growth_settings_read_as_before_and_as_words() {
    // A record written when growth was a boolean reads back unchanged; `auto` is a word.
    for (text, growth) in [
        ("true", Growth::On),
        ("false", Growth::Off),
        ("\"auto\"", Growth::Auto),
    ] {
        let read: Growth = serde_json::from_str(text).unwrap();
        assert_eq!(read, growth, "{text}");
        assert_eq!(serde_json::to_string(&growth).unwrap(), text);
    }
    let old = serde_json::to_value(config()).unwrap();
    assert!(
        old.get("grow_objects").is_none(),
        "off is left out, as before"
    );
    let mut on = old.clone();
    on["grow_objects"] = serde_json::Value::Bool(true);
    let read: RefineConfig = serde_json::from_value(on).unwrap();
    assert_eq!(read.grow_objects, Growth::On);
    let read: RefineConfig = serde_json::from_value(old).unwrap();
    assert_eq!(read.grow_objects, Growth::Off);
    for (word, growth) in [
        ("auto", Growth::Auto),
        ("on", Growth::On),
        ("false", Growth::Off),
    ] {
        assert_eq!(word.parse::<Growth>(), Ok(growth));
        assert_eq!(growth.to_string().parse::<Growth>(), Ok(growth));
    }
    let err = "sometimes".parse::<Growth>().unwrap_err().to_string();
    assert!(err.contains("auto") && err.contains("sometimes"), "{err}");
    assert!(serde_json::from_str::<Growth>("\"maybe\"").is_err());
}

/// A 4 × 4 map whose truth is a 2 × 2 block (pixels 5, 6, 9, 10) of the weak material 1 in
/// background 0, scored without noise: one pixel of the strong material 2 (worth four weak
/// ones) at 5 fits the counts almost as well, and no single pixel, move or recolour
/// improves it. Each non-background pixel outside the block costs `outside`.
fn stand_in_scores(outside: f64) -> impl Fn(&[u16], u64, u32) -> Scored {
    const BLOCK: [usize; 4] = [5, 6, 9, 10];
    move |a: &[u16], seed: u64, _photons: u32| -> Scored {
        let weight = |m: u16| [0.0, 1.0, 4.0][usize::from(m)];
        let signal: f64 = BLOCK.iter().map(|&p| weight(a[p])).sum();
        let grown = (0..16).filter(|p| !BLOCK.contains(p) && a[*p] != 0).count() as f64;
        let strong = a.iter().filter(|&&m| m == 2).count() as f64;
        let badness = 2.0 * (signal - 4.0).powi(2) + outside * grown + 1.5 * strong;
        let objects = a.iter().filter(|&&m| m != 0).count() as f64;
        let blocks: Vec<f64> = (0..8)
            .map(|b| {
                let sign = if b % 2 == 0 { 1.0 } else { -1.0 };
                -badness / 8.0 + sign * 0.001 * objects + ((seed % 97) as f64) * 0.01
            })
            .collect();
        (blocks.iter().sum(), blocks)
    }
}

/// A refinement of [`stand_in_start`] against [`stand_in_scores`] of `outside`, over the
/// three materials, handing each step's state to `on_step`.
fn run_stand_in(
    outside: f64,
    grow_objects: Growth,
    max_sweeps: u32,
    on_step: &mut dyn FnMut(&Refinement),
) -> Refinement {
    let config = RefineConfig {
        grow_objects,
        max_sweeps,
        ..config()
    };
    let score = stand_in_scores(outside);
    run_traced(
        config,
        stand_in_start(),
        vec![0, 1, 2],
        Vec::new(),
        Vec::new(),
        &score,
        on_step,
    )
}

/// The stand-in of [`stand_in_scores`]: the strong pixel at 5.
fn stand_in_start() -> Vec<u16> {
    let mut start = vec![0u16; 16];
    start[5] = 2;
    start
}

fn stand_in_truth() -> Vec<u16> {
    let mut truth = vec![0u16; 16];
    for p in [5, 6, 9, 10] {
        truth[p] = 1;
    }
    truth
}

#[test]
fn a_grown_map_that_loses_is_tried_and_kept_only_if_its_sweeps_beat_the_start() {
    // Grown too far, the map loses to the strong pixel (5 pixels outside the block cost
    // more than the strong pixel), but the sweeps from it trim it to the truth.
    let start = stand_in_start();
    let run = |max_sweeps| run_stand_in(0.4, Growth::On, max_sweeps, &mut |_| {});
    let tried = run(16);
    assert_eq!(
        tried.current().0,
        &stand_in_truth()[..],
        "{:?}",
        tried.history()
    );
    let ends: Vec<&SweepRecord> = tried
        .history()
        .iter()
        .filter(|h| h.trial_kept.is_some())
        .collect();
    assert!(
        ends.first().is_some_and(|h| h.trial_kept == Some(true)),
        "{ends:?}"
    );
    assert_eq!(ends[0].map, stand_in_truth(), "{ends:?}");
    assert!(tried.is_finished());
    // The trial survives a checkpoint: resumed midway, the run ends the same.
    let mut steps = 0;
    let mut midway = None;
    run_stand_in(0.4, Growth::On, 16, &mut |r: &Refinement| {
        steps += 1;
        if r.trial.is_some() && midway.is_none() {
            midway = Some(serde_json::to_string(r).unwrap());
        }
    });
    let midway: Refinement = serde_json::from_str(&midway.expect("a trial ran")).unwrap();
    assert!(steps > 0 && midway.trial.is_some());
    let resumed = drive(midway, &stand_in_scores(0.4), &mut |_| {});
    assert_eq!(resumed.current(), tried.current());
    assert_eq!(resumed.history().len(), tried.history().len());
    // Cut short by the sweep limit right after the round, the trial has not trimmed
    // anything: its map loses, and the strong pixel comes back.
    let round = tried.history().iter().position(|h| h.growth).unwrap() as u32;
    let cut = run(round + 1);
    assert_eq!(cut.current().0, &start[..], "{:?}", cut.history());
    let last = cut.history().last().unwrap();
    assert_eq!(last.trial_kept, Some(false), "{:?}", cut.history());
    assert_eq!(last.map, start);
    assert!(cut.is_finished());
    // The round records its best grown map's z. With a floor above it no trial runs, and
    // the stand-in stays; with a floor below every round's, the trials run as without one.
    let grown_z = tried.history().iter().find_map(|h| h.grown_z);
    let grown_z = grown_z.expect("the round records its best grown map's z");
    assert!(grown_z.is_finite() && grown_z < config().z, "{grown_z}");
    let floored = |floor: f64| {
        let config = RefineConfig {
            grow_objects: Growth::On,
            max_sweeps: 16,
            grow_trial_z: Some(floor),
            ..config()
        };
        let score = stand_in_scores(0.4);
        run_traced(
            config,
            start.clone(),
            vec![0, 1, 2],
            Vec::new(),
            Vec::new(),
            &score,
            &mut |_| {},
        )
    };
    let above = floored(grown_z + 0.5);
    assert!(above.history().iter().all(|h| h.trial_kept.is_none()));
    assert_eq!(above.current().0, &start[..], "{:?}", above.history());
    assert!(above.is_finished());
    let lowest = tried
        .history()
        .iter()
        .filter_map(|h| h.grown_z)
        .fold(grown_z, f64::min);
    let below = floored(lowest - 0.5);
    assert_eq!(below.current(), tried.current());
    assert_eq!(below.history(), tried.history());
}

#[test]
fn simplification_clears_what_the_scores_cannot_see() {
    // Pixels 12, 13, 14 and 15 (the bottom row) are hidden: no score sees them. The truth
    // is background but pixel 5 and the hidden pixel 12; the start has the truth and two
    // spurious hidden pixels, 14 and 15.
    let hidden = |p: usize| p >= 12;
    let mut truth = vec![0u16; 16];
    truth[5] = 1;
    truth[12] = 1;
    let score = |a: &[u16], seed: u64, photons: u32| -> Scored {
        let wrong = (0..16).filter(|&p| !hidden(p) && a[p] != truth[p]).count() as f64;
        // Noise that the hidden pixels move but that sums to nothing.
        let objects = (12..16).filter(|&p| a[p] != 0).count() as f64;
        let blocks: Vec<f64> = (0..8)
            .map(|b| {
                let sign = if b % 2 == 0 { 1.0 } else { -1.0 };
                -wrong / 8.0 + sign * 0.001 * objects + ((seed % 97) as f64) * 0.01
                    - f64::from(photons) * 0.01
            })
            .collect();
        (blocks.iter().sum(), blocks)
    };
    let mut start = truth.clone();
    start[14] = 1;
    start[15] = 1;
    let run = |simplify_z| {
        let config = RefineConfig {
            simplify_z,
            ..config()
        };
        run_scored(
            config,
            start.clone(),
            vec![0, 1],
            Vec::new(),
            Vec::new(),
            &score,
        )
    };
    // Without simplification nothing beats the start: it stays.
    let kept = run(None);
    assert_eq!(kept.current().0, &start[..]);
    assert!(kept.history().iter().all(|h| !h.simplification));
    // With it, every hidden pixel becomes the background (the hidden object too: the
    // scores cannot tell it), and the seen one stays.
    let simplified = run(Some(1.0));
    let mut expected = truth.clone();
    expected[12] = 0;
    assert_eq!(simplified.current().0, &expected[..]);
    let rounds: Vec<&SweepRecord> = simplified
        .history()
        .iter()
        .filter(|h| h.simplification)
        .collect();
    assert!(!rounds.is_empty());
    assert_eq!(rounds[0].changed, 3);
    // A second round, on the simplified map, changes nothing and ends the stage.
    assert_eq!(rounds.last().map(|h| h.changed), Some(0));
    assert!(rounds.len() <= MAX_SIMPLIFICATIONS as usize);
    // With an escalation, rounds come after it, at its doubled photons.
    let mut rounds = Vec::new();
    run_traced(
        RefineConfig {
            simplify_z: Some(1.0),
            escalations: 1,
            ..config()
        },
        start.clone(),
        vec![0, 1],
        Vec::new(),
        Vec::new(),
        &score,
        &mut |r| {
            if r.simplifying && matches!(r.waiting, Some(Waiting::Sweep { .. })) {
                rounds.push(r.pending()[0].photons);
            }
        },
    );
    assert!(
        !rounds.is_empty() && rounds.iter().all(|&p| p == 200),
        "{rounds:?}"
    );
    // A negative z would clear what loses: refused.
    assert!(RefineConfig {
        simplify_z: Some(-1.0),
        ..config()
    }
    .problem()
    .is_some());
}

#[test]
fn noiseless_scores_lead_to_the_truth() {
    let mut truth = vec![0u16; 16];
    truth[5] = 1;
    truth[10] = 2;
    let r = run(&truth, vec![0; 16], vec![0, 1, 2]);
    assert_eq!(r.current().0, &truth[..]);
    // The last sweep found nothing more.
    assert_eq!(r.history().last().map(|h| h.candidates), Some(0));
}

#[test]
fn a_map_that_is_right_stays() {
    let truth = vec![1u16; 16];
    let r = run(&truth, truth.clone(), vec![0, 1]);
    assert_eq!(r.current().0, &truth[..]);
    assert_eq!(r.history().len(), 1);
}

#[test]
fn recolours_set_a_whole_region_to_each_other_material() {
    let mut start = vec![0u16; 16];
    for p in [5, 6, 9, 10] {
        start[p] = 1;
    }
    start[15] = 2;
    let cfg = RefineConfig {
        recolour_regions: true,
        ..config()
    };
    let r = Refinement::new(cfg, 4, vec![0, 1, 2], 1, start.clone(), vec![], vec![]);
    let recolours = r.recolours();
    // The background (11 pixels) to 1 and 2, the block to 0 and 2; the single pixel 15 is
    // left to the pixel changes.
    assert_eq!(recolours.len(), 4, "{recolours:?}");
    let block_to_2: Vec<(u32, u16)> = [5, 6, 9, 10].map(|p| (p, 2)).to_vec();
    assert!(recolours.iter().any(|c| c.pixels == block_to_2));
    assert!(recolours
        .iter()
        .any(|c| c.pixels.len() == 11 && c.pixels.iter().all(|&(_, d)| d == 1)));
    // A block found with the wrong material is one change away from the truth.
    let mut truth = start.clone();
    for p in [5, 6, 9, 10] {
        truth[p] = 2;
    }
    let cfg = RefineConfig {
        recolour_regions: true,
        move_objects: false,
        ..config()
    };
    let found = run_with(cfg, &truth, start, vec![0, 1, 2], Vec::new(), Vec::new());
    assert_eq!(found.current().0, &truth[..]);
}

#[test]
fn noisy_recolours_are_left_out_of_differential_sweeps() {
    let mut start = vec![0u16; 16];
    for p in [5, 6, 9, 10] {
        start[p] = 1;
    }
    // 0 ↔ 1 is nearly exact, anything to or from 2 very noisy (a forward to a backward
    // phase function).
    let spread = vec![vec![1.0, 1.1, 300.0], vec![1.1, 1.0, 300.0], vec![300.0; 3]];
    let reweightable = vec![vec![true; 3]; 3];
    let cfg = |screen| RefineConfig {
        screen,
        recolour_regions: true,
        move_objects: false,
        ..config()
    };
    let r = Refinement::with_spread(
        cfg(Screen::Differential),
        4,
        vec![0, 1, 2],
        1,
        start.clone(),
        reweightable.clone(),
        vec![],
        spread.clone(),
    );
    let single = Change {
        pixels: vec![(3, 2)],
    };
    let block_to_0 = Change {
        pixels: [5, 6, 9, 10].map(|p| (p, 0)).to_vec(),
    };
    let block_to_2 = Change {
        pixels: [5, 6, 9, 10].map(|p| (p, 2)).to_vec(),
    };
    assert_eq!(r.spread_of(&start, &single), 1.0);
    assert!(r.spread_of(&start, &block_to_2) > MAX_SPREAD);
    assert!(
        !r.left_out(&single, &start, &single),
        "single pixels are always tried"
    );
    assert!(!r.left_out(&block_to_0, &start, &block_to_0));
    assert!(r.left_out(&block_to_2, &start, &block_to_2));
    // The sweep estimates 16 × 2 single pixels and 2 of the 4 recolours (the background
    // to 1 and the block to 0) in its one differential render.
    let estimated: usize = r.pending().iter().map(|q| q.changes.len()).sum();
    assert_eq!(r.pending().len(), 1);
    assert_eq!(estimated, 32 + 2);
    // Direct screening renders all four.
    let direct = Refinement::with_spread(
        cfg(Screen::Direct),
        4,
        vec![0, 1, 2],
        1,
        start,
        reweightable,
        vec![],
        spread,
    );
    assert_eq!(direct.pending().len(), 1 + 32 + 4);
}

#[test]
fn object_moves_shift_a_block_by_one_pixel() {
    let mut start = vec![0u16; 16];
    for p in [5, 6, 9, 10] {
        start[p] = 1;
    }
    let r = two_materials(config(), 4, start.clone());
    let right = r
        .object_moves()
        .into_iter()
        .find(|c| c.pixels.contains(&(7, 1)))
        .expect("a move to the right");
    assert_eq!(right.pixels, vec![(5, 0), (7, 1), (9, 0), (11, 1)]);
}

#[test]
fn swaps_exchange_neighbouring_pixels_of_different_materials() {
    // One object pixel (5) in a 4 × 4 map: its 8 neighbours each swap with it once.
    let mut start = vec![0u16; 16];
    start[5] = 1;
    let swapping = RefineConfig {
        swap_pixels: true,
        move_objects: false,
        ..config()
    };
    let r = two_materials(swapping.clone(), 4, start.clone());
    let swaps = r.swaps();
    assert_eq!(swaps.len(), 8);
    for c in &swaps {
        let [(p, a), (q, b)] = c.pixels[..] else {
            panic!("a swap of two pixels: {c:?}");
        };
        assert_eq!((a, b), (start[q as usize], start[p as usize]));
        assert!(p == 5 || q == 5);
    }
    assert!(swaps.iter().any(|c| c.pixels == vec![(5, 0), (10, 1)]));
    // A sweep tries them after the single pixels; without the option it does not.
    let tried = |config: RefineConfig| two_materials(config, 4, start.clone()).changes().len();
    let plain = RefineConfig {
        move_objects: false,
        ..config()
    };
    assert_eq!(tried(swapping), tried(plain) + 8);
}

#[test]
fn object_sides_grow_and_shrink_each_side_of_an_object() {
    // A 1 × 2 object (pixels 5 and 6) in a 4 × 4 map.
    let mut start = vec![0u16; 16];
    start[5] = 1;
    start[6] = 1;
    let r = two_materials(
        RefineConfig {
            blocks: true,
            ..config()
        },
        4,
        start,
    );
    let sides: Vec<Vec<(u32, u16)>> = r.object_sides().into_iter().map(|c| c.pixels).collect();
    // Grown up, down, left and right; shrunk from the left and the right (shrinking its
    // only row would clear it).
    assert_eq!(
        sides,
        vec![
            vec![(1, 1), (2, 1)],
            vec![(9, 1), (10, 1)],
            vec![(4, 1)],
            vec![(7, 1)],
            vec![(5, 0)],
            vec![(6, 0)],
        ]
    );
}

#[test]
fn a_growth_round_fills_an_objects_box_grown_by_each_side() {
    // An L of three pixels (5, 10, 11) in a 5 × 5 map: a 2 × 2 block (rows 1–2, columns
    // 0–1) with its top-right corner missing.
    let mut start = vec![0u16; 25];
    for p in [5, 10, 11] {
        start[p] = 1;
    }
    let r = two_materials(
        RefineConfig {
            grow_objects: Growth::On,
            ..config()
        },
        5,
        start,
    );
    let grown: Vec<Vec<(u32, u16)>> = r
        .growths_of_current()
        .into_iter()
        .map(|c| c.pixels)
        .collect();
    let set = |pixels: &[u32]| pixels.iter().map(|&p| (p, 1)).collect::<Vec<_>>();
    // The L with its 8-connected neighbours, then its box grown up, down and right,
    // filled (the missing corner, 6, with each); nothing lies left of column 0.
    assert_eq!(
        grown,
        vec![
            set(&[0, 1, 6, 7, 12, 15, 16, 17]),
            set(&[0, 1, 6]),
            set(&[6, 15, 16]),
            set(&[6, 7, 12]),
        ]
    );
    // A corner pixel's box grows only down and right.
    assert_eq!(grown_boxes(&[0], 5), vec![vec![0, 5], vec![0, 1]]);
}

#[test]
fn blocks_set_two_by_two_blocks_and_pairs_wholly_to_each_material() {
    // A 3 × 3 map, all background but pixel 4 (the centre): 4 blocks and 12 pairs.
    let mut start = vec![0u16; 9];
    start[4] = 1;
    let blocking = RefineConfig {
        blocks: true,
        move_objects: false,
        ..config()
    };
    let r = two_materials(blocking.clone(), 3, start.clone());
    let blocks = r.blocks();
    // To material 1 every block and pair changes, except the pairs through the centre
    // (one pixel each); to material 0 none changes two pixels.
    assert_eq!(blocks.len(), 4 + 12 - 4);
    for c in &blocks {
        assert!(c.pixels.len() >= 2, "{c:?}");
        assert!(c
            .pixels
            .iter()
            .all(|&(p, d)| d == 1 && start[p as usize] == 0));
        assert!(c.pixels.windows(2).all(|w| w[0].0 < w[1].0));
    }
    // The top-left block: pixels 0, 1 and 3 (4 already is material 1).
    assert_eq!(blocks[0].pixels, vec![(0, 1), (1, 1), (3, 1)]);
    assert!(blocks.iter().any(|c| c.pixels == vec![(6, 1), (7, 1)]));
    assert!(blocks.iter().any(|c| c.pixels == vec![(2, 1), (5, 1)]));
    // A sweep tries them all after the single pixels (the one-pixel object's sides add
    // nothing: grown, each is a single pixel already listed; shrunk, it would be cleared);
    // without the option it does not.
    let tried = |config: RefineConfig| two_materials(config, 3, start.clone()).changes().len();
    let plain = RefineConfig {
        move_objects: false,
        ..config()
    };
    assert_eq!(tried(blocking), tried(plain) + blocks.len());
}

#[test]
fn requests_share_a_seed_within_a_sweep_and_sweeps_differ() {
    let r = two_materials(config(), 4, vec![0; 16]);
    let seeds: BTreeSet<u64> = r.pending().iter().map(|p| p.seed).collect();
    assert_eq!(seeds.len(), 1);
    assert_eq!(r.pending().len(), 17);
    assert!(r.pending().iter().all(|p| p.photons == 100));
    assert!(config().problem().is_none());
    assert!(RefineConfig {
        z: f64::NAN,
        ..config()
    }
    .problem()
    .is_some());
    let trial_z = |z| {
        RefineConfig {
            grow_trial_z: Some(z),
            ..config()
        }
        .problem()
    };
    assert!(trial_z(f64::NAN).is_some_and(|p| p.contains("growth trial z")));
    assert!(trial_z(f64::NEG_INFINITY).is_none() && trial_z(-5.0).is_none());
}

/// Differential screening: the changes the reweighting covers ride on renders of the
/// current map (in chunks), the others are rendered directly, and the result is the one
/// direct screening finds.
#[test]
fn differential_screening_finds_what_direct_screening_does() {
    let mut truth = vec![0u16; 16];
    truth[5] = 1;
    truth[10] = 2;
    // 0 → anything and 1 → 0 reweight; 2 is like an opaque material: nothing leaves it.
    let reweightable = vec![
        vec![true, true, true],
        vec![true, true, false],
        vec![false, false, true],
    ];
    let cfg = RefineConfig {
        screen: Screen::Differential,
        changes_per_render: 10,
        ..config()
    };
    let first = Refinement::new(
        cfg.clone(),
        4,
        vec![0, 1, 2],
        1,
        vec![0; 16],
        reweightable.clone(),
        Vec::new(),
    );
    // 32 single-pixel changes, all from material 0: four differential renders of M.
    assert_eq!(first.pending().len(), 4);
    assert!(first.pending().iter().all(|q| q.assignment == vec![0; 16]));
    assert_eq!(
        first
            .pending()
            .iter()
            .map(|q| q.changes.len())
            .sum::<usize>(),
        32
    );
    let r = run_with(
        cfg,
        &truth,
        vec![0; 16],
        vec![0, 1, 2],
        reweightable,
        Vec::new(),
    );
    assert_eq!(r.current().0, &truth[..]);
    let direct = run(&truth, vec![0; 16], vec![0, 1, 2]);
    assert_eq!(r.current().0, direct.current().0);
}

/// The changes a differential sweep cannot reweight (here 0 → 2, like a scattering pixel
/// in a transmissive background) are rendered with `direct_photons`, paired with a render
/// of `M` at those photons (scores at other photons differ: a wrong pairing would take
/// every one of them), and the refinement still ends at the truth.
#[test]
fn direct_renders_of_a_differential_sweep_have_their_own_photons() {
    let mut truth = vec![0u16; 16];
    truth[5] = 1;
    truth[10] = 2;
    let reweightable = vec![
        vec![true, true, false],
        vec![true, true, false],
        vec![true, true, true],
    ];
    let cfg = RefineConfig {
        screen: Screen::Differential,
        changes_per_render: 10,
        direct_photons: Some(25),
        ..config()
    };
    let first = Refinement::new(
        cfg.clone(),
        4,
        vec![0, 1, 2],
        1,
        vec![0; 16],
        reweightable.clone(),
        Vec::new(),
    );
    let pending = first.pending();
    // 16 reweighted changes (0 → 1) in two differential renders, then M and the 16
    // direct changes (0 → 2) at 25 photons.
    assert_eq!(pending.len(), 2 + 1 + 16);
    assert!(pending[..2].iter().all(|q| q.photons == 100));
    assert!(pending[2..].iter().all(|q| q.photons == 25));
    assert_eq!(pending[2].assignment, vec![0; 16]);
    assert!(pending[2].changes.is_empty());
    let r = run_with(
        cfg,
        &truth,
        vec![0; 16],
        vec![0, 1, 2],
        reweightable,
        Vec::new(),
    );
    assert_eq!(r.current().0, &truth[..]);
}

/// Scores `request` (a direct render) for [`an_escalated_sweep_retests_only_what_came_close`]:
/// minus the wrong pixels per block, and for a map whose pixel 3 is 1, noise around a
/// slightly worse mean (z about −0.4 against the truth), so only that change comes close.
fn close_call_score(truth: &[u16], request: &RefineRequest) -> (f64, Vec<f64>) {
    let wrong = truth
        .iter()
        .zip(&request.assignment)
        .filter(|(a, b)| a != b)
        .count() as f64;
    let close = request.assignment[3] == 1 && wrong == 1.0;
    let blocks: Vec<f64> = (0..8)
        .map(|b| {
            if close {
                if b % 2 == 0 {
                    0.3
                } else {
                    -0.4
                }
            } else {
                -wrong / 8.0
            }
        })
        .collect();
    (blocks.iter().sum(), blocks)
}

/// After a sweep of the right map finds nothing, the escalated sweep renders only the
/// change that came within `retest_z` (and `M`); without `retest_z`, every change again.
#[test]
fn an_escalated_sweep_retests_only_what_came_close() {
    let truth = vec![0u16; 16];
    let second_sweep = |retest_z: Option<f64>| {
        let cfg = RefineConfig {
            escalations: 1,
            move_objects: false,
            retest_z,
            ..config()
        };
        let mut r = Refinement::new(cfg, 4, vec![0, 1], 1, truth.clone(), Vec::new(), Vec::new());
        assert_eq!(r.pending().len(), 1 + 16, "M and every pixel turned to 1");
        let scored: Vec<(f64, Vec<f64>)> = r
            .pending()
            .iter()
            .map(|q| close_call_score(&truth, q))
            .collect();
        let scores: Vec<BlockScore> = scored
            .iter()
            .map(|(v, b)| BlockScore {
                value: *v,
                blocks: b,
                changes: &[],
            })
            .collect();
        r.submit(&scores).unwrap();
        assert!(!r.is_finished(), "the sweep found nothing, so it escalates");
        assert!(r.pending().iter().all(|q| q.photons == 200));
        r.pending()
            .iter()
            .map(|q| q.assignment.clone())
            .collect::<Vec<_>>()
    };
    let mut close = truth.clone();
    close[3] = 1;
    assert_eq!(second_sweep(Some(-1.0)), vec![truth.clone(), close]);
    assert_eq!(second_sweep(Some(0.0)), vec![truth.clone()]);
    assert_eq!(second_sweep(None).len(), 1 + 16);
}

/// A pixel whose material nothing reweights out of to the background (3, like a
/// non-scattering one in a scattering background) is filled too, opaque or not.
#[test]
fn non_scattering_pixels_are_filled_too() {
    let mut start = vec![0u16; 16];
    start[3] = 3;
    start[9] = 1;
    let reweightable = vec![
        vec![true, true, true, true],
        vec![true, true, true, true],
        vec![false, false, true, false],
        vec![false, false, true, true],
    ];
    let cfg = RefineConfig {
        screen: Screen::Differential,
        ..config()
    };
    let r = Refinement::new(
        cfg,
        4,
        vec![0, 1, 3],
        1,
        start.clone(),
        reweightable,
        vec![false, false, true, false],
    );
    let mut base = start;
    base[3] = 0;
    assert_eq!(r.pending().len(), 1, "nothing rendered directly");
    assert_eq!(r.pending()[0].assignment, base);
    assert_eq!(r.pending()[0].changes[0].pixels, vec![(3, 3)]);
}

/// With an opaque material (2: nothing reweights out of it), a differential sweep renders
/// the filled base (the map with its opaque pixels set to the background): `M` is its
/// first change, clearing an opaque pixel is a change of it like any other, so nothing is
/// rendered directly, and the refinement ends where direct screening does.
#[test]
fn opaque_pixels_are_cleared_from_the_filled_base() {
    let mut truth = vec![0u16; 16];
    truth[5] = 2;
    truth[6] = 2;
    truth[10] = 1;
    // Start with an opaque pixel too many and one missing.
    let mut start = truth.clone();
    start[6] = 0;
    start[12] = 2;
    let reweightable = vec![
        vec![true, true, true],
        vec![true, true, true],
        vec![false, false, true],
    ];
    let opaque = vec![false, false, true];
    let cfg = RefineConfig {
        screen: Screen::Differential,
        ..config()
    };
    let first = Refinement::new(
        cfg.clone(),
        4,
        vec![0, 1, 2],
        1,
        start.clone(),
        reweightable.clone(),
        opaque.clone(),
    );
    let pending = first.pending();
    assert_eq!(pending.len(), 1, "one differential render, nothing direct");
    let mut base = start.clone();
    base[5] = 0;
    base[12] = 0;
    assert_eq!(pending[0].assignment, base);
    assert_eq!(
        pending[0].changes[0].pixels,
        vec![(5, 2), (12, 2)],
        "M is the base's first change"
    );
    // Clearing pixel 12 keeps pixel 5 opaque: the change of the base is (5, 2) alone.
    assert!(pending[0].changes[1..]
        .iter()
        .any(|c| c.pixels == vec![(5, 2)]));
    let r = run_with(
        cfg,
        &truth,
        start.clone(),
        vec![0, 1, 2],
        reweightable,
        opaque,
    );
    assert_eq!(r.current().0, &truth[..]);
    let direct = run(&truth, start, vec![0, 1, 2]);
    assert_eq!(r.current().0, direct.current().0);
}
