// Batched matrix multiply on every device: out[z] = op(A)[z] @ op(B)[z] (+ a bias row), or
// out[z] += ... when accumulating, with f32 accumulation. Host side and f64 reference: engine/src/ops/matmul.rs.
// The f16 path on devices with cooperative matrices is shaders/matmul_coop.wgsl.
//
// Entry points: `main` reads f32 operands; `main_f16` reads f16 operands stored two to a 32-bit
// word and unpacks them with unpack2x16float, so it needs no 16-bit device feature at all.
//
// Operands are addressed through strides, which is how the transposes are expressed:
//   op(A)[i, kk] = A[z * a_batch + i * a_row + kk * a_col]    (i < m, kk < k)
//   op(B)[kk, j] = B[z * b_batch + kk * b_row + j * b_col]    (kk < k, j < n)
//   out[z, i, j] = out[(z * m + i) * n + j]                    (row-major, dense)
// A batch stride of 0 broadcasts an operand over the batch.
//
// Tiling: a 256-invocation workgroup computes a 128x128 tile of out. Invocation (tx, ty) of a
// 16x16 grid owns an 8x8 register block: rows ty*4 + {0..3} and 64 + ty*4 + {0..3}, columns
// tx*4 + {0..3} and 64 + tx*4 + {0..3}. Splitting each side into two 4-wide halves makes the
// shared-memory reads of neighbouring invocations consecutive vec4s (no bank conflicts), and a
// whole 8x8 block costs 4 vec4 reads per k for 64 multiply-adds.
//
// K advances BK = 8 at a time through two shared-memory buffers: while step s is multiplied out
// of one buffer, step s+1 is read from memory into registers and then written to the other, so
// one barrier per step suffices and the memory latency hides behind the arithmetic.

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<u32>;
@group(0) @binding(1) var<storage, read> b: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
// [n] f32, added to each row when MATMUL_FLAG_BIAS is set (the bias of a linear layer); otherwise
// the host binds any buffer here and nothing reads it.
@group(0) @binding(3) var<storage, read> bias: array<f32>;
var<immediate> pc: Params;

const TILE: u32 = 128u;
const BK: u32 = 8u;
// A shared-memory row holds the 128 tile values of one k plus 4 of padding (33 vec4s). Without
// the padding the scattered writes of a k-contiguous load (8 k of one row per 8 invocations)
// would all land in 4 of the 32 banks.
const ROW: u32 = 33u;
// vec4s per buffer: BK rows.
const BUF: u32 = 264u;

// [buffer][k][row / 4], two buffers.
var<workgroup> a_tile: array<vec4<f32>, 528>;
var<workgroup> b_tile: array<vec4<f32>, 528>;

fn read_a(i: u32, half: bool) -> f32 {
    if half {
        let pair = unpack2x16float(a[i >> 1u]);
        return select(pair.x, pair.y, (i & 1u) != 0u);
    }
    return bitcast<f32>(a[i]);
}

fn read_b(i: u32, half: bool) -> f32 {
    if half {
        let pair = unpack2x16float(b[i >> 1u]);
        return select(pair.x, pair.y, (i & 1u) != 0u);
    }
    return bitcast<f32>(b[i]);
}

// Where the q-th of an invocation's 4 loads of a 128x8 operand tile goes: (row, k) in the tile.
// For an operand contiguous along k, 8 neighbouring invocations read the 8 consecutive k of one
// row (one 32-byte sector); otherwise 128 neighbouring invocations read 128 consecutive rows
// (or columns, for B) of one k. Either way the memory reads coalesce.
fn slot(t: u32, q: u32, k_contiguous: bool) -> vec2<u32> {
    if k_contiguous {
        return vec2<u32>(t / BK + 32u * q, t % BK);
    }
    return vec2<u32>(t % TILE, t / TILE + 2u * q);
}

// This invocation's 4 values of the op(A) tile at rows row0.., k k0.. (zero outside the matrix).
fn load_a(z: u32, row0: u32, k0: u32, t: u32, half: bool) -> vec4<f32> {
    let k_contiguous = pc.a_col == 1u;
    var v = vec4<f32>(0.0);
    for (var q = 0u; q < 4u; q++) {
        let s = slot(t, q, k_contiguous);
        let i = row0 + s.x;
        let kk = k0 + s.y;
        if i < pc.m && kk < pc.k {
            v[q] = read_a(z * pc.a_batch + i * pc.a_row + kk * pc.a_col, half);
        }
    }
    return v;
}

// The same for op(B) at columns col0.., k k0...
fn load_b(z: u32, col0: u32, k0: u32, t: u32, half: bool) -> vec4<f32> {
    let k_contiguous = pc.b_row == 1u;
    var v = vec4<f32>(0.0);
    for (var q = 0u; q < 4u; q++) {
        let s = slot(t, q, k_contiguous);
        let j = col0 + s.x;
        let kk = k0 + s.y;
        if j < pc.n && kk < pc.k {
            v[q] = read_b(z * pc.b_batch + kk * pc.b_row + j * pc.b_col, half);
        }
    }
    return v;
}

// Writes loaded values into shared buffer `buf`, laid out [k][row].
fn store_tiles(buf: u32, t: u32, va: vec4<f32>, vb: vec4<f32>) {
    let a_kc = pc.a_col == 1u;
    let b_kc = pc.b_row == 1u;
    for (var q = 0u; q < 4u; q++) {
        let sa = slot(t, q, a_kc);
        a_tile[buf * BUF + sa.y * ROW + sa.x / 4u][sa.x % 4u] = va[q];
        let sb = slot(t, q, b_kc);
        b_tile[buf * BUF + sb.y * ROW + sb.x / 4u][sb.x % 4u] = vb[q];
    }
}

