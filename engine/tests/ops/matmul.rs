//! Batched matmul (`engine/src/ops/matmul.rs`, `shaders/matmul*.wgsl`) against its f64
//! reference, on shapes that miss every tile multiple; f32 products with a narrow side on
//! both of their kernels.
use crate::common;
use common::*;
use half::f16;
use velox_engine::kernels::{
    MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS4_MAIN, MATMUL_COOP8_ROWS64_COLS64_FRAG_COLS2_MAIN,
    MATMUL_COOP_ROWS128_COLS128_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN,
    MATMUL_COOP_ROWS128_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS64_COLS128_FRAG_COLS2_MAIN,
    MATMUL_COOP_ROWS64_COLS64_FRAG_COLS2_MAIN,
};
use velox_engine::ops::matmul::{
    coop_eligible, coop_kernel, coop_kernel_for, coop_layout_ok, matmul, matmul_bias, matmul_into,
    matmul_sum_into, matmul_variant, plan, reference,
};
use velox_engine::{Error, Gpu, NarrowMatmul, Recorder};

/// Every f32 test runs on each kernel choice, whatever the device: the narrow-tile kernels
/// (GPUs' choice for a side of 64 or less), the row kernel and the CPU kernel (CPU devices'
/// choices; the CPU kernel takes the products whose contiguous axes are multiples of 4).
const NARROW_CHOICES: [NarrowMatmul; 3] = [NarrowMatmul::Tiles, NarrowMatmul::Rows, NarrowMatmul::Vec4];

fn recorder(gpu: &Gpu, narrow: NarrowMatmul) -> Recorder {
    let mut rec = gpu.recorder().unwrap();
    rec.set_narrow_matmul(narrow);
    rec
}

/// f32 products: measured NMSE is 5e-14 typically and 5e-12 at worst (a 1x1 output whose
/// 130-term sum cancels); the bound leaves room for another summation order without letting
/// an indexing error (NMSE near 1) through.
const F32_BOUND: f64 = 1e-10;
/// f16 operands against the reference on the same (rounded) operands: the products are exact
/// in f32, so only the f32 accumulation differs.
const F16_ROUNDED_BOUND: f64 = 1e-10;
/// f16 operands against the reference on the unrounded f32 data: the rounding of the inputs.
const F16_INPUT_BOUND: f64 = 5e-4;

const SIZES: [usize; 6] = [1, 3, 17, 64, 65, 130];

/// Shapes of a and b for op(a) = [m, k], op(b) = [k, n] with optional batch dimensions.
fn shapes(
    m: usize,
    n: usize,
    k: usize,
    ta: bool,
    tb: bool,
    a_batch: Option<usize>,
    b_batch: Option<usize>,
) -> (Vec<usize>, Vec<usize>) {
    let mut a = if ta { vec![k, m] } else { vec![m, k] };
    let mut b = if tb { vec![n, k] } else { vec![k, n] };
    if let Some(x) = a_batch {
        a.insert(0, x);
    }
    if let Some(x) = b_batch {
        b.insert(0, x);
    }
    (a, b)
}

fn numel(s: &[usize]) -> usize {
    s.iter().product()
}

fn round_f16(x: &[f32]) -> Vec<f16> {
    x.iter().map(|&v| f16::from_f32(v)).collect()
}

/// m, n, k, a batch, b batch.
type Sizes = (usize, usize, usize, Option<usize>, Option<usize>);

/// One pending f32 product: the result tensor and its reference.
struct Case {
    what: String,
    out: Tensor,
    reference: Vec<f64>,
}

#[test]
fn f32_awkward_shapes_all_transposes() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        f32_awkward_shapes_all_transposes_with(narrow);
    }
}

fn f32_awkward_shapes_all_transposes_with(narrow: NarrowMatmul) {
    let gpu = gpu();
    let mut rng = Rng::new(1);
    let mut worst: f64 = 0.0;
    for &m in &SIZES {
        for &n in &SIZES {
            // One submit per (m, n): every k and transpose combination.
            let mut rec = recorder(&gpu, narrow);
            let mut cases = Vec::new();
            for &k in &SIZES {
                for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
                    let (sa, sb) = shapes(m, n, k, ta, tb, None, None);
                    let a = rng.normal_vec(numel(&sa));
                    let b = rng.normal_vec(numel(&sb));
                    let ta_ = Tensor::from_slice(&gpu, &sa, &a).unwrap();
                    let tb_ = Tensor::from_slice(&gpu, &sb, &b).unwrap();
                    let out = matmul(&mut rec, &ta_, &tb_, ta, tb).unwrap();
                    assert_eq!(out.shape(), &[m, n]);
                    let (r, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
                    cases.push(Case {
                        what: format!("m={m} n={n} k={k} ta={ta} tb={tb}"),
                        out,
                        reference: r,
                    });
                }
            }
            rec.submit().unwrap();
            for c in cases {
                let got = c.out.read::<f32>().unwrap();
                worst = worst.max(nmse(&got, &c.reference));
                assert_nmse(&c.what, &got, &c.reference, F32_BOUND);
            }
        }
    }
    eprintln!("f32 awkward shapes: worst nmse {worst:.3e}");
}

#[test]
fn narrow_sides_between_32_and_64_take_partial_64_tiles() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        narrow_sides_between_32_and_64_take_partial_64_tiles_with(narrow);
    }
}

