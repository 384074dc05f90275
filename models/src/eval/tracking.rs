//! 3D tracking metrics as TAPVid-3D defines them (Koppula et al. 2024), on one video's tracks
//! in its camera's frame (x right, y down, z the depth along the optical axis, scene units).
//!
//! - **Thresholds**: for pixel thresholds d of 1, 2, 4, 8 and 16, a predicted point is within
//!   when its distance to the truth is below `d z / sqrt(fx fy)`, `z` the true depth: the
//!   3D size of d pixels at the truth's depth. A truth at or behind the camera has no
//!   threshold (nothing is within).
//! - **APD** (average percent of points within delta): per threshold, the share within,
//!   averaged over the five thresholds; over the points the truth shows (`apd_visible`, the
//!   benchmark's APD) and over every point whatever its visibility (`apd_all`).
//! - **AJ** (average Jaccard): per threshold, true positives (within, visible in truth and in
//!   the prediction) over true positives plus false negatives (the visible truth) plus false
//!   positives (predicted visible where the truth is occluded or the point is not within),
//!   averaged over the thresholds.
//! - **OA** (occlusion accuracy): the share of (track, frame) pairs whose predicted
//!   visibility is the truth's.
//! - **L2**: the mean Euclidean distance to the truth, over every point and over the visible.
//!
//! Every frame counts, the query frame included, and predictions are not rescaled (the
//! benchmark's `scaling='none'`): the tracker predicts in the scene's own units, so there is no
//! unknown scale to remove. Points out of the image are occluded in the truth.

use serde::Serialize;
use velox_engine::ops::raster::Camera;
use velox_engine::{Error, Result, Tensor};

use crate::velox::autoencoder::FRAMES;
use crate::velox::tracker::{Track, Tracker};

/// The pixel thresholds.
pub const THRESHOLDS: [f64; 5] = [1.0, 2.0, 4.0, 8.0, 16.0];

/// One video's predicted or true tracks: `positions[i * frames + f]` is track `i` at frame `f`
/// in the camera's frame, `occluded` the same way.
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
    pub apd_visible: f64,
    pub average_jaccard: f64,
    pub occlusion_accuracy: f64,
    /// Per threshold of [`THRESHOLDS`]: the share of visible points within.
    pub within_visible: [f64; 5],
    /// Per threshold: the Jaccard index.
    pub jaccard: [f64; 5],
}

