//! The coordinator's web face (`--http ADDR`): `/metrics` for Prometheus, a status page at `/`
//! (jobs with progress and ETA, workers with engine, throughput and last heartbeat, each job's
//! current best map and its convergence curve), `/jobs/{id}/map.png`, the map itself, and
//! `/jobs/{id}/convergence.svg`, the score and accuracy at the end of every level and sweep
//! against the photons spent ([`scatterfarm_job::convergence_plot`]).
//!
//! Everything is read from one snapshot of the [`Scheduler`] taken under its lock; pages, metrics
//! and maps are built after the lock is released, and a job's map is encoded once per state of
//! its progress (cached by its renders done). With a token, every path needs it
//! ([`crate::http_auth`]). With [`WebTls`] (the coordinator's `--tls-cert`/`--tls-key`) it
//! serves HTTPS only ([`crate::http_tls`]).

use super::scheduler::Scheduler;
use super::service::Farm;
use super::status::{all_statuses, duration_text, state_name};
use crate::http_auth::{self, LoginSettings, WebToken};
use crate::http_tls::{TlsListener, WebTls};
use anyhow::{Context, Result};
use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::middleware;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use scatterfarm_job::picture;
use scatterfarm_proto::v1 as pb;
use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Cumulative counters sampled once a second, for rates over the last ten seconds.
#[derive(Default)]
struct Rates {
    samples: VecDeque<(Instant, u64, u64)>,
}

impl Rates {
    fn push(&mut self, renders: u64, photons: u64) {
        let now = Instant::now();
        self.samples.push_back((now, renders, photons));
        while self
            .samples
            .front()
            .is_some_and(|s| now.duration_since(s.0) > Duration::from_secs(10))
        {
            self.samples.pop_front();
        }
    }

    /// (renders per second, photons per second).
    fn per_second(&self) -> (f64, f64) {
        match (self.samples.front(), self.samples.back()) {
            (Some(a), Some(b)) if b.0 > a.0 => {
                let dt = b.0.duration_since(a.0).as_secs_f64();
                ((b.1 - a.1) as f64 / dt, (b.2 - a.2) as f64 / dt)
            }
            _ => (0.0, 0.0),
        }
    }
}

/// Encoded maps by job: the renders done when encoded, and the PNG.
type MapCache = HashMap<String, (u64, Arc<Vec<u8>>)>;

#[derive(Clone)]
struct Web {
    farm: Arc<Farm>,
    rates: Arc<Mutex<Rates>>,
    maps: Arc<Mutex<MapCache>>,
}

/// What a page or a scrape shows, copied out of the scheduler.
struct Snapshot {
    jobs: Vec<pb::JobStatus>,
    workers: Vec<WorkerRow>,
    tasks_leased: usize,
    counters: super::scheduler::Counters,
}

struct WorkerRow {
    id: String,
    name: String,
    engine: String,
    adapter: String,
    photons_per_second: f64,
    leased: usize,
    completed: u64,
    heartbeat_ago: f64,
}

fn snapshot(scheduler: &Scheduler) -> Snapshot {
    let now = Instant::now();
    let mut workers: Vec<WorkerRow> = scheduler
        .workers
        .values()
        .map(|w| WorkerRow {
            id: w.id.clone(),
            name: w.name.clone(),
            engine: w.fingerprint_key.clone(),
            adapter: w.fingerprint.adapter.clone(),
            photons_per_second: w.photons_per_second,
            leased: scheduler
                .leases
                .values()
                .filter(|l| l.worker == w.id)
                .count(),
            completed: w.tasks_completed,
            heartbeat_ago: scheduler
                .liveness
                .last_seen(&w.id)
                .map_or(f64::INFINITY, |t| {
                    now.saturating_duration_since(t).as_secs_f64()
                }),
        })
        .collect();
    workers.sort_by(|a, b| a.id.cmp(&b.id));
    Snapshot {
        jobs: all_statuses(scheduler),
        workers,
        tasks_leased: scheduler.leases.len(),
        counters: scheduler.counters,
    }
}

