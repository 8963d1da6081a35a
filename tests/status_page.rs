//! The coordinator's status page in a real browser: headless Chromium loads `/` while a job runs
//! and must show the job, the worker and the job's current best map (the image must load). A
//! screenshot is kept in `target/test-artifacts/status-page.png`.
//!
//! Needs Debian's `chromium`. Without it the test says loudly that it skipped, except under
//! `CI=true`, where it fails.

use crate::harness::gating::{chromium, skip_or_fail};
use crate::harness::net::{free_port, wait_for_file};
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
    let http = free_port();
    let addr_file = dir.path().join("address");
    let mut coordinator = scatterfarm();
    coordinator
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(dir.path().join("data"))
        .arg("--address-file")
        .arg(&addr_file)
        .args(["--http", &format!("127.0.0.1:{http}")]);
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

    let page = format!("http://127.0.0.1:{http}/");
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
