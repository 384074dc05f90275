//! Point-to-window and point-to-cell assignment (the encoder's localized attention) and 4D
//! farthest point sampling, against their CPU references.

use crate::common;
use common::*;
use velox_engine::ops::assign::{self, assign_grouped, assign_nearest};
use velox_engine::ops::fps::{self, fps, random_candidates, sample_queries};
use velox_engine::ops::window::{self, group_by_window, validate_points, window_ids, WindowGrid};
use velox_engine::{Error, Feature};

/// `n` rows of (x, y, z, t): xyz uniform in [lo, hi), t uniform in [tlo, thi).
fn random_points(rng: &mut Rng, n: usize, (lo, hi): (f64, f64), (tlo, thi): (f64, f64)) -> Vec<f32> {
    (0..n)
        .flat_map(|_| {
            let t = rng.range(tlo, thi) as f32;
            [rng.range(lo, hi) as f32, rng.range(lo, hi) as f32, rng.range(lo, hi) as f32, t]
        })
        .collect()
}

/// Rows on a grid of eighths in [-1, 1]: every squared distance is exact in f32 and f64, so
/// ties are real ties and the kernels must break them as the reference does.
fn grid_points(rng: &mut Rng, n: usize) -> Vec<f32> {
    (0..4 * n).map(|_| (rng.below(17) as f32 - 8.0) / 8.0).collect()
}

fn upload(data: &[f32]) -> Tensor {
    Tensor::from_slice(&gpu(), &[data.len() / 4, 4], data).unwrap()
}

/// The encoder's default grid: cells of 0.5 over [-1, 1] in x, y, z, and 6 frames over 24.
fn encoder_grid() -> WindowGrid {
    WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, 24.0], [0.5, 0.5, 0.5, 6.0]).unwrap()
}

fn gpu_window_ids(points: &[f32], grid: &WindowGrid) -> Vec<u32> {
    let gpu = gpu();
    let mut rec = gpu.recorder().unwrap();
    let ids = window_ids(&mut rec, &upload(points), grid).unwrap();
    rec.submit().unwrap();
    ids.read::<u32>().unwrap()
}

#[test]
fn grid_geometry_and_border_cells() {
    let g = encoder_grid();
    assert_eq!(g.cells, [4, 4, 4, 4]);
    assert_eq!(g.num_windows(), 256);
    let s = g.shifted();
    assert_eq!(s.cells, [5, 5, 5, 5]);
    assert_eq!(s.origin, [-1.25, -1.25, -1.25, -3.0]);
    // Hand-worked cells, so the reference is not just checked against itself.
    let cell = |v: f32, grid: &WindowGrid, a: usize| {
        window::reference::axis_cell(v, grid.origin[a], grid.inv_cell()[a], grid.cells[a])
    };
    for (v, want) in [(-1.0, 0), (-0.5, 1), (-0.0, 2), (0.0, 2), (0.4999, 2), (0.5, 3), (1.0, 3), (7.0, 3)] {
        assert_eq!(cell(v, &g, 0), want, "unshifted x = {v}");
    }
    for (v, want) in [(-9.0, 0), (-1.25, 0), (-1.0, 0), (-0.75, 1), (0.0, 2), (0.25, 3), (1.0, 4), (1.3, 4)] {
        assert_eq!(cell(v, &s, 1), want, "shifted y = {v}");
    }
    for (t, want) in [(0.0, 0), (5.99, 0), (6.0, 1), (23.0, 3), (24.0, 3), (-1.0, 0)] {
        assert_eq!(cell(t, &g, 3), want, "unshifted t = {t}");
    }
    // t fastest, x slowest.
    assert_eq!(window::reference::window_ids(&[-1.0, -1.0, -1.0, 6.0], &g), [1]);
    assert_eq!(window::reference::window_ids(&[-1.0, -1.0, -0.5, 0.0], &g), [4]);
    assert_eq!(window::reference::window_ids(&[1.0, 1.0, 1.0, 24.0], &g), [255]);
    assert_eq!(window::reference::window_ids(&[-0.5, -1.0, -1.0, 0.0], &g), [64]);
    // Ratios a rounding error away from a whole number.
    let odd = WindowGrid::new([0.0; 4], [0.3, 1.0, 23.0, 0.7], [0.1, 0.25, 1.0, 0.3]).unwrap();
    assert_eq!(odd.cells, [3, 4, 23, 3]);
}

