//! Training data on lavapipe: the mesh rasteriser against a CPU ray cast, back-projection,
//! tracks, determinism, glTF import (real exports in tests/fixtures/gltf, whose credits are
//! in the README there, and files written here), corrupt files, the dataset on disk.
use crate::common;
use common::*;

use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use velox::data::camera::{input_cameras, Camera};
use velox::data::format::{
    read_ply, read_scene, scene_notes, write_arrays, write_ply, write_scene, CameraSet, SceneMeta, Severity,
    FORMAT,
};
use velox::data::gltf_import::import;
use velox::data::math::{sub, V3};
use velox::data::pipeline::{back_project, render_scene, FPS};
use velox::data::procedural::{scene, FRAMES};
use velox::data::raster::{reference, MeshRasteriser, NO_TRIANGLE};
use velox::data::{AnimatedMesh, SynthOptions};
use velox::models::train::order;
use velox::tasks::{Loader, LoaderOptions};

fn small_opts() -> SynthOptions {
    SynthOptions { res: 32, points: 3000, supersample: 1, tracks: 48, ..Default::default() }
}

pub(crate) fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("velox-data-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn distance_to_mesh(p: V3, mesh: &AnimatedMesh, f: usize) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.frames[f][i as usize]);
            reference::point_triangle_distance(p, a, b, c)
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn rasteriser_matches_cpu_ray_cast() {
    let (_, mesh) = scene(11, None).unwrap();
    let rast = MeshRasteriser::new(&gpu(), &mesh).unwrap();
    let cams: Vec<Camera> = input_cameras(40).into_iter().step_by(9).collect();
    for f in [0, 17] {
        let frame = rast.render(&mesh.frames[f], &cams).unwrap();
        for (v, cam) in cams.iter().enumerate() {
            let want = reference::depth_and_ids(&mesh.frames[f], &mesh.triangles, cam);
            let px = frame.pixels();
            let (mut same, mut covered) = (0usize, 0usize);
            let (mut got_d, mut want_d) = (Vec::new(), Vec::new());
            for (i, &(d, id)) in want.iter().enumerate() {
                let gid = frame.ids[v * px + i];
                covered += (id != NO_TRIANGLE || gid != NO_TRIANGLE) as usize;
                if gid == id {
                    same += (id != NO_TRIANGLE) as usize;
                    got_d.push(frame.depth[v * px + i]);
                    want_d.push(d);
                }
            }
            assert!(covered > 50, "frame {f} view {v}: the object covers only {covered} pixels");
            // Pixel centres on an edge may go either way in f32 against f64.
            assert!(
                same as f64 >= 0.97 * covered as f64,
                "frame {f} view {v}: ids agree on {same} of {covered}"
            );
            assert_nmse(&format!("depth f{f} v{v}"), &got_d, &want_d, 1e-9);
        }
    }
}

#[test]
fn back_projection_round_trip() {
    let (_, mesh) = scene(5, None).unwrap();
    let rast = MeshRasteriser::new(&gpu(), &mesh).unwrap();
    let cams = input_cameras(64);
    let (a, b) = (&cams[3], &cams[4]);
    let f = 9;
    let frame_a = rast.render(&mesh.frames[f], std::slice::from_ref(a)).unwrap();
    let points = back_project(&frame_a, std::slice::from_ref(a));
    assert!(points.len() > 200, "only {} pixels show the object", points.len());
    // Each point lies on the triangle its pixel names, and projects back onto its pixel.
    let hits: Vec<usize> = (0..frame_a.ids.len()).filter(|&k| frame_a.ids[k] != NO_TRIANGLE).collect();
    for (&k, (p, _, _)) in hits.iter().zip(&points) {
        let t = mesh.triangles[frame_a.ids[k] as usize].map(|i| mesh.frames[f][i as usize]);
        let d = reference::point_triangle_distance(*p, t[0], t[1], t[2]);
        assert!(d < 1e-4, "back-projected point {d} from its triangle");
        let (u, v, z) = a.project(*p);
        let (x, y) = ((k as u32 % 64) as f32 + 0.5, (k as u32 / 64) as f32 + 0.5);
        assert!((u - x).abs() < 1e-3 && (v - y).abs() < 1e-3 && (z - frame_a.depth[k]).abs() < 1e-4);
    }
    // Re-rendered from a second view, no back-projected point may sit in front of the surface
    // that view sees (beyond a silhouette's pixel), and many coincide with it.
    let frame_b = rast.render(&mesh.frames[f], std::slice::from_ref(b)).unwrap();
    let (mut in_front, mut on_surface, mut inside) = (0, 0, 0);
    for (p, _, _) in &points {
        let (u, v, z) = b.project(*p);
        if u < 0.0 || v < 0.0 || u >= 64.0 || v >= 64.0 {
            continue;
        }
        inside += 1;
        let d = frame_b.depth[v as usize * 64 + u as usize];
        let tol = 2.0 * z / b.fx;
        if d == 0.0 || z < d - tol {
            in_front += 1;
        } else if (z - d).abs() <= tol {
            on_surface += 1;
        }
    }
    assert!(
        in_front as f64 <= 0.03 * inside as f64,
        "{in_front} of {inside} points in front of view B's surface"
    );
    assert!(
        on_surface as f64 >= 0.3 * inside as f64,
        "only {on_surface} of {inside} points on view B's surface"
    );
}

#[test]
fn tracks_stay_on_the_surface_and_start_visible() {
    let (_, mesh) = scene(21, None).unwrap();
    let a = render_scene(&gpu(), &mesh, &small_opts(), 1, None, &mut |_| {}).unwrap();
    assert_eq!(a.tracks.len(), 48);
    for (t, track) in a.tracks.iter().enumerate() {
        assert_ne!(a.visibility[t][0], 0, "track {t} came from a frame-0 pixel but no camera sees it");
        for (f, &p) in track.iter().enumerate() {
            let d = distance_to_mesh(p, &mesh, f);
            assert!(d < 1e-5, "track {t} is {d} off the surface at frame {f}");
            let (tri, b) = a.anchors[t];
            assert_eq!(p, mesh.surface_point(f, tri, b));
        }
        // It moves with the surface: frame 0 is where its pixel back-projects.
        assert!(track[0].iter().all(|x| x.abs() <= 1.0));
    }
    let moving = a.tracks.iter().filter(|t| length3(sub(t[FRAMES - 1], t[0])) > 1e-3).count();
    assert!(moving > 0, "no track moves");
    // Points and occupancy agree: every point's voxel is occupied in its frame.
    for p in a.points.iter().step_by(17) {
        let f = (p[6] * FPS).round() as usize;
        let v = velox::data::pipeline::voxel_index([p[0], p[1], p[2]]);
        assert_eq!(a.occupancy[f * 4096 + v / 64] >> (v % 64) & 1, 1);
        assert!(p[3..6].iter().all(|c| (0.0..=1.0).contains(c)));
    }
}

/// Whether voxel `i` is set in one frame's words.
fn voxel_on(occ: &[u64], i: usize) -> bool {
    occ[i / 64] >> (i % 64) & 1 == 1
}

fn voxels_set(occ: &[u64]) -> usize {
    occ.iter().map(|w| w.count_ones() as usize).sum()
}

#[test]
fn occupancy_holds_the_voxels_each_triangle_crosses() {
    use velox::data::pipeline::{mark_triangle, GRID, OCCUPANCY_WORDS};
    // A square in the plane z = 0.3 over x, y in [-0.9, 0.9] is one layer of voxels: with
    // voxel i spanning [i, i + 1) of (x + 1) * 32, x from 3 (3.2) to 60 (60.8), z 41 (41.6).
    let (a, b, c, d) = ([-0.9, -0.9, 0.3], [0.9, -0.9, 0.3], [0.9, 0.9, 0.3], [-0.9, 0.9, 0.3]);
    let mut occ = vec![0u64; OCCUPANCY_WORDS];
    mark_triangle(&mut occ, [a, b, c]);
    mark_triangle(&mut occ, [a, c, d]);
    assert_eq!(voxels_set(&occ), 58 * 58);
    assert!(voxel_on(&occ, 3 + GRID * (3 + GRID * 41)) && voxel_on(&occ, 60 + GRID * (60 + GRID * 41)));
    // Collapsed triangles (a hidden part) set nothing.
    let mut occ = vec![0u64; OCCUPANCY_WORDS];
    mark_triangle(&mut occ, [a, a, a]);
    mark_triangle(&mut occ, [a, b, b]);
    assert_eq!(voxels_set(&occ), 0);
    // Random triangles against the f64 distance from each voxel's centre: a voxel set holds
    // part of the triangle, so its centre is within half the voxel's diagonal of it; a voxel
    // whose centre is within half a voxel (the inscribed ball) holds part of it, so is set.
    let h = 2.0 / GRID as f64;
    let mut rng = Rng::new(17);
    for t in 0..40 {
        let o: [f64; 3] = std::array::from_fn(|_| rng.range(-0.85, 0.85));
        let size = if t % 2 == 0 { 0.02 } else { 0.2 };
        let tri: [V3; 3] =
            std::array::from_fn(|_| std::array::from_fn(|k| (o[k] + rng.range(-size, size)) as f32));
        let mut occ = vec![0u64; OCCUPANCY_WORDS];
        mark_triangle(&mut occ, tri);
        let (mut set, mut inside) = (0, 0);
        for i in 0..GRID * GRID * GRID {
            let centre =
                [i % GRID, i / GRID % GRID, i / (GRID * GRID)].map(|v| (-1.0 + (v as f64 + 0.5) * h) as f32);
            let dist = reference::point_triangle_distance(centre, tri[0], tri[1], tri[2]) / h;
            if voxel_on(&occ, i) {
                set += 1;
                assert!(dist <= 0.75f64.sqrt() + 1e-4, "triangle {t}: voxel {i} is set {dist} voxels away");
            } else {
                assert!(dist >= 0.5 - 1e-4, "triangle {t}: voxel {i} is {dist} voxels away and not set");
            }
            inside += (dist < 0.5) as usize;
        }
        assert!(set >= inside.max(1), "triangle {t}: {set} voxels set, {inside} centres within half a voxel");
    }
}

#[test]
fn occupancy_is_one_shell_at_any_resolution() {
    // The triangles shown set the voxels, not the pixels' points: 32 px and 96 px views give
    // nearly the same shell (pixels alone found 85 % of the voxels at 48 px against 256 px).
    let (_, mesh) = scene(21, None).unwrap();
    let opts = |res| SynthOptions { res, points: 1000, supersample: 1, tracks: 0, ..Default::default() };
    let low = render_scene(&gpu(), &mesh, &opts(32), 1, None, &mut |_| {}).unwrap();
    let high = render_scene(&gpu(), &mesh, &opts(96), 1, None, &mut |_| {}).unwrap();
    let both: usize =
        low.occupancy.iter().zip(&high.occupancy).map(|(a, b)| (a & b).count_ones() as usize).sum();
    let either: usize =
        low.occupancy.iter().zip(&high.occupancy).map(|(a, b)| (a | b).count_ones() as usize).sum();
    let iou = both as f64 / either as f64;
    println!("occupancy IoU 32 px against 96 px: {iou:.4} ({either} voxels)");
    assert!(iou > 0.97, "occupancy IoU between 32 px and 96 px views {iou}");
}

fn length3(v: V3) -> f32 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[test]
fn same_seed_same_scene() {
    let (r1, m1) = scene(42, None).unwrap();
    let (r2, m2) = scene(42, None).unwrap();
    let (_, m3) = scene(43, None).unwrap();
    assert_eq!(r1.objects, r2.objects);
    assert_eq!(m1, m2);
    assert_ne!(m1, m3);
    assert_eq!(m1.frames.len(), FRAMES);
    assert!(m1.frames.iter().flatten().flatten().all(|x| x.abs() <= 1.0));
    let opts = small_opts();
    let a = render_scene(&gpu(), &m1, &opts, 9, None, &mut |_| {}).unwrap();
    let b = render_scene(&gpu(), &m2, &opts, 9, None, &mut |_| {}).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.points.len(), opts.points);
    assert!(a.points.windows(2).all(|w| w[0][6] <= w[1][6]), "points are ordered by frame");
}

