/*
 * velox view: the browser side of the local viewer for per-frame (4D) 3D Gaussians.
 *
 * What it does, top to bottom of this file:
 *   1. Constants: the project's rasteriser rules (engine/src/ops/raster), which the picture
 *      must match (EWA splatting, 0.3 px^2 dilation, alpha from 1/255 to 0.99, front-to-back
 *      blending over the background).
 *   2. Camera maths: the manifest's pinhole camera (x_c = R x_w + t, y down, z forward) and
 *      the user's orbit, pan and zoom around a target point.
 *   3. Loading: the manifest (manifest.json, or embedded in the page as
 *      <script id="velox-manifest" type="application/json">), the frames (binary
 *      "VXG1" + u32 count + count x 13 float32) of the main pane and of the optional
 *      compare pane, cached once decoded, and the optional tracks ("VXT1", see parseTracks).
 *      Each is fetched by relative URL, or, when its url is "#ID", read as base64 from the
 *      page's <script id="ID" type="application/octet-stream"> element.
 *   4. Depth sort: a stable radix sort of camera-space depths on the CPU (nearest first,
 *      ties by index, as the engine orders its tiles).
 *   5. WebGL2 renderer: per-Gaussian data in a float texture, the blending order in an
 *      integer texture, one quad (two triangles) per Gaussian over its footprint, the EWA
 *      projection in the vertex shader, alpha from the conic in the fragment shader,
 *      front-to-back blending into a float target, and a last pass that adds the
 *      background where light is left. Then the overlay: tracks as lines and dots.
 *   6. The page: one or two panes (the main one, and the compare one beside it when the
 *      manifest has `compare`; both show the same view and clip frame, each with its own
 *      canvas, WebGL2 context and renderer), the tracks over the main pane, controls
 *      (#frame, #play, #speed, #cameras, #reset, #show-compare, #show-tracks), status and
 *      errors, mouse handling, playback, the URL hash (camera=I, frame=K, play=1, ui=0,
 *      pane=compare, tracks=0|1, bench=1) and the data-* attributes tests read
 *      (data-frame, data-drawn, data-error, data-compare-frame, data-tracks).
 *
 * Plain ES2020 and WebGL2, no libraries, no requests but the page's own relative URLs.
 * This file must not contain the character sequence that closes a script element, so that
 * it can be inlined into a self-contained page.
 */
