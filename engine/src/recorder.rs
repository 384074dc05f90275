//! Records many dispatches into one command buffer and submits them once.
//!
//! A barrier goes in only where a dispatch depends on earlier work in the same command buffer:
//! it reads or writes a buffer written since the last barrier (read-after-write, write-after-
//! write), or writes a buffer read since then (write-after-read). What a kernel reads and
//! writes comes from naga's analysis at build time, so the tracking cannot drift from the
//! shader. Workgroup counts above the per-dimension limit are folded into a second dimension;
//! kernels recover the linear workgroup index as `wid.x + wid.y * nwg.x`.
//!
//! Each recorder owns its command pool, so recorders on several threads never share one (a
//! pool is externally synchronised in Vulkan). Buffers are bound with push descriptors where
//! the device has them, else through descriptor sets the recorder allocates from pools of its
//! own ([`Caps::push_descriptors`](crate::Caps)); the validation layer's synchronization checks
//! see only the second kind, so validation runs force it (`VELOX_DISABLE=push-descriptors`).
//! The last command of every recording makes the device's writes visible to the host, which
//! reads results from mapped memory once the fence has signalled.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::device::Gpu;
use crate::error::{Error, Result, VkCheck};
use crate::kernels::{ArgList, Binds, Kernel, KernelId};
use crate::profile;
use crate::tensor::{Buffer, Readback, Tensor};
use crate::validation;
use crate::Limit;

const MAX_TIMESTAMPS: u32 = 256;
/// Queries of a recorder when profiling: two per dispatch or so, for the longest recordings.
const PROFILE_TIMESTAMPS: u32 = 16384;

/// The precision a recording's layers compute in. The ops take their operands' types as given;
/// the model layers read this to choose (`velox_models::layers`): `F32` everywhere, or `F16`,
/// where matrix products and attention read f16 operands (weights from a store's f16 mirror,
/// activations cast before the product) and accumulate in f32, and everything else stays f32;
/// in training the backward products read f16 operands too (mixed-precision training).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Precision {
    #[default]
    F32,
    F16,
}

impl Precision {
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        }
    }
}

/// Which kernels f32 matrix products take in a recording.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum NarrowMatmul {
    /// The device's own: on CPU devices (lavapipe) `Vec4` where the layout allows, else `Rows`
    /// for a narrow side (64 or less); on GPUs `Tiles` for a narrow side and the 128x128 tile.
    #[default]
    Device,
    /// The narrow-tile kernels (`matmul_small.wgsl`), through workgroup memory.
    Tiles,
    /// One row of outputs per invocation, no workgroup memory (`matmul_rows.wgsl`).
    Rows,
    /// The CPU kernel (`matmul_cpu.wgsl`: texel-buffer reads, subgroup shuffles) wherever the
    /// device has texel buffers and the operands' views fit one, whatever the device.
    Vec4,
}

pub struct Recorder {
    gpu: Gpu,
    pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    /// Descriptor pools of the descriptor-set path, the last one being filled, and the sets it
    /// has left.
    descriptor_pools: Vec<vk::DescriptorPool>,
    sets_left: u32,
    /// Whether [`Recorder::dispatch`] inserts the barriers its hazards need (always, except in
    /// the test that shows a missing barrier is reported).
    track_hazards: bool,
    fence: vk::Fence,
    queries: Option<vk::QueryPool>,
    timestamps: u32,
    written: Vec<vk::Buffer>,
    read: Vec<vk::Buffer>,
    keep: Vec<Arc<Buffer>>,
    dispatches: usize,
    barriers: usize,
    submitted: bool,
    precision: Precision,
    narrow_matmul: NarrowMatmul,
    /// When the recording began, and the device's wait on the host it was submitted after
    /// ([`Finished::host_seconds`]).
    started: std::time::Instant,
    host_seconds: f64,
    /// Submitted and not yet counted out of the device's running recordings.
    in_flight: bool,
    /// With `VELOX_PROFILE`: the query written after the last dispatch.
    profile_end: Option<usize>,
    /// Whether the cooperative attention forward may take its 64-key tiles
    /// ([`Recorder::set_wide_key_tiles`]).
    wide_key_tiles: bool,
    /// Whether large cooperative-matrix products take 4 x 4 fragments a subgroup
    /// ([`Recorder::set_wide_matmul_blocks`]).
    wide_matmul_blocks: bool,
    /// Queries in the pool.
    capacity: u32,
    /// With `VELOX_PROFILE`: the query written before each dispatch, and its kernel.
    profiled: Vec<(u32, KernelId)>,
    /// Set once the recording has run to completion (see [`Completion`]).
    done: Completion,
    /// What the recording is, for a message about it ([`Recorder::set_label`]), and the first
    /// and last kernels it dispatched.
    label: Option<String>,
    kernels: Option<(KernelId, KernelId)>,
    /// How long [`Recorder::submit`] waits for the device (see [`wait_timeout`]).
    wait: std::time::Duration,
}

