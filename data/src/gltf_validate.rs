//! Checks a glTF 2.0 document against the rules of the specification the importer relies on,
//! before the `gltf` crate's readers touch it. Those readers index, slice and multiply with
//! what the file says: an index past its array, a count of 0, a stride shorter than an element
//! or float indices make them panic, and an accessor that runs past its buffer reads as absent.
//!
//! [`document`] checks the JSON alone: every index in range (accessors, buffer views, buffers,
//! nodes, meshes, skins, cameras, samplers, images, textures, materials, animation channels and
//! samplers); every accessor with at least one element, inside its buffer view (offset, stride
//! and element size, without overflow), and of the component type and type its use allows
//! (spec 3.7.2.1 for attributes, 3.7.2.2 for indices, 3.11 for animation samplers, 3.8 for
//! skins); buffer views inside their buffers with legal strides; sparse accessors inside their
//! views; one parent per node and no cycles; finite transforms. [`data`] checks what needs the
//! loaded bytes: every buffer as long as it says, sparse indices increasing and inside their
//! accessor. Each error starts with the JSON path of the object at fault.

use gltf::json::accessor::{ComponentType, Type};
use gltf::json::animation::{Interpolation, Property};
use gltf::json::mesh::Semantic;
use gltf::json::validation::Checked;
use gltf::json::{self, Index, Root};

type Check = Result<(), String>;

/// What the importer does with an extension a file requires (`extensionsRequired`). An
/// extension a file only uses (`extensionsUsed`) never stops an import: the file must work
/// without it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Extension {
    /// Read: it changes the points and renders, and the importer applies it.
    Read,
    /// Imported without it, with a warning: it cannot change the geometry, the animation or
    /// the base colour the importer samples (the reason).
    Ignored(&'static str),
    /// Refused by name (the reason).
    Refused(&'static str),
}

/// Every extension the importer has decided on (the README's table); any other required one
/// is refused by name.
pub const EXTENSIONS: &[(&str, Extension)] = &[
    ("KHR_mesh_quantization", Extension::Read),
    ("KHR_texture_transform", Extension::Read),
    ("KHR_materials_pbrSpecularGlossiness", Extension::Read),
    ("KHR_materials_unlit", Extension::Ignored("the base colour is the colour either way")),
    ("KHR_materials_emissive_strength", Extension::Ignored("emission is not sampled")),
    ("KHR_materials_ior", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_specular", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_transmission", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_volume", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_clearcoat", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_sheen", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_iridescence", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_anisotropy", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_dispersion", Extension::Ignored("shading is not sampled, the base colour is")),
    ("KHR_materials_variants", Extension::Ignored("the default material of each primitive is used")),
    ("KHR_lights_punctual", Extension::Ignored("lights play no part in points or supervision renders")),
    ("EXT_lights_image_based", Extension::Ignored("lights play no part in points or supervision renders")),
    ("KHR_xmp_json_ld", Extension::Ignored("metadata")),
    (
        "KHR_texture_basisu",
        Extension::Refused(
            "KTX2/Basis textures need a Basis Universal transcoder, and the crates that offer one wrap \
         its C++ library; re-export the textures as PNG or JPEG",
        ),
    ),
    (
        "EXT_meshopt_compression",
        Extension::Refused(
            "meshoptimizer-compressed buffers need its decoder, and the crates that offer one wrap its \
         C++ library; re-export without compression (gltfpack -noq, or Blender)",
        ),
    ),
    (
        "KHR_draco_mesh_compression",
        Extension::Refused(
            "Draco-compressed meshes need a Draco decoder, and no maintained Rust crate decodes them \
         without Google's C++ library; re-export without compression",
        ),
    ),
    ("EXT_mesh_gpu_instancing", Extension::Refused("instances would change the geometry, and are not read")),
    (
        "KHR_animation_pointer",
        Extension::Refused("animated properties would change the clip, and are not read"),
    ),
];

/// The decision on extension `name` ([`EXTENSIONS`]; `None` for one not decided on).
pub fn extension(name: &str) -> Option<Extension> {
    EXTENSIONS.iter().find(|(n, _)| *n == name).map(|&(_, e)| e)
}

/// Whether the file declares `name` (used or required).
pub fn uses(root: &Root, name: &str) -> bool {
    root.extensions_used.iter().chain(&root.extensions_required).any(|e| e == name)
}

/// Most nodes a document may have: each costs the importer a matrix per frame.
pub const MAX_NODES: usize = 1 << 16;

/// Most elements of an accessor without a buffer view (zeros, or sparse values over zeros):
/// its size comes from the JSON alone, not from bytes in the file.
pub const MAX_ZERO_ELEMENTS: u64 = 1 << 24;

/// Bytes of one component.
pub fn component_size(c: ComponentType) -> usize {
    match c {
        ComponentType::I8 | ComponentType::U8 => 1,
        ComponentType::I16 | ComponentType::U16 => 2,
        ComponentType::U32 | ComponentType::F32 => 4,
    }
}

/// Bytes of one element; matrix columns start on 4-byte boundaries (spec 3.6.2.4).
pub fn element_size(c: ComponentType, t: Type) -> usize {
    let n = match t {
        Type::Scalar => 1,
        Type::Vec2 => 2,
        Type::Vec3 => 3,
        Type::Vec4 | Type::Mat2 => 4,
        Type::Mat3 => 9,
        Type::Mat4 => 16,
    };
    match (t, component_size(c)) {
        (Type::Mat2, 1) => 8,
        (Type::Mat3, 1) => 12,
        (Type::Mat3, 2) => 24,
        (_, size) => n * size,
    }
}

fn type_name(t: Type) -> &'static str {
    match t {
        Type::Scalar => "SCALAR",
        Type::Vec2 => "VEC2",
        Type::Vec3 => "VEC3",
        Type::Vec4 => "VEC4",
        Type::Mat2 => "MAT2",
        Type::Mat3 => "MAT3",
        Type::Mat4 => "MAT4",
    }
}

