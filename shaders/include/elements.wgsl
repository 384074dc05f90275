// The elements of a linear kernel's invocation: its first, then every `element_stride` after
// it, over the whole dispatch (a grid-stride loop). A GPU gets a workgroup of 256 per 256
// elements, so each invocation takes one; a CPU device gets one per 4096
// (`Recorder::dispatch_elements`), so each takes 16: lavapipe spends about 350 ns starting a
// workgroup and 3 ns an element on one that stores a value (measured on a fill), and 16 elements
// an invocation spread that start over 4096 of them.
fn first_element(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * 256u + lid;
}

fn element_stride(nwg: vec3<u32>) -> u32 {
    return nwg.x * nwg.y * 256u;
}
