//! The layers of `velox::models::layers`: every GPU forward and backward against its f64
//! reference on awkward sizes, the composite references' backward passes (linear, the
//! feed-forwards) against central finite differences of their forwards (the single ops' are in
//! the engine's harness, `engine/tests/ops/cases.rs`), and stability at large and tiny
//! magnitudes.

use crate::common;
use common::*;
use velox::engine::ops::loss::LossKind;
use velox::engine::Recorder;
use velox::models::layers::reference as r;
use velox::models::layers::*;

const ROWS: [usize; 3] = [1, 3, 17];
const WIDTHS: [usize; 4] = [1, 5, 64, 130];

fn upload(shape: &[usize], data: &[f32]) -> Tensor {
    Tensor::from_slice(&gpu(), shape, data).unwrap()
}

fn read(t: &Tensor) -> Vec<f32> {
    t.read::<f32>().unwrap()
}

fn rec() -> Recorder {
    gpu().recorder().unwrap()
}

/// A parameter holding `value` whose gradient starts at `grad0` (not zero, so that the test
/// sees the backward add into it rather than overwrite it).
fn param(shape: &[usize], value: &[f32], grad0: &[f32]) -> Param {
    let p = Param::new(&gpu(), shape, value).unwrap();
    p.grad.write(grad0).unwrap();
    p
}

/// `grad0 + reference`, what an accumulated gradient must hold.
fn plus(grad0: &[f32], reference: &[f64]) -> Vec<f64> {
    grad0.iter().zip(reference).map(|(&a, b)| a as f64 + b).collect()
}

/// Checks `grads[k]` against central differences of `loss` in every element of `inputs[k]`;
/// returns the largest error relative to `1 + |gradient|`.
fn finite_differences(
    what: &str,
    inputs: &[Vec<f64>],
    grads: &[Vec<f64>],
    loss: impl Fn(&[Vec<f64>]) -> f64,
    eps: f64,
    tol: f64,
) -> f64 {
    let mut worst: f64 = 0.0;
    for (k, g) in grads.iter().enumerate() {
        assert_eq!(g.len(), inputs[k].len(), "{what}: gradient {k} has the wrong length");
        for i in 0..g.len() {
            let (mut p, mut m) = (inputs.to_vec(), inputs.to_vec());
            p[k][i] += eps;
            m[k][i] -= eps;
            let fd = (loss(&p) - loss(&m)) / (2.0 * eps);
            let err = (fd - g[i]).abs() / (1.0 + g[i].abs());
            assert!(err < tol, "{what}: d input {k} [{i}]: analytic {} vs finite difference {fd}", g[i]);
            worst = worst.max(err);
        }
    }
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("{what}: finite differences, worst relative error {worst:.2e}");
    }
    worst
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn normal(rng: &mut Rng, n: usize, scale: f32) -> Vec<f32> {
    rng.normal_vec(n).iter().map(|v| v * scale).collect()
}

#[test]
fn linear_matches_reference() {
    let mut rng = Rng::new(1);
    for (n, din, dout) in [(1, 1, 5), (3, 5, 64), (17, 130, 5), (17, 64, 130)] {
        for bias in [false, true] {
            let what = format!("linear n={n} in={din} out={dout} bias={bias}");
            let x = rng.normal_vec(n * din);
            let w = normal(&mut rng, din * dout, 0.2);
            let b = rng.normal_vec(dout);
            let dy = rng.normal_vec(n * dout);
            let (gw0, gb0) = (rng.normal_vec(din * dout), rng.normal_vec(dout));
            let layer =
                Linear::new(param(&[din, dout], &w, &gw0), bias.then(|| param(&[dout], &b, &gb0))).unwrap();
            let mut rec = rec();
            let (y, cache) = layer.forward(&mut rec, &upload(&[n, din], &x)).unwrap();
            let dx = layer.backward(&mut rec, &cache, &upload(&[n, dout], &dy)).unwrap();
            rec.submit().unwrap();
            let bref = bias.then(|| f64s(&b));
            let y_ref = r::linear(&f64s(&x), &f64s(&w), bref.as_deref(), n, din, dout);
            let (dx_ref, dw_ref, db_ref) = r::linear_backward(&f64s(&x), &f64s(&w), &f64s(&dy), n, din, dout);
            assert_nmse(&format!("y {what}"), &read(&y), &y_ref, 2e-13);
            assert_nmse(&format!("dx {what}"), &read(&dx), &dx_ref, 2e-13);
            assert_nmse(&format!("dw {what}"), &read(&layer.weight.grad), &plus(&gw0, &dw_ref), 2e-13);
            if let Some(bp) = &layer.bias {
                assert_nmse(&format!("db {what}"), &read(&bp.grad), &plus(&gb0, &db_ref), 2e-13);
            }
        }
    }
}

