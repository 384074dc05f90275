//! The Vulkan instance, the chosen physical device and its logical device.
//!
//! Device choice: discrete GPU first, then integrated, virtual, CPU; `VELOX_DEVICE` (an index
//! from `velox info`, or part of a device name) overrides. One process of a multi-process run
//! opens its device with [`Gpu::for_local_rank`]: local rank r takes the r-th discrete GPU
//! (wrapping around), so the processes of one machine spread over its GPUs. Everything the
//! kernels need to know about the device is read once into [`Caps`].

use std::ffi::{c_char, CStr};
use std::mem::ManuallyDrop;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::caps::{Caps, Switches};
use crate::error::{Error, Feature, Result, VkCheck};
use crate::kernels::PipelineCache;
use crate::validation;

/// A handle to the device; cheap to clone, shared by every tensor and recorder.
#[derive(Clone)]
pub struct Gpu {
    pub(crate) inner: Arc<GpuInner>,
}

pub(crate) struct GpuInner {
    _entry: ash::Entry,
    pub instance: ash::Instance,
    pub device: ash::Device,
    pub queue: Mutex<vk::Queue>,
    /// The compute family every recorder's command pool is made for.
    pub queue_family: u32,
    pub allocator: ManuallyDrop<Mutex<Allocator>>,
    /// Loaded where the device has VK_KHR_push_descriptor and `caps.push_descriptors` is on.
    pub push_descriptor: ash::khr::push_descriptor::Device,
    /// Validation asked for by `VELOX_VALIDATE`, and its messenger.
    pub validation: validation::Mode,
    messenger: Option<validation::Messenger>,
    pub caps: Caps,
    /// Reads and writes go through staging buffers even where memory is mapped
    /// (`VELOX_FORCE_STAGING=1`): the path discrete GPUs take, testable on any device.
    pub force_staging: bool,
    pub pipelines: PipelineCache,
    /// Bytes of device memory the engine's buffers hold now, and the most they have held since
    /// [`Gpu::reset_peak_memory`] (staging buffers included).
    pub memory_live: AtomicU64,
    pub memory_peak: AtomicU64,
    /// Bytes uploaded and downloaded through staging buffers since the device was opened.
    pub staged_bytes: AtomicU64,
    /// Submissions to the queue since the device was opened (each a host wait).
    pub submits: AtomicU64,
    /// How long a submit waits for its recording ([`crate::recorder::wait_timeout`]).
    pub wait_timeout: std::time::Duration,
    /// A recording never finished (see the recorder's drop): the device is left as it is at
    /// drop, since waiting for it to go idle would never return.
    pub hung: std::sync::atomic::AtomicBool,
    /// Recordings on the device, and when it was last seen idle
    /// ([`crate::Finished::host_seconds`]).
    pub busy: Mutex<Busy>,
    /// Uploads through staging buffers not yet copied to their tensors: the next submission
    /// copies them before its own work, in the same `vkQueueSubmit` (see
    /// [`crate::tensor::PendingUpload`]).
    pub pending_uploads: Mutex<Vec<crate::tensor::PendingUpload>>,
    /// Staging buffers whose transfer has finished, kept for the next transfer of their size
    /// class and memory location (`Buffer::staging`).
    pub staging_pool: Mutex<crate::tensor::StagingPool>,
}

/// Recordings submitted and not yet waited for, and when their count last fell to zero: what
/// [`crate::Finished::host_seconds`] counts from.
pub(crate) struct Busy {
    pub running: usize,
    pub idle_since: std::time::Instant,
}

/// One line of the device list shown by `velox info`.
#[derive(Clone, Debug)]
pub struct DeviceSummary {
    pub index: usize,
    pub name: String,
    pub kind: &'static str,
    pub api_version: String,
    /// Why the device cannot be used, if it cannot.
    pub unusable: Option<String>,
}

/// Extensions every device must have (VK_KHR_push_descriptor is used where present, with
/// descriptor sets in its place elsewhere).
const REQUIRED_EXTENSIONS: &[&CStr] = &[];

fn load_entry() -> Result<ash::Entry> {
    // SAFETY: loading the system Vulkan loader; its symbols are resolved by ash.
    unsafe { ash::Entry::load() }.map_err(|e| Error::NoLoader(e.to_string()))
}