fn narrow_sides_between_32_and_64_take_partial_64_tiles_with(narrow: NarrowMatmul) {
    // A narrow side of 33 to 64 takes the 64x64-tile kernel (4x4 outputs per invocation):
    // sides that leave its tiles partly filled, in both directions, with every transpose.
    let gpu = gpu();
    let mut rng = Rng::new(12);
    let mut rec = recorder(&gpu, narrow);
    let mut cases = Vec::new();
    for (m, n, k) in [(40, 47, 5), (100, 40, 33), (47, 200, 17), (33, 33, 70)] {
        for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
            let (sa, sb) = shapes(m, n, k, ta, tb, None, None);
            let (a, b) = (rng.normal_vec(numel(&sa)), rng.normal_vec(numel(&sb)));
            let out = matmul(
                &mut rec,
                &Tensor::from_slice(&gpu, &sa, &a).unwrap(),
                &Tensor::from_slice(&gpu, &sb, &b).unwrap(),
                ta,
                tb,
            )
            .unwrap();
            let (r, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
            cases.push((format!("m={m} n={n} k={k} ta={ta} tb={tb}"), out, r));
        }
    }
    rec.submit().unwrap();
    for (what, out, r) in cases {
        assert_nmse(&what, &out.read::<f32>().unwrap(), &r, F32_BOUND);
    }
}

#[test]
fn bias_is_added_to_every_row() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        bias_is_added_to_every_row_with(narrow);
    }
}

fn bias_is_added_to_every_row_with(narrow: NarrowMatmul) {
    // A bias per output column, added by every kernel: the tiled kernel (sides over 64), both
    // narrow-tile kernels, batches, a product split along K (added after the pieces are
    // summed), and f16 operands (the portable kernel adds it itself; the cooperative kernels
    // by a separate pass).
    let gpu = gpu();
    let mut rng = Rng::new(13);
    let mut rec = recorder(&gpu, narrow);
    let mut cases = Vec::new();
    let list: [(usize, usize, usize, Option<usize>, bool, bool); 7] = [
        (130, 70, 20, None, false, false),
        (100, 17, 9, None, false, true),
        (40, 47, 33, None, true, false),
        (65, 66, 8, Some(3), false, false),
        (40, 24, 4000, None, true, false),
        (136, 40, 24, Some(2), false, false),
        (9, 16, 40, None, true, true),
    ];
    for (i, &(m, n, k, batch, ta, tb)) in list.iter().enumerate() {
        let (sa, sb) = shapes(m, n, k, ta, tb, batch, None);
        let (a, b) = (rng.normal_vec(numel(&sa)), rng.normal_vec(numel(&sb)));
        let bias = rng.normal_vec(n);
        let half = i >= 5;
        let (ta_, tb_, a64, b64) = if half {
            let (ah, bh) = (round_f16(&a), round_f16(&b));
            let widen = |h: &[f16]| h.iter().map(|v| v.to_f64()).collect::<Vec<_>>();
            let (a64, b64) = (widen(&ah), widen(&bh));
            (
                Tensor::from_slice(&gpu, &sa, &ah).unwrap(),
                Tensor::from_slice(&gpu, &sb, &bh).unwrap(),
                a64,
                b64,
            )
        } else {
            (
                Tensor::from_slice(&gpu, &sa, &a).unwrap(),
                Tensor::from_slice(&gpu, &sb, &b).unwrap(),
                f64s(&a),
                f64s(&b),
            )
        };
        let tbias = Tensor::from_slice(&gpu, &[n], &bias).unwrap();
        let out = matmul_bias(&mut rec, &ta_, &tb_, ta, tb, &tbias).unwrap();
        let (r, _) = reference::matmul(&a64, &sa, &b64, &sb, ta, tb).unwrap();
        let want: Vec<f64> = r.iter().enumerate().map(|(e, x)| x + bias[e % n] as f64).collect();
        cases.push((format!("bias m={m} n={n} k={k} batch={batch:?} ta={ta} tb={tb} f16={half}"), out, want));
    }
    let a = Tensor::from_slice(&gpu, &[4, 3], &[0.0f32; 12]).unwrap();
    let b = Tensor::from_slice(&gpu, &[3, 5], &[0.0f32; 15]).unwrap();
    let wrong = Tensor::from_slice(&gpu, &[4], &[0.0f32; 4]).unwrap();
    let err = matmul_bias(&mut rec, &a, &b, false, false, &wrong).unwrap_err();
    assert!(matches!(err, Error::Shape(_)), "{err}");
    rec.submit().unwrap();
    for (what, out, want) in cases {
        assert_nmse(&what, &out.read::<f32>().unwrap(), &want, F16_ROUNDED_BOUND);
    }
}

#[test]
fn f32_batched_and_broadcast() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        f32_batched_and_broadcast_with(narrow);
    }
}

fn f32_batched_and_broadcast_with(narrow: NarrowMatmul) {
    let gpu = gpu();
    let mut rng = Rng::new(2);
    // (a batch, b batch): both batched, b broadcast (absent or 1), a broadcast.
    let batches = [
        (Some(1), Some(1)),
        (Some(3), Some(3)),
        (Some(3), None),
        (Some(3), Some(1)),
        (None, Some(3)),
        (Some(1), Some(3)),
    ];
    let mut worst: f64 = 0.0;
    let mut rec = recorder(&gpu, narrow);
    let mut cases = Vec::new();
    for (i, &(ab, bb)) in batches.iter().enumerate() {
        for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
            let (m, n, k) = [(17, 130, 65), (65, 3, 130), (130, 64, 17)][(i + ta as usize) % 3];
            let (sa, sb) = shapes(m, n, k, ta, tb, ab, bb);
            let a = rng.normal_vec(numel(&sa));
            let b = rng.normal_vec(numel(&sb));
            let ta_ = Tensor::from_slice(&gpu, &sa, &a).unwrap();
            let tb_ = Tensor::from_slice(&gpu, &sb, &b).unwrap();
            let out = matmul(&mut rec, &ta_, &tb_, ta, tb).unwrap();
            let (r, shape) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
            assert_eq!(out.shape(), shape.as_slice());
            cases.push(Case { what: format!("a {sa:?} b {sb:?} ta={ta} tb={tb}"), out, reference: r });
        }
    }
    rec.submit().unwrap();
    for c in cases {
        let got = c.out.read::<f32>().unwrap();
        worst = worst.max(nmse(&got, &c.reference));
        assert_nmse(&c.what, &got, &c.reference, F32_BOUND);
    }
    eprintln!("f32 batched and broadcast: worst nmse {worst:.3e}");
}

