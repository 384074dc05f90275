//! Device features and limits, read once when the device is opened.

use std::ffi::CStr;

use ash::vk;

use crate::error::{Error, Result};

/// Everything the kernels and the host side need to know about the device.
#[derive(Clone, Debug)]
pub struct Caps {
    pub index: usize,
    pub name: String,
    pub kind: &'static str,
    pub vendor_id: u32,
    pub api_version: String,
    pub driver: String,
    /// Subgroup size the driver reports by default, and the range it can run.
    pub subgroup_size: u32,
    pub min_subgroup_size: u32,
    pub max_subgroup_size: u32,
    /// A pipeline can ask for a subgroup size in `min..=max` (`subgroupSizeControl`, with
    /// compute among `requiredSubgroupSizeStages`).
    pub subgroup_size_control: bool,
    pub compute_full_subgroups: bool,
    /// Subgroup arithmetic (subgroupAdd and friends) in compute shaders.
    pub subgroup_arithmetic: bool,
    /// Subgroup shuffles (subgroupShuffleXor) in compute shaders.
    pub subgroup_shuffle: bool,
    /// Subgroup ballots (subgroupBallot) in compute shaders.
    pub subgroup_ballot: bool,
    pub max_shared_memory: u32,
    pub max_workgroup_invocations: u32,
    pub max_workgroup_size: [u32; 3],
    pub max_workgroup_count: [u32; 3],
    pub max_storage_buffer_range: u64,
    pub min_storage_buffer_offset_alignment: u64,
    pub max_buffer_size: u64,
    pub max_push_constants: u32,
    /// Storage texel buffers of `R32G32B32A32_SFLOAT` (a read-only vec4 view of a tensor; every
    /// Vulkan device has them), the most texels one view holds and the offset alignment of one.
    pub texel_reads: bool,
    pub max_texel_buffer_elements: u64,
    pub min_texel_buffer_offset_alignment: u64,
    /// f16 arithmetic in shaders, and 16-bit storage buffer access.
    pub f16_arithmetic: bool,
    pub f16_storage: bool,
    pub int64: bool,
    pub vulkan_memory_model: bool,
    /// Atomic add on f32 in storage buffers (VK_EXT_shader_atomic_float).
    pub float_atomic_add: bool,
    /// Every cooperative-matrix shape the device reports, as text for `velox info`.
    pub coop_matrix_shapes: Vec<String>,
    /// The FxFxF f16 x f16 -> f32 subgroup shape the cooperative kernels use, if offered:
    /// F = 16 where the device has it, else F = 8.
    pub coop_matrix_f16: Option<[u32; 3]>,
    /// Nanoseconds per timestamp tick, and whether the compute queue writes timestamps.
    pub timestamp_period_ns: f64,
    pub timestamps: bool,
    /// Every device-local memory type is host-visible (CPU devices, most integrated GPUs):
    /// tensors are mapped and read and written without staging.
    pub unified_memory: bool,
    /// Total device-local heap size, in bytes.
    pub device_memory: u64,
    /// Buffers are bound with VK_KHR_push_descriptor; where it is missing (or switched off),
    /// through ordinary descriptor sets, one per dispatch.
    pub push_descriptors: bool,
    /// The device is a portability implementation (it lists VK_KHR_portability_subset, as
    /// MoltenVK does): the engine enables the extension, as the specification requires.
    pub portability_subset: bool,
    /// The device offers `robustBufferAccess`, and whether the engine enabled it
    /// (`VELOX_ROBUST=1`): out-of-bounds reads return zero or in-bounds values and writes are
    /// dropped, instead of a device loss, at some cost in speed.
    pub robust_buffer_access_available: bool,
    pub robust_buffer_access: bool,
    /// The kernel variants shaped for CPU devices (lavapipe, SwiftShader: one SIMD group a
    /// workgroup, vec4 accesses, no workgroup barriers) instead of the GPU ones: on by default
    /// on CPU devices, set either way by `VELOX_CPU_KERNELS=1` or `0`.
    pub cpu_kernels: bool,
    /// The fallbacks forced by `VELOX_DISABLE` and `VELOX_MAX_BINDING` (see [`Switches`]), as
    /// `velox info` shows them; empty on a normal run.
    pub forced: Vec<String>,
}

