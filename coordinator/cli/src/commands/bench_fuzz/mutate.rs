//! The input generator of `scatterfarm bench fuzz`: valid seeds mutated, deterministically from
//! one seed (ChaCha8), by byte-level mutations (bit flips, interesting bytes, truncation,
//! insertion, deletion, duplication, splices with other seeds) and text-aware ones (numbers
//! replaced by huge, negative or non-finite ones, deep nesting, long repetitions, quotes and
//! brackets). Each input is a few parts (an NPY and its sidecar, a task and a result); one
//! mutation changes one part. Every input stays under [`MAX_INPUT_BYTES`].

use rand_chacha::rand_core::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The largest part a mutation makes.
pub const MAX_INPUT_BYTES: usize = 1 << 20;

/// Numbers a parser may not expect.
const NUMBERS: &[&str] = &[
    "0",
    "-0",
    "-1",
    "1",
    "3",
    "65536",
    "65537",
    "4096",
    "8192",
    "2147483647",
    "2147483648",
    "4294967295",
    "4294967296",
    "1073741824",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "-9223372036854775808",
    "99999999999999999999999999999",
    "1e308",
    "1e309",
    "-1e309",
    "5e-324",
    "1.5",
    "-0.5",
    "nan",
    "inf",
    "-inf",
    "NaN",
    "Infinity",
    "0x7fffffff",
    "1_000_000",
];

/// Bytes a parser may not expect.
const BYTES: &[u8] = &[
    0, 0xff, 0x7f, 0x80, 0xc3, b'"', b'\'', b'[', b']', b'{', b'}', b'(', b')', b',', b':', b'=',
    b'\n', b'\\', b'.', b'-', b'9', b'#',
];

/// A deterministic mutator.
pub struct Mutator {
    rng: ChaCha8Rng,
}

impl Mutator {
    pub fn new(seed: u64) -> Self {
        Mutator {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// A number in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        (self.rng.next_u64() % n.max(1) as u64) as usize
    }

    pub fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }

    pub fn u64(&mut self) -> u64 {
        self.rng.next_u64()
    }

    /// One of `items`.
    pub fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }

    /// A number worth trying: small, at a boundary, or random.
    pub fn number(&mut self) -> u64 {
        match self.below(4) {
            0 => self.below(10) as u64,
            1 => 1u64 << self.below(64),
            2 => (1u64 << self.below(64)).wrapping_sub(1),
            _ => self.u64(),
        }
    }

    /// `input` (one of `seeds`, parts alike) mutated 1 to 4 times in one part.
    pub fn mutate(&mut self, input: &[Vec<u8>], seeds: &[Vec<Vec<u8>>]) -> Vec<Vec<u8>> {
        let mut out = input.to_vec();
        if out.is_empty() {
            return out;
        }
        let part = self.below(out.len());
        let rounds = 1 + self.below(4);
        for _ in 0..rounds {
            let other = self.pick(seeds).get(part).cloned().unwrap_or_default();
            self.mutate_bytes(&mut out[part], &other);
        }
        out
    }

    /// One mutation of `data`; `other` is another input's same part, for splices.
    pub fn mutate_bytes(&mut self, data: &mut Vec<u8>, other: &[u8]) {
        let len = data.len();
        let at = self.below(len + 1);
        match self.below(12) {
            0 if len > 0 => {
                let i = self.below(len);
                data[i] ^= 1 << self.below(8);
            }
            1 if len > 0 => {
                let i = self.below(len);
                data[i] = *self.pick(BYTES);
            }
            2 => data.truncate(at),
            3 => {
                let n = 1 + self.below(8);
                let bytes: Vec<u8> = (0..n).map(|_| self.u64() as u8).collect();
                data.splice(at..at, bytes);
            }
            4 if len > 0 => {
                let end = (at + 1 + self.below(16)).min(len);
                data.drain(at.min(end)..end);
            }
            5 if len > 0 => {
                let start = self.below(len);
                let end = (start + 1 + self.below(64)).min(len);
                let chunk = data[start..end].to_vec();
                data.splice(at..at, chunk);
            }
            6 if !other.is_empty() => {
                // Splice: our head, the other's tail.
                let cut = self.below(other.len());
                data.truncate(at);
                data.extend_from_slice(&other[cut..]);
            }
            7 | 8 => self.replace_number(data),
            9 => {
                let depth = 1 + self.below(20_000);
                let (open, close) = *self.pick(&[
                    (&b"["[..], &b"]"[..]),
                    (b"{", b"}"),
                    (b"(", b")"),
                    (b"{\"a\":", b"}"),
                    (b"a={", b"}"),
                ]);
                let mut nest = open.repeat(depth);
                if self.chance(2) {
                    nest.extend(close.repeat(depth));
                }
                data.splice(at..at, nest);
            }
            10 if len > 0 => {
                let start = self.below(len);
                let end = (start + 1 + self.below(32)).min(len);
                let chunk = data[start..end].to_vec();
                let times = 1 + self.below(MAX_INPUT_BYTES / chunk.len().max(1) / 4);
                data.splice(at..at, chunk.repeat(times));
            }
            _ => {
                let b = *self.pick(BYTES);
                data.insert(at, b);
            }
        }
        data.truncate(MAX_INPUT_BYTES);
    }

    /// Replaces a run of digits (or, with none, any place) with a number worth trying.
    fn replace_number(&mut self, data: &mut Vec<u8>) {
        let number = self.pick(NUMBERS).as_bytes().to_vec();
        let runs: Vec<(usize, usize)> = digit_runs(data);
        if runs.is_empty() {
            let at = self.below(data.len() + 1);
            data.splice(at..at, number);
        } else {
            let (start, end) = *self.pick(&runs);
            data.splice(start..end, number);
        }
    }
}

/// The runs of ASCII digits (with a leading minus sign) in `data`.
fn digit_runs(data: &[u8]) -> Vec<(usize, usize)> {
    let mut runs = Vec::new();
    let mut i = 0;
    while i < data.len() {
        if data[i].is_ascii_digit() {
            let start = if i > 0 && data[i - 1] == b'-' {
                i - 1
            } else {
                i
            };
            let mut end = i;
            while end < data.len() && (data[end].is_ascii_digit() || data[end] == b'.') {
                end += 1;
            }
            runs.push((start, end));
            i = end;
        } else {
            i += 1;
        }
    }
    runs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutations_are_deterministic_and_bounded() {
        let seeds = vec![vec![b"grid = 16\nname = \"x\"\n".to_vec()]];
        let run = |seed| {
            let mut m = Mutator::new(seed);
            (0..500)
                .map(|_| m.mutate(&seeds[0], &seeds))
                .collect::<Vec<_>>()
        };
        let a = run(7);
        assert_eq!(a, run(7));
        assert_ne!(a, run(8));
        assert!(a.iter().all(|p| p[0].len() <= MAX_INPUT_BYTES));
        assert!(a.iter().any(|p| p[0] != seeds[0][0]));
    }
}
