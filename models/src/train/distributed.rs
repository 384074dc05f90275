//! Data-parallel training over MPI: one process (a rank) per GPU, on one machine or several,
//! started by `mpirun -np N velox ...`. Every rank holds the whole model, trains on its own
//! share of each step's micro-batches, and the ranks sum their gradients before the optimiser,
//! so every rank applies the same update and the parameters stay identical everywhere.
//!
//! [`Comm::world`] is the run's communicator. Started by an MPI launcher, it opens Open MPI's
//! library (`super::mpi`: no build of velox links MPI) and initialises MPI, once per process;
//! started without one, it is a single-rank `Comm` whose collectives do nothing, so the same
//! trainer runs alone. A process of an MPI launch whose MPI library does not open refuses to
//! start, rather than train N identical copies.
//!
//! A trainer's step, on every rank, with N ranks of k micro-batches each:
//! 1. `store.zero_grads(&mut rec)` (`velox_models::params::ParamStore`);
//! 2. the forward and backward passes of this rank's micro-batches, which add into the store's
//!    gradient buffer, recorded and submitted (submitting waits for the device); rank r takes
//!    micro-batches r k to (r + 1) k - 1 of the step's N k, the ones one process accumulating
//!    N k micro-batches would take in that order;
//! 3. [`Comm::all_reduce_sum`] of `store.flat_grads()`: the gradient buffer now holds the sum
//!    over every rank's micro-batches, identical on every rank;
//! 4. the optimiser (`store.adamw_step`), recorded and submitted after the all-reduce, scaling
//!    the summed gradients as one process accumulating all N k micro-batches would (a trainer
//!    that averages its micro-batches divides by N k); every rank applies the same update;
//! 5. logs, plots and checkpoints written by the root rank alone ([`Comm::is_root`]), with the
//!    other ranks' losses from [`Comm::all_gather_f64`]. A checkpoint holds nothing per rank,
//!    so a run may resume on another number of ranks.
//!
//! A rank that fails while the others may be waiting in a collective ends the run with
//! [`Comm::abort_all`]: returning an error and dropping the `Comm` would finalise MPI, which
//! waits for every rank, forever. A panic does so by itself (see the `Drop` of the MPI state).
//!
//! The MPI state lives as long as a `Comm` (clones share it) and is finalised when the last one
//! is dropped: drop it before `std::process::exit`, or `mpirun` reports a rank that exited
//! without finalising. MPI cannot start twice in a process, so a run keeps one `Comm` from
//! start to end, on the thread that created it (a `Comm` is neither `Send` nor `Sync`, alone or
//! not: MPI is initialised for calls from that thread only).
//!
//! Tests: `tests/distributed.rs` and `tools/tests/distributed_train.rs` (two processes over MPI).

use std::marker::PhantomData;

use velox_engine::{DType, Error, Result, Tensor};

/// Elements of a gradient bucket by default: 1 Mi f32, 4 MiB.
pub const DEFAULT_BUCKET_LEN: usize = 1 << 20;

/// The largest bucket: 2^28 f32 (1 GiB), so that every count passed to MPI fits its `int`.
pub const MAX_BUCKET_LEN: usize = 1 << 28;

/// The run's communicator: this process's rank among the run's processes, and the collective
/// operations a data-parallel trainer needs. Cheap to clone; clones share the MPI state.
#[derive(Clone)]
pub struct Comm {
    backend: Backend,
    bucket_len: usize,
    /// Neither `Send` nor `Sync` in every build, as the MPI state is.
    _one_thread: PhantomData<*const ()>,
}

#[derive(Clone)]
enum Backend {
    /// One process: every collective is the identity.
    Single,
    Mpi(std::rc::Rc<mpi_world::World>),
}

/// How this process was started, read from the variables MPI launchers set: Open MPI's
/// `mpirun` sets `OMPI_COMM_WORLD_SIZE`; MPICH's and Intel MPI's launchers, and Slurm's PMI,
/// set `PMI_SIZE`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Launch {
    Alone,
    Mpi { size: usize },
}

const SIZE_VARIABLES: [&str; 2] = ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"];

fn launch(var: impl Fn(&str) -> Option<String>) -> Result<Launch> {
    for name in SIZE_VARIABLES {
        if let Some(value) = var(name) {
            let size = value.trim().parse::<usize>().ok().filter(|&n| n > 0).ok_or_else(|| {
                Error::Mpi(format!("{name}={value} in the environment is not a number of processes"))
            })?;
            return Ok(Launch::Mpi { size });
        }
    }
    Ok(Launch::Alone)
}

