// Cloth by extended position-based dynamics (XPBD, Macklin et al. 2016), one substep at a time.
// Host side and f64 reference: engine/src/ops/cloth.rs, which gives the order of the kernels.
//
// Particles: positions x, positions at the substep's start p, velocities v (xyz rows, 3 floats
// each), inverse masses w (0 pins a particle). Distance constraints (stretch and bending) are
// solved one colour at a time: no two constraints of a colour share a particle, so a colour is
// one dispatch with no races, and the result is the same bits every run. Self-collision keeps
// particles 2 r apart: particles are sorted by hashed grid cell (the engine's radix sort), and
// each particle sums its pushes from the particles of its 27 neighbouring cells in sorted order
// (a Jacobi step: every particle reads positions and writes only its own correction). The
// ground is the plane y = ground, with friction and restitution. Gravity is along -y.

struct Params {
    n: u32,
    // The distance kernel's colour: constraints start .. start + count.
    start: u32,
    count: u32,
    // Hash table size (a power of two).
    table: u32,
    dt: f32,
    gravity: f32,
    ground: f32,
    friction: f32,
    restitution: f32,
    radius: f32,
    // Particles closer than this in the rest shape never collide (mesh neighbours).
    exclude: f32,
    cell: f32,
    // Velocity damping per second: v *= max(0, 1 - damping dt) each substep.
    damping: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<storage, read_write> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> p: array<f32>;
@group(0) @binding(2) var<storage, read_write> v: array<f32>;
@group(0) @binding(3) var<storage, read> w: array<f32>;
@group(0) @binding(4) var<storage, read> pairs: array<u32>;
@group(0) @binding(5) var<storage, read> rest: array<f32>;
@group(0) @binding(6) var<storage, read> compliance: array<f32>;
@group(0) @binding(7) var<storage, read_write> lambda: array<f32>;
@group(0) @binding(8) var<storage, read_write> keys: array<u32>;
@group(0) @binding(9) var<storage, read_write> order: array<u32>;
@group(0) @binding(10) var<storage, read> sorted_keys: array<u32>;
@group(0) @binding(11) var<storage, read> sorted_order: array<u32>;
@group(0) @binding(12) var<storage, read_write> cell_start: array<u32>;
@group(0) @binding(13) var<storage, read_write> cell_end: array<u32>;
@group(0) @binding(14) var<storage, read> rest_pos: array<f32>;
@group(0) @binding(15) var<storage, read_write> delta: array<f32>;
var<immediate> pc: Params;

fn index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * 256u + lid;
}

fn pos(i: u32) -> vec3<f32> {
    return vec3<f32>(x[3u * i], x[3u * i + 1u], x[3u * i + 2u]);
}

fn put(i: u32, q: vec3<f32>) {
    x[3u * i] = q.x;
    x[3u * i + 1u] = q.y;
    x[3u * i + 2u] = q.z;
}

fn prev(i: u32) -> vec3<f32> {
    return vec3<f32>(p[3u * i], p[3u * i + 1u], p[3u * i + 2u]);
}

// The substep's prediction: v += dt g, p = x, x += dt v (pinned particles stay).
@compute @workgroup_size(256)
fn predict(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let i = index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    let q = pos(i);
    p[3u * i] = q.x;
    p[3u * i + 1u] = q.y;
    p[3u * i + 2u] = q.z;
    if (w[i] == 0.0) {
        return;
    }
    let vy = v[3u * i + 1u] - pc.dt * pc.gravity;
    v[3u * i + 1u] = vy;
    put(i, q + pc.dt * vec3<f32>(v[3u * i], vy, v[3u * i + 2u]));
}

// One colour of distance constraints: C = |xa - xb| - rest, with compliance alpha:
// dl = (-C - alpha~ l) / (wa + wb + alpha~), alpha~ = alpha / dt^2; l += dl; xa += wa dl n,
// xb -= wb dl n, n = (xa - xb) / |xa - xb|.
@compute @workgroup_size(256)
fn distance(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let k = index(wid, nwg, lid);
    if (k >= pc.count) {
        return;
    }
    let c = pc.start + k;
    let a = pairs[2u * c];
    let b = pairs[2u * c + 1u];
    let wa = w[a];
    let wb = w[b];
    let alpha = compliance[c] / (pc.dt * pc.dt);
    let denom = wa + wb + alpha;
    if (denom == 0.0) {
        return;
    }
    let xa = pos(a);
    let xb = pos(b);
    let d = xa - xb;
    let len = length(d);
    if (len < 1e-12) {
        return;
    }
    let n = d / len;
    let dl = (-(len - rest[c]) - alpha * lambda[c]) / denom;
    lambda[c] = lambda[c] + dl;
    put(a, xa + (wa * dl) * n);
    put(b, xb - (wb * dl) * n);
}

