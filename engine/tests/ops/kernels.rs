//! Every kernel of every shader file against this device: its pipeline is made, or it is
//! refused before any Vulkan call with a reason that names the feature or the limit. Under
//! `VELOX_VALIDATE` the layer checks each module's SPIR-V (spirv-val, as the layer runs it) and
//! each pipeline's limits here, including kernels no other test of the run dispatches.
//! Would catch: a kernel over the device's workgroup-memory, invocation or push-constant limit
//! made anyway (undefined behaviour on a GPU), SPIR-V a validator rejects, a pipeline the driver
//! refuses, or a refusal that does not say why.

use crate::common;
use common::*;

use velox_engine::kernels::KernelId;
use velox_engine::{Error, Feature};

#[test]
fn every_kernel_is_made_or_refused_with_a_reason() {
    let gpu = gpu();
    let caps = gpu.caps();
    let (mut made, mut refused) = (Vec::new(), Vec::new());
    for k in KernelId::all() {
        let info = k.info();
        match gpu.unsupported_reason(k) {
            None => {
                gpu.prepare(k).unwrap_or_else(|e| panic!("{}: {e}", k.name()));
                // Made pipelines fit the limits the reason would have named.
                assert!(info.shared_bytes <= caps.max_shared_memory, "{}", k.name());
                assert!(info.push_bytes <= caps.max_push_constants, "{}", k.name());
                let invocations: u32 = info.workgroup_size.iter().product();
                assert!(invocations <= caps.max_workgroup_invocations, "{}", k.name());
                made.push(k.name());
            }
            Some((feature, why)) => {
                match gpu.prepare(k) {
                    Err(Error::Unsupported { feature: f, .. }) if f == feature => {}
                    other => panic!("{}: refused for {feature:?}, prepared as {other:?}", k.name()),
                }
                refused.push(format!("{}: {why}", k.name()));
            }
        }
    }
    gpu.check_validation().unwrap();
    eprintln!("{} kernels made, {} refused:", made.len(), refused.len());
    for r in &refused {
        eprintln!("  {r}");
    }
    assert!(!made.is_empty());
}

/// Would catch: a limit check that compares with the wrong figure or lets a kernel one step over
/// a limit through (FPS's 1024-invocation kernel once declared 32772 bytes of workgroup memory,
/// 4 over lavapipe's 32768, and nothing noticed).
#[test]
fn kernels_over_a_limit_are_refused_by_name() {
    let gpu = gpu();
    let fps = velox_engine::kernels::FPS_WG1024_MAIN.info();
    let roomy = {
        let mut c = gpu.caps().clone();
        c.max_workgroup_invocations = 1024;
        c.max_workgroup_size = [1024, 1024, 64];
        c.max_shared_memory = 49152;
        c.max_push_constants = 128;
        c.subgroup_arithmetic = true;
        c
    };
    assert_eq!(fps.unsupported_on(&roomy), None);
    let refused = |edit: &dyn Fn(&mut velox_engine::Caps)| {
        let mut c = roomy.clone();
        edit(&mut c);
        fps.unsupported_on(&c).map(|(feature, _)| feature)
    };
    let one_short = fps.shared_bytes - 1;
    assert_eq!(refused(&|c| c.max_shared_memory = one_short), Some(Feature::WorkgroupMemory));
    assert_eq!(refused(&|c| c.max_workgroup_invocations = 1023), Some(Feature::WorkgroupSize));
    assert_eq!(refused(&|c| c.max_workgroup_size = [512, 1024, 64]), Some(Feature::WorkgroupSize));
    let push = fps.push_bytes - 1;
    assert_eq!(refused(&|c| c.max_push_constants = push), Some(Feature::PushConstants));
    assert_eq!(refused(&|c| c.subgroup_arithmetic = false), Some(Feature::Subgroups));
    // A kernel written for subgroups of 32 on a device of 64, and on one that can be asked for 32.
    let coop = velox_engine::kernels::MATMUL_COOP_ROWS128_COLS128_FRAG_COLS2_MAIN.info();
    assert_eq!(coop.needs.subgroup_size, Some(32));
    let mut amd = roomy.clone();
    amd.coop_matrix_f16 = Some([16, 16, 16]);
    amd.f16_arithmetic = true;
    amd.f16_storage = true;
    amd.subgroup_shuffle = true;
    (amd.min_subgroup_size, amd.max_subgroup_size, amd.subgroup_size_control) = (64, 64, false);
    assert_eq!(coop.unsupported_on(&amd).map(|u| u.0), Some(Feature::SubgroupSize));
    (amd.min_subgroup_size, amd.subgroup_size_control) = (32, true);
    assert_eq!(coop.unsupported_on(&amd), None);
}

