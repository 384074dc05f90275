//! Fourier embedding of coordinates (xyz, tau, flow time). Kernel: `shaders/fourier.wgsl`.
//!
//! `x [N, c] -> [N, c * 2F (+ c)]`; each output row is laid out as
//! `[x_0 .. x_{c-1}]` (only with `include_input`), then `sin(pi w_f x_i)` at `i * F + f`, then
//! `cos(pi w_f x_i)` at `c * F + i * F + f`. docs/models.md uses 32 frequencies from 2^0 to 2^12
//! for xyz ([`Fourier::log_spaced`]`(3, 32, 12.0, ..)`) and 8 for tau.
//!
//! Tests: `tests/models/layers.rs` and the engine's harness row of the Fourier features.

use velox_engine::ops::fourier::{fourier, fourier_backward, fourier_width};
use velox_engine::{Gpu, Recorder, Result, Tensor};

pub struct Fourier {
    pub channels: usize,
    pub include_input: bool,
    /// The frequencies `w_f`, on the host and on the device.
    pub freqs: Vec<f32>,
    freq: Tensor,
}

#[derive(Clone, Debug)]
pub struct FourierCache {
    x: Tensor,
}

impl Fourier {
    pub fn new(gpu: &Gpu, channels: usize, freqs: Vec<f32>, include_input: bool) -> Result<Fourier> {
        let freq = Tensor::from_slice(gpu, &[freqs.len()], &freqs)?;
        Ok(Fourier { channels, include_input, freqs, freq })
    }

    /// Octave frequencies `w_f = 2^f`, `f in 0..n`.
    pub fn octaves(gpu: &Gpu, channels: usize, n: usize, include_input: bool) -> Result<Fourier> {
        Fourier::new(gpu, channels, (0..n).map(|f| (2.0f32).powi(f as i32)).collect(), include_input)
    }

    /// `n` frequencies spaced evenly in log2 from `2^0` to `2^max_octave`.
    pub fn log_spaced(
        gpu: &Gpu,
        channels: usize,
        n: usize,
        max_octave: f64,
        include_input: bool,
    ) -> Result<Fourier> {
        let step = if n > 1 { max_octave / (n - 1) as f64 } else { 0.0 };
        Fourier::new(gpu, channels, (0..n).map(|f| (step * f as f64).exp2() as f32).collect(), include_input)
    }

    pub fn out_width(&self) -> usize {
        fourier_width(self.channels, self.freqs.len(), self.include_input)
    }

    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, FourierCache)> {
        let y = fourier(rec, x, &self.freq, self.include_input)?;
        Ok((y, FourierCache { x: x.clone() }))
    }

    pub fn backward(&self, rec: &mut Recorder, cache: &FourierCache, dy: &Tensor) -> Result<Tensor> {
        fourier_backward(rec, &cache.x, &self.freq, self.include_input, dy)
    }
}
