//! The changes a refinement sweep tries on the current map: each pixel to each other
//! candidate, objects moved, their sides and boxes grown or shrunk, regions recoloured,
//! neighbours swapped, and the changes of growth and simplification rounds.

use super::{Change, Refinement, GROWTH_MAX_PIXELS};
use std::collections::BTreeSet;

/// The rows and columns `pixels` (indices of an `n × n` grid) span: first row, last row,
/// first column, last column; `None` for no pixels.
fn bounding_box(pixels: &[usize], n: usize) -> Option<(usize, usize, usize, usize)> {
    let rows = pixels.iter().map(|p| p / n);
    let columns = pixels.iter().map(|p| p % n);
    Some((
        rows.clone().min()?,
        rows.max()?,
        columns.clone().min()?,
        columns.max()?,
    ))
}

/// The bounding box of `pixels` (indices of an `n × n` grid) grown by one row or column on
/// each side in turn, where the grid has room: up, down, left, right, each as its pixels in
/// order.
pub(super) fn grown_boxes(pixels: &[usize], n: usize) -> Vec<Vec<usize>> {
    let Some((y0, y1, x0, x1)) = bounding_box(pixels, n) else {
        return Vec::new();
    };
    let boxes = [
        (y0 > 0).then(|| (y0 - 1, y1, x0, x1)),
        (y1 + 1 < n).then(|| (y0, y1 + 1, x0, x1)),
        (x0 > 0).then(|| (y0, y1, x0 - 1, x1)),
        (x1 + 1 < n).then(|| (y0, y1, x0, x1 + 1)),
    ];
    boxes
        .into_iter()
        .flatten()
        .map(|(ya, yb, xa, xb)| {
            (ya..=yb)
                .flat_map(|y| (xa..=xb).map(move |x| y * n + x))
                .collect()
        })
        .collect()
}

impl Refinement {
    /// Every change a sweep tries, in a fixed order, without repeats or no-ops.
    pub(super) fn changes(&self) -> Vec<Change> {
        if self.simplifying {
            return self.simplifications();
        }
        if self.growing {
            return self.growths_of_current();
        }
        let mut out: Vec<Change> = Vec::new();
        for (p, &m) in self.current.iter().enumerate() {
            for &d in &self.materials {
                if d != m {
                    out.push(Change {
                        pixels: vec![(p as u32, d)],
                    });
                }
            }
        }
        // Moves, recolours and swaps, in that order, each once and never a single already
        // listed (nor an empty move).
        let mut seen: BTreeSet<Vec<(u32, u16)>> = out.iter().map(|c| c.pixels.clone()).collect();
        let more = [
            (
                self.config.move_objects,
                Self::object_moves as fn(&Self) -> Vec<Change>,
            ),
            (self.config.recolour_regions, Self::recolours),
            (self.config.swap_pixels, Self::swaps),
            (self.config.blocks, Self::blocks),
            (self.config.blocks, Self::object_sides),
        ];
        for (on, changes) in more {
            if !on {
                continue;
            }
            for c in changes(self) {
                if !c.pixels.is_empty() && seen.insert(c.pixels.clone()) {
                    out.push(c);
                }
            }
        }
        out
    }

    /// A simplification round's changes: each pixel not of the background set to it, then
    /// each region of two pixels or more not of the background set wholly to it.
    pub(super) fn simplifications(&self) -> Vec<Change> {
        let background = self.background();
        let mut out: Vec<Change> = self
            .current
            .iter()
            .enumerate()
            .filter(|(_, &m)| m != background)
            .map(|(p, _)| Change {
                pixels: vec![(p as u32, background)],
            })
            .collect();
        for (m, pixels) in self.regions() {
            if m != background && pixels.len() >= 2 {
                out.push(Change {
                    pixels: pixels.iter().map(|&p| (p as u32, background)).collect(),
                });
            }
        }
        out
    }

