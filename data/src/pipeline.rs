//! From an animated mesh to a training scene: renders every frame from the input, supervision
//! and video cameras, back-projects the input views to the 4D colour point cloud, voxelises it
//! to occupancy, and follows surface points as tracks.
//!
//! - **Point cloud** (docs/models.md): every input-view pixel that shows the surface,
//!   back-projected at its centre with its depth, is a candidate (x, y, z, r, g, b,
//!   tau = frame / 100); a reservoir sample over all frames keeps the requested number, so each
//!   candidate is equally likely and frames with more visible surface give more points. When fewer candidates exist
//!   than were asked for, random candidates are repeated to reach the size. Points come out
//!   ordered by frame.
//! - **Occupancy**: the 64^3 voxels of [-1, 1]^3 that a triangle shown by some input pixel of
//!   the frame passes through (the exact triangle-box overlap), and those holding a candidate
//!   (depth rounding can put one a hair across a voxel face). Whole triangles, not the pixels'
//!   points: pixels alone leave holes where the surface is seen at a grazing angle, and more of
//!   them the lower the resolution (at 48 px, 15 % of the voxels a 256 px render finds; at 192
//!   px still 2 %), where the triangles give the same shell at any resolution. Triangles no
//!   pixel shows (inside another part, or hidden from every input camera) are left out: nothing
//!   downstream can know them.
//! - **Tracks**: the frame-0 render gives, for every input pixel, the triangle and the
//!   perspective-correct barycentrics of the surface point it shows, which is exactly the
//!   back-projected pixel: tracks are drawn from those pixels, so each lies on the frame-0
//!   surface at a back-projected pixel. The same triangle and barycentrics give its position
//!   in every frame. It is visible from an input camera at a frame when it projects into the
//!   image, its triangle is not collapsed (a hidden part) and it is not farther than the
//!   rendered depth there by more than three pixel footprints.
//! - **Video tracks** (the tracking task): the same, drawn from the video camera's frame-0
//!   pixels alone, so each query is a surface point the RGBD video's first frame shows, at a
//!   back-projected pixel of it; visible where the video camera sees it, by the same test.
//!   They come from a random stream of their own: the cloud and the tracks do not change.

use std::path::Path;

use velox_engine::rng::Rng;
use velox_engine::Gpu;

use crate::camera::{input_cameras, supervision_cameras, video_camera, Camera};
use crate::math::{cross, length, sub, V3};
use crate::mesh::AnimatedMesh;
use crate::raster::{Frame, MeshRasteriser, NO_TRIANGLE};
use crate::{DataError, DataResult};

/// Occupancy grid side.
pub const GRID: usize = 64;
/// u64 words of one frame's occupancy bits.
pub const OCCUPANCY_WORDS: usize = GRID * GRID * GRID / 64;
/// Frame times: tau = frame / FPS.
pub const FPS: f32 = 100.0;

/// Most points a scene holds (28 bytes each: 470 MB).
pub const MAX_POINTS: usize = 1 << 24;
/// Most tracks a scene holds (480 bytes each: 500 MB). A scene gets fewer when frame 0 shows
/// fewer surface pixels over the input views: one track per pixel at most.
pub const MAX_TRACKS: usize = 1 << 20;
/// Largest image side.
pub const MAX_RESOLUTION: u32 = 4096;
/// Largest supersampling factor.
pub const MAX_SUPERSAMPLE: u32 = 8;

/// What to make of a scene.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// Image side of every camera.
    pub res: u32,
    /// Points in the 4D point cloud, 1 to [`MAX_POINTS`].
    pub points: usize,
    /// Supersampling factor of the anti-aliased views (supervision and video).
    pub supersample: u32,
    /// Tracked surface points, at most [`MAX_TRACKS`]; fewer when frame 0 shows fewer surface
    /// pixels over the input views.
    pub tracks: usize,
    /// Colour of the background of the supervision views and the video, RGB in [0, 1] (a
    /// black model needs a lighter one); the point cloud has no background.
    pub background: [f32; 3],
}

impl SynthOptions {
    /// Checks the options against the limits above; the error names the option and its limit.
    pub fn check(&self) -> DataResult<()> {
        let limits = [
            ("resolution", self.res as usize, 1, MAX_RESOLUTION as usize),
            ("supersampling factor", self.supersample as usize, 1, MAX_SUPERSAMPLE as usize),
            ("points", self.points, 1, MAX_POINTS),
            ("tracks", self.tracks, 0, MAX_TRACKS),
        ];
        for (name, v, lo, hi) in limits {
            if !(lo..=hi).contains(&v) {
                return Err(DataError::Invalid(format!(
                    "{name} {v} is out of range: a scene takes {lo} to {hi}"
                )));
            }
        }
        if self.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return Err(DataError::Invalid(format!(
                "background {:?}: each channel must lie in [0, 1]",
                self.background
            )));
        }
        Ok(())
    }
}

