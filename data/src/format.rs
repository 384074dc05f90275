//! The dataset on disk, and reading it back.
//!
//! ```text
//! DIR/scene_00000/
//!   meta.json                 SceneMeta: format, source (recipe or glTF file and credits),
//!                             frames, fps, resolution, the counts below and the
//!                             background of the views (black when absent)
//!   cameras.json              {"input": [Camera; 35], "supervision": [Camera; 25], "video": Camera}
//!                             (camera.rs: world-to-camera rows, translation, fx fy cx cy, size)
//!   points.ply                binary little-endian PLY, float x y z r g b tau per point,
//!                             xyz in [-1, 1]^3, rgb in [0, 1], tau = frame / 100, frame order
//!   occupancy.bin             per frame 64^3 bits as 4096 little-endian u64 words; voxel
//!                             (x, y, z) of [-1, 1]^3 is bit (i % 64) of word i / 64,
//!                             i = x + 64 (y + 64 z)
//!   tracks.bin                per track, per frame: x y z as little-endian f32
//!   tracks_visibility.bin     per track, per frame: a little-endian u64, bit c set when
//!                             input camera c sees the point
//!   video_tracks.bin          the tracking task's queries (frame-0 surface points the video
//!                             shows), per query, per frame: x y z as little-endian f32
//!   video_tracks_visibility.bin  per query, per frame: a byte, 1 where the video camera
//!                             sees the point, else 0
//!   supervision/fFF_vVV.png   frame FF seen from supervision camera VV (RGB, anti-aliased)
//!   video/fFF.png             the conditioning video's frame FF (RGB, anti-aliased)
//!   video/fFF_depth.exr       its depth (one f32 channel Z: camera-space z, 0 where no
//!                             surface; one sample at each pixel's centre): the RGBD video of
//!                             the tracking task
//! ```
//! Background pixels are black. Everything needed to read a scene is in its folder; a scene
//! is written into `scene_XXXXX.partial` and renamed when complete, so a crash never leaves a
//! half scene under a scene's name.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, NUM_INPUT_CAMERAS};
use crate::pipeline::{
    SceneArrays, FPS, MAX_POINTS, MAX_RESOLUTION, MAX_SUPERSAMPLE, MAX_TRACKS, OCCUPANCY_WORDS,
};
use crate::procedural::FRAMES;
use crate::{DataError, DataResult};
use velox_io::ply;

pub const FORMAT: &str = "velox-data 1";
/// Most supervision views a scene may have (the writer makes 25).
pub const MAX_SUPERVISION_VIEWS: usize = 1024;
/// How far a track may lie outside [-1, 1]^3 (rounding of the normalised mesh).
const TRACK_SLACK: f32 = 1e-3;

/// A scene's `meta.json`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SceneMeta {
    pub format: String,
    /// "procedural seed S: walker, arm" or the glTF file's name.
    pub source: String,
    /// Credits of imported assets (glTF `asset.copyright` and `generator`), if any.
    pub credits: Option<String>,
    pub frames: usize,
    pub fps: f32,
    pub resolution: u32,
    pub points: usize,
    pub tracks: usize,
    /// Queries of the tracking task (`video_tracks.bin`); scenes written before it read 0.
    #[serde(default)]
    pub video_tracks: usize,
    pub supervision_views: usize,
    pub supersample: u32,
    /// The background of the supervision views and the video (scenes written before it:
    /// black), which renders compared with them are drawn on.
    #[serde(default)]
    pub background: [f32; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CameraSet {
    pub input: Vec<Camera>,
    pub supervision: Vec<Camera>,
    pub video: Option<Camera>,
}

fn io(path: &Path, e: impl std::fmt::Display) -> DataError {
    DataError::Engine(velox_engine::Error::file(path, velox_engine::FileOp::Read, e))
}

fn write_error(path: &Path, e: impl std::fmt::Display) -> DataError {
    DataError::Engine(velox_engine::Error::file(path, velox_engine::FileOp::Write, e))
}

/// Writes a file of a scene being made. These are not written atomically: they go into the
/// scene's `.partial` folder, which is renamed to the scene's name only when every file is
/// complete, so a failed or interrupted write never leaves a half scene under its name.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> DataResult<()> {
    std::fs::write(path, bytes).map_err(|e| write_error(path, e))
}

