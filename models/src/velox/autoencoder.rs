//! The Velox autoencoder: encoder E, 4D surface decoder V and Gaussian decoder G over one
//! parameter store, and one training step of L = L_V + L_GS + gamma L_C (docs/models.md).
//!
//! A micro-batch of B scenes ([`Autoencoder::accumulate`]), each with its own generator:
//! 1. E encodes every cloud (or a random `encoder_points` of each) to tokens s, the B clouds
//!    as one batch whose cells and windows stay within their cloud; L_C = gamma mean(s^2) per
//!    scene; the decoders read s + noise (the noise passes gradients through unchanged).
//! 2. Each scene draws `frames_per_sample` frames: V's flow-matching loss on
//!    `points_per_step` points of each (every scene's points in one pass, attending to their
//!    scene's tokens) gives L_V, the mean over the scene's points, and dL_V/ds.
//! 3. G decodes every drawn frame's occupied voxels (from the cloud) to Gaussians, all frames
//!    in one pass; each frame is rendered from `views_per_step` supervision views and compared:
//!    L_GS = the scene's mean over frames, views and pixels of |I_gt - I|^2, whose gradient
//!    flows back through the rasteriser and G into dL_GS/ds.
//! 4. E's backward takes the summed token gradient. The micro-batch adds `weight` times the
//!    gradient of its scenes' summed losses into the store; the trainer (`crate::train`) makes
//!    that the mean over a step's batch, and AdamW updates every parameter (noam schedule,
//!    global-norm clipping); a NaN or Inf gradient stops the step before anything changes.
//!    [`Autoencoder::train_step`] does all of it for one scene.
//!
//! Tests: `tests/models/autoencoder.rs` (the step against finite differences, learning),
//! `tests/models/slips.rs` (token noise, the token loss weight and the encoder's subset reaching
//! what they should), `tests/training/mixed_precision.rs` (f16 against f32, loss scaling, resume)
//! and `tools/tests/train_cli.rs` (the command).

use std::time::Instant;

use velox_engine::ops::adamw::AdamWConfig;
use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, binary_into, Binary};
use velox_engine::ops::fill::fill;
use velox_engine::ops::raster::{
    project, rasterize_within, render_backward, Camera, Gaussians, Projected, Rendered,
    MAX_TILES_PER_GAUSSIAN,
};
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Finished, Gpu, Precision, Recorder, Result, Tensor};

use crate::config::AutoencoderConfig;
use crate::layers::Loss;
use crate::params::{build, declare, ParamBuilder, ParamStore, Params, Update};
use crate::train::{Ahead, Finish, Losses, PassSeconds, PassTimer, Trainable};
use crate::velox::encoder::Encoder;
use crate::velox::gaussians::{occupied_voxels, GaussianDecoder, VoxelFrames};
use crate::velox::surface::{FlowNoise, PointFrames, SampleSpec, Sampler, SurfaceDecoder};
use velox_io::cloud::{self, CHANNELS};

/// The `model` a checkpoint of the autoencoder names.
pub const MODEL_KIND: &str = "velox autoencoder";

/// The clip's frames and frame times (tau = frame / 100), defined in `velox_io::frames`.
pub use velox_io::frames::{frame_of_tau, tau_of, FRAMES};

/// What a training step needs of a scene, on the host and the device.
pub struct TrainScene {
    /// The cloud `[N, 7]` as host rows and on the device.
    pub cloud_host: Vec<f32>,
    pub cloud: Tensor,
    /// xyz of each frame's points.
    pub frame_points: Vec<Vec<f32>>,
    /// Supervision cameras (the same for every frame) and images, frame-major then view,
    /// RGB in [0, 1], `[H, W, 3]` each.
    pub cameras: Vec<Camera>,
    pub images: Vec<Vec<f32>>,
    /// The images' background, RGB: the renders compared with them are drawn on it.
    pub background: [f32; 3],
}