/// The instance, with the validation layer, its messenger's extension and its optional checks
/// when `mode` asks for them.
fn create_instance(entry: &ash::Entry, mode: validation::Mode) -> Result<ash::Instance> {
    let app = vk::ApplicationInfo::default()
        .application_name(c"velox")
        .engine_name(c"velox-engine")
        .api_version(vk::API_VERSION_1_3);
    let mut layers: Vec<*const c_char> = Vec::new();
    let mut extensions: Vec<*const c_char> = Vec::new();
    // Portability implementations (MoltenVK) are listed only to an instance that asks for them.
    // SAFETY: plain enumeration call.
    let offered = unsafe { entry.enumerate_instance_extension_properties(None) }.unwrap_or_default();
    let portability =
        offered.iter().any(|e| e.extension_name_as_c_str() == Ok(ash::khr::portability_enumeration::NAME));
    if portability {
        extensions.push(ash::khr::portability_enumeration::NAME.as_ptr());
    }
    if mode != validation::Mode::Off {
        // SAFETY: plain enumeration call.
        let available = unsafe { entry.enumerate_instance_layer_properties() }.unwrap_or_default();
        if !available.iter().any(|l| l.layer_name_as_c_str() == Ok(validation::LAYER)) {
            return Err(Error::unsupported(
                Feature::ValidationLayer,
                "VELOX_VALIDATE asks for the Khronos validation layer, which the Vulkan loader does not \
                 find: install it (Debian: apt-get install vulkan-validationlayers) or unset VELOX_VALIDATE",
            ));
        }
        layers.push(validation::LAYER.as_ptr());
        extensions.push(ash::ext::debug_utils::NAME.as_ptr());
    }
    let features = mode.features();
    let mut checks = vk::ValidationFeaturesEXT::default().enabled_validation_features(features);
    // Messages from vkCreateInstance itself reach the callback through this one.
    let mut messenger = validation::messenger_info();
    let flags = if portability {
        vk::InstanceCreateFlags::ENUMERATE_PORTABILITY_KHR
    } else {
        vk::InstanceCreateFlags::empty()
    };
    let mut info = vk::InstanceCreateInfo::default()
        .flags(flags)
        .application_info(&app)
        .enabled_layer_names(&layers)
        .enabled_extension_names(&extensions);
    if mode != validation::Mode::Off {
        info = info.push_next(&mut checks).push_next(&mut messenger);
    }
    // SAFETY: the create info and everything it points to outlive the call.
    unsafe { entry.create_instance(&info, None) }.map_err(|e| match e {
        vk::Result::ERROR_INCOMPATIBLE_DRIVER => {
            Error::NoDevice("the Vulkan loader found no driver (ICD)".into())
        }
        other => Error::Vulkan { call: "vkCreateInstance", result: other },
    })
}

fn kind_name(t: vk::PhysicalDeviceType) -> (&'static str, u32) {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => ("discrete GPU", 0),
        vk::PhysicalDeviceType::INTEGRATED_GPU => ("integrated GPU", 1),
        vk::PhysicalDeviceType::VIRTUAL_GPU => ("virtual GPU", 2),
        vk::PhysicalDeviceType::CPU => ("CPU", 3),
        _ => ("other", 4),
    }
}

fn version_string(v: u32) -> String {
    format!("{}.{}.{}", vk::api_version_major(v), vk::api_version_minor(v), vk::api_version_patch(v))
}

/// Why a physical device cannot run the engine, or `None` when it can.
fn unusable_reason(instance: &ash::Instance, pd: vk::PhysicalDevice) -> Option<String> {
    // SAFETY: `pd` comes from this instance.
    let props = unsafe { instance.get_physical_device_properties(pd) };
    if props.api_version < vk::API_VERSION_1_3 {
        return Some(format!("Vulkan {} < 1.3", version_string(props.api_version)));
    }
    if compute_queue_family(instance, pd).is_none() {
        return Some("no compute queue".into());
    }
    // SAFETY: as above.
    let exts = unsafe { instance.enumerate_device_extension_properties(pd) }.unwrap_or_default();
    for req in REQUIRED_EXTENSIONS {
        if !exts.iter().any(|e| e.extension_name_as_c_str() == Ok(*req)) {
            return Some(format!("missing extension {}", req.to_string_lossy()));
        }
    }
    None
}

fn compute_queue_family(instance: &ash::Instance, pd: vk::PhysicalDevice) -> Option<u32> {
    // SAFETY: `pd` comes from this instance.
    let families = unsafe { instance.get_physical_device_queue_family_properties(pd) };
    // Prefer a family that does compute; graphics+compute families are fine.
    families.iter().position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE)).map(|i| i as u32)
}

