//! The 3D tracking network (docs/models.md, 3D tracking network; paper Sec. 3 and 5): from
//! the tokens of an RGBD video's back-projected cloud and query points on its first frame,
//! each query's position at every frame.
//!
//! The trunk is a [`VoxelPerceiver`] without self-attention: a query's feature is its Fourier
//! embedded position (and frame time 0, the first frame; with `query_colour`, its colour on
//! the first frame beside them), `blocks` blocks of cross-attention to the tokens and SwiGLU
//! feed-forward refine it, and the head gives `3 x 24` numbers: the query's offset at each
//! frame. Queries never see each other, so a prediction is the same
//! whatever other queries run with it, and any number of them run in chunks. The head starts
//! near zero, so an untrained tracker predicts that nothing moves (the static baseline).
//!
//! Visibility is not learned (as in the paper): a predicted point is occluded where the
//! video's camera does not see it in its depth frame (`Camera::sees`, the data's own test).
//!
//! Tests: `tests/models/tracker.rs` (the step against finite differences, learning against the
//! static baseline), `tests/models/slips.rs` (training reads the tokens prediction reads).

use velox_engine::ops::adamw::AdamWConfig;
use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, Binary};
use velox_engine::ops::columns::copy_columns;
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Gpu, Recorder, Result, Tensor};

use crate::config::{TrackLoss, TrackerConfig};
use crate::layers::{Fourier, Loss};
use crate::params::{build, declare, ParamBuilder, ParamStore, Params};
use crate::train::{Ahead, Losses, PassSeconds, PassTimer};
use crate::velox::autoencoder::FRAMES;
use crate::velox::perceiver::{PerceiverShape, VoxelFrames, VoxelPerceiver};
use velox_engine::ops::fourier::fourier_width;

/// The `model` a checkpoint of the tracker names.
pub const MODEL_KIND: &str = "velox tracker";
/// Queries one pass of [`Tracker::predict`] runs at most.
pub const CHUNK: usize = 16384;

/// One track: a point's position at each frame; frame 0 is the query.
pub type Track = [[f32; 3]; FRAMES];

/// What the tracker trains on from one scene: the tokens of its video's cloud and the true
/// tracks of its queries.
pub struct TrackSample {
    /// `[k, token_dim]` on the device (the frozen encoder's, from `velox encode --source video`).
    pub tokens: Tensor,
    /// `[k, 4]`: each token's query point (x, y, z, tau), as the token file stores it.
    pub token_points: Tensor,
    pub tracks: Vec<Track>,
    /// Each track's colour on the first frame (RGB in [0, 1]): its pixel of the video's frame 0.
    pub colours: Vec<[f32; 3]>,
}

impl TrackSample {
    /// Checks the shapes and values: tokens f32 `[k > 0, d > 0]`, at least one track, every
    /// position finite, a colour in [0, 1] per track.
    pub fn new(
        tokens: Tensor,
        token_points: Tensor,
        tracks: Vec<Track>,
        colours: Vec<[f32; 3]>,
    ) -> Result<TrackSample> {
        let ok_tokens = matches!(tokens.shape(), [k, d] if *k > 0 && *d > 0)
            && tokens.dtype() == velox_engine::DType::F32;
        if !ok_tokens {
            return Err(Error::Shape(format!("track sample: tokens must be f32 [k, d], got {tokens:?}")));
        }
        if token_points.shape() != [tokens.shape()[0], 4] || token_points.dtype() != velox_engine::DType::F32
        {
            return Err(Error::Shape(format!(
                "track sample: token points must be f32 [{}, 4], got {token_points:?}",
                tokens.shape()[0]
            )));
        }
        if tracks.is_empty() {
            return Err(Error::Invalid(
                "track sample: the scene has no tracks (made with 0 tracks?): nothing to learn".into(),
            ));
        }
        if let Some(i) = tracks.iter().position(|t| t.iter().flatten().any(|v| !v.is_finite())) {
            return Err(Error::Invalid(format!("track sample: track {i} has a non-finite position")));
        }
        check_colours("track sample", &colours, tracks.len())?;
        Ok(TrackSample { tokens, token_points, tracks, colours })
    }
}

