// The gate of a SwiGLU feed-forward, h = silu(a) * b with a = x W1 and b = x W3, and its
// backward: da = dh * b * silu'(a), db = dh * silu(a), silu'(a) = s (1 + a (1 - s)), s = sigmoid(a).
// One invocation per element.

struct Params {
    n: u32,
}

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> h: array<f32>;
@group(0) @binding(3) var<storage, read> dh: array<f32>;
@group(0) @binding(4) var<storage, read_write> da: array<f32>;
@group(0) @binding(5) var<storage, read_write> db: array<f32>;
@group(0) @binding(6) var<storage, read_write> dsilu: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

fn sigmoid(v: f32) -> f32 {
    // exp(large) is +inf and 1 / inf = 0: saturates without NaN.
    return 1.0 / (1.0 + exp(-v));
}

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        let v = a[i];
        h[i] = v * sigmoid(v) * b[i];
    }
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        let v = a[i];
        let g = dh[i];
        da[i] = g * b[i] * silu_grad(v);
        db[i] = g * v * sigmoid(v);
    }
}

// silu'(v) = s (1 + v (1 - s)), s = sigmoid(v).
fn silu_grad(v: f32) -> f32 {
    let s = sigmoid(v);
    return s * (1.0 + v * (1.0 - s));
}

// SiLU's backward alone (the gate with b = 1): dsilu = dh * silu'(a).
@compute @workgroup_size(256)
fn silu_backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        dsilu[i] = dh[i] * silu_grad(a[i]);
    }
}