impl TrainScene {
    /// Checks and uploads a scene: the cloud must be valid (see [`cloud::validate`]), there
    /// must be `FRAMES x cameras` images of each camera's size.
    pub fn new(
        gpu: &Gpu,
        cloud_host: Vec<f32>,
        cameras: Vec<Camera>,
        images: Vec<Vec<f32>>,
    ) -> Result<TrainScene> {
        cloud::validate(&cloud_host)?;
        if cameras.is_empty() || images.len() != FRAMES * cameras.len() {
            return Err(Error::Invalid(format!(
                "a training scene needs {FRAMES} x {} supervision images, got {}",
                cameras.len(),
                images.len()
            )));
        }
        for (i, img) in images.iter().enumerate() {
            let c = &cameras[i % cameras.len()];
            if img.len() != (c.width * c.height * 3) as usize {
                return Err(Error::Invalid(format!(
                    "supervision image {i} does not match its camera's size"
                )));
            }
        }
        let mut frame_points = vec![Vec::new(); FRAMES];
        for p in cloud_host.chunks(CHANNELS) {
            let f = (p[6] * 100.0).round() as usize;
            if f >= FRAMES {
                return Err(Error::Invalid(format!(
                    "a point has frame time {} beyond frame {}",
                    p[6],
                    FRAMES - 1
                )));
            }
            frame_points[f].extend_from_slice(&p[..3]);
        }
        let cloud = cloud::upload(gpu, &cloud_host)?;
        Ok(TrainScene { cloud_host, cloud, frame_points, cameras, images, background: [0.0; 3] })
    }

    /// The scene with its images on `background` (black unless set).
    pub fn with_background(mut self, background: [f32; 3]) -> TrainScene {
        self.background = background;
        self
    }

    /// Frames that have points.
    pub fn frames(&self) -> Vec<usize> {
        (0..FRAMES).filter(|&f| !self.frame_points[f].is_empty()).collect()
    }
}

/// The losses of one step (as read back after it ran).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct StepLosses {
    pub total: f64,
    pub surface: f64,
    pub gaussians: f64,
    pub tokens: f64,
    pub grad_norm: f64,
    pub lr: f64,
}

pub struct Autoencoder {
    pub cfg: AutoencoderConfig,
    pub store: ParamStore,
    pub encoder: Encoder,
    pub surface: SurfaceDecoder,
    pub gaussians: GaussianDecoder,
    pub adamw: AdamWConfig,
    /// The precision of encoding and decoding (training passes follow the store's training
    /// precision, which the trainer sets); set it with
    /// [`Autoencoder::set_precision`].
    precision: Precision,
    /// A factor on the scheduled learning rate (a cooldown at the end of a run); 1 by default,
    /// not saved with the model.
    pub lr_scale: f64,
    /// Seconds of the forward passes (encoder, decoders, renders) and of the backward passes
    /// of the micro-batches since [`Trainable::take_pass_seconds`] last took them.
    pass_seconds: PassSeconds,
    /// The (tile, Gaussian) pairs a training view's tile lists hold room for, from the steps
    /// before (0 before the first): with it, a micro-batch is one recording, renders included.
    pair_room: usize,
    /// The most pairs a first step's views may hold in all when their lists are sized by the
    /// bound no count can pass ([`first_room`]); [`FIRST_STEP_PAIRS`] unless a test lowers it.
    first_step_pairs: usize,
    /// The last micro-batch's views outgrew `pair_room`: how ([`Trainable::take_rerun`]).
    rerun: Option<String>,
}

impl Autoencoder {
    /// The three networks: `encoder.*`, `surface.*`, `gaussians.*`.
    fn parts(p: &mut Params, cfg: &AutoencoderConfig) -> Result<(Encoder, SurfaceDecoder, GaussianDecoder)> {
        let d = cfg.encoder.token_dim;
        let encoder = Encoder::new(p, "encoder", &cfg.encoder)?;
        let surface = SurfaceDecoder::new(p, "surface", &cfg.surface, d)?;
        Ok((encoder, surface, GaussianDecoder::new(p, "gaussians", &cfg.gaussians, d)?))
    }

    /// The parameters a config declares, without allocating them.
    pub fn declare(gpu: &Gpu, cfg: &AutoencoderConfig) -> Result<ParamBuilder> {
        cfg.validate()?;
        declare(gpu, |p| Self::parts(p, cfg))
    }

    /// A freshly initialised autoencoder (parameters from `seed`).
    pub fn new(gpu: &Gpu, cfg: &AutoencoderConfig, seed: u64) -> Result<Autoencoder> {
        cfg.validate()?;
        let ((encoder, surface, gaussians), store) = build(gpu, seed, |p| Self::parts(p, cfg))?;
        Ok(Autoencoder {
            cfg: cfg.clone(),
            store,
            encoder,
            surface,
            gaussians,
            adamw: AdamWConfig::default(),
            precision: Precision::F32,
            lr_scale: 1.0,
            pass_seconds: PassSeconds::default(),
            pair_room: 0,
            first_step_pairs: FIRST_STEP_PAIRS,
            rerun: None,
        })
    }