fn start(launch: Launch) -> Result<Backend> {
    match launch {
        Launch::Alone => Ok(Backend::Single),
        Launch::Mpi { size } => Ok(Backend::Mpi(mpi_world::World::get(size)?)),
    }
}

impl Comm {
    /// The run's communicator: MPI's world when started by an MPI launcher (opening Open MPI's
    /// library and initialising MPI on the first call; later calls on the same thread share it),
    /// a single rank otherwise. Fails when a process of an MPI launch cannot open Open MPI's
    /// library, when MPI cannot start, or when MPI was started and finalised already.
    pub fn world() -> Result<Comm> {
        let backend = start(launch(|name| std::env::var(name).ok())?)?;
        Ok(Comm { backend, bucket_len: DEFAULT_BUCKET_LEN, _one_thread: PhantomData })
    }

    /// A single-rank communicator, whatever the environment: every collective is the identity.
    pub fn single() -> Comm {
        Comm { backend: Backend::Single, bucket_len: DEFAULT_BUCKET_LEN, _one_thread: PhantomData }
    }

    /// This process's rank, in `0..size()`.
    pub fn rank(&self) -> usize {
        match &self.backend {
            Backend::Single => 0,
            Backend::Mpi(w) => w.rank,
        }
    }

    /// The number of processes in the run.
    pub fn size(&self) -> usize {
        match &self.backend {
            Backend::Single => 1,
            Backend::Mpi(w) => w.size,
        }
    }

    /// This process's rank among the run's processes on the same machine (those that share
    /// memory, from MPI's shared-memory split of the world), which picks its GPU:
    /// `velox_engine::Gpu::for_local_rank(comm.local_rank())`.
    pub fn local_rank(&self) -> usize {
        match &self.backend {
            Backend::Single => 0,
            Backend::Mpi(w) => w.local_rank,
        }
    }

    /// The number of the run's processes on this machine.
    pub fn local_size(&self) -> usize {
        match &self.backend {
            Backend::Single => 1,
            Backend::Mpi(w) => w.local_size,
        }
    }

    /// Whether this is rank 0, the one that writes logs, plots and checkpoints.
    pub fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Elements per bucket of [`Comm::all_reduce_sum`].
    pub fn bucket_len(&self) -> usize {
        self.bucket_len
    }

    /// Sets the elements per bucket of [`Comm::all_reduce_sum`] for this handle, between 1 and
    /// [`MAX_BUCKET_LEN`]. A sum uses the largest bucket any rank asks for, rounded up to a
    /// multiple of every rank's device view alignment. The sums do not depend on it; the host
    /// memory and the number of MPI calls do.
    pub fn set_bucket_len(&mut self, elements: usize) -> Result<()> {
        if elements == 0 || elements > MAX_BUCKET_LEN {
            return Err(Error::Invalid(format!(
                "an all-reduce bucket of {elements} elements: it takes 1 to {MAX_BUCKET_LEN}"
            )));
        }
        self.bucket_len = elements;
        Ok(())
    }

    /// Sums an f32 tensor across the ranks, in place: afterwards every rank holds, bit for bit,
    /// the same sum of what each rank held. Every rank must call it with a tensor of the same
    /// length: the ranks first exchange their lengths and buckets, so a mismatch is an error on
    /// every rank, not a hang.
    /// Call it with no recording in flight on the tensor (after the recording that wrote it was
    /// submitted).
    ///
    /// The tensor goes through the host in buckets of [`Comm::bucket_len`] elements, one after
    /// another. For each bucket: a read to the host (a copy of mapped memory on CPUs and
    /// integrated GPUs, a staging copy on discrete GPUs); an `MPI_Alltoall` that gives rank j
    /// the j-th of N slices of every rank's bucket; the sum of each element over the ranks, in
    /// rank order, by the rank that owns its slice; an `MPI_Allgather` of the summed slices;
    /// a write back to the device. Each rank sends and receives 2 (N - 1) / N times the
    /// bucket's bytes, the volume of a ring all-reduce, and holds at most three buckets of host
    /// memory (12 MiB at the default).
    ///
    /// Deterministic: each element is `((x_0 + x_1) + x_2) + ...`, the ranks' values added in
    /// rank order in f32 on the host, so the same inputs on the same number of ranks give the
    /// same bits whatever the timing, the bucket size or the machines. MPI moves the data but
    /// does no arithmetic: `MPI_Allreduce` would leave the order of the additions to the MPI
    /// library, and Open MPI picks its algorithm (reduction trees, rings, segment sizes) by
    /// message size, rank count, placement and tuning parameters, which the standard only
    /// recommends, and does not require, to give the same result for the same arguments. With
    /// a different number of ranks the order of the additions differs, and so may the last
    /// bits, as with a different split into micro-batches on one process.
    pub fn all_reduce_sum(&self, t: &Tensor) -> Result<()> {
        if t.dtype() != DType::F32 {
            return Err(Error::Shape(format!("all_reduce_sum takes an f32 tensor, not {t:?}")));
        }
        match &self.backend {
            Backend::Single => Ok(()),
            Backend::Mpi(w) => w.all_reduce_sum(t, self.bucket_len),
        }
    }