/// Checks one colour per query, each channel in [0, 1].
fn check_colours(what: &str, colours: &[[f32; 3]], queries: usize) -> Result<()> {
    if colours.len() != queries {
        return Err(Error::Shape(format!("{what}: {} colours for {queries} queries", colours.len())));
    }
    if let Some(i) = colours.iter().position(|c| c.iter().any(|v| !(0.0..=1.0).contains(v))) {
        return Err(Error::Invalid(format!(
            "{what}: query {i} has the colour {:?}: channels are in [0, 1]",
            colours[i]
        )));
    }
    Ok(())
}

/// The tracking network; see the module docs.
pub struct Tracker {
    pub cfg: TrackerConfig,
    pub store: ParamStore,
    trunk: VoxelPerceiver,
    /// With `token_positions`: the embedding of the tokens' query points.
    token_fourier: Option<Fourier>,
    pub adamw: AdamWConfig,
    pass_seconds: PassSeconds,
}

impl Tracker {
    fn shape(cfg: &TrackerConfig) -> PerceiverShape {
        PerceiverShape {
            width: cfg.width,
            heads: cfg.heads,
            blocks: cfg.blocks,
            self_layers: 0,
            ffn_ratio: cfg.ffn_ratio,
            xyz_freqs: cfg.xyz_freqs,
            // Every query is at frame time 0: one octave of a constant is all it needs.
            tau_freqs: 1,
            window: 2.0,
            input_hidden: cfg.input_hidden,
            head_hidden: cfg.head_hidden,
            out: 3 * FRAMES,
            head_std: 1e-3,
            query_features: if cfg.query_colour { 3 } else { 0 },
        }
    }

    /// Width of the cross-attention's context: the tokens, and with `token_positions` their
    /// points' embedding.
    fn context_width(cfg: &TrackerConfig) -> usize {
        cfg.token_dim + if cfg.token_positions { fourier_width(4, cfg.xyz_freqs, true) } else { 0 }
    }

    /// The trunk (`trunk.*`, the tracker's only parameters).
    fn trunk(p: &mut Params, cfg: &TrackerConfig) -> Result<VoxelPerceiver> {
        VoxelPerceiver::new(p, "trunk", &Self::shape(cfg), Self::context_width(cfg))
    }

    /// The parameters a config declares, without allocating them.
    pub fn declare(gpu: &Gpu, cfg: &TrackerConfig) -> Result<ParamBuilder> {
        cfg.validate()?;
        declare(gpu, |p| Self::trunk(p, cfg))
    }

    /// The cross-attention's context `[k, context]` of one scene (or a batch's, one after
    /// another), recorded into `rec`: the tokens as they are, or beside their points'
    /// embedding.
    fn context(&self, rec: &mut Recorder, tokens: &Tensor, points: &Tensor) -> Result<Tensor> {
        let Some(fourier) = &self.token_fourier else { return Ok(tokens.clone()) };
        let (k, d) = (tokens.shape()[0], self.cfg.token_dim);
        let (embedded, _) = fourier.forward(rec, points)?;
        let f = fourier.out_width();
        let out = Tensor::empty(tokens.gpu(), &[k, d + f], DType::F32)?;
        copy_columns(rec, tokens, 0, &out, 0, d, 1.0)?;
        copy_columns(rec, &embedded, 0, &out, d, f, 1.0)?;
        Ok(out)
    }

    /// A freshly initialised tracker (parameters from `seed`).
    pub fn new(gpu: &Gpu, cfg: &TrackerConfig, seed: u64) -> Result<Tracker> {
        cfg.validate()?;
        let (trunk, store) = build(gpu, seed, |p| Self::trunk(p, cfg))?;
        let token_fourier =
            if cfg.token_positions { Some(Fourier::octaves(gpu, 4, cfg.xyz_freqs, true)?) } else { None };
        Ok(Tracker {
            cfg: cfg.clone(),
            store,
            trunk,
            token_fourier,
            adamw: AdamWConfig::default(),
            pass_seconds: PassSeconds::default(),
        })
    }