#[test]
fn accumulate_adds_and_plain_overwrites() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        accumulate_adds_and_plain_overwrites_with(narrow);
    }
}

fn accumulate_adds_and_plain_overwrites_with(narrow: NarrowMatmul) {
    let gpu = gpu();
    let mut rng = Rng::new(3);
    // Sides over 64 (the tiled kernel) and a narrow product.
    for (ta, tb, (m, n, k)) in
        [(false, false, (65, 130, 17)), (true, true, (65, 130, 17)), (true, false, (40, 20, 17))]
    {
        let (sa, sb) = shapes(m, n, k, ta, tb, Some(3), None);
        let a = rng.normal_vec(numel(&sa));
        let b = rng.normal_vec(numel(&sb));
        let old = rng.normal_vec(3 * m * n);
        let ta_ = Tensor::from_slice(&gpu, &sa, &a).unwrap();
        let tb_ = Tensor::from_slice(&gpu, &sb, &b).unwrap();
        let acc = Tensor::from_slice(&gpu, &[3, m, n], &old).unwrap();
        // Without accumulate every element is written, NaN included.
        let plain = Tensor::from_slice(&gpu, &[3, m, n], &vec![f32::NAN; 3 * m * n]).unwrap();
        let mut rec = recorder(&gpu, narrow);
        matmul_into(&mut rec, &ta_, &tb_, ta, tb, &acc, true).unwrap();
        matmul_into(&mut rec, &ta_, &tb_, ta, tb, &plain, false).unwrap();
        rec.submit().unwrap();
        let (r, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
        let summed: Vec<f64> = r.iter().zip(&old).map(|(x, &o)| x + o as f64).collect();
        assert_nmse("accumulate", &acc.read::<f32>().unwrap(), &summed, F32_BOUND);
        assert_nmse("overwrite", &plain.read::<f32>().unwrap(), &r, F32_BOUND);
    }
}

#[test]
fn f16_accumulate_on_interior_and_edge_tiles() {
    // 256 x 136 outputs: two whole 128x128 tiles, which the cooperative kernels store straight
    // to memory, and two edge tiles, which they stage through workgroup memory; plain and
    // accumulating, every transpose. On devices without cooperative matrices this exercises
    // the portable f16 kernel the same way.
    let gpu = gpu();
    let mut rng = Rng::new(9);
    let (m, n, k) = (256, 136, 48);
    for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
        let what = format!("f16 ta={ta} tb={tb} ({})", matmul_variant(&gpu, DType::F16));
        check_f16_product(&gpu, &mut rng, (m, n, k), (ta, tb), None, true, &what);
    }
}

#[test]
fn f16_products_on_every_cooperative_tile() {
    // The five kernels of the cooperative tiles (128x128 in 4 x 4 and in 4 x 2 fragments a
    // subgroup, 128x64 for outputs at most 64 wide, 64x128 for at most 64 rows, 64x64), each
    // whole (stored straight to memory) and with edges (staged), plain and accumulating, every
    // transpose, a batch with a broadcast operand. Where the device has no cooperative
    // matrices this runs the portable f16 kernel.
    let gpu = gpu();
    let mut rng = Rng::new(14);
    for (m, n, k) in [
        (256, 64, 40),
        (200, 40, 24),
        (64, 256, 48),
        (40, 136, 16),
        (64, 64, 64),
        (24, 48, 8),
        (136, 72, 32),
        (256, 128, 48),
        (200, 136, 24),
    ] {
        for wide in [true, false] {
            let kernel = coop_kernel_for(gpu.caps(), m, n, wide).filter(|&k| gpu.supports(k));
            if !wide && kernel == coop_kernel_for(gpu.caps(), m, n, true).filter(|&k| gpu.supports(k)) {
                continue;
            }
            for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
                let what = format!("[{m}, {n}] k {k} ta={ta} tb={tb} on {kernel:?}");
                check_f16_product(&gpu, &mut rng, (m, n, k), (ta, tb), Some(1), wide, &what);
            }
        }
    }
}

/// A batch of two f16 products `[m, k] x [k, n]` (transposed as `trans`; the second operand
/// batched, or broadcast with `b_batch` Some(1)) into f32, accumulated onto random values and
/// written over NaN, against the f64 reference of the rounded inputs; `wide_blocks` as the
/// recording's [`velox_engine::Recorder::set_wide_matmul_blocks`].
fn check_f16_product(
    gpu: &Gpu,
    rng: &mut Rng,
    (m, n, k): (usize, usize, usize),
    (ta, tb): (bool, bool),
    b_batch: Option<usize>,
    wide_blocks: bool,
    what: &str,
) {
    let (sa, sb) = shapes(m, n, k, ta, tb, Some(2), b_batch);
    let (ah, bh) = (round_f16(&rng.normal_vec(numel(&sa))), round_f16(&rng.normal_vec(numel(&sb))));
    let old = rng.normal_vec(2 * m * n);
    let a = Tensor::from_slice(gpu, &sa, &ah).unwrap();
    let b = Tensor::from_slice(gpu, &sb, &bh).unwrap();
    let acc = Tensor::from_slice(gpu, &[2, m, n], &old).unwrap();
    let plain = Tensor::from_slice(gpu, &[2, m, n], &vec![f32::NAN; 2 * m * n]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    rec.set_wide_matmul_blocks(wide_blocks);
    matmul_into(&mut rec, &a, &b, ta, tb, &acc, true).unwrap();
    matmul_into(&mut rec, &a, &b, ta, tb, &plain, false).unwrap();
    rec.submit().unwrap();
    let widen = |h: &[f16]| h.iter().map(|v| v.to_f64()).collect::<Vec<_>>();
    let (r, _) = reference::matmul(&widen(&ah), &sa, &widen(&bh), &sb, ta, tb).unwrap();
    let summed: Vec<f64> = r.iter().zip(&old).map(|(x, &o)| x + o as f64).collect();
    assert_nmse(&format!("{what} accumulate"), &acc.read::<f32>().unwrap(), &summed, F16_ROUNDED_BOUND);
    assert_nmse(&format!("{what} overwrite"), &plain.read::<f32>().unwrap(), &r, F16_ROUNDED_BOUND);
}

#[test]
fn long_k_products_are_split_along_k() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        long_k_products_are_split_along_k_with(narrow);
    }
}

