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
//! for fewer photons than were recorded, is rendered for real by the CPU engine. With
//! `--search likelihood` the search's plain renders are scored tasks, answered with the recorded
//! renders' scores against the job's target instead of counts.
//!
//! After every job is searching and a warm-up, counters are read at the start and end of a
//! measured window: renders in results the coordinator accepted, the jobs' `renders_done`,
//! and the coordinator's utime + stime.
//!
//! - `coordinator`: the coordinator child process, its CPU time and memory from `/proc`;
//! - `replay`: the recording and the replay workers;
//! - `report`: the window's figures, printed and as JSON.

mod coordinator;
mod replay;
mod report;

use crate::commands::jobs::{self, status_error};
use anyhow::{bail, ensure, Context, Result};
use clap::Args;
use coordinator::{clock_ticks_per_second, load_average, ChildCoordinator};
use cpu_time::ProcessTime;
use replay::{record, replay_worker, Recording, Speaks, Stats};
use report::{Measured, Snapshot};
use scatterfarm_engines::CpuEngine;
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::plan::Plan;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_proto::channel::Endpoint;
use scatterfarm_proto::v1 as pb;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

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
    /// The jobs' search. With `likelihood` the workers (which say they score renders, as this
    /// release's do) are leased scored renders and answer each with the recorded render's
    /// score against the job's target, not its counts (`docs/model.md`, "Scored where the
    /// counts are"); with the others every render comes back as counts.
    #[arg(
        long,
        default_value_t = scatterfarm_job::options::SearchMode::Fast,
        value_parser = crate::args::choice::choice::<scatterfarm_job::options::SearchMode>()
    )]
    pub search: scatterfarm_job::options::SearchMode,
    /// Replay workers say they do not score renders (as workers before protocol 1.3), so a
    /// likelihood job's renders come back as counts and the coordinator scores them: the
    /// baseline of `--search likelihood`.
    #[arg(long)]
    pub no_worker_scoring: bool,
}

fn job_params(args: &FarmBenchArgs, index: usize) -> JobSpec {
    JobSpec {
        scene: Some(args.scene.clone()),
        permutations: args.permutations,
        iterations: 1,
        photons_per_iteration: args.photons,
        grid: Some(args.grid),
        positions: args.positions,
        directions: args.directions,
        seed: 1 + index as u64,
        // Every render at the full --photons, so the recording can answer it: the default
        // search's per-level share (a tenth) and racing's first stage (a quarter of that)
        // would ask for fewer photons than were recorded, and be rendered for real.
        level_photons: Some(vec![args.photons]),
        race_share: Some(1.0),
        rescore_photons: Some(args.photons),
        name: Some(format!("bench-farm-{index}")),
        search: args.search,
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

    let params: Vec<JobSpec> = (0..args.jobs).map(|i| job_params(&args, i)).collect();
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
            let tail = coordinator.log_tail();
            let log = if tail.trim().is_empty() {
                "the coordinator's log is empty".to_string()
            } else {
                format!("the coordinator's log ends:\n{tail}")
            };
            return Err(e.context(format!("bench farm failed; {log}")));
        }
    };
    runtime.shutdown_timeout(Duration::from_secs(1));
    drop(coordinator);
    report::report(
        &args,
        geometry,
        &recording,
        &outcome,
        (clk_tck, clk_source),
        peak_rss,
    )
}

/// Submits the jobs, starts the workers, waits for the search phase and the warm-up, and
/// measures the window.
async fn measure(
    args: &FarmBenchArgs,
    params: &[JobSpec],
    inputs: Inputs,
    coordinator: &ChildCoordinator,
    recording: Arc<Recording>,
) -> Result<Measured> {
    let endpoint = Endpoint {
        url: coordinator.url.clone(),
        ca_pem: None,
        token: None,
    };
    let mut client = jobs::client(&endpoint).await?;
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
            endpoint.clone(),
            Speaks {
                zstd: !args.no_zstd,
                scores_renders: !args.no_worker_scoring,
            },
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
        scored: load(&stats.renders_scored),
        renders_done,
        lease_nanos: load(&stats.lease_nanos),
        leases: load(&stats.leases),
        empty_leases: load(&stats.empty_leases),
        complete_nanos: load(&stats.complete_nanos),
        completes: load(&stats.completes),
    })
}
