//! Rendering in photon chunks with any engine: a render of many photons as a sum of smaller
//! ones (batch additivity, `docs/model.md`), so long renders report progress as they go.

use anyhow::{ensure, Result};
use scatterfarm_model::{
    CountMatrix, Engine, Geometry, Material, PhotonRange, RenderBatch, RenderItem,
};

/// What a chunked render produced: one count matrix per item, and the scattering events.
#[derive(Debug, Clone)]
pub struct Rendered {
    pub counts: Vec<CountMatrix>,
    pub scatter_events: u64,
}

/// Renders `items` over photons `[0, photons)` in chunks of `chunk` photons per source, calling
/// `on_chunk` with each chunk's size. By batch additivity the sum equals one single render.
pub fn render_in_chunks(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    items: &[RenderItem],
    photons: u32,
    chunk: u32,
    on_chunk: &mut dyn FnMut(u32),
) -> Result<Rendered> {
    render_range(engine, geometry, table, items, 0..photons, chunk, on_chunk)
}

/// Renders `items` over the photons `range` of every source, in chunks of `chunk` photons.
pub fn render_range(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    items: &[RenderItem],
    range: std::ops::Range<u32>,
    chunk: u32,
    on_chunk: &mut dyn FnMut(u32),
) -> Result<Rendered> {
    ensure!(chunk > 0, "a render chunk needs at least one photon");
    let mut counts = vec![CountMatrix::zeros(geometry.sources(), geometry.bins()); items.len()];
    let mut scatter_events = 0;
    let mut first = range.start;
    while first < range.end {
        let count = chunk.min(range.end - first);
        let batch = RenderBatch {
            geometry,
            table,
            items,
            photons: PhotonRange { first, count },
        };
        let outputs = engine.render(&batch)?;
        ensure!(
            outputs.len() == items.len(),
            "the engine returned {} results for {} items",
            outputs.len(),
            items.len()
        );
        for (total, out) in counts.iter_mut().zip(&outputs) {
            total.add(&out.counts)?;
            scatter_events += out.scatter_events;
        }
        first += count;
        on_chunk(count);
    }
    Ok(Rendered {
        counts,
        scatter_events,
    })
}