/// How long a submit waits for its recording before it gives up with [`Error::Timeout`]:
/// `VELOX_WAIT_TIMEOUT` seconds (a positive number), 600 by default. A hung kernel then ends
/// the command with an error naming its recording instead of holding it forever.
pub fn wait_timeout() -> Result<std::time::Duration> {
    match std::env::var("VELOX_WAIT_TIMEOUT") {
        Err(_) => Ok(std::time::Duration::from_secs(600)),
        Ok(v) => v
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|s| s.is_finite() && *s > 0.0 && *s < 1e9)
            .map(std::time::Duration::from_secs_f64)
            .ok_or_else(|| {
                Error::Invalid(format!("VELOX_WAIT_TIMEOUT={v}: give a positive number of seconds"))
            }),
    }
}

/// Whether a recording has been submitted and whether it has run: what a result cached across
/// recordings (an attention work list) checks before another recording reads it. Cloned
/// handles share the state.
#[derive(Clone, Debug, Default)]
pub struct Completion(Arc<AtomicU8>);

/// The states of a [`Completion`] after recording (0), in the order a recording goes through them.
const SUBMITTED: u8 = 1;
const DONE: u8 = 2;

impl Completion {
    /// The recording finished on the device (a wait for it returned successfully).
    pub fn is_done(&self) -> bool {
        self.0.load(Ordering::Acquire) == DONE
    }

    /// The recording has reached the queue (it may still be running).
    pub fn is_submitted(&self) -> bool {
        self.0.load(Ordering::Acquire) >= SUBMITTED
    }

    fn set(&self, state: u8) {
        self.0.store(state, Ordering::Release);
    }

    /// Whether the two handles are of the same recording.
    pub fn same(&self, other: &Completion) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }

    /// Whether work recorded in the recording of `self` is visible to later dispatches of the
    /// recording `now`: the same recording (the recorder's barriers order them), or one
    /// submitted already, which `now` can only follow on the queue, after the barrier that
    /// ends every recording and reaches every later command.
    pub fn visible_in(&self, now: &Completion) -> bool {
        self.same(now) || self.is_submitted()
    }
}

/// What a finished recording reports.
#[derive(Clone, Debug, Default)]
pub struct Finished {
    /// Timestamp values in nanoseconds, in the order they were written (empty when the device
    /// has no timestamps).
    pub timestamps_ns: Vec<f64>,
    pub dispatches: usize,
    pub barriers: usize,
    /// Seconds the device waited on the host for this recording: from the later of the
    /// recording's start ([`Gpu::recorder`]) and the end of the last wait on the device (the
    /// moment it was last seen idle) to the submission. Recording, and whatever the caller did
    /// between; a recording made while the one before it runs ([`Recorder::launch`]) hides
    /// its own.
    pub host_seconds: f64,
}

impl Gpu {
    /// A new recording; nothing runs until [`Recorder::submit`].
    pub fn recorder(&self) -> Result<Recorder> {
        let device = self.device();
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(self.inner.queue_family)
            .flags(vk::CommandPoolCreateFlags::TRANSIENT);
        // SAFETY: valid device and create info.
        let pool = unsafe { device.create_command_pool(&pool_info, None) }.vk("vkCreateCommandPool")?;
        let info = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is this recorder's own.
        let cmd = match unsafe { device.allocate_command_buffers(&info) } {
            Ok(c) => c[0],
            Err(e) => {
                // SAFETY: nothing was allocated from the pool.
                unsafe { device.destroy_command_pool(pool, None) };
                return Err(e).vk("vkAllocateCommandBuffers");
            }
        };
        // SAFETY: valid device.
        let fence = match unsafe { device.create_fence(&vk::FenceCreateInfo::default(), None) } {
            Ok(f) => f,
            Err(e) => {
                // SAFETY: the pool's one command buffer was never submitted.
                unsafe { device.destroy_command_pool(pool, None) };
                return Err(e).vk("vkCreateFence");
            }
        };
        let rec = Recorder {
            started: std::time::Instant::now(),
            host_seconds: 0.0,
            in_flight: false,
            profile_end: None,
            gpu: self.clone(),
            pool,
            cmd,
            descriptor_pools: Vec::new(),
            sets_left: 0,
            track_hazards: true,
            fence,
            queries: None,
            timestamps: 0,
            written: Vec::new(),
            read: Vec::new(),
            keep: Vec::new(),
            dispatches: 0,
            barriers: 0,
            submitted: false,
            precision: Precision::F32,
            narrow_matmul: NarrowMatmul::Device,
            wide_key_tiles: true,
            wide_matmul_blocks: true,
            capacity: 0,
            profiled: Vec::new(),
            done: Completion::default(),
            label: None,
            kernels: None,
            wait: self.inner.wait_timeout,
        };
        let begin = vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: a freshly allocated command buffer (the recorder's drop frees it on error).
        unsafe { device.begin_command_buffer(cmd, &begin) }.vk("vkBeginCommandBuffer")?;
        Ok(rec.with_timestamps_if_possible())
    }
}

/// Sets per descriptor pool of the descriptor-set path, and storage-buffer descriptors per set
/// on average (kernels bind 1 to 12).
const SETS_PER_POOL: u32 = 512;
const BUFFERS_PER_SET: u32 = 8;
const TEXELS_PER_SET: u32 = 2;

impl Recorder {
    fn with_timestamps_if_possible(mut self) -> Self {
        if self.gpu.caps().timestamps {
            let count = if profile::enabled() { PROFILE_TIMESTAMPS } else { MAX_TIMESTAMPS };
            let info =
                vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(count);
            // SAFETY: valid device; the pool is reset in the command buffer before use.
            if let Ok(pool) = unsafe { self.gpu.device().create_query_pool(&info, None) } {
                unsafe { self.gpu.device().cmd_reset_query_pool(self.cmd, pool, 0, count) };
                self.queries = Some(pool);
                self.capacity = count;
            }
        }
        self
    }

