// Fused AdamW over one flat parameter buffer (Loshchilov and Hutter, "Decoupled Weight Decay
// Regularization", Algorithm 2), one invocation per element:
//   g  = grad * grad_scale * clip,   clip = min(1, max_norm / (grad_scale * |grad| + 1e-6))
//   m  = beta1 m + (1 - beta1) g
//   v  = beta2 v + (1 - beta2) g^2
//   p -= lr * weight_decay * p          (only for elements [0, decay_end))
//   p -= lr * (m / bias1) / (sqrt(v / bias2) + eps),   bias_k = 1 - beta_k^step
// |grad| is the global gradient norm, read from `norm[0]` (written by norm.wgsl earlier in the
// same command buffer) so clipping needs no round trip to the host. When that norm is NaN or
// Inf the step is skipped: parameters and moments stay as they were, and the host, which
// reads the norm after the step, stops with a message instead of training on garbage.

struct Params {
    n: u32,          // elements in this dispatch
    decay_end: u32,  // elements [0, decay_end) get weight decay, the rest do not
    use_norm: u32,   // 1: read norm[0] (clip when max_norm > 0, skip when non-finite)
    step: u32,       // 1-based step, for the record; the bias terms come precomputed
    lr: f32,
    beta1: f32,
    one_minus_beta1: f32, // from the host in f64: 1 - 0.999 rounded from f32 is 1.3e-5 off
    beta2: f32,
    one_minus_beta2: f32,
    eps: f32,
    weight_decay: f32,
    grad_scale: f32,
    max_norm: f32,   // <= 0: no clipping
    bias1: f32,      // 1 - beta1^step
    bias2: f32,      // 1 - beta2^step
}

@group(0) @binding(0) var<storage, read_write> param: array<f32>;
@group(0) @binding(1) var<storage, read> grad: array<f32>;
@group(0) @binding(2) var<storage, read_write> m: array<f32>;
@group(0) @binding(3) var<storage, read_write> v: array<f32>;
@group(0) @binding(4) var<storage, read> norm: array<f32>;
var<immediate> pc: Params;

// Tested on the bits: a driver may assume float arithmetic never yields NaN.
fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.n) {
        return;
    }
    var scale = pc.grad_scale;
    if (pc.use_norm != 0u) {
        let total = norm[0];
        if (!is_finite(total)) {
            return;
        }
        if (pc.max_norm > 0.0) {
            scale *= min(1.0, pc.max_norm / (abs(pc.grad_scale) * total + 1e-6));
        }
    }
    let g = grad[i] * scale;
    let mi = pc.beta1 * m[i] + pc.one_minus_beta1 * g;
    let vi = pc.beta2 * v[i] + pc.one_minus_beta2 * (g * g);
    m[i] = mi;
    v[i] = vi;
    var p = param[i];
    if (i < pc.decay_end) {
        p -= pc.lr * pc.weight_decay * p;
    }
    let m_hat = mi / pc.bias1;
    let v_hat = vi / pc.bias2;
    param[i] = p - pc.lr * m_hat / (sqrt(v_hat) + pc.eps);
}