fn long_k_products_are_split_along_k_with(narrow: NarrowMatmul) {
    // Few output tiles and a long K (a weight gradient x^T dy over many rows) are cut into
    // pieces of K summed afterwards: pieces that divide K and ones that leave a remainder,
    // every transpose, f32 and f16 operands, plain and accumulating.
    let gpu = gpu();
    let mut rng = Rng::new(8);
    for (i, &(m, n, k)) in
        [(32, 32, 10_000), (5, 130, 3001), (130, 129, 1024), (1, 1, 700)].iter().enumerate()
    {
        let (ta, tb) = [(true, false), (false, false), (false, true), (true, true)][i];
        let (sa, sb) = shapes(m, n, k, ta, tb, None, None);
        let a = rng.normal_vec(numel(&sa));
        let b = rng.normal_vec(numel(&sb));
        let old = rng.normal_vec(m * n);
        let (a32, b32) =
            (Tensor::from_slice(&gpu, &sa, &a).unwrap(), Tensor::from_slice(&gpu, &sb, &b).unwrap());
        let a16 = Tensor::from_slice(&gpu, &sa, &round_f16(&a)).unwrap();
        let b16 = Tensor::from_slice(&gpu, &sb, &round_f16(&b)).unwrap();
        let acc = Tensor::from_slice(&gpu, &[m, n], &old).unwrap();
        // The weight gradient of f16 training: f16 operands added into an f32 gradient.
        let acc16 = Tensor::from_slice(&gpu, &[m, n], &old).unwrap();
        let mut rec = recorder(&gpu, narrow);
        let plain = matmul(&mut rec, &a32, &b32, ta, tb).unwrap();
        matmul_into(&mut rec, &a32, &b32, ta, tb, &acc, true).unwrap();
        let half = matmul(&mut rec, &a16, &b16, ta, tb).unwrap();
        matmul_into(&mut rec, &a16, &b16, ta, tb, &acc16, true).unwrap();
        rec.submit().unwrap();
        let what = format!("m {m} n {n} k {k} ta {ta} tb {tb}");
        let (r, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
        let summed: Vec<f64> = r.iter().zip(&old).map(|(x, &o)| x + o as f64).collect();
        assert_nmse(&format!("split {what}"), &plain.read::<f32>().unwrap(), &r, F32_BOUND);
        assert_nmse(&format!("split accumulate {what}"), &acc.read::<f32>().unwrap(), &summed, F32_BOUND);
        let rounded = |x: &[f32]| -> Vec<f64> { round_f16(x).iter().map(|h| h.to_f64()).collect() };
        let (r16, _) = reference::matmul(&rounded(&a), &sa, &rounded(&b), &sb, ta, tb).unwrap();
        assert_nmse(&format!("split f16 {what}"), &half.read::<f32>().unwrap(), &r16, F16_ROUNDED_BOUND);
        let summed16: Vec<f64> = r16.iter().zip(&old).map(|(x, &o)| x + o as f64).collect();
        let got = acc16.read::<f32>().unwrap();
        assert_nmse(&format!("split f16 accumulate {what}"), &got, &summed16, F16_ROUNDED_BOUND);
    }
}

#[test]
fn a_weight_gradient_on_cooperative_matrices_is_split_along_k() {
    // The weight gradient of f16 training (x^T dy, one 128x128 tile over K = 10000 rows) runs on
    // the cooperative-matrix kernel where the device has one, cut into pieces along K like the
    // tiled kernels' products: pieces starting at multiples of 8 (its 16-byte reads), a tail
    // piece, and the sum. Elsewhere the tiled f16 kernel splits it the same way.
    let gpu = gpu();
    let (m, n, k) = (64, 96, 10_000);
    let mut rng = Rng::new(12);
    let x = round_f16(&rng.normal_vec(k * m));
    let dy = round_f16(&rng.normal_vec(k * n));
    let tx = Tensor::from_slice(&gpu, &[k, m], &x).unwrap();
    let tdy = Tensor::from_slice(&gpu, &[k, n], &dy).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let before = rec.dispatch_count();
    let got = matmul(&mut rec, &tx, &tdy, true, false).unwrap();
    let dispatches = rec.dispatch_count() - before;
    rec.submit().unwrap();
    // 39 pieces of 256 rows (10000 / 39, rounded down to a multiple of 8), a tail of 16, a sum.
    assert!(dispatches >= 3, "{dispatches} dispatches: the product was not split");
    let wide = |v: &[f16]| v.iter().map(|h| h.to_f64()).collect::<Vec<_>>();
    let (want, _) = reference::matmul(&wide(&x), &[k, m], &wide(&dy), &[k, n], true, false).unwrap();
    assert_nmse("split weight gradient", &got.read::<f32>().unwrap(), &want, F16_ROUNDED_BOUND);
}

#[test]
fn empty_products() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        empty_products_with(narrow);
    }
}

