//! numpy arrays in and out. An array coming in must have the dtype and shape asked for
//! (`float32` for every value array; a float64 array is refused, never converted, so that a
//! result never depends on a silent cast); its values are read in C order whatever its
//! strides, and checked finite. An error names the argument, and the array's dtype and shape.

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::invalid;

/// `[a, b, ?]` for an expected shape (`None`: any size).
fn shape_text(shape: &[Option<usize>]) -> String {
    let dims: Vec<String> = shape.iter().map(|d| d.map_or("N".to_string(), |n| n.to_string())).collect();
    format!("[{}]", dims.join(", "))
}

/// The values and shape of `obj`, a float32 array of `shape` (`None`: any size there).
pub fn f32_array(
    obj: &Bound<'_, PyAny>,
    name: &str,
    shape: &[Option<usize>],
) -> PyResult<(Vec<f32>, Vec<usize>)> {
    let untyped = obj.cast::<PyUntypedArray>().map_err(|_| {
        let kind = obj.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into());
        invalid(format!("{name} must be a numpy float32 array of shape {}, got a {kind}", shape_text(shape)))
    })?;
    let got: Vec<usize> = untyped.shape().to_vec();
    let dtype = untyped.dtype().str().map(|s| s.to_string()).unwrap_or_else(|_| "?".into());
    let fits = got.len() == shape.len() && got.iter().zip(shape).all(|(&g, s)| s.is_none_or(|s| s == g));
    let typed = obj.cast::<PyArrayDyn<f32>>().ok().filter(|_| fits).ok_or_else(|| {
        invalid(format!(
            "{name} must be a float32 array of shape {}, got {dtype} of shape {got:?}",
            shape_text(shape)
        ))
    })?;
    let values: Vec<f32> = typed.readonly().as_array().iter().copied().collect();
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        let at = index_of(i, &got);
        return Err(invalid(format!("{name}{at:?} is {}: every value must be finite", values[i])));
    }
    Ok((values, got))
}

/// The index in an array of `shape` of its C-order element `i`.
fn index_of(mut i: usize, shape: &[usize]) -> Vec<usize> {
    let mut at = vec![0; shape.len()];
    for (k, &n) in shape.iter().enumerate().rev() {
        at[k] = i % n.max(1);
        i /= n.max(1);
    }
    at
}

/// A float32 array of `shape` holding `values` (C order), without a copy.
pub fn to_array<'py>(py: Python<'py>, values: Vec<f32>, shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    debug_assert_eq!(values.len(), shape.iter().product::<usize>());
    Ok(PyArray1::from_vec(py, values).reshape(shape.to_vec())?.into_any())
}

/// The values and shape of `obj`, a bool array of `shape` (`None`: any size there).
pub fn bool_array(
    obj: &Bound<'_, PyAny>,
    name: &str,
    shape: &[Option<usize>],
) -> PyResult<(Vec<bool>, Vec<usize>)> {
    let (dtype, got) = match obj.cast::<PyUntypedArray>() {
        Ok(a) => (a.dtype().str().map(|s| s.to_string()).unwrap_or_else(|_| "?".into()), a.shape().to_vec()),
        Err(_) => {
            return Err(invalid(format!("{name} must be a numpy bool array of shape {}", shape_text(shape))))
        }
    };
    let fits = got.len() == shape.len() && got.iter().zip(shape).all(|(&g, s)| s.is_none_or(|s| s == g));
    let typed = obj.cast::<PyArrayDyn<bool>>().ok().filter(|_| fits).ok_or_else(|| {
        invalid(format!(
            "{name} must be a bool array of shape {}, got {dtype} of shape {got:?}",
            shape_text(shape)
        ))
    })?;
    Ok((typed.readonly().as_array().iter().copied().collect(), got))
}
