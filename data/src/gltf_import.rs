//! glTF 2.0 import (.gltf with embedded or side-by-side buffers, and .glb): triangle meshes
//! under the node hierarchy of the default scene, skins (linear blend skinning with the
//! inverse bind matrices), morph targets (positions), node and morph-weight animation with
//! step, linear (slerp for rotations) and cubic-spline interpolation, and base-colour textures
//! times the base-colour factor (the factor alone where there is no texture).
//!
//! One animation is sampled at 24 evenly spaced times from its first to its last keyframe (a
//! file without animation gives a still clip); the clip is then normalised into [-1, 1]^3 like
//! the procedural objects. Per the specification, a skinned mesh ignores its own node's
//! transform. Points and lines are skipped; triangle strips and fans become triangles.
//! Every error names the file.

use std::path::Path;

use gltf::animation::{util::ReadOutputs, Interpolation, Property};
use gltf::mesh::Mode;

use crate::math::{add, add_scaled, mul, normalize_quat, slerp, transform_point, trs, M4, V3};
use crate::mesh::{AnimatedMesh, Texture};
use crate::procedural::FRAMES;
use crate::{DataError, DataResult};

/// Largest texture side kept; larger base-colour images are scaled down to it.
pub const MAX_TEXTURE: u32 = 1024;

/// An imported asset.
#[derive(Clone, Debug)]
pub struct Imported {
    pub mesh: AnimatedMesh,
    /// The animation sampled (index and name), if any.
    pub animation: Option<(usize, Option<String>)>,
    /// `asset.copyright` and `asset.generator`, for the scene's credits.
    pub credits: Option<String>,
}