fn component_name(c: ComponentType) -> &'static str {
    match c {
        ComponentType::I8 => "BYTE",
        ComponentType::U8 => "UNSIGNED_BYTE",
        ComponentType::I16 => "SHORT",
        ComponentType::U16 => "UNSIGNED_SHORT",
        ComponentType::U32 => "UNSIGNED_INT",
        ComponentType::F32 => "FLOAT",
    }
}

/// The item `index` names in `items`, or an error saying where the bad index is.
fn get<'a, T>(items: &'a [T], index: Index<T>, at: &str, array: &str) -> Result<&'a T, String> {
    items.get(index.value()).ok_or_else(|| {
        format!("{at} names {array}[{}], but the file has {} {array}", index.value(), items.len())
    })
}

fn valid<'a, T>(c: &'a Checked<T>, at: &str, what: &str) -> Result<&'a T, String> {
    match c {
        Checked::Valid(v) => Ok(v),
        Checked::Invalid => Err(format!("{at}: {what} is not a value glTF 2.0 allows")),
    }
}

fn finite(values: &[f32], at: &str) -> Check {
    match values.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(format!("{at} holds {v}, not a finite number")),
        None => Ok(()),
    }
}

/// An accessor's component type and type, once [`document`] has checked them.
fn kind(a: &json::Accessor) -> (ComponentType, Type) {
    match (&a.component_type, &a.type_) {
        (Checked::Valid(c), Checked::Valid(t)) => (c.0, *t),
        _ => unreachable!("accessor kinds are checked before their uses"),
    }
}

/// What an accessor is read as, and the kinds that use allows.
struct Use<'a> {
    what: String,
    types: &'a [Type],
    /// Component types allowed as they are, and those allowed when normalised.
    plain: &'a [ComponentType],
    normalized: &'a [ComponentType],
    /// Whether it must hold data (a buffer view or sparse values) rather than zeros.
    needs_data: bool,
}

const FLOAT: &[ComponentType] = &[ComponentType::F32];
const UNSIGNED_8_16: &[ComponentType] = &[ComponentType::U8, ComponentType::U16];
const ANY_8_16: &[ComponentType] =
    &[ComponentType::I8, ComponentType::U8, ComponentType::I16, ComponentType::U16];

