//! The GPU engine's differential render (`docs/model.md`, "Differential renders"): the shader's
//! `differential` entry point (`shaders/differential.wgsl`) traces the map's photons exactly as a
//! plain render does, tallies each photon's path in the pixels some change touches, and adds each
//! detected photon's `w − 1` under every change it touched to that change's (source, bin), in
//! 64-bit fixed point (2^-24 per unit, integer atomics), so a seed fixes every bit.
//!
//! The host's part, step by step:
//! 1. check the render as the CPU engine does, and which changes are reweightable
//!    ([`change_is_reweightable`]; the others are reported as `None`, as on the CPU);
//! 2. lay out the factors: per pixel, every (change, from, to) that sets it, and per material
//!    the [`Physics`] a weight needs;
//! 3. cut the sources into chunks whose delta arrays (changes × sources × bins × 8 bytes) fit a
//!    buffer, and each chunk's work into dispatches of at most as many invocations as the
//!    scratch (one slot of per-pixel tallies per invocation, [`SCRATCH_BYTES`] in all) holds;
//! 4. per chunk one submission: upload, dispatch, read back counts, events and deltas (again,
//!    with fewer photons per invocation, when the device cut a run short: see `end_of_run` in
//!    `tallies.wgsl`).

use super::device::{GpuDevice, WORKGROUP_SIZE};
use super::dispatch_plan::{self, Chunk};
use super::engine::Tuning;
use super::records::{Differential, HostLayout, Physics, PARAMS_BYTES};
use super::submission::{
    bind_records_and_buffers, encode_and_submit, fewer_per_invocation, map_and_wait, param_records,
    scatter_bytes, split_cut_short, Rendered, Work,
};
use crate::cpu::MAX_CHANGES;
use scatterfarm_model::differential::{
    change_is_reweightable, differential_batch, Change, DifferentialOutput,
};
use scatterfarm_model::engine::{CountMatrix, EngineError, RenderBatch};
use scatterfarm_model::{Geometry, Material, PhotonRange, RenderItem};
use wgpu::util::DeviceExt;

/// Most table materials a GPU differential render takes (each collision in a tallied pixel
/// sums one phase term per material).
pub const MAX_MATERIALS: usize = 64;

/// The scratch all invocations of one dispatch share (one slot each), at most.
const SCRATCH_BYTES: u64 = 256 << 20;

/// Fixed-point units per unit of weight (`FIXED_SCALE` in the shader).
const FIXED_SCALE: f64 = 16_777_216.0;

/// What the shader needs besides the plain render's records.
struct Layout {
    /// The N² + 1 offsets, then two words per factor.
    factors: Vec<u32>,
    physics: Vec<Physics>,
    sizes: Differential,
}

/// The buffers of one differential submission beyond those the readback maps.
struct Buffers {
    params: wgpu::Buffer,
    sources: wgpu::Buffer,
    medium: wgpu::Buffer,
    seeds: wgpu::Buffer,
    counts: wgpu::Buffer,
    scatters: wgpu::Buffer,
    sizes: wgpu::Buffer,
    factors: wgpu::Buffer,
    physics: wgpu::Buffer,
    scratch: wgpu::Buffer,
    deltas: wgpu::Buffer,
}

