//! Conversions between the protocol's messages and the engine's types, with every check a task
//! must pass before an engine sees it.
//!
//! A leased [`v1::Task`] becomes a [`RenderTask`] (geometry, material table, items, photon range)
//! or a typed [`ConvertError`]; an engine's outputs become one [`v1::CountMatrix`] per assignment
//! (little-endian `u32` counts). The reverse directions are here too (the coordinator builds
//! tasks with [`task_to_proto`] and decodes results with [`results_from_proto`]), so both ends of
//! the protocol encode and check the same way. Engine fingerprints cross the wire through
//! [`fingerprint_to_proto`] and [`fingerprint_from_proto`].

use crate::differential::{differential_from_proto, differential_to_proto, DifferentialPart};
use crate::scored::{check_scored, scored_to_proto};
use crate::v1;
use bytes::Bytes;
use scatterfarm_model::engine::{
    CountMatrix, EngineFingerprint, PhotonRange, RenderBatch, RenderItem, RenderOutput,
};
use scatterfarm_model::geometry::{Geometry, GeometryError};
use scatterfarm_model::likelihood::Target;
use scatterfarm_model::material::{Material, MaterialError};
use thiserror::Error;

/// Why a task (or a count matrix) from the wire cannot be used.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ConvertError {
    #[error("task of job {job_id} came without a geometry and the job's geometry is not cached")]
    MissingGeometry { job_id: String },
    #[error("invalid geometry: {0}")]
    Geometry(#[from] GeometryError),
    #[error("invalid material {index}: {source}")]
    Material { index: usize, source: MaterialError },
    #[error("the task has no assignments")]
    NoAssignments,
    #[error("assignment {item} has {bytes} bytes, the geometry needs {pixels} u16 indices ({} bytes)", 2 * pixels)]
    AssignmentSize {
        item: usize,
        pixels: usize,
        bytes: usize,
    },
    #[error(
        "assignment {item}, pixel {pixel}: material index {index} is outside the table of {table}"
    )]
    MaterialIndex {
        item: usize,
        pixel: usize,
        index: u16,
        table: usize,
    },
    #[error("the task asks for 0 photons per source")]
    NoPhotons,
    #[error("photons {first}..{first}+{count} do not fit in 32-bit photon indices")]
    PhotonRange { first: u32, count: u32 },
    #[error("the engine returned {got} results for {expected} assignments")]
    OutputCount { expected: usize, got: usize },
    #[error("result {item} is {got:?} (sources × bins, {len} counts), expected {expected:?}")]
    OutputShape {
        item: usize,
        expected: (usize, usize),
        got: (usize, usize),
        len: usize,
    },
    #[error("a {sources} × {bins} count matrix needs {} bytes, got {bytes}", 4 * sources * bins)]
    CountBytes {
        sources: usize,
        bins: usize,
        bytes: usize,
    },
    #[error("differential task: {0}")]
    Differential(String),
    #[error("target: {0}")]
    Target(String),
    #[error("change scores: {0}")]
    ChangeScores(String),
    #[error("scored task: {0}")]
    Scored(String),
    #[error("render scores: {0}")]
    RenderScores(String),
    #[error("result {item}: {source}")]
    Result {
        item: usize,
        source: Box<ConvertError>,
    },
    #[error(
        "lease request: {field} lists {entries} jobs, at most {MAX_CACHED_LISTED} are accepted \
         (a worker caches {WORKER_CACHE_JOBS})"
    )]
    CachedCount { field: &'static str, entries: usize },
    #[error("lease request: {field} entry {index} is {bytes} bytes, a job id is at most {MAX_JOB_ID_BYTES}")]
    CachedId {
        field: &'static str,
        index: usize,
        bytes: usize,
    },
}

/// Jobs one worker keeps a geometry and a target of, each (the agent's caches).
pub const WORKER_CACHE_JOBS: usize = 64;

/// The most entries a lease request's `cached_jobs` or `cached_targets` may list: a worker
/// caches [`WORKER_CACHE_JOBS`], and the coordinator looks each task's job up in these lists.
pub const MAX_CACHED_LISTED: usize = 16 * WORKER_CACHE_JOBS;

/// The longest job id a lease request may list (the coordinator's ids are a few bytes).
pub const MAX_JOB_ID_BYTES: usize = 256;

