// Batched matrix multiply of f16 operands with f32 accumulation on cooperative matrices
// (VK_KHR_cooperative_matrix, 16x16x16 f16 x f16 -> f32 at subgroup scope). Same operation,
// push constants and bindings as `main_f16` in shaders/matmul.wgsl; host side and f64 reference
// in engine/src/ops/matmul.rs, which picks this kernel only where it fits (see below).
//
// Requirements the host checks before choosing it:
// - subgroups of exactly 32 invocations (min = max subgroup size = 32): the 256-invocation
//   workgroup is eight subgroups, each owning one 64x32 block of the 128x128 output tile;
// - the contiguous axis of each operand (K, or M for a transposed A; N, or K for a transposed
//   B) a multiple of 8, so every 16-byte read of 8 halves lies inside one row;
// - 48 KiB of workgroup memory (the H100's whole allowance: 40 KiB of operand tiles, 8 KiB to
//   stage edge fragments).
// naga requires every cooperative operation to sit in control flow it can prove uniform, which
// rules out branching on function arguments or on the subgroup id: hence one entry point with
// the body inline, the transposes as push-constant flags, and one staging slot per subgroup.
//
// Addressing (strides in halves; A batch stride 0 broadcasts):
//   op(A)[i, kk] = A[z * a_batch + i * a_row + kk * a_col]
//   op(B)[kk, j] = B[z * b_batch + kk * b_row + j * b_col]
//   out[z, i, j] = out[(z * m + i) * n + j]
//
// Data flow per workgroup (output tile rows row0.., columns col0..):
// 1. K advances BK = 32 at a time. Each step, the 256 invocations copy the 128x32 op(A) tile and
//    the 32x128 op(B) tile from memory into workgroup memory, 16 bytes (8 halves) per read, two
//    reads per operand per invocation; chunks past the matrix edge are zero.
// 2. Each operand tile keeps the layout it has in memory, so the copy never transposes: the
//    contiguous axis stays contiguous. The fragment loads absorb the transposes instead, with
//    row-major (coopLoadT) or column-major (coopLoad) addressing:
//      "along-k" layout  (A not transposed, B transposed): tile[r * 40 + kk], r < 128, kk < 32
//      "along-r" layout  (A transposed, B not transposed): tile[kk * 136 + r]
//    where r is the row of op(A) or the column of op(B) within the tile. With the padding
//    (40 = 32+8, 136 = 128+8 halves; 80 and 272 bytes) 8 consecutive rows start at 8 different
//    16-byte offsets modulo 128 bytes, so an 8x8 fragment read touches every bank once. Both strides are multiples of 16 bytes
//    and every fragment origin is 32-byte aligned, as cooperative loads want.
// 3. Subgroup sg (0..7) owns tile rows wr + [0, 64) and columns wc + [0, 32), with
//    wr = (sg / 4) * 64 and wc = (sg % 4) * 32 (subgroup_id, not the invocation index, so
//    nothing assumes how the driver groups invocations): 4x2 accumulators of 16x16. Per 16-wide k slice it loads 4 A
//    and 2 B fragments and issues 8 multiply-adds, so each fragment load feeds 2 or 4 products.
// 4. Two workgroup-memory buffers alternate: while step s is multiplied out of one, step s+1 is
//    read from memory into registers and then written to the other; one barrier per step.
// 5. Output: a tile entirely inside the matrix, with n a multiple of 4 (16-byte row stride),
//    stores its accumulators straight to memory (coopStoreT, row stride n), adding what is there
//    when accumulating. An edge tile stages each 16x16 fragment through workgroup memory (1 KiB
//    per subgroup) and writes only the elements inside the matrix.

enable f16;
enable wgpu_cooperative_matrix;

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<vec4<u32>>;
@group(0) @binding(1) var<storage, read> b: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
var<immediate> pc: Params;

const TILE: u32 = 128u;
const BK: u32 = 32u;
// Row strides (halves) of the "along-k" and "along-r" tile layouts.
const RS_K: u32 = 40u;
const RS_R: u32 = 136u;
// Halves per operand tile: the larger of 128 * 40 and 32 * 136.
const REGION: u32 = 5120u;
// Chunks of 8 halves per operand tile, and per invocation.
const CHUNKS: u32 = 512u;