#[test]
fn window_ids_match_reference_with_and_without_shift() {
    let mut rng = Rng::new(11);
    // Random points, a fifth of them outside the bounds on some axis.
    let mut points = random_points(&mut rng, 3001, (-1.25, 1.25), (-3.0, 27.0));
    // Every combination of border values of both grids on x and t, and far outside.
    let borders = [-1e30, -1.25, -1.0, -0.75, -0.5, -0.25, -0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1e30];
    let times = [-1e30, -3.0, 0.0, 3.0, 6.0, 9.0, 12.0, 18.0, 21.0, 24.0, 27.0, 1e30];
    for &x in &borders {
        for &t in &times {
            points.extend_from_slice(&[x, -x, 0.5, t]);
        }
    }
    let g = encoder_grid();
    // A grid whose widths are not powers of two: borders round, and must round alike.
    let odd = WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, 24.0], [0.3, 0.7, 0.1, 5.0]).unwrap();
    for grid in [g, g.shifted(), odd, odd.shifted()] {
        let got = gpu_window_ids(&points, &grid);
        let want = window::reference::window_ids(&points, &grid);
        if let Some(i) = (0..want.len()).find(|&i| got[i] != want[i]) {
            panic!("grid {grid:?}: point {i} {:?}: id {} != {}", &points[4 * i..4 * i + 4], got[i], want[i]);
        }
        assert!(got.iter().all(|&id| (id as u64) < grid.num_windows()));
    }
    // Empty and single-point clouds.
    assert!(gpu_window_ids(&[], &g).is_empty());
    assert_eq!(gpu_window_ids(&[0.0, 0.0, 0.0, 12.0], &g), [2 * 64 + 2 * 16 + 2 * 4 + 2]);
}

/// Groups `ids` on the device and checks every output against the reference and the format's
/// promises.
fn check_grouping(ids: &[u32], num_windows: u64, what: &str) {
    let gpu = gpu();
    let n = ids.len();
    let t = Tensor::from_slice(&gpu, &[n], ids).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let seg = group_by_window(&mut rec, &t, num_windows).unwrap();
    rec.submit().unwrap();
    let (want_order, want_offsets, want_segment_ids) = window::reference::group_by_window(ids);
    let s = want_segment_ids.len();
    let capacity = (num_windows as usize).min(n);
    let order = seg.order.read::<u32>().unwrap();
    let offsets = seg.offsets.read::<u32>().unwrap();
    let segment_ids = seg.segment_ids.read::<u32>().unwrap();
    assert_eq!(seg.read_count().unwrap() as usize, s, "{what}: segment count");
    assert_eq!(offsets.len(), capacity + 1, "{what}: offsets length");
    assert_eq!(order, want_order, "{what}: order");
    assert_eq!(&offsets[..=s], &want_offsets[..], "{what}: offsets");
    assert!(offsets[s..].iter().all(|&o| o as usize == n), "{what}: offsets past the count");
    assert_eq!(&segment_ids[..s], &want_segment_ids[..], "{what}: segment ids");
    assert!(segment_ids[s..].iter().all(|&w| w == u32::MAX), "{what}: segment ids past the count");
    assert_eq!(
        seg.sorted_ids.read::<u32>().unwrap(),
        want_order.iter().map(|&i| ids[i as usize]).collect::<Vec<_>>()
    );
    // The format's promises, stated directly: every point once, one id per segment, segments
    // in increasing id, ascending point index inside a segment.
    let mut seen = vec![false; n];
    for w in 0..s {
        let run = &order[offsets[w] as usize..offsets[w + 1] as usize];
        assert!(!run.is_empty(), "{what}: segment {w} is empty");
        assert!(run.iter().all(|&p| ids[p as usize] == segment_ids[w]), "{what}: segment {w} mixes ids");
        assert!(run.windows(2).all(|p| p[0] < p[1]), "{what}: segment {w} is not in point order");
        if w > 0 {
            assert!(segment_ids[w - 1] < segment_ids[w], "{what}: segment ids not ascending");
        }
        for &p in run {
            assert!(!std::mem::replace(&mut seen[p as usize], true), "{what}: point {p} twice");
        }
    }
    assert!(seen.iter().all(|&x| x), "{what}: a point is missing");
}

