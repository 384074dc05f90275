// The first pass of farthest point sampling (shaders/fps.wgsl; host side engine/src/ops/fps.rs):
// one workgroup gives every candidate a 32-bit Morton code, 8 bits per axis over the candidates'
// bounding box, interleaved. The host sorts the candidates by it, so that neighbours in the
// sorted order are neighbours in space. It also writes 0, 1, ..., m - 1 as the values the sort
// carries, which become `perm`: the original position of each sorted slot. A file of its own,
// so that its workgroup memory is not counted with the main kernel's.

struct Params {
    m: u32, // candidates
    k: u32, // to choose (unused here)
}

const WG_ORDER: u32 = 256u;
const BIG: f32 = 3.0e38;

// The candidates in their original order.
@group(0) @binding(0) var<storage, read> cands: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> codes: array<u32>;
@group(0) @binding(2) var<storage, read_write> iota: array<u32>;
var<immediate> pc: Params;

var<workgroup> box_lo: array<vec4<f32>, WG_ORDER>;
var<workgroup> box_hi: array<vec4<f32>, WG_ORDER>;

// The 8 low bits of v spread to bits 0, 4, 8, ..., 28.
fn spread4(v: u32) -> u32 {
    var x = v & 0xffu;
    x = (x | (x << 12u)) & 0x000f000fu;
    x = (x | (x << 6u)) & 0x03030303u;
    x = (x | (x << 3u)) & 0x11111111u;
    return x;
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32) {
    var lo = vec4<f32>(BIG);
    var hi = vec4<f32>(-BIG);
    for (var j = lid; j < pc.m; j += WG_ORDER) {
        let p = cands[j];
        lo = min(lo, p);
        hi = max(hi, p);
    }
    box_lo[lid] = lo;
    box_hi[lid] = hi;
    workgroupBarrier();
    for (var s = WG_ORDER / 2u; s > 0u; s >>= 1u) {
        if (lid < s) {
            box_lo[lid] = min(box_lo[lid], box_lo[lid + s]);
            box_hi[lid] = max(box_hi[lid], box_hi[lid + s]);
        }
        workgroupBarrier();
    }
    let origin = box_lo[0];
    let extent = box_hi[0] - origin;
    // 256 cells over the box on each axis (an axis of zero extent gets cell 0).
    let scale = select(vec4<f32>(0.0), 256.0 / extent, extent > vec4<f32>(0.0));
    for (var j = lid; j < pc.m; j += WG_ORDER) {
        let q = vec4<u32>(clamp((cands[j] - origin) * scale, vec4<f32>(0.0), vec4<f32>(255.0)));
        codes[j] = spread4(q.x) | (spread4(q.y) << 1u) | (spread4(q.z) << 2u) | (spread4(q.w) << 3u);
        iota[j] = j;
    }
}

