// Batched matrix multiply of f16 operands with f32 accumulation on cooperative matrices
// (VK_KHR_cooperative_matrix, FxFxF f16 x f16 -> f32 at subgroup scope). Same operation, push
// constants and bindings as `main_f16` in shaders/matmul.wgsl; host side and f64 reference in
// engine/src/ops/matmul.rs, which picks this kernel only where it fits (see below).
//
// Two front files set the fragment size and the shapes that follow from it, then include this
// body:
//   matmul_coop.wgsl   F = 16, subgroups of 32 (NVIDIA), k step BK = 32;
//   matmul_coop8.wgsl  F = 8, subgroups of 8 (lavapipe 26 and later), BK = 16.
// Each defines FragA, FragB, FragC (the fragment types), F and BK, and is compiled in five
// variants of the output tile, ROWS x COLS with each 64 or 128, and of the block of 4 x
// FRAG_COLS fragments each subgroup owns: 128 x 128 for large outputs, in blocks of 4 x 4
// (FRAG_COLS = 4: 64 x 64 a subgroup at F = 16) or 4 x 2; 128 x 64 for outputs 64 columns wide
// or narrower, 64 x 128 for 64 rows or fewer, 64 x 64 for both, in blocks of 4 x 2 (the host's
// rule and its reasoning: docs/decisions/kernels.md, "cooperative tiles" and "subgroup
// blocks").
//
// Requirements the host checks before choosing it:
// - subgroups of exactly F*F/8 invocations (32 for F = 16, 8 for F = 8): subgroup sg owns one
//   4F x FRAG_COLS*F block of the ROWS x COLS tile (4 x FRAG_COLS fragments), and each lane
//   holds 8 elements of a fragment; the workgroup is as many subgroups as the tile has blocks
//   (WG invocations in 4 x 2 blocks: 256 for 128 x 128, 128 for the half tiles, 64 for 64 x 64;
//   128 for 128 x 128 in 4 x 4 blocks);
// - the contiguous axis of each operand (K, or M for a transposed A; N, or K for a transposed
//   B) a multiple of 8, so every 16-byte read of 8 halves lies inside one row;
// - the workgroup memory the variant declares (48 KiB at F = 16 for 128 x 128, 32 KiB at F = 8;
//   the half tiles take less).
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
// 1. K advances BK at a time. Each step, the WG invocations copy the ROWSxBK op(A) tile and the
//    BKxCOLS op(B) tile from memory into workgroup memory, 16 bytes (8 halves) per read,
//    CPI_A and CPI_B reads per invocation; chunks past the matrix edge are zero.
// 2. Each operand tile keeps the layout it has in memory, so the copy never transposes: the
//    contiguous axis stays contiguous. The fragment loads absorb the transposes instead, with
//    row-major (coopLoadT) or column-major (coopLoad) addressing:
//      "along-k" layout  (A not transposed, B transposed): tile[r * RS_K + kk], r < width, kk < BK
//      "along-r" layout  (A transposed, B not transposed): tile[kk * (width + 8) + r]
//    where r is the row of op(A) or the column of op(B) within the tile and width is ROWS for A,
//    COLS for B. Rows are padded by 8 halves (RS_K = BK + 8; width + 8), so consecutive rows
//    start at different 16-byte offsets modulo 128 bytes and a fragment read spreads over the
//    banks. Every stride is a multiple of 16 bytes and every fragment origin 16-byte aligned, as
//    cooperative loads want.
// 3. Subgroup sg owns tile rows wr + [0, 4F) and columns wc + [0, FRAG_COLS*F), with
//    wr = (sg / BLOCKS_PER_ROW) * 4F and wc = (sg % BLOCKS_PER_ROW) * FRAG_COLS*F,
//    BLOCKS_PER_ROW = COLS / (FRAG_COLS*F) (subgroup_id, not the invocation index, so nothing
//    assumes how the driver groups invocations): 4 x FRAG_COLS accumulators of FxF. Per F-wide
//    k slice it loads 4 A and FRAG_COLS B fragments and issues 4 * FRAG_COLS multiply-adds:
//    each fragment load feeds 1.33 products in 4 x 2 blocks, 2 in 4 x 4 blocks.
// 4. Two workgroup-memory buffers alternate: while step s is multiplied out of one, step s+1 is
//    read from memory into registers and then written to the other; one barrier per step.
// 5. Output: a tile entirely inside the matrix, with n a multiple of 4 (16-byte row stride),
//    stores its accumulators straight to memory (coopStoreT, row stride n), adding what is there
//    when accumulating. An edge tile stages each FxF fragment through workgroup memory (one slot
//    per subgroup, WG * 8 floats in all) and writes only the elements inside the matrix.

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<vec4<u32>>;
@group(0) @binding(1) var<storage, read> b: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
var<immediate> pc: Params;