#[test]
fn a_stack_of_linears_is_the_linears_side_by_side() {
    // k linears reading one input, their parameters stacked: the same outputs and gradients
    // as the linears one by one (f32), and the same as their f16 path in an f16 recording.
    use velox::models::layers::linear::LinearStack;
    use velox::models::params::{Init, ParamStore};
    let gpu = gpu();
    // Weights and biases of a multiple of 128 elements, so that they stack (lie one after
    // another) at every offset alignment a device may have (up to 256 bytes, 128 halves).
    let (k, n, din, dout) = (3, 37, 24, 128);
    let mut b = ParamStore::builder();
    for i in 0..k {
        b.add(&format!("l{i}.w"), &[din, dout], Init::Xavier).unwrap();
        b.add(&format!("l{i}.b"), &[dout], Init::Normal { std: 0.5 }).unwrap();
    }
    let store = b.build(&gpu, 4).unwrap();
    let names = |s: &str| (0..k).map(|i| format!("l{i}.{s}")).collect::<Vec<_>>();
    let (w, bias) = (names("w"), names("b"));
    let stack = LinearStack::new(
        store.stacked(&w).unwrap().expect("registered one after another"),
        Some(store.stacked(&bias).unwrap().expect("registered one after another")),
    )
    .unwrap();
    let linears: Vec<Linear> = (0..k)
        .map(|i| {
            let p = |s: &str| Param::from_store(&store, s).unwrap();
            Linear::new(p(&w[i]), Some(p(&bias[i]))).unwrap()
        })
        .collect();
    let mut rng = Rng::new(12);
    let x = upload(&[n, din], &rng.normal_vec(n * din));
    let dy = rng.normal_vec(k * n * dout);
    let dx0 = rng.normal_vec(n * din);
    for precision in [velox::engine::Precision::F32, velox::engine::Precision::F16] {
        let mut r1 = rec();
        r1.set_precision(precision);
        store.zero_grads(&mut r1).unwrap();
        let (ys, cache) = stack.forward(&mut r1, &x).unwrap();
        let dx_stack = upload(&[n, din], &dx0);
        stack.grads_into(&mut r1, &cache, &upload(&[k, n, dout], &dy), Some((&dx_stack, true))).unwrap();
        r1.submit().unwrap();
        let (y_stack, g_stack) = (read(&ys), read(store.flat_grads()));
        let mut r2 = rec();
        r2.set_precision(precision);
        store.zero_grads(&mut r2).unwrap();
        let dx_one = upload(&[n, din], &dx0);
        let mut y_one = Vec::new();
        for (i, l) in linears.iter().enumerate() {
            let (y, c) = l.forward(&mut r2, &x).unwrap();
            y_one.push(y);
            let d = upload(&[n, dout], &dy[i * n * dout..(i + 1) * n * dout]);
            l.grads_into(&mut r2, &c, &d, &dx_one, true).unwrap();
        }
        r2.submit().unwrap();
        let y_one: Vec<f32> = y_one.iter().flat_map(read).collect();
        let what = format!("stack of {k} in {precision:?}");
        // The same products summed in another order (dx adds k of them inside one kernel):
        // differences of a few f32 roundings, NMSE about eps^2 = 1.4e-14 (SwiftShader's
        // kernels reached 1.0e-13 on dx).
        assert_nmse(&format!("y {what}"), &y_stack, &f64s(&y_one), 1e-12);
        assert_nmse(&format!("grads {what}"), &g_stack, &f64s(&read(store.flat_grads())), 1e-12);
        assert_nmse(&format!("dx {what}"), &read(&dx_stack), &f64s(&read(&dx_one)), 1e-12);
    }
    // Parameters with others between them do not stack. Each is 128 elements, so that three
    // lie one after another at every offset alignment (up to 256 bytes: 128 halves).
    let mut b = ParamStore::builder();
    for name in ["a", "between", "c"] {
        b.add(name, &[8, 16], Init::Xavier).unwrap();
    }
    let store = b.build(&gpu, 0).unwrap();
    assert!(store.stacked(&["a", "c"]).unwrap().is_none());
    assert!(store.stacked(&["a", "between", "c"]).unwrap().is_some());
}

