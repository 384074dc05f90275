// Compute rasteriser of triangle meshes for the training data: depth, triangle id,
// perspective-correct barycentrics and shaded, textured RGB from many pinhole views at once.
//
// Four passes over one frame's mesh and a batch of views of one size (host: data/src/raster.rs):
//   `clear`   per pixel: depth bits and ids to 0xffffffff (nothing drawn);
//   `depth`   per (view, triangle): walk the triangle's pixel bounding box, and where a pixel
//             centre lies inside (edge functions >= 0, either winding) atomicMin the bits of its
//             view-space depth. Positive f32 values order like their u32 bits, so the smallest
//             bits are the nearest surface;
//   `resolve` per (view, triangle): the same walk with the same arithmetic, so the same depth
//             bits come out; where they equal the stored minimum, atomicMin the triangle id, so a
//             tie (two triangles at exactly the same depth, as on a shared edge) goes to the
//             lower id and the result does not depend on the order invocations run in;
//   `shade`   per pixel: for the winning triangle, recompute the barycentrics at the pixel
//             centre and write depth, barycentrics and RGB (texture times a diffuse term from a
//             world-fixed light, so a surface point has the same colour in every view).
// Inclusive edge tests on both sides of a shared edge leave no cracks; the tie rule removes
// the double cover. A triangle with a vertex nearer than `near` is skipped (the data's cameras
// never come that close to the [-1, 1]^3 objects), and a degenerate one (zero screen area, as
// a hidden part collapsed to a point) draws nothing.
//
// Cameras: 16 floats each, world to camera rows r0 t0 r1 t1 r2 t2 (x right, y down, z forward)
// then fx fy cx cy; pixel centres sit at integer + 0.5.

struct Params {
    n_tris: u32,
    n_views: u32,
    width: u32,
    height: u32,
    // xyz: unit direction towards the light (world); w: ambient share.
    light: vec4<f32>,
    // rgb: background colour; w: near plane distance.
    bg: vec4<f32>,
}

const WG: u32 = 64u;
const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<storage, read> verts: array<f32>;
@group(0) @binding(1) var<storage, read> tris: array<u32>;
@group(0) @binding(2) var<storage, read> cams: array<f32>;
@group(0) @binding(3) var<storage, read_write> depth_bits: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> ids: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read> uvs: array<f32>;
@group(0) @binding(6) var<storage, read> tri_tex: array<u32>;
@group(0) @binding(7) var<storage, read> tex_table: array<u32>;
@group(0) @binding(8) var<storage, read> texels: array<u32>;
@group(0) @binding(9) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(10) var<storage, read_write> out_bary: array<f32>;
@group(0) @binding(11) var<storage, read_write> out_rgb: array<u32>;
// RGB per vertex, multiplying the texture (glTF's COLOR_0; 1 where the mesh has none).
@group(0) @binding(12) var<storage, read> colours: array<f32>;
var<immediate> pc: Params;

fn vertex(i: u32) -> vec3<f32> {
    return vec3<f32>(verts[3u * i], verts[3u * i + 1u], verts[3u * i + 2u]);
}

fn vertex_colour(i: u32) -> vec3<f32> {
    return vec3<f32>(colours[3u * i], colours[3u * i + 1u], colours[3u * i + 2u]);
}

// Pixel coordinates (x, y) and view-space depth z of world point p in view `view`.
fn project(view: u32, p: vec3<f32>) -> vec3<f32> {
    let c = view * 16u;
    let x = cams[c + 0u] * p.x + cams[c + 1u] * p.y + cams[c + 2u] * p.z + cams[c + 3u];
    let y = cams[c + 4u] * p.x + cams[c + 5u] * p.y + cams[c + 6u] * p.z + cams[c + 7u];
    let z = cams[c + 8u] * p.x + cams[c + 9u] * p.y + cams[c + 10u] * p.z + cams[c + 11u];
    return vec3<f32>(cams[c + 12u] * x / z + cams[c + 14u], cams[c + 13u] * y / z + cams[c + 15u], z);
}