    /// Sends `data` from rank `root` to every rank: afterwards every rank's `data` equals the
    /// root's, whatever its length before. Every rank must name the same root. For the run's
    /// settings, a checkpoint, or a decision of the root (the data of a step) that every rank
    /// must follow.
    pub fn broadcast_bytes(&self, root: usize, data: &mut Vec<u8>) -> Result<()> {
        if root >= self.size() {
            return Err(Error::Invalid(format!(
                "broadcast from rank {root}, but the run has {} rank(s)",
                self.size()
            )));
        }
        match &self.backend {
            Backend::Single => Ok(()),
            Backend::Mpi(w) => w.broadcast_bytes(root, data),
        }
    }

    /// Every rank's `x`, in rank order, on every rank (for logging each rank's loss).
    pub fn all_gather_f64(&self, x: f64) -> Result<Vec<f64>> {
        match &self.backend {
            Backend::Single => Ok(vec![x]),
            Backend::Mpi(w) => w.all_gather_f64(x),
        }
    }

    /// Returns once every rank has called it.
    pub fn barrier(&self) -> Result<()> {
        match &self.backend {
            Backend::Single => Ok(()),
            Backend::Mpi(w) => w.barrier(),
        }
    }

    /// Ends every process of the run at once with exit status `code` (`MPI_Abort`), for a rank
    /// that fails while others may wait for it in a collective. A single rank just exits.
    pub fn abort_all(&self, code: i32) -> ! {
        match &self.backend {
            Backend::Single => std::process::exit(code),
            Backend::Mpi(w) => w.abort(code),
        }
    }
}

impl std::fmt::Debug for Comm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Comm(rank {} of {}, local rank {})", self.rank(), self.size(), self.local_rank())
    }
}

/// The bucket every rank of a sum uses, from what each rank told the others: its tensor's
/// length, the bucket length it asks for and its device's view alignment, in elements. Ranks
/// whose tensors differ in length are an error; otherwise the largest bucket asked for,
/// rounded up to a multiple of every rank's alignment, so that on every device each bucket
/// starts where a view can. (The sums do not depend on it, but the ranks must exchange the
/// same slices.)
fn agree_on_bucket(told: &[[u64; 3]]) -> Result<usize> {
    let first = told.first().map_or(0, |t| t[0]);
    if told.iter().any(|t| t[0] != first) {
        let each: Vec<String> = told.iter().enumerate().map(|(r, t)| format!("rank {r}: {}", t[0])).collect();
        return Err(Error::Mpi(format!(
            "all_reduce_sum: the ranks hold tensors of different lengths ({}); every rank must sum \
             the same buffer",
            each.join(", ")
        )));
    }
    fn gcd(a: u64, b: u64) -> u64 {
        if b == 0 {
            a
        } else {
            gcd(b, a % b)
        }
    }
    let too_large = || Error::Mpi(format!("all_reduce_sum: no common bucket for {told:?}"));
    let mut align = 1u64;
    for t in told {
        let a = t[2].max(1);
        align = (align / gcd(align, a)).checked_mul(a).ok_or_else(too_large)?;
    }
    let asked = told.iter().map(|t| t[1].max(1)).max().unwrap_or(1);
    let bucket = asked.checked_next_multiple_of(align).ok_or_else(too_large)?;
    usize::try_from(bucket).map_err(|_| too_large())
}