/// What to tell whoever made a scene, beside its files: fewer tracks than the `asked` (frame 0
/// shows too little surface over the input views to place them), and, as a warning, a scene
/// the tracking task cannot use because the video camera sees no surface at frame 0 (a flat
/// model seen edge-on from +x, say): `velox track` and `velox eval tracking` then have no
/// query to follow in it.
pub fn scene_notes(meta: &SceneMeta, asked: usize) -> Vec<(Severity, String)> {
    let mut notes = Vec::new();
    if meta.tracks < asked {
        notes.push((
            Severity::Note,
            format!(
                "{} tracks of the {asked} asked for: frame 0 shows only {} surface pixels over the input views",
                meta.tracks, meta.tracks
            ),
        ));
    }
    if asked > 0 && meta.video_tracks == 0 {
        notes.push((
            Severity::Warning,
            "the video camera (on +x, looking at the origin) sees no surface at frame 0, so the scene has \
             no tracking queries: velox track and eval tracking have nothing to follow in it (a flat \
             model seen edge-on does this; turn it in its file)"
                .to_string(),
        ));
    } else if meta.video_tracks < asked {
        notes.push((
            Severity::Note,
            format!(
                "{} tracking queries of the {asked} asked for: the video camera sees only {} surface pixels at frame 0",
                meta.video_tracks, meta.video_tracks
            ),
        ));
    }
    notes
}

/// How much a [`scene_notes`] entry matters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Severity {
    /// Worth knowing; the scene serves every task.
    Note,
    /// A task cannot use the scene.
    Warning,
}

/// Renders `mesh` into the scene folder `dir` (through `dir.partial`, renamed when complete, so
/// a crash never leaves a half scene under the scene's name). `source` names where the mesh
/// came from (a recipe, or a glTF file whose credits are `detail`); `progress` is called after
/// each frame.
#[allow(clippy::too_many_arguments)]
pub fn write_scene(
    gpu: &velox_engine::Gpu,
    mesh: &crate::mesh::AnimatedMesh,
    source: &str,
    detail: Option<String>,
    seed: u64,
    opts: &crate::pipeline::SynthOptions,
    dir: &Path,
    progress: &mut dyn FnMut(usize),
) -> DataResult<SceneMeta> {
    let partial = partial_dir(dir);
    let _ = std::fs::remove_dir_all(&partial);
    let arrays = crate::pipeline::render_scene(gpu, mesh, opts, seed, Some(&partial), progress)?;
    let is_gltf = source.ends_with(".gltf") || source.ends_with(".glb");
    let meta = SceneMeta {
        format: FORMAT.into(),
        source: match (&detail, is_gltf) {
            (Some(d), false) => format!("{source}: {d}"),
            _ => source.to_string(),
        },
        credits: if is_gltf { detail } else { None },
        frames: FRAMES,
        fps: FPS,
        resolution: opts.res,
        points: arrays.points.len(),
        tracks: arrays.tracks.len(),
        video_tracks: arrays.video_tracks.len(),
        supervision_views: arrays.supervision_cameras.len(),
        supersample: opts.supersample,
        background: opts.background,
    };
    write_arrays(&partial, &meta, &arrays)?;
    let _ = std::fs::remove_dir_all(dir);
    std::fs::rename(&partial, dir).map_err(|e| {
        DataError::Io(format!("cannot rename {} to {}: {e}", partial.display(), dir.display()))
    })?;
    Ok(meta)
}

/// The folder a scene is rendered into before it is complete.
pub fn partial_dir(dir: &Path) -> PathBuf {
    let mut name = dir.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    dir.with_file_name(name)
}

