//! Flatland photon transport through a pixel grid, exactly as `docs/model.md` ("Transport") says:
//! exact grid traversal, opaque pixels absorb on entry, analog absorption, flatland HG.
//!
//! [`Medium`] is a material assignment laid out for the tracer; [`trace_photon`] follows one
//! photon from its source to its bin (or its absorption) using that photon's own random stream.
//!
//! **Homogeneous blocks.** [`Medium::new`] covers the grid with the largest aligned power-of-two
//! squares of pixels that hold one material (the whole grid for a homogeneous medium). A flight
//! that starts in such a block and whose collision point `pos + (τ/σt)·dir` lies in the block's
//! closed square collides there without walking the grid: marching cell by cell through one
//! material spends τ at the same rate, so it would stop at the same point. Only flights that
//! leave their block take the exact grid traversal (`march`), with its corner and grid-line
//! rules; a flight that leaves a block covering the whole grid leaves the medium, and its exit
//! point is found by intersecting the ray with the square (`exit_straight`, with the same corner
//! rule). A ray running exactly along a block's side stays in the pixel the grid-line rule gave
//! it, because the closed square includes that side.

use crate::phase::{turn, HgTurn};
use crate::rng::{ln_open01, PhotonStream};
use crate::rules::{start_pixel, uniform_block_levels, CORNER_TOLERANCE};
use scatterfarm_model::geometry::{Edge, ExitBins, Geometry, Ray};
use scatterfarm_model::material::Material;

/// One pixel's material, in the form the tracer uses.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Cell {
    /// Extinction σt (mm⁻¹); 0 for transmissive.
    sigma_t: f64,
    /// 1/σt; +∞ for transmissive (and opaque, never used).
    inv_sigma_t: f64,
    /// Probability that a collision absorbs: σa/σt.
    absorb: f64,
    /// HG parameter, prepared for sampling.
    turn: HgTurn,
    opaque: bool,
}

/// An aligned square of pixels that all hold one material.
#[derive(Debug, Clone, Copy)]
struct Block {
    /// Lower-left and upper-right corners of the closed square, in mm.
    lo: [f64; 2],
    hi: [f64; 2],
    /// First and last pixel index along x and y.
    first: [i64; 2],
    last: [i64; 2],
    /// The block is the whole grid: leaving it is leaving the medium.
    whole: bool,
}

/// A material assignment over a geometry's grid, ready to trace.
#[derive(Debug, Clone)]
pub struct Medium {
    geometry: Geometry,
    /// Indexed `iy * N + ix` with `iy` counted from the **bottom** (the tracer's y points up).
    cells: Vec<Cell>,
    /// The block of each pixel (same indexing), an index into `blocks`.
    block_of: Vec<u32>,
    blocks: Vec<Block>,
    bins: ExitBins,
    h: f64,
    inv_h: f64,
}

/// How a photon ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fate {
    /// Left the medium into bin `j`.
    Exited(usize),
    /// Absorbed in a collision or by an opaque pixel.
    Absorbed,
}

/// A photon's fate and the number of scattering events along its path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Trace {
    pub fate: Fate,
    pub scatters: u32,
}

impl Medium {
    /// `assignment` holds `N²` indices into `table`, row-major with row 0 at the **top**.
    /// The caller has checked that every index is in range.
    pub fn new(geometry: Geometry, table: &[Material], assignment: &[u16]) -> Medium {
        let n = geometry.grid as usize;
        let mut cells = Vec::with_capacity(n * n);
        for iy in 0..n {
            let row = n - 1 - iy;
            for ix in 0..n {
                let m = table[assignment[row * n + ix] as usize];
                let sigma_t = m.sigma_t();
                let opaque = m.is_opaque();
                let sigma_t = if opaque { 0.0 } else { sigma_t };
                cells.push(Cell {
                    sigma_t,
                    inv_sigma_t: 1.0 / sigma_t,
                    absorb: if sigma_t > 0.0 {
                        m.sigma_a / sigma_t
                    } else {
                        0.0
                    },
                    turn: HgTurn::new(m.g),
                    opaque,
                });
            }
        }
        let (block_of, blocks) = homogeneous_blocks(&geometry, &cells);
        let h = geometry.pixel_size();
        Medium {
            geometry,
            cells,
            block_of,
            blocks,
            bins: ExitBins::new(&geometry),
            h,
            inv_h: 1.0 / h,
        }
    }

    pub fn geometry(&self) -> &Geometry {
        &self.geometry
    }