/// The sum over `ranks` of `slices` (the ranks' slices of `out.len()` elements, one after
/// another in rank order), each element added in rank order: `((s_0 + s_1) + s_2) + ...`.
fn sum_in_rank_order(slices: &[f32], ranks: usize, out: &mut [f32]) {
    let n = out.len();
    debug_assert_eq!(slices.len(), n * ranks);
    out.copy_from_slice(&slices[..n]);
    for slice in slices.chunks_exact(n).skip(1) {
        for (o, &x) in out.iter_mut().zip(slice) {
            *o += x;
        }
    }
}

mod mpi_world {
    //! The MPI side of [`super::Comm`], on Open MPI's C calls (`super::mpi`), every call's
    //! return code checked and returned as an error naming the call and MPI's message: MPI
    //! errors are set to return on the run's communicator instead of ending the job.

    use std::cell::RefCell;
    use std::ffi::{c_int, c_void};
    use std::rc::{Rc, Weak};
    use std::sync::atomic::{AtomicBool, Ordering};

    use velox_engine::{Error, Result, Tensor};

    use super::super::mpi::{self, Handle, Mpi};
    use super::{agree_on_bucket, sum_in_rank_order};

    /// Bytes per `MPI_Bcast` of a broadcast, so that a count fits MPI's `int`.
    const BROADCAST_PIECE: usize = 1 << 28;

    thread_local! {
        /// The live MPI state of this thread, shared by every `Comm` it hands out.
        static LIVE: RefCell<Weak<World>> = const { RefCell::new(Weak::new()) };
    }
    /// Whether this process ever initialised MPI (which it may do once).
    static STARTED: AtomicBool = AtomicBool::new(false);

    pub(super) struct World {
        mpi: &'static Mpi,
        /// A duplicate of `MPI_COMM_WORLD`, whose errors return to the caller; null until made.
        comm: Handle,
        pub rank: usize,
        pub size: usize,
        pub local_rank: usize,
        pub local_size: usize,
    }

    /// An MPI call's return code as a result that names the call.
    fn check(mpi: &Mpi, code: c_int, call: &str) -> Result<()> {
        if code == mpi::SUCCESS {
            return Ok(());
        }
        let mut text = vec![0u8; mpi::MAX_ERROR_STRING + 1];
        let mut len: c_int = 0;
        // SAFETY: the buffer holds MPI_MAX_ERROR_STRING characters, as MPI_Error_string needs.
        let ok = unsafe { (mpi.error_string)(code, text.as_mut_ptr().cast(), &mut len) };
        let message = if ok == mpi::SUCCESS {
            String::from_utf8_lossy(&text[..(len.max(0) as usize).min(text.len())]).into_owned()
        } else {
            format!("error code {code}")
        };
        Err(Error::Mpi(format!("{call} failed: {message}")))
    }

    fn count(n: usize, call: &str) -> Result<c_int> {
        c_int::try_from(n)
            .map_err(|_| Error::Mpi(format!("{call}: {n} elements are more than one MPI call can take")))
    }

