//! The library trainer over several processes, played by threads that share the device and
//! sum through memory: a run's samples do not depend on how its global batch is split, so two
//! processes of one micro-batch each train as one process accumulating two; and a stop asked
//! for in one process stops them all at the same step.

use crate::common;
use common::*;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Barrier, Mutex};

use velox::data::format::write_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::Result;
use velox::models::config::AutoencoderConfig;
use velox::models::run::RunRequest;
use velox::models::train::collective::{Collective, SingleProcess};
use velox::models::train::source::SampleSource;
use velox::models::train::trainer::{train, Begin, Outcome, Quiet, Stop, TrainOptions};
use velox::models::velox::autoencoder::{Autoencoder, TrainScene};
use velox::tasks::training::HostScene;

/// What the threads of a [`Threads`] group exchange.
struct Shared {
    barrier: Barrier,
    floats: Mutex<Vec<Vec<f32>>>,
    values: Mutex<Vec<f64>>,
    bytes: Mutex<Vec<u8>>,
}

/// One thread's place in a group that plays the processes of a run.
struct Threads {
    rank: usize,
    size: usize,
    shared: Arc<Shared>,
}

fn group(size: usize) -> Vec<Threads> {
    let shared = Arc::new(Shared {
        barrier: Barrier::new(size),
        floats: Mutex::new(vec![Vec::new(); size]),
        values: Mutex::new(vec![0.0; size]),
        bytes: Mutex::new(Vec::new()),
    });
    (0..size).map(|rank| Threads { rank, size, shared: shared.clone() }).collect()
}

impl Collective for Threads {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.size
    }

    fn all_reduce_sum(&self, tensor: &Tensor) -> Result<()> {
        self.shared.floats.lock().unwrap()[self.rank] = tensor.read()?;
        self.shared.barrier.wait();
        let sum = {
            let all = self.shared.floats.lock().unwrap();
            let mut sum = all[0].clone();
            for other in &all[1..] {
                sum.iter_mut().zip(other).for_each(|(s, o)| *s += o);
            }
            sum
        };
        self.shared.barrier.wait();
        tensor.write(&sum)
    }

    fn all_gather_f64(&self, value: f64) -> Result<Vec<f64>> {
        self.shared.values.lock().unwrap()[self.rank] = value;
        self.shared.barrier.wait();
        let all = self.shared.values.lock().unwrap().clone();
        self.shared.barrier.wait();
        Ok(all)
    }

    fn broadcast_bytes(&self, root: usize, bytes: &mut Vec<u8>) -> Result<()> {
        if self.rank == root {
            *self.shared.bytes.lock().unwrap() = bytes.clone();
        }
        self.shared.barrier.wait();
        *bytes = self.shared.bytes.lock().unwrap().clone();
        self.shared.barrier.wait();
        Ok(())
    }

    fn barrier(&self) -> Result<()> {
        self.shared.barrier.wait();
        Ok(())
    }
}

/// Scenes held in host memory, uploaded when prepared.
pub(crate) struct Memory {
    pub gpu: Gpu,
    pub scenes: Vec<HostScene>,
}

impl SampleSource for Memory {
    type Raw = usize;
    type Sample = TrainScene;

    fn len(&self) -> usize {
        self.scenes.len()
    }

    fn name(&self, index: usize) -> String {
        format!("memory_{index}")
    }

    fn read(&self, index: usize) -> Result<usize> {
        Ok(index)
    }

