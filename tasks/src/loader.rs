//! Reads scenes in a background thread while training runs.
//!
//! A [`Loader`] owns one thread that reads scenes in the order of [`velox_models::train::order`] (each pass
//! shuffled from the seed and the pass's number, or in name order), from any position of that
//! sequence, into a bounded queue of `prefetch` scenes, so reading
//! and PNG decoding overlap the caller's GPU work and memory stays bounded. A scene that fails
//! to read comes out as an error naming its folder, and the scenes after it still come.
//! Dropping the loader stops the thread after the scene it is reading.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::JoinHandle;

use velox_data::format::{list_scenes, read_scene, Scene};
use velox_data::DataResult;
use velox_models::train::order::epoch_order;

#[derive(Clone, Debug)]
pub struct LoaderOptions {
    /// Passes over the dataset (0: forever).
    pub epochs: usize,
    /// Shuffle each epoch with this seed and the epoch's number; `None` keeps name order.
    pub shuffle: Option<u64>,
    /// The position in the sequence of epochs to start from (0: the first scene of the first
    /// epoch; see [`velox_models::train::order`]): a resumed run starts where it stopped.
    pub start: u64,
    /// Scenes read ahead.
    pub prefetch: usize,
    /// Also decode the supervision images and the video.
    pub images: bool,
}

impl Default for LoaderOptions {
    fn default() -> LoaderOptions {
        LoaderOptions { epochs: 1, shuffle: None, start: 0, prefetch: 2, images: true }
    }
}

pub struct Loader {
    rx: Option<Receiver<DataResult<Scene>>>,
    thread: Option<JoinHandle<()>>,
    /// Scenes in the dataset.
    pub len: usize,
    /// The dataset's scene folders, in name order (the indices of [`velox_models::train::order`]).
    pub scenes: Vec<PathBuf>,
}

impl Loader {
    /// Starts reading the scenes under `root`.
    pub fn spawn(root: &Path, opts: LoaderOptions) -> DataResult<Loader> {
        let scenes = list_scenes(root)?;
        let len = scenes.len();
        let (tx, rx) = sync_channel(opts.prefetch.max(1));
        let dirs = scenes.clone();
        let thread = std::thread::Builder::new()
            .name("velox-data-loader".into())
            .spawn(move || {
                let n = dirs.len() as u64;
                let mut position = opts.start;
                while n > 0 && (opts.epochs == 0 || position / n < opts.epochs as u64) {
                    let epoch = position / n;
                    let order = epoch_order(dirs.len(), opts.shuffle, epoch);
                    while position / n == epoch {
                        let dir = &dirs[order[(position % n) as usize]];
                        if tx.send(read_scene(dir, opts.images)).is_err() {
                            return; // the loader was dropped
                        }
                        position += 1;
                    }
                }
            })
            .map_err(|e| velox_data::DataError::Io(format!("starting the loader thread: {e}")))?;
        Ok(Loader { rx: Some(rx), thread: Some(thread), len, scenes })
    }
}

impl Iterator for Loader {
    type Item = DataResult<Scene>;
    fn next(&mut self) -> Option<DataResult<Scene>> {
        self.rx.as_ref()?.recv().ok()
    }
}

impl Drop for Loader {
    fn drop(&mut self) {
        // Closing the channel makes the thread's next send fail, and it returns.
        self.rx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
