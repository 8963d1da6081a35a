//! What the in-process scheduler tests share: a small three-material job, a CPU worker's
//! registration, and its render of a leased task.

use scatterfarm_coordinator::scheduler::{Abilities, Rendered, Scheduler, TaskOut};
use scatterfarm_engines::cpu::CpuEngine;
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_model::differential::{render_in_chunks, PhotonChunks};
use scatterfarm_model::likelihood::{change_deviances, deviance};
use scatterfarm_model::{Engine, PhotonRange, RenderBatch};
use std::collections::BTreeMap;
use std::path::Path;

/// A 4 × 4 scene of three materials, opaque among them.
pub const SCENE: &str = r##"
[geometry]
grid = 4
positions = 16
directions = 3
[map]
legend = { "." = "moderate", "o" = "opaque", "b" = "back" }
rows = ["oo..", "oo..", "...b", "..bb"]
"##;

/// The job over [`SCENE`]: the fast search, small budgets.
pub const JOB: &str = "scene = \"three.toml\"\npermutations = 2\niterations = 4\nphotons_per_iteration = 256\nseed = 7\nsearch = \"fast\"\n";

/// [`JOB`] and its scene file, as a submission.
pub fn job() -> (JobSpec, Inputs) {
    let spec = JobSpec::from_toml(JOB, Path::new("job.toml")).unwrap();
    let inputs = Inputs {
        files: BTreeMap::from([("three.toml".to_string(), SCENE.as_bytes().to_vec())]),
    };
    (spec, inputs)
}

/// Registers a worker named `name` with `engine`'s fingerprint, 2e6 photons/s and this
/// build's abilities (`differential`: whether it renders differentially); its id.
pub fn register(s: &mut Scheduler, name: &str, engine: &CpuEngine, differential: bool) -> String {
    s.register(
        name.into(),
        engine.fingerprint(),
        2e6,
        Abilities::of_this_build(differential),
    )
}

/// `task` rendered by `engine`, as a worker returns it: a differential task in its chunks, its
/// changes scored against the job's target; a scored task's renders scored against it, their
/// counts kept back.
pub fn render(engine: &CpuEngine, task: &TaskOut) -> Rendered {
    if let Some(part) = &task.differential {
        let scoring = task
            .scoring
            .as_ref()
            .expect("a differential task's scoring");
        let output = render_in_chunks(
            engine,
            task.geometry,
            &task.table,
            &task.items[0],
            PhotonChunks {
                photons: task.piece.count,
                chunk: part.chunk,
            },
            &part.changes,
            &mut |_| {},
        )
        .unwrap();
        let scores =
            change_deviances(&scoring.target, &output, u64::from(task.piece.count)).unwrap();
        return Rendered {
            counts: Ok(vec![output.counts]),
            scatter_events: output.scatter_events,
            render_seconds: 0.01,
            change_scores: Ok(scores),
            render_scores: Ok(Vec::new()),
        };
    }
    let batch = RenderBatch {
        geometry: task.geometry,
        table: &task.table,
        items: &task.items,
        photons: PhotonRange {
            first: task.piece.first,
            count: task.piece.count,
        },
    };
    let counts: Vec<_> = engine
        .render(&batch)
        .unwrap()
        .into_iter()
        .map(|o| o.counts)
        .collect();
    if task.scored {
        let target = &task
            .scoring
            .as_ref()
            .expect("a scored task's scoring")
            .target;
        let photons = u64::from(task.piece.count);
        return Rendered {
            counts: Ok(Vec::new()),
            scatter_events: 0,
            render_seconds: 0.01,
            change_scores: Ok(Vec::new()),
            render_scores: Ok(counts
                .iter()
                .map(|c| deviance(target, c, photons).unwrap())
                .collect()),
        };
    }
    Rendered {
        counts: Ok(counts),
        scatter_events: 0,
        render_seconds: 0.01,
        change_scores: Ok(Vec::new()),
        render_scores: Ok(Vec::new()),
    }
}