fn summaries(instance: &ash::Instance) -> Result<(Vec<vk::PhysicalDevice>, Vec<DeviceSummary>)> {
    // SAFETY: plain enumeration call.
    let pds = unsafe { instance.enumerate_physical_devices() }.vk("vkEnumeratePhysicalDevices")?;
    let list = pds
        .iter()
        .enumerate()
        .map(|(index, &pd)| {
            // SAFETY: `pd` comes from this instance.
            let props = unsafe { instance.get_physical_device_properties(pd) };
            DeviceSummary {
                index,
                name: props.device_name_as_c_str().unwrap_or(c"?").to_string_lossy().into_owned(),
                kind: kind_name(props.device_type).0,
                api_version: version_string(props.api_version),
                unusable: unusable_reason(instance, pd),
            }
        })
        .collect();
    Ok((pds, list))
}

/// Which device a [`Gpu`] opens.
#[derive(Clone, Debug)]
enum Choice {
    /// The preferred one ([`choose_preferred`]), or `VELOX_DEVICE`'s.
    Preferred,
    /// That of the process with this rank on its machine in a multi-process run
    /// ([`choose_for_rank`]), or `VELOX_DEVICE`'s.
    LocalRank(usize),
    /// The one a caller names (an index or part of a name, as `VELOX_DEVICE` takes), whatever
    /// the environment says.
    Named(String),
}

/// The index of the device `choice` asks for.
fn choose(
    instance: &ash::Instance,
    pds: &[vk::PhysicalDevice],
    list: &[DeviceSummary],
    choice: &Choice,
) -> Result<usize> {
    if pds.is_empty() {
        return Err(Error::NoDevice("the Vulkan loader reports no physical device".into()));
    }
    let (asked, source) = match choice {
        Choice::Named(name) => (Some(name.clone()), "device"),
        _ => (std::env::var("VELOX_DEVICE").ok(), "VELOX_DEVICE"),
    };
    if let Some(want) = asked {
        let want = want.trim();
        let found = match want.parse::<usize>() {
            Ok(i) => list.get(i).map(|d| d.index),
            Err(_) => {
                list.iter().find(|d| d.name.to_lowercase().contains(&want.to_lowercase())).map(|d| d.index)
            }
        };
        let names: Vec<String> = list.iter().map(|d| format!("{}: {}", d.index, d.name)).collect();
        let i = found.ok_or_else(|| {
            Error::Invalid(format!("{source} {want:?} matches none of [{}]", names.join(", ")))
        })?;
        if let Some(why) = &list[i].unusable {
            return Err(Error::NoDevice(format!(
                "{source} {want:?} selects {}, which cannot be used: {why}",
                list[i].name
            )));
        }
        return Ok(i);
    }
    let usable: Vec<(usize, vk::PhysicalDeviceType)> = list
        .iter()
        .filter(|d| d.unusable.is_none())
        .map(|d| {
            // SAFETY: `pds[d.index]` comes from this instance.
            let props = unsafe { instance.get_physical_device_properties(pds[d.index]) };
            (d.index, props.device_type)
        })
        .collect();
    let chosen = match choice {
        Choice::LocalRank(rank) => choose_for_rank(&usable, *rank),
        _ => choose_preferred(&usable),
    };
    chosen.ok_or_else(|| {
        let why: Vec<String> =
            list.iter().map(|d| format!("{} ({})", d.name, d.unusable.clone().unwrap_or_default())).collect();
        Error::NoDevice(format!("none of the devices can be used: {}", why.join("; ")))
    })
}

/// The preferred of the usable devices `(index, type)`: the best kind (discrete GPU, integrated,
/// virtual, CPU), then the lowest index.
fn choose_preferred(usable: &[(usize, vk::PhysicalDeviceType)]) -> Option<usize> {
    usable.iter().min_by_key(|&&(index, kind)| (kind_name(kind).1, index)).map(|&(index, _)| index)
}

/// The device of the process with local rank `rank`: the `rank`-th discrete GPU in index order,
/// wrapping around when the machine runs more processes than it has discrete GPUs; on a machine
/// with none, every process takes the preferred device (lavapipe on a CPU-only machine).
fn choose_for_rank(usable: &[(usize, vk::PhysicalDeviceType)], rank: usize) -> Option<usize> {
    let discrete: Vec<usize> = usable
        .iter()
        .filter(|&&(_, kind)| kind == vk::PhysicalDeviceType::DISCRETE_GPU)
        .map(|&(index, _)| index)
        .collect();
    if discrete.is_empty() {
        choose_preferred(usable)
    } else {
        Some(discrete[rank % discrete.len()])
    }
}

