//! Device buffers and tensors.
//!
//! A tensor is a byte range of one `VkBuffer`: a fresh tensor has its own buffer, and views
//! ([`Tensor::view`]) share one at aligned offsets, so that, for example, every parameter of a
//! model can live in one buffer that one fused optimiser kernel updates. Memory comes from gpu-allocator: mapped host-visible memory on unified-memory devices
//! (CPU and most integrated GPUs: reads and writes are plain copies), device-local memory on
//! discrete GPUs (reads and writes go through a staging buffer).
//!
//! Staging buffers come from a pool the device keeps ([`Buffer::staging`]): a transfer takes
//! one of its size class where one has finished its last transfer, instead of creating a
//! buffer and allocating its memory each time.
//!
//! A write through a staging buffer does not wait: the bytes go to the staging buffer at once,
//! and the copy into the tensor is made by the next submission, before its own work and in the
//! same `vkQueueSubmit` ([`PendingUpload`]). So a training step's inputs, uploaded as it
//! records, cost no host wait each, as they would if every upload were its own submission.

use std::sync::{Arc, Weak};

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::device::Gpu;
use crate::error::{Error, Feature, Limit, Result, VkCheck};

/// Element type of a tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DType {
    F32,
    F16,
    U32,
    I32,
}

impl DType {
    pub fn size(self) -> usize {
        match self {
            DType::F16 => 2,
            _ => 4,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            DType::F32 => "f32",
            DType::F16 => "f16",
            DType::U32 => "u32",
            DType::I32 => "i32",
        }
    }
}

/// A raw device buffer with its memory.
pub struct Buffer {
    gpu: Gpu,
    pub(crate) raw: vk::Buffer,
    allocation: Option<Allocation>,
    /// Size in bytes the buffer was created with (at least 4).
    pub(crate) size: u64,
    /// Texel-buffer views made of it, by (offset, range), each made once and destroyed with the
    /// buffer (recorders keep the buffer alive while their work may read through a view).
    views: std::sync::Mutex<Vec<(u64, u64, vk::BufferView)>>,
    /// A staging buffer of the device's pool ([`Buffer::staging`]), given back to it when
    /// dropped: its memory location.
    pooled: Option<MemoryLocation>,
}

/// The device's staging buffers whose transfers have finished, by memory location and size
/// (a power of two from 4 KiB), at most [`StagingPool::MAX_BYTES`] in all: a transfer takes
/// one of its size where there is one instead of creating a buffer and allocating its memory.
#[derive(Default)]
pub struct StagingPool {
    free: Vec<(MemoryLocation, u64, vk::Buffer, Allocation)>,
    bytes: u64,
}

/// A buffer's handle, memory, size and pool, given up by [`Buffer::into_raw`]: held where a
/// `Buffer` (which holds the device) cannot be, in the device's own lists.
pub(crate) struct RawBuffer {
    pub raw: vk::Buffer,
    pub allocation: Allocation,
    pub size: u64,
    pooled: Option<MemoryLocation>,
}

impl StagingPool {
    pub const MAX_BYTES: u64 = 64 << 20;

    pub(crate) fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Every pooled buffer's handle and memory, for the device to free.
    pub(crate) fn drain(&mut self) -> impl Iterator<Item = (vk::Buffer, Allocation)> + '_ {
        self.bytes = 0;
        self.free.drain(..).map(|(_, _, raw, a)| (raw, a))
    }
}

