//! `velox bench layers`: each layer's forward and backward at the paper's sizes (8192 tokens
//! of width 512; feed-forwards of ratio 4; the encoder's Fourier embedding of 1.44 M points),
//! time against the f64 reference.
//!
//! Error: every layer here maps rows independently (given its parameters), so the outputs and
//! input gradients of a sample of rows are checked against the reference run on those rows.

use velox_engine::ops::fourier::reference as fourier_ref;
use velox_engine::ops::layernorm::reference as layernorm_ref;
use velox_engine::ops::rmsnorm::reference as rmsnorm_ref;
use velox_engine::rng::Rng;
use velox_engine::{Gpu, Recorder, Result, Tensor};
use velox_models::layers::{reference, Fourier, GeluMlp, Layer, LayerNorm, Linear, Param, RmsNorm, SwiGlu};

use super::{print_header, print_row, time_gpu, Record, SizeSet};

/// A benchmarked layer's sizes, the work of a pass, and its f64 reference (outputs and input
/// gradients of given rows).
struct Info {
    name: &'static str,
    shape: String,
    rows: usize,
    in_width: usize,
    out_width: usize,
    /// Forward and backward work, and the unit of their rate.
    work: (f64, f64, &'static str),
    /// Forward and backward (FLOPs, compulsory bytes): the inputs (parameters included) read
    /// once and the outputs (the backward's parameter gradients included) written once.
    traffic: [(f64, f64); 2],
    /// Inputs are coordinates in [-1, 1] (else standard normal).
    coordinates: bool,
    reference: Reference,
}

/// `(x, dy, rows) -> (y, dx)` in f64.
type Reference = Box<dyn Fn(&[f64], &[f64], usize) -> (Vec<f64>, Vec<f64>)>;

struct Case<L: Layer> {
    layer: L,
    info: Info,
}

/// What the benchmark needs of a case, whatever its layer type.
trait Bench {
    fn info(&self) -> &Info;
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor>;
    /// Records forward then backward; returns dx.
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor>;
}

impl<L: Layer> Bench for Case<L> {
    fn info(&self) -> &Info {
        &self.info
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, cache) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &cache, dy)
    }
}

fn param(gpu: &Gpu, rng: &mut Rng, shape: &[usize], std: f64) -> Result<(Param, Vec<f64>)> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| (rng.normal() * std) as f32).collect();
    Ok((Param::new(gpu, shape, &v)?, v.iter().map(|&x| x as f64).collect()))
}

