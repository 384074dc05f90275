//! 3D tracking metrics as TAPVid-3D defines them (Koppula et al. 2024), on one video's tracks
//! in its camera's frame (x right, y down, z the depth along the optical axis, scene units),
//! computed as the benchmark's evaluation code computes them (google-deepmind/tapnet,
//! `tapnet/tapvid3d/evaluation/metrics.py`, `compute_tapvid3d_metrics`, and
//! `evaluate_model.py`):
//!
//! - **Resolution of the thresholds**: the camera's fx and fy are first rescaled to a video
//!   whose short side is 256 pixels ([`METRIC_RESOLUTION`], [`benchmark_focal`]), whatever the
//!   video's own resolution, so "1 pixel" is a pixel of a 256-pixel image.
//! - **Scaling**: the prediction is rescaled before it is measured ([`Scaling`]; the
//!   benchmark's default is `median`, the ratio of the median norms of the points both the
//!   truth and the prediction show).
//! - **Thresholds**: for d of 1, 2, 4, 8 and 16 pixels, a predicted point is within when the
//!   squared distance to the truth is below `(d * (z / sqrt(fx fy)))^2`, `z` the true depth, in
//!   that order of operations (so a point on the radius falls as it does there); a truth behind
//!   the camera takes the radius of its absolute depth, as the square makes it there.
//! - **APD** (`average_pts_within_thresh`): per threshold, the share of the points the truth
//!   shows that are within, averaged over the five thresholds (`apd_visible`).
//! - **AJ** (average Jaccard): per threshold, true positives (within, visible in truth and in
//!   the prediction) over the visible truth plus false positives (predicted visible where the
//!   truth is occluded or the point is not within), averaged over the thresholds.
//! - **OA** (occlusion accuracy): the share of (track, frame) pairs whose predicted visibility
//!   is the truth's.
//!
//! Beside them, not the benchmark's: `apd_all` (the share within over every point, whatever its
//! visibility) and L2 (the mean Euclidean distance of the rescaled prediction to the truth, over
//! every point and over the visible). Every frame counts, the query frame (frame 0) included.
//! One stated difference: where the truth shows no point, the benchmark's code divides 0 by 0
//! and its means turn NaN; here [`TrackingMetrics::of`] refuses such a video by name and the
//! evaluation leaves it out of the means, saying so. The benchmark's code computes in the
//! arrays' precision (f32 for its files) and sums means pairwise; this module computes in f64
//! and sums in order, so figures agree to rounding (this module's tests check them to 1e-12 on
//! tracks worked out by hand from the official formulas, `the_benchmarks_formulas_by_hand`
//! and `local_neighbourhoods_by_hand`; `tests/models/eval_alignment.rs` checks that each track
//! and frame is scored against its own truth).

use serde::Serialize;
use velox_engine::ops::raster::Camera;
use velox_engine::{Error, Result, Tensor};

use crate::velox::autoencoder::FRAMES;
use crate::velox::tracker::{Track, Tracker};

/// The pixel thresholds.
pub const THRESHOLDS: [f64; 5] = [1.0, 2.0, 4.0, 8.0, 16.0];

/// The short side, in pixels, of the image the thresholds' pixels belong to (the benchmark's
/// `metric_eval_resolution`).
pub const METRIC_RESOLUTION: u32 = 256;

/// The radius, in scene units, of the neighbourhoods of [`Scaling::LocalNeighborhood`] (the
/// benchmark's `local_neighborhood_thresh`).
pub const LOCAL_NEIGHBORHOOD_RADIUS: f64 = 0.05;

/// A camera's focal lengths rescaled to the benchmark's 256-pixel short side: the video's own
/// focal lengths times `256 / min(width, height)` (`evaluate_model.py`).
pub fn benchmark_focal(fx: f64, fy: f64, width: u32, height: u32) -> (f64, f64) {
    let k = METRIC_RESOLUTION as f64 / width.min(height).max(1) as f64;
    (fx * k, fy * k)
}

/// How a prediction is rescaled to the truth's scale before it is measured: the benchmark's
/// `scaling` modes, each as `compute_tapvid3d_metrics` applies it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Scaling {
    /// Not rescaled.
    None,
    /// By the ratio of the medians of the norms `|p|` (at least 1e-6) of the points the truth
    /// and the prediction both show, over the whole video (the benchmark's default).
    #[default]
    Median,
    /// The same with means.
    Mean,
    /// Each track by the ratio of its true and predicted depths on its query frame (each at
    /// least 1e-12).
    PerTrajectory,
    /// Each track's neighbourhood (the points within [`LOCAL_NEIGHBORHOOD_RADIUS`] of the track's
    /// true point on the same frame, over every track) measured as one track, rescaled by the
    /// centre track's `per_trajectory` factor and weighted so that each track counts as many
    /// visible points as it has.
    LocalNeighborhood,
    /// Each point by the ratio of its true and predicted depths, which gives 2D TAP's thresholds.
    Reproduce2d,
    /// By the ratio of the medians of the norms on the query frames only.
    MedianOnQueries,
}

