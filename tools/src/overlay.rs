//! Tracks drawn over video frames, for a person to read: each query's path up to the frame
//! as a line in its own colour (a hue from where it lies in the first frame, so neighbours
//! share a colour), solid where the point is visible and faded where it is occluded, with a
//! dot at the frame's position.

use velox_engine::ops::raster::Camera;
use velox_models::velox::tracker::Track;
use velox_tasks::view::{points_as_gaussians, POINT_GREY};

/// A fully saturated colour for hue `h` in [0, 1).
fn hue(h: f32) -> [f32; 3] {
    let k = |n: f32| {
        let x = (n + h * 6.0) % 6.0;
        1.0 - (x.min(4.0 - x).clamp(0.0, 1.0))
    };
    [k(5.0), k(3.0), k(1.0)]
}

/// Each track's colour: its hue from the first frame's pixel column and row.
pub fn colours(tracks: &[Track], camera: &Camera) -> Vec<[f32; 3]> {
    tracks
        .iter()
        .map(|t| {
            let (u, v, _) = camera.project(t[0]);
            let (x, y) = (u / camera.width as f32, v / camera.height as f32);
            let c = hue((0.85 * x.clamp(0.0, 1.0) + 0.15 * y.clamp(0.0, 1.0)).fract());
            c.map(|c| 0.25 + 0.75 * c)
        })
        .collect()
}

/// Blends `colour` with weight `alpha` into pixel (x, y) of `rgb` (`[h, w, 3]`), if inside.
fn plot(rgb: &mut [f32], w: usize, h: usize, x: i64, y: i64, colour: [f32; 3], alpha: f32) {
    if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
        return;
    }
    let i = 3 * (y as usize * w + x as usize);
    for k in 0..3 {
        rgb[i + k] = (1.0 - alpha) * rgb[i + k] + alpha * colour[k];
    }
}

/// The pixels of a line from a to b (pixel coordinates), one per step of the longer axis.
fn line(a: (f32, f32), b: (f32, f32), w: usize, h: usize, out: &mut Vec<(i64, i64)>) {
    let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).clamp(1, 4 * (w + h));
    for s in 0..=steps {
        let t = s as f32 / steps as f32;
        out.push(((a.0 + t * (b.0 - a.0)).floor() as i64, (a.1 + t * (b.1 - a.1)).floor() as i64));
    }
}

/// Draws `tracks` (world positions per frame) over `rgb`, the video's frame `frame` seen by
/// `camera`: each path from frame 0 to `frame`, faded where `hidden[track][f]`, and a dot at
/// the frame's position (hollow when hidden). A pixel a path crosses several times is blended
/// once, at its most opaque, so a slow track's faded stretch stays faded.
pub fn draw_tracks(
    rgb: &mut [f32],
    camera: &Camera,
    tracks: &[Track],
    hidden: &[[bool; 24]],
    colours: &[[f32; 3]],
    frame: usize,
) {
    let (w, h) = (camera.width as usize, camera.height as usize);
    for ((t, hid), &c) in tracks.iter().zip(hidden).zip(colours) {
        let px = |f: usize| {
            let (u, v, _) = camera.project(t[f]);
            (u, v)
        };
        let mut marks: Vec<(i64, i64, f32)> = Vec::new();
        let mut pixels = Vec::new();
        for f in 1..=frame {
            let alpha = if hid[f] || hid[f - 1] { 0.3 } else { 0.9 };
            pixels.clear();
            line(px(f - 1), px(f), w, h, &mut pixels);
            marks.extend(pixels.iter().map(|&(x, y)| (x, y, alpha)));
        }
        let (u, v) = px(frame);
        let (x, y) = (u.floor() as i64, v.floor() as i64);
        for (dx, dy) in [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)] {
            if !(hid[frame] && (dx, dy) == (0, 0)) {
                marks.push((x + dx, y + dy, if hid[frame] { 0.5 } else { 1.0 }));
            }
        }
        // The most opaque mark of each pixel first, then one blend per pixel.
        marks.sort_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)).then(b.2.total_cmp(&a.2)));
        marks.dedup_by_key(|m| (m.0, m.1));
        for (x, y, alpha) in marks {
            plot(rgb, w, h, x, y, c, alpha);
        }
    }
}

/// Frames side by side (each `[h, w, 3]`, all of one size): one image `[h, n w, 3]`.
pub fn side_by_side(frames: &[Vec<f32>], w: usize, h: usize) -> Vec<f32> {
    let n = frames.len();
    let mut out = vec![0.0; h * n * w * 3];
    for (k, f) in frames.iter().enumerate() {
        for y in 0..h {
            let dst = 3 * (y * n * w + k * w);
            out[dst..dst + 3 * w].copy_from_slice(&f[3 * y * w..3 * (y + 1) * w]);
        }
    }
    out
}

/// `rgb` (`[h, w, 3]`) with each pixel a `k` x `k` block: `[k h, k w, 3]`.
pub fn enlarged(rgb: &[f32], w: usize, h: usize, k: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(rgb.len() * k * k);
    for y in 0..h * k {
        for x in 0..w * k {
            let i = 3 * ((y / k) * w + x / k);
            out.extend_from_slice(&rgb[i..i + 3]);
        }
    }
    out
}

/// Standard deviation of the Gaussian a decoded surface point is drawn as in a picture, in
/// scene units (the scenes span [-1, 1]).
pub const SURFACE_POINT_SIGMA: f32 = 0.012;