// Invocations per subgroup, blocks of 4F x FRAG_COLS*F per row of the tile, and invocations.
const SG: u32 = F * F / 8u;
const BLOCKS_PER_ROW: u32 = COLS / (FRAG_COLS * F);
const WG: u32 = (ROWS / (4u * F)) * BLOCKS_PER_ROW * SG;
// Row strides (halves) of the "along-k" layout and of the "along-r" layouts of A and B.
const RS_K: u32 = BK + 8u;
const RS_RA: u32 = ROWS + 8u;
const RS_RB: u32 = COLS + 8u;
// Halves per operand tile, the larger of its two layouts.
const REGION_A: u32 = max(ROWS * RS_K, BK * RS_RA);
const REGION_B: u32 = max(COLS * RS_K, BK * RS_RB);
const REGIONS: u32 = REGION_A + REGION_B;
// Chunks of 8 halves per invocation and operand tile (ROWS * BK / 8 chunks over WG invocations).
const CPI_A: u32 = ROWS * BK / 8u / WG;
const CPI_B: u32 = COLS * BK / 8u / WG;

// [buffer 0..1][operand A, then B], four halves an element: every offset and stride in the tiles
// is a multiple of 8 halves, so the kernel addresses halves and divides by 4 at each access
// (fragment loads read the vec4<f16> elements with strides in their units, as cooperative loads
// allow).
var<workgroup> tiles: array<vec4<f16>, 2u * REGIONS / 4u>;
// One FxF f32 fragment per subgroup for the edge epilogue.
var<workgroup> stage: array<f32, WG * 8u>;

// Position (r, kk) of the first half of chunk c in a tile `width` rows of op(A) (columns of
// op(B)) wide. Along-k: BK/8 chunks per row of BK k, so neighbouring invocations read one row's
// 2*BK bytes. Along-r: width/8 chunks per k row, so that many neighbouring invocations read
// 2*width consecutive bytes.
fn chunk_pos(c: u32, along_k: bool, width: u32) -> vec2<u32> {
    if along_k {
        return vec2<u32>(c / (BK / 8u), (c % (BK / 8u)) * 8u);
    }
    return vec2<u32>((c % (width / 8u)) * 8u, c / (width / 8u));
}

fn tile_offset(pos: vec2<u32>, along_k: bool, width: u32) -> u32 {
    if along_k {
        return pos.x * RS_K + pos.y;
    }
    return pos.y * (width + 8u) + pos.x;
}

// Chunk c of the op(A) tile at rows row0.., k k0.. (zero outside the matrix). A chunk is either
// wholly inside or wholly outside, because the contiguous axis is a multiple of 8; its first
// element index is a multiple of 8 for the same reason, so index / 8 addresses it exactly.
fn load_a(z: u32, row0: u32, k0: u32, c: u32, ta: bool) -> vec4<u32> {
    let pos = chunk_pos(c, !ta, ROWS);
    let i = row0 + pos.x;
    let kk = k0 + pos.y;
    if i < pc.m && kk < pc.k {
        return a[(z * pc.a_batch + i * pc.a_row + kk * pc.a_col) / 8u];
    }
    return vec4<u32>(0u);
}

// Chunk c of the op(B) tile at columns col0.., k k0...
fn load_b(z: u32, col0: u32, k0: u32, c: u32, tb: bool) -> vec4<u32> {
    let pos = chunk_pos(c, tb, COLS);
    let j = col0 + pos.x;
    let kk = k0 + pos.y;
    if j < pc.n && kk < pc.k {
        return b[(z * pc.b_batch + kk * pc.b_row + j * pc.b_col) / 8u];
    }
    return vec4<u32>(0u);
}

