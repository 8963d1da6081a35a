//! The boundary geometry of `docs/model.md`: the square medium, its pixel grid, arc length around the
//! boundary, the ideal-ray sources and the (position, direction) bins photons land in.
//!
//! Everything here is pure arithmetic on `f64`; the edge-case rules (bin-edge snapping, corner
//! exits) live in [`Geometry::bin_of_exit`] so every engine bins the same way ([`ExitBins`] is
//! the same function with its constants precomputed, for the CPU tracer).

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use thiserror::Error;

/// Within this distance of a whole number, a bin coordinate snaps to it (`docs/model.md`, "Bin edges").
pub const BIN_SNAP: f64 = 1e-4;

/// Size, grid and boundary sampling of a medium.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Geometry {
    /// Side `W` of the square, in mm.
    pub size_mm: f64,
    /// Pixels per side `N` (a power of two).
    pub grid: u32,
    /// Boundary positions `P` (divisible by 4).
    pub positions: u32,
    /// Directions per position `K`.
    pub directions: u32,
}

/// Why a geometry is not usable.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum GeometryError {
    #[error("size_mm must be a finite number > 0, got {0}")]
    Size(f64),
    #[error("grid must be a power of two between 1 and 4096, got {0}")]
    Grid(u32),
    #[error("positions must be a positive multiple of 4, got {0}")]
    Positions(u32),
    #[error("directions must be at least 1, got {0}")]
    Directions(u32),
    #[error("positions × directions = {0} sources is more than the 65536 supported")]
    TooManySources(u64),
}

impl Default for Geometry {
    fn default() -> Self {
        Geometry {
            size_mm: 16.0,
            grid: 16,
            positions: 128,
            directions: 9,
        }
    }
}

/// One of the four edges, in arc-length order starting at the lower-left corner.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Edge {
    Bottom = 0,
    Right = 1,
    Top = 2,
    Left = 3,
}

impl Edge {
    pub fn from_index(i: u32) -> Edge {
        match i % 4 {
            0 => Edge::Bottom,
            1 => Edge::Right,
            2 => Edge::Top,
            _ => Edge::Left,
        }
    }

    /// The inward unit normal.
    pub fn inward(self) -> [f64; 2] {
        match self {
            Edge::Bottom => [0.0, 1.0],
            Edge::Right => [-1.0, 0.0],
            Edge::Top => [0.0, -1.0],
            Edge::Left => [1.0, 0.0],
        }
    }
}

/// An ideal ray: a start point on the boundary and a unit direction into the medium.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: [f64; 2],
    pub direction: [f64; 2],
}

impl Geometry {
    /// A validated geometry.
    pub fn new(
        size_mm: f64,
        grid: u32,
        positions: u32,
        directions: u32,
    ) -> Result<Self, GeometryError> {
        let g = Geometry {
            size_mm,
            grid,
            positions,
            directions,
        };
        g.validate()?;
        Ok(g)
    }

    pub fn validate(&self) -> Result<(), GeometryError> {
        if !(self.size_mm.is_finite() && self.size_mm > 0.0) {
            return Err(GeometryError::Size(self.size_mm));
        }
        if !(self.grid.is_power_of_two() && self.grid <= 4096) {
            return Err(GeometryError::Grid(self.grid));
        }
        if self.positions == 0 || !self.positions.is_multiple_of(4) {
            return Err(GeometryError::Positions(self.positions));
        }
        if self.directions == 0 {
            return Err(GeometryError::Directions(self.directions));
        }
        let sources = u64::from(self.positions) * u64::from(self.directions);
        if sources > 65536 {
            return Err(GeometryError::TooManySources(sources));
        }
        Ok(())
    }

    /// Number of sources `P·K` (equal to the number of bins).
    pub fn sources(&self) -> usize {
        (self.positions * self.directions) as usize
    }

    /// Number of bins `P·K`.
    pub fn bins(&self) -> usize {
        self.sources()
    }

    /// Number of pixels `N²`.
    pub fn pixels(&self) -> usize {
        (self.grid as usize) * (self.grid as usize)
    }

