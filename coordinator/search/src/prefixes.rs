//! Counts of racing's first-stage renders, kept so that a contender's full render only renders
//! the photons it lacks: photons `[0, a)` and `[a, n)` of one seed add up to exactly the render
//! of `[0, n)` (`docs/model.md`, "Randomness").
//!
//! The store is bounded in bytes and forgets its oldest entries first; a forgotten prefix only
//! costs its photons again, never a different result.

use scatterfarm_model::CountMatrix;
use std::collections::{HashMap, VecDeque};

/// The default bound: enough for every first-stage render of a step at the default geometry.
pub const DEFAULT_BYTES: usize = 512 << 20;

/// A render's stream: the same assignment and seed (and, within one search level, the same
/// table, geometry and engine) at any number of photons.
pub type StreamKey = (Vec<u16>, u64);

/// First-stage counts by stream.
#[derive(Debug)]
pub struct Prefixes {
    entries: HashMap<StreamKey, (u32, CountMatrix)>,
    order: VecDeque<StreamKey>,
    bytes: usize,
    limit: usize,
}

impl Prefixes {
    pub fn new(limit: usize) -> Prefixes {
        Prefixes {
            entries: HashMap::new(),
            order: VecDeque::new(),
            bytes: 0,
            limit,
        }
    }

    fn size(c: &CountMatrix) -> usize {
        c.counts.len() * 4
    }

    /// Keeps `counts` (photons `[0, photons)` of `key`'s stream), replacing a shorter prefix.
    pub fn keep(&mut self, key: StreamKey, photons: u32, counts: CountMatrix) {
        if Self::size(&counts) > self.limit {
            return;
        }
        match self.entries.get(&key) {
            Some((p, _)) if *p >= photons => return,
            Some(_) => {
                if let Some((_, old)) = self.entries.remove(&key) {
                    self.bytes -= Self::size(&old);
                }
                self.order.retain(|k| k != &key);
            }
            None => {}
        }
        self.bytes += Self::size(&counts);
        self.entries.insert(key.clone(), (photons, counts));
        self.order.push_back(key);
        while self.bytes > self.limit {
            let Some(oldest) = self.order.pop_front() else {
                break;
            };
            if let Some((_, c)) = self.entries.remove(&oldest) {
                self.bytes -= Self::size(&c);
            }
        }
    }

    /// The longest kept prefix of `key`'s stream shorter than `photons`.
    pub fn get(&self, key: &StreamKey, photons: u32) -> Option<(u32, &CountMatrix)> {
        self.entries
            .get(key)
            .filter(|(p, _)| *p < photons)
            .map(|(p, c)| (*p, c))
    }

    pub fn clear(&mut self) {
        self.entries.clear();
        self.order.clear();
        self.bytes = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_longest_prefix_and_forgets_the_oldest_beyond_its_bound() {
        let m = |v: u32| CountMatrix {
            sources: 1,
            bins: 4,
            counts: vec![v; 4],
        };
        // Room for two 16-byte matrices.
        let mut p = Prefixes::new(32);
        p.keep((vec![0], 1), 10, m(1));
        p.keep((vec![0], 1), 5, m(2));
        assert_eq!(
            p.get(&(vec![0], 1), 20).map(|(n, c)| (n, c.counts[0])),
            Some((10, 1))
        );
        assert!(p.get(&(vec![0], 1), 10).is_none(), "only shorter prefixes");
        p.keep((vec![1], 1), 10, m(3));
        p.keep((vec![2], 1), 10, m(4));
        assert!(p.get(&(vec![0], 1), 20).is_none(), "the oldest went first");
        assert!(p.get(&(vec![1], 1), 20).is_some());
        assert!(p.get(&(vec![2], 1), 20).is_some());
    }
}
