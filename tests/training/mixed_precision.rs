//! f16 training (mixed precision): the passes' products read f16 operands and accumulate in
//! f32, the optimiser keeps f32 masters, the loss is scaled dynamically. It follows f32
//! training; a step whose gradients overflow f16 is skipped and run again at half the scale;
//! an f16 run stopped and resumed repeats the uninterrupted run bit for bit. Steps recorded
//! while the step before runs are the same steps, in either precision.

use crate::common;
use crate::trainer::Memory;
use common::*;

use std::path::{Path, PathBuf};

use velox::data::format::write_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::ops::adamw::AdamWConfig;
use velox::engine::{Precision, Result};
use velox::models::checkpoint;
use velox::models::config::AutoencoderConfig;
use velox::models::layers::{Linear, Loss, Param};
use velox::models::params::{Init, LossScale, ParamStore};
use velox::models::run::{RunRequest, RunSettings};
use velox::models::train::collective::SingleProcess;
use velox::models::train::trainer::{train, Begin, Finished, Quiet, StepReport, TrainOptions, Trainer};
use velox::models::train::{Ahead, Finish, Losses, Optimisation, Trainable};
use velox::models::velox::autoencoder::{Autoencoder, TrainScene};
use velox::tasks::training::HostScene;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-mixed-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// One small procedural scene, held on the host.
fn host_scene(gpu: &Gpu, dir: &Path) -> HostScene {
    host_scene_of(gpu, dir, 2)
}

/// The small procedural scene of `seed`, held on the host.
fn host_scene_of(gpu: &Gpu, dir: &Path, seed: u64) -> HostScene {
    let opts = SynthOptions { res: 24, points: 1500, supersample: 1, tracks: 8, ..Default::default() };
    let (_, mesh) = procedural::scene(seed, None).unwrap();
    let at = dir.join(format!("scene-{seed}"));
    write_scene(gpu, &mesh, "test", None, seed, &opts, &at, &mut |_| {}).unwrap();
    HostScene::new(&read_scene(&at, true).unwrap()).unwrap()
}

fn upload(gpu: &Gpu, s: &HostScene) -> TrainScene {
    TrainScene::new(gpu, s.cloud.clone(), s.cameras.clone(), s.images.clone()).unwrap()
}

/// The settings of a one-process run of `steps` steps in `precision` over one sample.
fn settings(precision: Precision, steps: u64) -> RunSettings {
    let request = RunRequest { steps: Some(steps), precision: Some(precision), ..Default::default() };
    RunSettings::new(&request, vec!["sample".into()], 1, 1).unwrap()
}

/// The tiny autoencoder's losses over `steps` steps on one scene in `precision`.
fn losses(gpu: &Gpu, scene: &TrainScene, precision: Precision, steps: u64) -> Vec<f64> {
    let mut model = Autoencoder::new(gpu, &AutoencoderConfig::tiny(), 3).unwrap();
    let mut trainer = Trainer::new(&mut model, &SingleProcess, settings(precision, steps)).unwrap();
    let reports = trainer.repeat_steps(&[scene], 1..steps + 1).unwrap();
    for r in &reports {
        assert_eq!(
            r.loss_scale,
            (precision == Precision::F16).then_some(LossScale::INITIAL),
            "step {}",
            r.step
        );
    }
    reports.iter().map(|r| r.losses.total()).collect()
}