    fn check_tokens(&self, tokens: &Tensor) -> Result<usize> {
        crate::velox::tokens::check_shape("tracker", tokens, self.cfg.token_dim)
    }

    fn loss(&self) -> Loss {
        match self.cfg.loss {
            TrackLoss::L1 => Loss::l1(),
            TrackLoss::L2 => Loss::mse(),
        }
    }

    /// The forward and backward passes of a micro-batch of scenes, adding `weight` times the
    /// gradient of the sum of their losses (each a scene's mean over its drawn queries,
    /// frames and coordinates) into the store's gradients. Each scene draws
    /// `queries_per_sample` of its tracks (all when it has fewer) from its generator.
    pub fn accumulate(&mut self, samples: &[&TrackSample], rngs: &mut [Rng], weight: f64) -> Result<Losses> {
        self.record_pass(samples, rngs, weight)?.run(self)
    }

    /// The recording of [`Tracker::accumulate`], not yet submitted, and its finish.
    fn record_pass(
        &mut self,
        samples: &[&TrackSample],
        rngs: &mut [Rng],
        weight: f64,
    ) -> Result<Ahead<Self>> {
        crate::train::check_micro_batch(samples.len(), rngs.len())?;
        let gpu = samples[0].tokens.gpu().clone();
        let counts = samples.iter().map(|s| self.check_tokens(&s.tokens)).collect::<Result<Vec<_>>>()?;
        let all = counts.iter().sum();
        let tokens = Tensor::empty(&gpu, &[all, self.cfg.token_dim], DType::F32)?;
        // The tokens' points join the context only with `token_positions`.
        let points = if self.token_fourier.is_some() {
            Some(Tensor::empty(&gpu, &[all, 4], DType::F32)?)
        } else {
            None
        };
        let mut rec = self.store.recorder()?;
        let mut timer = PassTimer::start(&mut rec);
        let mut at = 0;
        for (s, &k) in samples.iter().zip(&counts) {
            rec.copy_rows(&s.tokens, 0, &tokens, at, k)?;
            if let Some(points) = &points {
                rec.copy_rows(&s.token_points, 0, points, at, k)?;
            }
            at += k;
        }
        let context = match &points {
            Some(points) => self.context(&mut rec, &tokens, points)?,
            None => tokens,
        };
        let (mut queries, mut targets, mut rows) = (Vec::new(), Vec::new(), Vec::new());
        for (s, rng) in samples.iter().zip(rngs.iter_mut()) {
            let n = s.tracks.len();
            let take = self.cfg.queries_per_sample.min(n);
            let mut order: Vec<usize> = (0..n).collect();
            for i in 0..take {
                let j = i + rng.below((n - i) as u32) as usize;
                order.swap(i, j);
            }
            for &t in &order[..take] {
                let track = &s.tracks[t];
                queries.extend_from_slice(&track[0]);
                if self.cfg.query_colour {
                    queries.extend_from_slice(&s.colours[t]);
                }
                targets.extend(track.iter().flat_map(|p| (0..3).map(move |a| p[a] - track[0][a])));
            }
            rows.push(take);
        }
        let n: usize = rows.iter().sum();
        let frames =
            VoxelFrames { groups: vec![(0.0, n)], segments: Segments::from_lengths(&gpu, &rows, &counts)? };
        let positions = Tensor::from_slice(&gpu, &[n, self.query_width()], &queries)?;
        let (offsets, cache) = self.trunk.forward(&mut rec, &context, &positions, &frames)?;
        let target = Tensor::from_slice(&gpu, &[n, 3 * FRAMES], &targets)?;
        let (loss, d_offsets) = self
            .loss()
            .weighted(weight as f32)
            .forward_backward_segments(&mut rec, &offsets, &target, &rows)?;
        // The backward pass follows in the same recording: no host wait between the two.
        timer.backward(&mut rec);
        self.trunk.backward(&mut rec, &cache, &d_offsets)?;
        // Read back with this recording: no copy and wait of its own on a GPU.
        let loss = rec.read_back(&loss)?;
        timer.end(&mut rec);
        // The step's update, where the trainer asked for it with this pass (ParamStore::update_last).
        self.store.record_update(&mut rec)?;
        Ok(Ahead::one_loss(rec, timer, loss, |model: &mut Tracker| &mut model.pass_seconds))
    }

