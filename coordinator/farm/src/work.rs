//! A render group: renders that share geometry, material table and photon range (the
//! candidates of one search step that need the same photons, or one setup render), cut into
//! photon-range pieces for workers, with their partial counts summed in memory. A group may
//! start from counts already in hand (racing's first stage), rendering only the photons after
//! them.
//!
//! A differential group (a refinement's screen) is one render with the changes it also
//! estimates; it goes to one worker whole, which renders it in the job's chunks and returns its
//! counts with one score per change (the deltas behind them never cross the wire).
//!
//! Counts are additive over photon ranges (`[0, a) + [a, n) = [0, n)` per item, bit-exactly), so
//! a group's sums do not depend on how it was cut, in what order pieces came back, or how often a
//! piece was leased again.

use scatterfarm_job::plan::SetupKind;
use scatterfarm_model::differential::{change_is_reweightable, Change};
use scatterfarm_model::likelihood::{blocks, Deviance};
use scatterfarm_model::{CountMatrix, Geometry, Material};
pub use scatterfarm_search::steps::GroupItem;
use std::collections::VecDeque;

/// What a group's counts are for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    Setup(SetupKind),
    /// The renders of the search's current step that have no score yet.
    Search,
}

/// A photon range of a group handed to a worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Piece {
    pub task_id: u64,
    /// 1 for the first lease; each new lease of the same range adds one.
    pub attempt: u32,
    pub first: u32,
    pub count: u32,
}

/// Renders rendered together.
#[derive(Debug)]
pub struct RenderGroup {
    /// Unique within a coordinator's run; a result for a group that is gone is refused.
    pub id: u64,
    pub purpose: Purpose,
    pub geometry: Geometry,
    pub table: Vec<Material>,
    pub items: Vec<GroupItem>,
    /// Photons per source of every render of the group, when complete.
    pub photons: u32,
    /// The first photon the group renders: the photons before it came summed in.
    pub start: u32,
    /// The next photon never handed out.
    next: u32,
    /// Pieces handed back (expired, released or refused), handed out again first.
    requeue: VecDeque<Piece>,
    /// Photons per source summed so far.
    done: u64,
    /// Empty until the first piece arrives, whose matrices become the sums (no zero-filled
    /// 5 MB buffers, no first addition).
    sums: Vec<CountMatrix>,
    /// Scattering events reported with the summed pieces.
    pub scatter_events: u64,
    /// The changes a differential group's one render also estimates; empty for plain groups.
    pub changes: Vec<Change>,
    /// A differential group's change scores, once its piece is in.
    change_scores: Option<Vec<Option<Deviance>>>,
}

impl RenderGroup {
    pub fn new(
        id: u64,
        purpose: Purpose,
        geometry: Geometry,
        table: Vec<Material>,
        items: Vec<GroupItem>,
        photons: u32,
    ) -> RenderGroup {
        let sums = Vec::new();
        RenderGroup {
            id,
            purpose,
            geometry,
            table,
            items,
            photons,
            start: 0,
            next: 0,
            requeue: VecDeque::new(),
            done: 0,
            sums,
            scatter_events: 0,
            changes: Vec::new(),
            change_scores: None,
        }
    }

    /// The group as a differential render of its one item, estimating `changes` too.
    pub fn with_changes(mut self, changes: Vec<Change>) -> RenderGroup {
        self.changes = changes;
        self
    }

    /// Whether the group is a differential render.
    pub fn is_differential(&self) -> bool {
        !self.changes.is_empty()
    }

    /// The group with photons `[0, start)` of every item already summed in `sums` (one
    /// matrix per item, in order): only `[start, photons)` is handed out.
    pub fn starting_from(mut self, start: u32, sums: Vec<CountMatrix>) -> RenderGroup {
        if start == 0 || start >= self.photons || sums.len() != self.items.len() {
            return self;
        }
        self.start = start;
        self.next = start;
        self.done = u64::from(start);
        self.sums = sums;
        self
    }

    /// Whether a piece can be handed out now.
    pub fn has_work(&self) -> bool {
        !self.requeue.is_empty() || self.next < self.photons
    }

    /// The next piece: a handed-back one (next attempt), else up to `max_photons` new photons.
    /// `new_task_id` gives ids to new pieces.
    pub fn take(
        &mut self,
        max_photons: u32,
        new_task_id: &mut dyn FnMut() -> u64,
    ) -> Option<Piece> {
        if let Some(mut p) = self.requeue.pop_front() {
            p.attempt += 1;
            return Some(p);
        }
        if self.next >= self.photons {
            return None;
        }
        // A differential render goes whole: its worker scores the changes of all its photons.
        let count = if self.is_differential() {
            self.photons - self.next
        } else {
            max_photons.clamp(1, self.photons - self.next)
        };
        let piece = Piece {
            task_id: new_task_id(),
            attempt: 1,
            first: self.next,
            count,
        };
        self.next += count;
        Some(piece)
    }

