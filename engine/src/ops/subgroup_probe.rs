//! What a workgroup's subgroups really are on this device: one dispatch of
//! `shaders/subgroup_probe.wgsl`, read back. `velox info` shows it beside the size the driver
//! reports, and `engine/tests/ops/subgroups.rs` checks that the ids, counts and reductions the kernels rely
//! on agree with each other.
//!
//! The kernels never read the `subgroup_size` builtin: they count their subgroup's lanes with
//! `subgroupAdd(1)`. Drivers can disagree with themselves here: lavapipe (Mesa 25.0) with
//! `LP_NATIVE_VECTOR_WIDTH=1024` reports subgroups of 32 (property and builtin) while its
//! subgroup ids, counts and reductions run over 16 invocations.
//!
//! Tests: `engine/tests/ops/subgroups.rs` (the ids, counts and reductions the kernels rely on).

use crate::device::Gpu;
use crate::error::Result;
use crate::kernels::args;
use crate::kernels::SUBGROUP_PROBE_MAIN;
use crate::tensor::{DType, Tensor};

/// Invocations of the probe's one workgroup.
pub const WORKGROUP: usize = 256;
const ROW: usize = 6;

/// One invocation's view of its subgroup.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Lane {
    pub subgroup_id: u32,
    pub num_subgroups: u32,
    pub lane: u32,
    /// The `subgroup_size` builtin.
    pub reported_size: u32,
    /// The subgroup's invocations counted with `subgroupAdd(1)`.
    pub counted_size: u32,
    /// `subgroupMax` of the local invocation index.
    pub max_local_index: u32,
}

/// Every invocation of the probe's workgroup, by local index.
pub fn probe(gpu: &Gpu) -> Result<Vec<Lane>> {
    let rows = Tensor::empty(gpu, &[WORKGROUP * ROW], DType::U32)?;
    let mut rec = gpu.recorder()?;
    rec.dispatch(SUBGROUP_PROBE_MAIN, [1, 1, 1], args::SubgroupProbeMainArgs { rows: &rows }, &())?;
    rec.submit()?;
    let raw = rows.read::<u32>()?;
    Ok(raw
        .chunks_exact(ROW)
        .map(|r| Lane {
            subgroup_id: r[0],
            num_subgroups: r[1],
            lane: r[2],
            reported_size: r[3],
            counted_size: r[4],
            max_local_index: r[5],
        })
        .collect())
}

/// `(reported, counted)`: the `subgroup_size` builtin and the lanes a subgroup really has, as
/// invocation 0 sees them.
pub fn sizes(gpu: &Gpu) -> Result<(u32, u32)> {
    let lanes = probe(gpu)?;
    Ok((lanes[0].reported_size, lanes[0].counted_size))
}