/// Checks what a lease request lists before the coordinator uses it: at most
/// [`MAX_CACHED_LISTED`] jobs per list, each id at most [`MAX_JOB_ID_BYTES`].
pub fn check_lease_request(r: &v1::LeaseRequest) -> Result<(), ConvertError> {
    for (field, list) in [
        ("cached_jobs", &r.cached_jobs),
        ("cached_targets", &r.cached_targets),
    ] {
        if list.len() > MAX_CACHED_LISTED {
            return Err(ConvertError::CachedCount {
                field,
                entries: list.len(),
            });
        }
        if let Some((index, id)) = list
            .iter()
            .enumerate()
            .find(|(_, id)| id.len() > MAX_JOB_ID_BYTES)
        {
            return Err(ConvertError::CachedId {
                field,
                index,
                bytes: id.len(),
            });
        }
    }
    Ok(())
}

/// A leased task, decoded and validated: everything one engine call needs.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderTask {
    pub geometry: Geometry,
    pub table: Vec<Material>,
    pub items: Vec<RenderItem>,
    pub photons: PhotonRange,
    /// Present for a differential render (its one item, from photon 0); the job's target
    /// travels beside it ([`crate::differential::target_from_proto`]).
    pub differential: Option<DifferentialPart>,
    /// Whether the worker scores every render (all from photon 0) against the job's target and
    /// returns the scores instead of the counts ([`crate::scored`]).
    pub scored: bool,
}

impl RenderTask {
    /// The engine's view of the task.
    pub fn batch(&self) -> RenderBatch<'_> {
        RenderBatch {
            geometry: self.geometry,
            table: &self.table,
            items: &self.items,
            photons: self.photons,
        }
    }

    /// Photons the task launches: sources × photons per source × assignments.
    pub fn photons_launched(&self) -> u64 {
        self.geometry.sources() as u64 * u64::from(self.photons.count) * self.items.len() as u64
    }
}

/// Who a task is for and how long its lease lasts: the parts of a [`v1::Task`] that are not
/// the render itself.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TaskLease {
    pub job_id: String,
    pub task_id: u64,
    pub attempt: u32,
    pub lease_deadline_unix_ms: u64,
}

/// The wire task for `task` under `lease`. `geometry_is_job_geometry` says the geometry is the
/// job's (workers cache it); `send_geometry` is false when the worker already holds it. A
/// differential task carries `target` when it is given (the worker does not hold it).
pub fn task_to_proto(
    lease: TaskLease,
    task: &RenderTask,
    geometry_is_job_geometry: bool,
    send_geometry: bool,
    target: Option<&Target>,
) -> v1::Task {
    v1::Task {
        job_id: lease.job_id,
        task_id: lease.task_id,
        attempt: lease.attempt,
        lease_deadline_unix_ms: lease.lease_deadline_unix_ms,
        geometry: send_geometry.then(|| geometry_to_proto(&task.geometry)),
        geometry_is_job_geometry,
        table: task.table.iter().map(material_to_proto).collect(),
        assignments: task.items.iter().map(assignment_to_proto).collect(),
        photon_first: task.photons.first,
        photon_count: task.photons.count,
        differential: task
            .differential
            .as_ref()
            .map(|d| differential_to_proto(d, target)),
        scored: task.scored.then(|| scored_to_proto(target)),
    }
}

/// An engine fingerprint as the wire carries it.
pub fn fingerprint_to_proto(f: &EngineFingerprint) -> v1::EngineFingerprint {
    v1::EngineFingerprint {
        engine: f.engine.clone(),
        adapter: f.adapter.clone(),
        driver: f.driver.clone(),
        version: f.version.clone(),
    }
}

/// An engine fingerprint from the wire.
pub fn fingerprint_from_proto(f: v1::EngineFingerprint) -> EngineFingerprint {
    EngineFingerprint {
        engine: f.engine,
        adapter: f.adapter,
        driver: f.driver,
        version: f.version,
    }
}

/// A validated geometry from the wire.
pub fn geometry_from_proto(g: &v1::Geometry) -> Result<Geometry, ConvertError> {
    Ok(Geometry::new(g.size_mm, g.grid, g.positions, g.directions)?)
}

pub fn geometry_to_proto(g: &Geometry) -> v1::Geometry {
    v1::Geometry {
        size_mm: g.size_mm,
        grid: g.grid,
        positions: g.positions,
        directions: g.directions,
    }
}

