//! `scatterfarm demo`, and `reconstruct --data`: a coordinator and a worker in this process,
//! talking real gRPC over loopback, with the coordinator's state in a local folder — the farm
//! on one machine. Interrupted (Ctrl-C), the same command resumes where it stood.

use super::jobs::{self, client};
use crate::engines::EngineArgs;
use anyhow::{bail, Context, Result};
use clap::Args;
use scatterfarm_coordinator::scheduler::Settings;
use scatterfarm_coordinator::server::{self, ServerConfig};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::options::SearchMode;
use scatterfarm_job::report::Report;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_proto::channel::Endpoint;
use scatterfarm_worker::{self as agent, AgentConfig};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, Clone, Args)]
pub struct DemoArgs {
    /// The built-in scene (or scene file) to reconstruct. `demo8` (8×8) runs the fast search
    /// at a small budget (under a minute); any other runs the likelihood search with
    /// differential screening at 32 positions × 5 directions and 200 000 target photons per
    /// source (`fig7c`: a few minutes on 2 CPU cores).
    #[arg(long, default_value = "fig7c")]
    pub scene: String,
    /// The coordinator's data folder (run again with the same folder to resume).
    #[arg(long, default_value = "scatterfarm-demo/data")]
    pub data: PathBuf,
    /// Where the result images and report go.
    #[arg(long, default_value = "scatterfarm-demo/result")]
    pub out: PathBuf,
    #[command(flatten)]
    pub engine: EngineArgs,
    /// Serve the status page and metrics on this address (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    pub http: SocketAddr,
}

/// The demo's job for `scene`.
///
/// - `demo8`: the 8×8 built-in scene with the fast search, at a budget two CPU cores finish in
///   under a minute and at which it finds the truth (seed 1: every pixel; 8 iterations and 2
///   permutations, the paper search's demo budget, leave it at 93.8 %).
/// - any other scene: the likelihood search with its defaults, which are the quality bench's
///   `likelihood-differential-direct8` (`tests/bench/searches.sh`), at the bench's geometry,
///   32 positions × 5 directions and 200 000 target photons per source. On fig7c (16×16, a
///   transmissive background) it finds every pixel (`tests/bench/quality`). Its coarse stage is
///   the likelihood search's `auto`: every level on fig7c, whose one-material map does not
///   scatter; level 0 alone on a scattering background such as fig7a's.
pub fn demo_params(scene: &str) -> JobSpec {
    if scene == "demo8" {
        return JobSpec {
            scene: Some("demo8".into()),
            permutations: 3,
            iterations: 32,
            search: SearchMode::Fast,
            name: Some("demo".into()),
            ..JobSpec::default()
        };
    }
    JobSpec {
        scene: Some(scene.into()),
        permutations: 1,
        iterations: 8,
        photons_per_iteration: 512,
        positions: Some(32),
        directions: Some(5),
        target_photons: Some(200_000),
        search: SearchMode::Likelihood,
        name: Some(format!("demo {scene}")),
        ..JobSpec::default()
    }
}

/// Finds a stored job with the same parameters and input files.
fn existing_job(
    farm: &scatterfarm_coordinator::service::Farm,
    params: &JobSpec,
    inputs: &Inputs,
) -> Option<String> {
    let core = farm.scheduler();
    core.jobs
        .values()
        .filter(|j| j.record.params == *params)
        .find(|j| {
            j.record.files.len() == inputs.files.len()
                && inputs.files.iter().all(|(name, bytes)| {
                    core.store()
                        .blob(&j.id, &format!("input/{name}"))
                        .ok()
                        .flatten()
                        .as_deref()
                        == Some(bytes.as_slice())
                })
        })
        .map(|j| j.id.clone())
}