impl Use<'_> {
    /// Checks accessor `index` against this use; returns its element count.
    fn check(&self, root: &Root, index: Index<json::Accessor>, at: &str) -> Result<u64, String> {
        let a = get(&root.accessors, index, at, "accessors")?;
        let (c, t) = kind(a);
        let plain = self.plain.contains(&c) && !(a.normalized && c == ComponentType::F32);
        let normalized = a.normalized && self.normalized.contains(&c);
        if !self.types.contains(&t) || !(plain || normalized) {
            let allowed: Vec<&str> = self
                .plain
                .iter()
                .map(|c| component_name(*c))
                .chain(self.normalized.iter().map(|c| match c {
                    ComponentType::I8 => "normalized BYTE",
                    ComponentType::U8 => "normalized UNSIGNED_BYTE",
                    ComponentType::I16 => "normalized SHORT",
                    _ => "normalized UNSIGNED_SHORT",
                }))
                .collect();
            let types: Vec<&str> = self.types.iter().map(|t| type_name(*t)).collect();
            return Err(format!(
                "accessors[{}] ({}) is {} {}{}, expected {} of {}",
                index.value(),
                self.what,
                type_name(t),
                if a.normalized { "normalized " } else { "" },
                component_name(c),
                types.join(" or "),
                allowed.join(" or ")
            ));
        }
        if self.needs_data && a.buffer_view.is_none() && a.sparse.is_none() {
            return Err(format!(
                "accessors[{}] ({}) has neither a bufferView nor sparse values",
                index.value(),
                self.what
            ));
        }
        Ok(a.count.0)
    }
}

/// Checks the document's JSON (see the module docs). Returns the warnings: the harmless
/// deviations the import tolerates and the required extensions it imports without.
pub fn document(root: &Root) -> Result<Vec<String>, String> {
    if !root.asset.version.starts_with("2.") {
        return Err(format!("asset.version is {:?}: only glTF 2.0 is read", root.asset.version));
    }
    let mut warnings = Vec::new();
    for ext in &root.extensions_required {
        match extension(ext) {
            Some(Extension::Read) => {}
            Some(Extension::Ignored(why)) => {
                warnings.push(format!("extensionsRequired names {ext}, imported without it: {why}"))
            }
            Some(Extension::Refused(why)) => {
                return Err(format!("extensionsRequired names {ext}, which this importer refuses: {why}"))
            }
            None => {
                return Err(format!(
                    "extensionsRequired names {ext}, which this importer does not read (the README lists \
                     the extensions it reads, ignores and refuses)"
                ))
            }
        }
    }
    buffers_and_views(root)?;
    accessors(root)?;
    meshes(root)?;
    let parents = nodes(root)?;
    warnings.extend(scenes(root, &parents)?);
    skins(root)?;
    animations(root)?;
    materials_textures_images(root)?;
    Ok(warnings)
}

fn buffers_and_views(root: &Root) -> Check {
    for (i, b) in root.buffers.iter().enumerate() {
        if b.byte_length.0 == 0 {
            return Err(format!("buffers[{i}]: byteLength 0 (a buffer holds at least one byte)"));
        }
    }
    for (i, v) in root.buffer_views.iter().enumerate() {
        let at = format!("bufferViews[{i}]");
        let b = get(&root.buffers, v.buffer, &at, "buffers")?;
        let (offset, len) = (v.byte_offset.map_or(0, |o| o.0), v.byte_length.0);
        if len == 0 {
            return Err(format!("{at}: byteLength 0 (a view holds at least one byte)"));
        }
        let end = offset as u128 + len as u128;
        if end > b.byte_length.0 as u128 {
            return Err(format!(
                "{at}: bytes {offset} to {end} lie past the end of buffers[{}] ({} bytes)",
                v.buffer.value(),
                b.byte_length.0
            ));
        }
        if let Some(s) = v.byte_stride {
            if !(4..=252).contains(&s.0) || s.0 % 4 != 0 {
                return Err(format!("{at}: byteStride {} is not a multiple of 4 from 4 to 252", s.0));
            }
        }
    }
    Ok(())
}

/// `count` elements of `elem` bytes every `stride` from `offset`: the end, without overflow.
fn span_end(offset: u64, count: u64, stride: usize, elem: usize) -> u128 {
    offset as u128 + (count as u128 - 1) * stride as u128 + elem as u128
}

