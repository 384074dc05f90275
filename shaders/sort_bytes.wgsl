// One pass of a stable LSD radix sort of u32 keys with 32-bit values on a digit of up to 8 bits,
// digit = (key >> shift) & mask: half the passes of shaders/sort.wgsl's 4-bit digits, for GPUs
// whose subgroups have ballots and at least MIN_SUBGROUP invocations (engine/src/ops/sort.rs
// checks both, and takes these kernels only for sorts of more than one block).
//
// The passes have sort.wgsl's structure: `histogram` counts each block's digits into
// counts[digit * num_blocks + block], the host takes the exclusive scan of `counts`
// (ops::scan), which gives every (digit, block) the place its first element goes, and
// `scatter` moves each element to that place plus its rank among the block's elements of its
// digit. 256 digits are too many for sort.wgsl's per-invocation packed counters, so both
// kernels find the lanes that share a digit by subgroup ballots instead (`peers`: one ballot
// per digit bit), as GPU radix sorts with 8-bit digits do:
// - `histogram`: one lane of each group of equal digits adds the group's size to the block's
//   256 counters, so an atomic add a group, not an element.
// - `scatter`: each subgroup owns a run of SG * ITEMS consecutive elements of the block (SG its
//   size) and walks it in ITEMS rounds of SG elements. An element's rank in its digit is, in
//   that order: the elements of the digit in earlier subgroups' runs (a scan over the
//   subgroups' counts, per digit, once the rounds are done), in this subgroup's earlier rounds
//   (a running count per subgroup and digit, which one lane of each group of equal digits
//   advances with an atomic add and hands to the others by shuffle), and in this round's
//   lower lanes (a popcount of the group's ballot below the lane). Element order within a
//   block is (subgroup, round, lane), so the pass is stable.
// Elements are placed by subgroup_id and subgroup_invocation_id, so nothing assumes how the
// driver groups invocations; the workgroup must be whole subgroups (256 invocations in
// subgroups of a power of two up to 128, with full subgroups asked for where the device can:
// engine/src/kernels.rs, `subgroup_request`).

// @include sort_params.wgsl

const WG: u32 = 256u;
const ITEMS: u32 = 16u; // per invocation
const BLOCK: u32 = 4096u; // WG * ITEMS
const DIGITS: u32 = 256u;
// The smallest subgroup the kernels run with: the per-subgroup counters are sized for
// WG / MIN_SUBGROUP subgroups.
const MIN_SUBGROUP: u32 = 8u;
const MAX_SUBGROUPS: u32 = WG / MIN_SUBGROUP;
// Counters are 16 bits (a block holds at most 4096 of a digit), two digits a word.
const WORDS: u32 = DIGITS / 2u;


// `histogram`: the block's count of each digit.
var<workgroup> hist: array<atomic<u32>, DIGITS>;
// `scatter`: per subgroup and digit, its running count through the rounds, then its exclusive
// prefix over the earlier subgroups (16-bit fields, digit d in word d / 2 at (d % 2) * 16).
var<workgroup> runs: array<atomic<u32>, MAX_SUBGROUPS * WORDS>;
// `scatter`: where the block's first element of each digit goes in the output.
var<workgroup> base: array<u32, DIGITS>;

// The key at i, and whether i is an element (i < n); past the end, the last key is read and
// not used, so that every lane takes part in the ballots.
fn key_at(i: u32) -> u32 {
    return keys_in[min(i, pc.n - 1u)];
}

// The lanes of the subgroup below `lane`, as a ballot mask.
fn lanes_below(lane: u32) -> vec4<u32> {
    let word = vec4<u32>(0u, 1u, 2u, 3u);
    let at = vec4<u32>(lane / 32u);
    let partial = vec4<u32>((1u << (lane % 32u)) - 1u);
    return select(select(vec4<u32>(0u), partial, word == at), vec4<u32>(0xffffffffu), word < at);
}

fn popcount(m: vec4<u32>) -> u32 {
    let c = countOneBits(m);
    return c.x + c.y + c.z + c.w;
}

// The lowest lane of a non-empty ballot mask.
fn lowest_lane(m: vec4<u32>) -> u32 {
    if m.x != 0u {
        return firstTrailingBit(m.x);
    }
    if m.y != 0u {
        return 32u + firstTrailingBit(m.y);
    }
    if m.z != 0u {
        return 64u + firstTrailingBit(m.z);
    }
    return 96u + firstTrailingBit(m.w);
}