#[test]
fn norms_add_a_residual_gradient_in_their_backward_pass() {
    let mut rng = Rng::new(21);
    let (n, width) = (19, 48);
    let x = upload(&[n, width], &rng.normal_vec(n * width));
    let dy = upload(&[n, width], &rng.normal_vec(n * width));
    let res = rng.normal_vec(n * width);
    let rms =
        RmsNorm::new(param(&[width], &rng.uniform_vec(width, 0.5, 1.5), &vec![0.0; width]), 1e-6).unwrap();
    let affine = (
        param(&[width], &rng.normal_vec(width), &vec![0.0; width]),
        param(&[width], &vec![0.0; width], &vec![0.0; width]),
    );
    let ln = LayerNorm::new(width, Some(affine), 1e-6).unwrap();
    let mut rec = rec();
    let (_, rc) = rms.forward(&mut rec, &x).unwrap();
    let (_, lc) = ln.forward(&mut rec, &x).unwrap();
    let plain = [rms.backward(&mut rec, &rc, &dy).unwrap(), ln.backward(&mut rec, &lc, &dy).unwrap()];
    let res_t = upload(&[n, width], &res);
    let plus = [
        rms.backward_plus(&mut rec, &rc, &dy, Some(&res_t)).unwrap(),
        ln.backward_plus(&mut rec, &lc, &dy, Some(&res_t)).unwrap(),
    ];
    let wrong = upload(&[n, width + 1], &vec![0.0; n * (width + 1)]);
    assert!(rms.backward_plus(&mut rec, &rc, &dy, Some(&wrong)).is_err());
    rec.submit().unwrap();
    for (name, (a, b)) in ["rmsnorm", "layernorm"].iter().zip(plain.iter().zip(&plus)) {
        let want: Vec<f64> = read(a).iter().zip(&res).map(|(v, r)| *v as f64 + *r as f64).collect();
        assert_nmse(&format!("{name} dx + residual"), &read(b), &want, 1e-14);
    }
}

#[test]
fn linear_in_an_f16_recording_reads_rounded_operands() {
    // The f16 path: x and W rounded to f16, f32 accumulation, the bias added in f32. A weight
    // without an f16 copy (Param::new) is rounded as the layer runs.
    use velox::engine::ops::cast::reference::to_f16;
    let mut rng = Rng::new(2);
    for (n, din, dout) in [(1, 2, 5), (17, 130, 6), (33, 64, 130)] {
        let what = format!("f16 linear n={n} in={din} out={dout}");
        let (x, w, b) = (rng.normal_vec(n * din), normal(&mut rng, din * dout, 0.2), rng.normal_vec(dout));
        let zeros = vec![0.0; din * dout];
        let layer = Linear::new(param(&[din, dout], &w, &zeros), Some(param(&[dout], &b, &b))).unwrap();
        let mut rec = rec();
        rec.set_precision(velox::engine::Precision::F16);
        let (y, _) = layer.forward(&mut rec, &upload(&[n, din], &x)).unwrap();
        rec.submit().unwrap();
        let y_ref = r::linear(&to_f16(&x), &to_f16(&w), Some(&f64s(&b)), n, din, dout);
        // Measured on lavapipe: <= 2.6e-14.
        assert_nmse(&format!("y {what}, rounded operands"), &read(&y), &y_ref, 2e-13);
        let exact = r::linear(&f64s(&x), &f64s(&w), Some(&f64s(&b)), n, din, dout);
        let e = nmse(&read(&y), &exact);
        assert!(e > 0.0 && e < 1e-5, "{what}: NMSE {e} against exact operands: not an f16 product");
    }
}

#[test]
fn rmsnorm_matches_reference() {
    let mut rng = Rng::new(2);
    let eps = 1e-6;
    for n in ROWS.into_iter().chain([300]) {
        for width in WIDTHS {
            let what = format!("rmsnorm n={n} width={width}");
            let x = rng.normal_vec(n * width);
            let w = rng.uniform_vec(width, 0.5, 1.5);
            let dy = rng.normal_vec(n * width);
            let gw0 = rng.normal_vec(width);
            let layer = RmsNorm::new(param(&[width], &w, &gw0), eps).unwrap();
            let mut rec = rec();
            let (y, cache) = layer.forward(&mut rec, &upload(&[n, width], &x)).unwrap();
            let dx = layer.backward(&mut rec, &cache, &upload(&[n, width], &dy)).unwrap();
            rec.submit().unwrap();
            let (y_ref, _) = r::rmsnorm(&f64s(&x), &f64s(&w), eps as f64);
            let (dx_ref, dw_ref) = r::rmsnorm_backward(&f64s(&x), &f64s(&w), eps as f64, &f64s(&dy));
            // The CPU variants sum a row in order, one invocation to a row, where the GPU's
            // sum a row over a tree: measured 3.2e-14 at width 130 against the tree's 1e-14.
            assert_nmse(&format!("y {what}"), &read(&y), &y_ref, 1e-13);
            // With one column dx = r g w (1 - xhat^2), and 1 - xhat^2 = eps r^2 is eps-small but
            // formed as a difference of numbers near 1: its f32 relative error is large (the
            // absolute error stays at rounding level).
            let dx_bound = if width == 1 { 1e-4 } else { 3e-13 };
            assert_nmse(&format!("dx {what}"), &read(&dx), &dx_ref, dx_bound);
            assert_nmse(&format!("dw {what}"), &read(&layer.weight.grad), &plus(&gw0, &dw_ref), 3e-13);
        }
    }
}