(() => {
  'use strict';

  // ---------------------------------------------------------------------------------------
  // 1. Constants
  // ---------------------------------------------------------------------------------------

  /** The rasteriser's rules, as engine/src/ops/raster/mod.rs defines them. */
  const NEAR = 0.01; // camera-space depth below which a Gaussian is dropped
  const MIN_ALPHA = 1 / 255; // faintest alpha drawn, and faintest opacity kept
  const ALPHA_MAX = 0.99; // alpha is clamped to this
  const DILATION = 0.3; // added to the 2D covariance's diagonal, in px^2
  const MIN_DET = 1e-6; // 2D covariances with a smaller determinant are dropped

  /** A frame body: "VXG1", u32 count, then count records of 13 float32; then, for Gaussians
   * with higher spherical harmonics, "VXS1", u32 degree (1 to 3) and count x 3K float32 (K =
   * (degree + 1)^2 - 1: each Gaussian's K red, K green and K blue coefficients, as the PLY
   * stores them). */
  const MAGIC = 'VXG1';
  const HEADER_BYTES = 8;
  const FLOATS_PER_GAUSSIAN = 13; // mean xyz, covariance xx xy xz yy yz zz, opacity, rgb
  const RECORD_BYTES = 4 * FLOATS_PER_GAUSSIAN;
  const OPACITY = 9; // offset of the opacity in a record

  /** Smallest on-screen side a render is enlarged towards (by whole factors), in CSS pixels;
   * smaller when two panes share the screen. */
  const DISPLAY_SIDE = 512;
  const DISPLAY_SIDE_TWO_PANES = 384;

  /** Tracks: "VXT1", u32 tracks, u32 frames, then positions (float32 xyz), visibility (u8). */
  const TRACKS_MAGIC = 'VXT1';
  const TRACKS_HEADER_BYTES = 12;
  const HIDDEN_TRACK_ALPHA = 0.35; // opacity of a track where it is hidden
  const TRACK_DOT_PIXELS = 5; // diameter of the dot at the current frame on a 256-pixel render
  const TRACK_DOT_MIN_PIXELS = 2; // ... and the least on a small one

  /** Playback: frames per second at 1x, and how many frames ahead are fetched. */
  const FRAMES_PER_SECOND = 10;
  const PREFETCH = 2;

  /** The view used when the manifest has no cameras (and `velox render`'s default orbit). */
  const DEFAULT_VIEW = { width: 512, height: 512, fovDeg: 50, elevationDeg: 20, distance: 2.5 };

  /** Mouse sensitivity: a drag across the whole canvas turns the view by half a turn. */
  const ORBIT_PER_CANVAS = Math.PI;
  const ZOOM_PER_WHEEL_PIXEL = 0.0015;

  const LITTLE_ENDIAN_HOST = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

  // ---------------------------------------------------------------------------------------
  // 2. Camera maths
  //
  // A camera is the manifest's object: {name, width, height, fx, fy, cx, cy, rotation,
  // translation}, rotation being the world-to-camera matrix as three rows (the camera's x,
  // y and z axes in world coordinates) and x_c = R x_w + t.
  // ---------------------------------------------------------------------------------------

  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const length = (a) => Math.sqrt(dot(a, a));
  const normalise = (a) => scale(a, 1 / length(a));
  /** m v for a 3x3 matrix given as rows. */
  const matVec = (m, v) => [dot(m[0], v), dot(m[1], v), dot(m[2], v)];

  /** The rotation by `angle` radians about the unit vector `axis` (Rodrigues), as rows. */
  function rotationAbout(axis, angle) {
    const [x, y, z] = axis;
    const c = Math.cos(angle);
    const s = Math.sin(angle);
    const k = 1 - c;
    return [
      [c + x * x * k, x * y * k - z * s, x * z * k + y * s],
      [y * x * k + z * s, c + y * y * k, y * z * k - x * s],
      [z * x * k - y * s, z * y * k + x * s, c + z * z * k],
    ];
  }

  /**
   * The world axis (+-x, +-y or +-z) nearest to `v`: a scene camera's up (-y) direction
   * tilts with its pitch, so the orbit turns about the world axis it is closest to (y for
   * velox scenes, -y for COLMAP ones).
   */
  function nearestAxis(v) {
    const k = [0, 1, 2].reduce((best, i) => (Math.abs(v[i]) > Math.abs(v[best]) ? i : best), 0);
    const axis = [0, 0, 0];
    axis[k] = Math.sign(v[k]) || 1;
    return axis;
  }

  /** The camera centre in world coordinates: -R^T t. */
  function cameraEye(cam) {
    const [r0, r1, r2] = cam.rotation;
    const t = cam.translation;
    return [0, 1, 2].map((k) => -(r0[k] * t[0] + r1[k] * t[1] + r2[k] * t[2]));
  }

  /** The same intrinsics at a new pose (axes as rows, re-orthonormalised; eye in world). */
  function withPose(cam, axes, eye) {
    const x = normalise(axes[0]);
    const y = normalise(sub(axes[1], scale(x, dot(axes[1], x))));
    const z = cross(x, y);
    const rotation = [x, y, z];
    return { ...cam, rotation, translation: scale(matVec(rotation, eye), -1) };
  }

  /** Turns the camera about `pivot` by the world rotation `q` (rows). */
  function rotateAround(cam, pivot, q) {
    const eye = add(pivot, matVec(q, sub(cameraEye(cam), pivot)));
    return withPose(cam, cam.rotation.map((axis) => matVec(q, axis)), eye);
  }

  /**
   * Orbit: `yaw` about the world `up` axis through `target`, then `pitch` about the camera's
   * x axis (a positive pitch raises the camera). Pitch stops short of looking along `up`.
   */
  function orbit(cam, target, up, yaw, pitch) {
    let out = rotateAround(cam, target, rotationAbout(up, yaw));
    const tilted = rotateAround(out, target, rotationAbout(out.rotation[0], -pitch));
    if (Math.abs(dot(tilted.rotation[2], up)) < 0.995) out = tilted;
    return out;
  }

  /** Zoom: the camera moves towards (factor < 1) or away from the target. */
  function zoom(cam, target, factor) {
    const eye = add(target, scale(sub(cameraEye(cam), target), factor));
    return withPose(cam, cam.rotation, eye);
  }

  /**
   * Pan by (dx, dy) pixels: camera and target move together so that the target's depth
   * plane follows the mouse. Returns the new camera and target.
   */
  function pan(cam, target, dx, dy) {
    const eye = cameraEye(cam);
    const depth = dot(cam.rotation[2], target) + cam.translation[2];
    const d = depth > 1e-6 ? depth : length(sub(target, eye));
    const shift = add(scale(cam.rotation[0], (-dx * d) / cam.fx), scale(cam.rotation[1], (-dy * d) / cam.fy));
    return { camera: withPose(cam, cam.rotation, add(eye, shift)), target: add(target, shift) };
  }

  /** The engine's Camera::look_at: z towards the target, x = z cross up, y = z cross x. */
  function lookAtAxes(eye, target, up) {
    const z = normalise(sub(target, eye));
    const x = normalise(cross(z, up));
    return [x, cross(z, x), z];
  }

  /**
   * The view when the manifest has no cameras: looking at `target` from 2.5 bounding radii,
   * from azimuth 0 and 20 degrees up (y up), fov 50 degrees, 512 x 512.
   */
  function defaultCamera(target, radius) {
    const { width, height, fovDeg, elevationDeg, distance } = DEFAULT_VIEW;
    const f = (0.5 * height) / Math.tan((0.5 * fovDeg * Math.PI) / 180);
    const el = (elevationDeg * Math.PI) / 180;
    const eye = add(target, scale([0, Math.sin(el), Math.cos(el)], distance * radius));
    const base = { name: 'default view', width, height, fx: f, fy: f, cx: 0.5 * width, cy: 0.5 * height };
    return withPose(base, lookAtAxes(eye, target, [0, 1, 0]), eye);
  }

  /** The limits of x/z and y/z in the projection's Jacobian (as the engine clamps them). */
  function jacobianLimits(cam) {
    const tanX = (0.5 * cam.width) / cam.fx;
    const tanY = (0.5 * cam.height) / cam.fy;
    return [
      -(cam.cx / cam.fx + 0.3 * tanX),
      (cam.width - cam.cx) / cam.fx + 0.3 * tanX,
      -(cam.cy / cam.fy + 0.3 * tanY),
      (cam.height - cam.cy) / cam.fy + 0.3 * tanY,
    ];
  }

  // ---------------------------------------------------------------------------------------
  // 3. Loading the manifest and the frames
  // ---------------------------------------------------------------------------------------

  /** fetch() that turns an HTTP error into an Error with its status and body text (the caller
   * names the URL). */
  async function fetchOk(url) {
    let response;
    try {
      response = await fetch(url);
    } catch (e) {
      const hint = location.protocol === 'file:' ? ' (a page opened as a file cannot fetch; use `velox view`)' : '';
      throw new Error(`the request failed: ${e.message}${hint}`);
    }
    if (!response.ok) {
      const body = (await response.text().catch(() => '')).trim();
      throw new Error(`HTTP ${response.status} ${response.statusText}${body ? `\n${body}` : ''}`);
    }
    return response;
  }

  /** The manifest: embedded in the page when it has #velox-manifest, else manifest.json. */
  async function loadManifest() {
    const embedded = document.getElementById('velox-manifest');
    const source = embedded ? 'the embedded manifest' : 'manifest.json';
    let text;
    try {
      text = embedded ? embedded.textContent : await (await fetchOk('manifest.json')).text();
    } catch (e) {
      throw new Error(`${source}: ${e.message}`);
    }
    let json;
    try {
      json = JSON.parse(text);
    } catch (e) {
      throw new Error(`${source} is not valid JSON: ${e.message}`);
    }
    return checkManifest(json, source);
  }

  /** Checks the manifest's shape and fills the optional fields. */
  function checkManifest(m, source) {
    if (!m || typeof m !== 'object') throw new Error(`${source} is not a JSON object`);
    if (!Array.isArray(m.frames) || m.frames.length === 0) throw new Error(`${source} lists no frames`);
    m.frames.forEach((f, k) => {
      if (!f || typeof f.url !== 'string') throw new Error(`${source}: frames[${k}] has no url`);
    });
    const cameras = (m.cameras || []).map((c, i) => checkCamera(c, `${source}: cameras[${i}]`));
    const bg = Array.isArray(m.background) && m.background.length === 3 ? m.background.map(Number) : [0, 0, 0];
    return {
      title: String(m.title || 'velox view'),
      frames: m.frames,
      cameras,
      background: bg,
      compare: checkCompare(m.compare, source),
      tracks: checkTracks(m.tracks, source),
    };
  }

  /** The optional `compare`: null, or {title, frames} with frames listed as the main ones. */
  function checkCompare(c, source) {
    if (c === null || c === undefined) return null;
    if (typeof c !== 'object' || !Array.isArray(c.frames)) throw new Error(`${source}: compare lists no frames`);
    c.frames.forEach((f, k) => {
      if (!f || typeof f.url !== 'string') throw new Error(`${source}: compare.frames[${k}] has no url`);
    });
    return { title: String(c.title || 'compare'), frames: c.frames };
  }

  /** The optional `tracks`: null, or {url, count, frames} (the numbers may be absent). */
  function checkTracks(t, source) {
    if (t === null || t === undefined) return null;
    if (typeof t !== 'object' || typeof t.url !== 'string') throw new Error(`${source}: tracks has no url`);
    return { url: t.url, count: t.count, frames: t.frames };
  }

  function checkCamera(c, label) {
    const finite = (v) => typeof v === 'number' && Number.isFinite(v);
    const ok =
      c &&
      Number.isInteger(c.width) && c.width > 0 &&
      Number.isInteger(c.height) && c.height > 0 &&
      [c.fx, c.fy, c.cx, c.cy].every(finite) &&
      Array.isArray(c.rotation) && c.rotation.length === 3 &&
      c.rotation.every((row) => Array.isArray(row) && row.length === 3 && row.every(finite)) &&
      Array.isArray(c.translation) && c.translation.length === 3 && c.translation.every(finite);
    if (!ok) throw new Error(`${label} is not a camera (width, height, fx, fy, cx, cy, rotation, translation)`);
    return {
      name: String(c.name ?? label),
      width: c.width,
      height: c.height,
      fx: c.fx,
      fy: c.fy,
      cx: c.cx,
      cy: c.cy,
      rotation: c.rotation.map((row) => row.slice()),
      translation: c.translation.slice(),
    };
  }

  /** Base64 to bytes; characters outside the alphabet (whitespace, padding) are skipped. */
  function decodeBase64(text) {
    const alphabet = 'ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/';
    const value = new Int8Array(128).fill(-1);
    for (let i = 0; i < 64; i++) value[alphabet.charCodeAt(i)] = i;
    const out = new Uint8Array(Math.floor((text.length * 3) / 4));
    let bits = 0;
    let nbits = 0;
    let n = 0;
    for (let i = 0; i < text.length; i++) {
      const code = text.charCodeAt(i);
      const v = code < 128 ? value[code] : -1;
      if (v < 0) continue;
      bits = ((bits << 6) | v) & 0xffffff;
      nbits += 6;
      if (nbits >= 8) {
        nbits -= 8;
        out[n++] = (bits >> nbits) & 0xff;
      }
    }
    return out.slice(0, n);
  }

  /**
   * The bytes at `url`: fetched by relative URL or, for "#ID", the base64 text of the page's
   * element with id ID (a self-contained page). `what` names the data in an error.
   */
  async function urlBytes(url, what) {
    if (!url.startsWith('#')) return (await fetchOk(url)).arrayBuffer();
    const element = document.getElementById(url.slice(1));
    if (!element) throw new Error(`the page has no element ${url} with ${what}`);
    return decodeBase64(element.textContent).buffer;
  }

  /**
   * Checks a body's header (at least `headerBytes` long, starting with the 4 ASCII bytes
   * `magic`) and returns a little-endian view of it, or throws saying what is wrong.
   */
  function checkedHeader(buffer, magic, headerBytes) {
    if (buffer.byteLength < headerBytes) {
      throw new Error(`${buffer.byteLength} bytes, shorter than the ${headerBytes}-byte header`);
    }
    const found = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
    if (found !== magic) throw new Error(`starts with ${JSON.stringify(found)}, not ${magic}`);
    return new DataView(buffer);
  }

  /** `n` little-endian float32 of `view` from byte `at` (a view of the buffer where it can). */
  function floatsAt(view, at, n) {
    if (LITTLE_ENDIAN_HOST) return new Float32Array(view.buffer, at, n);
    const out = new Float32Array(n);
    for (let i = 0; i < n; i++) out[i] = view.getFloat32(at + 4 * i, true);
    return out;
  }

  /** A frame body as its records (count x 13 float32, with `.sh = {degree, coeffs}` when it
   * holds higher spherical harmonics), or an Error saying what is wrong. */
  function parseFrame(buffer) {
    const view = checkedHeader(buffer, MAGIC, HEADER_BYTES);
    const count = view.getUint32(4, true);
    const expected = HEADER_BYTES + RECORD_BYTES * count;
    const sh = buffer.byteLength > expected ? parseSh(buffer, expected, count) : null;
    if (!sh && buffer.byteLength !== expected) {
      throw new Error(
        `${buffer.byteLength} bytes, but ${count} Gaussians take ${expected} (8 + 52 x ${count}): truncated or corrupt`,
      );
    }
    const records = floatsAt(view, HEADER_BYTES, FLOATS_PER_GAUSSIAN * count);
    records.sh = sh;
    return records;
  }

  /** The spherical harmonics after a frame's records at byte `at`. */
  function parseSh(buffer, at, count) {
    const found = buffer.byteLength >= at + 8 ? String.fromCharCode(...new Uint8Array(buffer, at, 4)) : '';
    if (found !== 'VXS1') throw new Error(`${buffer.byteLength - at} bytes after the records, not spherical harmonics`);
    const view = new DataView(buffer);
    const degree = view.getUint32(at + 4, true);
    const stride = 3 * ((degree + 1) * (degree + 1) - 1);
    if (degree < 1 || degree > 3 || buffer.byteLength !== at + 8 + 4 * stride * count) {
      throw new Error(`spherical harmonics of degree ${degree} for ${count} Gaussians: truncated or corrupt`);
    }
    return { degree, coeffs: floatsAt(view, at + 8, stride * count) };
  }

  /** The clip frame number of a manifest frame entry (its position when it has none). */
  function frameNumber(entry, index) {
    return entry.frame ?? index;
  }

  /** What the status line and errors call a frame. */
  function frameLabel(entry, index) {
    return `frame ${frameNumber(entry, index)}`;
  }

  /** Loads frames on demand; each is decoded once and kept (index -> Float32Array). */
  class FrameStore {
    constructor(frames) {
      this.frames = frames;
      this.cache = new Map();
      this.pending = new Map();
    }

    /** The records of frame `index` (a promise); a failure is not kept, so it can be retried. */
    get(index) {
      if (this.cache.has(index)) return Promise.resolve(this.cache.get(index));
      if (!this.pending.has(index)) {
        const entry = this.frames[index];
        const load = urlBytes(entry.url, "this frame's data")
          .then(parseFrame)
          .then(
            (records) => {
              this.cache.set(index, records);
              this.pending.delete(index);
              return records;
            },
            (e) => {
              this.pending.delete(index);
              throw new Error(`${frameLabel(entry, index)} (${entry.url}): ${e.message}`);
            },
          );
        this.pending.set(index, load);
      }
      return this.pending.get(index);
    }

    /** Starts loading a frame without waiting for it (errors show when it is shown). */
    prefetch(index) {
      if (index >= 0 && index < this.frames.length) this.get(index).catch(() => {});
    }
  }

  /**
   * Tracks as their body holds them: "VXT1", u32 T (tracks), u32 F (clip frames), T x F x 3
   * float32 world positions (track t at clip frame f at (t F + f) 3), T x F bytes of
   * visibility (1 seen, 0 hidden), zero padding to a multiple of 4 bytes. Returns
   * {count, frames, positions, visible}, or throws saying what is wrong.
   */
  function parseTracks(buffer) {
    const view = checkedHeader(buffer, TRACKS_MAGIC, TRACKS_HEADER_BYTES);
    const count = view.getUint32(4, true);
    const frames = view.getUint32(8, true);
    const points = count * frames;
    const unpadded = TRACKS_HEADER_BYTES + 13 * points;
    const expected = unpadded + ((4 - (unpadded % 4)) % 4);
    if (buffer.byteLength !== expected) {
      throw new Error(
        `${buffer.byteLength} bytes, but ${count} tracks over ${frames} frames take ${expected} ` +
          `(12 + 12 x ${points} + ${points}, padded to a multiple of 4): truncated or corrupt`,
      );
    }
    const visibleAt = TRACKS_HEADER_BYTES + 12 * points;
    const positions = floatsAt(view, TRACKS_HEADER_BYTES, 3 * points);
    return { count, frames, positions, visible: new Uint8Array(buffer, visibleAt, points) };
  }

  /** The tracks the manifest's `tracks` names, checked against its counts when it gives them. */
  async function loadTracks(spec) {
    const tracks = parseTracks(await urlBytes(spec.url, 'the tracks'));
    const agrees = (said, found) => said === undefined || said === null || said === found;
    if (!agrees(spec.count, tracks.count) || !agrees(spec.frames, tracks.frames)) {
      throw new Error(
        `holds ${tracks.count} tracks over ${tracks.frames} frames, but the manifest says ` +
          `${spec.count} over ${spec.frames}`,
      );
    }
    return tracks;
  }

  /** The centre of a frame's means and the largest distance of a mean from it. */
  function boundingSphere(records) {
    const n = records.length / FLOATS_PER_GAUSSIAN;
    const centre = [0, 0, 0];
    for (let o = 0; o < records.length; o += FLOATS_PER_GAUSSIAN) {
      for (let k = 0; k < 3; k++) centre[k] += records[o + k] / n;
    }
    let radius = 0;
    for (let o = 0; o < records.length; o += FLOATS_PER_GAUSSIAN) {
      const d = length(sub([records[o], records[o + 1], records[o + 2]], centre));
      if (d > radius) radius = d;
    }
    const usable = n > 0 && centre.every(Number.isFinite) && Number.isFinite(radius) && radius > 0;
    return usable ? { centre, radius } : { centre: [0, 0, 0], radius: 1 };
  }

  // ---------------------------------------------------------------------------------------
  // 4. Depth sort
  // ---------------------------------------------------------------------------------------

  const RADIX_BITS = 11;
  const RADIX = 1 << RADIX_BITS;

  /**
   * Stable LSD radix sort of `values` by the u32 `keys` (first n entries), using the two
   * scratch arrays; returns the sorted values (a view of one of the arrays).
   */
  function radixSortPairs(keys, values, keysTmp, valuesTmp, n) {
    const counts = new Uint32Array(RADIX);
    let [srcK, srcV, dstK, dstV] = [keys, values, keysTmp, valuesTmp];
    for (let shift = 0; shift < 32; shift += RADIX_BITS) {
      counts.fill(0);
      for (let i = 0; i < n; i++) counts[(srcK[i] >>> shift) & (RADIX - 1)]++;
      if (n === 0 || counts[(srcK[0] >>> shift) & (RADIX - 1)] === n) continue; // one digit: skip
      let sum = 0;
      for (let b = 0; b < RADIX; b++) {
        const c = counts[b];
        counts[b] = sum;
        sum += c;
      }
      for (let i = 0; i < n; i++) {
        const k = srcK[i];
        const at = counts[(k >>> shift) & (RADIX - 1)]++;
        dstK[at] = k;
        dstV[at] = srcV[i];
      }
      [srcK, srcV, dstK, dstV] = [dstK, dstV, srcK, srcV];
    }
    return srcV.subarray(0, n);
  }

  /**
   * The order in which Gaussians are blended: the kept ones (depth >= NEAR, opacity >=
   * 1/255) by their float32 camera-space depth, nearest first, ties by index. Positive
   * floats sort as their bit patterns do, so the keys are the depths' bits.
   */
  class DepthSorter {
    constructor() {
      this.capacity = -1;
    }

    reserve(n) {
      if (n <= this.capacity) return;
      const depthBuffer = new ArrayBuffer(4 * n);
      this.depths = new Float32Array(depthBuffer);
      this.keys = new Uint32Array(depthBuffer);
      this.keysTmp = new Uint32Array(n);
      this.indices = new Uint32Array(n);
      this.indicesTmp = new Uint32Array(n);
      this.capacity = n;
    }

    /** Indices into `records` to draw, nearest first. */
    sort(records, cam) {
      const n = records.length / FLOATS_PER_GAUSSIAN;
      this.reserve(n);
      const [r0, r1, r2] = cam.rotation[2];
      const tz = cam.translation[2];
      let kept = 0;
      for (let i = 0, o = 0; i < n; i++, o += FLOATS_PER_GAUSSIAN) {
        const z = r0 * records[o] + r1 * records[o + 1] + r2 * records[o + 2] + tz;
        if (z >= NEAR && records[o + OPACITY] >= MIN_ALPHA) {
          this.depths[kept] = z;
          this.indices[kept] = i;
          kept++;
        }
      }
      return radixSortPairs(this.keys, this.indices, this.keysTmp, this.indicesTmp, kept);
    }
  }

  // ---------------------------------------------------------------------------------------
  // 5. WebGL2 renderer
  // ---------------------------------------------------------------------------------------

  /**
   * Splat vertex shader: the EWA projection of one Gaussian, as the engine's project_one
   * does it, and a quad over its footprint in pixels. Vertices 6 s .. 6 s + 5 are the two
   * triangles of the Gaussian in blending slot s, the order texture's entry s. (One plain
   * draw of 6 vertices per Gaussian rather than an instanced one: software renderers such
   * as SwiftShader run instances one by one, three times slower here.)
   * The data texture holds each record padded to 16 floats in 4 RGBA texels:
   * (x y z xx) (xy xz yy yz) (zz opacity r g) (b - - -).
   */
  const SPLAT_VS = `#version 300 es
precision highp float;
precision highp int;

uniform highp sampler2D u_data;
uniform int u_perRow;     // Gaussians per data texture row
uniform highp usampler2D u_order;  // Gaussian indices, nearest first
uniform int u_orderWidth; // entries per order texture row
uniform mat3 u_rotation;  // world to camera
uniform vec3 u_translation;
uniform vec4 u_focal;     // fx, fy, cx, cy
uniform vec4 u_limits;    // min and max of x/z, min and max of y/z
uniform vec2 u_size;      // width, height in pixels
uniform highp sampler2D u_sh;  // higher spherical harmonics: 12 texels a Gaussian, k-major
uniform int u_shPerRow;   // Gaussians per row of it
uniform int u_shDegree;   // 0: the colour alone

// The quad's corners, as two triangles, in units of its half-sides.
const vec2 CORNERS[6] = vec2[6](vec2(-1, -1), vec2(1, -1), vec2(-1, 1),
                                vec2(-1, 1), vec2(1, -1), vec2(1, 1));

flat out vec2 v_centre;   // (u, v) in pixels, v down
flat out vec3 v_conic;    // inverse 2D covariance: xx, xy, yy
flat out float v_opacity;
flat out vec3 v_colour;

// The SH basis' constants (3D Gaussian splatting's; velox_io::ply::sh_colour is the same sum).
const float C1 = 0.4886025119029199;
const float C2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                            -1.0925484305920792, 0.5462742152960396);
const float C3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                            0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                            -0.5900435899266435);
vec4 shTexels[12];

// Coefficient k (of the K past degree 0) of the three channels.
vec3 shc(int k) {
  int j = 3 * k;
  return vec3(shTexels[j / 4][j % 4], shTexels[(j + 1) / 4][(j + 1) % 4], shTexels[(j + 2) / 4][(j + 2) % 4]);
}

// The colour along the unit direction d from the camera: the degree-0 colour plus degrees 1
// to u_shDegree, clamped below at 0.
vec3 viewColour(int i, vec3 base, vec3 d) {
  ivec2 at = ivec2((i % u_shPerRow) * 12, i / u_shPerRow);
  int texels = (3 * ((u_shDegree + 1) * (u_shDegree + 1) - 1) + 3) / 4;
  for (int k = 0; k < 12; k++) {
    if (k < texels) shTexels[k] = texelFetch(u_sh, at + ivec2(k, 0), 0);
  }
  float x = d.x, y = d.y, z = d.z;
  vec3 c = base - C1 * y * shc(0) + C1 * z * shc(1) - C1 * x * shc(2);
  if (u_shDegree > 1) {
    float xx = x * x, yy = y * y, zz = z * z;
    c += C2[0] * x * y * shc(3) + C2[1] * y * z * shc(4) + C2[2] * (2.0 * zz - xx - yy) * shc(5)
       + C2[3] * x * z * shc(6) + C2[4] * (xx - yy) * shc(7);
    if (u_shDegree > 2) {
      c += C3[0] * y * (3.0 * xx - yy) * shc(8) + C3[1] * x * y * z * shc(9)
         + C3[2] * y * (4.0 * zz - xx - yy) * shc(10) + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * shc(11)
         + C3[4] * x * (4.0 * zz - xx - yy) * shc(12) + C3[5] * z * (xx - yy) * shc(13)
         + C3[6] * x * (xx - 3.0 * yy) * shc(14);
    }
  }
  return max(c, vec3(0.0));
}

const float MIN_ALPHA = ${MIN_ALPHA};
const float DILATION = ${DILATION};
const float MIN_DET = ${MIN_DET};

void drop() {
  gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: nothing drawn
}

void main() {
  int slot = gl_VertexID / 6;
  vec2 a_corner = CORNERS[gl_VertexID % 6];
  int i = int(texelFetch(u_order, ivec2(slot % u_orderWidth, slot / u_orderWidth), 0).r);
  ivec2 base = ivec2((i % u_perRow) * 4, i / u_perRow);
  vec4 t0 = texelFetch(u_data, base, 0);
  vec4 t1 = texelFetch(u_data, base + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(u_data, base + ivec2(2, 0), 0);
  vec4 t3 = texelFetch(u_data, base + ivec2(3, 0), 0);
  vec3 mean = t0.xyz;
  mat3 sigma = mat3(t0.w, t1.x, t1.y,   // symmetric: columns are rows
                    t1.x, t1.z, t1.w,
                    t1.y, t1.w, t2.x);
  float opacity = t2.y;
  vec3 colour = vec3(t2.zw, t3.x);
  if (u_shDegree > 0) {
    vec3 eye = -(transpose(u_rotation) * u_translation);
    colour = viewColour(i, colour, normalize(mean - eye));
  }

  vec3 t = u_rotation * mean + u_translation;
  float fx = u_focal.x, fy = u_focal.y;
  // Jacobian of the projection at t, with x/z and y/z clamped a little beyond the image.
  float rx = clamp(t.x / t.z, u_limits.x, u_limits.y);
  float ry = clamp(t.y / t.z, u_limits.z, u_limits.w);
  mat3 J = mat3(fx / t.z, 0.0, 0.0,
                0.0, fy / t.z, 0.0,
                -fx * rx / t.z, -fy * ry / t.z, 0.0);
  mat3 T = J * u_rotation;
  mat3 cov = T * sigma * transpose(T);
  float a = cov[0][0] + DILATION;
  float b = cov[0][1];
  float c = cov[1][1] + DILATION;
  float det = a * c - b * b;
  vec2 uv = vec2(fx * t.x / t.z + u_focal.z, fy * t.y / t.z + u_focal.w);
  bool finite = !isinf(det) && !isnan(det) && abs(uv.x) < 1e30 && abs(uv.y) < 1e30;
  if (!finite || !(det >= MIN_DET)) {
    drop();
    return;
  }

  // Alpha reaches 1/255 only inside the ellipse d^T conic d <= q. Its bounding box is the
  // engine's footprint, |d_x| <= sqrt(q a), |d_y| <= sqrt(q c): drop it if that misses the
  // image, as the engine does.
  float q = 2.0 * log(opacity / MIN_ALPHA);
  vec2 extent = sqrt(q * vec2(a, c));
  if (any(lessThan(uv + extent, vec2(0.0))) || any(greaterThan(uv - extent, u_size))) {
    drop();
    return;
  }
  // The quad is the rectangle along the ellipse's axes (eigenvectors of the covariance):
  // it holds the same pixels as the box with fewer fragments for elongated footprints
  // (the fragment shader's alpha test decides which are drawn either way). Half-sides stop
  // at the image's farthest corner, which keeps huge footprints' vertices finite.
  float mid = 0.5 * (a + c);
  float major = mid + sqrt(0.25 * (a - c) * (a - c) + b * b);
  float minor = det / major;
  float angle = 0.5 * atan(2.0 * b, a - c);
  vec2 axis = vec2(cos(angle), sin(angle));
  float reach = length(max(abs(uv), abs(uv - u_size))) + 1.0;
  vec2 half_sides = min(sqrt(q * vec2(major, minor)) * 1.001 + 0.01, vec2(reach));
  vec2 corner = uv + a_corner.x * half_sides.x * axis + a_corner.y * half_sides.y * vec2(-axis.y, axis.x);
  // Pixels to clip space; v grows downwards, clip y upwards.
  gl_Position = vec4(2.0 * corner.x / u_size.x - 1.0, 1.0 - 2.0 * corner.y / u_size.y, 0.0, 1.0);

  v_centre = uv;
  v_conic = vec3(c, -b, a) / det;
  v_opacity = opacity;
  v_colour = colour;
}
`;

  /** Splat fragment shader: alpha at the pixel centre, premultiplied colour out. */
  const SPLAT_FS = `#version 300 es
precision highp float;

uniform float u_height;

flat in vec2 v_centre;
flat in vec3 v_conic;
flat in float v_opacity;
flat in vec3 v_colour;

out vec4 o_colour;

const float MIN_ALPHA = ${MIN_ALPHA};
const float ALPHA_MAX = ${ALPHA_MAX};

void main() {
  // gl_FragCoord is the pixel centre with y up; the camera's v is down.
  vec2 pixel = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);
  vec2 d = v_centre - pixel;
  float power = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
  if (power < 0.0) discard;
  float alpha = min(ALPHA_MAX, v_opacity * exp(-power));
  if (alpha < MIN_ALPHA) discard;
  o_colour = vec4(v_colour * alpha, alpha);
}
`;

  /** Composite pass: one triangle over the canvas. */
  const COMPOSITE_VS = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}
`;

  /** Composite: the blended colour plus the background times the light left (1 - alpha). */
  const COMPOSITE_FS = `#version 300 es
precision highp float;
uniform highp sampler2D u_accum;
uniform vec3 u_background;
out vec4 o_colour;
void main() {
  vec4 acc = texelFetch(u_accum, ivec2(gl_FragCoord.xy), 0);
  o_colour = vec4(acc.rgb + (1.0 - acc.a) * u_background, 1.0);
}
`;

  function compileShader(gl, type, source) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(`a shader did not compile: ${gl.getShaderInfoLog(shader)}`);
    }
    return shader;
  }

  /** A linked program and its uniform locations by name. */
  function makeProgram(gl, vsSource, fsSource) {
    const program = gl.createProgram();
    gl.attachShader(program, compileShader(gl, gl.VERTEX_SHADER, vsSource));
    gl.attachShader(program, compileShader(gl, gl.FRAGMENT_SHADER, fsSource));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
      throw new Error(`a shader program did not link: ${gl.getProgramInfoLog(program)}`);
    }
    const uniforms = {};
    const n = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const name = gl.getActiveUniform(program, i).name;
      uniforms[name] = gl.getUniformLocation(program, name);
    }
    return { program, uniforms };
  }

  /**
   * Render-target formats, best first: RGBA32F needs EXT_color_buffer_float and
   * EXT_float_blend, RGBA16F EXT_color_buffer_float (or _half_float); RGBA8 always works
   * (with 8-bit accumulation).
   */
  function targetFormats(gl) {
    const float = gl.getExtension('EXT_color_buffer_float');
    const half = float || gl.getExtension('EXT_color_buffer_half_float');
    const blend32 = float && gl.getExtension('EXT_float_blend');
    const formats = [];
    if (blend32) formats.push({ name: 'RGBA32F', internal: gl.RGBA32F, type: gl.FLOAT });
    if (half) formats.push({ name: 'RGBA16F', internal: gl.RGBA16F, type: gl.HALF_FLOAT });
    formats.push({ name: 'RGBA8', internal: gl.RGBA8, type: gl.UNSIGNED_BYTE });
    return formats;
  }

  /** Draws the Gaussians of one frame, in a given order, from a given camera. */
  class SplatRenderer {
    constructor(canvas) {
      const gl = canvas.getContext('webgl2', {
        alpha: false,
        antialias: false,
        depth: false,
        stencil: false,
        premultipliedAlpha: false,
        preserveDrawingBuffer: true,
      });
      if (!gl) throw new Error('WebGL2 is not available in this browser; the viewer needs it');
      this.gl = gl;
      this.canvas = canvas;
      this.splat = makeProgram(gl, SPLAT_VS, SPLAT_FS);
      this.composite = makeProgram(gl, COMPOSITE_VS, COMPOSITE_FS);
      this.formats = targetFormats(gl);
      this.maxTexture = gl.getParameter(gl.MAX_TEXTURE_SIZE);
      this.perRow = Math.min(1024, Math.floor(this.maxTexture / 4));
      this.dataTexture = gl.createTexture();
      this.shPerRow = Math.min(1024, Math.floor(this.maxTexture / 12));
      this.shTexture = gl.createTexture();
      this.shDegree = 0;
      this.orderTexture = gl.createTexture();
      this.orderWidth = Math.min(4096, this.maxTexture);
      this.orderData = new Uint32Array(0);
      this.count = 0; // Gaussians to draw
      this.target = null;
    }

    /** Uploads a frame's records (count x 13 floats) to the data texture. */
    setFrame(records) {
      const gl = this.gl;
      const n = records.length / FLOATS_PER_GAUSSIAN;
      const rows = Math.max(1, Math.ceil(n / this.perRow));
      if (rows > this.maxTexture) {
        throw new Error(`${n} Gaussians are more than this GPU's textures hold (${this.perRow * this.maxTexture})`);
      }
      const packed = new Float32Array(rows * this.perRow * 16);
      for (let i = 0; i < n; i++) {
        const from = i * FLOATS_PER_GAUSSIAN;
        const to = i * 16;
        for (let k = 0; k < FLOATS_PER_GAUSSIAN; k++) packed[to + k] = records[from + k];
      }
      gl.bindTexture(gl.TEXTURE_2D, this.dataTexture);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, this.perRow * 4, rows, 0, gl.RGBA, gl.FLOAT, packed);
      setNearest(gl);
      this.setSh(records.sh, n);
      this.count = 0;
    }

    /** Uploads a frame's higher spherical harmonics (`sh` of parseFrame, or none): per
     * Gaussian 12 texels of its coefficients, coefficient-major (k, then red green blue). */
    setSh(sh, n) {
      const gl = this.gl;
      this.shDegree = sh ? sh.degree : 0;
      const per = sh ? (sh.degree + 1) * (sh.degree + 1) - 1 : 0;
      const rows = sh ? Math.max(1, Math.ceil(n / this.shPerRow)) : 1;
      if (rows > this.maxTexture) {
        throw new Error(`${n} Gaussians' spherical harmonics are more than this GPU's textures hold`);
      }
      const width = sh ? this.shPerRow * 12 : 1;
      const packed = new Float32Array(width * rows * 4);
      for (let i = 0; sh && i < n; i++) {
        for (let k = 0; k < per; k++) {
          for (let c = 0; c < 3; c++) packed[i * 48 + 3 * k + c] = sh.coeffs[i * 3 * per + c * per + k];
        }
      }
      gl.bindTexture(gl.TEXTURE_2D, this.shTexture);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, width, rows, 0, gl.RGBA, gl.FLOAT, packed);
      setNearest(gl);
    }

    /** The Gaussians to draw, in blending order (nearest first), to the order texture. */
    setOrder(indices) {
      const gl = this.gl;
      const width = this.orderWidth;
      const rows = Math.max(1, Math.ceil(indices.length / width));
      if (this.orderData.length < rows * width) this.orderData = new Uint32Array(rows * width);
      this.orderData.set(indices);
      gl.bindTexture(gl.TEXTURE_2D, this.orderTexture);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32UI, width, rows, 0, gl.RED_INTEGER, gl.UNSIGNED_INT, this.orderData, 0);
      setNearest(gl);
      this.count = indices.length;
    }

    /** Sizes the canvas (drawing buffer and CSS) and the blending target to the camera. */
    resize(width, height) {
      const canvas = this.canvas;
      if (canvas.width !== width || canvas.height !== height) {
        canvas.width = width;
        canvas.height = height;
      }
      // On screen a small render is shown enlarged by a whole factor (its pixels kept sharp),
      // so a 48-pixel scene is not a thumbnail; with ui=0 it is shown at its own size.
      // Two panes side by side are enlarged less, so that both fit next to the controls.
      const bare = document.body.classList.contains('bare');
      const side = document.body.classList.contains('two-panes') ? DISPLAY_SIDE_TWO_PANES : DISPLAY_SIDE;
      const scale = bare ? 1 : Math.max(1, Math.floor(side / Math.max(width, height)));
      canvas.style.width = `${width * scale}px`;
      canvas.style.height = `${height * scale}px`;
      canvas.style.imageRendering = scale > 1 ? 'pixelated' : 'auto';
      if (!this.target || this.target.width !== width || this.target.height !== height) {
        this.target = this.makeTarget(width, height);
      }
    }

    /** A framebuffer in the best format that is complete here. */
    makeTarget(width, height) {
      const gl = this.gl;
      if (this.target) {
        gl.deleteFramebuffer(this.target.framebuffer);
        gl.deleteTexture(this.target.texture);
      }
      for (const format of this.formats) {
        const texture = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D, texture);
        gl.texImage2D(gl.TEXTURE_2D, 0, format.internal, width, height, 0, gl.RGBA, format.type, null);
        setNearest(gl);
        const framebuffer = gl.createFramebuffer();
        gl.bindFramebuffer(gl.FRAMEBUFFER, framebuffer);
        gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
        const complete = gl.checkFramebufferStatus(gl.FRAMEBUFFER) === gl.FRAMEBUFFER_COMPLETE;
        gl.bindFramebuffer(gl.FRAMEBUFFER, null);
        if (complete) return { framebuffer, texture, width, height, format: format.name };
        gl.deleteFramebuffer(framebuffer);
        gl.deleteTexture(texture);
      }
      throw new Error('no render-target format works on this GPU');
    }

    /** Draws the current frame and order from `cam` over `background`. */
    draw(cam, background) {
      const gl = this.gl;
      this.resize(cam.width, cam.height);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.target.framebuffer);
      gl.viewport(0, 0, cam.width, cam.height);
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      if (this.count > 0) this.drawSplats(cam);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.useProgram(this.composite.program);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.target.texture);
      gl.uniform1i(this.composite.uniforms.u_accum, 0);
      gl.uniform3fv(this.composite.uniforms.u_background, background);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }

    /** Front-to-back blending: dst += (1 - dst.a) * (c a, a). */
    drawSplats(cam) {
      const gl = this.gl;
      const u = this.splat.uniforms;
      const r = cam.rotation;
      gl.useProgram(this.splat.program);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.dataTexture);
      gl.uniform1i(u.u_data, 0);
      gl.uniform1i(u.u_perRow, this.perRow);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, this.orderTexture);
      gl.uniform1i(u.u_order, 1);
      gl.uniform1i(u.u_orderWidth, this.orderWidth);
      gl.activeTexture(gl.TEXTURE2);
      gl.bindTexture(gl.TEXTURE_2D, this.shTexture);
      gl.uniform1i(u.u_sh, 2);
      gl.uniform1i(u.u_shPerRow, this.shPerRow);
      gl.uniform1i(u.u_shDegree, this.shDegree);
      // Column-major: the columns of R.
      gl.uniformMatrix3fv(u.u_rotation, false, [0, 1, 2].flatMap((c) => [r[0][c], r[1][c], r[2][c]]));
      gl.uniform3fv(u.u_translation, cam.translation);
      gl.uniform4f(u.u_focal, cam.fx, cam.fy, cam.cx, cam.cy);
      gl.uniform4fv(u.u_limits, jacobianLimits(cam));
      gl.uniform2f(u.u_size, cam.width, cam.height);
      gl.uniform1f(u.u_height, cam.height);
      gl.enable(gl.BLEND);
      gl.blendFuncSeparate(gl.ONE_MINUS_DST_ALPHA, gl.ONE, gl.ONE_MINUS_DST_ALPHA, gl.ONE);
      gl.drawArrays(gl.TRIANGLES, 0, 6 * this.count);
      gl.disable(gl.BLEND);
    }

    /** Clears the canvas to black. */
    clear() {
      const gl = this.gl;
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.clearColor(0, 0, 0, 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
    }

    /** Waits for the GPU to finish (for timing only). */
    finish() {
      const gl = this.gl;
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
    }
  }

  function setNearest(gl) {
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  /**
   * Overlay shaders: lines and round dots given in pixels (v down) with a straight (not
   * premultiplied) colour, blended over the picture. The pixel to clip space mapping is the
   * splat shader's, so a point drawn at a Gaussian's (u, v) lands on its centre.
   */
  const OVERLAY_VS = `#version 300 es
layout(location = 0) in vec2 a_pixel;
layout(location = 1) in vec4 a_colour;
uniform vec2 u_size;        // width, height in pixels
uniform float u_pointSize;  // dot diameter in pixels
out vec4 v_colour;
void main() {
  gl_Position = vec4(2.0 * a_pixel.x / u_size.x - 1.0, 1.0 - 2.0 * a_pixel.y / u_size.y, 0.0, 1.0);
  gl_PointSize = u_pointSize;
  v_colour = a_colour;
}
`;

  const OVERLAY_FS = `#version 300 es
precision highp float;
uniform bool u_round;  // dots: only the disc inside the point's square
in vec4 v_colour;
out vec4 o_colour;
void main() {
  if (u_round && length(gl_PointCoord - 0.5) > 0.5) discard;
  o_colour = v_colour;
}
`;

  /** Vertices of the overlay: u, v (pixels), r, g, b, a. */
  const OVERLAY_FLOATS = 6;

  /** Draws lines and dots over what a SplatRenderer drew, in the same WebGL2 context. */
  class OverlayRenderer {
    constructor(gl) {
      this.gl = gl;
      this.program = makeProgram(gl, OVERLAY_VS, OVERLAY_FS);
      this.buffer = gl.createBuffer();
      this.vao = gl.createVertexArray();
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
      const stride = 4 * OVERLAY_FLOATS;
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 2, gl.FLOAT, false, stride, 0);
      gl.enableVertexAttribArray(1);
      gl.vertexAttribPointer(1, 4, gl.FLOAT, false, stride, 8);
      gl.bindVertexArray(null);
    }

    /** Draws `lines` (vertex pairs) and then `dots` on the canvas of width x height pixels. */
    draw(lines, dots, width, height) {
      const gl = this.gl;
      const u = this.program.uniforms;
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, width, height);
      gl.useProgram(this.program.program);
      gl.uniform2f(u.u_size, width, height);
      // The dot keeps its share of the picture: smaller on a small render.
      const side = Math.min(width, height);
      gl.uniform1f(u.u_pointSize, Math.max(TRACK_DOT_MIN_PIXELS, Math.round((TRACK_DOT_PIXELS * side) / 256)));
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
      this.drawVertices(gl.LINES, lines, false);
      this.drawVertices(gl.POINTS, dots, true);
      gl.disable(gl.BLEND);
      gl.bindVertexArray(null);
    }

    drawVertices(mode, vertices, round) {
      if (vertices.length === 0) return;
      const gl = this.gl;
      gl.uniform1i(this.program.uniforms.u_round, round ? 1 : 0);
      gl.bufferData(gl.ARRAY_BUFFER, vertices, gl.STREAM_DRAW);
      gl.drawArrays(mode, 0, vertices.length / OVERLAY_FLOATS);
    }
  }

  // ---------------------------------------------------------------------------------------
  // 6. The page
  // ---------------------------------------------------------------------------------------

  /**
   * A pane: a canvas, its own WebGL2 context and renderer, and the frame it shows. The main
   * pane shows the manifest's frames; the compare pane shows the compare frame with the
   * same clip frame number. Both are drawn from the one camera of the page.
   */
  function makePane(canvas, label) {
    return {
      canvas,
      label, // the title above the canvas (shown when there are two panes)
      renderer: new SplatRenderer(canvas), // throws without WebGL2
      sorter: new DepthSorter(),
      title: '',
      frames: [], // manifest-form frame entries
      store: null, // FrameStore of `frames`
      byNumber: new Map(), // clip frame number -> index in `frames` (the compare pane's)
      visible: true, // whether it is drawn (the compare pane can be switched off)
      wanted: 0, // the manifest frame index asked for last
      shown: null, // {index, records} on the GPU; index -1 is "no such frame" (background)
      sortedFor: '', // the frame and view the GPU's order was sorted for
      lastDrawn: '', // the frame, view and overlay of the picture on the canvas
    };
  }

  /** An empty frame: what the compare pane draws (the background) for a missing frame. */
  const NO_RECORDS = new Float32Array(0);

  /** Everything the page knows; changed only through the functions below. */
  const state = {
    ui: null, // the DOM controls
    bare: false, // ui=0: a pane alone, no controls
    manifest: null,
    main: null, // the main pane
    compare: null, // the compare pane, when the manifest has `compare`
    tracks: null, // the decoded tracks, once loaded
    overlay: null, // OverlayRenderer drawing them over the main pane
    home: { centre: [0, 0, 0], radius: 1 }, // the first frame's bounding sphere
    camera: null, // the current view, a manifest-form camera
    cameraIndex: -1, // the scene camera the view is, or -1 for a user-made view
    target: [0, 0, 0], // the orbit's pivot
    up: [0, 1, 0], // the orbit's yaw axis
    viewVersion: 0, // bumped on every camera change
    drawn: 0, // pictures the main pane has drawn so far
    drawPending: false,
    playing: false,
    speed: 1,
    timer: 0,
    errors: new Map(), // the errors shown: slot (see errorSlot) -> {kind, message}
  };

  function findControls() {
    const byId = (id) => document.getElementById(id);
    return {
      canvas: byId('canvas'),
      canvasCompare: byId('canvas-compare'),
      paneCompare: byId('pane-compare'),
      labelMain: byId('label-main'),
      labelCompare: byId('label-compare'),
      title: byId('title'),
      frame: byId('frame'),
      play: byId('play'),
      speed: byId('speed'),
      status: byId('status'),
      cameras: byId('cameras'),
      reset: byId('reset'),
      showCompare: byId('show-compare'),
      showTracks: byId('show-tracks'),
      error: byId('error'),
    };
  }

  /**
   * Where an error of `kind` shows: the page's own kinds ('fatal', 'frame', 'hash') share
   * one slot, the newest replacing the one shown; a compare frame's and the tracks' errors
   * have a slot each, shown after it.
   */
  function errorSlot(kind) {
    return kind === 'compare' || kind === 'tracks' ? kind : 'main';
  }

  /** Whether an error of `kind` is shown. */
  function hasError(kind) {
    const shown = state.errors.get(errorSlot(kind));
    return shown !== undefined && shown.kind === kind;
  }

  /**
   * Shows an error. Frame, manifest and WebGL failures clear the main canvas, a compare
   * frame's failure the compare canvas; tracks and bad hash parameters leave the pictures
   * alone.
   */
  function showError(message, kind) {
    const slot = errorSlot(kind);
    state.errors.delete(slot);
    state.errors.set(slot, { kind, message });
    showErrors();
    const pane = kind === 'compare' ? state.compare : kind === 'fatal' || kind === 'frame' ? state.main : null;
    if (pane) pane.renderer.clear();
    console.error(`velox view: ${message}`);
  }

  /** Hides the error if it is of `kind` (a frame error goes once a frame draws). */
  function clearError(kind) {
    if (!hasError(kind)) return;
    state.errors.delete(errorSlot(kind));
    showErrors();
  }

  /** The error box and data-error: the messages shown, one per slot. */
  function showErrors() {
    const { error } = state.ui;
    const text = [...state.errors.values()].map((e) => e.message).join('\n\n');
    error.textContent = text;
    error.hidden = state.errors.size === 0;
    if (state.errors.size > 0) document.body.dataset.error = text;
    else delete document.body.dataset.error;
  }

  function formatNumber(x) {
    return String(Math.round(Number(x) * 1000) / 1000);
  }

  /** "frame F (tau T) · N Gaussians", or what is happening to that frame. */
  function setStatus(index, what) {
    const entry = state.manifest.frames[index];
    state.ui.status.textContent = `${frameLabel(entry, index)} (tau ${formatNumber(entry.tau ?? 0)}) · ${what}`;
  }

  /** The clip frame number of manifest frame `index`. */
  function clipFrame(index) {
    return frameNumber(state.manifest.frames[index], index);
  }

  // Drawing -------------------------------------------------------------------------------

  /** The panes there are and are switched on. */
  function visiblePanes() {
    return [state.main, state.compare].filter((pane) => pane && pane.visible);
  }

  /** The frame and view a pane's depth order is for. */
  function orderKey(pane) {
    return `${pane.shown ? pane.shown.index : '-'}/${state.viewVersion}`;
  }

  /** The frame, view and overlay a pane's picture shows. */
  function pictureKey(pane) {
    return pane === state.main ? `${orderKey(pane)}/${tracksShown() ? 'tracks' : ''}` : orderKey(pane);
  }

  /**
   * Draws soon, once for any number of requests in a row (camera moves), and only the panes
   * whose picture is not already the one on their canvas.
   */
  function requestDraw() {
    if (state.drawPending) return;
    state.drawPending = true;
    setTimeout(() => {
      state.drawPending = false;
      for (const pane of visiblePanes()) if (pictureKey(pane) !== pane.lastDrawn) drawPane(pane);
    }, 0);
  }

  /** Draws a pane's frame from the current camera, re-sorting if either changed. */
  function drawPane(pane) {
    const { shown, renderer } = pane;
    if (!shown || !state.camera || !pane.visible || hasError('fatal')) return;
    const key = orderKey(pane);
    if (pane.sortedFor !== key) {
      renderer.setOrder(pane.sorter.sort(shown.records, state.camera));
      pane.sortedFor = key;
    }
    renderer.draw(state.camera, state.manifest.background);
    pane.lastDrawn = pictureKey(pane);
    if (pane === state.main) mainDrawn(drawTracks());
    else compareDrawn();
  }

  /** The attributes tests read once the main pane has drawn (`tracks`: how many are on it). */
  function mainDrawn(tracks) {
    const { dataset } = document.body;
    state.drawn += 1;
    dataset.frame = String(state.main.shown.index);
    dataset.drawn = String(state.drawn);
    dataset.tracks = String(tracks);
    if (state.drawn === 1) dataset.firstPictureMs = performance.now().toFixed(0);
  }

  /** data-compare-frame: the clip frame the compare pane shows, or "none". */
  function compareDrawn() {
    const { shown, frames } = state.compare;
    const number = shown.index < 0 ? 'none' : frameNumber(frames[shown.index], shown.index);
    document.body.dataset.compareFrame = String(number);
  }

  // Tracks --------------------------------------------------------------------------------

  /** Whether the tracks are loaded and switched on. */
  function tracksShown() {
    return state.tracks !== null && state.ui.showTracks.checked;
  }

  /** Draws the tracks over the main pane, up to its clip frame; returns how many it drew. */
  function drawTracks() {
    if (!tracksShown()) return 0;
    const cam = state.camera;
    const { lines, dots } = trackVertices(state.tracks, clipFrame(state.main.shown.index), cam);
    state.overlay.draw(lines, dots, cam.width, cam.height);
    return state.tracks.count;
  }

  /**
   * The overlay's vertices for clip frame `c` from `cam`: each track's polyline through its
   * positions at clip frames 0 to c, faint where either end is hidden and broken where an
   * end is behind the near plane, and a dot at frame c.
   */
  function trackVertices(tracks, c, cam) {
    const { count, frames, positions, visible } = tracks;
    const last = Math.min(c, frames - 1);
    const lines = new Float32Array(2 * OVERLAY_FLOATS * count * Math.max(0, last));
    const dots = new Float32Array(OVERLAY_FLOATS * count);
    let nLines = 0;
    let nDots = 0;
    const put = (array, at, uv, rgb, alpha) => {
      array.set(uv, at);
      array.set(rgb, at + 2);
      array[at + 5] = alpha;
      return at + OVERLAY_FLOATS;
    };
    for (let t = 0; t < count; t++) {
      const rgb = trackColour(t, count);
      const first = t * frames; // the track's point at clip frame 0
      let previous = projectPoint(cam, positions, 3 * first);
      for (let f = 1; f <= last; f++) {
        const point = projectPoint(cam, positions, 3 * (first + f));
        if (previous && point) {
          const alpha = visible[first + f - 1] && visible[first + f] ? 1 : HIDDEN_TRACK_ALPHA;
          nLines = put(lines, nLines, previous, rgb, alpha);
          nLines = put(lines, nLines, point, rgb, alpha);
        }
        previous = point;
      }
      const dot = c >= 0 && c < frames ? projectPoint(cam, positions, 3 * (first + c)) : null;
      if (dot) nDots = put(dots, nDots, dot, rgb, visible[first + c] ? 1 : HIDDEN_TRACK_ALPHA);
    }
    return { lines: lines.subarray(0, nLines), dots: dots.subarray(0, nDots) };
  }

  /** The pixel (u, v) of the world point at positions[o..o+2], or null if behind the near plane. */
  function projectPoint(cam, positions, o) {
    const p = add(matVec(cam.rotation, [positions[o], positions[o + 1], positions[o + 2]]), cam.translation);
    if (!(p[2] >= NEAR)) return null;
    return [(cam.fx * p[0]) / p[2] + cam.cx, (cam.fy * p[1]) / p[2] + cam.cy];
  }

  /** Track t's colour: hues evenly spaced round the colour wheel, bright and saturated. */
  function trackColour(t, count) {
    const hue = (6 * t) / Math.max(1, count);
    const channel = (n) => {
      const k = (n + hue) % 6;
      return 1 - 0.85 * Math.max(0, Math.min(k, 4 - k, 1));
    };
    return [channel(5), channel(3), channel(1)];
  }

  /**
   * Starts loading the tracks, when the manifest has them; they are drawn once loaded. With
   * ui=0 they start switched off (the picture is the render alone) unless the hash says
   * tracks=1.
   */
  function setUpTracks() {
    const spec = state.manifest.tracks;
    state.ui.showTracks.checked = !state.bare;
    if (!spec) return;
    loadTracks(spec)
      .then((tracks) => {
        state.overlay = new OverlayRenderer(state.main.renderer.gl);
        state.tracks = tracks;
        requestDraw();
      })
      .catch((e) => showError(`the tracks (${spec.url}): ${e.message}`, 'tracks'));
  }

  // Frames --------------------------------------------------------------------------------

  /**
   * Shows manifest frame `index` in both panes; resolves when both are done, to what the
   * main pane's showMainFrame resolved to.
   */
  async function showFrame(index) {
    const [main] = await Promise.all([showMainFrame(index), showCompareFrame(index)]);
    return main;
  }

  /**
   * Shows frame `index` in the main pane: loads it (if needed), uploads and draws it, and
   * prefetches the next two. Resolves to 'shown', 'superseded' (another frame was asked for
   * meanwhile) or 'failed' (the error is shown).
   */
  async function showMainFrame(index) {
    const pane = state.main;
    const n = pane.frames.length;
    pane.wanted = index;
    setStatus(index, 'loading…');
    for (let k = 1; k <= PREFETCH && k < n; k++) pane.store.prefetch((index + k) % n);
    let records;
    try {
      records = await pane.store.get(index);
      if (pane.wanted !== index) return 'superseded';
      putFrame(pane, index, records);
    } catch (e) {
      if (pane.wanted !== index) return 'superseded';
      failFrame(index, e);
      return 'failed';
    }
    clearError('frame');
    setStatus(index, `${records.length / FLOATS_PER_GAUSSIAN} Gaussians`);
    drawPane(pane);
    return 'shown';
  }

  /** Makes frame `index` of a pane (its records) the one on its GPU. */
  function putFrame(pane, index, records) {
    if (pane.shown && pane.shown.index === index) return;
    pane.renderer.setFrame(records);
    pane.shown = { index, records };
    pane.sortedFor = '';
  }

  /** A frame that did not load: the message, a cleared canvas, playback stopped. */
  function failFrame(index, e) {
    state.main.shown = null;
    setPlaying(false);
    setStatus(index, 'failed');
    showError(e.message, 'frame');
  }

  /** The compare pane's frame index for manifest frame `index` (same clip frame), or -1. */
  function compareIndex(index) {
    return state.compare.byNumber.get(clipFrame(index)) ?? -1;
  }

  /**
   * Shows, in the compare pane (when it is on), the compare frame of manifest frame
   * `index`'s clip frame, or the background and "no frame F" when the compare has none.
   * Loads and prefetches as the main pane does; a failure shows its error and leaves the
   * main pane and playback alone.
   */
  async function showCompareFrame(index) {
    const pane = state.compare;
    if (!pane || !pane.visible) return;
    const n = state.manifest.frames.length;
    const number = clipFrame(index);
    const k = compareIndex(index);
    pane.wanted = index;
    for (let j = 1; j <= PREFETCH && j < n; j++) pane.store.prefetch(compareIndex((index + j) % n));
    let records = NO_RECORDS;
    try {
      if (k >= 0) records = await pane.store.get(k);
      if (pane.wanted !== index) return;
      putFrame(pane, k, records);
    } catch (e) {
      if (pane.wanted !== index) return;
      failCompareFrame(number, e);
      return;
    }
    clearError('compare');
    setCompareLabel(k < 0 ? `no frame ${number}` : '');
    drawPane(pane);
  }

  /** A compare frame that did not load: the message (naming the pane) and a cleared canvas. */
  function failCompareFrame(number, e) {
    const pane = state.compare;
    pane.shown = null;
    setCompareLabel(`frame ${number} failed`);
    document.body.dataset.compareFrame = 'none';
    showError(`the compare pane (${pane.title}): ${e.message}`, 'compare');
  }

  /** The compare pane's label: its title, and `note` when there is one. */
  function setCompareLabel(note) {
    const pane = state.compare;
    pane.label.textContent = note ? `${pane.title} · ${note}` : pane.title;
  }

  /**
   * The compare pane, when the manifest has one: a second canvas, WebGL2 context and
   * renderer, its frames, and whether it shows (#show-compare; with ui=0, pane=compare).
   */
  function setUpCompare(paneParameter) {
    const { ui, manifest } = state;
    if (!manifest.compare) return;
    let pane;
    try {
      pane = makePane(ui.canvasCompare, ui.labelCompare);
    } catch (e) {
      showError(`the compare pane: ${e.message}`, 'compare');
      return;
    }
    ui.canvasCompare.addEventListener('webglcontextlost', () => {
      const why = 'a GPU reset, or too little GPU memory';
      showError(`the compare pane's WebGL context was lost (${why}); reload the page`, 'compare');
    });
    pane.title = manifest.compare.title;
    pane.frames = manifest.compare.frames;
    pane.store = new FrameStore(pane.frames);
    pane.frames.forEach((entry, k) => {
      const number = frameNumber(entry, k);
      if (!pane.byNumber.has(number)) pane.byNumber.set(number, k);
    });
    state.compare = pane;
    ui.labelMain.textContent = manifest.title;
    ui.labelMain.hidden = false;
    setCompareLabel('');
    if (state.bare && paneParameter === 'compare') document.body.classList.add('pane-compare');
    setCompareVisible(state.bare ? paneParameter === 'compare' : ui.showCompare.checked);
  }

  /**
   * Switches the compare pane on or off. Two panes on screen are enlarged less (both
   * canvases are resized); a pane switched on loads and draws the current clip frame.
   */
  function setCompareVisible(on) {
    const pane = state.compare;
    pane.visible = on;
    state.ui.paneCompare.hidden = !on;
    document.body.classList.toggle('two-panes', on && !state.bare);
    if (state.camera) resizePanes();
    if (on) {
      if (state.camera) showCompareFrame(state.main.wanted);
    } else {
      clearError('compare');
      document.body.dataset.compareFrame = 'none';
    }
  }

  // Playback ------------------------------------------------------------------------------

  function setPlaying(on) {
    state.playing = on;
    state.ui.play.textContent = on ? 'Pause' : 'Play';
    clearTimeout(state.timer);
    if (on) state.timer = setTimeout(playTick, framePeriod());
  }

  function framePeriod() {
    return 1000 / (FRAMES_PER_SECOND * state.speed);
  }

  /** Advances one frame (looping); the next tick is one period after this one started. */
  async function playTick() {
    const started = performance.now();
    const next = (state.main.wanted + 1) % state.manifest.frames.length;
    state.ui.frame.value = String(next);
    await showFrame(next);
    if (!state.playing) return;
    const wait = Math.max(0, framePeriod() - (performance.now() - started));
    state.timer = setTimeout(playTick, wait);
  }

  // Views ---------------------------------------------------------------------------------

  /** Sizes every pane's canvas to the current camera. */
  function resizePanes() {
    for (const pane of [state.main, state.compare]) {
      if (pane) pane.renderer.resize(state.camera.width, state.camera.height);
    }
  }

  /** Makes `camera` the view of both panes; `index` is the scene camera it is, or -1. */
  function setView(camera, index) {
    state.camera = camera;
    state.cameraIndex = index;
    state.viewVersion += 1;
    resizePanes();
    state.ui.cameras.querySelectorAll('button').forEach((b, i) => b.classList.toggle('active', i === index));
    requestDraw();
  }

  /** Jumps to scene camera `index` exactly; the orbit turns about the world axis nearest its up. */
  function useSceneCamera(index) {
    const cam = state.manifest.cameras[index];
    state.target = state.home.centre.slice();
    state.up = nearestAxis(scale(cam.rotation[1], -1));
    setView(checkCamera(cam, cam.name), index);
  }

  /** The first scene camera, or the default view of the first frame. */
  function resetView() {
    if (state.manifest.cameras.length > 0) {
      useSceneCamera(0);
      return;
    }
    state.target = state.home.centre.slice();
    state.up = [0, 1, 0];
    setView(defaultCamera(state.home.centre, state.home.radius), -1);
  }

  // Controls ------------------------------------------------------------------------------

  /** Fills the controls from the manifest and connects them. */
  function setUpControls() {
    const { ui, manifest } = state;
    ui.title.textContent = manifest.title;
    document.title = `velox view: ${manifest.title}`;
    ui.frame.max = String(manifest.frames.length - 1);
    ui.frame.value = '0';
    ui.frame.addEventListener('input', () => showFrame(Number(ui.frame.value)));
    ui.play.addEventListener('click', () => setPlaying(!state.playing));
    ui.speed.addEventListener('change', () => {
      state.speed = Number(ui.speed.value) || 1;
      if (state.playing) setPlaying(true);
    });
    ui.reset.addEventListener('click', resetView);
    addCameraButtons();
    connectMouse(ui.canvas);
    // The checkboxes show only when there is something to switch.
    ui.showCompare.closest('label').hidden = !state.compare;
    ui.showTracks.closest('label').hidden = !manifest.tracks;
    ui.showTracks.closest('.row').hidden = !state.compare && !manifest.tracks;
    ui.showTracks.addEventListener('change', requestDraw);
    if (state.compare) {
      ui.showCompare.addEventListener('change', () => setCompareVisible(ui.showCompare.checked));
      connectMouse(ui.canvasCompare);
    }
  }

  function addCameraButtons() {
    const { ui, manifest } = state;
    ui.cameras.textContent = '';
    if (manifest.cameras.length === 0) ui.cameras.textContent = 'none in this manifest';
    manifest.cameras.forEach((cam, i) => {
      const button = document.createElement('button');
      button.type = 'button';
      button.id = `camera-${i}`;
      button.textContent = cam.name;
      button.title = `${cam.width}x${cam.height}, fx ${formatNumber(cam.fx)}, fy ${formatNumber(cam.fy)}`;
      button.addEventListener('click', () => useSceneCamera(i));
      ui.cameras.appendChild(button);
    });
  }

  /**
   * Left drag orbits, right or shift+left drag pans, the wheel zooms; on either pane's
   * canvas, moving the one view both show.
   */
  function connectMouse(canvas) {
    let drag = null;
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      const panning = e.button === 2 || (e.button === 0 && e.shiftKey);
      if (!state.camera || (e.button !== 0 && !panning)) return;
      drag = { mode: panning ? 'pan' : 'orbit', x: e.clientX, y: e.clientY };
      canvas.setPointerCapture(e.pointerId);
      canvas.classList.add('dragging');
      e.preventDefault();
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      // CSS pixels to drawing-buffer pixels.
      const s = canvas.width / (canvas.clientWidth || canvas.width);
      const dx = (e.clientX - drag.x) * s;
      const dy = (e.clientY - drag.y) * s;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.mode === 'orbit') orbitBy(dx, dy);
      else panBy(dx, dy);
    });
    const end = () => {
      drag = null;
      canvas.classList.remove('dragging');
    };
    canvas.addEventListener('pointerup', end);
    canvas.addEventListener('pointercancel', end);
    canvas.addEventListener(
      'wheel',
      (e) => {
        if (!state.camera) return;
        e.preventDefault();
        const pixels = e.deltaY * (e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? 400 : 1);
        setView(zoom(state.camera, state.target, Math.exp(pixels * ZOOM_PER_WHEEL_PIXEL)), -1);
      },
      { passive: false },
    );
  }

  /** Orbit by a drag of (dx, dy) pixels: right turns the scene right, down raises the camera. */
  function orbitBy(dx, dy) {
    const perPixel = ORBIT_PER_CANVAS / state.camera.width;
    setView(orbit(state.camera, state.target, state.up, -dx * perPixel, dy * perPixel), -1);
  }

  function panBy(dx, dy) {
    const moved = pan(state.camera, state.target, dx, dy);
    state.target = moved.target;
    setView(moved.camera, -1);
  }

  // The URL hash --------------------------------------------------------------------------

  function hashParameters() {
    return new URLSearchParams(location.hash.replace(/^#/, ''));
  }

  /**
   * pane=main or pane=compare (which pane ui=0 shows alone), checked against the manifest;
   * returns it, or null.
   */
  function paneParameter(params) {
    const pane = params.get('pane');
    if (pane === null || pane === 'main') return pane;
    if (pane !== 'compare') showError(`pane=${pane}: use pane=main or pane=compare`, 'hash');
    else if (!state.manifest.compare) showError('pane=compare: the manifest has no compare', 'hash');
    else return pane;
    return null;
  }

  /**
   * camera=I, frame=K, tracks=0|1 and play=1, applied through the controls as a user would.
   * Returns whether a frame was asked for (else the caller shows the first).
   */
  function applyHash(params) {
    const { ui, manifest } = state;
    let frameAsked = false;
    if (params.has('camera')) {
      const button = document.getElementById(`camera-${params.get('camera')}`);
      if (button) button.click();
      else showError(`camera=${params.get('camera')}: the manifest has ${manifest.cameras.length} cameras`, 'hash');
    }
    if (params.has('tracks')) {
      const on = params.get('tracks');
      if (on === '0' || on === '1') {
        ui.showTracks.checked = on === '1';
        ui.showTracks.dispatchEvent(new Event('change', { bubbles: true }));
      } else {
        showError(`tracks=${on}: use tracks=0 or tracks=1`, 'hash');
      }
    }
    if (params.has('frame')) {
      const k = Number(params.get('frame'));
      if (Number.isInteger(k) && k >= 0 && k < manifest.frames.length) {
        ui.frame.value = String(k);
        ui.frame.dispatchEvent(new Event('input', { bubbles: true }));
        frameAsked = true;
      } else {
        showError(`frame=${params.get('frame')}: the manifest has frames 0 to ${manifest.frames.length - 1}`, 'hash');
      }
    }
    if (params.get('play') === '1') ui.play.click();
    return frameAsked;
  }

  // Benchmark (bench=1) -------------------------------------------------------------------

  /** Pictures per second for `ms` milliseconds, calling `step` before each (GPU synced). */
  async function picturesPerSecond(ms, step) {
    const start = performance.now();
    let n = 0;
    while (performance.now() - start < ms) {
      step();
      drawPane(state.main);
      state.main.renderer.finish();
      n += 1;
      await new Promise((resolve) => setTimeout(resolve, 0));
    }
    return (n * 1000) / (performance.now() - start);
  }

  /**
   * bench=1: once the first picture is up, 3 s of orbiting (sort and draw every picture),
   * then 3 s of redrawing the same view (draw only); results in data-fps and
   * data-fps-static. (They time the main pane; a compare pane is drawn between pictures.)
   */
  async function runBench() {
    while (state.drawn === 0 && !state.errors.has('main')) await new Promise((r) => setTimeout(r, 20));
    if (state.errors.has('main')) return;
    const fps = await picturesPerSecond(3000, () => orbitBy(1, 0));
    const fpsStatic = await picturesPerSecond(3000, () => {});
    document.body.dataset.fps = fps.toFixed(2);
    document.body.dataset.fpsStatic = fpsStatic.toFixed(2);
    document.body.dataset.renderTarget = state.main.renderer.target.format;
  }

  // Start ---------------------------------------------------------------------------------

  async function main() {
    state.ui = findControls();
    const params = hashParameters();
    state.bare = params.get('ui') === '0';
    if (state.bare) document.body.classList.add('bare');
    try {
      state.main = makePane(state.ui.canvas, state.ui.labelMain);
    } catch (e) {
      showError(e.message, 'fatal');
      return;
    }
    state.ui.canvas.addEventListener('webglcontextlost', () => {
      showError('the WebGL context was lost (a GPU reset, or too little GPU memory); reload the page', 'fatal');
    });
    try {
      state.manifest = await loadManifest();
    } catch (e) {
      showError(`the manifest did not load: ${e.message}`, 'fatal');
      return;
    }
    state.main.title = state.manifest.title;
    state.main.frames = state.manifest.frames;
    state.main.store = new FrameStore(state.manifest.frames);
    if (params.has('frame')) state.main.store.prefetch(Number(params.get('frame')));
    setUpCompare(paneParameter(params));
    setUpTracks();
    setUpControls();
    // The orbit's target is the first frame's centre: load it before any view is set.
    state.home = await state.main.store.get(0).then(boundingSphere, () => ({ centre: [0, 0, 0], radius: 1 }));
    resetView();
    if (!applyHash(params)) showFrame(0);
    if (params.get('bench') === '1') runBench();
  }

  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', main);
  else main();
})();
