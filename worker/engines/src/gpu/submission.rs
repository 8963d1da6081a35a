//! One submission: a chunk's rows, all their photons, through the device as a linear pipeline
//! (the steps of wgpu's `hello_compute`), each step a function:
//! [`param_records`] → [`create_buffers`] → [`bind_group`] → [`encode_and_submit`] →
//! [`read_back`] → [`add_tallies`].

use super::device::{GpuDevice, WORKGROUP_SIZE};
use super::dispatch_plan::{self, Chunk, Dispatch};
use super::records::{HostLayout, Params, PARAMS_BYTES};
use scatterfarm_model::engine::{EngineError, RenderBatch, RenderOutput};
use std::sync::mpsc;
use wgpu::util::DeviceExt;

/// A chunk's work as the device runs it: its dispatches and how a row's photons are split.
pub(super) struct Work {
    pub(super) dispatches: Vec<Dispatch>,
    pub(super) per_invocation: u32,
    pub(super) splits: u32,
}

/// The buffers of one submission.
struct Buffers {
    params: wgpu::Buffer,
    sources: wgpu::Buffer,
    medium: wgpu::Buffer,
    seeds: wgpu::Buffer,
    counts: wgpu::Buffer,
    scatters: wgpu::Buffer,
    counts_read: wgpu::Buffer,
    scatters_read: wgpu::Buffer,
}

/// The tallies read back: per row and bin the counts, per item the scattering events as
/// (low, high) words, and the invocations the device cut short.
struct Tallies {
    counts: Vec<u32>,
    scatters: Vec<u32>,
    cut_short: u32,
}

/// Bytes of a chunk's `scatters` buffer: two words per item, then the count of invocations cut
/// short (`end_of_run` in `tallies.wgsl`).
pub(super) fn scatter_bytes(items: usize) -> u64 {
    items as u64 * 8 + 4
}

/// Splits a `scatters` readback into its per-item words and the count of invocations cut short.
pub(super) fn split_cut_short(mut words: Vec<u32>) -> (Vec<u32>, u32) {
    let cut = words.pop().unwrap_or(0);
    (words, cut)
}

/// What came of a chunk's submission.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Rendered {
    /// Every photon followed; the tallies are in the outputs.
    Whole,
    /// The device cut some invocations short (lavapipe's loop limit): nothing was added, and the
    /// chunk must be rendered again with fewer photons per invocation.
    CutShort(u32),
}

/// Photons per invocation for a chunk rendered again after `cut` invocations were cut short at
/// `per_invocation`, or an error when one photon per invocation was already too long.
pub(crate) fn fewer_per_invocation(
    gpu: &GpuDevice,
    per_invocation: u32,
    cut: u32,
) -> Result<u32, EngineError> {
    if per_invocation <= 1 {
        return Err(gpu.error(format!(
            "to follow every photon: {cut} invocations of one photon each were cut short (the \
             device ends loops past 65 535 iterations; a medium this dense needs a real GPU or \
             the CPU engine)"
        )));
    }
    let fewer = (per_invocation / 4).max(1);
    tracing::debug!(
        cut,
        per_invocation,
        fewer,
        "the device cut invocations short; rendering the chunk again"
    );
    Ok(fewer)
}

/// Renders the rows of `chunk` (all their photons) into `outputs`: `photons_per_dispatch` bounds
/// each dispatch's work. Nothing is added when the device cut a run short.
pub(crate) fn render_chunk(
    gpu: &GpuDevice,
    photons_per_dispatch: u64,
    batch: &RenderBatch<'_>,
    host: &HostLayout,
    chunk: &Chunk,
    per_invocation: u32,
    outputs: &mut [RenderOutput],
) -> Result<Rendered, EngineError> {
    let splits = batch.photons.count.div_ceil(per_invocation);
    let tasks = chunk.rows() as u64 * u64::from(splits);
    let max_tasks =
        u64::from(gpu.limits.max_compute_workgroups_per_dimension) * u64::from(WORKGROUP_SIZE);
    let work = Work {
        dispatches: dispatch_plan::dispatches(
            tasks,
            per_invocation,
            photons_per_dispatch,
            max_tasks,
        ),
        per_invocation,
        splits,
    };
    let stride = PARAMS_BYTES.next_multiple_of(u64::from(
        gpu.limits.min_uniform_buffer_offset_alignment.max(1),
    ));
    let params = param_records(batch, chunk, &work, stride);
    let buffers = create_buffers(gpu, batch, host, chunk, &params);
    let bind_group = bind_group(gpu, &buffers);
    encode_and_submit(
        gpu,
        &gpu.pipeline,
        "transport",
        &bind_group,
        &work.dispatches,
        stride,
        &[
            (&buffers.counts, &buffers.counts_read),
            (&buffers.scatters, &buffers.scatters_read),
        ],
    );
    let tallies = read_back(gpu, &buffers)?;
    if tallies.cut_short > 0 {
        return Ok(Rendered::CutShort(tallies.cut_short));
    }
    add_tallies(batch, chunk, &tallies, outputs);
    Ok(Rendered::Whole)
}

