//! Tests of the GPU engine against the CPU engine and against exact answers.
//!
//! Every test that needs a device gets it from [`engine_or_skip`]: with no adapter, the test
//! fails under `CI=true` and reports a loud skip elsewhere. Statistical tolerances come from the
//! counts (standard errors, χ² against its degrees of freedom), not from tuning.

use super::adapters::choose;
use super::engine::Tuning;
use super::*;
use crate::cpu::CpuEngine;
use scatterfarm_model::engine::{
    CountMatrix, Engine, EngineError, PhotonRange, RenderBatch, RenderItem, RenderOutput,
};
use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::material::{builtin_material, Material};

/// The engine on the default adapter, or `None` (and a loud note) when this machine has none.
/// Under `CI=true` a missing adapter fails the test instead.
pub(super) fn engine_or_skip() -> Option<GpuEngine> {
    match GpuEngine::new(&AdapterSelector::Auto) {
        Ok(engine) => Some(engine),
        Err(EngineError::Unavailable(why)) => {
            if std::env::var("CI").as_deref() == Ok("true") {
                panic!("no GPU adapter under CI=true (install mesa-vulkan-drivers and libvulkan1): {why}");
            }
            eprintln!("\n*** SKIPPED: no GPU adapter ({why}) ***\n");
            None
        }
        Err(e) => panic!("the GPU engine failed to start: {e}"),
    }
}

fn small() -> Geometry {
    Geometry {
        size_mm: 16.0,
        grid: 8,
        positions: 16,
        directions: 3,
    }
}

fn material(name: &str) -> Material {
    builtin_material(name).unwrap_or_else(|| panic!("no built-in material {name}"))
}

/// Table indices used by the scenes below.
const TRANSMISSIVE: u16 = 0;
const OPAQUE: u16 = 1;
const MODERATE: u16 = 2;
const MILD: u16 = 3;
const BACK: u16 = 4;
const FORWARD: u16 = 5;
const ABSORBER: u16 = 6;

fn table() -> Vec<Material> {
    vec![
        material("transmissive"),
        material("opaque"),
        material("moderate"),
        material("mild"),
        material("back"),
        Material {
            sigma_s: 0.5,
            sigma_a: 0.02,
            g: 0.99,
        },
        Material {
            sigma_s: 0.0,
            sigma_a: 0.1,
            g: 0.0,
        },
    ]
}

/// The heterogeneous 8×8 scene: moderate background with opaque (#), transmissive (t), back (b)
/// and g = 0.99 (f) regions, some of them on the boundary.
fn heterogeneous() -> Vec<u16> {
    let rows = [
        "#..ttt..", ".##..t..", ".##..t..", "...bb...", "...bbff.", ".ff..ff.", ".ff..t#.",
        "tt.....#",
    ];
    rows.iter()
        .flat_map(|r| {
            r.chars().map(|c| match c {
                '#' => OPAQUE,
                't' => TRANSMISSIVE,
                'b' => BACK,
                'f' => FORWARD,
                _ => MODERATE,
            })
        })
        .collect()
}

fn uniform_scene(geo: &Geometry, m: u16) -> Vec<u16> {
    vec![m; geo.pixels()]
}

fn render(
    engine: &dyn Engine,
    geo: Geometry,
    table: &[Material],
    items: &[RenderItem],
    photons: PhotonRange,
) -> Vec<RenderOutput> {
    let batch = RenderBatch {
        geometry: geo,
        table,
        items,
        photons,
    };
    match engine.render(&batch) {
        Ok(out) => out,
        Err(e) => panic!("render failed: {e}"),
    }
}

fn items(assignment: &[u16], seeds: std::ops::Range<u64>) -> Vec<RenderItem> {
    seeds
        .map(|seed| RenderItem {
            assignment: assignment.to_vec(),
            seed,
        })
        .collect()
}

/// The counts of several renders added up.
fn summed(outputs: &[RenderOutput]) -> CountMatrix {
    let first = &outputs[0].counts;
    let mut sum = CountMatrix::zeros(first.sources, first.bins);
    for o in outputs {
        sum.add(&o.counts).expect("same shapes");
    }
    sum
}

