//! Renders an [`AnimatedMesh`] frame from many cameras at once on the engine: depth, triangle
//! id, barycentrics and RGB. Kernels: `shaders/mesh_raster.wgsl` (the pass structure and the
//! tie rule are described there).
//!
//! Why a compute rasteriser rather than a Vulkan graphics pipeline: the engine is compute only
//! (storage buffers, push descriptors, one recorder), lavapipe runs compute well, and the
//! id/barycentric outputs the tracks need are plain buffers this way. The cost is a per-pixel
//! loop per triangle, which suits the data's small, many-triangle meshes.
//!
//! [`reference`] holds the CPU version the tests check it against (a ray cast per pixel).

use velox_engine::kernels::args;
use velox_engine::kernels::{MESH_RASTER_CLEAR, MESH_RASTER_DEPTH, MESH_RASTER_RESOLVE, MESH_RASTER_SHADE};
use velox_engine::{DType, Gpu, Tensor};

use crate::camera::Camera;
use crate::math::{normalize, V3};
use crate::mesh::AnimatedMesh;
use crate::{DataError, DataResult};

/// The triangle id of a pixel that shows no surface.
pub const NO_TRIANGLE: u32 = u32::MAX;

use velox_engine::kernels::params::MeshRasterParams as Params;

/// Lighting and background of the RGB output.
#[derive(Clone, Copy, Debug)]
pub struct Shading {
    /// Direction towards the light, world space (fixed, so colours do not depend on the view).
    pub light: V3,
    /// Share of ambient light in [0, 1].
    pub ambient: f32,
    pub background: [f32; 3],
}

impl Default for Shading {
    fn default() -> Shading {
        Shading { light: normalize([0.4, 1.0, 0.6]), ambient: 0.45, background: [0.0; 3] }
    }
}

/// What one batch of views of one frame shows; per-pixel arrays are view-major, then rows.
#[derive(Clone, Debug, Default)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub views: usize,
    /// Camera-space depth, 0 where no surface.
    pub depth: Vec<f32>,
    /// Triangle id, [`NO_TRIANGLE`] where no surface.
    pub ids: Vec<u32>,
    /// Perspective-correct barycentrics (b1, b2) of vertices 1 and 2 of the triangle.
    pub bary: Vec<[f32; 2]>,
    /// Shaded colour, RGBA8 (alpha 0 on the background).
    pub rgb: Vec<u32>,
}

impl Frame {
    pub fn pixels(&self) -> usize {
        (self.width * self.height) as usize
    }
}

/// Nearest plane: triangles with a vertex closer than this are not drawn.
pub const NEAR: f32 = 0.05;
/// Bytes the largest per-pixel output may take in one batch (lavapipe binds 128 MiB at most).
const MAX_BATCH_BYTES: usize = 64 << 20;

/// A mesh's fixed data on the device: connectivity, UVs and textures; frames come per render.
pub struct MeshRasteriser {
    gpu: Gpu,
    n_tris: u32,
    n_verts: usize,
    tris: Tensor,
    uvs: Tensor,
    tri_tex: Tensor,
    tex_table: Tensor,
    texels: Tensor,
    /// RGB per vertex (white for a mesh without colours).
    colours: Tensor,
    pub shading: Shading,
}

impl MeshRasteriser {
    pub fn new(gpu: &Gpu, mesh: &AnimatedMesh) -> DataResult<MeshRasteriser> {
        mesh.validate()?;
        let tris: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
        let uvs: Vec<f32> = mesh.uvs.iter().flatten().copied().collect();
        let mut table = Vec::with_capacity(4 * mesh.textures.len());
        let mut texels = Vec::new();
        for t in &mesh.textures {
            table.extend([texels.len() as u32, t.width, t.height, 0]);
            texels.extend_from_slice(&t.texels);
        }
        let colours: Vec<f32> = if mesh.colours.is_empty() {
            vec![1.0; 3 * mesh.num_vertices()]
        } else {
            mesh.colours.iter().flatten().copied().collect()
        };
        let n_tris = u32::try_from(mesh.triangles.len())
            .map_err(|_| DataError::Invalid("more than 2^32 triangles".into()))?;
        Ok(MeshRasteriser {
            gpu: gpu.clone(),
            n_tris,
            n_verts: mesh.num_vertices(),
            tris: Tensor::from_slice(gpu, &[tris.len()], &tris)?,
            uvs: Tensor::from_slice(gpu, &[uvs.len()], &uvs)?,
            tri_tex: Tensor::from_slice(gpu, &[mesh.tri_texture.len()], &mesh.tri_texture)?,
            tex_table: Tensor::from_slice(gpu, &[table.len()], &table)?,
            texels: Tensor::from_slice(gpu, &[texels.len()], &texels)?,
            colours: Tensor::from_slice(gpu, &[colours.len()], &colours)?,
            shading: Shading::default(),
        })
    }

