//! The `scatterfarm` binary as a user runs it: real processes, real files.

use crate::harness::process::{scatterfarm, scatterfarm_in, Proc};
use crate::harness::scenes::SMALL;

#[test]
fn render_writes_the_observation_and_its_sidecar() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("small.toml"), SMALL).unwrap();
    scatterfarm_in(
        &[
            "render",
            "small.toml",
            "--out",
            "out/obs.npy",
            "--photons",
            "2000",
            "--seed",
            "3",
            "--engine",
            "cpu",
        ],
        dir.path(),
    )
    .ok();
    let npy = std::fs::read(dir.path().join("out/obs.npy")).unwrap();
    // NPY magic, float32 little-endian, shape [48, 48].
    assert_eq!(&npy[..6], b"\x93NUMPY");
    let header = String::from_utf8_lossy(&npy[10..128]);
    assert!(
        header.contains("'descr': '<f4'") && header.contains("(48, 48)"),
        "{header}"
    );
    let side: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("out/obs.json")).unwrap()).unwrap();
    assert_eq!(side["format"], "scatterfarm-observation/1");
    assert_eq!(side["positions"], 16);
    assert_eq!(side["directions"], 3);
    assert_eq!(side["size_mm"], 16.0);
    assert_eq!(side["photons_per_source"], 2000);
    assert_eq!(side["seed"], 3);
    assert!(side["engine"].as_str().unwrap().starts_with("cpu/"));
    assert_eq!(side["scene_sha256"].as_str().unwrap().len(), 64);
    let exited = side["photons_exited"].as_u64().unwrap();
    let absorbed = side["photons_absorbed"].as_u64().unwrap();
    assert_eq!(exited + absorbed, 48 * 2000);
    assert!(exited > 0 && absorbed > 0);
    // Fractions sum to the exited photons over the photons per source.
    let values: Vec<f32> = npy[npy.len() - 48 * 48 * 4..]
        .chunks(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let sum: f64 = values.iter().map(|&v| f64::from(v)).sum();
    assert!((sum * 2000.0 - exited as f64).abs() < 0.5, "{sum}");

    // The same seed renders the same file; drawing it gives a PNG.
    scatterfarm_in(
        &[
            "render",
            "small.toml",
            "--out",
            "again.npy",
            "--photons",
            "2000",
            "--seed",
            "3",
            "--engine",
            "cpu",
        ],
        dir.path(),
    )
    .ok();
    assert_eq!(std::fs::read(dir.path().join("again.npy")).unwrap(), npy);
    scatterfarm_in(&["show", "out/obs.npy", "--out", "obs.png"], dir.path()).ok();
    let png = image::open(dir.path().join("obs.png")).unwrap();
    assert!(png.width() >= 48 && png.height() >= 48);
}

#[test]
fn a_bad_scene_names_the_file_and_place_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bad.toml"), SMALL.replace(".ff.", ".fx.")).unwrap();
    let err = scatterfarm_in(
        &["render", "bad.toml", "--out", "obs.npy", "--photons", "10"],
        dir.path(),
    )
    .fails();
    assert!(
        err.contains("bad.toml")
            && err.contains("row 3, column 3")
            && err.contains("unknown symbol 'x'"),
        "{err}"
    );
    assert!(!dir.path().join("obs.npy").exists() && !dir.path().join("obs.json").exists());
    let err = scatterfarm_in(&["render", "no-such-scene", "--out", "obs.npy"], dir.path()).fails();
    assert!(
        err.contains("no-such-scene") && err.contains("fig7a") && err.contains("phantom128"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "something was written"
    );
}

#[test]
fn scenes_are_listed_shown_and_drawn() {
    let dir = tempfile::tempdir().unwrap();
    let list = scatterfarm_in(&["scenes"], dir.path()).ok();
    for name in ["fig7a", "fig7f", "fig7l", "phantom16", "phantom128"] {
        assert!(list.contains(name), "{list}");
    }
    assert_eq!(list.lines().count(), 15);
    let text = scatterfarm_in(&["scenes", "show", "fig7k"], dir.path()).ok();
    std::fs::write(dir.path().join("k.toml"), &text).unwrap();
    assert!(text.contains("[map]") && text.contains("opaque"));
    scatterfarm_in(&["show", "k.toml", "--out", "k.png"], dir.path()).ok();
    let png = image::open(dir.path().join("k.png")).unwrap().to_rgb8();
    assert!(png.width() > 512);
    let err = scatterfarm_in(&["scenes", "show", "fig7z"], dir.path()).fails();
    assert!(err.contains("fig7z") && err.contains("fig7a"), "{err}");
}

#[test]
fn help_answers() {
    let dir = tempfile::tempdir().unwrap();
    let help = scatterfarm_in(&["--help"], dir.path()).ok();
    for cmd in ["render", "show", "scenes", "bench"] {
        assert!(help.contains(cmd), "{help}");
    }
    let help = scatterfarm_in(&["render", "--help"], dir.path()).ok();
    assert!(help.contains("--photons") && help.contains("--seed") && help.contains("--engine"));
}

