//! `scatterfarm bench farm`: what one coordinator can feed — full-size renders per second
//! ingested and scored, and the coordinator's CPU seconds per render.
//!
//! The coordinator runs as a child process (`scatterfarm coordinator` on a loopback port with a
//! scratch data folder) so its CPU time can be read from `/proc/PID/stat`. Search jobs with a
//! tiny budget (default: `fig7a` at its default geometry, 128 positions × 9 directions = 1152
//! sources × 1152 bins, searched at grid 4 with 32 photons per source and a practically endless
//! number of permutations) are submitted, and replay workers in this process — tokio tasks
//! speaking the ordinary worker protocol — lease their tasks and answer each with counts
//! recorded once at start (a real CPU-engine render of a homogeneous medium with a few photons
//! per source) instead of rendering. Workers announce a huge photons per second, so every task
//! is one whole render group. A task whose shape differs from the recorded one, or that asks
//! for fewer photons than were recorded, is rendered for real by the CPU engine.
//!
//! After every job is searching and a warm-up, counters are read at the start and end of a
//! measured window: renders in results the coordinator accepted, the jobs' `renders_done`,
//! and the coordinator's utime + stime.

use crate::commands::jobs::{self, status_error};
use anyhow::{bail, ensure, Context, Result};
use clap::Args;
use cpu_time::ProcessTime;
use scatterfarm_engines::CpuEngine;
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::params::JobParams;
use scatterfarm_job::plan::Plan;
use scatterfarm_model::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};
use scatterfarm_proto::channel::{Authed, Target};
use scatterfarm_proto::convert::{counts_to_proto, decode_task, geometry_from_proto};
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::worker_service_client::WorkerServiceClient;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tonic::codec::CompressionEncoding;

/// The throughput this benchmark reports against.
const GOAL_RENDERS_PER_SECOND: f64 = 200.0;
/// Announced by replay workers, so every task is one whole render group.
const REPLAY_PHOTONS_PER_SECOND: f64 = 1e15;
/// Distinct recorded matrices (different seeds), so the calibration pair differs (ε > 0) and
/// search renders differ from the target, as they would for real.
const RECORDED: u64 = 2;

#[derive(Debug, Args)]
pub struct FarmBenchArgs {
    /// Replay workers (tokio tasks in this process, one connection each).
    #[arg(long, default_value_t = 8)]
    pub workers: usize,
    /// Concurrent search jobs. A job has one render group in flight at a time, so this caps the
    /// tasks in flight.
    #[arg(long, default_value_t = 8)]
    pub jobs: usize,
    /// Length of the measured window, in seconds.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Seconds to run after every job is searching, before the window opens.
    #[arg(long, default_value_t = 3.0)]
    pub warmup: f64,
    /// Also write the JSON here.
    #[arg(long, alias = "out")]
    pub json: Option<PathBuf>,
    /// The scene the jobs search (its geometry is the render geometry).
    #[arg(long, default_value = "fig7a")]
    pub scene: String,
    /// The search grid (renders are full size whatever it is).
    #[arg(long, default_value_t = 4)]
    pub grid: u32,
    /// Override the boundary positions.
    #[arg(long)]
    pub positions: Option<u32>,
    /// Override the directions per position.
    #[arg(long)]
    pub directions: Option<u32>,
    /// Photons per source of every render of the jobs (one iteration of this many).
    #[arg(long, default_value_t = 32)]
    pub photons: u32,
    /// Photons per source of the recorded render the workers replay (at most --photons).
    #[arg(long, default_value_t = 8)]
    pub record_photons: u32,
    /// Permutations per level of each job (enough that no job finishes during the run).
    #[arg(long, default_value_t = 100_000)]
    pub permutations: u32,
    /// Workers send results uncompressed (real workers, and the default, use zstd).
    #[arg(long)]
    pub no_zstd: bool,
    /// Keep the coordinator's data folder and log here instead of a scratch folder.
    #[arg(long)]
    pub keep: Option<PathBuf>,
}

