//! glTF 2.0 import (.gltf with embedded or side-by-side buffers, and .glb): triangle meshes
//! under the node hierarchy of the default scene, skins (linear blend skinning with the
//! inverse bind matrices), morph targets (positions), node and morph-weight animation with
//! step, linear (slerp for rotations) and cubic-spline interpolation, and base-colour textures
//! times the base-colour factor (the factor alone where there is no texture) times the
//! vertex colours (`COLOR_0`, its RGB; alpha is not read), as the specification composes them.
//!
//! One animation is sampled at 24 evenly spaced times from its first to its last keyframe (a
//! file without animation gives a still clip); the clip is then normalised into [-1, 1]^3 like
//! the procedural objects. Per the specification, a skinned mesh ignores its own node's
//! transform. Points and lines are skipped; triangle strips and fans become triangles.
//!
//! A file is input from anywhere: [`gltf_load`] reads its bytes (URIs only
//! inside the file's folder), [`gltf_validate`] checks the document
//! against the specification before the `gltf` crate's readers see it, and a panic inside
//! them all the same becomes an error. Every error names the file.

use std::path::Path;

use gltf::animation::{util::ReadOutputs, Interpolation, Property};
use gltf::mesh::Mode;

use crate::math::{add, add_scaled, mul, normalize_quat, slerp, transform_point, trs, M4, V3};
use crate::mesh::{AnimatedMesh, Texture};
use crate::procedural::FRAMES;
use crate::{gltf_load, gltf_validate, DataError, DataResult};

/// Largest texture side kept; larger base-colour images are scaled down to it.
pub const MAX_TEXTURE: u32 = 1024;
/// Most vertices an import makes (24 frames of them: 600 MB); a scene that instances more
/// (a mesh under many nodes, say) is refused.
pub const MAX_VERTICES: usize = 1 << 21;

/// An imported asset.
#[derive(Clone, Debug)]
pub struct Imported {
    pub mesh: AnimatedMesh,
    /// The animation sampled (index and name), if any.
    pub animation: Option<(usize, Option<String>)>,
    /// `asset.copyright` and `asset.generator`, for the scene's credits.
    pub credits: Option<String>,
    /// What the file does that the specification does not allow but cannot make the import
    /// wrong, and the required extensions imported without (see `gltf_validate::EXTENSIONS`).
    pub warnings: Vec<String>,
}

/// Imports `path`, sampling animation `animation` (the first when `None`).
pub fn import(path: &Path, animation: Option<usize>) -> DataResult<Imported> {
    guard(path, || import_checked(path, animation))
}

/// Runs `f`, turning a panic into an error that names `path`: the last line of defence should
/// the `gltf` crate panic on a file the validator let through.
fn guard<T>(path: &Path, f: impl FnOnce() -> DataResult<T>) -> DataResult<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|payload| {
        let why = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "no message".into());
        Err(DataError::Invalid(format!(
            "{}: the glTF reader panicked on this file ({why}); it breaks a rule the importer does not check",
            path.display()
        )))
    })
}