    /// The (tile, Gaussian) pairs each training view's tile lists hold room for (0 before the
    /// first step, which sizes them by a bound or by its own counts, see [`first_room`]).
    pub fn pair_room(&self) -> usize {
        self.pair_room
    }

    /// Lowers the pairs a first step may hold by the bound (for the tests of the sizing
    /// submission that larger configs take).
    #[doc(hidden)]
    pub fn set_first_step_pairs(&mut self, pairs: usize) {
        self.first_step_pairs = pairs;
    }

    /// Sets that room (grown again by any step that outgrows it, which then runs again; the
    /// room changes no result, only memory and the work of the sort).
    pub fn set_pair_room(&mut self, pairs: usize) {
        self.pair_room = pairs;
    }

    /// Makes `encode`, `decode_points` and `decode_gaussians` run in `precision`. Choosing f16
    /// rounds the current parameters to the store's f16 copies; choose it again after the
    /// parameters change.
    pub fn set_precision(&mut self, precision: Precision) -> Result<()> {
        if precision == Precision::F16 {
            let mut rec = self.store.flat_params().gpu().recorder()?;
            self.store.sync_half(&mut rec)?;
            rec.submit()?;
        }
        self.precision = precision;
        Ok(())
    }

    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Tokens of a cloud (no noise), with the queries drawn from `seed`.
    pub fn encode(&self, cloud: &Tensor, seed: u64) -> Result<Tensor> {
        Ok(self.encode_with_queries(cloud, seed)?.0)
    }

    /// Tokens of a cloud as [`Autoencoder::encode`] gives them, and the cloud's row of each
    /// token's query (u32 `[k]`, the encoder layout's `queries`): token i belongs to point
    /// `queries[i]` of the cloud.
    pub fn encode_with_queries(&self, cloud: &Tensor, seed: u64) -> Result<(Tensor, Tensor)> {
        let gpu = cloud.gpu();
        let mut rec = gpu.recorder()?;
        rec.set_precision(self.precision);
        let (s, cache) = self.encoder.forward(&mut rec, cloud, &mut Rng::new(seed))?;
        rec.submit()?;
        Ok((s, cache.layout.queries))
    }

    /// Surface points `[n, 3]` at frame `tau`, sampled by the flow (in the autoencoder's
    /// precision, whatever `spec` says).
    pub fn decode_points(&self, tokens: &Tensor, tau: f32, spec: &SampleSpec) -> Result<Tensor> {
        self.surface.sample(tokens, tau, &SampleSpec { precision: self.precision, ..*spec })
    }

    /// Gaussians at frame `tau` over the occupied voxels `centres` (host, `[V * 3]`).
    pub fn decode_gaussians(&self, tokens: &Tensor, centres: &[f32], tau: f32) -> Result<Gaussians> {
        if centres.is_empty() {
            return Err(Error::Invalid(format!("no occupied voxels at frame time {tau}: nothing to decode")));
        }
        let gpu = tokens.gpu();
        let c = Tensor::from_slice(gpu, &[centres.len() / 3, 3], centres)?;
        let mut rec = gpu.recorder()?;
        rec.set_precision(self.precision);
        let (out, _) = self.gaussians.forward(&mut rec, tokens, &c, tau)?;
        rec.submit()?;
        Ok(out)
    }

    /// Occupied voxel centres of a frame from points (the ground truth in training; surface
    /// samples at inference).
    pub fn voxels_from_points(&self, xyz: &[f32], tau: f32) -> Vec<f32> {
        let cloud: Vec<f32> = xyz.chunks(3).flat_map(|p| [p[0], p[1], p[2], 0.0, 0.0, 0.0, tau]).collect();
        occupied_voxels(&cloud, tau, self.cfg.gaussians.grid)
    }