#[test]
fn grouping_by_window_is_a_stable_compact_segmentation() {
    let mut rng = Rng::new(12);
    for n in [0usize, 1, 2, 257, 4097, 30_001] {
        for num_windows in [1u64, 256, 625, 100_000] {
            let ids: Vec<u32> = (0..n).map(|_| rng.below(num_windows as u32)).collect();
            check_grouping(&ids, num_windows, &format!("n={n} windows={num_windows}"));
        }
    }
    // Few occupied windows among many, and a sorted and a reversed input.
    let ids: Vec<u32> = (0..5000).map(|i| [7, 70_000, 123, 99_999][i % 4]).collect();
    check_grouping(&ids, 100_000, "sparse");
    let ids: Vec<u32> = (0..5000).map(|i| i / 7).collect();
    check_grouping(&ids, 715, "sorted");
    let ids: Vec<u32> = (0..5000).rev().map(|i| i / 3).collect();
    check_grouping(&ids, 2000, "reversed");
    check_grouping(&[u32::MAX, 0, u32::MAX], 1 << 32, "full 32-bit ids");
}

#[test]
fn windows_then_groups_from_points() {
    let mut rng = Rng::new(13);
    let points = random_points(&mut rng, 6000, (-1.1, 1.1), (0.0, 24.0));
    let gpu = gpu();
    let grid = encoder_grid().shifted();
    let mut rec = gpu.recorder().unwrap();
    let ids = window_ids(&mut rec, &upload(&points), &grid).unwrap();
    let seg = group_by_window(&mut rec, &ids, grid.num_windows()).unwrap();
    rec.submit().unwrap();
    let want_ids = window::reference::window_ids(&points, &grid);
    let (order, offsets, segment_ids) = window::reference::group_by_window(&want_ids);
    let s = seg.read_count().unwrap() as usize;
    assert_eq!(seg.order.read::<u32>().unwrap(), order);
    assert_eq!(seg.offsets.read::<u32>().unwrap()[..=s], offsets[..]);
    assert_eq!(seg.segment_ids.read::<u32>().unwrap()[..s], segment_ids[..]);
}

fn gpu_nearest(points: &[f32], queries: &[f32]) -> Vec<u32> {
    let gpu = gpu();
    let mut rec = gpu.recorder().unwrap();
    let cells = assign_nearest(&mut rec, &upload(points), &upload(queries)).unwrap();
    rec.submit().unwrap();
    cells.read::<u32>().unwrap()
}

#[test]
fn nearest_query_is_exact_on_grid_points_with_ties() {
    let mut rng = Rng::new(21);
    // Sizes around the kernel's 512 points per workgroup and 256 queries per tile.
    for (n, k) in [(0, 5), (1, 1), (1, 300), (511, 1), (513, 256), (2000, 257), (1500, 600)] {
        let points = grid_points(&mut rng, n);
        let mut queries = grid_points(&mut rng, k);
        // Exact duplicates of earlier queries: the lower index must win.
        if k >= 10 {
            let q3: Vec<f32> = queries[12..16].to_vec();
            queries[36..40].copy_from_slice(&q3);
            let last = queries.len() - 4;
            queries.copy_within(0..4, last);
        }
        let got = gpu_nearest(&points, &queries);
        let want = assign::reference::assign_nearest(&points, &queries);
        if let Some(i) = (0..n).find(|&i| got[i] != want[i]) {
            panic!("n={n} k={k}: point {i} -> query {} but the reference says {}", got[i], want[i]);
        }
    }
    // Hand-made ties: (0, 0, 0, 1.875) is 4.515625 from all three queries, the origin is 1
    // from the last two.
    let queries = [0.0, 0.0, 0.0, 4.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0];
    let points = [0.0, 0.0, 0.0, 1.875, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0];
    assert_eq!(gpu_nearest(&points, &queries), [0, 1, 1, 2]);
}

#[test]
fn nearest_query_on_continuous_points_is_the_nearest_up_to_rounding() {
    let mut rng = Rng::new(22);
    let (n, k) = (3000, 300);
    let points = random_points(&mut rng, n, (-1.0, 1.0), (0.0, 2.0));
    let queries = random_points(&mut rng, k, (-1.0, 1.0), (0.0, 2.0));
    let got = gpu_nearest(&points, &queries);
    let want = assign::reference::assign_nearest(&points, &queries);
    let mut differ = 0;
    for i in 0..n {
        if got[i] == want[i] {
            continue;
        }
        // Only an f32 rounding near-tie may differ: the chosen query is as near to 1e-6.
        let p = &points[4 * i..4 * i + 4];
        let dg = assign::reference::dist2(p, &queries[4 * got[i] as usize..][..4]);
        let dw = assign::reference::dist2(p, &queries[4 * want[i] as usize..][..4]);
        assert!(
            dg - dw <= 1e-6 * dw.max(1e-12),
            "point {i}: query {} at {dg} vs {} at {dw}",
            got[i],
            want[i]
        );
        differ += 1;
    }
    assert!(differ <= 3, "{differ} near-ties differ");
}

