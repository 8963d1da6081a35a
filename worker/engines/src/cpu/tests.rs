//! Properties of the CPU engine's real output: exact bins of straight rays, Beer–Lambert
//! attenuation, conservation, 90° rotation symmetry, determinism and batch additivity.

use super::CpuEngine;
use scatterfarm_model::engine::{CountMatrix, Engine, PhotonRange, RenderBatch, RenderItem};
use scatterfarm_model::geometry::{snapped_floor, Geometry};
use scatterfarm_model::material::{builtin_material, Material};
use scatterfarm_model::scene::Scene;

fn render(
    engine: &CpuEngine,
    geo: Geometry,
    table: &[Material],
    assignment: Vec<u16>,
    seed: u64,
    photons: PhotonRange,
) -> CountMatrix {
    let items = [RenderItem { assignment, seed }];
    let batch = RenderBatch {
        geometry: geo,
        table,
        items: &items,
        photons,
    };
    engine.render(&batch).unwrap().remove(0).counts
}

fn homogeneous(engine: &CpuEngine, geo: Geometry, m: Material, photons: u32) -> CountMatrix {
    render(
        engine,
        geo,
        &[m],
        vec![0; geo.pixels()],
        7,
        PhotonRange::first_n(photons),
    )
}

/// Where the straight ray of `source` leaves the square, by intersecting it with the four edges,
/// and the bin that gives: position from the exit arc length, direction by integer arithmetic
/// from which edge it leaves through (opposite: k; next counter-clockwise: ⌊(K+2k+1)/2⌋;
/// previous: ⌊(2k+1−K)/2⌋).
fn hand_bin(geo: &Geometry, source: usize) -> (usize, f64) {
    let w = geo.size_mm;
    let k = (source % geo.directions as usize) as i64;
    let p = source / geo.directions as usize;
    let edge = (p / (geo.positions as usize / 4)) as i64;
    let ray = geo.source_ray(source);
    let [x, y] = ray.origin;
    let [dx, dy] = ray.direction;
    // Distance to each edge line along the ray (only those ahead).
    let mut best = (f64::INFINITY, 0i64);
    for (e, t) in [
        (0, -y / dy),
        (1, (w - x) / dx),
        (2, (w - y) / dy),
        (3, -x / dx),
    ] {
        if e != edge && t.is_finite() && t > 1e-12 && t < best.0 {
            best = (t, e);
        }
    }
    let (t, exit_edge) = best;
    let (ex, ey) = (x + t * dx, y + t * dy);
    let s = match exit_edge {
        0 => ex,
        1 => w + ey,
        2 => 3.0 * w - ex,
        _ => 4.0 * w - ey,
    };
    let kk = i64::from(geo.directions);
    let k_out = match (exit_edge - edge).rem_euclid(4) {
        2 => k,
        1 => (kk + 2 * k + 1).div_euclid(2),
        _ => (2 * k + 1 - kk).div_euclid(2),
    };
    let p_out = snapped_floor(s / geo.extent()).rem_euclid(i64::from(geo.positions));
    ((p_out * kk + k_out) as usize, t)
}

fn geometries() -> Vec<Geometry> {
    vec![
        Geometry::default(),
        Geometry::new(16.0, 8, 16, 3).unwrap(),
        Geometry::new(10.0, 4, 12, 5).unwrap(),
        Geometry::new(16.0, 4, 16, 4).unwrap(),
    ]
}

#[test]
fn transmissive_medium_puts_every_source_in_its_hand_computed_bin() {
    let engine = CpuEngine::new();
    for geo in geometries() {
        let photons = 8;
        let counts = homogeneous(&engine, geo, Material::TRANSMISSIVE, photons);
        for i in 0..geo.sources() {
            let (j, _) = hand_bin(&geo, i);
            assert_eq!(
                counts.row(i)[j],
                photons,
                "{geo:?}: source {i} missed bin {j}: row {:?}",
                counts.row(i)
            );
        }
    }
}

