// rng.wgsl — the photon random streams: Philox4x32-10 (Salmon et al., SC'11).
//
// The same function as worker/src/rng.rs, word for word: a photon's stream has the key
// (seed low 32 bits, seed high 32 bits) and the counter (photon, source, block, 0); each block
// gives four 32-bit words, used in order. Only the conversion to floats differs from the CPU
// (f32 here, see `uniform01`), so the two engines agree statistically, never bit for bit.

const PHILOX_M0: u32 = 0xD2511F53u;
const PHILOX_M1: u32 = 0xCD9E8D57u;
const PHILOX_W0: u32 = 0x9E3779B9u;
const PHILOX_W1: u32 = 0xBB67AE85u;

// The 64-bit product a·b as (high word, low word). WGSL has no mul_hi: build it from 16-bit
// halves. `cross` cannot overflow: (2^16−1)^2 + 2·(2^16−1) < 2^32. On devices with 64-bit
// integers the engine swaps this function for rng_int64.wgsl's (same result, one multiply).
// BEGIN mul_hi_lo
fn mul_hi_lo(a: u32, b: u32) -> vec2<u32> {
    let a_lo = a & 0xFFFFu;
    let a_hi = a >> 16u;
    let b_lo = b & 0xFFFFu;
    let b_hi = b >> 16u;
    let ll = a_lo * b_lo;
    let hl = a_hi * b_lo;
    let lh = a_lo * b_hi;
    let hh = a_hi * b_hi;
    let cross = (ll >> 16u) + (hl & 0xFFFFu) + lh;
    let hi = hh + (hl >> 16u) + (cross >> 16u);
    return vec2<u32>(hi, a * b);
}
// END mul_hi_lo

// One Philox round under round key `key`.
fn philox_round(ctr: vec4<u32>, key: vec2<u32>) -> vec4<u32> {
    let p0 = mul_hi_lo(PHILOX_M0, ctr.x);
    let p1 = mul_hi_lo(PHILOX_M1, ctr.z);
    return vec4<u32>(p1.x ^ ctr.y ^ key.x, p1.y, p0.x ^ ctr.w ^ key.y, p0.y);
}

// Philox4x32-10: ten rounds, the key bumped by the Weyl constants between rounds.
fn philox4x32_10(ctr_in: vec4<u32>, key_in: vec2<u32>) -> vec4<u32> {
    let bump = vec2<u32>(PHILOX_W0, PHILOX_W1);
    var ctr = ctr_in;
    var key = key_in;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    key += bump;
    ctr = philox_round(ctr, key);
    return ctr;
}

// The current photon's stream: key, photon, source, next block, and the words of the last block
// not used yet (front first) with their count, 0 to 3. (Scalars and whole vectors only: a write
// to one component of a vector variable is slow on lavapipe.)
var<private> rng_key: vec2<u32>;
var<private> rng_photon: u32;
var<private> rng_source: u32;
var<private> rng_block: u32;
var<private> rng_rest: vec4<u32>;
var<private> rng_count: u32;

// Starts the stream of photon `photon` of source `source` under `seed` = (low, high).
fn rng_start(seed: vec2<u32>, source: u32, photon: u32) {
    rng_key = seed;
    rng_photon = photon;
    rng_source = source;
    rng_block = 0u;
    rng_count = 0u;
}

// The stream's next three words: a flight draws exactly three (τ, then at its collision the
// absorption test and the turn), so flight k of a photon reads words 3k, 3k+1 and 3k+2 — the
// words the CPU tracer's sequential draws read.
//
// One Philox block is computed on every call and used when fewer than three words are left
// over (three calls in four). There is no `if` around it on purpose: SIMD CPU devices
// (lavapipe) run both sides of every branch, so a conditional refill in each draw would cost a
// block per word.
fn rng_next3() -> vec3<u32> {
    let fresh = philox4x32_10(vec4<u32>(rng_photon, rng_source, rng_block, 0u), rng_key);
    let c = rng_count;
    let rest = rng_rest;
    let words = select(
        select(select(rest.xyz, vec3<u32>(rest.xy, fresh.x), c == 2u), vec3<u32>(rest.x, fresh.xy), c == 1u),
        fresh.xyz,
        c == 0u,
    );
    rng_rest = select(
        select(select(vec4<u32>(0u), vec4<u32>(fresh.yzw, 0u), c == 2u), vec4<u32>(fresh.zw, 0u, 0u), c == 1u),
        vec4<u32>(fresh.w, 0u, 0u, 0u),
        c == 0u,
    );
    let used = c < 3u;
    rng_block += select(0u, 1u, used);
    rng_count = select(0u, c + 1u, used);
    return words;
}

// A word as a uniform number in the open interval (0, 1): its top 23 bits plus one half, scaled
// by 2^-23. Every value, 2^-24 … 1 − 2^-24, is exact in f32, so −log(ξ) and tan(π(ξ − ½)) stay
// finite (`model.md`). Using all 32 bits would round the top words to 1.0.
fn to_uniform(word: u32) -> f32 {
    return (f32(word >> 9u) + 0.5) * (1.0 / 8388608.0);
}