    /// Pixel side `h = W / N`.
    pub fn pixel_size(&self) -> f64 {
        self.size_mm / f64::from(self.grid)
    }

    /// Extent length `e = 4W / P`.
    pub fn extent(&self) -> f64 {
        4.0 * self.size_mm / f64::from(self.positions)
    }

    /// The point at arc length `s` and the edge it lies on.
    pub fn boundary_point(&self, s: f64) -> ([f64; 2], Edge) {
        let w = self.size_mm;
        if s < w {
            ([s, 0.0], Edge::Bottom)
        } else if s < 2.0 * w {
            ([w, s - w], Edge::Right)
        } else if s < 3.0 * w {
            ([3.0 * w - s, w], Edge::Top)
        } else {
            ([0.0, 4.0 * w - s], Edge::Left)
        }
    }

    /// The centre angle `α_k = −π/2 + (k+½)π/K` from the inward normal, computed so that the
    /// straight-ahead direction of odd `K` is exactly 0.
    pub fn direction_angle(&self, k: u32) -> f64 {
        let numerator = 2.0 * f64::from(k) + 1.0 - f64::from(self.directions);
        numerator * PI / (2.0 * f64::from(self.directions))
    }

    /// Source `i = p·K + k`: the centre of extent `p`, along the inward normal turned by `α_k`.
    pub fn source_ray(&self, source: usize) -> Ray {
        let k = (source % self.directions as usize) as u32;
        let p = (source / self.directions as usize) as u32;
        let s = (f64::from(p) + 0.5) * self.extent();
        let (origin, edge) = self.boundary_point(s);
        let n = edge.inward();
        let alpha = self.direction_angle(k);
        let (sin_a, cos_a) = if alpha == 0.0 {
            (0.0, 1.0)
        } else {
            alpha.sin_cos()
        };
        let direction = [n[0] * cos_a - n[1] * sin_a, n[0] * sin_a + n[1] * cos_a];
        Ray { origin, direction }
    }

    /// Arc length of a boundary point known to lie on `edge` (the other coordinate clamped).
    pub fn arc_length_on(&self, edge: Edge, point: [f64; 2]) -> f64 {
        let w = self.size_mm;
        match edge {
            Edge::Bottom => point[0].clamp(0.0, w),
            Edge::Right => w + point[1].clamp(0.0, w),
            Edge::Top => 3.0 * w - point[0].clamp(0.0, w),
            Edge::Left => 4.0 * w - point[1].clamp(0.0, w),
        }
    }

    /// The bin `j = p'·K + k'` of a photon leaving at arc length `s` with unit direction `d`.
    ///
    /// Applies `docs/model.md`'s rules: `u = s/e` and `u = (β+π/2)·K/π` snap to a whole number within
    /// [`BIN_SNAP`] (an edge belongs to the upper bin); `s = 4W` wraps to 0; a corner belongs to
    /// the edge whose arc-length interval starts there, and `β` is measured from that edge's
    /// outward normal. Both indices are clamped into range.
    pub fn bin_of_exit(&self, s: f64, d: [f64; 2]) -> usize {
        let positions = self.positions as i64;
        let mut p = snapped_floor(s / self.extent());
        if p >= positions {
            p -= positions;
        }
        let p = p.clamp(0, positions - 1);
        let edge = Edge::from_index((p / (positions / 4)) as u32);
        let inward = edge.inward();
        let outward = [-inward[0], -inward[1]];
        let cos_b = outward[0] * d[0] + outward[1] * d[1];
        let sin_b = outward[0] * d[1] - outward[1] * d[0];
        let beta = sin_b.atan2(cos_b);
        let k = snapped_floor((beta + PI / 2.0) * f64::from(self.directions) / PI)
            .clamp(0, i64::from(self.directions) - 1);
        (p as usize) * self.directions as usize + k as usize
    }

    /// Source (or bin) index after rotating the medium 90° counter-clockwise.
    pub fn rotate_index(&self, index: usize) -> usize {
        let k = self.directions as usize;
        let p = index / k;
        let p_rot = (p + self.positions as usize / 4) % self.positions as usize;
        p_rot * k + index % k
    }
}

