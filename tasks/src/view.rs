//! Watching a 4D result in a browser, for every front end (`velox view PATH`, `velox.view` in
//! Python). PATH is a folder of per-frame Gaussian
//! PLYs (`decode gaussians`, `generate`: `gaussians_fFF.ply`), of per-frame surface points
//! (`decode points`: `points_fFF.ply`), another tool's numbered PLY sequence (`frame_0000.ply`,
//! ...: each frame its number), a dataset scene (its 4D point cloud, split by frame) or one
//! Gaussian PLY. [`View::open`] checks every frame's header first (a folder without frames,
//! a file of another layout: an error before anything is served), then [`View::serve`] serves
//! on the listener its caller bound (the command: 127.0.0.1 unless `--host` says otherwise) a page written in this project
//! (`tasks/src/view/`: a WebGL2 renderer of 3D Gaussians with the engine's projection,
//! covariance, colour and front-to-back blending) and the frames, each converted when the page
//! asks for it. [`View::page`] is the page with the manifest and every frame inside it, one
//! file that opens offline.
//!
//! Beside PATH the page shows a second result of the same clip in step with it (`compare`;
//! by default the ground truth's points of the scene a decode output was made from), and over
//! it 3D tracks: those `velox track` wrote (`tracks.json`), or the scene's ground-truth tracks.
//!
//! What the page reads (relative URLs):
//! - `manifest.json`: the title, the kind (`gaussians` or `points`), the frames (frame index,
//!   tau, URL, count), the scene's cameras (the rasteriser's [`Camera`] with a name) and the
//!   background;
//! - `frames/K.bin`: frame K of the manifest as the bytes `VXG1`, a u32 count N, then N records
//!   of 13 little-endian f32: mean (3), the world covariance's upper triangle xx xy xz yy yz zz,
//!   opacity in [0, 1], colour (negative channels clamped to 0, as the rasteriser does). Points
//!   are drawn as small round opaque Gaussians ([`POINT_SIGMA`]). A frame that cannot be read
//!   answers 500 with the reason, which the page shows. `compare/K.bin`: the second result's
//!   frames, alike;
//! - `tracks.bin`: `VXT1`, u32 tracks T, u32 clip frames F, T F 3 f32 positions (track-major),
//!   T F visibility bytes, zero-padded to 4 bytes.
//!
//! Nothing but those routes is served: no path of the request reaches the file system.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Serialize;
use velox_data::format::{CameraSet, Scene};
use velox_engine::ops::raster::{Camera, GaussianData};
use velox_io::frames::{self, frame_of_tau, tau_of, FRAMES};
use velox_io::ply::{self, Header};
use velox_io::tracks::{self, TrackReport};

/// A viewer's errors: a file's, the data's, or what the viewer itself found, in words.
pub type ViewResult<T> = Result<T, Box<dyn std::error::Error + Send + Sync>>;

/// What to show.
#[derive(Clone, Debug, Default)]
pub struct ViewOptions {
    /// A folder of per-frame Gaussian PLYs (gaussians_fFF.ply) or surface points
    /// (points_fFF.ply), another tool's numbered PLY sequence (frame_0000.ply, ...), a dataset
    /// scene folder, or one Gaussian PLY.
    pub path: PathBuf,
    /// The scene whose cameras the page offers (default: the scene a decode output names in
    /// its decode.json, or PATH itself when it is a scene).
    pub scene: Option<PathBuf>,
    /// A second result to show beside PATH, in step with it (anything PATH may be; default: the
    /// ground truth's points of the scene a decode output names).
    pub compare: Option<PathBuf>,
    /// Show PATH alone, without the default comparison.
    pub no_compare: bool,
}

/// Colour of points that carry none (decoded surface points): a light grey.
pub const POINT_GREY: [f32; 3] = [0.8, 0.8, 0.8];

/// Points (xyz and colour) as small round Gaussians of standard deviation `sigma` and opacity
/// logit `logit`: how the viewer and the pictures draw point clouds.
pub fn points_as_gaussians(
    points: impl IntoIterator<Item = ([f32; 3], [f32; 3])>,
    sigma: f32,
    logit: f32,
) -> GaussianData {
    let mut g = GaussianData::default();
    for (xyz, rgb) in points {
        g.push(xyz, [sigma.ln(); 3], [1.0, 0.0, 0.0, 0.0], logit, rgb);
    }
    g
}

