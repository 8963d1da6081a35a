//! The client commands: `submit`, `status`, `watch`, `result`, `cancel`, `delete`, `jobs` and
//! `workers`, each a call (or a stream) of the coordinator's `ClientService`.

use super::connect::ConnectArgs;
use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use scatterfarm_coordinator::status::{duration_text, state_name};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::plan::Plan;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_proto::channel::{Authed, Endpoint};
use scatterfarm_proto::convert::fingerprint_from_proto;
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::client_service_client::ClientServiceClient;
use std::path::{Path, PathBuf};

/// A client of the coordinator's `ClientService`.
pub type Client = ClientServiceClient<Authed>;

/// Connects a client.
pub async fn client(endpoint: &Endpoint) -> Result<Client> {
    Ok(Endpoint::client_client(endpoint.connect().await?))
}

/// Runs `f` on a fresh single-threaded runtime.
fn block_on<T>(f: impl std::future::Future<Output = Result<T>>) -> Result<T> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?
        .block_on(f)
}

/// A gRPC failure as a readable error.
pub fn status_error(what: &str, s: tonic::Status) -> anyhow::Error {
    let hint = if s.code() == tonic::Code::Unknown && s.message().contains("transport error") {
        " (if the coordinator serves TLS, use an https:// URL, with --tls-ca for a private CA)"
    } else {
        ""
    };
    // The transport's own causes (an h2 GOAWAY, a reset, a keep-alive timeout) say more than
    // "http2 error".
    let mut causes = String::new();
    let mut source = std::error::Error::source(&s);
    while let Some(e) = source {
        causes.push_str(&format!(": {e}"));
        source = e.source();
    }
    anyhow::anyhow!("{what}: {}{causes} ({:?}){hint}", s.message(), s.code())
}

#[derive(Debug, Clone, Args)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The job file: TOML with the keys of `scatterfarm reconstruct`'s flags (dashes as
    /// underscores), e.g. `scene = "fig7a"`; relative paths are relative to the job file.
    pub job: PathBuf,
}

/// Reads a job file and the files it names, and checks the job as the coordinator will.
pub fn read_job(path: &Path) -> Result<(JobSpec, Inputs)> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the job file {}", path.display()))?;
    let params = JobSpec::from_toml(&text, path)?;
    let base = path.parent().unwrap_or(Path::new("."));
    let inputs =
        Inputs::gather(&params, base).with_context(|| format!("job file {}", path.display()))?;
    Plan::resolve(&params, &inputs).with_context(|| format!("job file {}", path.display()))?;
    Ok((params, inputs))
}

/// Sends a job; returns its id.
pub async fn submit(client: &mut Client, params: &JobSpec, inputs: Inputs) -> Result<String> {
    let request = pb::SubmitRequest {
        job_toml: params.to_toml()?,
        files: inputs
            .files
            .into_iter()
            .map(|(k, v)| (k, v.into()))
            .collect(),
    };
    let id = client
        .submit(request)
        .await
        .map_err(|s| status_error("the coordinator refused the job", s))?
        .into_inner()
        .job_id;
    Ok(id)
}

pub fn run_submit(args: SubmitArgs) -> Result<()> {
    let (params, inputs) = read_job(&args.job)?;
    let endpoint = args.connect.endpoint()?;
    let id = block_on(async {
        let mut c = client(&endpoint).await?;
        submit(&mut c, &params, inputs).await
    })?;
    println!("{id}");
    Ok(())
}

#[derive(Debug, Clone, Args)]
pub struct JobArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The job id (as `submit` printed it; see `scatterfarm jobs`).
    pub id: String,
}