    /// A growth round's changes: each object of at most [`GROWTH_MAX_PIXELS`] pixels not of
    /// the background, with its 8-connected neighbours, set wholly to each candidate material
    /// other than the background, then (an object of two pixels or more) its bounding box
    /// grown by each side in turn ([`grown_boxes`]) filled with its material; where two pixels
    /// or more change, objects in the order of their first pixel.
    pub(super) fn growths_of_current(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let background = self.background();
        let mut out = Vec::new();
        let mut seen = BTreeSet::new();
        for (m, pixels) in self.regions() {
            if m == background || pixels.len() > GROWTH_MAX_PIXELS {
                continue;
            }
            let mut grown: BTreeSet<usize> = BTreeSet::new();
            for &p in &pixels {
                let (y, x) = (p as i64 / n, p as i64 % n);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (yy, xx) = (y + dy, x + dx);
                        if (0..n).contains(&yy) && (0..n).contains(&xx) {
                            grown.insert((yy * n + xx) as usize);
                        }
                    }
                }
            }
            for &d in &self.materials {
                if d == background {
                    continue;
                }
                let pixels: Vec<(u32, u16)> = grown
                    .iter()
                    .filter(|&&p| self.current[p] != d)
                    .map(|&p| (p as u32, d))
                    .collect();
                if pixels.len() >= 2 && seen.insert(pixels.clone()) {
                    out.push(Change { pixels });
                }
            }
            if pixels.len() >= 2 {
                // An object found with a corner or a side missing (an L of three pixels where
                // a 3 × 2 block is): its bounding box grown by one row or column on each side
                // in turn, filled with its material.
                for rectangle in grown_boxes(&pixels, self.grid as usize) {
                    let pixels: Vec<(u32, u16)> = rectangle
                        .into_iter()
                        .filter(|&p| self.current[p] != m)
                        .map(|p| (p as u32, m))
                        .collect();
                    if pixels.len() >= 2 && seen.insert(pixels.clone()) {
                        out.push(Change { pixels });
                    }
                }
            }
        }
        out
    }

    /// Each 2 × 2 block, then each horizontal and each vertical pair of neighbouring pixels,
    /// set wholly to each candidate material where at least two of its pixels change; blocks
    /// and pairs in the order of their top-left pixel.
    pub(super) fn blocks(&self) -> Vec<Change> {
        let n = self.grid as usize;
        let shapes: [&[(usize, usize)]; 3] = [
            &[(0, 0), (0, 1), (1, 0), (1, 1)],
            &[(0, 0), (0, 1)],
            &[(0, 0), (1, 0)],
        ];
        let mut out = Vec::new();
        for shape in shapes {
            for y in 0..n {
                for x in 0..n {
                    if shape.iter().any(|&(dy, dx)| y + dy >= n || x + dx >= n) {
                        continue;
                    }
                    let pixels: Vec<usize> = shape
                        .iter()
                        .map(|&(dy, dx)| (y + dy) * n + x + dx)
                        .collect();
                    for &d in &self.materials {
                        let changed: Vec<(u32, u16)> = pixels
                            .iter()
                            .filter(|&&p| self.current[p] != d)
                            .map(|&p| (p as u32, d))
                            .collect();
                        if changed.len() >= 2 {
                            out.push(Change { pixels: changed });
                        }
                    }
                }
            }
        }
        out
    }

    /// Each object (as [`Self::object_moves`] finds them) grown by the row or column just
    /// outside each side of its bounding box, over the box's span, and shrunk by its outermost
    /// row or column on each side (its pixels there set to the background): a rectangle found
    /// one row too thin or too wide is then one change, with the signal of the whole row.
    pub(super) fn object_sides(&self) -> Vec<Change> {
        let n = self.grid as usize;
        let background = self.background();
        let mut out = Vec::new();
        for (m, pixels) in self.regions() {
            if m == background || pixels.len() * 2 > self.current.len() {
                continue;
            }
            let Some((y0, y1, x0, x1)) = bounding_box(&pixels, n) else {
                continue;
            };
            let row = |y: usize| (x0..=x1).map(move |x| y * n + x).collect::<Vec<_>>();
            let column = |x: usize| (y0..=y1).map(move |y| y * n + x).collect::<Vec<_>>();
            let mut grow = Vec::new();
            if y0 > 0 {
                grow.push(row(y0 - 1));
            }
            if y1 + 1 < n {
                grow.push(row(y1 + 1));
            }
            if x0 > 0 {
                grow.push(column(x0 - 1));
            }
            if x1 + 1 < n {
                grow.push(column(x1 + 1));
            }
            let shrink = [row(y0), row(y1), column(x0), column(x1)];
            for line in grow {
                let change: Vec<(u32, u16)> = line
                    .into_iter()
                    .filter(|&p| self.current[p] != m)
                    .map(|p| (p as u32, m))
                    .collect();
                out.push(Change { pixels: change });
            }
            for line in shrink {
                let change: Vec<(u32, u16)> = line
                    .into_iter()
                    .filter(|p| pixels.binary_search(p).is_ok())
                    .map(|p| (p as u32, background))
                    .collect();
                // Shrinking a line of the box away entirely is the object cleared or split.
                if change.len() < pixels.len() {
                    out.push(Change { pixels: change });
                }
            }
        }
        out
    }

    /// Each pair of 8-connected neighbouring pixels of different materials, their materials
    /// exchanged; pairs in the order of their first pixel, then right, down-left, down,
    /// down-right.
    pub(super) fn swaps(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let mut out = Vec::new();
        for p in 0..self.current.len() {
            let (y, x) = (p as i64 / n, p as i64 % n);
            for (dy, dx) in [(0i64, 1i64), (1, -1), (1, 0), (1, 1)] {
                let (yy, xx) = (y + dy, x + dx);
                if yy >= n || xx < 0 || xx >= n {
                    continue;
                }
                let q = (yy * n + xx) as usize;
                let (a, b) = (self.current[p], self.current[q]);
                if a != b {
                    out.push(Change {
                        pixels: vec![(p as u32, b), (q as u32, a)],
                    });
                }
            }
        }
        out
    }

    /// Each connected region of two pixels or more, background included, set wholly to each
    /// other candidate material.
    pub(super) fn recolours(&self) -> Vec<Change> {
        let mut out = Vec::new();
        for (m, pixels) in self.regions() {
            if pixels.len() < 2 {
                continue;
            }
            for &d in &self.materials {
                if d != m {
                    out.push(Change {
                        pixels: pixels.iter().map(|&p| (p as u32, d)).collect(),
                    });
                }
            }
        }
        out
    }

    /// The map's 4-connected regions of one material, each with its pixels in order, the
    /// regions in the order of their first pixel.
    pub(super) fn regions(&self) -> Vec<(u16, Vec<usize>)> {
        let n = self.grid as i64;
        let mut label = vec![usize::MAX; self.current.len()];
        let mut regions: Vec<(u16, Vec<usize>)> = Vec::new();
        for start in 0..self.current.len() {
            if label[start] != usize::MAX {
                continue;
            }
            let m = self.current[start];
            let id = regions.len();
            let mut stack = vec![start];
            let mut pixels = Vec::new();
            label[start] = id;
            while let Some(p) = stack.pop() {
                pixels.push(p);
                let (y, x) = (p as i64 / n, p as i64 % n);
                for (dy, dx) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
                    let (yy, xx) = (y + dy, x + dx);
                    if yy < 0 || yy >= n || xx < 0 || xx >= n {
                        continue;
                    }
                    let q = (yy * n + xx) as usize;
                    if label[q] == usize::MAX && self.current[q] == m {
                        label[q] = id;
                        stack.push(q);
                    }
                }
            }
            pixels.sort_unstable();
            regions.push((m, pixels));
        }
        regions
    }

    /// The map's most common material (ties: the lowest index).
    pub(super) fn background(&self) -> u16 {
        let mut counts = std::collections::BTreeMap::<u16, usize>::new();
        for &m in &self.current {
            *counts.entry(m).or_default() += 1;
        }
        counts
            .iter()
            .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
            .map(|(&m, _)| m)
            .unwrap_or(0)
    }

    /// Each object (4-connected region of one non-background material, at most half the map)
    /// moved by one pixel up, down, left and right: pixels it leaves take the background, pixels
    /// it enters take its material; moves that would leave the map are skipped.
    pub(super) fn object_moves(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let background = self.background();
        let objects: Vec<(u16, Vec<usize>)> = self
            .regions()
            .into_iter()
            .filter(|(m, _)| *m != background)
            .collect();
        let mut moves = Vec::new();
        for (m, pixels) in objects {
            if pixels.len() * 2 > self.current.len() {
                continue;
            }
            let inside: BTreeSet<usize> = pixels.iter().copied().collect();
            'dir: for (dy, dx) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let mut moved = BTreeSet::new();
                for &p in &pixels {
                    let (y, x) = (p as i64 / n + dy, p as i64 % n + dx);
                    if y < 0 || y >= n || x < 0 || x >= n {
                        continue 'dir;
                    }
                    moved.insert((y * n + x) as usize);
                }
                let mut change = Vec::new();
                for &p in inside.difference(&moved) {
                    change.push((p as u32, background));
                }
                for &p in moved.difference(&inside) {
                    if self.current[p] != m {
                        change.push((p as u32, m));
                    }
                }
                change.sort_unstable();
                moves.push(Change { pixels: change });
            }
        }
        moves
    }

    /// Whether two changes may not be taken together: they touch pixels within one pixel of
    /// each other, unless both set one pixel each, to the same material, and different pixels
    /// (neighbours growing or shrinking one object together).
    pub(super) fn near(&self, a: &Change, b: &Change) -> bool {
        if let ([(p, m)], [(q, d)]) = (&a.pixels[..], &b.pixels[..]) {
            if m == d && p != q {
                return false;
            }
        }
        let n = self.grid as i64;
        a.pixels.iter().any(|&(p, _)| {
            b.pixels.iter().any(|&(q, _)| {
                let (py, px) = (i64::from(p) / n, i64::from(p) % n);
                let (qy, qx) = (i64::from(q) / n, i64::from(q) % n);
                (py - qy).abs() <= 1 && (px - qx).abs() <= 1
            })
        })
    }
}
