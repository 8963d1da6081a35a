//! The wgpu engine: photon transport as a WGSL compute shader (`shaders/*.wgsl`).
//!
//! This module owns everything GPU-side:
//! - [`adapters`]: finding and choosing adapters;
//! - `device`: the device, its error handler and the transport pipeline, set up once;
//! - [`engine`]: [`GpuEngine`], which lays a batch out and renders it chunk by chunk;
//! - `dispatch_plan`: how a render batch is cut into submissions and dispatches (arithmetic);
//! - `submission`: one chunk through the device — buffers, bind group, dispatches, readback;
//! - `differential`: the differential render (per-pixel tallies and every change's weights) on
//!   the same device, through its own entry point of the shader;
//! - `records`: the records the shader reads, `Pod` structs the WGSL structs mirror;
//! - the shader source itself, concatenated here from the files in `shaders/` (random numbers,
//!   tallies, transport, differential).
//!
//! The shader implements `docs/model.md` exactly, with the same Philox stream layout as
//! [`crate::rng`]; floats are f32, so this engine agrees with the CPU engine statistically, and
//! with itself bit for bit on one device and driver.
//!
//! On machines without a GPU, Mesa's lavapipe (a Vulkan CPU device) runs the same shader. Its
//! cost model shaped the shader (see the header of `shaders/transport.wgsl`): it runs 8
//! invocations as SIMD lanes and executes both sides of every `if`, storage reads are per-lane
//! loops, integer division has no vector instruction, and writing one component of a vector
//! variable is slow. So the march steps through whole uniform blocks of pixels (exactly the same
//! optical depth as pixel by pixel), each flight uses one Philox block, and exits are tallied once
//! per round of flights.

pub mod adapters;
mod device;
mod differential;
mod dispatch_plan;
pub mod engine;
mod records;
mod submission;

#[cfg(test)]
mod differential_tests;
#[cfg(test)]
mod tests;

pub use adapters::{list_adapters, AdapterInfo, AdapterSelector, AdapterSelectorError};
pub use engine::{GpuEngine, GPU_ENGINE_VERSION};

use std::future::Future;
use std::sync::Arc;
use std::task::{Context, Poll, Wake, Waker};

/// The WGSL program: the shader files of `shaders/`, concatenated (WGSL declarations may come in
/// any order).
pub const SHADER_SOURCE: &str = concat!(
    include_str!("../../../../shaders/rng.wgsl"),
    "\n",
    include_str!("../../../../shaders/tallies.wgsl"),
    "\n",
    include_str!("../../../../shaders/transport.wgsl"),
    "\n",
    include_str!("../../../../shaders/differential.wgsl"),
);

/// `mul_hi_lo` with one 64-bit multiply, for devices with 64-bit integers (`SHADER_INT64`).
pub const SHADER_MUL_HI_INT64: &str = include_str!("../../../../shaders/rng_int64.wgsl");

/// The shader source for a device: with `int64`, rng.wgsl's 16-bit `mul_hi_lo` (between its
/// `BEGIN mul_hi_lo` and `END mul_hi_lo` lines) is replaced by [`SHADER_MUL_HI_INT64`]. Both
/// compute the same words.
pub fn shader_source(int64: bool) -> String {
    const BEGIN: &str = "// BEGIN mul_hi_lo";
    const END: &str = "// END mul_hi_lo";
    match (SHADER_SOURCE.find(BEGIN), SHADER_SOURCE.find(END)) {
        (Some(b), Some(e)) if int64 && b < e => {
            format!(
                "{}{}{}",
                &SHADER_SOURCE[..b],
                SHADER_MUL_HI_INT64,
                &SHADER_SOURCE[e + END.len()..]
            )
        }
        _ => SHADER_SOURCE.to_string(),
    }
}

/// FNV-1a (64-bit) of the shader source: part of the engine fingerprint, so a changed shader
/// never shares cached counts with an old one.
pub const SHADER_HASH: u64 =
    fnv1a64(SHADER_SOURCE.as_bytes()) ^ fnv1a64(SHADER_MUL_HI_INT64.as_bytes()).rotate_left(1);

const fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    let mut i = 0;
    while i < bytes.len() {
        hash ^= bytes[i] as u64;
        hash = hash.wrapping_mul(0x0000_0100_0000_01b3);
        i += 1;
    }
    hash
}

/// Makes `XDG_RUNTIME_DIR` name a private (mode 700) directory, so Mesa does not print
/// "XDG_RUNTIME_DIR is invalid or not set": when the variable is unset or names anything else,
/// creates `scatterfarm-runtime-<uid>` under the temp dir with mode 700 and points the variable
/// there. Runs once per process, before the first wgpu instance is made (it sets an environment
/// variable, so call it before other threads read the environment). Does nothing off Unix.
pub fn silence_mesa_runtime_dir_warning() {
    #[cfg(unix)]
    {
        static ONCE: std::sync::Once = std::sync::Once::new();
        ONCE.call_once(runtime_dir::ensure);
    }
}

#[cfg(unix)]
mod runtime_dir {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    use std::path::{Path, PathBuf};

    const VAR: &str = "XDG_RUNTIME_DIR";

    /// The uid this process runs as (the owner of `/proc/self`), if the platform shows it.
    fn current_uid() -> Option<u32> {
        std::fs::metadata("/proc/self").ok().map(|m| m.uid())
    }

    /// A real directory (not a symlink) owned by us with mode 700.
    fn is_private_dir(path: &Path, uid: Option<u32>) -> bool {
        match std::fs::symlink_metadata(path) {
            Ok(m) => m.is_dir() && m.mode() & 0o777 == 0o700 && uid.is_none_or(|u| m.uid() == u),
            Err(_) => false,
        }
    }

    /// Creates (or repairs) a private directory at `path`; `None` if it belongs to someone else.
    fn make_private_dir(path: &Path, uid: Option<u32>) -> Option<PathBuf> {
        match std::fs::DirBuilder::new().mode(0o700).create(path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(_) => return None,
        }
        let meta = std::fs::symlink_metadata(path).ok()?;
        if !meta.is_dir() || uid.is_some_and(|u| meta.uid() != u) {
            return None;
        }
        if meta.mode() & 0o777 != 0o700 {
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o700)).ok()?;
        }
        is_private_dir(path, uid).then(|| path.to_path_buf())
    }

    pub(super) fn ensure() {
        let uid = current_uid();
        if let Some(dir) = std::env::var_os(VAR) {
            if is_private_dir(Path::new(&dir), uid) {
                return;
            }
        }
        let tmp = std::env::temp_dir();
        let owner = uid.map_or_else(|| format!("pid{}", std::process::id()), |u| u.to_string());
        let candidates = [
            tmp.join(format!("scatterfarm-runtime-{owner}")),
            tmp.join(format!(
                "scatterfarm-runtime-{owner}-{}",
                std::process::id()
            )),
        ];
        match candidates.iter().find_map(|p| make_private_dir(p, uid)) {
            Some(dir) => {
                tracing::debug!("{VAR} set to the private directory {}", dir.display());
                std::env::set_var(VAR, dir);
            }
            None => tracing::debug!("could not make a private {VAR} under {}", tmp.display()),
        }
    }
}

/// Runs a future to completion on this thread. wgpu's native futures are ready at once or after
/// a `Device::poll`, so this needs no executor crate.
pub(crate) fn block_on<F: Future>(future: F) -> F::Output {
    struct Unpark(std::thread::Thread);
    impl Wake for Unpark {
        fn wake(self: Arc<Self>) {
            self.0.unpark();
        }
    }
    let waker = Waker::from(Arc::new(Unpark(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    let mut future = std::pin::pin!(future);
    loop {
        match future.as_mut().poll(&mut cx) {
            Poll::Ready(value) => return value,
            Poll::Pending => std::thread::park(),
        }
    }
}
