// transport.wgsl — flatland photon transport through the pixel grid, exactly as `model.md`
// ("Transport") and worker/src/transport.rs: exact grid traversal, opaque pixels absorb on entry,
// transmissive pixels pass, analog absorption, flatland Henyey–Greenstein.
//
// Work layout. The host cuts a render into chunks of tally rows: a row is one (item, source) pair
// and a chunk is some whole items, or some sources of one item. Each row's photon range
// [photon_first, photon_first + photon_count) is split into `splits` contiguous runs of
// `per_invocation` photons; a task is one (row, run) pair, task = row · splits + run, and one
// invocation follows every photon of its task, one after the other. The photon index still keys
// the random stream, so the counts do not depend on how photons are split over invocations or
// dispatches. A dispatch runs tasks [task_first, task_first + task_count).
//
// Within an invocation the loop runs one flight per iteration and starts the next photon as soon
// as one ends, so the lanes of a SIMD group stay busy until their whole run is done.
//
// Shape of the code. CPU devices (lavapipe) run 8 invocations in SIMD lanes and do not branch
// around an `if`: both sides always run, masked. So the loop body is kept short and branch-free
// where it can be: each flight draws its three random words with exactly one Philox block
// (rng.wgsl), the turn uses short polynomials, and exits are parked in registers and tallied
// once per round of FLIGHTS_PER_ROUND flights (a loop with the same trip count in every lane),
// not after every flight. None of this changes what a photon does: real GPUs just run it.
//
// Traversal. Spending σt·length pixel by pixel along a straight path through pixels of one
// material spends, exactly, σt times the whole length: so the march steps through the largest
// aligned uniform block around the current pixel at once (the host stores its level with every
// pixel; a uniform medium is one block), and stops only where the material may change. That is
// where the per-pixel rules matter, and they are applied there, on the pixel grid: a step through
// a block corner (within `corner_tol`) is diagonal and does not enter the side pixels; leaving a
// block through one wall, the coordinate along the wall picks the pixel, a coordinate on a grid
// line belonging to the pixel the ray moves into, or, for a ray running along that line, to the
// pixel on its left; entering an opaque pixel absorbs. Storage reads are the dearest operation on
// CPU devices (lavapipe), and this reads one record per block entered, none per collision.

