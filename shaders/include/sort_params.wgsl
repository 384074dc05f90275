// The push constants of the radix sort's passes (`sort.wgsl`, 4-bit digits, and
// `sort_bytes.wgsl`, 8-bit digits), mirrored by `Params` in engine/src/ops/sort.rs. A pass
// sorts on the digit (key >> shift) & mask.

struct Params {
    n: u32,
    num_blocks: u32,
    shift: u32,
    mask: u32,
    key_bits: u32, // `block` only: all the passes
    iota: u32,     // 1: the values are the elements' indices (values_in is not read)
}