/// What `VELOX_DISABLE` can switch off, so that every fallback a GPU may need runs on any
/// device: each name, and what the engine does without it.
pub const DISABLE_NAMES: &[(&str, &str)] = &[
    ("f16", "f16 arithmetic and 16-bit storage: f32 kernels only; f16 inference and training refused"),
    ("float-atomics", "f32 atomic add: scatter-add and the raster backward by compare-and-swap loops"),
    ("coop-matrix", "cooperative matrices: the portable f16 matmul and attention kernels"),
    ("push-descriptors", "VK_KHR_push_descriptor: buffers bound through descriptor sets"),
    (
        "subgroup-size-control",
        "required subgroup sizes: kernels that need one run only where the size is fixed",
    ),
];

/// The device's features and limits as switched by the environment: `VELOX_DISABLE` (a comma
/// list of [`DISABLE_NAMES`]) and `VELOX_MAX_BINDING` (bytes, with an optional K, M or G suffix
/// for KiB, MiB, GiB: the storage-binding range to assume, below the device's, so that the
/// paths that split large tensors across bindings run with small ones).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Switches {
    pub disabled: Vec<&'static str>,
    pub max_binding: Option<u64>,
    /// `VELOX_ROBUST=1`: enable robust buffer access where the device offers it.
    pub robust: bool,
    /// `VELOX_CPU_KERNELS`: the CPU devices' kernel variants forced on or off.
    pub cpu_kernels: Option<bool>,
}

impl Switches {
    /// The switches the environment sets; a name or size it cannot read is an error that lists
    /// what it accepts.
    pub fn from_env() -> Result<Switches> {
        let mut switches = Switches::parse(
            std::env::var("VELOX_DISABLE").ok().as_deref(),
            std::env::var("VELOX_MAX_BINDING").ok().as_deref(),
        )?;
        switches.cpu_kernels = match std::env::var("VELOX_CPU_KERNELS").ok().as_deref().map(str::trim) {
            None | Some("") => None,
            Some("1") => Some(true),
            Some("0") => Some(false),
            Some(other) => {
                return Err(Error::Invalid(format!(
                    "VELOX_CPU_KERNELS={other}: give 1 (the CPU devices' kernels) or 0 (the GPU ones)"
                )))
            }
        };
        switches.robust = match std::env::var("VELOX_ROBUST").ok().as_deref().map(str::trim) {
            None | Some("" | "0") => false,
            Some("1") => true,
            Some(other) => {
                return Err(Error::Invalid(format!(
                    "VELOX_ROBUST={other}: give 1 (robust buffer access) or 0"
                )))
            }
        };
        Ok(switches)
    }

    pub fn parse(disable: Option<&str>, max_binding: Option<&str>) -> Result<Switches> {
        let mut disabled = Vec::new();
        for name in disable.unwrap_or("").split([',', ' ']).map(str::trim).filter(|n| !n.is_empty()) {
            let known = DISABLE_NAMES.iter().find(|(n, _)| *n == name).ok_or_else(|| {
                let names: Vec<&str> = DISABLE_NAMES.iter().map(|(n, _)| *n).collect();
                Error::Invalid(format!("VELOX_DISABLE names {name:?}; known: {}", names.join(", ")))
            })?;
            if !disabled.contains(&known.0) {
                disabled.push(known.0);
            }
        }
        let max_binding = match max_binding.map(str::trim).filter(|v| !v.is_empty()) {
            None => None,
            Some(v) => {
                let (digits, unit) = match v.char_indices().find(|(_, c)| !c.is_ascii_digit()) {
                    Some((i, _)) => v.split_at(i),
                    None => (v, ""),
                };
                let scale: u64 = match unit.trim() {
                    "" => 1,
                    "K" | "k" => 1 << 10,
                    "M" | "m" => 1 << 20,
                    "G" | "g" => 1 << 30,
                    _ => 0,
                };
                let bytes = digits
                    .parse::<u64>()
                    .ok()
                    .and_then(|d| d.checked_mul(scale))
                    .filter(|&b| scale > 0 && b > 0);
                match bytes {
                    Some(b) if b >= 1 << 16 && b % 256 == 0 => Some(b),
                    _ => {
                        return Err(Error::Invalid(format!(
                            "VELOX_MAX_BINDING={v}: give bytes (a multiple of 256, at least 64K), \
                             with an optional K, M or G suffix"
                        )))
                    }
                }
            }
        };
        Ok(Switches { disabled, max_binding, robust: false, cpu_kernels: None })
    }

    pub fn disables(&self, name: &str) -> bool {
        self.disabled.contains(&name)
    }

