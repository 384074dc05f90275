//! Gaussians as a dict of float32 arrays, their 3D Gaussian splatting PLY files, and renders.
//!
//! The dict holds `means` [N, 3], `quats` [N, 4] (w, x, y, z), `colors` [N, 3] (RGB), and the
//! scales and opacities either as values (`scales` [N, 3], positive; `opacities` [N], in
//! (0, 1)), the default, or as the PLY stores them (`log_scales`, `opacity_logits`), with
//! `raw=True`: these pass through a file unchanged to the bit, where the values' exp/log
//! round trip may move the last bit. A dict given to a function holds one pair or the other.
//! Gaussians with higher spherical harmonics (degrees 1 to 3) also hold `sh` [N, 3, K]
//! (K = 3, 8 or 15 coefficients past degree 0 per channel, as the PLY's f_rest orders them),
//! which `read_gaussians` gives and `write_gaussians` writes and `render` draws along the view.

use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_engine::ops::raster::{render_view, Camera, GaussianData};
use velox_engine::Tensor;

use crate::arrays::{f32_array, to_array};
use crate::device::{gpu_of, Device};
use crate::errors::{self, invalid};

/// The host Gaussians a dict holds (see the module docs), checked.
pub fn from_dict(g: &Bound<'_, PyAny>) -> PyResult<GaussianData> {
    let d = g.cast::<PyDict>().map_err(|_| {
        invalid("gaussians must be a dict of numpy float32 arrays (means, scales, quats, opacities, colors)")
    })?;
    let get = |key: &str| d.get_item(key);
    let field = |key: &str, width: Option<usize>| -> PyResult<Option<(Vec<f32>, usize)>> {
        let Some(value) = get(key)? else { return Ok(None) };
        let name = format!("gaussians[{key:?}]");
        let shape: Vec<Option<usize>> = match width {
            Some(w) => vec![None, Some(w)],
            None => vec![None],
        };
        let (v, s) = f32_array(&value, &name, &shape)?;
        Ok(Some((v, s[0])))
    };
    let need = |key: &str, width: Option<usize>| -> PyResult<(Vec<f32>, usize)> {
        field(key, width)?.ok_or_else(|| invalid(format!("gaussians has no {key:?} array")))
    };
    let (means, n) = need("means", Some(3))?;
    let (quats, nq) = need("quats", Some(4))?;
    let (colours, nc) = need("colors", Some(3))?;
    let one_of = |value: &str, raw: &str, width: Option<usize>| -> PyResult<(Vec<f32>, usize, bool)> {
        match (field(value, width)?, field(raw, width)?) {
            (Some((v, n)), None) => Ok((v, n, false)),
            (None, Some((v, n))) => Ok((v, n, true)),
            (Some(_), Some(_)) => {
                Err(invalid(format!("gaussians holds both {value:?} and {raw:?}: give one of them")))
            }
            (None, None) => Err(invalid(format!("gaussians has neither {value:?} nor {raw:?}"))),
        }
    };
    let (scales, ns, scales_raw) = one_of("scales", "log_scales", Some(3))?;
    let (opacities, no, opacities_raw) = one_of("opacities", "opacity_logits", None)?;
    for (key, m) in [("quats", nq), ("colors", nc), ("scales", ns), ("opacities", no)] {
        if m != n {
            return Err(invalid(format!("gaussians[{key:?}] has {m} rows, gaussians[\"means\"] has {n}")));
        }
    }
    let log_scales = if scales_raw {
        scales
    } else {
        if let Some(i) = scales.iter().position(|&s| s <= 0.0) {
            return Err(invalid(format!(
                "gaussians[\"scales\"][{}, {}] is {}: scales must be positive",
                i / 3,
                i % 3,
                scales[i]
            )));
        }
        scales.iter().map(|&s| (s as f64).ln() as f32).collect()
    };
    let opacities = if opacities_raw {
        opacities
    } else {
        if let Some(i) = opacities.iter().position(|&a| !(a > 0.0 && a < 1.0)) {
            return Err(invalid(format!(
                "gaussians[\"opacities\"][{i}] is {}: opacities must lie in (0, 1) (give \"opacity_logits\" \
                 for values the logit of 0 or 1 cannot hold)",
                opacities[i]
            )));
        }
        opacities.iter().map(|&a| (a as f64 / (1.0 - a as f64)).ln() as f32).collect()
    };
    let data = GaussianData { means, log_scales, quats, opacities, colours };
    data.check().map_err(errors::engine)?;
    Ok(data)
}

