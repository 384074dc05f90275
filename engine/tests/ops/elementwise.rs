//! Cast, unary and binary maps, reductions, softmax, gather and scatter-add against their f64
//! references on lavapipe, on awkward sizes.

use crate::common;
use common::*;
use velox_engine::ops::binary::{self, binary, Binary};
use velox_engine::ops::cast::{self, cast};
use velox_engine::ops::gather::{self, gather};
use velox_engine::ops::reduce::{self, reduce, Reduce};
use velox_engine::ops::scatter_add::{self, scatter_add, scatter_add_cas};
use velox_engine::ops::softmax::{self, softmax};
use velox_engine::ops::unary::{self, unary, Unary};

const SIZES: [usize; 7] = [0, 1, 2, 255, 256, 257, 10_007];
/// More than 65535 workgroups of 256: the dispatch must fold into two dimensions.
const HUGE: usize = 65_536 * 256 + 3;

#[test]
fn cast_round_trips_f32_f16_f32() {
    let gpu = gpu();
    let mut rng = Rng::new(1);
    for &n in SIZES.iter().chain([HUGE].iter()) {
        let mut x = rng.normal_vec(n);
        if n > 3 {
            x[0] = 70000.0; // beyond f16: +Inf in IEEE
            x[1] = 1e-6; // subnormal in f16
            x[2] = -0.0;
        }
        let t = Tensor::from_slice(&gpu, &[n], &x).unwrap();
        if !binds_or_refused(&gpu, 4 * n, || cast(&mut gpu.recorder()?, &t, DType::F16)) {
            continue;
        }
        let mut rec = gpu.recorder().unwrap();
        let h = cast(&mut rec, &t, DType::F16).unwrap();
        let back = cast(&mut rec, &h, DType::F32).unwrap();
        rec.submit().unwrap();
        let want = cast::reference::to_f16(&x);
        let got_h: Vec<half::f16> = h.read().unwrap();
        let got: Vec<f32> = back.read().unwrap();
        for i in 0..n {
            assert_eq!(got_h[i].to_f64().to_bits(), want[i].to_bits(), "f16 bits at {i} of {n}");
            assert_eq!((got[i] as f64).to_bits(), want[i].to_bits(), "round trip at {i} of {n}");
        }
    }
}

#[test]
fn unary_maps_match_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(2);
    for &f in Unary::ALL {
        for &n in &SIZES {
            // Domains where the map is finite; large magnitudes test saturation.
            let x: Vec<f32> = match f {
                Unary::Log | Unary::Sqrt | Unary::Rsqrt => rng.uniform_vec(n, 1e-3, 100.0),
                Unary::Recip => rng
                    .uniform_vec(n, 0.1, 10.0)
                    .iter()
                    .zip(rng.normal_vec(n))
                    .map(|(v, s)| v * s.signum())
                    .collect(),
                Unary::Exp => rng.uniform_vec(n, -80.0, 80.0),
                Unary::Sin | Unary::Cos => rng.uniform_vec(n, -10.0, 10.0),
                _ => rng
                    .normal_vec(n)
                    .iter()
                    .enumerate()
                    .map(|(i, v)| if i % 17 == 0 { v * 1e4 } else { v * 4.0 })
                    .collect(),
            };
            let t = Tensor::from_slice(&gpu, &[n], &x).unwrap();
            let mut rec = gpu.recorder().unwrap();
            let y = unary(&mut rec, &t, f).unwrap();
            rec.submit().unwrap();
            let got: Vec<f32> = y.read().unwrap();
            let want = unary::reference::unary(&x, f);
            assert_nmse(&format!("{f:?} n={n}"), &got, &want, 1e-9);
            // Pointwise bound: no value may be far off even when small. The lavapipe-measured
            // bound (4e-6 relative, 1e-6 absolute) widened where Vulkan lets the builtin a
            // kernel calls be less precise, so that every conforming device passes.
            for i in 0..n {
                let tol = 4e-6 * want[i].abs() + 1e-6 + vulkan_allowance(f, x[i] as f64, want[i]);
                assert!(
                    (got[i] as f64 - want[i]).abs() <= tol,
                    "{f:?}({}) = {} want {}",
                    x[i],
                    got[i],
                    want[i]
                );
            }
        }
    }
}

