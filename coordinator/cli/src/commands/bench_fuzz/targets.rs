//! The parsers `scatterfarm bench fuzz` drives, each with its valid seeds and a run that says
//! whether the input was accepted or refused (a panic is caught by the caller).

use super::mutate::Mutator;
use prost::Message;
use scatterfarm_coordinator::job::Job;
use scatterfarm_coordinator::store::{decode_score, encode_score, MemoryStore, Store};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::observation::{self, Sidecar};
use scatterfarm_job::plan::{parse_bounds, Plan};
use scatterfarm_job::spec::JobSpec;
use scatterfarm_model::{likelihood, Change, CountMatrix, Geometry, Material, RenderItem, Scene};
use scatterfarm_proto::v1;
use scatterfarm_proto::{convert, differential, scored};
use std::collections::BTreeMap;
use std::path::Path;

/// An input: one or more parts (an NPY and its sidecar, a task and its result).
pub type Input = Vec<Vec<u8>>;

/// A structure-aware generator of inputs.
pub type Generator = fn(&mut Mutator) -> Input;

/// One parser under the fuzzer.
pub struct Target {
    pub name: &'static str,
    /// Valid inputs, each of one or more parts.
    pub seeds: Vec<Vec<Vec<u8>>>,
    /// Structure-aware inputs (fields of the format set to values worth trying), if any.
    pub generate: Option<Generator>,
    /// Parses an input; `true` when it is accepted.
    pub run: fn(&[Vec<u8>]) -> bool,
}

/// A small scene file, under the name `s.toml`.
const SCENE: &str = r##"[geometry]
size_mm = 8.0
grid = 4
positions = 8
directions = 2

[materials]
fog = { sigma_s = 0.3, sigma_a = 0.02, g = 0.1 }

[map]
legend = { "." = "moderate", "#" = "opaque", "f" = "fog" }
rows = ["....", ".#f.", ".ff.", "...."]
"##;

const JOB: &str = r#"version = 1
scene = "s.toml"
permutations = 1
iterations = 2
photons_per_iteration = 8
search = "fast"
level_photons = [4, 2]
race_share = 0.5
"#;

const JOB_RANDOM: &str = r#"version = 1
scene = "s.toml"
random_materials = 3
bounds = "sigma_s=0:1,sigma_a=0:0.03,g=0:1"
permutations = 2
iterations = 1
photons_per_iteration = 4
search = "paper"
grid = 2
positions = 4
directions = 1
"#;

const JOB_CAPTURE: &str = r#"version = 1
target = "t.npy"
calibration = "t.npy"
calibration_material = "moderate"
dictionary = ["moderate", "mild"]
permutations = 1
iterations = 1
photons_per_iteration = 4
grid = 2
"#;

/// The input files every job seed names.
fn inputs() -> Inputs {
    let mut files = BTreeMap::new();
    files.insert("s.toml".to_string(), SCENE.as_bytes().to_vec());
    let (npy, side) = observation_seed(8, 1);
    files.insert("t.npy".to_string(), npy);
    files.insert("t.json".to_string(), side);
    Inputs { files }
}

/// A valid observation (`positions × directions` sources) and its sidecar.
fn observation_seed(positions: u32, directions: u32) -> (Vec<u8>, Vec<u8>) {
    let geometry = Geometry::new(16.0, 1, positions, directions).unwrap_or_default();
    let n = geometry.sources();
    let mut sidecar = Sidecar::for_render(&geometry, 100);
    sidecar.seed = Some(1);
    let data: Vec<f32> = (0..n * n).map(|i| (i % 7) as f32 / 7.0).collect();
    let side = serde_json::to_vec_pretty(&sidecar).unwrap_or_default();
    (
        npy_bytes(1, "<f4", false, &[n as u64, n as u64], None, &data),
        side,
    )
}