/// Renders `item` differentially on `gpu`: see the module documentation.
pub(crate) fn render(
    gpu: &GpuDevice,
    tuning: &Tuning,
    geometry: Geometry,
    table: &[Material],
    item: &RenderItem,
    photons: PhotonRange,
    changes: &[Change],
) -> Result<DifferentialOutput, EngineError> {
    let batch = differential_batch(geometry, table, item, photons, changes, MAX_CHANGES)?;
    if table.len() > MAX_MATERIALS {
        return Err(EngineError::Unsupported(format!(
            "{} materials in a GPU differential render; at most {MAX_MATERIALS}",
            table.len()
        )));
    }
    let supported: Vec<bool> = changes
        .iter()
        .map(|c| change_is_reweightable(table, &item.assignment, c))
        .collect();
    let (sources, bins) = (geometry.sources(), geometry.bins());
    let mut output = DifferentialOutput {
        counts: CountMatrix::zeros(sources, bins),
        deltas: supported
            .iter()
            .map(|&s| s.then(|| vec![0.0; sources * bins]))
            .collect(),
        scatter_events: 0,
    };
    if photons.count == 0 {
        return Ok(output);
    }
    let layout = lay_out(&geometry, table, item, changes, &supported)?;
    let host = HostLayout::new(&batch);
    let limit = gpu.buffer_limit(tuning.max_buffer_bytes);
    let slot_bytes = u64::from(layout.sizes.slot_words) * 4;
    let max_tasks =
        u64::from(gpu.limits.max_compute_workgroups_per_dimension) * u64::from(WORKGROUP_SIZE);
    let slots = (SCRATCH_BYTES.min(limit) / slot_bytes).min(max_tasks);
    if slots == 0 {
        return Err(EngineError::Unsupported(format!(
            "one invocation's tallies need {slot_bytes} bytes, more than the {} this device \
             allows in one buffer",
            SCRATCH_BYTES.min(limit)
        )));
    }
    let row_bytes = changes.len().max(1) as u64 * bins as u64 * 8;
    if row_bytes > limit {
        return Err(EngineError::Device(format!(
            "one source's estimates of {} changes need {row_bytes} bytes, more than the {limit} \
             bytes this device allows in one buffer",
            changes.len()
        )));
    }
    let rows = ((limit / row_bytes) as usize).clamp(1, sources);
    let per_invocation = dispatch_plan::photons_per_invocation(
        sources,
        photons.count,
        tuning.target_invocations.min(slots),
        tuning.per_invocation,
    );
    gpu.take_errors("before this differential render")?;
    let mut first = 0;
    while first < sources {
        let chunk = Chunk {
            item_first: 0,
            item_count: 1,
            source_first: first,
            source_count: rows.min(sources - first),
        };
        let mut per = per_invocation;
        loop {
            let splits = photons.count.div_ceil(per);
            let work = Work {
                dispatches: dispatch_plan::dispatches(
                    chunk.rows() as u64 * u64::from(splits),
                    per,
                    tuning.photons_per_dispatch,
                    slots,
                ),
                per_invocation: per,
                splits,
            };
            match render_chunk(gpu, &batch, &host, &layout, &chunk, &work, &mut output)? {
                Rendered::Whole => break,
                Rendered::CutShort(cut) => per = fewer_per_invocation(gpu, per, cut)?,
            }
        }
        first += chunk.source_count;
    }
    Ok(output)
}

/// The factors per pixel (shader order: `iy · N + ix`, `iy` from the bottom) of every
/// reweightable change, and the sizes.
fn lay_out(
    geometry: &Geometry,
    table: &[Material],
    item: &RenderItem,
    changes: &[Change],
    supported: &[bool],
) -> Result<Layout, EngineError> {
    let n = geometry.grid as usize;
    let cells = geometry.pixels();
    let mut by_cell: Vec<Vec<[u32; 2]>> = vec![Vec::new(); cells];
    for (k, change) in changes.iter().enumerate() {
        if !supported[k] {
            continue;
        }
        for &(p, to) in &change.pixels {
            let p = p as usize;
            let from = item.assignment[p];
            if from == to {
                continue;
            }
            let cell = (n - 1 - p / n) * n + p % n;
            by_cell[cell].push([k as u32, (u32::from(from) << 16) | u32::from(to)]);
        }
    }
    let mut factors = Vec::with_capacity(cells + 1);
    let mut at = 0u32;
    for list in &by_cell {
        factors.push(at);
        at += list.len() as u32;
    }
    factors.push(at);
    factors.extend(by_cell.iter().flatten().flatten());
    let d = table.len();
    let slot_words = cells * (3 + d) + cells + 3 * changes.len();
    let slot_words = u32::try_from(slot_words).map_err(|_| {
        EngineError::Unsupported(format!("{slot_words} words of tallies per invocation"))
    })?;
    Ok(Layout {
        factors,
        physics: table.iter().map(Physics::of).collect(),
        sizes: Differential {
            changes: changes.len() as u32,
            materials: d as u32,
            cells: cells as u32,
            slot_words,
        },
    })
}