impl Buffer {
    pub(crate) fn new(gpu: &Gpu, size: u64, location: MemoryLocation, name: &str) -> Result<Buffer> {
        let caps = gpu.caps();
        // Vulkan forbids empty buffers; 16 bytes also keeps f16 tails in whole words.
        // Whole vec4s: a kernel may read a tensor's last 16 bytes as one (binding_range).
        let size = size.max(16).next_multiple_of(16);
        if size > caps.max_buffer_size {
            return Err(Error::too_large(
                Limit::Buffer,
                format!(
                    "{name}: a buffer of {size} bytes exceeds the device's maximum buffer size of {} bytes",
                    caps.max_buffer_size
                ),
            ));
        }
        let device = gpu.device();
        let mut usage = vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST;
        if caps.texel_reads {
            usage |= vk::BufferUsageFlags::STORAGE_TEXEL_BUFFER;
        }
        let info =
            vk::BufferCreateInfo::default().size(size).usage(usage).sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid device and create info.
        let raw = unsafe { device.create_buffer(&info, None) }.vk("vkCreateBuffer")?;
        // SAFETY: `raw` was just created on this device.
        let requirements = unsafe { device.get_buffer_memory_requirements(raw) };
        let allocation = gpu.inner.allocator.lock().unwrap().allocate(&AllocationCreateDesc {
            name,
            requirements,
            location,
            linear: true,
            allocation_scheme: AllocationScheme::GpuAllocatorManaged,
        });
        let allocation = match allocation {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: the buffer has no memory bound and is not in use.
                unsafe { device.destroy_buffer(raw, None) };
                return Err(Error::OutOfMemory(format!("{name}: {size} bytes: {e}")));
            }
        };
        // SAFETY: the allocation satisfies the buffer's requirements.
        if let Err(e) = unsafe { device.bind_buffer_memory(raw, allocation.memory(), allocation.offset()) } {
            // SAFETY: as above.
            unsafe { device.destroy_buffer(raw, None) };
            let _ = gpu.inner.allocator.lock().unwrap().free(allocation);
            return Err(Error::Vulkan { call: "vkBindBufferMemory", result: e });
        }
        gpu.account_memory(allocation.size(), true);
        Ok(Buffer {
            gpu: gpu.clone(),
            raw,
            allocation: Some(allocation),
            size,
            views: Default::default(),
            pooled: None,
        })
    }

    /// A host-visible buffer of at least `size` bytes at `location` for one transfer, from the
    /// device's pool where it holds one of the size class (a power of two from 4 KiB), else made;
    /// it goes back to the pool when dropped (after its transfer has finished: recorders keep
    /// the buffers they use until then).
    pub(crate) fn staging(gpu: &Gpu, size: u64, location: MemoryLocation, name: &str) -> Result<Buffer> {
        let class = size.max(4096).next_power_of_two();
        let taken = {
            let mut pool = gpu.inner.staging_pool.lock().unwrap();
            let at = pool.free.iter().position(|(l, s, ..)| *l == location && *s == class);
            at.map(|i| {
                pool.bytes -= class;
                pool.free.swap_remove(i)
            })
        };
        let mut buffer = match taken {
            Some((_, _, raw, allocation)) => {
                gpu.account_memory(allocation.size(), true);
                Buffer {
                    gpu: gpu.clone(),
                    raw,
                    allocation: Some(allocation),
                    size: class,
                    views: Default::default(),
                    pooled: None,
                }
            }
            None => Buffer::new(gpu, class, location, name)?,
        };
        buffer.pooled = Some(location);
        Ok(buffer)
    }

    /// A view of `range` bytes from `offset` as vec4 texels (`R32G32B32A32_SFLOAT`), made on
    /// first use.
    fn texel_view(&self, offset: u64, range: u64) -> Result<vk::BufferView> {
        let mut views = self.views.lock().unwrap();
        if let Some(&(_, _, v)) = views.iter().find(|(o, r, _)| *o == offset && *r == range) {
            return Ok(v);
        }
        let info = vk::BufferViewCreateInfo::default()
            .buffer(self.raw)
            .format(vk::Format::R32G32B32A32_SFLOAT)
            .offset(offset)
            .range(range);
        // SAFETY: buffers are made with STORAGE_TEXEL_BUFFER usage where the device has texel
        // buffers (Caps::texel_reads), and the caller checked the offset, range and texel count.
        let view = unsafe { self.gpu.device().create_buffer_view(&info, None) }.vk("vkCreateBufferView")?;
        views.push((offset, range, view));
        Ok(view)
    }

    /// The buffer's handle, memory and size, given up by this value (which then frees
    /// nothing): an upload's staging buffer waiting for a submission, which must not hold a
    /// `Gpu` (the device holds the pending uploads).
    fn into_raw(mut self) -> RawBuffer {
        let allocation = self.allocation.take().expect("a buffer with memory");
        let raw = std::mem::replace(&mut self.raw, vk::Buffer::null());
        RawBuffer { raw, allocation, size: self.size, pooled: self.pooled.take() }
    }

    /// A buffer of the handle and memory [`Buffer::into_raw`] gave up.
    pub(crate) fn from_raw(gpu: &Gpu, b: RawBuffer) -> Buffer {
        let RawBuffer { raw, allocation, size, pooled } = b;
        Buffer {
            gpu: gpu.clone(),
            raw,
            allocation: Some(allocation),
            size,
            views: Default::default(),
            pooled,
        }
    }

    /// The first `out.len()` bytes of a staging buffer whose copy into it has completed,
    /// counted as staged.
    fn read_staged(&self, out: &mut [u8]) -> Result<()> {
        let ptr = self.mapped().ok_or_else(|| {
            Error::unsupported(Feature::HostVisibleMemory, "staging memory is not host-visible")
        })?;
        // SAFETY: the caller's copy into the buffer has completed; the mapping holds at least
        // `out.len()` bytes (a staging buffer is made for its transfer's size or larger).
        unsafe { std::ptr::copy_nonoverlapping(ptr, out.as_mut_ptr(), out.len()) };
        self.gpu.inner.staged_bytes.fetch_add(out.len() as u64, std::sync::atomic::Ordering::Relaxed);
        Ok(())
    }

    /// The mapped bytes, when the buffer lives in host-visible memory.
    pub(crate) fn mapped(&self) -> Option<*mut u8> {
        self.allocation.as_ref().and_then(|a| a.mapped_ptr()).map(|p| p.as_ptr() as *mut u8)
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        // A staging buffer goes back to the device's pool while it has room (only such a
        // buffer's memory is taken here: any other's is freed below).
        if let Some(location) = self.pooled {
            let mut pool = self.gpu.inner.staging_pool.lock().unwrap();
            let room = pool.bytes + self.size <= StagingPool::MAX_BYTES;
            if let Some(a) = self.allocation.take_if(|_| room && self.views.get_mut().unwrap().is_empty()) {
                self.gpu.account_memory(a.size(), false);
                pool.bytes += self.size;
                pool.free.push((location, self.size, self.raw, a));
                return;
            }
        }
        // SAFETY: recorders keep an `Arc<Buffer>` of every buffer they bind until their work
        // has finished, so the last drop happens when no command uses the buffer or its views.
        unsafe {
            for (_, _, view) in self.views.get_mut().unwrap().drain(..) {
                self.gpu.device().destroy_buffer_view(view, None);
            }
            // A null handle (given up by `into_raw`) is ignored.
            self.gpu.device().destroy_buffer(self.raw, None)
        };
        if let Some(a) = self.allocation.take() {
            self.gpu.account_memory(a.size(), false);
            let _ = self.gpu.inner.allocator.lock().unwrap().free(a);
        }
    }
}