#[test]
fn layernorm_matches_reference() {
    let mut rng = Rng::new(3);
    let eps = 1e-5;
    for n in ROWS.into_iter().chain([300]) {
        for width in WIDTHS {
            for affine in [false, true] {
                let what = format!("layernorm n={n} width={width} affine={affine}");
                let x: Vec<f32> = rng.normal_vec(n * width).iter().map(|v| v * 2.0 + 0.5).collect();
                let (w, b) = (rng.uniform_vec(width, 0.5, 1.5), rng.normal_vec(width));
                let (gw0, gb0) = (rng.normal_vec(width), rng.normal_vec(width));
                let dy = rng.normal_vec(n * width);
                let params = affine.then(|| (param(&[width], &w, &gw0), param(&[width], &b, &gb0)));
                let layer = LayerNorm::new(width, params, eps).unwrap();
                let mut rec = rec();
                let (y, cache) = layer.forward(&mut rec, &upload(&[n, width], &x)).unwrap();
                let dx = layer.backward(&mut rec, &cache, &upload(&[n, width], &dy)).unwrap();
                rec.submit().unwrap();
                let (wf, bf) = (f64s(&w), f64s(&b));
                let aff = affine.then_some((wf.as_slice(), bf.as_slice()));
                let (y_ref, _, _) = r::layernorm(&f64s(&x), width, aff, eps as f64);
                let (dx_ref, dw_ref, db_ref) =
                    r::layernorm_backward(&f64s(&x), width, aff.map(|a| a.0), eps as f64, &f64s(&dy));
                assert_nmse(&format!("y {what}"), &read(&y), &y_ref, 5e-14);
                assert_nmse(&format!("dx {what}"), &read(&dx), &dx_ref, 5e-14);
                if let Some((pw, pb)) = &layer.affine {
                    assert_nmse(&format!("dw {what}"), &read(&pw.grad), &plus(&gw0, &dw_ref), 1e-12);
                    assert_nmse(&format!("db {what}"), &read(&pb.grad), &plus(&gb0, &db_ref), 1e-12);
                }
            }
        }
    }
}

#[test]
fn adaln_modulation_and_gated_residual_match_reference() {
    let mut rng = Rng::new(4);
    for (b, t, d) in [(1, 1, 1), (3, 17, 5), (2, 3, 130), (2, 1, 64)] {
        let what = format!("adaLN b={b} t={t} d={d}");
        let x = rng.normal_vec(b * t * d);
        let (shift, scale, gate) = (rng.normal_vec(b * d), rng.normal_vec(b * d), rng.normal_vec(b * d));
        let res = rng.normal_vec(b * t * d);
        let dout = rng.normal_vec(b * t * d);
        let mut rec = rec();
        let (y, mc) = Modulate
            .forward(&mut rec, &upload(&[b, t, d], &x), &upload(&[b, d], &shift), &upload(&[b, d], &scale))
            .unwrap();
        let (out, gc) =
            GatedResidual.forward(&mut rec, &upload(&[b, t, d], &res), &upload(&[b, d], &gate), &y).unwrap();
        let gg = GatedResidual.backward(&mut rec, &gc, &upload(&[b, t, d], &dout)).unwrap();
        let mg = Modulate.backward(&mut rec, &mc, &gg.dy).unwrap();
        rec.submit().unwrap();
        let y_ref = r::modulate(&f64s(&x), &f64s(&shift), &f64s(&scale), b, t, d);
        let out_ref = r::gated_residual(&f64s(&res), &f64s(&gate), &y_ref, b, t, d);
        let [dres_ref, dgate_ref, dy_ref] =
            r::gated_residual_backward(&f64s(&gate), &y_ref, &f64s(&dout), b, t, d);
        let [dx_ref, dshift_ref, dscale_ref] =
            r::modulate_backward(&f64s(&x), &f64s(&scale), &dy_ref, b, t, d);
        assert_nmse(&format!("y {what}"), &read(&y), &y_ref, 3e-14);
        assert_nmse(&format!("out {what}"), &read(&out), &out_ref, 3e-14);
        assert_nmse(&format!("dres {what}"), &read(&gg.dres), &dres_ref, 0.0);
        assert_nmse(&format!("dgate {what}"), &read(&gg.dgate), &dgate_ref, 3e-14);
        assert_nmse(&format!("dx {what}"), &read(&mg.dx), &dx_ref, 3e-14);
        assert_nmse(&format!("dshift {what}"), &read(&mg.dshift), &dshift_ref, 3e-14);
        assert_nmse(&format!("dscale {what}"), &read(&mg.dscale), &dscale_ref, 3e-14);
    }
}