    /// One optimiser step on one scene (a batch of one, outside the trainer): zero the
    /// gradients, [`Autoencoder::accumulate`], AdamW. `step` counts from 1. The passes run in
    /// the store's training precision, without the trainer's loss scaling.
    pub fn train_step(&mut self, scene: &TrainScene, step: u64, rng: &mut Rng) -> Result<StepLosses> {
        let opt = self.optimisation();
        let lr = opt.learning_rate(step) * self.lr_scale;
        // The gradients zeroed and the update recorded by the step's one recording, as the
        // trainer has them: one submission a step (see `accumulate` for a first step's).
        let drawn = rng.clone();
        let (losses, grad_norm) = loop {
            self.store.zero_grads_first();
            self.store.update_last(Update {
                adamw: opt.adamw,
                lr,
                max_norm: opt.max_grad_norm,
                loss_scale: 1.0,
                // The f16 passes read the copies: refresh them from the updated masters.
                sync_half: self.store.training_precision() == Precision::F16,
            });
            let losses = self.accumulate(&[scene], std::slice::from_mut(rng), 1.0);
            let recorded = self.store.take_update();
            let losses = losses?;
            if !recorded {
                return Err(Error::Invalid("the backward pass did not record the step's update".into()));
            }
            let norm = self.store.grad_norm();
            if self.take_rerun().is_none() {
                break (losses, norm? as f64);
            }
            // The views outgrew the room their tile lists were given; the device vetoed the
            // update. Again with the same draws and the room grown.
            if norm.is_ok() {
                return Err(Error::Invalid("a step whose tile lists overflowed was not vetoed".into()));
            }
            *rng = drawn.clone();
        };
        let term = |name: &str| losses.terms.iter().find(|t| t.0 == name).map_or(0.0, |t| t.1);
        Ok(StepLosses {
            total: losses.total(),
            surface: term("surface"),
            gaussians: term("image"),
            tokens: term("tokens"),
            grad_norm,
            lr,
        })
    }

    /// The forward and backward passes of a micro-batch of scenes (see the module docs),
    /// adding `weight` times the gradient of the sum of their losses into the store's
    /// gradients; `rngs` holds each scene's generator. Returns the loss terms ("total",
    /// "surface", "image", "tokens"), summed over the scenes, times `weight`.
    ///
    /// The scenes go through the networks together: the encoder encodes their clouds as one
    /// batch, the surface decoder takes every scene's points at once and the Gaussian decoder
    /// every scene's voxels, each attending only to its own scene's tokens (attention
    /// segments). A scene's randomness comes from its own generator alone, drawn in the same
    /// order whatever the batch, so a scene adds the same gradient alone or in a batch (to
    /// the summation order of the products over the batch's rows).
    pub fn accumulate(&mut self, scenes: &[&TrainScene], rngs: &mut [Rng], weight: f64) -> Result<Losses> {
        self.record_pass(scenes, rngs, weight)?.run(self)
    }

