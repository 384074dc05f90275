//! Training: what a run needs beyond the models' own forward and backward passes.

pub mod distributed;
