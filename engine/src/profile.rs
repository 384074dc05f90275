//! Per-kernel GPU time, to find where a workload spends it. With `VELOX_PROFILE=1` every
//! recorder writes a timestamp before each dispatch and one at submit, and charges each interval
//! to the dispatch it begins with (a barrier before the dispatch included). The totals gather
//! over the whole process; [`report`] formats them. A GPU that overlaps independent dispatches
//! blurs the split between neighbours, so read the figures as a guide; lavapipe runs dispatches
//! one after the other, so there they are exact.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};

/// Profiling turned on from code ([`set_enabled`]), beside the environment variable.
static FORCED: AtomicBool = AtomicBool::new(false);

/// Dispatches recorded by every recorder of the process, profiled or not.
static DISPATCHES: AtomicU64 = AtomicU64::new(0);

/// Dispatches recorded so far by the whole process (a cheap count, always kept): the
/// difference across a piece of work is what it recorded, when nothing else records meanwhile.
pub fn dispatches() -> u64 {
    DISPATCHES.load(Ordering::Relaxed)
}

pub(crate) fn count_dispatch() {
    DISPATCHES.fetch_add(1, Ordering::Relaxed);
}

/// Submissions by every recorder of the process. Each is also a host wait: a recorder's
/// submit waits for its work to finish.
static SUBMITS: AtomicU64 = AtomicU64::new(0);

/// Submissions (each with its host wait) so far by the whole process, counted as
/// [`dispatches`] are.
pub fn submits() -> u64 {
    SUBMITS.load(Ordering::Relaxed)
}

pub(crate) fn count_submit() {
    SUBMITS.fetch_add(1, Ordering::Relaxed);
}

/// Whether `VELOX_PROFILE` is set (to anything but `0`, read once), or [`set_enabled`] turned
/// profiling on.
pub fn enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    FORCED.load(Ordering::Relaxed)
        || *ON.get_or_init(|| std::env::var_os("VELOX_PROFILE").is_some_and(|v| v != "0"))
}

/// Turns profiling on or off for recorders created from now on (a benchmark that profiles
/// one step of several); `VELOX_PROFILE` keeps it on regardless.
pub fn set_enabled(on: bool) {
    FORCED.store(on, Ordering::Relaxed);
}

/// One kernel's totals: dispatches and GPU nanoseconds.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelTotal {
    pub kernel: String,
    pub dispatches: u64,
    pub ns: f64,
}

/// The totals gathered so far, longest first, and clears them.
pub fn take() -> Vec<KernelTotal> {
    let mut t = totals().lock().unwrap();
    let mut rows: Vec<KernelTotal> =
        t.drain().map(|(kernel, (dispatches, ns))| KernelTotal { kernel, dispatches, ns }).collect();
    rows.sort_by(|a, b| b.ns.total_cmp(&a.ns));
    rows
}

/// The family a kernel (`file::entry`) belongs to, for a step's time by kind of work: matrix
/// products, attention, norms, elementwise passes, reductions, layouts (sorts, scans, windows,
/// cells), rasterisation, the optimiser. A module built at several workgroup sizes
/// (`rmsnorm_wg8`, `fps_wg1024`) is of its source's family.
pub fn family(kernel: &str) -> &'static str {
    let file = kernel.split("::").next().unwrap_or(kernel);
    let file = match file.rsplit_once("_wg") {
        Some((source, size)) if !size.is_empty() && size.bytes().all(|b| b.is_ascii_digit()) => source,
        _ => file,
    };
    match file {
        f if f.starts_with("matmul") => "matmul",
        f if f.starts_with("attention") => "attention",
        f if f.starts_with("raster") || f == "gaussian_head" || f == "mesh_raster" => "raster",
        "rmsnorm" | "layernorm" => "norm",
        "reduce" | "loss" => "reduce",
        "sort" | "scan" | "window" | "assign" | "fps" | "fps_order" | "gather" | "scatter_add"
        | "columns" | "concat" => "layout",
        "adamw" | "norm" => "optimiser",
        "cast" => "cast",
        _ => "elementwise",
    }
}

/// kernel name -> (dispatches, nanoseconds).
fn totals() -> &'static Mutex<HashMap<String, (u64, f64)>> {
    static TOTALS: OnceLock<Mutex<HashMap<String, (u64, f64)>>> = OnceLock::new();
    TOTALS.get_or_init(Default::default)
}

pub(crate) fn add(kernel: String, ns: f64) {
    let mut t = totals().lock().unwrap();
    let e = t.entry(kernel).or_insert((0, 0.0));
    e.0 += 1;
    e.1 += ns;
}

/// The totals so far as a table, longest first (`None` when nothing was profiled).
pub fn report() -> Option<String> {
    let t = totals().lock().unwrap();
    if t.is_empty() {
        return None;
    }
    let mut rows: Vec<(&String, &(u64, f64))> = t.iter().collect();
    rows.sort_by(|a, b| b.1 .1.total_cmp(&a.1 .1));
    let all: f64 = rows.iter().map(|r| r.1 .1).sum();
    let count: u64 = rows.iter().map(|r| r.1 .0).sum();
    let recorded = dispatches();
    let untimed = match recorded.saturating_sub(count) {
        0 => String::new(),
        n => format!(" ({n} more recorded without a timestamp)"),
    };
    let mut out = format!(
        "GPU time by kernel (VELOX_PROFILE): {count} dispatches{untimed}, {:.1} ms\n{:<44} {:>9} {:>11} {:>6} {:>10}\n",
        all / 1e6,
        "kernel",
        "calls",
        "total ms",
        "%",
        "us/call"
    );
    for (name, &(n, ns)) in rows {
        out += &format!(
            "{name:<44} {n:>9} {:>11.2} {:>6.1} {:>10.1}\n",
            ns / 1e6,
            100.0 * ns / all.max(1e-9),
            ns / 1e3 / n as f64
        );
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::family;

    /// Would catch: a kernel built at a second workgroup size (the CPU row variants) counted
    /// as elementwise work, which `velox bench train`'s split by family showed as no norm time.
    #[test]
    fn every_variant_is_of_its_sources_family() {
        for (kernel, want) in [
            ("rmsnorm_wg256::forward", "norm"),
            ("rmsnorm_wg8::backward", "norm"),
            ("layernorm_wg8::forward", "norm"),
            ("fps_wg1024::fps", "layout"),
            ("fps_order::order", "layout"),
            ("matmul_cpu_layout1_cols4::main", "matmul"),
            ("attention_coop8_d16_bq64::forward", "attention"),
            ("norm::sum_squares", "optimiser"),
            ("raster_backward_cas::main", "raster"),
        ] {
            assert_eq!(family(kernel), want, "{kernel}");
        }
    }
}