/// How two renders of the same medium compare, from their counts alone.
#[derive(Debug, Clone)]
struct Agreement {
    /// Two-sample χ² over cells with at least [`MIN_CELL`] photons in both renders together.
    chi2: f64,
    df: usize,
    /// (χ² − df) / √(2·df): a standard normal for large df when the renders agree.
    chi2_z: f64,
    /// |difference| / standard error of the fraction of photons that left the medium.
    exit_z: f64,
    /// The largest such z over the exit-position marginal (positions p').
    position_z: f64,
    /// The largest such z over the exit-direction marginal (directions k').
    direction_z: f64,
}

/// Cells with fewer photons than this (both renders together) are left out of χ².
const MIN_CELL: u64 = 20;

impl Agreement {
    /// χ² within 5 of its normal approximation's standard deviations; fractions within 4
    /// standard errors.
    fn passes(&self) -> bool {
        self.chi2_z < 5.0 && self.exit_z < 4.0 && self.position_z < 4.0 && self.direction_z < 4.0
    }
}

/// |fa − fb| in standard errors, for fractions `xa / na` and `xb / nb` of independent photons
/// (pooled binomial variance; conservative when photons of different sources differ).
fn fraction_z(xa: u64, na: u64, xb: u64, nb: u64) -> f64 {
    let (fa, fb) = (xa as f64 / na as f64, xb as f64 / nb as f64);
    let p = (xa + xb) as f64 / (na + nb) as f64;
    let se = (p * (1.0 - p) * (1.0 / na as f64 + 1.0 / nb as f64)).sqrt();
    if se == 0.0 {
        if fa == fb {
            0.0
        } else {
            f64::INFINITY
        }
    } else {
        (fa - fb).abs() / se
    }
}

/// Compares counts `a` (from `na` photons per source) with `b` (from `nb` per source).
fn compare(geo: &Geometry, a: &CountMatrix, na: u64, b: &CountMatrix, nb: u64) -> Agreement {
    let k = geo.directions as usize;
    let p = geo.positions as usize;
    let (ka, kb) = (
        (nb as f64 / na as f64).sqrt(),
        (na as f64 / nb as f64).sqrt(),
    );
    let (mut chi2, mut df) = (0.0, 0usize);
    let (mut pos_a, mut pos_b) = (vec![0u64; p], vec![0u64; p]);
    let (mut dir_a, mut dir_b) = (vec![0u64; k], vec![0u64; k]);
    for (j, (&x, &y)) in a.counts.iter().zip(&b.counts).enumerate() {
        let (x, y) = (u64::from(x), u64::from(y));
        let bin = j % a.bins;
        pos_a[bin / k] += x;
        pos_b[bin / k] += y;
        dir_a[bin % k] += x;
        dir_b[bin % k] += y;
        if x + y >= MIN_CELL {
            let d = x as f64 * ka - y as f64 * kb;
            chi2 += d * d / (x + y) as f64;
            df += 1;
        }
    }
    let (la, lb) = (na * a.sources as u64, nb * b.sources as u64);
    let max_z = |xa: &[u64], xb: &[u64]| {
        xa.iter()
            .zip(xb)
            .map(|(&x, &y)| fraction_z(x, la, y, lb))
            .fold(0.0, f64::max)
    };
    Agreement {
        chi2,
        df,
        chi2_z: if df == 0 {
            0.0
        } else {
            (chi2 - df as f64) / (2.0 * df as f64).sqrt()
        },
        exit_z: fraction_z(a.total(), la, b.total(), lb),
        position_z: max_z(&pos_a, &pos_b),
        direction_z: max_z(&dir_a, &dir_b),
    }
}