fn benches(gpu: &Gpu, rng: &mut Rng, small: bool) -> Result<Vec<Box<dyn Bench>>> {
    let (n, d, points) = if small { (256, 64, 16_384) } else { (8192, 512, 1_440_000) };
    let h = 4 * d;
    let std = 1.0 / (d as f64).sqrt();
    let matmul = |flops: f64| (flops, 2.0 * flops, "TFLOP/s");
    // Row layers move each element in and out forward, and about twice that backward.
    let bytes = |elements: usize| (8.0 * elements as f64, 16.0 * elements as f64, "GB/s");
    let mut out: Vec<Box<dyn Bench>> = Vec::new();
    // Values of the activations in and out, in f32 bytes.
    let (nd, f4) = ((n * d) as f64, |v: f64| 4.0 * v);

    let (w, wv) = param(gpu, rng, &[d, d], std)?;
    let (b, bv) = param(gpu, rng, &[d], 0.1)?;
    out.push(Box::new(Case {
        layer: Linear::new(w, Some(b))?,
        info: Info {
            name: "linear (bias)",
            shape: format!("{n}x{d} -> {d}"),
            rows: n,
            in_width: d,
            out_width: d,
            work: matmul(2.0 * (n * d * d) as f64),
            // Backward: dx and dW (a product each) and db; reads x, dy, W, writes dx, dW, db.
            traffic: {
                let (dd, fl) = ((d * d) as f64, 2.0 * (n * d * d) as f64);
                [(fl, f4(2.0 * nd + dd + d as f64)), (2.0 * fl, f4(3.0 * nd + 2.0 * dd + d as f64))]
            },
            coordinates: false,
            reference: Box::new(move |x, dy, r| {
                (
                    reference::linear(x, &wv, Some(&bv), r, d, d),
                    reference::linear_backward(x, &wv, dy, r, d, d).0,
                )
            }),
        },
    }));

    let (g, gv) = param(gpu, rng, &[d], 1.0)?;
    out.push(Box::new(Case {
        layer: RmsNorm::new(g, 1e-6)?,
        info: Info {
            name: "rmsnorm",
            shape: format!("{n}x{d}"),
            rows: n,
            in_width: d,
            out_width: d,
            work: bytes(n * d),
            // A square, a sum, a scale and the gain a value forward, about twice that backward.
            traffic: [(4.0 * nd, f4(2.0 * nd + d as f64)), (8.0 * nd, f4(3.0 * nd + 2.0 * d as f64))],
            coordinates: false,
            reference: Box::new(move |x, dy, _| {
                (rmsnorm_ref::rmsnorm(x, &gv, 1e-6).0, rmsnorm_ref::rmsnorm_backward(x, &gv, 1e-6, dy).0)
            }),
        },
    }));

    let (g, gv) = param(gpu, rng, &[d], 1.0)?;
    let (bb, bbv) = param(gpu, rng, &[d], 0.1)?;
    out.push(Box::new(Case {
        layer: LayerNorm::new(d, Some((g, bb)), 1e-6)?,
        info: Info {
            name: "layernorm (affine)",
            shape: format!("{n}x{d}"),
            rows: n,
            in_width: d,
            out_width: d,
            work: bytes(n * d),
            // A mean, a variance, a normalisation and the affine map a value forward.
            traffic: [(7.0 * nd, f4(2.0 * nd + 2.0 * d as f64)), (12.0 * nd, f4(3.0 * nd + 4.0 * d as f64))],
            coordinates: false,
            reference: Box::new(move |x, dy, _| {
                let y = layernorm_ref::layernorm(x, d, Some((&gv, &bbv)), 1e-6).0;
                (y, layernorm_ref::layernorm_backward(x, d, Some(&gv), 1e-6, dy).0)
            }),
        },
    }));

    let (w1, w1v) = param(gpu, rng, &[d, h], std)?;
    let (w3, w3v) = param(gpu, rng, &[d, h], std)?;
    let (w2, w2v) = param(gpu, rng, &[h, d], 1.0 / (h as f64).sqrt())?;
    out.push(Box::new(Case {
        layer: SwiGlu::new(w1, w3, w2)?,
        info: Info {
            name: "swiglu feed-forward",
            shape: format!("{n}x{d} -> {h} -> {d}"),
            rows: n,
            in_width: d,
            out_width: d,
            work: matmul(2.0 * (n * d * h * 3) as f64),
            // Three products forward, six backward; the weights read (and their gradients
            // written backward) once.
            traffic: {
                let (dh, fl) = ((3 * d * h) as f64, 2.0 * (n * d * h * 3) as f64);
                [(fl, f4(2.0 * nd + dh)), (2.0 * fl, f4(3.0 * nd + 2.0 * dh))]
            },
            coordinates: false,
            reference: Box::new(move |x, dy, r| {
                let y = reference::swiglu_ff(x, &w1v, &w3v, &w2v, r, d, h, d);
                let [dx, ..] = reference::swiglu_ff_backward(x, &w1v, &w3v, &w2v, dy, r, d, h, d);
                (y, dx)
            }),
        },
    }));

    let (w1, w1v) = param(gpu, rng, &[d, h], std)?;
    let (b1, b1v) = param(gpu, rng, &[h], 0.1)?;
    let (w2, w2v) = param(gpu, rng, &[h, d], 1.0 / (h as f64).sqrt())?;
    let (b2, b2v) = param(gpu, rng, &[d], 0.1)?;
    out.push(Box::new(Case {
        layer: GeluMlp::new(w1, b1, w2, b2)?,
        info: Info {
            name: "gelu feed-forward",
            shape: format!("{n}x{d} -> {h} -> {d}"),
            rows: n,
            in_width: d,
            out_width: d,
            work: matmul(2.0 * (n * d * h * 2) as f64),
            traffic: {
                let (dh, fl) = ((2 * d * h + h + d) as f64, 2.0 * (n * d * h * 2) as f64);
                [(fl, f4(2.0 * nd + dh)), (2.0 * fl, f4(3.0 * nd + 2.0 * dh))]
            },
            coordinates: false,
            reference: Box::new(move |x, dy, r| {
                let y = reference::gelu_mlp(x, &w1v, &b1v, &w2v, &b2v, r, d, h, d);
                let [dx, ..] = reference::gelu_mlp_backward(x, &w1v, &b1v, &w2v, dy, r, d, h, d);
                (y, dx)
            }),
        },
    }));

    // docs/models.md: 32 frequencies 2^0 .. 2^12 for xyz, sin and cos, with the input itself. The
    // reference uses the layer's own f32 frequencies, widened.
    let layer = Fourier::log_spaced(gpu, 3, 32, 12.0, true)?;
    let freqs: Vec<f64> = layer.freqs.iter().map(|&w| w as f64).collect();
    let width = layer.out_width();
    out.push(Box::new(Case {
        layer,
        info: Info {
            name: "fourier embedding",
            shape: format!("{points}x3 -> {width}"),
            rows: points,
            in_width: 3,
            out_width: width,
            // Reads 3 and writes `width` floats per point forward; twice that backward.
            work: (4.0 * (points * (3 + width)) as f64, 8.0 * (points * (3 + width)) as f64, "GB/s"),
            // A product and a sine or cosine an output forward; backward reads dy and x and
            // writes dx.
            traffic: {
                let (pts, w) = (points as f64, width as f64);
                [(2.0 * pts * w, f4(pts * (3.0 + w))), (4.0 * pts * w, f4(pts * (6.0 + w)))]
            },
            coordinates: true,
            reference: Box::new(move |x, dy, _| {
                (
                    fourier_ref::fourier(x, 3, &freqs, true),
                    fourier_ref::fourier_backward(x, 3, &freqs, true, dy),
                )
            }),
        },
    }));
    Ok(out)
}

