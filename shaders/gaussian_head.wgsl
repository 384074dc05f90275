// The Gaussian decoder's head activations (docs/models.md, Gaussian decoder): each voxel token
// gives G Gaussians of 14 raw numbers (offset 3, scale 3, quaternion 4, opacity 1, rgb 3),
// mapped to the rasteriser's parameters:
//   mean      = voxel centre + (2 sigmoid(o) - 1) * offset_range
//   log_scale = log(scale_min + (scale_max - scale_min) * sigmoid(l))
//   quat      = q (the rasteriser normalises it)
//   logit     = a (the rasteriser applies the sigmoid: opacity = sigmoid(a))
//   colour    = sigmoid(c)
// `backward` maps the rasteriser's gradients back to the raw numbers.

struct Params {
    gaussians: u32,      // M = voxels x per_voxel
    per_voxel: u32,
    offset_range: f32,
    scale_min: f32,
    scale_max: f32,
}

@group(0) @binding(0) var<storage, read> raw: array<f32>;        // [M, 14]
@group(0) @binding(1) var<storage, read> centres: array<f32>;    // [V, 3]
@group(0) @binding(2) var<storage, read_write> means: array<f32>;      // [M, 3]
@group(0) @binding(3) var<storage, read_write> log_scales: array<f32>; // [M, 3]
@group(0) @binding(4) var<storage, read_write> quats: array<f32>;      // [M, 4]
@group(0) @binding(5) var<storage, read_write> logits: array<f32>;     // [M]
@group(0) @binding(6) var<storage, read_write> colours: array<f32>;    // [M, 3]
@group(0) @binding(7) var<storage, read> d_means: array<f32>;
@group(0) @binding(8) var<storage, read> d_log_scales: array<f32>;
@group(0) @binding(9) var<storage, read> d_quats: array<f32>;
@group(0) @binding(10) var<storage, read> d_logits: array<f32>;
@group(0) @binding(11) var<storage, read> d_colours: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_raw: array<f32>;     // [M, 14]
var<immediate> pc: Params;

fn sigmoid(v: f32) -> f32 {
    return 1.0 / (1.0 + exp(-v));
}

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let m = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (m >= pc.gaussians) {
        return;
    }
    let r = m * 14u;
    let v = m / pc.per_voxel;
    for (var a = 0u; a < 3u; a++) {
        means[m * 3u + a] = centres[v * 3u + a] + (2.0 * sigmoid(raw[r + a]) - 1.0) * pc.offset_range;
        log_scales[m * 3u + a] = log(pc.scale_min + (pc.scale_max - pc.scale_min) * sigmoid(raw[r + 3u + a]));
        colours[m * 3u + a] = sigmoid(raw[r + 11u + a]);
    }
    for (var a = 0u; a < 4u; a++) {
        quats[m * 4u + a] = raw[r + 6u + a];
    }
    logits[m] = raw[r + 10u];
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let m = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (m >= pc.gaussians) {
        return;
    }
    let r = m * 14u;
    for (var a = 0u; a < 3u; a++) {
        let so = sigmoid(raw[r + a]);
        d_raw[r + a] = d_means[m * 3u + a] * 2.0 * pc.offset_range * so * (1.0 - so);
        let sl = sigmoid(raw[r + 3u + a]);
        let span = pc.scale_max - pc.scale_min;
        let scale = pc.scale_min + span * sl;
        d_raw[r + 3u + a] = d_log_scales[m * 3u + a] * span * sl * (1.0 - sl) / scale;
        let sc = sigmoid(raw[r + 11u + a]);
        d_raw[r + 11u + a] = d_colours[m * 3u + a] * sc * (1.0 - sc);
    }
    for (var a = 0u; a < 4u; a++) {
        d_raw[r + 6u + a] = d_quats[m * 4u + a];
    }
    d_raw[r + 10u] = d_logits[m];
}
