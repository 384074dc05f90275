// adaLN modulation, fused: one pass each where the layers took two or three elementwise ops.
// `a` is [B, T, D] flat; a per-sample tensor `p` is [B, D], broadcast over the T rows of its
// sample: element i reads p[s] with s = (i / (T D)) D + i % D.
//   modulate:  out = a * (1 + p[s]) + q[s]            (x, scale, shift)
//   gate:      out = q[i] + p[s] * a                  (y, gate, res)
//   backward:  ga = g * (one + p[s]),  gp = g * a     (one = 1: modulate's dx and dy*x;
//                                                      one = 0: the gate's dy and dout*y)
// The per-sample gradients are gp summed over T (gp itself when T = 1).

struct Params {
    n: u32,
    t: u32,
    d: u32,
    one: f32,
}

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> p: array<f32>;
@group(0) @binding(2) var<storage, read> q: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;
@group(0) @binding(4) var<storage, read> g: array<f32>;
@group(0) @binding(5) var<storage, read_write> ga: array<f32>;
@group(0) @binding(6) var<storage, read_write> gp: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

fn index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * 256u + lid;
}

fn sample(i: u32) -> u32 {
    return (i / (pc.t * pc.d)) * pc.d + i % pc.d;
}

@compute @workgroup_size(256)
fn modulate(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        let s = sample(i);
        out[i] = a[i] * (1.0 + p[s]) + q[s];
    }
}

@compute @workgroup_size(256)
fn gate(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        out[i] = q[i] + p[sample(i)] * a[i];
    }
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        let gi = g[i];
        ga[i] = gi * (pc.one + p[sample(i)]);
        gp[i] = gi * a[i];
    }
}