impl Scaling {
    pub const ALL: [Scaling; 7] = [
        Scaling::None,
        Scaling::Median,
        Scaling::Mean,
        Scaling::PerTrajectory,
        Scaling::LocalNeighborhood,
        Scaling::Reproduce2d,
        Scaling::MedianOnQueries,
    ];

    /// The benchmark's name of the mode.
    pub fn name(self) -> &'static str {
        match self {
            Scaling::None => "none",
            Scaling::Median => "median",
            Scaling::Mean => "mean",
            Scaling::PerTrajectory => "per_trajectory",
            Scaling::LocalNeighborhood => "local_neighborhood",
            Scaling::Reproduce2d => "reproduce_2d",
            Scaling::MedianOnQueries => "median_on_queries",
        }
    }

    /// The mode the benchmark's name (or the same with dashes) names.
    pub fn parse(name: &str) -> Result<Scaling> {
        let want = name.trim().replace('-', "_");
        Scaling::ALL.into_iter().find(|s| s.name() == want).ok_or_else(|| {
            let names: Vec<&str> = Scaling::ALL.iter().map(|s| s.name()).collect();
            Error::Invalid(format!("tracking scaling {name:?}: use one of {}", names.join(", ")))
        })
    }
}

/// One video's predicted or true tracks: `positions[i * frames + f]` is track `i` at frame `f`
/// in the camera's frame, `occluded` the same way. Track `i`'s query is its frame 0.
#[derive(Clone, Copy, Debug)]
pub struct CameraTracks<'a> {
    pub positions: &'a [[f64; 3]],
    pub occluded: &'a [bool],
}

/// The metrics of one video (or their mean over videos, as the benchmark averages them).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct TrackingMetrics {
    pub l2_all: f64,
    pub l2_visible: f64,
    pub apd_all: f64,
    /// The benchmark's APD (`average_pts_within_thresh`).
    pub apd_visible: f64,
    pub average_jaccard: f64,
    pub occlusion_accuracy: f64,
    /// Per threshold of [`THRESHOLDS`]: the share of visible points within (`pts_within_d`).
    pub within_visible: [f64; 5],
    /// Per threshold: the Jaccard index (`jaccard_d`).
    pub jaccard: [f64; 5],
}

/// numpy's `median` of finite values: the middle one, or the mean of the two middle ones.
fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let h = v.len() / 2;
    Some(if v.len() % 2 == 1 { v[h] } else { (v[h - 1] + v[h]) / 2.0 })
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// `|p|` as the benchmark takes it for its ratios: at least 1e-6.
fn norm(p: [f64; 3]) -> f64 {
    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).max(1e-12).sqrt()
}

impl TrackingMetrics {
    /// The metrics of `pred` against `truth` (`tracks * frames` points each, finite positions)
    /// for a camera of focal lengths `fx`, `fy` in the thresholds' pixels (see
    /// [`benchmark_focal`]), the prediction rescaled by `scaling`. Fails on mismatched sizes,
    /// non-finite numbers, or a truth with no visible point (the benchmark's code gives NaN).
    pub fn of(
        truth: CameraTracks,
        pred: CameraTracks,
        frames: usize,
        fx: f64,
        fy: f64,
        scaling: Scaling,
    ) -> Result<TrackingMetrics> {
        let tracks = truth.positions.len() / frames.max(1);
        TrackingMetrics::of_queries(truth, pred, frames, &vec![0; tracks], fx, fy, scaling)
    }