#[test]
fn an_interrupted_render_leaves_no_file_behind() {
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = scatterfarm();
    cmd.args([
        "render",
        "phantom128",
        "--out",
        "obs.npy",
        "--photons",
        "1000000",
        "--engine",
        "cpu",
    ])
    .current_dir(dir.path())
    .stderr(std::process::Stdio::null());
    let mut render = Proc::spawn(cmd);
    std::thread::sleep(std::time::Duration::from_millis(1500));
    assert!(
        render.running(),
        "the render finished too soon to interrupt"
    );
    render.kill();
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

#[test]
fn a_bad_search_option_is_reported_before_any_engine_starts() {
    // The adapter does not exist: an engine opened before the options were checked would
    // report the adapter instead of the option.
    let dir = tempfile::tempdir().unwrap();
    let no_adapter = ["--engine", "gpu", "--adapter", "no-such-adapter"];
    let reconstruct = |option: &[&str]| {
        let args = [
            &["reconstruct", "--scene", "demo8"],
            option,
            &no_adapter,
            &["--out", "out"],
        ];
        let err = scatterfarm_in(&args.concat(), dir.path()).fails();
        assert!(!dir.path().join("out").exists(), "something was written");
        assert!(!err.contains("no-such-adapter"), "{err}");
        err
    };
    let err = reconstruct(&["--tie-z=-1"]);
    assert!(err.contains("--tie-z"), "{err}");
    // demo8's grid of 8 has 4 quad-tree levels.
    let err = reconstruct(&["--coarse-levels", "5"]);
    assert!(
        err.contains("--coarse-levels") && err.contains("1 ..= 4"),
        "{err}"
    );
    let err = reconstruct(&["--coarse-levels", "sometimes"]);
    assert!(
        err.contains("--coarse-levels") && err.contains("\"auto\""),
        "{err}"
    );
    let bench = [
        &[
            "bench",
            "reconstruct",
            "--scenes",
            "demo8",
            "--set",
            "race_share=2",
        ][..],
        &no_adapter,
        &["--out", "bench.json"],
    ];
    let err = scatterfarm_in(&bench.concat(), dir.path()).fails();
    assert!(
        err.contains("--race-share") && err.contains("demo8") && !err.contains("no-such-adapter"),
        "{err}"
    );
    assert!(!dir.path().join("bench.json").exists());
}

#[test]
fn the_quality_bench_reports_each_run_and_its_level_zero_map() {
    let dir = tempfile::tempdir().unwrap();
    scatterfarm_in(
        &[
            "bench",
            "reconstruct",
            "--engine",
            "cpu",
            "--scenes",
            "demo8",
            "--grid",
            "4",
            "--positions",
            "8",
            "--directions",
            "3",
            "--permutations",
            "1",
            "--iterations",
            "2",
            "--photons-per-iteration",
            "256",
            "--target-photons",
            "1024",
            "--seeds",
            "1,2",
            "--search",
            "fast",
            "--keep",
            "runs",
            "--out",
            "bench.json",
        ],
        dir.path(),
    )
    .ok();
    let bench: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("bench.json")).unwrap()).unwrap();
    let runs = bench["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 2);
    for run in runs {
        let seed = run["seed"].as_u64().unwrap();
        let report: serde_json::Value = serde_json::from_slice(
            &std::fs::read(dir.path().join(format!("runs/{seed}/demo8/report.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(run["pixel_accuracy"], report["pixel_accuracy"]);
        // Level 0 is one material everywhere: demo8 has 58 moderate, 4 opaque and 2 back
        // pixels of 64, so its accuracy is one of those shares.
        let level0 = run["level0_pixel_accuracy"].as_f64().unwrap();
        assert_eq!(
            run["level0_pixel_accuracy"],
            report["levels"][0]["pixel_accuracy"]
        );
        assert!(
            [58.0, 4.0, 2.0].contains(&(level0 * 64.0).round())
                && (level0 * 64.0 - (level0 * 64.0).round()).abs() < 1e-9,
            "level 0 accuracy {level0}"
        );
    }
    let scene = &bench["scenes"][0];
    let mean = (runs[0]["level0_pixel_accuracy"].as_f64().unwrap()
        + runs[1]["level0_pixel_accuracy"].as_f64().unwrap())
        / 2.0;
    assert!((scene["mean_level0_pixel_accuracy"].as_f64().unwrap() - mean).abs() < 1e-12);
}

/// A scene named by an absolute path runs (its outputs under its file stem), and at the
/// truth's grid the bench says whether the truth scores better than the map found.
#[test]
fn the_quality_bench_takes_scene_paths_and_checks_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("three.toml");
    std::fs::write(&scene, crate::harness::scenes::THREE).unwrap();
    scatterfarm_in(
        &[
            "bench",
            "reconstruct",
            "--engine",
            "cpu",
            "--scenes",
            scene.to_str().unwrap(),
            "--positions",
            "16",
            "--directions",
            "3",
            "--iterations",
            "4",
            "--target-photons",
            "20000",
            "--search",
            "likelihood",
            "--set",
            "refine_sweeps=2",
            "--set",
            "refine_photons=2048",
            "--set",
            "refine_direct_photons=2048",
            "--check-photons",
            "4096",
            "--keep",
            "runs",
            "--out",
            "bench.json",
        ],
        dir.path(),
    )
    .ok();
    let bench: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("bench.json")).unwrap()).unwrap();
    let run = &bench["runs"][0];
    assert!(dir.path().join("runs/1/three/report.json").exists());
    // The grid is the scene's own (4), so the truth is written in the search's table.
    let z = run["truth_margin_z"].as_f64().expect("a truth check");
    let margin = run["truth_margin"].as_f64().unwrap();
    assert!(z.is_finite() && margin.is_finite(), "{run}");
    if run["pixel_accuracy"] == 1.0 {
        assert_eq!(margin, 0.0, "the map found is the truth: {run}");
    }
    // The truth's one-pixel neighbours: the 12 non-opaque pixels' changes are estimated from
    // one differential render (nothing reweights out of the 4 opaque ones), and the target
    // tells some of them from the truth.
    let count = |key: &str| {
        run[key]
            .as_u64()
            .unwrap_or_else(|| panic!("no {key}: {run}"))
    };
    let (estimated, unresolved) = (
        count("neighbours_estimated"),
        count("neighbours_unresolved"),
    );
    assert!(estimated >= 12 && estimated % 12 == 0, "{run}");
    assert!(
        unresolved < estimated,
        "no neighbour is told from the truth: {run}"
    );
    let accuracy = run["pixel_accuracy"].as_f64().unwrap();
    let wrong = count("wrong_pixels");
    assert_eq!(wrong, ((1.0 - accuracy) * 16.0).round() as u64, "{run}");
    assert!(
        count("wrong_told") + count("wrong_untold") <= wrong,
        "{run}"
    );
    // The found map's own one-pixel changes: those beating it, and of those the ones that set
    // a wrong pixel right (at most one per wrong pixel).
    let (escapes, toward) = (count("escapes"), count("escapes_toward_truth"));
    assert!(toward <= escapes && toward <= wrong, "{run}");
    assert!(escapes <= 16 * 2, "{run}");
    assert!(
        run["escape_best_z"].as_f64().is_some_and(f64::is_finite),
        "{run}"
    );
}

#[test]
fn a_differential_search_runs_on_the_gpu_engine_or_on_a_cpu_device_on_the_cpu_engine() {
    // The GPU engine renders differentially on a GPU (`shaders/differential.wgsl`): the whole
    // search, refinement included, runs on it. A CPU device (lavapipe) does not offer it (the CPU
    // engine is about 15× faster there): the job then runs on the CPU engine, said in a warning,
    // rather than fail when its refinement starts.
    let dir = tempfile::tempdir().unwrap();
    let ran = scatterfarm_in(
        &[
            "reconstruct",
            "--engine",
            "gpu",
            "--scene",
            "demo8",
            "--search",
            "likelihood",
            "--refine-screen",
            "differential",
            "--iterations",
            "1",
            "--photons-per-iteration",
            "256",
            "--permutations",
            "1",
            "--refine-photons",
            "512",
            "--refine-confirm-photons",
            "1024",
            "--refine-sweeps",
            "1",
            "--positions",
            "4",
            "--directions",
            "1",
            "--out",
            "out",
        ],
        dir.path(),
    );
    if !ran.status.success() && ran.stderr.contains("cannot start the GPU engine") {
        crate::harness::gating::skip_or_fail(
            "a_differential_search_runs_on_the_gpu_engine_or_on_a_cpu_device_on_the_cpu_engine",
            "no Vulkan adapter",
            "install mesa-vulkan-drivers",
        );
        return;
    }
    ran.ok();
    // The engine picks hardware GPUs before CPU devices: a CPU device when every adapter is one.
    let adapters: serde_json::Value =
        serde_json::from_str(&scatterfarm_in(&["adapters", "--json"], dir.path()).ok()).unwrap();
    let cpu_device = adapters
        .as_array()
        .unwrap()
        .iter()
        .all(|a| a["type"] == "cpu");
    let fell_back = ran.stderr.contains("does not render differentially")
        && ran.stderr.contains("the CPU engine renders this job");
    assert_eq!(fell_back, cpu_device, "{}", ran.stderr);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("out/report.json")).unwrap())
            .unwrap();
    let engine = report["engine"].as_str().unwrap_or_default();
    let expected = if cpu_device { "cpu" } else { "gpu" };
    assert!(engine.starts_with(expected), "{report:#}");
}