fn accessors(root: &Root) -> Check {
    for (i, a) in root.accessors.iter().enumerate() {
        let at = format!("accessors[{i}]");
        let c = valid(&a.component_type, &at, "componentType")?.0;
        let t = *valid(&a.type_, &at, "type")?;
        let count = a.count.0;
        if count == 0 {
            return Err(format!("{at}: count 0 (an accessor holds at least one element)"));
        }
        if a.normalized && matches!(c, ComponentType::F32 | ComponentType::U32) {
            return Err(format!("{at}: a {} accessor cannot be normalized", component_name(c)));
        }
        let elem = element_size(c, t);
        match a.buffer_view {
            Some(vi) => {
                let view = get(&root.buffer_views, vi, &at, "bufferViews")?;
                let stride = view.byte_stride.map_or(elem, |s| s.0);
                if stride < elem {
                    return Err(format!(
                        "{at}: bufferViews[{}] has byteStride {stride}, less than one {} {} element ({elem} bytes)",
                        vi.value(),
                        type_name(t),
                        component_name(c)
                    ));
                }
                let offset = a.byte_offset.map_or(0, |o| o.0);
                let end = span_end(offset, count, stride, elem);
                if end > view.byte_length.0 as u128 {
                    return Err(format!(
                        "{at}: {count} elements of {elem} bytes every {stride} from byteOffset {offset} end at byte {end}, past the end of bufferViews[{}] ({} bytes)",
                        vi.value(),
                        view.byte_length.0
                    ));
                }
            }
            None if count > MAX_ZERO_ELEMENTS => {
                return Err(format!(
                    "{at}: {count} elements without a bufferView, more than the {MAX_ZERO_ELEMENTS} this importer makes from nothing"
                ))
            }
            None => {}
        }
        if let Some(sp) = &a.sparse {
            let at = format!("{at}.sparse");
            let n = sp.count.0;
            if n == 0 || n > count {
                return Err(format!("{at}: count {n}, expected 1 to the accessor's {count}"));
            }
            let ic = valid(&sp.indices.component_type, &at, "indices.componentType")?.0;
            if !matches!(ic, ComponentType::U8 | ComponentType::U16 | ComponentType::U32) {
                return Err(format!(
                    "{at}: indices of {}, expected an unsigned integer type",
                    component_name(ic)
                ));
            }
            let parts = [
                ("indices", sp.indices.buffer_view, sp.indices.byte_offset.0, component_size(ic)),
                ("values", sp.values.buffer_view, sp.values.byte_offset.0, elem),
            ];
            for (part, vi, offset, size) in parts {
                let view = get(&root.buffer_views, vi, &format!("{at}.{part}"), "bufferViews")?;
                if view.byte_stride.is_some() {
                    return Err(format!(
                        "{at}.{part}: bufferViews[{}] has a byteStride, which sparse data must not",
                        vi.value()
                    ));
                }
                let end = span_end(offset, n, size, size);
                if end > view.byte_length.0 as u128 {
                    return Err(format!(
                        "{at}.{part}: {n} of {size} bytes from byteOffset {offset} end at byte {end}, past the end of bufferViews[{}] ({} bytes)",
                        vi.value(),
                        view.byte_length.0
                    ));
                }
            }
        }
    }
    Ok(())
}

/// The number of morph targets of mesh `m` (that of its first primitive; all must agree).
fn targets_of(root: &Root, m: usize) -> usize {
    root.meshes[m].primitives.first().and_then(|p| p.targets.as_ref()).map_or(0, Vec::len)
}

/// Every component type but UNSIGNED_INT.
const FLOAT_AND_8_16: &[ComponentType] =
    &[ComponentType::F32, ComponentType::I8, ComponentType::U8, ComponentType::I16, ComponentType::U16];
const SIGNED_8_16: &[ComponentType] = &[ComponentType::I8, ComponentType::I16];
const FLOAT_AND_SIGNED_8_16: &[ComponentType] = &[ComponentType::F32, ComponentType::I8, ComponentType::I16];