type Labels = Vec<(String, String)>;

fn metrics_text(s: &Snapshot, rates: (f64, f64)) -> Result<String> {
    let mut reg = Registry::with_prefix("scatterfarm");
    let jobs = Family::<Labels, Gauge>::default();
    reg.register("jobs", "Jobs by state", jobs.clone());
    for state in [
        "preparing",
        "searching",
        "paused",
        "finished",
        "cancelled",
        "failed",
        "damaged",
    ] {
        let n = s
            .jobs
            .iter()
            .filter(|j| state_name(j.state) == state)
            .count();
        jobs.get_or_create(&vec![("state".into(), state.into())])
            .set(n as i64);
    }
    let gauge = |reg: &mut Registry, name: &str, help: &str, v: f64| {
        let g = Gauge::<f64, AtomicU64>::default();
        g.set(v);
        reg.register(name, help, g);
    };
    let counter = |reg: &mut Registry, name: &str, help: &str, v: u64| {
        let c = Counter::<u64>::default();
        c.inc_by(v);
        reg.register(name, help, c);
    };
    gauge(
        &mut reg,
        "tasks_leased",
        "Tasks leased to workers now",
        s.tasks_leased as f64,
    );
    gauge(
        &mut reg,
        "workers",
        "Registered workers",
        s.workers.len() as f64,
    );
    let busy = s.workers.iter().filter(|w| w.leased > 0).count();
    gauge(
        &mut reg,
        "worker_utilisation",
        "Share of registered workers holding a task",
        if s.workers.is_empty() {
            0.0
        } else {
            busy as f64 / s.workers.len() as f64
        },
    );
    gauge(
        &mut reg,
        "renders_per_second",
        "Renders completed per second over the last 10 s",
        rates.0,
    );
    gauge(
        &mut reg,
        "photons_per_second",
        "Photons rendered per second over the last 10 s",
        rates.1,
    );
    counter(
        &mut reg,
        "renders",
        "Renders completed since the coordinator started",
        s.counters.renders_completed,
    );
    counter(
        &mut reg,
        "renders_scored_on_workers",
        "Renders scored by the workers that rendered them (their scores sent, not their counts)",
        s.counters.renders_scored_on_workers,
    );
    counter(
        &mut reg,
        "photons",
        "Photons in accepted results since the coordinator started",
        s.counters.photons,
    );
    counter(
        &mut reg,
        "lease_expiries",
        "Leases handed out again after a deadline or lost heartbeats",
        s.counters.leases_expired,
    );
    counter(
        &mut reg,
        "results_refused",
        "Results refused (stale, malformed or impossible)",
        s.counters.results_refused,
    );
    counter(
        &mut reg,
        "results_accepted",
        "Results accepted",
        s.counters.results_accepted,
    );
    let progress = Family::<Labels, Gauge<f64, AtomicU64>>::default();
    reg.register(
        "job_progress",
        "Share of a job's renders done",
        progress.clone(),
    );
    let renders_done = Family::<Labels, Gauge>::default();
    reg.register(
        "job_renders_done",
        "Renders a job has done",
        renders_done.clone(),
    );
    let renders_total = Family::<Labels, Gauge>::default();
    reg.register(
        "job_renders_total",
        "Renders a job needs in all",
        renders_total.clone(),
    );
    for j in &s.jobs {
        let labels = vec![
            ("job".to_string(), j.job_id.clone()),
            ("state".to_string(), state_name(j.state).to_string()),
        ];
        progress
            .get_or_create(&labels)
            .set(j.renders_done as f64 / j.renders_total.max(1) as f64);
        renders_done
            .get_or_create(&labels)
            .set(j.renders_done as i64);
        renders_total
            .get_or_create(&labels)
            .set(j.renders_total as i64);
    }
    let mut out = String::new();
    encode(&mut out, &reg).context("cannot encode the metrics")?;
    Ok(out)
}

