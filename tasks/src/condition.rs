//! The generators' condition: the frames of a video (a scene's `video/`, or any folder of PNG
//! frames) as the generator and DINOv2 read them.
//!
//! Frames are the folder's PNG files in name order (a scene's `video/fFF.png`; its depth files
//! are EXR and not read). A video task reads `frames` of them spread evenly over the folder (all
//! 24 of a scene's); the image task reads the first. Each frame is cropped to its centred
//! square, resized to `size x size` (a Catmull-Rom filter, as bicubic resizing does), and
//! normalised with the ImageNet mean and deviation DINOv2 was trained with, channel-major:
//! `[frames, 3, size, size]`.
//!
//! The world of a scene is already the generator's: the data pipeline places the conditioning
//! camera on +x looking at the origin (`camera::video_camera`), which is the paper's rotation of
//! the world about the object so that the conditioning camera lies on +x. A generated object is
//! therefore seen from +x in a user's video too.

use std::path::{Path, PathBuf};

use image::imageops::FilterType;
/// The image type of [`condition_frame`].
pub use image::RgbImage;
use velox_models::config::GenerationTask;
use velox_models::velox::dinov2::{IMAGENET_MEAN, IMAGENET_STD};

use velox_data::{DataError, DataResult};

/// The PNG frames of a folder, in name order.
pub fn frame_files(dir: &Path) -> DataResult<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| DataError::Io(format!("{}: {e}", dir.display())))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")))
        .collect();
    files.sort();
    Ok(files)
}

pub use velox_data::capture::spread;

/// The condition frames of the video in `dir`: `[frames, 3, size, size]` (see the module docs).
pub fn read_condition_video(dir: &Path, frames: usize, size: usize) -> DataResult<Vec<f32>> {
    if frames == 0 || size == 0 {
        return Err(DataError::Invalid(format!("a condition of {frames} frames of {size} pixels")));
    }
    let files = frame_files(dir)?;
    if files.len() < frames {
        return Err(DataError::Invalid(format!(
            "{}: the generator reads {frames} frame(s) and the folder has {} PNG file(s)",
            dir.display(),
            files.len()
        )));
    }
    let mut out = Vec::with_capacity(frames * 3 * size * size);
    for i in spread(files.len(), frames) {
        out.extend(read_frame(&files[i], size)?);
    }
    Ok(out)
}

/// The condition of `task` from `path`: a video folder (a dataset scene's `video/`, or any
/// folder of PNG frames) for either task (the image task reads its first frame), or one image
/// file for the image task.
pub fn read_condition(path: &Path, task: GenerationTask, size: usize) -> DataResult<Vec<f32>> {
    if path.is_dir() {
        let scene = path.join("meta.json").is_file();
        let frames = if scene { path.join("video") } else { path.to_path_buf() };
        return read_condition_video(&frames, task.frames(), size);
    }
    if task == GenerationTask::Video {
        return Err(DataError::Invalid(format!(
            "{}: this generator reads videos (a folder of frames), not one image",
            path.display()
        )));
    }
    read_frame(path, size)
}

/// One frame, cropped square, resized and normalised, `[3, size, size]`.
pub fn read_frame(path: &Path, size: usize) -> DataResult<Vec<f32>> {
    let img = image::open(path).map_err(|e| DataError::Io(format!("{}: {e}", path.display())))?.to_rgb8();
    condition_frame(&img, size).map_err(|e| DataError::Invalid(format!("{}: {e}", path.display())))
}

/// An image as a condition frame, cropped square, resized and normalised, `[3, size, size]`.
pub fn condition_frame(img: &image::RgbImage, size: usize) -> DataResult<Vec<f32>> {
    let (w, h) = img.dimensions();
    let side = w.min(h);
    if side == 0 {
        return Err(DataError::Invalid("an empty image".into()));
    }
    let square = image::imageops::crop_imm(img, (w - side) / 2, (h - side) / 2, side, side).to_image();
    let resized = if side as usize == size {
        square
    } else {
        image::imageops::resize(&square, size as u32, size as u32, FilterType::CatmullRom)
    };
    let mut out = vec![0.0f32; 3 * size * size];
    for (i, p) in resized.pixels().enumerate() {
        for c in 0..3 {
            out[c * size * size + i] = (p[c] as f32 / 255.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_spread_evenly_and_the_image_task_reads_the_first() {
        assert_eq!(spread(24, 24), (0..24).collect::<Vec<_>>());
        assert_eq!(spread(48, 24).first(), Some(&0));
        assert_eq!(spread(48, 24).last(), Some(&47));
        assert_eq!(spread(30, 1), vec![0]);
        let s = spread(100, 24);
        assert!(s.windows(2).all(|w| w[1] > w[0]));
    }

    #[test]
    fn frames_are_cropped_resized_and_normalised() {
        let dir = std::env::temp_dir().join(format!("velox-condition-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // 3 frames 40 x 20: a white centred square on red, the margins blue.
        for f in 0..3u8 {
            let img = image::RgbImage::from_fn(40, 20, |x, _| {
                if !(10..30).contains(&x) {
                    image::Rgb([0, 0, 255])
                } else {
                    image::Rgb([255, 10 * f, 0])
                }
            });
            img.save(dir.join(format!("f{f:02}.png"))).unwrap();
        }
        std::fs::write(dir.join("f00_depth.exr"), b"not read").unwrap();
        let px = read_condition_video(&dir, 2, 14).unwrap();
        assert_eq!(px.len(), 2 * 3 * 14 * 14);
        // Frame 0 then frame 2; the blue margins are cropped away.
        let red = (1.0 - IMAGENET_MEAN[0]) / IMAGENET_STD[0];
        let blue = (0.0 - IMAGENET_MEAN[2]) / IMAGENET_STD[2];
        assert!(px[..14 * 14].iter().all(|v| (v - red).abs() < 1e-5));
        assert!(px[2 * 14 * 14..3 * 14 * 14].iter().all(|v| (v - blue).abs() < 1e-5));
        let green2 = (20.0 / 255.0 - IMAGENET_MEAN[1]) / IMAGENET_STD[1];
        assert!(px[3 * 14 * 14 + 14 * 14..3 * 14 * 14 + 2 * 14 * 14]
            .iter()
            .all(|v| (v - green2).abs() < 2e-2));
        let err = read_condition_video(&dir, 5, 14).unwrap_err().to_string();
        assert!(err.contains("reads 5 frame(s)") && err.contains("has 3 PNG"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