// [buffer 0..1][operand A = 0, B = 1][REGION halves]: 40 KiB.
var<workgroup> tiles: array<f16, 20480>;
// One 16x16 f32 fragment per subgroup for the edge epilogue: 8 KiB.
var<workgroup> stage: array<f32, 2048>;

// Position (r, kk) in the tile of the first half of chunk c (0..511). Along-k: 4 chunks per row
// of 32 k, so 4 neighbouring invocations read one row's 64 bytes. Along-r: 16 chunks per k row
// of 128, so 16 neighbouring invocations read 256 consecutive bytes.
fn chunk_pos(c: u32, along_k: bool) -> vec2<u32> {
    if along_k {
        return vec2<u32>(c / 4u, (c % 4u) * 8u);
    }
    return vec2<u32>((c % 16u) * 8u, c / 16u);
}

fn tile_offset(pos: vec2<u32>, along_k: bool) -> u32 {
    if along_k {
        return pos.x * RS_K + pos.y;
    }
    return pos.y * RS_R + pos.x;
}

// Chunk c of the op(A) tile at rows row0.., k k0.. (zero outside the matrix). A chunk is either
// wholly inside or wholly outside, because the contiguous axis is a multiple of 8; its first
// element index is a multiple of 8 for the same reason, so index / 8 addresses it exactly.
fn load_a(z: u32, row0: u32, k0: u32, c: u32, ta: bool) -> vec4<u32> {
    let pos = chunk_pos(c, !ta);
    let i = row0 + pos.x;
    let kk = k0 + pos.y;
    if i < pc.m && kk < pc.k {
        return a[(z * pc.a_batch + i * pc.a_row + kk * pc.a_col) / 8u];
    }
    return vec4<u32>(0u);
}

// Chunk c of the op(B) tile at columns col0.., k k0...
fn load_b(z: u32, col0: u32, k0: u32, c: u32, tb: bool) -> vec4<u32> {
    let pos = chunk_pos(c, tb);
    let j = col0 + pos.x;
    let kk = k0 + pos.y;
    if j < pc.n && kk < pc.k {
        return b[(z * pc.b_batch + kk * pc.b_row + j * pc.b_col) / 8u];
    }
    return vec4<u32>(0u);
}

// Writes the 8 halves of a chunk at tiles[o..o+8]; the lower half of each word comes first in
// memory, and unpack2x16float returns it as component 0. (naga 30 does not accept the
// size-changing bitcast<vec2<f16>>(u32); the round trip through f32 is exact for every half.)
fn put(o: u32, v: vec4<u32>) {
    let h0 = vec2<f16>(unpack2x16float(v.x));
    let h1 = vec2<f16>(unpack2x16float(v.y));
    let h2 = vec2<f16>(unpack2x16float(v.z));
    let h3 = vec2<f16>(unpack2x16float(v.w));
    tiles[o] = h0.x;
    tiles[o + 1u] = h0.y;
    tiles[o + 2u] = h1.x;
    tiles[o + 3u] = h1.y;
    tiles[o + 4u] = h2.x;
    tiles[o + 5u] = h2.y;
    tiles[o + 6u] = h3.x;
    tiles[o + 7u] = h3.y;
}

// Stores the chunks this invocation loaded (c = t and t + 256 of each operand) into buffer buf.
fn put_chunks(buf: u32, t: u32, ta: bool, tb: bool, a0: vec4<u32>, a1: vec4<u32>, b0: vec4<u32>,
              b1: vec4<u32>) {
    let base_a = buf * 2u * REGION;
    let base_b = base_a + REGION;
    put(base_a + tile_offset(chunk_pos(t, !ta), !ta), a0);
    put(base_a + tile_offset(chunk_pos(t + 256u, !ta), !ta), a1);
    put(base_b + tile_offset(chunk_pos(t, tb), tb), b0);
    put(base_b + tile_offset(chunk_pos(t + 256u, tb), tb), b1);
}

