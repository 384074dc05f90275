// @variants TS: 32 64
// Batched matrix multiply for products with a narrow side (M or N of 64 or less, the widths
// of the small models): TS x TS output tiles (32 or 64) instead of matmul.wgsl's 128x128,
// which would compute a mostly empty tile there. f32 operands, f32 accumulation, the same push
// constants, strides and output layout as matmul.wgsl (see there); host side
// engine/src/ops/matmul.rs, which takes TS = 32 when the narrow side is 32 or less, else 64.
//
// A 16x16 workgroup computes a TS x TS tile: invocation (tx, ty) owns the R x R outputs
// (R = TS / 16) at rows ty + 16i and columns tx + 16j, so 16 neighbouring invocations write
// 16 consecutive outputs. K advances 16 at a time through workgroup memory, [k][row] for A
// and [k][col] for B; per k each invocation reads R values of each and does R*R multiply-adds
// (R = 4: 16 per 8 reads, against 4 per 4 reads at R = 2). Each load walks the operand's
// contiguous axis with consecutive invocations, whichever axis that is (the transposes only
// change strides).

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
// [n] f32, added to each row when MATMUL_FLAG_BIAS is set (as in matmul.wgsl).
@group(0) @binding(3) var<storage, read> bias: array<f32>;
var<immediate> pc: Params;

const TS: u32 = 32u;
const R: u32 = TS / 16u;
const BK: u32 = 16u;

var<workgroup> a_tile: array<f32, BK * TS>;
var<workgroup> b_tile: array<f32, BK * TS>;

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
    var acc: array<f32, R * R>;
    for (var q = 0u; q < R * R; q++) {
        acc[q] = 0.0;
    }
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
            var x: array<f32, R>;
            var y: array<f32, R>;
            for (var i = 0u; i < R; i++) {
                x[i] = a_tile[kk * TS + lid.y + 16u * i];
                y[i] = b_tile[kk * TS + lid.x + 16u * i];
            }
            for (var i = 0u; i < R; i++) {
                for (var j = 0u; j < R; j++) {
                    acc[i * R + j] += x[i] * y[j];
                }
            }
        }
        workgroupBarrier();
    }
    let c_base = z * pc.m * pc.n;
    for (var i = 0u; i < R; i++) {
        for (var j = 0u; j < R; j++) {
            let row = row0 + lid.y + 16u * i;
            let col = col0 + lid.x + 16u * j;
            if row < pc.m && col < pc.n {
                let o = c_base + row * pc.n + col;
                var x = acc[i * R + j];
                if (pc.flags & MATMUL_FLAG_BIAS) != 0u {
                    x += bias[col];
                }
                if pc.accumulate != 0u {
                    x += out[o];
                }
                out[o] = x;
            }
        }
    }
}