/// A dense row-major tensor on the device.
#[derive(Clone)]
pub struct Tensor {
    pub(crate) buf: Arc<Buffer>,
    /// Byte offset of element 0 in `buf`.
    pub(crate) offset: u64,
    shape: Vec<usize>,
    dtype: DType,
}

impl std::fmt::Debug for Tensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Tensor({:?}, {})", self.shape, self.dtype.name())
    }
}

/// Plain element types that map to a [`DType`].
pub trait Element: bytemuck::Pod {
    const DTYPE: DType;
}
impl Element for f32 {
    const DTYPE: DType = DType::F32;
}
impl Element for u32 {
    const DTYPE: DType = DType::U32;
}
impl Element for i32 {
    const DTYPE: DType = DType::I32;
}
impl Element for half::f16 {
    const DTYPE: DType = DType::F16;
}

pub(crate) fn numel_of(shape: &[usize]) -> Result<usize> {
    shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d)).ok_or_else(|| {
        Error::too_large(Limit::Memory, format!("shape {shape:?} has more elements than fit in memory"))
    })
}

impl Tensor {
    /// An uninitialised tensor.
    pub fn empty(gpu: &Gpu, shape: &[usize], dtype: DType) -> Result<Tensor> {
        let n = numel_of(shape)?;
        let bytes = (n as u64)
            .checked_mul(dtype.size() as u64)
            .ok_or_else(|| Error::too_large(Limit::Memory, format!("shape {shape:?}")))?;
        let location =
            if gpu.caps().unified_memory { MemoryLocation::CpuToGpu } else { MemoryLocation::GpuOnly };
        let buf = Buffer::new(gpu, bytes, location, "tensor")?;
        Ok(Tensor { buf: Arc::new(buf), offset: 0, shape: shape.to_vec(), dtype })
    }

