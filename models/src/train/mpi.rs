//! Open MPI's library, opened when a run is started by an MPI launcher: every build of velox
//! can train on several processes, and none needs MPI to build, to run alone, or to test.
//!
//! The calls are the C ABI of Open MPI 3 to 5 (`libmpi.so.40`, which Debian's `openmpi-bin`
//! brings): its handles (`MPI_COMM_WORLD`, `MPI_FLOAT`, ...) are the addresses of the library's
//! predefined objects (`&ompi_mpi_comm_world`, ...), and its enumerations are fixed by its
//! `mpi.h` (read from Open MPI 4.1.4's: `MPI_THREAD_FUNNELED` 1, `MPI_COMM_TYPE_SHARED` 0,
//! `MPI_MAX_ERROR_STRING` 256). Other MPI libraries (MPICH's integer handles) have another ABI,
//! and a library without Open MPI's world communicator is refused by name.
//!
//! The library is opened once per process with `RTLD_GLOBAL` (Open MPI's components, which it
//! opens itself, resolve their symbols in it) and never closed: Open MPI may run code at exit.
//! `VELOX_MPI_LIBRARY` names another file to open.

use std::ffi::{c_char, c_int, c_void};
use std::sync::OnceLock;

use libloading::os::unix::{Library, RTLD_GLOBAL, RTLD_NOW};
use velox_engine::{Error, Result};

/// An Open MPI handle: the address of one of the library's objects.
pub(super) type Handle = *mut c_void;

pub(super) const SUCCESS: c_int = 0;
pub(super) const THREAD_FUNNELED: c_int = 1;
pub(super) const COMM_TYPE_SHARED: c_int = 0;
pub(super) const MAX_ERROR_STRING: usize = 256;

/// The files tried in turn when `VELOX_MPI_LIBRARY` is not set.
const LIBRARIES: [&str; 2] = ["libmpi.so.40", "libmpi.so"];

type Collective =
    unsafe extern "C" fn(*const c_void, c_int, Handle, *mut c_void, c_int, Handle, Handle) -> c_int;

/// The MPI calls the trainer makes, and the handles they take.
pub(super) struct Mpi {
    pub comm_world: Handle,
    pub comm_null: Handle,
    pub errors_return: Handle,
    pub info_null: Handle,
    pub float: Handle,
    pub double: Handle,
    pub uint64: Handle,
    pub uint8: Handle,
    pub initialized: unsafe extern "C" fn(*mut c_int) -> c_int,
    pub init_thread: unsafe extern "C" fn(*mut c_int, *mut *mut *mut c_char, c_int, *mut c_int) -> c_int,
    pub finalize: unsafe extern "C" fn() -> c_int,
    pub abort: unsafe extern "C" fn(Handle, c_int) -> c_int,
    pub error_string: unsafe extern "C" fn(c_int, *mut c_char, *mut c_int) -> c_int,
    pub comm_dup: unsafe extern "C" fn(Handle, *mut Handle) -> c_int,
    pub comm_free: unsafe extern "C" fn(*mut Handle) -> c_int,
    pub comm_rank: unsafe extern "C" fn(Handle, *mut c_int) -> c_int,
    pub comm_size: unsafe extern "C" fn(Handle, *mut c_int) -> c_int,
    pub comm_set_errhandler: unsafe extern "C" fn(Handle, Handle) -> c_int,
    pub comm_split_type: unsafe extern "C" fn(Handle, c_int, c_int, Handle, *mut Handle) -> c_int,
    pub alltoall: Collective,
    pub allgather: Collective,
    pub bcast: unsafe extern "C" fn(*mut c_void, c_int, Handle, c_int, Handle) -> c_int,
    pub barrier: unsafe extern "C" fn(Handle) -> c_int,
    /// Kept open for the life of the process.
    _library: Library,
}

// SAFETY: the handles are constant addresses in a library that stays loaded, and the functions
// are plain C functions; which thread may call MPI is the callers' business (see `World`).
unsafe impl Send for Mpi {}
// SAFETY: as above; nothing in `Mpi` changes after it is made.
unsafe impl Sync for Mpi {}

/// The process's MPI library, opened on the first call.
pub(super) fn library() -> Result<&'static Mpi> {
    static OPENED: OnceLock<std::result::Result<Mpi, String>> = OnceLock::new();
    OPENED
        .get_or_init(|| {
            let named = std::env::var("VELOX_MPI_LIBRARY").ok().filter(|s| !s.trim().is_empty());
            match named {
                Some(file) => open(&[file.as_str()]),
                None => open(&LIBRARIES),
            }
            .map_err(|e| match e {
                Error::Mpi(message) => message,
                other => other.to_string(),
            })
        })
        .as_ref()
        .map_err(|e| Error::Mpi(e.clone()))
}

