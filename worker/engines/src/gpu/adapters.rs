//! Finding and choosing GPU adapters: what `scatterfarm adapters` lists and what `--adapter` and
//! `--engine auto` pick.
//!
//! Adapters are numbered in wgpu's enumeration order (Vulkan only: the build drops GL). `Auto`
//! takes the first discrete or integrated GPU, else a virtual GPU, else a CPU device (lavapipe),
//! else anything left; with no adapter at all it is [`EngineError::Unavailable`], and the caller
//! falls back to the CPU engine.

use super::{block_on, silence_mesa_runtime_dir_warning};
use scatterfarm_model::engine::EngineError;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;
use thiserror::Error;

/// One adapter as the CLI shows it: identity, driver, and the limits that bound a render.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct AdapterInfo {
    /// Position in [`list_adapters`]' order; what `--adapter INDEX` names.
    pub index: usize,
    pub name: String,
    /// The wgpu backend, e.g. `vulkan`.
    pub backend: String,
    /// `discrete-gpu`, `integrated-gpu`, `virtual-gpu`, `cpu` or `other`.
    pub device_type: String,
    /// Driver name and driver info, e.g. `llvmpipe (Mesa 22.3.6 (LLVM 15.0.6))`.
    pub driver: String,
    pub max_storage_buffer_binding_size: u64,
    pub max_buffer_size: u64,
    pub max_compute_invocations_per_workgroup: u32,
    pub max_compute_workgroups_per_dimension: u32,
}

impl AdapterInfo {
    pub(crate) fn from_wgpu(index: usize, adapter: &wgpu::Adapter) -> AdapterInfo {
        let info = adapter.get_info();
        let limits = adapter.limits();
        AdapterInfo {
            index,
            name: info.name.clone(),
            backend: info.backend.to_str().to_string(),
            device_type: device_type_name(info.device_type).to_string(),
            driver: driver_string(&info),
            max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
            max_buffer_size: limits.max_buffer_size,
            max_compute_invocations_per_workgroup: limits.max_compute_invocations_per_workgroup,
            max_compute_workgroups_per_dimension: limits.max_compute_workgroups_per_dimension,
        }
    }

    /// True for a CPU device such as lavapipe.
    pub fn is_cpu(&self) -> bool {
        self.device_type == device_type_name(wgpu::DeviceType::Cpu)
    }
}

impl fmt::Display for AdapterInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "[{}] {} ({}, {}, driver {})",
            self.index, self.name, self.device_type, self.backend, self.driver
        )
    }
}

fn device_type_name(t: wgpu::DeviceType) -> &'static str {
    match t {
        wgpu::DeviceType::DiscreteGpu => "discrete-gpu",
        wgpu::DeviceType::IntegratedGpu => "integrated-gpu",
        wgpu::DeviceType::VirtualGpu => "virtual-gpu",
        wgpu::DeviceType::Cpu => "cpu",
        wgpu::DeviceType::Other => "other",
    }
}

fn driver_string(info: &wgpu::AdapterInfo) -> String {
    match (info.driver.is_empty(), info.driver_info.is_empty()) {
        (false, false) => format!("{} ({})", info.driver, info.driver_info),
        (false, true) => info.driver.clone(),
        (true, false) => info.driver_info.clone(),
        (true, true) => "unknown".to_string(),
    }
}

/// Which adapter to use: `--adapter INDEX|NAME`, or `auto`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum AdapterSelector {
    /// The first discrete or integrated GPU, else a virtual GPU, else a CPU device (lavapipe).
    #[default]
    Auto,
    /// The adapter at this position of [`list_adapters`].
    Index(usize),
    /// The first adapter whose name contains this text (case-insensitive), or whose PCI bus
    /// address is exactly this text.
    Name(String),
}

/// Why an `--adapter` argument is not a selector.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum AdapterSelectorError {
    #[error("an adapter selector must be an index, a name or \"auto\", got an empty string")]
    Empty,
}

impl FromStr for AdapterSelector {
    type Err = AdapterSelectorError;