fn meshes(root: &Root) -> Check {
    // KHR_mesh_quantization lets positions, normals, texture coordinates and morph targets
    // be 8- and 16-bit integers, plain or normalised.
    let quantized = uses(root, "KHR_mesh_quantization");
    let position = Use {
        what: "POSITION".into(),
        types: &[Type::Vec3],
        plain: if quantized { FLOAT_AND_8_16 } else { FLOAT },
        normalized: if quantized { ANY_8_16 } else { &[] },
        needs_data: true,
    };
    for (m, mesh) in root.meshes.iter().enumerate() {
        if mesh.primitives.is_empty() {
            return Err(format!("meshes[{m}] has no primitives"));
        }
        let targets = targets_of(root, m);
        if let Some(w) = &mesh.weights {
            if w.len() != targets {
                return Err(format!(
                    "meshes[{m}].weights has {} values for {targets} morph targets",
                    w.len()
                ));
            }
            finite(w, &format!("meshes[{m}].weights"))?;
        }
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let at = format!("meshes[{m}].primitives[{p}]");
            valid(&prim.mode, &at, "mode")?;
            let mut vertices: Option<(u64, String)> = None;
            for (semantic, &index) in &prim.attributes {
                let name = match semantic {
                    Checked::Valid(s) => s.to_string(),
                    Checked::Invalid => "an attribute".into(),
                };
                let what = format!("{name} of {at}");
                let count = match semantic {
                    Checked::Valid(Semantic::Positions) => {
                        Use { what, ..position }.check(root, index, &at)?
                    }
                    Checked::Valid(Semantic::Normals) => Use {
                        what,
                        types: &[Type::Vec3],
                        plain: FLOAT,
                        normalized: if quantized { SIGNED_8_16 } else { &[] },
                        needs_data: false,
                    }
                    .check(root, index, &at)?,
                    Checked::Valid(Semantic::TexCoords(_)) => Use {
                        what,
                        types: &[Type::Vec2],
                        plain: if quantized { FLOAT_AND_8_16 } else { FLOAT },
                        normalized: if quantized { ANY_8_16 } else { UNSIGNED_8_16 },
                        needs_data: true,
                    }
                    .check(root, index, &at)?,
                    Checked::Valid(Semantic::Colors(set)) => Use {
                        what,
                        types: &[Type::Vec3, Type::Vec4],
                        plain: FLOAT,
                        normalized: UNSIGNED_8_16,
                        // COLOR_0 is read; other sets are not.
                        needs_data: *set == 0,
                    }
                    .check(root, index, &at)?,
                    Checked::Valid(Semantic::Joints(_)) => Use {
                        what,
                        types: &[Type::Vec4],
                        plain: UNSIGNED_8_16,
                        normalized: &[],
                        needs_data: true,
                    }
                    .check(root, index, &at)?,
                    Checked::Valid(Semantic::Weights(_)) => Use {
                        what,
                        types: &[Type::Vec4],
                        plain: FLOAT,
                        normalized: UNSIGNED_8_16,
                        needs_data: true,
                    }
                    .check(root, index, &at)?,
                    // Attributes the importer does not read (tangents, and those it does not
                    // know) are not checked for their kind: a file whose tangents are of a kind
                    // an extension allows imports all the same. Their index must still be in
                    // range and their count the primitive's.
                    _ => get(&root.accessors, index, &what, "accessors")?.count.0,
                };
                match &vertices {
                    Some((n, first)) if *n != count => {
                        return Err(format!("{at}: {name} has {count} elements, {first} has {n}"));
                    }
                    None => vertices = Some((count, name)),
                    _ => {}
                }
            }
            if let Some(index) = prim.indices {
                let indices = Use {
                    what: format!("indices of {at}"),
                    types: &[Type::Scalar],
                    plain: &[ComponentType::U8, ComponentType::U16, ComponentType::U32],
                    normalized: &[],
                    needs_data: true,
                };
                indices.check(root, index, &at)?;
            }
            if let Some(material) = prim.material {
                get(&root.materials, material, &at, "materials")?;
            }
            let prim_targets = prim.targets.as_ref().map_or(0, Vec::len);
            if prim_targets != targets {
                return Err(format!(
                    "{at} has {prim_targets} morph targets, the mesh's first primitive {targets}"
                ));
            }
            for (k, target) in prim.targets.iter().flatten().enumerate() {
                let parts = [
                    ("POSITION", target.positions),
                    ("NORMAL", target.normals),
                    ("TANGENT", target.tangents),
                ];
                for (name, index) in parts {
                    let Some(index) = index else { continue };
                    let what = format!("{name} of morph target {k} of {at}");
                    let target_use = Use {
                        what,
                        types: &[Type::Vec3],
                        plain: if quantized { FLOAT_AND_SIGNED_8_16 } else { FLOAT },
                        normalized: if quantized { SIGNED_8_16 } else { &[] },
                        needs_data: false,
                    };
                    // A target's tangents are not read either: their kind is not checked.
                    let count = if name == "TANGENT" {
                        get(&root.accessors, index, &target_use.what, "accessors")?.count.0
                    } else {
                        target_use.check(root, index, &at)?
                    };
                    if let Some((n, first)) = &vertices {
                        if count != *n {
                            return Err(format!(
                                "{at}: morph target {k}'s {name} has {count} elements, {first} has {n}"
                            ));
                        }
                    }
                }
            }
        }
    }
    Ok(())
}