    /// Renders vertex positions `verts` (one frame) from `cameras`, which must share one image
    /// size. Views are split into batches that each device can bind.
    pub fn render(&self, verts: &[V3], cameras: &[Camera]) -> DataResult<Frame> {
        if verts.len() != self.n_verts {
            return Err(DataError::Invalid(format!(
                "render: {} vertices given, the mesh has {}",
                verts.len(),
                self.n_verts
            )));
        }
        let Some(first) = cameras.first() else {
            return Ok(Frame::default());
        };
        let (width, height) = (first.width, first.height);
        if cameras.iter().any(|c| c.width != width || c.height != height) {
            return Err(DataError::Invalid("render: cameras of one batch must share an image size".into()));
        }
        let pixels = (width * height) as usize;
        let per_batch = (MAX_BATCH_BYTES / (8 * pixels).max(1)).max(1);
        let flat: Vec<f32> = verts.iter().flatten().copied().collect();
        let verts_t = Tensor::from_slice(&self.gpu, &[flat.len()], &flat)?;
        let mut out = Frame {
            width,
            height,
            views: cameras.len(),
            depth: Vec::with_capacity(pixels * cameras.len()),
            ids: Vec::with_capacity(pixels * cameras.len()),
            bary: Vec::with_capacity(pixels * cameras.len()),
            rgb: Vec::with_capacity(pixels * cameras.len()),
        };
        for batch in cameras.chunks(per_batch) {
            self.render_batch(&verts_t, batch, &mut out)?;
        }
        Ok(out)
    }

    fn render_batch(&self, verts: &Tensor, cameras: &[Camera], out: &mut Frame) -> DataResult<()> {
        let gpu = &self.gpu;
        let (w, h) = (cameras[0].width, cameras[0].height);
        let n = cameras.len() * (w * h) as usize;
        let cams: Vec<f32> = cameras.iter().flat_map(crate::camera::gpu_row).collect();
        let cams = Tensor::from_slice(gpu, &[cams.len()], &cams)?;
        let depth_bits = Tensor::empty(gpu, &[n], DType::U32)?;
        let ids = Tensor::empty(gpu, &[n], DType::U32)?;
        let depth = Tensor::empty(gpu, &[n], DType::F32)?;
        let bary = Tensor::empty(gpu, &[2 * n], DType::F32)?;
        let rgb = Tensor::empty(gpu, &[n], DType::U32)?;
        let s = &self.shading;
        let params = Params {
            n_tris: self.n_tris,
            n_views: cameras.len() as u32,
            width: w,
            height: h,
            light: [s.light[0], s.light[1], s.light[2], s.ambient],
            bg: [s.background[0], s.background[1], s.background[2], NEAR],
        };
        let wg = 64u64;
        let tri_items = (cameras.len() as u64 * self.n_tris as u64).div_ceil(wg);
        let pix_items = (n as u64).div_ceil(wg);
        let mut rec = gpu.recorder()?;
        rec.dispatch_linear(
            MESH_RASTER_CLEAR,
            pix_items,
            args::MeshRasterClearArgs { depth_bits: &depth_bits, ids: &ids },
            &params,
        )?;
        rec.dispatch_linear(
            MESH_RASTER_DEPTH,
            tri_items,
            args::MeshRasterDepthArgs { verts, tris: &self.tris, cams: &cams, depth_bits: &depth_bits },
            &params,
        )?;
        rec.dispatch_linear(
            MESH_RASTER_RESOLVE,
            tri_items,
            args::MeshRasterResolveArgs {
                verts,
                tris: &self.tris,
                cams: &cams,
                depth_bits: &depth_bits,
                ids: &ids,
            },
            &params,
        )?;
        rec.dispatch_linear(
            MESH_RASTER_SHADE,
            pix_items,
            args::MeshRasterShadeArgs {
                verts,
                tris: &self.tris,
                cams: &cams,
                ids: &ids,
                uvs: &self.uvs,
                tri_tex: &self.tri_tex,
                tex_table: &self.tex_table,
                texels: &self.texels,
                out_depth: &depth,
                out_bary: &bary,
                out_rgb: &rgb,
                colours: &self.colours,
            },
            &params,
        )?;
        rec.submit()?;
        out.depth.extend(depth.read::<f32>()?);
        out.ids.extend(ids.read::<u32>()?);
        out.bary.extend(bary.read::<f32>()?.chunks_exact(2).map(|c| [c[0], c[1]]));
        out.rgb.extend(rgb.read::<u32>()?);
        Ok(())
    }