/// [`Geometry::bin_of_exit`] with its per-geometry constants worked out once, for tracers that
/// bin one photon after another: no `atan2`, no division, no `round`/`floor` library calls.
///
/// The direction bin is found by comparing `sin β` with the sines of the snapped bin edges
/// `β_m − δ` (`m = 1 … K−1`, `δ = BIN_SNAP·π/K`), which orders exits exactly as the snapped `u`
/// does because `sin` increases on `(−π/2, π/2)`; a direction with `cos β ≤ 0` (only possible
/// through rounding at grazing exits) falls back to [`Geometry::bin_of_exit`]. Both therefore
/// agree except for `u` within rounding of a snapping threshold `m ± BIN_SNAP`.
#[derive(Debug, Clone)]
pub struct ExitBins {
    geometry: Geometry,
    inv_extent: f64,
    /// `sin(β_m − δ)` for `m = 1 … K−1`, increasing.
    thresholds: Vec<f64>,
}

impl ExitBins {
    pub fn new(geometry: &Geometry) -> ExitBins {
        let k = f64::from(geometry.directions);
        let thresholds = (1..geometry.directions)
            .map(|m| (-PI / 2.0 + (f64::from(m) - BIN_SNAP) * PI / k).sin())
            .collect();
        ExitBins {
            geometry: *geometry,
            inv_extent: 1.0 / geometry.extent(),
            thresholds,
        }
    }

    /// The bin of a photon leaving at arc length `s` with unit direction `d`; the same as
    /// [`Geometry::bin_of_exit`] (see the type's note).
    #[inline]
    pub fn bin(&self, s: f64, d: [f64; 2]) -> usize {
        let positions = i64::from(self.geometry.positions);
        let u = s * self.inv_extent;
        let mut p = if u >= 0.0 {
            // u − ⌊u⌋ is exact here, so this is `snapped_floor` without library calls.
            let f = u as i64;
            let frac = u - f as f64;
            if frac - 1.0 >= -BIN_SNAP {
                f + 1
            } else {
                f
            }
        } else {
            snapped_floor(u)
        };
        if p >= positions {
            p -= positions;
        }
        let p = p.clamp(0, positions - 1);
        // Outward normals: bottom (0,−1), right (1,0), top (0,1), left (−1,0).
        let (cos_b, sin_b) = match p / (positions / 4) {
            0 => (-d[1], d[0]),
            1 => (d[0], d[1]),
            2 => (d[1], -d[0]),
            _ => (-d[0], -d[1]),
        };
        if cos_b <= 0.0 {
            return self.geometry.bin_of_exit(s, d);
        }
        let k = if self.thresholds.len() <= 32 {
            self.thresholds
                .iter()
                .map(|&t| usize::from(sin_b >= t))
                .sum()
        } else {
            self.thresholds.partition_point(|&t| t <= sin_b)
        };
        (p as usize) * self.geometry.directions as usize + k
    }
}