#[test]
fn grouped_cells_have_offsets_for_every_query() {
    let mut rng = Rng::new(23);
    for (n, k) in [(0, 4), (1, 1), (1, 9), (700, 1), (4000, 300), (300, 1000)] {
        let points = grid_points(&mut rng, n);
        // Queries far outside [-1, 1] own no points: empty cells, including the first and last.
        let mut queries = grid_points(&mut rng, k);
        for q in (0..k).step_by(5) {
            queries[4 * q] = 50.0 + q as f32;
        }
        let gpu = gpu();
        let mut rec = gpu.recorder().unwrap();
        let cells = assign_grouped(&mut rec, &upload(&points), &upload(&queries)).unwrap();
        rec.submit().unwrap();
        let want_cells = assign::reference::assign_nearest(&points, &queries);
        let (want_order, want_offsets) = assign::reference::group_by_cell(&want_cells, k);
        assert_eq!(cells.cells.read::<u32>().unwrap(), want_cells, "n={n} k={k}: cells");
        assert_eq!(cells.order.read::<u32>().unwrap(), want_order, "n={n} k={k}: order");
        let offsets = cells.offsets.read::<u32>().unwrap();
        assert_eq!(offsets, want_offsets, "n={n} k={k}: offsets");
        assert_eq!(offsets[k] as usize, n);
        let sorted = cells.sorted_cells.read::<u32>().unwrap();
        for c in 0..k {
            assert!(sorted[offsets[c] as usize..offsets[c + 1] as usize].iter().all(|&x| x as usize == c));
        }
    }
}

/// FPS on the GPU with each workgroup size the device can run (the device's choice and the
/// other one): all must choose the same points. A device whose limits the 1024-invocation
/// kernel exceeds (SwiftShader allows 256) must refuse it with an error naming the limit.
fn gpu_fps(points: &[f32], candidates: &[u32], k: usize) -> Vec<u32> {
    let gpu = gpu();
    let mut outs = Vec::new();
    for wg in [fps::WG_CPU, fps::WG_GPU] {
        let mut rec = gpu.recorder().unwrap();
        match fps::fps_with_workgroup(&mut rec, wg, &upload(points), candidates, k) {
            Ok(chosen) => {
                rec.submit().unwrap();
                outs.push(chosen.read::<u32>().unwrap());
            }
            Err(e) => {
                assert!(wg == fps::WG_GPU && gpu.caps().max_workgroup_invocations < wg, "{e}");
                assert!(matches!(e, Error::Unsupported { feature: Feature::WorkgroupSize, .. }), "{e}");
            }
        }
    }
    let mut rec = gpu.recorder().unwrap();
    let chosen = fps(&mut rec, &upload(points), candidates, k).unwrap();
    rec.submit().unwrap();
    assert!(outs.windows(2).all(|w| w[0] == w[1]), "the two workgroup sizes choose differently (k = {k})");
    assert_eq!(chosen.read::<u32>().unwrap(), outs[0], "fps differs from fps_with_workgroup");
    outs.pop().unwrap()
}

/// The FPS property, checked in f64 on the output alone: each chosen point is (up to f32
/// rounding) the farthest remaining candidate from the points chosen before it.
fn assert_fps_property(points: &[f32], candidates: &[u32], chosen: &[u32], what: &str) {
    let row = |c: u32| &points[4 * c as usize..4 * c as usize + 4];
    let mut min_dist = vec![f64::INFINITY; candidates.len()];
    let mut used = vec![false; candidates.len()];
    for (t, &c) in chosen.iter().enumerate() {
        let pos = (0..candidates.len()).find(|&j| candidates[j] == c && !used[j]);
        let pos = pos.unwrap_or_else(|| panic!("{what}: step {t} chose {c}, not an unused candidate"));
        if t == 0 {
            assert_eq!(pos, 0, "{what}: FPS starts from candidate 0");
        } else {
            let far = (0..candidates.len()).filter(|&j| !used[j]).map(|j| min_dist[j]).fold(0.0, f64::max);
            assert!(
                min_dist[pos] >= far * (1.0 - 1e-6),
                "{what}: step {t}: {} < farthest {far}",
                min_dist[pos]
            );
        }
        used[pos] = true;
        for (j, &cj) in candidates.iter().enumerate() {
            min_dist[j] = min_dist[j].min(assign::reference::dist2(row(cj), row(c)));
        }
    }
}