#[test]
fn many_seeds_make_valid_varied_scenes() {
    let mut kinds = std::collections::BTreeSet::new();
    for seed in 0..40 {
        let (recipe, mesh) = scene(seed, None).unwrap();
        mesh.validate().unwrap();
        kinds.extend(recipe.objects);
        let moved = mesh.frames[0] != mesh.frames[FRAMES - 1];
        assert!(moved, "seed {seed}: nothing moves");
    }
    assert_eq!(kinds.len(), 5, "kinds seen: {kinds:?}");
}

fn shared_gltf(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gltf").join(name)
}

#[test]
fn imports_real_skinned_and_morph_exports() {
    // SimpleSkin: Khronos glTF sample models, CC-BY 4.0. MorphStressTest: Analytical
    // Graphics, Inc., model and textures by Ed Mackey, CC-BY 4.0.
    let skin = import(&shared_gltf("SimpleSkin.gltf"), None).unwrap();
    let morph = import(&shared_gltf("MorphStressTest.gltf"), None).unwrap();
    for (name, imp) in [("SimpleSkin", &skin), ("MorphStressTest", &morph)] {
        let m = &imp.mesh;
        m.validate().unwrap();
        assert_eq!(m.frames.len(), FRAMES, "{name}");
        assert!(imp.animation.is_some(), "{name} has an animation");
        assert!(m.frames.iter().flatten().flatten().all(|x| x.abs() <= 1.0), "{name} is normalised");
        let moved = (0..FRAMES)
            .flat_map(|f| (0..m.num_vertices()).map(move |v| length3(sub(m.frames[f][v], m.frames[0][v]))))
            .fold(0.0f32, f32::max);
        assert!(moved > 0.05, "{name}: the animation moves vertices by at most {moved}");
    }
    assert!(morph.mesh.textures.iter().any(|t| t.width > 1), "MorphStressTest's PNG texture is imported");
    // A skinned import renders into a scene with tracks on it.
    let a = render_scene(&gpu(), &skin.mesh, &small_opts(), 3, None, &mut |_| {}).unwrap();
    assert!(!a.tracks.is_empty());
}

/// A quad under a parent node whose translation is animated, with a morph target that lifts
/// one corner, its weight animated from 0 to 1 over one second. Returns (json, binary).
fn quad_asset(uri: Option<&str>) -> (String, Vec<u8>) {
    let f = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = Vec::new();
    bin.extend(f(&[0., 0., 0., 1., 0., 0., 1., 1., 0., 0., 1., 0.])); // 0: positions
    bin.extend(f(&[0., 0., 0., 0., 0., 0., 0., 0., 1., 0., 0., 0.])); // 48: target
    bin.extend([0u16, 1, 2, 0, 2, 3].iter().flat_map(|i| i.to_le_bytes())); // 96: indices
    bin.extend(f(&[0., 1.])); // 108: times
    bin.extend(f(&[0., 1.])); // 116: weights
    bin.extend(f(&[0., 0., 0., 2., 0., 0.])); // 124: translations
    let buffer = match uri {
        Some(u) => format!(r#"{{"byteLength": {}, "uri": "{u}"}}"#, bin.len()),
        None => format!(r#"{{"byteLength": {}}}"#, bin.len()),
    };
    let json = format!(
        r#"{{
  "asset": {{"version": "2.0", "copyright": "test asset"}},
  "scene": 0,
  "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"children": [1]}}, {{"mesh": 0, "translation": [0, 1, 0]}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 2, "targets": [{{"POSITION": 1}}]}}], "weights": [0]}}],
  "buffers": [{buffer}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 48}},
    {{"buffer": 0, "byteOffset": 48, "byteLength": 48}},
    {{"buffer": 0, "byteOffset": 96, "byteLength": 12}},
    {{"buffer": 0, "byteOffset": 108, "byteLength": 8}},
    {{"buffer": 0, "byteOffset": 116, "byteLength": 8}},
    {{"buffer": 0, "byteOffset": 124, "byteLength": 24}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]}},
    {{"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [0, 0, 1]}},
    {{"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}},
    {{"bufferView": 3, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0], "max": [1]}},
    {{"bufferView": 4, "componentType": 5126, "count": 2, "type": "SCALAR"}},
    {{"bufferView": 5, "componentType": 5126, "count": 2, "type": "VEC3"}}
  ],
  "animations": [{{
    "samplers": [{{"input": 3, "output": 4}}, {{"input": 3, "output": 5}}],
    "channels": [{{"sampler": 0, "target": {{"node": 1, "path": "weights"}}}},
                 {{"sampler": 1, "target": {{"node": 0, "path": "translation"}}}}]
  }}]
}}"#
    );
    (json, bin)
}