/// One chunk of sources through the device, into `output`.
fn render_chunk(
    gpu: &GpuDevice,
    batch: &RenderBatch<'_>,
    host: &HostLayout,
    layout: &Layout,
    chunk: &Chunk,
    work: &Work,
    output: &mut DifferentialOutput,
) -> Result<Rendered, EngineError> {
    let stride = PARAMS_BYTES.next_multiple_of(u64::from(
        gpu.limits.min_uniform_buffer_offset_alignment.max(1),
    ));
    let params = param_records(batch, chunk, work, stride);
    let bins = batch.geometry.bins();
    let slots = work
        .dispatches
        .iter()
        .map(|d| u64::from(d.count))
        .max()
        .unwrap_or(1);
    let buffers = create_buffers(gpu, host, layout, chunk, bins, slots, &params);
    let bind_group = bind_group(gpu, &buffers);
    let counts_read = readback(gpu, "counts readback", buffers.counts.size());
    let scatters_read = readback(gpu, "scatters readback", buffers.scatters.size());
    let deltas_read = readback(gpu, "deltas readback", buffers.deltas.size());
    encode_and_submit(
        gpu,
        &gpu.differential,
        "differential",
        &bind_group,
        &work.dispatches,
        stride,
        &[
            (&buffers.counts, &counts_read),
            (&buffers.scatters, &scatters_read),
            (&buffers.deltas, &deltas_read),
        ],
    );
    let words = map_and_wait(gpu, &[&counts_read, &scatters_read, &deltas_read])?;
    let (scatters, cut_short) = split_cut_short(words[1].clone());
    if cut_short > 0 {
        return Ok(Rendered::CutShort(cut_short));
    }
    let (counts, deltas) = (&words[0], &words[2]);
    let source_count = chunk.source_count;
    for (r, row) in counts.chunks_exact(bins).enumerate() {
        let source = chunk.source_first + r;
        output.counts.counts[source * bins..(source + 1) * bins].copy_from_slice(row);
    }
    output.scatter_events += u64::from(scatters[0]) | (u64::from(scatters[1]) << 32);
    let per_change = source_count * bins;
    for (k, delta) in output.deltas.iter_mut().enumerate() {
        let Some(delta) = delta else { continue };
        let words = &deltas[2 * k * per_change..2 * (k + 1) * per_change];
        let rows = &mut delta[chunk.source_first * bins..][..per_change];
        for (x, pair) in rows.iter_mut().zip(words.chunks_exact(2)) {
            let fixed = (u64::from(pair[0]) | (u64::from(pair[1]) << 32)) as i64;
            *x = fixed as f64 / FIXED_SCALE;
        }
    }
    Ok(Rendered::Whole)
}

fn create_buffers(
    gpu: &GpuDevice,
    host: &HostLayout,
    layout: &Layout,
    chunk: &Chunk,
    bins: usize,
    slots: u64,
    params: &[u8],
) -> Buffers {
    let storage = wgpu::BufferUsages::STORAGE;
    let tally = storage | wgpu::BufferUsages::COPY_SRC;
    let init = |label: &str, contents: &[u8], usage: wgpu::BufferUsages| {
        gpu.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
    };
    let zeroed = |label: &str, size: u64, usage: wgpu::BufferUsages| {
        gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(8),
            usage,
            mapped_at_creation: false,
        })
    };
    let rows = chunk.rows() as u64;
    let changes = u64::from(layout.sizes.changes);
    Buffers {
        params: init("params", params, wgpu::BufferUsages::UNIFORM),
        sources: init("sources", bytemuck::cast_slice(&host.sources), storage),
        medium: init("medium", bytemuck::cast_slice(&host.medium[0]), storage),
        seeds: init("seeds", bytemuck::cast_slice(&host.seeds[..1]), storage),
        counts: zeroed("counts", rows * bins as u64 * 4, tally),
        scatters: zeroed("scatters", scatter_bytes(1), tally),
        sizes: init(
            "differential sizes",
            bytemuck::bytes_of(&layout.sizes),
            wgpu::BufferUsages::UNIFORM,
        ),
        factors: init("factors", bytemuck::cast_slice(&layout.factors), storage),
        physics: init("physics", bytemuck::cast_slice(&layout.physics), storage),
        scratch: zeroed(
            "scratch",
            slots * u64::from(layout.sizes.slot_words) * 4,
            storage,
        ),
        deltas: zeroed("deltas", changes * rows * bins as u64 * 8, tally),
    }
}

fn readback(gpu: &GpuDevice, label: &str, size: u64) -> wgpu::Buffer {
    gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

fn bind_group(gpu: &GpuDevice, b: &Buffers) -> wgpu::BindGroup {
    bind_records_and_buffers(
        gpu,
        "differential bind group",
        &gpu.differential_layout,
        &b.params,
        &[
            &b.sources,
            &b.medium,
            &b.seeds,
            &b.counts,
            &b.scatters,
            &b.sizes,
            &b.factors,
            &b.physics,
            &b.scratch,
            &b.deltas,
        ],
    )
}