fn edge(a: vec2<f32>, b: vec2<f32>, p: vec2<f32>) -> f32 {
    return (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x);
}

// One triangle in one view, ready for the pixel walk.
struct Screen {
    p0: vec3<f32>,
    p1: vec3<f32>,
    p2: vec3<f32>,
    area: f32,
    lo: vec2<i32>,
    hi: vec2<i32>,
    ok: bool,
}

fn setup(view: u32, tri: u32) -> Screen {
    var s: Screen;
    s.ok = false;
    s.p0 = project(view, vertex(tris[3u * tri]));
    s.p1 = project(view, vertex(tris[3u * tri + 1u]));
    s.p2 = project(view, vertex(tris[3u * tri + 2u]));
    let near = pc.bg.w;
    if (s.p0.z <= near || s.p1.z <= near || s.p2.z <= near) {
        return s;
    }
    s.area = edge(s.p0.xy, s.p1.xy, s.p2.xy);
    if (s.area == 0.0) {
        return s;
    }
    let mn = min(min(s.p0.xy, s.p1.xy), s.p2.xy);
    let mx = max(max(s.p0.xy, s.p1.xy), s.p2.xy);
    let size = vec2<f32>(f32(pc.width), f32(pc.height));
    // Pixel centres x + 0.5 in [mn, mx]; clamped to the image (also keeps i32 casts small).
    s.lo = vec2<i32>(ceil(clamp(mn - 0.5, vec2<f32>(-1.0), size)));
    s.hi = vec2<i32>(floor(clamp(mx - 0.5, vec2<f32>(-1.0), size - 1.0)));
    s.lo = max(s.lo, vec2<i32>(0));
    s.ok = true;
    return s;
}

// Screen-space barycentrics of pixel (x, y), or a negative component when outside.
fn screen_bary(s: Screen, x: i32, y: i32) -> vec3<f32> {
    let p = vec2<f32>(f32(x) + 0.5, f32(y) + 0.5);
    let inv = 1.0 / s.area;
    return vec3<f32>(edge(s.p1.xy, s.p2.xy, p) * inv, edge(s.p2.xy, s.p0.xy, p) * inv,
                     edge(s.p0.xy, s.p1.xy, p) * inv);
}

// View-space depth at screen barycentrics l: 1/z interpolates linearly on screen.
fn depth_at(s: Screen, l: vec3<f32>) -> f32 {
    return 1.0 / (l.x / s.p0.z + l.y / s.p1.z + l.z / s.p2.z);
}

fn item_index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * WG + lid;
}

@compute @workgroup_size(64)
fn clear(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = item_index(wid, nwg, lid);
    if (i >= pc.n_views * pc.width * pc.height) {
        return;
    }
    atomicStore(&depth_bits[i], NONE);
    atomicStore(&ids[i], NONE);
}

@compute @workgroup_size(64)
fn depth(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = item_index(wid, nwg, lid);
    if (i >= pc.n_views * pc.n_tris) {
        return;
    }
    let view = i / pc.n_tris;
    let tri = i % pc.n_tris;
    let s = setup(view, tri);
    if (!s.ok) {
        return;
    }
    let base = view * pc.width * pc.height;
    for (var y = s.lo.y; y <= s.hi.y; y = y + 1) {
        for (var x = s.lo.x; x <= s.hi.x; x = x + 1) {
            let l = screen_bary(s, x, y);
            if (l.x >= 0.0 && l.y >= 0.0 && l.z >= 0.0) {
                let z = depth_at(s, l);
                atomicMin(&depth_bits[base + u32(y) * pc.width + u32(x)], bitcast<u32>(z));
            }
        }
    }
}

@compute @workgroup_size(64)
fn resolve(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let i = item_index(wid, nwg, lid);
    if (i >= pc.n_views * pc.n_tris) {
        return;
    }
    let view = i / pc.n_tris;
    let tri = i % pc.n_tris;
    let s = setup(view, tri);
    if (!s.ok) {
        return;
    }
    let base = view * pc.width * pc.height;
    for (var y = s.lo.y; y <= s.hi.y; y = y + 1) {
        for (var x = s.lo.x; x <= s.hi.x; x = x + 1) {
            let l = screen_bary(s, x, y);
            if (l.x >= 0.0 && l.y >= 0.0 && l.z >= 0.0) {
                let p = base + u32(y) * pc.width + u32(x);
                if (bitcast<u32>(depth_at(s, l)) == atomicLoad(&depth_bits[p])) {
                    atomicMin(&ids[p], tri);
                }
            }
        }
    }
}