/// Opens the first of `files` that loads and resolves every call.
pub(super) fn open(files: &[&str]) -> Result<Mpi> {
    let mut tried = Vec::new();
    for file in files {
        // SAFETY: opening a shared library runs its initialisers; Open MPI's do no more than
        // set up its own state.
        match unsafe { Library::open(Some(file), RTLD_NOW | RTLD_GLOBAL) } {
            Ok(library) => return resolve(library, file),
            Err(e) => tried.push(format!("{file}: {e}")),
        }
    }
    Err(Error::Mpi(format!(
        "started by an MPI launcher, but Open MPI's library does not open ({}): install Open MPI \
         (Debian: apt-get install openmpi-bin) or name the library in VELOX_MPI_LIBRARY",
        tried.join("; ")
    )))
}

fn resolve(library: Library, file: &str) -> Result<Mpi> {
    /// The address of a symbol, or an error naming it.
    fn address(library: &Library, file: &str, name: &str) -> Result<*mut c_void> {
        let symbol = format!("{name}\0");
        // SAFETY: the symbol is only taken as an address here; its type is given by the caller.
        let found = unsafe { library.get::<*mut c_void>(symbol.as_bytes()) };
        match found.ok().map(|s| s.into_raw()).filter(|a| !a.is_null()) {
            Some(a) => Ok(a),
            _ if name.starts_with("ompi_") => Err(Error::Mpi(format!(
                "{file} is not Open MPI's library (it has no {name}): velox speaks Open MPI's ABI \
                 (libmpi.so.40 from Open MPI 3 to 5); name that library in VELOX_MPI_LIBRARY"
            ))),
            _ => Err(Error::Mpi(format!("{file} has no {name}: is it an MPI library?"))),
        }
    }
    let handle = |name: &str| address(&library, file, name);
    let comm_world = handle("ompi_mpi_comm_world")?;
    macro_rules! function {
        ($name:literal) => {{
            // SAFETY: the symbol is MPI's function of that name, whose C signature (Open MPI's
            // mpi.h) is the field's type; the library outlives the copy (it is kept beside it).
            let symbol = unsafe { library.get(concat!($name, "\0").as_bytes()) };
            *symbol.map_err(|_| Error::Mpi(format!("{file} has no {}: is it an MPI library?", $name)))?
        }};
    }
    Ok(Mpi {
        comm_world,
        comm_null: handle("ompi_mpi_comm_null")?,
        errors_return: handle("ompi_mpi_errors_return")?,
        info_null: handle("ompi_mpi_info_null")?,
        float: handle("ompi_mpi_float")?,
        double: handle("ompi_mpi_double")?,
        uint64: handle("ompi_mpi_uint64_t")?,
        uint8: handle("ompi_mpi_uint8_t")?,
        initialized: function!("MPI_Initialized"),
        init_thread: function!("MPI_Init_thread"),
        finalize: function!("MPI_Finalize"),
        abort: function!("MPI_Abort"),
        error_string: function!("MPI_Error_string"),
        comm_dup: function!("MPI_Comm_dup"),
        comm_free: function!("MPI_Comm_free"),
        comm_rank: function!("MPI_Comm_rank"),
        comm_size: function!("MPI_Comm_size"),
        comm_set_errhandler: function!("MPI_Comm_set_errhandler"),
        comm_split_type: function!("MPI_Comm_split_type"),
        alltoall: function!("MPI_Alltoall"),
        allgather: function!("MPI_Allgather"),
        bcast: function!("MPI_Bcast"),
        barrier: function!("MPI_Barrier"),
        _library: library,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_library_is_an_error_naming_it_and_the_package() {
        let e = open(&["/nonexistent/libmpi.so.40"]).err().expect("refused").to_string();
        assert!(e.contains("/nonexistent/libmpi.so.40") && e.contains("openmpi-bin"), "{e}");
        assert!(e.contains("VELOX_MPI_LIBRARY"), "{e}");
    }

    #[test]
    fn a_library_that_is_not_open_mpi_is_refused_by_name() {
        // The C library is on every Linux machine and is no MPI.
        let e = open(&["libc.so.6"]).err().expect("refused").to_string();
        assert!(
            e.contains("libc.so.6 is not Open MPI's library") && e.contains("ompi_mpi_comm_world"),
            "{e}"
        );
    }
}
