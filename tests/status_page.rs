//! The coordinator's status page in a real browser: headless Chromium loads `/` while a job runs
//! and must show the job, the worker and the job's current best map (the image must load). A
//! screenshot is kept in `target/test-artifacts/status-page.png`.
//!
//! The token check of the web face is tested with plain HTTP requests; with `--tls-cert` and
//! `--tls-key` the web face serves HTTPS with gRPC's certificate (tested with a rustls client
//! trusting the test CA), refuses plain HTTP, and its login cookie is `Secure`.
//!
//! The page test needs Debian's `chromium`. Without it the test says loudly that it skipped, except under
//! `CI=true`, where it fails.

use crate::harness::gating::{chromium, skip_or_fail};
use crate::harness::net::{http, https, port_of, wait_for_file, wait_for_file_from, HttpResponse};
use crate::harness::process::{output, repo_root, run, scatterfarm, Proc};
use crate::harness::scenes::LONG_DEMO_JOB;
use crate::harness::tls::certificates;
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
    let addr_file = dir.path().join("address");
    let http_file = dir.path().join("http-address");
    // Both on ports the coordinator chooses, so no other test can take them first.
    let mut coordinator = scatterfarm();
    coordinator
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(dir.path().join("data"))
        .arg("--address-file")
        .arg(&addr_file)
        .args(["--http", "127.0.0.1:0", "--http-address-file"])
        .arg(&http_file);
    let mut coordinator = Proc::logged(coordinator, &dir.path().join("coordinator.log"));
    let url = wait_for_file_from(&addr_file, &mut coordinator)
        .unwrap_or_else(|| panic!("the coordinator ended:\n{}", coordinator.log_text()));
    let http_url = wait_for_file(&http_file);
    assert!(http_url.starts_with("http://127.0.0.1:"), "{http_url}");
    let http_port = port_of(&http_url);
    let _coordinator = coordinator;
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
        let name = if open { "open" } else { "token" };
        let http_file = dir.path().join(format!("http-address-{name}"));
        let mut c = scatterfarm();
        c.args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
            .arg(dir.path().join(format!("data-{name}")))
            .arg("--token-file")
            .arg(dir.path().join("token"))
            .args(["--http", "127.0.0.1:0", "--http-address-file"])
            .arg(&http_file);
        if open {
            c.arg("--http-open");
        }
        let coordinator = Proc::spawn(c);
        (coordinator, port_of(&wait_for_file(&http_file)))
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
    // Plain HTTP: a Secure cookie would never be sent back.
    assert!(!cookie.contains("Secure"), "{cookie}");
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

/// The `Set-Cookie` value of a response.
fn set_cookie(r: &HttpResponse) -> String {
    r.headers
        .lines()
        .find_map(|l| {
            l.strip_prefix("set-cookie: ")
                .or_else(|| l.strip_prefix("Set-Cookie: "))
        })
        .unwrap_or_else(|| panic!("no cookie: {}", r.headers))
        .to_string()
}

/// A folder with the test CA (`ca.pem`), the server's certificate and key (`server.pem`,
/// `server.key`) and a token file (`token`: s3cret).
fn tls_folder() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = certificates();
    std::fs::write(dir.path().join("ca.pem"), ca).unwrap();
    std::fs::write(dir.path().join("server.pem"), cert).unwrap();
    std::fs::write(dir.path().join("server.key"), key).unwrap();
    std::fs::write(dir.path().join("token"), "s3cret\n").unwrap();
    dir
}

/// `scatterfarm coordinator` on the data folder `data` of `dir`, with its token, TLS files,
/// `--http http` and `extra`.
fn tls_coordinator(dir: &Path, data: &str, http: &str, extra: &[&str]) -> std::process::Command {
    let mut c = scatterfarm();
    c.env("RUST_LOG", "info")
        .current_dir(dir)
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data", data])
        .args(["--token-file", "token"])
        .args(["--tls-cert", "server.pem", "--tls-key", "server.key"])
        .args(["--http", http])
        .args(extra);
    c
}

