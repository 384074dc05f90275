// Elementwise maps y = f(x) over f32, one op code per call (a uniform branch).
// Written for stability: tanh never overflows, sigmoid saturates cleanly, and GELU uses an
// erfc form whose negative tail keeps its relative accuracy.

// @include sincos.wgsl

struct Params {
    n: u32,
    op: u32,
    alpha: f32,
    beta: f32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> y: array<f32>;
var<immediate> pc: Params;

const OP_AFFINE: u32 = 0u;   // alpha * x + beta
const OP_EXP: u32 = 1u;
const OP_LOG: u32 = 2u;
const OP_SIGMOID: u32 = 3u;
const OP_SILU: u32 = 4u;
const OP_GELU: u32 = 5u;     // exact (erf) GELU
const OP_GELU_TANH: u32 = 6u;
const OP_SQRT: u32 = 7u;
const OP_RSQRT: u32 = 8u;
const OP_ABS: u32 = 9u;
const OP_TANH: u32 = 10u;
const OP_RELU: u32 = 11u;
const OP_SQUARE: u32 = 12u;
const OP_RECIP: u32 = 13u;
const OP_SIN: u32 = 14u;
const OP_COS: u32 = 15u;

fn sigmoid(v: f32) -> f32 {
    // exp of a large positive argument is +inf and 1/inf = 0: saturates without NaN.
    return 1.0 / (1.0 + exp(-v));
}

// @include gelu_fn.wgsl

fn stable_tanh(v: f32) -> f32 {
    // tanh(15) rounds to 1 in f32; clamping keeps exp-based implementations finite.
    return tanh(clamp(v, -15.0, 15.0));
}

fn apply(op: u32, v: f32) -> f32 {
    switch op {
        case OP_AFFINE: { return pc.alpha * v + pc.beta; }
        case OP_EXP: { return exp(v); }
        case OP_LOG: { return log(v); }
        case OP_SIGMOID: { return sigmoid(v); }
        case OP_SILU: { return v * sigmoid(v); }
        case OP_GELU: { return gelu(v); }
        case OP_GELU_TANH: {
            // 0.5 v (1 + tanh u) = v sigmoid(2u): no cancellation in the negative tail.
            return v * sigmoid(1.5957691216057308 * (v + 0.044715 * v * v * v));
        }
        case OP_SQRT: { return sqrt(v); }
        case OP_RSQRT: { return inverseSqrt(v); }
        case OP_ABS: { return abs(v); }
        case OP_TANH: { return stable_tanh(v); }
        case OP_RELU: { return max(v, 0.0); }
        case OP_SQUARE: { return v * v; }
        case OP_RECIP: { return 1.0 / v; }
        case OP_SIN: { return sincos(v).x; }
        case OP_COS: { return sincos(v).y; }
        default: { return v; }
    }
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i < pc.n) {
        y[i] = apply(pc.op, x[i]);
    }
}
