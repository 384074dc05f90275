//! The kernel registry: SPIR-V modules compiled from `shaders/*.wgsl` at build time, and the
//! compute pipelines made from them lazily, once each, on first use.

use std::sync::{Arc, Mutex};

use ash::vk;

use crate::device::Gpu;
use crate::error::{Error, Feature, Result, VkCheck};

/// One SPIR-V module (one shader file).
pub struct ModuleSource {
    pub name: &'static str,
    pub spirv: &'static [u8],
}

/// A storage binding of an entry point and whether the entry point writes it.
#[derive(Clone, Copy, Debug)]
pub struct BindingInfo {
    pub binding: u32,
    pub writes: bool,
    /// The variable's name in the shader (and the field's in the kernel's argument struct).
    pub name: &'static str,
    /// Read as vec4s through a storage texel buffer (`texture_storage_1d<rgba32float, read>` in
    /// the shader; engine/build.rs), not as a storage buffer.
    pub texel: bool,
}

impl BindingInfo {
    /// The descriptor type the binding takes.
    pub fn descriptor_type(&self) -> vk::DescriptorType {
        if self.texel {
            vk::DescriptorType::STORAGE_TEXEL_BUFFER
        } else {
            vk::DescriptorType::STORAGE_BUFFER
        }
    }
}

/// Device features a kernel needs.
#[derive(Clone, Copy, Debug)]
pub struct Needs {
    pub f16: bool,
    pub float_atomics: bool,
    pub coop_matrix: bool,
    /// The Vulkan memory model (`vulkanMemoryModel`; naga's cooperative-matrix modules use it).
    pub memory_model: bool,
    /// Any subgroup operation, and which (`VkSubgroupFeatureFlags` bits: basic 1, vote 2,
    /// arithmetic 4, ballot 8, shuffle 16), from the capabilities the module declares.
    pub subgroups: bool,
    pub subgroup_ops: u32,
    /// The exact subgroup size the kernel is written for (`// @subgroup_size N` in its file),
    /// requested when its pipeline is made; `None` for kernels that work at any width.
    pub subgroup_size: Option<u32>,
}

/// One entry point of one shader file.
#[derive(Clone, Copy, Debug)]
pub struct KernelInfo {
    pub module: usize,
    pub file: &'static str,
    pub entry: &'static str,
    pub workgroup_size: [u32; 3],
    pub bindings: &'static [BindingInfo],
    pub push_bytes: u32,
    /// Workgroup memory the entry point uses, in bytes.
    pub shared_bytes: u32,
    pub needs: Needs,
}

