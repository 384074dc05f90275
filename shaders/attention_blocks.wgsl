// Work lists for segment attention. Rows (queries, or keys in the backward pass) are sorted
// by segment; segment s owns rows offsets[s] .. offsets[s + 1]. Each work item is a block of at
// most BLOCK rows of one segment, written as (segment, first row); unused entries of the list
// stay 0xffffffff and their workgroups exit at once. Empty segments get no items, so they cost
// nothing.
//
// `count`: items[s] = ceil(len(s) / BLOCK). An exclusive scan of `items` (the engine's scan op)
// gives each segment its first item; `write` then writes the items.
// `build`: all of that in one workgroup, for lists of few segments (the host chooses it up to
// BUILD_MAX_SEGMENTS): the segments in chunks of 256, each chunk's counts scanned in workgroup
// memory on top of the earlier chunks' total, then the unused tail of the list marked; one
// dispatch where the other way takes four.

struct Params {
    segments: u32,
    block: u32,
    rows: u32,     // offsets are clamped to the row count, so bad offsets make no bad items
    capacity: u32, // entries in `list`; items past it (only from non-monotonic offsets) are dropped
}

@group(0) @binding(0) var<storage, read> offsets: array<u32>;
@group(0) @binding(1) var<storage, read_write> items: array<u32>;
@group(0) @binding(2) var<storage, read> first_item: array<u32>;
@group(0) @binding(3) var<storage, read_write> list: array<vec2<u32>>;
var<immediate> pc: Params;

@compute @workgroup_size(256)
fn count(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let s = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (s >= pc.segments) {
        return;
    }
    let begin = min(offsets[s], pc.rows);
    let end = clamp(offsets[s + 1u], begin, pc.rows);
    items[s] = (end - begin + pc.block - 1u) / pc.block;
}

@compute @workgroup_size(256)
fn write(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let s = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (s >= pc.segments) {
        return;
    }
    let begin = min(offsets[s], pc.rows);
    let end = clamp(offsets[s + 1u], begin, pc.rows);
    let first = first_item[s];
    var b = 0u;
    for (var row = begin; row < end; row += pc.block) {
        if (first + b < pc.capacity) {
            list[first + b] = vec2<u32>(s, row);
        }
        b += 1u;
    }
}

// Two rows so each scan step reads one and writes the other.
var<workgroup> scan_rows: array<array<u32, 256>, 2>;

@compute @workgroup_size(256)
fn build(@builtin(local_invocation_index) lid: u32) {
    var carry = 0u;
    for (var base = 0u; base < pc.segments; base += 256u) {
        let s = base + lid;
        var begin = 0u;
        var end = 0u;
        if (s < pc.segments) {
            begin = min(offsets[s], pc.rows);
            end = clamp(offsets[s + 1u], begin, pc.rows);
        }
        let n = (end - begin + pc.block - 1u) / pc.block;
        var sum = n;
        scan_rows[0][lid] = sum;
        workgroupBarrier();
        var cur = 0u;
        for (var offset = 1u; offset < 256u; offset <<= 1u) {
            if (lid >= offset) {
                sum += scan_rows[cur][lid - offset];
            }
            scan_rows[1u - cur][lid] = sum;
            cur = 1u - cur;
            workgroupBarrier();
        }
        let first = carry + sum - n;
        var b = 0u;
        for (var row = begin; row < end; row += pc.block) {
            if (first + b < pc.capacity) {
                list[first + b] = vec2<u32>(s, row);
            }
            b += 1u;
        }
        carry += scan_rows[cur][255];
        // Every invocation has read the chunk's total before the next chunk overwrites it.
        workgroupBarrier();
    }
    for (var i = carry + lid; i < pc.capacity; i += 256u) {
        list[i] = vec2<u32>(0xffffffffu, 0xffffffffu);
    }
}
