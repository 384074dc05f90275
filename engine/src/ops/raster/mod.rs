//! Tile-based differentiable rasteriser of 3D Gaussians, forward and backward.
//!
//! It is one op family, so it follows the op layout of DESIGN.md: kernels in
//! `shaders/raster_*.wgsl`, host side here, f64 CPU reference in [`reference`]. It is a folder
//! rather than one file because the host side has two passes of several kernels each
//! ([`forward`]: project, tile lists, sort, ranges, blend; [`backward`]: blend backward, then
//! projection backward), and the reference, which holds both passes' rules, is as long again.
//!
//! # Conventions
//! - Gaussians: means `[N, 3]` (world), log-scales `[N, 3]` (scale = exp), quaternions
//!   `[N, 4]` as (w, x, y, z), normalised by the rasteriser (any non-zero length), opacities
//!   `[N]` as logits (opacity = sigmoid), colours `[N, 3]`, negative channels
//!   clamped to 0 (as 3D Gaussian splatting clamps its spherical-harmonic colour; a clamped
//!   channel gets no gradient), no upper clamp.
//!   Gradients are with respect to these same quantities.
//! - Camera: pinhole, world-to-camera rotation `R` and translation `t` (x right, y down, z
//!   forward), intrinsics fx, fy, cx, cy in pixels; pixel (x, y) has its centre at
//!   (x + 0.5, y + 0.5).
//! - Outputs: RGB `[H, W, 3]` = sum c_i w_i + T bg, alpha `[H, W]` = 1 - T, and the expected
//!   depth `[H, W]` = sum z_i w_i with w_i = alpha_i T_i (camera z, not normalised by alpha:
//!   divide by alpha for the depth of the covered part).
//!
//! # Guards
//! [`DILATION`], [`ALPHA_MAX`], [`MIN_ALPHA`], [`T_STOP`], [`MIN_DET`], [`NEAR`],
//! [`MAX_TILES_PER_GAUSSIAN`], [`MIN_QUAT_NORM2`]. A Gaussian with a NaN or Inf anywhere, a
//! zero quaternion or a degenerate projection is dropped and counted ([`RenderStats`]); so are
//! those behind the near plane, too faint, outside the image or over the tile limit. No
//! dropped Gaussian reaches a pixel or receives a gradient.

pub mod backward;
pub mod forward;
pub mod reference;
pub mod sh;

pub use backward::{render_backward, render_backward_cas, render_backward_with, BackwardKernel};
pub use forward::{
    project, rasterize, rasterize_within, render, render_view, Image, Projected, RenderStats, Rendered,
};
pub use sh::sh_colours;

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::rng::Rng;
use crate::tensor::{DType, Tensor};
use crate::Gpu;

/// Tile side in pixels; one workgroup blends one tile.
pub const TILE: u32 = 16;
/// Variance in px^2 added to the diagonal of every projected covariance: a low-pass filter
/// about one pixel wide (standard deviation 0.55 px) so that sub-pixel Gaussians still cover a
/// pixel centre instead of aliasing. The value 3D Gaussian splatting and gsplat use.
pub const DILATION: f32 = 0.3;
/// Largest alpha a Gaussian may have at a pixel, so that one Gaussian never makes a pixel
/// fully opaque and 1 - alpha stays invertible in the backward pass.
pub const ALPHA_MAX: f32 = 0.99;
/// Contributions with alpha below 1/255 (invisible in an 8-bit image) are skipped; it also
/// bounds each Gaussian's footprint and culls Gaussians with opacity below it.
pub const MIN_ALPHA: f32 = 1.0 / 255.0;
/// A pixel stops blending when the next Gaussian would bring its transmittance below this.
pub const T_STOP: f32 = 1e-4;
/// Projected 2D covariances with a determinant below this (px^4) are degenerate and dropped.
/// The dilation keeps a sound one above 0.09, so only lost precision gets here.
pub const MIN_DET: f32 = 1e-6;
/// Camera-space depth below which a Gaussian is behind the near plane and dropped.
pub const NEAR: f32 = 0.01;
/// Most tiles one Gaussian may touch (a 4096 x 4096 image has 65536): keeps one runaway
/// Gaussian from filling the key buffer. Larger ones are dropped and counted.
pub const MAX_TILES_PER_GAUSSIAN: u32 = 1 << 16;
/// Quaternions with a squared length below this are invalid.
pub const MIN_QUAT_NORM2: f32 = 1e-24;

