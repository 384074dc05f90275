// The colour each Gaussian shows from one camera centre: its degree-0 colour plus its higher
// spherical harmonics (degrees 1 to 3, as 3D Gaussian splatting's PLY files carry them in
// `f_rest_*`) evaluated along the unit direction from the camera centre to its mean. The
// rasteriser then draws these colours (clamping them below at 0, as 3D Gaussian splatting
// does). Forward only: the models predict view-independent colours; this draws other tools'
// scenes as they were trained. The f64 reference is `raster::reference::sh_colour`.

struct Params {
    n: u32,      // Gaussians
    degree: u32, // 1, 2 or 3
    eye_x: f32,
    eye_y: f32,
    eye_z: f32,
}

@group(0) @binding(0) var<storage, read> means: array<f32>;        // [N, 3]
@group(0) @binding(1) var<storage, read> base: array<f32>;         // [N, 3] degree-0 colours
// [N, 3K]: per Gaussian all K coefficients of red, then green, then blue (the PLY's order).
@group(0) @binding(2) var<storage, read> rest: array<f32>;
@group(0) @binding(3) var<storage, read_write> colours: array<f32>; // [N, 3]
var<immediate> pc: Params;

// The basis' constants (degree 1, 2, 3), as 3D Gaussian splatting's sh_utils gives them.
const C1: f32 = 0.4886025119029199;
const C2: array<f32, 5> = array<f32, 5>(1.0925484305920792, -1.0925484305920792,
                                        0.31539156525252005, -1.0925484305920792,
                                        0.5462742152960396);
const C3: array<f32, 7> = array<f32, 7>(-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                                        0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                                        -0.5900435899266435);

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (g >= pc.n) {
        return;
    }
    let k = (pc.degree + 1u) * (pc.degree + 1u) - 1u;
    let d = vec3<f32>(means[3u * g], means[3u * g + 1u], means[3u * g + 2u])
        - vec3<f32>(pc.eye_x, pc.eye_y, pc.eye_z);
    let len = length(d);
    // A mean at the camera centre has no direction: its degree-0 colour alone.
    var basis: array<f32, 15>;
    if (len > 0.0) {
        let u = d / len;
        let x = u.x;
        let y = u.y;
        let z = u.z;
        basis[0] = -C1 * y;
        basis[1] = C1 * z;
        basis[2] = -C1 * x;
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        basis[3] = C2[0] * x * y;
        basis[4] = C2[1] * y * z;
        basis[5] = C2[2] * (2.0 * zz - xx - yy);
        basis[6] = C2[3] * x * z;
        basis[7] = C2[4] * (xx - yy);
        basis[8] = C3[0] * y * (3.0 * xx - yy);
        basis[9] = C3[1] * x * y * z;
        basis[10] = C3[2] * y * (4.0 * zz - xx - yy);
        basis[11] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
        basis[12] = C3[4] * x * (4.0 * zz - xx - yy);
        basis[13] = C3[5] * z * (xx - yy);
        basis[14] = C3[6] * x * (xx - 3.0 * yy);
    }
    for (var c = 0u; c < 3u; c++) {
        var sum = base[3u * g + c];
        for (var j = 0u; j < k; j++) {
            sum += basis[j] * rest[(g * 3u + c) * k + j];
        }
        colours[3u * g + c] = sum;
    }
}