/// Imports `path`, sampling animation `animation` (the first when `None`).
pub fn import(path: &Path, animation: Option<usize>) -> DataResult<Imported> {
    let bad = |m: String| DataError::Invalid(format!("{}: {m}", path.display()));
    let (doc, buffers, images) =
        gltf::import(path).map_err(|e| bad(format!("not a readable glTF 2.0 file: {e}")))?;
    let scene = doc.default_scene().or_else(|| doc.scenes().next()).ok_or_else(|| bad("no scene".into()))?;

    let n_nodes = doc.nodes().len();
    let anim = match animation {
        Some(i) => Some(doc.animations().nth(i).ok_or_else(|| bad(format!("no animation {i}")))?),
        None => doc.animations().next(),
    };
    // Per node, per frame: local TRS and morph weights (None: the node's or mesh's defaults).
    let mut trs_frames: Vec<Vec<(V3, [f32; 4], V3)>> = doc
        .nodes()
        .map(|n| {
            let (t, r, s) = n.transform().decomposed();
            vec![(t, r, s); FRAMES]
        })
        .collect();
    let mut weight_frames: Vec<Option<Vec<Vec<f32>>>> = vec![None; n_nodes];
    if let Some(anim) = &anim {
        let mut start = f32::INFINITY;
        let mut end = f32::NEG_INFINITY;
        for ch in anim.channels() {
            let times: Vec<f32> = ch
                .reader(|b| Some(&buffers[b.index()]))
                .read_inputs()
                .ok_or_else(|| bad("an animation channel has no keyframe times".into()))?
                .collect();
            if let (Some(a), Some(b)) = (times.first(), times.last()) {
                start = start.min(*a);
                end = end.max(*b);
            }
        }
        if !start.is_finite() {
            start = 0.0;
            end = 0.0;
        }
        let times: Vec<f32> =
            (0..FRAMES).map(|f| start + (end - start) * f as f32 / (FRAMES - 1) as f32).collect();
        for ch in anim.channels() {
            let reader = ch.reader(|b| Some(&buffers[b.index()]));
            let keys: Vec<f32> = reader.read_inputs().into_iter().flatten().collect();
            if keys.is_empty() {
                continue;
            }
            let (values, width): (Vec<f32>, usize) = match reader.read_outputs() {
                Some(ReadOutputs::Translations(it)) => (it.flatten().collect(), 3),
                Some(ReadOutputs::Scales(it)) => (it.flatten().collect(), 3),
                Some(ReadOutputs::Rotations(it)) => (it.into_f32().flatten().collect(), 4),
                Some(ReadOutputs::MorphTargetWeights(it)) => {
                    let v: Vec<f32> = it.into_f32().collect();
                    let per_key =
                        if ch.sampler().interpolation() == Interpolation::CubicSpline { 3 } else { 1 };
                    let w = v.len() / (keys.len() * per_key).max(1);
                    (v, w)
                }
                None => return Err(bad("an animation channel has no output values".into())),
            };
            let interp = ch.sampler().interpolation();
            let per_key = if interp == Interpolation::CubicSpline { 3 } else { 1 };
            if width == 0 || values.len() != keys.len() * per_key * width {
                return Err(bad(format!(
                    "an animation channel has {} keyframes but {} output values",
                    keys.len(),
                    values.len()
                )));
            }
            let node = ch.target().node().index();
            let property = ch.target().property();
            let rotation = property == Property::Rotation;
            for (f, &t) in times.iter().enumerate() {
                let v = sample(&keys, &values, width, interp, t, rotation);
                let slot = &mut trs_frames[node][f];
                match property {
                    Property::Translation => slot.0 = [v[0], v[1], v[2]],
                    Property::Rotation => slot.1 = [v[0], v[1], v[2], v[3]],
                    Property::Scale => slot.2 = [v[0], v[1], v[2]],
                    Property::MorphTargetWeights => {
                        weight_frames[node].get_or_insert_with(|| vec![Vec::new(); FRAMES])[f] = v;
                    }
                }
            }
        }
    }

    // World matrices per frame, from the scene's roots down.
    let mut world: Vec<Vec<M4>> = vec![Vec::new(); n_nodes];
    let mut stack: Vec<(gltf::Node, Option<usize>)> = scene.nodes().map(|n| (n, None)).collect();
    let mut order = Vec::new();
    while let Some((node, parent)) = stack.pop() {
        let i = node.index();
        if !world[i].is_empty() {
            return Err(bad(format!("node {i} is reached twice (the node graph is not a tree)")));
        }
        world[i] = (0..FRAMES)
            .map(|f| {
                let (t, r, s) = trs_frames[i][f];
                let local = trs(t, normalize_quat(r), s);
                match parent {
                    Some(p) => mul(&world[p][f], &local),
                    None => local,
                }
            })
            .collect();
        order.push(node.clone());
        stack.extend(node.children().map(|c| (c, Some(i))));
    }

    let mut mesh = AnimatedMesh { frames: vec![Vec::new(); FRAMES], ..Default::default() };
    let mut material_texture: std::collections::HashMap<Option<usize>, u32> = Default::default();
    for node in &order {
        let Some(gmesh) = node.mesh() else { continue };
        let skin = node.skin();
        let joint_mats: Option<Vec<Vec<M4>>> = match &skin {
            Some(skin) => {
                let ibms: Vec<M4> =
                    match skin.reader(|b| Some(&buffers[b.index()])).read_inverse_bind_matrices() {
                        Some(it) => it.collect(),
                        None => vec![crate::math::IDENTITY; skin.joints().count()],
                    };
                let mut per_joint = Vec::new();
                for (j, joint) in skin.joints().enumerate() {
                    let w = &world[joint.index()];
                    if w.is_empty() {
                        return Err(bad(format!("skin joint node {} is not in the scene", joint.index())));
                    }
                    let ibm =
                        ibms.get(j).ok_or_else(|| bad("fewer inverse bind matrices than joints".into()))?;
                    per_joint.push((0..FRAMES).map(|f| mul(&w[f], ibm)).collect::<Vec<M4>>());
                }
                Some(per_joint)
            }
            None => None,
        };
        for prim in gmesh.primitives() {
            let mode = prim.mode();
            if !matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan) {
                continue;
            }
            let reader = prim.reader(|b| Some(&buffers[b.index()]));
            let Some(positions) = reader.read_positions() else {
                return Err(bad(format!("mesh {} has a primitive without positions", gmesh.index())));
            };
            let positions: Vec<V3> = positions.collect();
            let n = positions.len();
            let indices: Vec<u32> = match reader.read_indices() {
                Some(it) => it.into_u32().collect(),
                None => (0..n as u32).collect(),
            };
            if let Some(&i) = indices.iter().find(|&&i| i as usize >= n) {
                return Err(bad(format!("mesh {} indexes vertex {i} of {n}", gmesh.index())));
            }
            let tris = triangles(mode, &indices);
            if tris.is_empty() {
                continue;
            }
            let pbr = prim.material().pbr_metallic_roughness();
            let tex_info = pbr.base_color_texture();
            let uvs: Vec<[f32; 2]> = tex_info
                .as_ref()
                .and_then(|info| reader.read_tex_coords(info.tex_coord()))
                .map(|it| it.into_f32().collect())
                .unwrap_or_else(|| vec![[0.0; 2]; n]);
            if uvs.len() != n {
                return Err(bad(format!(
                    "mesh {}: {} texture coordinates for {n} vertices",
                    gmesh.index(),
                    uvs.len()
                )));
            }
            let key = prim.material().index();
            let tex = match material_texture.get(&key) {
                Some(&t) => t,
                None => {
                    let factor = pbr.base_color_factor();
                    let texture = match &tex_info {
                        Some(info) => {
                            let data = images
                                .get(info.texture().source().index())
                                .ok_or_else(|| bad("a texture names a missing image".into()))?;
                            to_texture(data, factor).map_err(bad)?
                        }
                        None => Texture::solid([factor[0], factor[1], factor[2]]),
                    };
                    mesh.textures.push(texture);
                    let t = mesh.textures.len() as u32 - 1;
                    material_texture.insert(key, t);
                    t
                }
            };
            let targets: Vec<Vec<V3>> = reader
                .read_morph_targets()
                .map(|(p, _, _)| p.map(|it| it.collect()).unwrap_or_else(|| vec![[0.0; 3]; n]))
                .collect();
            if targets.iter().any(|t| t.len() != n) {
                return Err(bad(format!(
                    "mesh {}: a morph target has the wrong vertex count",
                    gmesh.index()
                )));
            }
            let default_weights: Vec<f32> = gmesh.weights().map(|w| w.to_vec()).unwrap_or_default();
            let skinning = match (&joint_mats, reader.read_joints(0), reader.read_weights(0)) {
                (Some(mats), Some(j), Some(w)) => {
                    let joints: Vec<[u16; 4]> = j.into_u16().collect();
                    let weights: Vec<[f32; 4]> = w.into_f32().collect();
                    if joints.len() != n || weights.len() != n {
                        return Err(bad(format!(
                            "mesh {}: joints or weights do not match the vertices",
                            gmesh.index()
                        )));
                    }
                    if joints.iter().flatten().any(|&j| j as usize >= mats.len()) {
                        return Err(bad(format!(
                            "mesh {}: a vertex names a joint the skin lacks",
                            gmesh.index()
                        )));
                    }
                    Some((mats, joints, weights))
                }
                _ => None,
            };
            let base = mesh.uvs.len() as u32;
            for f in 0..FRAMES {
                let w = weight_frames[node.index()].as_ref().map(|w| &w[f]).unwrap_or(&default_weights);
                let verts = (0..n).map(|v| {
                    let mut p = positions[v];
                    for (k, target) in targets.iter().enumerate() {
                        let wk = w.get(k).copied().unwrap_or(0.0);
                        if wk != 0.0 {
                            p = add(p, crate::math::scale(target[v], wk));
                        }
                    }
                    match &skinning {
                        Some((mats, joints, weights)) => {
                            let mut m = [[0.0f32; 4]; 4];
                            for i in 0..4 {
                                if weights[v][i] != 0.0 {
                                    add_scaled(&mut m, &mats[joints[v][i] as usize][f], weights[v][i]);
                                }
                            }
                            transform_point(&m, p)
                        }
                        None => transform_point(&world[node.index()][f], p),
                    }
                });
                mesh.frames[f].extend(verts);
            }
            mesh.uvs.extend(uvs);
            mesh.triangles.extend(tris.iter().map(|t| t.map(|i| i + base)));
            mesh.tri_texture.extend(std::iter::repeat_n(tex, tris.len()));
        }
    }
    if mesh.triangles.is_empty() {
        return Err(bad("the default scene has no triangle meshes".into()));
    }
    mesh.normalise();
    mesh.validate().map_err(|e| bad(e.to_string()))?;
    let json = doc.as_json();
    let credits =
        [json.asset.copyright.clone(), json.asset.generator.clone().map(|g| format!("generator: {g}"))]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>();
    Ok(Imported {
        mesh,
        animation: anim.map(|a| (a.index(), a.name().map(str::to_string))),
        credits: (!credits.is_empty()).then(|| credits.join("; ")),
    })
}