impl TrackingMetrics {
    /// The metrics of `pred` against `truth` (same layout, finite positions), for a camera of
    /// focal lengths `fx`, `fy` in pixels. Fails on mismatched sizes, non-finite numbers, or a
    /// truth with no visible point (the visible-point metrics would be 0 / 0).
    pub fn of(truth: CameraTracks, pred: CameraTracks, fx: f64, fy: f64) -> Result<TrackingMetrics> {
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
        let per_pixel = 1.0 / (fx * fy).sqrt();
        let mut m = TrackingMetrics::default();
        let (mut l2_all, mut l2_visible) = (0.0, 0.0);
        let mut agree = 0usize;
        let mut within_all = [0usize; 5];
        let mut within_visible = [0usize; 5];
        let mut true_pos = [0usize; 5];
        let mut false_pos = [0usize; 5];
        for i in 0..n {
            let (t, p) = (truth.positions[i], pred.positions[i]);
            let d2: f64 = (0..3).map(|a| (p[a] - t[a]).powi(2)).sum();
            let d = d2.sqrt();
            let visible = !truth.occluded[i];
            let pred_visible = !pred.occluded[i];
            l2_all += d;
            if visible {
                l2_visible += d;
            }
            agree += (truth.occluded[i] == pred.occluded[i]) as usize;
            for (k, &px) in THRESHOLDS.iter().enumerate() {
                let radius = px * t[2] * per_pixel;
                let within = t[2] > 0.0 && d2 < radius * radius;
                within_all[k] += within as usize;
                within_visible[k] += (within && visible) as usize;
                true_pos[k] += (within && visible && pred_visible) as usize;
                false_pos[k] += (pred_visible && (!visible || !within)) as usize;
            }
        }
        let share = |a: usize, b: usize| a as f64 / b as f64;
        m.l2_all = l2_all / n as f64;
        m.l2_visible = l2_visible / visible_count as f64;
        m.occlusion_accuracy = share(agree, n);
        for k in 0..5 {
            m.within_visible[k] = share(within_visible[k], visible_count);
            m.jaccard[k] = share(true_pos[k], visible_count + false_pos[k]);
            m.apd_all += share(within_all[k], n) / 5.0;
        }
        m.apd_visible = m.within_visible.iter().sum::<f64>() / 5.0;
        m.average_jaccard = m.jaccard.iter().sum::<f64>() / 5.0;
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

    /// The metrics of `predicted` (one track per true one, in the same order).
    pub fn metrics(&self, predicted: &[Track]) -> Result<TrackingMetrics> {
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
        TrackingMetrics::of(
            CameraTracks { positions: &truth, occluded: &truth_hidden },
            CameraTracks { positions: &pred, occluded: &pred_hidden },
            self.camera.fx as f64,
            self.camera.fy as f64,
        )
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
/// their points) and
/// scores the tracker, the static baseline and the truth; returns the report and the
/// predicted tracks.
pub fn evaluate_scene(
    tracker: &Tracker,
    name: &str,
    tokens: &Tensor,
    token_points: &Tensor,
    scene: &TrackingScene,
) -> Result<(TrackingReport, Vec<Track>)> {
    let queries: Vec<[f32; 3]> = scene.truth.iter().map(|t| t[0]).collect();
    let predicted = tracker.predict(tokens, token_points, &queries, scene.colours)?;
    let still: Vec<Track> = queries.iter().map(|&q| [q; FRAMES]).collect();
    let report = TrackingReport {
        name: name.to_string(),
        queries: queries.len(),
        tracker: scene.metrics(&predicted)?,
        static_baseline: scene.metrics(&still)?,
        truth: scene.metrics(scene.truth)?,
    };
    Ok((report, predicted))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn approx(a: f64, b: f64) {
        assert!((a - b).abs() < 1e-12, "{a} vs {b}");
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
        let m = TrackingMetrics::of(
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
    /// fx and fy); a truth behind the camera has none.
    #[test]
    fn thresholds_scale_with_depth_and_focal_length() {
        let one = |truth: [f64; 3], off: f64, fx: f64, fy: f64| {
            let pred = [[truth[0] + off, truth[1], truth[2]]];
            TrackingMetrics::of(
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
        approx(one([0.0, 0.0, -4.0], 0.0, 100.0, 100.0), 0.0);
    }

    /// Out-of-frame and occluded points count only through the metrics that take every point,
    /// and a prediction that says so gains occlusion accuracy and Jaccard.
    #[test]
    fn occluded_points_leave_the_visible_metrics() {
        let truth = [[0.0, 0.0, 1.0], [5.0, 0.0, 1.0]];
        let far = [[0.0, 0.0, 1.0], [9.0, 0.0, 1.0]];
        let t_occ = [false, true];
        let run = |p_occ: &[bool]| {
            TrackingMetrics::of(
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
        assert!(TrackingMetrics::of(hidden, ok, 1.0, 1.0)
            .unwrap_err()
            .to_string()
            .contains("shows no point"));
        let nan = [[f64::NAN, 0.0, 1.0]];
        let bad = CameraTracks { positions: &nan, occluded: &[false] };
        assert!(TrackingMetrics::of(ok, bad, 1.0, 1.0).unwrap_err().to_string().contains("finite"));
        assert!(TrackingMetrics::of(ok, ok, 0.0, 1.0).unwrap_err().to_string().contains("focal"));
        let short = CameraTracks { positions: &[], occluded: &[] };
        assert!(TrackingMetrics::of(ok, short, 1.0, 1.0).is_err());
    }

    #[test]
    fn the_mean_is_per_metric() {
        let a = TrackingMetrics { l2_all: 1.0, jaccard: [1.0; 5], ..Default::default() };
        let b = TrackingMetrics { l2_all: 3.0, ..Default::default() };
        let m = TrackingMetrics::mean(&[a, b]);
        approx(m.l2_all, 2.0);
        approx(m.jaccard[4], 0.5);
    }
}