    /// The precision the layers recorded from now on compute in (f32 unless set).
    pub fn precision(&self) -> Precision {
        self.precision
    }

    pub fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }

    /// The kernels narrow f32 products recorded from now on take (the device's choice unless
    /// set; tests set both others, so that each runs on every device).
    pub fn narrow_matmul(&self) -> NarrowMatmul {
        self.narrow_matmul
    }

    pub fn set_narrow_matmul(&mut self, choice: NarrowMatmul) {
        self.narrow_matmul = choice;
    }

    /// Whether the cooperative-matrix attention forward recorded from now on may take 64-key
    /// tiles where the device and the segments suit them (the default); off, it keeps to
    /// 32-key tiles, so that the benchmarks time both on one device.
    pub fn wide_key_tiles(&self) -> bool {
        self.wide_key_tiles
    }

    pub fn set_wide_key_tiles(&mut self, on: bool) {
        self.wide_key_tiles = on;
    }

    /// Whether the cooperative-matrix products recorded from now on take their 128 x 128 tile
    /// in 4 x 4 fragments a subgroup (the default); off, in 4 x 2, so that the benchmarks time
    /// both on one device and the tests run both.
    pub fn wide_matmul_blocks(&self) -> bool {
        self.wide_matmul_blocks
    }

    pub fn set_wide_matmul_blocks(&mut self, on: bool) {
        self.wide_matmul_blocks = on;
    }

    /// Names the recording in the messages about it (a timeout, a lost device): "training step
    /// 12", say. Without a label it is described by its dispatch count and kernels.
    pub fn set_label(&mut self, label: impl Into<String>) {
        self.label = Some(label.into());
    }

    /// How long this recording's [`Recorder::submit`] waits for the device before it returns
    /// [`Error::Timeout`] (the device's `VELOX_WAIT_TIMEOUT` unless set).
    pub fn set_wait_timeout(&mut self, wait: std::time::Duration) {
        self.wait = wait;
    }

    /// The recording in words: its label, its dispatch count and its first and last kernels.
    pub fn describe(&self) -> String {
        let what = match self.kernels {
            None => format!("{} dispatches", self.dispatches),
            Some((a, b)) if a == b => format!("{} dispatches of {}", self.dispatches, a.name()),
            Some((a, b)) => format!("{} dispatches, {} to {}", self.dispatches, a.name(), b.name()),
        };
        match &self.label {
            Some(l) => format!("the recording \"{l}\" ({what})"),
            None => format!("a recording of {what}"),
        }
    }

    /// Turns the barriers [`Recorder::dispatch`] inserts on or off. Off, dispatches that depend
    /// on each other race: this exists for the test that shows the validation layer reports a
    /// missing barrier, and for nothing else.
    #[doc(hidden)]
    pub fn set_hazard_tracking(&mut self, on: bool) {
        self.track_hazards = on;
    }

    /// Inserts a barrier if the next access of `reads` and `writes` depends on earlier work.
    fn hazard_barrier(&mut self, reads: &[vk::Buffer], writes: &[vk::Buffer]) {
        if !self.track_hazards {
            return;
        }
        let raw_or_waw = reads.iter().chain(writes).any(|b| self.written.contains(b));
        let war = writes.iter().any(|b| self.read.contains(b));

        if raw_or_waw || war {
            self.full_barrier();
        }
        self.read.extend_from_slice(reads);
        self.written.extend_from_slice(writes);
    }

    /// Makes every earlier shader or transfer write visible to every later access.
    pub fn full_barrier(&mut self) {
        // SAFETY: recording state.
        unsafe { memory_barrier(self.gpu.device(), self.cmd, writes(), device_access()) };
        self.written.clear();
        self.read.clear();
        self.barriers += 1;
    }

