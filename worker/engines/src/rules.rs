//! The transport rules both engines apply on the host, defined once (`docs/model.md`,
//! "Transport" and "Rays along grid lines"): the tolerances, the grid-line rule that picks a
//! source's start pixel, and the uniform blocks of a material assignment.
//!
//! The CPU tracer ([`crate::transport`]) applies them photon by photon; the GPU engine's host
//! ([`crate::gpu`]) applies them in f64 while laying a batch out for the shader (start pixels,
//! per-pixel block levels) and passes the shader's own tolerance in its parameter record. Where
//! the shader applies a rule again (`grid_index`, the corner test), it uses that tolerance: WGSL
//! cannot call this code, so the shader's copies are checked against it by the GPU tests.

use scatterfarm_model::geometry::Geometry;

/// Two grid-line crossings closer than this fraction of a pixel are one diagonal step through
/// the corner: the zero-length pass through the side pixel neither enters nor is absorbed by it
/// (the CPU tracer, in f64).
pub const CORNER_TOLERANCE: f64 = 1e-9;

/// The GPU engine's corner and grid-line tolerance, as a fraction of the medium's side `W` (the
/// host passes `CORNER_TOLERANCE_F32 · W` to the shader as `Params::corner_tol`). The shader's
/// coordinates and distances are f32 values up to ~√2·W, each good to a few ulps (an ulp is
/// ~1.2e-7·W); this is ~70 ulps, far below any pixel of a valid grid (N ≤ 4096).
pub const CORNER_TOLERANCE_F32: f64 = 8e-6;

/// A source coordinate within this fraction of a pixel of a grid line lies on it.
pub const GRID_LINE_TOLERANCE: f64 = 1e-9;

/// The index of the pixel a ray starting at coordinate `x` (along one axis) runs in, given its
/// direction component `dx` along that axis and `left` — the sign of the ray's left normal along
/// that axis, used when the ray runs exactly along a grid line (`docs/model.md`: it is inside the
/// pixel on its left). `h` is the pixel side, `n` the pixels per side; the index is clamped into
/// the grid.
#[inline]
pub fn start_index(x: f64, dx: f64, left: f64, h: f64, n: i64) -> i64 {
    let u = x / h;
    // ⌊u⌋ and the nearest line without the `floor`/`round` library calls (u ≥ 0 on the square).
    let (below, line) = if u >= 0.0 {
        let f = u as i64;
        (f, if u - f as f64 >= 0.5 { f + 1 } else { f })
    } else {
        (u.floor() as i64, u.round() as i64)
    };
    let i = if (u - line as f64).abs() <= GRID_LINE_TOLERANCE {
        let side = if dx != 0.0 { dx } else { left };
        if side > 0.0 {
            line
        } else {
            line - 1
        }
    } else {
        below
    };
    i.clamp(0, n - 1)
}

/// The pixel (column, row from the bottom) a ray from `origin` along `dir` starts in: on each
/// axis [`start_index`], with the ray's left normal `(−dir.y, dir.x)` for a ray along a grid line.
#[inline]
pub fn start_pixel(geo: &Geometry, origin: [f64; 2], dir: [f64; 2]) -> (i64, i64) {
    let h = geo.pixel_size();
    let n = i64::from(geo.grid);
    (
        start_index(origin[0], dir[0], -dir[1], h, n),
        start_index(origin[1], dir[1], dir[0], h, n),
    )
}

/// Per cell of an `n × n` grid (row-major, `n` a power of two), the level `L` of the largest
/// aligned `2^L × 2^L` block around it whose cells are all equal. Aligned blocks nest, so every
/// cell of such a block has the same level. Each engine passes what it calls equal: the CPU its
/// prepared cells, the GPU host the material indices.
pub fn uniform_block_levels<T: PartialEq>(cells: &[T], n: usize) -> Vec<u8> {
    let mut levels = vec![0u8; n * n];
    // uniform[b] for the blocks of the current level, (n / side)² of them, row-major.
    let mut uniform = vec![true; n * n];
    let mut side = 1;
    let mut level = 0u8;
    while side < n {
        let (child, blocks) = (n / side, n / (2 * side));
        let next: Vec<bool> = (0..blocks * blocks)
            .map(|b| {
                let (by, bx) = (b / blocks, b % blocks);
                let kids =
                    [(0, 0), (0, 1), (1, 0), (1, 1)].map(|(dy, dx)| (2 * by + dy, 2 * bx + dx));
                let first = &cells[2 * by * side * n + 2 * bx * side];
                kids.iter().all(|&(y, x)| {
                    uniform[y * child + x] && cells[y * side * n + x * side] == *first
                })
            })
            .collect();
        side *= 2;
        level += 1;
        for (b, _) in next.iter().enumerate().filter(|(_, &u)| u) {
            let (by, bx) = (b / blocks, b % blocks);
            for y in by * side..(by + 1) * side {
                levels[y * n + bx * side..y * n + (bx + 1) * side].fill(level);
            }
        }
        uniform = next;
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_index_follows_the_grid_line_rule() {
        let (h, n) = (2.0, 8);
        // Inside a pixel: the pixel.
        assert_eq!(start_index(3.0, 1.0, 1.0, h, n), 1);
        // On a line: the pixel the ray moves into, or for a ray along it, the pixel on its left.
        assert_eq!(start_index(4.0, 1.0, 1.0, h, n), 2);
        assert_eq!(start_index(4.0, -1.0, 1.0, h, n), 1);
        assert_eq!(start_index(4.0 + 1e-10, 0.0, -1.0, h, n), 1);
        assert_eq!(start_index(4.0 - 1e-10, 0.0, 1.0, h, n), 2);
        // Clamped into the grid.
        assert_eq!(start_index(0.0, -1.0, 1.0, h, n), 0);
        assert_eq!(start_index(16.0, 1.0, 1.0, h, n), 7);
        // The library floor/round agree with the hand-made ones.
        for k in 0..2000 {
            let x = k as f64 * 0.0131;
            let u = x / h;
            let line = u.round();
            let want = if (u - line).abs() <= GRID_LINE_TOLERANCE {
                line as i64
            } else {
                u.floor() as i64
            };
            assert_eq!(start_index(x, 1.0, 1.0, h, n), want.clamp(0, n - 1));
        }
    }

    #[test]
    fn block_levels_are_the_largest_uniform_aligned_squares() {
        assert_eq!(uniform_block_levels(&[7u16; 16], 4), vec![2; 16]);
        let mut cells = [0u16; 16];
        cells[0] = 1;
        #[rustfmt::skip]
        let want = vec![
            0, 0, 1, 1,
            0, 0, 1, 1,
            1, 1, 1, 1,
            1, 1, 1, 1,
        ];
        assert_eq!(uniform_block_levels(&cells, 4), want);
        assert_eq!(uniform_block_levels(&[3u8], 1), vec![0]);
    }
}
