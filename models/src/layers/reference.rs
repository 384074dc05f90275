//! f64 references of the layers, in plain loops. Row-major arrays; `n` rows. The single-op
//! references (norms, Fourier features, losses, the SwiGLU gate, GELU, adaLN) live beside their
//! kernels' host sides in `engine/src/ops` and are re-exported here.
//!
//! Tests: `tests/models/layers.rs` (the composites against finite differences).

pub use velox_engine::ops::adaln::reference::{
    gated_residual, gated_residual_backward, modulate, modulate_backward,
};
pub use velox_engine::ops::fourier::reference::{fourier, fourier_backward};
pub use velox_engine::ops::layernorm::reference::{layernorm, layernorm_backward};
pub use velox_engine::ops::loss::reference::{loss, pointwise};
pub use velox_engine::ops::rmsnorm::reference::{rmsnorm, rmsnorm_backward};
use velox_engine::ops::swiglu::reference::{swiglu, swiglu_backward};
use velox_engine::ops::unary::reference::erf;

/// `a [n, k] @ b [k, m]`, with either operand read transposed.
fn mm(a: &[f64], b: &[f64], n: usize, k: usize, m: usize, ta: bool, tb: bool) -> Vec<f64> {
    let mut out = vec![0.0; n * m];
    for i in 0..n {
        for j in 0..m {
            let mut s = 0.0;
            for l in 0..k {
                let x = if ta { a[l * n + i] } else { a[i * k + l] };
                let y = if tb { b[j * k + l] } else { b[l * m + j] };
                s += x * y;
            }
            out[i * m + j] = s;
        }
    }
    out
}

/// `y = x W + b`, `x [n, d_in]`, `W [d_in, d_out]`.
pub fn linear(x: &[f64], w: &[f64], b: Option<&[f64]>, n: usize, d_in: usize, d_out: usize) -> Vec<f64> {
    let mut y = mm(x, w, n, d_in, d_out, false, false);
    if let Some(b) = b {
        for row in y.chunks_mut(d_out) {
            row.iter_mut().zip(b).for_each(|(v, bj)| *v += bj);
        }
    }
    y
}

/// Returns `(dx, dW, db)`.
pub fn linear_backward(
    x: &[f64],
    w: &[f64],
    dy: &[f64],
    n: usize,
    d_in: usize,
    d_out: usize,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let dx = mm(dy, w, n, d_out, d_in, false, true);
    let dw = mm(x, dy, d_in, n, d_out, true, false);
    let mut db = vec![0.0; d_out];
    for row in dy.chunks(d_out) {
        db.iter_mut().zip(row).for_each(|(a, g)| *a += g);
    }
    (dx, dw, db)
}

/// `y = (silu(x W1) * (x W3)) W2`, `W1`, `W3 [d, h]`, `W2 [h, d_out]`.
#[allow(clippy::too_many_arguments)]
pub fn swiglu_ff(
    x: &[f64],
    w1: &[f64],
    w3: &[f64],
    w2: &[f64],
    n: usize,
    d: usize,
    h: usize,
    d_out: usize,
) -> Vec<f64> {
    let a = mm(x, w1, n, d, h, false, false);
    let b = mm(x, w3, n, d, h, false, false);
    mm(&swiglu(&a, &b), w2, n, h, d_out, false, false)
}

/// Returns `(dx, dW1, dW3, dW2)`.
#[allow(clippy::too_many_arguments)]
pub fn swiglu_ff_backward(
    x: &[f64],
    w1: &[f64],
    w3: &[f64],
    w2: &[f64],
    dy: &[f64],
    n: usize,
    d: usize,
    h: usize,
    d_out: usize,
) -> [Vec<f64>; 4] {
    let a = mm(x, w1, n, d, h, false, false);
    let b = mm(x, w3, n, d, h, false, false);
    let hv = swiglu(&a, &b);
    let dw2 = mm(&hv, dy, h, n, d_out, true, false);
    let dh = mm(dy, w2, n, d_out, h, false, true);
    let (da, db) = swiglu_backward(&a, &b, &dh);
    let dw1 = mm(x, &da, d, n, h, true, false);
    let dw3 = mm(x, &db, d, n, h, true, false);
    let dx: Vec<f64> = mm(&da, w1, n, h, d, false, true)
        .iter()
        .zip(mm(&db, w3, n, h, d, false, true))
        .map(|(p, q)| p + q)
        .collect();
    [dx, dw1, dw3, dw2]
}

pub fn gelu(v: f64) -> f64 {
    0.5 * v * (1.0 + erf(v / std::f64::consts::SQRT_2))
}

/// `y = gelu(x W1 + b1) W2 + b2`.
#[allow(clippy::too_many_arguments)]
pub fn gelu_mlp(
    x: &[f64],
    w1: &[f64],
    b1: &[f64],
    w2: &[f64],
    b2: &[f64],
    n: usize,
    d: usize,
    h: usize,
    d_out: usize,
) -> Vec<f64> {
    let u = linear(x, w1, Some(b1), n, d, h);
    let g: Vec<f64> = u.iter().map(|&v| gelu(v)).collect();
    linear(&g, w2, Some(b2), n, h, d_out)
}

/// Returns `(dx, dW1, db1, dW2, db2)`.
#[allow(clippy::too_many_arguments)]
pub fn gelu_mlp_backward(
    x: &[f64],
    w1: &[f64],
    b1: &[f64],
    w2: &[f64],
    dy: &[f64],
    n: usize,
    d: usize,
    h: usize,
    d_out: usize,
) -> [Vec<f64>; 5] {
    let u = linear(x, w1, Some(b1), n, d, h);
    let g: Vec<f64> = u.iter().map(|&v| gelu(v)).collect();
    let (dg, dw2, db2) = linear_backward(&g, w2, dy, n, h, d_out);
    let du = velox_engine::ops::gelu::reference::gelu_backward(&u, &dg);
    let (dx, dw1, db1) = linear_backward(x, w1, &du, n, d, h);
    [dx, dw1, db1, dw2, db2]
}
