//! `velox info`: devices, the chosen one, its features and limits, and the kernel variants.

use std::path::Path;

use serde_json::json;
use velox_engine::ops::raster::BackwardKernel;
use velox_engine::ops::{matmul, scatter_add};
use velox_engine::{list_devices, DType, Gpu};

use crate::CliResult;

fn mib(bytes: u64) -> String {
    format!("{:.0} MiB", bytes as f64 / (1024.0 * 1024.0))
}

pub fn run(json_path: Option<&Path>, probe: bool) -> CliResult<()> {
    let devices = list_devices()?;
    println!("Vulkan devices:");
    for d in &devices {
        let note = d.unusable.as_ref().map(|w| format!("  [cannot be used: {w}]")).unwrap_or_default();
        println!("  {}: {} ({}, Vulkan {}){note}", d.index, d.name, d.kind, d.api_version);
    }
    let gpu = Gpu::new()?;
    let c = gpu.caps();
    let mut report = report(&gpu);
    if probe {
        let (reported, counted) = velox_engine::ops::subgroup_probe::sizes(&gpu)?;
        report["subgroup_probe"] = json!({ "builtin": reported, "lanes": counted });
    }
    println!();
    println!("Chosen device {}: {} ({})", c.index, c.name, c.kind);
    if let Ok(v) = std::env::var("VELOX_DEVICE") {
        println!("  (chosen by VELOX_DEVICE={v})");
    }
    println!("  driver            {}", c.driver);
    println!("  Vulkan            {}", c.api_version);
    println!(
        "  memory            {} device-local{}",
        mib(c.device_memory),
        if c.unified_memory { ", host-visible (no staging)" } else { "" }
    );
    println!(
        "  subgroup size     {} (range {}..{}{}){}",
        c.subgroup_size,
        c.min_subgroup_size,
        c.max_subgroup_size,
        if c.subgroup_size_control { ", controllable" } else { "" },
        match report["subgroup_probe"]["lanes"].as_u64() {
            Some(n) if n != c.subgroup_size as u64 =>
                format!("; {n} measured: the driver misreports (the kernels count their lanes)"),
            Some(n) => format!("; {n} measured"),
            None => String::new(),
        }
    );
    println!("  shared memory     {} KiB per workgroup", c.max_shared_memory / 1024);
    println!(
        "  workgroups        {} invocations, counts {:?}",
        c.max_workgroup_invocations, c.max_workgroup_count
    );
    println!(
        "  storage binding   {} max range, buffers up to {}",
        mib(c.max_storage_buffer_range),
        mib(c.max_buffer_size)
    );
    println!("  push constants    {} bytes", c.max_push_constants);
    if c.texel_reads {
        println!(
            "  texel buffers     vec4 views of tensors, up to {} texels, offsets a multiple of {} bytes{}",
            c.max_texel_buffer_elements,
            c.min_texel_buffer_offset_alignment,
            if c.texel_kernels() { " (the CPU kernels read through them)" } else { "" }
        );
    } else {
        println!("  texel buffers     none of vec4s (the CPU kernels' matmul and softmax are not taken)");
    }
    println!("  f16               arithmetic {}, storage {}", yes(c.f16_arithmetic), yes(c.f16_storage));
    println!("  f32 atomic add    {}", yes(c.float_atomic_add));
    println!("  timestamps        {} ({} ns per tick)", yes(c.timestamps), c.timestamp_period_ns);
    println!(
        "  buffer binding    {}",
        if c.push_descriptors { "push descriptors" } else { "descriptor sets, one per dispatch" }
    );
    println!("  validation        {} (VELOX_VALIDATE)", gpu.validation().name());
    println!(
        "  kernels           {} variants (VELOX_CPU_KERNELS=1 or 0 chooses)",
        if c.cpu_kernels { "CPU" } else { "GPU" }
    );
    println!(
        "  robust access     {} (VELOX_ROBUST=1 enables it{})",
        if c.robust_buffer_access { "on" } else { "off" },
        if c.robust_buffer_access_available { "" } else { "; this device does not offer it" }
    );
    if c.portability_subset {
        println!("  portability       a portability implementation (VK_KHR_portability_subset, as MoltenVK)");
    }
    if !c.forced.is_empty() {
        println!(
            "  forced fallbacks  {} (VELOX_DISABLE, VELOX_MAX_BINDING, VELOX_ROBUST, VELOX_CPU_KERNELS)",
            c.forced.join(", ")
        );
    }
    if c.coop_matrix_shapes.is_empty() {
        println!("  coop matrices     none");
    } else {
        println!("  coop matrices     {}", c.coop_matrix_shapes.join(", "));
    }
    println!();
    println!("Kernel variants on this device:");
    let variants = report["variants"].as_object().unwrap();
    let width = variants.keys().map(|k| k.len() + 2).max().unwrap_or(0).max(18);
    for (k, v) in variants {
        println!("  {k:<width$}{}", v.as_str().unwrap_or(""));
    }
    if let Some(path) = json_path {
        velox_io::write_bytes(path, serde_json::to_string_pretty(&report)?.as_bytes())?;
        println!("\nwrote {}", path.display());
    }
    Ok(())
}