    /// The recording of [`Autoencoder::accumulate`], not yet submitted, and its finish. A
    /// first step whose views' lists cannot be sized by the bound submits its forward pass
    /// here, to size them by its counts.
    fn record_pass(&mut self, scenes: &[&TrainScene], rngs: &mut [Rng], weight: f64) -> Result<Ahead<Self>> {
        crate::train::check_micro_batch(scenes.len(), rngs.len())?;
        let gpu = scenes[0].cloud.gpu().clone();
        let started = Instant::now();
        let nb = scenes.len();
        let k = self.cfg.encoder.tokens;
        let dim = self.cfg.encoder.token_dim;
        let weight = weight as f32;

        // Each scene's draws, in order: its frames, its first view, the encoder's subset of its
        // cloud (then, in the encoder, its queries).
        let mut plans = Vec::with_capacity(nb);
        let mut inputs = Vec::with_capacity(nb);
        for (scene, rng) in scenes.iter().zip(rngs.iter_mut()) {
            let frames = self.draw_frames(scene, rng)?;
            let view = rng.below(scene.cameras.len() as u32) as usize;
            inputs.push(self.encoder_subset(scene, rng)?);
            plans.push((frames, view));
        }
        let clouds: Vec<&Tensor> =
            inputs.iter().zip(scenes).map(|(sub, scene)| sub.as_ref().unwrap_or(&scene.cloud)).collect();

        // Forward: the encoder and the token loss, then per scene its token noise, then the
        // surface decoder's points and flow noise and the Gaussian decoder's voxels per frame.
        let mut rec = self.store.recorder()?;
        let mut timer = PassTimer::start(&mut rec);
        let (s, enc_cache) = self.encoder.forward_batch(&mut rec, &clouds, rngs)?;
        let zeros = Tensor::empty(&gpu, &[nb * k, dim], DType::F32)?;
        fill(&mut rec, &zeros, 0.0)?;
        // L_C is each scene's mean over its tokens: the mean over the batch times its size.
        let (token_loss, ds) = Loss::mse()
            .weighted(self.cfg.encoder.token_reg * weight * nb as f32)
            .forward_backward(&mut rec, &s, &zeros)?;
        let sigma = self.cfg.encoder.token_noise as f64;
        let noise: Vec<f32> = rngs
            .iter_mut()
            .flat_map(|rng| (0..k * dim).map(|_| (rng.normal() * sigma) as f32).collect::<Vec<_>>())
            .collect();
        let noise = Tensor::from_slice(&gpu, &[nb * k, dim], &noise)?;
        let s_noisy = binary(&mut rec, &s, &noise, Binary::Add)?;

        let p = self.cfg.surface.points_per_step;
        let (mut x, mut eps, mut t, mut taus) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut centres, mut groups) = (Vec::new(), Vec::new());
        let (mut point_counts, mut voxel_counts) = (Vec::with_capacity(nb), Vec::with_capacity(nb));
        for ((scene, rng), (frames, _)) in scenes.iter().zip(rngs.iter_mut()).zip(&plans) {
            let mut voxels = 0;
            for &frame in frames {
                let tau = tau_of(frame);
                let pts = &scene.frame_points[frame];
                for _ in 0..p {
                    let i = rng.below((pts.len() / 3) as u32) as usize;
                    x.extend_from_slice(&pts[3 * i..3 * i + 3]);
                }
                eps.extend(rng.normal_vec(p * 3));
                let t_min = self.cfg.surface.t_min as f64;
                t.extend(rng.uniform_vec(p, t_min, 1.0 - t_min));
                taus.push(tau);
                let c = self.voxels_from_points(pts, tau);
                groups.push((tau, c.len() / 3));
                voxels += c.len() / 3;
                centres.extend(c);
            }
            point_counts.push(frames.len() * p);
            voxel_counts.push(voxels);
        }
        let n = x.len() / 3;
        let x = Tensor::from_slice(&gpu, &[n, 3], &x)?;
        let flow_noise = FlowNoise::from_host(&gpu, &eps, &t)?;
        let token_counts = vec![k; nb];
        let point_frames =
            PointFrames { taus, segments: Segments::from_lengths(&gpu, &point_counts, &token_counts)? };
        let (x_t, u) = SurfaceDecoder::flow_pair(&mut rec, &x, &flow_noise)?;
        let (v, surface_cache) =
            self.surface.forward_frames(&mut rec, &x_t, &point_frames, &flow_noise.t, &s_noisy)?;
        // L_V is each scene's mean over its points (of all its frames).
        let (surface_loss, dv) =
            Loss::mse().weighted(weight).forward_backward_segments(&mut rec, &v, &u, &point_counts)?;
        let nv_total = centres.len() / 3;
        let c = Tensor::from_slice(&gpu, &[nv_total, 3], &centres)?;
        let voxel_frames = VoxelFrames {
            groups: groups.clone(),
            segments: Segments::from_lengths(&gpu, &voxel_counts, &token_counts)?,
        };
        let (gaussians, g_cache) = self.gaussians.forward_frames(&mut rec, &s_noisy, &c, &voxel_frames)?;

        // Each frame seen from `views_per_step` supervision views (spread evenly from the
        // drawn one), projected and rasterised in this recording, into tile lists with room
        // for the most pairs the steps before have seen (and a margin; a first step's, below).
        // A scene's image loss is the mean over its frames and views.
        let per_voxel = self.cfg.gaussians.gaussians_per_voxel;
        let mut frame_gaussians = Vec::with_capacity(groups.len());
        let mut first = 0;
        for &(_, count) in &groups {
            frame_gaussians.push((first * per_voxel, count * per_voxel));
            first += count;
        }
        let mut projected = Vec::new();
        let mut group = 0;
        for (scene, (frames, view)) in scenes.iter().zip(&plans) {
            let cams = scene.cameras.len();
            let nv = self.cfg.views_per_step.clamp(1, cams);
            for &frame in frames {
                let (start, len) = frame_gaussians[group];
                let g = slice_gaussians(&mut rec, &gaussians, start, len)?;
                let mut views = Vec::with_capacity(nv);
                for i in 0..nv {
                    let v = (view + i * cams / nv) % cams;
                    let cam = &scene.cameras[v];
                    let (h, w) = (cam.height as usize, cam.width as usize);
                    let gt = Tensor::from_slice(&gpu, &[h, w, 3], &scene.images[frame * cams + v])?;
                    views.push((project(&mut rec, &g, cam)?, gt, scene.background));
                }
                projected.push((g, views, weight / (frames.len() * nv) as f32));
                group += 1;
            }
        }
        // Without a room from earlier steps (a run's first step): the bound no count can pass
        // where the views' lists so sized stay small, else submit and size the room by this
        // step's counts (the forward and backward times are then the host's clock around each
        // recording). Either way the room after the step is sized by its counts.
        let first_step = self.pair_room == 0;
        let mut forward_done = None;
        let mut room = self.pair_room;
        if first_step {
            let views: Vec<(usize, u32)> = projected
                .iter()
                .flat_map(|(_, views, _)| views.iter().map(|v| (v.0.n, v.0.camera.tiles())))
                .map(|(n, (tx, ty))| (n, tx * ty))
                .collect();
            room = match first_room(&views, self.first_step_pairs) {
                Some(bound) => bound,
                None => {
                    rec.submit()?;
                    let most =
                        most_pairs(projected.iter().flat_map(|(_, views, _)| views.iter().map(|v| &v.0)))?;
                    forward_done = Some(Instant::now());
                    rec = self.store.recorder()?;
                    room_for(most)
                }
            };
        }