async fn metrics(State(web): State<Web>) -> Response {
    let Ok(snap) = web.farm.locked(|s| snapshot(s)).await else {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            "the coordinator is shutting down",
        )
            .into_response();
    };
    let rates = web
        .rates
        .lock()
        .map(|r| r.per_second())
        .unwrap_or((0.0, 0.0));
    match metrics_text(&snap, rates) {
        Ok(text) => (
            [(
                header::CONTENT_TYPE,
                "application/openmetrics-text; version=1.0.0; charset=utf-8",
            )],
            text,
        )
            .into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("{e:#}")).into_response(),
    }
}

/// Escapes text for HTML.
fn esc(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

fn page(s: &Snapshot, rates: (f64, f64)) -> String {
    let mut h = String::new();
    h.push_str(concat!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>scatterfarm</title>",
        "<meta http-equiv=\"refresh\" content=\"5\">",
        "<style>body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse}",
        "td,th{padding:4px 10px;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}",
        ".bar{width:160px;height:10px;background:#eee}.bar div{height:10px;background:#3a7}",
        "img.map{width:128px;height:128px;image-rendering:pixelated;border:1px solid #999}",
        "img.curve{width:320px;height:170px;border:1px solid #ddd}</style>",
        "</head><body><h1>scatterfarm coordinator</h1>"
    ));
    h.push_str(&format!(
        "<p>{} workers · {} tasks leased · {:.1} renders/s · {:.2} M photons/s · {} lease expiries · {} results refused</p>",
        s.workers.len(),
        s.tasks_leased,
        rates.0,
        rates.1 / 1e6,
        s.counters.leases_expired,
        s.counters.results_refused
    ));
    h.push_str("<h2>Jobs</h2>");
    if s.jobs.is_empty() {
        h.push_str("<p id=\"no-jobs\">No jobs.</p>");
    } else {
        h.push_str("<table id=\"jobs\"><tr><th>job</th><th>name</th><th>state</th><th>progress</th><th>stage</th><th>best similarity</th><th>ETA</th><th>workers busy</th><th>current best</th><th>convergence</th></tr>");
        for j in &s.jobs {
            let share = j.renders_done as f64 / j.renders_total.max(1) as f64;
            let map = if j.best_similarity.is_finite() {
                format!(
                    "<img class=\"map\" alt=\"current best map of {id}\" src=\"/jobs/{id}/map.png\" onload=\"this.dataset.loaded=1\">",
                    id = esc(&j.job_id)
                )
            } else {
                "—".into()
            };
            let curve = if j.best_similarity.is_finite() {
                format!(
                    "<img class=\"curve\" alt=\"convergence of {id}\" src=\"/jobs/{id}/convergence.svg\">",
                    id = esc(&j.job_id)
                )
            } else {
                "—".into()
            };
            h.push_str(&format!(
                "<tr class=\"job\" data-job=\"{id}\"><td>{id}</td><td>{name}</td><td>{state}<br><small>{msg}</small></td>\
                 <td><div class=\"bar\"><div style=\"width:{pct:.1}%\"></div></div>{done}/{total} renders ({pct:.1} %)</td>\
                 <td>{stage}</td><td>{best}</td><td>{eta}</td><td>{busy}</td><td>{map}</td><td>{curve}</td></tr>",
                id = esc(&j.job_id),
                name = esc(&j.name),
                state = state_name(j.state),
                msg = esc(&j.message),
                pct = share * 100.0,
                done = j.renders_done,
                total = j.renders_total,
                stage = esc(&crate::status::progress_of(j).stage()),
                best = if j.best_similarity.is_finite() {
                    format!("{:.4}", j.best_similarity)
                } else {
                    "—".into()
                },
                eta = duration_text(j.eta_seconds),
                busy = j.workers_busy,
            ));
        }
        h.push_str("</table>");
    }
    h.push_str("<h2>Workers</h2>");
    if s.workers.is_empty() {
        h.push_str("<p id=\"no-workers\">No workers.</p>");
    } else {
        h.push_str("<table id=\"workers\"><tr><th>worker</th><th>name</th><th>engine</th><th>adapter</th><th>throughput</th><th>tasks leased</th><th>tasks done</th><th>last heartbeat</th></tr>");
        for w in &s.workers {
            h.push_str(&format!(
                "<tr class=\"worker\"><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2} M photons/s</td><td>{}</td><td>{}</td><td>{:.1} s ago</td></tr>",
                esc(&w.id),
                esc(&w.name),
                esc(&w.engine),
                esc(&w.adapter),
                w.photons_per_second / 1e6,
                w.leased,
                w.completed,
                w.heartbeat_ago
            ));
        }
        h.push_str("</table>");
    }
    h.push_str("</body></html>");
    h
}