#[test]
fn fps_matches_reference_exactly() {
    let mut rng = Rng::new(31);
    let n = 5000;
    let points = random_points(&mut rng, n, (-1.0, 1.0), (0.0, 1.0));
    // m below, at and above the workgroups of 256 and 1024, so invocations own 0, 1 or several
    // candidates (up to 20), and runs end mid-way.
    for (m, ks) in
        [(1, vec![0, 1]), (2, vec![1, 2]), (300, vec![1, 2, 77, 300]), (3000, vec![150]), (5000, vec![1250])]
    {
        let candidates = random_candidates(n, m, &mut rng).unwrap();
        for k in ks {
            let got = gpu_fps(&points, &candidates, k);
            assert_eq!(got, fps::reference::fps(&points, &candidates, k), "m={m} k={k}");
            assert_fps_property(&points, &candidates, &got, &format!("m={m} k={k}"));
        }
    }
    // Grid points: exact distances, many ties, and duplicate points; the lower position wins
    // and every candidate position is chosen at most once, so k = m takes them all.
    let points = grid_points(&mut rng, 400);
    let mut candidates: Vec<u32> = (0..400).collect();
    candidates.extend_from_slice(&[5, 5, 17]);
    for k in [60, candidates.len()] {
        let got = gpu_fps(&points, &candidates, k);
        assert_eq!(got, fps::reference::fps(&points, &candidates, k), "grid k={k}");
        assert_fps_property(&points, &candidates, &got, &format!("grid k={k}"));
    }
    // A dense surface over time (points on a sphere, tau in [0, 1]), sampled down to a quarter:
    // late iterations measure only the runs near each new point, so this is where a wrong skip
    // would change a choice.
    let points: Vec<f32> = (0..6000)
        .flat_map(|_| {
            let v = [rng.normal(), rng.normal(), rng.normal()];
            let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-6);
            [0.8 * v[0] / len, 0.8 * v[1] / len, 0.8 * v[2] / len, rng.uniform()].map(|x| x as f32)
        })
        .collect();
    let candidates: Vec<u32> = (0..6000).collect();
    let got = gpu_fps(&points, &candidates, 1500);
    assert_eq!(got, fps::reference::fps(&points, &candidates, 1500), "sphere");
    // Two tight clusters far apart, each of repeated points: distances of zero and of 1e-12
    // beside ones of 100, ties everywhere.
    let mut points = Vec::new();
    for i in 0..2000 {
        let (base, jitter) = if i % 2 == 0 { (0.0f32, 1e-6f32) } else { (10.0, 0.0) };
        points.extend_from_slice(&[base + jitter * (i % 7) as f32, base, base, (i % 3) as f32 * jitter]);
    }
    let candidates: Vec<u32> = (0..2000).collect();
    for k in [10, 400, 2000] {
        let got = gpu_fps(&points, &candidates, k);
        assert_eq!(got, fps::reference::fps(&points, &candidates, k), "clusters k={k}");
    }
    // All candidates the same point.
    assert_eq!(gpu_fps(&points, &[9, 9, 9, 9], 4), [9, 9, 9, 9]);
}

#[test]
fn queries_are_sampled_from_random_candidates() {
    let mut rng = Rng::new(32);
    let c = random_candidates(100, 40, &mut rng).unwrap();
    assert_eq!(c.len(), 40);
    let mut sorted = c.clone();
    sorted.sort();
    sorted.dedup();
    assert_eq!(sorted.len(), 40, "candidates must be distinct");
    assert!(c.iter().all(|&i| i < 100));
    let mut all = random_candidates(50, 500, &mut rng).unwrap();
    all.sort();
    assert_eq!(all, (0..50).collect::<Vec<u32>>());

    let points = random_points(&mut rng, 2000, (-1.0, 1.0), (0.0, 1.0));
    let gpu = gpu();
    let run = |seed: u64, k: usize| {
        let mut rec = gpu.recorder().unwrap();
        let q = sample_queries(&mut rec, &upload(&points), k, &mut Rng::new(seed)).unwrap();
        rec.submit().unwrap();
        q.read::<u32>().unwrap()
    };
    let q = run(5, 64);
    assert_eq!(q, run(5, 64), "same seed, same queries");
    let want_candidates = random_candidates(2000, 4 * 64, &mut Rng::new(5)).unwrap();
    assert_eq!(q, fps::reference::fps(&points, &want_candidates, 64));
    // k = N: every point.
    let mut every = run(6, 2000);
    every.sort();
    assert_eq!(every, (0..2000).collect::<Vec<u32>>());
}

