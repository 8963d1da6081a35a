//! Launching `scatterfarm`: a clean environment, short commands run to their end and checked,
//! and long-lived processes that are killed (SIGKILL) and reaped when dropped, so no test leaves
//! one behind, even when it panics.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// `scatterfarm` with a clean environment: no token, coordinator URL or backtrace setting
/// leaks in from the caller; logs at warn, without colours; no stdin.
pub fn scatterfarm() -> Command {
    clean(Command::new(env!("CARGO_BIN_EXE_scatterfarm")))
}

/// [`scatterfarm`] run in the network namespace `netns`: `ip netns exec NETNS scatterfarm`
/// (`ip` execs it, so the child's pid is the command's).
pub fn scatterfarm_in_netns(netns: &str) -> Command {
    let mut cmd = Command::new("ip");
    cmd.args(["netns", "exec", netns, env!("CARGO_BIN_EXE_scatterfarm")]);
    clean(cmd)
}

fn clean(mut cmd: Command) -> Command {
    for var in [
        "SCATTERFARM_TOKEN",
        "SCATTERFARM_TOKEN_FILE",
        "SCATTERFARM_COORDINATOR",
        "RUST_BACKTRACE",
        "RUST_LIB_BACKTRACE",
    ] {
        cmd.env_remove(var);
    }
    cmd.env("RUST_LOG", "warn")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null());
    cmd
}

/// `scatterfarm ARGS…` run to its end in `dir`, its output captured.
pub fn scatterfarm_in(args: &[&str], dir: &Path) -> Ran {
    let mut cmd = scatterfarm();
    cmd.args(args).current_dir(dir);
    output(cmd)
}

/// `scatterfarm ARGS…`, for messages.
pub fn describe(cmd: &Command) -> String {
    let args: Vec<String> = cmd
        .get_args()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    format!("scatterfarm {}", args.join(" "))
}

/// A child process that is killed (SIGKILL) and reaped when dropped.
pub struct Proc {
    pub child: Child,
    pub what: String,
    /// Where its stderr goes.
    pub log: Option<PathBuf>,
}

impl Proc {
    pub fn spawn(mut cmd: Command) -> Proc {
        let what = describe(&cmd);
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start `{what}`: {e}"));
        Proc {
            child,
            what,
            log: None,
        }
    }

    /// Started with stdout discarded and stderr (the log) in `log`.
    pub fn logged(mut cmd: Command, log: &Path) -> Proc {
        cmd.stdout(Stdio::null()).stderr(File::create(log).unwrap());
        let mut proc = Proc::spawn(cmd);
        proc.log = Some(log.to_path_buf());
        proc
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Sends the signal `name` (`TERM`, `INT`, `USR1`) to the process, with `kill -s`.
    pub fn signal(&self, name: &str) {
        let pid = self.child.id().to_string();
        let status = Command::new("kill")
            .args(["-s", name, &pid])
            .status()
            .unwrap_or_else(|e| panic!("cannot run `kill -s {name} {pid}`: {e}"));
        assert!(status.success(), "`kill -s {name} {pid}` failed: {status}");
    }

    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    pub fn log_text(&self) -> String {
        self.log
            .as_ref()
            .and_then(|l| std::fs::read_to_string(l).ok())
            .unwrap_or_default()
    }

    /// Waits for the process to end by itself.
    pub fn wait_exit(&mut self, limit: Duration) -> ExitStatus {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "`{}` did not end within {limit:?}:\n{}",
                self.what,
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A finished short-lived command.
pub struct Ran {
    pub what: String,
    pub status: ExitStatus,
    pub stdout: String,
    pub stderr: String,
}

impl Ran {
    /// Its stdout; the test fails if the command did.
    pub fn ok(&self) -> String {
        assert!(
            self.status.success(),
            "`{}` failed ({}):\n{}\n{}",
            self.what,
            self.status,
            self.stdout,
            self.stderr
        );
        self.stdout.clone()
    }

    /// Its stderr; the test fails if the command succeeded.
    pub fn fails(&self) -> String {
        assert!(
            !self.status.success(),
            "`{}` succeeded where it should fail:\n{}\n{}",
            self.what,
            self.stdout,
            self.stderr
        );
        self.stderr.clone()
    }
}

/// Runs `cmd` to its end with its output captured in memory.
pub fn output(mut cmd: Command) -> Ran {
    let what = describe(&cmd);
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("cannot run `{what}`: {e}"));
    Ran {
        what,
        status: out.status,
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// Runs `cmd` to its end (killed, and the test failed, after `limit`); its output goes
/// through files in `scratch`.
pub fn run(mut cmd: Command, scratch: &Path, limit: Duration) -> Ran {
    static RUNS: AtomicUsize = AtomicUsize::new(0);
    let n = RUNS.fetch_add(1, Ordering::Relaxed);
    let out = scratch.join(format!("run-{n}.stdout"));
    let err = scratch.join(format!("run-{n}.stderr"));
    cmd.stdout(File::create(&out).unwrap())
        .stderr(File::create(&err).unwrap());
    let mut proc = Proc::spawn(cmd);
    proc.log = Some(err.clone());
    let status = proc.wait_exit(limit);
    Ran {
        what: proc.what.clone(),
        status,
        stdout: std::fs::read_to_string(&out).unwrap(),
        stderr: std::fs::read_to_string(&err).unwrap(),
    }
}

/// The repository's root (the binary's package is `coordinator/cli`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}