fn cell_of(q: vec3<f32>) -> vec3<i32> {
    return vec3<i32>(floor(q / pc.cell));
}

fn hash(c: vec3<i32>) -> u32 {
    let h = (u32(c.x) * 73856093u) ^ (u32(c.y) * 19349663u) ^ (u32(c.z) * 83492791u);
    return h & (pc.table - 1u);
}

// Each particle's hashed cell, and the identity order for the sort.
@compute @workgroup_size(256)
fn hash_keys(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    keys[i] = hash(cell_of(pos(i)));
    order[i] = i;
}

// Where each hashed cell's run of the sorted particles starts and ends (the tables start
// filled with 0: an empty cell is 0 .. 0).
@compute @workgroup_size(256)
fn cell_bounds(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let s = index(wid, nwg, lid);
    if (s >= pc.n) {
        return;
    }
    let k = sorted_keys[s];
    if (s == 0u || sorted_keys[s - 1u] != k) {
        cell_start[k] = s;
    }
    if (s + 1u == pc.n || sorted_keys[s + 1u] != k) {
        cell_end[k] = s + 1u;
    }
}

// Each particle's push away from the particles within 2 r of it (those not within `exclude`
// of it in the rest shape), half the overlap each, summed in sorted order.
@compute @workgroup_size(256)
fn collide(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let i = index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    var push = vec3<f32>(0.0);
    let xi = pos(i);
    let ri = vec3<f32>(rest_pos[3u * i], rest_pos[3u * i + 1u], rest_pos[3u * i + 2u]);
    let home = cell_of(xi);
    let reach = 2.0 * pc.radius;
    // Neighbouring cells can share a hashed bucket: each bucket is visited once.
    var seen: array<u32, 27>;
    var nseen = 0u;
    for (var dz = -1; dz <= 1; dz++) {
        for (var dy = -1; dy <= 1; dy++) {
            for (var dx = -1; dx <= 1; dx++) {
                let h = hash(home + vec3<i32>(dx, dy, dz));
                var dup = false;
                for (var s = 0u; s < nseen; s++) {
                    if (seen[s] == h) {
                        dup = true;
                    }
                }
                if (dup) {
                    continue;
                }
                seen[nseen] = h;
                nseen++;
                for (var s = cell_start[h]; s < cell_end[h]; s++) {
                    let j = sorted_order[s];
                    if (j == i) {
                        continue;
                    }
                    let rj = vec3<f32>(rest_pos[3u * j], rest_pos[3u * j + 1u], rest_pos[3u * j + 2u]);
                    if (length(ri - rj) < pc.exclude) {
                        continue;
                    }
                    let d = xi - pos(j);
                    let len = length(d);
                    if (len < reach && len > 1e-9) {
                        push += (0.5 * (reach - len) / len) * d;
                    }
                }
            }
        }
    }
    if (w[i] == 0.0) {
        push = vec3<f32>(0.0);
    }
    delta[3u * i] = push.x;
    delta[3u * i + 1u] = push.y;
    delta[3u * i + 2u] = push.z;
}

@compute @workgroup_size(256)
fn apply(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    put(i, pos(i) + vec3<f32>(delta[3u * i], delta[3u * i + 1u], delta[3u * i + 2u]));
}

// The ground and the velocity update: a particle below y = ground + r is lifted onto it, its
// sideways travel this substep cut by friction (by `friction` times the depth it was lifted,
// at most all of it), and its upward speed set to `restitution` times its downward speed
// before the contact; then v = (x - p) / dt, damped.
@compute @workgroup_size(256)
fn ground(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    let i = index(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    if (w[i] == 0.0) {
        v[3u * i] = 0.0;
        v[3u * i + 1u] = 0.0;
        v[3u * i + 2u] = 0.0;
        return;
    }
    var q = pos(i);
    let o = prev(i);
    let floor_y = pc.ground + pc.radius;
    var bounce = -1.0;
    if (q.y < floor_y) {
        let depth = floor_y - q.y;
        let falling = (q.y - o.y) / pc.dt;
        q.y = floor_y;
        let slide = vec2<f32>(q.x - o.x, q.z - o.z);
        let len = length(slide);
        var keep = 0.0;
        if (len > 1e-12) {
            keep = max(0.0, 1.0 - pc.friction * depth / len);
        }
        q.x = o.x + keep * slide.x;
        q.z = o.z + keep * slide.y;
        bounce = pc.restitution * max(-falling, 0.0);
        put(i, q);
    }
    let vel = (q - o) / pc.dt * max(0.0, 1.0 - pc.damping * pc.dt);
    v[3u * i] = vel.x;
    v[3u * i + 1u] = select(vel.y, bounce, bounce >= 0.0);
    v[3u * i + 2u] = vel.z;
}
