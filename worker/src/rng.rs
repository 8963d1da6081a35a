//! The counter-based random numbers of every engine: Philox4x32-10 (Salmon et al., SC'11).
//!
//! A photon's stream is a pure function of `(seed, source, photon)`: the key is the 64-bit
//! seed, the counter is `(photon, source, block, 0)`, and each block yields four 32-bit words.
//! The WGSL engine implements the same function, so both engines draw from identical streams
//! (their floats still differ, so they agree statistically, not bit for bit).

const M0: u32 = 0xD251_1F53;
const M1: u32 = 0xCD9E_8D57;
const W0: u32 = 0x9E37_79B9;
const W1: u32 = 0xBB67_AE85;

/// Philox4x32 with 10 rounds: the 4×32-bit counter `ctr` encrypted under the 2×32-bit key.
#[inline(always)]
pub fn philox4x32_10(mut ctr: [u32; 4], mut key: [u32; 2]) -> [u32; 4] {
    for round in 0..10 {
        if round > 0 {
            key[0] = key[0].wrapping_add(W0);
            key[1] = key[1].wrapping_add(W1);
        }
        let p0 = u64::from(M0) * u64::from(ctr[0]);
        let p1 = u64::from(M1) * u64::from(ctr[2]);
        ctr = [
            ((p1 >> 32) as u32) ^ ctr[1] ^ key[0],
            p1 as u32,
            ((p0 >> 32) as u32) ^ ctr[3] ^ key[1],
            p0 as u32,
        ];
    }
    ctr
}

/// A 32-bit word as a uniform number in the open interval (0, 1).
#[inline]
pub fn open01(word: u32) -> f64 {
    (f64::from(word) + 0.5) * (1.0 / 4_294_967_296.0)
}

/// The random stream of one photon: uniform numbers in (0, 1), four per Philox block.
#[derive(Debug, Clone)]
pub struct PhotonStream {
    key: [u32; 2],
    photon: u32,
    source: u32,
    block: u32,
    words: [u32; 4],
    next: usize,
}

impl PhotonStream {
    /// The stream of photon `photon` of source `source` under `seed`.
    pub fn new(seed: u64, source: u32, photon: u32) -> Self {
        PhotonStream {
            key: [seed as u32, (seed >> 32) as u32],
            photon,
            source,
            block: 0,
            words: [0; 4],
            next: 4,
        }
    }

    /// The next uniform number in (0, 1).
    #[inline(always)]
    pub fn uniform(&mut self) -> f64 {
        if self.next == 4 {
            self.words = philox4x32_10([self.photon, self.source, self.block, 0], self.key);
            self.block = self.block.wrapping_add(1);
            self.next = 0;
        }
        let w = self.words[self.next];
        self.next += 1;
        open01(w)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Known-answer vectors from the Random123 distribution (kat_vectors, philox4x32_10).
    #[test]
    fn known_answers() {
        assert_eq!(
            philox4x32_10([0, 0, 0, 0], [0, 0]),
            [0x6627_e8d5, 0xe169_c58d, 0xbc57_ac4c, 0x9b00_dbd8]
        );
        assert_eq!(
            philox4x32_10([u32::MAX; 4], [u32::MAX; 2]),
            [0x408f_276d, 0x41c8_3b0e, 0xa20b_c7c6, 0x6d54_51fd]
        );
        assert_eq!(
            philox4x32_10(
                [0x243f_6a88, 0x85a3_08d3, 0x1319_8a2e, 0x0370_7344],
                [0xa409_3822, 0x299f_31d0]
            ),
            [0xd16c_fe09, 0x94fd_cceb, 0x5001_e420, 0x2412_6ea1]
        );
    }

    #[test]
    fn uniforms_are_in_the_open_interval_and_roughly_uniform() {
        assert!(open01(0) > 0.0 && open01(u32::MAX) < 1.0);
        let mut s = PhotonStream::new(7, 3, 11);
        let n = 100_000;
        let mean: f64 = (0..n).map(|_| s.uniform()).sum::<f64>() / n as f64;
        // Standard error of the mean of U(0,1) is 0.2887/sqrt(n).
        assert!(
            (mean - 0.5).abs() < 4.0 * 0.2887 / (n as f64).sqrt(),
            "{mean}"
        );
    }

    #[test]
    fn streams_differ_by_seed_source_and_photon() {
        let first = |seed, source, photon| PhotonStream::new(seed, source, photon).uniform();
        let a = first(1, 0, 0);
        assert_ne!(a, first(2, 0, 0));
        assert_ne!(a, first(1, 1, 0));
        assert_ne!(a, first(1, 0, 1));
        assert_eq!(a, first(1, 0, 0));
    }
}
