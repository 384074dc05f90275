//! Textures for the objects: procedural patterns (checkers, value noise, stripes, gradients)
//! and random crops of a user's images (the paper's texture augmentation).

use std::path::{Path, PathBuf};

use velox_engine::rng::Rng;

use crate::mesh::{pack_rgb, Texture};
use crate::{DataError, DataResult};

/// Side of the procedural textures and of the image crops.
pub const TEXTURE_SIZE: u32 = 128;

fn random_colour(rng: &mut Rng) -> [f32; 3] {
    [rng.uniform() as f32, rng.uniform() as f32, rng.uniform() as f32]
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t)
}

/// One of the procedural patterns, drawn at random.
pub fn procedural(rng: &mut Rng) -> Texture {
    let n = TEXTURE_SIZE;
    let a = random_colour(rng);
    let b = random_colour(rng);
    let kind = rng.below(4);
    let texel: Box<dyn Fn(f32, f32) -> [f32; 3]> = match kind {
        0 => {
            let cells = 2 + rng.below(7) as i32;
            Box::new(move |u, v| {
                let c = ((u * cells as f32).floor() as i32 + (v * cells as f32).floor() as i32) & 1;
                if c == 0 {
                    a
                } else {
                    b
                }
            })
        }
        1 => {
            // Value noise: a random lattice, bilinear with smoothstep, two octaves; it wraps.
            let cells = 4 + rng.below(8) as usize;
            let grid: Vec<f32> = (0..cells * cells).map(|_| rng.uniform() as f32).collect();
            let fine: Vec<f32> = (0..4 * cells * cells).map(|_| rng.uniform() as f32).collect();
            let noise = move |g: &[f32], c: usize, u: f32, v: f32| {
                let (x, y) = (u * c as f32, v * c as f32);
                let (x0, y0) = (x.floor(), y.floor());
                let s = |t: f32| t * t * (3.0 - 2.0 * t);
                let (fx, fy) = (s(x - x0), s(y - y0));
                let at = |i: f32, j: f32| g[(j as usize % c) * c + (i as usize % c)];
                let top = at(x0, y0) + (at(x0 + 1.0, y0) - at(x0, y0)) * fx;
                let bot = at(x0, y0 + 1.0) + (at(x0 + 1.0, y0 + 1.0) - at(x0, y0 + 1.0)) * fx;
                top + (bot - top) * fy
            };
            Box::new(move |u, v| {
                let t = 0.7 * noise(&grid, cells, u, v) + 0.3 * noise(&fine, 2 * cells, u, v);
                mix(a, b, t)
            })
        }
        2 => {
            let count = 2.0 + rng.below(10) as f32;
            let angle = rng.range(0.0, std::f64::consts::PI) as f32;
            let (s, c) = angle.sin_cos();
            Box::new(move |u, v| if ((c * u + s * v) * count).fract().abs() < 0.5 { a } else { b })
        }
        _ => {
            let c = random_colour(rng);
            Box::new(move |u, v| mix(mix(a, b, u), c, v))
        }
    };
    let texels = (0..n * n)
        .map(|i| {
            let (x, y) = (i % n, i / n);
            pack_rgb(texel((x as f32 + 0.5) / n as f32, (y as f32 + 0.5) / n as f32))
        })
        .collect();
    Texture { width: n, height: n, texels }
}

/// A folder of images to crop textures from.
pub struct ImageFolder {
    files: Vec<PathBuf>,
}

impl ImageFolder {
    /// Lists the PNG and JPEG files of `dir` (not recursive), in name order.
    pub fn open(dir: &Path) -> DataResult<ImageFolder> {
        let read = std::fs::read_dir(dir)
            .map_err(|e| DataError::Io(format!("texture folder {}: {e}", dir.display())))?;
        let mut files: Vec<PathBuf> = read
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
            })
            .collect();
        files.sort();
        if files.is_empty() {
            return Err(DataError::Invalid(format!(
                "texture folder {} has no PNG or JPEG images",
                dir.display()
            )));
        }
        Ok(ImageFolder { files })
    }

    /// A random square crop (a quarter to all of the shorter side) of a random image, resized to
    /// [`TEXTURE_SIZE`]. An image that cannot be decoded is an error naming it.
    pub fn random_crop(&self, rng: &mut Rng) -> DataResult<Texture> {
        let path = &self.files[rng.below(self.files.len() as u32) as usize];
        let img = image::open(path)
            .map_err(|e| DataError::Invalid(format!("texture image {}: {e}", path.display())))?
            .to_rgb8();
        let (w, h) = img.dimensions();
        let short = w.min(h);
        let side = ((short as f64 * rng.range(0.25, 1.0)) as u32).max(1);
        let x = rng.below(w - side + 1);
        let y = rng.below(h - side + 1);
        let crop = image::imageops::crop_imm(&img, x, y, side, side).to_image();
        let n = TEXTURE_SIZE;
        let resized = image::imageops::resize(&crop, n, n, image::imageops::FilterType::Triangle);
        Ok(Texture::from_rgb8(n, n, resized.as_raw()))
    }
}
