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
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Recorder, Result, Tensor};
use velox_models::layers::{reference, Fourier, GeluMlp, LayerNorm, Linear, Param, RmsNorm, SwiGlu};

use super::{print_header, print_row, time_gpu, Record};

/// What one layer offers the benchmark: a forward, a backward, and the f64 reference of both
/// on given rows.
trait Bench {
    fn name(&self) -> String;
    fn shape(&self) -> String;
    /// (forward flops or bytes, backward flops or bytes, unit).
    fn work(&self) -> (f64, f64, &'static str);
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor>;
    /// Records forward then backward; returns dx.
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor>;
    /// Reference (y, dx) of the given input rows.
    fn reference(&self, x: &[f64], dy: &[f64], rows: usize) -> (Vec<f64>, Vec<f64>);
    fn in_width(&self) -> usize;
    fn out_width(&self) -> usize;
    /// Rows of the benchmark's input.
    fn rows(&self) -> usize;
    /// An input of `rows` rows: standard normal unless the layer wants coordinates.
    fn input(&self, rng: &mut Rng) -> Vec<f32> {
        rng.normal_vec(self.rows() * self.in_width())
    }
}

fn param(gpu: &Gpu, rng: &mut Rng, shape: &[usize], std: f64) -> Result<(Param, Vec<f64>)> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| (rng.normal() * std) as f32).collect();
    Ok((Param::new(gpu, shape, &v)?, v.iter().map(|&x| x as f64).collect()))
}

struct LinearBench {
    layer: Linear,
    w: Vec<f64>,
    b: Vec<f64>,
    n: usize,
}

