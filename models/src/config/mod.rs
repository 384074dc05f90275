//! Model sizes. Every number of docs/models.md is a field here, never a constant in code; `paper`
//! holds the paper's sizes, `small` a model that trains in minutes on one scene, `tiny` one
//! for tests. Configs are JSON (serde), stored in every checkpoint.

//!
//! One file per model family; the checks they share (sizes and numbers within their bounds,
//! attention widths that split into compiled head widths, config files read and validated) are
//! here.

use velox_engine::{Error, Result};

/// `sizes!(root; a.b: least, most; ...)`: each size field of `root` within its bounds, named in
/// the error by its path as written here, so a field and its message cannot part.
macro_rules! sizes {
    ($root:expr; $($($f:ident).+ : $lo:expr, $hi:expr);+ $(;)?) => {
        super::check_sizes(&[$((stringify!($($f).+), $root.$($f).+, $lo, $hi)),+])
    };
}

/// `numbers!(root; a.b: least, most, least allowed; ...)`: each number field of `root` finite and
/// in its range, named by its path as `sizes!` does.
macro_rules! numbers {
    ($root:expr; $($($f:ident).+ : $lo:expr, $hi:expr, $closed:expr);+ $(;)?) => {
        super::check_numbers(&[$((stringify!($($f).+), $root.$($f).+ as f64, $lo, $hi, $closed)),+])
    };
}

mod autoencoder;
mod generator;
mod tracker;
mod voxels;

pub use autoencoder::*;
pub use generator::*;
pub use tracker::*;
pub use voxels::*;

/// Reads a config JSON file and validates it; errors name the file.
fn read_config_file<T: serde::de::DeserializeOwned>(path: &str, validate: fn(&T) -> Result<()>) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        Error::Invalid(format!(
            "config {path:?} is not paper, small or tiny, and cannot be read as a file: {e}"
        ))
    })?;
    let c: T = serde_json::from_str(&text).map_err(|e| Error::Invalid(format!("config file {path}: {e}")))?;
    validate(&c).map_err(|e| match e {
        Error::Invalid(why) => Error::Invalid(format!("config file {path}: {why}")),
        other => other,
    })?;
    Ok(c)
}

/// An attention layer of `width` splits into `heads` of a width the kernels are compiled for.
fn heads_ok(what: &str, width: usize, heads: usize) -> Result<()> {
    if heads == 0 || !width.is_multiple_of(heads) {
        return Err(Error::Invalid(format!("{what}: width {width} does not split into {heads} heads")));
    }
    let d = width / heads;
    if !velox_engine::ops::attention::HEAD_DIMS.contains(&d) {
        return Err(Error::Invalid(format!(
            "{what}: head width {d} has no attention kernel (compiled: {:?})",
            velox_engine::ops::attention::HEAD_DIMS
        )));
    }
    Ok(())
}

/// Every `(name, value, least, most)` size within its bounds.
fn check_sizes<S: AsRef<str>>(sizes: &[(S, usize, usize, usize)]) -> Result<()> {
    for (name, v, lo, hi) in sizes {
        let (name, v, lo, hi) = (name.as_ref(), *v, *lo, *hi);
        if !(lo..=hi).contains(&v) {
            return Err(Error::Invalid(format!("config: {name} is {v}, expected {lo} to {hi}")));
        }
    }
    Ok(())
}

/// Every `(name, value, least, most, whether the least itself is allowed)` number finite and
/// in its range.
fn check_numbers(numbers: &[(&str, f64, f64, f64, bool)]) -> Result<()> {
    for &(name, v, lo, hi, closed) in numbers {
        let above = if closed { v >= lo } else { v > lo };
        if !(v.is_finite() && above && v <= hi) {
            let open = if closed { "[" } else { "(" };
            return Err(Error::Invalid(format!(
                "config: {name} is {v}, expected a number in {open}{lo}, {hi}]"
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn named_configs_are_valid_and_round_trip_through_json() {
        for name in ["paper", "small", "tiny"] {
            let c = AutoencoderConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: AutoencoderConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        assert!(AutoencoderConfig::named("/no/such/config.json")
            .unwrap_err()
            .to_string()
            .contains("paper, small or tiny"));
        let mut c = AutoencoderConfig::tiny();
        c.encoder.heads = 3;
        assert!(c.validate().is_err());
    }

    #[test]
    fn generator_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = GeneratorConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: GeneratorConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        assert_eq!(GeneratorConfig::paper().cond_width(), 2065);
        assert_eq!(GeneratorConfig::paper().cond_tokens(), 34656);
        let bad = |f: fn(&mut GeneratorConfig)| {
            let mut c = GeneratorConfig::small();
            f(&mut c);
            c.validate().unwrap_err().to_string()
        };
        assert!(bad(|c| c.image_size = 50).contains("multiple of the 14-pixel patch"));
        assert!(bad(|c| c.heads = 3).contains("heads"));
        assert!(bad(|c| c.cond_dropout = 1.5).contains("cond_dropout"));
        assert!(bad(|c| c.token_mean = vec![0.0; 3]).contains("statistics"));
        let c = GeneratorConfig {
            token_dim: 2,
            token_mean: vec![1.0, -2.0],
            token_std: vec![2.0, 0.5],
            ..GeneratorConfig::tiny()
        };
        assert_eq!(c.normalise(&[3.0, -1.0, 1.0, -2.0]), vec![1.0, 2.0, 0.0, 0.0]);
        assert_eq!(c.denormalise(&[1.0, 2.0, 0.0, 0.0]), vec![3.0, -1.0, 1.0, -2.0]);
    }

    #[test]
    fn tracker_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = TrackerConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: TrackerConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        let mut c = TrackerConfig::tiny();
        c.heads = 3;
        assert!(c.validate().unwrap_err().to_string().contains("heads"));
        let mut c = TrackerConfig::tiny();
        c.queries_per_sample = 0;
        assert!(c.validate().unwrap_err().to_string().contains("queries_per_sample"));
        let mut c = TrackerConfig::tiny();
        c.peak_lr = f64::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("peak_lr"));
    }

    #[test]
    fn voxel_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = VoxelConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: VoxelConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        let mut c = VoxelConfig::tiny();
        c.cells = 12;
        assert!(c.validate().unwrap_err().to_string().contains("divide 64"));
        let mut c = VoxelConfig::tiny();
        c.fine.window_cells = 100;
        assert!(c.validate().unwrap_err().to_string().contains("fine.window_cells"));
        let mut c = VoxelConfig::tiny();
        c.loss = OccupancyLoss::Focal { gamma: 0.5 };
        assert!(c.validate().unwrap_err().to_string().contains("gamma"));
        c.loss = OccupancyLoss::Focal { gamma: 2.0 };
        c.threshold = f32::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("threshold"));
    }
}
