// One pass of a stable LSD radix sort of u32 keys with 32-bit values, on one digit of up to
// 4 bits: digit = (key >> shift) & mask.
//
// Each workgroup owns a block of 4096 elements (256 invocations x 16 items).
// `histogram`: counts the digits of the block into counts[digit * num_blocks + block] (by
// workgroup atomics; `histogram_subgroups`, below, where subgroup adds are offered). The host
// then takes the exclusive scan of `counts` (ops::scan), which, thanks to that digit-major
// order, is where the block's first element of each digit goes: after every smaller digit, and
// after the same digit in every earlier block. That is what makes the pass stable.
// `scatter`: each invocation owns 16 consecutive elements of the block and counts their digits
// in one-hot counters, 16 digits x 16 bits packed into 8 u32 (two vec4<u32>), so a single
// workgroup-wide exclusive scan of those counters gives, for all 16 digits at once, how many
// elements of each digit the earlier invocations own (a block counts at most 4096 < 2^16 per
// digit, so the fields never carry into each other). An element's rank within its digit is
// that count plus the count in the invocation's own earlier elements. One scan a block (rather
// than one per 256-element chunk) made the scatter 17x faster on lavapipe. The scan uses
// workgroup memory only: no assumption on the subgroup size.
//
// `block`: every pass of a sort of at most one block (n <= 4096) in one workgroup, one
// dispatch in all: the scatter's ranks, with the digit bases taken from the block's own totals
// (what the histogram and the scan give for one block), the passes ping-ponging between
// keys_out/values_out and keys_tmp/values_tmp so that the last one writes the output. Small
// sorts (attention windows, a frame's Gaussians, the encoder's cells) took three dispatches a
// pass, 24 for 32-bit keys.

// @include sort_params.wgsl

const WG: u32 = 256u;
const ITEMS: u32 = 16u; // per invocation
const BLOCK: u32 = 4096u; // WG * ITEMS

@group(0) @binding(6) var<storage, read_write> keys_tmp: array<u32>;
@group(0) @binding(7) var<storage, read_write> values_tmp: array<u32>;

var<workgroup> hist: array<atomic<u32>, 16>;

// The histogram kernels' start: the block's counters zeroed, and the zeros visible.
fn clear_hist(lid: u32) {
    if (lid < 16u) {
        atomicStore(&hist[lid], 0u);
    }
    workgroupBarrier();
}

// Their end: once every invocation has added its share, the block's counts to `counts`.
fn write_hist(lid: u32, block: u32) {
    workgroupBarrier();
    if (lid < 16u) {
        counts[lid * pc.num_blocks + block] = atomicLoad(&hist[lid]);
    }
}

// Element c of invocation lid's share of the block, strided so that neighbouring invocations
// read neighbouring keys.
fn strided(block: u32, c: u32, lid: u32) -> u32 {
    return block * BLOCK + c * WG + lid;
}

@compute @workgroup_size(256)
fn histogram(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let block = wid.x + wid.y * nwg.x;
    if (block >= pc.num_blocks) {
        return;
    }
    clear_hist(lid);
    for (var c = 0u; c < ITEMS; c = c + 1u) {
        let i = strided(block, c, lid);
        if (i < pc.n) {
            atomicAdd(&hist[(keys_in[i] >> pc.shift) & pc.mask], 1u);
        }
    }
    write_hist(lid, block);
}