fn import_checked(path: &Path, animation: Option<usize>) -> DataResult<Imported> {
    let bad = |m: String| DataError::Invalid(format!("{}: {m}", path.display()));
    let bytes =
        std::fs::read(path).map_err(|e| velox_engine::Error::file(path, velox_engine::FileOp::Read, e))?;
    let (root, bin) = gltf_load::parse(&bytes).map_err(bad)?;
    let warnings = gltf_validate::document(&root).map_err(bad)?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let buffers = gltf_load::buffers(&root, bin, dir).map_err(bad)?;
    gltf_validate::data(&root, &buffers).map_err(bad)?;
    let credits = credits(&root);
    let doc = gltf::Document::from_json_without_validation(root);
    let buffer = |b: gltf::Buffer| Some(buffers[b.index()].as_slice());
    let mut warnings = warnings;
    let scene = doc.default_scene().or_else(|| doc.scenes().next());

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
                .reader(buffer)
                .read_inputs()
                .ok_or_else(|| bad("an animation channel has no keyframe times".into()))?
                .collect();
            if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] < w[0]) {
                return Err(bad(format!(
                    "animations[{}].samplers[{}]: keyframe times must be finite and increasing",
                    anim.index(),
                    ch.sampler().index()
                )));
            }
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
            let reader = ch.reader(buffer);
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

    // World matrices per frame of every node, from the roots of the node forest down (a node
    // has one parent and the graph no cycle: checked).
    let mut parent_of: Vec<Option<usize>> = vec![None; n_nodes];
    for node in doc.nodes() {
        for c in node.children() {
            parent_of[c.index()] = Some(node.index());
        }
    }
    let mut world: Vec<Vec<M4>> = vec![Vec::new(); n_nodes];
    let mut stack: Vec<(gltf::Node, Option<usize>)> =
        doc.nodes().filter(|n| parent_of[n.index()].is_none()).map(|n| (n, None)).collect();
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
        stack.extend(node.children().map(|c| (c, Some(i))));
    }
    // The nodes drawn: the subtrees of the scene's roots, each node once. A child the scene
    // also lists as a root (which the specification does not allow, and some exporters write)
    // is drawn under its parent when an ancestor is listed too, and at its place in the
    // hierarchy otherwise.
    // A file without scenes (the specification lets a client choose what to show) gives every
    // root node, as tolerant loaders do.
    let roots: Vec<gltf::Node> = match &scene {
        Some(scene) => scene.nodes().collect(),
        None => {
            if n_nodes == 0 {
                return Err(bad("no scene and no node: nothing to draw".into()));
            }
            warnings.push("the file has no scene: every root node is drawn".into());
            doc.nodes().filter(|n| parent_of[n.index()].is_none()).collect()
        }
    };
    let listed: Vec<usize> = roots.iter().map(|n| n.index()).collect();
    let listed_above = |mut i: usize| {
        while let Some(p) = parent_of[i] {
            if listed.contains(&p) {
                return true;
            }
            i = p;
        }
        false
    };
    let mut order = Vec::new();
    let mut stack: Vec<gltf::Node> = roots.into_iter().filter(|n| !listed_above(n.index())).collect();
    let mut drawn = vec![false; n_nodes];
    while let Some(node) = stack.pop() {
        if std::mem::replace(&mut drawn[node.index()], true) {
            continue; // listed twice
        }
        stack.extend(node.children());
        order.push(node);
    }

    // Per skin, per joint, per frame: the joint's world matrix times its inverse bind matrix
    // (once per skin, however many nodes share it).
    let mut skin_mats: Vec<Option<Vec<Vec<M4>>>> = vec![None; doc.skins().len()];
    for skin in order.iter().filter_map(|n| n.skin()) {
        if skin_mats[skin.index()].is_some() {
            continue;
        }
        let ibms: Vec<M4> = match skin.reader(buffer).read_inverse_bind_matrices() {
            Some(it) => it.collect(),
            None => vec![crate::math::IDENTITY; skin.joints().count()],
        };
        let mut per_joint = Vec::new();
        for (j, joint) in skin.joints().enumerate() {
            let w = &world[joint.index()];
            if w.is_empty() {
                return Err(bad(format!("skin joint node {} is not in the scene", joint.index())));
            }
            let ibm = ibms.get(j).ok_or_else(|| bad("fewer inverse bind matrices than joints".into()))?;
            per_joint.push((0..FRAMES).map(|f| mul(&w[f], ibm)).collect::<Vec<M4>>());
        }
        skin_mats[skin.index()] = Some(per_joint);
    }

    let mut mesh = AnimatedMesh { frames: vec![Vec::new(); FRAMES], ..Default::default() };
    let mut material_texture: std::collections::HashMap<Option<usize>, u32> = Default::default();
    for node in &order {
        let Some(gmesh) = node.mesh() else { continue };
        let joint_mats = node.skin().and_then(|s| skin_mats[s.index()].as_ref());
        for prim in gmesh.primitives() {
            let mode = prim.mode();
            if !matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan) {
                continue;
            }
            let reader = prim.reader(buffer);
            let Some(positions) = prim.get(&gltf::Semantic::Positions).and_then(|a| floats::<3>(a, buffer))
            else {
                return Err(bad(format!("mesh {} has a primitive without positions", gmesh.index())));
            };
            let n = positions.len();
            if mesh.uvs.len() + n > MAX_VERTICES {
                return Err(bad(format!(
                    "the default scene makes more than {MAX_VERTICES} vertices (mesh {} and those before it)",
                    gmesh.index()
                )));
            }
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
            // The base colour: the metallic-roughness model's, or the diffuse colour of a
            // specular-glossiness material (KHR_materials_pbrSpecularGlossiness).
            let material = prim.material();
            let (factor, tex_info) = match material.pbr_specular_glossiness() {
                Some(sg) => (sg.diffuse_factor(), sg.diffuse_texture()),
                None => {
                    let pbr = material.pbr_metallic_roughness();
                    (pbr.base_color_factor(), pbr.base_color_texture())
                }
            };
            let transform = tex_info.as_ref().and_then(|info| info.texture_transform());
            let set =
                transform.as_ref().and_then(|t| t.tex_coord()).or(tex_info.as_ref().map(|i| i.tex_coord()));
            let uvs: Vec<[f32; 2]> = set
                .and_then(|set| prim.get(&gltf::Semantic::TexCoords(set)))
                .and_then(|a| floats::<2>(a, buffer))
                .map(|uvs| match &transform {
                    Some(t) => uvs.iter().map(|&uv| texture_transform(t, uv)).collect(),
                    None => uvs,
                })
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
                    let texture = match &tex_info {
                        Some(info) => {
                            let index = info.texture().source().index();
                            let image = gltf_load::image(doc.as_json(), index, &buffers, dir).map_err(bad)?;
                            to_texture(image, factor)
                        }
                        None => Texture::solid([factor[0], factor[1], factor[2]]),
                    };
                    mesh.textures.push(texture);
                    let t = mesh.textures.len() as u32 - 1;
                    material_texture.insert(key, t);
                    t
                }
            };
            let targets: Vec<Vec<V3>> = prim
                .morph_targets()
                .map(|t| {
                    t.positions().and_then(|a| floats::<3>(a, buffer)).unwrap_or_else(|| vec![[0.0; 3]; n])
                })
                .collect();
            if targets.iter().any(|t| t.len() != n) {
                return Err(bad(format!(
                    "mesh {}: a morph target has the wrong vertex count",
                    gmesh.index()
                )));
            }
            let colours: Vec<[f32; 3]> = match reader.read_colors(0) {
                Some(c) => c.into_rgb_f32().collect(),
                None => vec![[1.0; 3]; n],
            };
            if let Some(c) = colours.iter().flatten().find(|c| !(0.0..=1.0).contains(*c)) {
                return Err(bad(format!(
                    "mesh {}: COLOR_0 holds {c}, outside [0, 1] where the specification keeps colours",
                    gmesh.index()
                )));
            }
            let default_weights: Vec<f32> = gmesh.weights().map(|w| w.to_vec()).unwrap_or_default();
            let skinning = match (joint_mats, reader.read_joints(0), reader.read_weights(0)) {
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
            mesh.colours.extend(colours);
            mesh.triangles.extend(tris.iter().map(|t| t.map(|i| i + base)));
            mesh.tri_texture.extend(std::iter::repeat_n(tex, tris.len()));
        }
    }
    if mesh.triangles.is_empty() {
        return Err(bad("the default scene has no triangle meshes".into()));
    }
    // A file without vertex colours keeps none (white): the mesh is then the one it was.
    if mesh.colours.iter().all(|c| *c == [1.0; 3]) {
        mesh.colours.clear();
    }
    // An animation whose keys hold one pose (a T-pose clip) imports as a still scene: legal,
    // but not what a user importing an animation means, so it is said.
    if let Some(a) = &anim {
        if mesh.frames.iter().all(|f| f == &mesh.frames[0]) {
            let name = a.name().map(|n| format!(" ({n})")).unwrap_or_default();
            warnings.push(format!(
                "animations[{}]{name} moves nothing: every sampled frame is the first, so the scene is still",
                a.index()
            ));
        }
    }
    // Before normalising, so that a NaN is named as such rather than spread over every vertex.
    mesh.validate().map_err(|e| bad(e.to_string()))?;
    mesh.normalise();
    mesh.validate().map_err(|e| bad(e.to_string()))?;
    Ok(Imported {
        mesh,
        animation: anim.map(|a| (a.index(), a.name().map(str::to_string))),
        credits,
        warnings,
    })
}

