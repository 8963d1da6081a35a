// rng_int64.wgsl — `mul_hi_lo` for devices with 64-bit integers (wgpu's SHADER_INT64): the
// engine puts it in place of rng.wgsl's 16-bit version. Same words, one 64-bit multiply.

fn mul_hi_lo(a: u32, b: u32) -> vec2<u32> {
    // The low word as a 32-bit product: narrowing the 64-bit one costs more on lavapipe.
    let p = u64(a) * u64(b);
    return vec2<u32>(u32(p >> 32u), a * b);
}
