//! The coordinator's status page in a real browser: headless Chromium loads `/` while a job runs
//! and must show the job, the worker and the job's current best map (the image must load). A
//! screenshot is kept in `target/test-artifacts/status-page.png`.
//!
//! The token check of the web face is tested with plain HTTP requests.
//!
//! The page test needs Debian's `chromium`. Without it the test says loudly that it skipped, except under
//! `CI=true`, where it fails.

use crate::harness::gating::{chromium, skip_or_fail};
use crate::harness::net::{free_port, http, wait_for_file};
use crate::harness::process::{output, repo_root, scatterfarm, Proc};
use crate::harness::scenes::LONG_DEMO_JOB;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Runs headless Chromium with `args` against `url`, returns stdout.
fn browse(browser: &Path, profile: &Path, args: &[&str], url: &str) -> String {
    let out = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--window-size=1400,900",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(args)
        .arg(url)
        .stderr(Stdio::null())
        .output()
        .expect("chromium runs");
    assert!(out.status.success(), "chromium failed: {:?}", out.status);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn the_status_page_shows_jobs_workers_and_the_current_map() {
    let Some(browser) = chromium() else {
        return skip_or_fail(
            "status_page::the_status_page_shows_jobs_workers_and_the_current_map",
            "Chromium is not installed; the status page was not tested",
            "apt-get install chromium",
        );
    };
    let dir = tempfile::tempdir().unwrap();
    let http_port = free_port();
    let addr_file = dir.path().join("address");
    let mut coordinator = scatterfarm();
    coordinator
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(dir.path().join("data"))
        .arg("--address-file")
        .arg(&addr_file)
        .args(["--http", &format!("127.0.0.1:{http_port}")]);
    let _coordinator = Proc::spawn(coordinator);
    let url = wait_for_file(&addr_file);
    let mut worker = scatterfarm();
    worker
        .args(["worker", "--engine", "cpu", "--name", "page-test-worker"])
        .args(["--coordinator", &url]);
    let _worker = Proc::spawn(worker);
    let job = dir.path().join("job.toml");
    std::fs::write(&job, LONG_DEMO_JOB).unwrap();
    let mut submit = scatterfarm();
    submit.args(["submit", "--coordinator", &url]).arg(&job);
    let id = output(submit).ok().trim().to_string();

    // Wait until something has been scored, so there is a map to show.
    let until = Instant::now() + Duration::from_secs(120);
    loop {
        let mut status = scatterfarm();
        status.args(["status", "--json", "--coordinator", &url, &id]);
        let v: serde_json::Value = serde_json::from_str(&output(status).stdout).unwrap_or_default();
        if v["best_similarity"].is_number() {
            break;
        }
        assert!(Instant::now() < until, "nothing was scored in time: {v}");
        std::thread::sleep(Duration::from_millis(200));
    }

    let page = format!("http://127.0.0.1:{http_port}/");
    let profile = dir.path().join("chromium-profile");
    let dom = browse(&browser, &profile, &["--dump-dom"], &page);
    assert!(
        dom.contains(&format!("data-job=\"{id}\"")),
        "job row missing:\n{dom}"
    );
    assert!(dom.contains("page-test-job"), "job name missing:\n{dom}");
    assert!(
        dom.contains("page-test-worker"),
        "worker row missing:\n{dom}"
    );
    assert!(dom.contains("cpu/cpu/"), "worker engine missing:\n{dom}");
    let img = dom
        .split("<img")
        .nth(1)
        .map(|rest| rest.split('>').next().unwrap_or(""))
        .unwrap_or_else(|| panic!("no map image on the page:\n{dom}"));
    assert!(img.contains(&format!("/jobs/{id}/map.png")), "{img}");
    assert!(
        img.contains("data-loaded=\"1\""),
        "the map image did not load: {img}"
    );

    // The convergence curve beside the map: an SVG with the score's polyline, once level 0
    // has ended (polled: the search may still be in it).
    assert!(
        dom.contains(&format!("/jobs/{id}/convergence.svg")),
        "no convergence plot on the page:\n{dom}"
    );
    let until = Instant::now() + Duration::from_secs(120);
    let svg = loop {
        let r = http(
            http_port,
            "GET",
            &format!("/jobs/{id}/convergence.svg"),
            &[],
            "",
        );
        if r.status == 200 {
            break r;
        }
        assert_eq!(r.status, 404, "{}", r.body);
        assert!(Instant::now() < until, "no curve in time: {}", r.body);
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(
        svg.headers.to_lowercase().contains("image/svg+xml"),
        "{}",
        svg.headers
    );
    assert!(
        svg.body.starts_with("<svg") && svg.body.contains("class=\"score\""),
        "{}",
        svg.body
    );
    let r = http(http_port, "GET", "/jobs/nope/convergence.svg", &[], "");
    assert_eq!(r.status, 404, "{}", r.body);

    let artifacts = repo_root().join("target/test-artifacts");
    std::fs::create_dir_all(&artifacts).unwrap();
    let shot = artifacts.join("status-page.png");
    let _ = std::fs::remove_file(&shot);
    browse(
        &browser,
        &profile,
        &[&format!("--screenshot={}", shot.display())],
        &page,
    );
    let meta = std::fs::metadata(&shot).expect("chromium wrote the screenshot");
    assert!(meta.len() > 1000, "the screenshot is empty");
    eprintln!("screenshot: {}", shot.display());
}

#[test]
fn the_web_face_asks_for_the_coordinators_token_unless_told_not_to() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("token"), "s3cret\n").unwrap();
    let start = |open: bool| {
        let port = free_port();
        let mut c = scatterfarm();
        c.args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
            .arg(dir.path().join(if open { "data-open" } else { "data" }))
            .arg("--token-file")
            .arg(dir.path().join("token"))
            .args(["--http", &format!("127.0.0.1:{port}")]);
        if open {
            c.arg("--http-open");
        }
        (Proc::spawn(c), port)
    };
    let (_coordinator, port) = start(false);
    let browser = "Accept: text/html";
    for path in [
        "/",
        "/metrics",
        "/jobs/j1/map.png",
        "/jobs/j1/convergence.svg",
    ] {
        let r = http(port, "GET", path, &[browser], "");
        assert_eq!(r.status, 401, "{path} without the token: {}", r.body);
    }
    let r = http(port, "GET", "/", &[browser], "");
    assert!(
        r.body.contains("<form") && r.body.contains("/login"),
        "{}",
        r.body
    );
    let r = http(port, "GET", "/metrics", &[], "");
    assert!(r.body.contains("Authorization: Bearer"), "{}", r.body);
    let r = http(port, "GET", "/metrics", &["Authorization: Bearer nope"], "");
    assert_eq!(r.status, 401);

    // As Prometheus asks: a bearer header.
    let r = http(
        port,
        "GET",
        "/metrics",
        &["Authorization: Bearer s3cret"],
        "",
    );
    assert_eq!(r.status, 200, "{}", r.body);
    assert!(r.body.contains("scatterfarm_jobs"), "{}", r.body);

    // As a browser does: the form sets a cookie.
    let form = "Content-Type: application/x-www-form-urlencoded";
    let r = http(port, "POST", "/login", &[form], "token=wrong");
    assert_eq!(r.status, 401);
    assert!(
        !r.headers.to_lowercase().contains("set-cookie"),
        "{}",
        r.headers
    );
    let r = http(port, "POST", "/login", &[form], "token=s3cret");
    assert_eq!(r.status, 303, "{}", r.headers);
    let cookie = r
        .headers
        .lines()
        .find_map(|l| {
            l.strip_prefix("set-cookie: ")
                .or_else(|| l.strip_prefix("Set-Cookie: "))
        })
        .unwrap_or_else(|| panic!("no cookie: {}", r.headers))
        .to_string();
    assert!(
        cookie.contains("HttpOnly") && cookie.contains("SameSite=Strict"),
        "{cookie}"
    );
    let pair = cookie.split(';').next().unwrap();
    let r = http(port, "GET", "/", &[&format!("Cookie: {pair}")], "");
    assert_eq!(r.status, 200, "{}", r.body);
    assert!(r.body.contains("Workers"), "{}", r.body);
    let r = http(port, "GET", "/", &["Cookie: scatterfarm_token=nope"], "");
    assert_eq!(r.status, 401);

    // Told not to: open to everyone.
    let (_open, port) = start(true);
    let r = http(port, "GET", "/metrics", &[], "");
    assert_eq!(r.status, 200, "{}", r.body);
}