/// A pinhole camera: world-to-camera rotation (rows) and translation, intrinsics in pixels.
/// `x_c = R x_w + t`, camera x right, y down, z forward (depth is the camera-space z); pixel
/// `u = fx x_c / z + cx`, `v = fy y_c / z + cy`, pixel (i, j) covers [i, i + 1) x [j, j + 1)
/// and its centre is (i + 0.5, j + 0.5). The rasteriser, the data's camera rigs and the
/// scenes' `cameras.json` all use this one type.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub rotation: [[f32; 3]; 3],
    pub translation: [f32; 3],
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn normalise(a: [f32; 3]) -> [f32; 3] {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

impl Camera {
    /// Focal length for a vertical field of view, principal point at the image centre.
    fn intrinsics(fov_y_deg: f32, width: u32, height: u32) -> (f32, f32, f32, f32) {
        let f = 0.5 * height as f32 / (0.5 * fov_y_deg.to_radians()).tan();
        (f, f, 0.5 * width as f32, 0.5 * height as f32)
    }

    /// At the origin looking down +z (y down), with a vertical field of view in degrees.
    pub fn identity(fov_y_deg: f32, width: u32, height: u32) -> Camera {
        let (fx, fy, cx, cy) = Camera::intrinsics(fov_y_deg, width, height);
        Camera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        }
    }

    /// At `eye` looking at `target`, with `up` pointing up in the image.
    pub fn look_at(
        eye: [f32; 3],
        target: [f32; 3],
        up: [f32; 3],
        fov_y_deg: f32,
        width: u32,
        height: u32,
    ) -> Camera {
        let z = normalise(sub(target, eye));
        let x = normalise(cross(z, up));
        let y = cross(z, x);
        let rotation = [x, y, z];
        let dot = |r: [f32; 3]| -(r[0] * eye[0] + r[1] * eye[1] + r[2] * eye[2]);
        Camera {
            rotation,
            translation: [dot(x), dot(y), dot(z)],
            ..Camera::identity(fov_y_deg, width, height)
        }
    }

    /// The same view with `factor` times the pixels on each side (for supersampling).
    pub fn upscaled(&self, factor: u32) -> Camera {
        let s = factor as f32;
        Camera {
            fx: self.fx * s,
            fy: self.fy * s,
            cx: self.cx * s,
            cy: self.cy * s,
            width: self.width * factor,
            height: self.height * factor,
            ..*self
        }
    }

    /// The camera's centre in the world, -R^T t.
    pub fn centre(&self) -> [f32; 3] {
        let (r, t) = (self.rotation, self.translation);
        std::array::from_fn(|k| -(r[0][k] * t[0] + r[1][k] * t[1] + r[2][k] * t[2]))
    }

    /// A world point in camera space.
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i])
    }

    /// Pixel coordinates and depth of a world point.
    pub fn project(&self, p: [f32; 3]) -> (f32, f32, f32) {
        let c = self.to_camera(p);
        (self.fx * c[0] / c[2] + self.cx, self.fy * c[1] / c[2] + self.cy, c[2])
    }

    /// Whether the camera sees world point `p` in `depth`, a depth frame of its image
    /// (camera z per pixel, row-major, 0 where no surface): `p` projects into the image, in
    /// front of the camera, onto a pixel that shows surface, and lies not farther than that
    /// surface by more than three pixel footprints (`3 z / fx`). The data's tracks and the
    /// tracker's occlusion both use this test. A point on a silhouette whose pixel's centre
    /// sample misses the object counts as unseen: the depth frame shows nothing there.
    pub fn sees(&self, p: [f32; 3], depth: &[f32]) -> bool {
        let (u, v, z) = self.project(p);
        let inside = z > 0.0 && u >= 0.0 && v >= 0.0 && u < self.width as f32 && v < self.height as f32;
        if !inside {
            return false;
        }
        let d = depth[v as usize * self.width as usize + u as usize];
        d > 0.0 && z <= d + 3.0 * z / self.fx
    }

    /// The world point at depth `z` under pixel position (u, v).
    pub fn unproject(&self, u: f32, v: f32, z: f32) -> [f32; 3] {
        let c = [(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z];
        let q = sub(c, self.translation);
        let r = &self.rotation;
        // R is orthonormal: its inverse is its transpose.
        std::array::from_fn(|k| r[0][k] * q[0] + r[1][k] * q[1] + r[2][k] * q[2])
    }

    /// Camera centre in the world.
    pub fn position(&self) -> [f32; 3] {
        self.unproject(self.cx, self.cy, 0.0)
    }

    /// Tiles across and down.
    pub fn tiles(&self) -> (u32, u32) {
        (self.width.div_ceil(TILE), self.height.div_ceil(TILE))
    }

    /// Bits of a tile index (at least one): the tile sort of the tile lists sorts on these.
    pub fn tile_bits(&self) -> u32 {
        let (tx, ty) = self.tiles();
        let tiles = tx * ty;
        (32 - (tiles.max(2) - 1).leading_zeros()).max(1)
    }

    pub(crate) fn check(&self) -> Result<()> {
        let (tx, ty) = self.tiles();
        if self.width == 0 || self.height == 0 || tx > 65535 || ty > 65535 || tx * ty > 1 << 24 {
            return Err(Error::Shape(format!(
                "camera image {}x{}: both sides must be non-zero and at most 2^24 tiles in all",
                self.width, self.height
            )));
        }
        let all = [self.fx, self.fy, self.cx, self.cy]
            .into_iter()
            .chain(self.rotation.into_iter().flatten())
            .chain(self.translation);
        if all.into_iter().any(|v| !v.is_finite()) || self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(Error::Invalid(format!(
                "camera has non-finite or non-positive focal lengths: {self:?}"
            )));
        }
        Ok(())
    }
}