// Writes the 8 halves of a chunk at halves o..o+8 of the tiles (o a multiple of 8): two
// 8-byte stores of four halves each, the lower half of each word first in memory as in the
// buffer. (naga 30 has no size-changing bitcast, so the words are written as a round trip
// through f32, vec2<f16>(unpack2x16float(w)), which engine/build.rs turns back into a bitcast
// in the SPIR-V: no conversion is executed.)
fn put(o: u32, v: vec4<u32>) {
    let q = o / 4u;
    tiles[q] = vec4<f16>(vec2<f16>(unpack2x16float(v.x)), vec2<f16>(unpack2x16float(v.y)));
    tiles[q + 1u] = vec4<f16>(vec2<f16>(unpack2x16float(v.z)), vec2<f16>(unpack2x16float(v.w)));
}

// The chunks one invocation moves per step: chunks t + WG q of each operand, q < CPI_A, CPI_B.
struct Chunks {
    a: array<vec4<u32>, CPI_A>,
    b: array<vec4<u32>, CPI_B>,
}

// Reads this invocation's chunks of the step at k k0.
fn load_chunks(z: u32, row0: u32, col0: u32, k0: u32, t: u32, ta: bool, tb: bool) -> Chunks {
    var c: Chunks;
    for (var q = 0u; q < CPI_A; q++) {
        c.a[q] = load_a(z, row0, k0, t + WG * q, ta);
    }
    for (var q = 0u; q < CPI_B; q++) {
        c.b[q] = load_b(z, col0, k0, t + WG * q, tb);
    }
    return c;
}

// Stores this invocation's chunks into buffer buf.
fn put_chunks(buf: u32, t: u32, ta: bool, tb: bool, c: Chunks) {
    let base_a = buf * REGIONS;
    let base_b = base_a + REGION_A;
    for (var q = 0u; q < CPI_A; q++) {
        put(base_a + tile_offset(chunk_pos(t + WG * q, !ta, ROWS), !ta, ROWS), c.a[q]);
    }
    for (var q = 0u; q < CPI_B; q++) {
        put(base_b + tile_offset(chunk_pos(t + WG * q, tb, COLS), tb, COLS), c.b[q]);
    }
}

// The FxF op(A) fragment at tile rows r.., k kk.. from the A tile at `base`.
// Along-k (A not transposed): element (row x, col y) at base + (r + x) * RS_K + kk + y:
// row-major. Along-r (A transposed): element (x, y) at base + (kk + y) * RS_RA + r + x:
// column-major.
fn frag_a(base: u32, r: u32, kk: u32) -> FragA {
    if (pc.flags & MATMUL_FLAG_TRANS_A) != 0u {
        return coopLoad<FragA>(&tiles[(base + kk * RS_RA + r) / 4u], RS_RA / 4u);
    }
    return coopLoadT<FragA>(&tiles[(base + r * RS_K + kk) / 4u], RS_K / 4u);
}

// The FxF op(B) fragment at k kk.., tile columns c.. from the B tile at `base`.
// Along-r (B not transposed): element (row x = k, col y = n) at base + (kk + x) * RS_RB + c + y:
// row-major. Along-k (B transposed): at base + (c + y) * RS_K + kk + x: column-major.
fn frag_b(base: u32, c: u32, kk: u32) -> FragB {
    if (pc.flags & MATMUL_FLAG_TRANS_B) != 0u {
        return coopLoad<FragB>(&tiles[(base + c * RS_K + kk) / 4u], RS_K / 4u);
    }
    return coopLoadT<FragB>(&tiles[(base + kk * RS_RB + c) / 4u], RS_RB / 4u);
}

// Stores one accumulator of an interior tile straight to out at element o (row stride n).
fn emit_direct(v: FragC, o: u32) {
    var r = v;
    if pc.accumulate != 0u {
        r = r + coopLoadT<FragC>(&out[o], pc.n);
    }
    // naga 30 lowers coopStore without first emitting the expressions in its arguments (the
    // SPIR-V writer then panics), so each argument is bound by an earlier `let`.
    let value = r;
    let dst = &out[o];
    let stride = pc.n;
    coopStoreT(value, dst, stride);
}