    /// A number is an index, `auto` is [`AdapterSelector::Auto`], anything else a name.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s.is_empty() {
            return Err(AdapterSelectorError::Empty);
        }
        if s.eq_ignore_ascii_case("auto") {
            return Ok(AdapterSelector::Auto);
        }
        Ok(match s.parse::<usize>() {
            Ok(index) => AdapterSelector::Index(index),
            Err(_) => AdapterSelector::Name(s.to_string()),
        })
    }
}

impl fmt::Display for AdapterSelector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            AdapterSelector::Auto => write!(f, "auto"),
            AdapterSelector::Index(i) => write!(f, "{i}"),
            AdapterSelector::Name(n) => write!(f, "{n}"),
        }
    }
}

/// A wgpu instance on every backend this build has (Vulkan).
pub(crate) fn new_instance() -> wgpu::Instance {
    silence_mesa_runtime_dir_warning();
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::all();
    wgpu::Instance::new(desc)
}

/// Every adapter of `instance`, in enumeration order.
pub(crate) fn enumerate(instance: &wgpu::Instance) -> Vec<wgpu::Adapter> {
    block_on(instance.enumerate_adapters(wgpu::Backends::all()))
}

/// Every adapter this machine offers, numbered as `--adapter INDEX` takes them. Empty when there
/// is no Vulkan driver.
pub fn list_adapters() -> Vec<AdapterInfo> {
    let instance = new_instance();
    enumerate(&instance)
        .iter()
        .enumerate()
        .map(|(i, a)| AdapterInfo::from_wgpu(i, a))
        .collect()
}

/// The adapter `selector` picks among `infos` (whose PCI bus addresses are `pci`), and why.
pub(crate) fn choose(
    infos: &[AdapterInfo],
    pci: &[String],
    selector: &AdapterSelector,
) -> Result<(usize, String), EngineError> {
    if infos.is_empty() {
        return Err(EngineError::Unavailable(
            "no GPU adapter found (no Vulkan driver? on Debian install mesa-vulkan-drivers and libvulkan1 \
             for lavapipe)"
                .to_string(),
        ));
    }
    let listing = || {
        infos
            .iter()
            .map(|a| a.to_string())
            .collect::<Vec<_>>()
            .join("; ")
    };
    match selector {
        AdapterSelector::Index(i) => {
            if *i < infos.len() {
                Ok((*i, format!("adapter index {i} was asked for")))
            } else {
                Err(EngineError::Unavailable(format!(
                    "no adapter with index {i}: there are {} ({})",
                    infos.len(),
                    listing()
                )))
            }
        }
        AdapterSelector::Name(name) => {
            let wanted = name.to_lowercase();
            let by_name = infos
                .iter()
                .position(|a| a.name.to_lowercase().contains(&wanted));
            let by_pci = || {
                pci.iter()
                    .position(|p| !p.is_empty() && p.eq_ignore_ascii_case(name))
            };
            match by_name.or_else(by_pci) {
                Some(i) => Ok((i, format!("its name or PCI address matches {name:?}"))),
                None => Err(EngineError::Unavailable(format!(
                    "no adapter whose name contains {name:?}: adapters are {}",
                    listing()
                ))),
            }
        }
        AdapterSelector::Auto => {
            let first = |types: &[&str]| {
                infos
                    .iter()
                    .position(|a| types.contains(&a.device_type.as_str()))
            };
            if let Some(i) = first(&["discrete-gpu", "integrated-gpu"]) {
                return Ok((i, "auto: the first discrete or integrated GPU".to_string()));
            }
            if let Some(i) = first(&["virtual-gpu"]) {
                return Ok((
                    i,
                    "auto: no discrete or integrated GPU; the first virtual GPU".to_string(),
                ));
            }
            if let Some(i) = first(&["cpu"]) {
                return Ok((
                    i,
                    "auto: no hardware GPU; the first CPU device (lavapipe or similar)".to_string(),
                ));
            }
            Ok((
                0,
                "auto: no GPU or CPU device type reported; the first adapter".to_string(),
            ))
        }
    }
}