    /// Records `kernel` over `groups` workgroups with the tensors of `args` bound to the
    /// shader's bindings of their names and `push` as its push constants.
    pub fn dispatch<P: bytemuck::Pod, B: Binds>(
        &mut self,
        kernel: Kernel<P, B>,
        groups: [u32; 3],
        args: B::Args<'_>,
        push: &P,
    ) -> Result<()> {
        let tensors = args.tensors();
        let args = tensors.as_ref();
        let info = kernel.info();
        if args.len() != info.bindings.len() {
            return Err(Error::Shape(format!(
                "kernel {} takes {} buffers, {} given",
                kernel.name(),
                info.bindings.len(),
                args.len()
            )));
        }
        let push_bytes = bytemuck::bytes_of(push);
        if push_bytes.len() as u32 != info.push_bytes {
            return Err(Error::Shape(format!(
                "kernel {} takes {} bytes of push constants, {} given",
                kernel.name(),
                info.push_bytes,
                push_bytes.len()
            )));
        }
        let max = self.gpu.caps().max_workgroup_count;
        if groups.iter().zip(max).any(|(g, m)| *g > m) {
            return Err(Error::too_large(
                Limit::Workgroups,
                format!("kernel {}: {groups:?} workgroups, the device allows {max:?}", kernel.name()),
            ));
        }
        if groups.contains(&0) {
            return Ok(());
        }
        for t in args {
            t.check_bindable(&kernel.name())?;
        }
        let pipeline = self.gpu.pipeline(kernel.id())?;

        let reads: Vec<vk::Buffer> = args.iter().map(|t| t.buf.raw).collect();
        let writes: Vec<vk::Buffer> =
            args.iter().zip(info.bindings).filter(|(_, b)| b.writes).map(|(t, _)| t.buf.raw).collect();
        self.hazard_barrier(&reads, &writes);

        let buffer_infos: Vec<[vk::DescriptorBufferInfo; 1]> = args
            .iter()
            .map(|t| {
                let (offset, range) = t.binding_range();
                [vk::DescriptorBufferInfo::default().buffer(t.buf.raw).offset(offset).range(range)]
            })
            .collect();
        // Texel buffers take a view of the tensor's bytes (made once per buffer and range).
        let texel_views: Vec<[vk::BufferView; 1]> = args
            .iter()
            .zip(info.bindings)
            .map(|(t, b)| Ok([if b.texel { t.texel_view(&kernel.name())? } else { vk::BufferView::null() }]))
            .collect::<Result<_>>()?;
        let writes_desc: Vec<vk::WriteDescriptorSet> = info
            .bindings
            .iter()
            .zip(buffer_infos.iter().zip(&texel_views))
            .map(|(b, (bi, view))| {
                let w = vk::WriteDescriptorSet::default()
                    .dst_binding(b.binding)
                    .descriptor_type(b.descriptor_type());
                if b.texel {
                    w.texel_buffer_view(view)
                } else {
                    w.buffer_info(bi)
                }
            })
            .collect();
        if profile::enabled() && self.timestamps + 2 < self.capacity {
            if let Some(q) = self.timestamp() {
                self.profiled.push((q as u32, kernel.id()));
            }
        }
        let set = if self.gpu.caps().push_descriptors { None } else { Some(self.descriptor_set(&pipeline)?) };
        let device = self.gpu.device();
        // SAFETY: recording state; every bound buffer is kept alive in `self.keep` until the
        // command buffer has finished; a descriptor set is written before it is bound and never
        // again.
        unsafe {
            device.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, pipeline.pipeline);
            match set {
                None => self.gpu.inner.push_descriptor.cmd_push_descriptor_set(
                    self.cmd,
                    vk::PipelineBindPoint::COMPUTE,
                    pipeline.layout,
                    0,
                    &writes_desc,
                ),
                Some(set) => {
                    let writes: Vec<vk::WriteDescriptorSet> =
                        writes_desc.into_iter().map(|w| w.dst_set(set)).collect();
                    device.update_descriptor_sets(&writes, &[]);
                    device.cmd_bind_descriptor_sets(
                        self.cmd,
                        vk::PipelineBindPoint::COMPUTE,
                        pipeline.layout,
                        0,
                        &[set],
                        &[],
                    );
                }
            }
            if !push_bytes.is_empty() {
                device.cmd_push_constants(
                    self.cmd,
                    pipeline.layout,
                    vk::ShaderStageFlags::COMPUTE,
                    0,
                    push_bytes,
                );
            }
            device.cmd_dispatch(self.cmd, groups[0], groups[1], groups[2]);
        }
        self.keep.extend(args.iter().map(|t| t.buf.clone()));
        self.kernels = Some(match self.kernels {
            None => (kernel.id(), kernel.id()),
            Some((first, _)) => (first, kernel.id()),
        });
        self.dispatches += 1;
        profile::count_dispatch();
        Ok(())
    }

    /// A fresh descriptor set of `pipeline`'s layout, from this recorder's pools (a new pool when
    /// the last one is full).
    fn descriptor_set(&mut self, pipeline: &crate::kernels::Pipeline) -> Result<vk::DescriptorSet> {
        let device = self.gpu.device();
        for attempt in 0..2 {
            if self.sets_left == 0 || attempt == 1 {
                let sizes = [
                    vk::DescriptorPoolSize::default()
                        .ty(vk::DescriptorType::STORAGE_BUFFER)
                        .descriptor_count(SETS_PER_POOL * BUFFERS_PER_SET),
                    vk::DescriptorPoolSize::default()
                        .ty(vk::DescriptorType::STORAGE_TEXEL_BUFFER)
                        .descriptor_count(SETS_PER_POOL * TEXELS_PER_SET),
                ];
                let info = vk::DescriptorPoolCreateInfo::default().max_sets(SETS_PER_POOL).pool_sizes(&sizes);
                // SAFETY: valid device and create info; the pool is destroyed with the recorder.
                let pool =
                    unsafe { device.create_descriptor_pool(&info, None) }.vk("vkCreateDescriptorPool")?;
                self.descriptor_pools.push(pool);
                self.sets_left = SETS_PER_POOL;
            }
            let layouts = [pipeline.set_layout];
            let pool = *self.descriptor_pools.last().expect("a pool was made above");
            let info = vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts);
            // SAFETY: the pool and layout are alive; the pool is used by this recorder only.
            match unsafe { device.allocate_descriptor_sets(&info) } {
                Ok(sets) => {
                    self.sets_left -= 1;
                    return Ok(sets[0]);
                }
                // The pool ran out of descriptors before sets (kernels with many bindings):
                // the next attempt takes a new one.
                Err(vk::Result::ERROR_OUT_OF_POOL_MEMORY | vk::Result::ERROR_FRAGMENTED_POOL)
                    if attempt == 0 => {}
                Err(e) => return Err(e).vk("vkAllocateDescriptorSets"),
            }
        }
        unreachable!("the second attempt returns")
    }

    /// Dispatches `total` workgroups of a kernel that linearises `wid.x + wid.y * nwg.x` and
    /// returns early past `total` (every 1D kernel in shaders/ does).
    pub fn dispatch_linear<P: bytemuck::Pod, B: Binds>(
        &mut self,
        kernel: Kernel<P, B>,
        total: u64,
        args: B::Args<'_>,
        push: &P,
    ) -> Result<()> {
        let groups = linear_groups(total, self.gpu.caps().max_workgroup_count).ok_or_else(|| {
            Error::too_large(Limit::Workgroups, format!("kernel {}: {total} workgroups", kernel.name()))
        })?;
        self.dispatch(kernel, groups, args, push)
    }

    /// Dispatches a linear kernel over `elements` elements, 256 invocations a workgroup, that
    /// loops over its elements from `first_element` by `element_stride`
    /// (`shaders/include/elements.wgsl`): a workgroup per 256 elements on a GPU, per 4096 on a
    /// device with the CPU kernels (`Caps::cpu_kernels`), where starting a workgroup costs as
    /// much as a hundred elements.
    pub fn dispatch_elements<P: bytemuck::Pod, B: Binds>(
        &mut self,
        kernel: Kernel<P, B>,
        elements: u64,
        args: B::Args<'_>,
        push: &P,
    ) -> Result<()> {
        let per_group = if self.gpu.caps().cpu_kernels { 256 * 16 } else { 256 };
        self.dispatch_linear(kernel, elements.div_ceil(per_group), args, push)
    }

    /// Copies `bytes` bytes between raw buffers (uploads and downloads).
    pub(crate) fn copy_raw(
        &mut self,
        src: &Buffer,
        src_offset: u64,
        dst: &Buffer,
        dst_offset: u64,
        bytes: u64,
    ) {
        self.hazard_barrier(&[src.raw], &[dst.raw]);
        let region = [vk::BufferCopy::default().src_offset(src_offset).dst_offset(dst_offset).size(bytes)];
        // SAFETY: recording state; the caller keeps both buffers alive until submit returns.
        unsafe { self.gpu.device().cmd_copy_buffer(self.cmd, src.raw, dst.raw, &region) };
    }

    /// `t` as this recording leaves it here, for the host to read once the recording has been
    /// submitted, with no submission of its own ([`Readback`]): on a device whose memory the
    /// host does not map, the recording copies `t` into a host-visible buffer here.
    pub fn read_back(&mut self, t: &Tensor) -> Result<Readback> {
        let staging = if t.staged() && t.bytes() > 0 {
            let staging =
                Arc::new(Buffer::staging(&self.gpu, t.bytes(), MemoryLocation::GpuToCpu, "readback")?);
            self.copy_raw(&t.buf, t.offset, &staging, 0, t.bytes());
            self.keep.push(t.buf.clone());
            self.keep.push(staging.clone());
            Some(staging)
        } else {
            None
        };
        Ok(Readback::new(t.clone(), staging, self.done.clone()))
    }

    /// Copies the whole of `src` into `dst` (same byte size).
    pub fn copy(&mut self, src: &Tensor, dst: &Tensor) -> Result<()> {
        if src.bytes() != dst.bytes() {
            return Err(Error::Shape(format!("copy {src:?} into {dst:?}: sizes differ")));
        }
        if src.bytes() == 0 {
            return Ok(());
        }
        self.copy_raw(&src.buf, src.offset, &dst.buf, dst.offset, src.bytes());
        self.keep.push(src.buf.clone());
        self.keep.push(dst.buf.clone());
        Ok(())
    }

    /// Copies `rows` rows (first axis) of `src` from row `src_row` into `dst` from row
    /// `dst_row`: both of one dtype and one row width. Batched models gather a sample's rows
    /// out of a batch and put them back this way.
    pub fn copy_rows(
        &mut self,
        src: &Tensor,
        src_row: usize,
        dst: &Tensor,
        dst_row: usize,
        rows: usize,
    ) -> Result<()> {
        let row_bytes = |t: &Tensor| -> Result<(usize, usize)> {
            match t.shape() {
                [] => Err(Error::Shape(format!("copy_rows: {t:?} has no rows"))),
                [r, rest @ ..] => Ok((*r, rest.iter().product::<usize>() * t.dtype().size())),
            }
        };
        let ((src_rows, width), (dst_rows, dst_width)) = (row_bytes(src)?, row_bytes(dst)?);
        if src.dtype() != dst.dtype() || width != dst_width {
            return Err(Error::Shape(format!("copy_rows from {src:?} into {dst:?}: the rows differ")));
        }
        if src_row.checked_add(rows).is_none_or(|e| e > src_rows)
            || dst_row.checked_add(rows).is_none_or(|e| e > dst_rows)
        {
            return Err(Error::Shape(format!(
                "copy_rows: rows {src_row}..+{rows} of {src:?} into rows {dst_row}.. of {dst:?} run past an end"
            )));
        }
        if rows == 0 || width == 0 {
            return Ok(());
        }
        let (at, to) = ((src_row * width) as u64, (dst_row * width) as u64);
        self.copy_raw(&src.buf, src.offset + at, &dst.buf, dst.offset + to, (rows * width) as u64);
        self.keep.push(src.buf.clone());
        self.keep.push(dst.buf.clone());
        Ok(())
    }

    /// Writes a GPU timestamp after all earlier work; returns its index in
    /// [`Finished::timestamps_ns`], or `None` if the device cannot time.
    pub fn timestamp(&mut self) -> Option<usize> {
        let pool = self.queries?;
        if self.timestamps >= self.capacity {
            return None;
        }
        // SAFETY: recording state, query index within the pool.
        unsafe {
            self.gpu.device().cmd_write_timestamp2(
                self.cmd,
                vk::PipelineStageFlags2::ALL_COMMANDS,
                pool,
                self.timestamps,
            )
        };
        self.timestamps += 1;
        Some(self.timestamps as usize - 1)
    }

    /// The device this recording is for.
    pub fn gpu(&self) -> &Gpu {
        &self.gpu
    }

    pub fn dispatch_count(&self) -> usize {
        self.dispatches
    }

    /// This recording's completion flag, set when [`Recorder::submit`] has waited for it.
    pub fn completion(&self) -> &Completion {
        &self.done
    }

    /// Submits the recording and waits for it to finish.
    pub fn submit(self) -> Result<Finished> {
        self.launch()?.wait()
    }

    /// Submits the recording without waiting for it: the host may record the next while the
    /// device runs this one ([`Launched::wait`] then waits). The queue runs submissions in
    /// order, and the barrier that ends every recording reaches every later one, so a
    /// recording submitted after this one sees everything it wrote.
    pub fn launch(mut self) -> Result<Launched> {
        let device = self.gpu.device().clone();
        // The end of the last profiled dispatch.
        self.profile_end = if self.profiled.is_empty() { None } else { self.timestamp() };
        // The host reads results from mapped memory (tensors on unified memory, staging buffers)
        // once the fence has signalled; the fence makes the device's writes available, and this
        // barrier makes them visible to the host's reads. It also orders them before the work of
        // later submissions (its second scope reaches every later command on the queue): waiting
        // on a fence orders nothing on the device, and a later recording that reads or rewrites
        // a buffer this one wrote (a gradient, a parameter) would otherwise race with it, as the
        // validation layer's submit-time checks report.
        // SAFETY: recording state; the fence is unsignalled; the queue is externally
        // synchronised by its mutex.
        unsafe {
            memory_barrier(&device, self.cmd, writes(), device_and_host());
            device.end_command_buffer(self.cmd).vk("vkEndCommandBuffer")?;
            // Taken under the queue's lock, so that no other thread's submission that reads an
            // upload can reach the queue before the copy does.
            let gpu = self.gpu.clone();
            let queue = gpu.inner.queue.lock().unwrap();
            let uploads = self.record_uploads()?;
            let cmds: Vec<vk::CommandBuffer> = uploads.into_iter().chain([self.cmd]).collect();
            let submit = [vk::SubmitInfo::default().command_buffers(&cmds)];
            device.queue_submit(*queue, &submit, self.fence).vk("vkQueueSubmit")?;
        }
        self.submitted = true;
        self.done.set(SUBMITTED);
        {
            let mut busy = self.gpu.inner.busy.lock().unwrap();
            let now = std::time::Instant::now();
            // The device idled since the later of the recording's start and its last work;
            // with other recordings still running, it has not idled.
            self.host_seconds = match busy.running {
                0 => now.duration_since(busy.idle_since.max(self.started)).as_secs_f64(),
                _ => 0.0,
            };
            busy.running += 1;
            self.in_flight = true;
        }
        profile::count_submit();
        self.gpu.inner.submits.fetch_add(1, Ordering::Relaxed);
        Ok(Launched(self))
    }

    /// Counts this recording out of the device's running ones, once.
    fn landed(&mut self) {
        if std::mem::take(&mut self.in_flight) {
            let mut busy = self.gpu.inner.busy.lock().unwrap();
            busy.running -= 1;
            if busy.running == 0 {
                busy.idle_since = std::time::Instant::now();
            }
        }
    }
}