#[derive(Debug, Clone, Args)]
pub struct StatusArgs {
    #[command(flatten)]
    pub job: JobArgs,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// A job status as JSON.
pub fn status_json(s: &pb::JobStatus) -> serde_json::Value {
    serde_json::json!({
        "job_id": s.job_id,
        "name": s.name,
        "state": state_name(s.state),
        "message": s.message,
        "engine": s.engine,
        "level": s.level,
        "levels": s.levels,
        "permutation": s.permutation,
        "permutations": s.permutations,
        "region": s.region,
        "regions": s.regions,
        "refining": s.refining,
        "sweep": s.sweep,
        "sweeps": s.sweeps,
        "renders_done": s.renders_done,
        "renders_total": s.renders_total,
        "best_similarity": finite(s.best_similarity),
        "photons": s.photons,
        "photons_per_second": s.photons_per_second,
        "eta_seconds": (s.eta_seconds >= 0.0).then_some(s.eta_seconds),
        "workers_busy": s.workers_busy,
        "submitted_unix_seconds": s.submitted_unix_seconds,
    })
}

/// The search's stage (level, permutation and region, or refinement sweep), best similarity,
/// rate, ETA and workers busy, and what the job waits for.
fn progress_text(s: &pb::JobStatus) -> String {
    let mut text = format!(
        "{} · best {} · {:.2} M photons/s · ETA {} · {} workers busy",
        scatterfarm_coordinator::status::progress_of(s).stage(),
        finite(s.best_similarity)
            .map(|v| format!("{v:.4}"))
            .unwrap_or_else(|| "-".into()),
        s.photons_per_second / 1e6,
        duration_text(s.eta_seconds),
        s.workers_busy
    );
    if !s.message.is_empty() && s.message != state_name(s.state) {
        text.push_str(&format!(" · {}", s.message));
    }
    text
}

/// One line describing a job.
pub fn status_line(s: &pb::JobStatus) -> String {
    format!(
        "{} {} · {}/{} renders · {}",
        s.job_id,
        state_name(s.state),
        s.renders_done,
        s.renders_total,
        progress_text(s)
    )
}

pub fn run_status(args: StatusArgs) -> Result<()> {
    let endpoint = args.job.connect.endpoint()?;
    let s = block_on(async {
        let mut c = client(&endpoint).await?;
        Ok(c.status(pb::JobRef {
            job_id: args.job.id.clone(),
        })
        .await
        .map_err(|s| status_error("status", s))?
        .into_inner())
    })?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&status_json(&s))?);
    } else {
        println!("{}", status_line(&s));
    }
    Ok(())
}

/// Follows a job with a progress bar until it ends (or `stop` fires); returns its last status.
pub async fn follow(
    client: &mut Client,
    id: &str,
    quiet: bool,
    mut stop: Option<tokio::sync::watch::Receiver<bool>>,
) -> Result<pb::JobStatus> {
    let mut stream = client
        .watch(pb::JobRef {
            job_id: id.to_string(),
        })
        .await
        .map_err(|s| status_error("watch", s))?
        .into_inner();
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(1)
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} renders · {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let mut last = None;
    loop {
        let next = match stop.as_mut() {
            Some(rx) => tokio::select! {
                m = stream.message() => m,
                _ = rx.wait_for(|&s| s) => {
                    bar.abandon();
                    bail!("interrupted");
                }
            },
            None => stream.message().await,
        };
        match next.map_err(|s| status_error("watch", s))? {
            Some(s) => {
                bar.set_length(s.renders_total.max(1));
                bar.set_position(s.renders_done);
                bar.set_message(format!("{} · {}", state_name(s.state), progress_text(&s)));
                last = Some(s);
            }
            None => break,
        }
    }
    bar.finish_and_clear();
    last.context("the coordinator sent no status")
}

pub fn run_watch(args: JobArgs) -> Result<()> {
    let endpoint = args.connect.endpoint()?;
    let s = block_on(async {
        let mut c = client(&endpoint).await?;
        follow(&mut c, &args.id, false, None).await
    })?;
    eprintln!("{}", status_line(&s));
    if s.state == pb::JobState::Failed as i32 {
        bail!("job {} failed: {}", s.job_id, s.message);
    }
    if s.state == pb::JobState::Damaged as i32 {
        bail!("job {} is {}", s.job_id, s.message);
    }
    Ok(())
}

#[derive(Debug, Clone, Args)]
pub struct ResultArgs {
    #[command(flatten)]
    pub job: JobArgs,
    /// Write report.json, materials.npy, materials.json, reconstruction.png, maps.png and convergence.png here.
    #[arg(long)]
    pub out: PathBuf,
}