    fn prepare(&self, index: usize) -> Result<TrainScene> {
        let s = &self.scenes[index];
        TrainScene::new(&self.gpu, s.cloud.clone(), s.cameras.clone(), s.images.clone())
    }
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-trainer-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Three small procedural scenes in memory.
fn scenes(gpu: &Gpu, dir: &Path) -> Memory {
    let opts = SynthOptions { res: 24, points: 1500, supersample: 1, tracks: 8, ..Default::default() };
    let scenes = (0..3)
        .map(|seed| {
            let (_, mesh) = procedural::scene(seed, None).unwrap();
            let at = dir.join(format!("scene_{seed}"));
            write_scene(gpu, &mesh, "test", None, seed, &opts, &at, &mut |_| {}).unwrap();
            HostScene::new(&read_scene(&at, true).unwrap()).unwrap()
        })
        .collect();
    Memory { gpu: gpu.clone(), scenes }
}

fn options(out: &Path, accumulate: u64) -> TrainOptions {
    TrainOptions {
        out: out.to_path_buf(),
        begin: Begin::New,
        request: RunRequest {
            seed: Some(5),
            steps: Some(3),
            steps_per_scene: Some(1),
            accumulate: Some(accumulate),
            ..Default::default()
        },
        checkpoint_every: 100,
        plot_every: 100,
        stop_at: None,
        prefetch: 1,
        overlap: None,
    }
}

/// Trains a tiny autoencoder on `memory` as rank `c.rank()` of its group.
fn run<C: Collective>(memory: &Memory, options: &TrainOptions, c: &C, stop: &dyn Fn() -> bool) -> Outcome {
    let mut model = Autoencoder::new(&memory.gpu, &AutoencoderConfig::tiny(), 5).unwrap();
    train(&mut model, memory, options, c, &mut Quiet, stop).unwrap()
}

fn log(out: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(out.join("log.jsonl")).unwrap();
    text.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn values(path: &Path) -> Vec<f32> {
    let (_, tensors) = velox::models::checkpoint::read_tensors(path).unwrap();
    tensors.into_values().flatten().collect()
}

#[test]
fn two_processes_of_one_micro_batch_train_as_one_process_accumulating_two() {
    let gpu = gpu();
    let dir = temp_dir("split");
    let memory = scenes(&gpu, &dir);
    let one = dir.join("one");
    let single = run(&memory, &options(&one, 2), &SingleProcess, &|| false);
    let two = dir.join("two");
    let outcomes: Vec<Outcome> = std::thread::scope(|s| {
        let (memory, two) = (&memory, &two);
        let runs: Vec<_> = group(2)
            .into_iter()
            .map(|c| s.spawn(move || run(memory, &options(two, 1), &c, &|| false)))
            .collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    });
    for o in &outcomes {
        assert_eq!((o.settings.global_batch, o.settings.accumulate, o.last.step), (2, 1, 3));
        assert_eq!(o.last.losses, outcomes[0].last.losses, "every process reports the batch's losses");
    }
    assert_eq!((single.settings.global_batch, single.settings.accumulate), (2, 2));
    // The same samples in the same slots, and the same losses before the first update.
    let (a, b) = (log(&one), log(&two));
    assert_eq!(a.len(), 3);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x["samples"], y["samples"], "step {}", x["step"]);
    }
    assert_eq!(a[0]["loss"], b[0]["loss"]);
    // The autoencoder adds each parameter's gradient once per micro-batch, so today the two sum
    // the same numbers in the same order and agree bit for bit; a model whose backward adds a
    // parameter's gradient in several parts would sum them in another order (each process's,
    // then across processes), hence a bound instead of equality.
    let (x, y) = (values(&one.join("checkpoint.safetensors")), values(&two.join("checkpoint.safetensors")));
    let e = nmse(&x, &f64s(&y));
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("one process accumulating two against two processes, 3 steps: nmse {e:.3e}");
    }
    assert!(e < 1e-10, "nmse {e:.3e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_stop_asked_in_one_process_stops_every_process_at_the_same_step() {
    let gpu = gpu();
    let dir = temp_dir("stop");
    let memory = scenes(&gpu, &dir);
    let out = dir.join("run");
    let outcomes: Vec<Outcome> = std::thread::scope(|s| {
        let runs: Vec<_> = group(2)
            .into_iter()
            .map(|c| {
                let (memory, out) = (&memory, &out);
                s.spawn(move || {
                    let asked = c.rank == 1;
                    run(memory, &options(out, 1), &c, &move || asked)
                })
            })
            .collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    });
    for o in &outcomes {
        assert_eq!((o.stopped, o.last.step), (Some(Stop::Asked), 1));
    }
    assert_eq!(velox::models::checkpoint::peek(&out.join("checkpoint.safetensors")).unwrap().step, 1);
    assert_eq!(log(&out).len(), 1);
    let _ = std::fs::remove_dir_all(&dir);
}