/// An NPY file with the given header fields (`length` overrides the header length).
fn npy_bytes(
    version: u8,
    descr: &str,
    fortran: bool,
    shape: &[u64],
    length: Option<u32>,
    data: &[f32],
) -> Vec<u8> {
    let shape: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape = match shape.len() {
        1 => format!("({},)", shape[0]),
        _ => format!("({})", shape.join(", ")),
    };
    let fortran = if fortran { "True" } else { "False" };
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}");
    let pre = if version == 1 { 10 } else { 12 };
    while !(pre + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.extend_from_slice(&[version, 0]);
    let len = length.unwrap_or(header.len() as u32);
    if version == 1 {
        out.extend_from_slice(&(len as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&len.to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

fn text(bytes: &[u8]) -> Option<&str> {
    std::str::from_utf8(bytes).ok()
}

fn run_scene(input: &[Vec<u8>]) -> bool {
    text(&input[0]).is_some_and(|t| Scene::from_toml(t).is_ok())
}

fn run_job(input: &[Vec<u8>]) -> bool {
    let Some(t) = text(&input[0]) else {
        return false;
    };
    let Ok(spec) = JobSpec::from_toml(t, Path::new("job.toml")) else {
        return false;
    };
    thread_local! {
        static INPUTS: Inputs = inputs();
    }
    INPUTS.with(|inputs| Plan::resolve(&spec, inputs).is_ok())
}

fn run_observation(input: &[Vec<u8>]) -> bool {
    observation::read_bytes(&input[0], &input[1], Path::new("o.npy")).is_ok()
}

/// A structure-aware observation: header fields and values set to ones worth trying.
fn generate_observation(m: &mut Mutator) -> Vec<Vec<u8>> {
    let positions = 4 * (1 + m.below(4) as u32);
    let directions = 1 + m.below(2) as u32;
    let (_, mut side) = observation_seed(positions, directions);
    let n = (positions * directions) as u64;
    let shape: Vec<u64> = match m.below(6) {
        0 => vec![m.number(), m.number()],
        1 => vec![n],
        2 => vec![n, n, 1],
        3 => vec![n, m.number()],
        _ => vec![n, n],
    };
    let count = if m.chance(3) {
        m.below(64)
    } else {
        (n * n) as usize
    };
    let mut data: Vec<f32> = (0..count).map(|i| i as f32 / 100.0).collect();
    if !data.is_empty() && m.chance(2) {
        let i = m.below(data.len());
        data[i] = *m.pick(&[
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1.0,
            -0.0,
            f32::MAX,
        ]);
    }
    let version = *m.pick(&[1u8, 1, 2, 3, 0, 4]);
    let length = m.chance(5).then(|| m.number() as u32);
    let descr = *m.pick(&["<f4", "<f4", "<f4", "<f8", ">f4", "|u1", "<i4", ""]);
    let npy = npy_bytes(version, descr, m.chance(8), &shape, length, &data);
    if m.chance(4) {
        let key = *m.pick(&[
            "positions",
            "directions",
            "size_mm",
            "photons_per_source",
            "format",
        ]);
        let number = m.number();
        if let Ok(mut v) = serde_json::from_slice::<serde_json::Value>(&side) {
            v[key] = match m.below(3) {
                0 => serde_json::json!(number),
                1 => serde_json::json!(-(number as i64)),
                _ => serde_json::json!(number.to_string()),
            };
            side = serde_json::to_vec(&v).unwrap_or_default();
        }
    }
    vec![npy, side]
}

/// Stored records of submitted jobs: record, progress and one score, the inputs kept aside.
fn record_seeds() -> Vec<Vec<Vec<u8>>> {
    let mut seeds = Vec::new();
    for job in [JOB, JOB_RANDOM, JOB_CAPTURE] {
        let store = MemoryStore::new();
        let Ok(spec) = JobSpec::from_toml(job, Path::new("job.toml")) else {
            continue;
        };
        if Job::submit("j1".into(), spec, inputs(), &store).is_err() {
            continue;
        }
        let record = store
            .records()
            .ok()
            .and_then(|r| r.first().map(|(_, v)| v.clone()));
        let progress = store.progress("j1").ok().flatten();
        let mut score = Vec::new();
        for w in [0.5f64.to_bits(), 3, 0.25f64.to_bits()] {
            score.extend_from_slice(&w.to_le_bytes());
        }
        // A differential render's score: blocks, and its changes' scores (one not estimated).
        let differential = encode_score(
            &scatterfarm_search::Score {
                value: -3.0,
                std_error: 0.5,
                secondary: None,
                blocks: vec![-1.0, -2.0],
                changes: vec![
                    Some(scatterfarm_search::ChangeScore {
                        value: -4.0,
                        blocks: vec![-1.5, -2.5],
                    }),
                    None,
                ],
            },
            3,
        );
        if let (Some(record), Some(progress)) = (record, progress) {
            seeds.push(vec![record.clone(), progress.clone(), score]);
            seeds.push(vec![record, progress, differential]);
        }
    }
    seeds
}

fn run_record(input: &[Vec<u8>]) -> bool {
    let store = MemoryStore::new();
    for (name, bytes) in &inputs().files {
        let _ = store.put_blob("j1", &format!("input/{name}"), bytes);
    }
    let _ = store.put_progress("j1", &input[1]);
    store.put_raw_score("j1", &[7; 32], &input[2]);
    decode_score(&input[2]).is_ok() && Job::restore("j1".into(), &input[0], &store).is_ok()
}

fn task_seed() -> v1::Task {
    let geometry = Geometry::new(8.0, 2, 4, 1).unwrap_or_default();
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
        job_id: "j1".into(),
        task_id: 3,
        attempt: 1,
        lease_deadline_unix_ms: 1_700_000_000_000,
        geometry: Some(convert::geometry_to_proto(&geometry)),
        geometry_is_job_geometry: true,
        table: vec![
            convert::material_to_proto(&Material {
                sigma_s: 0.6,
                sigma_a: 0.01,
                g: 0.75,
            }),
            convert::material_to_proto(&Material::OPAQUE),
        ],
        assignments: items.iter().map(convert::assignment_to_proto).collect(),
        photon_first: 10,
        photon_count: 20,
        differential: None,
        scored: None,
    }
}

/// The seed task made a scored one: from photon 0, with the job's target.
fn scored_seed() -> v1::Task {
    let mut task = task_seed();
    task.photon_first = 0;
    let target = likelihood::Target {
        values: (0..16).map(|i| i as f32 / 32.0).collect(),
        photons_per_source: 1000,
    };
    task.scored = Some(scored::scored_to_proto(Some(&target)));
    task
}

/// The seed task made a differential one: its first assignment from photon 0, two changes,
/// and the job's target.
fn differential_seed() -> v1::Task {
    let mut task = task_seed();
    task.assignments.truncate(1);
    task.photon_first = 0;
    let part = differential::DifferentialPart {
        changes: vec![
            Change {
                pixels: vec![(0, 1)],
            },
            Change {
                pixels: vec![(1, 0), (2, 0)],
            },
        ],
        chunk: 8,
    };
    let target = likelihood::Target {
        values: (0..16).map(|i| i as f32 / 32.0).collect(),
        photons_per_source: 1000,
    };
    task.differential = Some(differential::differential_to_proto(&part, Some(&target)));
    task
}

fn complete_seed(sources: u32) -> v1::CompleteRequest {
    let m = CountMatrix {
        sources: sources as usize,
        bins: sources as usize,
        counts: (0..sources * sources).collect(),
    };
    v1::CompleteRequest {
        worker_id: "w1".into(),
        job_id: "j1".into(),
        task_id: 3,
        attempt: 1,
        counts: vec![convert::counts_to_proto(&m), convert::counts_to_proto(&m)],
        scatter_events: 99,
        render_seconds: 0.5,
        change_scores: differential::change_scores_to_proto(&[
            None,
            Some(likelihood::Deviance {
                value: -3.0,
                blocks: vec![-1.0, -2.0],
            }),
        ]),
        render_scores: scored::render_scores_to_proto(&[likelihood::Deviance {
            value: -1.5,
            blocks: vec![-0.5, -1.0],
        }]),
    }
}

fn run_task(input: &[Vec<u8>]) -> bool {
    let task_ok = match v1::Task::decode(&input[0][..]) {
        Ok(task) => {
            let geometry = match &task.geometry {
                Some(g) => convert::geometry_from_proto(g),
                None => Ok(Geometry::default()),
            };
            let carried = task
                .differential
                .as_ref()
                .and_then(|d| d.target.as_ref())
                .or_else(|| task.scored.as_ref().and_then(|s| s.target.as_ref()));
            let target_ok = match carried {
                Some(t) => geometry.as_ref().is_ok_and(|g| {
                    differential::target_from_proto(t, g.sources() * g.bins()).is_ok()
                }),
                None => true,
            };
            geometry.is_ok_and(|g| convert::decode_task(&task, g).is_ok()) && target_ok
        }
        Err(_) => false,
    };
    let result_ok = match v1::CompleteRequest::decode(&input[1][..]) {
        Ok(r) => {
            convert::results_from_proto(&r.counts).is_ok()
                && differential::change_scores_from_proto(&r.change_scores).is_ok()
                && scored::render_scores_from_proto(&r.render_scores).is_ok()
        }
        Err(_) => false,
    };
    task_ok && result_ok
}

/// A structure-aware task and result: fields set to values worth trying.
fn generate_task(m: &mut Mutator) -> Vec<Vec<u8>> {
    let mut task = match m.below(3) {
        0 => differential_seed(),
        1 => scored_seed(),
        _ => task_seed(),
    };
    for _ in 0..1 + m.below(3) {
        match m.below(12) {
            0 => {
                if let Some(g) = task.geometry.as_mut() {
                    g.grid = m.number() as u32;
                }
            }
            1 => {
                if let Some(g) = task.geometry.as_mut() {
                    g.positions = m.number() as u32;
                    g.directions = m.number() as u32;
                }
            }
            2 => {
                if let Some(g) = task.geometry.as_mut() {
                    g.size_mm = *m.pick(&[f64::NAN, f64::INFINITY, -1.0, 0.0, 1e300, 5e-324]);
                }
            }
            3 => task.geometry = None,
            4 => {
                task.photon_first = m.number() as u32;
                task.photon_count = m.number() as u32;
            }
            5 => {
                let i = m.below(task.table.len());
                let sigma_s = *m.pick(&[f64::NAN, f64::INFINITY, -1.0, 1e308]);
                let g = *m.pick(&[f64::NAN, 1.0, -1.0, 2.0]);
                if let Some(material) = task.table.get_mut(i) {
                    material.sigma_s = sigma_s;
                    material.g = g;
                }
            }
            6 => {
                let n = m.below(40);
                let bytes: Vec<u8> = (0..n).map(|_| m.u64() as u8).collect();
                if let Some(a) = task.assignments.first_mut() {
                    a.indices_le_u16 = bytes.into();
                }
            }
            7 => task.table.clear(),
            8 => {
                let (pixel, material) = (m.number() as u32, m.number() as u32);
                if let Some(c) = task
                    .differential
                    .as_mut()
                    .and_then(|d| d.changes.first_mut())
                {
                    c.pixels.push(pixel);
                    if m.chance(2) {
                        c.materials.push(material);
                    }
                }
            }
            9 => {
                let (chunk, photons) = (m.number(), m.number());
                if let Some(d) = task.differential.as_mut() {
                    d.chunk_photons = chunk as u32;
                    if let Some(t) = d.target.as_mut() {
                        t.photons_per_source = photons;
                    }
                }
            }
            10 => {
                let n = m.below(80);
                let bytes: Vec<u8> = (0..n).map(|_| m.u64() as u8).collect();
                if let Some(t) = task.differential.as_mut().and_then(|d| d.target.as_mut()) {
                    t.values_le_f32 = bytes.into();
                }
            }
            _ => task.assignments.clear(),
        }
    }
    let mut result = complete_seed(4);
    if m.chance(2) {
        let i = m.below(result.counts.len());
        let (sources, bins) = (m.number() as u32, m.number() as u32);
        if let Some(c) = result.counts.get_mut(i) {
            c.sources = sources;
            c.bins = bins;
        }
    }
    if m.chance(2) {
        let i = m.below(result.change_scores.len());
        let value = *m.pick(&[f64::NAN, f64::INFINITY, -1.0, 0.0]);
        let blocks = m.below(300);
        if let Some(s) = result.change_scores.get_mut(i) {
            s.value = value;
            s.blocks = vec![value; blocks];
            s.estimated = m.chance(2);
        }
    }
    vec![task.encode_to_vec(), result.encode_to_vec()]
}

fn run_token(input: &[Vec<u8>]) -> bool {
    scatterfarm_proto::auth::parse_token_file(&input[0], Path::new("token")).is_ok()
}

fn run_bounds(input: &[Vec<u8>]) -> bool {
    text(&input[0]).is_some_and(|t| parse_bounds(t).is_ok())
}

/// Every target, with its seeds.
pub fn all() -> Vec<Target> {
    let builtin: Vec<Vec<Vec<u8>>> = scatterfarm_model::builtin::list()
        .iter()
        .filter_map(|b| scatterfarm_model::builtin::toml(b.name))
        .take(3)
        .map(|t| vec![t.into_bytes()])
        .collect();
    let mut scenes = vec![vec![SCENE.as_bytes().to_vec()]];
    scenes.extend(builtin);
    let (npy, side) = observation_seed(8, 1);
    let (npy2, side2) = observation_seed(4, 3);
    vec![
        Target {
            name: "scene",
            seeds: scenes,
            generate: None,
            run: run_scene,
        },
        Target {
            name: "job",
            seeds: [JOB, JOB_RANDOM, JOB_CAPTURE]
                .iter()
                .map(|j| vec![j.as_bytes().to_vec()])
                .collect(),
            generate: None,
            run: run_job,
        },
        Target {
            name: "observation",
            seeds: vec![vec![npy, side], vec![npy2, side2]],
            generate: Some(generate_observation),
            run: run_observation,
        },
        Target {
            name: "record",
            seeds: record_seeds(),
            generate: None,
            run: run_record,
        },
        Target {
            name: "task",
            seeds: vec![vec![
                task_seed().encode_to_vec(),
                complete_seed(4).encode_to_vec(),
            ]],
            generate: Some(generate_task),
            run: run_task,
        },
        Target {
            name: "token",
            seeds: vec![
                vec![b"s3cret-token\n".to_vec()],
                vec![b"  a b c  \r\nsecond line\n".to_vec()],
            ],
            generate: None,
            run: run_token,
        },
        Target {
            name: "bounds",
            seeds: vec![
                vec![b"sigma_s=0:1,sigma_a=0:0.03,g=0:1".to_vec()],
                vec![b"g=-1:1, sigma_s = 0.5:2".to_vec()],
            ],
            generate: None,
            run: run_bounds,
        },
    ]
}
