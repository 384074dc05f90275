//! Images as PNG (8 bits per channel, values in [0, 1] clamped and rounded, no gamma curve
//! applied: the rasteriser's colours are written as they are), sequences as animated GIF (the
//! same 8-bit values, each frame quantised to its own palette of 256 colours, looping), and
//! depth maps as single-channel f32 OpenEXR (channel `Z`).

use std::path::Path;

use velox_engine::{Error, Result};

use crate::{content_error, read_error, write_atomically, write_bytes};

fn check_len(what: &str, len: usize, width: u32, height: u32, channels: usize) -> Result<()> {
    if len != width as usize * height as usize * channels || width == 0 || height == 0 {
        return Err(Error::Shape(format!(
            "{what}: {len} values for a {width}x{height} image of {channels} channel(s)"
        )));
    }
    Ok(())
}

/// 8-bit values of RGB in [0, 1] (NaN as 0).
fn to_rgb8(rgb: &[f32]) -> Vec<u8> {
    rgb.iter().map(|&v| if v.is_nan() { 0 } else { (v.clamp(0.0, 1.0) * 255.0).round() as u8 }).collect()
}

/// Writes frames of row-major RGB `[H, W, 3]` in [0, 1] as an animated GIF that loops, each
/// frame shown for `delay_ms` milliseconds (GIF counts in hundredths of a second, so the delay
/// is rounded to 10 ms), atomically.
pub fn write_gif(path: &Path, frames: &[Vec<f32>], width: u32, height: u32, delay_ms: u32) -> Result<()> {
    if frames.is_empty() {
        return Err(Error::Shape("write_gif: no frames".into()));
    }
    let mut encoded = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        check_len(&format!("write_gif frame {i}"), f.len(), width, height, 3)?;
        let rgba: Vec<u8> = to_rgb8(f).chunks(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect();
        let buffer = image::RgbaImage::from_raw(width, height, rgba).expect("the length was checked");
        let delay = image::Delay::from_numer_denom_ms(delay_ms.div_ceil(10) * 10, 1);
        encoded.push(image::Frame::from_parts(buffer, 0, 0, delay));
    }
    let mut out = Vec::new();
    {
        let mut encoder = image::codecs::gif::GifEncoder::new_with_speed(&mut out, 10);
        let failed = |e: image::ImageError| Error::Invalid(format!("encoding a {width}x{height} GIF: {e}"));
        encoder.set_repeat(image::codecs::gif::Repeat::Infinite).map_err(failed)?;
        encoder.encode_frames(encoded).map_err(failed)?;
    }
    write_bytes(path, &out)
}

/// An animated GIF as read back: frames of row-major RGB in [0, 1] (composited as shown).
#[derive(Clone, Debug, PartialEq)]
pub struct Gif {
    pub frames: Vec<Vec<f32>>,
    pub width: u32,
    pub height: u32,
    /// Each frame's delay, in milliseconds.
    pub delays_ms: Vec<u32>,
}

/// Reads an animated GIF (for tests, and to check what was written).
pub fn read_gif(path: &Path) -> Result<Gif> {
    use image::AnimationDecoder;
    let file = std::fs::File::open(path).map_err(|e| read_error(path, e))?;
    let decoder = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(file))
        .map_err(|e| content_error(path, e))?;
    let frames = decoder.into_frames().collect_frames().map_err(|e| content_error(path, e))?;
    let (mut images, mut delays, mut size) = (Vec::new(), Vec::new(), (0, 0));
    for f in frames {
        let (n, d) = f.delay().numer_denom_ms();
        delays.push(n / d.max(1));
        let buffer = f.into_buffer();
        size = buffer.dimensions();
        images.push(buffer.pixels().flat_map(|p| [p[0], p[1], p[2]]).map(|b| b as f32 / 255.0).collect());
    }
    Ok(Gif { frames: images, width: size.0, height: size.1, delays_ms: delays })
}

/// Writes row-major RGB `[H, W, 3]` in [0, 1] as an 8-bit PNG (atomically, see
/// [`crate::write_atomically`]).
pub fn write_png(path: &Path, rgb: &[f32], width: u32, height: u32) -> Result<()> {
    check_len("write_png", rgb.len(), width, height, 3)?;
    write_bytes(path, &png_bytes(&to_rgb8(rgb), width, height)?)
}

/// The PNG file of 8-bit RGB rows `[H, W, 3]`, encoded in memory so that writing it is one
/// checked write of bytes.
pub fn png_bytes(rgb8: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    check_len("png_bytes", rgb8.len(), width, height, 3)?;
    let mut out = std::io::Cursor::new(Vec::new());
    image::write_buffer_with_format(
        &mut out,
        rgb8,
        width,
        height,
        image::ColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| Error::Invalid(format!("encoding a {width}x{height} PNG: {e}")))?;
    Ok(out.into_inner())
}

/// Reads a PNG as row-major RGB in [0, 1], with its width and height.
pub fn read_png(path: &Path) -> Result<(Vec<f32>, u32, u32)> {
    let img = image::ImageReader::open(path)
        .map_err(|e| read_error(path, e))?
        .with_guessed_format()
        .map_err(|e| content_error(path, e))?
        .decode()
        .map_err(|e| content_error(path, e))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok((img.into_raw().into_iter().map(|b| b as f32 / 255.0).collect(), w, h))
}

/// Writes a row-major depth map `[H, W]` as a one-channel (`Z`) f32 EXR.
pub fn write_exr_depth(path: &Path, depth: &[f32], width: u32, height: u32) -> Result<()> {
    use exr::prelude::*;
    check_len("write_exr_depth", depth.len(), width, height, 1)?;
    let w = width as usize;
    let channels = SpecificChannels::build()
        .with_channel("Z")
        .with_pixel_fn(|p: Vec2<usize>| (depth[p.y() * w + p.x()],));
    let img = Image::from_channels((w, height as usize), channels);
    write_atomically(path, |w| img.write().to_buffered(w).map_err(std::io::Error::other))
}

/// Reads the `Z` channel (or the only channel) of an EXR as f32, with its width and height.
pub fn read_exr_depth(path: &Path) -> Result<(Vec<f32>, u32, u32)> {
    let img = exr::prelude::read_first_flat_layer_from_file(path).map_err(|e| content_error(path, e))?;
    let size = img.layer_data.size;
    let list = &img.layer_data.channel_data.list;
    let ch = list
        .iter()
        .find(|c| c.name.to_string() == "Z")
        .or(if list.len() == 1 { list.first() } else { None })
        .ok_or_else(|| {
            Error::Invalid(format!("{}: no `Z` channel among {} channels", path.display(), list.len()))
        })?;
    Ok((ch.sample_data.values_as_f32().collect(), size.x() as u32, size.y() as u32))
}