/// Would catch: a host wait added to a training step (each submission is one: a read of a
/// result submitted on its own, an upload waited for, a pass split in two), and a first step
/// whose way of sizing the tile lists changes what it computes.
#[test]
fn a_training_step_is_one_submission_in_either_precision() {
    // This test's device while it runs, so that no other test's submissions are counted.
    let Some(gpu) = counting_gpu() else { return };
    let dir = temp_dir("submits");
    let scene = upload(&gpu, &host_scene(&gpu, &dir));
    for precision in [Precision::F32, Precision::F16] {
        // Each step's submissions, and the parameters after three steps: with the first step's
        // tile lists sized by the bound no count can pass (24-pixel views: 4 tiles), and with
        // that bound refused, so that the first step submits its projections to size them by
        // their counts, as configs with large views do.
        let run = |bound: bool| {
            let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 3).unwrap();
            if !bound {
                model.set_first_step_pairs(0);
            }
            let mut trainer = Trainer::new(&mut model, &SingleProcess, settings(precision, 3)).unwrap();
            let mut submits = Vec::new();
            for step in 1..4 {
                let before = gpu.submits();
                trainer.repeat_steps(&[&scene], step..step + 1).unwrap();
                submits.push(gpu.submits() - before);
            }
            (submits, model.store.flat_params().read::<f32>().unwrap())
        };
        // One a step: forward, rasterisation, backward and the update (the losses, read for
        // the log and the NaN check, and the gradient norm, read for f16's overflow decision,
        // come back with it).
        let (submits, bound) = run(true);
        assert_eq!(submits, [1, 1, 1], "{precision:?}: submissions a step");
        let (submits, counted) = run(false);
        assert_eq!(submits, [2, 1, 1], "{precision:?}: submissions a step, the first sized by its counts");
        assert!(bound == counted, "{precision:?}: the first step's room changed the parameters");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Would catch: a step trained on tile lists that dropped pairs, an update that went ahead
/// when they did, a rerun that draws anew or halves the loss scale, a room that changes bits.
#[test]
fn a_step_that_outgrows_its_tile_lists_is_vetoed_and_run_again() {
    let gpu = gpu();
    let dir = temp_dir("rerun");
    let scene = upload(&gpu, &host_scene(&gpu, &dir));
    for precision in [Precision::F32, Precision::F16] {
        let run = |room: usize| {
            let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 3).unwrap();
            model.set_pair_room(room);
            let initial = model.store.flat_params().read::<f32>().unwrap();
            let mut trainer = Trainer::new(&mut model, &SingleProcess, settings(precision, 3)).unwrap();
            let mut reruns = Vec::new();
            let mut reports = Vec::new();
            for step in 1..4 {
                loop {
                    trainer.begin_step(step).unwrap();
                    trainer.micro_batch(step, 0, &[&scene]).unwrap();
                    match trainer.finish_step(step).unwrap() {
                        Finished::Done(r) => break reports.push(r),
                        Finished::Rerun { why } => {
                            let store = trainer.model().store();
                            assert_eq!(store.step(), step - 1, "{precision:?}: a vetoed step counted");
                            if step == 1 {
                                let now = store.flat_params().read::<f32>().unwrap();
                                assert!(
                                    now == initial,
                                    "{precision:?}: a vetoed update moved the parameters"
                                );
                            }
                            reruns.push((step, why));
                        }
                        other => panic!("{precision:?}: step {step} ended {other:?}"),
                    }
                }
            }
            let room = model.pair_room();
            (
                model.store.flat_params().read::<f32>().unwrap(),
                reports,
                reruns,
                room,
                model.store.loss_scale(),
            )
        };
        let (want, want_reports, none, room, scale) = run(0);
        assert!(none.is_empty(), "{precision:?}: lists sized by the first step were outgrown: {none:?}");
        // Room for 16 pairs: the first step outgrows it and runs again with room enough.
        let (got, reports, reruns, grown, got_scale) = run(16);
        assert_eq!(reruns.len(), 1, "{precision:?}: {reruns:?}");
        assert!(reruns[0].0 == 1 && reruns[0].1.contains("outgrew the room for 16"), "{reruns:?}");
        assert!(grown > 16 && grown <= room, "{precision:?}: room {grown}, sized by the first step {room}");
        assert!(got == want, "{precision:?}: the parameters after a rerun differ from an unbroken run");
        let key = |r: &StepReport| (r.losses.total().to_bits(), r.grad_norm.to_bits());
        assert_eq!(
            reports.iter().map(key).collect::<Vec<_>>(),
            want_reports.iter().map(key).collect::<Vec<_>>()
        );
        assert_eq!(got_scale, scale, "{precision:?}: a rerun changed the loss scale");
        assert_eq!(reports[0].overflows, 0);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn f16_training_follows_f32_for_100_steps() {
    // The tolerance: every step's loss within 1 % of the f32 run's, and 0.1 % on average over
    // the run. Measured on lavapipe (portable f16 kernels): at most 0.066 %, 0.016 % on
    // average; the loss falls from 1.15 to 0.43 in both runs. (100 steps: the loss scale, which
    // grows after 1000 good ones, stays at its start in both lengths of run; 200 steps took
    // the suite's longest test, 76 s, and stayed within the same bounds.)
    let gpu = gpu();
    let dir = temp_dir("follow");
    let scene = upload(&gpu, &host_scene(&gpu, &dir));
    let steps = 100;
    let full = losses(&gpu, &scene, Precision::F32, steps);
    let half = losses(&gpu, &scene, Precision::F16, steps);
    let rel: Vec<f64> = full.iter().zip(&half).map(|(a, b)| (a - b).abs() / a.abs()).collect();
    let worst = rel.iter().cloned().fold(0.0, f64::max);
    let mean = rel.iter().sum::<f64>() / rel.len() as f64;
    eprintln!(
        "f16 against f32, tiny autoencoder, {steps} steps: loss {:.4} -> {:.4} (f32 {:.4} -> {:.4}); \
         relative difference at most {worst:.2e}, mean {mean:.2e}",
        half[0],
        half[steps as usize - 1],
        full[0],
        full[steps as usize - 1]
    );
    assert!(worst < 0.01 && mean < 1e-3, "f16 strays from f32: worst {worst:.3e}, mean {mean:.3e}");
    assert!(
        full[steps as usize - 1] < 0.8 * full[0],
        "the run must learn for the comparison to mean anything"
    );
    // Not the same bits: the f16 path is not the f32 path under another name.
    assert_ne!(full, half);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A linear map trained by the trainer, the gradient it makes chosen by its sample: enough to
/// drive an f16 product past f16's range.
struct Toy {
    store: ParamStore,
    linear: Linear,
    /// Which call of `record_ahead` fails (as one out of device memory would), if any, and the
    /// calls so far.
    refuse: Option<u32>,
    calls: u32,
}

impl Toy {
    fn new(gpu: &Gpu) -> Toy {
        let mut b = ParamStore::builder();
        b.add("w", &[4, 1], Init::Zeros).unwrap();
        let store = b.build(gpu, 0).unwrap();
        let linear = Linear::new(Param::from_store(&store, "w").unwrap(), None).unwrap();
        Toy { store, linear, refuse: None, calls: 0 }
    }
}

impl Trainable for Toy {
    /// Inputs `[n, 4]` and targets `[n, 1]`.
    type Sample = (Tensor, Tensor);

    fn store(&self) -> &ParamStore {
        &self.store
    }

    fn store_mut(&mut self) -> &mut ParamStore {
        &mut self.store
    }

    fn describe(&self) -> serde_json::Value {
        serde_json::json!({ "model": "toy" })
    }

    fn optimisation(&self) -> Optimisation {
        Optimisation {
            peak_lr: 0.01,
            warmup: 0,
            max_grad_norm: None,
            adamw: AdamWConfig::default(),
            batch: 1,
        }
    }

    fn accumulate(&mut self, samples: &[&(Tensor, Tensor)], _: &mut [Rng], weight: f64) -> Result<Losses> {
        let (x, y) = samples[0];
        let mut rec = self.store.recorder()?;
        let (pred, cache) = self.linear.forward(&mut rec, x)?;
        let (loss, d) = Loss::mse().weighted(weight as f32).forward_backward(&mut rec, &pred, y)?;
        self.linear.param_grads(&mut rec, &cache, &d)?;
        rec.submit()?;
        Ok(Losses { terms: vec![("total", loss.read::<f32>()?[0] as f64)] })
    }

    fn records_ahead(&self) -> bool {
        true
    }

    // The same passes with the update, where asked for, and the loss read with them.
    fn record_ahead(
        &mut self,
        samples: &[&(Tensor, Tensor)],
        _: &mut [Rng],
        weight: f64,
    ) -> Result<Ahead<Toy>> {
        self.calls += 1;
        if self.refuse == Some(self.calls) {
            return Err(velox::engine::Error::Invalid("out of device memory".into()));
        }
        let (x, y) = samples[0];
        let mut rec = self.store.recorder()?;
        let (pred, cache) = self.linear.forward(&mut rec, x)?;
        let (loss, d) = Loss::mse().weighted(weight as f32).forward_backward(&mut rec, &pred, y)?;
        self.linear.param_grads(&mut rec, &cache, &d)?;
        let loss = rec.read_back(&loss)?;
        self.store.record_update(&mut rec)?;
        let finish: Finish<Toy> =
            Box::new(move |_, _| Ok(Losses { terms: vec![("total", loss.read::<f32>()?[0] as f64)] }));
        Ok(Ahead { rec, finish })
    }
}

/// Would catch: a step recorded while the last ran that is submitted after the last
/// overflowed (run at the scale before the halving, or not run again), or after the scale
/// grew; and a store whose state for the running step the recording ahead overwrote.
#[test]
fn steps_recorded_ahead_follow_overflows_and_the_growing_scale() {
    let gpu = gpu();
    let x = Tensor::from_slice(&gpu, &[1, 4], &[1.0f32, 0.5, -1.0, 2.0]).unwrap();
    let run_refusing = |target: f32, good_steps: u64, overlap: bool, refuse: Option<u32>| {
        let y = Tensor::from_slice(&gpu, &[1, 1], &[target]).unwrap();
        let sample = (x.clone(), y);
        let mut toy = Toy::new(&gpu);
        toy.refuse = refuse;
        let scale = toy.store.loss_scale().scale;
        *toy.store.loss_scale_mut() = LossScale { scale, good_steps };
        let mut trainer = Trainer::new(&mut toy, &SingleProcess, settings(Precision::F16, 3)).unwrap();
        trainer.set_overlap(overlap);
        assert!(trainer.overlaps() == overlap);
        let reports = trainer.repeat_steps(&[&sample], 1..4).unwrap();
        let ahead = (trainer.recorded_ahead(), trainer.overlaps());
        let key: Vec<_> = reports
            .iter()
            .map(|r| (r.losses.total().to_bits(), r.grad_norm.to_bits(), r.loss_scale, r.overflows))
            .collect();
        (toy.store.flat_params().read::<f32>().unwrap(), key, toy.store.loss_scale(), ahead)
    };
    // 11 overflows in step 1 (see above): each try records step 2 and drops it; the last
    // try's recording of it runs, and step 2's of step 3.
    let run = |target: f32, good_steps: u64, overlap: bool| run_refusing(target, good_steps, overlap, None);
    let (want, want_reports, want_scale, none) = run(1000.0, 0, false);
    assert_eq!(none, ((0, 0), false));
    let (got, reports, scale, ahead) = run(1000.0, 0, true);
    assert_eq!(ahead, ((13, 2), true));
    assert!(got == want, "recorded ahead {got:?}, after {want:?}");
    assert_eq!((reports, scale), (want_reports, want_scale));
    // The scale doubles after step 2: step 3, recorded at the scale before, is recorded again.
    let grows = LossScale::GROWTH_INTERVAL - 2;
    let (want, want_reports, want_scale, _) = run(0.1, grows, false);
    assert_eq!(want_scale.scale, 2.0 * LossScale::INITIAL);
    let (got, reports, scale, ahead) = run(0.1, grows, true);
    assert_eq!(ahead, ((2, 1), true));
    assert!(got == want, "recorded ahead {got:?}, after {want:?}");
    assert_eq!((reports, scale), (want_reports.clone(), want_scale));
    // Step 2 cannot be recorded ahead (the toy's second recording fails, as one out of device
    // memory would): it is recorded when due, and the run records no more ahead.
    let (got, reports, scale, ahead) = run_refusing(0.1, grows, true, Some(2));
    assert_eq!(ahead, ((0, 0), false));
    assert!(got == want, "recorded ahead {got:?}, after {want:?}");
    assert_eq!((reports, scale), (want_reports, want_scale));
}

#[test]
fn a_step_whose_gradients_overflow_f16_is_run_again_at_half_the_scale() {
    let gpu = gpu();
    // A huge loss: prediction 0, target 1000, so dL/dpred = -2000 and the scaled gradient the
    // backward product reads is -2000 x scale, past f16's largest finite value (65504) for
    // every scale above 32: from 2^16 the step overflows 11 times, then runs at 32.
    let x = Tensor::from_slice(&gpu, &[1, 4], &[1.0f32, 0.5, -1.0, 2.0]).unwrap();
    let y = Tensor::from_slice(&gpu, &[1, 1], &[1000.0f32]).unwrap();
    let sample = (x, y);
    let run = |precision| {
        let mut toy = Toy::new(&gpu);
        let mut trainer = Trainer::new(&mut toy, &SingleProcess, settings(precision, 3)).unwrap();
        let reports = trainer.repeat_steps(&[&sample], 1..4).unwrap();
        (toy.store.flat_params().read::<f32>().unwrap(), reports, toy)
    };
    let (full, full_reports, _) = run(Precision::F32);
    let (half, reports, toy) = run(Precision::F16);
    assert_eq!(reports[0].overflows, 11, "{reports:?}");
    assert_eq!(reports[0].loss_scale, Some(32.0));
    // The later steps' gradients are smaller (the prediction moved): no more overflows.
    assert_eq!((reports[1].overflows, reports[2].overflows), (0, 0));
    assert_eq!(toy.store.loss_scale(), LossScale { scale: 32.0, good_steps: 3 });
    assert_eq!(full_reports[0].loss_scale, None);
    // Scaling by a power of two is exact, and the inputs and the first gradient are f16
    // numbers: the first step's loss and gradient norm are the f32 run's to the bit. The later
    // steps read the moved weights rounded to f16.
    let (a, b) = (&reports[0], &full_reports[0]);
    assert_eq!((a.losses.total(), a.grad_norm), (b.losses.total(), b.grad_norm));
    let moved = full.iter().map(|v| v.abs()).fold(0.0, f32::max);
    let off = half.iter().zip(&full).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(moved > 0.01 && off < 1e-3 * moved, "f16 {half:?} against f32 {full:?}");

    // The scale is part of the run's state: a checkpoint keeps it, and a load restores it.
    let dir = temp_dir("overflow");
    let path = dir.join("toy.safetensors");
    checkpoint::save(&path, &toy.store, "{}").unwrap();
    assert_eq!(checkpoint::peek(&path).unwrap().loss_scale, Some(LossScale { scale: 32.0, good_steps: 3 }));
    let mut other = Toy::new(&gpu);
    checkpoint::load(&path, &mut other.store).unwrap();
    assert_eq!(other.store.loss_scale(), toy.store.loss_scale());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_f16_run_stopped_and_resumed_repeats_the_uninterrupted_run() {
    let gpu = gpu();
    let dir = temp_dir("resume");
    let memory = Memory { gpu: gpu.clone(), scenes: vec![host_scene(&gpu, &dir)] };
    let options = |out: &Path, begin: Begin, stop_at| TrainOptions {
        out: out.to_path_buf(),
        request: RunRequest {
            steps: Some(4),
            precision: if begin == Begin::Resume { None } else { Some(Precision::F16) },
            ..Default::default()
        },
        begin,
        checkpoint_every: 100,
        plot_every: 100,
        stop_at,
        prefetch: 1,
        overlap: None,
    };
    let run = |out: &Path, begin: Begin, stop_at| {
        let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 7).unwrap();
        if begin == Begin::Resume {
            checkpoint::load(&out.join("checkpoint.safetensors"), &mut model.store).unwrap();
        }
        train(&mut model, &memory, &options(out, begin, stop_at), &SingleProcess, &mut Quiet, &|| false)
            .unwrap()
    };
    let whole = dir.join("whole");
    let outcome = run(&whole, Begin::New, None);
    assert_eq!(outcome.settings.precision, Precision::F16);
    let parts = dir.join("parts");
    run(&parts, Begin::New, Some(2));
    let resumed = run(&parts, Begin::Resume, None);
    assert_eq!(resumed.settings.precision, Precision::F16, "a resumed run keeps its precision");
    let bytes = |d: &Path| std::fs::read(d.join("checkpoint.safetensors")).unwrap();
    assert!(bytes(&whole) == bytes(&parts), "the resumed f16 run's checkpoint differs from the whole run's");
    assert!(checkpoint::peek(&whole.join("checkpoint.safetensors")).unwrap().loss_scale.is_some());
    // The log says the scale of every step.
    let log = std::fs::read_to_string(parts.join("log.jsonl")).unwrap();
    assert_eq!(log.lines().filter(|l| l.contains("\"loss_scale\":65536.0")).count(), 4, "{log}");
    // Asking a resumed run for another precision is refused.
    let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 7).unwrap();
    checkpoint::load(&parts.join("checkpoint.safetensors"), &mut model.store).unwrap();
    let mut asked = options(&parts, Begin::Resume, None);
    asked.request.precision = Some(Precision::F32);
    asked.request.steps = Some(6);
    let err = train(&mut model, &memory, &asked, &SingleProcess, &mut Quiet, &|| false).unwrap_err();
    assert!(err.to_string().contains("`precision` f32 differs from the f16"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Would catch: a step recorded while the last ran that differs from one recorded after it
/// (draws, room, update, the store's state for the running step), one submitted after the
/// last outgrew its tile lists, and a run whose next scenes, read ahead, come in another order.
#[test]
fn autoencoder_steps_recorded_while_the_last_runs_are_the_same_steps() {
    // The submissions are counted where the test has its device alone.
    let (gpu, counted) = match counting_gpu() {
        Some(gpu) => (gpu, true),
        None => (gpu(), false),
    };
    let dir = temp_dir("overlap");
    let host = host_scene(&gpu, &dir);
    let scene = upload(&gpu, &host);
    for precision in [Precision::F32, Precision::F16] {
        let run_accumulating = |room: usize, overlap: bool, accumulate: u64| {
            let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 3).unwrap();
            model.set_pair_room(room);
            let request = RunRequest {
                steps: Some(4),
                precision: Some(precision),
                accumulate: Some(accumulate),
                ..Default::default()
            };
            let settings = RunSettings::new(&request, vec!["sample".into()], 1, 1).unwrap();
            let mut trainer = Trainer::new(&mut model, &SingleProcess, settings).unwrap();
            trainer.set_overlap(overlap);
            let submits = gpu.submits();
            let reports = trainer.repeat_steps(&[&scene], 1..5).unwrap();
            let ahead = (trainer.recorded_ahead(), gpu.submits() - submits);
            let key: Vec<_> =
                reports.iter().map(|r| (r.losses.total().to_bits(), r.grad_norm.to_bits())).collect();
            (model.store.flat_params().read::<f32>().unwrap(), key, ahead)
        };
        let run = |room: usize, overlap: bool| run_accumulating(room, overlap, 1);
        let (want, want_reports, (_, want_submits)) = run(0, false);
        // The first step sizes the lists: steps 3 and 4 are recorded ahead, with no submission
        // of their own while the step before runs.
        let (got, reports, (ahead, submits)) = run(0, true);
        assert_eq!(ahead, (2, 2), "{precision:?}");
        if counted {
            assert_eq!((submits, want_submits), (4, 4), "{precision:?}: submissions of four steps");
        }
        assert!(got == want, "{precision:?}: steps recorded ahead changed the parameters");
        assert_eq!(reports, want_reports, "{precision:?}");
        // Room for 16 pairs: step 1 outgrows it, and step 2, recorded meanwhile, is dropped.
        let (got, reports, (ahead, _)) = run(16, true);
        assert_eq!(ahead, (4, 3), "{precision:?}");
        assert!(got == want, "{precision:?}: a rerun with steps recorded ahead changed the parameters");
        assert_eq!(reports, want_reports, "{precision:?}");
        // Two micro-batches a step, each recorded while the one before runs: with room for 16
        // pairs the first outgrows it, and the second, recorded with the update, is dropped
        // unsubmitted (the step counter goes back).
        let (want, want_reports, _) = run_accumulating(0, false, 2);
        for room in [0, 16] {
            let (got, reports, ((recorded, _), _)) = run_accumulating(room, true, 2);
            assert!(recorded >= 2, "{precision:?}, room {room}: {recorded} steps recorded ahead");
            assert!(
                got == want,
                "{precision:?}, room {room}: micro-batches recorded ahead changed the parameters"
            );
            assert_eq!(reports, want_reports, "{precision:?}, room {room}");
        }
    }

    // A run of the library's trainer on two scenes, stopped and resumed, its scenes read a
    // group ahead.
    let memory = Memory { gpu: gpu.clone(), scenes: vec![host, host_scene_of(&gpu, &dir, 3)] };
    let train_to = |out: &Path, begin: Begin, stop_at, overlap| {
        let mut model = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 7).unwrap();
        if begin == Begin::Resume {
            checkpoint::load(&out.join("checkpoint.safetensors"), &mut model.store).unwrap();
        }
        let options = TrainOptions {
            out: out.to_path_buf(),
            request: RunRequest { steps: Some(5), steps_per_scene: Some(2), ..Default::default() },
            begin,
            checkpoint_every: 100,
            plot_every: 100,
            stop_at,
            prefetch: 1,
            overlap: Some(overlap),
        };
        train(&mut model, &memory, &options, &SingleProcess, &mut Quiet, &|| false).unwrap()
    };
    let (whole, parts) = (dir.join("whole"), dir.join("parts"));
    train_to(&whole, Begin::New, None, false);
    let first = train_to(&parts, Begin::New, Some(3), true);
    assert_eq!(first.steps_run, 3);
    train_to(&parts, Begin::Resume, None, true);
    let bytes = |d: &Path| std::fs::read(d.join("checkpoint.safetensors")).unwrap();
    assert!(bytes(&whole) == bytes(&parts), "the run with steps recorded ahead differs from the one without");
    let _ = std::fs::remove_dir_all(&dir);
}
