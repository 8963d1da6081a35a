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

/// `ln x` for `x` in (0, 1) (a uniform from [`open01`]), inlined and without a division
/// (sampling `τ = −ln ξ` with the C library's `log` was a tenth of the CPU engine's time).
///
/// The table-driven scheme of ARM's optimized-routines `log`: `x = 2^k·z` with
/// `z ∈ [0.6875, 1.375)`; the top 7 bits of `z` pick a centre `c`; `r = (z − c)/c` (`z − c` is
/// exact, `|r| ≤ 2⁻⁸`) and `ln x = k·ln 2 + ln c + ln(1 + r)` with the series of `ln(1 + r)` to
/// `r⁶` (truncation below 2⁻⁵⁹). Error within a couple of ulps of `ln x`, and `c = 1` below 1 so
/// `ln x` near 1 keeps its relative precision.
#[inline(always)]
pub fn ln_open01(x: f64) -> f64 {
    // fdlibm's split of ln 2: `k·LN2_HI` is exact for |k| < 2¹¹.
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    const OFF: u64 = 0x3fe6_0000_0000_0000;
    let bits = x.to_bits();
    let tmp = bits.wrapping_sub(OFF);
    let i = ((tmp >> 45) & 127) as usize;
    let k = ((tmp as i64) >> 52) as f64;
    let z = f64::from_bits(bits.wrapping_sub(tmp & (0xfff << 52)));
    let [c, invc, logc] = LN_TABLE[i].map(f64::from_bits);
    let r = (z - c) * invc;
    let r2 = r * r;
    let poly = r2 * ((-0.5 + r * (1.0 / 3.0)) + r2 * ((-0.25 + r * 0.2) + r2 * (-1.0 / 6.0)));
    let hi = k * LN2_HI + logc;
    hi + r + (poly + k * LN2_LO)
}

