//! `velox.metrics`: the paper's metrics on numpy arrays, by the code the evaluations use
//! (`velox_models::metrics`, `velox_models::eval::tracking`).

use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_models::eval::tracking::{benchmark_focal, CameraTracks, Scaling, TrackingMetrics};

use crate::arrays::{bool_array, f32_array};
use crate::errors::{self, invalid};

/// Two images of one shape, [H, W] or [H, W, C], values in [0, 1].
fn image_pair(
    image: &Bound<'_, PyAny>,
    reference: &Bound<'_, PyAny>,
) -> PyResult<(Vec<f32>, Vec<f32>, [usize; 3])> {
    let any = |a: &Bound<'_, PyAny>, name: &str| -> PyResult<(Vec<f32>, Vec<usize>)> {
        let rank = a.getattr("ndim").and_then(|n| n.extract::<usize>()).unwrap_or(3);
        f32_array(a, name, &vec![None; if rank == 2 { 2 } else { 3 }])
    };
    let (a, sa) = any(image, "image")?;
    let (b, sb) = any(reference, "reference")?;
    if sa != sb || sa.contains(&0) {
        return Err(invalid(format!("image {sa:?} and reference {sb:?} must have one non-empty shape")));
    }
    let c = if sa.len() == 3 { sa[2] } else { 1 };
    Ok((a, b, [sa[0], sa[1], c]))
}

/// `psnr(image, reference)`: PSNR in dB of two images in [0, 1] (scikit-image's
/// `peak_signal_noise_ratio(..., data_range=1)`); inf for equal images.
#[pyfunction]
fn psnr(image: &Bound<'_, PyAny>, reference: &Bound<'_, PyAny>) -> PyResult<f64> {
    let (a, b, _) = image_pair(image, reference)?;
    Ok(velox_models::metrics::psnr(&a, &b))
}

/// `ssim(image, reference)`: SSIM of two [H, W] or [H, W, C] images in [0, 1]: an 11 x 11
/// Gaussian window of sigma 1.5 (scikit-image's `structural_similarity(...,
/// gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)`).
#[pyfunction]
fn ssim(image: &Bound<'_, PyAny>, reference: &Bound<'_, PyAny>) -> PyResult<f64> {
    let (a, b, [h, w, c]) = image_pair(image, reference)?;
    Ok(velox_models::metrics::ssim(&a, &b, h, w, c))
}

fn points(a: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<[f32; 3]>> {
    let (v, s) = f32_array(a, name, &[None, Some(3)])?;
    if s[0] == 0 {
        return Err(invalid(format!("{name} must hold at least one point, got shape {s:?}")));
    }
    Ok(v.chunks(3).map(|p| [p[0], p[1], p[2]]).collect())
}

/// `chamfer(a, b)`: the symmetric Chamfer distance of two point sets [N, 3] and [M, 3]: mean
/// squared distance to the nearest point, both ways, summed (the paper's figures' form).
#[pyfunction]
fn chamfer(py: Python<'_>, a: &Bound<'_, PyAny>, b: &Bound<'_, PyAny>) -> PyResult<f64> {
    let (a, b) = (points(a, "a")?, points(b, "b")?);
    Ok(py.detach(|| velox_models::metrics::chamfer(&a, &b)))
}

/// `tapvid3d(pred_tracks, pred_visible, gt_tracks, gt_visible, intrinsics, image_size,
/// scaling="median")`: TAPVid-3D's metrics of predicted tracks against the truth, both
/// [Q, T, 3] in the camera's frame (metres, z forward) with visibility [Q, T] (bool), under a
/// camera of `intrinsics` (fx, fy, cx, cy) and `image_size` (width, height), the thresholds
/// in pixels of the benchmark's 256-pixel short side; `scaling` as the benchmark's
/// (`median`, `none`, `mean`, `per_trajectory`, `local_neighborhood`, `reproduce_2d`,
/// `median_on_queries`); `query_frames` [Q]: each track's query frame (default 0), which the
/// per-trajectory and query scalings read. A dict of `average_jaccard`, `apd_visible` (APD_3D), `occlusion_accuracy`,
/// `l2_all`, `l2_visible`, `apd_all`, `within_visible` and `jaccard` (per threshold).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
#[pyo3(signature = (pred_tracks, pred_visible, gt_tracks, gt_visible, intrinsics, image_size, *, scaling = "median", query_frames = None))]
fn tapvid3d<'py>(
    py: Python<'py>,
    pred_tracks: &Bound<'py, PyAny>,
    pred_visible: &Bound<'py, PyAny>,
    gt_tracks: &Bound<'py, PyAny>,
    gt_visible: &Bound<'py, PyAny>,
    intrinsics: (f64, f64, f64, f64),
    image_size: (u32, u32),
    scaling: &str,
    query_frames: Option<Vec<usize>>,
) -> PyResult<Bound<'py, PyDict>> {
    let (truth, shape) = f32_array(gt_tracks, "gt_tracks", &[None, None, Some(3)])?;
    let (q, t) = (shape[0], shape[1]);
    let (pred, _) = f32_array(pred_tracks, "pred_tracks", &[Some(q), Some(t), Some(3)])?;
    let (truth_visible, _) = bool_array(gt_visible, "gt_visible", &[Some(q), Some(t)])?;
    let (pred_visible, _) = bool_array(pred_visible, "pred_visible", &[Some(q), Some(t)])?;
    let scaling = Scaling::parse(scaling).map_err(errors::engine)?;
    let (fx, fy) = benchmark_focal(intrinsics.0, intrinsics.1, image_size.0, image_size.1);
    let xyz = |v: &[f32]| -> Vec<[f64; 3]> {
        v.chunks(3).map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect()
    };
    let (truth, pred) = (xyz(&truth), xyz(&pred));
    let hidden = |v: &[bool]| -> Vec<bool> { v.iter().map(|&s| !s).collect() };
    let (truth_hidden, pred_hidden) = (hidden(&truth_visible), hidden(&pred_visible));
    let query_frames = query_frames.unwrap_or_else(|| vec![0; q]);
    let m = TrackingMetrics::of_queries(
        CameraTracks { positions: &truth, occluded: &truth_hidden },
        CameraTracks { positions: &pred, occluded: &pred_hidden },
        t,
        &query_frames,
        fx,
        fy,
        scaling,
    )
    .map_err(errors::engine)?;
    metrics_dict(py, &m)
}

