// Elementwise binary ops with broadcasting: out[i] = op(a[ia], b[ib]). The host collapses the
// broadcast to at most four dimensions; a broadcast dimension has stride 0. The output is
// dense, last dimension fastest.

struct Params {
    shape: vec4<u32>,     // output shape, dims 0..3 (outermost first)
    a_strides: vec4<u32>,
    b_strides: vec4<u32>,
    n: u32,
    op: u32,
}

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

const BINARY_OP_ADD: u32 = 0u;
const BINARY_OP_SUB: u32 = 1u;
const BINARY_OP_MUL: u32 = 2u;
const BINARY_OP_DIV: u32 = 3u;
const BINARY_OP_MAX: u32 = 4u;
const BINARY_OP_MIN: u32 = 5u;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        // Decompose the output index, last dimension fastest.
        var rem = i;
        let i3 = rem % pc.shape.w;
        rem = rem / pc.shape.w;
        let i2 = rem % pc.shape.z;
        rem = rem / pc.shape.z;
        let i1 = rem % pc.shape.y;
        let i0 = rem / pc.shape.y;
        let idx = vec4<u32>(i0, i1, i2, i3);
        let ia = dot(idx, pc.a_strides);
        let ib = dot(idx, pc.b_strides);
        let x = a[ia];
        let y = b[ib];
        var r: f32;
        switch pc.op {
            case BINARY_OP_ADD: { r = x + y; }
            case BINARY_OP_SUB: { r = x - y; }
            case BINARY_OP_MUL: { r = x * y; }
            case BINARY_OP_DIV: { r = x / y; }
            case BINARY_OP_MAX: { r = max(x, y); }
            case BINARY_OP_MIN: { r = min(x, y); }
            default: { r = x; }
        }
        out[i] = r;
    }
}
