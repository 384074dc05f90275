//! The forward pass: project, list the tiles each Gaussian touches, sort, find each tile's
//! range, blend. Kernels: `shaders/raster_project.wgsl`, `raster_tiles.wgsl`,
//! `raster_blend.wgsl`.
//!
//! It runs in two recordings: [`project`] (projection, tile counts and their exclusive scan),
//! then, once the number of (tile, Gaussian) pairs is known on the host, [`rasterize`] (key
//! emission into buffers of exactly that size, sort, ranges, blend). [`render`] does both.
//! Where the pairs can be bounded ahead (a training step, from the steps before it),
//! [`rasterize_within`] records the second part into the first's recording, into lists with
//! room for that many pairs: one submission, the count checked once it has run.

use super::{
    Camera, Gaussians, ALPHA_MAX, DILATION, MAX_TILES_PER_GAUSSIAN, MIN_ALPHA, MIN_DET, NEAR, T_STOP,
};
use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{
    RASTER_BLEND_BLEND, RASTER_PROJECT_PROJECT, RASTER_TILES_COUNTS_IN_DEPTH_ORDER, RASTER_TILES_DEPTHS,
    RASTER_TILES_EMIT, RASTER_TILES_RANGES_OF_TILES,
};
use crate::ops::fill::fill_bits;
use crate::ops::scan::exclusive_scan;
use crate::ops::sort::{sort_indices, sort_pairs};
use crate::recorder::Recorder;
use crate::tensor::{DType, Readback, Tensor};
use crate::Gpu;
use crate::Limit;

pub(crate) use crate::kernels::params::RasterProjectParams as ProjectParams;

impl ProjectParams {
    pub(crate) fn new(cam: &Camera, n: usize) -> ProjectParams {
        let r = cam.rotation;
        let t = cam.translation;
        let (tiles_x, tiles_y) = cam.tiles();
        ProjectParams {
            rot0: [r[0][0], r[0][1], r[0][2], t[0]],
            rot1: [r[1][0], r[1][1], r[1][2], t[1]],
            rot2: [r[2][0], r[2][1], r[2][2], t[2]],
            intr: [cam.fx, cam.fy, cam.cx, cam.cy],
            width: cam.width,
            height: cam.height,
            tiles_x,
            tiles_y,
            n: n as u32,
            near: NEAR,
            min_alpha: MIN_ALPHA,
            max_tiles: MAX_TILES_PER_GAUSSIAN,
            dilation: DILATION,
            min_det: MIN_DET,
            pad0: 0,
            pad1: 0,
        }
    }
}

pub(crate) use crate::kernels::params::RasterBlendParams as BlendParams;

impl BlendParams {
    /// The backward kernels' parameters: the Gaussians rendered and the slots the tile lists
    /// hold room for.
    pub(crate) fn for_backward(self, gaussians: u32, pairs: u32) -> BlendParams {
        BlendParams { gaussians, pairs, ..self }
    }

    pub(crate) fn new(cam: &Camera, background: [f32; 3]) -> BlendParams {
        BlendParams {
            background: [background[0], background[1], background[2], 0.0],
            width: cam.width,
            height: cam.height,
            tiles_x: cam.tiles().0,
            gaussians: 0,
            alpha_max: ALPHA_MAX,
            min_alpha: MIN_ALPHA,
            t_stop: T_STOP,
            pairs: 0,
        }
    }
}

use crate::kernels::params::RasterTilesParams as TileParams;

/// What [`project`] records: per-Gaussian screen-space data, tile counts and rectangles,
/// their exclusive scan, and the culling counters.
#[derive(Clone, Debug)]
pub struct Projected {
    pub n: usize,
    pub camera: Camera,
    /// `[N, 12]`: (u, v, depth, opacity), (conic a, b, c, 0), (r, g, b, 0).
    pub proj: Tensor,
    /// `[N]` tiles touched (0 for a dropped Gaussian).
    pub counts: Tensor,
    rects: Tensor,
    offsets: Tensor,
    /// `[8]` u32: drawn, invalid, behind, faint, outside, too many tiles.
    pub stats: Tensor,
    /// `[1]` u32: the (tile, Gaussian) pairs, on the device.
    pairs: Tensor,
    /// The same, read back with the projection's recording (no copy and wait of its own where
    /// the host does not map device memory).
    total: Readback,
}

