//! The farm's job reconstructed by `scatterfarm reconstruct --engine cpu` in one process: what
//! every farm run of the same job must end with.

use super::process::{run, scatterfarm};
use super::scenes::{Search, JOB_KEYS, THREE};
use serde_json::Value;
use std::sync::OnceLock;
use std::time::Duration;

/// The reconstruction's report and `materials.npy`.
pub struct Reference {
    pub report: Value,
    pub npy: Vec<u8>,
}

/// Computed once per search, by the first test that needs it.
pub fn reference_of(search: Search) -> &'static Reference {
    static PAPER: OnceLock<Reference> = OnceLock::new();
    static FAST: OnceLock<Reference> = OnceLock::new();
    static DIFFERENTIAL: OnceLock<Reference> = OnceLock::new();
    let cell = match search {
        Search::Paper => &PAPER,
        Search::Fast => &FAST,
        Search::Differential => &DIFFERENTIAL,
    };
    cell.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("three.toml"), THREE).unwrap();
        let mut cmd = scatterfarm();
        cmd.args(["reconstruct", "--scene", "three.toml"]);
        for (key, value) in JOB_KEYS {
            cmd.arg(format!("--{}", key.replace('_', "-"))).arg(value);
        }
        cmd.args(["--search", search.name()]);
        for (key, value) in search.keys() {
            cmd.arg(format!("--{}", key.replace('_', "-"))).arg(value);
        }
        cmd.args(["--engine", "cpu", "--quiet", "--out", "out"])
            .current_dir(dir.path());
        let ran = run(cmd, dir.path(), Duration::from_secs(300));
        ran.ok();
        let out = dir.path().join("out");
        Reference {
            report: serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap())
                .unwrap(),
            npy: std::fs::read(out.join("materials.npy")).unwrap(),
        }
    })
}

/// The paper's job's reference.
pub fn reference() -> &'static Reference {
    reference_of(Search::Paper)
}