/// Writes the arrays and metadata of a scene into `dir` (images are already there).
pub fn write_arrays(dir: &Path, meta: &SceneMeta, a: &SceneArrays) -> DataResult<()> {
    std::fs::create_dir_all(dir).map_err(|e| write_error(dir, e))?;
    write_file(&dir.join("meta.json"), json(meta).as_bytes())?;
    let cams = CameraSet {
        input: a.input_cameras.clone(),
        supervision: a.supervision_cameras.clone(),
        video: a.video_camera,
    };
    write_file(&dir.join("cameras.json"), json(&cams).as_bytes())?;
    write_ply(&dir.join("points.ply"), &a.points)?;
    write_file(&dir.join("occupancy.bin"), bytemuck::cast_slice(&a.occupancy))?;
    let tracks: Vec<f32> = a.tracks.iter().flatten().flatten().copied().collect();
    write_file(&dir.join("tracks.bin"), bytemuck::cast_slice(&tracks))?;
    let vis: Vec<u64> = a.visibility.iter().flatten().copied().collect();
    write_file(&dir.join("tracks_visibility.bin"), bytemuck::cast_slice(&vis))?;
    let video: Vec<f32> = a.video_tracks.iter().flatten().flatten().copied().collect();
    write_file(&dir.join("video_tracks.bin"), bytemuck::cast_slice(&video))?;
    let seen: Vec<u8> = a.video_visibility.iter().flatten().map(|&v| v as u8).collect();
    write_file(&dir.join("video_tracks_visibility.bin"), &seen)?;
    Ok(())
}

fn json<T: Serialize>(v: &T) -> String {
    serde_json::to_string_pretty(v).expect("plain data serialises")
}

const PLY_PROPS: [&str; 7] = ["x", "y", "z", "r", "g", "b", "tau"];

fn ply_header(n: usize) -> String {
    let mut h = format!(
        "ply\nformat binary_little_endian 1.0\ncomment velox 4D colour point cloud\nelement vertex {n}\n"
    );
    for p in PLY_PROPS {
        h.push_str(&format!("property float {p}\n"));
    }
    h.push_str("end_header\n");
    h
}

pub fn write_ply(path: &Path, points: &[[f32; 7]]) -> DataResult<()> {
    let file = std::fs::File::create(path).map_err(|e| write_error(path, e))?;
    let mut w = std::io::BufWriter::new(file);
    w.write_all(ply_header(points.len()).as_bytes()).map_err(|e| write_error(path, e))?;
    w.write_all(bytemuck::cast_slice(points)).map_err(|e| write_error(path, e))?;
    w.flush().map_err(|e| write_error(path, e))
}

/// The 4D colour cloud of a scene folder (its `points.ply`), of a PLY file of float `x y z r
/// g b tau` ([`read_ply`] validates it), or of a video folder (`camera.json` and RGBD frames,
/// as `velox import rgbd` and `velox import video` write them: back-projected by
/// [`crate::rgbd::rgbd_cloud`], at most [`crate::rgbd::DEFAULT_POINTS`] of its pixels, seed 0),
/// as host rows of 7. A capture imported in windows is refused with the windows' names: each
/// is a 24-frame clip of its own.
pub fn read_cloud(path: &Path) -> DataResult<Vec<f32>> {
    if path.is_dir() && !path.join("points.ply").exists() {
        if path.join("camera.json").exists() {
            let video = crate::rgbd::read_video_folder(path)?;
            let cloud = crate::rgbd::rgbd_cloud(&video, crate::rgbd::DEFAULT_POINTS, 0)?;
            return Ok(cloud.iter().flatten().copied().collect());
        }
        if path.join("window_000").is_dir() {
            let windows = std::fs::read_dir(path)
                .map_err(|e| io(path, e))?
                .filter_map(|e| e.ok()?.file_name().into_string().ok())
                .filter(|n| n.starts_with("window_"))
                .count();
            return Err(DataError::Invalid(format!(
                "{} holds a capture imported in {windows} windows of 24 frames: give one window \
                 ({}/window_000 to window_{:03}), each a clip of its own (velox decode takes the \
                 whole folder, window by window)",
                path.display(),
                path.display(),
                windows.saturating_sub(1)
            )));
        }
    }
    let file = if path.is_dir() { path.join("points.ply") } else { path.to_path_buf() };
    Ok(read_ply(&file)?.iter().flatten().copied().collect())
}