impl Default for SynthOptions {
    fn default() -> SynthOptions {
        SynthOptions { res: 128, points: 200_000, supersample: 2, tracks: 1024, background: [0.0; 3] }
    }
}

/// Everything of a scene but its images (which go straight to disk).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SceneArrays {
    /// (x, y, z, r, g, b, tau) per point.
    pub points: Vec<[f32; 7]>,
    /// Per frame, [`OCCUPANCY_WORDS`] words; bit `x + 64 (y + 64 z)`.
    pub occupancy: Vec<u64>,
    /// Track positions, track-major then frame.
    pub tracks: Vec<[V3; crate::procedural::FRAMES]>,
    /// Per track and frame, a bit per input camera: set where the point is visible.
    pub visibility: Vec<[u64; crate::procedural::FRAMES]>,
    /// The frame-0 triangle and barycentrics (b1, b2) of each track.
    pub anchors: Vec<(u32, [f32; 2])>,
    /// The tracking task's queries: surface points at pixels of the video camera's frame 0
    /// (drawn like the tracks, from that one camera), in every frame.
    pub video_tracks: Vec<[V3; crate::procedural::FRAMES]>,
    /// Per video track and frame: whether the video camera sees it (depth test as for tracks).
    pub video_visibility: Vec<[bool; crate::procedural::FRAMES]>,
    pub input_cameras: Vec<Camera>,
    pub supervision_cameras: Vec<Camera>,
    pub video_camera: Option<Camera>,
}

/// Back-projects every pixel of `frame` that shows the surface: (world point, rgb, view).
pub fn back_project(frame: &Frame, cameras: &[Camera]) -> Vec<(V3, [f32; 3], usize)> {
    let mut out = Vec::new();
    let px = frame.pixels();
    for (v, cam) in cameras.iter().enumerate() {
        for i in 0..px {
            let k = v * px + i;
            if frame.ids[k] == NO_TRIANGLE {
                continue;
            }
            let (x, y) = ((i as u32 % frame.width) as f32 + 0.5, (i as u32 / frame.width) as f32 + 0.5);
            let c = frame.rgb[k];
            let rgb = [c & 255, (c >> 8) & 255, (c >> 16) & 255].map(|b| b as f32 / 255.0);
            out.push((cam.unproject(x, y, frame.depth[k]), rgb, v));
        }
    }
    out
}

/// Index of the 64^3 voxel of [-1, 1]^3 holding `p`.
pub fn voxel_index(p: V3) -> usize {
    let c = p.map(|x| (((x + 1.0) * 0.5 * GRID as f32) as isize).clamp(0, GRID as isize - 1) as usize);
    c[0] + GRID * (c[1] + GRID * c[2])
}

/// Sets in `occ` (one frame's words) every voxel that triangle `tri` (world points) passes
/// through or touches: the exact triangle-box overlap (the separating-axis test of the box's
/// three normals, the triangle's normal and the nine cross products of their edges), in f64.
/// A triangle collapsed to a line or a point (a hidden part) sets nothing.
pub fn mark_triangle(occ: &mut [u64], tri: [V3; 3]) {
    // Voxel units: voxel i spans [i, i + 1) on each axis.
    let p = tri.map(|v| v.map(|x| (x as f64 + 1.0) * 0.5 * GRID as f64));
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let edges = [sub(p[1], p[0]), sub(p[2], p[1]), sub(p[0], p[2])];
    let normal = cross(edges[0], edges[1]);
    if normal == [0.0; 3] {
        return;
    }
    let unit = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let axes: [[f64; 3]; 10] =
        std::array::from_fn(|i| if i == 0 { normal } else { cross(unit[(i - 1) % 3], edges[(i - 1) / 3]) });
    let mut range = [(0usize, 0usize); 3];
    for (k, r) in range.iter_mut().enumerate() {
        let lo = p.iter().map(|v| v[k]).fold(f64::INFINITY, f64::min).floor();
        let hi = p.iter().map(|v| v[k]).fold(f64::NEG_INFINITY, f64::max).floor();
        if hi < 0.0 || lo >= GRID as f64 {
            return;
        }
        *r = (lo.max(0.0) as usize, hi.min(GRID as f64 - 1.0) as usize);
    }
    for z in range[2].0..=range[2].1 {
        for y in range[1].0..=range[1].1 {
            for x in range[0].0..=range[0].1 {
                let c = [x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5];
                let v = p.map(|q| sub(q, c));
                // Within the bounds, the box's own normals cannot separate; the other axes can.
                let apart = axes.iter().any(|&a| {
                    let d = v.map(|q| dot(a, q));
                    let r = 0.5 * (a[0].abs() + a[1].abs() + a[2].abs());
                    d.iter().copied().fold(f64::INFINITY, f64::min) > r
                        || d.iter().copied().fold(f64::NEG_INFINITY, f64::max) < -r
                });
                if !apart {
                    let i = x + GRID * (y + GRID * z);
                    occ[i / 64] |= 1 << (i % 64);
                }
            }
        }
    }
}