    #[inline]
    fn cell(&self, ix: i64, iy: i64) -> &Cell {
        &self.cells[(iy as usize) * self.geometry.grid as usize + ix as usize]
    }

    /// The distances from `pos` (in the closed square) along `dir` to the square's vertical
    /// and horizontal sides (infinite along a side's direction).
    fn side_distances(&self, pos: [f64; 2], dir: [f64; 2]) -> (f64, f64) {
        let w = self.geometry.size_mm;
        let dist = |p: f64, d: f64| {
            if d > 0.0 {
                (w - p) / d
            } else if d < 0.0 {
                -p / d
            } else {
                f64::INFINITY
            }
        };
        (dist(pos[0], dir[0]), dist(pos[1], dir[1]))
    }

    /// The distance from `pos` (in the closed square) along `dir` to the square's boundary.
    fn exit_length(&self, pos: [f64; 2], dir: [f64; 2]) -> f64 {
        let (tx, ty) = self.side_distances(pos, dir);
        tx.min(ty)
    }

    /// The tracer's cell index of the pixel at assignment index `p` (row 0 at the top).
    pub fn cell_of_pixel(&self, p: usize) -> usize {
        let n = self.geometry.grid as usize;
        let (row, ix) = (p / n, p % n);
        (n - 1 - row) * n + ix
    }

    /// The bin of a photon at `pos` (in the closed square) leaving along `dir` without another
    /// collision: the first side of the square the ray meets, or the corner it meets both at.
    fn exit_straight(&self, pos: [f64; 2], dir: [f64; 2]) -> usize {
        let w = self.geometry.size_mm;
        let (tx, ty) = self.side_distances(pos, dir);
        let s = if (tx - ty).abs() <= CORNER_TOLERANCE * self.h {
            // Through a corner: the edge whose arc-length interval starts there.
            corner_arc_length(dir[0] > 0.0, dir[1] > 0.0, w)
        } else if tx < ty {
            let y = pos[1] + tx * dir[1];
            let edge = if dir[0] > 0.0 {
                Edge::Right
            } else {
                Edge::Left
            };
            self.geometry.arc_length_on(edge, [w, y])
        } else {
            let x = pos[0] + ty * dir[0];
            let edge = if dir[1] > 0.0 {
                Edge::Top
            } else {
                Edge::Bottom
            };
            self.geometry.arc_length_on(edge, [x, w])
        };
        self.bins.bin(s, dir)
    }
}

/// Covers the grid with the largest aligned power-of-two squares of equal cells
/// ([`uniform_block_levels`]): returns each cell's block index and the blocks.
fn homogeneous_blocks(geometry: &Geometry, cells: &[Cell]) -> (Vec<u32>, Vec<Block>) {
    let n = geometry.grid as usize;
    let h = geometry.pixel_size();
    let whole = n.trailing_zeros() as u8;
    let levels = uniform_block_levels(cells, n);
    let mut block_of = vec![u32::MAX; n * n];
    let mut blocks = Vec::new();
    for iy in 0..n {
        for ix in 0..n {
            if block_of[iy * n + ix] != u32::MAX {
                continue;
            }
            // Scanning row by row from the bottom left meets an aligned block at its corner.
            let level = levels[iy * n + ix];
            let size = 1usize << level;
            let (x0, y0) = (ix & !(size - 1), iy & !(size - 1));
            let id = blocks.len() as u32;
            for y in y0..y0 + size {
                block_of[y * n + x0..y * n + x0 + size].fill(id);
            }
            let (last_x, last_y) = (x0 + size - 1, y0 + size - 1);
            blocks.push(Block {
                lo: [x0 as f64 * h, y0 as f64 * h],
                hi: if level == whole {
                    [geometry.size_mm; 2]
                } else {
                    [(last_x + 1) as f64 * h, (last_y + 1) as f64 * h]
                },
                first: [x0 as i64, y0 as i64],
                last: [last_x as i64, last_y as i64],
                whole: level == whole,
            });
        }
    }
    (block_of, blocks)
}

/// Arc length of the corner a photon leaves through heading right (`right`) and up (`up`).
fn corner_arc_length(right: bool, up: bool, w: f64) -> f64 {
    match (right, up) {
        (false, false) => 0.0,
        (true, false) => w,
        (true, true) => 2.0 * w,
        (false, true) => 3.0 * w,
    }
}

