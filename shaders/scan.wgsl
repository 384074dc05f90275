// Exclusive prefix scan of u32 (wrapping add), one level of a multi-level scan.
//
// A block is 256 invocations x `pc.items` consecutive elements each. `block_scan`: each
// invocation sums its elements, the workgroup scans those 256 sums in workgroup memory, and
// each invocation then writes its elements' exclusive prefixes in order; the block's total goes
// to `block_sums`. `add_block_offsets`: once the host has scanned the block sums (recursively,
// with these same two kernels), each element gets its block's offset added. Several elements
// per invocation keep the workgroup scan (and its barriers) to a small share of the work; one
// element per invocation is what lets the tests reach more than 65535 workgroups on lavapipe.
// The workgroup scan uses shared memory only, never subgroup operations, so it does not depend
// on the subgroup size (8 on lavapipe, 32 on NVIDIA, 64 on AMD).
//
// u32 arithmetic in WGSL wraps, which gives the modulo-2^32 semantics of the CPU reference.

struct Params {
    n: u32,
    items: u32,
}

const WG: u32 = 256u;

@group(0) @binding(0) var<storage, read> src: array<u32>;
@group(0) @binding(1) var<storage, read_write> dst: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;
@group(0) @binding(3) var<storage, read> block_offsets: array<u32>;
var<immediate> pc: Params;

// Two rows so each Hillis-Steele step reads one row and writes the other (one barrier a step).
var<workgroup> rows: array<array<u32, WG>, 2>;

@compute @workgroup_size(256)
fn block_scan(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let block = wid.x + wid.y * nwg.x;
    let start = block * WG * pc.items;
    // Uniform across the workgroup, so returning before the barriers is safe.
    if (start >= pc.n) {
        return;
    }
    let first = start + lid * pc.items;
    var own = 0u;
    for (var j = 0u; j < pc.items; j = j + 1u) {
        if (first + j < pc.n) {
            own = own + src[first + j];
        }
    }
    rows[0][lid] = own;
    workgroupBarrier();
    // Inclusive scan: after the step with `offset`, rows[cur][t] holds the sum of the
    // 2 * offset invocation sums ending at t.
    var cur = 0u;
    var inclusive = own;
    for (var offset = 1u; offset < WG; offset = offset << 1u) {
        if (lid >= offset) {
            inclusive = inclusive + rows[cur][lid - offset];
        }
        rows[1u - cur][lid] = inclusive;
        cur = 1u - cur;
        workgroupBarrier();
    }
    var running = inclusive - own;
    for (var j = 0u; j < pc.items; j = j + 1u) {
        let i = first + j;
        if (i < pc.n) {
            let x = src[i];
            dst[i] = running;
            running = running + x;
        }
    }
    if (lid == WG - 1u) {
        block_sums[block] = inclusive;
    }
}

@compute @workgroup_size(256)
fn add_block_offsets(@builtin(workgroup_id) wid: vec3<u32>,
                     @builtin(num_workgroups) nwg: vec3<u32>,
                     @builtin(local_invocation_index) lid: u32) {
    let block = wid.x + wid.y * nwg.x;
    let start = block * WG * pc.items;
    // Block 0's offset is zero; skipping it saves a read and a write per element there.
    if (block == 0u || start >= pc.n) {
        return;
    }
    let offset = block_offsets[block];
    // Strided so that neighbouring invocations touch neighbouring elements.
    for (var j = 0u; j < pc.items; j = j + 1u) {
        let i = start + j * WG + lid;
        if (i < pc.n) {
            dst[i] = dst[i] + offset;
        }
    }
}