    /// Hands a leased piece back to be leased again.
    pub fn give_back(&mut self, piece: Piece) {
        self.requeue.push_back(piece);
    }

    /// Checks a piece's counts: one matrix per item, each of the group's shape, and no source
    /// with more exits than photons launched; and a differential group's change scores.
    pub fn check(
        &self,
        piece: &Piece,
        counts: &[CountMatrix],
        change_scores: &[Option<Deviance>],
    ) -> Result<(), String> {
        self.check_change_scores(change_scores)?;
        if counts.len() != self.items.len() {
            return Err(format!(
                "{} count matrices for {} assignments",
                counts.len(),
                self.items.len()
            ));
        }
        let (sources, bins) = (self.geometry.sources(), self.geometry.bins());
        for (i, c) in counts.iter().enumerate() {
            if c.sources != sources || c.bins != bins || c.counts.len() != sources * bins {
                return Err(format!(
                    "assignment {i}: a {}×{} matrix with {} counts, expected {sources}×{bins}",
                    c.sources,
                    c.bins,
                    c.counts.len()
                ));
            }
            for s in 0..sources {
                let total: u64 = c.row(s).iter().map(|&v| u64::from(v)).sum();
                if total > u64::from(piece.count) {
                    return Err(format!(
                        "assignment {i}, source {s}: {total} photons exited, {} were launched",
                        piece.count
                    ));
                }
            }
        }
        Ok(())
    }