    /// Applies the switches to what the device reports.
    pub fn apply(&self, caps: &mut Caps) {
        let mut forced = Vec::new();
        if self.disables("f16") {
            caps.f16_arithmetic = false;
            caps.f16_storage = false;
            caps.coop_matrix_f16 = None;
        }
        if self.disables("float-atomics") {
            caps.float_atomic_add = false;
        }
        if self.disables("coop-matrix") {
            caps.coop_matrix_f16 = None;
        }
        if self.disables("push-descriptors") {
            caps.push_descriptors = false;
        }
        if self.disables("subgroup-size-control") {
            caps.subgroup_size_control = false;
            caps.compute_full_subgroups = false;
        }
        for name in &self.disabled {
            forced.push(format!("no {name}"));
        }
        if let Some(b) = self.max_binding {
            if b < caps.max_storage_buffer_range {
                caps.max_storage_buffer_range = b;
            }
            forced.push(format!("storage bindings of at most {b} bytes"));
        }
        if let Some(on) = self.cpu_kernels {
            if on != caps.cpu_kernels {
                forced.push(format!("{} kernels", if on { "CPU" } else { "GPU" }));
            }
            caps.cpu_kernels = on;
        }
        caps.robust_buffer_access = self.robust && caps.robust_buffer_access_available;
        if self.robust {
            forced.push(if caps.robust_buffer_access {
                "robust buffer access".to_string()
            } else {
                "robust buffer access asked for, which the device does not offer".to_string()
            });
        }
        caps.forced = forced;
    }
}

fn cstr(bytes: &[c_char_t]) -> String {
    // The driver strings are NUL-terminated fixed arrays.
    let raw: Vec<u8> = bytes.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
    String::from_utf8_lossy(&raw).into_owned()
}

#[allow(non_camel_case_types)]
type c_char_t = std::ffi::c_char;

/// `VK_KHR_portability_subset` (a provisional extension, so not among ash's names).
pub(crate) const PORTABILITY_SUBSET: &CStr = c"VK_KHR_portability_subset";

fn has_ext(exts: &[vk::ExtensionProperties], name: &CStr) -> bool {
    exts.iter().any(|e| e.extension_name_as_c_str() == Ok(name))
}

fn component_name(t: vk::ComponentTypeKHR) -> &'static str {
    match t {
        vk::ComponentTypeKHR::FLOAT16 => "f16",
        vk::ComponentTypeKHR::FLOAT32 => "f32",
        vk::ComponentTypeKHR::FLOAT64 => "f64",
        vk::ComponentTypeKHR::SINT8 => "i8",
        vk::ComponentTypeKHR::UINT8 => "u8",
        vk::ComponentTypeKHR::SINT32 => "i32",
        vk::ComponentTypeKHR::UINT32 => "u32",
        _ => "other",
    }
}