    /// [`TrackingMetrics::of`] for tracks whose queries lie on the frames `query_frames` (one
    /// a track; TAPVid-3D's `queries_xyt`), which the per-trajectory and query scalings read.
    pub fn of_queries(
        truth: CameraTracks,
        pred: CameraTracks,
        frames: usize,
        query_frames: &[usize],
        fx: f64,
        fy: f64,
        scaling: Scaling,
    ) -> Result<TrackingMetrics> {
        let n = truth.positions.len();
        if n == 0 || [pred.positions.len(), truth.occluded.len(), pred.occluded.len()].iter().any(|&m| m != n)
        {
            return Err(Error::Invalid(format!(
                "tracking metrics: {} true positions, {} predicted, {} true and {} predicted occlusion flags \
                 (they must be equal and non-zero)",
                n,
                pred.positions.len(),
                truth.occluded.len(),
                pred.occluded.len()
            )));
        }
        if frames == 0 || !n.is_multiple_of(frames) {
            return Err(Error::Invalid(format!(
                "tracking metrics: {n} points are not whole tracks of {frames} frames"
            )));
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(Error::Invalid(format!(
                "tracking metrics: focal lengths {fx}, {fy} must be positive"
            )));
        }
        let finite = |p: &[[f64; 3]]| p.iter().flatten().all(|v| v.is_finite());
        if !finite(truth.positions) || !finite(pred.positions) {
            return Err(Error::Invalid("tracking metrics: a position is not finite".into()));
        }
        let visible_count = truth.occluded.iter().filter(|&&o| !o).count();
        if visible_count == 0 {
            return Err(Error::Invalid(
                "tracking metrics: the truth shows no point, so the visible-point metrics are undefined"
                    .into(),
            ));
        }
        let tracks = n / frames;
        if query_frames.len() != tracks || query_frames.iter().any(|&f| f >= frames) {
            return Err(Error::Invalid(format!(
                "tracking metrics: {} query frames for {tracks} tracks of {frames} frames (one each, below {frames})",
                query_frames.len()
            )));
        }
        let query = |i: usize| i * frames + query_frames[i];
        // The factor each point's prediction is multiplied by; NaN where the benchmark's is
        // (no point visible in both for the medians): no such point is within.
        let both = |k: usize| !truth.occluded[k] && !pred.occluded[k];
        let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => a / b,
            _ => f64::NAN,
        };
        let per_track = |i: usize| {
            let q = query(i);
            truth.positions[q][2].max(1e-12) / pred.positions[q][2].max(1e-12)
        };
        let factor: Vec<f64> = match scaling {
            Scaling::None => vec![1.0; n],
            Scaling::Median | Scaling::Mean => {
                let pick =
                    |of: &[[f64; 3]]| (0..n).filter(|&k| both(k)).map(|k| norm(of[k])).collect::<Vec<_>>();
                let (g, p) = (pick(truth.positions), pick(pred.positions));
                let s = if scaling == Scaling::Median {
                    ratio(median(g), median(p))
                } else {
                    ratio(mean(&g), mean(&p))
                };
                vec![s; n]
            }
            Scaling::MedianOnQueries => {
                let pick = |of: &[[f64; 3]]| {
                    (0..tracks).map(query).filter(|&k| both(k)).map(|k| norm(of[k])).collect::<Vec<_>>()
                };
                vec![ratio(median(pick(truth.positions)), median(pick(pred.positions))); n]
            }
            Scaling::PerTrajectory | Scaling::LocalNeighborhood => {
                (0..n).map(|k| per_track(k / frames)).collect()
            }
            Scaling::Reproduce2d => (0..n).map(|k| truth.positions[k][2] / pred.positions[k][2]).collect(),
        };
        let scaled: Vec<[f64; 3]> =
            pred.positions.iter().zip(&factor).map(|(p, s)| [p[0] * s, p[1] * s, p[2] * s]).collect();
        let dist2 = |a: [f64; 3], b: [f64; 3]| {
            let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        };
        let focal = (fx * fy).sqrt();
        let within = |k: usize, px: f64| {
            let r = px * (truth.positions[k][2] / focal);
            dist2(scaled[k], truth.positions[k]) < r * r
        };

        // The measured points with their weights: every point once, or every track's
        // neighbourhood (the point k of centre track c, with c's factor and weight).
        let mut measured: Vec<(usize, [f64; 3], f64)> = Vec::new();
        if scaling == Scaling::LocalNeighborhood {
            let r2 = LOCAL_NEIGHBORHOOD_RADIUS * LOCAL_NEIGHBORHOOD_RADIUS;
            for c in 0..tracks {
                let s = per_track(c);
                let members: Vec<usize> = (0..n)
                    .filter(|&k| dist2(truth.positions[k], truth.positions[c * frames + k % frames]) < r2)
                    .collect();
                let own = (0..frames).filter(|&f| !truth.occluded[c * frames + f]).count() as f64;
                let shown = members.iter().filter(|&&k| !truth.occluded[k]).count() as f64;
                let w = own / shown.max(1.0);
                for k in members {
                    let p = pred.positions[k];
                    measured.push((k, [p[0] * s, p[1] * s, p[2] * s], w));
                }
            }
        } else {
            measured.extend((0..n).map(|k| (k, scaled[k], 1.0)));
        }

        let mut m = TrackingMetrics::default();
        let (mut total_w, mut agree_w, mut visible_w) = (0.0, 0.0, 0.0);
        let mut correct = [0.0f64; 5];
        let mut true_pos = [0.0f64; 5];
        let mut false_pos = [0.0f64; 5];
        for &(k, p, w) in &measured {
            let t = truth.positions[k];
            let visible = !truth.occluded[k];
            let pred_visible = !pred.occluded[k];
            total_w += w;
            agree_w += if truth.occluded[k] == pred.occluded[k] { w } else { 0.0 };
            visible_w += if visible { w } else { 0.0 };
            let d2 = dist2(p, t);
            for (i, &px) in THRESHOLDS.iter().enumerate() {
                let r = px * (t[2] / focal);
                let inside = d2 < r * r;
                correct[i] += if inside && visible { w } else { 0.0 };
                true_pos[i] += if inside && visible && pred_visible { w } else { 0.0 };
                false_pos[i] += if pred_visible && (!visible || !inside) { w } else { 0.0 };
            }
        }
        m.occlusion_accuracy = agree_w / total_w;
        for i in 0..5 {
            m.within_visible[i] = correct[i] / visible_w;
            m.jaccard[i] = true_pos[i] / (visible_w + false_pos[i]);
        }
        m.apd_visible = m.within_visible.iter().sum::<f64>() / 5.0;
        m.average_jaccard = m.jaccard.iter().sum::<f64>() / 5.0;