#[test]
fn imports_written_gltf_and_glb_with_hierarchy_and_morph_animation() {
    let dir = temp_dir("gltf");
    let (json, bin) = quad_asset(None);
    let data_uri = format!("data:application/octet-stream;base64,{}", base64(&bin));
    let (embedded, _) = quad_asset(Some(&data_uri));
    std::fs::write(dir.join("quad.gltf"), embedded).unwrap();
    std::fs::write(dir.join("quad.glb"), glb(&json, &bin)).unwrap();
    let (side, _) = quad_asset(Some("quad.bin"));
    std::fs::write(dir.join("side.gltf"), side).unwrap();
    std::fs::write(dir.join("quad.bin"), &bin).unwrap();

    // What the file says, sampled at 24 times over its one second, then normalised.
    let mut want = AnimatedMesh::default();
    let rest: [V3; 4] = [[0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]];
    want.frames = (0..FRAMES)
        .map(|f| {
            let s = f as f32 / (FRAMES - 1) as f32;
            rest.iter()
                .enumerate()
                .map(|(v, p)| [p[0] + 2.0 * s, p[1] + 1.0, p[2] + if v == 2 { s } else { 0.0 }])
                .collect()
        })
        .collect();
    want.normalise();

    let a = import(&dir.join("quad.gltf"), None).unwrap();
    let b = import(&dir.join("quad.glb"), None).unwrap();
    let c = import(&dir.join("side.gltf"), None).unwrap();
    assert_eq!(a.mesh, b.mesh);
    assert_eq!(a.mesh, c.mesh);
    assert_eq!(a.mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(a.credits.as_deref(), Some("test asset"));
    for f in 0..FRAMES {
        for v in 0..4 {
            let d = length3(sub(a.mesh.frames[f][v], want.frames[f][v]));
            assert!(d < 1e-5, "frame {f} vertex {v}: {:?} vs {:?}", a.mesh.frames[f][v], want.frames[f][v]);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn corrupt_gltf_files_get_errors_that_name_them() {
    let dir = temp_dir("corrupt");
    let (json, bin) = quad_asset(None);
    let good = glb(&json, &bin);
    let mut bad_bin = bin.clone();
    bad_bin[98] = 9; // the second index names vertex 9 of 4
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("truncated.glb", good[..good.len() / 2].to_vec()),
        ("garbage.gltf", b"{ this is not json".to_vec()),
        ("empty.glb", Vec::new()),
        ("missing_buffer.gltf", quad_asset(Some("nowhere.bin")).0.into_bytes()),
        ("no_scene.gltf", br#"{"asset": {"version": "2.0"}}"#.to_vec()),
        ("bad_index.glb", glb(&json, &bad_bin)),
    ];
    std::fs::write(dir.join("quad.bin"), &bin).unwrap();
    for (name, bytes) in cases {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let err = import(&path, None).expect_err(name).to_string();
        assert!(err.contains(name), "{name}: the error does not name the file: {err}");
    }
    let err = import(&dir.join("absent.gltf"), None).unwrap_err().to_string();
    assert!(err.contains("absent.gltf"), "{err}");
    // A missing side file is named.
    let err = import(&dir.join("missing_buffer.gltf"), None).unwrap_err().to_string();
    assert!(err.contains("nowhere.bin") && err.contains("buffers[0]"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The quad asset as editable JSON and its binary.
fn quad_parts() -> (Value, Vec<u8>) {
    let (json, bin) = quad_asset(None);
    (serde_json::from_str(&json).unwrap(), bin)
}

/// Appends `bytes` to the binary (at a 4-byte boundary) as a new buffer view; its index.
fn add_view(v: &mut Value, bin: &mut Vec<u8>, bytes: &[u8]) -> usize {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let offset = bin.len();
    bin.extend_from_slice(bytes);
    v["buffers"][0]["byteLength"] = bin.len().into();
    let views = v["bufferViews"].as_array_mut().unwrap();
    views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}));
    views.len() - 1
}

/// Writes `bytes` as `dir/name` and imports it.
fn import_file(dir: &Path, name: &str, bytes: &[u8]) -> Result<velox::data::gltf_import::Imported, String> {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    import(&path, None).map_err(|e| e.to_string())
}

/// Sets the value at a JSON pointer, adding the last key if it is missing.
fn set_at(v: &mut Value, pointer: &str, value: Value) {
    let (parent, key) = pointer.rsplit_once('/').unwrap();
    match v.pointer_mut(parent).unwrap_or_else(|| panic!("no {parent}")) {
        Value::Array(a) => a[key.parse::<usize>().unwrap()] = value,
        Value::Object(o) => drop(o.insert(key.to_string(), value)),
        other => panic!("{parent} is {other}"),
    }
}

/// A name, an edit of the quad's JSON and binary, and what the error must say.
type GltfCase<'a> = (&'a str, &'a dyn Fn(&mut Value, &mut Vec<u8>), &'a [&'a str]);

/// Imports each case (a name and an edit of the quad's JSON and binary, as a GLB) and checks
/// that the error names the file and says each needle.
fn expect_gltf_errors(dir: &Path, cases: &[GltfCase]) {
    for (name, edit, needles) in cases {
        let (mut v, mut bin) = quad_parts();
        edit(&mut v, &mut bin);
        let file = format!("{name}.glb");
        let e = match import_file(dir, &file, &glb(&v.to_string(), &bin)) {
            Ok(_) => panic!("{name}: the file was imported"),
            Err(e) => e,
        };
        assert!(e.contains(&file), "{name}: the error does not name the file: {e}");
        assert!(!e.contains("panicked"), "{name}: the glTF reader panicked: {e}");
        for n in *needles {
            assert!(e.contains(n), "{name}: the error should say {n:?}: {e}");
        }
    }
}

#[test]
fn malformed_gltf_documents_are_errors_not_panics() {
    let dir = temp_dir("malformed");
    let set = |pointer: &'static str, value: Value| {
        move |v: &mut Value, _: &mut Vec<u8>| set_at(v, pointer, value.clone())
    };
    let textured = |texture: Value, image: Value| {
        move |v: &mut Value, _: &mut Vec<u8>| {
            v["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
            v["meshes"][0]["primitives"][0]["material"] = 0.into();
            v["textures"] = json!([texture.clone()]);
            v["images"] = json!([image.clone()]);
        }
    };
    let cases: &[GltfCase] = &[
        // The five files that panicked inside the gltf crate.
        ("count0", &set("/accessors/0/count", 0.into()), &["accessors[0]: count 0"]),
        (
            "channel_node",
            &set("/animations/0/channels/0/target/node", 99.into()),
            &["animations[0].channels[0].target names nodes[99], but the file has 2 nodes"],
        ),
        (
            "missing_accessor",
            &set("/meshes/0/primitives/0/attributes/POSITION", 99.into()),
            &["meshes[0].primitives[0] names accessors[99]"],
        ),
        (
            "short_stride",
            &set("/bufferViews/0/byteStride", 4.into()),
            &["bufferViews[0] has byteStride 4, less than one VEC3 FLOAT element (12 bytes)"],
        ),
        (
            "float_indices",
            &|v: &mut Value, _: &mut Vec<u8>| {
                v["accessors"][2]["componentType"] = 5126.into();
                v["accessors"][2]["count"] = 3.into();
            },
            &["accessors[2] (indices of meshes[0].primitives[0]) is SCALAR FLOAT, expected SCALAR of UNSIGNED_BYTE"],
        ),
        // Every other kind of index out of range.
        ("child", &set("/nodes/0/children/0", 7.into()), &["nodes[0].children names nodes[7]"]),
        ("mesh", &set("/nodes/1/mesh", 5.into()), &["nodes[1] names meshes[5]"]),
        ("skin", &set("/nodes/1/skin", 0.into()), &["nodes[1] names skins[0], but the file has 0 skins"]),
        ("view", &set("/accessors/3/bufferView", 9.into()), &["accessors[3] names bufferViews[9]"]),
        ("buffer", &set("/bufferViews/1/buffer", 3.into()), &["bufferViews[1] names buffers[3]"]),
        ("material", &set("/meshes/0/primitives/0/material", 2.into()), &["names materials[2]"]),
        ("sampler", &set("/animations/0/channels/1/sampler", 5.into()), &["channels[1] names samplers[5]"]),
        ("scene", &set("/scene", 4.into()), &["scene names scenes[4]"]),
        ("scene_node", &set("/scenes/0/nodes/0", 3.into()), &["scenes[0].nodes names nodes[3]"]),
        (
            "texture_index",
            &|v: &mut Value, b: &mut Vec<u8>| {
                textured(json!({"source": 0}), json!({"uri": "a.png"}))(v, b);
                v["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"] = 3.into();
            },
            &["materials[0] names textures[3]"],
        ),
        ("image", &textured(json!({"source": 2}), json!({"uri": "a.png"})), &["textures[0] names images[2]"]),
        (
            "texture_sampler",
            &textured(json!({"source": 0, "sampler": 4}), json!({"uri": "a.png"})),
            &["textures[0] names samplers[4]"],
        ),
        // Counts and offsets no buffer holds; strides the specification forbids.
        (
            "huge_count",
            &set("/accessors/0/count", 1_000_000_000_000_000_000u64.into()),
            &["accessors[0]: 1000000000000000000 elements", "past the end of bufferViews[0] (48 bytes)"],
        ),
        ("huge_offset", &set("/accessors/1/byteOffset", u64::MAX.into()), &["accessors[1]", "past the end"]),
        ("odd_stride", &set("/bufferViews/0/byteStride", 14.into()), &["byteStride 14 is not a multiple of 4"]),
        (
            "huge_view",
            &set("/bufferViews/5/byteLength", u64::MAX.into()),
            &["bufferViews[5]: bytes 124 to", "past the end of buffers[0] (148 bytes)"],
        ),
        // A node graph that is not a tree.
        ("cycle", &set("/nodes/1/children", json!([0])), &["lies on a cycle"]),
        ("two_parents", &set("/nodes/0/children", json!([1, 1])), &["nodes[1] is a child of both"]),
        (
            "same_target",
            &set("/animations/0/channels/1/target", json!({"node": 1, "path": "weights"})),
            &["animations[0].channels[1] animates the same node and path as an earlier channel"],
        ),
        (
            "many_nodes",
            &|v: &mut Value, _: &mut Vec<u8>| v["nodes"].as_array_mut().unwrap().resize(70_000, json!({})),
            &["70000 nodes, more than the 65536 this importer reads"],
        ),
    ];
    expect_gltf_errors(&dir, cases);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn gltf_data_that_does_not_fit_its_use_is_refused() {
    let dir = temp_dir("misfit");
    let set = |pointer: &'static str, value: Value| {
        move |v: &mut Value, _: &mut Vec<u8>| set_at(v, pointer, value.clone())
    };
    let float_at = |at: usize, x: f32| {
        move |_: &mut Value, b: &mut Vec<u8>| b[at..at + 4].copy_from_slice(&x.to_le_bytes())
    };
    let cases: &[GltfCase] = &[
        (
            "long_indices",
            &set("/accessors/2/count", 600.into()),
            &["accessors[2]: 600 elements of 2 bytes every 2 from byteOffset 0 end at byte 1200, past the end of bufferViews[2] (12 bytes)"],
        ),
        ("position_scalar", &set("/accessors/0/type", "SCALAR".into()), &["(POSITION of meshes[0].primitives[0]) is SCALAR FLOAT, expected VEC3 of FLOAT"]),
        ("position_vec2", &set("/accessors/0/type", "VEC2".into()), &["is VEC2 FLOAT, expected VEC3"]),
        ("position_bytes", &set("/accessors/0/componentType", 5121.into()), &["is VEC3 UNSIGNED_BYTE, expected VEC3 of FLOAT"]),
        ("short_buffer", &set("/buffers/0/byteLength", 4096.into()), &["buffers[0]: byteLength 4096, but its data has 148 bytes"]),
        (
            "weights_count",
            &set("/accessors/4/count", 1.into()),
            &["animations[0].samplers[0]: 2 keyframes need 2 output values", "the output has 1"],
        ),
        ("times_backwards", &float_at(108, 5.0), &["keyframe times must be finite and increasing"]),
        ("times_nan", &float_at(112, f32::NAN), &["keyframe times must be finite and increasing"]),
        ("position_nan", &float_at(16, f32::NAN), &["non-finite vertex positions"]),
        ("translation_inf", &set("/nodes/1/translation", json!([0, 1e39, 0])), &["nodes[1].translation holds inf"]),
        ("target_count", &set("/accessors/1/count", 3.into()), &["morph target 0's POSITION has 3 elements, POSITION has 4"]),
        ("required_extension", &set("/extensionsRequired", json!(["KHR_draco_mesh_compression"])), &["KHR_draco_mesh_compression"]),
    ];
    expect_gltf_errors(&dir, cases);

    // A mesh of 2^16 vertices under 40 nodes: more vertices than an import makes.
    let (mut v, mut bin) = quad_parts();
    let positions: Vec<u8> = (0..3 << 16).flat_map(|i| ((i % 7) as f32).to_le_bytes()).collect();
    let view = add_view(&mut v, &mut bin, &positions);
    v["accessors"][0] = json!({"bufferView": view, "componentType": 5126, "count": 1 << 16, "type": "VEC3"});
    v["meshes"][0] = json!({"primitives": [{"attributes": {"POSITION": 0}}]});
    v["animations"] = json!([]);
    v["nodes"] = (0..40).map(|_| json!({"mesh": 0})).collect();
    v["scenes"][0]["nodes"] = (0..40).collect();
    let e = import_file(&dir, "instanced.glb", &glb(&v.to_string(), &bin)).unwrap_err();
    assert!(e.contains("instanced.glb") && e.contains("more than 2097152 vertices"), "{e}");

    // A sparse morph target: the same mesh as the dense one; indices must increase.
    let sparse = |indices: &[u16], count: usize| {
        let (mut v, mut bin) = quad_parts();
        let idx: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let values: Vec<u8> = [0f32, 0., 1., 0., 0., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
        let (iv, vv) = (add_view(&mut v, &mut bin, &idx), add_view(&mut v, &mut bin, &values));
        v["accessors"][1] = json!({"componentType": 5126, "count": 4, "type": "VEC3", "sparse": {
            "count": count, "indices": {"bufferView": iv, "componentType": 5123}, "values": {"bufferView": vv}}});
        glb(&v.to_string(), &bin)
    };
    let (json, bin) = quad_asset(None);
    let dense = import_file(&dir, "dense.glb", &glb(&json, &bin)).unwrap();
    assert_eq!(import_file(&dir, "sparse.glb", &sparse(&[2, 1], 1)).unwrap().mesh, dense.mesh);
    let e = import_file(&dir, "sparse_order.glb", &sparse(&[2, 1], 2)).unwrap_err();
    assert!(
        e.contains("sparse_order.glb")
            && e.contains("accessors[1].sparse: index 1 is 1; sparse indices must increase"),
        "{e}"
    );
    let e = import_file(&dir, "sparse_range.glb", &sparse(&[7, 8], 1)).unwrap_err();
    assert!(e.contains("index 0 is 7") && e.contains("below the count 4"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn gltf_uris_stay_inside_the_files_folder() {
    let root = temp_dir("uris");
    let (dir, outside) = (root.join("asset"), root.join("outside"));
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    std::fs::create_dir_all(&outside).unwrap();
    let (json, bin) = quad_asset(None);
    std::fs::write(outside.join("secret.bin"), &bin).unwrap();
    std::fs::write(dir.join("quad data.bin"), &bin).unwrap();
    std::os::unix::fs::symlink(outside.join("secret.bin"), dir.join("link.bin")).unwrap();
    let want = import_file(&dir, "quad.glb", &glb(&json, &bin)).unwrap().mesh;
    let with_uri = |uri: &str| quad_asset(Some(uri)).0.into_bytes();
    // Inside the folder, percent-encoded or through `..` that stays inside: read.
    for uri in ["quad%20data.bin", "sub/../quad%20data.bin", "./quad data.bin"] {
        let got = import_file(&dir, "inside.gltf", &with_uri(uri)).unwrap_or_else(|e| panic!("{uri}: {e}"));
        assert_eq!(got.mesh, want, "{uri}");
    }
    for (uri, needle) in [
        ("../../../../etc/passwd", "climbs out of the glTF file's folder"),
        ("../outside/secret.bin", "climbs out of the glTF file's folder"),
        ("%2e%2e/outside/secret.bin", "climbs out of the glTF file's folder"),
        ("sub/../../outside/secret.bin", "climbs out of the glTF file's folder"),
        ("/etc/passwd", "is an absolute path"),
        ("%2Fetc%2Fpasswd", "is an absolute path"),
        ("file:///etc/passwd", "has the scheme file"),
        ("http://example.com/quad.bin", "has the scheme http"),
        ("link.bin", "outside the glTF file's folder"),
        ("nowhere.bin", "nowhere.bin: No such file"),
        ("bad%zzname.bin", "a % not followed by two hex digits"),
        ("data:application/octet-stream,plain", "is not base64"),
        ("data:application/octet-stream;base64,@@@@", "byte 0 of the base64 data"),
    ] {
        let e = import_file(&dir, "escape.gltf", &with_uri(uri)).expect_err(uri);
        assert!(e.contains("escape.gltf") && e.contains("buffers[0]") && e.contains(needle), "{uri}: {e}");
    }
    // Images follow the same rules.
    for uri in ["../outside/secret.bin", "/etc/passwd", "link.bin"] {
        let (mut v, mut bin) = quad_parts();
        textured_quad(&mut v, &mut bin, json!({"uri": uri}));
        let e = import_file(&dir, "image.glb", &glb(&v.to_string(), &bin)).expect_err(uri);
        assert!(e.contains("image.glb") && e.contains("images[0]") && e.contains(uri), "{uri}: {e}");
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// Gives the quad texture coordinates (0, 0) to (1, 1) and a material whose base colour is a
/// texture of `image`.
fn textured_quad(v: &mut Value, bin: &mut Vec<u8>, image: Value) {
    let uv: Vec<u8> = [0f32, 0., 1., 0., 1., 1., 0., 1.].iter().flat_map(|x| x.to_le_bytes()).collect();
    let view = add_view(v, bin, &uv);
    let accessors = v["accessors"].as_array_mut().unwrap();
    accessors.push(json!({"bufferView": view, "componentType": 5126, "count": 4, "type": "VEC2"}));
    v["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"] = (accessors.len() - 1).into();
    v["meshes"][0]["primitives"][0]["material"] = 0.into();
    v["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
    v["textures"] = json!([{"source": 0}]);
    v["images"] = json!([image]);
}

#[test]
fn gltf_textures_read_png_and_jpeg_from_uris_and_buffer_views() {
    let dir = temp_dir("textures-gltf");
    let img = image::RgbImage::from_fn(8, 6, |x, _| {
        if x < 4 {
            image::Rgb([200, 40, 10])
        } else {
            image::Rgb([10, 90, 250])
        }
    });
    let encode = |format: image::ImageFormat| {
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, format).unwrap();
        bytes.into_inner()
    };
    let (png, jpeg) = (encode(image::ImageFormat::Png), encode(image::ImageFormat::Jpeg));
    std::fs::write(dir.join("tex.png"), &png).unwrap();
    std::fs::write(dir.join("tex.jpg"), &jpeg).unwrap();
    type MakeImage<'a> = Box<dyn Fn(&mut Value, &mut Vec<u8>) -> Value + 'a>;
    let cases: Vec<(&str, MakeImage, u8)> = vec![
        ("png_uri", Box::new(|_, _| json!({"uri": "tex.png"})), 0),
        ("jpeg_uri", Box::new(|_, _| json!({"uri": "tex.jpg"})), 8),
        (
            "png_data_uri",
            Box::new(|_, _| json!({"uri": format!("data:image/png;base64,{}", base64(&png))})),
            0,
        ),
        (
            "png_view",
            Box::new(|v, b| json!({"bufferView": add_view(v, b, &png), "mimeType": "image/png"})),
            0,
        ),
        (
            "jpeg_view",
            Box::new(|v, b| json!({"bufferView": add_view(v, b, &jpeg), "mimeType": "image/jpeg"})),
            8,
        ),
    ];
    for (name, image, tolerance) in cases {
        let (mut v, mut bin) = quad_parts();
        let source = image(&mut v, &mut bin);
        textured_quad(&mut v, &mut bin, source);
        let got = import_file(&dir, &format!("{name}.glb"), &glb(&v.to_string(), &bin))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let t = &got.mesh.textures[0];
        assert_eq!((t.width, t.height), (8, 6), "{name}");
        for (x, want) in [(0usize, [200u8, 40, 10]), (7, [10, 90, 250])] {
            let texel = t.texels[8 * 3 + x];
            for (c, want) in want.into_iter().enumerate() {
                let have = (texel >> (8 * c)) as u8;
                assert!(
                    have.abs_diff(want) <= tolerance,
                    "{name}: texel {x} channel {c} is {have}, want {want}"
                );
            }
        }
    }
    // Not PNG or JPEG, or not an image at all: errors naming the image.
    let (mut v, mut bin) = quad_parts();
    textured_quad(&mut v, &mut bin, json!({"uri": "tex.bmp"}));
    std::fs::write(dir.join("tex.bmp"), b"BM not really").unwrap();
    let e = import_file(&dir, "bmp.glb", &glb(&v.to_string(), &bin)).unwrap_err();
    assert!(e.contains("bmp.glb") && e.contains("images[0] is neither PNG nor JPEG"), "{e}");
    let (mut v, mut bin) = quad_parts();
    let view = add_view(&mut v, &mut bin, &png[..png.len() / 2]);
    textured_quad(&mut v, &mut bin, json!({"bufferView": view, "mimeType": "image/png"}));
    let e = import_file(&dir, "half_png.glb", &glb(&v.to_string(), &bin)).unwrap_err();
    assert!(e.contains("half_png.glb") && e.contains("images[0]"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The quad (no texture) imported from the JSON and binary given.
fn import_quad(dir: &Path, name: &str, v: &Value, bin: &[u8]) -> velox::data::gltf_import::Imported {
    import_file(dir, name, &glb(&v.to_string(), bin)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

#[test]
fn a_child_listed_as_a_scene_root_is_drawn_once_with_a_warning() {
    let dir = temp_dir("child-root");
    let (v, bin) = quad_parts();
    let plain = import_quad(&dir, "plain.glb", &v, &bin);
    assert!(plain.warnings.is_empty(), "{:?}", plain.warnings);
    // The child listed beside its parent (some exporters write this): drawn once, under its
    // parent, so the import is the plain one.
    let mut both = v.clone();
    both["scenes"][0]["nodes"] = json!([0, 1]);
    let got = import_quad(&dir, "both.glb", &both, &bin);
    assert_eq!(got.mesh, plain.mesh);
    assert_eq!(got.warnings.len(), 1, "{:?}", got.warnings);
    assert!(got.warnings[0].contains("nodes[1], a child of nodes[0], as a root"), "{:?}", got.warnings);
    // Listed alone: drawn where the hierarchy puts it (its parent's animated translation too).
    let mut alone = v.clone();
    alone["scenes"][0]["nodes"] = json!([1]);
    let got = import_quad(&dir, "alone.glb", &alone, &bin);
    assert_eq!(got.mesh, plain.mesh);
    assert_eq!(got.warnings.len(), 1);
    // No scene at all: every root node is drawn, and a warning says so.
    let mut none = v.clone();
    none.as_object_mut().unwrap().remove("scenes");
    none.as_object_mut().unwrap().remove("scene");
    let got = import_quad(&dir, "no_scene.glb", &none, &bin);
    assert_eq!(got.mesh, plain.mesh);
    assert!(got.warnings.len() == 1 && got.warnings[0].contains("no scene"), "{:?}", got.warnings);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn quantized_positions_and_morph_targets_read_as_their_values() {
    // KHR_mesh_quantization: the quad's positions as normalised shorts and as plain unsigned
    // bytes (4-byte strides), its morph target as normalised shorts: the import of the floats.
    let dir = temp_dir("quantized");
    let (v, bin) = quad_parts();
    let plain = import_quad(&dir, "plain.glb", &v, &bin);
    let positions = [[0i16, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]];
    let shorts = |m: i16| -> Vec<u8> {
        positions.iter().flat_map(|p| p.iter().chain(&[0]).flat_map(|c| (c * m).to_le_bytes())).collect()
    };
    let target: Vec<u8> = [[0i16, 0, 0], [0, 0, 0], [0, 0, 32767], [0, 0, 0]]
        .iter()
        .flat_map(|p| p.iter().chain(&[0]).flat_map(|c| c.to_le_bytes()))
        .collect();
    let bytes: Vec<u8> = positions.iter().flat_map(|p| [p[0] as u8, p[1] as u8, p[2] as u8, 0]).collect();
    type Case = (&'static str, Vec<u8>, u32, bool);
    let cases: [Case; 2] = [("shorts", shorts(32767), 5122, true), ("bytes", bytes, 5121, false)];
    for (name, data, component, normalized) in cases {
        let (mut q, mut b) = (v.clone(), bin.clone());
        let view = add_view(&mut q, &mut b, &data);
        q["bufferViews"][view]["byteStride"] = json!(if component == 5122 { 8 } else { 4 });
        let tview = add_view(&mut q, &mut b, &target);
        q["bufferViews"][tview]["byteStride"] = json!(8);
        let accessors = q["accessors"].as_array_mut().unwrap();
        accessors.push(json!({"bufferView": view, "componentType": component, "normalized": normalized,
            "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]}));
        accessors.push(json!({"bufferView": tview, "componentType": 5122, "normalized": true,
            "count": 4, "type": "VEC3"}));
        let n = accessors.len();
        q["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(n - 2);
        q["meshes"][0]["primitives"][0]["targets"][0]["POSITION"] = json!(n - 1);
        // Without the extension declared, integer positions break the specification.
        let e = import_file(&dir, &format!("{name}_undeclared.glb"), &glb(&q.to_string(), &b)).unwrap_err();
        assert!(e.contains("POSITION") && e.contains("expected VEC3 of FLOAT"), "{name}: {e}");
        q["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
        q["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
        let got = import_quad(&dir, &format!("{name}.glb"), &q, &b);
        assert_eq!(got.mesh, plain.mesh, "{name}");
        assert!(got.warnings.is_empty(), "{name}: {:?}", got.warnings);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// An animation whose keys hold one pose imports as a still scene, with a warning naming it;
/// the moving one has none. Would catch: a T-pose clip imported as motionless without a word.
#[test]
fn an_animation_that_moves_nothing_is_said() {
    let dir = temp_dir("still-animation");
    let (v, bin) = quad_parts();
    let moving = import_quad(&dir, "moving.glb", &v, &bin);
    assert!(moving.warnings.is_empty(), "{:?}", moving.warnings);
    // Only the translation channel, its two keys the same.
    let (mut q, mut b) = (v.clone(), bin.clone());
    let still: Vec<u8> = [0f32, 1., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
    let view = add_view(&mut q, &mut b, &still);
    let accessors = q["accessors"].as_array_mut().unwrap();
    accessors.push(json!({"bufferView": view, "componentType": 5126, "count": 2, "type": "VEC3"}));
    let n = accessors.len();
    q["animations"][0]["samplers"][1]["output"] = json!(n - 1);
    q["animations"][0]["channels"] = json!([{"sampler": 1, "target": {"node": 0, "path": "translation"}}]);
    q["animations"][0]["name"] = json!("rest");
    let got = import_quad(&dir, "still.glb", &q, &b);
    assert!(got.mesh.frames.iter().all(|f| f == &got.mesh.frames[0]), "the scene is still");
    assert_eq!(got.warnings.len(), 1, "{:?}", got.warnings);
    assert!(got.warnings[0].contains("animations[0] (rest) moves nothing"), "{:?}", got.warnings);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A flat model seen edge-on by the video camera (on +x) gives the scene no tracking queries,
/// and the scene's notes say so as a warning; the same model turned to face the camera gets
/// its queries and no warning. Would catch: a scene the tracking task cannot use written
/// without a word.
#[test]
fn a_scene_the_video_camera_cannot_see_is_warned_of() {
    let dir = temp_dir("edge-on");
    let (mut v, bin) = quad_parts();
    // Without its morph target the quad stays in z = 0 (its animation moves it along x), the
    // plane the video camera lies in.
    v["meshes"][0]["primitives"][0].as_object_mut().unwrap().remove("targets");
    v["meshes"][0].as_object_mut().unwrap().remove("weights");
    v["animations"][0]["channels"] = json!([{"sampler": 1, "target": {"node": 0, "path": "translation"}}]);
    let opts = SynthOptions { res: 24, points: 300, supersample: 1, tracks: 8, ..Default::default() };
    let notes = |name: &str, v: &Value| {
        let imported = import_quad(&dir, &format!("{name}.glb"), v, &bin);
        let meta = write_scene(&gpu(), &imported.mesh, name, None, 0, &opts, &dir.join(name), &mut |_| {})
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        (meta.video_tracks, scene_notes(&meta, opts.tracks))
    };
    let (queries, edge_on) = notes("edge-on", &v);
    assert_eq!(queries, 0);
    let warnings: Vec<_> = edge_on.iter().filter(|n| n.0 == Severity::Warning).collect();
    assert_eq!(warnings.len(), 1, "{edge_on:?}");
    assert!(warnings[0].1.contains("no tracking queries"), "{edge_on:?}");
    // Turned a quarter about y, it faces the camera.
    let mut facing = v.clone();
    facing["nodes"][0]["rotation"] =
        json!([0.0, std::f32::consts::FRAC_1_SQRT_2, 0.0, std::f32::consts::FRAC_1_SQRT_2]);
    let (queries, facing) = notes("facing", &facing);
    assert!(queries > 0, "{facing:?}");
    assert!(facing.iter().all(|n| n.0 == Severity::Note), "{facing:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Tangents are never read by the import, so no kind of them stops it: normalised bytes (as
/// KHR_mesh_quantization allows), or a kind no extension allows; their index must still be in
/// range and their count the primitive's. Would catch: a file refused for an attribute the
/// import does not use ("TANGENT ... expected VEC4 of FLOAT" for a valid quantized file).
#[test]
fn attributes_the_import_does_not_read_never_stop_it() {
    let dir = temp_dir("unread-attributes");
    let (v, bin) = quad_parts();
    let plain = import_quad(&dir, "plain.glb", &v, &bin);
    let tangent_bytes: Vec<u8> = [[127i8, 0, 0, 127]; 4].iter().flatten().map(|&c| c as u8).collect();
    let cases: [(&str, u32, bool, &str, bool); 3] = [
        ("normalized_bytes", 5120, true, "VEC4", true),
        ("plain_bytes_undeclared", 5120, false, "VEC4", false),
        ("scalar_bytes", 5121, false, "SCALAR", false),
    ];
    for (name, component, normalized, kind, quantized) in cases {
        let (mut q, mut b) = (v.clone(), bin.clone());
        let view = add_view(&mut q, &mut b, &tangent_bytes);
        let accessors = q["accessors"].as_array_mut().unwrap();
        accessors.push(json!({"bufferView": view, "componentType": component, "normalized": normalized,
            "count": 4, "type": kind}));
        let n = accessors.len();
        q["meshes"][0]["primitives"][0]["attributes"]["TANGENT"] = json!(n - 1);
        if quantized {
            q["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
            q["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
        }
        let got = import_quad(&dir, &format!("{name}.glb"), &q, &b);
        assert_eq!(got.mesh, plain.mesh, "{name}");
    }
    // Out of range, or of another count than the positions: refused, by name.
    let mut q = v.clone();
    q["meshes"][0]["primitives"][0]["attributes"]["TANGENT"] = json!(99);
    let e = import_file(&dir, "out_of_range.glb", &glb(&q.to_string(), &bin)).unwrap_err();
    assert!(e.contains("TANGENT") && e.contains("accessors[99]"), "{e}");
    let (mut q, mut b) = (v.clone(), bin.clone());
    let view = add_view(&mut q, &mut b, &tangent_bytes);
    let accessors = q["accessors"].as_array_mut().unwrap();
    accessors.push(json!({"bufferView": view, "componentType": 5121, "count": 3, "type": "VEC4"}));
    let n = accessors.len();
    q["meshes"][0]["primitives"][0]["attributes"]["TANGENT"] = json!(n - 1);
    let e = import_file(&dir, "short.glb", &glb(&q.to_string(), &b)).unwrap_err();
    assert!(e.contains("TANGENT") && e.contains("3 elements"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_texture_transform_moves_the_sampled_coordinates() {
    // KHR_texture_transform on the base colour: scale, then rotation, then offset, as the
    // extension's example says (offset (0, 1), rotation pi/2, scale 1/2: the lower-left quadrant).
    let dir = temp_dir("texture-transform");
    let png = {
        let img = image::RgbImage::from_fn(4, 4, |x, y| image::Rgb([60 * x as u8, 60 * y as u8, 0]));
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        bytes.into_inner()
    };
    let uvs = [[0f32, 0.], [1., 0.], [1., 1.], [0., 1.]];
    let cases: [(&str, Value, [[f32; 2]; 4]); 3] = [
        ("none", json!({}), uvs),
        (
            "offset_scale",
            json!({"offset": [0.5, 0.25], "scale": [0.5, 2.0]}),
            [[0.5, 0.25], [1.0, 0.25], [1.0, 2.25], [0.5, 2.25]],
        ),
        (
            "example",
            json!({"offset": [0, 1], "rotation": std::f32::consts::FRAC_PI_2, "scale": [0.5, 0.5]}),
            [[0.0, 1.0], [0.0, 0.5], [0.5, 0.5], [0.5, 1.0]],
        ),
    ];
    for (name, transform, want) in cases {
        let (mut v, mut bin) = quad_parts();
        let view = add_view(&mut v, &mut bin, &png);
        textured_quad(&mut v, &mut bin, json!({"bufferView": view, "mimeType": "image/png"}));
        if transform != json!({}) {
            v["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["extensions"] =
                json!({"KHR_texture_transform": transform});
            v["extensionsUsed"] = json!(["KHR_texture_transform"]);
        }
        let got = import_quad(&dir, &format!("{name}.glb"), &v, &bin);
        for (have, want) in got.mesh.uvs.iter().zip(want) {
            assert!(
                (have[0] - want[0]).abs() < 1e-6 && (have[1] - want[1]).abs() < 1e-6,
                "{name}: {have:?} vs {want:?}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn required_extensions_are_read_ignored_with_a_warning_or_refused_by_name() {
    let dir = temp_dir("extensions");
    let (v, bin) = quad_parts();
    let plain = import_quad(&dir, "plain.glb", &v, &bin);
    let with = |used: Value, required: Value| {
        let mut q = v.clone();
        q["extensionsUsed"] = used;
        q["extensionsRequired"] = required;
        q
    };
    // Lights: no part in points or renders; imported with a note.
    let got = import_quad(
        &dir,
        "lights.glb",
        &with(json!(["KHR_lights_punctual"]), json!(["KHR_lights_punctual"])),
        &bin,
    );
    assert_eq!(got.mesh, plain.mesh);
    assert!(got.warnings.len() == 1 && got.warnings[0].contains("KHR_lights_punctual"), "{:?}", got.warnings);
    // An extension only used never stops an import, known or not.
    let got = import_quad(
        &dir,
        "used.glb",
        &with(json!(["EXT_meshopt_compression", "EXT_made_up"]), json!([])),
        &bin,
    );
    assert_eq!(got.mesh, plain.mesh);
    assert!(got.warnings.is_empty(), "{:?}", got.warnings);
    // Required and refused, or unknown: errors that name it.
    for (ext, says) in [
        ("EXT_meshopt_compression", "refuses"),
        ("KHR_draco_mesh_compression", "refuses"),
        ("KHR_texture_basisu", "refuses"),
        ("EXT_made_up", "does not read"),
    ] {
        let q = with(json!([ext]), json!([ext]));
        let e = import_file(&dir, &format!("{ext}.glb"), &glb(&q.to_string(), &bin)).unwrap_err();
        assert!(e.contains(ext) && e.contains(says) && e.contains(&format!("{ext}.glb")), "{e}");
    }
    // A specular-glossiness material: its diffuse colour is the base colour.
    let mut q =
        with(json!(["KHR_materials_pbrSpecularGlossiness"]), json!(["KHR_materials_pbrSpecularGlossiness"]));
    q["meshes"][0]["primitives"][0]["material"] = json!(0);
    q["materials"] = json!([{"extensions": {"KHR_materials_pbrSpecularGlossiness": {"diffuseFactor": [0.2, 0.4, 0.6, 1.0]}}}]);
    let got = import_quad(&dir, "specgloss.glb", &q, &bin);
    assert_eq!(got.mesh.textures, vec![velox::data::Texture::solid([0.2, 0.4, 0.6])]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_scene_file_that_fails_is_a_file_error_with_its_path() {
    use velox::data::DataError;
    use velox::engine::{Error, FileOp};
    let dir = temp_dir("file-errors");
    let file_error = |e: DataError| match e {
        DataError::Engine(Error::File { path, op, .. }) => (path, op),
        other => panic!("not a file error: {other}"),
    };
    let (path, op) = file_error(read_scene(&dir, false).unwrap_err());
    assert_eq!((path, op), (dir.join("meta.json"), FileOp::Read));
    std::fs::write(dir.join("meta.json"), b"{ not json").unwrap();
    let (path, op) = file_error(read_scene(&dir, false).unwrap_err());
    assert_eq!((path, op), (dir.join("meta.json"), FileOp::Content));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dataset_on_disk_reads_back_in_the_background() {
    let root = temp_dir("dataset");
    let opts = SynthOptions { res: 16, points: 500, supersample: 2, tracks: 8, ..Default::default() };
    let mut written = Vec::new();
    for seed in 0..2u64 {
        let (_, mesh) = scene(seed, None).unwrap();
        let dir = root.join(format!("scene_{seed:05}"));
        let a = render_scene(&gpu(), &mesh, &opts, seed, Some(&dir), &mut |_| {}).unwrap();
        let meta = SceneMeta {
            format: FORMAT.into(),
            source: format!("procedural seed {seed}"),
            credits: None,
            frames: FRAMES,
            fps: FPS,
            resolution: opts.res,
            points: a.points.len(),
            tracks: a.tracks.len(),
            video_tracks: a.video_tracks.len(),
            supervision_views: a.supervision_cameras.len(),
            supersample: opts.supersample,
            background: opts.background,
        };
        write_arrays(&dir, &meta, &a).unwrap();
        written.push(a);
    }
    let s = read_scene(&root.join("scene_00001"), true).unwrap();
    assert_eq!(s.points, written[1].points);
    assert_eq!(s.occupancy, written[1].occupancy);
    assert_eq!(s.tracks, written[1].tracks);
    assert_eq!(s.visibility, written[1].visibility);
    assert_eq!(s.video_tracks, written[1].video_tracks);
    assert_eq!(s.video_visibility, written[1].video_visibility);
    assert_eq!(s.cameras.supervision, written[1].supervision_cameras);
    assert_eq!(s.supervision.len(), FRAMES * 25);
    assert_eq!(s.video.len(), FRAMES);
    assert!(s.supervision.iter().any(|img| img.iter().any(|&b| b > 0)), "supervision views show the object");

    // A damaged scene is an error naming it; the loader goes on to the next.
    std::fs::write(root.join("scene_00000/points.ply"), b"ply\nnonsense").unwrap();
    let results: Vec<_> =
        Loader::spawn(&root, LoaderOptions { images: false, ..Default::default() }).unwrap().collect();
    assert_eq!(results.len(), 2);
    let err = results[0].as_ref().unwrap_err().to_string();
    assert!(err.contains("scene_00000") && err.contains("points.ply"), "{err}");
    assert_eq!(results[1].as_ref().unwrap().points, written[1].points);
    // Shuffled, several epochs, dropped early: the thread stops.
    let mut l = Loader::spawn(
        &root,
        LoaderOptions { epochs: 0, shuffle: Some(1), images: false, ..Default::default() },
    )
    .unwrap();
    for _ in 0..5 {
        assert!(l.next().is_some());
    }
    drop(l);
    // Started part-way (mid-epoch), the loader reads the scenes of `order::scene_at` from there
    // on (scene_00000 is the damaged one), and a count of epochs counts from the first.
    let opts = LoaderOptions { epochs: 4, shuffle: Some(7), start: 3, images: false, prefetch: 1 };
    let got: Vec<usize> = Loader::spawn(&root, opts).unwrap().map(|r| r.is_ok() as usize).collect();
    let want: Vec<usize> = (3..8).map(|p| order::scene_at(2, Some(7), p)).collect();
    assert_eq!(got, want);
    let _ = std::fs::remove_dir_all(&root);
}

/// Bytes of `path` with `edit` applied, written back; the original bytes are returned.
fn edit_file(path: &Path, edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let original = std::fs::read(path).unwrap();
    let mut bytes = original.clone();
    edit(&mut bytes);
    std::fs::write(path, bytes).unwrap();
    original
}

#[test]
fn point_cloud_files_are_checked_against_their_header_and_the_format() {
    let dir = temp_dir("ply");
    let points: Vec<[f32; 7]> =
        (0..5).map(|i| [0.1 * i as f32, -0.5, 0.25, 0.2, 0.4, 0.6, i as f32 / FPS]).collect();
    let path = dir.join("points.ply");
    write_ply(&path, &points).unwrap();
    assert_eq!(read_ply(&path).unwrap(), points);
    let body = 5 * 28;
    let expect = |what: &str, edit: &dyn Fn(&mut Vec<u8>), needles: &[&str]| {
        let original = edit_file(&path, edit);
        let e = read_ply(&path).expect_err(what).to_string();
        assert!(e.contains("points.ply"), "{what}: the error does not name the file: {e}");
        for n in needles {
            assert!(e.contains(n), "{what}: the error should mention {n:?}: {e}");
        }
        std::fs::write(&path, original).unwrap();
    };
    let header = |from: &'static str, to: &'static str| {
        move |b: &mut Vec<u8>| {
            let head = String::from_utf8(b[..b.len() - body].to_vec()).unwrap();
            let rest = b[b.len() - body..].to_vec();
            *b = [head.replace(from, to).into_bytes(), rest].concat();
        }
    };
    let huge = header("element vertex 5", "element vertex 1000000000000000000");
    expect("a count past any file", &huge, &["truncated", "1000000000000000000 vertex of 28 bytes"]);
    let uchar = header("property float", "property uchar");
    expect("uchar properties", &uchar, &["not one vertex element of float x y z r g b tau"]);
    expect("trailing bytes", &|b| b.extend_from_slice(&[0; 28]), &["does not match the header", "has 168"]);
    expect("a short body", &|b| b.truncate(b.len() - 3), &["truncated"]);
    let value = |point: usize, channel: usize, v: f32| {
        move |b: &mut Vec<u8>| {
            let at = b.len() - body + 28 * point + 4 * channel;
            b[at..at + 4].copy_from_slice(&v.to_le_bytes());
        }
    };
    expect("NaN", &value(3, 1, f32::NAN), &["point 3 has a non-finite value in channel 1"]);
    expect("Inf", &value(2, 6, f32::INFINITY), &["point 2 has a non-finite value in channel 6"]);
    expect("outside the cube", &value(1, 2, 1.5), &["point 1", "outside [-1, 1]^3"]);
    expect("colour", &value(4, 4, 2.0), &["point 4 has colour"]);
    expect("a frame past the clip", &value(0, 6, 0.5), &["point 0 has frame time tau = 0.5"]);
    expect("between frames", &value(0, 6, 0.015), &["point 0 has frame time tau = 0.015"]);
    let empty = dir.join("empty.ply");
    write_ply(&empty, &[]).unwrap();
    assert!(read_ply(&empty).unwrap_err().to_string().contains("empty"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn damaged_scene_folders_are_errors_naming_the_file_and_the_problem() {
    let root = temp_dir("damaged");
    let dir = root.join("scene");
    let (_, mesh) = scene(2, None).unwrap();
    let opts = SynthOptions { res: 16, points: 400, supersample: 1, tracks: 6, ..Default::default() };
    let meta = write_scene(&gpu(), &mesh, "procedural seed 2", None, 2, &opts, &dir, &mut |_| {}).unwrap();
    let good = read_scene(&dir, true).unwrap();
    assert_eq!((good.points.len(), good.tracks.len()), (400, 6));
    // `edit` changes one file (meta.json unless the name says otherwise: "edited > named");
    // the error must name the file it finds at fault.
    let expect = |files: &str, what: &str, edit: &dyn Fn(&mut Vec<u8>), needles: &[&str]| {
        let (edited, named) = files.split_once(" > ").unwrap_or((files, files));
        let original = edit_file(&dir.join(edited), edit);
        let Err(e) = read_scene(&dir, false) else { panic!("{what}: the scene was accepted") };
        let e = e.to_string();
        assert!(
            e.contains(&dir.join(named).display().to_string()),
            "{what}: the error does not name {named}: {e}"
        );
        for n in needles {
            assert!(e.contains(n), "{what}: the error should mention {n:?}: {e}");
        }
        std::fs::write(dir.join(edited), original).unwrap();
    };
    let meta_with = |f: &dyn Fn(&mut SceneMeta)| {
        let mut m = meta.clone();
        f(&mut m);
        move |b: &mut Vec<u8>| *b = serde_json::to_vec(&m).unwrap()
    };
    // Counts that overflow, that the files do not hold, or that readers would index past.
    let huge = meta_with(&|m| m.tracks = 1_000_000_000_000_000_000);
    expect("meta.json", "10^18 tracks", &huge, &["tracks is 1000000000000000000, expected 0 to 1048576"]);
    let no_views = meta_with(&|m| m.supervision_views = 0);
    expect("meta.json", "no supervision views", &no_views, &["supervision_views is 0"]);
    let glowing = meta_with(&|m| m.background = [0.0, 2.0, 0.0]);
    expect("meta.json", "a background past white", &glowing, &["background [0.0, 2.0, 0.0]"]);
    let fewer_views = meta_with(&|m| m.supervision_views = 24);
    expect(
        "meta.json > cameras.json",
        "a view too few",
        &fewer_views,
        &["25 supervision cameras", "supervision_views = 24"],
    );
    let points = meta_with(&|m| m.points = 401);
    expect(
        "meta.json > points.ply",
        "a wrong point count",
        &points,
        &["400 points", "meta.json says points = 401"],
    );
    let tracks = meta_with(&|m| m.tracks = 7);
    expect(
        "meta.json > tracks.bin",
        "a track more",
        &tracks,
        &["1728 bytes, expected 2016", "7 tracks, as meta.json says"],
    );
    for (res, needle) in [(0, "resolution is 0"), (100_000, "resolution is 100000, expected 1 to 4096")] {
        expect("meta.json", "resolution", &meta_with(&|m| m.resolution = res), &[needle]);
    }
    expect("occupancy.bin", "truncated occupancy", &|b| b.truncate(1000), &["1000 bytes, expected 786432"]);
    // Cameras: finite, a rotation, positive focal lengths, the scene's size.
    let cameras: CameraSet =
        serde_json::from_slice(&std::fs::read(dir.join("cameras.json")).unwrap()).unwrap();
    let cams_with = |f: &dyn Fn(&mut CameraSet)| {
        let mut c = cameras.clone();
        f(&mut c);
        move |b: &mut Vec<u8>| *b = serde_json::to_vec(&c).unwrap()
    };
    let fx = cams_with(&|c| c.supervision[3].fx = -1.0);
    expect("cameras.json", "a negative focal length", &fx, &["supervision camera 3", "fx = -1"]);
    let big = cams_with(&|c| c.input[5].translation[1] = 123456.0);
    let inf = move |b: &mut Vec<u8>| {
        big(b);
        *b = String::from_utf8(b.clone()).unwrap().replace("123456.0", "1e39").into_bytes();
    };
    expect("cameras.json", "an infinite translation", &inf, &["input camera 5 has a non-finite"]);
    let skew = cams_with(&|c| c.video.as_mut().unwrap().rotation[0][1] += 0.5);
    expect("cameras.json", "a skewed rotation", &skew, &["the video camera", "not a rotation matrix"]);
    let size = cams_with(&|c| c.input[0].width = 17);
    expect("cameras.json", "a wrong image size", &size, &["input camera 0 is 17 x 16"]);
    let few = cams_with(&|c| c.input.truncate(34));
    expect("cameras.json", "a missing input camera", &few, &["34 input cameras, expected 35"]);
    // Values: tracks finite and inside the cube, visibility only from the input cameras.
    let nan = |b: &mut Vec<u8>| b[4 * 7..4 * 8].copy_from_slice(&f32::NAN.to_le_bytes());
    expect("tracks.bin", "a NaN track", &nan, &["track 0 at frame 2 has coordinate NaN"]);
    let bit = |b: &mut Vec<u8>| b[8 * 30..8 * 31].copy_from_slice(&(1u64 << 40).to_le_bytes());
    expect("tracks_visibility.bin", "camera 40", &bit, &["track 1 at frame 6 is seen by camera 40"]);
    let late = |b: &mut Vec<u8>| {
        let at = b.len() - 4;
        b[at..].copy_from_slice(&0.3f32.to_le_bytes());
    };
    expect("points.ply", "tau past the clip", &late, &["point 399 has frame time tau = 0.3"]);
    assert_eq!(read_scene(&dir, true).unwrap().points, good.points, "every file was restored");
    // Options out of range are refused before anything is written.
    for (opts, needle) in [
        (SynthOptions { points: 0, ..opts.clone() }, "points 0 is out of range: a scene takes 1 to 16777216"),
        (SynthOptions { tracks: 1 << 30, ..opts.clone() }, "tracks 1073741824 is out of range"),
    ] {
        let e = write_scene(&gpu(), &mesh, "x", None, 0, &opts, &root.join("refused"), &mut |_| {});
        let e = e.unwrap_err().to_string();
        assert!(e.contains(needle), "{e}");
    }
    assert!(!root.join("refused").exists());
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn textures_crop_a_folder_of_images() {
    let dir = temp_dir("textures");
    let img = image::RgbImage::from_fn(300, 200, |x, y| image::Rgb([(x % 256) as u8, (y % 256) as u8, 77]));
    img.save(dir.join("a.png")).unwrap();
    std::fs::write(dir.join("notes.txt"), "not an image").unwrap();
    let folder = velox::data::texture::ImageFolder::open(&dir).unwrap();
    let mut rng = Rng::new(3);
    let t = folder.random_crop(&mut rng).unwrap();
    assert_eq!((t.width, t.height, t.texels.len()), (128, 128, 128 * 128));
    assert!(t.texels.iter().all(|&v| (v >> 16) & 255 == 77), "the crop keeps the image's blue channel");
    // Scenes with a folder use its crops on some objects.
    let (_, mesh) = scene(4, Some(&folder)).unwrap();
    assert!(mesh.textures.iter().any(|t| t.texels.iter().all(|&v| (v >> 16) & 255 == 77)));
    // A broken image is an error naming it.
    std::fs::write(dir.join("a.png"), b"\x89PNG broken").unwrap();
    let err = folder.random_crop(&mut rng).unwrap_err().to_string();
    assert!(err.contains("a.png"), "{err}");
    let empty = temp_dir("no-images");
    assert!(velox::data::texture::ImageFolder::open(&empty).is_err());
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&empty);
}

/// The tracking task's data: the video's depth frames back-project to a cloud of what the
/// video shows; each query is a back-projected pixel of its first frame, seen there, and
/// where the video sees a query later it is not behind the depth frame there. A depth frame
/// that does not fit the camera or the scene's box is refused.
#[test]
fn tracking_video_is_rgbd_and_its_queries_lie_on_its_first_frame() {
    use velox::data::rgbd::{colours_at, read_rgbd_video, rgbd_cloud};
    use velox::io::image::write_exr_depth;
    let root = temp_dir("tracking-video");
    let opts = SynthOptions { res: 48, points: 500, supersample: 1, tracks: 40, ..Default::default() };
    let (_, mesh) = scene(3, None).unwrap();
    let dir = root.join("scene_00003");
    let a = render_scene(&gpu(), &mesh, &opts, 3, Some(&dir), &mut |_| {}).unwrap();
    assert_eq!(a.video_tracks.len(), 40);
    let cam = a.video_camera.unwrap();
    let video = read_rgbd_video(&dir.join("video"), cam).unwrap();
    let all = rgbd_cloud(&video, usize::MAX, 0).unwrap();
    let surface: usize = video.depth.iter().map(|d| d.iter().filter(|&&z| z > 0.0).count()).sum();
    assert_eq!(all.len(), surface);
    assert!(all.windows(2).all(|w| w[0][6] <= w[1][6]), "frame order");
    let first: Vec<&[f32; 7]> = all.iter().filter(|p| p[6] == 0.0).collect();
    let w = cam.width as usize;
    let queries: Vec<[f32; 3]> = a.video_tracks.iter().map(|t| t[0]).collect();
    let colours = colours_at(&video.rgb[0], &cam, &queries);
    for ((t, seen), colour) in a.video_tracks.iter().zip(&a.video_visibility).zip(&colours) {
        assert!(seen[0], "a query is seen on the first frame");
        let distance = |p: &[f32; 7]| (0..3).map(|k| (p[k] - t[0][k]).powi(2)).sum::<f32>().sqrt();
        let nearest = first.iter().min_by(|p, q| distance(p).total_cmp(&distance(q))).unwrap();
        assert!(
            distance(nearest) < 1e-3,
            "query {:?} is {} from every back-projected pixel",
            t[0],
            distance(nearest)
        );
        // A query's colour is its pixel's: the back-projected point it lies on carries it.
        assert_eq!(colour[..], nearest[3..6], "the colour of query {:?}", t[0]);
        for f in (0..FRAMES).filter(|&f| seen[f]) {
            let (u, v, z) = cam.project(t[f]);
            let d = video.depth[f][v as usize * w + u as usize];
            assert!(
                d > 0.0 && z <= d + 3.0 * z / cam.fx,
                "frame {f}: seen at depth {z}, the surface is at {d}"
            );
        }
    }
    assert!(a.video_visibility.iter().any(|s| s.iter().any(|&v| !v)), "some query is hidden at some frame");
    // A point beyond the image's left edge takes the colour of the edge's pixel in its row.
    let outside = cam.unproject(-7.5, 10.5, 2.0);
    let pixel = |u: usize, v: usize| video.rgb[0][3 * (v * w + u)..3 * (v * w + u) + 3].to_vec();
    assert_eq!(colours_at(&video.rgb[0], &cam, &[outside])[0].to_vec(), pixel(0, 10));
    let some = rgbd_cloud(&video, 100, 1).unwrap();
    assert_eq!(some.len(), 100);
    assert!(some.iter().all(|p| all.contains(p)), "a draw keeps points of the cloud");
    assert_eq!(some, rgbd_cloud(&video, 100, 1).unwrap(), "the same seed draws the same points");

    let far: Vec<f32> = video.depth[5].iter().map(|z| z * 10.0).collect();
    write_exr_depth(&dir.join("video/f05_depth.exr"), &far, cam.width, cam.height).unwrap();
    let e = rgbd_cloud(&read_rgbd_video(&dir.join("video"), cam).unwrap(), 100, 0).unwrap_err().to_string();
    assert!(e.contains("frame 5") && e.contains("outside"), "{e}");
    let mut bad = video.depth[5].clone();
    bad[7] = f32::NAN;
    write_exr_depth(&dir.join("video/f05_depth.exr"), &bad, cam.width, cam.height).unwrap();
    let e = read_rgbd_video(&dir.join("video"), cam).unwrap_err().to_string();
    assert!(e.contains("f05_depth.exr") && e.contains("(7, 0)"), "{e}");
    write_exr_depth(&dir.join("video/f05_depth.exr"), &video.depth[5][..w * 20], cam.width, 20).unwrap();
    let e = read_rgbd_video(&dir.join("video"), cam).unwrap_err().to_string();
    assert!(e.contains("48 x 20"), "{e}");
}

#[test]
fn a_background_colours_the_views_and_never_the_cloud() {
    use velox::tasks::training::HostScene;
    let root = temp_dir("background");
    let (_, mesh) = scene(3, None).unwrap();
    let black = SynthOptions { res: 16, points: 400, supersample: 2, tracks: 4, ..Default::default() };
    let white = SynthOptions { background: [1.0, 0.5, 0.25], ..black.clone() };
    for (name, opts) in [("black", &black), ("white", &white)] {
        write_scene(&gpu(), &mesh, "procedural seed 3", None, 3, opts, &root.join(name), &mut |_| {})
            .unwrap();
    }
    let (b, w) =
        (read_scene(&root.join("black"), true).unwrap(), read_scene(&root.join("white"), true).unwrap());
    assert_eq!((b.meta.background, w.meta.background), ([0.0; 3], [1.0, 0.5, 0.25]));
    // The cloud, its colours and the tracks are the same bits: the background is no surface.
    assert_eq!(b.points, w.points);
    assert_eq!(b.tracks, w.tracks);
    // A pixel the object does not cover is the background in the views and the video.
    let corner = |img: &[u8]| [img[0], img[1], img[2]];
    assert_eq!(corner(&b.supervision[0]), [0, 0, 0]);
    assert_eq!(corner(&w.supervision[0]), [255, 128, 64]);
    assert_eq!(corner(&w.video[0]), [255, 128, 64]);
    // Training renders on it.
    assert_eq!(HostScene::new(&w).unwrap().upload(&gpu()).unwrap().background, [1.0, 0.5, 0.25]);
    let bad = SynthOptions { background: [1.5, 0.0, 0.0], ..black };
    let e = write_scene(&gpu(), &mesh, "x", None, 3, &bad, &root.join("bad"), &mut |_| {}).unwrap_err();
    assert!(e.to_string().contains("background [1.5, 0.0, 0.0]: each channel must lie in [0, 1]"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

/// The channels of each pixel that shows the surface, as fractions of 255.
fn surface_rgb(frame: &velox::data::raster::Frame) -> Vec<[f64; 3]> {
    (0..frame.ids.len())
        .filter(|&k| frame.ids[k] != NO_TRIANGLE)
        .map(|k| [0, 8, 16].map(|s| ((frame.rgb[k] >> s) & 255) as f64 / 255.0))
        .collect()
}

#[test]
fn vertex_colours_multiply_the_base_colour_in_the_import_and_the_render() {
    // The quad with COLOR_0 as normalised unsigned bytes (RGBA) and as floats (RGB), and a
    // base-colour factor: the import keeps every vertex's colour, and the render shows the
    // product (a pink model imported white before). Shading scales the three channels alike,
    // so their ratios are the product's.
    let dir = temp_dir("vertex-colours");
    let pink = [1.0f32, 0.4, 0.7];
    let factor = [0.5f32, 1.0, 1.0];
    let bytes: Vec<u8> = (0..4).flat_map(|_| [255u8, 102, 179, 255]).collect();
    let floats: Vec<u8> = (0..4).flat_map(|_| pink).flat_map(f32::to_le_bytes).collect();
    let cams: Vec<Camera> = input_cameras(16);
    let (v, bin) = quad_parts();
    let plain = import_quad(&dir, "plain.glb", &v, &bin);
    assert!(plain.mesh.colours.is_empty(), "a file without COLOR_0 has no vertex colours");
    for (name, data, component, ty) in [("bytes", &bytes, 5121, "VEC4"), ("floats", &floats, 5126, "VEC3")] {
        let (mut v, mut bin) = quad_parts();
        let view = add_view(&mut v, &mut bin, data);
        let accessors = v["accessors"].as_array_mut().unwrap();
        accessors
            .push(json!({"bufferView": view, "componentType": component, "normalized": component != 5126,
                              "count": 4, "type": ty}));
        let index = accessors.len() - 1;
        v["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = index.into();
        v["meshes"][0]["primitives"][0]["material"] = 0.into();
        v["materials"] =
            json!([{"pbrMetallicRoughness": {"baseColorFactor": [factor[0], factor[1], factor[2], 1.0]}}]);
        let got = import_quad(&dir, &format!("{name}.glb"), &v, &bin);
        assert_eq!(got.mesh.colours.len(), 4, "{name}");
        for c in &got.mesh.colours {
            for k in 0..3 {
                assert!((c[k] - pink[k]).abs() < 1.0 / 255.0, "{name}: vertex colour {c:?}, want {pink:?}");
            }
        }
        let rast = MeshRasteriser::new(&gpu(), &got.mesh).unwrap();
        let rgb = surface_rgb(&rast.render(&got.mesh.frames[0], &cams).unwrap());
        let bright: Vec<&[f64; 3]> = rgb.iter().filter(|c| c[0] > 0.3).collect();
        assert!(bright.len() > 50, "{name}: {} lit pixels show the quad", bright.len());
        let want = [0, 1, 2].map(|k| (factor[k] * pink[k]) as f64);
        for c in bright {
            for k in 1..3 {
                let (ratio, expected) = (c[k] / c[0], want[k] / want[0]);
                assert!(
                    (ratio - expected).abs() < 0.03,
                    "{name}: pixel {c:?}: channel {k} / red {ratio}, want {expected}"
                );
            }
        }
    }
    // The same quad without COLOR_0 renders the factor alone.
    let rast = MeshRasteriser::new(&gpu(), &plain.mesh).unwrap();
    let rgb = surface_rgb(&rast.render(&plain.mesh.frames[0], &cams).unwrap());
    assert!(rgb.iter().all(|c| c[0] == c[1] && c[1] == c[2]), "the plain quad is grey");
    // Colours outside [0, 1] are refused by name.
    let (mut v, mut bin) = quad_parts();
    let too_bright: Vec<u8> = (0..4).flat_map(|_| [2.0f32, 0.5, 0.5]).flat_map(f32::to_le_bytes).collect();
    let view = add_view(&mut v, &mut bin, &too_bright);
    let accessors = v["accessors"].as_array_mut().unwrap();
    accessors.push(json!({"bufferView": view, "componentType": 5126, "count": 4, "type": "VEC3"}));
    let index = accessors.len() - 1;
    v["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = index.into();
    let e = import_file(&dir, "too_bright.glb", &glb(&v.to_string(), &bin)).unwrap_err();
    assert!(e.contains("too_bright.glb") && e.contains("COLOR_0") && e.contains("[0, 1]"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