    impl World {
        /// This thread's MPI state, initialising MPI on the first call of the process; `launched`
        /// is the number of processes the launcher's environment announced.
        pub fn get(launched: usize) -> Result<Rc<World>> {
            if let Some(world) = LIVE.with(|live| live.borrow().upgrade()) {
                return Ok(world);
            }
            let mpi = mpi::library()?;
            if STARTED.swap(true, Ordering::SeqCst) {
                return Err(Error::Mpi(
                    "MPI was started once in this process already and was finalised when its last \
                     Comm was dropped, or belongs to another thread; MPI cannot start twice: keep \
                     one Comm for the whole run, on one thread"
                        .into(),
                ));
            }
            let mut already: c_int = 0;
            // SAFETY: MPI_Initialized may be called at any time; the out-pointer is valid.
            check(mpi, unsafe { (mpi.initialized)(&mut already) }, "MPI_Initialized")?;
            if already != 0 {
                return Err(Error::Mpi(
                    "MPI was initialised in this process by something other than velox".into(),
                ));
            }
            let mut provided: c_int = 0;
            // SAFETY: no arguments to pass on (null argc and argv are allowed); valid out-pointer.
            let code = unsafe {
                (mpi.init_thread)(
                    std::ptr::null_mut(),
                    std::ptr::null_mut(),
                    mpi::THREAD_FUNNELED,
                    &mut provided,
                )
            };
            check(mpi, code, "MPI_Init_thread")?;
            // From here on, dropping `world` finalises MPI, on the error paths too.
            let mut world =
                World { mpi, comm: mpi.comm_null, rank: 0, size: 1, local_rank: 0, local_size: 1 };
            if provided < mpi::THREAD_FUNNELED {
                return Err(Error::Mpi(format!(
                    "MPI provides thread level {provided}, less than MPI_THREAD_FUNNELED, which a run \
                     whose device work runs on other threads needs"
                )));
            }
            // SAFETY: MPI is initialised; the out-pointer is valid.
            check(mpi, unsafe { (mpi.comm_dup)(mpi.comm_world, &mut world.comm) }, "MPI_Comm_dup")?;
            // SAFETY: `world.comm` is a valid communicator.
            check(
                mpi,
                unsafe { (mpi.comm_set_errhandler)(world.comm, mpi.errors_return) },
                "MPI_Comm_set_errhandler",
            )?;
            (world.rank, world.size) = rank_and_size(mpi, world.comm)?;
            if world.size != launched {
                // An MPI library that did not recognise its launcher starts each process alone.
                return Err(Error::Mpi(format!(
                    "the launcher started {launched} processes, but MPI's world holds {}: was this \
                     velox started by Open MPI's mpirun?",
                    world.size
                )));
            }
            let mut node = mpi.comm_null;
            // SAFETY: valid communicator and constants; the out-pointer is valid.
            check(
                mpi,
                unsafe {
                    (mpi.comm_split_type)(
                        world.comm,
                        mpi::COMM_TYPE_SHARED,
                        world.rank as c_int,
                        mpi.info_null,
                        &mut node,
                    )
                },
                "MPI_Comm_split_type",
            )?;
            let local = rank_and_size(mpi, node);
            // SAFETY: `node` was created above and is used no more.
            let freed = check(mpi, unsafe { (mpi.comm_free)(&mut node) }, "MPI_Comm_free");
            (world.local_rank, world.local_size) = local?;
            freed?;
            let world = Rc::new(world);
            LIVE.with(|live| *live.borrow_mut() = Rc::downgrade(&world));
            Ok(world)
        }

        pub fn all_reduce_sum(&self, t: &Tensor, bucket_len: usize) -> Result<()> {
            let n = t.numel();
            // Every rank must exchange the same slices: agree on the length and the bucket first.
            let told = self.all_gather_u64s(&[n as u64, bucket_len as u64, t.view_alignment() as u64])?;
            let told: Vec<[u64; 3]> = told.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let bucket = agree_on_bucket(&told)?;
            if self.size == 1 || n == 0 {
                return Ok(());
            }
            let flat = t.reshape(&[n])?;
            let bucket = bucket.min(n);
            let ranks = self.size;
            let most = bucket.div_ceil(ranks);
            let mut received = vec![0f32; most * ranks];
            let mut summed = vec![0f32; most];
            for start in (0..n).step_by(bucket) {
                let len = bucket.min(n - start);
                let part = flat.view(start, &[len])?;
                // Rank j sums elements [j * slice, (j + 1) * slice) of the bucket; zeros pad the
                // last slice.
                let slice = len.div_ceil(ranks);
                let mut host = part.read::<f32>()?;
                host.resize(slice * ranks, 0.0);
                self.all_to_all_f32(&host, &mut received[..slice * ranks], slice)?;
                sum_in_rank_order(&received[..slice * ranks], ranks, &mut summed[..slice]);
                self.all_gather_f32(&summed[..slice], &mut host)?;
                part.write(&host[..len])?;
            }
            Ok(())
        }

        fn all_to_all_f32(&self, send: &[f32], recv: &mut [f32], each: usize) -> Result<()> {
            let n = count(each, "MPI_Alltoall")?;
            // SAFETY: both buffers hold `each * size` f32; the communicator is valid.
            check(
                self.mpi,
                unsafe {
                    (self.mpi.alltoall)(
                        send.as_ptr().cast::<c_void>(),
                        n,
                        self.mpi.float,
                        recv.as_mut_ptr().cast::<c_void>(),
                        n,
                        self.mpi.float,
                        self.comm,
                    )
                },
                "MPI_Alltoall",
            )
        }