/// Mean and standard error of the mean of replicate values.
fn mean_se(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// Replicates (items with their own seeds) per engine, and photons per source per replicate.
const REPLICATES: u64 = 8;
const PHOTONS_PER_REPLICATE: u32 = 6_250;

/// Renders `assignment` on the GPU and the CPU (independent seeds), `REPLICATES` items each,
/// checks that they agree (counts, and scattering events per photon between replicate means),
/// and that the CPU engine with every g negated does *not* agree with either.
fn check_agreement(label: &str, geo: Geometry, assignment: &[u16]) {
    let Some(gpu) = engine_or_skip() else { return };
    let cpu = CpuEngine::new();
    let table = table();
    let photons = PhotonRange::first_n(PHOTONS_PER_REPLICATE);
    let n = u64::from(PHOTONS_PER_REPLICATE) * REPLICATES;

    let g = render(
        &gpu,
        geo,
        &table,
        &items(assignment, 1000..1000 + REPLICATES),
        photons,
    );
    let c = render(
        &cpu,
        geo,
        &table,
        &items(assignment, 2000..2000 + REPLICATES),
        photons,
    );
    let (gs, cs) = (summed(&g), summed(&c));
    let agreement = compare(&geo, &gs, n, &cs, n);
    eprintln!(
        "{label}: GPU vs CPU χ² = {:.1} on {} cells: {agreement:?}",
        agreement.chi2, agreement.df
    );
    assert!(
        agreement.df > 100,
        "{label}: too few cells with counts for χ²: {agreement:?}"
    );
    assert!(
        agreement.passes(),
        "{label}: the GPU and CPU engines disagree: {agreement:?}"
    );

    // Scattering events per photon: the replicates' means agree (Welch t, 2×7 degrees of
    // freedom, hence the bound of 5).
    let per_photon = |o: &[RenderOutput]| -> Vec<f64> {
        o.iter()
            .map(|r| {
                r.scatter_events as f64 / (f64::from(PHOTONS_PER_REPLICATE) * geo.sources() as f64)
            })
            .collect()
    };
    let ((mg, sg), (mc, sc)) = (mean_se(&per_photon(&g)), mean_se(&per_photon(&c)));
    let t = (mg - mc).abs() / (sg * sg + sc * sc).sqrt();
    eprintln!("{label}: scattering events per photon GPU {mg:.5} ± {sg:.5}, CPU {mc:.5} ± {sc:.5}");
    assert!(
        mg > 0.0 && t < 5.0,
        "{label}: scattering events per photon differ: GPU {mg} ± {sg}, CPU {mc} ± {sc}"
    );

    // The same comparison catches a deliberately wrong engine: g negated everywhere.
    let negated: Vec<Material> = table.iter().map(|m| Material { g: -m.g, ..*m }).collect();
    let w = summed(&render(
        &cpu,
        geo,
        &negated,
        &items(assignment, 3000..3000 + REPLICATES),
        photons,
    ));
    for (name, reference) in [("GPU", &gs), ("CPU", &cs)] {
        let wrong = compare(&geo, reference, n, &w, n);
        eprintln!("{label}: {name} vs CPU with g negated {wrong:?}");
        assert!(
            !wrong.passes(),
            "{label}: the comparison does not catch a negated g against {name}: {wrong:?}"
        );
    }
}

#[test]
fn agrees_with_cpu_on_homogeneous_moderate() {
    let geo = small();
    check_agreement("moderate", geo, &uniform_scene(&geo, MODERATE));
}

#[test]
fn agrees_with_cpu_on_heterogeneous_scene() {
    check_agreement("heterogeneous", small(), &heterogeneous());
}

/// The shader draws the CPU tracer's random words (same Philox stream layout: key = seed,
/// counter = (photon, source, block, 0), flight k reads words 3k..3k+2): with one seed both
/// engines follow the same paths, up to f32 rounding, so their counts nearly coincide, far
/// closer than two independent renders. (Statistical agreement alone cannot see the layout.)
#[test]
fn follows_the_cpu_random_streams() {
    let Some(gpu) = engine_or_skip() else { return };
    let cpu = CpuEngine::new();
    let table = table();
    let geo = small();
    let photons = PhotonRange {
        first: 1000,
        count: 2000,
    };
    let n = u64::from(photons.count) * geo.sources() as u64;
    let moved = |a: &CountMatrix, b: &CountMatrix| -> f64 {
        let diff: u64 = a
            .counts
            .iter()
            .zip(&b.counts)
            .map(|(&x, &y)| u64::from(x.abs_diff(y)))
            .sum();
        diff as f64 / 2.0 / n as f64
    };
    for (label, scene) in [
        ("moderate", uniform_scene(&geo, MODERATE)),
        ("heterogeneous", heterogeneous()),
    ] {
        let g = render(&gpu, geo, &table, &items(&scene, 77..78), photons);
        let c = render(&cpu, geo, &table, &items(&scene, 77..78), photons);
        let other = render(&cpu, geo, &table, &items(&scene, 78..79), photons);
        let (same, different) = (
            moved(&g[0].counts, &c[0].counts),
            moved(&other[0].counts, &c[0].counts),
        );
        eprintln!(
            "{label}: photons binned differently: same seed {same:.5}, another seed {different:.5}"
        );
        // Independent renders differ by their sampling noise (a few per cent of the photons
        // here); the same streams differ only where f32 and f64 rounding part a path.
        assert!(
            same < 0.002,
            "{label}: {same} of the photons land elsewhere than on the CPU with the same seed"
        );
        assert!(
            same * 20.0 < different,
            "{label}: same seed {same} is not far below another seed's {different}"
        );
    }
}

/// The 64-bit-multiply shader (devices with SHADER_INT64) and the 16-bit-piece one compute the
/// same Philox words, hence the same counts.
#[test]
fn int64_and_16_bit_multiplies_give_identical_counts() {
    let Some(gpu) = engine_or_skip() else { return };
    let emulated = match GpuEngine::with_int64(&AdapterSelector::Index(gpu.adapter().index), false)
    {
        Ok(e) => e,
        Err(e) => panic!("the engine without 64-bit integers failed to start: {e}"),
    };
    assert!(!emulated.uses_int64());
    if !gpu.uses_int64() {
        eprintln!(
            "note: {} has no 64-bit integers; both engines use 16-bit pieces",
            gpu.adapter().name
        );
    }
    let table = table();
    let geo = small();
    let it = items(&heterogeneous(), 5..7);
    let photons = PhotonRange::first_n(1500);
    assert_eq!(
        render(&gpu, geo, &table, &it, photons),
        render(&emulated, geo, &table, &it, photons)
    );
}

#[test]
fn transmissive_lands_exactly_in_the_cpu_bin() {
    let Some(gpu) = engine_or_skip() else { return };
    let cpu = CpuEngine::new();
    let table = table();
    let photons = PhotonRange::first_n(5);
    for geo in [Geometry::default(), small()] {
        let it = items(&uniform_scene(&geo, TRANSMISSIVE), 7..8);
        let g = render(&gpu, geo, &table, &it, photons);
        let c = render(&cpu, geo, &table, &it, photons);
        for i in 0..geo.sources() {
            let row = g[0].counts.row(i);
            let bins: Vec<usize> = (0..geo.bins()).filter(|&j| row[j] > 0).collect();
            assert_eq!(bins.len(), 1, "{geo:?} source {i}: light in bins {bins:?}");
            assert_eq!(
                row[bins[0]], photons.count,
                "{geo:?} source {i}: fraction is not 1"
            );
            assert_eq!(
                row,
                c[0].counts.row(i),
                "{geo:?} source {i}: GPU bin {} differs from the CPU's",
                bins[0]
            );
        }
        assert_eq!(g[0].scatter_events, 0);
    }
}

/// Scenes of transmissive and opaque pixels only are deterministic: the GPU must match the CPU
/// bit for bit. This exercises the grid-line rule (sources on pixel corners when N ≥ P/2), the
/// corner rule (45° rays for even K), absorption on entry and bin snapping at many geometries.
#[test]
fn transmissive_and_opaque_scenes_match_cpu_exactly() {
    let Some(gpu) = engine_or_skip() else { return };
    let cpu = CpuEngine::new();
    let table = table();
    let geometries = [
        Geometry::default(),
        small(),
        Geometry {
            size_mm: 16.0,
            grid: 4,
            positions: 16,
            directions: 2,
        },
        Geometry {
            size_mm: 16.0,
            grid: 8,
            positions: 32,
            directions: 4,
        },
        Geometry {
            size_mm: 10.0,
            grid: 16,
            positions: 32,
            directions: 5,
        },
        Geometry {
            size_mm: 16.0,
            grid: 32,
            positions: 64,
            directions: 6,
        },
    ];
    for geo in geometries {
        // A fixed pseudo-random map, about one pixel in five opaque.
        let mut state = 0x9E37_79B9_7F4A_7C15u64 ^ u64::from(geo.grid * 131 + geo.directions);
        let map: Vec<u16> = (0..geo.pixels())
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                if (state >> 33).is_multiple_of(5) {
                    OPAQUE
                } else {
                    TRANSMISSIVE
                }
            })
            .collect();
        let it = [
            RenderItem {
                assignment: map,
                seed: 3,
            },
            RenderItem {
                assignment: uniform_scene(&geo, TRANSMISSIVE),
                seed: 4,
            },
        ];
        let g = render(&gpu, geo, &table, &it, PhotonRange::first_n(2));
        let c = render(&cpu, geo, &table, &it, PhotonRange::first_n(2));
        for (k, (go, co)) in g.iter().zip(&c).enumerate() {
            for i in 0..geo.sources() {
                assert_eq!(
                    go.counts.row(i),
                    co.counts.row(i),
                    "{geo:?} item {k} source {i}: GPU and CPU differ"
                );
            }
        }
    }
}