/// The error Vulkan's precision rules allow the builtin behind `f` at `x` beyond the bound
/// lavapipe meets ("Precision and Operation of SPIR-V Instructions": exp within 3 + 2|x| ulp,
/// log within 3 ulp outside [0.5, 2] and 2^-21 absolute inside, division 2.5 ulp, inverseSqrt
/// 2 ulp, sqrt as 1 / inverseSqrt, tanh and the sigmoid family as their exp formulas). Sin and
/// cos are the kernels' own (`shaders/include/sincos.wgsl`), so they keep the tight bound.
fn vulkan_allowance(f: Unary, x: f64, want: f64) -> f64 {
    let ulp = |v: f64| v.abs() * f32::EPSILON as f64;
    let exp_ulps = 3.0 + 2.0 * x.abs();
    match f {
        Unary::Exp => exp_ulps * ulp(want),
        Unary::Log if (0.5..=2.0).contains(&x) => 2f64.powi(-21),
        Unary::Log => 3.0 * ulp(want),
        Unary::Recip => 2.5 * ulp(want),
        Unary::Rsqrt => 2.0 * ulp(want),
        Unary::Sqrt => 5.0 * ulp(want),
        // exp(-|x|) off by its ulps, then a division: relative to the result, or to 1 for tanh's
        // cancellation near 0.
        Unary::Sigmoid | Unary::Silu | Unary::Gelu | Unary::GeluTanh => (exp_ulps + 3.0) * ulp(want),
        Unary::Tanh => (exp_ulps.min(33.0) + 3.0) * f32::EPSILON as f64,
        _ => 0.0,
    }
}

#[test]
fn unary_on_more_workgroups_than_one_dimension_allows() {
    let gpu = gpu();
    let x: Vec<f32> = (0..HUGE).map(|i| (i % 1000) as f32).collect();
    let t = Tensor::from_slice(&gpu, &[HUGE], &x).unwrap();
    if !binds_or_refused(&gpu, 4 * HUGE, || unary(&mut gpu.recorder()?, &t, Unary::Affine(2.0, 1.0))) {
        return;
    }
    let mut rec = gpu.recorder().unwrap();
    let y = unary(&mut rec, &t, Unary::Affine(2.0, 1.0)).unwrap();
    rec.submit().unwrap();
    let got: Vec<f32> = y.read().unwrap();
    assert!(got.iter().enumerate().all(|(i, &v)| v == 2.0 * (i % 1000) as f32 + 1.0));
}

#[test]
fn binary_broadcasts_match_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(3);
    let cases: &[(&[usize], &[usize])] = &[
        (&[0], &[0]),
        (&[1], &[1]),
        (&[257], &[257]),
        (&[257], &[1]),
        (&[3, 1], &[1, 5]),
        (&[2, 3, 4], &[4]),
        (&[2, 3, 4], &[3, 1]),
        (&[2, 1, 4, 5], &[3, 1, 1]),
        (&[6, 7, 8, 9, 10], &[7, 8, 9, 10]),
    ];
    for &op in Binary::ALL {
        for &(sa, sb) in cases {
            let na: usize = sa.iter().product();
            let nb: usize = sb.iter().product();
            let a = rng.normal_vec(na);
            let b: Vec<f32> = rng
                .normal_vec(nb)
                .iter()
                .map(|v| if op == Binary::Div { v.signum() * (v.abs() + 0.5) } else { *v })
                .collect();
            let ta = Tensor::from_slice(&gpu, sa, &a).unwrap();
            let tb = Tensor::from_slice(&gpu, sb, &b).unwrap();
            let mut rec = gpu.recorder().unwrap();
            let out = binary(&mut rec, &ta, &tb, op).unwrap();
            rec.submit().unwrap();
            let (shape, want) = binary::reference::binary(&a, sa, &b, sb, op);
            assert_eq!(out.shape(), &shape[..]);
            assert_nmse(&format!("{op:?} {sa:?} {sb:?}"), &out.read::<f32>().unwrap(), &want, 1e-13);
        }
    }
}