/// Standard deviation of the Gaussian a point is drawn as, in scene units (the scenes span
/// [-1, 1]: a point covers a few pixels at the data's resolutions).
pub const POINT_SIGMA: f32 = 0.006;
/// The opacity logit of a drawn point: its sigmoid rounds to 1 in f32 (opaque).
const OPAQUE_LOGIT: f32 = 20.0;
/// Floats per Gaussian in a frame's body.
const RECORD: usize = 13;

/// Where a frame's Gaussians come from.
enum FrameData {
    /// A 3D Gaussian splatting PLY.
    Gaussians(PathBuf),
    /// A PLY of points (x y z, maybe r g b or red green blue).
    Points(PathBuf),
    /// A surface mesh (`velox decode mesh`), drawn as a flat Gaussian a triangle.
    Mesh(PathBuf),
    /// Frame `frame` of a scene's 4D cloud (rows x y z r g b tau).
    ScenePoints { cloud: Arc<Vec<[f32; 7]>>, frame: usize },
}

struct Frame {
    frame: usize,
    count: usize,
    data: FrameData,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
enum Kind {
    Gaussians,
    Points,
}

/// A scene camera and its name (`input 3`, `supervision 0`).
#[derive(Serialize)]
pub struct NamedCamera {
    pub name: String,
    #[serde(flatten)]
    pub camera: Camera,
}

/// What PATH holds, checked.
struct Source {
    title: String,
    kind: Kind,
    frames: Vec<Frame>,
    cameras: Vec<NamedCamera>,
    /// Another result of the same clip, shown beside this one.
    compare: Option<Box<Source>>,
    tracks: Option<Tracks>,
    /// The dataset scene the result belongs to, if known.
    scene: Option<PathBuf>,
}

/// 3D tracks through the clip: `positions[(t * frames + f) * 3..][..3]` is track t at clip
/// frame f, `visible[t * frames + f]` whether it is seen there.
struct Tracks {
    count: usize,
    frames: usize,
    positions: Vec<f32>,
    visible: Vec<u8>,
}

impl Tracks {
    /// The page's `tracks.bin`: `VXT1`, u32 count, u32 frames, the positions as f32, the
    /// visibility as bytes, zero-padded to a multiple of 4 bytes.
    fn body(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(12 + 4 * self.positions.len() + self.visible.len() + 3);
        out.extend_from_slice(b"VXT1");
        out.extend_from_slice(&(self.count as u32).to_le_bytes());
        out.extend_from_slice(&(self.frames as u32).to_le_bytes());
        for v in &self.positions {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&self.visible);
        out.resize(out.len().next_multiple_of(4), 0);
        out
    }
}

/// The tracks `velox track` wrote (`tracks.json`), over the clip's frames.
fn read_track_json(dir: &Path) -> ViewResult<Tracks> {
    let report = TrackReport::read(dir)?;
    let positions = report.queries.iter().flat_map(|q| q.positions.iter().flatten().copied()).collect();
    let visible = report.queries.iter().flat_map(|q| q.visible.iter().map(|&b| b as u8)).collect();
    Ok(Tracks { count: report.queries.len(), frames: report.frames, positions, visible })
}

/// A dataset scene's ground-truth surface tracks, seen where any input camera sees them;
/// none when the scene was made without tracks.
fn scene_tracks(s: &Scene) -> Option<Tracks> {
    if s.tracks.is_empty() {
        return None;
    }
    let positions = s.tracks.iter().flatten().flatten().copied().collect();
    let visible = s.visibility.iter().flatten().map(|&bits| (bits != 0) as u8).collect();
    Some(Tracks { count: s.tracks.len(), frames: FRAMES, positions, visible })
}

#[derive(Serialize)]
struct ManifestFrame {
    frame: usize,
    tau: f32,
    url: String,
    count: usize,
}

#[derive(Serialize)]
struct Manifest<'a> {
    version: u32,
    title: &'a str,
    kind: Kind,
    frames: Vec<ManifestFrame>,
    cameras: &'a [NamedCamera],
    background: [f32; 3],
    compare: Option<ManifestCompare<'a>>,
    tracks: Option<ManifestTracks>,
}

#[derive(Serialize)]
struct ManifestCompare<'a> {
    title: &'a str,
    frames: Vec<ManifestFrame>,
}

