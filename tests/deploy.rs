//! Runs `deploy/local-cluster.sh` with the built `scatterfarm`: a coordinator and two CPU workers,
//! each in its own network namespace on a private bridge, reconstruct a small job over gRPC with a
//! token; the script checks that every worker rendered part of it and that SIGTERM stops them all
//! cleanly, and removes everything it created.
//!
//! It needs root (network namespaces, veth pairs) and iproute2's `ip`. Without them the test says
//! loudly that it skipped, except with `CI=true`, where it fails.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

/// The script's exit status for "this machine cannot run it".
const CANNOT_RUN: i32 = 77;

fn under_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// Fails under `CI=true`; otherwise says loudly that the test did not run. The message goes
/// straight to the process's stderr, past the test harness's capture, so that a plain
/// `cargo test` shows it.
fn skip_or_fail(why: &str) {
    if under_ci() {
        panic!("deploy/local-cluster.sh cannot run here and CI=true: {why}");
    }
    let bar = "!".repeat(88);
    let message = format!(
        "\n{bar}\n!! SKIPPED deploy::local_cluster: {why}\n!! (run the tests as root with \
         iproute2 installed to exercise deploy/local-cluster.sh; with CI=true this is a \
         failure)\n{bar}\n\n"
    );
    let _ = std::io::stderr().lock().write_all(message.as_bytes());
}

/// The effective user id, from /proc (else `id -u`).
fn effective_uid() -> Option<u32> {
    if let Ok(status) = std::fs::read_to_string("/proc/self/status") {
        let uid = status
            .lines()
            .find_map(|l| l.strip_prefix("Uid:"))
            .and_then(|ids| ids.split_whitespace().nth(1))
            .and_then(|euid| euid.parse().ok());
        if uid.is_some() {
            return uid;
        }
    }
    let out = Command::new("id").arg("-u").output().ok()?;
    String::from_utf8_lossy(&out.stdout).trim().parse().ok()
}

fn has_ip() -> bool {
    Command::new("ip")
        .arg("-V")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

#[test]
fn local_cluster() {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/local-cluster.sh");
    assert!(script.is_file(), "{} is missing", script.display());
    match effective_uid() {
        Some(0) => {}
        Some(uid) => return skip_or_fail(&format!("not root (uid {uid})")),
        None => return skip_or_fail("cannot tell whether this runs as root"),
    }
    if !has_ip() {
        return skip_or_fail("iproute2's `ip` is not on PATH");
    }

    let output = Command::new("bash")
        .arg(&script)
        .arg(env!("CARGO_BIN_EXE_scatterfarm"))
        .args(["--workers", "2", "--engine", "cpu", "--timeout", "400"])
        .stdin(Stdio::null())
        .output()
        .expect("cannot run bash");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    eprintln!("---- deploy/local-cluster.sh ----\n{stdout}{stderr}");
    if output.status.code() == Some(CANNOT_RUN) {
        return skip_or_fail("the script cannot run on this machine (see its output above)");
    }
    assert!(
        output.status.success(),
        "deploy/local-cluster.sh failed ({}); its output is above",
        output.status
    );
    for expected in [
        "all 2 workers registered",
        "every worker rendered part of the job",
        "PASSED",
        "cleaned up",
    ] {
        assert!(
            stderr.contains(expected),
            "the script's output lacks {expected:?}"
        );
    }
}