fn triangles(mode: Mode, idx: &[u32]) -> Vec<[u32; 3]> {
    match mode {
        Mode::TriangleStrip => {
            (2..idx.len())
                .map(|i| {
                    if i % 2 == 0 {
                        [idx[i - 2], idx[i - 1], idx[i]]
                    } else {
                        [idx[i - 1], idx[i - 2], idx[i]]
                    }
                })
                .collect()
        }
        Mode::TriangleFan => (2..idx.len()).map(|i| [idx[0], idx[i - 1], idx[i]]).collect(),
        _ => idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
    }
}

/// Value of a sampler at time `t`: `values` holds `width` numbers per key (three groups per
/// key, in-tangent, value, out-tangent, for cubic splines). Times outside the keys clamp.
fn sample(
    keys: &[f32],
    values: &[f32],
    width: usize,
    interp: Interpolation,
    t: f32,
    rotation: bool,
) -> Vec<f32> {
    let cubic = interp == Interpolation::CubicSpline;
    let value = |k: usize| -> &[f32] {
        let s = if cubic { (3 * k + 1) * width } else { k * width };
        &values[s..s + width]
    };
    let last = keys.len() - 1;
    if t <= keys[0] || last == 0 {
        return value(0).to_vec();
    }
    if t >= keys[last] {
        return value(last).to_vec();
    }
    let k = keys.partition_point(|&x| x <= t).saturating_sub(1).min(last - 1);
    let dt = keys[k + 1] - keys[k];
    let s = if dt > 0.0 { (t - keys[k]) / dt } else { 0.0 };
    let (a, b) = (value(k), value(k + 1));
    let out: Vec<f32> = match interp {
        Interpolation::Step => a.to_vec(),
        Interpolation::Linear if rotation => {
            slerp([a[0], a[1], a[2], a[3]], [b[0], b[1], b[2], b[3]], s).to_vec()
        }
        Interpolation::Linear => (0..width).map(|i| a[i] + (b[i] - a[i]) * s).collect(),
        Interpolation::CubicSpline => {
            let out_tan = &values[(3 * k + 2) * width..(3 * k + 3) * width];
            let in_tan = &values[(3 * (k + 1)) * width..(3 * (k + 1) + 1) * width];
            let (s2, s3) = (s * s, s * s * s);
            (0..width)
                .map(|i| {
                    (2.0 * s3 - 3.0 * s2 + 1.0) * a[i]
                        + (s3 - 2.0 * s2 + s) * dt * out_tan[i]
                        + (-2.0 * s3 + 3.0 * s2) * b[i]
                        + (s3 - s2) * dt * in_tan[i]
                })
                .collect()
        }
    };
    if rotation {
        normalize_quat([out[0], out[1], out[2], out[3]]).to_vec()
    } else {
        out
    }
}

