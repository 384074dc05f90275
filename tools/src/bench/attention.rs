//! `velox bench attention`: fused segment attention at the paper's sizes, forward and
//! backward in f32 and on f16 inputs, time against the f64 reference (on the exact inputs, so
//! the f16 rows' errors include the rounding of q, k and v). The f16 backward row takes the f16
//! forward pass's o and lse, as training on f16 inputs would.
//!
//! The f16 rows run the cooperative-matrix kernel where the device has one (precision
//! "f16 coop": both products on f16 fragments, the softmax weights rounded to f16), else the
//! portable f16-input kernel (precision "f16": f16 reads, f32 arithmetic).
//!
//! Error: the reference is computed on a sample of segments (all their rows, so o, dq, dk and
//! dv are all exact there), or, for one dense segment too large for a CPU reference, on a
//! sample of query rows (o and dq, which depend on one query row each).

use velox_engine::ops::attention::{self, attention, attention_backward, reference, Segments};
use velox_engine::ops::cast::cast;
use velox_engine::ops::matmul;
use velox_engine::rng::Rng;
use velox_engine::{DType, Gpu, Result, Tensor};

use super::{print_header, print_row, time_gpu, Record, SizeSet};

struct Case {
    name: &'static str,
    q_lens: Vec<usize>,
    /// Key lengths; `None` means self-attention (keys are the queries).
    k_lens: Option<Vec<usize>>,
    heads: usize,
    d: usize,
}

/// `count` segment lengths, each `mean` +- `spread` (at least 1).
fn lengths(rng: &mut Rng, count: usize, mean: usize, spread: usize) -> Vec<usize> {
    (0..count)
        .map(|_| (mean as i64 + rng.below(2 * spread as u32 + 1) as i64 - spread as i64).max(1) as usize)
        .collect()
}

fn cases(rng: &mut Rng, small: bool) -> Vec<Case> {
    if small {
        vec![
            Case { name: "dense self", q_lens: vec![512], k_lens: None, heads: 4, d: 32 },
            Case { name: "window self", q_lens: lengths(rng, 64, 32, 12), k_lens: None, heads: 4, d: 32 },
            Case {
                name: "cell cross",
                q_lens: vec![1; 256],
                k_lens: Some(lengths(rng, 256, 40, 30)),
                heads: 4,
                d: 32,
            },
            Case { name: "global cross", q_lens: vec![600], k_lens: Some(vec![512]), heads: 2, d: 64 },
        ]
    } else {
        // The paper's sizes (docs/models.md): 8192 tokens of width 512 in 16 heads; voxel
        // windows of about 32 tokens; cells of about 180 of 1.44 M points, one query each; Gaussian
        // decoder queries (10k) over all 8192 tokens in 8 heads of 64.
        // 8192 cells of 176 +- 120 points: about 1.44 M points.
        let cells = lengths(rng, 8192, 176, 120);
        let n_cells = cells.len();
        vec![
            Case { name: "dense self", q_lens: vec![8192], k_lens: None, heads: 16, d: 32 },
            Case { name: "window self", q_lens: lengths(rng, 256, 32, 12), k_lens: None, heads: 16, d: 32 },
            Case { name: "cell cross", q_lens: vec![1; n_cells], k_lens: Some(cells), heads: 16, d: 32 },
            Case { name: "global cross", q_lens: vec![10_000], k_lens: Some(vec![8192]), heads: 8, d: 64 },
        ]
    }
}