#[derive(Serialize)]
struct ManifestTracks {
    url: String,
    count: usize,
    frames: usize,
}

/// The header of a PLY file and its vertex count, reading only the start of the file; the
/// file's length is checked against the header.
fn ply_header(path: &Path) -> ViewResult<(Header, usize)> {
    let (header, file) = header_only(path)?;
    let (_, vertex) =
        header.find("vertex").ok_or_else(|| format!("{}: the PLY has no vertex element", path.display()))?;
    let count = vertex.count;
    let need: u128 = header.elements.iter().map(|e| e.count as u128 * e.stride() as u128).sum();
    let have = file.metadata().map(|m| m.len()).unwrap_or(0) as u128 - header.body_start as u128;
    if need != have {
        return Err(format!(
            "{}: the header declares {need} bytes after it, the file has {have} (truncated or not what it says)",
            path.display()
        )
        .into());
    }
    Ok((header, count))
}

/// The header of a PLY file, reading only the start of it, and the file.
fn header_only(path: &Path) -> ViewResult<(Header, std::fs::File)> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut start = Vec::new();
    (&file)
        .take(64 * 1024)
        .read_to_end(&mut start)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let header = Header::parse(&start).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((header, file))
}

/// The triangles a mesh PLY's header declares (its faces; the page checks the rest when it
/// reads the frame).
fn mesh_triangles(path: &Path) -> ViewResult<usize> {
    let (header, _) = header_only(path)?;
    let faces = header.elements.iter().find(|e| e.name == "face");
    Ok(faces.ok_or_else(|| format!("{}: a mesh PLY without a face element", path.display()))?.count)
}

/// Whether a PLY header has every property of the Gaussian layout.
fn is_gaussian(header: &Header) -> bool {
    let Some((_, vertex)) = header.find("vertex") else { return false };
    let names: Vec<&str> = vertex.properties.iter().map(|p| p.0.as_str()).collect();
    ["x", "f_dc_0", "opacity", "scale_0", "rot_0"].iter().all(|p| names.contains(p))
}

/// A scene folder's cameras: its input views, then its supervision views (the order of the
/// viewer's camera buttons and of `velox render --view`).
pub fn scene_cameras(scene: &Path) -> velox_data::DataResult<Vec<NamedCamera>> {
    Ok(named_cameras(velox_data::format::read_cameras(scene)?))
}

fn named_cameras(set: CameraSet) -> Vec<NamedCamera> {
    let name = |group: &'static str| move |(i, camera)| NamedCamera { name: format!("{group} {i}"), camera };
    let input = set.input.into_iter().enumerate().map(name("input"));
    input.chain(set.supervision.into_iter().enumerate().map(name("supervision"))).collect()
}

/// The scene a decode or generate output was made from (decode.json's `cloud`), when it is a
/// scene folder.
fn named_scene(dir: &Path) -> Option<PathBuf> {
    velox_io::decoded::DecodeReport::read(dir).ok()?.scene()
}

/// The scene a track output was made from (tracks.json's `video`), when it is a scene folder.
fn tracked_scene(dir: &Path) -> Option<PathBuf> {
    TrackReport::read(dir).ok()?.scene()
}