/// Lists the devices the loader sees, without creating any logical device.
pub fn list_devices() -> Result<Vec<DeviceSummary>> {
    let entry = load_entry()?;
    let instance = create_instance(&entry, validation::Mode::Off)?;
    let result = summaries(&instance).map(|(_, l)| l);
    // SAFETY: nothing created from the instance is alive.
    unsafe { instance.destroy_instance(None) };
    result
}

impl Gpu {
    /// Opens the preferred device (see the module docs).
    pub fn new() -> Result<Gpu> {
        Self::create(Choice::Preferred)
    }

    /// Opens the device of the process with rank `local_rank` among the processes of a
    /// multi-process run on this machine: the `local_rank`-th discrete GPU, wrapping around, or
    /// the preferred device where there is no discrete GPU. `VELOX_DEVICE` still overrides.
    pub fn for_local_rank(local_rank: usize) -> Result<Gpu> {
        Self::create(Choice::LocalRank(local_rank))
    }

    /// Opens the device `name` names: an index of [`list_devices`] (as `velox info` numbers
    /// them), or part of a device's name (case ignored); `VELOX_DEVICE` does not apply.
    pub fn named(name: &str) -> Result<Gpu> {
        Self::create(Choice::Named(name.to_string()))
    }

    fn create(choice: Choice) -> Result<Gpu> {
        let mode = validation::Mode::from_env()?;
        let switches = Switches::from_env()?;
        let wait_timeout = crate::recorder::wait_timeout()?;
        let entry = load_entry()?;
        let instance = create_instance(&entry, mode)?;
        // `entry` stays alive here: dropping it unloads the loader, whose functions the
        // error path below still calls.
        match Self::open(entry.clone(), instance.clone(), &choice, mode, &switches, wait_timeout) {
            Ok(gpu) => Ok(gpu),
            Err(e) => {
                // SAFETY: `open` failed before handing the instance to a GpuInner.
                unsafe { instance.destroy_instance(None) };
                Err(e)
            }
        }
    }

    fn open(
        entry: ash::Entry,
        instance: ash::Instance,
        choice: &Choice,
        mode: validation::Mode,
        switches: &Switches,
        wait_timeout: std::time::Duration,
    ) -> Result<Gpu> {
        let messenger = if mode == validation::Mode::Off {
            None
        } else {
            Some(validation::Messenger::new(&entry, &instance)?)
        };
        let opened = Self::open_device(&entry, &instance, choice, switches, mode != validation::Mode::Off);
        let allocator = opened.and_then(|(device, physical, queue_family, caps)| {
            let desc = AllocatorCreateDesc {
                instance: instance.clone(),
                device: device.clone(),
                physical_device: physical,
                debug_settings: Default::default(),
                buffer_device_address: false,
                allocation_sizes: Default::default(),
            };
            match Allocator::new(&desc) {
                Ok(a) => Ok((device, queue_family, caps, a)),
                Err(e) => {
                    // SAFETY: nothing was created from the device yet.
                    unsafe { device.destroy_device(None) };
                    Err(Error::OutOfMemory(format!("creating the allocator: {e}")))
                }
            }
        });
        let (device, queue_family, caps, allocator) = match allocator {
            Ok(d) => d,
            Err(e) => {
                if let Some(m) = &messenger {
                    // SAFETY: created above from this instance, destroyed once.
                    unsafe { m.destroy() };
                }
                return Err(e);
            }
        };
        let push_descriptor = ash::khr::push_descriptor::Device::new(&instance, &device);
        // SAFETY: the queue family and index were requested when the device was created.
        let queue = unsafe { device.get_device_queue(queue_family, 0) };
        Ok(Gpu {
            inner: Arc::new(GpuInner {
                _entry: entry,
                instance,
                device,
                queue: Mutex::new(queue),
                queue_family,
                allocator: ManuallyDrop::new(Mutex::new(allocator)),
                push_descriptor,
                validation: mode,
                messenger,
                caps,
                force_staging: std::env::var("VELOX_FORCE_STAGING").is_ok_and(|v| v == "1"),
                pipelines: PipelineCache::new(),
                memory_live: AtomicU64::new(0),
                memory_peak: AtomicU64::new(0),
                staged_bytes: AtomicU64::new(0),
                submits: AtomicU64::new(0),
                wait_timeout,
                hung: std::sync::atomic::AtomicBool::new(false),
                busy: Mutex::new(Busy { running: 0, idle_since: std::time::Instant::now() }),
                pending_uploads: Mutex::new(Vec::new()),
                staging_pool: Mutex::new(Default::default()),
            }),
        })
    }

