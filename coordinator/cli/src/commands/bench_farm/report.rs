//! The measured window's figures: renders per second ingested and scored, the coordinator's CPU
//! per render, latencies, printed and written as JSON.

use super::replay::Recording;
use super::FarmBenchArgs;
use anyhow::Result;
use scatterfarm_model::Geometry;
use std::time::{Duration, Instant};

/// The throughput this benchmark reports against.
const GOAL_RENDERS_PER_SECOND: f64 = 200.0;

#[derive(Debug, Clone, Copy)]
pub(super) struct Snapshot {
    pub(super) at: Instant,
    pub(super) load_average: Option<f64>,
    pub(super) coordinator_ticks: u64,
    pub(super) bench_cpu: Duration,
    pub(super) tasks: u64,
    pub(super) renders: u64,
    pub(super) bytes: u64,
    pub(super) refused: u64,
    pub(super) replayed: u64,
    pub(super) rendered: u64,
    pub(super) scored: u64,
    pub(super) renders_done: u64,
    pub(super) lease_nanos: u64,
    pub(super) leases: u64,
    pub(super) empty_leases: u64,
    pub(super) complete_nanos: u64,
    pub(super) completes: u64,
}

/// The counters at the start and the end of the measured window.
pub(super) struct Measured {
    pub(super) start: Snapshot,
    pub(super) end: Snapshot,
}

/// Prints the window's figures and emits them as JSON (to `--json` too).
pub(super) fn report(
    args: &FarmBenchArgs,
    geometry: Geometry,
    recording: &Recording,
    outcome: &Measured,
    (clk_tck, clk_source): (f64, &str),
    peak_rss: Option<u64>,
) -> Result<()> {
    let matrix_bytes = 4 * recording.sources * recording.bins;
    let (a, b) = (outcome.start, outcome.end);
    let wall = b.at.duration_since(a.at).as_secs_f64();
    let renders = b.renders - a.renders;
    let tasks = b.tasks - a.tasks;
    let cpu = (b.coordinator_ticks - a.coordinator_ticks) as f64 / clk_tck;
    let bench_cpu = (b.bench_cpu.saturating_sub(a.bench_cpu)).as_secs_f64();
    let per_render = (renders > 0).then(|| cpu / renders as f64);
    let rate = renders as f64 / wall;
    let mean_ms = |nanos: u64, n: u64| (n > 0).then(|| nanos as f64 / n as f64 / 1e6);
    let host_cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);

    eprintln!(
        "bench farm: {rate:.1} full-size renders/s ingested and scored (goal {GOAL_RENDERS_PER_SECOND:.0}: {}), \
         coordinator {} CPU per render, {:.2} cores busy; {renders} renders in {tasks} tasks over {wall:.1} s; \
         {} replay workers sending recorded counts{} ({} renders as scores), {} jobs, {host_cores} host cores",
        if rate >= GOAL_RENDERS_PER_SECOND { "met" } else { "not met" },
        per_render
            .map(|s| format!("{:.2} ms", s * 1e3))
            .unwrap_or_else(|| "-".into()),
        cpu / wall,
        args.workers,
        if args.no_zstd { " uncompressed" } else { " with zstd" },
        b.scored - a.scored,
        args.jobs,
    );
    let busiest = a
        .load_average
        .into_iter()
        .chain(b.load_average)
        .reduce(f64::max);
    if let Some(load) = busiest.filter(|&l| l > host_cores as f64) {
        eprintln!(
            "bench farm: warning: the host was busy (load average {load:.1} on {host_cores} cores): \
             renders/s understates what the coordinator can do; CPU per render is the steadier figure"
        );
    }
    if b.refused > a.refused {
        eprintln!(
            "bench farm: warning: the coordinator refused {} results in the window",
            b.refused - a.refused
        );
    }

    let mut json = serde_json::json!({
        "bench": "farm",
        "workers_replay_recorded_counts": true,
        "note": "workers do not render: they answer every task with count matrices recorded once \
                 (a CPU-engine render of a homogeneous medium), or a scored task with those \
                 renders' scores against the job's target, so this measures the coordinator",
        "scene": args.scene,
        "geometry": {
            "size_mm": geometry.size_mm,
            "grid": args.grid,
            "positions": geometry.positions,
            "directions": geometry.directions,
        },
        "sources": recording.sources,
        "bins": recording.bins,
        "matrix_bytes": matrix_bytes,
        "photons_per_source": args.photons,
        "recorded_photons_per_source": args.record_photons,
        "workers": args.workers,
        "jobs": args.jobs,
        "zstd": !args.no_zstd,
        "host_cores": host_cores,
        "host_load_average_1m": { "window_start": a.load_average, "window_end": b.load_average },
        "warmup_seconds": args.warmup,
        "window_seconds": wall,
        "renders": renders,
        "tasks": tasks,
        "renders_per_task": (tasks > 0).then(|| renders as f64 / tasks as f64),
        "renders_per_second": rate,
        "search_renders_done": b.renders_done - a.renders_done,
        "renders_replayed": b.replayed - a.replayed,
        "renders_rendered_for_real": b.rendered - a.rendered,
        "results_refused": b.refused - a.refused,
        "ingested_megabytes_per_second": (b.bytes - a.bytes) as f64 / wall / 1e6,
        "coordinator_cpu_seconds": cpu,
        "coordinator_cpu_seconds_per_render": per_render,
        "coordinator_cores_used": cpu / wall,
        "renders_per_coordinator_cpu_second": per_render.map(|s| 1.0 / s),
        "coordinator_peak_rss_bytes": peak_rss,
        "clock_ticks_per_second": clk_tck,
        "clock_ticks_source": clk_source,
        "bench_process_cpu_seconds": bench_cpu,
        "lease_ms_mean": mean_ms(b.lease_nanos - a.lease_nanos, b.leases - a.leases),
        "empty_leases": b.empty_leases - a.empty_leases,
        "complete_ms_mean": mean_ms(b.complete_nanos - a.complete_nanos, b.completes - a.completes),
        "goal_renders_per_second": GOAL_RENDERS_PER_SECOND,
        "meets_goal": rate >= GOAL_RENDERS_PER_SECOND,
    });
    // Apart: one literal this long passes `json!`'s recursion limit.
    json["search"] = serde_json::json!(args.search);
    json["workers_score_renders"] = serde_json::json!(!args.no_worker_scoring);
    json["renders_scored_on_workers"] = serde_json::json!(b.scored - a.scored);
    super::super::emit(&json, args.json.as_deref())
}
