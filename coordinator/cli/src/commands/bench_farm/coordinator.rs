//! The coordinator under test: `scatterfarm coordinator` as a child process on a loopback port,
//! its CPU time and peak memory read from `/proc`, and the host's clock ticks and load.

use anyhow::{bail, ensure, Context, Result};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The coordinator child process; killed when dropped.
pub(super) struct ChildCoordinator {
    child: Child,
    pub(super) url: String,
    log: PathBuf,
}

impl Drop for ChildCoordinator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl ChildCoordinator {
    /// Starts `scatterfarm coordinator` on a loopback port with `dir` as data folder and waits
    /// for its address.
    pub(super) fn start(dir: &Path) -> Result<ChildCoordinator> {
        let exe = std::env::current_exe().context("cannot find this program's executable")?;
        let data = dir.join("data");
        let address_file = dir.join("address");
        let log = dir.join("coordinator.log");
        // A data folder left by an earlier run would resume its jobs beside ours.
        ensure!(
            !data.exists(),
            "{} exists: give --keep an empty or new folder",
            data.display()
        );
        match std::fs::remove_file(&address_file) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(e).with_context(|| format!("cannot remove {}", address_file.display()))
            }
        }
        let log_file = std::fs::File::create(&log)
            .with_context(|| format!("cannot create {}", log.display()))?;
        let mut command = Command::new(&exe);
        die_with_parent(&mut command);
        let child = command
            .arg("coordinator")
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--data")
            .arg(&data)
            .arg("--address-file")
            .arg(&address_file)
            .arg("--drain-seconds")
            .arg("0")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .with_context(|| format!("cannot start {} coordinator", exe.display()))?;
        let mut coordinator = ChildCoordinator {
            child,
            url: String::new(),
            log,
        };
        let until = Instant::now() + Duration::from_secs(60);
        loop {
            if let Ok(text) = std::fs::read_to_string(&address_file) {
                let url = text.trim();
                if !url.is_empty() {
                    coordinator.url = url.to_string();
                    return Ok(coordinator);
                }
            }
            if let Some(status) = coordinator
                .child
                .try_wait()
                .context("cannot check on the coordinator")?
            {
                bail!(
                    "the coordinator exited ({status}) before listening:\n{}",
                    coordinator.log_tail()
                );
            }
            ensure!(
                Instant::now() < until,
                "the coordinator did not write its address within 60 s:\n{}",
                coordinator.log_tail()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub(super) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The last lines of the coordinator's log.
    pub(super) fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(20)..].join("\n")
    }

    /// utime + stime of the coordinator so far, in clock ticks (threads that ended included).
    pub(super) fn cpu_ticks(&self) -> Result<u64> {
        let path = format!("/proc/{}/stat", self.pid());
        let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {path}"))?;
        // Fields after the parenthesized command name, from field 3 (state) on.
        let rest = text
            .rsplit_once(')')
            .map(|(_, r)| r)
            .with_context(|| format!("{path}: unexpected contents"))?;
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let field = |n: usize| -> Result<u64> {
            fields
                .get(n - 3)
                .and_then(|f| f.parse().ok())
                .with_context(|| format!("{path}: no field {n}"))
        };
        Ok(field(14)? + field(15)?)
    }

    /// The coordinator's peak resident memory, in bytes (`VmHWM`).
    pub(super) fn peak_rss_bytes(&self) -> Option<u64> {
        let text = std::fs::read_to_string(format!("/proc/{}/status", self.pid())).ok()?;
        let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kb * 1024)
    }
}

/// Makes the child get SIGKILL when this process dies, however it dies: a bench stopped by
/// `timeout` or Ctrl-C must not leave its coordinator running (it would keep a core busy and
/// skew the next run's figures).
fn die_with_parent(command: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: the closure runs in the forked child before exec and only calls prctl(2), which
    // is async-signal-safe; it allocates nothing and takes no lock.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) == -1 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// Clock ticks per second of `/proc/PID/stat` (`getconf CLK_TCK`; 100, Linux's USER_HZ on
/// every common architecture, if getconf is missing).
pub(super) fn clock_ticks_per_second() -> (f64, &'static str) {
    let measured = Command::new("getconf")
        .arg("CLK_TCK")
        .stderr(Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| {
            String::from_utf8_lossy(&o.stdout)
                .trim()
                .parse::<f64>()
                .ok()
        })
        .filter(|&t| t > 0.0);
    match measured {
        Some(t) => (t, "getconf CLK_TCK"),
        None => (100.0, "assumed (USER_HZ)"),
    }
}

/// The host's 1-minute load average (other work on the host skews every figure).
pub(super) fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}