#[test]
fn pure_absorber_follows_beer_lambert() {
    let engine = CpuEngine::new();
    let sigma_a = 0.1;
    for geo in [
        Geometry::new(16.0, 4, 16, 3).unwrap(),
        Geometry::new(16.0, 8, 16, 5).unwrap(),
    ] {
        let photons = 4000;
        let counts = homogeneous(
            &engine,
            geo,
            Material::new(0.0, sigma_a, 0.0).unwrap(),
            photons,
        );
        for i in 0..geo.sources() {
            let (j, chord) = hand_bin(&geo, i);
            let expected = (-sigma_a * chord).exp();
            let row = counts.row(i);
            assert_eq!(
                row.iter().map(|&c| u64::from(c)).sum::<u64>(),
                u64::from(row[j]),
                "light outside bin {j}"
            );
            let f = f64::from(row[j]) / f64::from(photons);
            let se = (expected * (1.0 - expected) / f64::from(photons)).sqrt();
            assert!(
                (f - expected).abs() < 4.0 * se,
                "source {i}: {f} vs exp(-σa·{chord}) = {expected} ± {se}"
            );
        }
    }
}

#[test]
fn opaque_frame_lets_nothing_out() {
    let text = r##"
[geometry]
grid = 8
positions = 16
directions = 3
[map]
legend = { "o" = "opaque", "." = "moderate", "-" = "transmissive" }
rows = ["oooooooo", "o......o", "o.-----o", "o.-..-.o", "o......o", "o..--..o", "o......o", "oooooooo"]
"##;
    let s = Scene::from_toml(text).unwrap();
    let counts = render(
        &CpuEngine::new(),
        s.geometry,
        &s.table.physics(),
        s.assignment,
        3,
        PhotonRange::first_n(500),
    );
    assert_eq!(counts.total(), 0);
}

#[test]
fn rows_never_exceed_one_and_equal_one_without_absorption() {
    let engine = CpuEngine::new();
    let geo = Geometry::new(16.0, 8, 16, 3).unwrap();
    let photons = 2000;
    let lossless = Material::new(0.6, 0.0, 0.75).unwrap();
    let table = [
        lossless,
        Material::TRANSMISSIVE,
        Material::new(1.2, 0.0, -0.9).unwrap(),
    ];
    let assignment: Vec<u16> = (0..geo.pixels()).map(|i| (i * 7 % 3) as u16).collect();
    let counts = render(
        &engine,
        geo,
        &table,
        assignment,
        1,
        PhotonRange::first_n(photons),
    );
    for i in 0..geo.sources() {
        assert_eq!(
            counts.row(i).iter().sum::<u32>(),
            photons,
            "source {i} lost light without absorption"
        );
    }
    let absorbing = homogeneous(&engine, geo, builtin_material("back").unwrap(), photons);
    for i in 0..geo.sources() {
        let sum: u32 = absorbing.row(i).iter().sum();
        assert!(sum <= photons && sum > 0);
    }
}

/// χ² of counts of sources on edge 0 against the same cells rotated by `quarters` × 90°,
/// over cells with at least 20 photons between the two, as a z-score.
fn rotation_z(geo: &Geometry, counts: &CountMatrix, quarters: usize) -> f64 {
    let rot = |mut i: usize| {
        for _ in 0..quarters {
            i = geo.rotate_index(i);
        }
        i
    };
    let per_edge = geo.sources() / 4;
    let (mut chi2, mut dof) = (0.0, 0usize);
    for i in 0..per_edge {
        for j in 0..geo.bins() {
            let a = f64::from(counts.row(i)[j]);
            let b = f64::from(counts.row(rot(i))[rot(j)]);
            if a + b >= 20.0 {
                chi2 += (a - b).powi(2) / (a + b);
                dof += 1;
            }
        }
    }
    assert!(dof > 50, "too few populated cells: {dof}");
    (chi2 - dof as f64) / (2.0 * dof as f64).sqrt()
}

#[test]
fn rotation_symmetric_scene_gives_rotation_symmetric_observations() {
    // grid 8 with 16 positions: sources sit on grid lines, exercising the grid-line rule.
    let symmetric = r##"
[geometry]
grid = 8
positions = 16
directions = 3
[map]
legend = { "." = "moderate", "#" = "opaque", "m" = "mild", "-" = "transmissive", "b" = "back" }
rows = ["........", "..m.-...", "..b..bm.", ".-.##...", "...##.-.", ".mb..b..", "...-.m..", "........"]
"##;
    let s = Scene::from_toml(symmetric).unwrap();
    let n = s.geometry.grid as usize;
    // The map really is invariant under a 90° rotation.
    for r in 0..n {
        for c in 0..n {
            assert_eq!(s.assignment[r * n + c], s.assignment[(n - 1 - c) * n + r]);
        }
    }
    let engine = CpuEngine::new();
    let photons = PhotonRange::first_n(20_000);
    let counts = render(
        &engine,
        s.geometry,
        &s.table.physics(),
        s.assignment.clone(),
        11,
        photons,
    );
    for q in 1..4 {
        let z = rotation_z(&s.geometry, &counts, q);
        assert!(
            z.abs() < 4.0,
            "symmetric scene rejected at {q} quarter turns: z = {z}"
        );
    }
    // The same test rejects a scene that is not symmetric: one more opaque pixel in a corner.
    let mut broken = s.assignment.clone();
    broken[n + 1] = s.table.index_of("opaque").unwrap();
    let counts = render(&engine, s.geometry, &s.table.physics(), broken, 11, photons);
    let z = rotation_z(&s.geometry, &counts, 1);
    assert!(
        z > 10.0,
        "asymmetric scene passed the symmetry test: z = {z}"
    );
}

