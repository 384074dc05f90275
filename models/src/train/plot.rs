//! Line plots as PNG, labels in a small built-in bitmap font (no font files needed): loss
//! curves (`loss.png` of a training run: log-scale y with a line per decade, steps on x, each
//! series drawn faint as logged and bold as an exponential moving average of weight 0.1, since
//! losses of single random views and frames are noisy), and plain curves on a linear y
//! ([`curve_plot`]: the cloth evaluation's height, velocity and acceleration over the frames).

use std::path::Path;

use image::{Rgb, RgbImage};
use velox_engine::Result;

use super::log::Terms;
use velox_io::image::png_bytes;
use velox_io::write_bytes;

const W: u32 = 900;
const H: u32 = 480;
const LEFT: u32 = 70;
const RIGHT: u32 = 20;
const TOP: u32 = 20;
const BOTTOM: u32 = 50;
const BG: Rgb<u8> = Rgb([255, 255, 255]);
const AXIS: Rgb<u8> = Rgb([60, 60, 60]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);
/// Series colours, in order.
pub const COLOURS: [[u8; 3]; 4] = [[20, 20, 20], [31, 119, 180], [214, 39, 40], [44, 160, 44]];

/// 3 x 5 glyphs, one row per string, '#' set.
fn glyph(c: char) -> Option<[&'static str; 5]> {
    Some(match c {
        '0' => ["###", "#.#", "#.#", "#.#", "###"],
        '1' => [".#.", "##.", ".#.", ".#.", "###"],
        '2' => ["###", "..#", "###", "#..", "###"],
        '3' => ["###", "..#", ".##", "..#", "###"],
        '4' => ["#.#", "#.#", "###", "..#", "..#"],
        '5' => ["###", "#..", "###", "..#", "###"],
        '6' => ["###", "#..", "###", "#.#", "###"],
        '7' => ["###", "..#", ".#.", ".#.", ".#."],
        '8' => ["###", "#.#", "###", "#.#", "###"],
        '9' => ["###", "#.#", "###", "..#", "###"],
        '-' => ["...", "...", "###", "...", "..."],
        '.' => ["...", "...", "...", "...", ".#."],
        'a' => ["...", "##.", "..#", "###", "###"],
        'b' => ["#..", "#..", "###", "#.#", "###"],
        'd' => ["..#", "..#", "###", "#.#", "###"],
        'h' => ["#..", "#..", "###", "#.#", "#.#"],
        'v' => ["...", "#.#", "#.#", "#.#", ".#."],
        'y' => ["#.#", "#.#", "###", "..#", "###"],
        'c' => ["...", "###", "#..", "#..", "###"],
        'e' => ["###", "#.#", "###", "#..", "###"],
        'f' => [".##", "#..", "###", "#..", "#.."],
        'g' => ["###", "#.#", "###", "..#", "##."],
        'i' => [".#.", "...", ".#.", ".#.", ".#."],
        'k' => ["#..", "#.#", "##.", "#.#", "#.#"],
        'l' => ["#..", "#..", "#..", "#..", "###"],
        'm' => ["...", "###", "###", "#.#", "#.#"],
        'n' => ["...", "##.", "#.#", "#.#", "#.#"],
        'o' => ["...", "###", "#.#", "#.#", "###"],
        'p' => ["###", "#.#", "###", "#..", "#.."],
        'r' => ["...", "###", "#..", "#..", "#.."],
        's' => ["###", "#..", "###", "..#", "###"],
        't' => ["#..", "###", "#..", "#..", "###"],
        'u' => ["...", "#.#", "#.#", "#.#", "###"],
        'x' => ["...", "#.#", ".#.", "#.#", "#.#"],
        ' ' => ["...", "...", "...", "...", "..."],
        _ => return None,
    })
}

