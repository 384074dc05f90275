// Batched matrix multiply for products with a narrow side (M or N of 64 or less, the widths
// of the small models): 32x32 output tiles instead of matmul.wgsl's 128x128, which would
// compute a mostly empty tile there. f32 operands, f32 accumulation, the same push constants,
// strides and output layout as matmul.wgsl (see there); host side engine/src/ops/matmul.rs.
//
// A 16x16 workgroup computes a 32x32 tile: invocation (tx, ty) owns rows 2ty, 2ty+1 and
// columns 2tx, 2tx+1. K advances 16 at a time through workgroup memory, [k][row] for A and
// [k][col] for B. Each load walks the operand's contiguous axis with consecutive invocations,
// whichever axis that is (the transposes only change strides).

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
var<immediate> pc: Params;

const TS: u32 = 32u;
const BK: u32 = 16u;

var<workgroup> a_tile: array<f32, 512>; // BK * TS
var<workgroup> b_tile: array<f32, 512>;

// The (k, row-or-column) slot that load number `i` of a tile fills: consecutive loads along
// k when k is the operand's contiguous axis, else along the rows or columns.
fn slot(i: u32, k_contiguous: bool) -> vec2<u32> {
    if k_contiguous {
        return vec2<u32>(i % BK, i / BK);
    }
    return vec2<u32>(i / TS, i % TS);
}

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let z = wid.z + pc.batch_base;
    let row0 = wid.y * TS;
    let col0 = wid.x * TS;
    let t = lid.y * 16u + lid.x;
    let a_base = z * pc.a_batch;
    let b_base = z * pc.b_batch;
    var c00 = 0.0;
    var c01 = 0.0;
    var c10 = 0.0;
    var c11 = 0.0;
    for (var k0 = 0u; k0 < pc.k; k0 += BK) {
        for (var i = t; i < BK * TS; i += 256u) {
            let sa = slot(i, pc.a_col == 1u);
            let r = row0 + sa.y;
            let ka = k0 + sa.x;
            var va = 0.0;
            if r < pc.m && ka < pc.k {
                va = a[a_base + r * pc.a_row + ka * pc.a_col];
            }
            a_tile[sa.x * TS + sa.y] = va;
            let sb = slot(i, pc.b_row == 1u);
            let c = col0 + sb.y;
            let kb = k0 + sb.x;
            var vb = 0.0;
            if c < pc.n && kb < pc.k {
                vb = b[b_base + kb * pc.b_row + c * pc.b_col];
            }
            b_tile[sb.x * TS + sb.y] = vb;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let x0 = a_tile[kk * TS + 2u * lid.y];
            let x1 = a_tile[kk * TS + 2u * lid.y + 1u];
            let y0 = b_tile[kk * TS + 2u * lid.x];
            let y1 = b_tile[kk * TS + 2u * lid.x + 1u];
            c00 += x0 * y0;
            c01 += x0 * y1;
            c10 += x1 * y0;
            c11 += x1 * y1;
        }
        workgroupBarrier();
    }
    let c_base = z * pc.m * pc.n;
    let i0 = row0 + 2u * lid.y;
    let j0 = col0 + 2u * lid.x;
    let v = array<f32, 4>(c00, c01, c10, c11);
    for (var q = 0u; q < 4u; q++) {
        let i = i0 + q / 2u;
        let j = j0 + q % 2u;
        if i < pc.m && j < pc.n {
            let o = c_base + i * pc.n + j;
            var x = v[q];
            if pc.accumulate != 0u {
                x += out[o];
            }
            out[o] = x;
        }
    }
}
