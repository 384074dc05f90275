//! Decoding a 4D colour point cloud with a trained autoencoder: the cloud is encoded once
//! ([`Decoding::encode`]), then each frame asked for is decoded from the tokens, to surface
//! points sampled by the 4D surface decoder's flow ([`Decoding::surface_points`]) or to
//! Gaussians over the frame's occupied voxels ([`Decoding::gaussians`]). `velox decode` and
//! `velox eval recon` both decode this way.
//!
//! One seed rule for every frame: the encoder's queries draw from the seed itself, and the
//! sampler's noise of frame `f` from [`frame_seed`]`(seed, f)` = `seed ^ ((f + 1) *
//! 0x9e3779b97f4a7c15)`. So a frame decodes to the same points whichever other frames are
//! decoded with it, in `decode` and in `eval` alike, and no frame's noise is the encoder's.
//!
//! The Gaussian decoder's queries are the occupied voxels of a frame ([`VoxelSource`]): those
//! a voxel decoder predicts from the tokens (the paper's way, fast), those of the input cloud's
//! points of that frame (as in training), or those of surface points sampled from the tokens
//! (the surface ODE, slow). Surface samples outside [-1, 1]^3, where no normalised surface
//! lies, are dropped first (the grid would clamp them onto its border voxels). Predicted voxels
//! of the 64^3 grid are taken to the Gaussian decoder's grid (a voxel there is occupied where
//! one of its 64^3 voxels is).
//!
//! Tests: `tools/tests/models_cli.rs` (decode commands) and `tests/models/eval_alignment.rs`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;
use velox_engine::ops::raster::Gaussians;
use velox_engine::{Error, Precision, Result, Tensor};

use crate::velox::autoencoder::{frame_of_tau, tau_of, Autoencoder, FRAMES};
use crate::velox::surface::{SampleSpec, Sampler};
use crate::velox::voxels::{occupied_centres, VoxelDecoder};
use velox_io::cloud::{self, CHANNELS};
use velox_io::{ply, write_bytes};

/// Where the Gaussian decoder's occupied voxels come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum VoxelSource {
    /// Voxels a voxel decoder predicts from the tokens.
    Predicted,
    /// Voxels of surface points sampled from the tokens.
    Surface,
    /// Voxels of the input cloud's points of the frame (as in training).
    Input,
}

impl VoxelSource {
    /// The name it is written under (as serde writes it).
    pub fn name(self) -> &'static str {
        match self {
            VoxelSource::Predicted => "predicted",
            VoxelSource::Surface => "surface",
            VoxelSource::Input => "input",
        }
    }
}

/// How surface points are sampled: `points` points, `steps` steps of `sampler`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    pub points: usize,
    pub steps: usize,
    pub sampler: Sampler,
}

impl Sampling {
    /// The default sampler: Heun, 20 steps.
    pub fn heun(points: usize) -> Sampling {
        Sampling { points, steps: 20, sampler: Sampler::Heun }
    }
}

/// The name a report gives a sampler: "heun" or "euler".
pub fn sampler_name(s: Sampler) -> &'static str {
    match s {
        Sampler::Heun => "heun",
        Sampler::Euler => "euler",
    }
}

/// The seed of frame `frame`'s sampler noise in a decoding seeded with `seed` (see the module
/// docs).
pub fn frame_seed(seed: u64, frame: usize) -> u64 {
    seed ^ (frame as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15)
}

/// xyz of each frame's points of a validated cloud (rows of x, y, z, r, g, b, tau).
pub fn frame_points(cloud: &[f32]) -> Vec<Vec<f32>> {
    let mut frames = vec![Vec::new(); FRAMES];
    for p in cloud.chunks(CHANNELS) {
        frames[frame_of_tau(p[6])].extend_from_slice(&p[..3]);
    }
    frames
}

/// A cloud encoded by an autoencoder, ready to decode frame by frame.
pub struct Decoding<'a> {
    ae: &'a Autoencoder,
    /// The voxel decoder of [`VoxelSource::Predicted`], if any.
    voxel_decoder: Option<&'a VoxelDecoder>,
    tokens: Tensor,
    /// xyz of the input cloud's points, per frame.
    input: Vec<Vec<f32>>,
    seed: u64,
}