/// Draws `k` of a stream uniformly at random, whatever its length (reservoir sampling).
pub(crate) struct Reservoir<T> {
    pub(crate) k: usize,
    pub(crate) seen: u64,
    pub(crate) items: Vec<T>,
}

impl<T: Clone> Reservoir<T> {
    pub(crate) fn offer(&mut self, rng: &mut Rng, item: T) {
        self.seen += 1;
        if self.items.len() < self.k {
            self.items.push(item);
        } else {
            let j = ((rng.next_u32() as u64) << 32 | rng.next_u32() as u64) % self.seen;
            if (j as usize) < self.k {
                self.items[j as usize] = item;
            }
        }
    }
}

/// Renders a scene. `seed` draws the supervision and video cameras, the point sample and the
/// tracks. When `dir` is given, the supervision views (`supervision/fFF_vVV.png`) and the
/// conditioning video (`video/fFF.png`, with its depth `video/fFF_depth.exr`) are written
/// there as they are rendered; `progress` is called after each frame.
pub fn render_scene(
    gpu: &Gpu,
    mesh: &AnimatedMesh,
    opts: &SynthOptions,
    seed: u64,
    dir: Option<&Path>,
    progress: &mut dyn FnMut(usize),
) -> DataResult<SceneArrays> {
    let frames = mesh.frames.len();
    if frames != crate::procedural::FRAMES {
        return Err(DataError::Invalid(format!(
            "a scene has {} frames, the data needs {}",
            frames,
            crate::procedural::FRAMES
        )));
    }
    opts.check()?;
    let mut rast = MeshRasteriser::new(gpu, mesh)?;
    rast.shading.background = opts.background;
    let mut rng = Rng::new(seed ^ 0x9e37_79b9_7f4a_7c15);
    let inputs = input_cameras(opts.res);
    let sup = supervision_cameras(&mut rng, opts.res);
    let video = video_camera(&mut rng, opts.res);
    if let Some(dir) = dir {
        for sub in ["supervision", "video"] {
            std::fs::create_dir_all(dir.join(sub))
                .map_err(|e| DataError::Io(format!("{}: {e}", dir.join(sub).display())))?;
        }
    }
    let mut reservoir = Reservoir { k: opts.points, seen: 0, items: Vec::new() };
    // Its own stream, so the video's queries leave the cloud and the tracks as they were.
    let mut video_rng = Rng::new(seed ^ 0x5851_f42d_4c95_7f2d);
    let mut video_anchors = Vec::new();
    let mut out = SceneArrays {
        occupancy: vec![0u64; frames * OCCUPANCY_WORDS],
        input_cameras: inputs.clone(),
        supervision_cameras: sup.clone(),
        video_camera: Some(video),
        ..Default::default()
    };
    for f in 0..frames {
        let verts = &mesh.frames[f];
        let frame = rast.render(verts, &inputs)?;
        let tau = f as f32 / FPS;
        let occ = &mut out.occupancy[f * OCCUPANCY_WORDS..(f + 1) * OCCUPANCY_WORDS];
        for (p, rgb, _) in back_project(&frame, &inputs) {
            let v = voxel_index(p);
            occ[v / 64] |= 1 << (v % 64);
            reservoir.offer(&mut rng, [p[0], p[1], p[2], rgb[0], rgb[1], rgb[2], tau]);
        }
        let mut seen = vec![false; mesh.triangles.len()];
        for &id in frame.ids.iter().filter(|&&id| id != NO_TRIANGLE) {
            seen[id as usize] = true;
        }
        for (tri, _) in mesh.triangles.iter().zip(&seen).filter(|(_, &s)| s) {
            mark_triangle(occ, tri.map(|i| verts[i as usize]));
        }
        if f == 0 {
            out.anchors = pick_anchors(&frame, opts.tracks, &mut rng);
            out.tracks = vec![[[0.0; 3]; crate::procedural::FRAMES]; out.anchors.len()];
            out.visibility = vec![[0; crate::procedural::FRAMES]; out.anchors.len()];
        }
        for (t, &(tri, b)) in out.anchors.iter().enumerate() {
            let p = mesh.surface_point(f, tri, b);
            out.tracks[t][f] = p;
            out.visibility[t][f] = visibility(mesh, f, tri, p, &frame, &inputs);
        }
        let seen_by_video = rast.render(verts, std::slice::from_ref(&video))?;
        if f == 0 {
            video_anchors = pick_anchors(&seen_by_video, opts.tracks, &mut video_rng);
            out.video_tracks = vec![[[0.0; 3]; crate::procedural::FRAMES]; video_anchors.len()];
            out.video_visibility = vec![[false; crate::procedural::FRAMES]; video_anchors.len()];
        }
        for (t, &(tri, b)) in video_anchors.iter().enumerate() {
            let p = mesh.surface_point(f, tri, b);
            out.video_tracks[t][f] = p;
            out.video_visibility[t][f] =
                visibility(mesh, f, tri, p, &seen_by_video, std::slice::from_ref(&video)) & 1 == 1;
        }

        if let Some(dir) = dir {
            let images = rast.render_rgb_supersampled(verts, &sup, opts.supersample)?;
            for (v, img) in images.iter().enumerate() {
                save_png(&dir.join(format!("supervision/f{f:02}_v{v:02}.png")), opts.res, img)?;
            }
            let img = rast.render_rgb_supersampled(verts, std::slice::from_ref(&video), opts.supersample)?;
            save_png(&dir.join(format!("video/f{f:02}.png")), opts.res, &img[0])?;
            let depth = dir.join(format!("video/f{f:02}_depth.exr"));
            velox_io::image::write_exr_depth(&depth, &seen_by_video.depth, opts.res, opts.res)
                .map_err(|e| DataError::Io(format!("{}: {e}", depth.display())))?;
        }
        progress(f);
    }
    if reservoir.items.is_empty() {
        return Err(DataError::Invalid("no input camera sees the object in any frame".into()));
    }
    out.points = fill_in_frame_order(reservoir.items, opts.points, &mut rng);
    Ok(out)
}