/// Reads a PLY written by [`write_ply`]: one `vertex` element of float x y z r g b tau,
/// binary little-endian, a body of exactly the declared points, every point as the format
/// says (see [`check_points`]).
pub fn read_ply(path: &Path) -> DataResult<Vec<[f32; 7]>> {
    let invalid = |why: String| DataError::Invalid(format!("{}: {why}", path.display()));
    let bytes = std::fs::read(path).map_err(|e| io(path, e))?;
    let header = ply::Header::parse(&bytes).map_err(|e| invalid(engine_message(e)))?;
    let layout_ok = matches!(header.elements.as_slice(), [e] if e.name == "vertex"
        && e.properties.len() == PLY_PROPS.len()
        && e.properties.iter().zip(PLY_PROPS).all(|((name, ty), want)| name == want && *ty == ply::Scalar::F32));
    if !layout_ok {
        return Err(invalid("PLY layout is not one vertex element of float x y z r g b tau".into()));
    }
    header.check_length(&bytes).map_err(|e| invalid(engine_message(e)))?;
    let points: Vec<[f32; 7]> = bytes[header.body_start..]
        .chunks_exact(28)
        .map(|c| std::array::from_fn(|k| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap())))
        .collect();
    check_points(&points).map_err(invalid)?;
    Ok(points)
}

/// The message of an engine error without its kind.
fn engine_message(e: velox_engine::Error) -> String {
    match e {
        velox_engine::Error::Invalid(why) => why,
        other => other.to_string(),
    }
}

/// Checks the points of a cloud against the format: at least one, every value finite, xyz in
/// [-1, 1]^3 and rgb in [0, 1] (the model's cloud check), tau = frame / 100 for a frame of the
/// clip.
pub fn check_points(points: &[[f32; 7]]) -> Result<(), String> {
    velox_io::cloud::validate(bytemuck::cast_slice(points)).map_err(engine_message)?;
    for (i, p) in points.iter().enumerate() {
        let f = p[6] * FPS;
        if f.round() >= FRAMES as f32 || (f - f.round()).abs() > 1e-3 {
            return Err(format!(
                "point {i} has frame time tau = {}, not frame / {FPS} for a frame 0 to {}",
                p[6],
                FRAMES - 1
            ));
        }
    }
    Ok(())
}

/// A scene read back from disk.
#[derive(Clone, Debug)]
pub struct Scene {
    pub dir: PathBuf,
    pub meta: SceneMeta,
    pub cameras: CameraSet,
    pub points: Vec<[f32; 7]>,
    pub occupancy: Vec<u64>,
    pub tracks: Vec<[[f32; 3]; FRAMES]>,
    pub visibility: Vec<[u64; FRAMES]>,
    /// The tracking task's queries in every frame, and whether the video camera sees each.
    pub video_tracks: Vec<[[f32; 3]; FRAMES]>,
    pub video_visibility: Vec<[bool; FRAMES]>,
    /// Supervision images, frame-major then view, 8-bit RGB rows (empty unless asked for).
    pub supervision: Vec<Vec<u8>>,
    /// The conditioning video's frames, 8-bit RGB rows (empty unless asked for).
    pub video: Vec<Vec<u8>>,
}

impl Scene {
    /// Whether voxel `index` (x + 64 (y + 64 z)) is occupied at frame `f`.
    pub fn occupied(&self, f: usize, index: usize) -> bool {
        self.occupancy[f * OCCUPANCY_WORDS + index / 64] >> (index % 64) & 1 == 1
    }
}

/// A scene folder's cameras (`cameras.json`).
pub fn read_cameras(dir: &Path) -> DataResult<CameraSet> {
    read_json(&dir.join("cameras.json"))
}

pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> DataResult<T> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    serde_json::from_str(&text)
        .map_err(|e| DataError::Engine(velox_engine::Error::file(path, velox_engine::FileOp::Content, e)))
}

