// differential.wgsl — the differential render (`docs/model.md`, "Differential renders"): the plain
// transport of transport.wgsl, photon for photon the same flights, with each photon's path tallied
// per pixel (length, scattering collisions and, per table material, Σ ln(1 + g² − 2g·cos θ) over
// those collisions) in the pixels some change touches, and for every detected photon its weight
// under each change added, as `w − 1` in fixed point, to that change's (row, bin).
//
// The march is `main`'s, step for step, through the same `block_ahead` and `leave_block`: the
// same blocks, the same positions, the same random words, so the counts are those of a plain
// render. What the tally needs is computed beside it: a straight piece inside a block is split
// into its pixels by a grid walk that moves nothing, and a collision's pixel is the pixel of its
// position within the block. Exits are tallied at once (this entry point does not batch them in
// rounds: a detected photon's weights are computed from its own tally before the next photon
// starts).
//
// Per invocation, a slot of `scratch` (`diff.slot_words` words; invocation `gid.x` of a dispatch
// uses slot `gid.x`, left clean for the next dispatch) holds:
//   per pixel (iy·N + ix):  seen, length (f32), collisions (f32), then one phase sum per material;
//   the pixels touched, in order;
//   per change: its log-weight (f32), then the changes hit, in order, then per change its mark
//   (0 not hit, 1 hit, 2 weight 0).
//
// Weights are added as 64-bit fixed-point numbers with 2^-24 per unit (two 32-bit atomics per
// (change, row, bin), the low word's carry added to the high word): integer sums do not depend on
// the order of the adds, so a seed fixes every bit.

struct Differential {
    // Changes in this render, materials in the table, pixels N², words per scratch slot.
    changes: u32,
    materials: u32,
    cells: u32,
    slot_words: u32,
}