/// What a traced photon did in each pixel, for differential renders (`docs/model.md`,
/// "Differential renders"). Cells are the tracer's indices (`iy * N + ix`, `iy` from the
/// bottom). A plain render uses [`NoTally`], which the compiler removes.
pub trait Tally {
    /// Whether the tracer reports to this tally at all.
    const ACTIVE: bool;
    /// The photon flew `length` mm inside `cell`.
    fn length(&mut self, cell: usize, length: f64);
    /// The photon scattered in `cell`, turning by an angle of cosine `cos`.
    fn scatter(&mut self, cell: usize, cos: f64);
}

/// The tally of a plain render: nothing.
pub struct NoTally;

impl Tally for NoTally {
    const ACTIVE: bool = false;
    #[inline(always)]
    fn length(&mut self, _: usize, _: f64) {}
    #[inline(always)]
    fn scatter(&mut self, _: usize, _: f64) {}
}

/// Splits a straight flight of `length` from `pos` along `dir`, starting in pixel `(ix, iy)`,
/// into its pieces per pixel (a flight the homogeneous-block shortcut did not walk).
fn split_flight<T: Tally>(
    medium: &Medium,
    pos: [f64; 2],
    dir: [f64; 2],
    length: f64,
    (mut ix, mut iy): (i64, i64),
    tally: &mut T,
) {
    let n = medium.geometry.grid as i64;
    let h = medium.h;
    let step_x: i64 = if dir[0] > 0.0 { 1 } else { -1 };
    let step_y: i64 = if dir[1] > 0.0 { 1 } else { -1 };
    let next_line = |i: i64, step: i64| (if step > 0 { i + 1 } else { i }) as f64 * h;
    let mut t_max_x = if dir[0] != 0.0 {
        ((next_line(ix, step_x) - pos[0]) / dir[0]).max(0.0)
    } else {
        f64::INFINITY
    };
    let mut t_max_y = if dir[1] != 0.0 {
        ((next_line(iy, step_y) - pos[1]) / dir[1]).max(0.0)
    } else {
        f64::INFINITY
    };
    let t_delta_x = h / dir[0].abs();
    let t_delta_y = h / dir[1].abs();
    let mut t = 0.0;
    loop {
        let t_next = t_max_x.min(t_max_y).min(length);
        if t_next > t {
            tally.length((iy * n + ix) as usize, t_next - t);
        }
        t = t_next;
        if t >= length {
            return;
        }
        if t_max_x <= t_max_y {
            ix = (ix + step_x).clamp(0, n - 1);
            t_max_x += t_delta_x;
        } else {
            iy = (iy + step_y).clamp(0, n - 1);
            t_max_y += t_delta_y;
        }
    }
}

/// Follows one photon of source `ray` (source index `source`) with stream `rng` to its fate.
pub fn trace_photon(medium: &Medium, ray: &Ray, rng: &mut PhotonStream) -> Trace {
    trace_photon_tallied(medium, ray, rng, &mut NoTally)
}

/// [`trace_photon`], reporting the photon's path to `tally`: the same random numbers, the same
/// fate.
pub fn trace_photon_tallied<T: Tally>(
    medium: &Medium,
    ray: &Ray,
    rng: &mut PhotonStream,
    tally: &mut T,
) -> Trace {
    let geo = &medium.geometry;
    let n = geo.grid as i64;
    let mut pos = ray.origin;
    let mut dir = ray.direction;
    let (mut ix, mut iy) = start_pixel(geo, pos, dir);
    let mut scatters = 0u32;

    if medium.cell(ix, iy).opaque {
        return Trace {
            fate: Fate::Absorbed,
            scatters,
        };
    }

    loop {
        // A new flight: optical depth to spend, from `pos` along `dir`.
        let tau = -ln_open01(rng.uniform());
        let index = (iy * n + ix) as usize;
        let cell = medium.cells[index];
        let block = &medium.blocks[medium.block_of[index] as usize];
        let d = tau * cell.inv_sigma_t;
        let next = [pos[0] + d * dir[0], pos[1] + d * dir[1]];
        // Transmissive: d = ∞ gives ±∞ or NaN, never inside.
        let inside = (next[0] >= block.lo[0])
            & (next[0] <= block.hi[0])
            & (next[1] >= block.lo[1])
            & (next[1] <= block.hi[1]);
        let cell = if inside {
            if T::ACTIVE {
                split_flight(medium, pos, dir, d, (ix, iy), tally);
            }
            pos = next;
            ix = ((next[0] * medium.inv_h) as i64).clamp(block.first[0], block.last[0]);
            iy = ((next[1] * medium.inv_h) as i64).clamp(block.first[1], block.last[1]);
            cell
        } else if block.whole {
            if T::ACTIVE {
                let length = medium.exit_length(pos, dir);
                split_flight(medium, pos, dir, length, (ix, iy), tally);
            }
            return Trace {
                fate: Fate::Exited(medium.exit_straight(pos, dir)),
                scatters,
            };
        } else {
            match march(medium, &mut pos, dir, tau, &mut ix, &mut iy, tally) {
                Some(fate) => return Trace { fate, scatters },
                None => *medium.cell(ix, iy),
            }
        };

        // Collision inside pixel (ix, iy).
        if rng.uniform() < cell.absorb {
            return Trace {
                fate: Fate::Absorbed,
                scatters,
            };
        }
        scatters += 1;
        let turned = cell.turn.sample(rng.uniform());
        if T::ACTIVE {
            tally.scatter((iy * n + ix) as usize, turned.0);
        }
        // A rotation keeps |dir| = 1 to within a few ulps per event; no renormalization needed.
        dir = turn(dir, turned);
    }
}