// The dispatch's parameters (a dynamic-offset uniform: one record per dispatch).
struct Params {
    // Side W of the medium (mm), pixel side h = W / N, 1/h, and 1/e for the extent e = 4W / P.
    size_mm: f32,
    pixel: f32,
    inv_pixel: f32,
    inv_extent: f32,
    // Two grid-line crossings closer than this (mm along the ray) are one corner step.
    corner_tol: f32,
    // N, P, K, and the number of sources P·K (= bins).
    grid: u32,
    positions: u32,
    directions: u32,
    sources: u32,
    // The photon range of every row, and its split into runs.
    photon_first: u32,
    photon_count: u32,
    per_invocation: u32,
    splits: u32,
    // This dispatch's tasks.
    task_first: u32,
    task_count: u32,
    // The chunk's rows: local item r / source_count, source source_first + r % source_count.
    source_first: u32,
    source_count: u32,
    // Padding to the uniform layout's 16-byte multiple.
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

// A source's ideal ray, computed in f64 on the host: origin, unit direction, and the pixel
// (column, row counted from the bottom) it starts in, after the grid-line rule.
struct Source {
    origin: vec2<f32>,
    dir: vec2<f32>,
    start: vec2<u32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> sources: array<Source>;
// Per chunk item and pixel (iy · N + ix, iy from the bottom): (σt or −1 for opaque, block level
// L, σa/σt, HG c = (1−g)/(1+g) or −1 for g = −1). The pixel lies in an aligned block of 2^L × 2^L
// pixels of one material, the largest such block (see "Traversal" below).
@group(0) @binding(2) var<storage, read> medium: array<vec4<f32>>;
// Per chunk item: the seed as (low 32 bits, high 32 bits).
@group(0) @binding(3) var<storage, read> seeds: array<vec2<u32>>;
// Per chunk row and bin: photons counted.
@group(0) @binding(4) var<storage, read_write> counts: array<atomic<u32>>;
// Per chunk item: scattering events as a 64-bit (low, high) pair; then one word counting the
// invocations cut short (see `end_of_run`).
@group(0) @binding(5) var<storage, read_write> scatters: array<atomic<u32>>;

override WORKGROUP_SIZE: u32 = 64u;

// Stands in for an infinite distance (no crossing along an axis the ray does not move on).
const FAR: f32 = 1e30;
// Flights per round between tallies (see `main`).
const FLIGHTS_PER_ROUND: u32 = 8u;

// The pixel index along one axis of a point at coordinate `x` moving with sign `side` along that
// axis: a coordinate on a grid line (within `corner_tol`) belongs to the pixel the ray moves into.
// May be −1 or N (outside the grid).
fn grid_index(x: f32, side: f32) -> i32 {
    let u = x * params.inv_pixel;
    let line = round(u);
    if (abs(x - line * params.pixel) <= params.corner_tol) {
        return select(i32(line) - 1, i32(line), side > 0.0);
    }
    return i32(floor(u));
}

// One invocation's run of photons (see "Work layout"): its chunk row, that row's item and source,
// the photons it follows, and where the item's medium records and the row's counts begin.
struct Run {
    row: u32,
    item: u32,
    source: u32,
    photon_first: u32,
    photons: u32,
    cell_base: u32,
    tally_base: u32,
}

fn run_of_task(task: u32) -> Run {
    let row = task / params.splits;
    let run = task % params.splits;
    let run_first = run * params.per_invocation;
    let item = row / params.source_count;
    return Run(
        row,
        item,
        params.source_first + row % params.source_count,
        params.photon_first + run_first,
        min(params.per_invocation, params.photon_count - run_first),
        item * params.grid * params.grid,
        row * params.sources,
    );
}

// The block the march is in (see "Traversal"): 2^L pixels a side, aligned, its lowest pixel, the
// walls ahead and the distances along the ray to them (an axis the ray does not move along has no
// wall ahead: its quotient is dropped), and the distance to the nearer one.
struct Block {
    side: i32,
    lo: vec2<i32>,
    wall: vec2<f32>,
    t_wall: vec2<f32>,
    t_exit: f32,
}

// The block of pixel `cell` (record `m`) for a ray at `pos` moving along `dir` (signs `step`).
fn block_ahead(cell: vec2<i32>, m: vec4<f32>, pos: vec2<f32>, dir: vec2<f32>, step: vec2<i32>) -> Block {
    let side = 1 << u32(m.y);
    let lo = cell & vec2<i32>(-side);
    let ahead = select(vec2<i32>(0), vec2<i32>(side), step > vec2<i32>(0));
    let wall = vec2<f32>(lo + ahead) * params.pixel;
    let t_wall = select(vec2<f32>(FAR), max((wall - pos) / dir, vec2<f32>(0.0)), dir != vec2<f32>(0.0));
    return Block(side, lo, wall, t_wall, min(t_wall.x, t_wall.y));
}

// Where the ray is once it has left block `b`: the point on the wall and the pixel beyond it.
struct Crossing {
    pos: vec2<f32>,
    cell: vec2<i32>,
}

// Leaves block `b` through one wall, or through a corner (diagonally). The pixel along the wall
// crossed (unless both were, at a corner): the ray's direction along it, or for a ray running
// along it, its left normal, picks the side of a grid line. The pixel may lie outside the grid.
fn leave_block(b: Block, pos: vec2<f32>, dir: vec2<f32>, step: vec2<i32>) -> Crossing {
    let corner = abs(b.t_wall.x - b.t_wall.y) <= params.corner_tol;
    let cross = vec2<bool>(corner || b.t_wall.x < b.t_wall.y, corner || b.t_wall.y < b.t_wall.x);
    let at = select(pos + b.t_exit * dir, b.wall, cross);
    let free_x = !cross.x;
    let along = grid_index(
        select(at.y, at.x, free_x),
        select(select(dir.x, dir.y, dir.y != 0.0), select(-dir.y, dir.x, dir.x != 0.0), free_x),
    );
    let beyond = b.lo + select(vec2<i32>(-1), vec2<i32>(b.side), step > vec2<i32>(0));
    return Crossing(at, select(vec2<i32>(along), beyond, cross));
}

fn outside_grid(cell: vec2<i32>) -> bool {
    return any((cell < vec2<i32>(0)) | (cell >= vec2<i32>(i32(params.grid))));
}

// sin(a) for a ∈ [0, π/2], from a² (Taylor to a¹¹: error below 6e-8).
fn sin_quadrant(a: f32, a2: f32) -> f32 {
    let p = -1.0 / 39916800.0;
    let q = fma(a2, p, 1.0 / 362880.0);
    let r = fma(a2, q, -1.0 / 5040.0);
    let t = fma(a2, r, 1.0 / 120.0);
    let v = fma(a2, t, -1.0 / 6.0);
    return a * fma(a2, v, 1.0);
}

// cos(a) for a ∈ [0, π/2], from a² (Taylor to a¹²: error below 7e-9).
fn cos_quadrant(a2: f32) -> f32 {
    let p = fma(a2, 1.0 / 479001600.0, -1.0 / 3628800.0);
    let q = fma(a2, p, 1.0 / 40320.0);
    let r = fma(a2, q, -1.0 / 720.0);
    let t = fma(a2, r, 1.0 / 24.0);
    let v = fma(a2, t, -0.5);
    return fma(a2, v, 1.0);
}

// The direction `dir` turned by θ = 2·atan(c·tan φ), φ = π(ξ − ½): flatland Henyey–Greenstein
// with c = (1−g)/(1+g), or a full reversal for c < 0 (g = −1). With u = c·tan φ the half-angle
// identities give cos θ = (1−u²)/(1+u²) and sin θ = 2u/(1+u²); multiplied through by cos²φ,
//   cos θ = (cos²φ − c²sin²φ) / D,  sin θ = 2c·sin φ·cos φ / D,  D = cos²φ + c²sin²φ,
// and sin φ, cos φ come from short polynomials in a = π/2 − |φ| = π·min(ξ, 1−ξ) ∈ (0, π/2]
// (no range reduction, and accurate where cos φ is tiny). D > 0 (cos φ = sin a > 0) and the
// host keeps c ≤ 1e18, so nothing overflows or divides by zero, for g = 1 (c = 0) too.
fn hg_turn(dir: vec2<f32>, c: f32, xi: f32) -> vec2<f32> {
    let a = PI * min(xi, 1.0 - xi);
    let a2 = a * a;
    let cos_phi = sin_quadrant(a, a2);
    let sin_abs = cos_quadrant(a2);
    let sin_phi = select(-sin_abs, sin_abs, xi > 0.5);
    let cc = cos_phi * cos_phi;
    let ss = c * c * sin_phi * sin_phi;
    let inv = 1.0 / (cc + ss);
    let turn = select(vec2<f32>(-1.0, 0.0), vec2<f32>((cc - ss) * inv, 2.0 * c * sin_phi * cos_phi * inv), c >= 0.0);
    let d = vec2<f32>(dir.x * turn.x - dir.y * turn.y, dir.x * turn.y + dir.y * turn.x);
    // One Newton step towards unit length (|d|² is 1 to within a few ulps).
    return d * (1.5 - 0.5 * dot(d, d));
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.task_count) {
        return;
    }
    // Which row (item, source) and which run of photons this invocation follows.
    let r = run_of_task(params.task_first + gid.x);
    var left = r.photons;
    var photon = r.photon_first;
    let ray = sources[r.source];
    let seed = seeds[r.item];
    let n = i32(params.grid);
    let start = vec2<i32>(ray.start);
    let m_start = medium[r.cell_base + u32(start.y * n + start.x)];
    if (m_start.x < 0.0) {
        // The source's first pixel is opaque: every photon is absorbed on entry.
        return;
    }

