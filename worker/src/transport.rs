//! Flatland photon transport through a pixel grid, exactly as `model.md` ("Transport") says:
//! exact grid traversal, opaque pixels absorb on entry, analog absorption, flatland HG.
//!
//! [`Medium`] is a material assignment laid out for the tracer; [`trace_photon`] follows one
//! photon from its source to its bin (or its absorption) using that photon's own random stream.

use crate::geometry::{Edge, Geometry, Ray};
use crate::material::Material;
use crate::phase::{sample_turn, turn};
use crate::rng::PhotonStream;

/// Two grid-line crossings closer than this fraction of a pixel are one diagonal step through
/// the corner: the zero-length pass through the side pixel neither enters nor is absorbed by it.
pub const CORNER_TOLERANCE: f64 = 1e-9;

/// A source coordinate within this fraction of a pixel of a grid line lies on it.
const GRID_LINE_TOLERANCE: f64 = 1e-9;

/// One pixel's material, in the form the tracer uses.
#[derive(Debug, Clone, Copy)]
struct Cell {
    /// Extinction σt (mm⁻¹); 0 for transmissive.
    sigma_t: f64,
    /// Probability that a collision absorbs: σa/σt.
    absorb: f64,
    /// HG parameter.
    g: f64,
    opaque: bool,
}

/// A material assignment over a geometry's grid, ready to trace.
#[derive(Debug, Clone)]
pub struct Medium {
    geometry: Geometry,
    /// Indexed `iy * N + ix` with `iy` counted from the **bottom** (the tracer's y points up).
    cells: Vec<Cell>,
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
                cells.push(Cell {
                    sigma_t: if m.is_opaque() { 0.0 } else { sigma_t },
                    absorb: if sigma_t > 0.0 && !m.is_opaque() {
                        m.sigma_a / sigma_t
                    } else {
                        0.0
                    },
                    g: m.g,
                    opaque: m.is_opaque(),
                });
            }
        }
        Medium { geometry, cells }
    }

    pub fn geometry(&self) -> &Geometry {
        &self.geometry
    }

    #[inline]
    fn cell(&self, ix: i64, iy: i64) -> &Cell {
        &self.cells[(iy as usize) * self.geometry.grid as usize + ix as usize]
    }
}

/// The index of the pixel a ray starting at coordinate `x` (along one axis) runs in, given its
/// direction component `dx` along that axis and `left` — the sign of the ray's left normal along
/// that axis, used when the ray runs exactly along a grid line (`model.md`: it is inside the
/// pixel on its left).
fn start_index(x: f64, dx: f64, left: f64, h: f64, n: i64) -> i64 {
    let u = x / h;
    let line = u.round();
    let i = if (u - line).abs() <= GRID_LINE_TOLERANCE {
        let side = if dx != 0.0 { dx } else { left };
        if side > 0.0 {
            line as i64
        } else {
            line as i64 - 1
        }
    } else {
        u.floor() as i64
    };
    i.clamp(0, n - 1)
}

/// Follows one photon of source `ray` (source index `source`) with stream `rng` to its fate.
pub fn trace_photon(medium: &Medium, ray: &Ray, rng: &mut PhotonStream) -> Trace {
    let geo = &medium.geometry;
    let n = geo.grid as i64;
    let h = geo.pixel_size();
    let w = geo.size_mm;
    let mut pos = ray.origin;
    let mut dir = ray.direction;
    let mut ix = start_index(pos[0], dir[0], -dir[1], h, n);
    let mut iy = start_index(pos[1], dir[1], dir[0], h, n);
    let mut scatters = 0u32;

    if medium.cell(ix, iy).opaque {
        return Trace {
            fate: Fate::Absorbed,
            scatters,
        };
    }

    loop {
        // A new flight: optical depth to spend, marching from `pos` along `dir`.
        let mut tau = -rng.uniform().ln();
        let step_x: i64 = if dir[0] > 0.0 { 1 } else { -1 };
        let step_y: i64 = if dir[1] > 0.0 { 1 } else { -1 };
        // Distances along the ray to the next vertical and horizontal grid lines, and between
        // successive ones (infinite for a ray parallel to those lines).
        let inv = [1.0 / dir[0], 1.0 / dir[1]];
        let next_line = |i: i64, step: i64| (if step > 0 { i + 1 } else { i }) as f64 * h;
        let mut t_max_x = if dir[0] != 0.0 {
            ((next_line(ix, step_x) - pos[0]) * inv[0]).max(0.0)
        } else {
            f64::INFINITY
        };
        let mut t_max_y = if dir[1] != 0.0 {
            ((next_line(iy, step_y) - pos[1]) * inv[1]).max(0.0)
        } else {
            f64::INFINITY
        };
        let t_delta_x = h * inv[0].abs();
        let t_delta_y = h * inv[1].abs();
        let mut t = 0.0;

        let collided_at = loop {
            let cell = medium.cell(ix, iy);
            let t_next = t_max_x.min(t_max_y);
            let spend = cell.sigma_t * (t_next - t);
            if spend >= tau {
                break t + tau / cell.sigma_t;
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
                ix += step_x;
                t_max_x += t_delta_x;
            }
            if cross_y {
                iy += step_y;
                t_max_y += t_delta_y;
            }
            let out_x = ix < 0 || ix >= n;
            let out_y = iy < 0 || iy >= n;
            if out_x || out_y {
                let exit = [pos[0] + t * dir[0], pos[1] + t * dir[1]];
                let s = exit_arc_length(
                    geo,
                    exit,
                    out_x.then_some(step_x),
                    out_y.then_some(step_y),
                    w,
                );
                return Trace {
                    fate: Fate::Exited(geo.bin_of_exit(s, dir)),
                    scatters,
                };
            }
            if medium.cell(ix, iy).opaque {
                return Trace {
                    fate: Fate::Absorbed,
                    scatters,
                };
            }
        };

        // Collision inside pixel (ix, iy).
        pos = [pos[0] + collided_at * dir[0], pos[1] + collided_at * dir[1]];
        let cell = medium.cell(ix, iy);
        if rng.uniform() < cell.absorb {
            return Trace {
                fate: Fate::Absorbed,
                scatters,
            };
        }
        scatters += 1;
        // A rotation keeps |dir| = 1 to within a few ulps per event; no renormalization needed.
        dir = turn(dir, sample_turn(cell.g, rng.uniform()));
    }
}

/// Arc length of a photon leaving at `exit`, through the side(s) it stepped out of.
fn exit_arc_length(
    geo: &Geometry,
    exit: [f64; 2],
    out_x: Option<i64>,
    out_y: Option<i64>,
    w: f64,
) -> f64 {
    match (out_x, out_y) {
        // Through a corner: the edge whose arc-length interval starts there.
        (Some(sx), Some(sy)) => match (sx > 0, sy > 0) {
            (false, false) => 0.0,
            (true, false) => w,
            (true, true) => 2.0 * w,
            (false, true) => 3.0 * w,
        },
        (Some(sx), None) => {
            let edge = if sx > 0 { Edge::Right } else { Edge::Left };
            geo.arc_length_on(edge, exit)
        }
        (None, Some(sy)) => {
            let edge = if sy > 0 { Edge::Top } else { Edge::Bottom };
            geo.arc_length_on(edge, exit)
        }
        (None, None) => unreachable!("exit_arc_length is called only for a photon that left"),
    }
}