/// How many Gaussians were drawn and why the others were dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderStats {
    pub drawn: u32,
    /// NaN or Inf anywhere, zero quaternion, or a degenerate projection.
    pub invalid: u32,
    pub behind_near_plane: u32,
    pub too_faint: u32,
    pub outside_image: u32,
    pub too_many_tiles: u32,
    /// (tile, Gaussian) pairs sorted and blended.
    pub intersections: u64,
}

impl Projected {
    /// `[N]` u32: each Gaussian's first slot in the tile lists (the exclusive scan of the
    /// counts).
    pub(crate) fn offsets(&self) -> &Tensor {
        &self.offsets
    }

    /// `[1]` u32: the number of (tile, Gaussian) pairs, on the device (what
    /// [`veto_if_over`](crate::ops::norm::veto_if_over) compares with the room
    /// [`rasterize_within`] was given).
    pub fn pairs(&self) -> &Tensor {
        &self.pairs
    }

    /// The number of (tile, Gaussian) pairs; valid once the recording of [`project`] has been
    /// submitted.
    pub fn intersections(&self) -> Result<usize> {
        Ok(self.total.read::<u32>()?[0] as usize)
    }

    /// The culling counters; valid once the recording of [`project`] has been submitted.
    pub fn stats(&self) -> Result<RenderStats> {
        let s: Vec<u32> = self.stats.read()?;
        Ok(RenderStats {
            drawn: s[0],
            invalid: s[1],
            behind_near_plane: s[2],
            too_faint: s[3],
            outside_image: s[4],
            too_many_tiles: s[5],
            intersections: self.intersections()? as u64,
        })
    }
}

/// Records the projection of every Gaussian, its tile count and the exclusive scan of the
/// counts. Submit, then read [`Projected::intersections`] and call [`rasterize`].
pub fn project(rec: &mut Recorder, g: &Gaussians, cam: &Camera) -> Result<Projected> {
    let n = g.check()?;
    cam.check()?;
    let gpu = rec.gpu().clone();
    let proj = Tensor::empty(&gpu, &[n, 12], DType::F32)?;
    let counts = Tensor::empty(&gpu, &[n], DType::U32)?;
    let rects = Tensor::empty(&gpu, &[n, 2], DType::U32)?;
    let offsets = Tensor::empty(&gpu, &[n], DType::U32)?;
    let stats = Tensor::empty(&gpu, &[8], DType::U32)?;
    fill_bits(rec, &stats, 0)?;
    let p = ProjectParams::new(cam, n);
    rec.dispatch_linear(
        RASTER_PROJECT_PROJECT,
        (n as u64).div_ceil(256),
        args::RasterProjectProjectArgs {
            means: &g.means,
            log_scales: &g.log_scales,
            quats: &g.quats,
            opacities: &g.opacities,
            colours: &g.colours,
            proj: &proj,
            counts: &counts,
            rects: &rects,
            stats: &stats,
        },
        &p,
    )?;
    let pairs = exclusive_scan(rec, &counts, &offsets)?;
    let total = rec.read_back(&pairs)?;
    Ok(Projected { n, camera: *cam, proj, counts, rects, offsets, stats, pairs, total })
}

/// The forward pass's outputs, and what the backward pass needs.
#[derive(Clone, Debug)]
pub struct Image {
    /// `[H, W, 3]`.
    pub rgb: Tensor,
    /// `[H, W]`: 1 - final transmittance.
    pub alpha: Tensor,
    /// `[H, W]`: sum of depth x blending weight.
    pub depth: Tensor,
    /// `[H, W]` final transmittance.
    pub final_t: Tensor,
    /// `[H, W]` u32: tile entries up to the pixel's last blended Gaussian.
    pub last: Tensor,
    /// `[tiles, 2]` u32: each tile's range of sorted pairs.
    pub ranges: Tensor,
    /// `[pairs]` u32: Gaussian index of each sorted pair.
    pub ids: Tensor,
    /// `[pairs]` u32: slot of each sorted pair, where Gaussian g's pairs hold slots
    /// `offsets[g]..offsets[g] + counts[g]` (the backward pass sums its gradients by slot).
    pub slots: Tensor,
    pub background: [f32; 3],
    /// The pairs the tile lists hold room for: the number of pairs where [`rasterize`] sized
    /// them, the room given to [`rasterize_within`] (its last entries unused).
    pub room: usize,
}