/// Reads and checks what PATH holds.
fn discover(path: &Path, scene: Option<&Path>) -> ViewResult<Source> {
    if !path.exists() {
        return Err(format!("{} does not exist", path.display()).into());
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let (kind, frames, own_scene) = if path.is_file() {
        let (header, count) = ply_header(path)?;
        if !is_gaussian(&header) {
            return Err(format!(
                "{} is not a Gaussian PLY (x, f_dc_*, opacity, scale_*, rot_*)",
                path.display()
            )
            .into());
        }
        (
            Kind::Gaussians,
            vec![Frame { frame: 0, count, data: FrameData::Gaussians(path.to_path_buf()) }],
            None,
        )
    } else if path.join("points.ply").is_file() && path.join("cameras.json").is_file() {
        // A dataset scene, read once: its cloud frame by frame, its cameras and its tracks
        // (`--scene` names another scene for the cameras and tracks).
        let s = velox_data::format::read_scene(path, false)?;
        let (cameras, tracks) = match scene {
            Some(other) => {
                let o = velox_data::format::read_scene(other, false)?;
                (named_cameras(o.cameras.clone()), scene_tracks(&o))
            }
            None => (named_cameras(s.cameras.clone()), scene_tracks(&s)),
        };
        let mut counts = [0usize; FRAMES];
        for p in &s.points {
            counts[frame_of_tau(p[6])] += 1;
        }
        let cloud = Arc::new(s.points);
        let frames: Vec<Frame> = (0..counts.len())
            .filter(|&f| counts[f] > 0)
            .map(|f| Frame {
                frame: f,
                count: counts[f],
                data: FrameData::ScenePoints { cloud: cloud.clone(), frame: f },
            })
            .collect();
        let title = format!("points of {name}: {} frame(s)", frames.len());
        let scene = Some(scene.unwrap_or(path).to_path_buf());
        return Ok(Source { title, kind: Kind::Points, frames, cameras, compare: None, tracks, scene });
    } else {
        let of = |prefix: &str| frames::frame_files(path, prefix);
        // Gaussians first; else decoded points; else a track output's points; else meshes.
        let (gaussians, points, tracked) = (of("gaussians")?, of("points")?, of("tracks")?);
        let meshes = of("mesh")?;
        let is_mesh = gaussians.is_empty() && points.is_empty() && tracked.is_empty() && !meshes.is_empty();
        let (kind, list) = if !gaussians.is_empty() {
            (Kind::Gaussians, gaussians)
        } else if !points.is_empty() {
            (Kind::Points, points)
        } else if !tracked.is_empty() {
            (Kind::Points, tracked)
        } else if is_mesh {
            (Kind::Gaussians, meshes)
        } else {
            // Another tool's numbered sequence: its PLYs that end in a number, one prefix to
            // them all, each frame its number; Gaussians or points by the first one's header.
            let list = frames::numbered_files(path)?;
            let Some((_, first)) = list.first() else {
                return Err(format!(
                    "{} holds no frames: expected gaussians_fFF.ply (velox decode gaussians, velox generate), \
                     points_fFF.ply (velox decode points), tracks_fFF.ply (velox track), a numbered PLY \
                     sequence (frame_0000.ply, frame_0001.ply, ...), or a dataset scene (points.ply and \
                     cameras.json)",
                    path.display()
                )
                .into());
            };
            let kind = if is_gaussian(&ply_header(first)?.0) { Kind::Gaussians } else { Kind::Points };
            (kind, list)
        };
        let mut frames = Vec::new();
        for (f, file) in list {
            if is_mesh {
                // A Gaussian a triangle.
                frames.push(Frame { frame: f, count: mesh_triangles(&file)?, data: FrameData::Mesh(file) });
                continue;
            }
            let (header, count) = ply_header(&file)?;
            let data = match kind {
                Kind::Gaussians if is_gaussian(&header) => FrameData::Gaussians(file),
                Kind::Points if !is_gaussian(&header) => FrameData::Points(file),
                _ => {
                    return Err(format!(
                        "{}: frames of different formats: it is {} a Gaussian PLY, unlike the folder's other frames",
                        file.display(),
                        if is_gaussian(&header) { "" } else { "not" }
                    )
                    .into())
                }
            };
            frames.push(Frame { frame: f, count, data });
        }
        (kind, frames, named_scene(path).or_else(|| tracked_scene(path)))
    };
    let scene = scene.map(Path::to_path_buf).or(own_scene);
    let cameras = match &scene {
        Some(s) => scene_cameras(s)?,
        None => Vec::new(),
    };
    let what = match kind {
        _ if frames.first().is_some_and(|f| matches!(f.data, FrameData::Mesh(_))) => "mesh triangles",
        Kind::Gaussians => "Gaussians",
        Kind::Points => "points",
    };
    let title = format!("{what} of {name}: {} frame(s)", frames.len());
    // A track output's own tracks; a decode output's scene's come with it (see
    // `discover_with_compare`, which reads that scene once).
    let tracks = if path.join(tracks::FILE).is_file() { Some(read_track_json(path)?) } else { None };
    Ok(Source { title, kind, frames, cameras, compare: None, tracks, scene })
}

/// PATH with what goes beside it: `compare` when given; else, unless `none`, the ground
/// truth's points of the scene PATH was decoded from (when PATH is not that scene itself).
fn discover_with_compare(a: &ViewOptions) -> ViewResult<Source> {
    let mut source = discover(&a.path, a.scene.as_deref())?;
    // The scene PATH was made from, when PATH is not that scene itself.
    let origin = source.scene.clone().filter(|s| !same_folder(s, &a.path));
    let mut truth = None;
    let compare = match (&a.compare, &origin) {
        _ if a.no_compare => None,
        (Some(other), _) => Some(discover(other, source.scene.as_deref())?),
        (None, Some(scene)) => {
            let mut t = discover(scene, None)?;
            t.title = format!("ground truth: {}", t.title);
            truth = t.tracks.take();
            Some(t)
        }
        (None, None) => None,
    };
    if source.tracks.is_none() {
        source.tracks = match (truth, &origin) {
            (Some(t), _) => Some(t),
            (None, Some(scene)) => scene_tracks(&velox_data::format::read_scene(scene, false)?),
            (None, None) => None,
        };
    }
    source.compare = compare.map(|c| Box::new(Source { compare: None, tracks: None, ..c }));
    Ok(source)
}

fn same_folder(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// The upper triangle of `R(q) diag(exp(log_scale))^2 R(q)^T` (q = (w, x, y, z), normalised).
fn covariance(log_scale: &[f32], q: &[f32]) -> [f32; 6] {
    let n = q.iter().map(|v| (*v as f64) * (*v as f64)).sum::<f64>().sqrt().max(1e-30);
    let [w, x, y, z] = [q[0], q[1], q[2], q[3]].map(|v| v as f64 / n);
    let r = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    let s2 = [0, 1, 2].map(|k| (2.0 * log_scale[k] as f64).exp());
    let c = |i: usize, j: usize| (0..3).map(|k| r[i][k] * s2[k] * r[j][k]).sum::<f64>() as f32;
    [c(0, 0), c(0, 1), c(0, 2), c(1, 1), c(1, 2), c(2, 2)]
}

/// The frame's body for the page (see the module docs).
fn gaussian_body(g: &GaussianData) -> Vec<u8> {
    gaussian_body_sh(g, None)
}

/// [`gaussian_body`] with the Gaussians' higher spherical harmonics after the records
/// (`VXS1`, the degree, the coefficients as the PLY holds them): the page adds them to the
/// colour along each view direction and clamps the sum, so the colour is sent unclamped.
fn gaussian_body_sh(g: &GaussianData, sh: Option<&ply::Sh>) -> Vec<u8> {
    let n = g.means.len() / 3;
    let mut out = Vec::with_capacity(8 + n * RECORD * 4 + sh.map_or(0, |s| 8 + 4 * s.coeffs.len()));
    out.extend_from_slice(b"VXG1");
    out.extend_from_slice(&(n as u32).to_le_bytes());
    for i in 0..n {
        let cov = covariance(&g.log_scales[3 * i..3 * i + 3], &g.quats[4 * i..4 * i + 4]);
        let opacity = 1.0 / (1.0 + (-g.opacities[i] as f64).exp()) as f32;
        let colour =
            [0, 1, 2]
                .map(|k| if sh.is_some() { g.colours[3 * i + k] } else { g.colours[3 * i + k].max(0.0) });
        for v in g.means[3 * i..3 * i + 3].iter().chain(&cov).chain([&opacity]).chain(&colour) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    if let Some(sh) = sh {
        out.extend_from_slice(b"VXS1");
        out.extend_from_slice(&(sh.degree as u32).to_le_bytes());
        for v in &sh.coeffs {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// A mesh as a frame's body: each triangle a flat, nearly opaque Gaussian with the triangle's
/// second moment (doubled, so that neighbours overlap into a closed surface; a hair's
/// thickness along the normal), grey lit from a fixed direction on both faces.
fn mesh_body(m: &velox_io::mesh::Mesh) -> Vec<u8> {
    const LIGHT: [f64; 3] = [0.29, 0.82, 0.49];
    let mut out = Vec::with_capacity(8 + m.triangles.len() * RECORD * 4);
    out.extend_from_slice(b"VXG1");
    out.extend_from_slice(&(m.triangles.len() as u32).to_le_bytes());
    for &t in &m.triangles {
        let (p, n) = m.face(t);
        let centre: [f64; 3] = std::array::from_fn(|a| (p[0][a] + p[1][a] + p[2][a]) / 3.0);
        let d = p.map(|v| std::array::from_fn::<f64, 3, _>(|a| v[a] - centre[a]));
        let twice_area = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let n = n.map(|v| v / twice_area.max(1e-30));
        let thickness = 1e-3 * twice_area.sqrt();
        // The uniform triangle's covariance is the sum of d d^T over its corners / 12.
        let cov = |a: usize, b: usize| {
            (2.0 * d.iter().map(|v| v[a] * v[b]).sum::<f64>() / 12.0 + thickness * thickness * n[a] * n[b])
                as f32
        };
        let lit = (0.3 + 0.7 * (n[0] * LIGHT[0] + n[1] * LIGHT[1] + n[2] * LIGHT[2]).abs()) as f32;
        let record = [
            centre[0] as f32,
            centre[1] as f32,
            centre[2] as f32,
            cov(0, 0),
            cov(0, 1),
            cov(0, 2),
            cov(1, 1),
            cov(1, 2),
            cov(2, 2),
            0.98,
            lit,
            lit,
            lit,
        ];
        for v in record {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Points (xyz and colour) as small round opaque Gaussians, as a frame's body.
fn points_body(points: impl IntoIterator<Item = ([f32; 3], [f32; 3])>) -> Vec<u8> {
    gaussian_body(&points_as_gaussians(points, POINT_SIGMA, OPAQUE_LOGIT))
}

/// The points of a points PLY (x y z and, if present, r g b or red green blue in [0, 1] or
/// 0..255 for integer channels).
fn read_points(path: &Path) -> ViewResult<Vec<([f32; 3], [f32; 3])>> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let header = Header::parse(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    header.check_length(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    let (start, vertex) =
        header.find("vertex").ok_or_else(|| format!("{}: no vertex element", path.display()))?;
    let mut offsets = Vec::new();
    let mut at = 0;
    for (name, scalar) in &vertex.properties {
        offsets.push((name.as_str(), at, *scalar));
        at += scalar.size();
    }
    let field = |names: &[&str]| offsets.iter().find(|(n, _, _)| names.contains(n)).copied();
    let xyz = [field(&["x"]), field(&["y"]), field(&["z"])];
    if xyz.iter().any(Option::is_none) {
        return Err(format!("{}: points need x, y and z", path.display()).into());
    }
    let rgb = [field(&["r", "red"]), field(&["g", "green"]), field(&["b", "blue"])];
    let stride = vertex.stride();
    let mut points = Vec::with_capacity(vertex.count);
    for i in 0..vertex.count {
        let item = &bytes[start + i * stride..start + (i + 1) * stride];
        let read = |(_, at, s): (&str, usize, ply::Scalar)| s.read(&item[at..]);
        let p = xyz.map(|f| read(f.expect("checked above")) as f32);
        if p.iter().any(|v| !v.is_finite()) {
            return Err(format!("{}: point {i} is not finite", path.display()).into());
        }
        let c = match rgb {
            [Some(r), Some(g), Some(b)] => [r, g, b].map(|f| {
                let v = read(f);
                (if matches!(f.2, ply::Scalar::F32 | ply::Scalar::F64) { v } else { v / 255.0 }) as f32
            }),
            _ => POINT_GREY,
        };
        points.push((p, c));
    }
    Ok(points)
}

impl Frame {
    /// The frame's body for the page, read and converted now.
    fn body(&self) -> ViewResult<Vec<u8>> {
        Ok(match &self.data {
            FrameData::Gaussians(path) => {
                let (g, sh) = ply::read_sh(path)?;
                gaussian_body_sh(&g, sh.as_ref())
            }
            FrameData::Points(path) => points_body(read_points(path)?),
            FrameData::Mesh(path) => mesh_body(&velox_io::mesh::read(path)?),
            FrameData::ScenePoints { cloud, frame } => {
                let of_frame = cloud.iter().filter(|p| frame_of_tau(p[6]) == *frame);
                points_body(of_frame.map(|p| ([p[0], p[1], p[2]], [p[3], p[4], p[5]])))
            }
        })
    }
}

impl Source {
    /// The manifest's list of `frames`, at URLs `{route}/K.bin` (or `#{route}-K` embedded).
    fn manifest_frames(frames: &[Frame], route: &str, embedded: bool) -> Vec<ManifestFrame> {
        let url = |k: usize| {
            if embedded {
                format!("#{}", embedded_id(route, k))
            } else {
                format!("{route}/{k}.bin")
            }
        };
        let frame = |(k, f): (usize, &Frame)| ManifestFrame {
            frame: f.frame,
            tau: tau_of(f.frame),
            url: url(k),
            count: f.count,
        };
        frames.iter().enumerate().map(frame).collect()
    }

    fn manifest(&self, embedded: bool) -> String {
        let m = Manifest {
            version: 1,
            title: &self.title,
            kind: self.kind,
            frames: Source::manifest_frames(&self.frames, FRAMES_ROUTE, embedded),
            cameras: &self.cameras,
            // The scene's background (its views were drawn on it), else black.
            background: self
                .scene
                .as_deref()
                .and_then(|s| velox_data::format::read_meta(s).ok())
                .map_or([0.0; 3], |m| m.background),
            compare: self.compare.as_ref().map(|c| ManifestCompare {
                title: &c.title,
                frames: Source::manifest_frames(&c.frames, COMPARE_ROUTE, embedded),
            }),
            tracks: self.tracks.as_ref().map(|t| ManifestTracks {
                url: if embedded { "#tracks".into() } else { "tracks.bin".into() },
                count: t.count,
                frames: t.frames,
            }),
        };
        serde_json::to_string(&m).expect("the manifest serialises")
    }
}

const INDEX: &str = include_str!("view/index.html");
const VIEWER: &str = include_str!("view/viewer.js");
/// Where `--html` puts the manifest and the frames in the page.
const EMBED_MARKER: &str = "<!--velox-embedded-->";

/// Standard base64 with padding.
fn base64(bytes: &[u8]) -> String {
    const ABC: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ABC[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Where the served page fetches frame K of the result (`frames/K.bin`) and of the comparison.
const FRAMES_ROUTE: &str = "frames";
const COMPARE_ROUTE: &str = "compare";

/// The id of the element that holds frame `k` of `route` in the one-file page: the manifest's
/// URL for it is `#` and this id, so both are made here.
fn embedded_id(route: &str, k: usize) -> String {
    format!("{route}-{k}")
}

/// The page with the manifest and every frame inside it, and the viewer's script inline.
fn embedded_page(source: &Source) -> ViewResult<String> {
    if !INDEX.contains(EMBED_MARKER) {
        return Err("the viewer page has no place for embedded frames".into());
    }
    // `</` cannot close a script element inside JSON or base64 once escaped.
    let mut inserts = format!(
        "<script id=\"velox-manifest\" type=\"application/json\">{}</script>\n",
        source.manifest(true).replace("</", "<\\/")
    );
    let data = |id: &str, bytes: &[u8]| {
        format!("<script id=\"{id}\" type=\"application/octet-stream\">{}</script>\n", base64(bytes))
    };
    for (k, f) in source.frames.iter().enumerate() {
        inserts.push_str(&data(&embedded_id(FRAMES_ROUTE, k), &f.body()?));
    }
    for (k, f) in source.compare.iter().flat_map(|c| c.frames.iter().enumerate()) {
        inserts.push_str(&data(&embedded_id(COMPARE_ROUTE, k), &f.body()?));
    }
    if let Some(t) = &source.tracks {
        inserts.push_str(&data("tracks", &t.body()));
    }
    let script = format!("<script>\n{}\n</script>", VIEWER.replace("</script", "<\\/script"));
    Ok(INDEX.replacen(EMBED_MARKER, &inserts, 1).replacen("<script src=\"viewer.js\"></script>", &script, 1))
}

/// One HTTP response.
fn respond(stream: &mut TcpStream, status: &str, kind: &str, body: &[u8]) -> std::io::Result<()> {
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes())?;
    stream.write_all(body)?;
    stream.flush()
}

/// Answers one request: the page, its script, the manifest or a frame; anything else is 404.
fn handle(mut stream: TcpStream, source: &Source, manifest: &str) -> std::io::Result<()> {
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut line = String::new();
    reader.by_ref().take(8192).read_line(&mut line)?;
    // The headers are read and ignored (to the blank line), so the client sees its request taken.
    let mut header = String::new();
    while reader.by_ref().take(8192).read_line(&mut header)? > 2 {
        header.clear();
    }
    let mut parts = line.split_whitespace();
    let (method, target) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    if method != "GET" {
        return respond(&mut stream, "405 Method Not Allowed", "text/plain", b"only GET is served");
    }
    let route = target.split(['?', '#']).next().unwrap_or("");
    match route {
        "/" | "/index.html" => respond(&mut stream, "200 OK", "text/html; charset=utf-8", INDEX.as_bytes()),
        "/viewer.js" => respond(&mut stream, "200 OK", "text/javascript; charset=utf-8", VIEWER.as_bytes()),
        "/manifest.json" => respond(&mut stream, "200 OK", "application/json", manifest.as_bytes()),
        "/tracks.bin" => match &source.tracks {
            Some(t) => respond(&mut stream, "200 OK", "application/octet-stream", &t.body()),
            None => respond(&mut stream, "404 Not Found", "text/plain", b"not found"),
        },
        _ => {
            let numbered = |prefix: &str| {
                route
                    .strip_prefix(prefix)
                    .and_then(|r| r.strip_suffix(".bin"))
                    .and_then(|k| k.parse::<usize>().ok())
            };
            let frame = match (numbered("/frames/"), numbered("/compare/"), &source.compare) {
                (Some(k), _, _) => source.frames.get(k).map(|f| (k, f)),
                (_, Some(k), Some(c)) => c.frames.get(k).map(|f| (k, f)),
                _ => None,
            };
            match frame {
                Some((k, f)) => match f.body() {
                    Ok(body) => respond(&mut stream, "200 OK", "application/octet-stream", &body),
                    Err(e) => {
                        let why = format!("frame {k} (frame {} of the clip): {e}", f.frame);
                        respond(
                            &mut stream,
                            "500 Internal Server Error",
                            "text/plain; charset=utf-8",
                            why.as_bytes(),
                        )
                    }
                },
                None => respond(&mut stream, "404 Not Found", "text/plain", b"not found"),
            }
        }
    }
}

/// A result, checked, ready to be shown.
pub struct View {
    source: Source,
}

impl View {
    /// What `options` asks to show, every frame's header checked (see the module docs).
    pub fn open(options: &ViewOptions) -> ViewResult<View> {
        Ok(View { source: discover_with_compare(options)? })
    }

    /// The page's title (what is shown).
    pub fn title(&self) -> &str {
        &self.source.title
    }

    /// What is shown besides: the comparison and the tracks, as a phrase ("beside it ...; 64
    /// tracks"), empty when nothing.
    pub fn extras(&self) -> String {
        let mut extra = Vec::new();
        if let Some(c) = &self.source.compare {
            extra.push(format!("beside it {}", c.title));
        }
        if let Some(t) = &self.source.tracks {
            extra.push(format!("{} tracks", t.count));
        }
        extra.join("; ")
    }

    /// The page with the manifest and every frame inside it: one HTML file that opens offline.
    pub fn page(&self) -> ViewResult<String> {
        embedded_page(&self.source)
    }

    /// Serves the page and the frames on `listener` until the process ends (a thread a
    /// request).
    pub fn serve(self, listener: TcpListener) {
        let manifest = Arc::new(self.source.manifest(false));
        let source = Arc::new(self.source);
        for stream in listener.incoming() {
            let Ok(stream) = stream else { continue };
            let (source, manifest) = (source.clone(), manifest.clone());
            std::thread::spawn(move || {
                // A client that goes away mid-answer is no error of ours.
                let _ = handle(stream, &source, &manifest);
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_the_standard_alphabet_and_padding() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn a_covariance_is_the_rotated_squared_scales() {
        // No rotation: the squared scales on the diagonal.
        let c = covariance(&[0.0, 2f32.ln(), 0.5f32.ln()], &[1.0, 0.0, 0.0, 0.0]);
        let want = [1.0, 0.0, 0.0, 4.0, 0.0, 0.25];
        assert!(c.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6), "{c:?}");
        // A quarter turn about z (any quaternion length) swaps x and y.
        let h = std::f32::consts::FRAC_PI_4;
        let c = covariance(&[0.0, 2f32.ln(), 0.0], &[3.0 * h.cos(), 0.0, 0.0, 3.0 * h.sin()]);
        let want = [4.0, 0.0, 0.0, 1.0, 0.0, 1.0];
        assert!(c.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "{c:?}");
    }
}