    /// Anti-aliased RGB: renders at `factor` times the resolution and averages each
    /// `factor` x `factor` block. Returns 8-bit RGB rows per camera.
    pub fn render_rgb_supersampled(
        &self,
        verts: &[V3],
        cameras: &[Camera],
        factor: u32,
    ) -> DataResult<Vec<Vec<u8>>> {
        let big: Vec<Camera> = cameras.iter().map(|c| c.upscaled(factor)).collect();
        let frame = self.render(verts, &big)?;
        Ok(cameras
            .iter()
            .enumerate()
            .map(|(v, c)| {
                downsample(&frame.rgb[v * frame.pixels()..(v + 1) * frame.pixels()], c.width, factor)
            })
            .collect())
    }
}

/// Box filter of a `width * factor` square RGBA8 image down to `width` pixels a side, as RGB8.
fn downsample(rgba: &[u32], width: u32, factor: u32) -> Vec<u8> {
    let big = (width * factor) as usize;
    let (w, f) = (width as usize, factor as usize);
    let mut out = Vec::with_capacity(3 * w * w);
    for y in 0..w {
        for x in 0..w {
            let mut acc = [0u32; 3];
            for dy in 0..f {
                for dx in 0..f {
                    let t = rgba[(y * f + dy) * big + x * f + dx];
                    acc[0] += t & 255;
                    acc[1] += (t >> 8) & 255;
                    acc[2] += (t >> 16) & 255;
                }
            }
            let d = (f * f) as u32;
            out.extend(acc.map(|a| ((a + d / 2) / d) as u8));
        }
    }
    out
}

/// The CPU version the kernels are checked against: a ray cast per pixel centre, nearest hit.
pub mod reference {
    use crate::camera::Camera;
    use crate::math::{cross, dot, sub, V3};

    /// (depth, triangle id) per pixel, row-major; (0, u32::MAX) where the ray hits nothing.
    pub fn depth_and_ids(verts: &[V3], tris: &[[u32; 3]], cam: &Camera) -> Vec<(f64, u32)> {
        let origin = cam.position();
        let mut out = Vec::with_capacity((cam.width * cam.height) as usize);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let far = cam.unproject(x as f32 + 0.5, y as f32 + 0.5, 1.0);
                let dir = sub(far, origin);
                let mut best = (f64::INFINITY, u32::MAX);
                for (i, t) in tris.iter().enumerate() {
                    let [a, b, c] = t.map(|k| verts[k as usize]);
                    if let Some(s) = intersect(origin, dir, a, b, c) {
                        // `dir` has unit camera-space z, so the ray parameter is the depth.
                        if s < best.0 {
                            best = (s, i as u32);
                        }
                    }
                }
                out.push(if best.1 == u32::MAX { (0.0, u32::MAX) } else { best });
            }
        }
        out
    }

    /// Möller-Trumbore in f64; the ray parameter of the hit, if any.
    fn intersect(o: V3, d: V3, a: V3, b: V3, c: V3) -> Option<f64> {
        let f = |v: V3| v.map(|x| x as f64);
        let (o, d, a, b, c) = (f(o), f(d), f(a), f(b), f(c));
        let sub = |p: [f64; 3], q: [f64; 3]| [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
        let cross = |p: [f64; 3], q: [f64; 3]| {
            [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]]
        };
        let dot = |p: [f64; 3], q: [f64; 3]| p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
        let e1 = sub(b, a);
        let e2 = sub(c, a);
        let p = cross(d, e2);
        let det = dot(e1, p);
        if det.abs() < 1e-14 {
            return None;
        }
        let inv = 1.0 / det;
        let s = sub(o, a);
        let u = dot(s, p) * inv;
        let q = cross(s, e1);
        let v = dot(d, q) * inv;
        let t = dot(e2, q) * inv;
        (u >= 0.0 && v >= 0.0 && u + v <= 1.0 && t > 0.0).then_some(t)
    }

    /// Distance from `p` to triangle (a, b, c), in f64.
    pub fn point_triangle_distance(p: V3, a: V3, b: V3, c: V3) -> f64 {
        // Project onto the plane; if inside use the plane distance, else the nearest edge.
        let n = cross(sub(b, a), sub(c, a));
        let nn = dot(n, n) as f64;
        let edge_dist = |u: V3, v: V3| {
            let e = sub(v, u);
            let t = (dot(sub(p, u), e) as f64 / (dot(e, e) as f64).max(1e-30)).clamp(0.0, 1.0);
            let q: [f64; 3] = std::array::from_fn(|k| u[k] as f64 + t * e[k] as f64 - p[k] as f64);
            (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt()
        };
        if nn > 0.0 {
            let inside =
                [(a, b), (b, c), (c, a)].iter().all(|&(u, v)| dot(cross(sub(v, u), sub(p, u)), n) >= 0.0);
            if inside {
                return (dot(sub(p, a), n) as f64).abs() / nn.sqrt();
            }
        }
        edge_dist(a, b).min(edge_dist(b, c)).min(edge_dist(c, a))
    }
}
