//! Replay workers: tokio tasks in this process speaking the ordinary worker protocol, answering
//! every task with count matrices recorded once at start (a CPU render where a task does not fit
//! the recording). A scored task is answered with the recorded renders' scores against the
//! job's target, scored once per job and photon count; like real workers they keep the
//! targets they were sent and name them when they lease.

use crate::commands::jobs::status_error;
use anyhow::{Context, Result};
use scatterfarm_engines::CpuEngine;
use scatterfarm_job::plan::Plan;
use scatterfarm_model::likelihood::deviance;
use scatterfarm_model::{CountMatrix, Engine, Geometry, PhotonRange, RenderBatch, RenderItem};
use scatterfarm_proto::channel::{Authed, Endpoint};
use scatterfarm_proto::convert::{counts_to_proto, decode_task, geometry_from_proto};
use scatterfarm_proto::differential::target_from_proto;
use scatterfarm_proto::scored::render_scores_to_proto;
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::worker_service_client::WorkerServiceClient;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tonic::codec::CompressionEncoding;

/// Announced by replay workers, so every task is one whole render group.
const REPLAY_PHOTONS_PER_SECOND: f64 = 1e15;
/// Distinct recorded matrices (different seeds), so the calibration pair differs (ε > 0) and
/// search renders differ from the target, as they would for real.
const RECORDED: u64 = 2;

/// Counts recorded once and replayed as every result of the same shape.
pub(super) struct Recording {
    pub(super) sources: usize,
    pub(super) bins: usize,
    pub(super) photons: u32,
    /// Encoded once; cloning shares the bytes.
    pub(super) matrices: Vec<pb::CountMatrix>,
    /// The same counts, for scoring against a job's target.
    pub(super) counts: Vec<CountMatrix>,
    pub(super) scatter_events: Vec<u64>,
}

/// Renders the recorded matrices: the calibration material, homogeneous, over the search's
/// boundary sampling.
pub(super) fn record(plan: &Plan, photons: u32) -> Result<Recording> {
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
        counts: out.iter().map(|o| o.counts.clone()).collect(),
        scatter_events: out.iter().map(|o| o.scatter_events).collect(),
    })
}

/// Which recorded render answers assignment `i` of `task`.
fn replayed(task: &pb::Task, i: u64) -> usize {
    ((task.task_id + i) % RECORDED) as usize
}

/// What the replay workers did, summed over all of them.
#[derive(Default)]
pub(super) struct Stats {
    pub(super) tasks_accepted: AtomicU64,
    pub(super) renders_accepted: AtomicU64,
    pub(super) renders_replayed: AtomicU64,
    pub(super) renders_rendered: AtomicU64,
    /// Renders answered with their recorded scores (scored tasks).
    pub(super) renders_scored: AtomicU64,
    pub(super) bytes_accepted: AtomicU64,
    pub(super) refused: AtomicU64,
    pub(super) empty_leases: AtomicU64,
    pub(super) lease_nanos: AtomicU64,
    pub(super) leases: AtomicU64,
    pub(super) complete_nanos: AtomicU64,
    pub(super) completes: AtomicU64,
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
        Endpoint::worker_client(channel)
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
                let k = replayed(task, i);
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

/// How a replay worker speaks the protocol.
#[derive(Debug, Clone, Copy)]
pub(super) struct Speaks {
    /// It compresses its results with zstd (as real workers do).
    pub(super) zstd: bool,
    /// It says it scores renders, and is leased scored renders.
    pub(super) scores_renders: bool,
}

/// What a replay worker keeps of the jobs whose scored tasks it answered: the targets it was
/// sent, and the recorded renders' scores against them per photon count.
#[derive(Default)]
struct Targets {
    targets: HashMap<String, scatterfarm_model::likelihood::Target>,
    scores: HashMap<(String, u32), Vec<pb::RenderScore>>,
}

impl Targets {
    /// The jobs whose targets it holds, as a lease names them.
    fn jobs(&self) -> Vec<String> {
        self.targets.keys().cloned().collect()
    }

    /// The scores of a scored task: the recorded render each assignment replays, scored once
    /// per job and photon count against the target the task carries or the one kept.
    fn scores(&mut self, task: &pb::Task, recording: &Recording) -> Result<Vec<pb::RenderScore>> {
        let observations = recording.sources * recording.bins;
        if let Some(t) = task.scored.as_ref().and_then(|s| s.target.as_ref()) {
            let target = target_from_proto(t, observations)?;
            self.targets.insert(task.job_id.clone(), target);
            self.scores.retain(|(job, _), _| *job != task.job_id);
        }
        let key = (task.job_id.clone(), task.photon_count);
        if !self.scores.contains_key(&key) {
            let target = self.targets.get(&task.job_id).with_context(|| {
                format!("a scored task of job {} without its target", task.job_id)
            })?;
            let scores = recording
                .counts
                .iter()
                .map(|c| deviance(target, c, u64::from(task.photon_count)))
                .collect::<Result<Vec<_>, _>>()
                .context("cannot score the recorded render")?;
            self.scores
                .insert(key.clone(), render_scores_to_proto(&scores));
        }
        let recorded = &self.scores[&key];
        Ok((0..task.assignments.len() as u64)
            .map(|i| recorded[replayed(task, i)].clone())
            .collect())
    }
}

/// One replay worker: registers (saying whether it scores renders), heartbeats, leases and
/// answers until `stop`.
pub(super) async fn replay_worker(
    index: usize,
    endpoint: Endpoint,
    how: Speaks,
    recording: Arc<Recording>,
    engine: Arc<CpuEngine>,
    stats: Arc<Stats>,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    let channel = endpoint.connect().await?;
    let mut client = worker_client(channel, how.zstd);
    let fingerprint = engine.fingerprint().tagged("replay");
    let registered = client
        .register(pb::RegisterRequest {
            renders_differentially: false,
            scores_renders: how.scores_renders,
            protocol: Some(pb::PROTOCOL),
            fingerprint: Some(scatterfarm_proto::convert::fingerprint_to_proto(
                &fingerprint,
            )),
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
    let mut targets = Targets::default();
    while !stop.load(Ordering::Relaxed) {
        let t0 = Instant::now();
        let response = client
            .lease(pb::LeaseRequest {
                cached_targets: targets.jobs(),
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
        let (counts, scatter_events, render_scores) = if task.scored.is_some() {
            let scores = targets.scores(&task, &recording)?;
            stats
                .renders_scored
                .fetch_add(scores.len() as u64, Ordering::Relaxed);
            let events = (0..task.assignments.len() as u64)
                .map(|i| recording.scatter_events[replayed(&task, i)])
                .sum();
            (Vec::new(), events, scores)
        } else {
            let (counts, events) = answer(&task, &recording, &engine, &stats).await?;
            (counts, events, Vec::new())
        };
        let renders = (counts.len() + render_scores.len()) as u64;
        let bytes: u64 = counts
            .iter()
            .map(|c| c.counts_le_u32.len() as u64)
            .sum::<u64>()
            + render_scores
                .iter()
                .map(|s| 8 * (1 + s.blocks.len() as u64))
                .sum::<u64>();
        let t1 = Instant::now();
        let outcome = client
            .complete(pb::CompleteRequest {
                change_scores: Vec::new(),
                render_scores,
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
