//! Physics of generated cloth (paper, cloth simulation): the centre of mass of the decoded
//! point cloud per frame against the simulation's, as `velox eval cloth` reports it.
//!
//! A frame's centre of mass is the mean of surface points sampled from the tokens (all of one
//! mass, as the simulation's particles are); its height is its component along the scene's up
//! vector (against gravity). The metric is the paper's "RMSE on the position of the center of
//! mass along the gravity direction": the root mean square over the clip's frames of the
//! generated height minus the simulated one, in scene units (a scene unit is half a metre,
//! `velox_data::cloth`, so 0.02 units are the paper's 1 cm; [`CM_PER_UNIT`]). Velocity and
//! acceleration along gravity are central differences of the heights (one-sided at the ends),
//! for the plots. Test: `heights_derivatives_and_rmse_by_hand`.

use serde::Serialize;
use velox_engine::{Error, Result};

/// Centimetres in a scene unit of the cloth data (half a metre).
pub const CM_PER_UNIT: f64 = 50.0;

/// The mean of `points` (xyz rows).
pub fn centre_of_mass(points: &[f32]) -> Result<[f64; 3]> {
    let n = points.len() / 3;
    if n == 0 || !points.len().is_multiple_of(3) {
        return Err(Error::Invalid(format!("a centre of mass of {} values", points.len())));
    }
    let mut c = [0.0f64; 3];
    for p in points.chunks_exact(3) {
        for k in 0..3 {
            c[k] += p[k] as f64;
        }
    }
    Ok(c.map(|v| v / n as f64))
}

/// Each centre's component along `up` (normalised here).
pub fn heights(centres: &[[f64; 3]], up: [f64; 3]) -> Result<Vec<f64>> {
    let len = (up[0] * up[0] + up[1] * up[1] + up[2] * up[2]).sqrt();
    if !(len.is_finite() && len > 0.0) {
        return Err(Error::Invalid(format!("the up vector {up:?} has no direction")));
    }
    Ok(centres.iter().map(|c| (c[0] * up[0] + c[1] * up[1] + c[2] * up[2]) / len).collect())
}

/// Root mean square of `a - b`.
pub fn rmse(a: &[f64], b: &[f64]) -> Result<f64> {
    if a.len() != b.len() || a.is_empty() {
        return Err(Error::Invalid(format!("an RMSE of {} values against {}", a.len(), b.len())));
    }
    Ok((a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>() / a.len() as f64).sqrt())
}

/// The derivative of samples `v` spaced `dt` apart: central differences, one-sided at the ends.
pub fn derivative(v: &[f64], dt: f64) -> Vec<f64> {
    let n = v.len();
    (0..n)
        .map(|i| match (i, n) {
            (_, 0 | 1) => 0.0,
            (0, _) => (v[1] - v[0]) / dt,
            (i, n) if i == n - 1 => (v[i] - v[i - 1]) / dt,
            (i, _) => (v[i + 1] - v[i - 1]) / (2.0 * dt),
        })
        .collect()
}

/// One scene's physics: the heights of the generated, the encoded (the encoder's tokens of the
/// scene, decoded the same way) and the simulated centre of mass per frame, and the RMSE of
/// each decoded one against the simulation.
#[derive(Clone, Debug, Serialize)]
pub struct ClothScene {
    pub scene: String,
    pub rmse_generated: f64,
    pub rmse_encoded: f64,
    pub generated: Vec<f64>,
    pub encoded: Vec<f64>,
    pub simulated: Vec<f64>,
}

impl ClothScene {
    pub fn new(
        scene: &str,
        generated: Vec<f64>,
        encoded: Vec<f64>,
        simulated: Vec<f64>,
    ) -> Result<ClothScene> {
        Ok(ClothScene {
            scene: scene.to_string(),
            rmse_generated: rmse(&generated, &simulated)?,
            rmse_encoded: rmse(&encoded, &simulated)?,
            generated,
            encoded,
            simulated,
        })
    }

    /// Height, velocity and acceleration along gravity over the frames, generated and encoded
    /// against simulated, as three PNG plots `PREFIX_height.png`, `_velocity.png`,
    /// `_acceleration.png`.
    pub fn plot(&self, prefix: &std::path::Path, dt: f64) -> Result<Vec<std::path::PathBuf>> {
        let frames = |v: &[f64]| v.iter().enumerate().map(|(f, &y)| (f as f64, y)).collect::<Vec<_>>();
        let mut written = Vec::new();
        let mut series = [self.simulated.clone(), self.generated.clone(), self.encoded.clone()];
        for (what, unit) in
            [("height", "units"), ("velocity", "units per s"), ("acceleration", "units per s2")]
        {
            let name = format!(
                "{}_{what}.png",
                prefix.file_name().map_or(String::new(), |n| n.to_string_lossy().into())
            );
            let path = prefix.with_file_name(name);
            let s = [
                ("simulated", frames(&series[0])),
                ("generated", frames(&series[1])),
                ("encoded", frames(&series[2])),
            ];
            crate::train::plot::curve_plot(&path, &format!("{what} along gravity {unit}"), "frame", &s)?;
            written.push(path);
            series = series.map(|v| derivative(&v, dt));
        }
        Ok(written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heights_derivatives_and_rmse_by_hand() {
        let c = centre_of_mass(&[0.0, 1.0, 2.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(c, [1.0, 2.0, 3.0]);
        let h = heights(&[[1.0, 2.0, 0.0], [0.0, 0.0, 5.0]], [0.0, 2.0, 0.0]).unwrap();
        assert_eq!(h, vec![2.0, 0.0]);
        assert!(heights(&[[0.0; 3]], [0.0; 3]).is_err());
        // Free fall y = 1 - 5 t^2 at dt = 0.1: central differences are exact for a parabola.
        let y: Vec<f64> = (0..6).map(|i| 1.0 - 5.0 * (0.1 * i as f64).powi(2)).collect();
        let v = derivative(&y, 0.1);
        assert!((v[2] - -2.0).abs() < 1e-12 && (v[3] - -3.0).abs() < 1e-12);
        let a = derivative(&v, 0.1);
        assert!((a[2] - -10.0).abs() < 1e-9, "{a:?}");
        assert!((rmse(&[1.0, 2.0], &[1.0, 4.0]).unwrap() - 2f64.sqrt()).abs() < 1e-15);
        assert!(rmse(&[1.0], &[]).is_err());
    }
}