// The 16x16 op(A) fragment at tile rows r.., k kk.. from the A tile at `base`.
// Along-k (A not transposed): element (row x, col y) at base + (r + x) * 40 + kk + y: row-major.
// Along-r (A transposed):     element (x, y) at base + (kk + y) * 136 + r + x: column-major.
fn frag_a(base: u32, r: u32, kk: u32) -> coop_mat16x16<f16, A> {
    if (pc.flags & 1u) != 0u {
        return coopLoad<coop_mat16x16<f16, A>>(&tiles[base + kk * RS_R + r], RS_R);
    }
    return coopLoadT<coop_mat16x16<f16, A>>(&tiles[base + r * RS_K + kk], RS_K);
}

// The 16x16 op(B) fragment at k kk.., tile columns c.. from the B tile at `base`.
// Along-r (B not transposed): element (row x = k, col y = n) at base + (kk + x) * 136 + c + y:
// row-major. Along-k (B transposed): at base + (c + y) * 40 + kk + x: column-major.
fn frag_b(base: u32, c: u32, kk: u32) -> coop_mat16x16<f16, B> {
    if (pc.flags & 2u) != 0u {
        return coopLoad<coop_mat16x16<f16, B>>(&tiles[base + c * RS_K + kk], RS_K);
    }
    return coopLoadT<coop_mat16x16<f16, B>>(&tiles[base + kk * RS_R + c], RS_R);
}

// Stores one accumulator of an interior tile straight to out at element o (row stride n).
fn emit_direct(v: coop_mat16x16<f32, C>, o: u32) {
    var r = v;
    if pc.accumulate != 0u {
        r = r + coopLoadT<coop_mat16x16<f32, C>>(&out[o], pc.n);
    }
    // naga 30 lowers coopStore without first emitting the expressions in its arguments (the
    // SPIR-V writer then panics), so each argument is bound by an earlier `let`.
    let value = r;
    let dst = &out[o];
    let stride = pc.n;
    coopStoreT(value, dst, stride);
}