fn empty_products_with(narrow: NarrowMatmul) {
    let gpu = gpu();
    let mut rng = Rng::new(4);
    // K = 0: zeros, or unchanged under accumulate.
    for dtype in [DType::F32, DType::F16] {
        let a = Tensor::empty(&gpu, &[2, 5, 0], dtype).unwrap();
        let b = Tensor::empty(&gpu, &[0, 7], dtype).unwrap();
        let old = rng.normal_vec(70);
        let acc = Tensor::from_slice(&gpu, &[2, 5, 7], &old).unwrap();
        let mut rec = recorder(&gpu, narrow);
        let zeros = matmul(&mut rec, &a, &b, false, false).unwrap();
        matmul_into(&mut rec, &a, &b, false, false, &acc, true).unwrap();
        rec.submit().unwrap();
        assert!(zeros.read::<f32>().unwrap().iter().all(|&v| v == 0.0));
        assert_eq!(acc.read::<f32>().unwrap(), old);
    }
    // M = 0 or N = 0 or batch 0: an empty output, no work.
    for (sa, sb) in [(vec![0, 4], vec![4, 3]), (vec![5, 4], vec![4, 0]), (vec![0, 5, 4], vec![4, 3])] {
        let a = Tensor::empty(&gpu, &sa, DType::F32).unwrap();
        let b = Tensor::empty(&gpu, &sb, DType::F32).unwrap();
        let mut rec = recorder(&gpu, narrow);
        let out = matmul(&mut rec, &a, &b, false, false).unwrap();
        rec.submit().unwrap();
        assert_eq!(out.numel(), 0, "{sa:?} @ {sb:?}");
    }
}

#[test]
fn f16_operands_accumulate_in_f32() {
    let gpu = gpu();
    let mut rng = Rng::new(5);
    let mut worst_rounded: f64 = 0.0;
    let mut worst_input: f64 = 0.0;
    let mut rec = gpu.recorder().unwrap();
    let mut cases = Vec::new();
    // Awkward sizes, shapes whose contiguous axes are multiples of 8 (the cooperative kernel's
    // layout on devices that have it), batches and broadcast.
    let list: [Sizes; 6] = [
        (17, 3, 65, None, None),
        (130, 65, 1, None, None),
        (1, 130, 130, Some(3), None),
        (64, 64, 64, Some(3), Some(3)),
        (136, 40, 24, Some(2), Some(1)),
        (3, 17, 64, None, Some(3)),
    ];
    for &(m, n, k, ab, bb) in &list {
        for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
            let (sa, sb) = shapes(m, n, k, ta, tb, ab, bb);
            let a = rng.normal_vec(numel(&sa));
            let b = rng.normal_vec(numel(&sb));
            let (ah, bh) = (round_f16(&a), round_f16(&b));
            let ta_ = Tensor::from_slice(&gpu, &sa, &ah).unwrap();
            let tb_ = Tensor::from_slice(&gpu, &sb, &bh).unwrap();
            let out = matmul(&mut rec, &ta_, &tb_, ta, tb).unwrap();
            let widen = |h: &[f16]| h.iter().map(|v| v.to_f64()).collect::<Vec<_>>();
            let (rounded, _) = reference::matmul(&widen(&ah), &sa, &widen(&bh), &sb, ta, tb).unwrap();
            let (exact, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
            cases.push((format!("f16 a {sa:?} b {sb:?} ta={ta} tb={tb}"), out, rounded, exact));
        }
    }
    rec.submit().unwrap();
    for (what, out, rounded, exact) in cases {
        let got = out.read::<f32>().unwrap();
        worst_rounded = worst_rounded.max(nmse(&got, &rounded));
        worst_input = worst_input.max(nmse(&got, &exact));
        assert_nmse(&what, &got, &rounded, F16_ROUNDED_BOUND);
        assert_nmse(&what, &got, &exact, F16_INPUT_BOUND);
    }
    eprintln!(
        "f16 operands ({}): worst nmse {worst_rounded:.3e} against rounded inputs, {worst_input:.3e} against f32 inputs",
        matmul_variant(&gpu, DType::F16)
    );
}

/// Which kind of error `r` is (the test fails on success).
fn kind(r: velox_engine::Result<Tensor>) -> &'static str {
    match r {
        Err(Error::Shape(_)) => "shape",
        Err(Error::DType(_)) => "dtype",
        Err(Error::Invalid(_)) => "invalid",
        other => panic!("expected a shape, dtype or argument error, got {other:?}"),
    }
}

#[test]
fn bad_shapes_and_dtypes_are_refused() {
    let gpu = gpu();
    let t = |s: &[usize], d: DType| Tensor::empty(&gpu, s, d).unwrap();
    let f = DType::F32;
    let mut rec = gpu.recorder().unwrap();
    // Inner sizes differ.
    assert_eq!(kind(matmul(&mut rec, &t(&[3, 4], f), &t(&[5, 6], f), false, false)), "shape");
    // A transpose makes them agree or disagree.
    assert!(matmul(&mut rec, &t(&[4, 3], f), &t(&[4, 6], f), true, false).is_ok());
    assert_eq!(kind(matmul(&mut rec, &t(&[3, 4], f), &t(&[6, 4], f), false, false)), "shape");
    // Too few or too many axes; batch sizes that differ.
    assert_eq!(kind(matmul(&mut rec, &t(&[4], f), &t(&[4, 2], f), false, false)), "shape");
    assert_eq!(kind(matmul(&mut rec, &t(&[1, 2, 3, 4], f), &t(&[4, 2], f), false, false)), "shape");
    assert_eq!(kind(matmul(&mut rec, &t(&[2, 3, 4], f), &t(&[3, 4, 2], f), false, false)), "shape");
    // Operand dtypes that differ, or that no kernel takes.
    assert_eq!(kind(matmul(&mut rec, &t(&[3, 4], f), &t(&[4, 2], DType::F16), false, false)), "dtype");
    let u = DType::U32;
    assert_eq!(kind(matmul(&mut rec, &t(&[3, 4], u), &t(&[4, 2], u), false, false)), "dtype");

    let (a, b) = (t(&[3, 4], f), t(&[4, 2], f));
    let into = |rec: &mut velox_engine::Recorder, out: &Tensor| {
        matmul_into(rec, &a, &b, false, false, out, false).map(|_| out.clone())
    };
    assert_eq!(kind(into(&mut rec, &t(&[2, 3], f))), "shape");
    assert_eq!(kind(into(&mut rec, &t(&[3, 2], DType::F16))), "dtype");
    // An output that shares storage with an operand.
    let sq = t(&[4, 4], f);
    let shared = matmul_into(&mut rec, &sq, &t(&[4, 4], f), false, false, &sq, true).map(|_| sq.clone());
    assert_eq!(kind(shared), "shape");
    rec.submit().unwrap();
}

