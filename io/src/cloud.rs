//! The 4D colour point cloud every Velox model reads: N rows of (x, y, z, r, g, b, tau),
//! xyz in [-1, 1]^3, rgb in [0, 1], tau = frame / 100 (docs/models.md, Data conventions).

use velox_engine::{Error, Gpu, Result, Tensor};

/// Channels per point.
pub const CHANNELS: usize = 7;
/// Slack on the [-1, 1] bounds and the [0, 1] colours, for data normalised in f32.
pub const SLACK: f32 = 1e-3;

/// Checks host data before upload; the error names the first bad point and what is wrong.
/// Returns the number of points.
pub fn validate(data: &[f32]) -> Result<usize> {
    if data.is_empty() {
        return Err(Error::Invalid("the point cloud is empty".into()));
    }
    if !data.len().is_multiple_of(CHANNELS) {
        return Err(Error::Invalid(format!(
            "a point cloud has {CHANNELS} channels (x, y, z, r, g, b, tau) per point; {} values is not a whole number of points",
            data.len()
        )));
    }
    for (i, p) in data.chunks(CHANNELS).enumerate() {
        if let Some(c) = p.iter().position(|v| !v.is_finite()) {
            return Err(Error::Invalid(format!("point {i} has a non-finite value in channel {c}: {p:?}")));
        }
        if p[..3].iter().any(|v| v.abs() > 1.0 + SLACK) {
            return Err(Error::Invalid(format!(
                "point {i} at ({}, {}, {}) lies outside [-1, 1]^3: normalise the scene first",
                p[0], p[1], p[2]
            )));
        }
        if p[3..6].iter().any(|v| *v < -SLACK || *v > 1.0 + SLACK) {
            return Err(Error::Invalid(format!("point {i} has colour {:?} outside [0, 1]", &p[3..6])));
        }
        if p[6] < 0.0 {
            return Err(Error::Invalid(format!("point {i} has a negative frame time tau = {}", p[6])));
        }
    }
    Ok(data.len() / CHANNELS)
}

/// Validates and uploads a cloud as f32 `[N, 7]`.
pub fn upload(gpu: &Gpu, data: &[f32]) -> Result<Tensor> {
    let n = validate(data)?;
    Tensor::from_slice(gpu, &[n, CHANNELS], data)
}

/// The query points (x, y, z, tau; `[k, 4]` row-major) of the cloud's rows `picked` (the
/// encoder's query indices): what a token file stores beside the tokens.
pub fn query_points(data: &[f32], picked: &[u32]) -> Vec<f32> {
    picked
        .iter()
        .flat_map(|&q| {
            let p = &data[q as usize * CHANNELS..][..CHANNELS];
            [p[0], p[1], p[2], p[6]]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_clouds_are_named() {
        let ok = [0.1, -0.2, 0.3, 0.5, 0.5, 0.5, 0.01];
        assert_eq!(validate(&ok).unwrap(), 1);
        assert!(validate(&[]).unwrap_err().to_string().contains("empty"));
        assert!(validate(&ok[..6]).unwrap_err().to_string().contains("7 channels"));
        let mut nan = ok;
        nan[2] = f32::NAN;
        assert!(validate(&nan)
            .unwrap_err()
            .to_string()
            .contains("point 0 has a non-finite value in channel 2"));
        let mut far = ok;
        far[0] = 1.5;
        assert!(validate(&far).unwrap_err().to_string().contains("outside [-1, 1]^3"));
        let mut colour = ok;
        colour[4] = 2.0;
        assert!(validate(&colour).unwrap_err().to_string().contains("colour"));
        let mut tau = ok;
        tau[6] = -1.0;
        assert!(validate(&tau).unwrap_err().to_string().contains("negative frame time"));
    }
}