pub fn run(gpu: &Gpu, sizes: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let small = sizes.small();
    let mut rng = Rng::new(11);
    let c = gpu.caps();
    let device = c.name.clone();
    let f32_peak = c.known_peaks().map(|p| p.1);
    let f16_peak = c.known_peaks().map(|p| p.0);
    let (roof16, roof32) = (super::Roof::of(c, true), super::Roof::of(c, false));
    println!("device: {device} ({}); {repeats} timed repeats per case, median shown", c.kind);
    print_header();
    let mut records = Vec::new();
    for case in cases(&mut rng, small) {
        let k_lens = case.k_lens.clone().unwrap_or_else(|| case.q_lens.clone());
        let (h, d) = (case.heads, case.d);
        let (nq, nk): (usize, usize) = (case.q_lens.iter().sum(), k_lens.iter().sum());
        let q = rng.normal_vec(nq * h * d);
        let k = if case.k_lens.is_none() { q.clone() } else { rng.normal_vec(nk * h * d) };
        let v = rng.normal_vec(nk * h * d);
        let g = rng.normal_vec(nq * h * d);
        let tq = Tensor::from_slice(gpu, &[nq, h, d], &q)?;
        let tk = if case.k_lens.is_none() { tq.clone() } else { Tensor::from_slice(gpu, &[nk, h, d], &k)? };
        let tv = Tensor::from_slice(gpu, &[nk, h, d], &v)?;
        let tg = Tensor::from_slice(gpu, &[nq, h, d], &g)?;
        let seg = Segments::from_lengths(gpu, &case.q_lens, &k_lens)?;
        let scale = 1.0 / (d as f32).sqrt();

        let mut out = None;
        let (fwd_ms, fwd_min, timed) = time_gpu(gpu, repeats, |rec| {
            out = Some(attention(rec, &tq, &tk, &tv, &seg, scale)?);
            Ok(())
        })?;
        let out = out.unwrap();
        let mut rec = gpu.recorder()?;
        let (q16, k16, v16) = (
            cast(&mut rec, &tq, DType::F16)?,
            cast(&mut rec, &tk, DType::F16)?,
            cast(&mut rec, &tv, DType::F16)?,
        );
        rec.submit()?;
        let mut out16 = None;
        let (f16_ms, f16_min, _) = time_gpu(gpu, repeats, |rec| {
            out16 = Some(attention(rec, &q16, &k16, &v16, &seg, scale)?);
            Ok(())
        })?;
        let out16 = out16.unwrap();
        let o16: Vec<f32> = out16.o.read()?;
        // Where the device takes 64-key tiles here, the 32-key tiles timed beside them, so that
        // a run says what the wider tile is worth.
        let coop = attention::coop_forward_chosen(gpu, d, nq, nk, case.q_lens.len(), true);
        let narrow = match coop {
            Some(c) if c.keys > attention::COOP_KEY_TILES[0] => {
                let mut out = None;
                let timing = time_gpu(gpu, repeats, |rec| {
                    rec.set_wide_key_tiles(false);
                    out = Some(attention(rec, &q16, &k16, &v16, &seg, scale)?);
                    Ok(())
                })?;
                let narrow = attention::coop_forward_chosen(gpu, d, nq, nk, case.q_lens.len(), false);
                let name = narrow.map_or("f16".to_string(), |c| format!("f16 coop{}x{}", c.rows, c.keys));
                Some((name, timing, out.unwrap().o.read::<f32>()?))
            }
            _ => None,
        };
        let mut narrow_got = Vec::new();
        let mut grads = None;
        let (bwd_ms, bwd_min, _) = time_gpu(gpu, repeats, |rec| {
            grads = Some(attention_backward(rec, &tq, &tk, &tv, &out, &tg, &seg, scale)?);
            Ok(())
        })?;
        let grads = grads.unwrap();
        let mut grads16 = None;
        let (bwd16_ms, bwd16_min, _) = time_gpu(gpu, repeats, |rec| {
            grads16 = Some(attention_backward(rec, &q16, &k16, &v16, &out16, &tg, &seg, scale)?);
            Ok(())
        })?;
        let grads16 = grads16.unwrap();
        let (dq16, dk16, dv16): (Vec<f32>, Vec<f32>, Vec<f32>) =
            (grads16.dq.read()?, grads16.dk.read()?, grads16.dv.read()?);

        // Reference on a sample.
        let (o, dq, dk, dv): (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) =
            (out.o.read()?, grads.dq.read()?, grads.dk.read()?, grads.dv.read()?);
        let q_off = reference::offsets(&case.q_lens);
        let k_off = reference::offsets(&k_lens);
        let row = h * d;
        let (mut fwd_got, mut fwd_want, mut bwd_got, mut bwd_want) = (vec![], vec![], vec![], vec![]);
        let (mut f16_got, mut bwd16_got) = (vec![], vec![]);
        let segments = case.q_lens.len();
        let sampled_rows = segments == 1 && nq * nk > 1 << 22;
        let picks: Vec<usize> = if segments <= 8 {
            (0..segments).collect()
        } else {
            (0..8).map(|_| rng.below(segments as u32) as usize).collect()
        };
        for s in picks {
            let rows: Vec<usize> = if sampled_rows {
                (0..32).map(|_| q_off[s] + rng.below(case.q_lens[s] as u32) as usize).collect()
            } else {
                (q_off[s]..q_off[s + 1]).collect()
            };
            let pick = |t: &[f32], rows: &[usize]| -> Vec<f64> {
                rows.iter().flat_map(|&r| t[r * row..(r + 1) * row].iter().map(|&x| x as f64)).collect()
            };
            let keys: Vec<usize> = (k_off[s]..k_off[s + 1]).collect();
            let (sq, sg) = (pick(&q, &rows), pick(&g, &rows));
            let (sk, sv) = (pick(&k, &keys), pick(&v, &keys));
            let qo = [0, rows.len()];
            let ko = [0, keys.len()];
            let (o_ref, _) = reference::attention(&sq, &sk, &sv, &qo, &ko, h, d, scale as f64);
            let (dq_ref, dk_ref, dv_ref) =
                reference::attention_backward(&sq, &sk, &sv, &sg, &qo, &ko, h, d, scale as f64);
            let as32 = |t: &[f32], rows: &[usize]| -> Vec<f32> {
                rows.iter().flat_map(|&r| t[r * row..(r + 1) * row].iter().copied()).collect()
            };
            fwd_got.extend(as32(&o, &rows));
            f16_got.extend(as32(&o16, &rows));
            if let Some((_, _, o)) = &narrow {
                narrow_got.extend(as32(o, &rows));
            }
            fwd_want.extend(o_ref);
            bwd_got.extend(as32(&dq, &rows));
            bwd16_got.extend(as32(&dq16, &rows));
            bwd_want.extend(dq_ref);
            if !sampled_rows {
                bwd_got.extend(as32(&dk, &keys));
                bwd16_got.extend(as32(&dk16, &keys));
                bwd_want.extend(dk_ref);
                bwd_got.extend(as32(&dv, &keys));
                bwd16_got.extend(as32(&dv16, &keys));
                bwd_want.extend(dv_ref);
            }
        }
        let error_over = if sampled_rows {
            "o and dq on sampled query rows".to_string()
        } else {
            "all outputs of sampled segments".to_string()
        };
        let flops = attention::forward_flops(&case.q_lens, &k_lens, h, d);
        let f16_name = match coop {
            Some(c) => format!("f16 coop{}x{}", c.rows, c.keys),
            None => "f16".to_string(),
        };
        let shape = format!("{nq}x{nk} h{h} d{d} ({segments} seg)");
        // Compulsory traffic: the forward reads Q, K, V and writes O and each row's log-sum-exp;
        // the backward reads Q, K, V, O, dO and the log-sum-exps and writes dQ, dK, dV (its dQ,
        // dK, dV in f32 whatever the inputs).
        let (q_vals, kv_vals, lse) = ((nq * h * d) as f64, (nk * h * d) as f64, (nq * h * 4) as f64);
        let fwd_bytes = |elem: f64| elem * (2.0 * q_vals + 2.0 * kv_vals) + lse;
        let bwd_bytes = |elem: f64| {
            elem * (2.0 * q_vals + 2.0 * kv_vals) + 4.0 * q_vals + lse + 4.0 * (q_vals + 2.0 * kv_vals)
        };
        let coop_bwd = attention::coop_backward_chosen(gpu, d, nq, nk, case.q_lens.len());
        let f16_bwd_name =
            if coop_bwd { format!("f16 coop{}", attention::COOP_BWD_BLOCK) } else { "f16".to_string() };
        let f16_bwd_kernel = if coop_bwd {
            attention::f16_backward_variant(gpu, d)
        } else {
            attention::portable_variant(gpu, d, DType::F16).to_string()
        };
        let portable = attention::portable_variant(gpu, d, DType::F32);
        let f16_fwd_kernel = attention::f16_forward_variant(gpu, d);
        let mut rows = vec![
            ("fwd", "f32", fwd_ms, fwd_min, flops, &fwd_got, &fwd_want, fwd_bytes(4.0), portable.to_string()),
            (
                "fwd",
                f16_name.as_str(),
                f16_ms,
                f16_min,
                flops,
                &f16_got,
                &fwd_want,
                fwd_bytes(2.0),
                f16_fwd_kernel.clone(),
            ),
            (
                "bwd",
                "f32",
                bwd_ms,
                bwd_min,
                2.5 * flops,
                &bwd_got,
                &bwd_want,
                bwd_bytes(4.0),
                portable.to_string(),
            ),
            (
                "bwd",
                f16_bwd_name.as_str(),
                bwd16_ms,
                bwd16_min,
                2.5 * flops,
                &bwd16_got,
                &bwd_want,
                bwd_bytes(2.0),
                f16_bwd_kernel,
            ),
        ];
        if let Some((name, (ms, min, _), _)) = &narrow {
            let kernel = format!("{f16_fwd_kernel} (32-key tiles, beside the 64-key row)");
            rows.push((
                "fwd",
                name.as_str(),
                *ms,
                *min,
                flops,
                &narrow_got,
                &fwd_want,
                fwd_bytes(2.0),
                kernel,
            ));
        }
        for (pass, precision, ms, min, f, got, want, bytes, kernel) in rows {
            let tflops = f / (ms * 1e-3) / 1e12;
            let name = format!("attn {} {pass}", case.name);
            let peak = if precision.starts_with("f16") { f16_peak } else { f32_peak };
            let r = Record::timed(
                name,
                shape.clone(),
                precision,
                &device,
                (ms, min, timed),
                repeats,
                tflops,
                "TFLOP/s",
            )
            .peak(peak.map(|p| tflops / p))
            .against(got, want, error_over.clone())
            .work(f, bytes, if precision.starts_with("f16") { roof16 } else { roof32 })
            .kernel(kernel);
            print_row(&r);
            records.push(r);
        }

        // Windowed attention against its matmuls alone: a batched S = Q K^T and O = P V over
        // the same number of 32-token windows and heads, on f32 operands and on f16 ones (the
        // baseline of the f16 attention rows). f16 windows are rounded up to a multiple of 8
        // rows so both products suit the cooperative-matrix kernel where there is one (its
        // operands' contiguous axes must be multiples of 8).
        if case.name == "window self" {
            let b = segments * h;
            let w = nq.div_ceil(segments);
            for (dtype, rows, peak) in
                [(DType::F32, w, f32_peak), (DType::F16, w.next_multiple_of(8), f16_peak)]
            {
                let timing = window_matmuls(gpu, &mut rng, [b, rows, d], dtype, repeats)?;
                let tflops = 4.0 * (b * rows * rows * d) as f64 / (timing.0 * 1e-3) / 1e12;
                let r = Record::timed(
                    "window matmuls alone",
                    format!("{b} x ({rows}x{rows}x{d}) x2"),
                    dtype.name(),
                    &device,
                    timing,
                    repeats,
                    tflops,
                    "TFLOP/s",
                )
                .peak(peak.map(|p| tflops / p))
                .error(0.0, 0.0, "not checked (timing baseline)");
                // Q, P read and S, O written, in the operands' type (the outputs f32).
                let elem = if dtype == DType::F16 { 2.0 } else { 4.0 };
                let bytes = (b * rows * (rows + d)) as f64 * (elem + 4.0);
                let roof = if dtype == DType::F16 { roof16 } else { roof32 };
                let r = r.work(4.0 * (b * rows * rows * d) as f64, bytes, roof);
                print_row(&r);
                records.push(r);
            }
        }
    }
    Ok(records)
}

/// Times S = Q K^T and O = P V for `b` windows of `w` rows of width `d` on `dtype` operands
/// (random Q and P; the values do not matter to the time).
fn window_matmuls(
    gpu: &Gpu,
    rng: &mut Rng,
    [b, w, d]: [usize; 3],
    dtype: DType,
    repeats: u32,
) -> Result<(f64, f64, bool)> {
    let mut rec = gpu.recorder()?;
    let q = cast(&mut rec, &Tensor::from_slice(gpu, &[b, w, d], &rng.normal_vec(b * w * d))?, dtype)?;
    let p = cast(&mut rec, &Tensor::from_slice(gpu, &[b, w, w], &rng.normal_vec(b * w * w))?, dtype)?;
    rec.submit()?;
    let s = Tensor::empty(gpu, &[b, w, w], DType::F32)?;
    let o = Tensor::empty(gpu, &[b, w, d], DType::F32)?;
    time_gpu(gpu, repeats, |rec| {
        matmul::matmul_into(rec, &q, &q, false, true, &s, false)?;
        matmul::matmul_into(rec, &p, &q, false, false, &o, false)
    })
}