// `histogram_subgroups`: the same counts without an atomic add per element, where the device
// has subgroup arithmetic. Each invocation counts its 16 elements' digits in packed one-hot
// counters (as `scatter` does: 16-bit fields, which a block's at most 4096 of a digit never
// overflow), the subgroup adds its lanes' counters (two subgroupAdds of vec4<u32>), and one
// lane a subgroup adds the 16 totals into workgroup memory: 16 atomic adds a subgroup, not one
// an element all contending for 16 counters. Works at any subgroup size.
@compute @workgroup_size(256)
fn histogram_subgroups(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                       @builtin(local_invocation_index) lid: u32,
                       @builtin(subgroup_invocation_id) lane: u32) {
    // Uniform over the workgroup: the subgroup adds below see every lane.
    let block = wid.x + wid.y * nwg.x;
    if (block >= pc.num_blocks) {
        return;
    }
    clear_hist(lid);
    var lo = vec4<u32>(0u);
    var hi = vec4<u32>(0u);
    for (var c = 0u; c < ITEMS; c = c + 1u) {
        let i = strided(block, c, lid);
        if (i < pc.n) {
            let h = one_hot((keys_in[i] >> pc.shift) & pc.mask);
            lo = lo + h.lo;
            hi = hi + h.hi;
        }
    }
    lo = subgroupAdd(lo);
    hi = subgroupAdd(hi);
    if (lane == 0u) {
        for (var d = 0u; d < 16u; d = d + 1u) {
            let count = field(lo, hi, d);
            if (count != 0u) {
                atomicAdd(&hist[d], count);
            }
        }
    }
    write_hist(lid, block);
}

// Packed per-digit counters: word w = digit / 2 of lo (w < 4) or hi (w >= 4), 16 bits at
// (digit % 2) * 16. Two rows so each scan step reads one and writes the other.
var<workgroup> scan_lo: array<array<vec4<u32>, WG>, 2>;
var<workgroup> scan_hi: array<array<vec4<u32>, WG>, 2>;
// Where the block's first element of each digit goes in the output.
var<workgroup> base: array<u32, 16>;

// The 16-bit counter of `digit` in a packed pair.
fn field(lo: vec4<u32>, hi: vec4<u32>, digit: u32) -> u32 {
    let w = digit >> 1u;
    let word = select(lo, hi, w >= 4u)[w & 3u];
    return (word >> ((digit & 1u) * 16u)) & 0xffffu;
}

// One-hot packed counter of `digit` (see `field`), as its lo and hi halves (a struct, not an
// array: arrays do not cross function boundaries in the kernels, see engine/build.rs).
struct Halves {
    lo: vec4<u32>,
    hi: vec4<u32>,
}

fn one_hot(digit: u32) -> Halves {
    let one = vec4<u32>(1u << ((digit & 1u) * 16u));
    let w = vec4<u32>(digit >> 1u);
    let lanes = vec4<u32>(0u, 1u, 2u, 3u);
    return Halves(select(vec4<u32>(0u), one, lanes == w), select(vec4<u32>(0u), one, lanes + 4u == w));
}

// The inclusive scan of every invocation's packed counters over the workgroup (Hillis-Steele,
// all 16 counters at once): this invocation's, and the scan row that holds them all (its entry
// WG - 1 has the block's totals).
struct Scanned {
    lo: vec4<u32>,
    hi: vec4<u32>,
    row: u32,
}

fn scan_counters(lid: u32, own_lo: vec4<u32>, own_hi: vec4<u32>) -> Scanned {
    var lo = own_lo;
    var hi = own_hi;
    scan_lo[0][lid] = lo;
    scan_hi[0][lid] = hi;
    workgroupBarrier();
    var cur = 0u;
    for (var offset = 1u; offset < WG; offset = offset << 1u) {
        if (lid >= offset) {
            lo = lo + scan_lo[cur][lid - offset];
            hi = hi + scan_hi[cur][lid - offset];
        }
        scan_lo[1u - cur][lid] = lo;
        scan_hi[1u - cur][lid] = hi;
        cur = 1u - cur;
        workgroupBarrier();
    }
    return Scanned(lo, hi, cur);
}

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let block = wid.x + wid.y * nwg.x;
    if (block >= pc.num_blocks) {
        return;
    }
    if (lid < 16u) {
        base[lid] = offsets[lid * pc.num_blocks + block];
    }
    // This invocation owns ITEMS consecutive elements of the block, so block order is
    // invocation-major. The scan's first barrier also publishes `base`.
    let first = block * BLOCK + lid * ITEMS;
    var keys: array<u32, ITEMS>;
    var lo = vec4<u32>(0u);
    var hi = vec4<u32>(0u);
    for (var j = 0u; j < ITEMS; j = j + 1u) {
        if (first + j < pc.n) {
            keys[j] = keys_in[first + j];
            let h = one_hot((keys[j] >> pc.shift) & pc.mask);
            lo = lo + h.lo;
            hi = hi + h.hi;
        }
    }
    // Exclusive counts: the elements of each digit in earlier invocations.
    let counts = scan_counters(lid, lo, hi);
    lo = counts.lo - lo;
    hi = counts.hi - hi;
    for (var j = 0u; j < ITEMS; j = j + 1u) {
        let i = first + j;
        if (i < pc.n) {
            let digit = (keys[j] >> pc.shift) & pc.mask;
            let dest = base[digit] + field(lo, hi, digit);
            keys_out[dest] = keys[j];
            var value = i;
            if (pc.iota == 0u) {
                value = values_in[i];
            }
            values_out[dest] = value;
            let h = one_hot(digit);
            lo = lo + h.lo;
            hi = hi + h.hi;
        }
    }
}