    /// Chooses the physical device and creates the logical one with exactly the features the
    /// (switched) caps say are there.
    fn open_device(
        entry: &ash::Entry,
        instance: &ash::Instance,
        choice: &Choice,
        switches: &Switches,
        validating: bool,
    ) -> Result<(ash::Device, vk::PhysicalDevice, u32, Caps)> {
        let (pds, list) = summaries(instance)?;
        let index = choose(instance, &pds, &list, choice)?;
        let physical = pds[index];
        let queue_family = compute_queue_family(instance, physical).expect("checked");
        let mut caps = Caps::query(entry, instance, physical, index, queue_family)?;
        switches.apply(&mut caps);
        if validating {
            // The layer's synchronization checks do not see buffers bound by push descriptors.
            caps.push_descriptors = false;
        }
        // Enable exactly what the caps say is there.
        let mut f11 =
            vk::PhysicalDeviceVulkan11Features::default().storage_buffer16_bit_access(caps.f16_storage);
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
            .shader_float16(caps.f16_arithmetic)
            .vulkan_memory_model(caps.vulkan_memory_model)
            .vulkan_memory_model_device_scope(caps.vulkan_memory_model);
        let mut f13 = vk::PhysicalDeviceVulkan13Features::default()
            .subgroup_size_control(caps.subgroup_size_control)
            .compute_full_subgroups(caps.compute_full_subgroups)
            .synchronization2(true)
            .maintenance4(true);
        let mut atomics = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
            .shader_buffer_float32_atomics(caps.float_atomic_add)
            .shader_buffer_float32_atomic_add(caps.float_atomic_add);
        let mut coop = vk::PhysicalDeviceCooperativeMatrixFeaturesKHR::default()
            .cooperative_matrix(caps.coop_matrix_f16.is_some());
        let base = vk::PhysicalDeviceFeatures::default()
            .shader_int64(caps.int64)
            .robust_buffer_access(caps.robust_buffer_access);

        let mut extensions: Vec<*const c_char> = REQUIRED_EXTENSIONS.iter().map(|e| e.as_ptr()).collect();
        if caps.push_descriptors {
            extensions.push(ash::khr::push_descriptor::NAME.as_ptr());
        }
        if caps.portability_subset {
            // Required wherever a device lists it (VUID-VkDeviceCreateInfo-pProperties-04451).
            extensions.push(crate::caps::PORTABILITY_SUBSET.as_ptr());
        }
        let mut features = vk::PhysicalDeviceFeatures2::default()
            .features(base)
            .push_next(&mut f11)
            .push_next(&mut f12)
            .push_next(&mut f13);
        if caps.float_atomic_add {
            extensions.push(ash::ext::shader_atomic_float::NAME.as_ptr());
            features = features.push_next(&mut atomics);
        }
        if caps.coop_matrix_f16.is_some() {
            extensions.push(ash::khr::cooperative_matrix::NAME.as_ptr());
            features = features.push_next(&mut coop);
        }
        let priorities = [1.0f32];
        let queues = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queues)
            .enabled_extension_names(&extensions)
            .push_next(&mut features);
        // SAFETY: the create info and its chain outlive the call.
        let device = unsafe { instance.create_device(physical, &info, None) }.vk("vkCreateDevice")?;
        Ok((device, physical, queue_family, caps))
    }

    /// `(live, peak)`: bytes of device memory the engine's buffers hold now, and the most they
    /// held at once since the last [`Gpu::reset_peak_memory`] (or since the device was opened).
    pub fn memory(&self) -> (u64, u64) {
        (self.inner.memory_live.load(Ordering::Relaxed), self.inner.memory_peak.load(Ordering::Relaxed))
    }

    /// Bytes the host has written and read through staging buffers since the device was
    /// opened: zero where every tensor is mapped (unified memory), unless
    /// `VELOX_FORCE_STAGING=1` sends the transfers through staging as a discrete GPU's do.
    pub fn staged_bytes(&self) -> u64 {
        self.inner.staged_bytes.load(Ordering::Relaxed)
    }

    /// Bytes of staging buffers the device keeps for later transfers (at most 64 MiB; not in
    /// [`Gpu::memory_live`]).
    pub fn staging_pool_bytes(&self) -> u64 {
        self.inner.staging_pool.lock().unwrap().bytes()
    }

    /// Recordings submitted to this device since it was opened, each waited for by the host
    /// (`profile::submits` counts the process's, over every device).
    pub fn submits(&self) -> u64 {
        self.inner.submits.load(Ordering::Relaxed)
    }

    /// Starts a new peak from what is held now.
    pub fn reset_peak_memory(&self) {
        let live = self.inner.memory_live.load(Ordering::Relaxed);
        self.inner.memory_peak.store(live, Ordering::Relaxed);
    }

    /// Counts `bytes` allocated (`grow`) or freed.
    pub(crate) fn account_memory(&self, bytes: u64, grow: bool) {
        if grow {
            let live = self.inner.memory_live.fetch_add(bytes, Ordering::Relaxed) + bytes;
            self.inner.memory_peak.fetch_max(live, Ordering::Relaxed);
        } else {
            self.inner.memory_live.fetch_sub(bytes, Ordering::Relaxed);
        }
    }

    /// What the device offers and what the kernels will use.
    pub fn caps(&self) -> &Caps {
        &self.inner.caps
    }

    pub(crate) fn device(&self) -> &ash::Device {
        &self.inner.device
    }
}