pub fn run(gpu: &Gpu, sizes: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let small = sizes.small();
    let mut rng = Rng::new(13);
    let c = gpu.caps();
    let device = c.name.clone();
    let peaks = c.known_peaks();
    println!("device: {device} ({}); {repeats} timed repeats per case, median shown", c.kind);
    print_header();
    let mut records = Vec::new();
    for b in benches(gpu, &mut rng, small)? {
        let info = b.info();
        let (rows, wi, wo) = (info.rows, info.in_width, info.out_width);
        let x =
            if info.coordinates { rng.uniform_vec(rows * wi, -1.0, 1.0) } else { rng.normal_vec(rows * wi) };
        let dy = rng.normal_vec(rows * wo);
        let tx = Tensor::from_slice(gpu, &[rows, wi], &x)?;
        let tdy = Tensor::from_slice(gpu, &[rows, wo], &dy)?;
        let mut y = None;
        let (fwd_ms, fwd_min, timed) = time_gpu(gpu, repeats, |rec| {
            y = Some(b.forward(rec, &tx)?);
            Ok(())
        })?;
        let mut dx = None;
        let (all_ms, all_min, _) = time_gpu(gpu, repeats, |rec| {
            dx = Some(b.forward_backward(rec, &tx, &tdy)?);
            Ok(())
        })?;
        let (y, dx): (Vec<f32>, Vec<f32>) = (y.unwrap().read()?, dx.unwrap().read()?);
        // Reference on the first 32 rows and 32 rows from the middle.
        let sample: Vec<usize> = (0..32.min(rows)).chain((rows / 2..rows).take(32)).collect();
        let pick = |t: &[f32], w: usize| -> Vec<f32> {
            sample.iter().flat_map(|&r| t[r * w..(r + 1) * w].iter().copied()).collect()
        };
        let x64: Vec<f64> = pick(&x, wi).iter().map(|&v| v as f64).collect();
        let dy64: Vec<f64> = pick(&dy, wo).iter().map(|&v| v as f64).collect();
        let (y_ref, dx_ref) = (info.reference)(&x64, &dy64, sample.len());
        let (y_got, dx_got) = (pick(&y, wo), pick(&dx, wi));
        let (fwd_work, bwd_work, unit) = info.work;
        let scale = if unit == "TFLOP/s" { 1e12 } else { 1e9 };
        let peak = |t: f64| peaks.map(|p| if unit == "TFLOP/s" { t / p.1 } else { t / p.2 });
        let [(ff, fb), (bf, bb)] = info.traffic;
        for (pass, ms, min, work, got, want, (flops, bytes)) in [
            ("fwd", fwd_ms, fwd_min, fwd_work, &y_got, &y_ref, (ff, fb)),
            ("fwd+bwd", all_ms, all_min, fwd_work + bwd_work, &dx_got, &dx_ref, (ff + bf, fb + bb)),
        ] {
            let t = work / (ms * 1e-3) / scale;
            let what = if pass == "fwd" { "y" } else { "dx" };
            let over = format!("{what} of {} on {} sampled rows", info.name, sample.len());
            let name = format!("{} {pass}", info.name);
            let r =
                Record::timed(name, info.shape.clone(), "f32", &device, (ms, min, timed), repeats, t, unit)
                    .peak(peak(t))
                    .against(got, want, over)
                    .work(flops, bytes, super::Roof::of(c, false));
            print_row(&r);
            records.push(r);
        }
    }
    Ok(records)
}