/// Checks the node graph; returns each node's parent.
fn nodes(root: &Root) -> Result<Vec<Option<usize>>, String> {
    let n = root.nodes.len();
    if n > MAX_NODES {
        return Err(format!("{n} nodes, more than the {MAX_NODES} this importer reads"));
    }
    let mut parent: Vec<Option<usize>> = vec![None; n];
    for (i, node) in root.nodes.iter().enumerate() {
        let at = format!("nodes[{i}]");
        for &child in node.children.iter().flatten() {
            get(&root.nodes, child, &format!("{at}.children"), "nodes")?;
            let c = child.value();
            if let Some(p) = parent[c] {
                return Err(format!(
                    "nodes[{c}] is a child of both nodes[{p}] and nodes[{i}] (the node graph must be a tree)"
                ));
            }
            parent[c] = Some(i);
        }
        if let Some(mesh) = node.mesh {
            get(&root.meshes, mesh, &at, "meshes")?;
        }
        if let Some(camera) = node.camera {
            get(&root.cameras, camera, &at, "cameras")?;
        }
        if let Some(skin) = node.skin {
            get(&root.skins, skin, &at, "skins")?;
            if node.mesh.is_none() {
                return Err(format!("{at} has a skin but no mesh"));
            }
        }
        if let Some(w) = &node.weights {
            let targets = node.mesh.map_or(0, |m| targets_of(root, m.value()));
            if w.len() != targets {
                return Err(format!("{at}.weights has {} values for {targets} morph targets", w.len()));
            }
            finite(w, &format!("{at}.weights"))?;
        }
        let trs = [
            node.translation.as_ref().map(|t| &t[..]),
            node.rotation.as_ref().map(|r| &r.0[..]),
            node.scale.as_ref().map(|s| &s[..]),
        ];
        for (name, values) in ["translation", "rotation", "scale"].iter().zip(trs) {
            finite(values.unwrap_or(&[]), &format!("{at}.{name}"))?;
        }
        finite(node.matrix.as_ref().map_or(&[][..], |m| &m[..]), &format!("{at}.matrix"))?;
    }
    // Every node reached from a root, or it lies on a cycle (one parent each: a node with no
    // path up to a root is below or on a loop).
    let mut reached = vec![false; n];
    let mut stack: Vec<usize> = (0..n).filter(|&i| parent[i].is_none()).collect();
    while let Some(i) = stack.pop() {
        reached[i] = true;
        stack.extend(root.nodes[i].children.iter().flatten().map(|c| c.value()));
    }
    if let Some(i) = reached.iter().position(|r| !r) {
        return Err(format!("nodes[{i}] lies on a cycle of children (the node graph must be a tree)"));
    }
    Ok(parent)
}

/// Checks the scenes' node lists; a child listed as a root is a warning (the import draws each
/// node once, under its parent: see `gltf_import`).
fn scenes(root: &Root, parent: &[Option<usize>]) -> Result<Vec<String>, String> {
    if let Some(scene) = root.scene {
        get(&root.scenes, scene, "scene", "scenes")?;
    }
    let mut warnings = Vec::new();
    for (s, scene) in root.scenes.iter().enumerate() {
        for &node in &scene.nodes {
            get(&root.nodes, node, &format!("scenes[{s}].nodes"), "nodes")?;
            if let Some(p) = parent[node.value()] {
                warnings.push(format!(
                    "scenes[{s}] lists nodes[{}], a child of nodes[{p}], as a root: drawn once, under its parent",
                    node.value()
                ));
            }
        }
    }
    Ok(warnings)
}