async fn index(State(web): State<Web>) -> Html<String> {
    let Ok(snap) = web.farm.locked(|s| snapshot(s)).await else {
        return Html("the coordinator is shutting down".into());
    };
    let rates = web
        .rates
        .lock()
        .map(|r| r.per_second())
        .unwrap_or((0.0, 0.0));
    Html(page(&snap, rates))
}

fn png_response(png: Arc<Vec<u8>>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png.as_ref().clone(),
    )
        .into_response()
}

async fn map_png(State(web): State<Web>, Path(id): Path<String>) -> Response {
    // Under the lock (on a blocking thread) only the job's progress, and its map when the
    // cached picture is not of that progress; a second try (the cache changed meanwhile)
    // always takes the map.
    let cached = |done: Option<u64>| {
        web.maps.lock().ok().and_then(|m| {
            m.get(&id)
                .filter(|(at, _)| done.is_none_or(|d| *at == d))
                .map(|c| (c.0, c.1.clone()))
        })
    };
    let mut picture = None;
    let mut done = 0;
    for cached_at in [cached(None).map(|c| c.0), None] {
        let wanted = id.clone();
        let taken = web
            .farm
            .locked(move |s| {
                let job = s.jobs.get(&wanted)?;
                let search = &job.checkpoint.search;
                let done = search.progress().renders_done;
                if cached_at == Some(done) {
                    return Some((done, None));
                }
                let best = search
                    .result()
                    .map(|r| r.assignment.clone())
                    .or_else(|| search.current_best().map(|b| b.0));
                let picture =
                    best.map(|a| (a, job.plan.config.grid as usize, search.table().clone()));
                Some((done, Some(picture)))
            })
            .await;
        let Ok(Some((at, taken))) = taken else {
            return (StatusCode::NOT_FOUND, format!("no job {id}")).into_response();
        };
        done = at;
        match taken {
            Some(p) => {
                picture = Some(p);
                break;
            }
            None => {
                if let Some((_, png)) = cached(Some(done)) {
                    return png_response(png);
                }
            }
        }
    }
    let Some((assignment, grid, table)) = picture.flatten() else {
        return (StatusCode::NOT_FOUND, "nothing scored yet").into_response();
    };
    let img = picture::material_map(&assignment, grid, &table, picture::cell_size(grid).min(32));
    let mut png = Vec::new();
    match image::DynamicImage::ImageRgb8(img)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
    {
        Ok(()) => {
            let png = Arc::new(png);
            if let Ok(mut m) = web.maps.lock() {
                m.insert(id, (done, png.clone()));
            }
            png_response(png)
        }
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// `/jobs/{id}/convergence.svg`: the job's curve so far. Its points (a few maps of the grid)
/// are copied under the lock; the accuracies and the drawing are made after it.
async fn convergence_svg(State(web): State<Web>, Path(id): Path<String>) -> Response {
    let wanted = id.clone();
    let taken = web
        .farm
        .locked(move |s| {
            s.jobs.get(&wanted).map(|job| {
                let search = &job.checkpoint.search;
                (
                    scatterfarm_search::convergence::curve(search),
                    search.table().clone(),
                    job.plan.truth.clone(),
                    job.plan.config.grid as usize,
                )
            })
        })
        .await;
    let Ok(Some((points, table, truth, grid))) = taken else {
        return (StatusCode::NOT_FOUND, format!("no job {id}")).into_response();
    };
    let accuracy = |a: &[u16]| {
        let t = truth.as_ref()?;
        (a.len() == grid * grid)
            .then(|| scatterfarm_job::outcome::pixel_accuracy(a, grid, &table, t))
    };
    let curve = scatterfarm_job::outcome::convergence(points, &accuracy);
    match scatterfarm_job::convergence_plot::svg(&curve) {
        Some(svg) => (
            [
                (header::CONTENT_TYPE, "image/svg+xml"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            svg,
        )
            .into_response(),
        None => (StatusCode::NOT_FOUND, "no level has ended yet").into_response(),
    }
}

/// The web face's listener: plain HTTP, or HTTPS.
enum Listening {
    Http(tokio::net::TcpListener),
    Https(TlsListener),
}

/// Serves the web face on `addr` until `shutdown` resolves, asking for `token` when it is set,
/// over HTTPS with `tls` (else plain HTTP); returns the bound address and the serving future.
/// On shutdown it stops accepting and waits for the requests in flight.
pub async fn start(
    addr: SocketAddr,
    farm: Arc<Farm>,
    token: Option<String>,
    tls: Option<WebTls>,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(SocketAddr, impl std::future::Future<Output = Result<()>>)> {
    let rates = Arc::new(Mutex::new(Rates::default()));
    {
        let (farm, rates) = (farm.clone(), rates.clone());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tick.tick().await;
                let c = farm.scheduler().counters;
                if let Ok(mut r) = rates.lock() {
                    r.push(c.renders_completed, c.photons);
                }
            }
        });
    }
    let token = WebToken(token.map(Arc::from));
    let pages = Router::new()
        .route("/", get(index))
        .route("/metrics", get(metrics))
        .route("/jobs/{id}/map.png", get(map_png))
        .route("/jobs/{id}/convergence.svg", get(convergence_svg))
        .route_layer(middleware::from_fn_with_state(
            token.clone(),
            http_auth::require,
        ))
        .with_state(Web {
            farm,
            rates,
            maps: Arc::default(),
        });
    let login = Router::new()
        .route("/login", get(http_auth::login_form).post(http_auth::login))
        .with_state(LoginSettings {
            token,
            secure_cookie: tls.is_some(),
        });
    let app = pages.merge(login);
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("cannot listen on {addr} (--http)"))?;
    let bound = listener.local_addr()?;
    let listener = match &tls {
        Some(tls) => Listening::Https(TlsListener::new(listener, tls)?),
        None => Listening::Http(listener),
    };
    let serving = async move {
        let served = match listener {
            Listening::Https(l) => axum::serve(l, app).with_graceful_shutdown(shutdown).await,
            Listening::Http(l) => axum::serve(l, app).with_graceful_shutdown(shutdown).await,
        };
        served.context("the HTTP server failed")
    };
    Ok((bound, serving))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn html_is_escaped() {
        assert_eq!(
            esc("<a href=\"x\">&'"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;"
        );
    }

    #[test]
    fn metrics_name_every_family() {
        let snap = Snapshot {
            jobs: vec![pb::JobStatus {
                job_id: "j1".into(),
                state: pb::JobState::Searching as i32,
                renders_done: 5,
                renders_total: 20,
                ..Default::default()
            }],
            workers: Vec::new(),
            tasks_leased: 2,
            counters: crate::scheduler::Counters {
                leases_expired: 1,
                results_refused: 3,
                results_accepted: 7,
                renders_completed: 9,
                renders_scored_on_workers: 4,
                photons: 1000,
            },
        };
        let text = metrics_text(&snap, (1.5, 2e6)).unwrap();
        for needle in [
            "scatterfarm_jobs{state=\"searching\"} 1",
            "scatterfarm_tasks_leased 2",
            "scatterfarm_lease_expiries_total 1",
            "scatterfarm_results_refused_total 3",
            "scatterfarm_renders_scored_on_workers_total 4",
            "scatterfarm_photons_per_second 2000000",
            "scatterfarm_job_progress{job=\"j1\",state=\"searching\"} 0.25",
            "scatterfarm_workers 0",
        ] {
            assert!(text.contains(needle), "{needle} missing from\n{text}");
        }
    }
}
