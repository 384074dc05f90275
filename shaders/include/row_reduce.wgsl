// Rows of a workgroup, and sums and maxima over each row. The WG invocations form groups of
// `lanes` consecutive invocations (a power of two from 1 to WG, the same for the whole
// dispatch: a push constant), and each group owns one row, its invocations striding over it
// by `lanes`. Narrow rows then share a workgroup instead of leaving most of WG invocations
// idle: `row_lanes` in engine/src/ops/rmsnorm.rs picks about 4 elements per invocation.
// Included by the row kernels: softmax, RMSNorm, LayerNorm, each built twice: WG = 256 for
// GPUs, and WG = 8 with one row per invocation (lanes 1) for CPU devices, where a workgroup is
// one SIMD group and the trees below reduce to a copy (lavapipe runs a barrier as a switch
// between every SIMD group of the workgroup: 32 of them at 256).
const WG: u32 = 256u;
//
// The reductions are trees in workgroup memory within each group; every invocation of the
// workgroup must call them (they hold barriers), and every one gets its own row's result. A
// row of one lane is its own sum, without a barrier (`lanes` is uniform, so every invocation
// takes the same way).

var<workgroup> partial: array<f32, WG>;

// Where invocation `lid` works: its row, its lane within the row's group, and whether the row
// exists. `first_row` of the workgroup is uniform, so a workgroup past the end can return
// before any barrier.
struct RowSlot {
    first_row: u32,
    row: u32,
    lane: u32,
    live: bool,
}

fn row_slot(wid: vec3<u32>, nwg: vec3<u32>, lid: u32, lanes: u32, rows: u32) -> RowSlot {
    let first = (wid.x + wid.y * nwg.x) * (WG / lanes);
    let row = first + lid / lanes;
    return RowSlot(first, row, lid % lanes, row < rows);
}

fn reduce_sum(lid: u32, lanes: u32, v: f32) -> f32 {
    if (lanes == 1u) {
        return v;
    }
    partial[lid] = v;
    workgroupBarrier();
    for (var s = lanes / 2u; s > 0u; s >>= 1u) {
        if ((lid & (lanes - 1u)) < s) {
            partial[lid] = partial[lid] + partial[lid + s];
        }
        workgroupBarrier();
    }
    let r = partial[lid & ~(lanes - 1u)];
    workgroupBarrier();
    return r;
}

fn reduce_max(lid: u32, lanes: u32, v: f32) -> f32 {
    if (lanes == 1u) {
        return v;
    }
    partial[lid] = v;
    workgroupBarrier();
    for (var s = lanes / 2u; s > 0u; s >>= 1u) {
        if ((lid & (lanes - 1u)) < s) {
            partial[lid] = max(partial[lid], partial[lid + s]);
        }
        workgroupBarrier();
    }
    let r = partial[lid & ~(lanes - 1u)];
    workgroupBarrier();
    return r;
}
