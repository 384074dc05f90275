// Backward of the exact GELU, gelu(x) = x Phi(x):  dx = dy * (Phi(x) + x phi(x)),
// Phi(x) = 0.5 erfc(-x / sqrt 2), phi(x) = exp(-x^2 / 2) / sqrt(2 pi). The forward is
// `unary.wgsl`'s OP_GELU, with the same erfc. One invocation per element.

struct Params {
    n: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read> dy: array<f32>;
@group(0) @binding(2) var<storage, read_write> dx: array<f32>;
var<immediate> pc: Params;

// erfc(z) for z >= 0, Abramowitz & Stegun 7.1.26 (absolute error < 1.5e-7).
fn erfc_pos(z: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))));
    return poly * exp(-z * z);
}

fn gelu_grad(v: f32) -> f32 {
    let c = erfc_pos(abs(v) * 0.70710678118654752);
    var cdf = 0.5 * c;
    if (v >= 0.0) {
        cdf = 1.0 - 0.5 * c;
    }
    // exp(-v^2 / 2) underflows to 0 for |v| > 14: the density term vanishes cleanly.
    let pdf = 0.39894228040143268 * exp(-0.5 * v * v);
    return cdf + v * pdf;
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.n) {
        return;
    }
    dx[i] = dy[i] * gelu_grad(x[i]);
}