impl Caps {
    pub(crate) fn query(
        entry: &ash::Entry,
        instance: &ash::Instance,
        pd: vk::PhysicalDevice,
        index: usize,
        queue_family: u32,
    ) -> Result<Caps> {
        // SAFETY: every query below reads properties of a device of this instance into
        // structures that live for the duration of the call.
        unsafe {
            let exts = instance.enumerate_device_extension_properties(pd).unwrap_or_default();
            let has_atomic_ext = has_ext(&exts, ash::ext::shader_atomic_float::NAME);
            let has_coop_ext = has_ext(&exts, ash::khr::cooperative_matrix::NAME);
            let push_descriptors = has_ext(&exts, ash::khr::push_descriptor::NAME);
            let portability_subset = has_ext(&exts, PORTABILITY_SUBSET);

            let mut p11 = vk::PhysicalDeviceVulkan11Properties::default();
            let mut p12 = vk::PhysicalDeviceVulkan12Properties::default();
            let mut p13 = vk::PhysicalDeviceVulkan13Properties::default();
            let mut props = vk::PhysicalDeviceProperties2::default()
                .push_next(&mut p11)
                .push_next(&mut p12)
                .push_next(&mut p13);
            instance.get_physical_device_properties2(pd, &mut props);
            let p = props.properties;
            let limits = p.limits;

            let mut f11 = vk::PhysicalDeviceVulkan11Features::default();
            let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
            let mut f13 = vk::PhysicalDeviceVulkan13Features::default();
            let mut fa = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
            let mut fc = vk::PhysicalDeviceCooperativeMatrixFeaturesKHR::default();
            let mut features = vk::PhysicalDeviceFeatures2::default()
                .push_next(&mut f11)
                .push_next(&mut f12)
                .push_next(&mut f13);
            if has_atomic_ext {
                features = features.push_next(&mut fa);
            }
            if has_coop_ext {
                features = features.push_next(&mut fc);
            }
            instance.get_physical_device_features2(pd, &mut features);
            let base = features.features;

            let mut coop_matrix_shapes = Vec::new();
            let mut coop_matrix_f16 = None;
            if has_coop_ext && fc.cooperative_matrix == vk::TRUE {
                let coop = ash::khr::cooperative_matrix::Instance::new(entry, instance);
                let list = coop.get_physical_device_cooperative_matrix_properties(pd).unwrap_or_default();
                for c in &list {
                    coop_matrix_shapes.push(format!(
                        "{}x{}x{} {}*{}+{}->{}{}",
                        c.m_size,
                        c.n_size,
                        c.k_size,
                        component_name(c.a_type),
                        component_name(c.b_type),
                        component_name(c.c_type),
                        component_name(c.result_type),
                        if c.scope == vk::ScopeKHR::SUBGROUP { "" } else { " (non-subgroup scope)" }
                    ));
                    // The matmul and attention kernels exist for 16x16x16 (NVIDIA) and 8x8x8
                    // (lavapipe) fragments; 16 is preferred where both are offered.
                    let size = c.m_size;
                    if (size == 16 || (size == 8 && coop_matrix_f16.is_none()))
                        && c.n_size == size
                        && c.k_size == size
                        && c.a_type == vk::ComponentTypeKHR::FLOAT16
                        && c.b_type == vk::ComponentTypeKHR::FLOAT16
                        && c.c_type == vk::ComponentTypeKHR::FLOAT32
                        && c.result_type == vk::ComponentTypeKHR::FLOAT32
                        && c.scope == vk::ScopeKHR::SUBGROUP
                    {
                        coop_matrix_f16 = Some([size; 3]);
                    }
                }
            }
            // naga's cooperative-matrix SPIR-V needs f16 storage and arithmetic too.
            let f16_arithmetic = f12.shader_float16 == vk::TRUE;
            let f16_storage = f11.storage_buffer16_bit_access == vk::TRUE;
            // ... and the Vulkan memory model, which its modules declare.
            let vulkan_memory_model =
                f12.vulkan_memory_model == vk::TRUE && f12.vulkan_memory_model_device_scope == vk::TRUE;
            if !(f16_arithmetic && f16_storage && vulkan_memory_model) {
                coop_matrix_f16 = None;
            }

            // lavapipe's image reads hold at most 8 lanes (its default 256 bits): run wider
            // (subgroups of 16 or 32, LP_NATIVE_VECTOR_WIDTH=512 or 1024) a texel fetch
            // overruns its stack and aborts the process, so a CPU device with subgroups over 8
            // reads storage buffers instead.
            let texel_reads = instance
                .get_physical_device_format_properties(pd, vk::Format::R32G32B32A32_SFLOAT)
                .buffer_features
                .contains(vk::FormatFeatureFlags::STORAGE_TEXEL_BUFFER)
                && !(p.device_type == vk::PhysicalDeviceType::CPU && p11.subgroup_size > 8);

            let families = instance.get_physical_device_queue_family_properties(pd);
            let timestamps = limits.timestamp_compute_and_graphics == vk::TRUE
                || families[queue_family as usize].timestamp_valid_bits > 0;

            let mem = instance.get_physical_device_memory_properties(pd);
            let types = &mem.memory_types[..mem.memory_type_count as usize];
            let unified_memory = types
                .iter()
                .filter(|t| t.property_flags.contains(vk::MemoryPropertyFlags::DEVICE_LOCAL))
                .all(|t| t.property_flags.contains(vk::MemoryPropertyFlags::HOST_VISIBLE))
                || p.device_type == vk::PhysicalDeviceType::CPU;
            let device_memory = mem.memory_heaps[..mem.memory_heap_count as usize]
                .iter()
                .filter(|h| h.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL))
                .map(|h| h.size)
                .sum();

            Ok(Caps {
                index,
                name: p.device_name_as_c_str().unwrap_or(c"?").to_string_lossy().into_owned(),
                kind: match p.device_type {
                    vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
                    vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
                    vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
                    vk::PhysicalDeviceType::CPU => "CPU",
                    _ => "other",
                },
                vendor_id: p.vendor_id,
                api_version: format!(
                    "{}.{}.{}",
                    vk::api_version_major(p.api_version),
                    vk::api_version_minor(p.api_version),
                    vk::api_version_patch(p.api_version)
                ),
                driver: format!("{} {}", cstr(&p12.driver_name), cstr(&p12.driver_info)).trim().to_string(),
                subgroup_size: p11.subgroup_size,
                min_subgroup_size: p13.min_subgroup_size,
                max_subgroup_size: p13.max_subgroup_size,
                subgroup_size_control: f13.subgroup_size_control == vk::TRUE
                    && p13.required_subgroup_size_stages.contains(vk::ShaderStageFlags::COMPUTE),
                compute_full_subgroups: f13.compute_full_subgroups == vk::TRUE,
                subgroup_shuffle: p11
                    .subgroup_supported_operations
                    .contains(vk::SubgroupFeatureFlags::SHUFFLE)
                    && p11.subgroup_supported_stages.contains(vk::ShaderStageFlags::COMPUTE),
                subgroup_ballot: p11.subgroup_supported_operations.contains(vk::SubgroupFeatureFlags::BALLOT)
                    && p11.subgroup_supported_stages.contains(vk::ShaderStageFlags::COMPUTE),
                subgroup_arithmetic: p11
                    .subgroup_supported_operations
                    .contains(vk::SubgroupFeatureFlags::ARITHMETIC | vk::SubgroupFeatureFlags::VOTE)
                    && p11.subgroup_supported_stages.contains(vk::ShaderStageFlags::COMPUTE),
                max_shared_memory: limits.max_compute_shared_memory_size,
                max_workgroup_invocations: limits.max_compute_work_group_invocations,
                max_workgroup_size: limits.max_compute_work_group_size,
                max_workgroup_count: limits.max_compute_work_group_count,
                max_storage_buffer_range: limits.max_storage_buffer_range as u64,
                min_storage_buffer_offset_alignment: limits.min_storage_buffer_offset_alignment,
                max_buffer_size: p13.max_buffer_size,
                max_push_constants: limits.max_push_constants_size,
                texel_reads,
                max_texel_buffer_elements: limits.max_texel_buffer_elements as u64,
                min_texel_buffer_offset_alignment: limits.min_texel_buffer_offset_alignment,
                f16_arithmetic,
                f16_storage,
                int64: base.shader_int64 == vk::TRUE,
                vulkan_memory_model,
                float_atomic_add: has_atomic_ext && fa.shader_buffer_float32_atomic_add == vk::TRUE,
                coop_matrix_shapes,
                coop_matrix_f16,
                timestamp_period_ns: limits.timestamp_period as f64,
                timestamps,
                unified_memory,
                device_memory,
                push_descriptors,
                portability_subset,
                robust_buffer_access_available: base.robust_buffer_access == vk::TRUE,
                robust_buffer_access: false,
                cpu_kernels: p.device_type == vk::PhysicalDeviceType::CPU,
                forced: Vec::new(),
            })
        }
    }

    /// Whether the CPU kernels read through texel buffers here: they are on, and the device has
    /// storage texel buffers of vec4s (buffers are made with that usage wherever it has them;
    /// views then start on its texel offset alignment too).
    pub fn texel_kernels(&self) -> bool {
        self.cpu_kernels && self.texel_reads
    }

    /// Whether a pipeline can run with subgroups of exactly `size` invocations: the device's
    /// only size, or one it can be asked for (subgroup size control).
    pub fn subgroup_size_fits(&self, size: u32) -> bool {
        (self.min_subgroup_size == size && self.max_subgroup_size == size)
            || (self.subgroup_size_control
                && (self.min_subgroup_size..=self.max_subgroup_size).contains(&size))
    }

    /// Peak rates for devices whose figures are known: (f16 tensor TFLOP/s, f32 TFLOP/s, GB/s).
    /// Dense figures from the vendors' data sheets; used only to print a fraction of peak.
    pub fn known_peaks(&self) -> Option<(f64, f64, f64)> {
        let n = self.name.to_lowercase();
        if n.contains("h100") && (n.contains("pcie") || n.contains("nvl")) {
            Some((756.0, 51.0, 2000.0))
        } else if n.contains("h100") {
            Some((989.0, 67.0, 3350.0))
        } else if n.contains("h200") {
            Some((989.0, 67.0, 4800.0))
        } else {
            None
        }
    }
}