    /// A tensor holding `data`, which must have as many elements as `shape`.
    pub fn from_slice<T: Element>(gpu: &Gpu, shape: &[usize], data: &[T]) -> Result<Tensor> {
        let n = numel_of(shape)?;
        if n != data.len() {
            return Err(Error::Shape(format!(
                "shape {shape:?} holds {n} elements but {} were given",
                data.len()
            )));
        }
        let t = Tensor::empty(gpu, shape, T::DTYPE)?;
        t.write(data)?;
        Ok(t)
    }

    /// Overwrites the whole tensor with `data`.
    pub fn write<T: Element>(&self, data: &[T]) -> Result<()> {
        self.check_host_type::<T>(data.len())?;
        self.gpu().write_buffer(&self.buf, self.offset, bytemuck::cast_slice(data))
    }

    /// Reads the whole tensor back.
    pub fn read<T: Element>(&self) -> Result<Vec<T>> {
        self.check_host_type::<T>(self.numel())?;
        let mut out = vec![T::zeroed(); self.numel()];
        self.gpu().read_buffer(&self.buf, self.offset, bytemuck::cast_slice_mut(&mut out))?;
        Ok(out)
    }

    fn check_host_type<T: Element>(&self, len: usize) -> Result<()> {
        if T::DTYPE != self.dtype {
            return Err(Error::DType(format!(
                "tensor is {} but the host data is {}",
                self.dtype.name(),
                T::DTYPE.name()
            )));
        }
        if len != self.numel() {
            return Err(Error::Shape(format!(
                "tensor {:?} holds {} elements, host data {}",
                self.shape,
                self.numel(),
                len
            )));
        }
        Ok(())
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }
    pub fn dtype(&self) -> DType {
        self.dtype
    }
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn bytes(&self) -> u64 {
        (self.numel() * self.dtype.size()) as u64
    }
    pub fn gpu(&self) -> &Gpu {
        &self.buf.gpu
    }

    /// The same data under another shape with the same number of elements.
    pub fn reshape(&self, shape: &[usize]) -> Result<Tensor> {
        if numel_of(shape)? != self.numel() {
            return Err(Error::Shape(format!("cannot reshape {:?} to {shape:?}", self.shape)));
        }
        Ok(Tensor { buf: self.buf.clone(), offset: self.offset, shape: shape.to_vec(), dtype: self.dtype })
    }

    /// A view of `shape` starting `start` elements into this tensor, sharing its storage. The
    /// start must be a multiple of [`Tensor::view_alignment`] elements (the device's storage
    /// offset alignment) so that the view can be bound by itself.
    pub fn view(&self, start: usize, shape: &[usize]) -> Result<Tensor> {
        let n = numel_of(shape)?;
        if start.checked_add(n).is_none_or(|end| end > self.numel()) {
            return Err(Error::Shape(format!(
                "view of {n} elements at {start} runs past the end of {self:?}"
            )));
        }
        let align = self.view_alignment();
        if !start.is_multiple_of(align) {
            return Err(Error::Shape(format!(
                "view start {start} of {self:?} is not a multiple of {align} elements (the device's storage offset alignment)"
            )));
        }
        let offset = if n == 0 { self.offset } else { self.offset + (start * self.dtype.size()) as u64 };
        Ok(Tensor { buf: self.buf.clone(), offset, shape: shape.to_vec(), dtype: self.dtype })
    }