/// A set of N Gaussians as one list of values per quantity (see the module conventions):
/// means `[N, 3]`, log-scales `[N, 3]`, quaternions `[N, 4]`, opacity logits `[N]`, colours
/// `[N, 3]`. On the device it is [`Gaussians`] (tensors), on the host [`GaussianData`] (f32
/// vectors). The Gaussian decoder's head writes one, the rasteriser draws one, and gradients
/// with respect to a set are a set of the same shapes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianSet<T> {
    pub means: T,
    pub log_scales: T,
    pub quats: T,
    pub opacities: T,
    pub colours: T,
}

/// Gaussians on the device.
pub type Gaussians = GaussianSet<Tensor>;
/// Gaussians on the host.
pub type GaussianData = GaussianSet<Vec<f32>>;

/// Values per Gaussian of each quantity, in field order.
pub const GAUSSIAN_WIDTHS: [usize; 5] = [3, 3, 4, 1, 3];
/// The quantities' names, in field order.
pub const GAUSSIAN_FIELDS: [&str; 5] = ["means", "log_scales", "quats", "opacities", "colours"];

impl<T> GaussianSet<T> {
    /// The five quantities in field order.
    pub fn fields(&self) -> [&T; 5] {
        [&self.means, &self.log_scales, &self.quats, &self.opacities, &self.colours]
    }

    /// A set built from the five quantities in field order.
    pub fn from_fields([means, log_scales, quats, opacities, colours]: [T; 5]) -> GaussianSet<T> {
        GaussianSet { means, log_scales, quats, opacities, colours }
    }

    /// Each quantity through `f` (with its values per Gaussian), in field order.
    pub fn try_map<U, E>(
        &self,
        mut f: impl FnMut(&T, usize) -> std::result::Result<U, E>,
    ) -> std::result::Result<GaussianSet<U>, E> {
        let [m, l, q, o, c] = self.fields();
        Ok(GaussianSet {
            means: f(m, 3)?,
            log_scales: f(l, 3)?,
            quats: f(q, 4)?,
            opacities: f(o, 1)?,
            colours: f(c, 3)?,
        })
    }
}