// One row of 4 results at out row i, columns j0..j0+3, guarded against the matrix edge.
fn write4(c_base: u32, i: u32, j0: u32, v: vec4<f32>) {
    if i >= pc.m {
        return;
    }
    for (var c = 0u; c < 4u; c++) {
        let j = j0 + c;
        if j < pc.n {
            let o = c_base + i * pc.n + j;
            var x = v[c];
            if (pc.flags & MATMUL_FLAG_BIAS) != 0u {
                x += bias[j];
            }
            if pc.accumulate != 0u {
                x += out[o];
            }
            out[o] = x;
        }
    }
}

fn gemm(wid: vec3<u32>, t: u32, half: bool) {
    let z = wid.z + pc.batch_base;
    let row0 = wid.y * TILE;
    let col0 = wid.x * TILE;
    let tx = t % 16u;
    let ty = t / 16u;

    // Accumulators: c<r><h> is register-block row r (0..3: tile row ty*4 + r; 4..7: tile row
    // 64 + ty*4 + r - 4), column half h (l: tx*4.., r: 64 + tx*4..).
    var c0l = vec4<f32>(0.0);
    var c0r = vec4<f32>(0.0);
    var c1l = vec4<f32>(0.0);
    var c1r = vec4<f32>(0.0);
    var c2l = vec4<f32>(0.0);
    var c2r = vec4<f32>(0.0);
    var c3l = vec4<f32>(0.0);
    var c3r = vec4<f32>(0.0);
    var c4l = vec4<f32>(0.0);
    var c4r = vec4<f32>(0.0);
    var c5l = vec4<f32>(0.0);
    var c5r = vec4<f32>(0.0);
    var c6l = vec4<f32>(0.0);
    var c6r = vec4<f32>(0.0);
    var c7l = vec4<f32>(0.0);
    var c7r = vec4<f32>(0.0);

    let steps = (pc.k + BK - 1u) / BK;
    store_tiles(0u, t, load_a(z, row0, 0u, t, half), load_b(z, col0, 0u, t, half));
    workgroupBarrier();

    for (var s = 0u; s < steps; s++) {
        let cur = s & 1u;
        let more = s + 1u < steps;
        // Prefetch the next step into registers; its memory latency overlaps the FMAs below.
        var na = vec4<f32>(0.0);
        var nb = vec4<f32>(0.0);
        if more {
            na = load_a(z, row0, (s + 1u) * BK, t, half);
            nb = load_b(z, col0, (s + 1u) * BK, t, half);
        }
        let base = cur * BUF;
        for (var kk = 0u; kk < BK; kk++) {
            let r = base + kk * ROW;
            let a_lo = a_tile[r + ty];
            let a_hi = a_tile[r + 16u + ty];
            let b_lo = b_tile[r + tx];
            let b_hi = b_tile[r + 16u + tx];
            c0l = fma(vec4<f32>(a_lo.x), b_lo, c0l);
            c0r = fma(vec4<f32>(a_lo.x), b_hi, c0r);
            c1l = fma(vec4<f32>(a_lo.y), b_lo, c1l);
            c1r = fma(vec4<f32>(a_lo.y), b_hi, c1r);
            c2l = fma(vec4<f32>(a_lo.z), b_lo, c2l);
            c2r = fma(vec4<f32>(a_lo.z), b_hi, c2r);
            c3l = fma(vec4<f32>(a_lo.w), b_lo, c3l);
            c3r = fma(vec4<f32>(a_lo.w), b_hi, c3r);
            c4l = fma(vec4<f32>(a_hi.x), b_lo, c4l);
            c4r = fma(vec4<f32>(a_hi.x), b_hi, c4r);
            c5l = fma(vec4<f32>(a_hi.y), b_lo, c5l);
            c5r = fma(vec4<f32>(a_hi.y), b_hi, c5r);
            c6l = fma(vec4<f32>(a_hi.z), b_lo, c6l);
            c6r = fma(vec4<f32>(a_hi.z), b_hi, c6r);
            c7l = fma(vec4<f32>(a_hi.w), b_lo, c7l);
            c7r = fma(vec4<f32>(a_hi.w), b_hi, c7r);
        }
        // The other buffer was last read in step s-1, before the barrier that ended it.
        if more {
            store_tiles(cur ^ 1u, t, na, nb);
        }
        workgroupBarrier();
    }

    let c_base = z * pc.m * pc.n;
    let i_lo = row0 + ty * 4u;
    let i_hi = row0 + 64u + ty * 4u;
    let j_lo = col0 + tx * 4u;
    let j_hi = col0 + 64u + tx * 4u;
    write4(c_base, i_lo, j_lo, c0l);
    write4(c_base, i_lo, j_hi, c0r);
    write4(c_base, i_lo + 1u, j_lo, c1l);
    write4(c_base, i_lo + 1u, j_hi, c1r);
    write4(c_base, i_lo + 2u, j_lo, c2l);
    write4(c_base, i_lo + 2u, j_hi, c2r);
    write4(c_base, i_lo + 3u, j_lo, c3l);
    write4(c_base, i_lo + 3u, j_hi, c3r);
    write4(c_base, i_hi, j_lo, c4l);
    write4(c_base, i_hi, j_hi, c4r);
    write4(c_base, i_hi + 1u, j_lo, c5l);
    write4(c_base, i_hi + 1u, j_hi, c5r);
    write4(c_base, i_hi + 2u, j_lo, c6l);
    write4(c_base, i_hi + 2u, j_hi, c6r);
    write4(c_base, i_hi + 3u, j_lo, c7l);
    write4(c_base, i_hi + 3u, j_hi, c7r);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    gemm(wid, t, false);
}

@compute @workgroup_size(256)
fn main_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    gemm(wid, t, true);
}