/// Reads `count` little-endian words of `T` from `path`, whose size must be exactly that
/// (`what` says what the words are, for the error).
fn read_words<T: bytemuck::Pod>(path: &Path, count: usize, what: &str) -> DataResult<Vec<T>> {
    let size = std::mem::size_of::<T>();
    let len = std::fs::metadata(path).map_err(|e| io(path, e))?.len();
    let expected = count.checked_mul(size).map(|b| b as u64);
    if expected != Some(len) {
        return Err(DataError::Invalid(format!(
            "{}: {len} bytes, expected {} ({what})",
            path.display(),
            expected.map_or("more than any file holds".into(), |b| b.to_string()),
        )));
    }
    let bytes = std::fs::read(path).map_err(|e| io(path, e))?;
    if bytes.len() as u64 != len {
        return Err(DataError::Io(format!("{}: the file changed while it was read", path.display())));
    }
    Ok(bytes.chunks_exact(size).map(bytemuck::pod_read_unaligned).collect())
}

fn read_png(path: &Path, res: u32) -> DataResult<Vec<u8>> {
    let img = image::open(path).map_err(|e| io(path, e))?.to_rgb8();
    if img.dimensions() != (res, res) {
        return Err(DataError::Invalid(format!("{}: image is not {res} x {res}", path.display())));
    }
    Ok(img.into_raw())
}

/// Checks a scene's `meta.json` against the format and the writer's limits.
fn check_meta(meta: &SceneMeta) -> Result<(), String> {
    if meta.format != FORMAT {
        return Err(format!("format {:?}, expected {FORMAT:?}", meta.format));
    }
    if meta.frames != FRAMES || meta.fps != FPS {
        return Err(format!("{} frames at {} fps, expected {FRAMES} at {FPS}", meta.frames, meta.fps));
    }
    let in_range = |name: &str, v: usize, lo: usize, hi: usize| {
        if (lo..=hi).contains(&v) {
            Ok(())
        } else {
            Err(format!("{name} is {v}, expected {lo} to {hi}"))
        }
    };
    in_range("resolution", meta.resolution as usize, 1, MAX_RESOLUTION as usize)?;
    in_range("supersample", meta.supersample as usize, 1, MAX_SUPERSAMPLE as usize)?;
    in_range("points", meta.points, 1, MAX_POINTS)?;
    in_range("tracks", meta.tracks, 0, MAX_TRACKS)?;
    in_range("video_tracks", meta.video_tracks, 0, MAX_TRACKS)?;
    in_range("supervision_views", meta.supervision_views, 1, MAX_SUPERVISION_VIEWS)?;
    if meta.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
        return Err(format!("background {:?}: each channel must lie in [0, 1]", meta.background));
    }
    Ok(())
}

/// Checks the cameras of a scene: the counts the format and `meta` give, finite values, a
/// rotation, positive focal lengths and the scene's resolution.
fn check_cameras(cams: &CameraSet, meta: &SceneMeta) -> Result<(), String> {
    if cams.input.len() != NUM_INPUT_CAMERAS {
        return Err(format!("{} input cameras, expected {NUM_INPUT_CAMERAS}", cams.input.len()));
    }
    if cams.supervision.len() != meta.supervision_views {
        return Err(format!(
            "{} supervision cameras, but meta.json says supervision_views = {}",
            cams.supervision.len(),
            meta.supervision_views
        ));
    }
    let named = cams.input.iter().enumerate().map(|(i, c)| (format!("input camera {i}"), c));
    let named =
        named.chain(cams.supervision.iter().enumerate().map(|(i, c)| (format!("supervision camera {i}"), c)));
    for (name, c) in named.chain(cams.video.iter().map(|c| ("the video camera".to_string(), c))) {
        check_camera(&name, c)?;
        if c.width != meta.resolution || c.height != meta.resolution {
            return Err(format!(
                "{name} is {} x {}, the scene's resolution is {}",
                c.width, c.height, meta.resolution
            ));
        }
    }
    Ok(())
}

