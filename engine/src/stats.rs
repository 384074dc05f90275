//! Error measures between a computed result and its f64 reference.

/// Normalised mean square error: sum (x - r)^2 / sum r^2 (or the plain mean square error when
/// the reference is all zeros). NaN or Inf anywhere in `x` where `r` is finite gives +Inf, so
/// no NaN can pass a bound.
pub fn nmse<T: Copy + Into<f64>>(x: &[T], reference: &[f64]) -> f64 {
    assert_eq!(x.len(), reference.len(), "nmse: lengths differ");
    if x.is_empty() {
        return 0.0;
    }
    let mut err = 0.0;
    let mut norm = 0.0;
    for (&a, &r) in x.iter().zip(reference) {
        let a: f64 = a.into();
        if !a.is_finite() && r.is_finite() {
            return f64::INFINITY;
        }
        err += (a - r) * (a - r);
        norm += r * r;
    }
    if norm > 0.0 {
        err / norm
    } else {
        err / x.len() as f64
    }
}

/// Largest absolute difference (+Inf if any value is not finite where the reference is).
pub fn max_abs_err<T: Copy + Into<f64>>(x: &[T], reference: &[f64]) -> f64 {
    assert_eq!(x.len(), reference.len(), "max_abs_err: lengths differ");
    x.iter().zip(reference).fold(0.0, |m, (&a, &r)| {
        let a: f64 = a.into();
        if !a.is_finite() && r.is_finite() {
            f64::INFINITY
        } else {
            m.max((a - r).abs())
        }
    })
}