fn skins(root: &Root) -> Check {
    for (s, skin) in root.skins.iter().enumerate() {
        let at = format!("skins[{s}]");
        if skin.joints.is_empty() {
            return Err(format!("{at} has no joints"));
        }
        for &j in &skin.joints {
            get(&root.nodes, j, &format!("{at}.joints"), "nodes")?;
        }
        if let Some(skeleton) = skin.skeleton {
            get(&root.nodes, skeleton, &format!("{at}.skeleton"), "nodes")?;
        }
        if let Some(ibm) = skin.inverse_bind_matrices {
            let what = format!("inverseBindMatrices of {at}");
            let count = Use { what, types: &[Type::Mat4], plain: FLOAT, normalized: &[], needs_data: true }
                .check(root, ibm, &at)?;
            if count < skin.joints.len() as u64 {
                return Err(format!("{at}: {count} inverse bind matrices for {} joints", skin.joints.len()));
            }
        }
    }
    Ok(())
}

fn animations(root: &Root) -> Check {
    for (a, anim) in root.animations.iter().enumerate() {
        for (s, sampler) in anim.samplers.iter().enumerate() {
            let at = format!("animations[{a}].samplers[{s}]");
            valid(&sampler.interpolation, &at, "interpolation")?;
            let input = Use {
                what: format!("input of {at}"),
                types: &[Type::Scalar],
                plain: FLOAT,
                normalized: &[],
                needs_data: true,
            };
            input.check(root, sampler.input, &at)?;
            get(&root.accessors, sampler.output, &at, "accessors")?;
        }
        let mut targets = std::collections::HashSet::new();
        for (c, channel) in anim.channels.iter().enumerate() {
            let at = format!("animations[{a}].channels[{c}]");
            let sampler = anim.samplers.get(channel.sampler.value()).ok_or_else(|| {
                format!(
                    "{at} names samplers[{}], but animations[{a}] has {} samplers",
                    channel.sampler.value(),
                    anim.samplers.len()
                )
            })?;
            let node = get(&root.nodes, channel.target.node, &format!("{at}.target"), "nodes")?;
            let path = *valid(&channel.target.path, &at, "target.path")?;
            if !targets.insert((channel.target.node.value(), path as u8)) {
                return Err(format!(
                    "{at} animates the same node and path as an earlier channel of animations[{a}]"
                ));
            }
            let (types, plain, normalized, per_key): (&[Type], _, _, usize) = match path {
                Property::Translation | Property::Scale => (&[Type::Vec3], FLOAT, &[][..], 1),
                Property::Rotation => (&[Type::Vec4], FLOAT, ANY_8_16, 1),
                Property::MorphTargetWeights => {
                    let targets = node.mesh.map_or(0, |m| targets_of(root, m.value()));
                    if targets == 0 {
                        return Err(format!(
                            "{at} animates the morph weights of nodes[{}], whose mesh has no morph targets",
                            channel.target.node.value()
                        ));
                    }
                    (&[Type::Scalar], FLOAT, ANY_8_16, targets)
                }
            };
            let sampler_at = format!("animations[{a}].samplers[{}]", channel.sampler.value());
            let output =
                Use { what: format!("output of {sampler_at}"), types, plain, normalized, needs_data: true };
            let values = output.check(root, sampler.output, &at)?;
            let keys = root.accessors[sampler.input.value()].count.0;
            let cubic = matches!(sampler.interpolation, Checked::Valid(Interpolation::CubicSpline));
            let expected = keys as u128 * if cubic { 3 } else { 1 } * per_key as u128;
            if values as u128 != expected {
                return Err(format!(
                    "{sampler_at}: {keys} keyframes need {expected} output values for {at}, the output has {values}"
                ));
            }
        }
    }
    Ok(())
}