/// `⌊u⌋`, except that `u` within [`BIN_SNAP`] of a whole number counts as that number.
pub fn snapped_floor(u: f64) -> i64 {
    let n = u.round();
    if (u - n).abs() <= BIN_SNAP {
        n as i64
    } else {
        u.floor() as i64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation() {
        assert!(Geometry::default().validate().is_ok());
        assert_eq!(
            Geometry::new(16.0, 12, 128, 9),
            Err(GeometryError::Grid(12))
        );
        assert_eq!(
            Geometry::new(16.0, 16, 126, 9),
            Err(GeometryError::Positions(126))
        );
        assert_eq!(
            Geometry::new(16.0, 16, 128, 0),
            Err(GeometryError::Directions(0))
        );
        assert!(matches!(
            Geometry::new(-1.0, 16, 128, 9),
            Err(GeometryError::Size(_))
        ));
    }

    #[test]
    fn sources_start_on_the_boundary_pointing_inward() {
        let g = Geometry::default();
        for i in 0..g.sources() {
            let ray = g.source_ray(i);
            let [x, y] = ray.origin;
            let on_edge = x == 0.0 || y == 0.0 || x == g.size_mm || y == g.size_mm;
            assert!(on_edge, "source {i} at {x},{y}");
            let norm = ray.direction[0].hypot(ray.direction[1]);
            assert!((norm - 1.0).abs() < 1e-12);
            // A small step inward stays inside the square.
            let (px, py) = (x + 1e-6 * ray.direction[0], y + 1e-6 * ray.direction[1]);
            assert!(
                (0.0..=g.size_mm).contains(&px) && (0.0..=g.size_mm).contains(&py),
                "source {i}"
            );
        }
    }

    #[test]
    fn straight_ahead_is_exact_for_odd_k() {
        let g = Geometry::default();
        assert_eq!(g.direction_angle(4), 0.0);
        assert_eq!(g.source_ray(4).direction, [0.0, 1.0]);
    }

    #[test]
    fn corners_belong_to_the_edge_starting_there() {
        let g = Geometry::new(16.0, 4, 16, 3).unwrap();
        // Leaving through the lower-right corner, heading right: first extent of the right edge.
        let j = g.bin_of_exit(16.0, [1.0, 0.0]);
        assert_eq!(j / 3, 4);
        // s = 4W wraps to the bottom edge's first extent.
        let j = g.bin_of_exit(64.0, [0.0, -1.0]);
        assert_eq!(j / 3, 0);
    }

    #[test]
    fn bin_edges_belong_to_the_upper_bin() {
        let g = Geometry::new(16.0, 4, 16, 3).unwrap();
        // β = π/6 from the bottom's outward normal (0,−1) is exactly the edge between k'=1 and 2.
        let beta = PI / 6.0;
        let d = [beta.sin(), -beta.cos()];
        assert_eq!(g.bin_of_exit(2.0, d) % 3, 2);
        assert_eq!(snapped_floor(2.99995), 3);
        assert_eq!(snapped_floor(2.9998), 2);
    }

    /// The fast binner agrees with the reference on random exits and on every bin edge.
    #[test]
    fn exit_bins_agree_with_bin_of_exit() {
        for g in [
            Geometry::default(),
            Geometry::new(16.0, 4, 16, 3).unwrap(),
            Geometry::new(10.0, 4, 12, 4).unwrap(),
            Geometry::new(16.0, 4, 4, 1).unwrap(),
            Geometry::new(16.0, 4, 8, 40).unwrap(),
        ] {
            let fast = ExitBins::new(&g);
            let w = g.size_mm;
            let k = f64::from(g.directions);
            let mut state = 0x9e37_79b9_7f4a_7c15u64;
            let mut uniform = || {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            };
            let check = |s: f64, beta: f64| {
                let p = (snapped_floor(s / g.extent()).rem_euclid(i64::from(g.positions))) as u32;
                let edge = Edge::from_index(p / (g.positions / 4));
                let out = edge.inward().map(|c| -c);
                let (sin_b, cos_b) = beta.sin_cos();
                let d = [
                    out[0] * cos_b - out[1] * sin_b,
                    out[0] * sin_b + out[1] * cos_b,
                ];
                assert_eq!(fast.bin(s, d), g.bin_of_exit(s, d), "{g:?} s={s} β={beta}");
            };
            for _ in 0..20_000 {
                check(4.0 * w * uniform(), (uniform() - 0.5) * PI);
            }
            // Exactly on, and just around, every position and direction edge.
            for p in 0..=g.positions {
                for m in 0..=g.directions {
                    for ds in [-2e-4, -1e-4 + 1e-9, 0.0, 1e-4 - 1e-9, 2e-4] {
                        for du in [-2e-4, -1e-4 + 1e-9, 0.0, 1e-4 - 1e-9, 2e-4] {
                            let s = ((f64::from(p) + ds) * g.extent()).clamp(0.0, 4.0 * w);
                            let u = (f64::from(m) + du).clamp(1e-6, k - 1e-6);
                            check(s, -PI / 2.0 + u * PI / k);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn rotation_maps_positions_by_a_quarter() {
        let g = Geometry::new(16.0, 4, 16, 3).unwrap();
        assert_eq!(g.rotate_index(0), 12);
        assert_eq!(g.rotate_index(3 * 13 + 2), 3 + 2);
    }
}
