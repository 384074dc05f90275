//! Reads scenes in a background thread while training runs.
//!
//! A [`Loader`] owns one thread that reads scenes in the order it is given (shuffled per
//! epoch by a seed, or in name order) into a bounded queue of `prefetch` scenes, so reading
//! and PNG decoding overlap the caller's GPU work and memory stays bounded. A scene that fails
//! to read comes out as an error naming its folder, and the scenes after it still come.
//! Dropping the loader stops the thread after the scene it is reading.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::JoinHandle;

use velox_engine::rng::Rng;

use crate::format::{list_scenes, read_scene, Scene};
use crate::DataResult;

#[derive(Clone, Debug)]
pub struct LoaderOptions {
    /// Passes over the dataset (0: forever).
    pub epochs: usize,
    /// Shuffle each epoch with this seed; `None` keeps name order.
    pub shuffle: Option<u64>,
    /// Scenes read ahead.
    pub prefetch: usize,
    /// Also decode the supervision images and the video.
    pub images: bool,
}

impl Default for LoaderOptions {
    fn default() -> LoaderOptions {
        LoaderOptions { epochs: 1, shuffle: None, prefetch: 2, images: true }
    }
}

pub struct Loader {
    rx: Option<Receiver<DataResult<Scene>>>,
    thread: Option<JoinHandle<()>>,
    /// Scenes in the dataset.
    pub len: usize,
}

impl Loader {
    /// Starts reading the scenes under `root`.
    pub fn spawn(root: &Path, opts: LoaderOptions) -> DataResult<Loader> {
        let scenes = list_scenes(root)?;
        let len = scenes.len();
        let (tx, rx) = sync_channel(opts.prefetch.max(1));
        let thread = std::thread::Builder::new()
            .name("velox-data-loader".into())
            .spawn(move || {
                let mut rng = opts.shuffle.map(Rng::new);
                let mut epoch = 0;
                while !scenes.is_empty() && (opts.epochs == 0 || epoch < opts.epochs) {
                    let mut order: Vec<&PathBuf> = scenes.iter().collect();
                    if let Some(rng) = rng.as_mut() {
                        for i in (1..order.len()).rev() {
                            order.swap(i, rng.below(i as u32 + 1) as usize);
                        }
                    }
                    for dir in order {
                        if tx.send(read_scene(dir, opts.images)).is_err() {
                            return; // the loader was dropped
                        }
                    }
                    epoch += 1;
                }
            })
            .map_err(|e| crate::DataError::Io(format!("starting the loader thread: {e}")))?;
        Ok(Loader { rx: Some(rx), thread: Some(thread), len })
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
