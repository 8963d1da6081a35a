//! `scatterfarm adapters`: every GPU adapter wgpu finds, with the limits that matter here.

use anyhow::Result;
use clap::Args;
use scatterfarm_engines::gpu;

#[derive(Debug, Args)]
pub struct AdaptersArgs {
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: AdaptersArgs) -> Result<()> {
    let adapters = gpu::list_adapters();
    if args.json {
        let rows: Vec<_> = adapters
            .iter()
            .map(|a| {
                serde_json::json!({
                    "index": a.index, "name": a.name, "backend": a.backend, "type": a.device_type,
                    "driver": a.driver,
                    "max_storage_buffer_binding_size": a.max_storage_buffer_binding_size,
                    "max_buffer_size": a.max_buffer_size,
                    "max_compute_invocations_per_workgroup": a.max_compute_invocations_per_workgroup,
                    "max_compute_workgroups_per_dimension": a.max_compute_workgroups_per_dimension,
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&rows)?);
        return Ok(());
    }
    if adapters.is_empty() {
        eprintln!(
            "no GPU adapter found: renders use the CPU engine (for a software Vulkan device, install Mesa's \
             Vulkan drivers, e.g. Debian's mesa-vulkan-drivers)"
        );
        return Ok(());
    }
    println!(
        "{:<5} {:<36} {:<8} {:<14} {:>12} {:>12} {:>10} {:>10}  driver",
        "index", "name", "backend", "type", "storage MiB", "buffer MiB", "wg invoc", "wg/dim"
    );
    for a in adapters {
        println!(
            "{:<5} {:<36} {:<8} {:<14} {:>12} {:>12} {:>10} {:>10}  {}",
            a.index,
            a.name,
            a.backend,
            a.device_type,
            a.max_storage_buffer_binding_size >> 20,
            a.max_buffer_size >> 20,
            a.max_compute_invocations_per_workgroup,
            a.max_compute_workgroups_per_dimension,
            a.driver
        );
    }
    Ok(())
}
