//! Files for other tools: surface meshes (from points, read and written as PLY, OBJ or glTF),
//! decoded clips exported for other viewers, and video files imported through ffmpeg.
//!
//! A mesh is a dict of `positions` (float32 [V, 3]) and `triangles` (uint32 [T, 3],
//! counter-clockwise seen from outside).

use std::path::PathBuf;

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_io::mesh::{self, Mesh};

use crate::arrays::{f32_array, to_array};
use crate::errors::{self, invalid};

fn mesh_dict<'py>(py: Python<'py>, m: Mesh) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let (v, t) = (m.positions.len(), m.triangles.len());
    d.set_item("positions", to_array(py, m.positions.into_iter().flatten().collect(), &[v, 3])?)?;
    let triangles: Vec<u32> = m.triangles.into_iter().flatten().collect();
    d.set_item("triangles", PyArray1::from_vec(py, triangles).reshape(vec![t, 3])?)?;
    Ok(d)
}

fn mesh_of_dict(mesh: &Bound<'_, PyAny>) -> PyResult<Mesh> {
    let d = mesh.cast::<PyDict>().map_err(|_| invalid("mesh must be a dict of positions and triangles"))?;
    let item = |key: &str| d.get_item(key)?.ok_or_else(|| invalid(format!("mesh has no {key:?} array")));
    let (p, _) = f32_array(&item("positions")?, "mesh[\"positions\"]", &[None, Some(3)])?;
    let triangles = item("triangles")?;
    let untyped = triangles
        .cast::<PyUntypedArray>()
        .map_err(|_| invalid("mesh[\"triangles\"] must be a numpy array"))?;
    let shape = untyped.shape().to_vec();
    let typed =
        triangles.cast::<PyArrayDyn<u32>>().ok().filter(|_| shape.len() == 2 && shape[1] == 3).ok_or_else(
            || {
                let dtype = untyped.dtype().str().map(|s| s.to_string()).unwrap_or_default();
                invalid(format!(
                "mesh[\"triangles\"] must be a uint32 array of shape [N, 3], got {dtype} of shape {shape:?}"
            ))
            },
        )?;
    let t: Vec<u32> = typed.readonly().as_array().iter().copied().collect();
    let m = Mesh {
        positions: p.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        triangles: t.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
    };
    m.check().map_err(errors::engine)?;
    Ok(m)
}

/// `velox.mesh_of_points(points, resolution=96)`: the triangle mesh of the surface the points
/// ([N, 3] float32, a decoder's samples) lie on, as `velox decode mesh` makes each frame's.
#[pyfunction]
#[pyo3(signature = (points, *, resolution = 96))]
fn mesh_of_points<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    resolution: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let (xyz, _) = f32_array(points, "points", &[None, Some(3)])?;
    let m = py.detach(|| velox_data::surface::mesh_of_points(&xyz, resolution)).map_err(errors::data)?;
    mesh_dict(py, m)
}

/// `velox.read_mesh(path)`: a mesh from a .ply, .obj or .glb file.
#[pyfunction]
fn read_mesh(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyDict>> {
    let m = py.detach(|| mesh::read(&path)).map_err(errors::engine)?;
    mesh_dict(py, m)
}

/// `velox.write_mesh(path, mesh)`: writes a mesh in the format its extension names (.ply, .obj,
/// .glb), atomically.
#[pyfunction]
fn write_mesh(py: Python<'_>, path: PathBuf, mesh: &Bound<'_, PyAny>) -> PyResult<()> {
    let m = mesh_of_dict(mesh)?;
    let format = mesh::Format::of_path(&path).map_err(errors::engine)?;
    py.detach(|| mesh::write(&path, &m, format)).map_err(errors::engine)
}

/// `velox.export(dir, to, out=None, spz_version=3, scene=None)`: a folder of per-frame Gaussians
/// in the files other viewers play (`to`: "ply-seq", "splatv", "spz" or "glb"), as `velox
/// export` writes them; returns the files written.
#[pyfunction]
#[pyo3(signature = (dir, to, *, out = None, spz_version = 3, scene = None))]
fn export(
    py: Python<'_>,
    dir: PathBuf,
    to: &str,
    out: Option<PathBuf>,
    spz_version: u32,
    scene: Option<PathBuf>,
) -> PyResult<Vec<String>> {
    use velox_tasks::export::{export, ExportOptions, Format};
    let format = Format::named(to).map_err(errors::engine)?;
    let options = ExportOptions { format, out, spz_version, scene };
    let done = py.detach(|| export(&dir, &options)).map_err(errors::engine)?;
    Ok(done.files.iter().map(|f| f.display().to_string()).collect())
}

/// `velox.data.import_video(file, out, depth=None, intrinsics=None, fov=None, fps=None,
/// depth_scale=0.001, max_depth=None, windows=None)`: a video file's frames through ffmpeg, as
/// `velox import video` writes them: colour alone as `out/frame_00000.png`, ...; with a depth
/// video and the intrinsics (a JSON file, or `fov` degrees) the tracker's video. Returns the
/// frames decoded, their size and rate, and with depth what capture.json records.
#[pyfunction]
#[pyo3(signature = (file, out, *, depth = None, intrinsics = None, fov = None, fps = None, depth_scale = 0.001, max_depth = None, windows = None))]
#[allow(clippy::too_many_arguments)]
fn import_video<'py>(
    py: Python<'py>,
    file: PathBuf,
    out: PathBuf,
    depth: Option<PathBuf>,
    intrinsics: Option<PathBuf>,
    fov: Option<f64>,
    fps: Option<f64>,
    depth_scale: f64,
    max_depth: Option<f64>,
    windows: Option<usize>,
) -> PyResult<Bound<'py, PyDict>> {
    use velox_data::capture::CaptureOptions;
    use velox_data::video::{import_video, VideoOptions};
    let capture = CaptureOptions { depth_scale, max_depth, windows, fps: None };
    let options = VideoOptions { depth, intrinsics, fov_y: fov, fps, capture };
    let r = py.detach(|| import_video(&file, &out, &options)).map_err(errors::data)?;
    let d = PyDict::new(py);
    d.set_item("frames", r.frames)?;
    d.set_item("width", r.width)?;
    d.set_item("height", r.height)?;
    d.set_item("fps", r.fps)?;
    d.set_item("frames_dir", r.frames_dir.display().to_string())?;
    let capture = match &r.capture {
        Some(c) => {
            let text = serde_json::to_string(c).map_err(|e| invalid(e.to_string()))?;
            py.import("json")?.call_method1("loads", (text,))?.unbind()
        }
        None => py.None(),
    };
    d.set_item("capture", capture)?;
    Ok(d)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(mesh_of_points, m)?)?;
    m.add_function(wrap_pyfunction!(read_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(write_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(export, m)?)?;
    m.add_function(wrap_pyfunction!(import_video, m)?)?;
    Ok(())
}
