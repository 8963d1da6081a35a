//! The built-in scenes: twelve 16×16 scenes modelled on the paper's Fig. 7 (a)–(l), a coarse
//! Shepp–Logan phantom (moderate background, mild object) at 16×16 and 128×128, and `demo8`, a
//! small scene for a first reconstruction.
//!
//! The Fig. 7 scenes are TOML files in `worker/model/scenes/`, compiled in; the phantoms are
//! rasterized here from the modified Shepp–Logan ellipses.

use crate::geometry::Geometry;
use crate::material::{builtin_material, MaterialTable};
use crate::scene::{Scene, SceneError};

/// A built-in scene's name and a one-line description.
#[derive(Debug, Clone, Copy)]
pub struct BuiltinInfo {
    pub name: &'static str,
    pub description: &'static str,
}

const FIG7: [(&str, &str, &str); 12] = [
    ("fig7a", "moderate background with mild objects", include_str!("../scenes/fig7a.toml")),
    ("fig7b", "moderate background with opaque objects", include_str!("../scenes/fig7b.toml")),
    ("fig7c", "transmissive background with moderate objects", include_str!("../scenes/fig7c.toml")),
    ("fig7d", "moderate background with transmissive and opaque objects", include_str!("../scenes/fig7d.toml")),
    ("fig7e", "moderate background with transmissive, opaque and uniform objects", include_str!("../scenes/fig7e.toml")),
    ("fig7f", "moderate background with back, opaque and uniform objects", include_str!("../scenes/fig7f.toml")),
    ("fig7g", "transmissive background with moderate, mild and opaque objects", include_str!("../scenes/fig7g.toml")),
    ("fig7h", "transmissive background with mild, uniform and back objects", include_str!("../scenes/fig7h.toml")),
    ("fig7i", "moderate background with mild, uniform and back objects (paper: all six materials searched)", include_str!("../scenes/fig7i.toml")),
    ("fig7j", "tunnel: transmissive background, opaque objects hidden behind a floating opaque block", include_str!("../scenes/fig7j.toml")),
    ("fig7k", "tunnel: moderate background, opaque objects hidden behind a floating opaque block", include_str!("../scenes/fig7k.toml")),
    ("fig7l", "tunnel: mild background, opaque objects hidden behind a floating opaque block", include_str!("../scenes/fig7l.toml")),
];

const DEMO: (&str, &str, &str) = (
    "demo8",
    "small 8x8 scene for a first reconstruction: moderate background, opaque block, back-scattering bar",
    include_str!("../scenes/demo8.toml"),
);

const PHANTOMS: [(&str, &str, u32); 2] = [
    (
        "phantom16",
        "coarse Shepp-Logan phantom, 16x16: moderate background, mild object",
        16,
    ),
    (
        "phantom128",
        "coarse Shepp-Logan phantom, 128x128: moderate background, mild object",
        128,
    ),
];

/// Every built-in scene, in listing order.
pub fn list() -> Vec<BuiltinInfo> {
    FIG7.iter()
        .map(|(name, description, _)| BuiltinInfo { name, description })
        .chain(
            PHANTOMS
                .iter()
                .map(|(name, description, _)| BuiltinInfo { name, description }),
        )
        .chain(std::iter::once(BuiltinInfo {
            name: DEMO.0,
            description: DEMO.1,
        }))
        .collect()
}

/// A built-in scene's TOML text, or `None` for an unknown name.
pub fn toml(name: &str) -> Option<String> {
    if name == DEMO.0 {
        return Some(DEMO.2.to_string());
    }
    if let Some((_, _, text)) = FIG7.iter().find(|(n, _, _)| *n == name) {
        return Some((*text).to_string());
    }
    PHANTOMS
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, description, grid)| {
            format!("# {name}: {description}.\n{}", phantom(*grid).to_toml())
        })
}

/// A built-in scene, parsed.
pub fn scene(name: &str) -> Option<Result<Scene, SceneError>> {
    toml(name).map(|text| Scene::from_toml(&text))
}

/// The modified Shepp–Logan ellipses: intensity, semi-axes a, b, centre x0, y0, angle (degrees).
const SHEPP_LOGAN: [[f64; 6]; 10] = [
    [1.0, 0.69, 0.92, 0.0, 0.0, 0.0],
    [-0.8, 0.6624, 0.874, 0.0, -0.0184, 0.0],
    [-0.2, 0.11, 0.31, 0.22, 0.0, -18.0],
    [-0.2, 0.16, 0.41, -0.22, 0.0, 18.0],
    [0.1, 0.21, 0.25, 0.0, 0.35, 0.0],
    [0.1, 0.046, 0.046, 0.0, 0.1, 0.0],
    [0.1, 0.046, 0.046, 0.0, -0.1, 0.0],
    [0.1, 0.046, 0.023, -0.08, -0.605, 0.0],
    [0.1, 0.023, 0.023, 0.0, -0.606, 0.0],
    [0.1, 0.023, 0.046, 0.06, -0.605, 0.0],
];