impl GaussianData {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }
    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// Fails unless every quantity has the length N Gaussians need.
    pub fn check(&self) -> Result<()> {
        let n = self.len();
        let lens = [self.means.len(), self.log_scales.len(), self.quats.len(), self.colours.len()];
        if lens != [3 * n, 3 * n, 4 * n, 3 * n] {
            return Err(Error::Shape(format!(
                "Gaussians: {n} opacities need 3N means, log-scales and colours and 4N quaternions, got {lens:?}"
            )));
        }
        Ok(())
    }

    /// The tensors the rasteriser takes.
    pub fn upload(&self, gpu: &Gpu) -> Result<Gaussians> {
        self.check()?;
        let n = self.len();
        self.try_map(|v, w| Tensor::from_slice(gpu, &field_shape(n, w), v))
    }

    /// Appends one Gaussian.
    pub fn push(
        &mut self,
        mean: [f32; 3],
        log_scale: [f32; 3],
        quat: [f32; 4],
        logit: f32,
        colour: [f32; 3],
    ) {
        self.means.extend(mean);
        self.log_scales.extend(log_scale);
        self.quats.extend(quat);
        self.opacities.push(logit);
        self.colours.extend(colour);
    }

    /// The benchmark scene gsplat is compared on, for a camera at the origin looking down +z:
    /// means ~ N(0, 0.6^2) per axis shifted to z = 3, log-scales ~ N(ln 0.01, 0.3^2), random
    /// unit quaternions, opacity sigmoid(N(0, 1)) (so logits ~ N(0, 1)), colours uniform in
    /// [0, 1).
    pub fn benchmark_scene(n: usize, seed: u64) -> GaussianData {
        let mut rng = Rng::new(seed);
        let mut g = GaussianData::default();
        for _ in 0..n {
            let mean = [0.6 * rng.normal(), 0.6 * rng.normal(), 3.0 + 0.6 * rng.normal()].map(|v| v as f32);
            let log_scale = [0; 3].map(|_| (0.01f64.ln() + 0.3 * rng.normal()) as f32);
            let q = [0; 4].map(|_| rng.normal());
            let l = q.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
            let quat = q.map(|v| (v / l) as f32);
            let logit = rng.normal() as f32;
            let colour = [0; 3].map(|_| rng.uniform() as f32);
            g.push(mean, log_scale, quat, logit, colour);
        }
        g
    }
}

/// The shape of a quantity of `w` values per Gaussian: `[n]` for one, else `[n, w]`.
fn field_shape(n: usize, w: usize) -> Vec<usize> {
    if w == 1 {
        vec![n]
    } else {
        vec![n, w]
    }
}

impl Gaussians {
    pub fn len(&self) -> usize {
        self.opacities.numel()
    }

    /// Uninitialised tensors for `n` Gaussians.
    pub fn empty(gpu: &Gpu, n: usize) -> Result<Gaussians> {
        let t = |w: usize| Tensor::empty(gpu, &field_shape(n, w), DType::F32);
        Ok(GaussianSet { means: t(3)?, log_scales: t(3)?, quats: t(4)?, opacities: t(1)?, colours: t(3)? })
    }

    /// Copies the set to the host.
    pub fn download(&self) -> Result<GaussianData> {
        self.check()?;
        self.try_map(|t, _| t.read::<f32>())
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Number of Gaussians after checking every shape and dtype.
    pub fn check(&self) -> Result<usize> {
        let n = self.len();
        let want: [(&Tensor, usize, &str); 5] = [
            (&self.means, 3, "means"),
            (&self.log_scales, 3, "log_scales"),
            (&self.quats, 4, "quats"),
            (&self.opacities, 1, "opacities"),
            (&self.colours, 3, "colours"),
        ];
        for (t, width, name) in want {
            if t.dtype() != DType::F32 || t.numel() != n * width {
                return Err(Error::Shape(format!(
                    "Gaussians: {name} {t:?} must be f32 with {width} values for each of the {n} Gaussians"
                )));
            }
        }
        fit_u32(n, || format!("{n} Gaussians"))?;
        Ok(n)
    }
}
