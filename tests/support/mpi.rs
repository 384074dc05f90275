//! Whether the two-process tests can run here, shared by `tests/distributed.rs` and
//! `tools/tests/distributed_train.rs` (each includes this file by path).

use std::process::Command;

/// Whether Open MPI's `mpirun` runs on the PATH. Where it is missing the two-process tests say
/// so and pass, unless `VELOX_MPI_TESTS=1` (the test command, tools/test.sh, sets it, having
/// installed Open MPI), where that is a failure.
pub fn mpirun_present() -> bool {
    let found = Command::new("mpirun").arg("--version").output().is_ok_and(|o| o.status.success());
    if !found {
        assert!(
            std::env::var("VELOX_MPI_TESTS").as_deref() != Ok("1"),
            "VELOX_MPI_TESTS=1 but mpirun does not run: install Open MPI (Debian: openmpi-bin)"
        );
        eprintln!("skipped: no mpirun on the PATH (Debian: apt-get install openmpi-bin)");
    }
    found
}