/// The parameter records, one per dispatch, `stride` bytes apart (the device's uniform offset
/// alignment).
pub(super) fn param_records(
    batch: &RenderBatch<'_>,
    chunk: &Chunk,
    work: &Work,
    stride: u64,
) -> Vec<u8> {
    let geometry = Params::for_geometry(&batch.geometry);
    let mut bytes = vec![0u8; work.dispatches.len() * stride as usize];
    for (k, d) in work.dispatches.iter().enumerate() {
        let record = Params {
            photon_first: batch.photons.first,
            photon_count: batch.photons.count,
            per_invocation: work.per_invocation,
            splits: work.splits,
            task_first: d.first,
            task_count: d.count,
            source_first: chunk.source_first as u32,
            source_count: chunk.source_count as u32,
            ..geometry
        };
        bytes[k * stride as usize..][..PARAMS_BYTES as usize]
            .copy_from_slice(bytemuck::bytes_of(&record));
    }
    bytes
}

/// The buffers: inputs initialised from the host, tallies zeroed by wgpu, and readback buffers.
fn create_buffers(
    gpu: &GpuDevice,
    batch: &RenderBatch<'_>,
    host: &HostLayout,
    chunk: &Chunk,
    params: &[u8],
) -> Buffers {
    let items = chunk.item_first..chunk.item_first + chunk.item_count;
    let storage = wgpu::BufferUsages::STORAGE;
    let init = |label: &str, contents: &[u8], usage: wgpu::BufferUsages| {
        gpu.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
    };
    let medium: Vec<_> = host.medium[items.clone()].concat();
    let counts_bytes = (chunk.rows() * batch.geometry.bins() * 4) as u64;
    let scatter_bytes = scatter_bytes(chunk.item_count);
    let zeroed = |label: &str, size: u64, usage: wgpu::BufferUsages| {
        gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    };
    let tally = storage | wgpu::BufferUsages::COPY_SRC;
    let readback = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
    Buffers {
        params: init("params", params, wgpu::BufferUsages::UNIFORM),
        sources: init("sources", bytemuck::cast_slice(&host.sources), storage),
        medium: init("medium", bytemuck::cast_slice(&medium), storage),
        seeds: init("seeds", bytemuck::cast_slice(&host.seeds[items]), storage),
        counts: zeroed("counts", counts_bytes, tally),
        scatters: zeroed("scatters", scatter_bytes, tally),
        counts_read: zeroed("counts readback", counts_bytes, readback),
        scatters_read: zeroed("scatters readback", scatter_bytes, readback),
    }
}

/// The bind group: one parameter record (its offset set per dispatch), then the whole buffers.
fn bind_group(gpu: &GpuDevice, buffers: &Buffers) -> wgpu::BindGroup {
    bind_records_and_buffers(
        gpu,
        "transport bind group",
        &gpu.layout,
        &buffers.params,
        &[
            &buffers.sources,
            &buffers.medium,
            &buffers.seeds,
            &buffers.counts,
            &buffers.scatters,
        ],
    )
}

