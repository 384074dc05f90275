//! Per-kernel GPU time, to find where a workload spends it. With `VELOX_PROFILE=1` every
//! recorder writes a timestamp before each dispatch and one at submit, and charges each interval
//! to the dispatch it begins with (a barrier before the dispatch included). The totals gather
//! over the whole process; [`report`] formats them. A GPU that overlaps independent dispatches
//! blurs the split between neighbours, so read the figures as a guide; lavapipe runs dispatches
//! one after the other, so there they are exact.

use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

/// Whether `VELOX_PROFILE` is set (to anything but `0`), read once.
pub fn enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("VELOX_PROFILE").is_some_and(|v| v != "0"))
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
    let mut out = format!(
        "GPU time by kernel (VELOX_PROFILE): {count} dispatches, {:.1} ms\n{:<44} {:>9} {:>11} {:>6} {:>10}\n",
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