    /// Checks a differential group's change scores: one per change, a score exactly where the
    /// change can be reweighted, each with the geometry's blocks, every block a deviance's
    /// (not above 0) and the value their sum. A plain group takes none.
    fn check_change_scores(&self, scores: &[Option<Deviance>]) -> Result<(), String> {
        if scores.len() != self.changes.len() {
            return Err(format!(
                "{} change scores for {} changes",
                scores.len(),
                self.changes.len()
            ));
        }
        let Some(item) = self.items.first().filter(|_| self.is_differential()) else {
            return Ok(());
        };
        let expected = blocks(self.geometry.sources() * self.geometry.bins());
        for (k, (change, score)) in self.changes.iter().zip(scores).enumerate() {
            let reweightable = change_is_reweightable(&self.table, &item.item.assignment, change);
            match score {
                None if reweightable => {
                    return Err(format!("change {k} can be reweighted, yet it has no score"))
                }
                Some(_) if !reweightable => {
                    return Err(format!(
                        "change {k} cannot be reweighted, yet it has a score"
                    ))
                }
                None => {}
                Some(d) => {
                    if d.blocks.len() != expected {
                        return Err(format!(
                            "change {k}: {} blocks, expected {expected}",
                            d.blocks.len()
                        ));
                    }
                    let sum: f64 = d.blocks.iter().sum();
                    if d.blocks.iter().any(|b| *b > 0.0) || sum.to_bits() != d.value.to_bits() {
                        return Err(format!(
                            "change {k}: a score of {} that is not the sum of its blocks, or a \
                             block above 0",
                            d.value
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// Adds a checked piece's counts (and a differential group's change scores).
    pub fn accumulate(
        &mut self,
        piece: &Piece,
        counts: Vec<CountMatrix>,
        scatter_events: u64,
        change_scores: Vec<Option<Deviance>>,
    ) {
        if self.is_differential() {
            self.change_scores = Some(change_scores);
        }
        if self.sums.is_empty() {
            self.sums = counts;
        } else {
            for (sum, c) in self.sums.iter_mut().zip(&counts) {
                for (a, b) in sum.counts.iter_mut().zip(&c.counts) {
                    *a += *b;
                }
            }
        }
        self.done += u64::from(piece.count);
        self.scatter_events += scatter_events;
    }

    /// Whether every photon of every render has been summed.
    pub fn is_complete(&self) -> bool {
        self.done == u64::from(self.photons)
    }

    /// Photons per source summed so far.
    pub fn done(&self) -> u64 {
        self.done
    }

    /// The summed counts, one per item, and a differential group's change scores.
    pub fn into_parts(self) -> (Vec<CountMatrix>, Option<Vec<Option<Deviance>>>) {
        if self.sums.is_empty() {
            let zeros = CountMatrix::zeros(self.geometry.sources(), self.geometry.bins());
            return (vec![zeros; self.items.len()], self.change_scores);
        }
        (self.sums, self.change_scores)
    }

    /// The summed counts, one per item.
    pub fn into_sums(self) -> Vec<CountMatrix> {
        self.into_parts().0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_engines::CpuEngine;
    use scatterfarm_model::{Engine, PhotonRange, RenderBatch, RenderItem};

    fn geometry() -> Geometry {
        Geometry {
            size_mm: 16.0,
            grid: 2,
            positions: 8,
            directions: 3,
        }
    }

    fn group(photons: u32) -> RenderGroup {
        let items = (0..2)
            .map(|i| GroupItem {
                identity: [i; 32],
                item: RenderItem {
                    assignment: vec![0, i as u16, 1, 0],
                    seed: 5 + u64::from(i),
                },
            })
            .collect();
        let table = vec![
            Material {
                sigma_s: 0.5,
                sigma_a: 0.01,
                g: 0.3,
            },
            Material {
                sigma_s: 0.1,
                sigma_a: 0.2,
                g: 0.0,
            },
        ];
        RenderGroup::new(1, Purpose::Search, geometry(), table, items, photons)
    }

    fn render(g: &RenderGroup, p: &Piece) -> Vec<CountMatrix> {
        let items: Vec<RenderItem> = g.items.iter().map(|i| i.item.clone()).collect();
        CpuEngine::new()
            .render(&RenderBatch {
                geometry: g.geometry,
                table: &g.table,
                items: &items,
                photons: PhotonRange {
                    first: p.first,
                    count: p.count,
                },
            })
            .unwrap()
            .into_iter()
            .map(|o| o.counts)
            .collect()
    }

    #[test]
    fn pieces_out_of_order_and_retried_sum_to_one_render() {
        let mut whole = group(100);
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        let all = whole.take(1000, &mut next).unwrap();
        assert_eq!((all.first, all.count), (0, 100));
        let c = render(&whole, &all);
        whole.accumulate(&all, c, 0, Vec::new());
        assert!(whole.is_complete());

        let mut cut = group(100);
        let a = cut.take(30, &mut next).unwrap();
        let b = cut.take(30, &mut next).unwrap();
        let c2 = cut.take(30, &mut next).unwrap();
        let d = cut.take(30, &mut next).unwrap();
        assert_eq!((d.first, d.count), (90, 10));
        assert!(cut.take(30, &mut next).is_none());
        // b expires and comes back as attempt 2 with the same range and id.
        cut.give_back(b);
        let b2 = cut.take(30, &mut next).unwrap();
        assert_eq!((b2.task_id, b2.attempt, b2.first), (b.task_id, 2, b.first));
        for p in [d, a, b2, c2] {
            let counts = render(&cut, &p);
            cut.check(&p, &counts, &[]).unwrap();
            cut.accumulate(&p, counts, 0, Vec::new());
        }
        assert!(cut.is_complete());
        assert_eq!(cut.into_sums(), whole.into_sums());
    }

    #[test]
    fn a_group_started_from_a_prefix_sums_to_the_whole_render() {
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        let mut whole = group(100);
        let all = whole.take(1000, &mut next).unwrap();
        let c = render(&whole, &all);
        whole.accumulate(&all, c, 0, Vec::new());

        let mut first = group(40);
        let p = first.take(1000, &mut next).unwrap();
        let c = render(&first, &p);
        first.accumulate(&p, c, 0, Vec::new());
        let mut rest = group(100).starting_from(40, first.into_sums());
        assert_eq!(rest.start, 40);
        let p = rest.take(1000, &mut next).unwrap();
        assert_eq!(
            (p.first, p.count),
            (40, 60),
            "only the photons after the prefix"
        );
        let c = render(&rest, &p);
        rest.accumulate(&p, c, 0, Vec::new());
        assert!(rest.is_complete());
        assert_eq!(rest.into_sums(), whole.into_sums());
    }

    #[test]
    fn bad_counts_are_refused_with_a_reason() {
        let mut g = group(10);
        let p = g.take(10, &mut || 1).unwrap();
        let mut c = render(&g, &p);
        assert!(g
            .check(&p, &c[..1], &[])
            .unwrap_err()
            .contains("1 count matrices"));
        c[1].counts[0] += 11;
        assert!(g.check(&p, &c, &[]).unwrap_err().contains("exited"));
        let wrong = vec![CountMatrix::zeros(3, 3); 2];
        assert!(g.check(&p, &wrong, &[]).unwrap_err().contains("expected"));
    }
}
