//! How a render batch is cut for the device: submissions ("chunks" of tally rows that fit the
//! device's buffer limits), runs of photons per invocation, and dispatches.
//!
//! Pure arithmetic, no wgpu: the engine asks for a plan and records it. A tally row is one
//! (item, source) pair. A chunk is some whole items, or, when one item's count matrix is larger
//! than a buffer may be, some sources of one item. Each row's photons are split into runs of
//! `per_invocation` photons (one invocation each), and the chunk's tasks (row, run) are cut into
//! dispatches of bounded work. None of this changes the counts: every photon keeps its index.

/// At most this many photons per invocation. Longer runs even out the work of the lanes of a
/// SIMD group (they wait for the slowest; on lavapipe 128 beats 36 by ~15%), but leave fewer
/// invocations to spread over a device.
pub const MAX_PHOTONS_PER_INVOCATION: u32 = 128;

/// Tasks are indexed in 32 bits in the shader; keep well inside.
const MAX_TASKS_PER_CHUNK: u64 = 1 << 31;

/// A submission's tally rows: items `[item_first, item_first + item_count)`, and of each the
/// sources `[source_first, source_first + source_count)` (all sources when `item_count > 1`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Chunk {
    pub item_first: usize,
    pub item_count: usize,
    pub source_first: usize,
    pub source_count: usize,
}

impl Chunk {
    /// Tally rows in this chunk.
    pub fn rows(&self) -> usize {
        self.item_count * self.source_count
    }
}

/// The sizes a plan depends on.
#[derive(Debug, Clone, Copy)]
pub struct Shape {
    pub items: usize,
    pub sources: usize,
    pub bins: usize,
    pub pixels: usize,
}

/// Bytes per pixel of the medium buffer (σt, block level, σa/σt, HG c as f32).
pub const PIXEL_BYTES: u64 = std::mem::size_of::<super::records::Pixel>() as u64;

/// Cuts the batch into chunks whose every buffer fits in `limit` bytes, or says why it cannot.
pub fn chunks(shape: Shape, limit: u64) -> Result<Vec<Chunk>, String> {
    let row_bytes = shape.bins as u64 * 4;
    let item_tally_bytes = shape.sources as u64 * row_bytes;
    let item_pixel_bytes = shape.pixels as u64 * PIXEL_BYTES;
    if item_pixel_bytes > limit {
        return Err(format!(
            "one assignment of {} pixels needs a {item_pixel_bytes}-byte buffer, more than the {limit} bytes this \
             device allows in one buffer",
            shape.pixels
        ));
    }
    if row_bytes > limit {
        return Err(format!(
            "one source's {} bins need a {row_bytes}-byte buffer, more than the {limit} bytes this device allows",
            shape.bins
        ));
    }
    let mut out = Vec::new();
    if item_tally_bytes <= limit {
        let per_chunk = (limit / item_tally_bytes)
            .min(limit / item_pixel_bytes.max(1))
            .max(1) as usize;
        let mut first = 0;
        while first < shape.items {
            let count = per_chunk.min(shape.items - first);
            out.push(Chunk {
                item_first: first,
                item_count: count,
                source_first: 0,
                source_count: shape.sources,
            });
            first += count;
        }
    } else {
        let rows = ((limit / row_bytes) as usize).max(1);
        for item in 0..shape.items {
            let mut first = 0;
            while first < shape.sources {
                let count = rows.min(shape.sources - first);
                out.push(Chunk {
                    item_first: item,
                    item_count: 1,
                    source_first: first,
                    source_count: count,
                });
                first += count;
            }
        }
    }
    Ok(out)
}

/// Photons per invocation for `rows` rows of `photons` photons each: enough invocations to fill
/// a device that wants `target_invocations` in flight, at most [`MAX_PHOTONS_PER_INVOCATION`]
/// photons each, and few enough tasks to index in 32 bits. `fixed` overrides the choice (within
/// those bounds).
pub fn photons_per_invocation(
    rows: usize,
    photons: u32,
    target_invocations: u64,
    fixed: Option<u32>,
) -> u32 {
    if photons == 0 {
        return 1;
    }
    let total = rows as u64 * u64::from(photons);
    let per = match fixed {
        Some(p) => u64::from(p),
        None => {
            let fill = total.div_ceil(target_invocations.max(1));
            fill.min(u64::from(MAX_PHOTONS_PER_INVOCATION))
        }
    };
    let floor = total.div_ceil(MAX_TASKS_PER_CHUNK);
    per.max(floor).clamp(1, u64::from(photons)) as u32
}

/// One dispatch: tasks `[first, first + count)` of a chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dispatch {
    pub first: u32,
    pub count: u32,
}

/// Cuts `tasks` tasks of `per_invocation` photons into dispatches of at most `photon_budget`
/// photons and `max_tasks` tasks each.
pub fn dispatches(
    tasks: u64,
    per_invocation: u32,
    photon_budget: u64,
    max_tasks: u64,
) -> Vec<Dispatch> {
    let per_dispatch =
        (photon_budget / u64::from(per_invocation.max(1))).clamp(1, max_tasks.max(1));
    let mut out = Vec::new();
    let mut first = 0u64;
    while first < tasks {
        let count = per_dispatch.min(tasks - first);
        // Chunks keep tasks below 2^31, so these fit.
        out.push(Dispatch {
            first: first as u32,
            count: count as u32,
        });
        first += count;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn whole_items_per_chunk_when_they_fit() {
        let shape = Shape {
            items: 5,
            sources: 48,
            bins: 48,
            pixels: 64,
        };
        let item = 48 * 48 * 4;
        let c = chunks(shape, 2 * item).unwrap();
        assert_eq!(c.len(), 3);
        assert_eq!(c.iter().map(|c| c.item_count).sum::<usize>(), 5);
        assert!(c
            .iter()
            .all(|c| c.source_count == 48 && c.source_first == 0));
    }

    #[test]
    fn sources_of_one_item_when_an_item_is_too_large() {
        let shape = Shape {
            items: 2,
            sources: 48,
            bins: 48,
            pixels: 64,
        };
        let c = chunks(shape, 10 * 48 * 4).unwrap();
        assert_eq!(c.len(), 10);
        assert_eq!(
            c.iter()
                .filter(|c| c.item_first == 1)
                .map(|c| c.source_count)
                .sum::<usize>(),
            48
        );
        assert!(chunks(shape, 47 * 4).is_err());
        assert!(chunks(
            Shape {
                pixels: 1 << 20,
                ..shape
            },
            1 << 20
        )
        .is_err());
    }

    #[test]
    fn runs_and_dispatches_cover_every_task() {
        assert_eq!(photons_per_invocation(1152, 512, 16_384, None), 36);
        assert_eq!(photons_per_invocation(1152, 512, 2_048, None), 128);
        assert_eq!(photons_per_invocation(48, 10, 16_384, None), 1);
        assert_eq!(photons_per_invocation(1, 1000, 1, None), 128);
        assert_eq!(photons_per_invocation(4, 7, 1, Some(100)), 7);
        let d = dispatches(1000, 64, 64 * 300, 65535 * 64);
        assert_eq!(d.len(), 4);
        assert_eq!(d.iter().map(|d| u64::from(d.count)).sum::<u64>(), 1000);
        assert_eq!(
            d[3],
            Dispatch {
                first: 900,
                count: 100
            }
        );
    }
}