        // The views' rasterisation (the forward pass's last step), then backward: image losses
        // and the rasteriser per frame into the Gaussians' gradient, the Gaussian decoder, the
        // surface decoder, then the encoder. A view whose pairs outgrow the room vetoes the
        // step's update on the device (the step then runs again, see below).
        let mut rendered = Vec::with_capacity(projected.len());
        for (g, views, image_weight) in projected {
            let mut images = Vec::with_capacity(views.len());
            for (projected, gt, background) in views {
                let image = rasterize_within(&mut rec, &projected, room, background)?;
                self.store.veto_update_if_over(projected.pairs(), room as u32);
                images.push((Rendered { projected, image }, gt));
            }
            rendered.push((g, images, image_weight));
        }
        timer.backward(&mut rec);
        let image_loss = Tensor::empty(&gpu, &[1], DType::F32)?;
        let mut image_loss_started = false;
        // The alpha and depth gradients are zero: one zero image per size, for every view.
        let mut zeros: Vec<Tensor> = Vec::new();
        let d_gaussians = Gaussians::empty(&gpu, gaussians.len())?;
        for ((g, views, image_weight), &(start, len)) in rendered.iter().zip(&frame_gaussians) {
            let mut d_frame: Option<Gaussians> = None;
            for (r, gt) in views {
                let loss = Loss::mse().weighted(*image_weight);
                let d_rgb =
                    loss.forward_backward_into(&mut rec, &r.image.rgb, gt, &image_loss, image_loss_started)?;
                image_loss_started = true;
                let hw = &gt.shape()[..2];
                let d_zero = match zeros.iter().find(|z| z.shape() == hw) {
                    Some(z) => z.clone(),
                    None => {
                        let z = Tensor::empty(&gpu, hw, DType::F32)?;
                        fill(&mut rec, &z, 0.0)?;
                        zeros.push(z.clone());
                        z
                    }
                };
                let d = render_backward(&mut rec, g, r, &d_rgb, &d_zero, &d_zero)?;
                match &d_frame {
                    None => d_frame = Some(d),
                    Some(acc) => {
                        for (a, b) in acc.fields().into_iter().zip(d.fields()) {
                            binary_into(&mut rec, a, b, a, Binary::Add)?;
                        }
                    }
                }
            }
            let d_frame = d_frame.expect("at least one view");
            for (src, dst) in d_frame.fields().into_iter().zip(d_gaussians.fields()) {
                rec.copy_rows(src, 0, dst, start, len)?;
            }
        }
        // Both decoders add their tokens' gradients into the token loss's.
        self.gaussians.backward_into(&mut rec, &g_cache, &d_gaussians, &ds, true)?;
        self.surface.backward_into(&mut rec, &surface_cache, &dv, &ds, true)?;
        self.encoder.backward(&mut rec, &enc_cache, &ds)?;
        // The three terms side by side, read back with this recording: on a GPU, whose memory
        // the host does not map, a read of its own would be a copy and a wait.
        let terms = Tensor::empty(&gpu, &[3], DType::F32)?;
        for (i, t) in [&surface_loss, &image_loss, &token_loss].into_iter().enumerate() {
            rec.copy_rows(t, 0, &terms, i, 1)?;
        }
        let terms = rec.read_back(&terms)?;
        timer.end(&mut rec);
        // The step's update, where the trainer asked for it with this pass (ParamStore::update_last).
        self.store.record_update(&mut rec)?;
        let projected = rendered
            .into_iter()
            .flat_map(|(_, views, _)| views.into_iter().map(|(r, _)| r.projected))
            .collect();
        let tail = PassTail { started, timer, forward_done, first_step, room, projected, terms };
        let finish: Finish<Self> =
            Box::new(move |model: &mut Self, finished| model.finish_pass(finished, tail));
        Ok(Ahead { rec, finish })
    }

    /// Reads a micro-batch's results once its recording has run (`finished`): its losses, and
    /// whether its views outgrew their room (then it asks for a rerun, and reports no loss).
    fn finish_pass(&mut self, finished: &Finished, tail: PassTail) -> Result<Losses> {
        let PassTail { started, timer, forward_done, first_step, room, projected, terms } = tail;
        match forward_done {
            None => timer.add(finished, &mut self.pass_seconds),
            Some(done) => {
                self.pass_seconds.forward += (done - started).as_secs_f64();
                self.pass_seconds.backward += done.elapsed().as_secs_f64();
                self.pass_seconds.host += finished.host_seconds;
            }
        }
        let most = most_pairs(projected.iter())?;
        if first_step {
            self.pair_room = room_for(most);
        }
        if most > room {
            // Pairs were dropped: the images are wrong and the update (if recorded) vetoed.
            self.pair_room = room_for(most);
            self.rerun = Some(format!(
                "a view's {most} (tile, Gaussian) pairs outgrew the room for {room}; the lists now hold {}",
                self.pair_room
            ));
            return Ok(Losses::default());
        }

        let terms = terms.read::<f32>()?;
        let (surface, image, tokens) = (terms[0] as f64, terms[1] as f64, terms[2] as f64);
        let total = surface + image + tokens;
        if !total.is_finite() {
            return Err(Error::Invalid(format!(
                "the loss became non-finite (surface {surface}, image {image}, tokens {tokens})"
            )));
        }
        Ok(Losses {
            terms: vec![("total", total), ("surface", surface), ("image", image), ("tokens", tokens)],
        })
    }

    /// The frames a sample trains on: `frames_per_sample` distinct frames that have points,
    /// drawn from `rng` (all of them when the scene has fewer).
    fn draw_frames(&self, scene: &TrainScene, rng: &mut Rng) -> Result<Vec<usize>> {
        let mut frames = scene.frames();
        if frames.is_empty() {
            return Err(Error::Invalid("a training scene has no points".into()));
        }
        let f = self.cfg.frames_per_sample.clamp(1, frames.len());
        // Partial Fisher-Yates: the first f of a random permutation.
        for i in 0..f {
            let j = i + rng.below((frames.len() - i) as u32) as usize;
            frames.swap(i, j);
        }
        frames.truncate(f);
        Ok(frames)
    }

    /// The encoder's input of a step when `encoder_points` asks for a subset: that many points
    /// drawn without replacement, in their order in the cloud.
    fn encoder_subset(&self, scene: &TrainScene, rng: &mut Rng) -> Result<Option<Tensor>> {
        let n = scene.cloud_host.len() / CHANNELS;
        let k = self.cfg.encoder_points;
        if k == 0 || k >= n {
            return Ok(None);
        }
        // Partial Fisher-Yates over the indices.
        let mut idx: Vec<u32> = (0..n as u32).collect();
        for i in 0..k {
            let j = i + rng.below((n - i) as u32) as usize;
            idx.swap(i, j);
        }
        let mut pick = idx[..k].to_vec();
        pick.sort_unstable();
        let rows: Vec<f32> = pick
            .iter()
            .flat_map(|&i| scene.cloud_host[i as usize * CHANNELS..][..CHANNELS].iter().copied())
            .collect();
        Ok(Some(Tensor::from_slice(scene.cloud.gpu(), &[k, CHANNELS], &rows)?))
    }

    /// The generator of step `step` of a run seeded with `seed`: a resumed run draws exactly
    /// what an uninterrupted one would.
    pub fn step_rng(seed: u64, step: u64) -> Rng {
        Rng::new(seed ^ step.wrapping_mul(0x9e37_79b9_7f4a_7c15))
    }

    /// Samples surface points with the config's default sampler: Heun, 20 steps.
    pub fn default_sampling(points: usize, seed: u64) -> SampleSpec {
        SampleSpec { points, steps: 20, sampler: Sampler::Heun, seed, precision: Precision::F32 }
    }
}