fn shepp_logan(x: f64, y: f64) -> f64 {
    SHEPP_LOGAN
        .iter()
        .filter(|[_, a, b, x0, y0, phi]| {
            let (s, c) = phi.to_radians().sin_cos();
            let (dx, dy) = (x - x0, y - y0);
            let (u, v) = (dx * c + dy * s, -dx * s + dy * c);
            (u / a).powi(2) + (v / b).powi(2) <= 1.0
        })
        .map(|e| e[0])
        .sum()
}

/// The phantom at `grid × grid`: a pixel is `mild` where the phantom's mean intensity over 4×4
/// samples is at least 0.1 (skull, brain and small features), `moderate` elsewhere (outside
/// and the two dark ventricles).
fn phantom(grid: u32) -> Scene {
    let geometry = Geometry {
        grid,
        ..Geometry::default()
    };
    let mut table = MaterialTable::default();
    // Both names are in the built-in dictionary.
    let moderate = table.push(
        "moderate",
        builtin_material("moderate").unwrap_or(crate::Material::TRANSMISSIVE),
    );
    let mild = table.push(
        "mild",
        builtin_material("mild").unwrap_or(crate::Material::TRANSMISSIVE),
    );
    let n = grid as usize;
    let sub = 4;
    let mut assignment = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let mut sum = 0.0;
            for i in 0..sub {
                for j in 0..sub {
                    let x = ((c * sub + j) as f64 + 0.5) / (n * sub) as f64 * 2.0 - 1.0;
                    let y = 1.0 - ((r * sub + i) as f64 + 0.5) / (n * sub) as f64 * 2.0;
                    sum += shepp_logan(x, y);
                }
            }
            assignment.push(if sum / (sub * sub) as f64 >= 0.1 {
                mild
            } else {
                moderate
            });
        }
    }
    Scene {
        geometry,
        table,
        symbols: vec!['.', 'm'],
        assignment,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_parses_with_its_expected_grid() {
        for info in list() {
            let scene = scene(info.name)
                .unwrap()
                .unwrap_or_else(|e| panic!("{}: {e}", info.name));
            let expected = match info.name {
                "phantom128" => 128,
                "demo8" => 8,
                _ => 16,
            };
            assert_eq!(scene.geometry.grid, expected, "{}", info.name);
            assert!(scene.table.len() >= 2, "{} has one material", info.name);
        }
        assert!(scene("fig7z").is_none());
    }

    #[test]
    fn phantom_has_a_mild_head_with_moderate_holes() {
        let s = phantom(16);
        let mild = s.assignment.iter().filter(|&&i| i == 1).count();
        assert!(mild > 60 && mild < 200, "{mild}");
        // Corners are background, the centre row has the dark ventricles.
        assert_eq!(s.assignment[0], 0);
        let centre_row = &s.assignment[8 * 16..9 * 16];
        assert!(centre_row.contains(&0) && centre_row.contains(&1));
    }

    /// The tunnel scenes: every straight line through the two leftmost objects crosses the
    /// floating opaque block.
    #[test]
    fn tunnel_hides_the_two_leftmost_objects() {
        let s = scene("fig7j").unwrap().unwrap();
        let opaque = |r: i64, c: i64| {
            (0..16).contains(&r)
                && (0..16).contains(&c)
                && s.material_at(r as usize, c as usize).is_opaque()
        };
        // Block pixels: the C-shaped wall (rows 1 and 14, and column 9).
        let block = |r: i64, c: i64| opaque(r, c) && (r == 1 || r == 14 || c == 9);
        for (r0, c0) in [
            (4, 3),
            (4, 4),
            (5, 3),
            (5, 4),
            (10, 4),
            (10, 5),
            (11, 4),
            (11, 5),
        ] {
            assert!(opaque(r0, c0));
            for a in 0..720 {
                let phi = (a as f64 + 0.25) * std::f64::consts::PI / 720.0;
                let (dy, dx) = phi.sin_cos();
                let hit = [1.0, -1.0].iter().any(|sign| {
                    (1..4000).any(|step| {
                        let t = sign * step as f64 * 0.005;
                        let (y, x) = (r0 as f64 + 0.5 + t * dy, c0 as f64 + 0.5 + t * dx);
                        block(y.floor() as i64, x.floor() as i64)
                    })
                });
                assert!(
                    hit,
                    "a line through ({r0},{c0}) at {phi} rad misses the block"
                );
            }
        }
    }
}