/// A decoded glTF image as an RGBA8 texture times `factor`, scaled down past [`MAX_TEXTURE`].
fn to_texture(data: &gltf::image::Data, factor: [f32; 4]) -> Result<Texture, String> {
    use gltf::image::Format;
    let (channels, bytes) = match data.format {
        Format::R8 => (1, 1),
        Format::R8G8 => (2, 1),
        Format::R8G8B8 => (3, 1),
        Format::R8G8B8A8 => (4, 1),
        Format::R16 => (1, 2),
        Format::R16G16 => (2, 2),
        Format::R16G16B16 => (3, 2),
        Format::R16G16B16A16 => (4, 2),
        Format::R32G32B32FLOAT => (3, 4),
        Format::R32G32B32A32FLOAT => (4, 4),
    };
    let (w, h) = (data.width, data.height);
    let stride = channels * bytes;
    if w == 0 || h == 0 || data.pixels.len() != (w * h) as usize * stride {
        return Err(format!("a base-colour image has {} bytes for {w} x {h} pixels", data.pixels.len()));
    }
    let channel = |px: &[u8], c: usize| -> f32 {
        let c = c.min(channels - 1);
        let b = &px[c * bytes..(c + 1) * bytes];
        match bytes {
            1 => b[0] as f32 / 255.0,
            2 => u16::from_le_bytes([b[0], b[1]]) as f32 / 65535.0,
            _ => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        }
    };
    let rgb: Vec<u8> = data
        .pixels
        .chunks_exact(stride)
        .flat_map(|px| {
            let grey = channels < 3;
            (0..3).map(move |c| {
                let v = channel(px, if grey { 0 } else { c }) * factor[c];
                (v.clamp(0.0, 1.0) * 255.0).round() as u8
            })
        })
        .collect();
    if w.max(h) > MAX_TEXTURE {
        let img = image::RgbImage::from_raw(w, h, rgb).ok_or("image size mismatch")?;
        let s = MAX_TEXTURE as f32 / w.max(h) as f32;
        let (nw, nh) = (((w as f32 * s) as u32).max(1), ((h as f32 * s) as u32).max(1));
        let small = image::imageops::resize(&img, nw, nh, image::imageops::FilterType::Triangle);
        return Ok(Texture::from_rgb8(nw, nh, small.as_raw()));
    }
    Ok(Texture::from_rgb8(w, h, &rgb))
}