/// Distance from `origin` along `dir` to the boundary of the square.
fn chord(geo: &Geometry, origin: [f64; 2], dir: [f64; 2]) -> f64 {
    let w = geo.size_mm;
    (0..2)
        .filter(|&a| dir[a] != 0.0)
        .map(|a| ((if dir[a] > 0.0 { w } else { 0.0 }) - origin[a]) / dir[a])
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn pure_absorber_transmits_exp_minus_sigma_a_chord() {
    let Some(gpu) = engine_or_skip() else { return };
    let cpu = CpuEngine::new();
    let table = table();
    let n = 4_000u32;
    for geo in [small(), Geometry::default()] {
        let g = render(
            &gpu,
            geo,
            &table,
            &items(&uniform_scene(&geo, ABSORBER), 11..12),
            PhotonRange::first_n(n),
        );
        // The bin each source's straight ray lands in, from the CPU engine on a clear medium.
        let clear = render(
            &cpu,
            geo,
            &table,
            &items(&uniform_scene(&geo, TRANSMISSIVE), 0..1),
            PhotonRange::first_n(1),
        );
        for i in 0..geo.sources() {
            let row = g[0].counts.row(i);
            let bin = (0..geo.bins())
                .find(|&j| clear[0].counts.row(i)[j] == 1)
                .expect("a clear ray exits");
            let ray = geo.source_ray(i);
            let p = (-0.1 * chord(&geo, ray.origin, ray.direction)).exp();
            let se = (p * (1.0 - p) / f64::from(n)).sqrt();
            let got = f64::from(row[bin]) / f64::from(n);
            assert!(
                (got - p).abs() < 4.0 * se,
                "{geo:?} source {i}: {got} vs exp(-σa·chord) = {p} ± {se}"
            );
            let elsewhere: u64 =
                row.iter().map(|&c| u64::from(c)).sum::<u64>() - u64::from(row[bin]);
            assert_eq!(
                elsewhere, 0,
                "{geo:?} source {i}: light outside the straight-through bin"
            );
        }
        assert_eq!(g[0].scatter_events, 0);
    }
}

#[test]
fn opaque_frame_gives_no_light() {
    let Some(gpu) = engine_or_skip() else { return };
    let table = table();
    let geo = small();
    let n = geo.grid as usize;
    let frame: Vec<u16> = (0..geo.pixels())
        .map(|p| {
            let (r, c) = (p / n, p % n);
            if r == 0 || c == 0 || r == n - 1 || c == n - 1 {
                OPAQUE
            } else {
                MODERATE
            }
        })
        .collect();
    let it = [
        RenderItem {
            assignment: frame,
            seed: 5,
        },
        RenderItem {
            assignment: uniform_scene(&geo, OPAQUE),
            seed: 6,
        },
    ];
    for out in render(&gpu, geo, &table, &it, PhotonRange::first_n(1000)) {
        assert_eq!(out.counts.total(), 0);
        assert_eq!(out.scatter_events, 0);
    }
}

#[test]
fn same_seed_gives_identical_counts() {
    let Some(gpu) = engine_or_skip() else { return };
    let table = table();
    let geo = small();
    let it = items(&heterogeneous(), 42..43);
    let a = render(&gpu, geo, &table, &it, PhotonRange::first_n(2000));
    let b = render(&gpu, geo, &table, &it, PhotonRange::first_n(2000));
    assert!(a[0].counts.total() > 0);
    assert_eq!(a, b);
    let other = render(
        &gpu,
        geo,
        &table,
        &items(&heterogeneous(), 43..44),
        PhotonRange::first_n(2000),
    );
    assert_ne!(
        a[0].counts, other[0].counts,
        "a different seed should give different counts"
    );
}

#[test]
fn batch_equals_items_one_at_a_time() {
    let Some(gpu) = engine_or_skip() else { return };
    let table = table();
    let geo = small();
    let it = vec![
        RenderItem {
            assignment: heterogeneous(),
            seed: 1,
        },
        RenderItem {
            assignment: uniform_scene(&geo, MILD),
            seed: 2,
        },
        RenderItem {
            assignment: uniform_scene(&geo, MODERATE),
            seed: 1,
        },
    ];
    let photons = PhotonRange {
        first: 100,
        count: 1500,
    };
    let batch = render(&gpu, geo, &table, &it, photons);
    for (k, item) in it.iter().enumerate() {
        let single = render(&gpu, geo, &table, std::slice::from_ref(item), photons);
        assert_eq!(
            batch[k], single[0],
            "item {k} differs between batch and single render"
        );
    }
}

#[test]
fn photon_ranges_add_up() {
    let Some(gpu) = engine_or_skip() else { return };
    let table = table();
    let geo = small();
    let it = items(&heterogeneous(), 9..11);
    let (a, n) = (777u32, 2500u32);
    let whole = render(&gpu, geo, &table, &it, PhotonRange::first_n(n));
    let head = render(&gpu, geo, &table, &it, PhotonRange { first: 0, count: a });
    let tail = render(
        &gpu,
        geo,
        &table,
        &it,
        PhotonRange {
            first: a,
            count: n - a,
        },
    );
    for k in 0..it.len() {
        let mut sum = head[k].counts.clone();
        sum.add(&tail[k].counts).expect("same shapes");
        assert_eq!(
            sum, whole[k].counts,
            "item {k}: [0,a) + [a,n) differs from [0,n)"
        );
        assert_eq!(
            head[k].scatter_events + tail[k].scatter_events,
            whole[k].scatter_events
        );
    }
}

/// However the work is cut — photons per invocation, dispatches, submissions, sub-item chunks —
/// the counts are the same.
#[test]
fn work_splitting_does_not_change_counts() {
    let Some(mut gpu) = engine_or_skip() else {
        return;
    };
    let table = table();
    let geo = small();
    let it = vec![
        RenderItem {
            assignment: heterogeneous(),
            seed: 1,
        },
        RenderItem {
            assignment: uniform_scene(&geo, BACK),
            seed: 8,
        },
        RenderItem {
            assignment: uniform_scene(&geo, FORWARD),
            seed: 9,
        },
    ];
    let photons = PhotonRange {
        first: 5,
        count: 1000,
    };
    let reference = render(&gpu, geo, &table, &it, photons);
    let row = (geo.bins() * 4) as u64;
    let default = gpu.tuning.clone();
    let variants = [
        Tuning {
            per_invocation: Some(1),
            ..default.clone()
        },
        Tuning {
            per_invocation: Some(1000),
            ..default.clone()
        },
        Tuning {
            per_invocation: Some(37),
            photons_per_dispatch: 3_000,
            ..default.clone()
        },
        // One item per submission, then 10 sources per submission.
        Tuning {
            max_buffer_bytes: row * geo.sources() as u64,
            ..default.clone()
        },
        Tuning {
            max_buffer_bytes: row * 10,
            per_invocation: Some(64),
            ..default.clone()
        },
    ];
    for tuning in variants {
        gpu.tuning = tuning.clone();
        let got = render(&gpu, geo, &table, &it, photons);
        assert_eq!(got, reference, "counts change with {tuning:?}");
    }
    // A device whose buffers cannot hold even one source's bins: a clear error, no crash.
    gpu.tuning = Tuning {
        max_buffer_bytes: row - 4,
        ..default
    };
    let batch = RenderBatch {
        geometry: geo,
        table: &table,
        items: &it,
        photons,
    };
    match gpu.render(&batch) {
        Err(EngineError::Device(msg)) => assert!(msg.contains("too large"), "{msg}"),
        other => panic!("expected a too-large error, got {other:?}"),
    }
}

#[test]
fn invalid_batches_are_errors() {
    let Some(gpu) = engine_or_skip() else { return };
    let table = table();
    let geo = small();
    let bad = [RenderItem {
        assignment: vec![0; 3],
        seed: 1,
    }];
    let batch = RenderBatch {
        geometry: geo,
        table: &table,
        items: &bad,
        photons: PhotonRange::first_n(10),
    };
    assert!(matches!(
        gpu.render(&batch),
        Err(EngineError::AssignmentSize { .. })
    ));
    let empty = render(&gpu, geo, &table, &[], PhotonRange::first_n(10));
    assert!(empty.is_empty());
    let none = render(
        &gpu,
        geo,
        &table,
        &items(&heterogeneous(), 1..2),
        PhotonRange::first_n(0),
    );
    assert_eq!(none[0].counts.total(), 0);
}

#[test]
fn fingerprint_and_adapter_listing() {
    let Some(gpu) = engine_or_skip() else { return };
    let f = gpu.fingerprint();
    assert_eq!(f.engine, "gpu");
    assert_eq!(f.adapter, gpu.adapter().name);
    assert!(
        f.version.starts_with(GPU_ENGINE_VERSION)
            && f.version.contains(&format!("{SHADER_HASH:016x}"))
    );
    let listed = list_adapters();
    assert_eq!(listed.get(gpu.adapter().index), Some(gpu.adapter()));
    // Selecting by index and by name finds the same adapter.
    let by_index = GpuEngine::new(&AdapterSelector::Index(gpu.adapter().index)).expect("by index");
    assert_eq!(by_index.adapter(), gpu.adapter());
    let by_name =
        GpuEngine::new(&AdapterSelector::Name(gpu.adapter().name.to_uppercase())).expect("by name");
    assert_eq!(by_name.adapter().name, gpu.adapter().name);
    assert!(matches!(
        GpuEngine::new(&AdapterSelector::Index(listed.len())),
        Err(EngineError::Unavailable(_))
    ));
}

fn fake(index: usize, name: &str, device_type: &str) -> AdapterInfo {
    AdapterInfo {
        index,
        name: name.into(),
        backend: "vulkan".into(),
        device_type: device_type.into(),
        driver: "test".into(),
        max_storage_buffer_binding_size: 1 << 27,
        max_buffer_size: 1 << 31,
        max_compute_invocations_per_workgroup: 1024,
        max_compute_workgroups_per_dimension: 65535,
    }
}

#[test]
fn auto_prefers_hardware_gpus_then_cpu_devices() {
    let lavapipe = fake(0, "llvmpipe (LLVM 15, 256 bits)", "cpu");
    let discrete = fake(1, "NVIDIA GeForce RTX 4090", "discrete-gpu");
    let pci = vec![String::new(), "0000:01:00.0".to_string()];
    let both = [lavapipe.clone(), discrete];
    assert_eq!(
        choose(&both, &pci, &AdapterSelector::Auto)
            .map(|c| c.0)
            .ok(),
        Some(1)
    );
    assert_eq!(
        choose(&both[..1], &pci, &AdapterSelector::Auto)
            .map(|c| c.0)
            .ok(),
        Some(0)
    );
    assert_eq!(
        choose(&both, &pci, &"rtx".parse().expect("a name"))
            .map(|c| c.0)
            .ok(),
        Some(1)
    );
    assert_eq!(
        choose(&both, &pci, &"0000:01:00.0".parse().expect("a name"))
            .map(|c| c.0)
            .ok(),
        Some(1)
    );
    assert_eq!(
        choose(&both, &pci, &"0".parse().expect("an index"))
            .map(|c| c.0)
            .ok(),
        Some(0)
    );
    assert!(matches!(
        choose(&both, &pci, &AdapterSelector::Index(2)),
        Err(EngineError::Unavailable(_))
    ));
    assert!(matches!(
        choose(&both, &pci, &"radeon".parse().expect("a name")),
        Err(EngineError::Unavailable(_))
    ));
    assert!(matches!(
        choose(&[], &[], &AdapterSelector::Auto),
        Err(EngineError::Unavailable(_))
    ));
    assert_eq!("auto".parse(), Ok(AdapterSelector::Auto));
    assert_eq!("3".parse(), Ok(AdapterSelector::Index(3)));
    assert_eq!(
        " llvmpipe ".parse(),
        Ok(AdapterSelector::Name("llvmpipe".into()))
    );
    assert!("".parse::<AdapterSelector>().is_err());
}

#[cfg(unix)]
#[test]
fn runtime_dir_is_private_after_silencing() {
    use std::os::unix::fs::PermissionsExt;
    silence_mesa_runtime_dir_warning();
    let dir = std::env::var_os("XDG_RUNTIME_DIR").expect("XDG_RUNTIME_DIR is set");
    let meta = std::fs::metadata(&dir).expect("the runtime dir exists");
    assert!(meta.is_dir());
    assert_eq!(meta.permissions().mode() & 0o777, 0o700);
}

/// The standard medium of the performance goal: 16 mm, grid 16, 128 positions, 9 directions,
/// every pixel moderate, 512 photons per source. Prints scattering events and photons per
/// CPU-second (all threads of the process, lavapipe's included) for the GPU and the CPU engine.
/// Run with `cargo test --release -p scatterfarm-worker -- --ignored --nocapture bench_`.
#[test]
#[ignore = "benchmark: run explicitly"]
fn bench_standard_medium_events_per_cpu_second() {
    let Some(gpu) = engine_or_skip() else { return };
    let geo = Geometry::default();
    let table = vec![material("moderate")];
    let photons = PhotonRange::first_n(512);
    let it = items(&vec![0; geo.pixels()], 1..2);
    let measure = |engine: &dyn Engine, name: &str| -> f64 {
        render(engine, geo, &table, &it, photons); // warm-up (shader compilation)
        let start = cpu_time::ProcessTime::now();
        let wall = std::time::Instant::now();
        let (mut events, mut renders) = (0u64, 0u64);
        while start.elapsed().as_secs_f64() < 6.0 {
            events += render(engine, geo, &table, &it, photons)[0].scatter_events;
            renders += 1;
        }
        let cpu_s = start.elapsed().as_secs_f64();
        let photons_total = renders as f64 * (geo.sources() as f64) * f64::from(photons.count);
        println!(
            "{name}: {renders} renders, {:.1} M scattering events/CPU-s, {:.2} M photons/CPU-s, {:.3} s wall per render",
            events as f64 / cpu_s / 1e6,
            photons_total / cpu_s / 1e6,
            wall.elapsed().as_secs_f64() / renders as f64
        );
        events as f64 / cpu_s
    };
    let g = measure(&gpu, &format!("gpu ({})", gpu.adapter().name));
    let c = measure(&CpuEngine::new(), "cpu");
    println!("gpu/cpu events per CPU-second: {:.2}", g / c);
}

/// Photons per invocation on the standard medium: prints events per CPU-second for each.
#[test]
#[ignore = "benchmark: run explicitly"]
fn bench_photons_per_invocation() {
    let Some(mut gpu) = engine_or_skip() else {
        return;
    };
    let geo = Geometry::default();
    let table = vec![material("moderate")];
    let photons = PhotonRange::first_n(512);
    let it = items(&vec![0; geo.pixels()], 1..2);
    render(&gpu, geo, &table, &it, photons);
    for per in [16u32, 32, 64, 128, 256] {
        gpu.tuning.per_invocation = Some(per);
        let start = cpu_time::ProcessTime::now();
        let mut events = 0u64;
        while start.elapsed().as_secs_f64() < 3.0 {
            events += render(&gpu, geo, &table, &it, photons)[0].scatter_events;
        }
        println!(
            "{per:4} photons/invocation: {:.1} M events/CPU-s",
            events as f64 / start.elapsed().as_secs_f64() / 1e6
        );
    }
}

/// Lavapipe ends an invocation's loops past 65 535 iterations in all, dropping the photons not
/// yet followed; the engine notices (`end_of_run` in `tallies.wgsl`) and renders the chunk again
/// with fewer photons per invocation, to the same counts, or refuses when even one photon is too
/// long. Dense media (σs = 6 and 40 per mm over 16 mm) make long runs.
#[test]
fn runs_the_device_cuts_short_are_rendered_again_or_refused() {
    let Some(mut gpu) = engine_or_skip() else {
        return;
    };
    let geo = Geometry::new(16.0, 4, 8, 3).unwrap();
    let dense = |gpu: &GpuEngine, sigma_s: f64, photons: u32| {
        let table = [Material::new(sigma_s, 0.0001, 0.0).unwrap()];
        let items = [RenderItem {
            assignment: vec![0; 16],
            seed: 5,
        }];
        gpu.render(&RenderBatch {
            geometry: geo,
            table: &table,
            items: &items,
            photons: PhotonRange::first_n(photons),
        })
    };
    let default = gpu.tuning.clone();
    gpu.tuning.per_invocation = Some(1);
    let one = dense(&gpu, 6.0, 400).expect("one photon per invocation is followed whole");
    gpu.tuning.per_invocation = Some(400);
    let long = dense(&gpu, 6.0, 400).expect("a long run is rendered again");
    assert_eq!(
        long, one,
        "runs rendered again give the counts of short ones"
    );
    gpu.tuning.per_invocation = Some(1);
    let refused = dense(&gpu, 40.0, 200);
    if gpu.adapter().is_cpu() {
        match refused {
            Err(EngineError::Device(msg)) => assert!(msg.contains("cut short"), "{msg}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
    } else {
        assert!(refused.is_ok(), "{refused:?}");
    }
    gpu.tuning = default;
}