/// Material `index` of a table from the wire: `opaque` makes σa infinite whatever it says (the
/// model's opaque material is σa = +∞, which [`material_to_proto`] sends as it is).
pub fn material_from_proto(index: usize, m: &v1::Material) -> Result<Material, ConvertError> {
    let sigma_a = if m.opaque { f64::INFINITY } else { m.sigma_a };
    Material::new(m.sigma_s, sigma_a, m.g)
        .map_err(|source| ConvertError::Material { index, source })
}

pub fn material_to_proto(m: &Material) -> v1::Material {
    v1::Material {
        sigma_s: m.sigma_s,
        sigma_a: m.sigma_a,
        g: m.g,
        opaque: m.is_opaque(),
    }
}

pub fn assignment_to_proto(item: &RenderItem) -> v1::Assignment {
    let bytes: Vec<u8> = item
        .assignment
        .iter()
        .flat_map(|i| i.to_le_bytes())
        .collect();
    v1::Assignment {
        indices_le_u16: Bytes::from(bytes),
        seed: item.seed,
    }
}

/// Decodes and checks `task` over `geometry` (the task's own, or the job's cached one): every
/// material valid, every assignment `grid²` indices into the table, at least one photon, and the
/// photon range within 32-bit indices.
pub fn decode_task(task: &v1::Task, geometry: Geometry) -> Result<RenderTask, ConvertError> {
    geometry.validate()?;
    let table = task
        .table
        .iter()
        .enumerate()
        .map(|(index, m)| material_from_proto(index, m))
        .collect::<Result<Vec<_>, _>>()?;
    if task.assignments.is_empty() {
        return Err(ConvertError::NoAssignments);
    }
    let pixels = geometry.pixels();
    let items = task
        .assignments
        .iter()
        .enumerate()
        .map(|(item, a)| decode_assignment(item, a, pixels, table.len()))
        .collect::<Result<Vec<_>, _>>()?;
    if task.photon_count == 0 {
        return Err(ConvertError::NoPhotons);
    }
    let photons = PhotonRange {
        first: task.photon_first,
        count: task.photon_count,
    };
    if photons.end() > u64::from(u32::MAX) + 1 {
        return Err(ConvertError::PhotonRange {
            first: photons.first,
            count: photons.count,
        });
    }
    let differential = task
        .differential
        .as_ref()
        .map(|d| differential_from_proto(d, items.len(), photons.first, pixels, table.len()))
        .transpose()?;
    let scored = task.scored.is_some();
    if scored {
        check_scored(differential.is_some(), photons.first)?;
    }
    Ok(RenderTask {
        geometry,
        table,
        items,
        photons,
        differential,
        scored,
    })
}

fn decode_assignment(
    item: usize,
    a: &v1::Assignment,
    pixels: usize,
    table: usize,
) -> Result<RenderItem, ConvertError> {
    let bytes = &a.indices_le_u16;
    if bytes.len() != 2 * pixels {
        return Err(ConvertError::AssignmentSize {
            item,
            pixels,
            bytes: bytes.len(),
        });
    }
    let assignment: Vec<u16> = bytes
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    if let Some((pixel, &index)) = assignment
        .iter()
        .enumerate()
        .find(|(_, &i)| usize::from(i) >= table)
    {
        return Err(ConvertError::MaterialIndex {
            item,
            pixel,
            index,
            table,
        });
    }
    Ok(RenderItem {
        assignment,
        seed: a.seed,
    })
}

/// A count matrix as little-endian `u32` bytes.
pub fn counts_to_proto(m: &CountMatrix) -> v1::CountMatrix {
    let mut bytes = Vec::with_capacity(4 * m.counts.len());
    for c in &m.counts {
        bytes.extend_from_slice(&c.to_le_bytes());
    }
    v1::CountMatrix {
        // Geometry caps sources and bins at 65536.
        sources: m.sources as u32,
        bins: m.bins as u32,
        counts_le_u32: Bytes::from(bytes),
    }
}

/// A count matrix from the wire; its byte length must match its shape.
pub fn counts_from_proto(m: &v1::CountMatrix) -> Result<CountMatrix, ConvertError> {
    let (sources, bins) = (m.sources as usize, m.bins as usize);
    let bytes = &m.counts_le_u32;
    if Some(bytes.len()) != sources.checked_mul(bins).and_then(|n| n.checked_mul(4)) {
        return Err(ConvertError::CountBytes {
            sources,
            bins,
            bytes: bytes.len(),
        });
    }
    let counts = bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok(CountMatrix {
        sources,
        bins,
        counts,
    })
}

