//! An animated triangle mesh: fixed connectivity, UVs and textures, one vertex array a frame.
//!
//! Procedural objects and glTF imports both end up here. Parts that are absent in a frame are
//! collapsed to a point there (zero-area triangles draw nothing), so connectivity never changes
//! and a surface point keeps its triangle and barycentrics through the whole clip.

use crate::math::V3;
use crate::{DataError, DataResult};

/// An RGBA8 image, red in the low byte of each texel.
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<u32>,
}

impl Texture {
    /// A 1x1 texture of one colour (rgb in [0, 1]).
    pub fn solid(rgb: [f32; 3]) -> Texture {
        Texture { width: 1, height: 1, texels: vec![pack_rgb(rgb)] }
    }

    /// From 8-bit RGB rows.
    pub fn from_rgb8(width: u32, height: u32, rgb: &[u8]) -> Texture {
        let texels =
            rgb.chunks_exact(3).map(|c| c[0] as u32 | (c[1] as u32) << 8 | (c[2] as u32) << 16).collect();
        Texture { width, height, texels }
    }
}

/// Packs rgb in [0, 1] into an RGBA8 texel (alpha 255).
pub fn pack_rgb(rgb: [f32; 3]) -> u32 {
    let b = rgb.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u32);
    b[0] | b[1] << 8 | b[2] << 16 | 255 << 24
}

/// A triangle mesh animated over a fixed number of frames.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AnimatedMesh {
    /// Vertex positions, one array per frame, all of the same length.
    pub frames: Vec<Vec<V3>>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
    /// Texture coordinates per vertex, fixed on frame 0 and carried through the animation.
    pub uvs: Vec<[f32; 2]>,
    /// Texture of each triangle (index into `textures`).
    pub tri_texture: Vec<u32>,
    pub textures: Vec<Texture>,
    /// A colour per vertex that multiplies its triangle's texture (glTF's `COLOR_0`, RGB in
    /// [0, 1], read like the base-colour factor), interpolated across each triangle; empty for
    /// a mesh without, which is white.
    pub colours: Vec<[f32; 3]>,
}

impl AnimatedMesh {
    pub fn num_vertices(&self) -> usize {
        self.uvs.len()
    }

    /// Appends `other` (same number of frames) with its own textures.
    pub fn append(&mut self, other: AnimatedMesh) {
        if self.frames.is_empty() {
            *self = other;
            return;
        }
        let base = self.num_vertices() as u32;
        let tex_base = self.textures.len() as u32;
        if !(self.colours.is_empty() && other.colours.is_empty()) {
            // Either side without colours is white.
            self.colours.resize(base as usize, [1.0; 3]);
            if other.colours.is_empty() {
                self.colours.resize(base as usize + other.num_vertices(), [1.0; 3]);
            } else {
                self.colours.extend_from_slice(&other.colours);
            }
        }
        for (mine, theirs) in self.frames.iter_mut().zip(other.frames) {
            mine.extend(theirs);
        }
        self.triangles.extend(other.triangles.iter().map(|t| t.map(|i| i + base)));
        self.uvs.extend(other.uvs);
        self.tri_texture.extend(other.tri_texture.iter().map(|t| t + tex_base));
        self.textures.extend(other.textures);
    }

    /// Checks the invariants every consumer relies on; names the first problem.
    pub fn validate(&self) -> DataResult<()> {
        let n = self.num_vertices();
        let bad = |m: String| Err(DataError::Invalid(m));
        if self.frames.is_empty() {
            return bad("mesh has no frames".into());
        }
        if self.triangles.is_empty() {
            return bad("mesh has no triangles".into());
        }
        if let Some(f) = self.frames.iter().position(|f| f.len() != n) {
            return bad(format!("frame {f} has {} vertices, the mesh {n}", self.frames[f].len()));
        }
        if self.frames.iter().flatten().flatten().any(|v| !v.is_finite()) {
            return bad("mesh has non-finite vertex positions".into());
        }
        if self.uvs.iter().flatten().any(|v| !v.is_finite()) {
            return bad("mesh has non-finite texture coordinates".into());
        }
        if !self.colours.is_empty() && self.colours.len() != n {
            return bad(format!("{} vertex colours for {n} vertices", self.colours.len()));
        }
        if let Some(c) = self.colours.iter().flatten().find(|c| !(0.0..=1.0).contains(*c)) {
            return bad(format!("a vertex colour of {c}: colours are in [0, 1]"));
        }
        if self.triangles.iter().flatten().any(|&i| i as usize >= n) {
            return bad(format!("a triangle index is out of range ({n} vertices)"));
        }
        if self.tri_texture.len() != self.triangles.len() {
            return bad("one texture index per triangle is needed".into());
        }
        if self.tri_texture.iter().any(|&t| t as usize >= self.textures.len()) {
            return bad("a triangle names a missing texture".into());
        }
        if self
            .textures
            .iter()
            .any(|t| t.width == 0 || t.height == 0 || t.texels.len() != (t.width * t.height) as usize)
        {
            return bad("a texture has a wrong size".into());
        }
        Ok(())
    }

    /// Moves and scales every frame by one transform so that the whole clip fits [-1, 1]^3,
    /// centred, touching the cube on its longest side. Returns (centre, scale) of the map
    /// `x -> (x - centre) * scale`.
    pub fn normalise(&mut self) -> (V3, f32) {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for v in self.frames.iter().flatten() {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        let centre: V3 = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
        let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max);
        let s = if extent > 0.0 { 2.0 / extent } else { 1.0 };
        for v in self.frames.iter_mut().flatten() {
            *v = std::array::from_fn(|k| ((v[k] - centre[k]) * s).clamp(-1.0, 1.0));
        }
        (centre, s)
    }

    /// Position at frame `f` of the point with barycentrics (1 - b1 - b2, b1, b2) on triangle `tri`.
    pub fn surface_point(&self, f: usize, tri: u32, b: [f32; 2]) -> V3 {
        let t = self.triangles[tri as usize];
        let v = &self.frames[f];
        let b0 = 1.0 - b[0] - b[1];
        std::array::from_fn(|k| {
            b0 * v[t[0] as usize][k] + b[0] * v[t[1] as usize][k] + b[1] * v[t[2] as usize][k]
        })
    }
}