/// The dict of host Gaussians: values, or as the PLY stores them with `raw`.
pub fn to_dict<'py>(py: Python<'py>, g: GaussianData, raw: bool) -> PyResult<Bound<'py, PyDict>> {
    let n = g.len();
    let d = PyDict::new(py);
    d.set_item("means", to_array(py, g.means, &[n, 3])?)?;
    if raw {
        d.set_item("log_scales", to_array(py, g.log_scales, &[n, 3])?)?;
    } else {
        let scales = g.log_scales.iter().map(|&s| (s as f64).exp() as f32).collect();
        d.set_item("scales", to_array(py, scales, &[n, 3])?)?;
    }
    d.set_item("quats", to_array(py, g.quats, &[n, 4])?)?;
    if raw {
        d.set_item("opacity_logits", to_array(py, g.opacities, &[n])?)?;
    } else {
        let alpha = g.opacities.iter().map(|&l| (1.0 / (1.0 + (-(l as f64)).exp())) as f32).collect();
        d.set_item("opacities", to_array(py, alpha, &[n])?)?;
    }
    d.set_item("colors", to_array(py, g.colours, &[n, 3])?)?;
    Ok(d)
}

/// `velox.read_gaussians(path, raw=False)`: the Gaussians of a 3D Gaussian splatting PLY, with
/// `sh` when it holds higher spherical harmonics.
#[pyfunction]
#[pyo3(signature = (path, *, raw = false))]
fn read_gaussians(py: Python<'_>, path: std::path::PathBuf, raw: bool) -> PyResult<Bound<'_, PyDict>> {
    let (g, sh) = py.detach(|| velox_io::ply::read_sh(&path)).map_err(errors::engine)?;
    let n = g.len();
    let d = to_dict(py, g, raw)?;
    if let Some(sh) = sh {
        let k = velox_io::ply::Sh::per_channel(sh.degree);
        d.set_item("sh", to_array(py, sh.coeffs, &[n, 3, k])?)?;
    }
    Ok(d)
}

/// The higher spherical harmonics a dict holds (`sh` [N, 3, K], K = 3, 8 or 15), if any.
fn sh_of_dict(gaussians: &Bound<'_, PyAny>, n: usize) -> PyResult<Option<velox_io::ply::Sh>> {
    let Ok(d) = gaussians.cast::<PyDict>() else { return Ok(None) };
    let Some(value) = d.get_item("sh")? else { return Ok(None) };
    let (coeffs, shape) = f32_array(&value, "gaussians[\"sh\"]", &[Some(n), Some(3), None])?;
    let degree = [3, 8, 15].iter().position(|&k| k == shape[2]).map(|d| d + 1).ok_or_else(|| {
        invalid(format!(
            "gaussians[\"sh\"] has {} coefficients a channel: degrees 1, 2 and 3 have 3, 8 and 15",
            shape[2]
        ))
    })?;
    Ok(Some(velox_io::ply::Sh { degree, coeffs }))
}

/// `velox.write_gaussians(path, gaussians)`: the 3D Gaussian splatting PLY `velox render` and
/// splat viewers read (written atomically), with `sh` as f_rest_* when the dict holds it.
#[pyfunction]
fn write_gaussians(py: Python<'_>, path: std::path::PathBuf, gaussians: &Bound<'_, PyAny>) -> PyResult<()> {
    let g = from_dict(gaussians)?;
    let sh = sh_of_dict(gaussians, g.len())?;
    py.detach(|| {
        let bytes = velox_io::ply::to_bytes_sh(&g, sh.as_ref())?;
        velox_io::write_bytes(&path, &bytes)
    })
    .map_err(errors::engine)
}

/// A camera from its dict: `world_to_camera` [4, 4] (x_c = R x_w + t; camera x right, y down,
/// z forward) and the intrinsics `fx, fy, cx, cy` in pixels.
pub fn camera_of(camera: &Bound<'_, PyAny>, width: u32, height: u32) -> PyResult<Camera> {
    let d = camera.cast::<PyDict>().map_err(|_| {
        invalid("camera must be a dict of world_to_camera ([4, 4]) and fx, fy, cx, cy (pixels)")
    })?;
    let item = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        d.get_item(key)?.ok_or_else(|| invalid(format!("camera has no {key:?}")))
    };
    let m: Vec<Vec<f64>> = item("world_to_camera")?
        .extract()
        .map_err(|_| invalid("camera[\"world_to_camera\"] must be a 4 x 4 matrix of numbers"))?;
    if m.len() != 4 || m.iter().any(|r| r.len() != 4) {
        let rows: Vec<usize> = m.iter().map(Vec::len).collect();
        return Err(invalid(format!("camera[\"world_to_camera\"] must be 4 x 4, got rows of {rows:?}")));
    }
    if m[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(invalid(format!(
            "camera[\"world_to_camera\"]'s last row must be 0, 0, 0, 1, got {:?}",
            m[3]
        )));
    }
    let number = |key: &str| -> PyResult<f32> {
        item(key)?
            .extract::<f64>()
            .map(|v| v as f32)
            .map_err(|_| invalid(format!("camera[{key:?}] must be a number")))
    };
    let cam = Camera {
        width,
        height,
        fx: number("fx")?,
        fy: number("fy")?,
        cx: number("cx")?,
        cy: number("cy")?,
        rotation: [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[i][j] as f32)),
        translation: [0, 1, 2].map(|i| m[i][3] as f32),
    };
    let sound = [cam.fx, cam.fy].iter().all(|v| v.is_finite() && *v > 0.0)
        && [cam.cx, cam.cy].iter().all(|v| v.is_finite())
        && m.iter().flatten().all(|v| v.is_finite());
    if !sound {
        return Err(invalid(format!(
            "camera: fx, fy must be positive and every value finite, got fx {} fy {} cx {} cy {}",
            cam.fx, cam.fy, cam.cx, cam.cy
        )));
    }
    Ok(cam)
}