/// The elements of a vector accessor as floats: float components as they are, 8- and 16-bit
/// integers (texture coordinates in core glTF, and positions, texture coordinates and morph
/// targets under KHR_mesh_quantization) as their values, or mapped to [0, 1] (unsigned) and
/// [-1, 1] (signed) where the accessor is normalised (glTF 2.0, 3.11). `None` for an accessor
/// with no data (nor sparse values).
fn floats<'a, const N: usize>(
    accessor: gltf::Accessor<'a>,
    buffer: impl Clone + Fn(gltf::Buffer<'a>) -> Option<&'a [u8]>,
) -> Option<Vec<[f32; N]>>
where
    [f32; N]: gltf::accessor::Item,
    [i8; N]: gltf::accessor::Item,
    [u8; N]: gltf::accessor::Item,
    [i16; N]: gltf::accessor::Item,
    [u16; N]: gltf::accessor::Item,
{
    use gltf::accessor::{DataType, Iter};
    let norm = accessor.normalized();
    fn map<T: Copy, const N: usize>(it: impl Iterator<Item = [T; N]>, f: impl Fn(T) -> f32) -> Vec<[f32; N]> {
        it.map(|v| v.map(&f)).collect()
    }
    Some(match accessor.data_type() {
        DataType::F32 => Iter::<[f32; N]>::new(accessor, buffer)?.collect(),
        DataType::I8 => map(Iter::<[i8; N]>::new(accessor, buffer)?, |c| {
            if norm {
                (c as f32 / 127.0).max(-1.0)
            } else {
                c as f32
            }
        }),
        DataType::U8 => {
            map(Iter::<[u8; N]>::new(accessor, buffer)?, |c| if norm { c as f32 / 255.0 } else { c as f32 })
        }
        DataType::I16 => map(Iter::<[i16; N]>::new(accessor, buffer)?, |c| {
            if norm {
                (c as f32 / 32767.0).max(-1.0)
            } else {
                c as f32
            }
        }),
        DataType::U16 => {
            map(
                Iter::<[u16; N]>::new(accessor, buffer)?,
                |c| {
                    if norm {
                        c as f32 / 65535.0
                    } else {
                        c as f32
                    }
                },
            )
        }
        // Not an attribute type the validator lets through.
        DataType::U32 => return None,
    })
}

