//! Runs `deploy/local-cluster.sh` with the built `scatterfarm`: a coordinator and two CPU workers,
//! each in its own network namespace on a private bridge, reconstruct a small job over gRPC with a
//! token; the script checks that every worker rendered part of it and that SIGTERM stops them all
//! cleanly, and removes everything it created.
//!
//! It needs root (network namespaces, veth pairs) and iproute2's `ip`. Without them the test says
//! loudly that it skipped, except with `CI=true`, where it fails.

use crate::harness::gating::{effective_uid, has_ip, skip_or_fail};
use crate::harness::process::repo_root;
use std::process::{Command, Stdio};

/// The script's exit status for "this machine cannot run it".
const CANNOT_RUN: i32 = 77;

/// Fails under `CI=true`; otherwise says loudly that the test did not run.
fn skip(why: &str) {
    skip_or_fail(
        "deploy::local_cluster",
        why,
        "run the tests as root with iproute2 installed to exercise deploy/local-cluster.sh",
    );
}

#[test]
fn local_cluster() {
    let script = repo_root().join("deploy/local-cluster.sh");
    assert!(script.is_file(), "{} is missing", script.display());
    match effective_uid() {
        Some(0) => {}
        Some(uid) => return skip(&format!("not root (uid {uid})")),
        None => return skip("cannot tell whether this runs as root"),
    }
    if !has_ip() {
        return skip("iproute2's `ip` is not on PATH");
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
        return skip("the script cannot run on this machine (see its output above)");
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