        // The extras, over every point once with its own factor (not the benchmark's; the
        // prediction as it is where the factor is undefined).
        let (mut l2_all, mut l2_visible) = (0.0, 0.0);
        for k in 0..n {
            let p = if factor[k].is_finite() { scaled[k] } else { pred.positions[k] };
            let d = dist2(p, truth.positions[k]).sqrt();
            l2_all += d;
            if !truth.occluded[k] {
                l2_visible += d;
            }
            let inside = THRESHOLDS.iter().filter(|&&px| within(k, px)).count();
            m.apd_all += inside as f64 / (5 * n) as f64;
        }
        m.l2_all = l2_all / n as f64;
        m.l2_visible = l2_visible / visible_count as f64;
        Ok(m)
    }

    /// The mean of each metric over videos (the benchmark's figure for a set of videos).
    pub fn mean(all: &[TrackingMetrics]) -> TrackingMetrics {
        let mut m = TrackingMetrics::default();
        let w = 1.0 / all.len().max(1) as f64;
        for a in all {
            m.l2_all += w * a.l2_all;
            m.l2_visible += w * a.l2_visible;
            m.apd_all += w * a.apd_all;
            m.apd_visible += w * a.apd_visible;
            m.average_jaccard += w * a.average_jaccard;
            m.occlusion_accuracy += w * a.occlusion_accuracy;
            for k in 0..5 {
                m.within_visible[k] += w * a.within_visible[k];
                m.jaccard[k] += w * a.jaccard[k];
            }
        }
        m
    }
}

/// One scene's tracking problem, as `velox eval tracking` reads it: the true tracks of its
/// queries (frame 0 is the query), whether its video camera sees each at each frame, the
/// camera and its depth frames (camera z, 0 where no surface).
pub struct TrackingScene<'a> {
    pub truth: &'a [Track],
    /// Each track's colour on the first frame (what a tracker with `query_colour` reads).
    pub colours: &'a [[f32; 3]],
    pub visible: &'a [[bool; FRAMES]],
    pub camera: &'a Camera,
    pub depth: &'a [Vec<f32>],
}

impl TrackingScene<'_> {
    /// Tracks in the camera's frame, occluded where the camera does not see them in the
    /// video's depth (`Camera::sees`: the paper's visibility, not learned).
    pub fn in_camera(&self, tracks: &[Track]) -> (Vec<[f64; 3]>, Vec<bool>) {
        let c = self.camera;
        let (mut positions, mut hidden) = (Vec::new(), Vec::new());
        for t in tracks {
            for (f, p) in t.iter().enumerate() {
                positions.push(c.to_camera(*p).map(|v| v as f64));
                hidden.push(!c.sees(*p, &self.depth[f]));
            }
        }
        (positions, hidden)
    }

    /// The metrics of `predicted` (one track per true one, in the same order), rescaled by
    /// `scaling`, with the thresholds in pixels of the benchmark's 256-pixel short side.
    pub fn metrics(&self, predicted: &[Track], scaling: Scaling) -> Result<TrackingMetrics> {
        if predicted.len() != self.truth.len() || self.visible.len() != self.truth.len() {
            return Err(Error::Invalid(format!(
                "tracking: {} predicted tracks and {} visibility rows for {} true tracks",
                predicted.len(),
                self.visible.len(),
                self.truth.len()
            )));
        }
        if self.depth.len() != FRAMES
            || self.depth.iter().any(|d| d.len() != self.camera.width as usize * self.camera.height as usize)
        {
            return Err(Error::Invalid(format!(
                "tracking: {FRAMES} depth frames of {} x {} are needed",
                self.camera.width, self.camera.height
            )));
        }
        let (truth, _) = self.in_camera(self.truth);
        let truth_hidden: Vec<bool> = self.visible.iter().flatten().map(|&v| !v).collect();
        let (pred, pred_hidden) = self.in_camera(predicted);
        let c = self.camera;
        let (fx, fy) = benchmark_focal(c.fx as f64, c.fy as f64, c.width, c.height);
        TrackingMetrics::of(
            CameraTracks { positions: &truth, occluded: &truth_hidden },
            CameraTracks { positions: &pred, occluded: &pred_hidden },
            FRAMES,
            fx,
            fy,
            scaling,
        )
    }

    /// Whether the truth shows any point (the benchmark's metrics are 0 / 0 where it does not).
    pub fn shows_any(&self) -> bool {
        self.visible.iter().flatten().any(|&v| v)
    }
}