/// A recording submitted and not yet waited for ([`Recorder::launch`]). Dropped unwaited, it
/// waits for the device before it frees what the recording uses.
pub struct Launched(Recorder);

impl Launched {
    /// Waits for the recording to finish and reports it.
    pub fn wait(self) -> Result<Finished> {
        let mut rec = self.0;
        let device = rec.gpu.device().clone();
        let start = std::time::Instant::now();
        let nanos = u64::try_from(rec.wait.as_nanos()).unwrap_or(u64::MAX);
        // SAFETY: the fence was submitted with the recording.
        match unsafe { device.wait_for_fences(&[rec.fence], true, nanos) } {
            Ok(()) => {}
            Err(vk::Result::TIMEOUT) => {
                return Err(Error::Timeout { recording: rec.describe(), waited: start.elapsed() })
            }
            Err(vk::Result::ERROR_DEVICE_LOST) => {
                return Err(Error::DeviceLost(format!("while waiting for {}", rec.describe())))
            }
            Err(e) => return Err(e).vk("vkWaitForFences"),
        }
        rec.landed();
        rec.done.set(DONE);
        rec.gpu.check_validation_during(Some(rec.cmd), &rec.describe())?;
        let mut timestamps_ns = Vec::new();
        if let (Some(pool), n) = (rec.queries, rec.timestamps) {
            if n > 0 {
                let mut raw = vec![0u64; n as usize];
                // SAFETY: the work has finished, so every written query is available.
                unsafe {
                    device
                        .get_query_pool_results(pool, 0, &mut raw, vk::QueryResultFlags::TYPE_64)
                        .vk("vkGetQueryPoolResults")?
                };
                let period = rec.gpu.caps().timestamp_period_ns;
                timestamps_ns = raw.iter().map(|&t| t as f64 * period).collect();
            }
        }
        if let Some(end) = rec.profile_end {
            for (i, &(q, kernel)) in rec.profiled.iter().enumerate() {
                let next = rec.profiled.get(i + 1).map_or(end, |p| p.0 as usize);
                profile::add(kernel.name(), timestamps_ns[next] - timestamps_ns[q as usize]);
            }
        }
        Ok(Finished {
            timestamps_ns,
            dispatches: rec.dispatches,
            barriers: rec.barriers,
            host_seconds: rec.host_seconds,
        })
    }
}