    /// Element multiple at which views of this tensor may start: the device's storage offset
    /// alignment, and where the CPU kernels read through texel buffers its texel offset alignment.
    pub fn view_alignment(&self) -> usize {
        let caps = self.gpu().caps();
        let texel = if caps.texel_kernels() { caps.min_texel_buffer_offset_alignment } else { 1 };
        let bytes = caps.min_storage_buffer_offset_alignment.max(texel).max(4) as usize;
        bytes.div_ceil(self.dtype.size())
    }

    /// Whether the tensor can be bound as a texel buffer of vec4s ([`Tensor::texel_view`]): the
    /// device has them, the view's offset is aligned for one and its texels fit one.
    pub fn texel_bindable(&self) -> bool {
        let caps = self.gpu().caps();
        let (offset, range) = self.binding_range();
        caps.texel_reads
            && offset.is_multiple_of(caps.min_texel_buffer_offset_alignment.max(1))
            && range.is_multiple_of(16)
            && range / 16 <= caps.max_texel_buffer_elements
    }

    /// The tensor's bytes (its binding range) as a texel buffer of vec4s.
    pub(crate) fn texel_view(&self, what: &str) -> Result<vk::BufferView> {
        if !self.texel_bindable() {
            let caps = self.gpu().caps();
            return Err(Error::unsupported(
                Feature::TexelBuffers,
                format!(
                    "{what}: tensor {:?} {} at byte {} as a texel buffer of vec4s (the device: texel \
                     buffers of vec4s {}, at most {} texels, offsets a multiple of {})",
                    self.shape,
                    self.dtype.name(),
                    self.offset,
                    if caps.texel_reads { "yes" } else { "no" },
                    caps.max_texel_buffer_elements,
                    caps.min_texel_buffer_offset_alignment
                ),
            ));
        }
        let (offset, range) = self.binding_range();
        self.buf.texel_view(offset, range)
    }

    /// The byte range to bind: the tensor's bytes rounded up to whole vec4s (16 bytes, which
    /// kernels reading f32 tensors in vec4s rely on: buffers are allocated so, and views start on
    /// the storage offset alignment, at least 16), never past the buffer nor the device's range.
    pub(crate) fn binding_range(&self) -> (u64, u64) {
        let max = self.gpu().caps().max_storage_buffer_range;
        let range = self.bytes().next_multiple_of(16).max(16).min(self.buf.size - self.offset);
        (self.offset, range.min(max.max(self.bytes().next_multiple_of(4))))
    }

    /// Whether two tensors share storage.
    pub fn same_storage(&self, other: &Tensor) -> bool {
        Arc::ptr_eq(&self.buf, &other.buf)
    }

    /// Fails with a clear message when the tensor cannot be bound as one storage buffer.
    pub(crate) fn check_bindable(&self, what: &str) -> Result<()> {
        let max = self.gpu().caps().max_storage_buffer_range;
        if self.bytes() > max {
            return Err(Error::too_large(Limit::Binding, format!(
                "{what}: tensor {:?} {} is {} bytes, more than the {} bytes this device binds as one storage buffer",
                self.shape,
                self.dtype.name(),
                self.bytes(),
                max
            )));
        }
        Ok(())
    }
}

/// A tensor's value as a recording left it where [`crate::Recorder::read_back`] was called,
/// for the host to read once that recording has been submitted, without a submission or a
/// wait of its own: on a device whose memory the host maps, the tensor itself, read in place
/// (so read it before later work rewrites it); elsewhere a host-visible buffer the recording
/// copies the tensor into. A [`Tensor::read`] on such a device is a copy submitted and waited
/// for: a training step reads its tile-pair counts, its losses and its gradient norm so instead.
#[derive(Clone)]
pub struct Readback {
    tensor: Tensor,
    staging: Option<Arc<Buffer>>,
    done: crate::Completion,
}

impl std::fmt::Debug for Readback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Readback({:?}, {})",
            self.tensor,
            if self.staging.is_some() { "staged" } else { "in place" }
        )
    }
}

impl Readback {
    pub(crate) fn new(tensor: Tensor, staging: Option<Arc<Buffer>>, done: crate::Completion) -> Readback {
        Readback { tensor, staging, done }
    }