/// The coordinator child process; killed when dropped.
struct ChildCoordinator {
    child: Child,
    url: String,
    log: PathBuf,
}

impl Drop for ChildCoordinator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl ChildCoordinator {
    /// Starts `scatterfarm coordinator` on a loopback port with `dir` as data folder and waits
    /// for its address.
    fn start(dir: &Path) -> Result<ChildCoordinator> {
        let exe = std::env::current_exe().context("cannot find this program's executable")?;
        let data = dir.join("data");
        let address_file = dir.join("address");
        let log = dir.join("coordinator.log");
        // A data folder left by an earlier run would resume its jobs beside ours.
        ensure!(
            !data.exists(),
            "{} exists: give --keep an empty or new folder",
            data.display()
        );
        match std::fs::remove_file(&address_file) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(e).with_context(|| format!("cannot remove {}", address_file.display()))
            }
        }
        let log_file = std::fs::File::create(&log)
            .with_context(|| format!("cannot create {}", log.display()))?;
        let child = Command::new(&exe)
            .arg("coordinator")
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--data")
            .arg(&data)
            .arg("--address-file")
            .arg(&address_file)
            .arg("--drain-seconds")
            .arg("0")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .with_context(|| format!("cannot start {} coordinator", exe.display()))?;
        let mut coordinator = ChildCoordinator {
            child,
            url: String::new(),
            log,
        };
        let until = Instant::now() + Duration::from_secs(60);
        loop {
            if let Ok(text) = std::fs::read_to_string(&address_file) {
                let url = text.trim();
                if !url.is_empty() {
                    coordinator.url = url.to_string();
                    return Ok(coordinator);
                }
            }
            if let Some(status) = coordinator
                .child
                .try_wait()
                .context("cannot check on the coordinator")?
            {
                bail!(
                    "the coordinator exited ({status}) before listening:\n{}",
                    coordinator.log_tail()
                );
            }
            ensure!(
                Instant::now() < until,
                "the coordinator did not write its address within 60 s:\n{}",
                coordinator.log_tail()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The last lines of the coordinator's log.
    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(20)..].join("\n")
    }

    /// utime + stime of the coordinator so far, in clock ticks (threads that ended included).
    fn cpu_ticks(&self) -> Result<u64> {
        let path = format!("/proc/{}/stat", self.pid());
        let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {path}"))?;
        // Fields after the parenthesized command name, from field 3 (state) on.
        let rest = text
            .rsplit_once(')')
            .map(|(_, r)| r)
            .with_context(|| format!("{path}: unexpected contents"))?;
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let field = |n: usize| -> Result<u64> {
            fields
                .get(n - 3)
                .and_then(|f| f.parse().ok())
                .with_context(|| format!("{path}: no field {n}"))
        };
        Ok(field(14)? + field(15)?)
    }

    /// The coordinator's peak resident memory, in bytes (`VmHWM`).
    fn peak_rss_bytes(&self) -> Option<u64> {
        let text = std::fs::read_to_string(format!("/proc/{}/status", self.pid())).ok()?;
        let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kb * 1024)
    }
}

/// Clock ticks per second of `/proc/PID/stat` (`getconf CLK_TCK`; 100, Linux's USER_HZ on
/// every common architecture, if getconf is missing).
fn clock_ticks_per_second() -> (f64, &'static str) {
    let measured = Command::new("getconf")
        .arg("CLK_TCK")
        .stderr(Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| {
            String::from_utf8_lossy(&o.stdout)
                .trim()
                .parse::<f64>()
                .ok()
        })
        .filter(|&t| t > 0.0);
    match measured {
        Some(t) => (t, "getconf CLK_TCK"),
        None => (100.0, "assumed (USER_HZ)"),
    }
}

/// The host's 1-minute load average (other work on the host skews every figure).
fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Counts recorded once and replayed as every result of the same shape.
struct Recording {
    sources: usize,
    bins: usize,
    photons: u32,
    /// Encoded once; cloning shares the bytes.
    matrices: Vec<pb::CountMatrix>,
    scatter_events: Vec<u64>,
}