impl Recorder {
    /// A command buffer that copies the device's pending uploads into their tensors and ends
    /// with a barrier before any later work (this recording's, submitted right after it), or
    /// `None` when nothing is pending. The staging buffers, and the tensors copied into, are
    /// kept until this recording's work has finished. The caller holds the queue's lock.
    fn record_uploads(&mut self) -> Result<Option<vk::CommandBuffer>> {
        let pending = std::mem::take(&mut *self.gpu.inner.pending_uploads.lock().unwrap());
        if pending.is_empty() {
            return Ok(None);
        }
        let device = self.gpu.device().clone();
        let mut copies = Vec::with_capacity(pending.len());
        for u in pending {
            let staging = Arc::new(Buffer::from_raw(&self.gpu, u.staging));
            // A tensor dropped before this submission needs no copy.
            if let Some(dst) = u.dst.upgrade() {
                copies.push((staging.raw, dst.raw, u.offset, u.bytes));
                self.keep.push(dst);
            }
            self.keep.push(staging);
        }
        let info = vk::CommandBufferAllocateInfo::default()
            .command_pool(self.pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is this recorder's own and the queue's lock is held, so no other
        // thread records into it; the buffers copied are alive (kept above) until the fence.
        unsafe {
            let cmd = device.allocate_command_buffers(&info).vk("vkAllocateCommandBuffers")?[0];
            let begin =
                vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
            device.begin_command_buffer(cmd, &begin).vk("vkBeginCommandBuffer")?;
            // A tensor written twice before this submission gets its copies in the order they
            // were written, the later after a barrier.
            let mut written = std::collections::HashSet::new();
            for (src, dst, offset, bytes) in copies {
                if !written.insert(dst) {
                    memory_barrier(&device, cmd, transfer_writes(), transfer_writes());
                    written.clear();
                    written.insert(dst);
                }
                let region = [vk::BufferCopy::default().src_offset(0).dst_offset(offset).size(bytes)];
                device.cmd_copy_buffer(cmd, src, dst, &region);
            }
            memory_barrier(&device, cmd, transfer_writes(), device_and_host());
            device.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
            Ok(Some(cmd))
        }
    }
}

/// One side of a memory barrier: pipeline stages, and the accesses at them.
type Scope = (vk::PipelineStageFlags2, vk::AccessFlags2);

/// Every shader and transfer write.
fn writes() -> Scope {
    (
        vk::PipelineStageFlags2::COMPUTE_SHADER | vk::PipelineStageFlags2::TRANSFER,
        vk::AccessFlags2::SHADER_WRITE | vk::AccessFlags2::TRANSFER_WRITE,
    )
}

/// Every shader and transfer access.
fn device_access() -> Scope {
    (
        vk::PipelineStageFlags2::COMPUTE_SHADER | vk::PipelineStageFlags2::TRANSFER,
        vk::AccessFlags2::SHADER_READ
            | vk::AccessFlags2::SHADER_WRITE
            | vk::AccessFlags2::TRANSFER_READ
            | vk::AccessFlags2::TRANSFER_WRITE,
    )
}

/// Every shader and transfer access, and the host's reads.
fn device_and_host() -> Scope {
    let (stages, access) = device_access();
    (stages | vk::PipelineStageFlags2::HOST, access | vk::AccessFlags2::HOST_READ)
}

/// The copies of uploads: transfer writes.
fn transfer_writes() -> Scope {
    (vk::PipelineStageFlags2::TRANSFER, vk::AccessFlags2::TRANSFER_WRITE)
}

/// Records into `cmd` a barrier from the accesses `src` to `dst`.
///
/// # Safety
/// `cmd` is in the recording state and only this thread records into it.
unsafe fn memory_barrier(device: &ash::Device, cmd: vk::CommandBuffer, src: Scope, dst: Scope) {
    let barrier = [vk::MemoryBarrier2::default()
        .src_stage_mask(src.0)
        .src_access_mask(src.1)
        .dst_stage_mask(dst.0)
        .dst_access_mask(dst.1)];
    device.cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().memory_barriers(&barrier));
}