// One table material as a change's weight needs it (`cpu::differential::Physics`).
struct Physics {
    // σt (0 for opaque), ln σs, ln(1 − g²), g.
    sigma_t: f32,
    ln_sigma_s: f32,
    ln_norm: f32,
    g: f32,
    // 1 when σs > 0; 1 when opaque.
    scatters: u32,
    opaque: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(6) var<uniform> diff: Differential;
// Per pixel p (iy·N + ix): its factors are words [2·factors[p], 2·factors[p+1]) after the
// N² + 1 offsets, two words each: the change, and (from material << 16) | to material.
@group(0) @binding(7) var<storage, read> factors: array<u32>;
@group(0) @binding(8) var<storage, read> physics: array<Physics>;
@group(0) @binding(9) var<storage, read_write> scratch: array<u32>;
// Per change, chunk row (one item per chunk: the row is the source's) and bin: Σ (w − 1) as (low, high) words of a 64-bit fixed-point number.
@group(0) @binding(10) var<storage, read_write> deltas: array<atomic<u32>>;

// Fixed-point units per unit of weight (2^24), and the largest weight added (2^20: beyond it a
// change's estimate has no effective sample size left; documented in model.md).
const FIXED_SCALE: f32 = 16777216.0;
const MAX_WEIGHT: f32 = 1048576.0;
const LN_MAX_WEIGHT: f32 = 13.862944;

// This invocation's scratch slot, and how many pixels its photon has touched.
var<private> slot_base: u32;
var<private> touched_count: u32;

fn cell_words() -> u32 {
    return 3u + diff.materials;
}

fn path_word(cell: u32) -> u32 {
    return slot_base + cell * cell_words();
}

fn touched_word() -> u32 {
    return slot_base + diff.cells * cell_words();
}

fn logw_word() -> u32 {
    return touched_word() + diff.cells;
}

fn hits_word() -> u32 {
    return logw_word() + diff.changes;
}

fn marks_word() -> u32 {
    return hits_word() + diff.changes;
}

fn has_factors(cell: u32) -> bool {
    return factors[cell + 1u] > factors[cell];
}

// The first word of `cell`'s tally, marking it touched.
fn touch(cell: u32) -> u32 {
    let w = path_word(cell);
    if (scratch[w] == 0u) {
        scratch[w] = 1u;
        scratch[touched_word() + touched_count] = cell;
        touched_count += 1u;
    }
    return w;
}

fn add_f32(word: u32, v: f32) {
    scratch[word] = bitcast<u32>(bitcast<f32>(scratch[word]) + v);
}

fn tally_length(cell: u32, length: f32) {
    if (length > 0.0 && has_factors(cell)) {
        let w = touch(cell);
        add_f32(w + 1u, length);
    }
}

fn tally_scatter(cell: u32, cos_theta: f32) {
    if (!has_factors(cell)) {
        return;
    }
    let w = touch(cell);
    add_f32(w + 2u, 1.0);
    for (var k = 0u; k < diff.materials; k++) {
        let g = physics[k].g;
        add_f32(w + 3u + k, log(max(1.0 + g * g - 2.0 * g * cos_theta, 1e-30)));
    }
}

// Splits the straight piece of `length` from `pos` along `dir`, inside the block of side `side`
// whose lowest pixel is `lo`, into its pixels (`transport::split_flight`).
fn tally_piece(pos: vec2<f32>, dir: vec2<f32>, length: f32, lo: vec2<i32>, side: i32) {
    let n = i32(params.grid);
    let h = params.pixel;
    let hi = lo + vec2<i32>(side - 1);
    var p = clamp(vec2<i32>(floor(pos * params.inv_pixel)), lo, hi);
    let step = vec2<i32>(select(-1, 1, dir.x > 0.0), select(-1, 1, dir.y > 0.0));
    let line = vec2<f32>(p + select(vec2<i32>(0), vec2<i32>(1), step > vec2<i32>(0))) * h;
    let moving = dir != vec2<f32>(0.0);
    var t_max = select(vec2<f32>(FAR), max((line - pos) / dir, vec2<f32>(0.0)), moving);
    let t_delta = select(vec2<f32>(FAR), h / abs(dir), moving);
    var t = 0.0;
    // A straight piece crosses at most 2·side pixels of its block; the bound only guards.
    for (var i = 0; i < 2 * side + 2; i++) {
        let t_next = min(min(t_max.x, t_max.y), length);
        if (t_next > t) {
            tally_length(u32(p.y * n + p.x), t_next - t);
        }
        t = t_next;
        if (t >= length) {
            break;
        }
        if (t_max.x <= t_max.y) {
            p.x = clamp(p.x + step.x, lo.x, hi.x);
            t_max.x += t_delta.x;
        } else {
            p.y = clamp(p.y + step.y, lo.y, hi.y);
            t_max.y += t_delta.y;
        }
    }
}

// The log-weight factor of a pixel going from material `m_old` to `m_new` for a photon with `length`, `n`
// collisions and phase sums from word `phase` there (`cpu::differential::log_factor`); `zero`
// set for weight 0.
fn log_factor(m_old: u32, m_new: u32, length: f32, n: f32, phase: u32, zero: ptr<function, bool>) -> f32 {
    let a = physics[m_old];
    let b = physics[m_new];
    if (b.opaque != 0u) {
        *zero = true;
        return 0.0;
    }
    let path = -(b.sigma_t - a.sigma_t) * length;
    if (b.scatters == 0u) {
        *zero = n > 0.0;
        return path;
    }
    if (n == 0.0) {
        return path;
    }
    var lw = path + n * (b.ln_sigma_s - a.ln_sigma_s);
    if (a.g != b.g) {
        lw += n * (b.ln_norm - a.ln_norm) - (bitcast<f32>(scratch[phase + m_new]) - bitcast<f32>(scratch[phase + m_old]));
    }
    return lw;
}

// Adds `v` to the 64-bit fixed-point number at words `index`, `index + 1`.
fn add_fixed(index: u32, v: f32) {
    let x = round(clamp(v, -1.0, MAX_WEIGHT) * FIXED_SCALE);
    var lo = 0u;
    var hi = 0u;
    if (x < 2147483648.0) {
        // −2^24 ≤ x < 2^31: exact as an i32, sign-extended into the high word.
        let xi = i32(x);
        lo = bitcast<u32>(xi);
        hi = select(0u, 0xffffffffu, xi < 0);
    } else {
        // x ≥ 2^31 is a multiple of 2^8: both words are exact in f32.
        let high = floor(x * 2.3283064365386963e-10);
        lo = u32(x - high * 4294967296.0);
        hi = u32(high);
    }
    let old = atomicAdd(&deltas[index], lo);
    let carry = select(0u, 1u, old + lo < old);
    atomicAdd(&deltas[index + 1u], hi + carry);
}

// The photon's end: if it was detected in `bin` of chunk row `row`, every change it touched gets
// `w − 1` there; then the slot is cleared for the next photon.
fn finish_photon(detected: bool, row: u32, bin: u32) {
    let factor_base = diff.cells + 1u;
    if (detected) {
        var hits = 0u;
        for (var i = 0u; i < touched_count; i++) {
            let cell = scratch[touched_word() + i];
            let w = path_word(cell);
            let length = bitcast<f32>(scratch[w + 1u]);
            let n = bitcast<f32>(scratch[w + 2u]);
            for (var f = factors[cell]; f < factors[cell + 1u]; f++) {
                let k = factors[factor_base + 2u * f];
                let pair = factors[factor_base + 2u * f + 1u];
                var zero = false;
                let lw = log_factor(pair >> 16u, pair & 0xffffu, length, n, w + 3u, &zero);
                var mark = scratch[marks_word() + k];
                if (mark == 0u) {
                    scratch[hits_word() + hits] = k;
                    hits += 1u;
                    scratch[logw_word() + k] = bitcast<u32>(0.0);
                    mark = 1u;
                }
                if (zero) {
                    mark = 2u;
                } else {
                    add_f32(logw_word() + k, lw);
                }
                scratch[marks_word() + k] = mark;
            }
        }
        let bins = params.sources;
        for (var j = 0u; j < hits; j++) {
            let k = scratch[hits_word() + j];
            let mark = scratch[marks_word() + k];
            let lw = bitcast<f32>(scratch[logw_word() + k]);
            let weight = select(exp(min(lw, LN_MAX_WEIGHT)), 0.0, mark == 2u);
            add_fixed(2u * ((k * params.source_count + row) * bins + bin), weight - 1.0);
            scratch[marks_word() + k] = 0u;
        }
    }
    for (var i = 0u; i < touched_count; i++) {
        let w = path_word(scratch[touched_word() + i]);
        for (var j = 0u; j < cell_words(); j++) {
            scratch[w + j] = 0u;
        }
    }
    touched_count = 0u;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn differential(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.task_count) {
        return;
    }
    slot_base = gid.x * diff.slot_words;
    touched_count = 0u;
    let r = run_of_task(params.task_first + gid.x);
    var left = r.photons;
    var photon = r.photon_first;
    let ray = sources[r.source];
    let seed = seeds[r.item];
    let n = i32(params.grid);
    let start = vec2<i32>(ray.start);
    let m_start = medium[r.cell_base + u32(start.y * n + start.x)];
    if (m_start.x < 0.0) {
        return;
    }

    var events_lo = 0u;
    var events_hi = 0u;
    var alive = false;
    var pos = vec2<f32>(0.0);
    var dir = vec2<f32>(0.0);
    var cell = vec2<i32>(0);
    var m = vec4<f32>(0.0);
    var finished = false;

    // Rounds of FLIGHTS_PER_ROUND flights, as in `main`.
    loop {
        for (var flight = 0u; flight < FLIGHTS_PER_ROUND; flight++) {
            if (!alive) {
                if (left == 0u) {
                    break;
                }
                left -= 1u;
                rng_start(seed, r.source, photon);
                photon += 1u;
                pos = ray.origin;
                dir = ray.dir;
                cell = start;
                m = m_start;
                alive = true;
            }

            // A flight, as in `main`, with each straight piece tallied by pixel.
            let words = rng_next3();
            var tau = -log(to_uniform(words.x));
            let step = vec2<i32>(select(-1, 1, dir.x > 0.0), select(-1, 1, dir.y > 0.0));
            loop {
                let b = block_ahead(cell, m, pos, dir, step);
                let spend = m.x * b.t_exit;
                if (spend >= tau) {
                    let length = tau / m.x;
                    tally_piece(pos, dir, length, b.lo, b.side);
                    pos += length * dir;
                    break;
                }
                tally_piece(pos, dir, b.t_exit, b.lo, b.side);
                tau -= spend;
                let crossed = leave_block(b, pos, dir, step);
                pos = crossed.pos;
                cell = crossed.cell;
                if (outside_grid(cell)) {
                    break;
                }
                m = medium[r.cell_base + u32(cell.y * n + cell.x)];
                if (m.x < 0.0) {
                    break;
                }
            }
            let out = (cell < vec2<i32>(0)) | (cell >= vec2<i32>(n));

            if (any(out)) {
                let bin = bin_of_exit(exit_arc_length(pos, out, step), dir);
                atomicAdd(&counts[r.tally_base + bin], 1u);
                finish_photon(true, r.row, bin);
                alive = false;
                continue;
            }
            if (m.x < 0.0) {
                finish_photon(false, r.row, 0u);
                alive = false;
                continue;
            }
            if (to_uniform(words.y) < m.z) {
                finish_photon(false, r.row, 0u);
                alive = false;
                continue;
            }
            events_lo += 1u;
            events_hi += select(0u, 1u, events_lo == 0u);
            let turned = hg_turn(dir, m.w, to_uniform(words.z));
            // The collision's pixel: its position's, within the block.
            let side = 1 << u32(m.y);
            let lo = cell & vec2<i32>(-side);
            let at = clamp(vec2<i32>(floor(pos * params.inv_pixel)), lo, lo + vec2<i32>(side - 1));
            tally_scatter(u32(at.y * n + at.x), clamp(dot(dir, turned), -1.0, 1.0));
            dir = turned;
        }
        if (left == 0u && !alive) {
            finished = true;
            break;
        }
    }
    end_of_run(finished);
    add_scatter_events(r.item, vec2<u32>(events_lo, events_hi));
}