/// `(c, 1/c, ln c)` for the 128 subintervals of `z ∈ [0.6875, 1.375)` (bit patterns of f64);
/// `c` is the midpoint, and exactly 1 for the interval just below 1.
const LN_TABLE: [[u64; 3]; 128] = [
    [0x3fe6100000000000, 0x3ff734f0c541fe8d, 0xbfd7cc7f7db46a0e],
    [0x3fe6300000000000, 0x3ff713786d9c7c09, 0xbfd76feecb947175],
    [0x3fe6500000000000, 0x3ff6f26016f26017, 0xbfd713e33a46a17c],
    [0x3fe6700000000000, 0x3ff6d1a62681c861, 0xbfd6b85b4cffa3fd],
    [0x3fe6900000000000, 0x3ff6b1490aa31a3d, 0xbfd65d558d4ce00b],
    [0x3fe6b00000000000, 0x3ff691473a88d0c0, 0xbfd602d08af091ec],
    [0x3fe6d00000000000, 0x3ff6719f3601671a, 0xbfd5a8cadbbedfa1],
    [0x3fe6f00000000000, 0x3ff6524f853b4aa3, 0xbfd54f431b7be1a9],
    [0x3fe7100000000000, 0x3ff63356b88ac0de, 0xbfd4f637ebba9810],
    [0x3fe7300000000000, 0x3ff614b36831ae94, 0xbfd49da7f3bcc41f],
    [0x3fe7500000000000, 0x3ff5f66434292dfc, 0xbfd44591e0539f49],
    [0x3fe7700000000000, 0x3ff5d867c3ece2a5, 0xbfd3edf463c1683e],
    [0x3fe7900000000000, 0x3ff5babcc647fa91, 0xbfd396ce359bbf54],
    [0x3fe7b00000000000, 0x3ff59d61f123ccaa, 0xbfd3401e12aecba1],
    [0x3fe7d00000000000, 0x3ff5805601580560, 0xbfd2e9e2bce12286],
    [0x3fe7f00000000000, 0x3ff56397ba7c52e2, 0xbfd2941afb186b7c],
    [0x3fe8100000000000, 0x3ff54725e6bb82fe, 0xbfd23ec5991eba49],
    [0x3fe8300000000000, 0x3ff52aff56a8054b, 0xbfd1e9e1678899f4],
    [0x3fe8500000000000, 0x3ff50f22e111c4c5, 0xbfd1956d3b9bc2fa],
    [0x3fe8700000000000, 0x3ff4f38f62dd4c9b, 0xbfd14167ef367783],
    [0x3fe8900000000000, 0x3ff4d843bedc2c4c, 0xbfd0edd060b78081],
    [0x3fe8b00000000000, 0x3ff4bd3edda68fe1, 0xbfd09aa572e6c6d4],
    [0x3fe8d00000000000, 0x3ff4a27fad76014a, 0xbfd047e60cde83b8],
    [0x3fe8f00000000000, 0x3ff4880522014880, 0xbfcfeb2233ea07cd],
    [0x3fe9100000000000, 0x3ff46dce34596066, 0xbfcf474b134df229],
    [0x3fe9300000000000, 0x3ff453d9e2c776ca, 0xbfcea4449f04aaf5],
    [0x3fe9500000000000, 0x3ff43a2730abee4d, 0xbfce020cc6235ab5],
    [0x3fe9700000000000, 0x3ff420b5265e5951, 0xbfcd60a17f903515],
    [0x3fe9900000000000, 0x3ff40782d10e6566, 0xbfccc000c9db3c52],
    [0x3fe9b00000000000, 0x3ff3ee8f42a5af07, 0xbfcc2028ab17f9b4],
    [0x3fe9d00000000000, 0x3ff3d5d991aa75c6, 0xbfcb811730b823d2],
    [0x3fe9f00000000000, 0x3ff3bd60d9232955, 0xbfcae2ca6f672bd4],
    [0x3fea100000000000, 0x3ff3a524387ac822, 0xbfca454082e6ab05],
    [0x3fea300000000000, 0x3ff38d22d366088e, 0xbfc9a8778debaa38],
    [0x3fea500000000000, 0x3ff3755bd1c945ee, 0xbfc90c6db9fcbcd9],
    [0x3fea700000000000, 0x3ff35dce5f9f2af8, 0xbfc871213750e994],
    [0x3fea900000000000, 0x3ff34679ace01346, 0xbfc7d6903caf5ad0],
    [0x3feab00000000000, 0x3ff32f5ced6a1dfa, 0xbfc73cb9074fd14d],
    [0x3fead00000000000, 0x3ff3187758e9ebb6, 0xbfc6a399dabbd383],
    [0x3feaf00000000000, 0x3ff301c82ac40260, 0xbfc60b3100b09476],
    [0x3feb100000000000, 0x3ff2eb4ea1fed14b, 0xbfc5737cc9018cdd],
    [0x3feb300000000000, 0x3ff2d50a012d50a0, 0xbfc4dc7b897bc1c8],
    [0x3feb500000000000, 0x3ff2bef98e5a3711, 0xbfc4462b9dc9b3dc],
    [0x3feb700000000000, 0x3ff2a91c92f3c105, 0xbfc3b08b6757f2a9],
    [0x3feb900000000000, 0x3ff293725bb804a5, 0xbfc31b994d3a4f85],
    [0x3febb00000000000, 0x3ff27dfa38a1ce4d, 0xbfc28753bc11aba5],
    [0x3febd00000000000, 0x3ff268b37cd60127, 0xbfc1f3b925f25d41],
    [0x3febf00000000000, 0x3ff2539d7e9177b2, 0xbfc160c8024b27b1],
    [0x3fec100000000000, 0x3ff23eb79717605b, 0xbfc0ce7ecdccc28d],
    [0x3fec300000000000, 0x3ff22a0122a0122a, 0xbfc03cdc0a51ec0d],
    [0x3fec500000000000, 0x3ff21579804855e6, 0xbfbf57bc7d9005db],
    [0x3fec700000000000, 0x3ff2012012012012, 0xbfbe3707ee30487b],
    [0x3fec900000000000, 0x3ff1ecf43c7fb84c, 0xbfbd179788219364],
    [0x3fecb00000000000, 0x3ff1d8f5672e4abd, 0xbfbbf968769fca11],
    [0x3fecd00000000000, 0x3ff1c522fc1ce059, 0xbfbadc77ee5aea8c],
    [0x3fecf00000000000, 0x3ff1b17c67f2bae3, 0xbfb9c0c32d4d2548],
    [0x3fed100000000000, 0x3ff19e0119e0119e, 0xbfb8a6477a91dc29],
    [0x3fed300000000000, 0x3ff18ab083902bdb, 0xbfb78d02263d82d3],
    [0x3fed500000000000, 0x3ff1778a191bd684, 0xbfb674f089365a7a],
    [0x3fed700000000000, 0x3ff1648d50fc3201, 0xbfb55e10050e0384],
    [0x3fed900000000000, 0x3ff151b9a3fdd5c9, 0xbfb4485e03dbdfad],
    [0x3fedb00000000000, 0x3ff13f0e8d344724, 0xbfb333d7f8183f4b],
    [0x3fedd00000000000, 0x3ff12c8b89edc0ac, 0xbfb2207b5c78549e],
    [0x3fedf00000000000, 0x3ff11a3019a74826, 0xbfb10e45b3cae831],
    [0x3fee100000000000, 0x3ff107fbbe011080, 0xbfaffa6911ab9301],
    [0x3fee300000000000, 0x3ff0f5edfab325a2, 0xbfadda8adc67ee4e],
    [0x3fee500000000000, 0x3ff0e40655826011, 0xbfabbcebfc68f420],
    [0x3fee700000000000, 0x3ff0d24456359e3a, 0xbfa9a187b573de7c],
    [0x3fee900000000000, 0x3ff0c0a7868b4171, 0xbfa788595a3577ba],
    [0x3feeb00000000000, 0x3ff0af2f722eecb5, 0xbfa5715c4c03ceef],
    [0x3feed00000000000, 0x3ff09ddba6af8360, 0xbfa35c8bfaa1306b],
    [0x3feef00000000000, 0x3ff08cabb37565e2, 0xbfa149e3e4005a8d],
    [0x3fef100000000000, 0x3ff07b9f29b8eae2, 0xbf9e72bf2813ce51],
    [0x3fef300000000000, 0x3ff06ab59c7912fb, 0xbf9a55f548c5c43f],
    [0x3fef500000000000, 0x3ff059eea0727586, 0xbf963d6178690bd6],
    [0x3fef700000000000, 0x3ff04949cc1664c5, 0xbf9228fb1fea2e28],
    [0x3fef900000000000, 0x3ff038c6b78247fc, 0xbf8c317384c75f06],
    [0x3fefb00000000000, 0x3ff02864fc7729e9, 0xbf841929f96832f0],
    [0x3fefd00000000000, 0x3ff0182436517a37, 0xbf78121214586b54],
    [0x3ff0000000000000, 0x3ff0000000000000, 0x0000000000000000],
    [0x3ff0100000000000, 0x3fefe01fe01fe020, 0x3f6ff00aa2b10bc0],
    [0x3ff0300000000000, 0x3fefa11caa01fa12, 0x3f87dc475f810a77],
    [0x3ff0500000000000, 0x3fef6310aca0dbb5, 0x3f93cea44346a575],
    [0x3ff0700000000000, 0x3fef25f644230ab5, 0x3f9b9fc027af9198],
    [0x3ff0900000000000, 0x3feee9c7f8458e02, 0x3fa1b0d98923d980],
    [0x3ff0b00000000000, 0x3feeae807aba01eb, 0x3fa58a5bafc8e4d5],
    [0x3ff0d00000000000, 0x3fee741aa59750e4, 0x3fa95c830ec8e3eb],
    [0x3ff0f00000000000, 0x3fee3a9179dc1a73, 0x3fad276b8adb0b52],
    [0x3ff1100000000000, 0x3fee01e01e01e01e, 0x3fb075983598e471],
    [0x3ff1300000000000, 0x3fedca01dca01dca, 0x3fb253f62f0a1417],
    [0x3ff1500000000000, 0x3fed92f2231e7f8a, 0x3fb42edcbea646f0],
    [0x3ff1700000000000, 0x3fed5cac807572b2, 0x3fb60658a93750c4],
    [0x3ff1900000000000, 0x3fed272ca3fc5b1a, 0x3fb7da766d7b12cd],
    [0x3ff1b00000000000, 0x3fecf26e5c44bfc6, 0x3fb9ab42462033ad],
    [0x3ff1d00000000000, 0x3fecbe6d9601cbe7, 0x3fbb78c82bb0eda1],
    [0x3ff1f00000000000, 0x3fec8b265afb8a42, 0x3fbd4313d66cb35d],
    [0x3ff2100000000000, 0x3fec5894d10d4986, 0x3fbf0a30c01162a6],
    [0x3ff2300000000000, 0x3fec26b5392ea01c, 0x3fc0671512ca596e],
    [0x3ff2500000000000, 0x3febf583ee868d8b, 0x3fc14785846742ac],
    [0x3ff2700000000000, 0x3febc4fd65883e7b, 0x3fc2266f190a5acb],
    [0x3ff2900000000000, 0x3feb951e2b18ff23, 0x3fc303d718e47fd3],
    [0x3ff2b00000000000, 0x3feb65e2e3beee05, 0x3fc3dfc2b0ecc62a],
    [0x3ff2d00000000000, 0x3feb37484ad806ce, 0x3fc4ba36f39a55e5],
    [0x3ff2f00000000000, 0x3feb094b31d922a4, 0x3fc59338d9982086],
    [0x3ff3100000000000, 0x3feadbe87f94905e, 0x3fc66acd4272ad51],
    [0x3ff3300000000000, 0x3feaaf1d2f87ebfd, 0x3fc740f8f54037a5],
    [0x3ff3500000000000, 0x3fea82e65130e159, 0x3fc815c0a14357eb],
    [0x3ff3700000000000, 0x3fea574107688a4a, 0x3fc8e928de886d41],
    [0x3ff3900000000000, 0x3fea2c2a87c51ca0, 0x3fc9bb362e7dfb83],
    [0x3ff3b00000000000, 0x3fea01a01a01a01a, 0x3fca8becfc882f19],
    [0x3ff3d00000000000, 0x3fe9d79f176b682d, 0x3fcb5b519e8fb5a4],
    [0x3ff3f00000000000, 0x3fe9ae24ea5510da, 0x3fcc2968558c18c1],
    [0x3ff4100000000000, 0x3fe9852f0d8ec0ff, 0x3fccf6354e09c5dc],
    [0x3ff4300000000000, 0x3fe95cbb0be377ae, 0x3fcdc1bca0abec7d],
    [0x3ff4500000000000, 0x3fe934c67f9b2ce6, 0x3fce8c0252aa5a60],
    [0x3ff4700000000000, 0x3fe90d4f120190d5, 0x3fcf550a564b7b37],
    [0x3ff4900000000000, 0x3fe8e6527af1373f, 0x3fd00e6c45ad501d],
    [0x3ff4b00000000000, 0x3fe8bfce8062ff3a, 0x3fd071b85fcd590d],
    [0x3ff4d00000000000, 0x3fe899c0f601899c, 0x3fd0d46b579ab74b],
    [0x3ff4f00000000000, 0x3fe87427bcc092b9, 0x3fd136870293a8b0],
    [0x3ff5100000000000, 0x3fe84f00c2780614, 0x3fd1980d2dd4236f],
    [0x3ff5300000000000, 0x3fe82a4a0182a4a0, 0x3fd1f8ff9e48a2f3],
    [0x3ff5500000000000, 0x3fe8060180601806, 0x3fd2596010df763a],
    [0x3ff5700000000000, 0x3fe7e225515a4f1d, 0x3fd2b9303ab89d25],
    [0x3ff5900000000000, 0x3fe7beb3922e017c, 0x3fd31871c9544185],
    [0x3ff5b00000000000, 0x3fe79baa6bb6398b, 0x3fd3772662bfd85b],
    [0x3ff5d00000000000, 0x3fe77908119ac60d, 0x3fd3d54fa5c1f710],
    [0x3ff5f00000000000, 0x3fe756cac201756d, 0x3fd432ef2a04e814],
];

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

    /// The stream is block after block of `philox4x32_10` on `(photon, source, block, 0)`.
    #[test]
    fn stream_follows_the_counter_layout() {
        let seed = 0x0123_4567_89ab_cdefu64;
        let key = [seed as u32, (seed >> 32) as u32];
        let mut s = PhotonStream::new(seed, 77, 123_456);
        for block in 0..9 {
            for word in philox4x32_10([123_456, 77, block, 0], key) {
                assert_eq!(s.uniform(), open01(word));
            }
        }
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
    fn inlined_log_matches_the_library_log() {
        let mut worst: f64 = 0.0;
        let mut s = PhotonStream::new(1, 2, 3);
        let words = (0..200_000u32)
            .map(|_| (s.uniform() * 4_294_967_296.0) as u32)
            .chain([0, 1, 2, 1 << 31, (1 << 31) - 1, u32::MAX - 1, u32::MAX]);
        for w in words {
            let x = open01(w);
            let exact = x.ln();
            let fast = ln_open01(x);
            worst = worst.max(((fast - exact) / exact.abs()).abs());
        }
        assert!(worst < 6e-16, "worst relative error {worst}");
        assert_eq!(ln_open01(0.5), -std::f64::consts::LN_2);
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
