//! The collectives of data-parallel training over MPI (`velox_models::train::distributed`), on
//! two processes: `cargo test --release --test distributed` (Open MPI's `openmpi-bin`
//! installed).
//!
//! A test binary without libtest's harness: started by cargo, `main` checks the single-rank
//! `Comm` in this process, then runs this same binary as two ranks under
//! `mpirun -np 2 --timeout`, where `main` finds Open MPI's variables in its environment and runs
//! the rank checks on each rank's device. A rank that fails ends the whole run (the checks panic
//! and the `Comm` aborts every rank), so mpirun's exit status says whether both ranks passed;
//! two more runs check that a rank's error and a rank's panic end the run instead of leaving
//! the other rank waiting in a collective.

use std::io::Read;
use std::process::{Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

use velox::engine::{DType, Gpu, Tensor};
use velox::models::train::distributed::{Comm, DEFAULT_BUCKET_LEN};

/// mpirun ends a run still going after this many seconds (the checks take a few).
const MPIRUN_TIMEOUT_S: u64 = 300;
/// What mpirun prints when its `--timeout` ends a run.
const MPIRUN_TIMED_OUT: &str = "time limit for job execution";

/// A check of the test process: `Err` says what failed.
type Check = fn() -> Result<(), String>;

fn main() -> ExitCode {
    if std::env::var_os("OMPI_COMM_WORLD_SIZE").is_some() {
        return rank_main();
    }
    if !mpirun_present() {
        return ExitCode::SUCCESS;
    }
    let tests: [(&str, Check); 5] = [
        ("single_rank_without_mpirun", single_rank_without_mpirun),
        ("two_ranks_sum_broadcast_and_gather", two_ranks_sum_broadcast_and_gather),
        ("a_rank_error_ends_the_run", || a_failing_rank_ends_the_run("fail-error")),
        ("a_rank_panic_ends_the_run", || a_failing_rank_ends_the_run("fail-panic")),
        ("a_library_that_is_not_open_mpi_is_refused", a_library_that_is_not_open_mpi_is_refused),
    ];
    let mut failed = 0;
    for (name, test) in tests {
        match test() {
            Ok(()) => println!("test {name} ... ok"),
            Err(e) => {
                println!("test {name} ... FAILED\n{e}");
                failed += 1;
            }
        }
    }
    let passed = tests.len() - failed;
    let result = if failed == 0 { "ok" } else { "FAILED" };
    println!("\ntest result: {result}. {passed} passed; {failed} failed");
    if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

// ---------------------------------------------------------------------------------------------
// In the test process.

#[path = "support/mpi.rs"]
mod mpi;
use mpi::mpirun_present;

/// Without mpirun, `Comm::world` is one rank that changes nothing, and starts no MPI.
fn single_rank_without_mpirun() -> Result<(), String> {
    let comm = Comm::world().map_err(|e| e.to_string())?;
    check((comm.rank(), comm.size(), comm.local_rank()) == (0, 1, 0), format!("{comm:?}"))?;
    let gpu = Gpu::new().map_err(|e| e.to_string())?;
    let data: Vec<f32> = (0..1000).map(|i| contribution(0, i)).collect();
    let t = Tensor::from_slice(&gpu, &[1000], &data).map_err(|e| e.to_string())?;
    comm.all_reduce_sum(&t).map_err(|e| e.to_string())?;
    check(same_bits(&t.read::<f32>().map_err(|e| e.to_string())?, &data), "one rank's sum changed the data")?;
    let half = Tensor::empty(&gpu, &[4], DType::F16).map_err(|e| e.to_string())?;
    let e = comm.all_reduce_sum(&half).err().map(|e| e.to_string()).unwrap_or_default();
    check(e.contains("f32"), format!("an f16 tensor: {e:?}"))
}

fn two_ranks_sum_broadcast_and_gather() -> Result<(), String> {
    let run = mpirun(&[], &[], MPIRUN_TIMEOUT_S)?;
    check(run.success, format!("mpirun failed:\n{}", run.output))?;
    for rank in 0..2 {
        let line = format!("rank {rank} of 2: every check passed");
        check(run.output.contains(&line), format!("no line {line:?} in:\n{}", run.output))?;
    }
    Ok(())
}

/// Rank 1 fails while rank 0 waits for it in a barrier: the run must end with a failure, and
/// before mpirun's time limit.
fn a_failing_rank_ends_the_run(mode: &str) -> Result<(), String> {
    let run = mpirun(&[], &[mode], 120)?;
    check(!run.success, format!("mpirun succeeded although rank 1 failed:\n{}", run.output))?;
    check(
        !run.output.contains(MPIRUN_TIMED_OUT),
        format!("the run hung until mpirun's timeout:\n{}", run.output),
    )?;
    check(
        !run.output.contains("passed the barrier"),
        format!("rank 0 passed a barrier without rank 1:\n{}", run.output),
    )?;
    check(
        run.output.contains("rank 1 fails on purpose"),
        format!("rank 1 did not get to fail:\n{}", run.output),
    )
}

/// Each rank opens the MPI library VELOX_MPI_LIBRARY names; one that is not Open MPI's (the C
/// library) stops every rank with an error naming it, before any MPI call.
fn a_library_that_is_not_open_mpi_is_refused() -> Result<(), String> {
    let run = mpirun(&["-x", "VELOX_MPI_LIBRARY=libc.so.6"], &[], 120)?;
    check(!run.success, format!("mpirun succeeded with the C library as MPI:\n{}", run.output))?;
    check(
        run.output.matches("a rank could not start: MPI: libc.so.6 is not Open MPI's library").count() == 2,
        format!("not both ranks said why:\n{}", run.output),
    )
}

struct Run {
    success: bool,
    output: String,
}

/// Runs this binary as two ranks (with mpirun's `options` and the binary's `args`), with
/// mpirun's own time limit and, should mpirun itself hang, a kill 60 s after it.
fn mpirun(options: &[&str], args: &[&str], timeout_s: u64) -> Result<Run, String> {
    let exe = std::env::current_exe().map_err(|e| format!("the test binary's path: {e}"))?;
    let mut child = Command::new("mpirun")
        .args(["--allow-run-as-root", "--oversubscribe", "--timeout", &timeout_s.to_string(), "-np", "2"])
        .args(options)
        .arg(&exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot start mpirun ({e}): install Open MPI (apt-get install openmpi-bin)"))?;
    let readers = [drain(child.stdout.take().expect("piped")), drain(child.stderr.take().expect("piped"))];
    let deadline = Instant::now() + Duration::from_secs(timeout_s + 60);
    let status = loop {
        match child.try_wait().map_err(|e| format!("waiting for mpirun: {e}"))? {
            Some(status) => break Some(status),
            None if Instant::now() > deadline => {
                let _ = child.kill();
                let _ = child.wait();
                break None;
            }
            None => std::thread::sleep(Duration::from_millis(100)),
        }
    };
    let output: String = readers.into_iter().map(|r| r.join().unwrap_or_default()).collect();
    match status {
        Some(status) => Ok(Run { success: status.success(), output }),
        None => Err(format!("mpirun did not end within {} s; killed it:\n{output}", timeout_s + 60)),
    }
}

fn drain(mut pipe: impl Read + Send + 'static) -> std::thread::JoinHandle<String> {
    std::thread::spawn(move || {
        let mut bytes = Vec::new();
        let _ = pipe.read_to_end(&mut bytes);
        String::from_utf8_lossy(&bytes).into_owned()
    })
}

fn check(ok: bool, what: impl Into<String>) -> Result<(), String> {
    if ok {
        Ok(())
    } else {
        Err(what.into())
    }
}

// ---------------------------------------------------------------------------------------------
// In each rank, under mpirun.

fn rank_main() -> ExitCode {
    let comm = match Comm::world() {
        Ok(comm) => comm,
        Err(e) => {
            eprintln!("a rank could not start: {e}");
            return ExitCode::FAILURE;
        }
    };
    match std::env::args().nth(1).as_deref() {
        Some(mode @ ("fail-error" | "fail-panic")) if comm.rank() == 1 => {
            eprintln!("rank 1 fails on purpose ({mode})");
            if mode == "fail-error" {
                comm.abort_all(3);
            }
            panic!("rank 1 fails on purpose");
        }
        Some("fail-error" | "fail-panic") => {
            let waited = comm.barrier();
            println!("rank {} passed the barrier: {waited:?}", comm.rank());
            return ExitCode::SUCCESS;
        }
        _ => {}
    }
    // A failed check panics, and the panic ends every rank (see `Comm`).
    rank_checks(&comm);
    println!("rank {} of {}: every check passed", comm.rank(), comm.size());
    ExitCode::SUCCESS
}

fn rank_checks(comm: &Comm) {
    let rank = comm.rank();
    assert_eq!(comm.size(), 2, "{comm:?}");
    assert!(rank < 2 && comm.is_root() == (rank == 0), "{comm:?}");

    // Both ranks run on this machine: local ranks 0 and 1, as Open MPI numbers them.
    assert_eq!(comm.local_size(), 2, "{comm:?}");
    let ompi_local = std::env::var("OMPI_COMM_WORLD_LOCAL_RANK").ok().and_then(|v| v.parse().ok());
    assert_eq!(Some(comm.local_rank()), ompi_local, "{comm:?}");
    let mut locals = comm.all_gather_f64(comm.local_rank() as f64).unwrap();
    locals.sort_by(f64::total_cmp);
    assert_eq!(locals, [0.0, 1.0]);
    let gpu = Gpu::for_local_rank(comm.local_rank()).unwrap();
    println!("rank {rank}: local rank {} on {}", comm.local_rank(), gpu.caps().name);

    // all_gather_f64: every rank's value in rank order.
    assert_eq!(comm.all_gather_f64(rank as f64 * 1.5 - 0.25).unwrap(), [-0.25, 1.25]);

    // broadcast_bytes: the root's bytes everywhere, whatever the others held, from either root.
    let sent: Vec<u8> = (0..100_003u32).map(|i| (i * 7 + 3) as u8).collect();
    let mut data = if rank == 0 { sent.clone() } else { vec![9; 5] };
    comm.broadcast_bytes(0, &mut data).unwrap();
    assert!(data == sent, "rank {rank}: the broadcast from rank 0 differs");
    let mut data = if rank == 1 { Vec::new() } else { vec![1; 10] };
    comm.broadcast_bytes(1, &mut data).unwrap();
    assert!(data.is_empty(), "rank {rank}: an empty broadcast from rank 1 left {} bytes", data.len());
    let e = comm.broadcast_bytes(2, &mut data).unwrap_err().to_string();
    assert!(e.contains("rank 2") && e.contains("2 rank(s)"), "{e}");

    // all_reduce_sum in small buckets: empty, one element, around one bucket, several buckets
    // with a short last one, a 2-D tensor, and a bucket length the alignment rounds up.
    let mut small = comm.clone();
    small.set_bucket_len(256).unwrap();
    for n in [0, 1, 2, 255, 256, 257, 3 * 256 + 7, 10 * 256] {
        check_sum(&small, &gpu, &[n]);
    }
    check_sum(&small, &gpu, &[7, 111]);
    let mut odd = comm.clone();
    odd.set_bucket_len(5).unwrap();
    check_sum(&odd, &gpu, &[13]);
    // Ranks that ask for different buckets: they agree on one.
    let mut mixed = comm.clone();
    mixed.set_bucket_len(if rank == 0 { 256 } else { 1000 }).unwrap();
    check_sum(&mixed, &gpu, &[3 * 1000 + 1]);
    // The default bucket, and one more element.
    check_sum(comm, &gpu, &[DEFAULT_BUCKET_LEN + 1]);

    // A view: only its elements are summed; the rest of the buffer stays this rank's.
    let whole: Vec<f32> = (0..1000).map(|i| contribution(rank, i)).collect();
    let buffer = Tensor::from_slice(&gpu, &[1000], &whole).unwrap();
    small.all_reduce_sum(&buffer.view(256, &[300]).unwrap()).unwrap();
    let got = buffer.read::<f32>().unwrap();
    for (i, (&g, &mine)) in got.iter().zip(&whole).enumerate() {
        let want = if (256..556).contains(&i) { contribution(0, i) + contribution(1, i) } else { mine };
        assert_eq!(g.to_bits(), want.to_bits(), "rank {rank}: element {i} of the view test");
    }

    // Ranks that disagree on the length get an error naming each length, on every rank.
    let mine = Tensor::from_slice(&gpu, &[10 + 2 * rank], &vec![1f32; 10 + 2 * rank]).unwrap();
    let e = comm.all_reduce_sum(&mine).unwrap_err().to_string();
    assert!(e.contains("rank 0: 10, rank 1: 12"), "{e}");
    // Not f32: refused before any exchange.
    let half = Tensor::empty(&gpu, &[4], DType::F16).unwrap();
    assert!(comm.all_reduce_sum(&half).unwrap_err().to_string().contains("f32"));
    comm.barrier().unwrap();
}

/// Sums a tensor of `shape` holding each rank's contribution, twice, and checks every element
/// against rank 0's value plus rank 1's in f32, bit for bit, and that both ranks agree.
fn check_sum(comm: &Comm, gpu: &Gpu, shape: &[usize]) {
    let n: usize = shape.iter().product();
    let rank = comm.rank();
    let mine: Vec<f32> = (0..n).map(|i| contribution(rank, i)).collect();
    let want: Vec<f32> = (0..n).map(|i| contribution(0, i) + contribution(1, i)).collect();
    let mut first: Option<Vec<f32>> = None;
    for call in 0..2 {
        let t = Tensor::from_slice(gpu, shape, &mine).unwrap();
        comm.all_reduce_sum(&t).unwrap();
        let got = t.read::<f32>().unwrap();
        if let Some(i) = (0..n).find(|&i| got[i].to_bits() != want[i].to_bits()) {
            panic!(
                "rank {rank}: sum of {shape:?} (bucket {}), call {call}: element {i} is {} where {} + {} = {}",
                comm.bucket_len(),
                got[i],
                contribution(0, i),
                contribution(1, i),
                want[i]
            );
        }
        if let Some(first) = &first {
            assert!(same_bits(first, &got), "rank {rank}: two sums of {shape:?} differ");
        }
        first = Some(got);
    }
    // Both ranks hold the same bits (a checksum of them, exact in f64).
    let sum = first.unwrap().iter().fold(0u32, |h, v| h.rotate_left(5) ^ v.to_bits());
    let sums = comm.all_gather_f64(sum as f64).unwrap();
    assert_eq!(sums[0], sums[1], "the ranks' sums of {shape:?} differ");
}

/// Rank `rank`'s value at element `i`: signed, of magnitudes from 2^-20 to 2^20, so that the
/// sums round.
fn contribution(rank: usize, i: usize) -> f32 {
    let mut h =
        (rank as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (i as u64).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h ^= h >> 31;
    h = h.wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^= h >> 29;
    let unit = (h >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0;
    unit * 2f32.powi((h % 41) as i32 - 20)
}

fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}