fn yes(b: bool) -> &'static str {
    if b {
        "yes"
    } else {
        "no"
    }
}

/// The device report as JSON (shared with the demo).
pub fn report(gpu: &Gpu) -> serde_json::Value {
    let c = gpu.caps();
    let raster_backward = match velox_engine::ops::raster::backward::variant(gpu) {
        Ok(v) => v.1.to_string(),
        Err(e) => format!("unsupported: {e}"),
    };
    let bench_kernel = BackwardKernel::fastest(gpu);
    let raster_backward_bench = match bench_kernel.check(gpu) {
        Ok(()) => format!(
            "{}; `velox bench raster` times it beside the deterministic kernel",
            bench_kernel.describe()
        ),
        Err(e) => format!("unsupported: {e}"),
    };
    // Apart, as one json! of everything passes the macro's recursion limit.
    let variants = json!({
        "matmul f32": matmul::matmul_variant(gpu, DType::F32),
        "matmul f16": matmul::matmul_variant(gpu, DType::F16),
        "rows (softmax, norms)": velox_engine::ops::rmsnorm::row_variant(gpu),
        "attention f32": velox_engine::ops::attention::portable_variant(gpu, 32, DType::F32),
        "attention f16": velox_engine::ops::attention::f16_forward_variant(gpu, 32),
        "attention f16 backward": velox_engine::ops::attention::f16_backward_variant(gpu, 32),
        "scatter-add": scatter_add::variant(gpu),
        "gather": velox_engine::ops::gather::variant(gpu),
        "fps": velox_engine::ops::fps::variant(gpu).1,
        "sort": format!("LSD radix, {}", velox_engine::ops::sort::Radix::chosen(gpu).describe()),
        "scan": "workgroup-memory block scan, multi-level",
        "raster backward": raster_backward,
        "raster backward (bench)": raster_backward_bench,
        "training steps": if velox_models::train::trainer::overlaps_by_default(gpu) {
            "each micro-batch recorded while the last runs, with one process (train --overlap off records after its wait)"
        } else {
            "each recorded after the last one's wait: a CPU device's work shares the host's cores (train --overlap on records while the last runs)"
        },
        "determinism": "training and decoding give the same bits for the same seed on the same device: every reduction sums in a fixed order (scatter-add's atomics add once per row where the models use it)",
    });
    json!({
        "device": c.name, "kind": c.kind, "driver": c.driver, "vulkan": c.api_version,
        "device_memory_bytes": c.device_memory, "unified_memory": c.unified_memory,
        "subgroup_size": c.subgroup_size, "min_subgroup_size": c.min_subgroup_size,
        "max_subgroup_size": c.max_subgroup_size, "max_shared_memory": c.max_shared_memory,
        "max_workgroup_invocations": c.max_workgroup_invocations,
        "max_workgroup_count": c.max_workgroup_count,
        "max_storage_buffer_range": c.max_storage_buffer_range, "max_buffer_size": c.max_buffer_size,
        "f16_arithmetic": c.f16_arithmetic, "f16_storage": c.f16_storage,
        "float_atomic_add": c.float_atomic_add, "subgroup_arithmetic": c.subgroup_arithmetic,
        "subgroup_shuffle": c.subgroup_shuffle, "subgroup_ballot": c.subgroup_ballot, "coop_matrix_shapes": c.coop_matrix_shapes,
        "timestamps": c.timestamps, "push_descriptors": c.push_descriptors,
        "validation": gpu.validation().name(), "forced_fallbacks": c.forced,
        "portability_subset": c.portability_subset, "robust_buffer_access": c.robust_buffer_access,
        "vulkan_memory_model": c.vulkan_memory_model, "cpu_kernels": c.cpu_kernels,
        "texel_reads": c.texel_reads, "max_texel_buffer_elements": c.max_texel_buffer_elements,
        "variants": variants,
    })
}
