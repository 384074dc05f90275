// What one workgroup's subgroups really are, for `velox info` and engine/tests/ops/subgroups.rs (host side
// engine/src/ops/subgroups.rs). Every invocation writes one row: its subgroup id, the number of
// subgroups, its lane, the `subgroup_size` builtin, its subgroup's lanes counted with
// subgroupAdd, and the largest local index in its subgroup (subgroupMax). The engine's kernels
// rely on the counted lanes, the ids and the reductions agreeing; a driver may report another
// size in the builtin (lavapipe at LP_NATIVE_VECTOR_WIDTH=1024 says 32 and runs 16).

const WG: u32 = 256u;
const ROW: u32 = 6u;

@group(0) @binding(0) var<storage, read_write> rows: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32, @builtin(subgroup_id) sg: u32,
        @builtin(num_subgroups) nsg: u32, @builtin(subgroup_invocation_id) lane: u32,
        @builtin(subgroup_size) size: u32) {
    let counted = subgroupAdd(1u);
    let top = subgroupMax(lid);
    let o = lid * ROW;
    rows[o] = sg;
    rows[o + 1u] = nsg;
    rows[o + 2u] = lane;
    rows[o + 3u] = size;
    rows[o + 4u] = counted;
    rows[o + 5u] = top;
}
