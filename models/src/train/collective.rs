//! What the trainer needs of the processes of a data-parallel run: each process runs its share
//! of a step's micro-batches, the gradients are summed over the processes, and every process
//! then takes the same optimiser step, so all hold the same parameters. A one-process run uses
//! [`SingleProcess`], whose operations have nothing to do; an MPI run implements the trait over
//! its communicator.
//!
//! Tests: `tests/training/trainer.rs` (one process's all-reduce).

use velox_engine::{Error, Result, Tensor};

/// The collective operations of a group of processes, each identified by its rank.
pub trait Collective {
    /// This process's rank, 0 to `size() - 1`.
    fn rank(&self) -> usize;

    /// The number of processes.
    fn size(&self) -> usize;

    /// Whether this process is rank 0, the one that writes the run's files.
    fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Replaces `tensor` (f32) in every process by its sum over the processes, in an order
    /// that does not depend on timing (the same inputs give the same bits).
    fn all_reduce_sum(&self, tensor: &Tensor) -> Result<()>;

    /// Every process's `value`, in rank order.
    fn all_gather_f64(&self, value: f64) -> Result<Vec<f64>>;

    /// Replaces `bytes` in every process by the bytes of process `root`.
    fn broadcast_bytes(&self, root: usize, bytes: &mut Vec<u8>) -> Result<()>;

    /// Returns once every process has called it.
    fn barrier(&self) -> Result<()>;
}

/// A run of one process: the sum over the processes is the process's own.
#[derive(Clone, Copy, Debug, Default)]
pub struct SingleProcess;

impl Collective for SingleProcess {
    fn rank(&self) -> usize {
        0
    }

    fn size(&self) -> usize {
        1
    }

    fn all_reduce_sum(&self, _tensor: &Tensor) -> Result<()> {
        Ok(())
    }

    fn all_gather_f64(&self, value: f64) -> Result<Vec<f64>> {
        Ok(vec![value])
    }

    fn broadcast_bytes(&self, root: usize, _bytes: &mut Vec<u8>) -> Result<()> {
        if root != 0 {
            return Err(Error::Invalid(format!("a broadcast from process {root} in a run of one process")));
        }
        Ok(())
    }

    fn barrier(&self) -> Result<()> {
        Ok(())
    }
}