    /// The values, once the recording that reads them back has run (an error before).
    pub fn read<T: Element>(&self) -> Result<Vec<T>> {
        if !self.done.is_done() {
            return Err(Error::Invalid(format!(
                "{:?} read back before the recording that copies it has run",
                self.tensor
            )));
        }
        let Some(staging) = &self.staging else { return self.tensor.read() };
        self.tensor.check_host_type::<T>(self.tensor.numel())?;
        let mut out = vec![T::zeroed(); self.tensor.numel()];
        // The recording's copy into the staging buffer has completed (`done`).
        staging.read_staged(bytemuck::cast_slice_mut(&mut out))?;
        Ok(out)
    }

    /// The tensor read back.
    pub fn tensor(&self) -> &Tensor {
        &self.tensor
    }
}

impl Tensor {
    /// Whether the host reads this tensor through a staging copy (its memory is not mapped,
    /// or `VELOX_FORCE_STAGING=1`).
    pub(crate) fn staged(&self) -> bool {
        self.buf.mapped().is_none() || self.gpu().inner.force_staging
    }
}

/// A write waiting in its staging buffer for the next submission to copy it into `dst` (see
/// the module docs). The destination is held weakly: a tensor dropped before any submission
/// is not copied into. The staging buffer is held as its raw parts, since the device holds the
/// list and a `Buffer` holds the device.
pub(crate) struct PendingUpload {
    pub staging: RawBuffer,
    pub dst: Weak<Buffer>,
    pub offset: u64,
    pub bytes: u64,
}

impl Gpu {
    pub(crate) fn write_buffer(&self, buf: &Arc<Buffer>, offset: u64, bytes: &[u8]) -> Result<()> {
        if bytes.is_empty() {
            return Ok(());
        }
        if let Some(ptr) = buf.mapped().filter(|_| !self.inner.force_staging) {
            // SAFETY: the mapping covers `buf.size >= offset + bytes.len()` bytes (tensors and
            // views never extend past their buffer), and no GPU work is in flight: every
            // recorder waits for its work before returning.
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), ptr.add(offset as usize), bytes.len()) };
            return Ok(());
        }
        let staging = Buffer::staging(self, bytes.len() as u64, MemoryLocation::CpuToGpu, "upload staging")?;
        let ptr = staging.mapped().ok_or_else(|| {
            Error::unsupported(Feature::HostVisibleMemory, "staging memory is not host-visible")
        })?;
        // SAFETY: the staging mapping holds at least `bytes.len()` bytes.
        unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), ptr, bytes.len()) };
        self.inner.staged_bytes.fetch_add(bytes.len() as u64, std::sync::atomic::Ordering::Relaxed);
        let staging = staging.into_raw();
        self.inner.pending_uploads.lock().unwrap().push(PendingUpload {
            staging,
            dst: Arc::downgrade(buf),
            offset,
            bytes: bytes.len() as u64,
        });
        Ok(())
    }

    pub(crate) fn read_buffer(&self, buf: &Buffer, offset: u64, out: &mut [u8]) -> Result<()> {
        if out.is_empty() {
            return Ok(());
        }
        if let Some(ptr) = buf.mapped().filter(|_| !self.inner.force_staging) {
            // SAFETY: as in `write_buffer`.
            unsafe { std::ptr::copy_nonoverlapping(ptr.add(offset as usize), out.as_mut_ptr(), out.len()) };
            return Ok(());
        }
        let staging = Buffer::staging(self, out.len() as u64, MemoryLocation::GpuToCpu, "download staging")?;
        self.copy_now(buf, offset, &staging, 0, out.len() as u64)?;
        staging.read_staged(out)
    }

    fn copy_now(
        &self,
        src: &Buffer,
        src_offset: u64,
        dst: &Buffer,
        dst_offset: u64,
        bytes: u64,
    ) -> Result<()> {
        let mut rec = self.recorder()?;
        rec.copy_raw(src, src_offset, dst, dst_offset, bytes);
        rec.submit()?;
        Ok(())
    }
}