// The lanes of the subgroup holding an element (`valid`) whose digit is this lane's: every
// lane's ballot of each digit bit, kept where it agrees with this lane's bit. Called by every
// lane of the subgroup; empty for a lane without an element.
fn peers(digit: u32, valid: bool) -> vec4<u32> {
    var m = subgroupBallot(valid);
    if !valid {
        m = vec4<u32>(0u);
    }
    for (var b = 0u; b < 8u; b = b + 1u) {
        let bit = ((digit >> b) & 1u) != 0u;
        let ones = subgroupBallot(valid && bit);
        m = m & select(~ones, ones, bit);
    }
    return m;
}

@compute @workgroup_size(256)
fn histogram(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32,
             @builtin(subgroup_invocation_id) lane: u32) {
    // Uniform over the workgroup: every lane reaches the ballots.
    let block = wid.x + wid.y * nwg.x;
    if block >= pc.num_blocks {
        return;
    }
    atomicStore(&hist[lid], 0u);
    workgroupBarrier();
    let below = lanes_below(lane);
    for (var c = 0u; c < ITEMS; c = c + 1u) {
        // Strided, so that neighbouring lanes read neighbouring keys.
        let i = block * BLOCK + c * WG + lid;
        let valid = i < pc.n;
        let digit = (key_at(i) >> pc.shift) & pc.mask;
        let m = peers(digit, valid);
        if valid && popcount(m & below) == 0u {
            atomicAdd(&hist[digit], popcount(m));
        }
    }
    workgroupBarrier();
    counts[lid * pc.num_blocks + block] = atomicLoad(&hist[lid]);
}

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32,
           @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) nsg: u32,
           @builtin(subgroup_invocation_id) lane: u32) {
    // The subgroup's lanes, counted: the `subgroup_size` builtin is not read (lavapipe at 32
    // lanes reports 32 and runs 16; engine/src/ops/subgroup_probe.rs).
    let size = subgroupAdd(1u);
    let block = wid.x + wid.y * nwg.x;
    if block >= pc.num_blocks {
        return;
    }
    base[lid] = offsets[lid * pc.num_blocks + block];
    for (var w = lid; w < nsg * WORDS; w = w + WG) {
        atomicStore(&runs[w], 0u);
    }
    workgroupBarrier();

    // This subgroup's run of the block, walked a round of `size` elements at a time.
    let run = block * BLOCK + sg * size * ITEMS;
    let below = lanes_below(lane);
    var keys: array<u32, ITEMS>;
    var ranks: array<u32, ITEMS>;
    for (var j = 0u; j < ITEMS; j = j + 1u) {
        let i = run + j * size + lane;
        let valid = i < pc.n;
        keys[j] = key_at(i);
        let digit = (keys[j] >> pc.shift) & pc.mask;
        let m = peers(digit, valid);
        let lower = popcount(m & below);
        // The group's lowest lane advances the subgroup's count of the digit and learns what
        // it was; the group's lanes follow it in this round's order.
        var before = 0u;
        if valid && lower == 0u {
            let shift = (digit & 1u) * 16u;
            let old = atomicAdd(&runs[sg * WORDS + digit / 2u], popcount(m) << shift);
            before = (old >> shift) & 0xffffu;
        }
        let leader = select(lane, lowest_lane(m), valid);
        ranks[j] = subgroupShuffle(before, leader) + lower;
        // The next round's adds follow this one's.
        workgroupBarrier();
    }

    // Each digit's counts over the subgroups, in subgroup order, become exclusive prefixes.
    if lid < WORDS {
        var total = 0u;
        for (var s = 0u; s < nsg; s = s + 1u) {
            let count = atomicLoad(&runs[s * WORDS + lid]);
            atomicStore(&runs[s * WORDS + lid], total);
            // Both 16-bit fields at once: neither passes 4096, so neither carries.
            total = total + count;
        }
    }
    workgroupBarrier();

    for (var j = 0u; j < ITEMS; j = j + 1u) {
        let i = run + j * size + lane;
        if i < pc.n {
            let digit = (keys[j] >> pc.shift) & pc.mask;
            let prefix = (atomicLoad(&runs[sg * WORDS + digit / 2u]) >> ((digit & 1u) * 16u)) & 0xffffu;
            let dest = base[digit] + prefix + ranks[j];
            keys_out[dest] = keys[j];
            var value = i;
            if pc.iota == 0u {
                value = values_in[i];
            }
            values_out[dest] = value;
        }
    }
}