#[test]
fn binary_rejects_bad_shapes_and_too_many_dims() {
    let gpu = gpu();
    let a = Tensor::empty(&gpu, &[2, 3], DType::F32).unwrap();
    let b = Tensor::empty(&gpu, &[4], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let err = binary(&mut rec, &a, &b, Binary::Add).unwrap_err();
    assert!(matches!(err, velox_engine::Error::Shape(_)), "{err}");
    // Alternating broadcasts over five dims cannot merge to four.
    let a = Tensor::empty(&gpu, &[2, 1, 2, 1, 2], DType::F32).unwrap();
    let b = Tensor::empty(&gpu, &[1, 2, 1, 2, 1], DType::F32).unwrap();
    let _ = binary(&mut rec, &a, &b, Binary::Add).unwrap_err();
    let u = Tensor::empty(&gpu, &[2], DType::U32).unwrap();
    assert!(binary(&mut rec, &u, &u, Binary::Add).is_err());
}

#[test]
fn reductions_match_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(4);
    let shapes: &[&[usize]] =
        &[&[1], &[5], &[3, 0], &[0, 3], &[257, 3], &[3, 1000], &[4, 5, 6], &[2, 3001, 3], &[70_000, 3]];
    for &shape in shapes {
        for axis in 0..shape.len() {
            for op in [Reduce::Sum, Reduce::Mean, Reduce::Max] {
                if shape[axis] == 0 && op == Reduce::Max {
                    continue;
                }
                let n: usize = shape.iter().product();
                let x: Vec<f32> = rng.normal_vec(n).iter().map(|v| v * 100.0).collect();
                let t = Tensor::from_slice(&gpu, shape, &x).unwrap();
                let mut rec = gpu.recorder().unwrap();
                let y = reduce(&mut rec, &t, axis, op).unwrap();
                // The same into a tensor that holds values already: added to them.
                let m: usize =
                    shape.iter().enumerate().filter(|&(a, _)| a != axis).map(|(_, &s)| s).product();
                let old = rng.normal_vec(m);
                let acc = Tensor::from_slice(&gpu, &[m], &old).unwrap();
                reduce::reduce_into(&mut rec, &t, axis, op, &acc, true).unwrap();
                rec.submit().unwrap();
                let want = reduce::reference::reduce(&x, shape, axis, op);
                let what = format!("{op:?} axis {axis} of {shape:?}");
                assert_nmse(&what, &y.read::<f32>().unwrap(), &want, 1e-10);
                let added: Vec<f64> = want.iter().zip(&old).map(|(w, &o)| w + o as f64).collect();
                assert_nmse(&format!("{what}, accumulated"), &acc.read::<f32>().unwrap(), &added, 1e-10);
            }
        }
    }
    let t = Tensor::empty(&gpu, &[3, 0], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(reduce(&mut rec, &t, 1, Reduce::Max).is_err());
    assert!(reduce(&mut rec, &t, 2, Reduce::Sum).is_err());
    // An output of the wrong size, or the input itself, is refused.
    let x = Tensor::from_slice(&gpu, &[2, 3], &[1.0f32; 6]).unwrap();
    let wrong = Tensor::empty(&gpu, &[2], DType::F32).unwrap();
    assert!(reduce::reduce_into(&mut rec, &x, 0, Reduce::Sum, &wrong, true).is_err());
    assert!(reduce::reduce_into(&mut rec, &x, 0, Reduce::Sum, &x.view(0, &[3]).unwrap(), true).is_err());
}

#[test]
fn softmax_matches_reference_and_is_stable() {
    let gpu = gpu();
    let mut rng = Rng::new(5);
    for &(rows, len, scale) in &[
        (0, 5, 1.0),
        (1, 1, 1.0),
        (3, 7, 1.0),
        (5, 257, 10.0),
        (2, 100_000, 3.0),
        (70_000, 2, 1.0),
        (4, 1000, 1e4),
        (4, 33, 1e6),
    ] {
        let x: Vec<f32> = rng.normal_vec(rows * len).iter().map(|v| v * scale as f32).collect();
        let t = Tensor::from_slice(&gpu, &[rows, len], &x).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let y = softmax(&mut rec, &t).unwrap();
        rec.submit().unwrap();
        let got: Vec<f32> = y.read().unwrap();
        assert!(got.iter().all(|v| v.is_finite()), "non-finite softmax at scale {scale}");
        assert_nmse(
            &format!("softmax {rows}x{len} scale {scale}"),
            &got,
            &softmax::reference::softmax(&x, len),
            1e-11,
        );
    }
}

#[test]
fn gather_and_scatter_add_match_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(6);
    // Widths of a multiple of 4 take the vec4 kernel on CPU devices, the others the scalar one.
    let cases = [(1, 1, 0), (1, 1, 1), (5, 3, 17), (9, 4, 50), (6, 12, 31), (100, 64, 1000), (7, 1, 70_001)];
    for &(src_rows, width, n_idx) in &cases {
        let src = rng.normal_vec(src_rows * width);
        // Include out-of-range indices: gather gives zeros, scatter skips them.
        let idx: Vec<u32> = (0..n_idx)
            .map(|i| if i % 13 == 12 { src_rows as u32 + 3 } else { rng.below(src_rows as u32) })
            .collect();
        let ts = Tensor::from_slice(&gpu, &[src_rows, width], &src).unwrap();
        let ti = Tensor::from_slice(&gpu, &[n_idx], &idx).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let g = gather(&mut rec, &ts, &ti).unwrap();
        rec.submit().unwrap();
        let want = gather::reference::gather(&src, width, &idx);
        assert_nmse("gather", &g.read::<f32>().unwrap(), &want, 0.0);
        // The same rows added to a base in the pass.
        let base = rng.normal_vec(n_idx * width);
        let tb = Tensor::from_slice(&gpu, &[n_idx, width], &base).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let g = gather::gather_plus(&mut rec, &ts, &ti, &tb).unwrap();
        rec.submit().unwrap();
        let want: Vec<f64> = want.iter().zip(&base).map(|(w, b)| (*w as f32 + b) as f64).collect();
        assert_nmse("gather_plus", &g.read::<f32>().unwrap(), &want, 0.0);

        // Scatter the gathered rows back, through both kernels: many rows collide.
        let rows_src = rng.normal_vec(n_idx * width);
        let init = rng.normal_vec(src_rows * width);
        let want = scatter_add::reference::scatter_add(&rows_src, width, &idx, &init);
        let trs = Tensor::from_slice(&gpu, &[n_idx, width], &rows_src).unwrap();
        for cas in [false, true] {
            let out = Tensor::from_slice(&gpu, &[src_rows, width], &init).unwrap();
            let mut rec = gpu.recorder().unwrap();
            if cas {
                scatter_add_cas(&mut rec, &trs, &ti, &out).unwrap();
            } else {
                scatter_add(&mut rec, &trs, &ti, &out).unwrap();
            }
            rec.submit().unwrap();
            // The adds land in the order the device runs them, so the rounding differs by
            // device: r adds of unit-variance rows in any order leave an NMSE of about
            // r eps^2 / 24 (rounding errors of variance eps^2 / 12 relative to partial sums
            // of growing size), 5.9e-12 at r = 10^4 rows per output. Bound: 10x that, at
            // least 1e-11 (SwiftShader measured 1.2e-11 there).
            let per_output = n_idx as f64 / src_rows as f64;
            let bound = (10.0 * per_output * (f32::EPSILON as f64).powi(2) / 24.0).max(1e-11);
            assert_nmse(
                &format!("scatter_add cas={cas} {src_rows}x{width} <- {n_idx}"),
                &out.read::<f32>().unwrap(),
                &want,
                bound,
            );
        }
    }
}