/// Renders the recorded matrices: the calibration material, homogeneous, over the search's
/// boundary sampling.
fn record(plan: &Plan, photons: u32) -> Result<Recording> {
    let geometry = Geometry {
        grid: 1,
        ..plan.search_geometry
    };
    let table = [plan.calibration_material];
    let items: Vec<RenderItem> = (0..RECORDED)
        .map(|seed| RenderItem {
            assignment: vec![0; geometry.pixels()],
            seed: 0x5eed_0000 + seed,
        })
        .collect();
    let out = CpuEngine::new()
        .render(&RenderBatch {
            geometry,
            table: &table,
            items: &items,
            photons: PhotonRange::first_n(photons),
        })
        .context("cannot record the replayed render")?;
    Ok(Recording {
        sources: geometry.sources(),
        bins: geometry.bins(),
        photons,
        matrices: out.iter().map(|o| counts_to_proto(&o.counts)).collect(),
        scatter_events: out.iter().map(|o| o.scatter_events).collect(),
    })
}

/// What the replay workers did, summed over all of them.
#[derive(Default)]
struct Stats {
    tasks_accepted: AtomicU64,
    renders_accepted: AtomicU64,
    renders_replayed: AtomicU64,
    renders_rendered: AtomicU64,
    bytes_accepted: AtomicU64,
    refused: AtomicU64,
    empty_leases: AtomicU64,
    lease_nanos: AtomicU64,
    leases: AtomicU64,
    complete_nanos: AtomicU64,
    completes: AtomicU64,
}

#[derive(Debug, Clone, Copy)]
struct Snapshot {
    at: Instant,
    load_average: Option<f64>,
    coordinator_ticks: u64,
    bench_cpu: Duration,
    tasks: u64,
    renders: u64,
    bytes: u64,
    refused: u64,
    replayed: u64,
    rendered: u64,
    renders_done: u64,
    lease_nanos: u64,
    leases: u64,
    empty_leases: u64,
    complete_nanos: u64,
    completes: u64,
}

type WorkerClient = WorkerServiceClient<Authed>;

/// Aborts a spawned task when dropped (a replay worker's heartbeat dies with it).
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

