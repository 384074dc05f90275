//! `velox bench kernels`: matmul, softmax, scan, sort, scatter-add, row gathers, and the encoder's query
//! sampling: farthest point sampling and the nearest-query assignment.
//!
//! Errors: against the f64 reference over the whole output, except for matmuls too large for
//! a CPU reference, whose error is measured on a fixed random sample of output entries.

use velox_engine::ops::cast::cast;
use velox_engine::ops::{assign, fps, matmul, scan, scatter_add, softmax, sort};
use velox_engine::rng::Rng;
use velox_engine::{DType, Gpu, Result, Tensor};

use super::{print_header, print_row, time_gpu, Record, SizeSet};

/// A model-shaped f32 product: (what, m, n, k, a transposed).
type Shaped = (&'static str, usize, usize, usize, bool);

struct Sizes {
    matmul: Vec<usize>,
    /// Products shaped like the models' (narrow activations, weight gradients over many rows):
    /// the narrow-tile kernels and the split along K.
    shaped: Vec<Shaped>,
    softmax: Vec<(usize, usize)>,
    scan: Vec<usize>,
    sort: Vec<(usize, u32)>,
    scatter: Vec<(usize, usize, usize)>,
    /// Row gathers: (source rows, width, rows gathered).
    gather: Vec<(usize, usize, usize)>,
    /// Farthest point sampling: (candidates, chosen).
    fps: Vec<(usize, usize)>,
    /// Nearest-query assignment: (points, queries).
    assign: Vec<(usize, usize)>,
}

fn sizes(set: SizeSet) -> Sizes {
    if set.small() {
        Sizes {
            matmul: vec![128, 256],
            shaped: vec![
                ("narrow x@W", 10_000, 128, 32, false),
                ("narrow 64 x@W", 10_000, 64, 256, false),
                ("narrow 32 x@W", 10_000, 32, 128, false),
                ("weight grad x^T dy", 32, 32, 10_000, true),
            ],
            softmax: vec![(256, 1024)],
            scan: vec![1 << 20],
            sort: vec![(1 << 18, 32), (1 << 18, 16)],
            scatter: vec![(1 << 16, 8, 1024)],
            gather: vec![(10_000, 32, 10_000), (10_000, 64, 10_000)],
            fps: vec![(4096, 1024), (32768, 8192)],
            assign: vec![(100_000, 2048)],
        }
    } else {
        Sizes {
            matmul: vec![1024, 2048, 4096, 8192],
            shaped: vec![
                ("narrow x@W", 1 << 18, 32, 32, false),
                ("narrow 64 x@W", 1 << 18, 64, 256, false),
                ("tokens x@W", 8192, 2048, 512, false),
                ("weight grad x^T dy", 512, 512, 1 << 18, true),
            ],
            softmax: vec![(16384, 8192), (65536, 128)],
            scan: vec![1 << 26],
            sort: vec![(1 << 24, 32), (1 << 24, 16)],
            scatter: vec![(1 << 22, 32, 1 << 16)],
            gather: vec![(1 << 20, 32, 1 << 20), (1 << 20, 64, 1 << 20)],
            fps: vec![(4096, 1024), (32768, 8192)],
            assign: vec![(1_440_000, 8192)],
        }
    }
}

pub fn run(gpu: &Gpu, set: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let s = sizes(set);
    let c = gpu.caps();
    let peaks = c.known_peaks();
    let (roof16, roof32) = (super::Roof::of(c, true), super::Roof::of(c, false));
    let device = c.name.clone();
    let mut out = Vec::new();
    let mut rng = Rng::new(7);
    println!("device: {device} ({}); {repeats} timed repeats per case, median shown", c.kind);
    print_header();
    let mut push = |r: Record| {
        print_row(&r);
        out.push(r);
    };

    for &n in &s.matmul {
        for precision in [DType::F32, DType::F16] {
            let a = rng.normal_vec(n * n);
            let b = rng.normal_vec(n * n);
            let ta = Tensor::from_slice(gpu, &[n, n], &a)?;
            let tb = Tensor::from_slice(gpu, &[n, n], &b)?;
            let (ta, tb, a64, b64) = if precision == DType::F16 {
                let mut rec = gpu.recorder()?;
                let ha = cast(&mut rec, &ta, DType::F16)?;
                let hb = cast(&mut rec, &tb, DType::F16)?;
                rec.submit()?;
                // The reference multiplies the f16-rounded inputs: the error shown is the kernel's.
                let round =
                    |v: &[f32]| v.iter().map(|&x| half::f16::from_f32(x).to_f64()).collect::<Vec<f64>>();
                (ha, hb, round(&a), round(&b))
            } else {
                let wide = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
                (ta, tb, wide(&a), wide(&b))
            };
            // Sample up to 4096 entries (all of them for small n).
            let samples: Vec<(usize, usize)> = if n * n <= 4096 {
                (0..n * n).map(|i| (i / n, i % n)).collect()
            } else {
                (0..4096).map(|_| (rng.below(n as u32) as usize, rng.below(n as u32) as usize)).collect()
            };
            let want: Vec<f64> =
                samples.iter().map(|&(i, j)| (0..n).map(|k| a64[i * n + k] * b64[k * n + j]).sum()).collect();
            // The device's choice ("matmul"), and where a cooperative product could take its
            // large tile in 4 x 2 fragments a subgroup instead of 4 x 4, that beside it, so that
            // a run says what the choice is worth.
            let with_wide = |wide: bool| -> Result<String> {
                let mut rec = gpu.recorder()?;
                rec.set_wide_matmul_blocks(wide);
                matmul::product_kernel(&rec, &ta, &tb, false, false)
            };
            let other = with_wide(false)?;
            let other_differs = other != with_wide(true)?;
            let label = if precision == DType::F16 { "f16->f32" } else { "f32" };
            let (elem, roof) = if precision == DType::F16 { (2.0, roof16) } else { (4.0, roof32) };
            let over = if samples.len() == n * n {
                "all outputs".to_string()
            } else {
                format!("{} sampled outputs", samples.len())
            };
            for (name, wide) in [("matmul", true), ("matmul other blocks", false)] {
                if !wide && !other_differs {
                    continue;
                }
                let c_out = Tensor::empty(gpu, &[n, n], DType::F32)?;
                let timing = time_gpu(gpu, repeats, |rec| {
                    rec.set_wide_matmul_blocks(wide);
                    matmul::matmul_into(rec, &ta, &tb, false, false, &c_out, false)
                })?;
                let got: Vec<f32> = c_out.read()?;
                let have: Vec<f32> = samples.iter().map(|&(i, j)| got[i * n + j]).collect();
                let tflops = 2.0 * (n as f64).powi(3) / (timing.0 * 1e-3) / 1e12;
                let peak = peaks.map(|p| tflops / if precision == DType::F16 { p.0 } else { p.1 });
                let what = (name.to_string(), format!("{n}x{n}x{n}"), label);
                let r = product_record(what, &device, timing, repeats, (n, n, n), elem, roof);
                let kernel = if wide { matmul::matmul_variant(gpu, precision) } else { other.as_str() };
                push(r.peak(peak).against(&have, &want, over.clone()).kernel(kernel));
            }
        }
    }

    for &(what, m, n, k, trans_a) in &s.shaped {
        let a = rng.normal_vec(m * k);
        let b = rng.normal_vec(k * n);
        let a_shape = if trans_a { [k, m] } else { [m, k] };
        let samples: Vec<(usize, usize)> =
            (0..1024).map(|_| (rng.below(m as u32) as usize, rng.below(n as u32) as usize)).collect();
        // f32, and f16 as training in f16 multiplies (the cooperative tiles where the device has
        // them); the reference multiplies the inputs as the kernel reads them.
        for precision in [DType::F32, DType::F16] {
            let (a, b): (Vec<f32>, Vec<f32>) = match precision {
                DType::F16 => {
                    let round = |v: &[f32]| v.iter().map(|&x| half::f16::from_f32(x).to_f32()).collect();
                    (round(&a), round(&b))
                }
                _ => (a.clone(), b.clone()),
            };
            let ta = Tensor::from_slice(gpu, &a_shape, &a)?;
            let tb = Tensor::from_slice(gpu, &[k, n], &b)?;
            let (ta, tb) = if precision == DType::F16 {
                let mut rec = gpu.recorder()?;
                let pair = (cast(&mut rec, &ta, DType::F16)?, cast(&mut rec, &tb, DType::F16)?);
                rec.submit()?;
                pair
            } else {
                (ta, tb)
            };
            let kernel = matmul::product_kernel(&gpu.recorder()?, &ta, &tb, trans_a, false)?;
            let c_out = Tensor::empty(gpu, &[m, n], DType::F32)?;
            let timing = time_gpu(gpu, repeats, |rec| {
                matmul::matmul_into(rec, &ta, &tb, trans_a, false, &c_out, false)
            })?;
            let got: Vec<f32> = c_out.read()?;
            let a_at = |i: usize, kk: usize| if trans_a { a[kk * m + i] } else { a[i * k + kk] } as f64;
            let want: Vec<f64> = samples
                .iter()
                .map(|&(i, j)| (0..k).map(|kk| a_at(i, kk) * b[kk * n + j] as f64).sum())
                .collect();
            let have: Vec<f32> = samples.iter().map(|&(i, j)| got[i * n + j]).collect();
            let tflops = 2.0 * (m * n * k) as f64 / (timing.0 * 1e-3) / 1e12;
            let shape = format!("{m}x{n}x{k}{}", if trans_a { " (a^T)" } else { "" });
            let (label, elem, roof, peak) = match precision {
                DType::F16 => ("f16->f32", 2.0, roof16, peaks.map(|p| tflops / p.0)),
                _ => ("f32", 4.0, roof32, peaks.map(|p| tflops / p.1)),
            };
            let what = (format!("matmul {what}"), shape, label);
            let r = product_record(what, &device, timing, repeats, (m, n, k), elem, roof);
            push(r.peak(peak).against(&have, &want, "1024 sampled outputs").kernel(&kernel));
        }
    }

    let gbs = |bytes: f64, ms: f64| bytes / (ms * 1e-3) / 1e9;
    let bw_peak = |g: f64| peaks.map(|p| g / p.2);

    for &(rows, len) in &s.softmax {
        let x: Vec<f32> = rng.normal_vec(rows * len).iter().map(|v| v * 10.0).collect();
        let t = Tensor::from_slice(gpu, &[rows, len], &x)?;
        let mut y = None;
        let timing = time_gpu(gpu, repeats, |rec| {
            y = Some(softmax::softmax(rec, &t)?);
            Ok(())
        })?;
        let got: Vec<f32> = y.unwrap().read()?;
        let want = softmax::reference::softmax(&x, len);
        let g = gbs((rows * len * 8) as f64, timing.0);
        let r = Record::timed("softmax", format!("{rows}x{len}"), "f32", &device, timing, repeats, g, "GB/s");
        // A value's maximum, difference, exp, sum and scale: five operations.
        let r = r.work(5.0 * (rows * len) as f64, (rows * len * 8) as f64, roof32);
        push(r.peak(bw_peak(g)).against(&got, &want, "all outputs"));
    }

    for &n in &s.scan {
        let x: Vec<u32> = (0..n).map(|_| rng.below(1000)).collect();
        let t = Tensor::from_slice(gpu, &[n], &x)?;
        let y = Tensor::empty(gpu, &[n], DType::U32)?;
        let timing = time_gpu(gpu, repeats, |rec| scan::exclusive_scan(rec, &t, &y).map(|_| ()))?;
        let got: Vec<u32> = y.read()?;
        let mut acc = 0u32;
        let mut wrong = 0usize;
        for (i, &v) in x.iter().enumerate() {
            wrong += (got[i] != acc) as usize;
            acc = acc.wrapping_add(v);
        }
        let g = gbs((n * 8) as f64, timing.0);
        let r = Record::timed("exclusive scan", format!("{n}"), "u32", &device, timing, repeats, g, "GB/s");
        let over = "exact: nmse = fraction wrong, max abs = count wrong";
        let r = r.work(0.0, (n * 8) as f64, roof32);
        push(r.peak(bw_peak(g)).error(wrong as f64 / n as f64, wrong as f64, over));
    }

    for &(n, bits) in &s.sort {
        let mask = if bits == 32 { u32::MAX } else { (1u32 << bits) - 1 };
        let keys: Vec<u32> = (0..n).map(|_| rng.next_u32() & mask).collect();
        let vals: Vec<u32> = (0..n as u32).collect();
        let tk = Tensor::from_slice(gpu, &[n], &keys)?;
        let tv = Tensor::from_slice(gpu, &[n], &vals)?;
        let mut order: Vec<u32> = vals.clone();
        order.sort_by_key(|&i| keys[i as usize]);
        // The device's way of sorting ("radix sort pairs"), and every other way it can run
        // beside it, so that a run says what the choice is worth.
        let chosen = sort::Radix::chosen(gpu);
        let others = sort::Radix::ALL.into_iter().filter(|&r| r != chosen && r.runs_on(gpu));
        for radix in std::iter::once(chosen).chain(others) {
            let name = match radix {
                _ if radix == chosen => "radix sort pairs",
                sort::Radix::Bytes => "radix sort 8-bit",
                sort::Radix::Subgroups => "radix sort 4-bit subgroup",
                _ => "radix sort 4-bit atomics",
            };
            let mut res = None;
            let timing = time_gpu(gpu, repeats, |rec| {
                res = Some(sort::sort_pairs_with(rec, &tk, &tv, bits, radix)?);
                Ok(())
            })?;
            let (sk, sv) = res.unwrap();
            let (gk, gv): (Vec<u32>, Vec<u32>) = (sk.read()?, sv.read()?);
            let wrong = (0..n).filter(|&i| gv[i] != order[i] || gk[i] != keys[order[i] as usize]).count();
            let mkeys = n as f64 / (timing.0 * 1e-3) / 1e6;
            let r = Record::timed(
                name,
                format!("{n} x {bits} bits"),
                "u32",
                &device,
                timing,
                repeats,
                mkeys,
                "Mkey/s",
            );
            let over = "exact and stable: nmse = fraction wrong, max abs = count wrong";
            // Keys and values read once and written once.
            let r = r.work(0.0, (n * 16) as f64, roof32).kernel(radix.describe());
            push(r.error(wrong as f64 / n as f64, wrong as f64, over));
        }
    }

    for &(rows, width, dst_rows) in &s.scatter {
        let src = rng.normal_vec(rows * width);
        let idx: Vec<u32> = (0..rows).map(|_| rng.below(dst_rows as u32)).collect();
        let ts = Tensor::from_slice(gpu, &[rows, width], &src)?;
        let ti = Tensor::from_slice(gpu, &[rows], &idx)?;
        let out = Tensor::empty(gpu, &[dst_rows, width], DType::F32)?;
        let timing = time_gpu(gpu, repeats, |rec| {
            velox_engine::ops::fill::fill(rec, &out, 0.0)?;
            scatter_add::scatter_add(rec, &ts, &ti, &out)
        })?;
        let got: Vec<f32> = out.read()?;
        let want = scatter_add::reference::scatter_add(&src, width, &idx, &vec![0.0; dst_rows * width]);
        let g = gbs((rows * width * 8 + rows * 4) as f64, timing.0);
        let name = if gpu.supports(velox_engine::kernels::SCATTER_ADD_MAIN) {
            "scatter-add (atomic)"
        } else {
            "scatter-add (CAS)"
        };
        let r = Record::timed(
            name,
            format!("{rows}x{width} -> {dst_rows}"),
            "f32",
            &device,
            timing,
            repeats,
            g,
            "GB/s",
        );
        // Each source value read and added into its row (read and written once), the indices read.
        let bytes = (rows * width * 4 + rows * 4 + 2 * dst_rows * width * 4) as f64;
        let r = r.work((rows * width) as f64, bytes, roof32);
        push(r.peak(bw_peak(g)).against(&got, &want, "all outputs"));
    }

    for &(src_rows, width, rows) in &s.gather {
        let src = rng.normal_vec(src_rows * width);
        let idx: Vec<u32> = (0..rows).map(|_| rng.below(src_rows as u32)).collect();
        let ts = Tensor::from_slice(gpu, &[src_rows, width], &src)?;
        let ti = Tensor::from_slice(gpu, &[rows], &idx)?;
        let mut y = None;
        let timing = time_gpu(gpu, repeats, |rec| {
            y = Some(velox_engine::ops::gather::gather(rec, &ts, &ti)?);
            Ok(())
        })?;
        let got: Vec<f32> = y.unwrap().read()?;
        let want = velox_engine::ops::gather::reference::gather(&src, width, &idx);
        // Each output row read from its source row and written, the indices read.
        let bytes = (2 * rows * width * 4 + rows * 4) as f64;
        let g = gbs(bytes, timing.0);
        let shape = format!("{rows} of {src_rows}x{width}");
        let r = Record::timed("gather rows", shape, "f32", &device, timing, repeats, g, "GB/s");
        push(r.work(0.0, bytes, roof32).peak(bw_peak(g)).against(&got, &want, "all outputs"));
    }

    for &(m, k) in &s.fps {
        let points = surface_cloud(m, &mut rng);
        let tp = Tensor::from_slice(gpu, &[m, 4], &points)?;
        let candidates: Vec<u32> = (0..m as u32).collect();
        let mut res = None;
        let timing = time_gpu(gpu, repeats, |rec| {
            res = Some(fps::fps(rec, &tp, &candidates, k)?);
            Ok(())
        })?;
        let got: Vec<u32> = res.unwrap().read()?;
        let wrong = fps_violations(&points, &got);
        let r = Record::timed(
            "farthest point sampling",
            format!("{m} -> {k}"),
            "f32",
            &device,
            timing,
            repeats,
            (k - 1) as f64 / timing.0,
            "iter/ms",
        );
        let over = "steps not choosing the farthest remaining point (f64, up to 1e-5 relative): \
                    nmse = fraction, max abs = count";
        // Each step updates every point's distance to the chosen set (a difference, a squared
        // length and a minimum: 9 operations) and takes the farthest; the points read once.
        let r = r.work(9.0 * (m * (k - 1)) as f64, (m * 16 + k * 4) as f64, roof32);
        push(r.error(wrong as f64 / k as f64, wrong as f64, over));
    }

    for &(n, k) in &s.assign {
        let points = surface_cloud(n, &mut rng);
        let queries: Vec<f32> = points[..4 * k].to_vec();
        let tp = Tensor::from_slice(gpu, &[n, 4], &points)?;
        let tq = Tensor::from_slice(gpu, &[k, 4], &queries)?;
        let mut res = None;
        let timing = time_gpu(gpu, repeats, |rec| {
            res = Some(assign::assign_nearest(rec, &tp, &tq)?);
            Ok(())
        })?;
        let got: Vec<u32> = res.unwrap().read()?;
        // The reference on a fixed sample of 4096 points: all of them would take minutes.
        let sample: Vec<usize> = (0..4096.min(n)).map(|i| i * n / 4096.min(n)).collect();
        let dist = |p: usize, q: usize| {
            assign::reference::dist2(&points[4 * p..4 * p + 4], &queries[4 * q..4 * q + 4])
        };
        // A point counts as wrong when its query is farther than the nearest by more than f32
        // rounding (ties and near-ties may go either way).
        let wrong = sample
            .iter()
            .filter(|&&p| {
                let best = (0..k).map(|q| dist(p, q)).fold(f64::INFINITY, f64::min);
                dist(p, got[p] as usize) > best * (1.0 + 1e-5) + 1e-12
            })
            .count();
        let tflops = assign::flops(n, k) as f64 / (timing.0 * 1e-3) / 1e12;
        let r = Record::timed(
            "nearest-query assignment",
            format!("{n} points, {k} queries"),
            "f32",
            &device,
            timing,
            repeats,
            tflops,
            "TFLOP/s",
        );
        let over = "4096 sampled points against the f64 nearest: nmse = fraction farther, max abs = count";
        let r = r.work(assign::flops(n, k) as f64, ((n + k) * 16 + n * 4) as f64, roof32);
        push(r.peak(peaks.map(|p| tflops / p.1)).error(
            wrong as f64 / sample.len() as f64,
            wrong as f64,
            over,
        ));
    }
    Ok(out)
}

/// The steps of an FPS run over candidates `0..m` (every point) whose choice is not the
/// farthest remaining point from those chosen before, in f64, up to 1e-5 relative: f32
/// distances within rounding of each other may be chosen in either order (and then the runs
/// part ways), so the f64 reference's exact sequence is not the measure.
fn fps_violations(points: &[f32], chosen: &[u32]) -> usize {
    let m = points.len() / 4;
    let row = |i: usize| &points[4 * i..4 * i + 4];
    let mut min_dist = vec![f64::INFINITY; m];
    let mut used = vec![false; m];
    let mut wrong = usize::from(chosen.first() != Some(&0));
    for (t, &c) in chosen.iter().enumerate() {
        let c = c as usize;
        if used[c] {
            wrong += 1;
            continue;
        }
        if t > 0 {
            let far = (0..m).filter(|&j| !used[j]).map(|j| min_dist[j]).fold(0.0, f64::max);
            wrong += usize::from(min_dist[c] < far * (1.0 - 1e-5));
        }
        used[c] = true;
        for (j, d) in min_dist.iter_mut().enumerate() {
            *d = d.min(assign::reference::dist2(row(j), row(c)));
        }
    }
    wrong
}

/// `n` points `(x, y, z, tau)` on a sphere of radius 0.8 whose centre moves over tau in [0, 1]:
/// a 2D surface over time, shaped like the clouds the encoder samples its queries from.
fn surface_cloud(n: usize, rng: &mut Rng) -> Vec<f32> {
    let mut out = Vec::with_capacity(4 * n);
    for _ in 0..n {
        let v = [rng.normal(), rng.normal(), rng.normal()];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-6);
        let tau = rng.uniform();
        let row = [0.8 * v[0] / len + 0.1 * tau, 0.8 * v[1] / len, 0.8 * v[2] / len, tau];
        out.extend(row.iter().map(|&x| x as f32));
    }
    out
}

/// The record of a timed product `[m, k] x [k, n]` into f32 of `elem`-byte operands, named
/// (name, shape, precision) by `what`: its TFLOP/s, and its work (each operand read once, the
/// output written once) against the roofline `roof`.
fn product_record(
    (name, shape, label): (String, String, &str),
    device: &str,
    timing: (f64, f64, bool),
    repeats: u32,
    (m, n, k): (usize, usize, usize),
    elem: f64,
    roof: Option<super::Roof>,
) -> Record {
    let flops = 2.0 * (m * n * k) as f64;
    let bytes = elem * (m * k + k * n) as f64 + 4.0 * (m * n) as f64;
    let tflops = flops / (timing.0 * 1e-3) / 1e12;
    Record::timed(name, shape, label, device, timing, repeats, tflops, "TFLOP/s").work(flops, bytes, roof)
}