impl KernelInfo {
    /// What a device with `c` lacks to run this kernel and why, naming the feature or the limit
    /// and both figures; `None` when it can run it.
    pub fn unsupported_on(&self, c: &crate::Caps) -> Option<(Feature, String)> {
        let info = self;
        let n = info.needs;
        if n.f16 && !(c.f16_arithmetic && c.f16_storage) {
            return Some((Feature::F16, "f16 arithmetic and 16-bit storage".into()));
        }
        if n.float_atomics && !c.float_atomic_add {
            return Some((Feature::FloatAtomics, "f32 atomic add (VK_EXT_shader_atomic_float)".into()));
        }
        if n.coop_matrix && c.coop_matrix_f16.is_none() {
            return Some((
                Feature::CooperativeMatrix,
                "f16 cooperative matrices (VK_KHR_cooperative_matrix)".into(),
            ));
        }
        if info.bindings.iter().any(|b| b.texel) && !c.texel_reads {
            return Some((Feature::TexelBuffers, "storage texel buffers of R32G32B32A32_SFLOAT".into()));
        }
        if n.memory_model && !c.vulkan_memory_model {
            return Some((Feature::MemoryModel, "the Vulkan memory model (vulkanMemoryModel)".into()));
        }
        const VOTE_OR_ARITHMETIC: u32 = 2 | 4;
        const BALLOT: u32 = 8;
        const SHUFFLE: u32 = 16;
        if (n.subgroups || n.subgroup_ops & VOTE_OR_ARITHMETIC != 0) && !c.subgroup_arithmetic {
            return Some((Feature::Subgroups, "subgroup arithmetic and votes in compute shaders".into()));
        }
        if n.subgroup_ops & SHUFFLE != 0 && !c.subgroup_shuffle {
            return Some((Feature::Subgroups, "subgroup shuffles in compute shaders".into()));
        }
        if n.subgroup_ops & BALLOT != 0 && !c.subgroup_ballot {
            return Some((Feature::Subgroups, "subgroup ballots in compute shaders".into()));
        }
        if let Some(size) = n.subgroup_size {
            if !c.subgroup_size_fits(size) {
                return Some((
                    Feature::SubgroupSize,
                    format!(
                        "subgroups of exactly {size} invocations; the device runs {}..={}{}",
                        c.min_subgroup_size,
                        c.max_subgroup_size,
                        if c.subgroup_size_control { "" } else { " and cannot be asked for one size" }
                    ),
                ));
            }
        }
        if info.shared_bytes > c.max_shared_memory {
            return Some((
                Feature::WorkgroupMemory,
                format!(
                    "{} bytes of workgroup memory; the device has {} (maxComputeSharedMemorySize)",
                    info.shared_bytes, c.max_shared_memory
                ),
            ));
        }
        let wg = info.workgroup_size;
        let invocations = wg.iter().map(|&d| d as u64).product::<u64>();
        if invocations > c.max_workgroup_invocations as u64 {
            return Some((Feature::WorkgroupSize, format!(
                "workgroups of {invocations} invocations; the device allows {} (maxComputeWorkGroupInvocations)",
                c.max_workgroup_invocations
            )));
        }
        if wg.iter().zip(c.max_workgroup_size).any(|(&w, m)| w > m) {
            return Some((
                Feature::WorkgroupSize,
                format!(
                    "a workgroup of {wg:?}; the device allows {:?} (maxComputeWorkGroupSize)",
                    c.max_workgroup_size
                ),
            ));
        }
        if info.push_bytes > c.max_push_constants {
            return Some((
                Feature::PushConstants,
                format!(
                    "{} bytes of push constants; the device offers {} (maxPushConstantsSize)",
                    info.push_bytes, c.max_push_constants
                ),
            ));
        }
        None
    }
}

/// Index of a kernel in [`KERNELS`]; the constants below name every one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct KernelId(pub usize);

impl KernelId {
    /// Every kernel of every shader file.
    pub fn all() -> impl Iterator<Item = KernelId> {
        (0..KERNELS.len()).map(KernelId)
    }

    pub fn info(self) -> &'static KernelInfo {
        &KERNELS[self.0]
    }
    pub fn name(self) -> String {
        format!("{}::{}", self.info().file, self.info().entry)
    }
}

/// A kernel with the types of its interface: the constants below, generated from the shaders,
/// give each entry point the mirror of its `var<immediate>` struct (in [`params`]; `()` where
/// it has none) and the struct of its storage buffers by name (in [`args`]), so that a recorder
/// takes only those for it.
pub struct Kernel<P, B> {
    id: KernelId,
    interface: std::marker::PhantomData<fn() -> (P, B)>,
}

/// The argument struct of a kernel, at any lifetime of its tensors.
pub trait Binds {
    type Args<'a>: ArgList<'a>;
}

/// Tensors in binding order (an array: a dispatch allocates nothing for them).
pub trait ArgList<'a> {
    type List: AsRef<[&'a crate::tensor::Tensor]>;
    fn tensors(&self) -> Self::List;
}

impl<P, B> Clone for Kernel<P, B> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<P, B> Copy for Kernel<P, B> {}
impl<P, B> PartialEq for Kernel<P, B> {
    fn eq(&self, other: &Self) -> bool {
        self.id == other.id
    }
}
impl<P, B> Eq for Kernel<P, B> {}
impl<P, B> std::fmt::Debug for Kernel<P, B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Kernel({})", self.id.name())
    }
}

impl<P, B> Kernel<P, B> {
    const fn new(index: usize) -> Self {
        Kernel { id: KernelId(index), interface: std::marker::PhantomData }
    }
    pub const fn id(self) -> KernelId {
        self.id
    }
    pub fn info(self) -> &'static KernelInfo {
        self.id.info()
    }
    pub fn name(self) -> String {
        self.id.name()
    }
}

