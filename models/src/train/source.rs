//! Where a run's samples come from: a [`SampleSource`] names its samples and loads any of them
//! by index, in two halves: [`SampleSource::read`] (files to host memory) runs on a background
//! thread ahead of the steps that need it ([`prefetch`]), [`SampleSource::prepare`] (host to
//! device) on the training thread. The data crate implements it for a folder of scenes; the
//! models crate cannot read those itself.
//!
//! Tests: `tests/training/trainer.rs` and `tests/data/tokens.rs`.

use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::Scope;

use velox_engine::{Error, Result};

/// A dataset the trainer can draw samples from, by index (0 to `len() - 1`).
pub trait SampleSource: Sync {
    /// A sample read into host memory, as the background thread hands it over.
    type Raw: Send;
    /// A sample as the model trains on it.
    type Sample;

    /// Samples in the dataset.
    fn len(&self) -> usize;

    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The sample's name (a scene's folder name): what the log and the checkpoint record.
    fn name(&self, index: usize) -> String;

    /// Where the sample lives (a scene's folder), for reports; its name by default.
    fn location(&self, index: usize) -> String {
        self.name(index)
    }

    /// Reads a sample into host memory (called on the prefetch thread); the error names it.
    fn read(&self, index: usize) -> Result<Self::Raw>;

    /// Makes a read sample ready for the model (uploads it; called on the training thread).
    fn prepare(&self, raw: Self::Raw) -> Result<Self::Sample>;

    /// Reads and prepares a sample on the calling thread.
    fn load(&self, index: usize) -> Result<Self::Sample> {
        self.prepare(self.read(index)?)
    }

    /// Every sample's name, in index order.
    fn names(&self) -> Vec<String> {
        (0..self.len()).map(|i| self.name(i)).collect()
    }
}

/// Reads the samples `indices` yields, in that order, on a thread of `scope`, keeping at most
/// `depth` read ahead of the receiver. A sample that fails to read arrives as its error, and
/// the ones after it still come. Dropping the receiver stops the thread after the sample it is
/// reading.
pub fn prefetch<'scope, S: SampleSource>(
    scope: &'scope Scope<'scope, '_>,
    source: &'scope S,
    indices: impl Iterator<Item = usize> + Send + 'scope,
    depth: usize,
) -> Result<Receiver<Result<S::Raw>>> {
    let (tx, rx) = sync_channel(depth.max(1));
    std::thread::Builder::new()
        .name("velox-prefetch".into())
        .spawn_scoped(scope, move || {
            for index in indices {
                if tx.send(source.read(index)).is_err() {
                    return; // the receiver is gone: the run ended
                }
            }
        })
        .map_err(|e| Error::Io(format!("cannot start the sample-reading thread: {e}")))?;
    Ok(rx)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Numbers as samples; index 3 cannot be read.
    struct Numbers;

    impl SampleSource for Numbers {
        type Raw = usize;
        type Sample = String;
        fn len(&self) -> usize {
            5
        }
        fn name(&self, index: usize) -> String {
            format!("n{index}")
        }
        fn read(&self, index: usize) -> Result<usize> {
            if index == 3 {
                return Err(Error::Invalid("sample n3 is unreadable".into()));
            }
            Ok(index * 10)
        }
        fn prepare(&self, raw: usize) -> Result<String> {
            Ok(raw.to_string())
        }
    }

    #[test]
    fn prefetch_reads_in_order_passes_errors_on_and_stops_with_its_receiver() {
        std::thread::scope(|scope| {
            let rx = prefetch(scope, &Numbers, [4, 0, 3, 1].into_iter(), 1).unwrap();
            let got: Vec<String> =
                rx.iter().map(|r| r.map_or_else(|e| e.to_string(), |v| v.to_string())).collect();
            assert_eq!(got[..2], ["40", "0"]);
            assert!(got[2].contains("sample n3 is unreadable"), "{}", got[2]);
            assert_eq!(got[3], "10");
            // An endless sequence ends when the receiver is dropped (the scope joins the thread).
            let rx = prefetch(scope, &Numbers, (0..5).cycle().filter(|&i| i != 3), 2).unwrap();
            assert_eq!(rx.recv().unwrap().unwrap(), 0);
            drop(rx);
        });
        assert_eq!(Numbers.names(), ["n0", "n1", "n2", "n3", "n4"]);
        assert_eq!(Numbers.load(2).unwrap(), "20");
    }
}