/// Draws `text` with its top-left corner at (x, y), each font pixel `scale` pixels wide.
fn text(img: &mut RgbImage, x: u32, y: u32, s: &str, colour: Rgb<u8>, scale: u32) {
    for (i, c) in s.chars().enumerate() {
        let Some(rows) = glyph(c) else { continue };
        for (r, row) in rows.iter().enumerate() {
            for (col, b) in row.bytes().enumerate() {
                if b == b'#' {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let px = x + (i as u32 * 4 + col as u32) * scale + dx;
                            let py = y + r as u32 * scale + dy;
                            if px < W && py < H {
                                img.put_pixel(px, py, colour);
                            }
                        }
                    }
                }
            }
        }
    }
}

fn line(img: &mut RgbImage, (x0, y0): (f64, f64), (x1, y1): (f64, f64), colour: Rgb<u8>) {
    let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let (x, y) = (x0 + t * (x1 - x0), y0 + t * (y1 - y0));
        if x >= 0.0 && y >= 0.0 && (x as u32) < W && (y as u32) < H {
            img.put_pixel(x as u32, y as u32, colour);
        }
    }
}

/// The y axis of a plot.
#[derive(Clone, Copy, PartialEq)]
enum Axis {
    /// Log scale, a line per decade; the series are smoothed as losses.
    Log,
    /// Linear, five lines from the lowest value to the highest.
    Linear,
}

/// Plots `series` (name, points of (step, value)) on a log scale; non-positive or non-finite
/// values are left out.
pub fn loss_plot(path: &Path, series: &[(&str, Vec<(f64, f64)>)]) -> Result<()> {
    plot(path, "step", series, Axis::Log)
}

/// Plots `series` (name, points of (x, value)) on a linear scale, `x_label` under the x axis
/// and `title` above the plot; non-finite values are left out.
pub fn curve_plot(path: &Path, title: &str, x_label: &str, series: &[(&str, Vec<(f64, f64)>)]) -> Result<()> {
    let mut img = draw(x_label, series, Axis::Linear);
    text(&mut img, LEFT, 4, title, AXIS, 2);
    write_bytes(path, &png_bytes(img.as_raw(), W, H)?)
}

fn plot(path: &Path, x_label: &str, series: &[(&str, Vec<(f64, f64)>)], axis: Axis) -> Result<()> {
    let img = draw(x_label, series, axis);
    write_bytes(path, &png_bytes(img.as_raw(), W, H)?)
}