impl<'a> Decoding<'a> {
    /// Encodes `cloud` (host rows of x, y, z, r, g, b, tau, checked here) with the queries
    /// drawn from `seed`, in the autoencoder's precision.
    pub fn encode(ae: &'a Autoencoder, cloud: &[f32], seed: u64) -> Result<Decoding<'a>> {
        let n = cloud::validate(cloud)?;
        let k = ae.cfg.encoder.tokens;
        if n < k {
            return Err(Error::Invalid(format!(
                "the cloud has {n} points; this model's encoder needs at least {k}"
            )));
        }
        let gpu = ae.store.flat_params().gpu();
        let tokens = ae.encode(&cloud::upload(gpu, cloud)?, seed)?;
        Ok(Decoding { ae, voxel_decoder: None, tokens, input: frame_points(cloud), seed })
    }

    /// Tokens made elsewhere (a generator's, or stored ones), `[k, token_dim]` of this
    /// autoencoder's width, with the cloud whose points [`VoxelSource::Input`] reads when there
    /// is one (host rows, checked; without one, every frame has no input points).
    pub fn from_tokens(
        ae: &'a Autoencoder,
        tokens: Tensor,
        cloud: Option<&[f32]>,
        seed: u64,
    ) -> Result<Decoding<'a>> {
        let d = ae.cfg.encoder.token_dim;
        if !matches!(tokens.shape(), [k, w] if *k > 0 && *w == d) {
            return Err(Error::Shape(format!("tokens for the autoencoder must be [k, {d}], got {tokens:?}")));
        }
        let input = match cloud {
            Some(c) => {
                cloud::validate(c)?;
                frame_points(c)
            }
            None => vec![Vec::new(); FRAMES],
        };
        Ok(Decoding { ae, voxel_decoder: None, tokens, input, seed })
    }

    /// Predicts voxels with `decoder` ([`VoxelSource::Predicted`]); it must read tokens as wide
    /// as the autoencoder's.
    pub fn with_voxel_decoder(mut self, decoder: &'a VoxelDecoder) -> Result<Decoding<'a>> {
        let (want, got) = (self.ae.cfg.encoder.token_dim, decoder.cfg.token_dim);
        if want != got {
            return Err(Error::Invalid(format!(
                "the voxel decoder reads tokens {got} wide, the autoencoder's are {want}"
            )));
        }
        self.voxel_decoder = Some(decoder);
        Ok(self)
    }

    /// Occupied voxel centres at the Gaussian decoder's grid, predicted by the voxel decoder.
    pub fn predicted_voxels(&self, frame: usize) -> Result<Vec<f32>> {
        let decoder = self.voxel_decoder.ok_or_else(|| {
            Error::setting("voxel_decoder", "predicted voxels need a voxel decoder ({voxel_decoder})")
        })?;
        let p = decoder.predict(&self.tokens, &[tau_of(frame)])?;
        occupied_centres(&p[0].occupancy, self.ae.cfg.gaussians.grid)
    }

    pub fn tokens(&self) -> &Tensor {
        &self.tokens
    }

    /// xyz of the input cloud's points of `frame`.
    pub fn input_points(&self, frame: usize) -> &[f32] {
        &self.input[frame]
    }

    /// Surface points of `frame` sampled from the tokens, as xyz rows.
    pub fn surface_points(&self, frame: usize, sampling: &Sampling) -> Result<Vec<f32>> {
        let spec = SampleSpec {
            points: sampling.points,
            steps: sampling.steps,
            sampler: sampling.sampler,
            seed: frame_seed(self.seed, frame),
            precision: Precision::F32, // the autoencoder's own precision applies
        };
        self.ae.decode_points(&self.tokens, tau_of(frame), &spec)?.read()
    }

    /// Occupied voxel centres of surface samples of `frame`, without the samples outside
    /// [-1, 1]^3.
    pub fn surface_voxels(&self, samples: &[f32], frame: usize) -> Vec<f32> {
        let inside: Vec<f32> =
            samples.chunks(3).filter(|p| p.iter().all(|v| v.abs() <= 1.0)).flatten().copied().collect();
        self.ae.voxels_from_points(&inside, tau_of(frame))
    }

    /// Occupied voxel centres of the input cloud's points of `frame`.
    pub fn cloud_voxels(&self, frame: usize) -> Vec<f32> {
        self.ae.voxels_from_points(&self.input[frame], tau_of(frame))
    }

    /// The voxels `source` gives for `frame` (sampling the surface with `sampling` for
    /// [`VoxelSource::Surface`]); an error says why when there are none.
    pub fn voxels(&self, frame: usize, source: VoxelSource, sampling: &Sampling) -> Result<Vec<f32>> {
        let centres = match source {
            VoxelSource::Input if self.input[frame].is_empty() => {
                return Err(Error::Invalid(format!(
                    "frame {frame} has no points in the cloud, so it has no voxels: choose other frames or \
                     the surface's voxels"
                )))
            }
            VoxelSource::Input => self.cloud_voxels(frame),
            VoxelSource::Surface => self.surface_voxels(&self.surface_points(frame, sampling)?, frame),
            VoxelSource::Predicted => self.predicted_voxels(frame)?,
        };
        if centres.is_empty() {
            return Err(Error::Invalid(format!(
                "frame {frame}: the {} gives no occupied voxels, so there is nothing to decode",
                match source {
                    VoxelSource::Predicted => "voxel decoder",
                    _ => "surface sampled inside [-1, 1]^3",
                }
            )));
        }
        Ok(centres)
    }

    /// The Gaussians of `frame` over the voxel centres `centres` (host, `[V * 3]`).
    pub fn gaussians(&self, frame: usize, centres: &[f32]) -> Result<Gaussians> {
        self.ae.decode_gaussians(&self.tokens, centres, tau_of(frame))
    }

    /// Decodes `frames` in order and writes one file per frame into the folder `out` (which
    /// must exist): `points_fFF.ply` ([`points_ply`]) or `gaussians_fFF.ply` (the 3D Gaussian
    /// splatting layout of `velox_io::ply`). `on_frame(f)` is called before frame `f` is
    /// decoded. What `velox decode` and the demo write.
    pub fn write_frames(
        &self,
        frames: &[usize],
        output: FrameOutput,
        sampling: &Sampling,
        out: &Path,
        on_frame: &mut dyn FnMut(usize),
    ) -> Result<Vec<WrittenFrame>> {
        let named: Vec<(usize, usize)> = frames.iter().map(|&f| (f, f)).collect();
        self.write_frames_named(&named, output, sampling, out, on_frame)
    }

    /// [`Decoding::write_frames`] of the frames `(frame, name)`: frame `frame` of this clip
    /// written as frame `name` (its file, and the frame of its [`WrittenFrame`]; `on_frame`
    /// is given the name). A clip that is a window of a longer capture names its frames by the
    /// capture's.
    pub fn write_frames_named(
        &self,
        frames: &[(usize, usize)],
        output: FrameOutput,
        sampling: &Sampling,
        out: &Path,
        on_frame: &mut dyn FnMut(usize),
    ) -> Result<Vec<WrittenFrame>> {
        let mut written = Vec::with_capacity(frames.len());
        for &(frame, name) in frames {
            on_frame(name);
            let start = Instant::now();
            let (path, count, voxels) = match output {
                FrameOutput::Points => {
                    let xyz = self.surface_points(frame, sampling)?;
                    let path = out.join(velox_io::frames::frame_file("points", name));
                    write_bytes(&path, &points_ply(&xyz, tau_of(frame)))?;
                    (path, xyz.len() / 3, None)
                }
                FrameOutput::Gaussians(source) => {
                    let centres = self.voxels(frame, source, sampling)?;
                    let g = self.gaussians(frame, &centres)?.download()?;
                    let path = out.join(velox_io::frames::frame_file("gaussians", name));
                    ply::write(&path, &g)?;
                    (path, g.len(), Some(centres.len() / 3))
                }
            };
            let seconds = start.elapsed().as_secs_f64();
            written.push(WrittenFrame { frame: name, tau: tau_of(frame), path, count, voxels, seconds });
        }
        Ok(written)
    }
}

/// What [`Decoding::write_frames`] writes for each frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameOutput {
    /// Surface points sampled from the tokens.
    Points,
    /// Gaussians over the voxels of a source.
    Gaussians(VoxelSource),
}

