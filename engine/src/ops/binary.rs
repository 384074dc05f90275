//! Elementwise binary ops with numpy-style broadcasting. Kernel: `shaders/binary.wgsl`.
//!
//! Tests: the harness's `binary` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (broadcasts, bad shapes).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::BINARY_MAIN;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The ops, each one of the op codes `BINARY_OP_*` of `shaders/binary.wgsl` (exported by the
/// build; checked both ways by the harness).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Binary {
    Add,
    Sub,
    Mul,
    Div,
    Max,
    Min,
}

impl Binary {
    pub const ALL: &[Binary] =
        &[Binary::Add, Binary::Sub, Binary::Mul, Binary::Div, Binary::Max, Binary::Min];

    /// The shader's op code.
    pub fn code(self) -> u32 {
        use crate::kernels as k;
        match self {
            Binary::Add => k::BINARY_OP_ADD,
            Binary::Sub => k::BINARY_OP_SUB,
            Binary::Mul => k::BINARY_OP_MUL,
            Binary::Div => k::BINARY_OP_DIV,
            Binary::Max => k::BINARY_OP_MAX,
            Binary::Min => k::BINARY_OP_MIN,
        }
    }
}

use crate::kernels::params::BinaryParams as Params;

/// The broadcast output shape of `a` and `b` (right-aligned, size-1 dims stretch).
pub fn broadcast_shape(a: &[usize], b: &[usize]) -> Result<Vec<usize>> {
    let rank = a.len().max(b.len());
    let dim = |s: &[usize], i: usize| {
        if i + s.len() >= rank {
            s[i + s.len() - rank]
        } else {
            1
        }
    };
    (0..rank)
        .map(|i| match (dim(a, i), dim(b, i)) {
            (x, y) if x == y => Ok(x),
            (1, y) => Ok(y),
            (x, 1) => Ok(x),
            _ => Err(Error::Shape(format!("shapes {a:?} and {b:?} do not broadcast"))),
        })
        .collect()
}

/// Strides of `s` read as `out` (right-aligned; stride 0 where `s` is broadcast).
fn broadcast_strides(s: &[usize], out: &[usize]) -> Vec<usize> {
    let rank = out.len();
    let mut strides = vec![0; rank];
    let mut acc = 1;
    for i in (0..rank).rev() {
        if i + s.len() >= rank {
            let d = s[i + s.len() - rank];
            strides[i] = if d == 1 { 0 } else { acc };
            acc *= d;
        }
    }
    strides
}

/// Merges adjacent dimensions that both operands walk contiguously, so that any broadcast
/// that fits the kernel's four dimensions does. Returns (shape, a strides, b strides).
fn collapse(out: &[usize], sa: &[usize], sb: &[usize]) -> (Vec<usize>, Vec<usize>, Vec<usize>) {
    let mut shape: Vec<usize> = Vec::new();
    let mut a: Vec<usize> = Vec::new();
    let mut b: Vec<usize> = Vec::new();
    for i in 0..out.len() {
        if out[i] == 1 {
            continue;
        }
        if let Some(&last) = shape.last() {
            let k = shape.len() - 1;
            // dims k and i merge when stride[k] == stride[i] * out[i] for both operands
            if a[k] == sa[i] * out[i] && b[k] == sb[i] * out[i] {
                shape[k] = last * out[i];
                a[k] = sa[i];
                b[k] = sb[i];
                continue;
            }
        }
        shape.push(out[i]);
        a.push(sa[i]);
        b.push(sb[i]);
    }
    (shape, a, b)
}

/// out = op(a, b) with broadcasting, as a new tensor.
pub fn binary(rec: &mut Recorder, a: &Tensor, b: &Tensor, op: Binary) -> Result<Tensor> {
    let shape = broadcast_shape(a.shape(), b.shape())?;
    let out = Tensor::empty(a.gpu(), &shape, DType::F32)?;
    binary_into(rec, a, b, &out, op)?;
    Ok(out)
}

/// out = op(a, b) into `out`, whose shape must be the broadcast shape (it may alias `a`).
pub fn binary_into(rec: &mut Recorder, a: &Tensor, b: &Tensor, out: &Tensor, op: Binary) -> Result<()> {
    if [a, b, out].iter().any(|t| t.dtype() != DType::F32) {
        return Err(Error::Shape(format!("{op:?} needs f32 tensors: {a:?}, {b:?} -> {out:?}")));
    }
    let shape = broadcast_shape(a.shape(), b.shape())?;
    if shape != out.shape() {
        return Err(Error::Shape(format!("{op:?}: {a:?} and {b:?} broadcast to {shape:?}, not {out:?}")));
    }
    let n = fit_u32(out.numel(), || format!("{op:?} on {out:?}"))?;
    if n == 0 {
        return Ok(());
    }
    let (dims, sa, sb) =
        collapse(&shape, &broadcast_strides(a.shape(), &shape), &broadcast_strides(b.shape(), &shape));
    if dims.len() > 4 {
        return Err(Error::Shape(format!(
            "{op:?}: broadcasting {:?} with {:?} needs {} dimensions after merging, the kernel takes 4",
            a.shape(),
            b.shape(),
            dims.len()
        )));
    }
    let pad = 4 - dims.len();
    let mut p =
        Params { shape: [1; 4], a_strides: [0; 4], b_strides: [0; 4], n, op: op.code(), _pad0: [0; 2] };
    for i in 0..dims.len() {
        p.shape[pad + i] = dims[i] as u32;
        p.a_strides[pad + i] = sa[i] as u32;
        p.b_strides[pad + i] = sb[i] as u32;
    }
    rec.dispatch_elements(BINARY_MAIN, n as u64, args::BinaryMainArgs { a, b, out }, &p)
}

pub mod reference {
    use super::{broadcast_shape, broadcast_strides, Binary};

    pub fn apply(op: Binary, x: f64, y: f64) -> f64 {
        match op {
            Binary::Add => x + y,
            Binary::Sub => x - y,
            Binary::Mul => x * y,
            Binary::Div => x / y,
            Binary::Max => x.max(y),
            Binary::Min => x.min(y),
        }
    }

    pub fn binary(a: &[f32], sa: &[usize], b: &[f32], sb: &[usize], op: Binary) -> (Vec<usize>, Vec<f64>) {
        let shape = broadcast_shape(sa, sb).unwrap();
        let (ta, tb) = (broadcast_strides(sa, &shape), broadcast_strides(sb, &shape));
        let n: usize = shape.iter().product();
        let mut out = Vec::with_capacity(n);
        for i in 0..n {
            let (mut rem, mut ia, mut ib) = (i, 0, 0);
            for d in (0..shape.len()).rev() {
                let c = rem % shape[d];
                rem /= shape[d];
                ia += c * ta[d];
                ib += c * tb[d];
            }
            out.push(apply(op, a[ia] as f64, b[ib] as f64));
        }
        (shape, out)
    }
}
