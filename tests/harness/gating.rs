//! Tests that need something of the machine (root and iproute2 for network namespaces,
//! Chromium for the status page): without it they say loudly that they skipped, except under
//! `CI=true`, where they fail.

use std::io::Write;
use std::path::PathBuf;
use std::process::{Command, Stdio};

/// Whether `CI=true`.
pub fn under_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// Fails under `CI=true`; otherwise says loudly that `test` did not run, `why`, and how to run
/// it (`remedy`). The message goes straight to the process's stderr, past the test harness's
/// capture, so that a plain `cargo test` shows it.
pub fn skip_or_fail(test: &str, why: &str, remedy: &str) {
    if under_ci() {
        panic!("{test} cannot run here and CI=true: {why} ({remedy})");
    }
    let bar = "!".repeat(88);
    let message = format!(
        "\n{bar}\n!! SKIPPED {test}: {why}\n!! ({remedy}; with CI=true this is a failure)\n{bar}\n\n"
    );
    let _ = std::io::stderr().lock().write_all(message.as_bytes());
}

/// The effective user id, from /proc (else `id -u`).
pub fn effective_uid() -> Option<u32> {
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

/// Whether iproute2's `ip` is on PATH.
pub fn has_ip() -> bool {
    Command::new("ip")
        .arg("-V")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Whether iproute2's `tc` is on PATH.
pub fn has_tc() -> bool {
    Command::new("tc")
        .arg("-V")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Debian's Chromium, if installed.
pub fn chromium() -> Option<PathBuf> {
    ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}