impl Drop for Recorder {
    fn drop(&mut self) {
        let gpu = self.gpu.clone();
        let device = gpu.device();
        // SAFETY: after a wait the work has completed (or failed to start); without a submit
        // the command buffer never ran.
        unsafe {
            if self.submitted && device.get_fence_status(self.fence) != Ok(true) {
                // Launched and never waited for, or waiting failed or timed out: the device may
                // still run the commands. Wait, as long as a wait may; if it has not finished (a hung
                // kernel, a lost device), the pool, fence and buffers are left alive rather than
                // freed under the device's feet: a leak, where the process is about to report
                // the failure.
                let nanos = u64::try_from(self.wait.as_nanos()).unwrap_or(u64::MAX);
                if device.wait_for_fences(&[self.fence], true, nanos).is_err() {
                    std::mem::forget(std::mem::take(&mut self.keep));
                    self.gpu.inner.hung.store(true, Ordering::Release);
                    return;
                }
            }
            self.landed();
            device.destroy_command_pool(self.pool, None);
            if self.gpu.validation() != validation::Mode::Off {
                validation::forget_command_buffer(vk::Handle::as_raw(self.cmd));
            }
            for &p in &self.descriptor_pools {
                device.destroy_descriptor_pool(p, None);
            }
            device.destroy_fence(self.fence, None);
            if let Some(q) = self.queries {
                device.destroy_query_pool(q, None);
            }
        }
        self.keep.clear();
    }
}