#[test]
fn more_batches_than_one_dispatch_dimension_takes_are_split() {
    for narrow in NARROW_CHOICES {
        eprintln!("narrow f32 products on the {narrow:?} kernels");
        more_batches_than_one_dispatch_dimension_takes_are_split_with(narrow);
    }
}

fn more_batches_than_one_dispatch_dimension_takes_are_split_with(narrow: NarrowMatmul) {
    // 70000 batches of [2, 3] x [3, 2]: the z dimension allows 65535 on lavapipe.
    let gpu = gpu();
    let mut rng = Rng::new(77);
    let batch = 70_000;
    let a = rng.normal_vec(batch * 6);
    let b = rng.normal_vec(batch * 6);
    let ta = Tensor::from_slice(&gpu, &[batch, 2, 3], &a).unwrap();
    let tb = Tensor::from_slice(&gpu, &[batch, 3, 2], &b).unwrap();
    let mut rec = recorder(&gpu, narrow);
    let c = matmul(&mut rec, &ta, &tb, false, false).unwrap();
    rec.submit().unwrap();
    let got: Vec<f32> = c.read().unwrap();
    let mut want = Vec::with_capacity(batch * 4);
    for z in 0..batch {
        for i in 0..2 {
            for j in 0..2 {
                want.push(
                    (0..3).map(|k| a[z * 6 + i * 3 + k] as f64 * b[z * 6 + k * 2 + j] as f64).sum::<f64>(),
                );
            }
        }
    }
    assert_nmse("70000 batches", &got, &want, 1e-12);
}

#[test]
fn plan_broadcasts_and_names_sizes() {
    let p = plan(&[3, 5, 4], &[4, 2], false, false).unwrap();
    assert_eq!((p.batch, p.m, p.n, p.k), (3, 5, 2, 4));
    assert_eq!((p.a_batch_stride, p.b_batch_stride), (20, 0));
    assert_eq!(p.out_shape, vec![3, 5, 2]);
    let p = plan(&[4, 5], &[3, 2, 4], true, true).unwrap();
    assert_eq!((p.batch, p.m, p.n, p.k), (3, 5, 2, 4));
    assert_eq!((p.a_batch_stride, p.b_batch_stride), (0, 8));
    let p = plan(&[1, 5, 4], &[3, 4, 2], false, false).unwrap();
    assert_eq!((p.batch, p.a_batch_stride, p.b_batch_stride), (3, 0, 8));
    assert_eq!(plan(&[5, 4], &[4, 2], false, false).unwrap().out_shape, vec![5, 2]);
}

