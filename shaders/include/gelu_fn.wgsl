// Exact (erf) GELU and its derivative, shared by unary.wgsl and voxel_head.wgsl.

// erfc(z) for z >= 0, Abramowitz & Stegun 7.1.26 (absolute error < 1.5e-7).
fn erfc_pos(z: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))));
    return poly * exp(-z * z);
}

fn gelu(v: f32) -> f32 {
    // 0.5 v (1 + erf(v / sqrt 2)) = 0.5 v erfc(-v / sqrt 2)
    let c = erfc_pos(abs(v) * 0.70710678118654752);
    if (v >= 0.0) {
        return 0.5 * v * (2.0 - c);
    }
    return 0.5 * v * c;
}

// gelu'(v) = Phi(v) + v phi(v), Phi(v) = 0.5 erfc(-v / sqrt 2), phi the normal density.
fn gelu_grad(v: f32) -> f32 {
    let c = erfc_pos(abs(v) * 0.70710678118654752);
    var cdf = 0.5 * c;
    if (v >= 0.0) {
        cdf = 1.0 - 0.5 * c;
    }
    // exp(-v^2 / 2) underflows to 0 for |v| > 14: the density term vanishes cleanly.
    let pdf = 0.39894228040143268 * exp(-0.5 * v * v);
    return cdf + v * pdf;
}