impl Drop for GpuInner {
    fn drop(&mut self) {
        // SAFETY: the last handle is going away; no tensor or recorder can still use the
        // device because each holds a `Gpu` clone.
        if self.hung.load(Ordering::Acquire) {
            return;
        }
        unsafe {
            let _ = self.device.device_wait_idle();
            self.pipelines.destroy(&self.device);
            // Uploads no submission took: their tensors are gone with the last handle.
            for u in self.pending_uploads.get_mut().unwrap().drain(..) {
                self.device.destroy_buffer(u.staging.raw, None);
                let _ = self.allocator.lock().unwrap().free(u.staging.allocation);
            }
            for (raw, allocation) in self.staging_pool.get_mut().unwrap().drain() {
                self.device.destroy_buffer(raw, None);
                let _ = self.allocator.lock().unwrap().free(allocation);
            }
            ManuallyDrop::drop(&mut self.allocator);
            self.device.destroy_device(None);
            if let Some(m) = &self.messenger {
                m.destroy();
            }
            self.instance.destroy_instance(None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vk::PhysicalDeviceType as T;

    /// Usable devices `(index, type)` from a list of types, in index order.
    fn devices(kinds: &[T]) -> Vec<(usize, T)> {
        kinds.iter().copied().enumerate().collect()
    }

    #[test]
    fn a_lone_process_takes_the_best_kind_then_the_lowest_index() {
        assert_eq!(choose_preferred(&devices(&[T::CPU, T::INTEGRATED_GPU])), Some(1));
        assert_eq!(choose_preferred(&devices(&[T::CPU, T::DISCRETE_GPU, T::DISCRETE_GPU])), Some(1));
        assert_eq!(choose_preferred(&devices(&[T::VIRTUAL_GPU, T::CPU])), Some(0));
        assert_eq!(choose_preferred(&[]), None);
    }

    #[test]
    fn local_ranks_spread_over_the_discrete_gpus_and_wrap_around() {
        let list = devices(&[T::CPU, T::DISCRETE_GPU, T::INTEGRATED_GPU, T::DISCRETE_GPU]);
        let chosen: Vec<Option<usize>> = (0..5).map(|r| choose_for_rank(&list, r)).collect();
        assert_eq!(chosen, [Some(1), Some(3), Some(1), Some(3), Some(1)]);
        // An unusable device is not in the list at all: the ranks share the one left.
        let list = vec![(0, T::CPU), (2, T::DISCRETE_GPU)];
        assert_eq!((0..3).map(|r| choose_for_rank(&list, r)).collect::<Vec<_>>(), [Some(2); 3]);
    }

    #[test]
    fn without_a_discrete_gpu_every_rank_takes_the_preferred_device() {
        for kinds in [&[T::CPU][..], &[T::CPU, T::INTEGRATED_GPU], &[T::VIRTUAL_GPU, T::CPU, T::OTHER]] {
            let list = devices(kinds);
            for r in 0..4 {
                assert_eq!(choose_for_rank(&list, r), choose_preferred(&list), "{kinds:?}, rank {r}");
            }
        }
        assert_eq!(choose_for_rank(&devices(&[T::CPU, T::INTEGRATED_GPU]), 3), Some(1));
        assert_eq!(choose_for_rank(&[], 0), None);
    }
}