#[test]
fn kernel_choice_follows_the_device() {
    let gpu = gpu();
    let caps = gpu.caps().clone();
    let f32_variant = matmul_variant(&gpu, DType::F32);
    assert!(
        f32_variant.contains("tiled f32") || (caps.kind == "CPU" && f32_variant.contains("CPU kernel")),
        "{f32_variant}"
    );
    if caps.coop_matrix_f16.is_none() {
        // lavapipe before Mesa 26 and other devices without cooperative matrices: the portable
        // f16 kernel.
        assert!(!coop_eligible(&caps));
        assert!(matmul_variant(&gpu, DType::F16).contains("tiled f16"));
    } else if coop_eligible(&caps) {
        assert!(matmul_variant(&gpu, DType::F16).contains("cooperative-matrix"));
    }
    // A device like the H100: 16x16x16 f16 shapes, subgroups of exactly 32, 48 KiB shared.
    let mut h100 = caps.clone();
    h100.cpu_kernels = false;
    h100.subgroup_size_control = false;
    h100.coop_matrix_f16 = Some([16, 16, 16]);
    h100.min_subgroup_size = 32;
    h100.max_subgroup_size = 32;
    h100.max_shared_memory = 49152;
    assert!(coop_eligible(&h100));
    // The same fragments on a CPU device that runs the CPU kernel variants (lavapipe 26
    // emulates them, slower than its portable kernels): not chosen.
    let mut emulated = h100.clone();
    emulated.cpu_kernels = true;
    assert!(!coop_eligible(&emulated));
    // Subgroups of 64 (AMD) or a variable size: the kernel's layout needs exactly 32.
    let mut amd = h100.clone();
    amd.min_subgroup_size = 64;
    amd.max_subgroup_size = 64;
    assert!(!coop_eligible(&amd));
    // A range that holds 32 (AMD RDNA: 32..64) qualifies where a pipeline can ask for 32, and
    // then the pipeline does; without subgroup size control it cannot be relied on.
    let mut variable = h100.clone();
    variable.min_subgroup_size = 8;
    variable.max_subgroup_size = 64;
    variable.subgroup_size_control = true;
    assert!(coop_eligible(&variable));
    variable.subgroup_size_control = false;
    assert!(!coop_eligible(&variable));
    let mut small = h100.clone();
    small.max_shared_memory = 32768;
    assert!(!coop_eligible(&small));
    let mut no_coop = h100.clone();
    no_coop.coop_matrix_f16 = None;
    assert!(!coop_eligible(&no_coop));
    assert_eq!(coop_kernel(&h100), Some(MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN));
    // The tile follows the output: a side of at most 64 takes the 64-wide tile. The 128x128
    // tile takes 4 x 4 fragments a subgroup unless the recording asks for 4 x 2.
    assert_eq!(coop_kernel_for(&h100, 65, 65, true), Some(MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN));
    assert_eq!(coop_kernel_for(&h100, 65, 65, false), Some(MATMUL_COOP_ROWS128_COLS128_FRAG_COLS2_MAIN));
    for wide in [true, false] {
        assert_eq!(
            coop_kernel_for(&h100, 10_000, 64, wide),
            Some(MATMUL_COOP_ROWS128_COLS64_FRAG_COLS2_MAIN)
        );
        assert_eq!(
            coop_kernel_for(&h100, 10_000, 32, wide),
            Some(MATMUL_COOP_ROWS128_COLS64_FRAG_COLS2_MAIN)
        );
        assert_eq!(coop_kernel_for(&h100, 64, 512, wide), Some(MATMUL_COOP_ROWS64_COLS128_FRAG_COLS2_MAIN));
        assert_eq!(coop_kernel_for(&h100, 1, 1, wide), Some(MATMUL_COOP_ROWS64_COLS64_FRAG_COLS2_MAIN));
        assert_eq!(coop_kernel_for(&emulated, 64, 64, wide), None);
    }
    // A device like lavapipe from Mesa 26: 8x8x8 shapes, subgroups of 8, 32 KiB shared, with
    // the GPU kernel variants (VELOX_CPU_KERNELS=0, as tools/coop-check.sh runs it).
    let mut lvp = caps.clone();
    lvp.cpu_kernels = false;
    lvp.coop_matrix_f16 = Some([8, 8, 8]);
    lvp.min_subgroup_size = 8;
    lvp.max_subgroup_size = 8;
    lvp.max_shared_memory = 32768;
    assert_eq!(coop_kernel(&lvp), Some(MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS4_MAIN));
    assert_eq!(coop_kernel_for(&lvp, 40, 64, true), Some(MATMUL_COOP8_ROWS64_COLS64_FRAG_COLS2_MAIN));
    let mut wide = lvp.clone();
    wide.min_subgroup_size = 32;
    wide.max_subgroup_size = 32;
    assert_eq!(coop_kernel(&wide), None, "8x8 fragments need subgroups of 8");

    // The contiguous axis of each operand must be a multiple of 8.
    let p = plan(&[24, 40], &[40, 16], false, false).unwrap();
    assert!(coop_layout_ok(&p, false, false));
    let p = plan(&[17, 40], &[40, 16], false, false).unwrap();
    assert!(coop_layout_ok(&p, false, false), "M is not a contiguous axis of A");
    assert!(!coop_layout_ok(&plan(&[40, 17], &[40, 16], true, false).unwrap(), true, false));
    assert!(!coop_layout_ok(&plan(&[24, 41], &[41, 16], false, false).unwrap(), false, false));
    assert!(coop_layout_ok(&plan(&[24, 40], &[17, 40], false, true).unwrap(), false, true));
    assert!(!coop_layout_ok(&plan(&[24, 40], &[40, 17], false, false).unwrap(), false, false));
}