fn draw(x_label: &str, series: &[(&str, Vec<(f64, f64)>)], axis: Axis) -> RgbImage {
    let mut img = RgbImage::from_pixel(W, H, BG);
    let shown = |v: f64| v.is_finite() && (axis == Axis::Linear || v > 0.0);
    // The y axis maps `f(v)` (log10 or v) linearly.
    let f = |v: f64| if axis == Axis::Log { v.log10() } else { v };
    let vals = series.iter().flat_map(|(_, p)| p.iter()).filter(|(_, v)| shown(*v));
    let (mut lo, mut hi, mut min_x, mut max_x) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, 1.0f64);
    for &(x, v) in vals {
        lo = lo.min(f(v));
        hi = hi.max(f(v));
        min_x = min_x.min(x);
        max_x = max_x.max(x);
    }
    if !lo.is_finite() {
        (lo, hi) = (-1.0, 0.0);
    }
    let min_x = if axis == Axis::Log || !min_x.is_finite() { 0.0 } else { min_x.min(max_x - 1e-9) };
    let (lo, hi) = match axis {
        Axis::Log => (lo.floor(), hi.ceil().max(lo.floor() + 1.0)),
        Axis::Linear => {
            let pad = 0.05 * (hi - lo).max(1e-9);
            (lo - pad, hi + pad)
        }
    };
    let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
    let px = |x: f64| LEFT as f64 + pw * (x - min_x) / (max_x - min_x);
    let py = |v: f64| TOP as f64 + ph * (hi - f(v)) / (hi - lo);
    match axis {
        Axis::Log => {
            for d in lo as i32..=hi as i32 {
                let y = py(10f64.powi(d));
                line(&mut img, (LEFT as f64, y), ((W - RIGHT) as f64, y), GRID);
                text(&mut img, 8, (y as u32).saturating_sub(5), &format!("1e{d}"), AXIS, 2);
            }
        }
        Axis::Linear => {
            for i in 0..=4 {
                let v = lo + (hi - lo) * i as f64 / 4.0;
                let y = py(v);
                line(&mut img, (LEFT as f64, y), ((W - RIGHT) as f64, y), GRID);
                text(&mut img, 4, (y as u32).saturating_sub(5), &format!("{v:.2}"), AXIS, 2);
            }
        }
    }
    for i in 0..=4 {
        let step = min_x + (max_x - min_x) * i as f64 / 4.0;
        let x = px(step);
        line(&mut img, (x, TOP as f64), (x, (H - BOTTOM) as f64), GRID);
        text(
            &mut img,
            (x as u32).saturating_sub(8),
            H - BOTTOM + 8,
            &format!("{}", step.round() as i64),
            AXIS,
            2,
        );
    }
    text(&mut img, W / 2 - 24, H - 18, x_label, AXIS, 2);
    line(&mut img, (LEFT as f64, TOP as f64), (LEFT as f64, (H - BOTTOM) as f64), AXIS);
    line(&mut img, (LEFT as f64, (H - BOTTOM) as f64), ((W - RIGHT) as f64, (H - BOTTOM) as f64), AXIS);
    for (i, (name, points)) in series.iter().enumerate() {
        let colour = Rgb(COLOURS[i % COLOURS.len()]);
        // Two thirds of the way to white.
        let faint = Rgb(colour.0.map(|c| ((c as u16 + 2 * 255) / 3) as u8));
        let mut smooth: Vec<(f64, f64)> = Vec::with_capacity(points.len());
        let mut ema: Option<f64> = None;
        for &(x, v) in points {
            if shown(v) {
                // Averaged in log space, as the axis is.
                let l = v.ln();
                let e = ema.map_or(l, |e| 0.9 * e + 0.1 * l);
                ema = Some(e);
                smooth.push((x, e.exp()));
            }
        }
        // Losses: faint as logged, bold smoothed; curves: as they are.
        let passes = match axis {
            Axis::Log => [(points.as_slice(), faint), (smooth.as_slice(), colour)],
            Axis::Linear => [(points.as_slice(), colour), (&[][..], colour)],
        };
        for (pts, c) in passes {
            let mut prev: Option<(f64, f64)> = None;
            for &(x, v) in pts {
                if !shown(v) {
                    prev = None;
                    continue;
                }
                let p = (px(x), py(v));
                if let Some(q) = prev {
                    line(&mut img, q, p, c);
                }
                prev = Some(p);
            }
        }
        let (lx, ly) = (W - RIGHT - 150, TOP + 10 + 16 * i as u32);
        for dy in 0..8 {
            for dx in 0..14 {
                img.put_pixel(lx + dx, ly + dy, colour);
            }
        }
        text(&mut img, lx + 20, ly - 1, name, AXIS, 2);
    }
    img
}

/// Plots every loss term of a run's log (its `(step, terms)` history) against the step, in the
/// order of the last line's terms (the total first).
pub fn plot_log(path: &Path, history: &[(u64, Terms)]) -> Result<()> {
    let names: Vec<&str> =
        history.last().map_or(Vec::new(), |l| l.1 .0.iter().map(|t| t.0.as_str()).collect());
    let series: Vec<(&str, Vec<(f64, f64)>)> = names
        .iter()
        .map(|&name| {
            let points =
                history.iter().filter_map(|(step, loss)| Some((*step as f64, loss.get(name)?))).collect();
            (name, points)
        })
        .collect();
    loss_plot(path, &series)
}
