// 4D voxel windows of points (x, y, z, tau * time_scale), and the grouping of points by window
// into variable-length segments. Host side and format: engine/src/ops/window.rs.
//
// `window_ids`: one invocation per point. The cell along each axis is
// floor((p - origin) * inv_cell) in f32, clamped to [0, cells - 1], so points outside the grid
// land in the border cell; the CPU reference computes the same f32 expression, so ids agree
// bit for bit (sub and mul are correctly rounded in Vulkan, and there is no a * b + c to
// contract). The id is the row-major index over (x, y, z, t): t varies fastest.
//
// `heads`, `segments`: after the host has sorted (id, point index) pairs by id, `heads` flags
// the first element of each run of equal ids, the host scans the flags, and `segments` writes
// each run's start to its place in the compact offsets list, with the run's window id.

struct WindowParams {
    origin: vec4<f32>,
    inv_cell: vec4<f32>,
    cells: vec4<u32>,
    n: u32,
    capacity: u32, // `segments`: entries of segment_ids (offsets has one more)
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<storage, read> points: array<f32>;
@group(0) @binding(1) var<storage, read_write> ids: array<u32>;
@group(0) @binding(2) var<storage, read> sorted_ids: array<u32>;
@group(0) @binding(3) var<storage, read_write> flags: array<u32>;
@group(0) @binding(4) var<storage, read> positions: array<u32>;
@group(0) @binding(5) var<storage, read_write> offsets: array<u32>;
@group(0) @binding(6) var<storage, read_write> segment_ids: array<u32>;
var<immediate> pc: WindowParams;

fn linear_index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * 256u + lid;
}

// Cell along one axis; a NaN coordinate gives some cell in range, never one outside.
fn axis_cell(v: f32, origin: f32, inv_cell: f32, cells: u32) -> u32 {
    let c = floor((v - origin) * inv_cell);
    let top = f32(cells - 1u);
    let clamped = min(max(c, 0.0), top);
    return min(u32(clamped), cells - 1u);
}

@compute @workgroup_size(256)
fn window_ids(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let i = linear_index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    let cx = axis_cell(points[4u * i], pc.origin.x, pc.inv_cell.x, pc.cells.x);
    let cy = axis_cell(points[4u * i + 1u], pc.origin.y, pc.inv_cell.y, pc.cells.y);
    let cz = axis_cell(points[4u * i + 2u], pc.origin.z, pc.inv_cell.z, pc.cells.z);
    let ct = axis_cell(points[4u * i + 3u], pc.origin.w, pc.inv_cell.w, pc.cells.w);
    ids[i] = ((cx * pc.cells.y + cy) * pc.cells.z + cz) * pc.cells.w + ct;
}

fn is_head(i: u32) -> bool {
    return i == 0u || sorted_ids[i] != sorted_ids[i - 1u];
}

@compute @workgroup_size(256)
fn heads(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = linear_index(wid, nwg, lid);
    if (i < pc.n) {
        flags[i] = select(0u, 1u, is_head(i));
    }
}

// `positions` is the exclusive scan of the flags: a head's segment number. The entries from
// the segment count on (count <= capacity <= n, so invocation i covers entry i) read as empty
// segments ending at n with no window (0xffffffff), and offsets[capacity] is n.
@compute @workgroup_size(256)
fn segments(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let i = linear_index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    if (is_head(i)) {
        let s = positions[i];
        offsets[s] = i;
        segment_ids[s] = sorted_ids[i];
    }
    let count = positions[pc.n - 1u] + flags[pc.n - 1u];
    if (i >= count && i < pc.capacity) {
        offsets[i] = pc.n;
        segment_ids[i] = 0xffffffffu;
    }
    if (i == 0u) {
        offsets[pc.capacity] = pc.n;
    }
}