#[test]
fn column_copies_and_permutation_inverse() {
    use velox_engine::ops::columns::{self, columns, copy_columns};
    use velox_engine::ops::gather::invert_permutation;
    let gpu = gpu();
    let mut rng = Rng::new(8);
    for &rows in &[0usize, 1, 257, 70_001] {
        let src = rng.normal_vec(rows * 7);
        let t = Tensor::from_slice(&gpu, &[rows, 7], &src).unwrap();
        let dst = Tensor::from_slice(&gpu, &[rows, 4], &vec![9.0f32; rows * 4]).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let xyz = columns(&mut rec, &t, 0, 3, 1.0).unwrap();
        copy_columns(&mut rec, &t, 0, &dst, 0, 3, 1.0).unwrap();
        copy_columns(&mut rec, &t, 6, &dst, 3, 1, 2.5).unwrap();
        rec.submit().unwrap();
        assert_nmse(
            "xyz columns",
            &xyz.read::<f32>().unwrap(),
            &columns::reference::columns(&src, 7, 0, 3, 1.0),
            0.0,
        );
        let got: Vec<f32> = dst.read().unwrap();
        for r in 0..rows {
            assert_eq!(&got[r * 4..r * 4 + 3], &src[r * 7..r * 7 + 3]);
            assert_eq!(got[r * 4 + 3], 2.5 * src[r * 7 + 6]);
        }
        // A random permutation and its inverse.
        let mut perm: Vec<u32> = (0..rows as u32).collect();
        for i in (1..rows).rev() {
            perm.swap(i, rng.below(i as u32 + 1) as usize);
        }
        let tp = Tensor::from_slice(&gpu, &[rows], &perm).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let inv = invert_permutation(&mut rec, &tp).unwrap();
        rec.submit().unwrap();
        assert_eq!(
            inv.read::<u32>().unwrap(),
            velox_engine::ops::gather::reference::invert_permutation(&perm)
        );
    }
    let t = Tensor::empty(&gpu, &[3, 7], DType::F32).unwrap();
    let d = Tensor::empty(&gpu, &[3, 4], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(copy_columns(&mut rec, &t, 5, &d, 0, 3, 1.0).is_err());
    assert!(copy_columns(&mut rec, &t, 0, &d, 2, 3, 1.0).is_err());
}

/// The voxel head's forward and backward are rows of the harness (`cases.rs`); this keeps the
/// refusal of a features tensor of the wrong width.
#[test]
fn the_voxel_head_refuses_features_of_the_wrong_width() {
    use velox_engine::ops::voxel_head;
    let gpu = gpu();
    let mut rec = gpu.recorder().unwrap();
    let bad = Tensor::empty(&gpu, &[2, 7], DType::F32).unwrap();
    let (e, o) = (
        Tensor::empty(&gpu, &[4, 5], DType::F32).unwrap(),
        Tensor::empty(&gpu, &[4, 3], DType::F32).unwrap(),
    );
    assert!(voxel_head::forward(&mut rec, &bad, &e, &o, false).is_err());
}