// Writes one accumulator of an edge tile whose top-left element is out row i0, column j0: each
// subgroup stores its fragment row-major into its own slot of F*F floats, then each of its SG
// lanes writes the 8 of the F*F elements it reads (lane, lane + SG, ...) that lie inside the
// matrix. The workgroup barriers (a subgroup-scope one would do, but naga's subgroupBarrier
// orders only subgroup memory) make the slot's contents visible to the lanes, and keep the next
// store from overwriting it early.
fn emit_staged(v: FragC, i0: u32, j0: u32, c_base: u32, sg: u32, lane: u32) {
    let slot = sg * F * F;
    let dst = &stage[slot];
    let stride = F;
    coopStoreT(v, dst, stride);
    workgroupBarrier();
    for (var q = 0u; q < 8u; q++) {
        let e = lane + SG * q;
        let i = i0 + e / F;
        let j = j0 + e % F;
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

@compute @workgroup_size(WG)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32,
        @builtin(subgroup_id) sg: u32, @builtin(subgroup_invocation_id) lane: u32) {
    let ta = (pc.flags & MATMUL_FLAG_TRANS_A) != 0u;
    let tb = (pc.flags & MATMUL_FLAG_TRANS_B) != 0u;
    let z = wid.z + pc.batch_base;
    let row0 = wid.y * ROWS;
    let col0 = wid.x * COLS;
    // This subgroup's 4F x FRAG_COLS*F block of the tile.
    let wr = (sg / BLOCKS_PER_ROW) * 4u * F;
    let wc = (sg % BLOCKS_PER_ROW) * FRAG_COLS * F;

    // acc[FRAG_COLS * i + j]: rows wr + F*i.., columns wc + F*j... Declared without an
    // initialiser: zero. The loops over i and j have constant bounds, so a compiler unrolls them
    // and keeps every fragment in registers.
    var acc: array<FragC, 4u * FRAG_COLS>;

    let steps = (pc.k + BK - 1u) / BK;
    put_chunks(0u, t, ta, tb, load_chunks(z, row0, col0, 0u, t, ta, tb));
    workgroupBarrier();

    for (var s = 0u; s < steps; s++) {
        let cur = s & 1u;
        let more = s + 1u < steps;
        // Prefetch step s+1 into registers while step s is multiplied out.
        var next: Chunks;
        if more {
            next = load_chunks(z, row0, col0, (s + 1u) * BK, t, ta, tb);
        }
        let base_a = cur * REGIONS;
        let base_b = base_a + REGION_A;
        for (var kk = 0u; kk < BK; kk += F) {
            var fa: array<FragA, 4>;
            for (var i = 0u; i < 4u; i++) {
                fa[i] = frag_a(base_a, wr + i * F, kk);
            }
            for (var j = 0u; j < FRAG_COLS; j++) {
                let g = frag_b(base_b, wc + j * F, kk);
                for (var i = 0u; i < 4u; i++) {
                    acc[FRAG_COLS * i + j] = coopMultiplyAdd(fa[i], g, acc[FRAG_COLS * i + j]);
                }
            }
        }
        // The other buffer was last read in step s-1, before the barrier that ended it.
        if more {
            put_chunks(cur ^ 1u, t, ta, tb, next);
        }
        workgroupBarrier();
    }

    let c_base = z * pc.m * pc.n;
    let i0 = row0 + wr;
    let j0 = col0 + wc;
    // Workgroup-uniform: depends only on the tile position and the push constants.
    let interior = row0 + ROWS <= pc.m && col0 + COLS <= pc.n && pc.n % 4u == 0u;
    for (var i = 0u; i < 4u; i++) {
        for (var j = 0u; j < FRAG_COLS; j++) {
            if interior {
                emit_direct(acc[FRAG_COLS * i + j], c_base + (i0 + i * F) * pc.n + j0 + j * F);
            } else {
                emit_staged(acc[FRAG_COLS * i + j], i0 + i * F, j0 + j * F, c_base, sg, lane);
            }
        }
    }
}