impl<P, B> From<Kernel<P, B>> for KernelId {
    fn from(k: Kernel<P, B>) -> KernelId {
        k.id
    }
}

include!(concat!(env!("OUT_DIR"), "/kernels.rs"));

/// A compute pipeline with its layouts.
pub(crate) struct Pipeline {
    pub pipeline: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    pub set_layout: vk::DescriptorSetLayout,
}

#[derive(Default)]
struct CacheState {
    modules: Vec<Option<vk::ShaderModule>>,
    pipelines: Vec<Option<Arc<Pipeline>>>,
}

pub(crate) struct PipelineCache {
    state: Mutex<CacheState>,
}

impl PipelineCache {
    pub fn new() -> Self {
        PipelineCache {
            state: Mutex::new(CacheState {
                modules: vec![None; MODULES.len()],
                pipelines: vec![None; KERNELS.len()],
            }),
        }
    }

    /// # Safety
    /// No pipeline may be in use.
    pub unsafe fn destroy(&self, device: &ash::Device) {
        let mut s = self.state.lock().unwrap();
        for p in s.pipelines.iter_mut().filter_map(Option::take) {
            device.destroy_pipeline(p.pipeline, None);
            device.destroy_pipeline_layout(p.layout, None);
            device.destroy_descriptor_set_layout(p.set_layout, None);
        }
        for m in s.modules.iter_mut().filter_map(Option::take) {
            device.destroy_shader_module(m, None);
        }
    }
}

impl Gpu {
    /// Whether this device can run the kernel: its features are all present and its workgroup
    /// fits the device's limits (see [`Gpu::unsupported_reason`]).
    pub fn supports(&self, kernel: impl Into<KernelId>) -> bool {
        self.unsupported_reason(kernel).is_none()
    }

    /// Why this device cannot run the kernel, naming the feature or the limit and both figures;
    /// `None` when it can (see [`KernelInfo::unsupported_on`]). Every pipeline is checked this way
    /// before it is made, so a kernel over a limit is an error that says so, never a driver's
    /// undefined behaviour.
    pub fn unsupported_reason(&self, kernel: impl Into<KernelId>) -> Option<(Feature, String)> {
        kernel.into().info().unsupported_on(self.caps())
    }

    /// Fails with [`Error::Unsupported`] (the feature, and why) when this device cannot run the
    /// kernel.
    pub fn check_supported(&self, kernel: impl Into<KernelId>) -> Result<()> {
        let kernel = kernel.into();
        match self.unsupported_reason(kernel) {
            Some((feature, why)) => {
                Err(Error::unsupported(feature, format!("kernel {} needs {why}", kernel.name())))
            }
            None => Ok(()),
        }
    }

    /// Makes the kernel's pipeline now instead of at its first dispatch: the device (and, under
    /// `VELOX_VALIDATE`, the validation layer) checks its SPIR-V and limits here.
    pub fn prepare(&self, kernel: impl Into<KernelId>) -> Result<()> {
        self.pipeline(kernel.into()).map(|_| ())
    }