#[test]
fn feed_forwards_match_reference() {
    let mut rng = Rng::new(5);
    for (n, d, h, dout) in [(1, 1, 1, 1), (3, 5, 17, 5), (17, 64, 130, 64)] {
        let what = format!("n={n} d={d} h={h} out={dout}");
        let x = rng.normal_vec(n * d);
        let dy = rng.normal_vec(n * dout);
        let (w1, w3) = (normal(&mut rng, d * h, 0.5), normal(&mut rng, d * h, 0.5));
        let w2 = normal(&mut rng, h * dout, 0.2);
        let (b1, b2) = (rng.normal_vec(h), rng.normal_vec(dout));
        let g0: Vec<Vec<f32>> =
            [d * h, d * h, h * dout, h, dout].iter().map(|&k| rng.normal_vec(k)).collect();

        let swiglu = SwiGlu::new(
            param(&[d, h], &w1, &g0[0]),
            param(&[d, h], &w3, &g0[1]),
            param(&[h, dout], &w2, &g0[2]),
        )
        .unwrap();
        let mlp = GeluMlp::new(
            param(&[d, h], &w1, &g0[0]),
            param(&[h], &b1, &g0[3]),
            param(&[h, dout], &w2, &g0[2]),
            param(&[dout], &b2, &g0[4]),
        )
        .unwrap();
        let mut rec = rec();
        let (xt, dyt) = (upload(&[n, d], &x), upload(&[n, dout], &dy));
        let (ys, cs) = swiglu.forward(&mut rec, &xt).unwrap();
        let dxs = swiglu.backward(&mut rec, &cs, &dyt).unwrap();
        let (yg, cg) = mlp.forward(&mut rec, &xt).unwrap();
        let dxg = mlp.backward(&mut rec, &cg, &dyt).unwrap();
        rec.submit().unwrap();

        let (xf, dyf) = (f64s(&x), f64s(&dy));
        let (w1f, w3f, w2f) = (f64s(&w1), f64s(&w3), f64s(&w2));
        let ys_ref = r::swiglu_ff(&xf, &w1f, &w3f, &w2f, n, d, h, dout);
        let [dx, dw1, dw3, dw2] = r::swiglu_ff_backward(&xf, &w1f, &w3f, &w2f, &dyf, n, d, h, dout);
        assert_nmse(&format!("swiglu y {what}"), &read(&ys), &ys_ref, 3e-13);
        assert_nmse(&format!("swiglu dx {what}"), &read(&dxs), &dx, 3e-13);
        assert_nmse(&format!("swiglu dW1 {what}"), &read(&swiglu.w1.weight.grad), &plus(&g0[0], &dw1), 3e-13);
        assert_nmse(&format!("swiglu dW3 {what}"), &read(&swiglu.w3.weight.grad), &plus(&g0[1], &dw3), 3e-13);
        assert_nmse(&format!("swiglu dW2 {what}"), &read(&swiglu.w2.weight.grad), &plus(&g0[2], &dw2), 3e-13);

        let (b1f, b2f) = (f64s(&b1), f64s(&b2));
        let yg_ref = r::gelu_mlp(&xf, &w1f, &b1f, &w2f, &b2f, n, d, h, dout);
        let [dx, dw1, db1, dw2, db2] = r::gelu_mlp_backward(&xf, &w1f, &b1f, &w2f, &dyf, n, d, h, dout);
        let fc1b = mlp.fc1.bias.as_ref().unwrap();
        let fc2b = mlp.fc2.bias.as_ref().unwrap();
        assert_nmse(&format!("gelu y {what}"), &read(&yg), &yg_ref, 3e-13);
        assert_nmse(&format!("gelu dx {what}"), &read(&dxg), &dx, 3e-13);
        assert_nmse(&format!("gelu dW1 {what}"), &read(&mlp.fc1.weight.grad), &plus(&g0[0], &dw1), 3e-13);
        assert_nmse(&format!("gelu db1 {what}"), &read(&fc1b.grad), &plus(&g0[3], &db1), 3e-13);
        assert_nmse(&format!("gelu dW2 {what}"), &read(&mlp.fc2.weight.grad), &plus(&g0[2], &dw2), 3e-13);
        assert_nmse(&format!("gelu db2 {what}"), &read(&fc2b.grad), &plus(&g0[4], &db2), 3e-13);
    }
}