/// Records key emission, the sort, the tile ranges and the blending. The recording of
/// [`project`] must have been submitted: the number of (tile, Gaussian) pairs it counted sizes
/// the buffers here.
pub fn rasterize(rec: &mut Recorder, p: &Projected, background: [f32; 3]) -> Result<Image> {
    let pairs = p.intersections()?;
    rasterize_lists(rec, p, Room::Exact(pairs), background)
}

/// [`rasterize`] into tile lists with room for `room` pairs, recorded without the number of
/// pairs on the host: into the recording of [`project`] itself, or any after it. The pairs
/// past the room are dropped (never written out of bounds), so the image is only right where
/// [`Projected::intersections`], read once the recording has run, is at most `room`; a step
/// that records an update after this vetoes it on the device otherwise
/// ([`veto_if_over`](crate::ops::norm::veto_if_over) with [`Projected::pairs`]). Within the
/// room the result has the bits of [`rasterize`]'s: the unused entries sort last, behind
/// every tile.
pub fn rasterize_within(
    rec: &mut Recorder,
    p: &Projected,
    room: usize,
    background: [f32; 3],
) -> Result<Image> {
    rasterize_lists(rec, p, Room::Ahead(room), background)
}

/// How the tile lists are sized.
#[derive(Clone, Copy)]
enum Room {
    /// To the number of pairs, read on the host.
    Exact(usize),
    /// Ahead of the count: the entries past the pairs keep a key past every tile.
    Ahead(usize),
}

impl Room {
    /// The entries the lists hold.
    fn pairs(self) -> usize {
        let (Room::Exact(pairs) | Room::Ahead(pairs)) = self;
        pairs
    }
}

fn rasterize_lists(rec: &mut Recorder, p: &Projected, room: Room, background: [f32; 3]) -> Result<Image> {
    let pairs = room.pairs();
    let gpu = rec.gpu().clone();
    let cam = &p.camera;
    let max_pairs = gpu.caps().max_storage_buffer_range / 4;
    if pairs as u64 > max_pairs.min(u32::MAX as u64) {
        return Err(Error::too_large(
            Limit::Binding,
            format!(
                "{pairs} (tile, Gaussian) pairs: this device sorts at most {max_pairs} in one buffer; \
                 render at a lower resolution or with fewer or smaller Gaussians"
            ),
        ));
    }
    let (tiles_x, tiles_y) = cam.tiles();
    let tiles = (tiles_x * tiles_y) as usize;
    let (h, w) = (cam.height as usize, cam.width as usize);
    let ranges = Tensor::empty(&gpu, &[tiles, 2], DType::U32)?;
    fill_bits(rec, &ranges, 0)?;
    let (ids, slots) = if pairs > 0 {
        tile_lists(rec, p, room, &ranges)?
    } else {
        (Tensor::empty(&gpu, &[0], DType::U32)?, Tensor::empty(&gpu, &[0], DType::U32)?)
    };
    let image = Image {
        rgb: Tensor::empty(&gpu, &[h, w, 3], DType::F32)?,
        alpha: Tensor::empty(&gpu, &[h, w], DType::F32)?,
        depth: Tensor::empty(&gpu, &[h, w], DType::F32)?,
        final_t: Tensor::empty(&gpu, &[h, w], DType::F32)?,
        last: Tensor::empty(&gpu, &[h, w], DType::U32)?,
        ranges,
        ids,
        slots,
        background,
        room: pairs,
    };
    rec.dispatch(
        RASTER_BLEND_BLEND,
        [tiles_x, tiles_y, 1],
        args::RasterBlendBlendArgs {
            ranges: &image.ranges,
            ids: &image.ids,
            proj: &p.proj,
            rgb: &image.rgb,
            alpha_out: &image.alpha,
            depth_out: &image.depth,
            final_t: &image.final_t,
            last_out: &image.last,
        },
        &BlendParams::new(cam, background),
    )?;
    Ok(image)
}

