//! The subgroups a device runs, as the kernels see them: ids, counts and reductions must agree
//! with each other, whatever size the driver reports (see `engine/src/ops/subgroup_probe.rs`).
//! Would catch: a driver (or a lavapipe width setting) under which `subgroup_id`,
//! `num_subgroups`, the lane index and `subgroupAdd`/`subgroupMax` disagree, which would make
//! every subgroup reduction in the kernels (FPS's argmax, the raster backward's sums) wrong.

use crate::common;
use common::*;
use velox_engine::ops::subgroup_probe::{probe, WORKGROUP};

#[test]
fn subgroup_ids_counts_and_reductions_agree() {
    let gpu = gpu();
    if !gpu.caps().subgroup_arithmetic {
        let err = probe(&gpu).unwrap_err();
        return assert!(matches!(err, velox_engine::Error::Unsupported { .. }), "{err}");
    }
    let lanes = probe(&gpu).unwrap();
    let size = lanes[0].counted_size as usize;
    assert!(size.is_power_of_two() && WORKGROUP.is_multiple_of(size), "{size} lanes in a subgroup");
    for (lid, l) in lanes.iter().enumerate() {
        let what = format!("invocation {lid}: {l:?}");
        assert_eq!(l.counted_size as usize, size, "{what}");
        assert_eq!(l.num_subgroups as usize, WORKGROUP / size, "{what}");
        assert_eq!(l.subgroup_id as usize, lid / size, "{what}");
        assert_eq!(l.lane as usize, lid % size, "{what}");
        assert_eq!(l.max_local_index as usize, (lid / size + 1) * size - 1, "{what}");
    }
    let reported = lanes[0].reported_size;
    if reported as usize != size {
        eprintln!(
            "note: this driver reports subgroups of {reported} (range {}..={}) but runs {size}; \
             the kernels count their lanes, so they are unaffected",
            gpu.caps().min_subgroup_size,
            gpu.caps().max_subgroup_size
        );
    }
}
