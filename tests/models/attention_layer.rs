//! The multi-head attention layer (projections around the fused kernel), self and cross,
//! forward and backward against an f64 composition of the references.

use crate::common;
use common::*;
use velox::engine::ops::attention::{reference, Segments};
use velox::models::layers::{attention::MultiHeadAttention, Linear, Param};

/// x [n, i] @ w [i, o] in f64.
fn mm(x: &[f64], w: &[f64], n: usize, i: usize, o: usize) -> Vec<f64> {
    let mut y = vec![0.0; n * o];
    for r in 0..n {
        for c in 0..o {
            y[r * o + c] = (0..i).map(|k| x[r * i + k] * w[k * o + c]).sum();
        }
    }
    y
}

/// a^T [i, n] @ b [n, o], i.e. the weight gradient x^T dy.
fn mm_tn(a: &[f64], b: &[f64], n: usize, i: usize, o: usize) -> Vec<f64> {
    let mut y = vec![0.0; i * o];
    for r in 0..n {
        for p in 0..i {
            for c in 0..o {
                y[p * o + c] += a[r * i + p] * b[r * o + c];
            }
        }
    }
    y
}

/// dy [n, o] @ w^T -> [n, i].
fn mm_nt(dy: &[f64], w: &[f64], n: usize, i: usize, o: usize) -> Vec<f64> {
    let mut y = vec![0.0; n * i];
    for r in 0..n {
        for p in 0..i {
            y[r * i + p] = (0..o).map(|c| dy[r * o + c] * w[p * o + c]).sum();
        }
    }
    y
}

fn add(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x + y).collect()
}

fn check(cross: bool, seed: u64) {
    let gpu = gpu();
    let mut rng = Rng::new(seed);
    let (width, cwidth, heads, d) = (12, if cross { 7 } else { 12 }, 2, 16);
    let inner = heads * d;
    let q_lens = [5usize, 0, 9];
    let k_lens = if cross { [3usize, 4, 20] } else { q_lens };
    let (nq, nk): (usize, usize) = (q_lens.iter().sum(), k_lens.iter().sum());
    let x = rng.normal_vec(nq * width);
    let c = if cross { rng.normal_vec(nk * cwidth) } else { x.clone() };
    let ws: Vec<Vec<f32>> = [(width, inner), (cwidth, inner), (cwidth, inner), (inner, width)]
        .iter()
        .map(|&(i, o)| rng.normal_vec(i * o).iter().map(|v| v * 0.3).collect())
        .collect();
    let dims = [(width, inner), (cwidth, inner), (cwidth, inner), (inner, width)];
    let params: Vec<Param> =
        ws.iter().zip(dims).map(|(w, (i, o))| Param::new(&gpu, &[i, o], w).unwrap()).collect();
    let lin = |p: &Param| Linear::new(p.clone(), None).unwrap();
    let layer =
        MultiHeadAttention::new(lin(&params[0]), lin(&params[1]), lin(&params[2]), lin(&params[3]), heads)
            .unwrap();
    let seg = Segments::from_lengths(&gpu, &q_lens, &k_lens).unwrap();
    let tx = Tensor::from_slice(&gpu, &[nq, width], &x).unwrap();
    let tc = Tensor::from_slice(&gpu, &[nk, cwidth], &c).unwrap();
    let dy = rng.normal_vec(nq * width);
    let tdy = Tensor::from_slice(&gpu, &[nq, width], &dy).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let (y, cache) = layer.forward(&mut rec, &tx, cross.then_some(&tc), &seg).unwrap();
    let (dx, dc) = layer.backward(&mut rec, &cache, &tdy, &seg).unwrap();
    rec.submit().unwrap();

    // The f64 composition.
    let (x64, c64, dy64) = (f64s(&x), f64s(&c), f64s(&dy));
    let w: Vec<Vec<f64>> = ws.iter().map(|w| f64s(w)).collect();
    let q = mm(&x64, &w[0], nq, width, inner);
    let k = mm(&c64, &w[1], nk, cwidth, inner);
    let v = mm(&c64, &w[2], nk, cwidth, inner);
    let (qo, ko) = (reference::offsets(&q_lens), reference::offsets(&k_lens));
    let scale = 1.0 / (d as f64).sqrt();
    let (o, _) = reference::attention(&q, &k, &v, &qo, &ko, heads, d, scale);
    let y_ref = mm(&o, &w[3], nq, inner, width);
    let d_o = mm_nt(&dy64, &w[3], nq, inner, width);
    let dwo = mm_tn(&o, &dy64, nq, inner, width);
    let (dq, dk, dv) = reference::attention_backward(&q, &k, &v, &d_o, &qo, &ko, heads, d, scale);
    let dwq = mm_tn(&x64, &dq, nq, width, inner);
    let dwk = mm_tn(&c64, &dk, nk, cwidth, inner);
    let dwv = mm_tn(&c64, &dv, nk, cwidth, inner);
    let dx_q = mm_nt(&dq, &w[0], nq, width, inner);
    let dc_ref = add(&mm_nt(&dk, &w[1], nk, cwidth, inner), &mm_nt(&dv, &w[2], nk, cwidth, inner));
    let what = if cross { "cross" } else { "self" };
    assert_nmse(&format!("{what} y"), &y.read::<f32>().unwrap(), &y_ref, 1e-11);
    if cross {
        assert_nmse("cross dx", &dx.read::<f32>().unwrap(), &dx_q, 1e-11);
        assert_nmse("cross dcontext", &dc.unwrap().read::<f32>().unwrap(), &dc_ref, 1e-11);
    } else {
        assert!(dc.is_none());
        assert_nmse("self dx", &dx.read::<f32>().unwrap(), &add(&dx_q, &dc_ref), 1e-11);
    }
    for (p, want, name) in [
        (&params[0], &dwq, "dWq"),
        (&params[1], &dwk, "dWk"),
        (&params[2], &dwv, "dWv"),
        (&params[3], &dwo, "dWo"),
    ] {
        assert_nmse(&format!("{what} {name}"), &p.grad.read::<f32>().unwrap(), want, 1e-11);
    }
}

#[test]
fn self_attention_layer_matches_reference() {
    check(false, 1);
}

#[test]
fn cross_attention_layer_matches_reference() {
    check(true, 2);
}

#[test]
fn mismatched_projections_are_refused() {
    let gpu = gpu();
    let p = |i: usize, o: usize| {
        Linear::new(Param::new(&gpu, &[i, o], &vec![0.0; i * o]).unwrap(), None).unwrap()
    };
    assert!(MultiHeadAttention::new(p(8, 32), p(8, 32), p(8, 32), p(32, 8), 3).is_err());
    assert!(MultiHeadAttention::new(p(8, 32), p(8, 16), p(8, 32), p(32, 8), 2).is_err());
    assert!(MultiHeadAttention::new(p(8, 32), p(5, 32), p(6, 32), p(32, 8), 2).is_err());
}