/// Splits `total` workgroups into a 2D grid within the per-dimension limits.
pub fn linear_groups(total: u64, max: [u32; 3]) -> Option<[u32; 3]> {
    if total == 0 {
        return Some([0, 1, 1]);
    }
    let x = total.min(max[0] as u64);
    let y = total.div_ceil(x);
    (y <= max[1] as u64).then_some([x as u32, y as u32, 1])
}

impl Gpu {
    /// Fails with [`Error::Validation`] when the validation layer reported errors on this
    /// thread's Vulkan calls that no check on this thread reported yet; does nothing when
    /// validation is off.
    pub fn check_validation(&self) -> Result<()> {
        self.check_validation_during(None, "this thread's Vulkan calls")
    }

    /// [`Gpu::check_validation`], and the errors that name the command buffer `cmd`.
    fn check_validation_during(&self, cmd: Option<vk::CommandBuffer>, what: &str) -> Result<()> {
        if self.inner.validation == validation::Mode::Off {
            return Ok(());
        }
        validation::take_failure(cmd.map(vk::Handle::as_raw), what).map_or(Ok(()), Err)
    }

    /// The validation `VELOX_VALIDATE` asked for when the device was opened.
    pub fn validation(&self) -> validation::Mode {
        self.inner.validation
    }
}