fn worker_client(channel: Authed, zstd: bool) -> WorkerClient {
    if zstd {
        Target::worker_client(channel)
    } else {
        // Still accepts zstd; only what this worker sends goes plain.
        WorkerServiceClient::new(channel)
            .max_decoding_message_size(pb::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(pb::MAX_MESSAGE_BYTES)
            .accept_compressed(CompressionEncoding::Zstd)
    }
}

/// The counts for one leased task: the recording where it fits, else a real CPU render.
async fn answer(
    task: &pb::Task,
    recording: &Recording,
    engine: &Arc<CpuEngine>,
    stats: &Stats,
) -> Result<(Vec<pb::CountMatrix>, u64)> {
    let geometry = task
        .geometry
        .as_ref()
        .context("a task came without its geometry (this worker caches none)")?;
    let geometry = geometry_from_proto(geometry)?;
    if geometry.sources() == recording.sources
        && geometry.bins() == recording.bins
        && task.photon_count >= recording.photons
    {
        let mut events = 0;
        let counts = (0..task.assignments.len() as u64)
            .map(|i| {
                let k = ((task.task_id + i) % RECORDED) as usize;
                events += recording.scatter_events[k];
                recording.matrices[k].clone()
            })
            .collect();
        stats
            .renders_replayed
            .fetch_add(task.assignments.len() as u64, Ordering::Relaxed);
        return Ok((counts, events));
    }
    let render = decode_task(task, geometry)?;
    let engine = engine.clone();
    let outputs = tokio::task::spawn_blocking(move || engine.render(&render.batch()))
        .await
        .context("the CPU render panicked")??;
    stats
        .renders_rendered
        .fetch_add(outputs.len() as u64, Ordering::Relaxed);
    let events = outputs.iter().map(|o| o.scatter_events).sum();
    Ok((
        outputs.iter().map(|o| counts_to_proto(&o.counts)).collect(),
        events,
    ))
}

/// One replay worker: registers, heartbeats, leases and answers until `stop`.
async fn replay_worker(
    index: usize,
    target: Target,
    zstd: bool,
    recording: Arc<Recording>,
    engine: Arc<CpuEngine>,
    stats: Arc<Stats>,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    let channel = target.connect().await?;
    let mut client = worker_client(channel, zstd);
    let fingerprint = engine.fingerprint();
    let registered = client
        .register(pb::RegisterRequest {
            protocol: Some(pb::PROTOCOL),
            fingerprint: Some(pb::EngineFingerprint {
                engine: fingerprint.engine,
                adapter: fingerprint.adapter,
                driver: fingerprint.driver,
                version: format!("{}+replay", fingerprint.version),
            }),
            photons_per_second: REPLAY_PHOTONS_PER_SECOND,
            name: format!("bench-replay-{index}"),
        })
        .await
        .map_err(|s| status_error("register", s))?
        .into_inner();
    let worker_id = registered.worker_id;
    let _heartbeat = {
        let mut client = client.clone();
        let worker_id = worker_id.clone();
        let every = Duration::from_millis(u64::from(registered.heartbeat_interval_ms.max(50)));
        AbortOnDrop(tokio::spawn(async move {
            let mut tick = tokio::time::interval(every);
            loop {
                tick.tick().await;
                let request = pb::HeartbeatRequest {
                    worker_id: worker_id.clone(),
                };
                if let Err(s) = client.heartbeat(request).await {
                    tracing::warn!("heartbeat of {worker_id}: {}", s.message());
                }
            }
        }))
    };
    while !stop.load(Ordering::Relaxed) {
        let t0 = Instant::now();
        let response = client
            .lease(pb::LeaseRequest {
                worker_id: worker_id.clone(),
                cached_jobs: Vec::new(),
            })
            .await
            .map_err(|s| status_error("lease", s))?
            .into_inner();
        stats
            .lease_nanos
            .fetch_add(t0.elapsed().as_nanos() as u64, Ordering::Relaxed);
        stats.leases.fetch_add(1, Ordering::Relaxed);
        let Some(task) = response.task else {
            stats.empty_leases.fetch_add(1, Ordering::Relaxed);
            let pause = Duration::from_millis(u64::from(response.retry_after_ms).min(1000));
            tokio::time::sleep(pause).await;
            continue;
        };
        let (counts, scatter_events) = answer(&task, &recording, &engine, &stats).await?;
        let renders = counts.len() as u64;
        let bytes: u64 = counts.iter().map(|c| c.counts_le_u32.len() as u64).sum();
        let t1 = Instant::now();
        let outcome = client
            .complete(pb::CompleteRequest {
                worker_id: worker_id.clone(),
                job_id: task.job_id.clone(),
                task_id: task.task_id,
                attempt: task.attempt,
                counts,
                scatter_events,
                render_seconds: 0.0,
            })
            .await;
        stats
            .complete_nanos
            .fetch_add(t1.elapsed().as_nanos() as u64, Ordering::Relaxed);
        stats.completes.fetch_add(1, Ordering::Relaxed);
        match outcome {
            Ok(_) => {
                stats.tasks_accepted.fetch_add(1, Ordering::Relaxed);
                stats.renders_accepted.fetch_add(renders, Ordering::Relaxed);
                stats.bytes_accepted.fetch_add(bytes, Ordering::Relaxed);
            }
            Err(s) => {
                stats.refused.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(
                    "task {} of job {} refused: {} ({:?})",
                    task.task_id,
                    task.job_id,
                    s.message(),
                    s.code()
                );
            }
        }
    }
    Ok(())
}

fn job_params(args: &FarmBenchArgs, index: usize) -> JobParams {
    JobParams {
        scene: Some(args.scene.clone()),
        permutations: args.permutations,
        iterations: 1,
        photons_per_iteration: args.photons,
        grid: Some(args.grid),
        positions: args.positions,
        directions: args.directions,
        seed: 1 + index as u64,
        name: Some(format!("bench-farm-{index}")),
        ..Default::default()
    }
}

pub fn run(args: FarmBenchArgs) -> Result<()> {
    ensure!(args.workers > 0, "--workers must be at least 1");
    ensure!(args.jobs > 0, "--jobs must be at least 1");
    ensure!(
        args.seconds > 0.0 && args.seconds.is_finite(),
        "--seconds must be positive"
    );
    ensure!(
        args.warmup >= 0.0 && args.warmup.is_finite(),
        "--warmup must be >= 0"
    );
    ensure!(args.photons > 0, "--photons must be at least 1");
    ensure!(
        (1..=args.photons).contains(&args.record_photons),
        "--record-photons must lie in 1..=--photons"
    );
    ensure!(
        cfg!(target_os = "linux"),
        "bench farm reads the coordinator's CPU time from /proc (Linux only)"
    );

    let params: Vec<JobParams> = (0..args.jobs).map(|i| job_params(&args, i)).collect();
    let inputs = Inputs::gather(&params[0], Path::new("."))?;
    let plan = Plan::resolve(&params[0], &inputs).context("the benchmark's job")?;
    let geometry = plan.search_geometry;
    let recording = Arc::new(record(&plan, args.record_photons)?);
    let matrix_bytes = 4 * recording.sources * recording.bins;

    let scratch = tempfile::tempdir().context("cannot create a scratch folder")?;
    let dir = match &args.keep {
        Some(d) => {
            std::fs::create_dir_all(d).with_context(|| format!("cannot create {}", d.display()))?;
            d.clone()
        }
        None => scratch.path().to_path_buf(),
    };
    let coordinator = ChildCoordinator::start(&dir)?;
    let (clk_tck, clk_source) = clock_ticks_per_second();
    eprintln!(
        "bench farm: coordinator pid {} at {}; {} replay workers (recorded counts, not rendering), \
         {} jobs of {} at grid {}, {}×{} count matrices ({:.1} MB each)",
        coordinator.pid(),
        coordinator.url,
        args.workers,
        args.jobs,
        args.scene,
        args.grid,
        recording.sources,
        recording.bins,
        matrix_bytes as f64 / 1e6
    );

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let outcome = runtime.block_on(measure(
        &args,
        &params,
        inputs,
        &coordinator,
        recording.clone(),
    ));
    let peak_rss = coordinator.peak_rss_bytes();
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            return Err(e.context(format!(
                "the coordinator's log ends:\n{}",
                coordinator.log_tail()
            )))
        }
    };
    runtime.shutdown_timeout(Duration::from_secs(1));
    drop(coordinator);

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
         {} replay workers sending recorded counts{}, {} jobs, {host_cores} host cores",
        if rate >= GOAL_RENDERS_PER_SECOND { "met" } else { "not met" },
        per_render
            .map(|s| format!("{:.2} ms", s * 1e3))
            .unwrap_or_else(|| "-".into()),
        cpu / wall,
        args.workers,
        if args.no_zstd { " uncompressed" } else { " with zstd" },
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

    let json = serde_json::json!({
        "bench": "farm",
        "workers_replay_recorded_counts": true,
        "note": "workers do not render: they answer every task with count matrices recorded once \
                 (a CPU-engine render of a homogeneous medium), so this measures the coordinator",
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
    super::emit(&json, args.json.as_deref())
}

struct Measured {
    start: Snapshot,
    end: Snapshot,
}

/// Submits the jobs, starts the workers, waits for the search phase and the warm-up, and
/// measures the window.
async fn measure(
    args: &FarmBenchArgs,
    params: &[JobParams],
    inputs: Inputs,
    coordinator: &ChildCoordinator,
    recording: Arc<Recording>,
) -> Result<Measured> {
    let target = Target {
        url: coordinator.url.clone(),
        ca_pem: None,
        token: None,
    };
    let mut client = jobs::client(&target).await?;
    let mut ids = Vec::new();
    for p in params {
        ids.push(jobs::submit(&mut client, p, inputs.clone()).await?);
    }

    let stats = Arc::new(Stats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let engine = Arc::new(CpuEngine::new());
    let mut workers = tokio::task::JoinSet::new();
    for i in 0..args.workers {
        workers.spawn(replay_worker(
            i,
            target.clone(),
            !args.no_zstd,
            recording.clone(),
            engine.clone(),
            stats.clone(),
            stop.clone(),
        ));
    }

    let result = async {
        // Setup renders (target, calibration pair) first; then the warm-up.
        let setup_until = Instant::now() + Duration::from_secs(300);
        loop {
            check_workers(&mut workers)?;
            let list = client
                .list_jobs(pb::ListJobsRequest {})
                .await
                .map_err(|s| status_error("jobs", s))?
                .into_inner()
                .jobs;
            let ours: Vec<&pb::JobStatus> =
                list.iter().filter(|j| ids.contains(&j.job_id)).collect();
            if let Some(j) = ours.iter().find(|j| {
                matches!(
                    pb::JobState::try_from(j.state),
                    Ok(pb::JobState::Failed | pb::JobState::Cancelled | pb::JobState::Finished)
                )
            }) {
                bail!("job {} ended before the window: {}", j.job_id, j.message);
            }
            if ours.len() == ids.len()
                && ours
                    .iter()
                    .all(|j| j.state == pb::JobState::Searching as i32)
            {
                break;
            }
            ensure!(
                Instant::now() < setup_until,
                "the jobs did not finish their setup renders within 300 s"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;
        check_workers(&mut workers)?;
        let start = snapshot(&mut client, coordinator, &stats, &ids).await?;
        tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
        let end = snapshot(&mut client, coordinator, &stats, &ids).await?;
        check_workers(&mut workers)?;
        Ok(Measured { start, end })
    }
    .await;
    stop.store(true, Ordering::Relaxed);
    workers.abort_all();
    result
}

/// Fails if a worker stopped with an error.
fn check_workers(workers: &mut tokio::task::JoinSet<Result<()>>) -> Result<()> {
    if let Some(done) = workers.try_join_next() {
        match done {
            Ok(Ok(())) => bail!("a replay worker stopped early"),
            Ok(Err(e)) => return Err(e.context("a replay worker failed")),
            Err(e) => bail!("a replay worker panicked: {e}"),
        }
    }
    Ok(())
}

async fn snapshot(
    client: &mut jobs::Client,
    coordinator: &ChildCoordinator,
    stats: &Stats,
    ids: &[String],
) -> Result<Snapshot> {
    let list = client
        .list_jobs(pb::ListJobsRequest {})
        .await
        .map_err(|s| status_error("jobs", s))?
        .into_inner()
        .jobs;
    let renders_done = list
        .iter()
        .filter(|j| ids.contains(&j.job_id))
        .map(|j| j.renders_done)
        .sum();
    let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
    Ok(Snapshot {
        at: Instant::now(),
        load_average: load_average(),
        coordinator_ticks: coordinator.cpu_ticks()?,
        bench_cpu: ProcessTime::now().as_duration(),
        tasks: load(&stats.tasks_accepted),
        renders: load(&stats.renders_accepted),
        bytes: load(&stats.bytes_accepted),
        refused: load(&stats.refused),
        replayed: load(&stats.renders_replayed),
        rendered: load(&stats.renders_rendered),
        renders_done,
        lease_nanos: load(&stats.lease_nanos),
        leases: load(&stats.leases),
        empty_leases: load(&stats.empty_leases),
        complete_nanos: load(&stats.complete_nanos),
        completes: load(&stats.completes),
    })
}