// Writes one accumulator of an edge tile whose top-left element is out row i0, column j0: each
// subgroup stores its fragment row-major into its own 1 KiB slot, then each of its 32 lanes
// writes the 8 of the 256 elements it reads (lane, lane + 32, ...) that lie inside the matrix.
// The workgroup barriers (a subgroup-scope one would do, but naga's subgroupBarrier orders only
// subgroup memory) make the slot's contents visible to the lanes, and keep the next store from
// overwriting it early.
fn emit_staged(v: coop_mat16x16<f32, C>, i0: u32, j0: u32, c_base: u32, sg: u32, lane: u32) {
    let slot = sg * 256u;
    let dst = &stage[slot];
    let stride = 16u;
    coopStoreT(v, dst, stride);
    workgroupBarrier();
    for (var q = 0u; q < 8u; q++) {
        let e = lane + 32u * q;
        let i = i0 + e / 16u;
        let j = j0 + e % 16u;
        if i < pc.m && j < pc.n {
            let o = c_base + i * pc.n + j;
            var x = stage[slot + e];
            if pc.accumulate != 0u {
                x += out[o];
            }
            out[o] = x;
        }
    }
    workgroupBarrier();
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32,
        @builtin(subgroup_id) sg: u32, @builtin(subgroup_invocation_id) lane: u32) {
    let ta = (pc.flags & 1u) != 0u;
    let tb = (pc.flags & 2u) != 0u;
    let z = wid.z + pc.batch_base;
    let row0 = wid.y * TILE;
    let col0 = wid.x * TILE;
    // This subgroup's 64x32 block of the tile.
    let wr = (sg / 4u) * 64u;
    let wc = (sg % 4u) * 32u;

    // acc<i><j>: rows wr + 16i.., columns wc + 16j... Declared without initialiser: zero.
    var acc00: coop_mat16x16<f32, C>;
    var acc01: coop_mat16x16<f32, C>;
    var acc10: coop_mat16x16<f32, C>;
    var acc11: coop_mat16x16<f32, C>;
    var acc20: coop_mat16x16<f32, C>;
    var acc21: coop_mat16x16<f32, C>;
    var acc30: coop_mat16x16<f32, C>;
    var acc31: coop_mat16x16<f32, C>;

    let steps = (pc.k + BK - 1u) / BK;
    put_chunks(0u, t, ta, tb, load_a(z, row0, 0u, t, ta), load_a(z, row0, 0u, t + 256u, ta),
               load_b(z, col0, 0u, t, tb), load_b(z, col0, 0u, t + 256u, tb));
    workgroupBarrier();

    for (var s = 0u; s < steps; s++) {
        let cur = s & 1u;
        let more = s + 1u < steps;
        // Prefetch step s+1 into registers while step s is multiplied out.
        var na0 = vec4<u32>(0u);
        var na1 = vec4<u32>(0u);
        var nb0 = vec4<u32>(0u);
        var nb1 = vec4<u32>(0u);
        if more {
            let k1 = (s + 1u) * BK;
            na0 = load_a(z, row0, k1, t, ta);
            na1 = load_a(z, row0, k1, t + 256u, ta);
            nb0 = load_b(z, col0, k1, t, tb);
            nb1 = load_b(z, col0, k1, t + 256u, tb);
        }
        let base_a = cur * 2u * REGION;
        let base_b = base_a + REGION;
        for (var kk = 0u; kk < BK; kk += 16u) {
            let f0 = frag_a(base_a, wr, kk);
            let f1 = frag_a(base_a, wr + 16u, kk);
            let f2 = frag_a(base_a, wr + 32u, kk);
            let f3 = frag_a(base_a, wr + 48u, kk);
            let g0 = frag_b(base_b, wc, kk);
            let g1 = frag_b(base_b, wc + 16u, kk);
            acc00 = coopMultiplyAdd(f0, g0, acc00);
            acc01 = coopMultiplyAdd(f0, g1, acc01);
            acc10 = coopMultiplyAdd(f1, g0, acc10);
            acc11 = coopMultiplyAdd(f1, g1, acc11);
            acc20 = coopMultiplyAdd(f2, g0, acc20);
            acc21 = coopMultiplyAdd(f2, g1, acc21);
            acc30 = coopMultiplyAdd(f3, g0, acc30);
            acc31 = coopMultiplyAdd(f3, g1, acc31);
        }
        // The other buffer was last read in step s-1, before the barrier that ended it.
        if more {
            put_chunks(cur ^ 1u, t, ta, tb, na0, na1, nb0, nb1);
        }
        workgroupBarrier();
    }

    let c_base = z * pc.m * pc.n;
    let i0 = row0 + wr;
    let j0 = col0 + wc;
    // Workgroup-uniform: depends only on the tile position and the push constants.
    let interior = row0 + TILE <= pc.m && col0 + TILE <= pc.n && pc.n % 4u == 0u;
    if interior {
        let n = pc.n;
        emit_direct(acc00, c_base + i0 * n + j0);
        emit_direct(acc01, c_base + i0 * n + j0 + 16u);
        emit_direct(acc10, c_base + (i0 + 16u) * n + j0);
        emit_direct(acc11, c_base + (i0 + 16u) * n + j0 + 16u);
        emit_direct(acc20, c_base + (i0 + 32u) * n + j0);
        emit_direct(acc21, c_base + (i0 + 32u) * n + j0 + 16u);
        emit_direct(acc30, c_base + (i0 + 48u) * n + j0);
        emit_direct(acc31, c_base + (i0 + 48u) * n + j0 + 16u);
    } else {
        emit_staged(acc00, i0, j0, c_base, sg, lane);
        emit_staged(acc01, i0, j0 + 16u, c_base, sg, lane);
        emit_staged(acc10, i0 + 16u, j0, c_base, sg, lane);
        emit_staged(acc11, i0 + 16u, j0 + 16u, c_base, sg, lane);
        emit_staged(acc20, i0 + 32u, j0, c_base, sg, lane);
        emit_staged(acc21, i0 + 32u, j0 + 16u, c_base, sg, lane);
        emit_staged(acc30, i0 + 48u, j0, c_base, sg, lane);
        emit_staged(acc31, i0 + 48u, j0 + 16u, c_base, sg, lane);
    }
}