// Bilinear, wrapping texture lookup in texture `t`; RGBA8 texels, red in the low byte.
fn texel(t: u32, x: i32, y: i32) -> vec3<f32> {
    let w = i32(tex_table[4u * t + 1u]);
    let h = i32(tex_table[4u * t + 2u]);
    let xx = ((x % w) + w) % w;
    let yy = ((y % h) + h) % h;
    let v = texels[tex_table[4u * t] + u32(yy * w + xx)];
    return vec3<f32>(f32(v & 255u), f32((v >> 8u) & 255u), f32((v >> 16u) & 255u)) / 255.0;
}

fn sample_texture(t: u32, uv: vec2<f32>) -> vec3<f32> {
    let size = vec2<f32>(f32(tex_table[4u * t + 1u]), f32(tex_table[4u * t + 2u]));
    let p = uv * size - 0.5;
    let f = floor(p);
    let a = p - f;
    let x = i32(f.x);
    let y = i32(f.y);
    let top = mix(texel(t, x, y), texel(t, x + 1, y), a.x);
    let bottom = mix(texel(t, x, y + 1), texel(t, x + 1, y + 1), a.x);
    return mix(top, bottom, a.y);
}

@compute @workgroup_size(64)
fn shade(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = item_index(wid, nwg, lid);
    let pixels = pc.width * pc.height;
    if (i >= pc.n_views * pixels) {
        return;
    }
    let tri = atomicLoad(&ids[i]);
    if (tri == NONE) {
        out_depth[i] = 0.0;
        out_bary[2u * i] = 0.0;
        out_bary[2u * i + 1u] = 0.0;
        let bg = vec3<u32>(round(clamp(pc.bg.xyz, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0));
        out_rgb[i] = bg.x | (bg.y << 8u) | (bg.z << 16u);
        return;
    }
    let view = i / pixels;
    let x = i32((i % pixels) % pc.width);
    let y = i32((i % pixels) / pc.width);
    let s = setup(view, tri);
    let l = screen_bary(s, x, y);
    let z = depth_at(s, l);
    // Perspective-correct barycentrics.
    let b = vec3<f32>(l.x / s.p0.z, l.y / s.p1.z, l.z / s.p2.z) * z;
    out_depth[i] = z;
    out_bary[2u * i] = b.y;
    out_bary[2u * i + 1u] = b.z;

    let i0 = tris[3u * tri];
    let i1 = tris[3u * tri + 1u];
    let i2 = tris[3u * tri + 2u];
    let uv = b.x * vec2<f32>(uvs[2u * i0], uvs[2u * i0 + 1u]) + b.y * vec2<f32>(uvs[2u * i1], uvs[2u * i1 + 1u])
        + b.z * vec2<f32>(uvs[2u * i2], uvs[2u * i2 + 1u]);
    // From vertex 0 by the other two's differences: exactly 1 where every vertex is white.
    let c0 = vertex_colour(i0);
    let tint = c0 + b.y * (vertex_colour(i1) - c0) + b.z * (vertex_colour(i2) - c0);
    let albedo = sample_texture(tri_tex[tri], uv) * tint;
    let v0 = vertex(i0);
    let n = cross(vertex(i1) - v0, vertex(i2) - v0);
    let len = length(n);
    var diffuse = 1.0;
    if (len > 0.0) {
        diffuse = abs(dot(n / len, pc.light.xyz));
    }
    let shaded = albedo * (pc.light.w + (1.0 - pc.light.w) * diffuse);
    let c = vec3<u32>(round(clamp(shaded, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0));
    out_rgb[i] = c.x | (c.y << 8u) | (c.z << 16u) | (255u << 24u);
}