        /// `MPI_Allgather`: every rank's `send` into `recv` (`send.len() * size` long), in rank
        /// order. `datatype` must be the MPI type of `T`.
        ///
        /// SAFETY (of the callers): `datatype` describes `T`.
        unsafe fn all_gather<T: Copy>(&self, send: &[T], recv: &mut [T], datatype: Handle) -> Result<()> {
            if recv.len() != send.len() * self.size {
                return Err(Error::Invalid(format!(
                    "MPI_Allgather: {} values received for {} sent by each of {} ranks",
                    recv.len(),
                    send.len(),
                    self.size
                )));
            }
            let n = count(send.len(), "MPI_Allgather")?;
            // SAFETY: `recv` holds `send.len()` values of `datatype` per rank; the communicator is
            // valid.
            check(
                self.mpi,
                unsafe {
                    (self.mpi.allgather)(
                        send.as_ptr().cast::<c_void>(),
                        n,
                        datatype,
                        recv.as_mut_ptr().cast::<c_void>(),
                        n,
                        datatype,
                        self.comm,
                    )
                },
                "MPI_Allgather",
            )
        }

        fn all_gather_f32(&self, send: &[f32], recv: &mut [f32]) -> Result<()> {
            // SAFETY: MPI_FLOAT is f32.
            unsafe { self.all_gather(send, recv, self.mpi.float) }
        }

        pub fn all_gather_f64(&self, x: f64) -> Result<Vec<f64>> {
            let mut all = vec![0f64; self.size];
            // SAFETY: MPI_DOUBLE is f64.
            unsafe { self.all_gather(&[x], &mut all, self.mpi.double) }?;
            Ok(all)
        }

        fn all_gather_u64s(&self, x: &[u64]) -> Result<Vec<u64>> {
            let mut all = vec![0u64; x.len() * self.size];
            // SAFETY: MPI_UINT64_T is u64.
            unsafe { self.all_gather(x, &mut all, self.mpi.uint64) }?;
            Ok(all)
        }

        pub fn broadcast_bytes(&self, root: usize, data: &mut Vec<u8>) -> Result<()> {
            // The length first, little-endian whatever the machines.
            let mut len = (data.len() as u64).to_le_bytes();
            self.broadcast_piece(&mut len, root)?;
            let len = u64::from_le_bytes(len);
            let len = usize::try_from(len)
                .map_err(|_| Error::Mpi(format!("a broadcast of {len} bytes does not fit in memory")))?;
            if self.rank != root {
                data.clear();
                data.resize(len, 0);
            }
            for piece in data.chunks_mut(BROADCAST_PIECE) {
                self.broadcast_piece(piece, root)?;
            }
            Ok(())
        }

        fn broadcast_piece(&self, piece: &mut [u8], root: usize) -> Result<()> {
            let n = count(piece.len(), "MPI_Bcast")?;
            // SAFETY: `piece` holds `n` bytes; root < size was checked by `Comm::broadcast_bytes`.
            check(
                self.mpi,
                unsafe {
                    (self.mpi.bcast)(piece.as_mut_ptr().cast(), n, self.mpi.uint8, root as c_int, self.comm)
                },
                "MPI_Bcast",
            )
        }

        pub fn barrier(&self) -> Result<()> {
            // SAFETY: the communicator is valid.
            check(self.mpi, unsafe { (self.mpi.barrier)(self.comm) }, "MPI_Barrier")
        }

        pub fn abort(&self, code: i32) -> ! {
            // SAFETY: MPI is initialised; MPI_Abort does not return when it succeeds.
            unsafe { (self.mpi.abort)(self.mpi.comm_world, code) };
            std::process::abort()
        }
    }

    fn rank_and_size(mpi: &Mpi, comm: Handle) -> Result<(usize, usize)> {
        let (mut rank, mut size): (c_int, c_int) = (0, 0);
        // SAFETY: a valid communicator and out-pointers.
        check(mpi, unsafe { (mpi.comm_rank)(comm, &mut rank) }, "MPI_Comm_rank")?;
        // SAFETY: as above.
        check(mpi, unsafe { (mpi.comm_size)(comm, &mut size) }, "MPI_Comm_size")?;
        Ok((rank as usize, size as usize))
    }

    impl Drop for World {
        fn drop(&mut self) {
            if std::thread::panicking() {
                // Other ranks may be waiting for this one in a collective, and finalising waits
                // for every rank: end the whole run instead of hanging it.
                eprintln!(
                    "velox: rank {} of {} panicked; ending every rank of the run",
                    self.rank, self.size
                );
                self.abort(1);
            }
            // SAFETY: no Comm uses the communicator any more (this is the last reference), and
            // MPI is finalised once, here.
            unsafe {
                if self.comm != self.mpi.comm_null {
                    (self.mpi.comm_free)(&mut self.comm);
                }
                (self.mpi.finalize)();
            }
        }
    }
}