#[test]
fn a_parameter_used_twice_sums_its_gradients() {
    let mut rng = Rng::new(6);
    let (n, din, dout) = (3, 5, 4);
    let w = rng.normal_vec(din * dout);
    let layer = Linear::new(param(&[din, dout], &w, &vec![0.0; din * dout]), None).unwrap();
    let (x1, x2, dy1, dy2) = (
        rng.normal_vec(n * din),
        rng.normal_vec(n * din),
        rng.normal_vec(n * dout),
        rng.normal_vec(n * dout),
    );
    let mut rec = rec();
    let (_, c1) = layer.forward(&mut rec, &upload(&[n, din], &x1)).unwrap();
    let (_, c2) = layer.forward(&mut rec, &upload(&[n, din], &x2)).unwrap();
    layer.backward(&mut rec, &c2, &upload(&[n, dout], &dy2)).unwrap();
    layer.backward(&mut rec, &c1, &upload(&[n, dout], &dy1)).unwrap();
    rec.submit().unwrap();
    let (_, a, _) = r::linear_backward(&f64s(&x1), &f64s(&w), &f64s(&dy1), n, din, dout);
    let (_, b, _) = r::linear_backward(&f64s(&x2), &f64s(&w), &f64s(&dy2), n, din, dout);
    let sum: Vec<f64> = a.iter().zip(&b).map(|(p, q)| p + q).collect();
    assert_nmse("dW of a weight used twice", &read(&layer.weight.grad), &sum, 1e-14);
}

#[test]
fn fourier_embedding_matches_reference() {
    let mut rng = Rng::new(7);
    let gpu = gpu();
    // xyz as in docs/models.md (32 frequencies 2^0..2^12, with the input), tau with 8 octaves.
    let layers = [
        Fourier::log_spaced(&gpu, 3, 32, 12.0, true).unwrap(),
        Fourier::octaves(&gpu, 1, 8, false).unwrap(),
        Fourier::octaves(&gpu, 5, 1, true).unwrap(),
    ];
    // The log-spaced frequencies round w x once in f32 (see shaders/fourier.wgsl); octaves are exact.
    let bounds = [(5e-9, 2e-7), (1e-13, 1e-13), (1e-13, 1e-13)];
    for (layer, (y_bound, dx_bound)) in layers.iter().zip(bounds) {
        for n in ROWS {
            let c = layer.channels;
            let what = format!("fourier c={c} F={} n={n} input={}", layer.freqs.len(), layer.include_input);
            let x = rng.uniform_vec(n * c, -1.0, 1.0);
            let dy = rng.normal_vec(n * layer.out_width());
            let mut rec = rec();
            let (y, cache) = layer.forward(&mut rec, &upload(&[n, c], &x)).unwrap();
            let dx = layer.backward(&mut rec, &cache, &upload(&[n, layer.out_width()], &dy)).unwrap();
            rec.submit().unwrap();
            let freqs = f64s(&layer.freqs);
            let y_ref = r::fourier(&f64s(&x), c, &freqs, layer.include_input);
            let dx_ref = r::fourier_backward(&f64s(&x), c, &freqs, layer.include_input, &f64s(&dy));
            assert_nmse(&format!("y {what}"), &read(&y), &y_ref, y_bound);
            assert_nmse(&format!("dx {what}"), &read(&dx), &dx_ref, dx_bound);
        }
    }
}

#[test]
fn residual_passes_gradients_to_both_branches() {
    let mut rng = Rng::new(8);
    let (x, fx, dy) = (rng.normal_vec(17 * 5), rng.normal_vec(17 * 5), rng.normal_vec(17 * 5));
    let mut rec = rec();
    let (y, cache) = Residual.forward(&mut rec, &upload(&[17, 5], &x), &upload(&[17, 5], &fx)).unwrap();
    let (dx, dfx) = Residual.backward(&mut rec, &cache, &upload(&[17, 5], &dy)).unwrap();
    rec.submit().unwrap();
    let y_ref: Vec<f64> = x.iter().zip(&fx).map(|(a, b)| *a as f64 + *b as f64).collect();
    assert_nmse("residual y", &read(&y), &y_ref, 1e-15);
    assert_nmse("residual dx", &read(&dx), &f64s(&dy), 0.0);
    assert_nmse("residual dfx", &read(&dfx), &f64s(&dy), 0.0);
}

