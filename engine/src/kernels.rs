//! The kernel registry: SPIR-V modules compiled from `shaders/*.wgsl` at build time, and the
//! compute pipelines made from them lazily, once each, on first use.

use std::sync::{Arc, Mutex};

use ash::vk;

use crate::device::Gpu;
use crate::error::{Error, Result, VkCheck};

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
}

/// Device features a kernel needs.
#[derive(Clone, Copy, Debug)]
pub struct Needs {
    pub f16: bool,
    pub float_atomics: bool,
    pub coop_matrix: bool,
    pub subgroups: bool,
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

/// Index of a kernel in [`KERNELS`]; the constants below name every one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct KernelId(pub usize);

impl KernelId {
    pub fn info(self) -> &'static KernelInfo {
        &KERNELS[self.0]
    }
    pub fn name(self) -> String {
        format!("{}::{}", self.info().file, self.info().entry)
    }
}

include!(concat!(env!("OUT_DIR"), "/kernels.rs"));

/// A compute pipeline with its layouts.
pub(crate) struct Pipeline {
    pub pipeline: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
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
    /// Whether this device can run the kernel (its features are all present).
    pub fn supports(&self, kernel: KernelId) -> bool {
        self.missing_feature(kernel).is_none()
    }

    fn missing_feature(&self, kernel: KernelId) -> Option<&'static str> {
        let c = self.caps();
        let n = kernel.info().needs;
        if n.f16 && !(c.f16_arithmetic && c.f16_storage) {
            return Some("f16 arithmetic and 16-bit storage");
        }
        if n.float_atomics && !c.float_atomic_add {
            return Some("f32 atomic add (VK_EXT_shader_atomic_float)");
        }
        if n.coop_matrix && c.coop_matrix_f16.is_none() {
            return Some("f16 cooperative matrices (VK_KHR_cooperative_matrix)");
        }
        if kernel.info().shared_bytes > c.max_shared_memory {
            return Some("more workgroup memory than the device has");
        }
        None
    }

    /// The pipeline for `kernel`, created on first use.
    pub(crate) fn pipeline(&self, kernel: KernelId) -> Result<Arc<Pipeline>> {
        let device = self.device();
        let mut s = self.inner.pipelines.state.lock().unwrap();
        if let Some(p) = &s.pipelines[kernel.0] {
            return Ok(p.clone());
        }
        if let Some(missing) = self.missing_feature(kernel) {
            return Err(Error::Unsupported(format!("kernel {} needs {missing}", kernel.name())));
        }
        let info = kernel.info();
        if info.push_bytes > self.caps().max_push_constants {
            return Err(Error::Unsupported(format!(
                "kernel {} needs {} bytes of push constants, the device offers {}",
                kernel.name(),
                info.push_bytes,
                self.caps().max_push_constants
            )));
        }
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
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let set_info = vk::DescriptorSetLayoutCreateInfo::default()
            .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
            .bindings(&bindings);
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
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(&entry);
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
