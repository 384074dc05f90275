// The push constants of the rasteriser's blend pass and of its backward kernels (one
// declaration, so the host side fills one struct for both).
struct Params {
    background: vec4<f32>,
    width: u32,
    height: u32,
    tiles_x: u32,
    gaussians: u32, // Gaussians in the frame: `sum_pairs` of the per-pair backward kernel reads it
    alpha_max: f32,
    min_alpha: f32,
    t_stop: f32,
    pairs: u32, // `sum_pairs`: the slots `pair_grads` holds (the tile lists' room)
}