/// A bind group of `layout`: binding 0 one parameter record of `params` (its offset set per
/// dispatch), bindings 1, 2, … the whole of each of `buffers`.
pub(super) fn bind_records_and_buffers(
    gpu: &GpuDevice,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    params: &wgpu::Buffer,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let record = wgpu::BindGroupEntry {
        binding: 0,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: params,
            offset: 0,
            size: wgpu::BufferSize::new(PARAMS_BYTES),
        }),
    };
    let entries: Vec<wgpu::BindGroupEntry> = std::iter::once(record)
        .chain((1..).zip(buffers).map(|(i, b)| whole(i, b)))
        .collect();
    gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}

/// One compute pass of `pipeline` over the bounded dispatches (each with its own parameter
/// record), then the copies `(from, to)` of the tallies to their readback buffers; submitted.
pub(super) fn encode_and_submit(
    gpu: &GpuDevice,
    pipeline: &wgpu::ComputePipeline,
    label: &str,
    bind_group: &wgpu::BindGroup,
    dispatches: &[Dispatch],
    stride: u64,
    copies: &[(&wgpu::Buffer, &wgpu::Buffer)],
) {
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
    {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        for (k, d) in dispatches.iter().enumerate() {
            pass.set_bind_group(0, bind_group, &[(k as u64 * stride) as u32]);
            pass.dispatch_workgroups(d.count.div_ceil(WORKGROUP_SIZE), 1, 1);
        }
    }
    for (from, to) in copies {
        encoder.copy_buffer_to_buffer(from, 0, to, 0, from.size());
    }
    gpu.queue.submit(Some(encoder.finish()));
}

pub(super) fn whole(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// Waits for the submission and reads the tallies back.
fn read_back(gpu: &GpuDevice, buffers: &Buffers) -> Result<Tallies, EngineError> {
    let mut words = map_and_wait(gpu, &[&buffers.counts_read, &buffers.scatters_read])?;
    let (scatters, cut_short) = split_cut_short(words.pop().unwrap_or_default());
    let counts = words.pop().unwrap_or_default();
    Ok(Tallies {
        counts,
        scatters,
        cut_short,
    })
}

/// Waits for the submission, maps every readback buffer and returns each one's contents as
/// 32-bit words (the buffers unmapped again).
pub(super) fn map_and_wait(
    gpu: &GpuDevice,
    buffers: &[&wgpu::Buffer],
) -> Result<Vec<Vec<u32>>, EngineError> {
    let (tx, rx) = mpsc::channel();
    for (which, buffer) in buffers.iter().enumerate() {
        let tx = tx.clone();
        buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send((which, r));
        });
    }
    drop(tx);
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| gpu.error(format!("while rendering: {e}")))?;
    gpu.take_errors("while rendering")?;
    for _ in buffers {
        match rx.recv() {
            Ok((_, Ok(()))) => {}
            Ok((which, Err(e))) => {
                return Err(EngineError::Device(format!(
                    "reading back buffer {which} failed: {e}"
                )));
            }
            Err(_) => {
                return Err(EngineError::Device(
                    "the device dropped a readback".to_string(),
                ))
            }
        }
    }
    buffers.iter().map(|b| read_words(b)).collect()
}

/// A mapped readback buffer's contents as 32-bit words (then unmapped).
fn read_words(buffer: &wgpu::Buffer) -> Result<Vec<u32>, EngineError> {
    let words = {
        let view = buffer
            .slice(..)
            .get_mapped_range()
            .map_err(|e| EngineError::Device(format!("cannot read back the tallies: {e}")))?;
        bytemuck::pod_collect_to_vec(&view[..])
    };
    buffer.unmap();
    Ok(words)
}

/// Puts a chunk's tallies into its items' outputs: its rows' counts, its items' events.
fn add_tallies(
    batch: &RenderBatch<'_>,
    chunk: &Chunk,
    tallies: &Tallies,
    outputs: &mut [RenderOutput],
) {
    let bins = batch.geometry.bins();
    for (r, row) in tallies.counts.chunks_exact(bins).enumerate() {
        let item = chunk.item_first + r / chunk.source_count;
        let source = chunk.source_first + r % chunk.source_count;
        outputs[item].counts.counts[source * bins..(source + 1) * bins].copy_from_slice(row);
    }
    for (i, pair) in tallies.scatters.chunks_exact(2).enumerate() {
        outputs[chunk.item_first + i].scatter_events +=
            u64::from(pair[0]) | (u64::from(pair[1]) << 32);
    }
}
