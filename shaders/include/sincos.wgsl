// sin and cos of f32 arguments to about 1 ulp on every device. Vulkan asks of the builtin sin and
// cos only an absolute error of 2^-11 inside [-pi, pi] (and nothing outside), and
// implementations differ by orders of magnitude (SwiftShader's reaches 3e-4); these give the
// same answer everywhere up to rounding.
//
// The argument is reduced to r in [-pi/4, pi/4] and a quadrant n: sin and cos of r come from
// their Taylor series to x^9 and x^10 (the first term left out is below 2e-9 there), and the
// quadrant rotates them. `sincos(v)` reduces radians by Cody and Waite's method, with pi/2 split
// into three parts (12, 12 and 24 bits) so that n times each of the first two is exact: within 1e-7
// of the true values for |v| up to 1e4, the reach the tests measure. `sincospi(q)` takes
// half-turns (sin(pi q), cos(pi q)) and reduces exactly: q modulo 2, then to a quarter turn.

const SC_PI: f32 = 3.14159265358979;
const SC_TWO_OVER_PI: f32 = 0.636619772367581;
const SC_PIO2_1: f32 = 1.5703125;
const SC_PIO2_2: f32 = 4.837512969970703e-4;
const SC_PIO2_3: f32 = 7.549790126404332e-8;

// (sin r, cos r) for |r| <= pi/4, turned by n quarter turns.
fn sincos_quadrant(r: f32, n: i32) -> vec2<f32> {
    let z = r * r;
    let s = r + r * z * (-1.0 / 6.0 + z * (1.0 / 120.0 + z * (-1.0 / 5040.0 + z * (1.0 / 362880.0))));
    let c = 1.0 + z * (-0.5 + z * (1.0 / 24.0 + z * (-1.0 / 720.0 + z * (1.0 / 40320.0 + z * (-1.0 / 3628800.0)))));
    switch (n & 3) {
        case 0: { return vec2<f32>(s, c); }
        case 1: { return vec2<f32>(c, -s); }
        case 2: { return vec2<f32>(-s, -c); }
        default: { return vec2<f32>(-c, s); }
    }
}

// (sin v, cos v).
fn sincos(v: f32) -> vec2<f32> {
    let n = round(v * SC_TWO_OVER_PI);
    let r = ((v - n * SC_PIO2_1) - n * SC_PIO2_2) - n * SC_PIO2_3;
    return sincos_quadrant(r, i32(n));
}

// (sin(pi q), cos(pi q)).
fn sincospi(q: f32) -> vec2<f32> {
    let m = q - 2.0 * floor(q * 0.5 + 0.5); // q modulo 2, in [-1, 1), exact
    let n = round(2.0 * m);
    let r = m - 0.5 * n; // in [-1/4, 1/4], exact
    return sincos_quadrant(SC_PI * r, i32(n));
}