/// Runs `params` on an embedded coordinator (data in `data`) and worker, and writes the
/// outputs into `out`. A job with the same parameters in `data` is resumed, not restarted.
pub fn run_embedded(
    params: &JobSpec,
    engine: &EngineArgs,
    data: &Path,
    out: &Path,
    quiet: bool,
    http: Option<SocketAddr>,
) -> Result<Report> {
    let inputs = Inputs::gather(params, Path::new("."))?;
    let plan = scatterfarm_job::plan::Plan::resolve(params, &inputs)?;
    // The job's differential renders go only to engines that render them.
    let engine: Arc<dyn scatterfarm_model::Engine> = Arc::from(engine.open_for(&plan)?);
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?
        .block_on(async {
            // `stop` ends the worker and the coordinator: on Ctrl-C/SIGTERM, or when the job ends.
            let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
            let stop_tx = Arc::new(stop_tx);
            let interrupted = Arc::new(std::sync::atomic::AtomicBool::new(false));
            {
                let (stop_tx, interrupted) = (stop_tx.clone(), interrupted.clone());
                tokio::spawn(async move {
                    server::termination().await;
                    interrupted.store(true, std::sync::atomic::Ordering::SeqCst);
                    let _ = stop_tx.send(true);
                });
            }
            let until_stop = server::stopped;
            let config = ServerConfig {
                listen: "127.0.0.1:0".parse()?,
                data: data.to_path_buf(),
                token: None,
                tls: None,
                settings: Settings::default(),
                drain_timeout: Duration::from_secs(30),
            };
            let (running, serving) = server::start(config, until_stop(stop_rx.clone())).await?;
            let serving = tokio::spawn(serving);
            if let Some(addr) = http {
                let (bound, web) =
                    scatterfarm_coordinator::http::start(addr, running.farm.clone(), None, None, until_stop(stop_rx.clone()))
                        .await?;
                eprintln!("status page: http://{bound}/");
                tokio::spawn(web);
            }
            let endpoint = Endpoint {
                url: format!("http://{}", running.address),
                ca_pem: None,
                token: None,
            };
            let agent = tokio::spawn(agent::run(
                AgentConfig {
                    endpoint: endpoint.clone(),
                    name: Some("embedded".into()),
                    photons_per_second: None,
                    max_tasks: None,
                },
                engine,
                until_stop(stop_rx.clone()),
            ));
            let mut c = client(&endpoint).await?;
            let id = match existing_job(&running.farm, params, &inputs) {
                Some(id) => {
                    tracing::info!("resuming job {id} from {}", data.display());
                    id
                }
                None => jobs::submit(&mut c, params, inputs).await?,
            };
            let outcome = async {
                let status = jobs::follow(&mut c, &id, quiet, Some(stop_rx.clone())).await?;
                if status.state != scatterfarm_proto::v1::JobState::Finished as i32 {
                    bail!("job {id} did not finish: {}", status.message);
                }
                jobs::fetch_result(&mut c, &id, out).await?;
                let text = std::fs::read(out.join("report.json"))?;
                Ok::<Report, anyhow::Error>(serde_json::from_slice(&text)?)
            }
            .await;
            // Stop the worker and the coordinator: the worker returns the task in hand, the
            // coordinator drains and flushes its store.
            let _ = stop_tx.send(true);
            match tokio::time::timeout(Duration::from_secs(60), agent).await {
                Ok(Ok(Err(e))) => tracing::warn!("the embedded worker: {e}"),
                Ok(Err(e)) => tracing::warn!("the embedded worker: {e}"),
                Err(_) => tracing::warn!("the embedded worker did not stop in time"),
                Ok(Ok(Ok(_))) => {}
            }
            match tokio::time::timeout(Duration::from_secs(60), serving).await {
                Ok(Ok(Err(e))) => tracing::warn!("the embedded coordinator: {e:#}"),
                Ok(Err(e)) => tracing::warn!("the embedded coordinator: {e}"),
                Err(_) => tracing::warn!("the embedded coordinator did not stop in time"),
                Ok(Ok(Ok(()))) => {}
            }
            match outcome {
                Err(e) if interrupted.load(std::sync::atomic::Ordering::SeqCst) => Err(e.context(format!(
                    "interrupted: the job's progress is kept in {}; run the same command again to resume",
                    data.display()
                ))),
                other => other,
            }
        })
}

pub fn run(args: DemoArgs) -> Result<()> {
    let params = demo_params(&args.scene);
    let engine = args.engine.clone();
    eprintln!(
        "scatterfarm demo: reconstructing `{}` with the {} search, a coordinator and a worker in this process (state in {})",
        args.scene,
        params.search.name(),
        args.data.display()
    );
    let report = run_embedded(
        &params,
        &engine,
        &args.data,
        &args.out,
        false,
        Some(args.http),
    )?;
    eprintln!(
        "done: similarity {:.4}, pixel accuracy {:.1} %, {} renders on {}.\nThe result is in {}: reconstruction.png (truth | reconstruction | wrong pixels), maps.png, convergence.png (score and accuracy against photons), materials.npy, report.json",
        report.similarity,
        report.pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
        report.renders,
        report.engine,
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_job::plan::Plan;
    use scatterfarm_search::refine::Screen;

    /// The default demo is a 16×16 scene at the bench's geometry, refined by differential
    /// renders; `demo8` keeps its small fast search. Both resolve into plans.
    #[test]
    fn the_demos_resolve_into_the_searches_they_describe() {
        let fig7c = demo_params("fig7c");
        let inputs = Inputs::gather(&fig7c, Path::new(".")).unwrap();
        let plan = Plan::resolve(&fig7c, &inputs).unwrap();
        assert_eq!(plan.search_geometry.grid, 16);
        assert_eq!(plan.search_geometry.sources(), 32 * 5);
        let refine = plan
            .search
            .config()
            .refine
            .clone()
            .expect("a refinement stage");
        assert_eq!(refine.screen, Screen::Differential);
        assert_eq!(
            (refine.photons, refine.confirm_photons, refine.max_sweeps),
            (102_400, 204_800, 24)
        );
        assert_eq!(refine.direct_photons, Some(12_800));
        let demo8 = demo_params("demo8");
        let inputs = Inputs::gather(&demo8, Path::new(".")).unwrap();
        let plan = Plan::resolve(&demo8, &inputs).unwrap();
        assert_eq!(plan.search_geometry.grid, 8);
        assert!(plan.search.config().refine.is_none());
    }
}