/// Checks one camera (`name` for the message): finite values, a rotation, positive focal
/// lengths, an image of at least a pixel.
pub(crate) fn check_camera(name: &str, c: &Camera) -> Result<(), String> {
    let values = c.rotation.iter().flatten().chain(&c.translation).chain([&c.cx, &c.cy]);
    if values.clone().any(|v| !v.is_finite()) {
        return Err(format!("{name} has a non-finite rotation, translation or principal point"));
    }
    let r = &c.rotation;
    let orthonormal = (0..3).all(|i| {
        (0..3).all(|j| {
            let d: f32 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
            (d - (i == j) as u8 as f32).abs() < 1e-3
        })
    });
    if !orthonormal {
        return Err(format!("{name}: the rotation {r:?} is not a rotation matrix"));
    }
    if !(c.fx.is_finite() && c.fx > 0.0 && c.fy.is_finite() && c.fy > 0.0) {
        return Err(format!(
            "{name}: focal lengths fx = {}, fy = {} must be positive and finite",
            c.fx, c.fy
        ));
    }
    if c.width == 0 || c.height == 0 {
        return Err(format!("{name}: an image of {} x {} pixels", c.width, c.height));
    }
    Ok(())
}

/// Reads the scene in `dir`; images too when `images` is set. Everything is checked against
/// the format first: counts against each other and against the files' sizes, cameras, points,
/// tracks and visibility bits; a scene that breaks a rule is an error naming the file.
pub fn read_scene(dir: &Path, images: bool) -> DataResult<Scene> {
    let invalid =
        |file: &str, why: String| DataError::Invalid(format!("{}: {why}", dir.join(file).display()));
    let meta = read_meta(dir)?;
    let cameras = read_cameras(dir)?;
    check_cameras(&cameras, &meta).map_err(|why| invalid("cameras.json", why))?;
    let points = read_ply(&dir.join("points.ply"))?;
    if points.len() != meta.points {
        return Err(invalid(
            "points.ply",
            format!("{} points, but meta.json says points = {}", points.len(), meta.points),
        ));
    }
    let occupancy = read_occupancy_words(dir)?;
    let tracks = read_positions(dir, "tracks.bin", meta.tracks)?;
    let vis_what = format!("{} tracks, as meta.json says, x {FRAMES} frames x 1 u64", meta.tracks);
    let vis = read_words::<u64>(&dir.join("tracks_visibility.bin"), meta.tracks * FRAMES, &vis_what)?;
    if let Some(i) = vis.iter().position(|&bits| bits >> NUM_INPUT_CAMERAS != 0) {
        return Err(invalid(
            "tracks_visibility.bin",
            format!(
                "track {} at frame {} is seen by camera {}, there are {NUM_INPUT_CAMERAS} input cameras",
                i / FRAMES,
                i % FRAMES,
                63 - vis[i].leading_zeros()
            ),
        ));
    }
    let visibility = vis.chunks_exact(FRAMES).map(|c| std::array::from_fn(|f| c[f])).collect();
    let (video_tracks, video_visibility) = read_video_tracks_of(dir, &meta)?;
    let (mut supervision, mut video) = (Vec::new(), Vec::new());
    if images {
        for f in 0..FRAMES {
            for v in 0..meta.supervision_views {
                supervision
                    .push(read_png(&dir.join(format!("supervision/f{f:02}_v{v:02}.png")), meta.resolution)?);
            }
            video.push(read_png(&dir.join(format!("video/f{f:02}.png")), meta.resolution)?);
        }
    }
    Ok(Scene {
        dir: dir.to_path_buf(),
        meta,
        cameras,
        points,
        occupancy,
        tracks,
        visibility,
        video_tracks,
        video_visibility,
        supervision,
        video,
    })
}

/// A scene's video tracks (every frame of each) and whether its video camera sees each.
pub type VideoTracks = (Vec<[[f32; 3]; FRAMES]>, Vec<[bool; FRAMES]>);

/// The tracking task's queries of the scene in `dir` in every frame, and whether its video
/// camera sees each, as [`read_scene`] reads them (`meta.json` checked first), without the
/// rest of the scene: what the tracker trains on beside stored tokens.
pub fn read_video_tracks(dir: &Path) -> DataResult<VideoTracks> {
    read_video_tracks_of(dir, &read_meta(dir)?)
}