/// Points (xyz rows) drawn as small, nearly opaque light-grey Gaussians from `camera` on black:
/// `[h, w, 3]`.
pub fn splat_points(
    gpu: &velox_engine::Gpu,
    points: &[f32],
    camera: &velox_engine::ops::raster::Camera,
) -> crate::CliResult<Vec<f32>> {
    let grey = points.chunks_exact(3).map(|p| ([p[0], p[1], p[2]], POINT_GREY));
    let g = points_as_gaussians(grey, SURFACE_POINT_SIGMA, 3.0);
    if g.is_empty() {
        return Ok(vec![0.0; 3 * camera.width as usize * camera.height as usize]);
    }
    let image = velox_engine::ops::raster::render(gpu, &g.upload(gpu)?, camera, [0.0; 3])?;
    Ok(image.image.rgb.read()?)
}

/// The frames `frames` of a clip as an animated GIF at `gif`, each frame shown `delay_ms`: the
/// first supervision view of the dataset scene `scene` beside the pictures `panes(f, camera)`
/// makes of frame `f` from that view's camera (on black, as the data's images), enlarged by
/// the smallest whole factor that makes it at least [`GIF_MIN_WIDTH`] wide (each pixel a
/// square of pixels: no filtering blurs what is compared). With `pngs`, each frame also as
/// `fFF.png` in that folder, at the views' own size.
pub fn clip_gif(
    scene: &std::path::Path,
    frames: &[usize],
    mut panes: impl FnMut(usize, &velox_engine::ops::raster::Camera, [f32; 3]) -> crate::CliResult<Vec<Vec<f32>>>,
    gif: &std::path::Path,
    delay_ms: u32,
    pngs: Option<&std::path::Path>,
) -> crate::CliResult<()> {
    let scene = velox_data::format::read_scene(scene, true)?;
    let camera = scene.cameras.supervision[0];
    let (w, h) = (camera.width as usize, camera.height as usize);
    let views = scene.meta.supervision_views;
    if let Some(dir) = pngs {
        std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
    }
    let mut images = Vec::with_capacity(frames.len());
    let mut width = w;
    for &f in frames {
        let truth: Vec<f32> = scene.supervision[f * views].iter().map(|&b| b as f32 / 255.0).collect();
        let row: Vec<Vec<f32>> =
            std::iter::once(truth).chain(panes(f, &camera, scene.meta.background)?).collect();
        width = row.len() * w;
        let frame = side_by_side(&row, w, h);
        if let Some(dir) = pngs {
            velox_io::image::write_png(&dir.join(format!("f{f:02}.png")), &frame, width as u32, h as u32)?;
        }
        images.push(frame);
    }
    let k = GIF_MIN_WIDTH.div_ceil(width.max(1)).max(1);
    let images: Vec<Vec<f32>> = images.iter().map(|i| enlarged(i, width, h, k)).collect();
    velox_io::image::write_gif(gif, &images, (k * width) as u32, (k * h) as u32, delay_ms)?;
    Ok(())
}

/// The narrowest a clip's GIF is written: a few hundred pixels, so that views of tens of
/// pixels can be seen.
pub const GIF_MIN_WIDTH: usize = 256;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_track_is_drawn_where_the_camera_sees_it() {
        let cam = Camera::look_at([0.0, 0.0, -3.0], [0.0; 3], [0.0, 1.0, 0.0], 40.0, 32, 32);
        // A point moving along +x in the world, from the centre.
        let t: Track = std::array::from_fn(|f| [0.02 * f as f32, 0.0, 0.0]);
        let mut rgb = vec![0.0; 32 * 32 * 3];
        let colour = [[1.0, 0.0, 0.0]];
        draw_tracks(&mut rgb, &cam, &[t], &[[false; 24]], &colour, 23);
        let lit = |x: usize, y: usize| rgb[3 * (y * 32 + x)] > 0.5;
        let (u0, v0, _) = cam.project(t[0]);
        let (u1, v1, _) = cam.project(t[23]);
        assert!(lit(u0 as usize, v0 as usize) && lit(u1 as usize, v1 as usize));
        let lit_count = (0..32 * 32).filter(|i| rgb[3 * i] > 0.0).count();
        assert!(lit_count < 64, "{lit_count} pixels for a short path");
        // Hidden: the path is faded, the dot hollow.
        let mut faded = vec![0.0; 32 * 32 * 3];
        draw_tracks(&mut faded, &cam, &[t], &[[true; 24]], &colour, 23);
        assert!(faded[3 * (v1 as usize * 32 + u1 as usize)] < 0.5);
        let colours = colours(&[t], &cam);
        assert!(colours[0].iter().all(|c| (0.25..=1.0).contains(c)));
        let wide = side_by_side(&[rgb.clone(), faded], 32, 32);
        assert_eq!(&wide[..96], &rgb[..96]);
        let big = enlarged(&[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 2, 1, 2);
        assert_eq!(big.len(), 2 * 4 * 3);
        assert_eq!(&big[..6], &[0.1, 0.2, 0.3, 0.1, 0.2, 0.3]);
        assert_eq!(&big[12..18], &[0.1, 0.2, 0.3, 0.1, 0.2, 0.3]);
        assert_eq!(&big[18..], &[0.4, 0.5, 0.6, 0.4, 0.5, 0.6]);
    }
}