#[test]
fn products_summed_over_the_batch() {
    // sum_i op(a[i]) @ op(b[i]) into one output: in one dispatch on the narrow-side kernel,
    // as a batched product and a sum elsewhere; plain and accumulating, every transpose, f16
    // operands too, and a broadcast operand.
    let gpu = gpu();
    let mut rng = Rng::new(31);
    for narrow in NARROW_CHOICES {
        for (i, &(m, n, k, batch)) in [(300, 24, 40, 3), (7, 64, 130, 2), (65, 17, 5, 6)].iter().enumerate() {
            for (ta, tb) in [(false, false), (false, true), (true, false), (true, true)] {
                let bb = if i == 2 { None } else { Some(batch) };
                let (sa, sb) = shapes(m, n, k, ta, tb, Some(batch), bb);
                let (a, b) = (round_f16(&rng.normal_vec(numel(&sa))), round_f16(&rng.normal_vec(numel(&sb))));
                let widen = |h: &[f16]| h.iter().map(|v| v.to_f32()).collect::<Vec<_>>();
                let (a32, b32) = (widen(&a), widen(&b));
                let old = rng.normal_vec(m * n);
                let (r, _) = reference::matmul(&f64s(&a32), &sa, &f64s(&b32), &sb, ta, tb).unwrap();
                let summed: Vec<f64> =
                    (0..m * n).map(|j| (0..batch).map(|z| r[z * m * n + j]).sum::<f64>()).collect();
                let added: Vec<f64> = summed.iter().zip(&old).map(|(s, &o)| s + o as f64).collect();
                let what = format!("sum of {batch} [{m}, {n}] k {k} ta {ta} tb {tb} {narrow:?}");
                for (name, ta_, tb_) in [
                    (
                        "f32",
                        Tensor::from_slice(&gpu, &sa, &a32).unwrap(),
                        Tensor::from_slice(&gpu, &sb, &b32).unwrap(),
                    ),
                    (
                        "f16",
                        Tensor::from_slice(&gpu, &sa, &a).unwrap(),
                        Tensor::from_slice(&gpu, &sb, &b).unwrap(),
                    ),
                ] {
                    let plain = Tensor::from_slice(&gpu, &[m, n], &vec![f32::NAN; m * n]).unwrap();
                    let acc = Tensor::from_slice(&gpu, &[m, n], &old).unwrap();
                    let mut rec = recorder(&gpu, narrow);
                    matmul_sum_into(&mut rec, &ta_, &tb_, ta, tb, &plain, false).unwrap();
                    matmul_sum_into(&mut rec, &ta_, &tb_, ta, tb, &acc, true).unwrap();
                    rec.submit().unwrap();
                    assert_nmse(&format!("{what} {name}"), &plain.read::<f32>().unwrap(), &summed, F32_BOUND);
                    assert_nmse(
                        &format!("{what} {name} accumulate"),
                        &acc.read::<f32>().unwrap(),
                        &added,
                        F32_BOUND,
                    );
                }
            }
        }
    }
    let a = Tensor::empty(&gpu, &[2, 4, 3], DType::F32).unwrap();
    let b = Tensor::empty(&gpu, &[2, 3, 5], DType::F32).unwrap();
    let wrong = Tensor::empty(&gpu, &[2, 4, 5], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(matmul_sum_into(&mut rec, &a, &b, false, false, &wrong, false).is_err());
}

#[test]
fn a_batched_product_takes_a_bias_per_entry() {
    // A stack of linear layers: x [rows, in] against W [k, in, out] with a bias [k, out], each
    // entry's row of biases added to its own output, fused or as a separate add.
    let gpu = gpu();
    let mut rng = Rng::new(32);
    let (k, rows, din, dout) = (3, 70, 12, 40);
    let x = rng.normal_vec(rows * din);
    let w = rng.normal_vec(k * din * dout);
    let bias = rng.normal_vec(k * dout);
    let (r, _) =
        reference::matmul(&f64s(&x), &[rows, din], &f64s(&w), &[k, din, dout], false, false).unwrap();
    let want: Vec<f64> =
        r.iter().enumerate().map(|(i, v)| v + bias[(i / (rows * dout)) * dout + i % dout] as f64).collect();
    for narrow in NARROW_CHOICES {
        let mut rec = recorder(&gpu, narrow);
        let t = |s: &[usize], d: &[f32]| Tensor::from_slice(&gpu, s, d).unwrap();
        let y = matmul_bias(
            &mut rec,
            &t(&[rows, din], &x),
            &t(&[k, din, dout], &w),
            false,
            false,
            &t(&[k, dout], &bias),
        )
        .unwrap();
        rec.submit().unwrap();
        assert_nmse(&format!("bias per entry, {narrow:?}"), &y.read::<f32>().unwrap(), &want, F32_BOUND);
    }
    let mut rec = gpu.recorder().unwrap();
    let wrong = Tensor::empty(&gpu, &[k + 1, dout], DType::F32).unwrap();
    let (xt, wt) = (
        Tensor::empty(&gpu, &[rows, din], DType::F32).unwrap(),
        Tensor::empty(&gpu, &[k, din, dout], DType::F32).unwrap(),
    );
    assert!(matmul_bias(&mut rec, &xt, &wt, false, false, &wrong).is_err());
}

/// Would catch: a slip in the CPU kernel's indexing that no other shape reaches: every layout
/// (a [M, K] or [K, M], b [K, N] or [N, K]) at multiples of 4 (its vec4 paths) and not (its
/// scalar paths) that leave its 8 x 32, 64 and 128 tiles and its 8-deep K blocks partly filled
/// (K a multiple of 4 and not of 8 among them), batched and broadcast operands, a bias (per
/// column and per entry), accumulation and a sum over the batch.
#[test]
fn the_cpu_kernel_takes_every_layout_with_partial_tiles() {
    let gpu = gpu();
    let mut rng = Rng::new(33);
    let mut rec = recorder(&gpu, NarrowMatmul::Vec4);
    let mut cases = Vec::new();
    let list: [Sizes; 11] = [
        (4, 4, 4, None, None),
        (9, 97, 13, None, None),
        (16, 256, 28, None, Some(2)),
        (12, 36, 20, None, None),
        (68, 132, 36, None, None),
        (9, 40, 6, None, None),
        (20, 12, 44, Some(3), Some(3)),
        (36, 8, 12, Some(2), None),
        (1, 1, 1, None, None),
        (37, 3, 195, None, None),
        (10, 41, 7, Some(2), Some(2)),
    ];
    for &(m, n, k, ab, bb) in &list {
        for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
            let (sa, sb) = shapes(m, n, k, ta, tb, ab, bb);
            let (a, b) = (rng.normal_vec(numel(&sa)), rng.normal_vec(numel(&sb)));
            let batch = ab.or(bb).unwrap_or(1);
            let bias = rng.normal_vec(batch * n);
            let old = rng.normal_vec(batch * m * n);
            let t = |s: &[usize], d: &[f32]| Tensor::from_slice(&gpu, s, d).unwrap();
            let (at, bt) = (t(&sa, &a), t(&sb, &b));
            let plain = matmul(&mut rec, &at, &bt, ta, tb).unwrap();
            let shape = plain.shape().to_vec();
            // One bias row, or one per batch entry.
            let bias_shape = if batch > 1 { vec![batch, n] } else { vec![n] };
            let biased = matmul_bias(&mut rec, &at, &bt, ta, tb, &t(&bias_shape, &bias)).unwrap();
            let acc = t(&shape, &old);
            matmul_into(&mut rec, &at, &bt, ta, tb, &acc, true).unwrap();
            let (r, _) = reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb).unwrap();
            let with_bias: Vec<f64> =
                r.iter().enumerate().map(|(i, v)| v + bias[(i / (m * n)) * n + i % n] as f64).collect();
            let added: Vec<f64> = r.iter().zip(&old).map(|(v, &o)| v + o as f64).collect();
            let what = format!("m={m} n={n} k={k} batches {ab:?} {bb:?} ta={ta} tb={tb}");
            cases.push((what.clone(), plain, r));
            cases.push((format!("{what} bias"), biased, with_bias));
            cases.push((format!("{what} accumulate"), acc, added));
            if batch > 1 {
                let sum = t(&[m, n], &vec![f32::NAN; m * n]);
                matmul_sum_into(&mut rec, &at, &bt, ta, tb, &sum, false).unwrap();
                let want: Vec<f64> = (0..m * n)
                    .map(|j| (0..batch).map(|z| cases[cases.len() - 3].2[z * m * n + j]).sum())
                    .collect();
                cases.push((format!("{what} summed"), sum, want));
            }
        }
    }
    rec.submit().unwrap();
    for (what, out, want) in cases {
        assert_nmse(&what, &out.read::<f32>().unwrap(), &want, F32_BOUND);
    }
}