fn losses() -> [Loss; 7] {
    [
        Loss::mse(),
        Loss::l1(),
        Loss::huber(0.7),
        Loss::bce_with_logits(),
        Loss::mse().weighted(1e-4),
        Loss::focal(2.0),
        Loss::focal(1.0).weighted(3.0),
    ]
}

fn loss_inputs(rng: &mut Rng, kind: LossKind, n: usize) -> (Vec<f32>, Vec<f32>) {
    let pred = normal(rng, n, 2.0);
    let target = match kind {
        LossKind::BceWithLogits | LossKind::Focal { .. } => rng.uniform_vec(n, 0.0, 1.0),
        _ => rng.normal_vec(n),
    };
    (pred, target)
}

#[test]
fn losses_match_reference() {
    let mut rng = Rng::new(9);
    for loss in losses() {
        for n in [1, 17, 390] {
            let what = format!("{:?} x{} n={n}", loss.kind, loss.weight);
            let (pred, target) = loss_inputs(&mut rng, loss.kind, n);
            let mut rec = rec();
            let (l, g) =
                loss.forward_backward(&mut rec, &upload(&[n], &pred), &upload(&[n], &target)).unwrap();
            rec.submit().unwrap();
            let (l_ref, g_ref) = r::loss(loss.kind, &f64s(&pred), &f64s(&target), loss.weight as f64);
            assert_eq!(l.shape(), [1]);
            // The focal loss's f32 pow and its two gradient terms, which nearly cancel where a
            // label is near 0.5, cost a few more ulps (measured: 2.5e-13 at worst).
            let bound = if matches!(loss.kind, LossKind::Focal { .. }) { 1e-12 } else { 5e-14 };
            assert_nmse(&format!("loss {what}"), &read(&l), &[l_ref], bound);
            assert_nmse(&format!("grad {what}"), &read(&g), &g_ref, bound);
        }
    }
}

#[test]
fn norms_are_stable_at_large_tiny_and_constant_rows() {
    let mut rng = Rng::new(10);
    let width = 130;
    let mut x = Vec::new();
    x.extend(normal(&mut rng, width, 1e4));
    x.extend(normal(&mut rng, width, 1e-4));
    x.extend(vec![3.0f32; width]);
    x.extend(vec![0.0f32; width]);
    x.extend(vec![-1e4f32; width]);
    let n = 5;
    let dy = rng.normal_vec(n * width);
    let w = rng.uniform_vec(width, 0.5, 1.5);
    let b = rng.normal_vec(width);
    let zeros = vec![0.0f32; width];
    let eps = 1e-5;
    let rms = RmsNorm::new(param(&[width], &w, &zeros), eps).unwrap();
    let ln =
        LayerNorm::new(width, Some((param(&[width], &w, &zeros), param(&[width], &b, &zeros))), eps).unwrap();
    let mut rec = rec();
    let (xt, dyt) = (upload(&[n, width], &x), upload(&[n, width], &dy));
    let (yr, cr) = rms.forward(&mut rec, &xt).unwrap();
    let dxr = rms.backward(&mut rec, &cr, &dyt).unwrap();
    let (yl, cl) = ln.forward(&mut rec, &xt).unwrap();
    let dxl = ln.backward(&mut rec, &cl, &dyt).unwrap();
    rec.submit().unwrap();
    let (xf, wf, bf, dyf) = (f64s(&x), f64s(&w), f64s(&b), f64s(&dy));
    let (yr_ref, _) = r::rmsnorm(&xf, &wf, eps as f64);
    let (dxr_ref, dwr_ref) = r::rmsnorm_backward(&xf, &wf, eps as f64, &dyf);
    let (yl_ref, _, _) = r::layernorm(&xf, width, Some((&wf, &bf)), eps as f64);
    let (dxl_ref, dwl_ref, dbl_ref) = r::layernorm_backward(&xf, width, Some(&wf), eps as f64, &dyf);
    for (what, t) in [("rms y", &yr), ("rms dx", &dxr), ("ln y", &yl), ("ln dx", &dxl)] {
        assert!(read(t).iter().all(|v| v.is_finite()), "{what}: not finite");
    }
    // Row by row: each row's error against its own scale. The CPU variants' sum in order of a
    // constant row of -1e4 rounds the same way at every addition (measured: 7e-13 for y; the
    // GPU's tree sums it exactly), the rest stay under 3e-14.
    for row in 0..n {
        let bound = if row == 4 { 2e-12 } else { 3e-14 };
        let s = row * width..(row + 1) * width;
        let at = |t: &Tensor| read(t)[s.clone()].to_vec();
        assert_nmse(&format!("stable rms y row {row}"), &at(&yr), &yr_ref[s.clone()], bound);
        assert_nmse(&format!("stable rms dx row {row}"), &at(&dxr), &dxr_ref[s.clone()], bound);
        assert_nmse(&format!("stable ln y row {row}"), &at(&yl), &yl_ref[s.clone()], bound);
        assert_nmse(&format!("stable ln dx row {row}"), &at(&dxl), &dxl_ref[s.clone()], bound);
    }
    // The weight's gradient sums every row's, the constant row's rounding with them (3e-13
    // with the CPU variants).
    assert_nmse("stable rms dw", &read(&rms.weight.grad), &dwr_ref, 1e-12);
    let (pw, pb) = ln.affine.as_ref().unwrap();
    assert_nmse("stable ln dw", &read(&pw.grad), &dwl_ref, 3e-14);
    assert_nmse("stable ln db", &read(&pb.grad), &dbl_ref, 3e-14);
}