/// Fetches a job's outputs into `out` (each file written atomically); returns whether they are
/// partial (the job has not finished) and the job's status.
pub async fn fetch_result(
    client: &mut Client,
    id: &str,
    out: &Path,
) -> Result<(bool, pb::JobStatus)> {
    let r = client
        .result(pb::JobRef {
            job_id: id.to_string(),
        })
        .await
        .map_err(|s| status_error("result", s))?
        .into_inner();
    for (name, bytes) in &r.files {
        let safe = Path::new(name)
            .file_name()
            .filter(|f| f.to_string_lossy() == name.as_str())
            .with_context(|| format!("the coordinator sent a file with a bad name {name:?}"))?;
        scatterfarm_job::observation::write_atomically(&out.join(safe), |w| {
            w.write_all(bytes)?;
            Ok(())
        })?;
    }
    Ok((r.partial, r.status.unwrap_or_default()))
}

pub fn run_result(args: ResultArgs) -> Result<()> {
    let endpoint = args.job.connect.endpoint()?;
    let (partial, status) = block_on(async {
        let mut c = client(&endpoint).await?;
        fetch_result(&mut c, &args.job.id, &args.out).await
    })?;
    if partial {
        eprintln!(
            "job {} is {}: wrote its current best (partial) to {}",
            args.job.id,
            state_name(status.state),
            args.out.display()
        );
    } else {
        eprintln!(
            "wrote report.json, materials.npy, materials.json, reconstruction.png, maps.png and convergence.png to {}",
            args.out.display()
        );
    }
    Ok(())
}

pub fn run_cancel(args: JobArgs) -> Result<()> {
    let endpoint = args.connect.endpoint()?;
    block_on(async {
        let mut c = client(&endpoint).await?;
        c.cancel(pb::JobRef {
            job_id: args.id.clone(),
        })
        .await
        .map_err(|s| status_error("cancel", s))?;
        Ok(())
    })?;
    eprintln!("job {} cancelled", args.id);
    Ok(())
}

pub fn run_delete(args: JobArgs) -> Result<()> {
    let endpoint = args.connect.endpoint()?;
    block_on(async {
        let mut c = client(&endpoint).await?;
        c.delete(pb::JobRef {
            job_id: args.id.clone(),
        })
        .await
        .map_err(|s| status_error("delete", s))?;
        Ok(())
    })?;
    eprintln!("job {} deleted", args.id);
    Ok(())
}

#[derive(Debug, Clone, Args)]
pub struct ListArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run_jobs(args: ListArgs) -> Result<()> {
    let endpoint = args.connect.endpoint()?;
    let jobs = block_on(async {
        let mut c = client(&endpoint).await?;
        Ok(c.list_jobs(pb::ListJobsRequest {})
            .await
            .map_err(|s| status_error("jobs", s))?
            .into_inner()
            .jobs)
    })?;
    if args.json {
        let v: Vec<_> = jobs.iter().map(status_json).collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else if jobs.is_empty() {
        eprintln!("no jobs");
    } else {
        for j in &jobs {
            println!("{}  {}", status_line(j), j.name);
        }
    }
    Ok(())
}

pub fn run_workers(args: ListArgs) -> Result<()> {
    let endpoint = args.connect.endpoint()?;
    let workers = block_on(async {
        let mut c = client(&endpoint).await?;
        Ok(c.list_workers(pb::ListWorkersRequest {})
            .await
            .map_err(|s| status_error("workers", s))?
            .into_inner()
            .workers)
    })?;
    let engine = |w: &pb::WorkerStatus| {
        w.fingerprint
            .as_ref()
            .map(|f| fingerprint_from_proto(f.clone()).key())
            .unwrap_or_default()
    };
    if args.json {
        let v: Vec<_> = workers
            .iter()
            .map(|w| {
                serde_json::json!({
                    "worker_id": w.worker_id,
                    "name": w.name,
                    "engine": engine(w),
                    "photons_per_second": w.photons_per_second,
                    "tasks_leased": w.tasks_leased,
                    "tasks_completed": w.tasks_completed,
                    "last_heartbeat_seconds_ago": w.last_heartbeat_seconds_ago,
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else if workers.is_empty() {
        eprintln!("no workers");
    } else {
        for w in &workers {
            println!(
                "{}  {}  {}  {:.2} M photons/s  {} leased  {} done  heartbeat {:.1} s ago",
                w.worker_id,
                w.name,
                engine(w),
                w.photons_per_second / 1e6,
                w.tasks_leased,
                w.tasks_completed,
                w.last_heartbeat_seconds_ago
            );
        }
    }
    Ok(())
}