/// A cloud drawn from candidates (not empty) grown to `n` points by repeating random ones,
/// then ordered by frame time (a stable sort: the draw's order within a frame stays).
pub(crate) fn fill_in_frame_order(mut points: Vec<[f32; 7]>, n: usize, rng: &mut Rng) -> Vec<[f32; 7]> {
    let have = points.len();
    while points.len() < n {
        let p = points[rng.below(have as u32) as usize];
        points.push(p);
    }
    points.sort_by(|a, b| a[6].total_cmp(&b[6]));
    points
}

/// Up to `n` distinct surface pixels of frame 0, drawn at random over all input views.
fn pick_anchors(frame: &Frame, n: usize, rng: &mut Rng) -> Vec<(u32, [f32; 2])> {
    let mut hits: Vec<usize> = (0..frame.ids.len()).filter(|&k| frame.ids[k] != NO_TRIANGLE).collect();
    let n = n.min(hits.len());
    // Partial Fisher-Yates: the first n entries become a uniform sample.
    for i in 0..n {
        let j = i + rng.below((hits.len() - i) as u32) as usize;
        hits.swap(i, j);
    }
    hits[..n].iter().map(|&k| (frame.ids[k], frame.bary[k])).collect()
}

/// Visibility bits of surface point `p` (on triangle `tri`) at frame `f` over the cameras.
fn visibility(mesh: &AnimatedMesh, f: usize, tri: u32, p: V3, frame: &Frame, cams: &[Camera]) -> u64 {
    let t = mesh.triangles[tri as usize].map(|i| mesh.frames[f][i as usize]);
    if length(cross(sub(t[1], t[0]), sub(t[2], t[0]))) == 0.0 {
        return 0;
    }
    let px = frame.pixels();
    let mut bits = 0u64;
    for (c, cam) in cams.iter().enumerate() {
        if cam.sees(p, &frame.depth[c * px..(c + 1) * px]) {
            bits |= 1 << c;
        }
    }
    bits
}

/// Encodes in memory, then writes with one checked write (an encoder writing to the file
/// itself drops its buffer's last flush, and with it a full disk's error).
pub(crate) fn save_png(path: &Path, res: u32, rgb: &[u8]) -> DataResult<()> {
    crate::format::write_file(path, &velox_io::image::png_bytes(rgb, res, res)?)
}
