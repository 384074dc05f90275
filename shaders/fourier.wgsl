// Fourier features of every channel of x [rows, c]. Output row layout (width
// c * 2F + (c if include_input)):
//   [ x_0 .. x_{c-1} ]                         only when include_input
//   [ sin(pi w_f x_i) for i in 0..c, f in 0..F ]  index i * F + f
//   [ cos(pi w_f x_i) for i in 0..c, f in 0..F ]  same order
// with w_f = freq[f]. q = w_f x is rounded once in f32 and its sine and cosine in half-turns
// come from `sincospi` (include/sincos.wgsl: exact reduction, then ~1 ulp on every device; the
// builtins are held to 2^-11 only, and SwiftShader's miss by 3e-4). For octave frequencies
// (powers of two) q is exact and the features are accurate to ~1e-7; for other frequencies
// the one rounding of q (relative 6e-8, 2.4e-4 half-turns at q = 4096) is the error.
// (Splitting w and x into 12-bit halves whose products are exact gave the same results on
// lavapipe, so the simple form stays.)
// `backward`: one invocation per input element,
//   dx_i = dy_in_i + sum_f pi w_f (cos(pi w_f x_i) dy_sin_if - sin(pi w_f x_i) dy_cos_if).

struct Params {
    rows: u32,
    channels: u32,
    freqs: u32,
    include_input: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read> freq: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;
@group(0) @binding(3) var<storage, read> dy: array<f32>;
@group(0) @binding(4) var<storage, read_write> dx: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

const PI: f32 = 3.14159265358979;

// @include sincos.wgsl

fn out_width() -> u32 {
    return pc.channels * 2u * pc.freqs + select(0u, pc.channels, pc.include_input != 0u);
}

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    for (var o = first_element(wid, nwg, lid); ; o += element_stride(nwg)) {
        let width = out_width();
        if (o >= pc.rows * width) {
            break;
        }
        let row = o / width;
        var k = o % width;
        if (pc.include_input != 0u) {
            if (k < pc.channels) {
                y[o] = x[row * pc.channels + k];
                continue;
            }
            k -= pc.channels;
        }
        let block = pc.channels * pc.freqs;
        let is_cos = k >= block;
        let kk = k % block;
        let i = kk / pc.freqs;
        let f = kk % pc.freqs;
        let sc = sincospi(freq[f] * x[row * pc.channels + i]);
        y[o] = select(sc.x, sc.y, is_cos);
    }
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var e = first_element(wid, nwg, lid); e < pc.rows * pc.channels; e += element_stride(nwg)) {
        let row = e / pc.channels;
        let i = e % pc.channels;
        let width = out_width();
        var base = row * width;
        var g = 0.0;
        if (pc.include_input != 0u) {
            g = dy[base + i];
            base += pc.channels;
        }
        let v = x[e];
        let block = pc.channels * pc.freqs;
        for (var f = 0u; f < pc.freqs; f++) {
            let w = freq[f];
            let sc = sincospi(w * v);
            let k = base + i * pc.freqs + f;
            g += PI * w * (sc.y * dy[k] - sc.x * dy[k + block]);
        }
        dx[e] = g;
    }
}
