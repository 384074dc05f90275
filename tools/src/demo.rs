//! `velox demo`: the device report and a quick kernel benchmark, written to a folder.

use std::path::Path;

use velox_engine::Gpu;

use crate::bench::{self, Record};
use crate::CliResult;

pub fn run(out: &Path) -> CliResult<()> {
    std::fs::create_dir_all(out).map_err(|e| format!("creating {}: {e}", out.display()))?;
    let gpu = Gpu::new()?;
    let report = crate::info::report(&gpu);
    println!("velox demo on {} ({})\n", gpu.caps().name, gpu.caps().kind);
    let records: Vec<Record> = bench::kernels_quick(&gpu)?;
    let info_path = out.join("device.json");
    std::fs::write(&info_path, serde_json::to_string_pretty(&report)?)
        .map_err(|e| format!("writing {}: {e}", info_path.display()))?;
    bench::write_json(&out.join("bench_kernels.json"), &records)?;
    println!(
        "\nDemo outputs are in {}: device.json (device report), bench_kernels.json (times and errors).",
        out.display()
    );
    Ok(())
}
