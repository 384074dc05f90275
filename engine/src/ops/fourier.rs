//! Fourier features and their backward. Kernel: `shaders/fourier.wgsl`.
//!
//! For `x [rows, c]` and frequencies `w [F]` each output row is, in this order:
//! `x_0 .. x_{c-1}` (only with `include_input`), then `sin(pi w_f x_i)` at `i * F + f`, then
//! `cos(pi w_f x_i)` at `c * F + i * F + f`: width `c * 2F (+ c)`.
//!
//! Tests: the harness's `fourier` row (`engine/tests/ops/cases.rs`: forward and backward, the
//! reference against finite differences against the f64 reference at awkward shapes); the layer's
//! `tests/models/layers.rs`.

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{FOURIER_BACKWARD, FOURIER_FORWARD};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::kernels::params::FourierParams as Params;
use crate::{fit_u32, Limit};

/// Output width for `channels` inputs and `freqs` frequencies.
pub fn fourier_width(channels: usize, freqs: usize, include_input: bool) -> usize {
    channels * 2 * freqs + if include_input { channels } else { 0 }
}

fn params(x: &Tensor, freq: &Tensor, include_input: bool) -> Result<(Params, usize)> {
    if x.dtype() != DType::F32 || x.shape().len() != 2 || freq.dtype() != DType::F32 {
        return Err(Error::Shape(format!(
            "fourier: needs f32 x [rows, c] and f32 frequencies, got {x:?}, {freq:?}"
        )));
    }
    let (rows, c) = (x.shape()[0], x.shape()[1]);
    let width = fourier_width(c, freq.numel(), include_input);
    let fit = |v: usize| fit_u32(v, || format!("fourier of {x:?}"));
    fit(rows
        .checked_mul(width)
        .ok_or_else(|| Error::too_large(Limit::Index, format!("fourier of {x:?}")))?)?;
    let p = Params {
        rows: fit(rows)?,
        channels: fit(c)?,
        freqs: fit(freq.numel())?,
        include_input: include_input as u32,
    };
    Ok((p, width))
}

/// Fourier features of `x [rows, c]` at frequencies `freq [F]`: `[rows, fourier_width]`.
pub fn fourier(rec: &mut Recorder, x: &Tensor, freq: &Tensor, include_input: bool) -> Result<Tensor> {
    let (p, width) = params(x, freq, include_input)?;
    let y = Tensor::empty(x.gpu(), &[x.shape()[0], width], DType::F32)?;
    rec.dispatch_elements(
        FOURIER_FORWARD,
        y.numel() as u64,
        args::FourierForwardArgs { x, freq, y: &y },
        &p,
    )?;
    Ok(y)
}

/// `dx [rows, c]` from `dy [rows, fourier_width]`.
pub fn fourier_backward(
    rec: &mut Recorder,
    x: &Tensor,
    freq: &Tensor,
    include_input: bool,
    dy: &Tensor,
) -> Result<Tensor> {
    let (p, width) = params(x, freq, include_input)?;
    if dy.dtype() != DType::F32 || dy.shape() != [x.shape()[0], width] {
        return Err(Error::Shape(format!(
            "fourier backward: dy must be f32 [{}, {width}], got {dy:?}",
            x.shape()[0]
        )));
    }
    let dx = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    rec.dispatch_elements(
        FOURIER_BACKWARD,
        x.numel() as u64,
        args::FourierBackwardArgs { x, freq, dy, dx: &dx },
        &p,
    )?;
    Ok(dx)
}

/// Plain f64 loops, in the layout documented above.
pub mod reference {
    use std::f64::consts::PI;

    pub fn fourier(x: &[f64], channels: usize, freq: &[f64], include_input: bool) -> Vec<f64> {
        let f = freq.len();
        let mut y = Vec::new();
        for row in x.chunks(channels) {
            if include_input {
                y.extend_from_slice(row);
            }
            for v in row {
                y.extend(freq.iter().map(|w| (PI * w * v).sin()));
            }
            for v in row {
                y.extend(freq.iter().map(|w| (PI * w * v).cos()));
            }
        }
        debug_assert_eq!(
            y.len(),
            x.len() / channels.max(1) * super::fourier_width(channels, f, include_input)
        );
        y
    }

    pub fn fourier_backward(
        x: &[f64],
        channels: usize,
        freq: &[f64],
        include_input: bool,
        dy: &[f64],
    ) -> Vec<f64> {
        let f = freq.len();
        let width = super::fourier_width(channels, f, include_input);
        let mut dx = Vec::with_capacity(x.len());
        for (row, g) in x.chunks(channels).zip(dy.chunks(width)) {
            let (g_in, g) = g.split_at(if include_input { channels } else { 0 });
            let (g_sin, g_cos) = g.split_at(channels * f);
            for (i, v) in row.iter().enumerate() {
                let mut d = if include_input { g_in[i] } else { 0.0 };
                for (k, w) in freq.iter().enumerate() {
                    let p = PI * w * v;
                    d += PI * w * (p.cos() * g_sin[i * f + k] - p.sin() * g_cos[i * f + k]);
                }
                dx.push(d);
            }
        }
        dx
    }
}