#[test]
fn with_tls_the_web_face_serves_https_with_the_grpc_certificate_and_refuses_plain_http() {
    let dir = tls_folder();
    let ca = std::fs::read_to_string(dir.path().join("ca.pem")).unwrap();
    let c = tls_coordinator(
        dir.path(),
        "data",
        "127.0.0.1:0",
        &[
            "--address-file",
            "address",
            "--http-address-file",
            "http-address",
        ],
    );
    let mut coordinator = Proc::logged(c, &dir.path().join("coordinator.log"));
    // Prove it: gRPC is TLS, with the CA.
    let url = wait_for_file(&dir.path().join("address"));
    let http_url = wait_for_file(&dir.path().join("http-address"));
    assert!(http_url.starts_with("https://127.0.0.1:"), "{http_url}");
    let port = port_of(&http_url);
    assert!(url.starts_with("https://"), "{url}");
    let mut jobs = scatterfarm();
    jobs.current_dir(dir.path())
        .args(["jobs", "--json", "--coordinator", &url])
        .args(["--tls-ca", "ca.pem", "--token-file", "token"]);
    assert_eq!(output(jobs).ok().trim(), "[]");

    // HTTPS on the --http port, the token asked for as over plain HTTP.
    let get = |path: &str, headers: &[&str]| https(port, &ca, "GET", path, headers, "");
    for path in [
        "/",
        "/metrics",
        "/jobs/j1/map.png",
        "/jobs/j1/convergence.svg",
    ] {
        let r = get(path, &["Accept: text/html"]);
        assert_eq!(r.status, 401, "{path} without the token: {}", r.body);
    }
    let r = get("/metrics", &["Authorization: Bearer nope"]);
    assert_eq!(r.status, 401, "{}", r.body);
    let r = get("/metrics", &["Authorization: Bearer s3cret"]);
    assert_eq!(r.status, 200, "{}", r.body);
    assert!(r.body.contains("scatterfarm_jobs"), "{}", r.body);

    // The login cookie is Secure: a browser sends it back over HTTPS only.
    let form = "Content-Type: application/x-www-form-urlencoded";
    let r = https(port, &ca, "POST", "/login", &[form], "token=s3cret");
    assert_eq!(r.status, 303, "{}", r.headers);
    let cookie = set_cookie(&r);
    for attribute in ["HttpOnly", "SameSite=Strict", "Secure"] {
        assert!(
            cookie.split(';').any(|a| a.trim() == attribute),
            "{attribute} missing: {cookie}"
        );
    }
    let pair = cookie.split(';').next().unwrap();
    let r = get("/", &[&format!("Cookie: {pair}")]);
    assert_eq!(r.status, 200, "{}", r.body);
    assert!(r.body.contains("Workers"), "{}", r.body);

    // Plain HTTP on the same port, even with the right token, gets a refusal and no page.
    let r = http(
        port,
        "GET",
        "/metrics",
        &["Authorization: Bearer s3cret"],
        "",
    );
    assert_eq!(r.status, 400, "{}", r.body);
    assert!(r.body.contains("https://"), "{}", r.body);
    assert!(!r.body.contains("scatterfarm_jobs"), "{}", r.body);
    // A connection that never says anything does not hold up the others.
    let silent = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    let r = get("/metrics", &["Authorization: Bearer s3cret"]);
    assert_eq!(r.status, 200, "{}", r.body);
    drop(silent);
    let log = coordinator.log_text();
    assert!(
        log.contains(&format!("status page on https://127.0.0.1:{port}/")),
        "{log}"
    );

    // SIGTERM still stops the web face with the rest: the port closes.
    coordinator.signal("TERM");
    let status = coordinator.wait_exit(Duration::from_secs(60));
    assert!(status.success(), "{status}:\n{}", coordinator.log_text());
    assert!(
        std::net::TcpStream::connect(("127.0.0.1", port)).is_err(),
        "the HTTPS port is still open after the coordinator stopped"
    );
}

#[test]
fn http_plaintext_opts_out_of_tls_with_a_warning_and_bad_tls_files_are_named() {
    let dir = tls_folder();
    // Off loopback, plain HTTP next to gRPC's TLS: served, with a warning.
    let c = tls_coordinator(
        dir.path(),
        "data",
        "0.0.0.0:0",
        &["--http-plaintext", "--http-address-file", "http-address"],
    );
    let coordinator = Proc::logged(c, &dir.path().join("plaintext.log"));
    let http_url = wait_for_file(&dir.path().join("http-address"));
    assert!(http_url.starts_with("http://0.0.0.0:"), "{http_url}");
    let port = port_of(&http_url);
    let r = http(
        port,
        "GET",
        "/metrics",
        &["Authorization: Bearer s3cret"],
        "",
    );
    assert_eq!(r.status, 200, "{}", r.body);
    let r = http(port, "GET", "/metrics", &[], "");
    assert_eq!(r.status, 401, "{}", r.body);
    let form = "Content-Type: application/x-www-form-urlencoded";
    let r = http(port, "POST", "/login", &[form], "token=s3cret");
    assert!(!set_cookie(&r).contains("Secure"), "{}", r.headers);
    let log = coordinator.log_text();
    assert!(
        log.contains("--http-plaintext") && log.contains("in the clear"),
        "no warning about plain HTTP:\n{log}"
    );
    drop(coordinator);

    // A certificate or key that cannot be read or parsed is named, and nothing starts.
    std::fs::write(dir.path().join("garbage.pem"), "not a certificate\n").unwrap();
    let (_, _, other_key) = certificates();
    std::fs::write(dir.path().join("other.key"), other_key).unwrap();
    let limit = Duration::from_secs(60);
    for (cert, key, named, why) in [
        (
            "garbage.pem",
            "server.key",
            "garbage.pem",
            "no PEM certificate",
        ),
        ("missing.pem", "server.key", "missing.pem", "cannot read"),
        (
            "server.pem",
            "server.pem",
            "server.pem",
            "no PEM private key",
        ),
        ("server.pem", "other.key", "other.key", "does not belong"),
    ] {
        let mut c = scatterfarm();
        c.current_dir(dir.path())
            .args(["coordinator", "--listen", "127.0.0.1:0", "--data", "bad"])
            .args(["--tls-cert", cert, "--tls-key", key])
            .args(["--http", "127.0.0.1:0"]);
        let stderr = run(c, dir.path(), limit).fails();
        assert!(
            stderr.contains(named) && stderr.contains(why),
            "{cert} + {key}: {stderr}"
        );
    }
}