/// Records the tile lists of [`rasterize`] (see `shaders/raster_tiles.wgsl`): the pairs in
/// blending order, by tile and then by the full 32-bit depth (a stable sort of the Gaussians
/// on the depth, their pairs emitted in that order, then a stable sort of the pairs on the
/// tile), with each tile's range filled into `ranges`. Returns the Gaussian and the slot of
/// every sorted pair. With room ahead of the count, the tile keys start as a key past every
/// tile, which the stable sort keeps last and the ranges skip.
fn tile_lists(rec: &mut Recorder, p: &Projected, room: Room, ranges: &Tensor) -> Result<(Tensor, Tensor)> {
    let pairs = room.pairs();
    let gpu = rec.gpu().clone();
    let (tiles_x, tiles_y) = p.camera.tiles();
    let n = p.n;
    let per_gaussian = || Tensor::empty(&gpu, &[n], DType::U32);
    let per_pair = || Tensor::empty(&gpu, &[pairs], DType::U32);
    let tp = TileParams { n: n as u32, tiles_x, limit: pairs as u32, pad: 0 };
    let gaussian_groups = (n as u64).div_ceil(256);
    let depth_keys = per_gaussian()?;
    rec.dispatch_linear(
        RASTER_TILES_DEPTHS,
        gaussian_groups,
        args::RasterTilesDepthsArgs { counts: &p.counts, proj: &p.proj, depth_keys: &depth_keys },
        &tp,
    )?;
    let (_, order) = sort_indices(rec, &depth_keys, 32)?;
    let (ordered_counts, ordered_offsets) = (per_gaussian()?, per_gaussian()?);
    rec.dispatch_linear(
        RASTER_TILES_COUNTS_IN_DEPTH_ORDER,
        gaussian_groups,
        args::RasterTilesCountsInDepthOrderArgs {
            counts: &p.counts,
            order: &order,
            ordered_counts: &ordered_counts,
        },
        &tp,
    )?;
    exclusive_scan(rec, &ordered_counts, &ordered_offsets)?;
    let (tile_keys, pair_slots, slot_gaussians) = (per_pair()?, per_pair()?, per_pair()?);
    if let Room::Ahead(_) = room {
        // The unused entries follow every pair, and the sort is stable: with all their key
        // bits set they stay behind the last tile's pairs, which the ranges then skip.
        fill_bits(rec, &tile_keys, u32::MAX)?;
    }
    rec.dispatch_linear(
        RASTER_TILES_EMIT,
        gaussian_groups,
        args::RasterTilesEmitArgs {
            counts: &p.counts,
            offsets: &p.offsets,
            rects: &p.rects,
            order: &order,
            ordered_offsets: &ordered_offsets,
            tile_keys: &tile_keys,
            pair_slots: &pair_slots,
            slot_gaussians: &slot_gaussians,
        },
        &tp,
    )?;
    let (sorted_tiles, slots) = sort_pairs(rec, &tile_keys, &pair_slots, p.camera.tile_bits())?;
    let ids = per_pair()?;
    let tp = TileParams { n: pairs as u32, limit: tiles_x * tiles_y, ..tp };
    rec.dispatch_linear(
        RASTER_TILES_RANGES_OF_TILES,
        (pairs as u64).div_ceil(256),
        args::RasterTilesRangesOfTilesArgs {
            slot_gaussians: &slot_gaussians,
            sorted_tiles: &sorted_tiles,
            sorted_slots: &slots,
            ranges,
            ids: &ids,
        },
        &tp,
    )?;
    Ok((ids, slots))
}

/// A finished forward pass.
#[derive(Clone, Debug)]
pub struct Rendered {
    pub projected: Projected,
    pub image: Image,
}

impl Rendered {
    pub fn stats(&self) -> Result<RenderStats> {
        self.projected.stats()
    }
}

/// Renders `g` from `cam` over `background`: [`project`], submit, [`rasterize`], submit.
pub fn render(gpu: &Gpu, g: &Gaussians, cam: &Camera, background: [f32; 3]) -> Result<Rendered> {
    render_view(gpu, g, None, cam, background)
}

/// [`render`], the colours seen along the view from the spherical harmonics `(rest, degree)`
/// where given ([`sh_colours`](super::sh_colours), recorded with the projection), else `g`'s own.
pub fn render_view(
    gpu: &Gpu,
    g: &Gaussians,
    harmonics: Option<(&Tensor, usize)>,
    cam: &Camera,
    background: [f32; 3],
) -> Result<Rendered> {
    let mut rec = gpu.recorder()?;
    let projected = match harmonics {
        Some((rest, degree)) => {
            let colours = super::sh_colours(&mut rec, g, rest, degree, cam.centre())?;
            project(&mut rec, &Gaussians { colours, ..g.clone() }, cam)?
        }
        None => project(&mut rec, g, cam)?,
    };
    rec.submit()?;
    let mut rec = gpu.recorder()?;
    let image = rasterize(&mut rec, &projected, background)?;
    rec.submit()?;
    Ok(Rendered { projected, image })
}