// Buffers of the `block` passes: 0 the input, 1 the output, 2 the scratch pair.
fn block_key(buf: u32, i: u32) -> u32 {
    if (buf == 0u) {
        return keys_in[i];
    }
    if (buf == 1u) {
        return keys_out[i];
    }
    return keys_tmp[i];
}

fn block_value(buf: u32, i: u32) -> u32 {
    if (buf == 0u) {
        if (pc.iota != 0u) {
            return i;
        }
        return values_in[i];
    }
    if (buf == 1u) {
        return values_out[i];
    }
    return values_tmp[i];
}

fn block_store(buf: u32, i: u32, key: u32, value: u32) {
    if (buf == 1u) {
        keys_out[i] = key;
        values_out[i] = value;
    } else {
        keys_tmp[i] = key;
        values_tmp[i] = value;
    }
}

@compute @workgroup_size(256)
fn block(@builtin(local_invocation_index) lid: u32) {
    let passes = (pc.key_bits + 3u) / 4u;
    let first = lid * ITEMS;
    var src = 0u;
    for (var p = 0u; p < passes; p = p + 1u) {
        // The last pass writes the output: the passes before alternate back from it.
        let dst = select(2u, 1u, (passes - 1u - p) % 2u == 0u);
        let shift = p * 4u;
        let mask = (1u << min(4u, pc.key_bits - shift)) - 1u;
        var keys: array<u32, ITEMS>;
        var values: array<u32, ITEMS>;
        var lo = vec4<u32>(0u);
        var hi = vec4<u32>(0u);
        for (var j = 0u; j < ITEMS; j = j + 1u) {
            if (first + j < pc.n) {
                keys[j] = block_key(src, first + j);
                values[j] = block_value(src, first + j);
                let h = one_hot((keys[j] >> shift) & mask);
                lo = lo + h.lo;
                hi = hi + h.hi;
            }
        }
        let counts = scan_counters(lid, lo, hi);
        // The block's totals per digit (the last invocation's inclusive counts), and where
        // each digit starts: after every smaller one.
        if (lid == 0u) {
            let total_lo = scan_lo[counts.row][WG - 1u];
            let total_hi = scan_hi[counts.row][WG - 1u];
            var at = 0u;
            for (var d = 0u; d < 16u; d = d + 1u) {
                base[d] = at;
                at = at + field(total_lo, total_hi, d);
            }
        }
        workgroupBarrier();
        lo = counts.lo - lo;
        hi = counts.hi - hi;
        for (var j = 0u; j < ITEMS; j = j + 1u) {
            if (first + j < pc.n) {
                let digit = (keys[j] >> shift) & mask;
                block_store(dst, base[digit] + field(lo, hi, digit), keys[j], values[j]);
                let h = one_hot(digit);
                lo = lo + h.lo;
                hi = hi + h.hi;
            }
        }
        // The pass's writes are the next pass's reads; and the scan rows and bases are
        // reused.
        storageBarrier();
        workgroupBarrier();
        src = dst;
    }
}