/// Would catch: a kernel that declares more workgroup memory than 32 KiB (lavapipe, SwiftShader
/// and many mobile GPUs) without being a variant chosen by the limit.
#[test]
fn workgroup_memory_fits_32_kib_outside_the_48_kib_variants() {
    for k in KernelId::all() {
        let info = k.info();
        assert!(
            info.shared_bytes <= 32768 || info.needs.coop_matrix,
            "{} declares {} bytes of workgroup memory: only the cooperative-matrix kernels for 48 KiB \
             devices may exceed 32 KiB",
            k.name(),
            info.shared_bytes
        );
    }
}

/// The capabilities a SPIR-V module declares (its `OpCapability` operands).
fn capabilities(spirv: &[u8]) -> Vec<u32> {
    let words: Vec<u32> =
        spirv.chunks_exact(4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    let mut out = Vec::new();
    let mut at = 5;
    while at < words.len() {
        let count = ((words[at] >> 16) as usize).max(1);
        if words[at] & 0xffff == 17 && count == 2 {
            out.push(words[at + 1]);
        }
        at += count;
    }
    out
}

/// Would catch: a module that declares a capability the device is never created with (naga
/// declares f16 inputs and outputs and f16 uniform buffers for every `enable f16` module; NVIDIA
/// offers no `storageInputOutput16`, and such a module is invalid, VUID-VkShaderModuleCreateInfo-
/// pCode-08740), and kernels whose needs, read from the capabilities, do not say what they use.
#[test]
fn modules_declare_only_capabilities_the_engine_enables() {
    use velox_engine::kernels::{KERNELS, MODULES};
    // Shader, Float16, ImageBuffer (texel buffers: every Vulkan device has it, no feature),
    // GroupNonUniform{,Vote,Arithmetic,Ballot,Shuffle} (no feature: the device's supported
    // subgroup operations, which `Caps` reads), StorageBuffer16BitAccess, VulkanMemoryModel,
    // CooperativeMatrixKHR, AtomicFloat32AddEXT.
    let enabled = [1, 9, 47, 61, 62, 63, 64, 65, 4433, 5345, 6022, 6033];
    for (index, m) in MODULES.iter().enumerate() {
        let caps = capabilities(m.spirv);
        assert!(caps.contains(&1), "{}: no Shader capability (not a module?)", m.name);
        for c in &caps {
            assert!(
                enabled.contains(c),
                "{}.spv declares capability {c}, which the engine does not enable",
                m.name
            );
        }
        for k in KERNELS.iter().filter(|k| k.module == index) {
            let n = k.needs;
            let name = format!("{}::{}", k.file, k.entry);
            assert_eq!(n.f16, caps.contains(&9) || caps.contains(&4433), "{name}: f16 need");
            assert_eq!(n.coop_matrix, caps.contains(&6022), "{name}: cooperative-matrix need");
            assert_eq!(n.float_atomics, caps.contains(&6033), "{name}: float-atomics need");
            assert_eq!(n.memory_model, caps.contains(&5345), "{name}: memory-model need");
            assert_eq!(n.subgroups, caps.iter().any(|c| (61..=65).contains(c)), "{name}: subgroup need");
            assert_eq!(n.subgroup_ops & 8 != 0, caps.contains(&64), "{name}: subgroup-ballot need");
            // A module with texel buffers declares ImageBuffer, and binds them as such.
            let texel = k.bindings.iter().any(|b| b.texel);
            assert!(!texel || caps.contains(&47), "{name}: texel bindings without ImageBuffer");
        }
        if caps.contains(&47) {
            assert!(
                KERNELS.iter().any(|k| k.module == index && k.bindings.iter().any(|b| b.texel)),
                "{}: ImageBuffer without a texel binding",
                m.name
            );
        }
    }
    // The f16 and texel-buffer modules are among them, so the check saw what it is for.
    assert!(MODULES.iter().any(|m| capabilities(m.spirv).contains(&9)));
    assert!(MODULES.iter().any(|m| capabilities(m.spirv).contains(&47)));
}