/// One flight by exact grid traversal from `pos` in pixel `(ix, iy)` along `dir`, spending
/// optical depth `tau`. Returns `None` after a collision (`pos`, `ix`, `iy` updated to it) and
/// the photon's fate if it left the medium or entered an opaque pixel.
fn march<T: Tally>(
    medium: &Medium,
    pos: &mut [f64; 2],
    dir: [f64; 2],
    mut tau: f64,
    ix: &mut i64,
    iy: &mut i64,
    tally: &mut T,
) -> Option<Fate> {
    let geo = &medium.geometry;
    let n = geo.grid as i64;
    let h = medium.h;
    let w = geo.size_mm;
    let step_x: i64 = if dir[0] > 0.0 { 1 } else { -1 };
    let step_y: i64 = if dir[1] > 0.0 { 1 } else { -1 };
    // Distances along the ray to the next vertical and horizontal grid lines, and between
    // successive ones (infinite for a ray parallel to those lines).
    let inv = [1.0 / dir[0], 1.0 / dir[1]];
    let next_line = |i: i64, step: i64| (if step > 0 { i + 1 } else { i }) as f64 * h;
    let mut t_max_x = if dir[0] != 0.0 {
        ((next_line(*ix, step_x) - pos[0]) * inv[0]).max(0.0)
    } else {
        f64::INFINITY
    };
    let mut t_max_y = if dir[1] != 0.0 {
        ((next_line(*iy, step_y) - pos[1]) * inv[1]).max(0.0)
    } else {
        f64::INFINITY
    };
    let t_delta_x = h * inv[0].abs();
    let t_delta_y = h * inv[1].abs();
    let mut t = 0.0;

    loop {
        let cell = medium.cell(*ix, *iy);
        let t_next = t_max_x.min(t_max_y);
        let spend = cell.sigma_t * (t_next - t);
        if spend >= tau {
            let at = t + tau * cell.inv_sigma_t;
            if T::ACTIVE {
                tally.length((*iy * n + *ix) as usize, at - t);
            }
            *pos = [pos[0] + at * dir[0], pos[1] + at * dir[1]];
            return None;
        }
        if T::ACTIVE {
            tally.length((*iy * n + *ix) as usize, t_next - t);
        }
        tau -= spend;
        t = t_next;
        // Cross into the next pixel: one axis, or both at once through a corner.
        let corner = (t_max_x - t_max_y).abs() <= CORNER_TOLERANCE * h;
        let (cross_x, cross_y) = if corner {
            (true, true)
        } else {
            (t_max_x < t_max_y, t_max_y < t_max_x)
        };
        if cross_x {
            *ix += step_x;
            t_max_x += t_delta_x;
        }
        if cross_y {
            *iy += step_y;
            t_max_y += t_delta_y;
        }
        let out_x = *ix < 0 || *ix >= n;
        let out_y = *iy < 0 || *iy >= n;
        if out_x || out_y {
            let exit = [pos[0] + t * dir[0], pos[1] + t * dir[1]];
            let s = match (out_x, out_y) {
                (true, true) => corner_arc_length(step_x > 0, step_y > 0, w),
                (true, false) => {
                    let edge = if step_x > 0 { Edge::Right } else { Edge::Left };
                    geo.arc_length_on(edge, exit)
                }
                _ => {
                    let edge = if step_y > 0 { Edge::Top } else { Edge::Bottom };
                    geo.arc_length_on(edge, exit)
                }
            };
            return Some(Fate::Exited(medium.bins.bin(s, dir)));
        }
        if medium.cell(*ix, *iy).opaque {
            return Some(Fate::Absorbed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_model::material::builtin_material;

    impl Medium {
        /// The same medium with every pixel its own block: every flight walks the grid.
        fn grid_walk_only(mut self) -> Medium {
            let n = self.geometry.grid as usize;
            self.blocks = (0..n * n)
                .map(|i| {
                    let (x, y) = ((i % n) as i64, (i / n) as i64);
                    Block {
                        lo: [-1.0, -1.0],
                        hi: [-1.0, -1.0],
                        first: [x, y],
                        last: [x, y],
                        whole: false,
                    }
                })
                .collect();
            self.block_of = (0..(n * n) as u32).collect();
            self
        }
    }

    /// Photon by photon, the block shortcuts give the fates of the pure grid walk (the same
    /// random numbers drive both; only rounding may part a rare photon).
    #[test]
    fn blocks_agree_with_the_grid_walk_photon_by_photon() {
        let moderate = builtin_material("moderate").unwrap();
        let back = builtin_material("back").unwrap();
        let cases: Vec<(Geometry, Vec<Material>, Vec<u16>)> = vec![
            (Geometry::default(), vec![moderate], vec![0; 256]),
            (
                Geometry::new(16.0, 8, 16, 3).unwrap(),
                vec![Material::TRANSMISSIVE],
                vec![0; 64],
            ),
            (
                // Sources on grid lines; 4×4, 2×2 and 1×1 blocks, opaque and transmissive.
                Geometry::new(16.0, 8, 16, 3).unwrap(),
                vec![
                    moderate,
                    back,
                    Material::OPAQUE,
                    Material::TRANSMISSIVE,
                    Material::new(0.9, 0.0, 1.0).unwrap(),
                    Material::new(0.7, 0.05, -1.0).unwrap(),
                ],
                (0..64)
                    .map(|i| {
                        let (x, y) = (i % 8, i / 8);
                        match (x / 4, y / 4) {
                            (0, 0) => 0,
                            (1, 0) => [1, 1, 4, 4][(x % 4 / 2) + 2 * (y % 4 / 2)],
                            (0, 1) => [(i % 3) as u16, 5, 3, 1][(x % 2) + 2 * (y % 2)],
                            _ => [1, 2, 3, 0][(x % 2) + 2 * (y % 2)],
                        }
                    })
                    .collect(),
            ),
        ];
        for (geo, table, assignment) in cases {
            let fast = Medium::new(geo, &table, &assignment);
            let slow = Medium::new(geo, &table, &assignment).grid_walk_only();
            let (mut same, mut total) = (0usize, 0usize);
            for source in 0..geo.sources() {
                let ray = geo.source_ray(source);
                for photon in 0..200 {
                    let a = trace_photon(
                        &fast,
                        &ray,
                        &mut PhotonStream::new(5, source as u32, photon),
                    );
                    let b = trace_photon(
                        &slow,
                        &ray,
                        &mut PhotonStream::new(5, source as u32, photon),
                    );
                    same += usize::from(a == b);
                    total += 1;
                }
            }
            assert!(
                same as f64 >= 0.9999 * total as f64,
                "{geo:?}: {} of {total} photons differ",
                total - same
            );
        }
    }

    #[test]
    fn blocks_cover_the_grid_with_uniform_aligned_squares() {
        let geo = Geometry::new(16.0, 8, 16, 3).unwrap();
        let moderate = builtin_material("moderate").unwrap();
        let table = [moderate, Material::OPAQUE];
        let homogeneous = Medium::new(geo, &table, &[0; 64]);
        assert_eq!(homogeneous.blocks.len(), 1);
        assert!(homogeneous.blocks[0].whole);
        // One odd pixel in the top-left corner (row 0, column 0) splits the grid into three 4×4
        // blocks, three 2×2, three 1×1 and the pixel itself.
        let mut a = vec![0u16; 64];
        a[0] = 1;
        let m = Medium::new(geo, &table, &a);
        let mut sizes: Vec<i64> = m
            .blocks
            .iter()
            .map(|b| b.last[0] - b.first[0] + 1)
            .collect();
        sizes.sort_unstable();
        assert_eq!(sizes, [1, 1, 1, 1, 2, 2, 2, 4, 4, 4]);
        for (i, &b) in m.block_of.iter().enumerate() {
            let block = m.blocks[b as usize];
            let (x, y) = ((i % 8) as i64, (i / 8) as i64);
            assert!((block.first[0]..=block.last[0]).contains(&x));
            assert!((block.first[1]..=block.last[1]).contains(&y));
            assert_eq!(m.cells[i], *m.cell(block.first[0], block.first[1]));
        }
    }
}