/// Scenes written before the tracking task have neither file (and `video_tracks` = 0).
fn read_video_tracks_of(dir: &Path, meta: &SceneMeta) -> DataResult<VideoTracks> {
    if meta.video_tracks == 0 {
        return Ok((Vec::new(), Vec::new()));
    }
    let tracks = read_positions(dir, "video_tracks.bin", meta.video_tracks)?;
    let what = format!("{} video tracks, as meta.json says, x {FRAMES} frames x 1 byte", meta.video_tracks);
    let file = dir.join("video_tracks_visibility.bin");
    let seen = read_words::<u8>(&file, meta.video_tracks * FRAMES, &what)?;
    if let Some(i) = seen.iter().position(|&b| b > 1) {
        return Err(DataError::Invalid(format!(
            "{}: video track {} at frame {} has byte {}, not 0 or 1",
            file.display(),
            i / FRAMES,
            i % FRAMES,
            seen[i]
        )));
    }
    Ok((tracks, seen.chunks_exact(FRAMES).map(|c| std::array::from_fn(|f| c[f] == 1)).collect()))
}

/// `count` tracks of [`FRAMES`] positions from `file` in `dir` (`count` at most
/// [`MAX_TRACKS`], so the sizes do not overflow), every coordinate in [-1, 1].
fn read_positions(dir: &Path, file: &str, count: usize) -> DataResult<Vec<[[f32; 3]; FRAMES]>> {
    let what = format!("{count} tracks, as meta.json says, x {FRAMES} frames x 3 f32");
    let flat = read_words::<f32>(&dir.join(file), count * FRAMES * 3, &what)?;
    if let Some(i) = flat.iter().position(|v| !(v.is_finite() && v.abs() <= 1.0 + TRACK_SLACK)) {
        return Err(DataError::Invalid(format!(
            "{}: track {} at frame {} has coordinate {}, outside [-1, 1]",
            dir.join(file).display(),
            i / (3 * FRAMES),
            i / 3 % FRAMES,
            flat[i]
        )));
    }
    Ok(flat
        .chunks_exact(3 * FRAMES)
        .map(|c| std::array::from_fn(|f| [c[3 * f], c[3 * f + 1], c[3 * f + 2]]))
        .collect())
}

/// A scene's `meta.json`, read and checked against the format.
pub fn read_meta(dir: &Path) -> DataResult<SceneMeta> {
    let path = dir.join("meta.json");
    let meta: SceneMeta = read_json(&path)?;
    check_meta(&meta).map_err(|why| DataError::Invalid(format!("{}: {why}", path.display())))?;
    Ok(meta)
}

fn read_occupancy_words(dir: &Path) -> DataResult<Vec<u64>> {
    read_words::<u64>(&dir.join("occupancy.bin"), FRAMES * OCCUPANCY_WORDS, "24 frames of 4096 u64 words")
}

/// A scene's occupancy alone, as [`read_scene`] reads it (`meta.json` checked first), without
/// its points, tracks or images: what the voxel decoder trains on beside stored tokens.
pub fn read_occupancy(dir: &Path) -> DataResult<Vec<u64>> {
    read_meta(dir)?;
    read_occupancy_words(dir)
}

/// The complete scenes under `root` (folders with a `meta.json`, `.partial` ones skipped), in
/// name order.
pub fn list_scenes(root: &Path) -> DataResult<Vec<PathBuf>> {
    let read = std::fs::read_dir(root).map_err(|e| io(root, e))?;
    let mut dirs: Vec<PathBuf> = read
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("meta.json").is_file() && p.extension().is_none_or(|e| e != "partial"))
        .collect();
    dirs.sort();
    Ok(dirs)
}

/// [`list_scenes`], where none is an error that says how to make some.
pub fn list_some_scenes(root: &Path) -> DataResult<Vec<PathBuf>> {
    let dirs = list_scenes(root)?;
    if dirs.is_empty() {
        return Err(DataError::Invalid(format!(
            "{} holds no scenes (folders with a meta.json); make some with `velox data synth`",
            root.display()
        )));
    }
    Ok(dirs)
}