impl super::collective::Collective for Comm {
    fn rank(&self) -> usize {
        Comm::rank(self)
    }

    fn size(&self) -> usize {
        Comm::size(self)
    }

    fn all_reduce_sum(&self, tensor: &Tensor) -> Result<()> {
        Comm::all_reduce_sum(self, tensor)
    }

    fn all_gather_f64(&self, value: f64) -> Result<Vec<f64>> {
        Comm::all_gather_f64(self, value)
    }

    fn broadcast_bytes(&self, root: usize, bytes: &mut Vec<u8>) -> Result<()> {
        Comm::broadcast_bytes(self, root, bytes)
    }

    fn barrier(&self) -> Result<()> {
        Comm::barrier(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env<'a>(vars: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |name| vars.iter().find(|(n, _)| *n == name).map(|(_, v)| v.to_string())
    }

    #[test]
    fn the_launch_is_read_from_the_launchers_variables() {
        assert_eq!(launch(env(&[])).unwrap(), Launch::Alone);
        assert_eq!(launch(env(&[("OMPI_COMM_WORLD_SIZE", "4")])).unwrap(), Launch::Mpi { size: 4 });
        assert_eq!(launch(env(&[("PMI_SIZE", " 2 ")])).unwrap(), Launch::Mpi { size: 2 });
        for bad in ["", "two", "0", "-1"] {
            let e = launch(env(&[("OMPI_COMM_WORLD_SIZE", bad)])).unwrap_err().to_string();
            assert!(e.contains("OMPI_COMM_WORLD_SIZE") && e.contains("not a number of processes"), "{e}");
        }
    }

    #[test]
    fn a_single_rank_is_rank_zero_of_one_and_its_collectives_are_the_identity() {
        let comm = Comm::single();
        assert_eq!((comm.rank(), comm.size(), comm.local_rank(), comm.local_size()), (0, 1, 0, 1));
        assert!(comm.is_root());
        assert_eq!(comm.all_gather_f64(2.5).unwrap(), [2.5]);
        let mut data = vec![1, 2, 3];
        comm.broadcast_bytes(0, &mut data).unwrap();
        assert_eq!(data, [1, 2, 3]);
        let e = comm.broadcast_bytes(1, &mut data).unwrap_err().to_string();
        assert!(e.contains("rank 1") && e.contains("1 rank(s)"), "{e}");
        comm.barrier().unwrap();
    }

    #[test]
    fn bucket_lengths_out_of_range_are_refused() {
        let mut comm = Comm::single();
        assert!(comm.set_bucket_len(0).is_err());
        assert!(comm.set_bucket_len(MAX_BUCKET_LEN + 1).is_err());
        comm.set_bucket_len(300).unwrap();
        assert_eq!(comm.bucket_len(), 300);
    }

    #[test]
    fn ranks_agree_on_one_bucket_that_every_device_can_view() {
        assert_eq!(agree_on_bucket(&[[1000, 256, 4], [1000, 256, 4]]).unwrap(), 256);
        // The largest bucket asked for, rounded up to every rank's alignment.
        assert_eq!(agree_on_bucket(&[[1000, 1000, 4], [1000, 5, 64]]).unwrap(), 1024);
        assert_eq!(agree_on_bucket(&[[7, 5, 4], [7, 5, 4]]).unwrap(), 8);
        assert_eq!(agree_on_bucket(&[[0, 1 << 20, 4]]).unwrap(), 1 << 20);
        let e = agree_on_bucket(&[[10, 256, 4], [12, 256, 4]]).unwrap_err().to_string();
        assert!(e.contains("rank 0: 10, rank 1: 12"), "{e}");
    }

    #[test]
    fn sums_over_ranks_add_in_rank_order() {
        // In f32, (1e8 - 1e8) + 1 = 1 but 1e8 + (-1e8 + 1) = 0: the order shows in the result.
        let slices = [1e8f32, 2.0, -1e8, 3.0, 1.0, 4.0];
        let mut out = [0f32; 2];
        sum_in_rank_order(&slices, 3, &mut out);
        assert_eq!(out, [1.0, 9.0]);
        let mut one = [0f32; 2];
        sum_in_rank_order(&slices[..2], 1, &mut one);
        assert_eq!(one, [1e8, 2.0]);
    }
}
