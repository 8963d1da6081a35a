// tallies.wgsl — where a leaving photon is counted: arc length, bin, and the atomic tallies.
//
// Mirrors `Geometry::bin_of_exit` and `transport::exit_arc_length` (worker/src): bin coordinates
// within BIN_SNAP of a whole number snap to it (an edge belongs to the upper bin), s = 4W wraps
// to 0, and a corner exit counts on the edge whose arc-length interval starts at that corner.

const PI: f32 = 3.14159265358979;
const HALF_PI: f32 = 1.57079632679490;
const BIN_SNAP: f32 = 1e-4;

// ⌊u⌋, except that u within BIN_SNAP of a whole number counts as that number.
fn snapped_floor(u: f32) -> i32 {
    let n = round(u);
    if (abs(u - n) <= BIN_SNAP) {
        return i32(n);
    }
    return i32(floor(u));
}

// Arc length of a photon that left the grid at `exit`, through the side(s) `out` it stepped out
// of, moving with the signs `step`.
fn exit_arc_length(exit: vec2<f32>, out: vec2<bool>, step: vec2<i32>) -> f32 {
    let w = params.size_mm;
    if (out.x && out.y) {
        // Through a corner: the edge whose arc-length interval starts there.
        if (step.x < 0 && step.y < 0) {
            return 0.0;
        }
        if (step.x > 0 && step.y < 0) {
            return w;
        }
        if (step.x > 0 && step.y > 0) {
            return 2.0 * w;
        }
        return 3.0 * w;
    }
    if (out.x) {
        if (step.x > 0) {
            return w + clamp(exit.y, 0.0, w);
        }
        return 4.0 * w - clamp(exit.y, 0.0, w);
    }
    if (step.y > 0) {
        return 3.0 * w - clamp(exit.x, 0.0, w);
    }
    return clamp(exit.x, 0.0, w);
}

// The bin j = p'·K + k' of a photon leaving at arc length `s` with unit direction `d`.
fn bin_of_exit(s: f32, d: vec2<f32>) -> u32 {
    let positions = i32(params.positions);
    let directions = i32(params.directions);
    var p = snapped_floor(s * params.inv_extent);
    if (p >= positions) {
        p -= positions;
    }
    p = clamp(p, 0, positions - 1);
    // The outward normal of edge p / (P/4): bottom, right, top, left. (Compared, not divided:
    // CPUs have no vector integer division, so a division costs one per lane.)
    let quarter = positions / 4;
    var outward = vec2<f32>(0.0, -1.0);
    if (p >= 3 * quarter) {
        outward = vec2<f32>(-1.0, 0.0);
    } else if (p >= 2 * quarter) {
        outward = vec2<f32>(0.0, 1.0);
    } else if (p >= quarter) {
        outward = vec2<f32>(1.0, 0.0);
    }
    let cos_b = dot(outward, d);
    let sin_b = outward.x * d.y - outward.y * d.x;
    let beta = atan2(sin_b, cos_b);
    let k = clamp(snapped_floor((beta + HALF_PI) * f32(directions) / PI), 0, directions - 1);
    return u32(p) * params.directions + u32(k);
}

// Adds this invocation's scattering events, `events` = (low word, high word), to its item's
// 64-bit total: the add whose low word wrapped carries one into the high word.
fn add_scatter_events(item: u32, events: vec2<u32>) {
    let old = atomicAdd(&scatters[2u * item], events.x);
    let carry = select(0u, 1u, old + events.x < old);
    atomicAdd(&scatters[2u * item + 1u], events.y + carry);
}

// Counts this invocation in the last word of `scatters` unless its run `finished`. Lavapipe ends
// every loop of an invocation once their iterations together pass 65 535 (gallivm's
// LP_MAX_TGSI_LOOP_ITERATIONS, shared between all loops of a shader): the loop is left as if by a
// `break`, and the photons not yet followed are lost. A run cut short so is counted here, and the
// host renders its chunk again with fewer photons per invocation. Real GPUs never cut a loop.
fn end_of_run(finished: bool) {
    if (!finished) {
        atomicAdd(&scatters[arrayLength(&scatters) - 1u], 1u);
    }
}