/// A scene's figures: the tracker, and in the same table the static baseline (every query
/// stays where it is on the first frame) and the truth itself (the ceiling: its APD is 1, its
/// OA how often the depth test agrees with the data's visibility).
#[derive(Clone, Debug, Serialize)]
pub struct TrackingReport {
    pub name: String,
    pub queries: usize,
    pub tracker: TrackingMetrics,
    pub static_baseline: TrackingMetrics,
    pub truth: TrackingMetrics,
}

impl TrackingReport {
    /// The mean of each method's figures over scenes.
    pub fn mean(all: &[TrackingReport]) -> TrackingReport {
        let pick = |f: fn(&TrackingReport) -> &TrackingMetrics| {
            TrackingMetrics::mean(&all.iter().map(|r| f(r).clone()).collect::<Vec<_>>())
        };
        TrackingReport {
            name: "mean".into(),
            queries: all.iter().map(|r| r.queries).sum(),
            tracker: pick(|r| &r.tracker),
            static_baseline: pick(|r| &r.static_baseline),
            truth: pick(|r| &r.truth),
        }
    }
}

/// Tracks the queries of `scene` (the first frame of its true tracks) from its `tokens` (and
/// their points) and scores the tracker, the static baseline and the truth, every one rescaled
/// by `scaling`; returns the report and the predicted tracks.
pub fn evaluate_scene(
    tracker: &Tracker,
    name: &str,
    tokens: &Tensor,
    token_points: &Tensor,
    scene: &TrackingScene,
    scaling: Scaling,
) -> Result<(TrackingReport, Vec<Track>)> {
    let queries: Vec<[f32; 3]> = scene.truth.iter().map(|t| t[0]).collect();
    let predicted = tracker.predict(tokens, token_points, &queries, scene.colours)?;
    let still: Vec<Track> = queries.iter().map(|&q| [q; FRAMES]).collect();
    let report = TrackingReport {
        name: name.to_string(),
        queries: queries.len(),
        tracker: scene.metrics(&predicted, scaling)?,
        static_baseline: scene.metrics(&still, scaling)?,
        truth: scene.metrics(scene.truth, scaling)?,
    };
    Ok((report, predicted))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn approx(a: f64, b: f64) {
        assert!((a - b).abs() < 1e-12, "{a} vs {b}");
    }

    /// One-frame tracks, not rescaled.
    fn of_none(truth: CameraTracks, pred: CameraTracks, fx: f64, fy: f64) -> Result<TrackingMetrics> {
        TrackingMetrics::of(truth, pred, 1, fx, fy, Scaling::None)
    }

    /// Focal 100 px, truth at depth 2: a pixel is 0.02 units, so the thresholds are 0.02,
    /// 0.04, 0.08, 0.16 and 0.32.
    #[test]
    fn worked_by_hand() {
        let truth = [[0.0, 0.0, 2.0]; 4];
        // Off by 0.03 (within 2, 4, 8, 16 px), 0.1 (within 8, 16), 1.0 (none), exact (all).
        let pred = [[0.03, 0.0, 2.0], [0.0, 0.1, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 2.0]];
        // Truth: track 2 occluded. Prediction: track 1 called occluded, track 2 visible.
        let t_occ = [false, false, true, false];
        let p_occ = [false, true, false, false];
        let m = of_none(
            CameraTracks { positions: &truth, occluded: &t_occ },
            CameraTracks { positions: &pred, occluded: &p_occ },
            100.0,
            100.0,
        )
        .unwrap();
        approx(m.l2_all, (0.03 + 0.1 + 1.0 + 0.0) / 4.0);
        approx(m.l2_visible, (0.03 + 0.1 + 0.0) / 3.0);
        approx(m.occlusion_accuracy, 0.5);
        // Visible points within per threshold: {3}, {0, 3}, {0, 3}, {0, 1, 3}, {0, 1, 3}.
        let within = [1.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0, 1.0, 1.0];
        for (got, want) in m.within_visible.iter().zip(within) {
            approx(*got, want);
        }
        approx(m.apd_visible, within.iter().sum::<f64>() / 5.0);
        // All points: the same counts over 4 (track 2 is never within).
        approx(m.apd_all, [1.0, 2.0, 2.0, 3.0, 3.0].iter().sum::<f64>() / 4.0 / 5.0);
        // Jaccard: predicted visible are 0, 2, 3. Track 2 is always a false positive (occluded
        // in truth); track 0 is one below 2 px. True positives: those of {0, 3} within.
        let jaccard = [1.0 / (3.0 + 2.0), 2.0 / (3.0 + 1.0), 2.0 / 4.0, 2.0 / 4.0, 2.0 / 4.0];
        for (got, want) in m.jaccard.iter().zip(jaccard) {
            approx(*got, want);
        }
        approx(m.average_jaccard, jaccard.iter().sum::<f64>() / 5.0);
    }

    /// The threshold grows with depth and with a shorter focal length (the geometric mean of
    /// fx and fy); a truth behind the camera takes the radius of its absolute depth, as the
    /// benchmark's square makes it.
    #[test]
    fn thresholds_scale_with_depth_and_focal_length() {
        let one = |truth: [f64; 3], off: f64, fx: f64, fy: f64| {
            let pred = [[truth[0] + off, truth[1], truth[2]]];
            of_none(
                CameraTracks { positions: &[truth], occluded: &[false] },
                CameraTracks { positions: &pred, occluded: &[false] },
                fx,
                fy,
            )
            .unwrap()
            .within_visible[0]
        };
        // 1 px at depth 4, focal 100: 0.04.
        approx(one([0.0, 0.0, 4.0], 0.039, 100.0, 100.0), 1.0);
        approx(one([0.0, 0.0, 4.0], 0.041, 100.0, 100.0), 0.0);
        approx(one([0.0, 0.0, 2.0], 0.039, 100.0, 100.0), 0.0);
        // sqrt(50 200) = 100.
        approx(one([0.0, 0.0, 4.0], 0.039, 50.0, 200.0), 1.0);
        approx(one([0.0, 0.0, 4.0], 0.039, 200.0, 200.0), 0.0);
        approx(one([0.0, 0.0, -4.0], 0.039, 100.0, 100.0), 1.0);
        approx(one([0.0, 0.0, -4.0], 0.041, 100.0, 100.0), 0.0);
        // At depth 0 the radius is 0 and nothing is within, not even an exact prediction.
        approx(one([0.0, 0.0, 0.0], 0.0, 100.0, 100.0), 0.0);
    }

    /// Out-of-frame and occluded points count only through the metrics that take every point,
    /// and a prediction that says so gains occlusion accuracy and Jaccard.
    #[test]
    fn occluded_points_leave_the_visible_metrics() {
        let truth = [[0.0, 0.0, 1.0], [5.0, 0.0, 1.0]];
        let far = [[0.0, 0.0, 1.0], [9.0, 0.0, 1.0]];
        let t_occ = [false, true];
        let run = |p_occ: &[bool]| {
            of_none(
                CameraTracks { positions: &truth, occluded: &t_occ },
                CameraTracks { positions: &far, occluded: p_occ },
                100.0,
                100.0,
            )
            .unwrap()
        };
        let said = run(&[false, true]);
        approx(said.apd_visible, 1.0);
        approx(said.apd_all, 0.5);
        approx(said.l2_visible, 0.0);
        approx(said.l2_all, 2.0);
        approx(said.occlusion_accuracy, 1.0);
        approx(said.average_jaccard, 1.0);
        let missed = run(&[false, false]);
        approx(missed.apd_visible, 1.0);
        approx(missed.occlusion_accuracy, 0.5);
        approx(missed.average_jaccard, 0.5);
    }

    #[test]
    fn bad_input_is_refused() {
        let p = [[0.0, 0.0, 1.0]];
        let ok = CameraTracks { positions: &p, occluded: &[false] };
        let hidden = CameraTracks { positions: &p, occluded: &[true] };
        assert!(of_none(hidden, ok, 1.0, 1.0).unwrap_err().to_string().contains("shows no point"));
        let nan = [[f64::NAN, 0.0, 1.0]];
        let bad = CameraTracks { positions: &nan, occluded: &[false] };
        assert!(of_none(ok, bad, 1.0, 1.0).unwrap_err().to_string().contains("finite"));
        assert!(of_none(ok, ok, 0.0, 1.0).unwrap_err().to_string().contains("focal"));
        let short = CameraTracks { positions: &[], occluded: &[] };
        assert!(of_none(ok, short, 1.0, 1.0).is_err());
    }

    #[test]
    fn the_mean_is_per_metric() {
        let a = TrackingMetrics { l2_all: 1.0, jaccard: [1.0; 5], ..Default::default() };
        let b = TrackingMetrics { l2_all: 3.0, ..Default::default() };
        let m = TrackingMetrics::mean(&[a, b]);
        approx(m.l2_all, 2.0);
        approx(m.jaccard[4], 0.5);
    }

    /// Six points (three tracks of two frames) worked out by hand with the benchmark's
    /// formulas (`compute_tapvid3d_metrics`), thresholds in pixels of a 256-pixel short side
    /// (fx = fy = 320 there: a 128-pixel video of focal 160, or a 256-pixel one of 320).
    ///
    /// truth (camera frame)   prediction        scaled by 2      distance  z
    /// A t0 f0 (0, 0, 1)      (0, 0, 0.5)       (0, 0, 1)        0         1
    /// B t0 f1 (0, 0, 1.5)    (0.005, 0, 0.75)  (0.01, 0, 1.5)   0.01      1.5
    /// C t1 f0 (0, 0, 2)      (0, 0, 1)         (0, 0, 2)        0         2
    /// D t1 f1 (0, 0, 3)      (0.0075, 0, 1.5)  (0.015, 0, 3)    0.015     3
    /// E t2 f0 (0, 0, 4)      (0.04, 0, 2)      (0.08, 0, 4)     0.08      4
    /// F t2 f1 (0, 0, 5)      (0, 0, 2.5)       occluded in the truth only
    ///
    /// Scale factors: median: the norms of the points both show (A to E) are 1, 1.5, 2, 3, 4
    /// and 0.5, 0.75002, 1, 1.50002, 2.0004: medians 2 and 1, factor 2 exactly. per_trajectory
    /// (true over predicted depth on frame 0): 1/0.5, 2/1, 4/2, all 2. reproduce_2d: every
    /// point's true over predicted depth, 2. median_on_queries (A, C, E): 2 / 1. mean:
    /// 2.3 / 1.150087, within 1e-4 of 2, which moves no point across a threshold.
    /// Radii d z / 320: B (z 1.5) 0.0047, 0.0094, 0.019, ...; D (z 3) 0.0094, 0.019, ...;
    /// E (z 4) 0.0125, 0.025, 0.05, 0.1, 0.2. Within, over the five visible points, per
    /// threshold 1, 2, 4, 8, 16: {A, C}, {A, C, D}, {A, B, C, D}, all, all.
    /// Everything is predicted visible: true positives are those counts, false positives F
    /// plus the visible points not within (B, D, E; B, E; E; none; none).
    #[test]
    fn the_benchmarks_formulas_by_hand() {
        let truth = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.5],
            [0.0, 0.0, 2.0],
            [0.0, 0.0, 3.0],
            [0.0, 0.0, 4.0],
            [0.0, 0.0, 5.0],
        ];
        let pred = [
            [0.0, 0.0, 0.5],
            [0.005, 0.0, 0.75],
            [0.0, 0.0, 1.0],
            [0.0075, 0.0, 1.5],
            [0.04, 0.0, 2.0],
            [0.0, 0.0, 2.5],
        ];
        let t_occ = [false, false, false, false, false, true];
        let p_occ = [false; 6];
        let within = [2.0 / 5.0, 3.0 / 5.0, 4.0 / 5.0, 1.0, 1.0];
        let jaccard = [2.0 / (5.0 + 4.0), 3.0 / (5.0 + 3.0), 4.0 / (5.0 + 2.0), 5.0 / 6.0, 5.0 / 6.0];
        for (width, focal) in [(128, 160.0), (256, 320.0)] {
            let (fx, fy) = benchmark_focal(focal, focal, width, width);
            assert_eq!((fx, fy), (320.0, 320.0));
            for scaling in
                Scaling::ALL.into_iter().filter(|&s| s != Scaling::None && s != Scaling::LocalNeighborhood)
            {
                let m = TrackingMetrics::of(
                    CameraTracks { positions: &truth, occluded: &t_occ },
                    CameraTracks { positions: &pred, occluded: &p_occ },
                    2,
                    fx,
                    fy,
                    scaling,
                )
                .unwrap();
                for k in 0..5 {
                    approx(m.within_visible[k], within[k]);
                    approx(m.jaccard[k], jaccard[k]);
                }
                approx(m.apd_visible, 0.76);
                approx(m.average_jaccard, jaccard.iter().sum::<f64>() / 5.0);
                approx(m.occlusion_accuracy, 5.0 / 6.0);
            }
            // Not rescaled, every prediction is off by half its depth and 16 px is z / 20:
            // none within.
            let m = TrackingMetrics::of(
                CameraTracks { positions: &truth, occluded: &t_occ },
                CameraTracks { positions: &pred, occluded: &p_occ },
                2,
                fx,
                fy,
                Scaling::None,
            )
            .unwrap();
            approx(m.apd_visible, 0.0);
            approx(m.average_jaccard, 0.0);
            approx(m.occlusion_accuracy, 5.0 / 6.0);
        }
        // In the 128-pixel video's own pixels (focal 160), every radius doubles: D falls
        // within 1 pixel, B within 2, E within 4, so the figures are not the benchmark's.
        let own = TrackingMetrics::of(
            CameraTracks { positions: &truth, occluded: &t_occ },
            CameraTracks { positions: &pred, occluded: &p_occ },
            2,
            160.0,
            160.0,
            Scaling::Median,
        )
        .unwrap();
        approx(own.apd_visible, (3.0 / 5.0 + 4.0 / 5.0 + 1.0 + 1.0 + 1.0) / 5.0);
    }

    /// Neighbourhoods (radius 0.05 in the truth) by hand: two tracks 0.01 apart at every
    /// frame are each other's neighbours, a third 1 away has none but itself. Track 0's
    /// group holds 4 points, 3 of them visible; track 0 shows 2, so each of its group's points
    /// weighs 2/3; track 1 shows 1 of its 2: 1/3; track 2 shows 2 of its own 2: 1.
    #[test]
    fn local_neighbourhoods_by_hand() {
        // Tracks of 2 frames: t0 and t1 close, t2 far. Depth 2, predictions exact at half
        // scale (per_trajectory factor 2 for each), except t1's frame 1, which is 0.2 off.
        let truth = [
            [0.0, 0.0, 2.0],
            [0.0, 0.0, 2.0],
            [0.01, 0.0, 2.0],
            [0.01, 0.0, 2.0],
            [1.0, 0.0, 2.0],
            [1.0, 0.0, 2.0],
        ];
        let pred = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.005, 0.0, 1.0],
            [0.105, 0.0, 1.0],
            [0.5, 0.0, 1.0],
            [0.5, 0.0, 1.0],
        ];
        let t_occ = [false, false, false, true, false, false];
        let p_occ = [false; 6];
        let m = TrackingMetrics::of(
            CameraTracks { positions: &truth, occluded: &t_occ },
            CameraTracks { positions: &pred, occluded: &p_occ },
            2,
            320.0,
            320.0,
            Scaling::LocalNeighborhood,
        )
        .unwrap();
        // Groups: t0 -> points 0..4 (weight 2/3 each), t1 -> points 0..4 (1/3 each: t1 shows
        // 1, its group 3), t2 -> points 4, 5 (weight 1). Point 3 (t1 f1) is occluded in the
        // truth and 0.2 off; the others are exact. Visible weight: 3 (2/3) + 3 (1/3) + 2 = 5;
        // within (every threshold): the same 5; false positives: point 3 in two groups,
        // 2/3 + 1/3 = 1; total weight 4 (2/3) + 4 (1/3) + 2 = 6; agreeing: all but point 3,
        // 6 - 1 = 5.
        approx(m.apd_visible, 1.0);
        approx(m.average_jaccard, 5.0 / (5.0 + 1.0));
        approx(m.occlusion_accuracy, 5.0 / 6.0);
    }

    /// `TrackingScene::metrics` measures in pixels of a 256-pixel short side whatever the
    /// video's resolution: the same view at 128 and at 256 pixels gives the same figures, those
    /// of the focal lengths rescaled by hand, and not those of the 128-pixel video's own.
    #[test]
    fn a_scene_measures_in_256_pixel_units_at_any_resolution() {
        let small = Camera::identity(45.0, 128, 96);
        let large = small.upscaled(2);
        let truth: Vec<Track> = (0..3).map(|i| [[0.1 * i as f32, 0.0, 2.0 + i as f32]; FRAMES]).collect();
        let pred: Vec<Track> = truth
            .iter()
            .enumerate()
            .map(|(i, t)| {
                std::array::from_fn(|f| [t[f][0] + 0.002 * (i * FRAMES + f) as f32, t[f][1], t[f][2]])
            })
            .collect();
        let visible = vec![[true; FRAMES]; 3];
        let colours = vec![[0.5f32; 3]; 3];
        // A far wall behind every point: the camera sees them all, so predictions are visible.
        let figures = |camera: &Camera| {
            let depth = vec![vec![100.0f32; (camera.width * camera.height) as usize]; FRAMES];
            let scene =
                TrackingScene { truth: &truth, colours: &colours, visible: &visible, camera, depth: &depth };
            scene.metrics(&pred, Scaling::Median).unwrap()
        };
        let (a, b) = (figures(&small), figures(&large));
        assert_eq!(a, b);
        let scene = TrackingScene {
            truth: &truth,
            colours: &colours,
            visible: &visible,
            camera: &small,
            depth: &vec![vec![100.0; 128 * 96]; FRAMES],
        };
        let (t, _) = scene.in_camera(&truth);
        let (p, hidden) = scene.in_camera(&pred);
        let t_occ = vec![false; t.len()];
        let of = |fx: f64, fy: f64| {
            TrackingMetrics::of(
                CameraTracks { positions: &t, occluded: &t_occ },
                CameraTracks { positions: &p, occluded: &hidden },
                FRAMES,
                fx,
                fy,
                Scaling::Median,
            )
            .unwrap()
        };
        // 96 is the short side: focal lengths times 256 / 96.
        let k = 256.0 / 96.0;
        assert_eq!(a, of(small.fx as f64 * k, small.fy as f64 * k));
        assert!(a.apd_visible > 0.0 && a.apd_visible < 1.0, "{a:?}");
        assert!(hidden.iter().all(|&h| !h));
        assert_ne!(a.apd_visible, of(small.fx as f64, small.fy as f64).apd_visible);
    }
}