/// A texture coordinate under KHR_texture_transform: scaled, then rotated, then offset
/// (`T * R * S * uv`), with `R = [[cos, sin], [-sin, cos]]` (rows): the rotation of the
/// extension's example, where offset (0, 1), rotation pi/2 and scale 1/2 keep every coordinate
/// in the image's lower-left quadrant (the matrix its GLSL sketch spells, transposed, would not;
/// Khronos' sample viewer rotates this way).
fn texture_transform(t: &gltf::texture::TextureTransform, uv: [f32; 2]) -> [f32; 2] {
    let [sx, sy] = t.scale();
    let (s, c) = t.rotation().sin_cos();
    let [ox, oy] = t.offset();
    let (x, y) = (uv[0] * sx, uv[1] * sy);
    [c * x + s * y + ox, -s * x + c * y + oy]
}

/// `asset.copyright` and `asset.generator`, for the scene's credits.
fn credits(root: &gltf::json::Root) -> Option<String> {
    let credits: Vec<String> =
        [root.asset.copyright.clone(), root.asset.generator.clone().map(|g| format!("generator: {g}"))]
            .into_iter()
            .flatten()
            .collect();
    (!credits.is_empty()).then(|| credits.join("; "))
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
/// Grey images give grey texels; alpha is dropped.
fn to_texture(image: image::DynamicImage, factor: [f32; 4]) -> Texture {
    let (w, h) = (image.width(), image.height());
    let image = if w.max(h) > MAX_TEXTURE {
        let s = MAX_TEXTURE as f32 / w.max(h) as f32;
        let (nw, nh) = (((w as f32 * s) as u32).max(1), ((h as f32 * s) as u32).max(1));
        image.resize_exact(nw, nh, image::imageops::FilterType::Triangle)
    } else {
        image
    };
    let rgb = image.to_rgb32f();
    let bytes: Vec<u8> = rgb
        .pixels()
        .flat_map(|p| (0..3).map(move |c| ((p[c] * factor[c]).clamp(0.0, 1.0) * 255.0).round() as u8))
        .collect();
    Texture::from_rgb8(rgb.width(), rgb.height(), &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The last line of defence: a panic below the importer becomes an error naming the file.
    #[test]
    fn a_panic_while_importing_is_an_error_naming_the_file() {
        let e = guard(Path::new("dir/model.glb"), || -> DataResult<()> { panic!("index out of bounds") })
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("dir/model.glb") && e.contains("panicked") && e.contains("index out of bounds"),
            "{e}"
        );
        let e = guard(Path::new("m.gltf"), || -> DataResult<()> { std::panic::panic_any(7u8) }).unwrap_err();
        assert!(e.to_string().contains("m.gltf: the glTF reader panicked on this file (no message)"), "{e}");
        assert_eq!(guard(Path::new("m.gltf"), || Ok(3)).unwrap(), 3);
    }
}