#[test]
fn same_seed_same_counts_whatever_the_thread_count() {
    let geo = Geometry::new(16.0, 4, 16, 3).unwrap();
    let s = scatterfarm_model::builtin::scene("fig7f").unwrap().unwrap();
    let table = s.table.physics();
    // Down-sample the 16×16 map to 4×4.
    let assignment: Vec<u16> = (0..16)
        .map(|i| s.assignment[(i / 4) * 4 * 16 + (i % 4) * 4 + 1])
        .collect();
    let range = PhotonRange::first_n(3000);
    let one = render(
        &CpuEngine::with_threads(1).unwrap(),
        geo,
        &table,
        assignment.clone(),
        5,
        range,
    );
    let two = render(
        &CpuEngine::with_threads(2).unwrap(),
        geo,
        &table,
        assignment.clone(),
        5,
        range,
    );
    let many = render(
        &CpuEngine::with_threads(7).unwrap(),
        geo,
        &table,
        assignment.clone(),
        5,
        range,
    );
    assert_eq!(one, two);
    assert_eq!(one, many);
    let other_seed = render(&CpuEngine::new(), geo, &table, assignment, 6, range);
    assert_ne!(one, other_seed);
}

#[test]
fn photon_ranges_add_up_exactly_and_batches_equal_single_renders() {
    let engine = CpuEngine::new();
    let geo = Geometry::new(16.0, 4, 16, 3).unwrap();
    let table = [
        builtin_material("moderate").unwrap(),
        Material::OPAQUE,
        builtin_material("back").unwrap(),
    ];
    let a: Vec<u16> = (0..16).map(|i| (i % 3) as u16).collect();
    let b: Vec<u16> = (0..16).map(|i| ((i / 3) % 2) as u16 * 2).collect();
    let whole = render(
        &engine,
        geo,
        &table,
        a.clone(),
        9,
        PhotonRange {
            first: 0,
            count: 2500,
        },
    );
    let mut parts = render(
        &engine,
        geo,
        &table,
        a.clone(),
        9,
        PhotonRange {
            first: 0,
            count: 1234,
        },
    );
    parts
        .add(&render(
            &engine,
            geo,
            &table,
            a.clone(),
            9,
            PhotonRange {
                first: 1234,
                count: 1266,
            },
        ))
        .unwrap();
    assert_eq!(whole, parts);

    let items = [
        RenderItem {
            assignment: a.clone(),
            seed: 9,
        },
        RenderItem {
            assignment: b.clone(),
            seed: 4,
        },
    ];
    let batch = RenderBatch {
        geometry: geo,
        table: &table,
        items: &items,
        photons: PhotonRange::first_n(2500),
    };
    let out = engine.render(&batch).unwrap();
    assert_eq!(out[0].counts, whole);
    assert_eq!(
        out[1].counts,
        render(&engine, geo, &table, b, 4, PhotonRange::first_n(2500))
    );
}

#[test]
fn bad_batches_are_refused() {
    let engine = CpuEngine::new();
    let geo = Geometry::new(16.0, 4, 16, 3).unwrap();
    let table = [Material::TRANSMISSIVE];
    let items = [RenderItem {
        assignment: vec![0; 15],
        seed: 1,
    }];
    let batch = RenderBatch {
        geometry: geo,
        table: &table,
        items: &items,
        photons: PhotonRange::first_n(1),
    };
    assert!(engine.render(&batch).is_err());
    let items = [RenderItem {
        assignment: vec![1; 16],
        seed: 1,
    }];
    let batch = RenderBatch {
        geometry: geo,
        table: &table,
        items: &items,
        photons: PhotonRange::first_n(1),
    };
    assert!(engine.render(&batch).is_err());
}
