// Per-element losses and their gradients, scaled by `scale` (weight / n for a mean), written
// side by side; the host sums the per-element losses with reduce.wgsl. `label` holds the
// target (`target` is reserved in WGSL); r = pred - target.
//   MSE:   r^2,                                   grad 2 r
//   L1:    |r|,                                   grad sign(r) (0 at r = 0)
//   Huber: 0.5 r^2 if |r| <= delta, else delta (|r| - 0.5 delta),   grad clamp(r, -delta, delta)
//   BCE with logits x = pred, label y = target:
//          max(x, 0) - x y + log(1 + exp(-|x|))   (never exponentiates a positive number)
//          grad sigmoid(x) - y
//   Focal (Lin et al. 2017) with logits, focusing gamma = delta: q = 1 - p_t, the probability
//   given to the wrong answer, q = y sigmoid(-x) + (1 - y) sigmoid(x) (no cancellation near
//   0 or 1), and loss q^gamma BCE; with dq/dx = (1 - 2y) p (1 - p):
//          grad q^gamma (p - y) + gamma q^(gamma - 1) (1 - 2y) p (1 - p) BCE
//   gamma 0 is BCE; gamma >= 1 is what the host allows, so q^(gamma - 1) never divides by 0.

struct Params {
    n: u32,
    kind: u32,
    delta: f32,
    scale: f32,
}

@group(0) @binding(0) var<storage, read> pred: array<f32>;
@group(0) @binding(1) var<storage, read> label: array<f32>;
@group(0) @binding(2) var<storage, read_write> loss: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

const LOSS_OP_MSE: u32 = 0u;
const LOSS_OP_L1: u32 = 1u;
const LOSS_OP_HUBER: u32 = 2u;
const LOSS_OP_BCE: u32 = 3u;
const LOSS_OP_FOCAL: u32 = 4u;

// log(1 + u) for u >= 0, accurate when u is tiny (where 1 + u rounds to 1).
fn log1p_pos(u: f32) -> f32 {
    let v = 1.0 + u;
    if (v == 1.0) {
        return u;
    }
    return log(v) * (u / (v - 1.0));
}

// One element's loss and gradient, scaled.
fn element(i: u32) {
    let x = pred[i];
    let t = label[i];
    let r = x - t;
    var l = 0.0;
    var g = 0.0;
    switch pc.kind {
        case LOSS_OP_MSE: {
            l = r * r;
            g = 2.0 * r;
        }
        case LOSS_OP_L1: {
            l = abs(r);
            g = sign(r);
        }
        case LOSS_OP_HUBER: {
            let a = abs(r);
            if (a <= pc.delta) {
                l = 0.5 * r * r;
            } else {
                l = pc.delta * (a - 0.5 * pc.delta);
            }
            g = clamp(r, -pc.delta, pc.delta);
        }
        case LOSS_OP_FOCAL: {
            let ce = max(x, 0.0) - x * t + log1p_pos(exp(-abs(x)));
            let p = 1.0 / (1.0 + exp(-x));
            let q = t / (1.0 + exp(x)) + (1.0 - t) * p;
            let gamma = pc.delta;
            let qg = pow(max(q, 0.0), gamma);
            var focus = 0.0;
            if (q > 0.0) {
                focus = gamma * qg / q * (1.0 - 2.0 * t) * p * (1.0 - p) * ce;
            }
            l = qg * ce;
            g = qg * (p - t) + focus;
        }
        default: {
            l = max(x, 0.0) - x * t + log1p_pos(exp(-abs(x)));
            g = 1.0 / (1.0 + exp(-x)) - t;
        }
    }
    loss[i] = l * pc.scale;
    grad[i] = g * pc.scale;
}

// The elements of the dispatch (a workgroup per 256 on GPUs, per 4096 on CPU devices).
@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.n; i += element_stride(nwg)) {
        element(i);
    }
}