    // Scattering events as a 64-bit (low, high) count.
    var events_lo = 0u;
    var events_hi = 0u;
    var alive = false;
    var pos = vec2<f32>(0.0);
    var dir = vec2<f32>(0.0);
    // A pixel of the block the photon is in, and that pixel's record.
    var cell = vec2<i32>(0);
    var m = vec4<f32>(0.0);
    // Exits not tallied yet: how many (0 to 2), and each one's arc length and direction.
    var pending = 0u;
    var exit_s0 = 0.0;
    var exit_d0 = vec2<f32>(0.0);
    var exit_s1 = 0.0;
    var exit_d1 = vec2<f32>(0.0);
    var finished = false;

    loop {
        // A round of FLIGHTS_PER_ROUND flights, then the round's exits are tallied. (The round's
        // trip count is the same for every lane; tallying after each flight would run the
        // tally code on every flight, branches being predicated on SIMD CPU devices.)
        for (var flight = 0u; flight < FLIGHTS_PER_ROUND; flight++) {
            // 1. Launch the next photon of the run at its source, unless one is in flight (or
            // the lane has no photon left, or no free exit slot until the tally).
            if (!alive) {
                if (left == 0u || pending == 2u) {
                    continue;
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

            // 2. A flight: spend the optical depth τ = −ln ξ block by block. Its three random
            // words: τ, and for its collision the absorption test and the turn.
            let words = rng_next3();
            var tau = -log(to_uniform(words.x));
            let step = vec2<i32>(select(-1, 1, dir.x > 0.0), select(-1, 1, dir.y > 0.0));
            loop {
                let b = block_ahead(cell, m, pos, dir, step);
                let spend = m.x * b.t_exit;
                if (spend >= tau) {
                    // τ runs out in this block (σt > 0 here, since τ > 0): a collision.
                    pos += (tau / m.x) * dir;
                    break;
                }
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
            // The flight ended outside the grid (the photon left), in an opaque pixel (entering it
            // absorbed the photon; `m` is that pixel's record), or else in a collision.
            let out = (cell < vec2<i32>(0)) | (cell >= vec2<i32>(n));

            // 3. The photon left the medium: park its exit in a free slot until the tally.
            if (any(out)) {
                let s = exit_arc_length(pos, out, step);
                if (pending == 0u) {
                    exit_s0 = s;
                    exit_d0 = dir;
                } else {
                    exit_s1 = s;
                    exit_d1 = dir;
                }
                pending += 1u;
                alive = false;
                continue;
            }
            if (m.x < 0.0) {
                alive = false;
                continue;
            }

            // 4. A collision in the block of `cell`: analog absorption with probability σa/σt ...
            if (to_uniform(words.y) < m.z) {
                alive = false;
                continue;
            }
            // ... else a scattering event: turn by θ = 2·atan(c·tan φ), φ = π(ξ−½) (flatland HG).
            events_lo += 1u;
            events_hi += select(0u, 1u, events_lo == 0u);
            dir = hg_turn(dir, m.w, to_uniform(words.z));
        }

        // 5. Tally the round's exits in their bins.
        if (pending > 0u) {
            atomicAdd(&counts[r.tally_base + bin_of_exit(exit_s0, exit_d0)], 1u);
        }
        if (pending > 1u) {
            atomicAdd(&counts[r.tally_base + bin_of_exit(exit_s1, exit_d1)], 1u);
        }
        pending = 0u;
        if (left == 0u && !alive) {
            finished = true;
            break;
        }
    }
    end_of_run(finished);
    add_scatter_events(r.item, vec2<u32>(events_lo, events_hi));
}
