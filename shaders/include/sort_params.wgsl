// The push constants of the radix sort's passes (`sort.wgsl`, 4-bit digits, and
// `sort_bytes.wgsl`, 8-bit digits), mirrored by `Params` in engine/src/ops/sort.rs, and the
// bindings both take. A pass sorts on the digit (key >> shift) & mask.

struct Params {
    n: u32,
    num_blocks: u32,
    shift: u32,
    mask: u32,
    key_bits: u32, // `block` only: all the passes
    iota: u32,     // 1: the values are the elements' indices (values_in is not read)
}

@group(0) @binding(0) var<storage, read> keys_in: array<u32>;
@group(0) @binding(1) var<storage, read> values_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;
var<immediate> pc: Params;