/// One file [`Decoding::write_frames`] wrote.
#[derive(Clone, Debug)]
pub struct WrittenFrame {
    /// The frame's name: its frame in the clip, or in the capture of which the clip is a window.
    pub frame: usize,
    /// The decoder's frame time (of the frame in its clip).
    pub tau: f32,
    pub path: PathBuf,
    /// Points or Gaussians in the file.
    pub count: usize,
    /// Occupied voxels the Gaussians were decoded from (for Gaussians).
    pub voxels: Option<usize>,
    pub seconds: f64,
}

/// Surface points at frame time `tau` as a binary little-endian PLY: one `vertex` element with
/// the float properties `x y z tau` (the same tau for every point of a file).
pub fn points_ply(xyz: &[f32], tau: f32) -> Vec<u8> {
    let n = xyz.len() / 3;
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment velox decoded surface points\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\nproperty float tau\nend_header\n"
    )
    .into_bytes();
    bytes.reserve(16 * n);
    for p in xyz.chunks(3) {
        for v in [p[0], p[1], p[2], tau] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_get_distinct_seeds_and_points_their_frame() {
        let seeds: std::collections::HashSet<u64> = (0..FRAMES).map(|f| frame_seed(0, f)).collect();
        assert_eq!(seeds.len(), FRAMES);
        assert!(!seeds.contains(&0), "no frame draws the encoder's seed");
        let cloud = [0.1, 0.2, 0.3, 0.5, 0.5, 0.5, 0.05, -0.1, -0.2, -0.3, 0.5, 0.5, 0.5, 0.23];
        let frames = frame_points(&cloud);
        assert_eq!((frames[5].as_slice(), frames[23].as_slice()), (&cloud[..3], &cloud[7..10]));
        let ply = points_ply(&cloud[..6], 0.05);
        let body = &ply[ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11..];
        assert_eq!(body.len(), 2 * 16);
        assert_eq!(f32::from_le_bytes(body[12..16].try_into().unwrap()), 0.05);
    }
}