/// The focal loss's reference gradient is checked against finite differences in the engine's
/// harness (`engine/tests/ops/cases.rs`); here, its parameter's range.
#[test]
fn focal_loss_refuses_gamma_below_one() {
    let mut rec = rec();
    let t = upload(&[1], &[1.0]);
    assert!(Loss::focal(0.5).forward_backward(&mut rec, &t, &t).is_err(), "gamma below 1 is refused");
}

#[test]
fn bce_with_saturated_logits_stays_finite() {
    let pred = [100.0f32, -100.0, 100.0, -100.0, 0.0, 30.0, -30.0, 88.0, -88.0];
    let target = [1.0f32, 0.0, 0.0, 1.0, 0.5, 1.0, 1.0, 0.3, 0.7];
    let n = pred.len();
    for loss in [Loss::bce_with_logits(), Loss::focal(2.0)] {
        let mut rec = rec();
        let (l, g) = loss.forward_backward(&mut rec, &upload(&[n], &pred), &upload(&[n], &target)).unwrap();
        rec.submit().unwrap();
        let (l_ref, g_ref) = r::loss(loss.kind, &f64s(&pred), &f64s(&target), 1.0);
        assert!(read(&l)[0].is_finite() && read(&g).iter().all(|v| v.is_finite()));
        assert_nmse(&format!("{:?} saturated loss", loss.kind), &read(&l), &[l_ref], 1e-13);
        assert_nmse(&format!("{:?} saturated grad", loss.kind), &read(&g), &g_ref, 1e-13);
    }
}

// ---- the layer references' backward passes against finite differences of their forwards (the
// single ops' are in the engine's harness, engine/tests/ops/cases.rs) ----

const EPS: f64 = 1e-6;
const FD_TOL: f64 = 1e-8;

fn normals(rng: &mut Rng, n: usize) -> Vec<f64> {
    (0..n).map(|_| rng.normal()).collect()
}

#[test]
fn reference_linear_and_feed_forwards_match_finite_differences() {
    let mut rng = Rng::new(20);
    let (n, d, h, o) = (3, 4, 5, 2);
    let g = normals(&mut rng, n * o);
    let inputs = vec![normals(&mut rng, n * d), normals(&mut rng, d * o), normals(&mut rng, o)];
    let (dx, dw, db) = r::linear_backward(&inputs[0], &inputs[1], &g, n, d, o);
    let loss = |v: &[Vec<f64>]| dot(&r::linear(&v[0], &v[1], Some(&v[2]), n, d, o), &g);
    finite_differences("linear", &inputs, &[dx, dw, db], loss, EPS, FD_TOL);

    let inputs = vec![
        normals(&mut rng, n * d),
        normals(&mut rng, d * h),
        normals(&mut rng, d * h),
        normals(&mut rng, h * o),
    ];
    let grads = r::swiglu_ff_backward(&inputs[0], &inputs[1], &inputs[2], &inputs[3], &g, n, d, h, o);
    let loss = |v: &[Vec<f64>]| dot(&r::swiglu_ff(&v[0], &v[1], &v[2], &v[3], n, d, h, o), &g);
    finite_differences("swiglu feed-forward", &inputs, &grads, loss, EPS, FD_TOL);

    let inputs = vec![
        normals(&mut rng, n * d),
        normals(&mut rng, d * h),
        normals(&mut rng, h),
        normals(&mut rng, h * o),
        normals(&mut rng, o),
    ];
    let grads = r::gelu_mlp_backward(&inputs[0], &inputs[1], &inputs[2], &inputs[3], &g, n, d, h, o);
    let loss = |v: &[Vec<f64>]| dot(&r::gelu_mlp(&v[0], &v[1], &v[2], &v[3], &v[4], n, d, h, o), &g);
    finite_differences("gelu feed-forward", &inputs, &grads, loss, EPS, FD_TOL);
}
