// Elementwise maps y = f(x) over f32, one op code per call (a uniform branch), and their
// backward dx = dy f'(x).
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
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read_write> dx: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

const UNARY_OP_AFFINE: u32 = 0u;   // alpha * x + beta
const UNARY_OP_EXP: u32 = 1u;
const UNARY_OP_LOG: u32 = 2u;
const UNARY_OP_SIGMOID: u32 = 3u;
const UNARY_OP_SILU: u32 = 4u;
const UNARY_OP_GELU: u32 = 5u;     // exact (erf) GELU
const UNARY_OP_GELU_TANH: u32 = 6u;
const UNARY_OP_SQRT: u32 = 7u;
const UNARY_OP_RSQRT: u32 = 8u;
const UNARY_OP_ABS: u32 = 9u;
const UNARY_OP_TANH: u32 = 10u;
const UNARY_OP_RELU: u32 = 11u;
const UNARY_OP_SQUARE: u32 = 12u;
const UNARY_OP_RECIP: u32 = 13u;
const UNARY_OP_SIN: u32 = 14u;
const UNARY_OP_COS: u32 = 15u;

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
        case UNARY_OP_AFFINE: { return pc.alpha * v + pc.beta; }
        case UNARY_OP_EXP: { return exp(v); }
        case UNARY_OP_LOG: { return log(v); }
        case UNARY_OP_SIGMOID: { return sigmoid(v); }
        case UNARY_OP_SILU: { return v * sigmoid(v); }
        case UNARY_OP_GELU: { return gelu(v); }
        case UNARY_OP_GELU_TANH: {
            // 0.5 v (1 + tanh u) = v sigmoid(2u): no cancellation in the negative tail.
            return v * sigmoid(1.5957691216057308 * (v + 0.044715 * v * v * v));
        }
        case UNARY_OP_SQRT: { return sqrt(v); }
        case UNARY_OP_RSQRT: { return inverseSqrt(v); }
        case UNARY_OP_ABS: { return abs(v); }
        case UNARY_OP_TANH: { return stable_tanh(v); }
        case UNARY_OP_RELU: { return max(v, 0.0); }
        case UNARY_OP_SQUARE: { return v * v; }
        case UNARY_OP_RECIP: { return 1.0 / v; }
        case UNARY_OP_SIN: { return sincos(v).x; }
        case UNARY_OP_COS: { return sincos(v).y; }
        default: { return v; }
    }
}

// f'(v), written from the same pieces as `apply`.
fn derivative(op: u32, v: f32) -> f32 {
    switch op {
        case UNARY_OP_AFFINE: { return pc.alpha; }
        case UNARY_OP_EXP: { return exp(v); }
        case UNARY_OP_LOG: { return 1.0 / v; }
        case UNARY_OP_SIGMOID: { let s = sigmoid(v); return s * (1.0 - s); }
        case UNARY_OP_SILU: { let s = sigmoid(v); return s * (1.0 + v * (1.0 - s)); }
        case UNARY_OP_GELU: { return gelu_grad(v); }
        case UNARY_OP_GELU_TANH: {
            // y = v s with s = sigmoid(2u), u = c (v + 0.044715 v^3).
            let s = sigmoid(1.5957691216057308 * (v + 0.044715 * v * v * v));
            return s + v * s * (1.0 - s) * 1.5957691216057308 * (1.0 + 0.134145 * v * v);
        }
        case UNARY_OP_SQRT: { return 0.5 * inverseSqrt(v); }
        case UNARY_OP_RSQRT: { let r = inverseSqrt(v); return -0.5 * r * r * r; }
        case UNARY_OP_ABS: { return sign(v); }
        case UNARY_OP_TANH: { let t = stable_tanh(v); return 1.0 - t * t; }
        case UNARY_OP_RELU: { return select(0.0, 1.0, v > 0.0); }
        case UNARY_OP_SQUARE: { return 2.0 * v; }
        case UNARY_OP_RECIP: { let r = 1.0 / v; return -r * r; }
        case UNARY_OP_SIN: { return sincos(v).y; }
        case UNARY_OP_COS: { return -sincos(v).x; }
        default: { return 1.0; }
    }
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        y[i] = apply(pc.op, x[i]);
    }
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        dx[i] = dy[i] * derivative(pc.op, x[i]);
    }
}