fn materials_textures_images(root: &Root) -> Check {
    for (m, material) in root.materials.iter().enumerate() {
        let at = format!("materials[{m}]");
        let pbr = &material.pbr_metallic_roughness;
        finite(&pbr.base_color_factor.0, &format!("{at}.pbrMetallicRoughness.baseColorFactor"))?;
        let textures = [
            pbr.base_color_texture.as_ref().map(|t| t.index),
            pbr.metallic_roughness_texture.as_ref().map(|t| t.index),
            material.normal_texture.as_ref().map(|t| t.index),
            material.occlusion_texture.as_ref().map(|t| t.index),
            material.emissive_texture.as_ref().map(|t| t.index),
        ];
        for t in textures.into_iter().flatten() {
            get(&root.textures, t, &at, "textures")?;
        }
        // KHR_materials_pbrSpecularGlossiness: its diffuse colour is the base colour.
        if let Some(sg) = material.extensions.as_ref().and_then(|e| e.pbr_specular_glossiness.as_ref()) {
            let at = format!("{at}.extensions.KHR_materials_pbrSpecularGlossiness");
            finite(&sg.diffuse_factor.0, &format!("{at}.diffuseFactor"))?;
            if let Some(t) = &sg.diffuse_texture {
                get(&root.textures, t.index, &at, "textures")?;
            }
        }
        // KHR_texture_transform of the base colour: finite offset, rotation and scale.
        let base = pbr.base_color_texture.as_ref();
        if let Some(tt) = base.and_then(|t| t.extensions.as_ref()).and_then(|e| e.texture_transform.as_ref())
        {
            let at = format!("{at}.pbrMetallicRoughness.baseColorTexture.extensions.KHR_texture_transform");
            finite(&[tt.offset.0[0], tt.offset.0[1], tt.rotation.0, tt.scale.0[0], tt.scale.0[1]], &at)?;
        }
    }
    for (t, texture) in root.textures.iter().enumerate() {
        let at = format!("textures[{t}]");
        get(&root.images, texture.source, &at, "images")?;
        if let Some(sampler) = texture.sampler {
            get(&root.samplers, sampler, &at, "samplers")?;
        }
    }
    for (i, image) in root.images.iter().enumerate() {
        let at = format!("images[{i}]");
        match (&image.uri, image.buffer_view) {
            (Some(_), None) => {}
            (None, Some(view)) => {
                get(&root.buffer_views, view, &at, "bufferViews")?;
                if image.mime_type.is_none() {
                    return Err(format!("{at} is read from a bufferView but has no mimeType"));
                }
            }
            _ => return Err(format!("{at} needs exactly one of uri and bufferView")),
        }
        if let Some(mime) = &image.mime_type {
            if !matches!(mime.0.as_str(), "image/png" | "image/jpeg") {
                return Err(format!("{at}: mimeType {:?}, expected image/png or image/jpeg", mime.0));
            }
        }
    }
    Ok(())
}

/// Checks what needs the loaded bytes: every buffer holds at least its byteLength, and the
/// indices of every sparse accessor increase and lie inside the accessor. Call after
/// [`document`].
pub fn data(root: &Root, buffers: &[Vec<u8>]) -> Check {
    for (i, (b, bytes)) in root.buffers.iter().zip(buffers).enumerate() {
        if (bytes.len() as u64) < b.byte_length.0 {
            return Err(format!(
                "buffers[{i}]: byteLength {} but {} bytes were loaded",
                b.byte_length.0,
                bytes.len()
            ));
        }
    }
    for (i, a) in root.accessors.iter().enumerate() {
        let Some(sp) = &a.sparse else { continue };
        let view = &root.buffer_views[sp.indices.buffer_view.value()];
        let ic = match &sp.indices.component_type {
            Checked::Valid(c) => c.0,
            Checked::Invalid => unreachable!("checked by document"),
        };
        let size = component_size(ic);
        let start = (view.byte_offset.map_or(0, |o| o.0) + sp.indices.byte_offset.0) as usize;
        let bytes = &buffers[view.buffer.value()][start..start + size * sp.count.0 as usize];
        let mut last: Option<u64> = None;
        for (k, b) in bytes.chunks_exact(size).enumerate() {
            let index = match size {
                1 => b[0] as u64,
                2 => u16::from_le_bytes([b[0], b[1]]) as u64,
                _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64,
            };
            if index >= a.count.0 || last.is_some_and(|l| index <= l) {
                return Err(format!(
                    "accessors[{i}].sparse: index {k} is {index}; sparse indices must increase and lie below the count {}",
                    a.count.0
                ));
            }
            last = Some(index);
        }
    }
    Ok(())
}