    /// The pipeline for `kernel`, created on first use.
    pub(crate) fn pipeline(&self, kernel: KernelId) -> Result<Arc<Pipeline>> {
        let device = self.device();
        let mut s = self.inner.pipelines.state.lock().unwrap();
        if let Some(p) = &s.pipelines[kernel.0] {
            return Ok(p.clone());
        }
        self.check_supported(kernel)?;
        let info = kernel.info();
        let module = match s.modules[info.module] {
            Some(m) => m,
            None => {
                let src = &MODULES[info.module];
                let words = ash::util::read_spv(&mut std::io::Cursor::new(src.spirv))
                    .map_err(|e| Error::Invalid(format!("SPIR-V of {}: {e}", src.name)))?;
                let ci = vk::ShaderModuleCreateInfo::default().code(&words);
                // SAFETY: valid SPIR-V produced and validated by naga at build time.
                let m = unsafe { device.create_shader_module(&ci, None) }.vk("vkCreateShaderModule")?;
                s.modules[info.module] = Some(m);
                m
            }
        };
        let bindings: Vec<vk::DescriptorSetLayoutBinding> = info
            .bindings
            .iter()
            .map(|b| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(b.binding)
                    .descriptor_type(b.descriptor_type())
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let set_flags = if self.caps().push_descriptors {
            vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR
        } else {
            vk::DescriptorSetLayoutCreateFlags::empty()
        };
        let set_info = vk::DescriptorSetLayoutCreateInfo::default().flags(set_flags).bindings(&bindings);
        let (required_size, stage_flags) = subgroup_request(self.caps(), info);
        let mut required = vk::PipelineShaderStageRequiredSubgroupSizeCreateInfo::default()
            .required_subgroup_size(required_size.unwrap_or(0));
        // SAFETY: valid device and create infos throughout.
        unsafe {
            let set_layout =
                device.create_descriptor_set_layout(&set_info, None).vk("vkCreateDescriptorSetLayout")?;
            let ranges = [vk::PushConstantRange::default()
                .stage_flags(vk::ShaderStageFlags::COMPUTE)
                .offset(0)
                .size(info.push_bytes.next_multiple_of(4))];
            let set_layouts = [set_layout];
            let mut layout_info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
            if info.push_bytes > 0 {
                layout_info = layout_info.push_constant_ranges(&ranges);
            }
            let layout = match device.create_pipeline_layout(&layout_info, None) {
                Ok(l) => l,
                Err(e) => {
                    device.destroy_descriptor_set_layout(set_layout, None);
                    return Err(Error::Vulkan { call: "vkCreatePipelineLayout", result: e });
                }
            };
            let entry = std::ffi::CString::new(info.entry).expect("entry names have no NUL");
            let mut stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .flags(stage_flags)
                .module(module)
                .name(&entry);
            if required_size.is_some() {
                stage = stage.push_next(&mut required);
            }
            let ci = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(layout)];
            let pipeline = match device.create_compute_pipelines(vk::PipelineCache::null(), &ci, None) {
                Ok(p) => p[0],
                Err((_, e)) => {
                    device.destroy_pipeline_layout(layout, None);
                    device.destroy_descriptor_set_layout(set_layout, None);
                    return Err(Error::Vulkan { call: "vkCreateComputePipelines", result: e });
                }
            };
            let p = Arc::new(Pipeline { pipeline, layout, set_layout });
            s.pipelines[kernel.0] = Some(p.clone());
            Ok(p)
        }
    }
}

/// What a pipeline asks of the subgroups it runs with:
/// - a kernel written for one subgroup size (`Needs::subgroup_size`) asks for that size where the
///   device has subgroup size control (elsewhere [`Gpu::unsupported_reason`] has already checked
///   that it is the device's only size);
/// - a kernel that uses subgroup operations asks for full subgroups where the device allows it
///   and its workgroup's width is a multiple of the largest size it could get, so that
///   `subgroup_id`, `num_subgroups` and every lane count mean what the kernel assumes on
///   devices that vary the size between dispatches (Intel runs 8, 16 or 32).
fn subgroup_request(
    caps: &crate::Caps,
    info: &KernelInfo,
) -> (Option<u32>, vk::PipelineShaderStageCreateFlags) {
    let width = info.workgroup_size[0];
    match info.needs.subgroup_size {
        Some(size) if caps.subgroup_size_control => {
            let full = caps.compute_full_subgroups && width.is_multiple_of(size);
            let flags = if full {
                vk::PipelineShaderStageCreateFlags::REQUIRE_FULL_SUBGROUPS
            } else {
                vk::PipelineShaderStageCreateFlags::empty()
            };
            (Some(size), flags)
        }
        _ if info.needs.subgroups
            && caps.compute_full_subgroups
            && width.is_multiple_of(caps.max_subgroup_size) =>
        {
            (None, vk::PipelineShaderStageCreateFlags::REQUIRE_FULL_SUBGROUPS)
        }
        _ => (None, vk::PipelineShaderStageCreateFlags::empty()),
    }
}