fn metrics_dict<'py>(py: Python<'py>, m: &TrackingMetrics) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("average_jaccard", m.average_jaccard)?;
    d.set_item("apd_visible", m.apd_visible)?;
    d.set_item("occlusion_accuracy", m.occlusion_accuracy)?;
    d.set_item("l2_all", m.l2_all)?;
    d.set_item("l2_visible", m.l2_visible)?;
    d.set_item("apd_all", m.apd_all)?;
    d.set_item("within_visible", m.within_visible.to_vec())?;
    d.set_item("jaccard", m.jaccard.to_vec())?;
    Ok(d)
}

/// `tapvid3d_files(ground_truth, predictions, scalings=("median",))`: TAPVid-3D's metrics of
/// a tracker's predictions on the benchmark's own clips, as `velox eval tapvid3d` computes
/// them: `ground_truth` and `predictions` are lists of `.npz` paths, clip i against prediction
/// i (tracks_XYZ [T, N, 3] and visibility [T, N]). Returns a dict of `clips` (per clip, a dict
/// per scaling) and `mean` (per scaling).
#[pyfunction]
#[pyo3(signature = (ground_truth, predictions, *, scalings = vec!["median".to_string()]))]
fn tapvid3d_files<'py>(
    py: Python<'py>,
    ground_truth: Vec<std::path::PathBuf>,
    predictions: Vec<std::path::PathBuf>,
    scalings: Vec<String>,
) -> PyResult<Bound<'py, PyDict>> {
    let parsed = scalings.iter().map(|s| Scaling::parse(s)).collect::<velox_engine::Result<Vec<_>>>();
    let parsed = parsed.map_err(errors::engine)?;
    let gt: Vec<&std::path::Path> = ground_truth.iter().map(|p| p.as_path()).collect();
    let pred: Vec<&std::path::Path> = predictions.iter().map(|p| p.as_path()).collect();
    let mut clips = Vec::new();
    let means = py
        .detach(|| velox_tasks::tapvid3d::evaluate(&gt, &pred, &parsed, &mut |_, m| clips.push(m.to_vec())))
        .map_err(errors::data)?;
    let per_scaling = |py: Python<'py>, ms: &[TrackingMetrics]| -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (name, m) in scalings.iter().zip(ms) {
            d.set_item(name, metrics_dict(py, m)?)?;
        }
        Ok(d)
    };
    let out = PyDict::new(py);
    out.set_item("clips", clips.iter().map(|c| per_scaling(py, c)).collect::<PyResult<Vec<_>>>()?)?;
    out.set_item("mean", per_scaling(py, &means)?)?;
    Ok(out)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(tapvid3d_files, m)?)?;
    m.add_function(wrap_pyfunction!(psnr, m)?)?;
    m.add_function(wrap_pyfunction!(ssim, m)?)?;
    m.add_function(wrap_pyfunction!(chamfer, m)?)?;
    m.add_function(wrap_pyfunction!(tapvid3d, m)?)?;
    Ok(())
}