impl Bench for LinearBench {
    fn name(&self) -> String {
        "linear (bias)".into()
    }
    fn shape(&self) -> String {
        format!("{}x{} -> {}", self.n, self.in_width(), self.out_width())
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let f = 2.0 * (self.n * self.in_width() * self.out_width()) as f64;
        (f, 2.0 * f, "TFLOP/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], rows: usize) -> (Vec<f64>, Vec<f64>) {
        let (i, o) = (self.in_width(), self.out_width());
        let y = reference::linear(x, &self.w, Some(&self.b), rows, i, o);
        (y, reference::linear_backward(x, &self.w, dy, rows, i, o).0)
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn in_width(&self) -> usize {
        self.layer.in_features
    }
    fn out_width(&self) -> usize {
        self.layer.out_features
    }
}

struct RmsBench {
    layer: RmsNorm,
    w: Vec<f64>,
    n: usize,
}

impl Bench for RmsBench {
    fn name(&self) -> String {
        "rmsnorm".into()
    }
    fn shape(&self) -> String {
        format!("{}x{}", self.n, self.w.len())
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let e = (self.n * self.w.len()) as f64 * 4.0;
        (2.0 * e, 4.0 * e, "GB/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], _rows: usize) -> (Vec<f64>, Vec<f64>) {
        let (y, _) = rmsnorm_ref::rmsnorm(x, &self.w, 1e-6);
        (y, rmsnorm_ref::rmsnorm_backward(x, &self.w, 1e-6, dy).0)
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn in_width(&self) -> usize {
        self.w.len()
    }
    fn out_width(&self) -> usize {
        self.w.len()
    }
}

struct LayerNormBench {
    layer: LayerNorm,
    w: Vec<f64>,
    b: Vec<f64>,
    n: usize,
}

impl Bench for LayerNormBench {
    fn name(&self) -> String {
        "layernorm (affine)".into()
    }
    fn shape(&self) -> String {
        format!("{}x{}", self.n, self.w.len())
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let e = (self.n * self.w.len()) as f64 * 4.0;
        (2.0 * e, 4.0 * e, "GB/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], _rows: usize) -> (Vec<f64>, Vec<f64>) {
        let width = self.w.len();
        let (y, _, _) = layernorm_ref::layernorm(x, width, Some((&self.w, &self.b)), 1e-6);
        (y, layernorm_ref::layernorm_backward(x, width, Some(&self.w), 1e-6, dy).0)
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn in_width(&self) -> usize {
        self.w.len()
    }
    fn out_width(&self) -> usize {
        self.w.len()
    }
}

struct SwiGluBench {
    layer: SwiGlu,
    w: [Vec<f64>; 3],
    n: usize,
    d: usize,
    h: usize,
}

impl Bench for SwiGluBench {
    fn name(&self) -> String {
        "swiglu feed-forward".into()
    }
    fn shape(&self) -> String {
        format!("{}x{} -> {} -> {}", self.n, self.d, self.h, self.d)
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let f = 2.0 * (self.n * self.d * self.h * 3) as f64;
        (f, 2.0 * f, "TFLOP/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], rows: usize) -> (Vec<f64>, Vec<f64>) {
        let [w1, w3, w2] = &self.w;
        let y = reference::swiglu_ff(x, w1, w3, w2, rows, self.d, self.h, self.d);
        let [dx, ..] = reference::swiglu_ff_backward(x, w1, w3, w2, dy, rows, self.d, self.h, self.d);
        (y, dx)
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn in_width(&self) -> usize {
        self.d
    }
    fn out_width(&self) -> usize {
        self.d
    }
}

struct GeluBench {
    layer: GeluMlp,
    w: [Vec<f64>; 4],
    n: usize,
    d: usize,
    h: usize,
}

impl Bench for GeluBench {
    fn name(&self) -> String {
        "gelu feed-forward".into()
    }
    fn shape(&self) -> String {
        format!("{}x{} -> {} -> {}", self.n, self.d, self.h, self.d)
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let f = 2.0 * (self.n * self.d * self.h * 2) as f64;
        (f, 2.0 * f, "TFLOP/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], rows: usize) -> (Vec<f64>, Vec<f64>) {
        let [w1, b1, w2, b2] = &self.w;
        let y = reference::gelu_mlp(x, w1, b1, w2, b2, rows, self.d, self.h, self.d);
        let [dx, ..] = reference::gelu_mlp_backward(x, w1, b1, w2, dy, rows, self.d, self.h, self.d);
        (y, dx)
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn in_width(&self) -> usize {
        self.d
    }
    fn out_width(&self) -> usize {
        self.d
    }
}

struct FourierBench {
    layer: Fourier,
    /// The layer's f32 frequencies, widened: the reference uses the same ones.
    freqs: Vec<f64>,
    n: usize,
}

impl Bench for FourierBench {
    fn name(&self) -> String {
        "fourier embedding".into()
    }
    fn shape(&self) -> String {
        format!("{}x3 -> {}", self.n, self.layer.out_width())
    }
    fn work(&self) -> (f64, f64, &'static str) {
        let b = (self.n * (3 + self.layer.out_width())) as f64 * 4.0;
        (b, 2.0 * b, "GB/s")
    }
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.layer.forward(rec, x)?.0)
    }
    fn forward_backward(&self, rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        let (_, c) = self.layer.forward(rec, x)?;
        self.layer.backward(rec, &c, dy)
    }
    fn reference(&self, x: &[f64], dy: &[f64], _rows: usize) -> (Vec<f64>, Vec<f64>) {
        let y = fourier_ref::fourier(x, 3, &self.freqs, true);
        (y, fourier_ref::fourier_backward(x, 3, &self.freqs, true, dy))
    }
    fn rows(&self) -> usize {
        self.n
    }
    fn input(&self, rng: &mut Rng) -> Vec<f32> {
        rng.uniform_vec(self.n * 3, -1.0, 1.0)
    }
    fn in_width(&self) -> usize {
        3
    }
    fn out_width(&self) -> usize {
        self.layer.out_width()
    }
}

fn benches(gpu: &Gpu, rng: &mut Rng, small: bool) -> Result<Vec<Box<dyn Bench>>> {
    let (n, d, points) = if small { (256, 64, 16_384) } else { (8192, 512, 1_440_000) };
    let h = 4 * d;
    let std = 1.0 / (d as f64).sqrt();
    let (w, wv) = param(gpu, rng, &[d, d], std)?;
    let (b, bv) = param(gpu, rng, &[d], 0.1)?;
    let linear = LinearBench { layer: Linear::new(w, Some(b))?, w: wv, b: bv, n };
    let (g, gv) = param(gpu, rng, &[d], 1.0)?;
    let rms = RmsBench { layer: RmsNorm::new(g, 1e-6)?, w: gv, n };
    let (g, gv) = param(gpu, rng, &[d], 1.0)?;
    let (bb, bbv) = param(gpu, rng, &[d], 0.1)?;
    let ln = LayerNormBench { layer: LayerNorm::new(d, Some((g, bb)), 1e-6)?, w: gv, b: bbv, n };
    let (w1, w1v) = param(gpu, rng, &[d, h], std)?;
    let (w3, w3v) = param(gpu, rng, &[d, h], std)?;
    let (w2, w2v) = param(gpu, rng, &[h, d], 1.0 / (h as f64).sqrt())?;
    let swiglu = SwiGluBench { layer: SwiGlu::new(w1, w3, w2)?, w: [w1v, w3v, w2v], n, d, h };
    let (w1, w1v) = param(gpu, rng, &[d, h], std)?;
    let (b1, b1v) = param(gpu, rng, &[h], 0.1)?;
    let (w2, w2v) = param(gpu, rng, &[h, d], 1.0 / (h as f64).sqrt())?;
    let (b2, b2v) = param(gpu, rng, &[d], 0.1)?;
    let gelu = GeluBench { layer: GeluMlp::new(w1, b1, w2, b2)?, w: [w1v, b1v, w2v, b2v], n, d, h };
    // MODELS.md: 32 frequencies 2^0 .. 2^12 for xyz, sin and cos, with the input itself.
    let layer = Fourier::log_spaced(gpu, 3, 32, 12.0, true)?;
    let freqs = layer.freqs.iter().map(|&w| w as f64).collect();
    let fourier = FourierBench { layer, freqs, n: points };
    Ok(vec![
        Box::new(linear),
        Box::new(rms),
        Box::new(ln),
        Box::new(swiglu),
        Box::new(gelu),
        Box::new(fourier),
    ])
}

pub fn run(gpu: &Gpu, quick: bool, repeats: u32) -> Result<Vec<Record>> {
    let small = quick || gpu.caps().kind == "CPU";
    let mut rng = Rng::new(13);
    let c = gpu.caps();
    let device = c.name.clone();
    let peaks = c.known_peaks();
    println!("device: {device} ({}); {repeats} timed repeats per case, median shown", c.kind);
    print_header();
    let mut records = Vec::new();
    for b in benches(gpu, &mut rng, small)? {
        let (rows, wi, wo) = (b.rows(), b.in_width(), b.out_width());
        let x = b.input(&mut rng);
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
        let (y_ref, dx_ref) = b.reference(&x64, &dy64, sample.len());
        let (y_got, dx_got) = (pick(&y, wo), pick(&dx, wi));
        let (fwd_work, bwd_work, unit) = b.work();
        let scale = if unit == "TFLOP/s" { 1e12 } else { 1e9 };
        let peak = |t: f64| peaks.map(|p| if unit == "TFLOP/s" { t / p.1 } else { t / p.2 });
        for (pass, ms, min, work, got, want) in [
            ("fwd", fwd_ms, fwd_min, fwd_work, &y_got, &y_ref),
            ("fwd+bwd", all_ms, all_min, fwd_work + bwd_work, &dx_got, &dx_ref),
        ] {
            let t = work / (ms * 1e-3) / scale;
            let r = Record {
                name: format!("{} {pass}", b.name()),
                shape: b.shape(),
                precision: "f32".into(),
                device: device.clone(),
                median_ms: ms,
                min_ms: min,
                repeats,
                throughput: t,
                throughput_unit: unit.into(),
                peak_fraction: peak(t),
                nmse: nmse(got, want),
                max_abs_err: max_abs_err(got, want),
                error_over: format!(
                    "{} of {} on {} sampled rows",
                    if pass == "fwd" { "y" } else { "dx" },
                    b.name(),
                    sample.len()
                ),
                gpu_timed: timed,
            };
            print_row(&r);
            records.push(r);
        }
    }
    Ok(records)
}