    /// Numbers per query row: its position, and its colour with `query_colour`.
    fn query_width(&self) -> usize {
        3 + self.trunk.shape.query_features
    }

    /// Records the tracks `[n, 24, 3]` of the queries `positions` (`[n, 3]`, or `[n, 6]` with
    /// the colours after the positions under `query_colour`) into `rec`, from one scene's
    /// `tokens` and their points; unchecked (see [`Tracker::predict`]).
    pub fn record_tracks(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        token_points: &Tensor,
        positions: &Tensor,
    ) -> Result<Tensor> {
        let (n, k) = (positions.shape()[0], tokens.shape()[0]);
        let context = self.context(rec, tokens, token_points)?;
        let frames = VoxelFrames::single(tokens.gpu(), 0.0, n, k)?;
        let (offsets, _) = self.trunk.forward(rec, &context, positions, &frames)?;
        let start = if self.query_width() == 3 {
            positions.clone()
        } else {
            let xyz = Tensor::empty(tokens.gpu(), &[n, 3], DType::F32)?;
            copy_columns(rec, positions, 0, &xyz, 0, 3, 1.0)?;
            xyz
        };
        binary(rec, &offsets.reshape(&[n, FRAMES, 3])?, &start.reshape(&[n, 1, 3])?, Binary::Add)
    }

    /// The tracks of `queries` (points on the first frame, in the scene's [-1, 1]^3 box, with
    /// their `colours` there, RGB in [0, 1], which only a tracker with `query_colour` reads)
    /// from one scene's `tokens` and their points (`[k, 4]`): each query's position at every
    /// frame, frame 0 its prediction for the query itself. Runs [`CHUNK`] queries a pass.
    pub fn predict(
        &self,
        tokens: &Tensor,
        token_points: &Tensor,
        queries: &[[f32; 3]],
        colours: &[[f32; 3]],
    ) -> Result<Vec<Track>> {
        let k = self.check_tokens(tokens)?;
        if token_points.shape() != [k, 4] {
            return Err(Error::Shape(format!(
                "tracker: token points must be [{k}, 4], got {token_points:?}"
            )));
        }
        if let Some(i) = queries.iter().position(|q| q.iter().any(|v| !(v.is_finite() && v.abs() <= 1.0))) {
            return Err(Error::Invalid(format!(
                "tracker: query {i} at {:?} is not a finite point of the scene's [-1, 1]^3 box",
                queries[i]
            )));
        }
        check_colours("tracker", colours, queries.len())?;
        let gpu = tokens.gpu().clone();
        let mut out = Vec::with_capacity(queries.len());
        for (chunk, colours) in queries.chunks(CHUNK).zip(colours.chunks(CHUNK)) {
            let flat: Vec<f32> = chunk
                .iter()
                .zip(colours)
                .flat_map(|(q, c)| q.iter().chain(if self.cfg.query_colour { &c[..] } else { &[] }))
                .copied()
                .collect();
            let positions = Tensor::from_slice(&gpu, &[chunk.len(), self.query_width()], &flat)?;
            let mut rec = gpu.recorder()?;
            let moved = self.record_tracks(&mut rec, tokens, token_points, &positions)?;
            rec.submit()?;
            let values: Vec<f32> = moved.read()?;
            out.extend(
                values
                    .chunks_exact(3 * FRAMES)
                    .map(|t| std::array::from_fn(|f| [t[3 * f], t[3 * f + 1], t[3 * f + 2]])),
            );
        }
        Ok(out)
    }
}

crate::train::token_model_files!(Tracker, TrackerConfig, "tracker");
crate::train::trainable!(Tracker, TrackSample;
    fn records_ahead(&self) -> bool {
        true
    }
);