/// A result's count matrices from the wire, in order, each checked by [`counts_from_proto`];
/// an error names the first malformed one.
pub fn results_from_proto(counts: &[v1::CountMatrix]) -> Result<Vec<CountMatrix>, ConvertError> {
    counts
        .iter()
        .enumerate()
        .map(|(item, m)| {
            counts_from_proto(m).map_err(|e| ConvertError::Result {
                item,
                source: Box::new(e),
            })
        })
        .collect()
}

/// The engine's outputs for `task` as the wire's count matrices (one per assignment, in order)
/// and the total scattering events; checks the engine kept its side of the contract.
pub fn outputs_to_proto(
    task: &RenderTask,
    outputs: &[RenderOutput],
) -> Result<(Vec<v1::CountMatrix>, u64), ConvertError> {
    if outputs.len() != task.items.len() {
        return Err(ConvertError::OutputCount {
            expected: task.items.len(),
            got: outputs.len(),
        });
    }
    let expected = (task.geometry.sources(), task.geometry.bins());
    let mut scatter_events = 0u64;
    let mut counts = Vec::with_capacity(outputs.len());
    for (item, out) in outputs.iter().enumerate() {
        let m = &out.counts;
        if (m.sources, m.bins) != expected || m.counts.len() != expected.0 * expected.1 {
            return Err(ConvertError::OutputShape {
                item,
                expected,
                got: (m.sources, m.bins),
                len: m.counts.len(),
            });
        }
        scatter_events = scatter_events.saturating_add(out.scatter_events);
        counts.push(counts_to_proto(m));
    }
    Ok((counts, scatter_events))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MODERATE: Material = Material {
        sigma_s: 0.6,
        sigma_a: 0.01,
        g: 0.75,
    };

    fn geometry() -> Geometry {
        Geometry::new(4.0, 2, 4, 1).unwrap()
    }

    fn task() -> v1::Task {
        let items = [
            RenderItem {
                assignment: vec![0, 1, 1, 0],
                seed: 7,
            },
            RenderItem {
                assignment: vec![1, 1, 1, 1],
                seed: 8,
            },
        ];
        v1::Task {
            job_id: "job".into(),
            task_id: 3,
            attempt: 1,
            lease_deadline_unix_ms: 0,
            geometry: Some(geometry_to_proto(&geometry())),
            geometry_is_job_geometry: true,
            table: vec![
                material_to_proto(&MODERATE),
                material_to_proto(&Material::OPAQUE),
            ],
            assignments: items.iter().map(assignment_to_proto).collect(),
            photon_first: 10,
            photon_count: 20,
            differential: None,
            scored: None,
        }
    }

    fn decode(t: &v1::Task) -> Result<RenderTask, ConvertError> {
        let g = geometry_from_proto(t.geometry.as_ref().unwrap())?;
        decode_task(t, g)
    }

    #[test]
    fn task_round_trips() {
        let r = decode(&task()).unwrap();
        assert_eq!(r.geometry, geometry());
        assert_eq!(r.table, vec![MODERATE, Material::OPAQUE]);
        assert_eq!(r.items[0].assignment, vec![0, 1, 1, 0]);
        assert_eq!(r.items[1].seed, 8);
        assert_eq!(
            r.photons,
            PhotonRange {
                first: 10,
                count: 20
            }
        );
        assert_eq!(r.photons_launched(), 4 * 20 * 2);
        let batch = r.batch();
        assert_eq!(batch.items.len(), 2);
        assert!(scatterfarm_model::engine::validate_batch(&batch).is_ok());
    }

    #[test]
    fn opaque_flag_wins_over_sigma_a() {
        let m = v1::Material {
            sigma_s: 0.0,
            sigma_a: 0.0,
            g: 0.0,
            opaque: true,
        };
        assert!(material_from_proto(0, &m).unwrap().is_opaque());
        let wire = material_to_proto(&Material::OPAQUE);
        assert!(wire.opaque);
        assert_eq!(material_from_proto(0, &wire).unwrap(), Material::OPAQUE);
    }

    #[test]
    fn builtin_materials_round_trip_bit_exactly() {
        use scatterfarm_model::material::BUILTIN_MATERIALS;
        for (name, m) in BUILTIN_MATERIALS {
            let back = material_from_proto(0, &material_to_proto(&m)).unwrap();
            assert_eq!(back.sigma_s.to_bits(), m.sigma_s.to_bits(), "{name}: σs");
            assert_eq!(back.sigma_a.to_bits(), m.sigma_a.to_bits(), "{name}: σa");
            assert_eq!(back.g.to_bits(), m.g.to_bits(), "{name}: g");
            assert_eq!(back.is_opaque(), m.is_opaque(), "{name}: opaque");
        }
    }

    #[test]
    fn task_to_proto_round_trips() {
        let r = decode(&task()).unwrap();
        let lease = TaskLease {
            job_id: "job".into(),
            task_id: 3,
            attempt: 1,
            lease_deadline_unix_ms: 0,
        };
        let wire = task_to_proto(lease.clone(), &r, true, true, None);
        assert_eq!(wire, task());
        assert_eq!(decode(&wire).unwrap(), r);
        let cached = task_to_proto(lease, &r, true, false, None);
        assert!(cached.geometry.is_none());
        assert!(cached.geometry_is_job_geometry);
        assert_eq!(decode_task(&cached, geometry()).unwrap(), r);
    }

    #[test]
    fn fingerprints_round_trip() {
        let f = EngineFingerprint {
            engine: "gpu".into(),
            adapter: "H200".into(),
            driver: "550.1".into(),
            version: "3".into(),
        };
        assert_eq!(fingerprint_from_proto(fingerprint_to_proto(&f)), f);
    }

    #[test]
    fn results_name_the_malformed_matrix() {
        let m = CountMatrix {
            sources: 1,
            bins: 2,
            counts: vec![3, 4],
        };
        let good = counts_to_proto(&m);
        let bad = v1::CountMatrix {
            counts_le_u32: good.counts_le_u32.slice(..7),
            ..good.clone()
        };
        assert_eq!(
            results_from_proto(&[good.clone(), good.clone()]).unwrap(),
            vec![m.clone(), m]
        );
        assert_eq!(
            results_from_proto(&[good, bad]),
            Err(ConvertError::Result {
                item: 1,
                source: Box::new(ConvertError::CountBytes {
                    sources: 1,
                    bins: 2,
                    bytes: 7
                })
            })
        );
    }

    #[test]
    fn counts_round_trip_as_little_endian() {
        let m = CountMatrix {
            sources: 2,
            bins: 3,
            counts: vec![0, 1, 256, 65_536, u32::MAX, 42],
        };
        let wire = counts_to_proto(&m);
        assert_eq!(wire.counts_le_u32.len(), 24);
        assert_eq!(&wire.counts_le_u32[8..12], &[0, 1, 0, 0]);
        assert_eq!(counts_from_proto(&wire).unwrap(), m);
        let short = v1::CountMatrix {
            counts_le_u32: wire.counts_le_u32.slice(..23),
            ..wire
        };
        assert_eq!(
            counts_from_proto(&short),
            Err(ConvertError::CountBytes {
                sources: 2,
                bins: 3,
                bytes: 23
            })
        );
    }

    #[test]
    fn bad_geometry_is_refused() {
        let mut t = task();
        t.geometry.as_mut().unwrap().grid = 3;
        assert_eq!(
            decode(&t),
            Err(ConvertError::Geometry(GeometryError::Grid(3)))
        );
        t.geometry.as_mut().unwrap().grid = 2;
        t.geometry.as_mut().unwrap().positions = 6;
        assert_eq!(
            decode(&t),
            Err(ConvertError::Geometry(GeometryError::Positions(6)))
        );
        let bad = Geometry {
            size_mm: f64::NAN,
            ..geometry()
        };
        assert!(matches!(
            decode_task(&task(), bad),
            Err(ConvertError::Geometry(GeometryError::Size(_)))
        ));
    }

    #[test]
    fn invalid_materials_are_refused() {
        let mut t = task();
        t.table[1] = v1::Material {
            sigma_s: -1.0,
            sigma_a: 0.0,
            g: 0.0,
            opaque: false,
        };
        assert_eq!(
            decode(&t),
            Err(ConvertError::Material {
                index: 1,
                source: MaterialError::SigmaS(-1.0)
            })
        );
        t.table[1] = v1::Material {
            sigma_s: 0.5,
            sigma_a: 0.0,
            g: 2.0,
            opaque: false,
        };
        assert!(matches!(
            decode(&t),
            Err(ConvertError::Material { index: 1, .. })
        ));
    }

    #[test]
    fn assignment_length_must_be_grid_squared() {
        let mut t = task();
        t.assignments[1].indices_le_u16 = Bytes::from_static(&[0, 0, 1, 0, 1, 0]);
        assert_eq!(
            decode(&t),
            Err(ConvertError::AssignmentSize {
                item: 1,
                pixels: 4,
                bytes: 6
            })
        );
        // An odd byte count is refused, not truncated.
        t.assignments[1].indices_le_u16 = Bytes::from_static(&[0, 0, 1, 0, 1, 0, 0]);
        assert!(matches!(
            decode(&t),
            Err(ConvertError::AssignmentSize { bytes: 7, .. })
        ));
    }

    #[test]
    fn indices_must_be_inside_the_table() {
        let mut t = task();
        t.assignments[0] = assignment_to_proto(&RenderItem {
            assignment: vec![0, 1, 2, 0],
            seed: 1,
        });
        assert_eq!(
            decode(&t),
            Err(ConvertError::MaterialIndex {
                item: 0,
                pixel: 2,
                index: 2,
                table: 2
            })
        );
        t.table.clear();
        assert!(matches!(
            decode(&t),
            Err(ConvertError::MaterialIndex {
                item: 0,
                pixel: 0,
                table: 0,
                ..
            })
        ));
    }

    #[test]
    fn photons_and_assignments_are_required() {
        let mut t = task();
        t.photon_count = 0;
        assert_eq!(decode(&t), Err(ConvertError::NoPhotons));
        let mut t = task();
        t.photon_first = u32::MAX;
        t.photon_count = 2;
        assert_eq!(
            decode(&t),
            Err(ConvertError::PhotonRange {
                first: u32::MAX,
                count: 2
            })
        );
        t.photon_count = 1;
        assert!(decode(&t).is_ok(), "the last photon index is usable");
        let mut t = task();
        t.assignments.clear();
        assert_eq!(decode(&t), Err(ConvertError::NoAssignments));
    }

    #[test]
    fn outputs_are_checked_and_encoded_in_order() {
        let r = decode(&task()).unwrap();
        let out = |fill: u32, events| RenderOutput {
            counts: CountMatrix {
                sources: 4,
                bins: 4,
                counts: vec![fill; 16],
            },
            scatter_events: events,
        };
        let (wire, events) = outputs_to_proto(&r, &[out(1, 5), out(2, 6)]).unwrap();
        assert_eq!(events, 11);
        assert_eq!(counts_from_proto(&wire[1]).unwrap().counts, vec![2; 16]);
        assert_eq!(
            outputs_to_proto(&r, &[out(1, 5)]),
            Err(ConvertError::OutputCount {
                expected: 2,
                got: 1
            })
        );
        let mut wrong = out(1, 0);
        wrong.counts.bins = 3;
        assert!(matches!(
            outputs_to_proto(&r, &[out(1, 5), wrong]),
            Err(ConvertError::OutputShape { item: 1, .. })
        ));
        let mut short = out(1, 0);
        short.counts.counts.pop();
        assert!(matches!(
            outputs_to_proto(&r, &[short, out(1, 5)]),
            Err(ConvertError::OutputShape {
                item: 0,
                len: 15,
                ..
            })
        ));
    }

    #[test]
    fn lease_requests_list_at_most_the_cached_jobs_limit_of_short_ids() {
        let request = |jobs: usize, targets: usize, id_bytes: usize| v1::LeaseRequest {
            worker_id: "w".into(),
            cached_jobs: (0..jobs).map(|_| "j".repeat(id_bytes)).collect(),
            cached_targets: (0..targets).map(|_| "t".repeat(id_bytes)).collect(),
        };
        let limit = MAX_CACHED_LISTED;
        assert_eq!(
            check_lease_request(&request(limit, limit, MAX_JOB_ID_BYTES)),
            Ok(())
        );
        assert_eq!(
            check_lease_request(&request(limit + 1, 0, 3)),
            Err(ConvertError::CachedCount {
                field: "cached_jobs",
                entries: limit + 1
            })
        );
        assert_eq!(
            check_lease_request(&request(0, limit + 1, 3)),
            Err(ConvertError::CachedCount {
                field: "cached_targets",
                entries: limit + 1
            })
        );
        let e = check_lease_request(&request(2, 0, MAX_JOB_ID_BYTES + 1)).unwrap_err();
        assert_eq!(
            e,
            ConvertError::CachedId {
                field: "cached_jobs",
                index: 0,
                bytes: MAX_JOB_ID_BYTES + 1
            }
        );
        assert!(e.to_string().contains("cached_jobs entry 0"), "{e}");
    }
}