fn invalid_message(r: velox_engine::Result<impl Sized>) -> String {
    match r {
        Err(e @ (Error::Invalid(_) | Error::Shape(_))) => e.to_string(),
        Err(e) => panic!("expected an invalid-input or shape error, got {e}"),
        Ok(_) => panic!("expected an error"),
    }
}

#[test]
fn bad_inputs_get_clear_errors() {
    let gpu = gpu();
    let mut data = vec![0.5f32; 4 * 10];
    assert_eq!(validate_points(&data).unwrap(), 10);
    data[4 * 7 + 3] = f32::NAN;
    let e = invalid_message(validate_points(&data));
    assert!(e.contains("point 7") && e.contains("NaN"), "{e}");
    data[4 * 7 + 3] = 0.0;
    data[4 * 8] = f32::NEG_INFINITY;
    assert!(invalid_message(validate_points(&data)).contains("point 8"));
    assert!(invalid_message(validate_points(&data[..7])).contains("rows of 4"));

    let points = upload(&[0.0; 4 * 10]);
    let three = Tensor::from_slice(&gpu, &[10, 3], &[0.0f32; 30]).unwrap();
    let flat = Tensor::from_slice(&gpu, &[40], &[0.0f32; 40]).unwrap();
    let ints = Tensor::from_slice(&gpu, &[10, 4], &[0u32; 40]).unwrap();
    let no_queries = Tensor::from_slice(&gpu, &[0, 4], &[0.0f32; 0]).unwrap();
    let ids_f32 = Tensor::from_slice(&gpu, &[10], &[0.0f32; 10]).unwrap();
    let ids = Tensor::from_slice(&gpu, &[10], &[0u32; 10]).unwrap();
    let grid = encoder_grid();
    let mut rec = gpu.recorder().unwrap();
    for bad in [&three, &flat, &ints] {
        assert!(invalid_message(window_ids(&mut rec, bad, &grid)).contains("[N, 4]"));
        assert!(invalid_message(assign_nearest(&mut rec, bad, &points)).contains("[N, 4]"));
        assert!(invalid_message(assign_nearest(&mut rec, &points, bad)).contains("[N, 4]"));
        assert!(invalid_message(fps(&mut rec, bad, &[0], 1)).contains("[N, 4]"));
    }
    assert!(invalid_message(assign_nearest(&mut rec, &points, &no_queries)).contains("no queries"));
    assert!(invalid_message(group_by_window(&mut rec, &ids_f32, 4)).contains("u32"));
    assert!(invalid_message(group_by_window(&mut rec, &ids, 0)).contains("windows"));
    assert!(invalid_message(assign::group_by_cell(&mut rec, &ids, 0)).contains("cells"));
    let e = invalid_message(fps(&mut rec, &points, &[1, 2, 3], 4));
    assert!(e.contains("k = 4") && e.contains("3 candidates"), "{e}");
    assert!(invalid_message(fps(&mut rec, &points, &[1, 10], 1)).contains("candidate 1 is point 10"));
    assert!(invalid_message(sample_queries(&mut rec, &points, 11, &mut Rng::new(1))).contains("k = 11"));
    assert!(invalid_message(sample_queries(&mut rec, &points, 0, &mut Rng::new(1))).contains("k = 0"));
    let e = invalid_message(WindowGrid::new([0.0; 4], [1.0; 4], [0.5, 0.0, 0.5, 0.5]));
    assert!(e.contains("axis 1"), "{e}");
    assert!(WindowGrid::new([0.0; 4], [1.0, f32::NAN, 1.0, 1.0], [0.5; 4]).is_err());
    assert!(WindowGrid::new([0.0; 4], [-1.0, 1.0, 1.0, 1.0], [0.5; 4]).is_err());
    let huge = WindowGrid { origin: [0.0; 4], cell: [1.0; 4], cells: [70_000; 4] };
    assert!(window_ids(&mut rec, &points, &huge).is_err());
}
