//! Loss curves as a PNG (`loss.png` of a training run): log-scale y with a line per decade,
//! steps on x, one coloured line per series with a legend, labels in a small built-in bitmap
//! font (no font files needed). Each series is drawn faint as logged and bold as an exponential
//! moving average (weight 0.1), since losses of single random views and frames are noisy.

use std::path::Path;

use image::{Rgb, RgbImage};
use velox_engine::Result;

use super::log::Terms;
use crate::files::image::png_bytes;
use crate::files::write_bytes;

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

/// Plots `series` (name, points of (step, value)) on a log scale; non-positive or non-finite
/// values are left out.
pub fn loss_plot(path: &Path, series: &[(&str, Vec<(f64, f64)>)]) -> Result<()> {
    let mut img = RgbImage::from_pixel(W, H, BG);
    let vals = series.iter().flat_map(|(_, p)| p.iter()).filter(|(_, v)| v.is_finite() && *v > 0.0);
    let (mut lo, mut hi, mut max_x) = (f64::INFINITY, f64::NEG_INFINITY, 1.0f64);
    for &(x, v) in vals {
        lo = lo.min(v.log10());
        hi = hi.max(v.log10());
        max_x = max_x.max(x);
    }
    if !lo.is_finite() {
        (lo, hi) = (-1.0, 0.0);
    }
    let (lo, hi) = (lo.floor(), hi.ceil().max(lo.floor() + 1.0));
    let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
    let px = |x: f64| LEFT as f64 + pw * x / max_x;
    let py = |v: f64| TOP as f64 + ph * (hi - v.log10()) / (hi - lo);
    for d in lo as i32..=hi as i32 {
        let y = py(10f64.powi(d));
        line(&mut img, (LEFT as f64, y), ((W - RIGHT) as f64, y), GRID);
        text(&mut img, 8, (y as u32).saturating_sub(5), &format!("1e{d}"), AXIS, 2);
    }
    for i in 0..=4 {
        let step = max_x * i as f64 / 4.0;
        let x = px(step);
        line(&mut img, (x, TOP as f64), (x, (H - BOTTOM) as f64), GRID);
        text(
            &mut img,
            (x as u32).saturating_sub(8),
            H - BOTTOM + 8,
            &format!("{}", step.round() as u64),
            AXIS,
            2,
        );
    }
    text(&mut img, W / 2 - 24, H - 18, "step", AXIS, 2);
    line(&mut img, (LEFT as f64, TOP as f64), (LEFT as f64, (H - BOTTOM) as f64), AXIS);
    line(&mut img, (LEFT as f64, (H - BOTTOM) as f64), ((W - RIGHT) as f64, (H - BOTTOM) as f64), AXIS);
    for (i, (name, points)) in series.iter().enumerate() {
        let colour = Rgb(COLOURS[i % COLOURS.len()]);
        // Two thirds of the way to white.
        let faint = Rgb(colour.0.map(|c| ((c as u16 + 2 * 255) / 3) as u8));
        let mut smooth: Vec<(f64, f64)> = Vec::with_capacity(points.len());
        let mut ema: Option<f64> = None;
        for &(x, v) in points {
            if v.is_finite() && v > 0.0 {
                // Averaged in log space, as the axis is.
                let l = v.ln();
                let e = ema.map_or(l, |e| 0.9 * e + 0.1 * l);
                ema = Some(e);
                smooth.push((x, e.exp()));
            }
        }
        for (pts, c) in [(points.as_slice(), faint), (smooth.as_slice(), colour)] {
            let mut prev: Option<(f64, f64)> = None;
            for &(x, v) in pts {
                if !(v.is_finite() && v > 0.0) {
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
    write_bytes(path, &png_bytes(img.as_raw(), W, H)?)
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