crate::train::trainable!(Autoencoder, TrainScene;
    fn take_rerun(&mut self) -> Option<String> {
        self.rerun.take()
    }

    // A first step sizes its tile lists by its own counts, which the steps after it read.
    fn records_ahead(&self) -> bool {
        self.pair_room > 0
    }
);

/// What [`Autoencoder::finish_pass`] reads of a recorded micro-batch: its timing, the
/// room its views' tile lists were sized for, their projections (whose pair counts the
/// recording reads back) and its three loss terms.
struct PassTail {
    started: Instant,
    timer: PassTimer,
    /// When a first step's forward pass, submitted alone to size the lists, finished.
    forward_done: Option<Instant>,
    first_step: bool,
    room: usize,
    projected: Vec<Projected>,
    terms: velox_engine::Readback,
}

crate::model::model!(Autoencoder, AutoencoderConfig, "autoencoder");

/// The most (tile, Gaussian) pairs among projections whose recording has run.
fn most_pairs<'a>(projected: impl Iterator<Item = &'a Projected>) -> Result<usize> {
    projected.map(Projected::intersections).try_fold(0, |most, n| Ok(most.max(n?)))
}

/// How many pairs a first step's views may hold in all when their lists are sized by the
/// bound (about 70 MiB of lists, sort and gradients at 17 words a pair): past it, the step
/// submits its projections and sizes the lists by their counts, one host wait more.
pub const FIRST_STEP_PAIRS: usize = 1 << 20;