/// `velox.render(gaussians, camera, width, height, background=(0, 0, 0), alpha=False,
/// depth=False, device=None)`: RGB [H, W, 3] float32, the pixels `velox render` writes (before
/// they are rounded to 8 bits; `sh` in the dict colours each Gaussian along the view); with `alpha` or `depth`, a tuple that adds the coverage [H, W]
/// and the depth [H, W] (blended depth over coverage, 0 where nothing is drawn), in that
/// order.
#[pyfunction]
#[pyo3(signature = (gaussians, camera, width, height, *, background = (0.0, 0.0, 0.0), alpha = false, depth = false, device = None))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    gaussians: &Bound<'py, PyAny>,
    camera: &Bound<'py, PyAny>,
    width: u32,
    height: u32,
    background: (f32, f32, f32),
    alpha: bool,
    depth: bool,
    device: Option<&Bound<'py, Device>>,
) -> PyResult<Bound<'py, PyAny>> {
    let g = from_dict(gaussians)?;
    let sh = sh_of_dict(gaussians, g.len())?;
    let cam = camera_of(camera, width, height)?;
    let bg = [background.0, background.1, background.2];
    if bg.iter().any(|v| !v.is_finite()) {
        return Err(invalid(format!("background {bg:?} must be finite")));
    }
    let gpu = gpu_of(py, device)?;
    let (rgb, a, z) = py
        .detach(|| -> velox_engine::Result<_> {
            let rest = match &sh {
                Some(sh) => Some(Tensor::from_slice(&gpu, &[g.len(), sh.stride()], &sh.coeffs)?),
                None => None,
            };
            let harmonics = rest.as_ref().zip(sh.as_ref().map(|sh| sh.degree));
            let r = render_view(&gpu, &g.upload(&gpu)?, harmonics, &cam, bg)?;
            let rgb: Vec<f32> = r.image.rgb.read()?;
            let a: Vec<f32> = r.image.alpha.read()?;
            let d: Vec<f32> = r.image.depth.read()?;
            let z = d
                .iter()
                .zip(&a)
                .map(|(&d, &a)| if a > 1.0 / 255.0 { d / a } else { 0.0 })
                .collect::<Vec<_>>();
            Ok((rgb, a, z))
        })
        .map_err(errors::engine)?;
    let (h, w) = (height as usize, width as usize);
    let rgb = to_array(py, rgb, &[h, w, 3])?;
    if !alpha && !depth {
        return Ok(rgb);
    }
    let mut out = vec![rgb];
    if alpha {
        out.push(to_array(py, a, &[h, w])?);
    }
    if depth {
        out.push(to_array(py, z, &[h, w])?);
    }
    Ok(pyo3::types::PyTuple::new(py, out)?.into_any())
}

/// `velox.read_image(path)`: a PNG as float32 RGB [H, W, 3] in [0, 1] (the renders,
/// supervision views and GIF frames Velox writes).
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let (rgb, w, h) = py.detach(|| velox_io::image::read_png(&path)).map_err(errors::engine)?;
    to_array(py, rgb, &[h as usize, w as usize, 3])
}

/// `velox.write_image(path, rgb)`: float32 RGB [H, W, 3] in [0, 1] as an 8-bit PNG (values
/// clamped, then rounded), as `velox render` writes its frames.
#[pyfunction]
fn write_image(py: Python<'_>, path: std::path::PathBuf, rgb: &Bound<'_, PyAny>) -> PyResult<()> {
    let (values, shape) = f32_array(rgb, "rgb", &[None, None, Some(3)])?;
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    py.detach(|| velox_io::image::write_png(&path, &values, w, h)).map_err(errors::engine)
}

/// `velox.data.read_cloud(path)`: the 4D colour point cloud [N, 7] (x, y, z, r, g, b, tau) of
/// a scene folder (its points.ply), of a PLY file, or of an imported video folder (its RGBD
/// frames back-projected), validated.
#[pyfunction]
fn read_cloud<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let rows = py.detach(|| velox_data::format::read_cloud(&path)).map_err(errors::data)?;
    let n = rows.len() / 7;
    to_array(py, rows, &[n, 7])
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(write_image, m)?)?;
    m.add_function(wrap_pyfunction!(read_cloud, m)?)?;
    m.add_function(wrap_pyfunction!(read_gaussians, m)?)?;
    m.add_function(wrap_pyfunction!(write_gaussians, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    Ok(())
}