/// The room for a first step's views, `(Gaussians, tiles of the image)` each, that no count
/// can pass: a Gaussian touches at most every tile (and at most
/// [`MAX_TILES_PER_GAUSSIAN`]), so the most Gaussians times the most tiles any view has, in
/// whole sort blocks; `None` where the views' lists would hold more than `limit` pairs in all.
/// Small images make it small: a 96-pixel view has 36 tiles.
pub fn first_room(views: &[(usize, u32)], limit: usize) -> Option<usize> {
    let most = views
        .iter()
        .map(|&(n, tiles)| n.checked_mul(tiles.min(MAX_TILES_PER_GAUSSIAN) as usize))
        .try_fold(0usize, |most, v| Some(most.max(v?)))?;
    let room = most.max(1).checked_next_multiple_of(velox_engine::ops::sort::BLOCK)?;
    (room.checked_mul(views.len())? <= limit).then_some(room)
}

/// The tile lists' room for views that have needed up to `pairs` pairs: a quarter more, in
/// whole blocks of the sort (4096), so that a step's views rarely outgrow it as training moves
/// the Gaussians; each view's lists are that long.
fn room_for(pairs: usize) -> usize {
    (pairs + pairs / 4 + 1).next_multiple_of(velox_engine::ops::sort::BLOCK)
}

/// Gaussians `start .. start + len` of a set, as a set of their own (the whole set when it is
/// all of it).
fn slice_gaussians(rec: &mut Recorder, g: &Gaussians, start: usize, len: usize) -> Result<Gaussians> {
    if start == 0 && len == g.len() {
        return Ok(g.clone());
    }
    let out = Gaussians::empty(rec.gpu(), len)?;
    for (src, dst) in g.fields().into_iter().zip(out.fields()) {
        rec.copy_rows(src, start, dst, 0, len)?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_first_step_is_sized_by_a_bound_only_where_it_is_small() {
        let block = velox_engine::ops::sort::BLOCK;
        // The most Gaussians times the most tiles, in whole sort blocks, for every view.
        assert_eq!(first_room(&[(1000, 36), (3000, 4)], 1 << 20), Some(36_864));
        assert_eq!(first_room(&[(1000, 36)], 36_864), Some(36_864));
        assert_eq!(first_room(&[(1000, 36), (10, 9)], 36_864), None, "two views of 36864 past the limit");
        // A Gaussian touches at most MAX_TILES_PER_GAUSSIAN tiles, however many the image has.
        let huge = MAX_TILES_PER_GAUSSIAN * 4;
        assert_eq!(first_room(&[(2, huge)], usize::MAX), Some(2 * MAX_TILES_PER_GAUSSIAN as usize));
        // No Gaussians still gets a block; products past usize are refused, not wrapped.
        assert_eq!(first_room(&[(0, 4)], 1 << 20), Some(block));
        assert_eq!(first_room(&[(usize::MAX, 4)], usize::MAX), None);
        assert_eq!(first_room(&[], 0), Some(block), "no views hold nothing");
        // The room after a step: a quarter more than the most pairs seen, in whole blocks.
        assert_eq!(room_for(0), block);
        assert_eq!(room_for(4000), 8192);
        assert_eq!(room_for(10_000), 16_384);
    }
}
