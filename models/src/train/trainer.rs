//! The trainer every model shares: [`train`] runs a whole run (its settings, samples,
//! optimiser steps, log, loss plot, checkpoints, stops), and [`Trainer`] takes one optimiser
//! step at a time (what [`train`] and `velox bench train` call).
//!
//! A step `s` (counted from 1) of a run of `P` processes, each accumulating `A` micro-batches
//! of the model's `B` samples (a global batch of `G = B A P` samples):
//! 1. the gradients are zeroed;
//! 2. process `r` runs its micro-batches `m = 0..A`: micro-batch `m` holds the slots
//!    `(r A + m) B ..` of the global batch, slot `g` the sample at position
//!    `((s - 1) / steps_per_scene) G + g` of the run's order with the generator
//!    `slot_rng(seed, s, g)` ([`super::order`]); [`Trainable::accumulate`] adds `1 / G` times
//!    the gradient of the micro-batch's summed losses;
//! 3. the processes gather each loss term (a NaN or Inf anywhere stops every process) and sum
//!    the gradients ([`Collective::all_reduce_sum`]), so the gradient is the global batch's
//!    mean;
//! 4. AdamW updates the parameters with the model's learning rate at `s` times the run's
//!    cooldown factor, clipped to the model's gradient norm; a NaN or Inf gradient norm leaves
//!    the parameters as they were and stops the run.
//!
//! In f16 training (the run's `precision`) the passes' products read f16 operands (the
//! parameters' f16 copies, refreshed after every update from the f32 masters) and the loss is
//! scaled by the store's [`crate::params::LossScale`]: the weight of step 2 is `scale / G`, the update divides
//! the scale out. Gradients that overflow (a NaN or Inf norm) skip the update: the scale is
//! halved and the step is run again on the same samples with the same generators
//! ([`Finished::Overflowed`]), so the steps of a run, and its resumption, stay the same.
//!
//! Every process then holds the same parameters; process 0 alone writes `log.jsonl`, the loss
//! plot and the checkpoints (atomically), and every file failure or stop request is agreed on
//! by all processes. The samples of a step depend on the seed, the step and the dataset, not
//! on how `G` is split, so a run's samples are the same on one process or several, and a
//! resumed run repeats the uninterrupted one bit for bit.
//!
//! With one process, [`Trainer::run_step`] records each micro-batch's pass while the one before
//! runs on the device, step `s + 1`'s first while step `s`'s last runs, and submits it once
//! the one before is known good (a step recorded
//! with what `s` then changed, an overflow, a grown loss scale or outgrown tile lists, is
//! recorded again), so the device does not wait for the host's recording and the steps stay
//! the same to the bit ([`Trainer::set_overlap`]; `docs/decisions/recorder.md`).
//!
//! Tests: `tests/training/trainer.rs` (micro-batches, accumulation, resume to the bit),
//! `tests/training/mixed_precision.rs` and `tools/tests/train_cli.rs`.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use velox_engine::rng::Rng;
use velox_engine::{Error, FileOp, Precision, Result};

use super::collective::Collective;
use super::log::{Log, LogLine, Terms};
use super::order::{slot_position, slot_rng, step_position, Order};
use super::plot::plot_log;
use super::source::{prefetch, SampleSource};
use super::{Losses, Trainable};
use crate::checkpoint;
use crate::params::Update;
use crate::run::{RunRequest, RunSettings};
use crate::schedule::cooldown;

/// Whether a trainer on `gpu` records each step while the last runs unless told
/// ([`Trainer::set_overlap`]): on every device but a CPU one, where the host's recording would
/// take cores from the device's work.
pub fn overlaps_by_default(gpu: &velox_engine::Gpu) -> bool {
    gpu.caps().kind != "CPU"
}

/// The most samples one process takes in a step (over its micro-batches): a bound on what a
/// checkpoint's settings can make it hold.
pub const MAX_SAMPLES_PER_PROCESS: u64 = 1 << 20;

/// Seconds of a step by part.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TimeSplit {
    /// Waiting for samples and preparing them (the reading runs ahead on another thread).
    pub data: f64,
    /// The model's forward and backward passes, when the model measures them
    /// ([`Trainable::take_pass_seconds`]); both are within `compute`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forward: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backward: Option<f64>,
    /// The host's part of `compute` before the passes' submissions, when the model measures
    /// it: recording them and the host work between (drawing, uploads), during which the
    /// device waits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host: Option<f64>,
    /// The micro-batches' [`Trainable::accumulate`] calls: forward, backward and their reads.
    pub compute: f64,
    /// Gathering the losses and summing the gradients over the processes.
    pub all_reduce: f64,
    /// The AdamW update and the check of the gradient norm.
    pub optimiser: f64,
}

impl TimeSplit {
    /// The step's seconds.
    pub fn total(&self) -> f64 {
        self.data + self.compute + self.all_reduce + self.optimiser
    }

    /// The parts summed with another step's.
    pub fn add(&self, o: &TimeSplit) -> TimeSplit {
        let both = |a: Option<f64>, b: Option<f64>| Some(a? + b?);
        TimeSplit {
            data: self.data + o.data,
            forward: both(self.forward, o.forward),
            backward: both(self.backward, o.backward),
            host: both(self.host, o.host),
            compute: self.compute + o.compute,
            all_reduce: self.all_reduce + o.all_reduce,
            optimiser: self.optimiser + o.optimiser,
        }
    }

    /// Every part times `f` (1 / steps: the mean of a sum).
    pub fn scale(&self, f: f64) -> TimeSplit {
        TimeSplit {
            data: self.data * f,
            forward: self.forward.map(|v| v * f),
            backward: self.backward.map(|v| v * f),
            host: self.host.map(|v| v * f),
            compute: self.compute * f,
            all_reduce: self.all_reduce * f,
            optimiser: self.optimiser * f,
        }
    }
}

/// What an optimiser step reports.
#[derive(Clone, Debug, PartialEq)]
pub struct StepReport {
    pub step: u64,
    /// The loss terms, means over the global batch, the total first.
    pub losses: Losses,
    /// The global gradient norm before clipping.
    pub grad_norm: f64,
    /// The learning rate of the update (cooldown included).
    pub lr: f64,
    /// This process's seconds by part.
    pub time: TimeSplit,
    /// f16 training: the loss scale the step ran at, and the tries of the step at higher
    /// scales that overflowed before it.
    pub loss_scale: Option<f64>,
    pub overflows: u32,
}

/// How [`Trainer::finish_step`] ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Finished {
    /// The parameters were updated.
    Done(StepReport),
    /// f16 training: the gradients overflowed at loss scale `scale`; the update was skipped
    /// and the scale halved. Run the step again ([`Trainer::begin_step`] with the same step).
    Overflowed { scale: f64 },
    /// The model outgrew work it sized ahead ([`Trainable::take_rerun`]: `why`); nothing was
    /// updated and the model has grown the room. Run the step again, as after an overflow.
    Rerun { why: String },
}

/// Optimiser steps of a model, one at a time: [`Trainer::begin_step`], then
/// [`Trainer::micro_batch`] for each of this process's micro-batches, then
/// [`Trainer::finish_step`] (see the module docs).
pub struct Trainer<'a, M: Trainable, C: Collective> {
    model: &'a mut M,
    collective: &'a C,
    settings: RunSettings,
    losses: Losses,
    time: TimeSplit,
    /// What went wrong in this process's share of the step, reported by `finish_step` once
    /// every process knows.
    failed: Option<Error>,
    /// Tries of the step under way that overflowed, and which step that is.
    overflows: u32,
    retry_of: Option<u64>,
    /// This process's micro-batches outgrew what the model sized ahead: why.
    rerun: Option<String>,
    /// Whether [`Trainer::run_step`] records a step's pass while the step before runs
    /// ([`Trainer::set_overlap`]).
    overlap: bool,
    /// The next step's pass, recorded while the last ran and not yet submitted.
    ahead: Option<AheadStep<M>>,
    /// Passes recorded ahead, and of them those the device ran as recorded.
    recorded_ahead: (u64, u64),
}

/// A step's pass recorded while the step before ran ([`Trainer::run_step`]): the update it
/// records and the store's state it left, for the check that both still hold when it is due.
struct AheadStep<M: Trainable> {
    step: u64,
    update: Update,
    pass: super::Ahead<M>,
    state: crate::params::PassState,
}

impl<'a, M: Trainable, C: Collective> Trainer<'a, M, C> {
    /// A trainer of `model` with a run's settings, whose global batch must be the model's
    /// micro-batch times the settings' `accumulate` times the processes.
    pub fn new(model: &'a mut M, collective: &'a C, settings: RunSettings) -> Result<Self> {
        let (b, p, a) = (model.optimisation().batch as u64, collective.size() as u64, settings.accumulate);
        let mine = b.checked_mul(a).filter(|&n| n > 0 && n <= MAX_SAMPLES_PER_PROCESS);
        if mine.and_then(|n| n.checked_mul(p)) != Some(settings.global_batch) {
            return Err(Error::Invalid(format!(
                "a batch of {} samples a step is not {b} a micro-batch x {a} micro-batches x {p} process(es) \
                 (at most {MAX_SAMPLES_PER_PROCESS} samples a process)",
                settings.global_batch
            )));
        }
        model.store_mut().set_training_precision(settings.precision)?;
        let overlap = overlaps_by_default(model.store().flat_params().gpu());
        Ok(Trainer {
            model,
            collective,
            settings,
            losses: Losses::default(),
            time: TimeSplit::default(),
            failed: None,
            overflows: 0,
            retry_of: None,
            rerun: None,
            overlap,
            ahead: None,
            recorded_ahead: (0, 0),
        })
    }

    /// Has [`Trainer::run_step`] record each step's pass while the step before runs, where
    /// the run can (one process, a model that [records ahead](Trainable::records_ahead)): the device then waits on the host only from
    /// the end of a step to the next one's submission, not for its recording. On by default
    /// except on CPU devices, where recording would take cores from the device's work. The
    /// steps are the same to the bit either way; a pass recorded ahead holds its activations
    /// while the step before runs (up to twice the memory of one).
    pub fn set_overlap(&mut self, on: bool) {
        self.overlap = on;
        if !on {
            self.ahead = None;
        }
    }

    /// Whether [`Trainer::run_step`] records steps ahead ([`Trainer::set_overlap`]).
    pub fn overlaps(&self) -> bool {
        self.overlap && self.collective.size() == 1
    }

    /// How many steps' passes were recorded while the step before ran, and how many of them
    /// ran as recorded (the others were recorded again: the step before overflowed or
    /// outgrew its room, or the loss scale changed).
    pub fn recorded_ahead(&self) -> (u64, u64) {
        self.recorded_ahead
    }

    pub fn model(&self) -> &M {
        self.model
    }

    pub fn settings(&self) -> &RunSettings {
        &self.settings
    }

    /// What the step's loss is multiplied by: the loss scale in f16 training, else 1.
    fn loss_scale(&self) -> f64 {
        match self.settings.precision {
            Precision::F16 => self.model.store().loss_scale().scale,
            Precision::F32 => 1.0,
        }
    }

    /// The slots of the global batch that this process's micro-batch `m` holds.
    pub fn slots(&self, m: u64) -> Range<u64> {
        let b = self.model.optimisation().batch as u64;
        let first = (self.collective.rank() as u64 * self.settings.accumulate + m) * b;
        first..first + b
    }

    /// Starts step `step` (or runs it again after [`Finished::Overflowed`]): the gradients
    /// are zeroed by the step's first recording. The parameters must be at step `step - 1`.
    pub fn begin_step(&mut self, step: u64) -> Result<()> {
        let at = self.model.store().step();
        if at + 1 != step {
            return Err(Error::Invalid(format!("step {step} asked of a model at step {at}")));
        }
        if self.retry_of.take() != Some(step) {
            self.overflows = 0;
        }
        self.losses = Losses::default();
        // Seconds getting the step's samples, added before it began, stay.
        self.time = TimeSplit { data: self.time.data, ..TimeSplit::default() };
        self.failed = None;
        self.rerun = None;
        // Recorded first by the step's first pass (no submit of its own).
        self.model.store_mut().zero_grads_first();
        self.model.store_mut().take_update();
        Ok(())
    }

    /// The optimiser step that ends step `step`.
    fn update(&self, step: u64) -> Update {
        let s = &self.settings;
        let opt = self.model.optimisation();
        Update {
            adamw: opt.adamw,
            lr: opt.learning_rate(step) * cooldown(s.steps, s.cooldown, step),
            max_norm: opt.max_grad_norm,
            loss_scale: self.loss_scale(),
            // The f16 copies the next passes read (unchanged when the update was skipped).
            sync_half: s.precision == Precision::F16,
        }
    }

    /// Adds seconds spent getting samples to the step's time split.
    pub fn add_data_seconds(&mut self, seconds: f64) {
        self.time.data += seconds;
    }

    /// Records that this process's share of the step failed (a sample could not be read):
    /// the rest of its micro-batches are skipped and [`Trainer::finish_step`] stops every
    /// process with this error.
    pub fn fail(&mut self, error: Error) {
        self.failed.get_or_insert(error);
    }

    /// Whether this process's share of the step failed.
    pub fn failed(&self) -> bool {
        self.failed.is_some()
    }

    /// Runs micro-batch `m` of step `step` on `samples` (the samples of [`Trainer::slots`]).
    /// A model error is kept for [`Trainer::finish_step`], so that every process learns of it.
    pub fn micro_batch(&mut self, step: u64, m: u64, samples: &[&M::Sample]) -> Result<()> {
        let slots = self.slots(m);
        if m >= self.settings.accumulate || samples.len() as u64 != slots.end - slots.start {
            return Err(Error::Invalid(format!(
                "micro-batch {m} of {} given {} samples for {} slots",
                self.settings.accumulate,
                samples.len(),
                slots.end - slots.start
            )));
        }
        if self.failed.is_some() || self.rerun.is_some() {
            return Ok(());
        }
        let mut rngs = self.prepare_pass(step, m);
        let scale = self.loss_scale();
        let t = Instant::now();
        let losses = self.model.accumulate(samples, &mut rngs, scale / self.settings.global_batch as f64);
        self.add_losses(losses, scale, t.elapsed().as_secs_f64());
        Ok(())
    }

    /// Takes in a micro-batch's losses (or its failure) at loss scale `scale`, and the seconds
    /// its passes took.
    fn add_losses(&mut self, losses: Result<Losses>, scale: f64, seconds: f64) {
        match losses {
            Ok(mut l) => {
                l.terms.iter_mut().for_each(|t| t.1 /= scale);
                self.losses.add(&l)
            }
            Err(e) => self.fail(e),
        }
        self.rerun = self.model.take_rerun();
        self.time.compute += seconds;
    }

    /// Runs step `step` on `samples` (this process's, in the order of its slots): the step's
    /// micro-batches, then [`Trainer::finish_step`]. Where the trainer
    /// [overlaps](Trainer::overlaps), it records each micro-batch's pass while the one before
    /// runs on the device, and the pass of step `step + 1`'s first micro-batch on `next` (its
    /// samples) while this step's last runs; it submits that one when step `step + 1` is run,
    /// on the same samples, if the update and the state it was recorded with still hold (else
    /// it records it again). A caller that stops after this step just does not run it.
    pub fn run_step(
        &mut self,
        step: u64,
        samples: &[&M::Sample],
        next: Option<&[&M::Sample]>,
    ) -> Result<Finished> {
        let b = self.model.optimisation().batch;
        if samples.len() as u64 != b as u64 * self.settings.accumulate {
            return Err(Error::Invalid(format!(
                "step {step} given {} samples for {} micro-batches of {b}",
                samples.len(),
                self.settings.accumulate
            )));
        }
        let ahead = self.ahead.take();
        if !self.overlaps() || !(ahead.is_some() || self.model.records_ahead()) {
            self.begin_step(step)?;
            for (m, mine) in samples.chunks(b).enumerate() {
                self.micro_batch(step, m as u64, mine)?;
            }
            return self.finish_step(step);
        }
        // The first micro-batch's pass recorded ahead, if what it recorded still holds; else
        // it is recorded now. Each micro-batch's pass is then launched, the next one (or the
        // next step's first) recorded while it runs, and it is finished before the next is
        // launched: a micro-batch that failed or outgrew its room ends the step there. The
        // step's compute time is the wall time from here to its finish, the recording of the
        // next step included (a step recorded ahead was timed with the step before).
        let t = Instant::now();
        self.begin_step(step)?;
        let scale = self.loss_scale();
        let acc = self.settings.accumulate;
        let mut pass = match ahead {
            // (begin_step has checked that the parameters are at the step before.)
            Some(a) if a.step == step && a.update == self.update(step) => {
                self.model.store_mut().restore_pass_state(a.state);
                self.recorded_ahead.1 += 1;
                Ok(a.pass)
            }
            _ => self.record_pass(step, 0, &samples[..b], scale),
        };
        for m in 0..acc {
            let launched = pass.and_then(|pass| Ok((pass.rec.launch()?, pass.finish)));
            let next_pass = match (&launched, next) {
                (Err(_), _) => None,
                _ if m + 1 < acc => {
                    let mine = &samples[(m as usize + 1) * b..(m as usize + 2) * b];
                    Some(self.record_pass(step, m + 1, mine, scale))
                }
                (_, Some(next)) if self.model.records_ahead() => {
                    self.ahead = self.record_ahead(step + 1, &next[..b]);
                    None
                }
                _ => None,
            };
            let losses = launched.and_then(|(launched, finish)| finish(self.model, &launched.wait()?));
            self.add_losses(losses, scale, 0.0);
            match next_pass {
                Some(p) if self.failed.is_none() && self.rerun.is_none() => pass = p,
                Some(_) => {
                    // Dropped unsubmitted: where it recorded the update, the step counter it
                    // advanced goes back, and nothing was updated.
                    let store = self.model.store_mut();
                    if store.take_update() {
                        let at = store.step();
                        store.set_step(at - 1);
                    }
                    break;
                }
                None => break,
            }
        }
        self.time.compute += t.elapsed().as_secs_f64();
        let finished = self.finish_step(step)?;
        if !matches!(finished, Finished::Done(_)) {
            self.ahead = None;
        }
        Ok(finished)
    }

    /// Readies the pass of micro-batch `m` of step `step`: with one process, nothing comes
    /// between the last micro-batch's backward pass and the update, so the last pass records
    /// it at its end (one submission and one host wait fewer). Returns the pass's generators.
    fn prepare_pass(&mut self, step: u64, m: u64) -> Vec<Rng> {
        if m + 1 == self.settings.accumulate && self.collective.size() == 1 {
            let update = self.update(step);
            self.model.store_mut().update_last(update);
        }
        self.slots(m).map(|g| slot_rng(self.settings.seed, step, g)).collect()
    }

    /// Records the pass of micro-batch `m` of step `step` at loss scale `scale`, not
    /// submitted, the step's update with it where it is the last.
    fn record_pass(
        &mut self,
        step: u64,
        m: u64,
        samples: &[&M::Sample],
        scale: f64,
    ) -> Result<super::Ahead<M>> {
        let mut rngs = self.prepare_pass(step, m);
        self.model.record_ahead(samples, &mut rngs, scale / self.settings.global_batch as f64)
    }

    /// Records step `step`'s pass on `samples` while the step before runs, with the store's
    /// state of that step taken out and put back after. `None` where the recording failed
    /// (out of device memory with two steps' activations, a sample the model refuses): the
    /// step records it again when it is due, after the step before has let its memory go, and
    /// reports a failure then; the run records no more steps ahead.
    fn record_ahead(&mut self, step: u64, samples: &[&M::Sample]) -> Option<AheadStep<M>> {
        let running = self.model.store_mut().take_pass_state();
        let update = self.update(step);
        self.model.store_mut().zero_grads_first();
        let pass = self.record_pass(step, 0, samples, update.loss_scale);
        let state = self.model.store_mut().take_pass_state();
        self.model.store_mut().restore_pass_state(running);
        let Ok(pass) = pass else {
            self.overlap = false;
            return None;
        };
        self.recorded_ahead.0 += 1;
        Some(AheadStep { step, update, pass, state })
    }

    /// Ends step `step`: gathers the losses and sums the gradients over the processes, then
    /// updates the parameters (with one process, the last micro-batch's pass has recorded the
    /// update already, see [`ParamStore::update_last`](crate::params::ParamStore::update_last)).
    /// Fails, on every process, if any process's share failed or its loss is not finite (the
    /// run stops there: no checkpoint is written of the step), and when the gradient norm is
    /// NaN or Inf (the parameters then stay as they were) in f32 training; in f16 training
    /// such a step comes back as [`Finished::Overflowed`], to be run again at the halved loss
    /// scale.
    pub fn finish_step(&mut self, step: u64) -> Result<Finished> {
        if let Some(p) = self.model.take_pass_seconds() {
            self.time.forward = Some(p.forward);
            self.time.backward = Some(p.backward);
            self.time.host = Some(p.host);
        }
        let t = Instant::now();
        // Every process runs the step again if any outgrew what its model sized ahead, unless
        // one failed (2 below): the failure ends the run, as it would have.
        let state = match (&self.failed, &self.rerun) {
            (Some(_), _) => 2.0,
            (None, Some(_)) => 1.0,
            (None, None) => 0.0,
        };
        let states = self.collective.all_gather_f64(state)?;
        let failed_anywhere = states.contains(&2.0);
        if let Some(r) = states.iter().position(|&s| s == 1.0).filter(|_| !failed_anywhere) {
            let store = self.model.store_mut();
            // With one process the update rode with the pass, and the device vetoed it.
            if store.take_update() && store.grad_norm().is_ok() {
                return Err(Error::Invalid("a step whose pass outgrew its room was not vetoed".into()));
            }
            self.retry_of = Some(step);
            let why = match self.rerun.take() {
                Some(why) if self.collective.size() == 1 => why,
                Some(why) => format!("process {}: {why}", self.collective.rank()),
                None => format!("process {r} outgrew what its model sized ahead"),
            };
            return Ok(Finished::Rerun { why });
        }
        let local = if self.failed.is_some() { f64::NAN } else { self.losses.total() };
        let totals = self.collective.all_gather_f64(local)?;
        if let Some(e) = self.failed.take() {
            return Err(e);
        }
        if let Some(r) = totals.iter().position(|t| !t.is_finite()) {
            return Err(Error::Invalid(match self.collective.size() {
                1 => format!("the loss became {}", totals[r]),
                _ => format!("process {r}'s share of the step failed or its loss became {}", totals[r]),
            }));
        }
        let mut terms = self.losses.terms.clone();
        let Some(total) = terms.first_mut() else {
            return Err(Error::Invalid("the model reported no loss for the step".into()));
        };
        total.1 = totals.iter().fold(0.0, |a, b| a + b);
        for term in terms.iter_mut().skip(1) {
            term.1 = self.collective.all_gather_f64(term.1)?.iter().fold(0.0, |a, b| a + b);
        }
        // A process whose micro-batches recorded nothing still brings zeros.
        self.model.store().settle_zero()?;
        self.collective.all_reduce_sum(self.model.store().flat_grads())?;
        self.time.all_reduce = t.elapsed().as_secs_f64();

        let t = Instant::now();
        let update = self.update(step);
        let (lr, scale) = (update.lr, update.loss_scale);
        let half = self.settings.precision == Precision::F16;
        let gpu = self.model.store().flat_params().gpu().clone();
        let store = self.model.store_mut();
        // Unless the last pass recorded the update (and submitted it with itself).
        if !store.take_update() {
            let mut rec = gpu.recorder()?;
            store.record(&mut rec, &update)?;
            rec.submit()?;
        }
        let grad_norm = match store.grad_norm() {
            Ok(norm) => norm as f64 / scale,
            Err(_) if half => {
                store.loss_scale_mut().overflowed()?;
                self.overflows += 1;
                self.retry_of = Some(step);
                self.time.optimiser = t.elapsed().as_secs_f64();
                return Ok(Finished::Overflowed { scale });
            }
            Err(e) => return Err(e),
        };
        if half {
            store.loss_scale_mut().good();
        }
        self.time.optimiser = t.elapsed().as_secs_f64();
        Ok(Finished::Done(StepReport {
            step,
            losses: Losses { terms },
            grad_norm,
            lr,
            time: std::mem::take(&mut self.time),
            loss_scale: half.then_some(scale),
            overflows: self.overflows,
        }))
    }

    /// Runs the steps `steps` with every slot of every step taking `samples[g % len]` (for
    /// benchmarks and tests: no dataset, no files) and returns their reports.
    pub fn repeat_steps(&mut self, samples: &[&M::Sample], steps: Range<u64>) -> Result<Vec<StepReport>> {
        if samples.is_empty() {
            return Err(Error::Invalid("steps on no samples".into()));
        }
        // Every step takes the same samples.
        let mine: Vec<&M::Sample> = (0..self.settings.accumulate)
            .flat_map(|m| self.slots(m))
            .map(|g| samples[(g % samples.len() as u64) as usize])
            .collect();
        let mut reports = Vec::new();
        for step in steps.clone() {
            let next = (step + 1 < steps.end).then_some(&mine[..]);
            loop {
                if let Finished::Done(report) = self.run_step(step, &mine, next)? {
                    reports.push(report);
                    break;
                }
            }
        }
        Ok(reports)
    }
}

/// How a run begins.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Begin {
    /// A new run from the model as given (freshly initialised).
    New,
    /// A new run from the parameters of another run's checkpoint (step 0, fresh moments).
    Init(PathBuf),
    /// The run in the output folder, from its checkpoint, which the model was loaded from.
    Resume,
}

/// The files of a run in its output folder.
#[derive(Clone, Debug)]
pub struct RunFolder {
    pub dir: PathBuf,
    pub checkpoint: PathBuf,
    pub log: PathBuf,
    pub plot: PathBuf,
}

impl RunFolder {
    pub fn new(dir: &Path) -> RunFolder {
        RunFolder {
            dir: dir.to_path_buf(),
            checkpoint: dir.join("checkpoint.safetensors"),
            log: dir.join("log.jsonl"),
            plot: dir.join("loss.png"),
        }
    }

    /// Creates the folder and checks that it suits the run: a resumed run needs its
    /// checkpoint, a new one must not overwrite another's.
    pub fn prepare(&self, begin: &Begin) -> Result<()> {
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| Error::Io(format!("cannot create {}: {e}", self.dir.display())))?;
        match (begin, self.checkpoint.exists()) {
            (Begin::Resume, false) => Err(Error::setting(
                "resume",
                format!("{{resume}}: {} holds no checkpoint.safetensors to resume from", self.dir.display()),
            )),
            (Begin::New | Begin::Init(_), true) => Err(Error::setting(
                "out",
                format!(
                    "{} already holds a checkpoint: ask for {{resume}} to continue it, or choose another {{out}}",
                    self.dir.display()
                ),
            )),
            _ => Ok(()),
        }
    }
}

/// What a run needs besides the model, the samples and the processes.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// The output folder: checkpoint.safetensors, log.jsonl, loss.png.
    pub out: PathBuf,
    pub begin: Begin,
    /// The run settings the caller asks for (a resumed run keeps its own; see
    /// [`RunSettings::resume`]).
    pub request: RunRequest,
    /// Steps between checkpoints (one is always written at the end).
    pub checkpoint_every: u64,
    /// Steps between redraws of the loss plot.
    pub plot_every: u64,
    /// Stop after this step, as a stop request does.
    pub stop_at: Option<u64>,
    /// Samples read ahead of the steps, per process.
    pub prefetch: usize,
    /// Whether a step is recorded while the last runs ([`Trainer::set_overlap`]); `None`: the
    /// device's default (on except on CPU devices). The steps are the same either way.
    pub overlap: Option<bool>,
}

/// Why a run ended before its last step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// A stop was asked for (the caller's `stop` said so, in some process).
    Asked,
    /// At [`TrainOptions::stop_at`].
    StopAt,
}

/// What a run reports at its end.
#[derive(Clone, Debug)]
pub struct Outcome {
    pub settings: RunSettings,
    pub checkpoint: PathBuf,
    pub first: StepReport,
    pub last: StepReport,
    /// Steps this call ran, and their seconds.
    pub steps_run: u64,
    pub seconds: f64,
    /// The mean time split of a step (this process's).
    pub time: TimeSplit,
    /// Samples of the global batch per second over the steps this call ran.
    pub samples_per_second: f64,
    /// `None` when the run reached its last step.
    pub stopped: Option<Stop>,
}

/// What a run tells as it goes; the library prints nothing itself.
pub trait Observer {
    /// Something the user should know (a setting kept, a checkpoint of an older layout).
    fn note(&mut self, _text: &str) {}
    /// The run starts after step `start_step` (0 for a new run).
    fn begin(&mut self, _settings: &RunSettings, _start_step: u64) {}
    /// A step ended.
    fn step(&mut self, _report: &StepReport, _samples_per_second: f64) {}
    /// The run ends: at its last step or a stop (`completed`), or with an error.
    fn end(&mut self, _completed: bool) {}
}

/// An observer that ignores everything.
pub struct Quiet;

impl Observer for Quiet {}

/// The run settings a checkpoint stores (under `"run"` in its config JSON); `None` for a
/// checkpoint saved outside a run, or before runs stored them.
pub fn run_settings(path: &Path) -> Result<Option<RunSettings>> {
    match checkpoint::config_json(path)?.get("run") {
        None => Ok(None),
        Some(run) => serde_json::from_value(run.clone()).map(Some).map_err(|e| {
            Error::Invalid(format!("checkpoint {}: the run's settings are unreadable: {e}", path.display()))
        }),
    }
}

/// Writes `model` to `path` with the run's settings (what a resumed run needs).
pub fn save_checkpoint<M: Trainable>(model: &M, settings: &RunSettings, path: &Path) -> Result<()> {
    let mut config = model.describe();
    config["run"] = serde_json::to_value(settings).expect("plain data serialises");
    checkpoint::save(path, model.store(), &config.to_string())
}

/// Fails unless the checkpoint `path` a run starts from ([`Begin::Init`]) holds a model of the
/// kind `ours` (the `"model"` of [`Trainable::describe`]).
pub fn check_init_kind(path: &Path, ours: &serde_json::Value) -> Result<()> {
    if let Some(kind) = checkpoint::config_json(path)?.get("model").filter(|k| *k != ours) {
        return Err(Error::setting(
            "init",
            format!("{{init}} {} holds a {kind} checkpoint; this run trains a {ours}", path.display()),
        ));
    }
    Ok(())
}

/// Sets `model`'s parameters to those of another run's checkpoint, `path` (the moments and the
/// step stay those of a new model). The checkpoint must be of the same kind of model
/// ([`Trainable::describe`]'s `"model"`) with parameters of the same names and shapes; the
/// error names what differs.
pub fn init_parameters<M: Trainable>(model: &mut M, path: &Path) -> Result<()> {
    let shown = path.display();
    check_init_kind(path, &model.describe()["model"])?;
    if model.store().step() != 0 {
        return Err(Error::setting("init", format!("{{init}} {shown}: the model has already taken steps")));
    }
    checkpoint::load_params(path, model.store_mut()).map(|_| ()).map_err(|e| match e {
        Error::Invalid(why) => Error::setting("init", format!("{{init}}: {why}")),
        Error::File { path, op: FileOp::Content, reason } => {
            Error::setting("init", format!("{{init}} {}: {reason}", path.display()))
        }
        Error::File { path, op, reason } => {
            Error::File { path, op, reason: format!("the parameters to start from: {reason}") }
        }
        other => other,
    })
}

/// What a run stopped by an error says of its checkpoint: written at some earlier step, it is
/// called good only once every value in it is checked finite.
fn last_good(checkpoint: &Path) -> String {
    if !checkpoint.exists() {
        return "no checkpoint was written yet".into();
    }
    match checkpoint::verify_finite(checkpoint) {
        Ok(info) => format!(
            "the last good checkpoint is {} (step {}, every value checked finite)",
            checkpoint.display(),
            info.step
        ),
        Err(e) => format!("the checkpoint is no good either: {e}"),
    }
}

/// An error's own words (without the "invalid input" its display adds).
fn words(e: &Error) -> String {
    match e {
        Error::Invalid(why) => why.clone(),
        other => other.to_string(),
    }
}

/// Runs `work` on process 0 alone, and has every process agree on its success: process 0
/// returns its error, the others one that points to it.
fn on_root<T, C: Collective>(collective: &C, work: impl FnOnce() -> Result<T>) -> Result<Option<T>> {
    let result = if collective.is_root() { Some(work()) } else { None }.transpose();
    let ok = collective.all_gather_f64(if result.is_ok() { 1.0 } else { 0.0 })?;
    let value = result?;
    if ok.contains(&0.0) {
        return Err(Error::Io("process 0 could not write the run's files (its error says why)".into()));
    }
    Ok(value)
}

/// Checks that every process runs with the settings of process 0 (the same dataset, the same
/// checkpoint).
fn same_everywhere<C: Collective>(collective: &C, settings: &RunSettings) -> Result<()> {
    if collective.size() == 1 {
        return Ok(());
    }
    let ours = serde_json::to_vec(settings).expect("plain data serialises");
    let mut root = ours.clone();
    collective.broadcast_bytes(0, &mut root)?;
    let same = collective.all_gather_f64(if root == ours { 1.0 } else { 0.0 })?;
    if let Some(r) = same.iter().position(|&s| s == 0.0) {
        return Err(Error::Invalid(format!(
            "process {r} would run with other settings than process 0 (a different dataset or checkpoint): \
             every process must see the same files"
        )));
    }
    Ok(())
}

/// Trains `model` on `source` as `options` say (see the module docs): settles the run's
/// settings (new, from another run's weights, or resumed from the checkpoint the model was
/// loaded from), then runs the steps to the run's last, `stop_at`, or a stop request (`stop`
/// returns true in some process: the step under way finishes and the checkpoint is written),
/// with the log, the plot and periodic checkpoints. An error in a step (a sample that cannot be
/// read, a loss or gradient that is not finite) stops the run with a message that names the
/// last good checkpoint.
pub fn train<M, S, C>(
    model: &mut M,
    source: &S,
    options: &TrainOptions,
    collective: &C,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
) -> Result<Outcome>
where
    M: Trainable,
    S: SampleSource<Sample = M::Sample>,
    C: Collective,
{
    let folder = RunFolder::new(&options.out);
    folder.prepare(&options.begin)?;
    if source.is_empty() {
        return Err(Error::Invalid("the dataset holds no samples".into()));
    }
    let names = source.names();
    let (micro, processes) = (model.optimisation().batch as u64, collective.size() as u64);
    let settings = match &options.begin {
        Begin::New => RunSettings::new(&options.request, names.clone(), micro, processes)?,
        Begin::Init(from) => {
            init_parameters(model, from)?;
            RunSettings::new(&options.request, names.clone(), micro, processes)?
        }
        Begin::Resume => match run_settings(&folder.checkpoint)? {
            None => {
                observer.note(&format!(
                    "{} does not store its run's settings (it predates that): the command line's are \
                     used, and the order of the samples may differ from the run's first part",
                    folder.checkpoint.display()
                ));
                RunSettings::new(&options.request, names.clone(), micro, processes)?
            }
            Some(stored) => {
                let (settings, notes) =
                    stored.resume(&options.request, &names, &folder.checkpoint, micro, processes)?;
                notes.iter().for_each(|n| observer.note(n));
                settings
            }
        },
    };
    same_everywhere(collective, &settings)?;
    let start_step = model.store().step();
    if start_step >= settings.steps {
        return Err(Error::setting(
            "steps",
            format!(
                "the checkpoint is at step {start_step} of a run of {} steps: ask for more {{steps}} to go on",
                settings.steps
            ),
        ));
    }
    if let Some(at) = options.stop_at.filter(|&at| at <= start_step || at > settings.steps) {
        return Err(Error::setting(
            "stop_at",
            format!(
                "{{stop_at}} {at} is not a step to come: the run goes from step {} to {}",
                start_step + 1,
                settings.steps
            ),
        ));
    }
    let mut log = on_root(collective, || Log::open(&folder.log, start_step))?;
    let mut trainer = Trainer::new(model, collective, settings.clone())?;
    if let Some(on) = options.overlap {
        trainer.set_overlap(on);
        if on && !trainer.overlaps() {
            observer.note(
                "each step is recorded after the last one's wait: recording a step while the last runs \
                 takes one process",
            );
        }
    }
    observer.begin(&settings, start_step);
    let result = std::thread::scope(|scope| {
        run_steps(&mut trainer, source, &folder, options, scope, log.as_mut(), observer, stop, &names)
    });
    observer.end(result.is_ok());
    result
}

/// The next sample from the reading thread, prepared.
fn read_one<S: SampleSource>(
    samples: &std::sync::mpsc::Receiver<Result<S::Raw>>,
    source: &S,
) -> Result<S::Sample> {
    samples
        .recv()
        .map_err(|_| Error::Io("the sample-reading thread stopped".into()))
        .and_then(|raw| source.prepare(raw?))
}

/// The next `n` samples from the reading thread, prepared.
fn read_group<S: SampleSource>(
    samples: &std::sync::mpsc::Receiver<Result<S::Raw>>,
    n: u64,
    source: &S,
) -> Result<Vec<S::Sample>> {
    (0..n).map(|_| read_one(samples, source)).collect()
}

/// The steps of [`train`], with the samples read ahead on a thread of `scope`.
#[allow(clippy::too_many_arguments)]
fn run_steps<'scope, M, S, C>(
    trainer: &mut Trainer<'_, M, C>,
    source: &'scope S,
    folder: &RunFolder,
    options: &TrainOptions,
    scope: &'scope std::thread::Scope<'scope, '_>,
    mut log: Option<&mut Log>,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    names: &[String],
) -> Result<Outcome>
where
    M: Trainable,
    S: SampleSource<Sample = M::Sample>,
    C: Collective,
{
    let settings = trainer.settings().clone();
    let collective = trainer.collective;
    let (global, acc, per_scene) = (settings.global_batch, settings.accumulate, settings.steps_per_scene);
    let b = trainer.model().optimisation().batch as u64;
    let start_step = trainer.model().store().step();
    // This process's slots of each group of steps, read in the order they are trained on.
    let mine = (collective.rank() as u64 * acc * b)..((collective.rank() as u64 + 1) * acc * b);
    let groups = step_position(start_step + 1, per_scene)..=step_position(settings.steps, per_scene);
    let mut order = Order::new(names.len(), settings.seed);
    let slots = mine.clone();
    let indices =
        groups.flat_map(move |k| slots.clone().map(move |g| k * global + g)).map(move |p| order.at(p));
    let samples = prefetch(scope, source, indices, options.prefetch)?;

    // The samples of this process's slots, kept while their group of steps lasts: slot by
    // slot, or (where the trainer overlaps steps) the group's at once, and the next group's
    // read ahead.
    let mut held: Vec<Option<S::Sample>> = (0..acc * b).map(|_| None).collect();
    let mut group_samples: Option<(u64, Result<Vec<S::Sample>>)> = None;
    let mut next_group: Option<(u64, Result<Vec<S::Sample>>)> = None;
    let mut group = None;
    let mut names_of_group = Vec::new();
    let mut order = Order::new(names.len(), settings.seed);
    let started = Instant::now();
    let seconds_before = log.as_ref().map_or(0.0, |l| l.seconds());
    let (mut first, mut last, mut time) = (None, None, TimeSplit::default());
    let mut saved = start_step;
    let mut stopped = None;
    let mut steps_run = 0;
    for step in start_step + 1..=settings.steps {
        let k = step_position(step, per_scene);
        if group != Some(k) {
            held.iter_mut().for_each(|s| *s = None);
            group = Some(k);
            names_of_group = (0..global)
                .map(|g| names[order.at(slot_position(step, per_scene, global, g))].clone())
                .collect();
        }
        // The group's last step lets its samples go once it is done (not before: an f16
        // overflow, or a model outgrowing what it sized ahead, runs the step again).
        let keep = !step.is_multiple_of(per_scene) && step < settings.steps;
        // Where the trainer overlaps steps, the next step's first pass is recorded while this
        // one runs (Trainer::run_step): its samples are read first, the next group's too where
        // the next step starts one (unless the run stops after this step).
        let overlap = trainer.overlaps();
        let t = Instant::now();
        if overlap && group_samples.as_ref().is_none_or(|g| g.0 != k) {
            group_samples = Some(match next_group.take() {
                Some((at, read)) if at == k => (k, read),
                _ => (k, read_group(&samples, acc * b, source)),
            });
        }
        let next_k = step_position(step + 1, per_scene);
        let last_step = step == settings.steps || options.stop_at == Some(step);
        if overlap && !last_step && next_k != k && next_group.is_none() {
            next_group = Some((next_k, read_group(&samples, acc * b, source)));
        }
        trainer.add_data_seconds(t.elapsed().as_secs_f64());
        let report = loop {
            let finished = match group_samples.as_ref().filter(|_| overlap) {
                Some((_, Ok(mine))) => {
                    let mine: Vec<&S::Sample> = mine.iter().collect();
                    let next = match &next_group {
                        _ if last_step => None,
                        Some((_, Ok(theirs))) => Some(theirs.iter().collect::<Vec<_>>()),
                        Some((_, Err(_))) => None,
                        None => Some(mine.clone()),
                    };
                    trainer.run_step(step, &mine, next.as_deref())
                }
                Some((_, Err(e))) => {
                    trainer.begin_step(step)?;
                    trainer.fail(Error::Invalid(words(e)));
                    trainer.finish_step(step)
                }
                None => {
                    trainer.begin_step(step)?;
                    for m in 0..acc {
                        let range = (m * b) as usize..((m + 1) * b) as usize;
                        let t = Instant::now();
                        for slot in range.clone() {
                            if held[slot].is_none() && !trainer.failed() {
                                match read_one(&samples, source) {
                                    Ok(s) => held[slot] = Some(s),
                                    Err(e) => trainer.fail(e),
                                }
                            }
                        }
                        trainer.add_data_seconds(t.elapsed().as_secs_f64());
                        if !trainer.failed() {
                            let batch: Vec<&S::Sample> =
                                held[range.clone()].iter().map(|s| s.as_ref().expect("read above")).collect();
                            trainer.micro_batch(step, m, &batch)?;
                        }
                    }
                    trainer.finish_step(step)
                }
            };
            let finished = finished.map_err(|e| {
                Error::Invalid(format!(
                    "training stopped at step {step}: {}; {}",
                    words(&e),
                    last_good(&folder.checkpoint)
                ))
            })?;
            match finished {
                Finished::Done(report) => break report,
                Finished::Overflowed { scale } => {
                    let again = scale / 2.0;
                    observer.note(&format!(
                        "step {step}: the f16 gradients overflowed at loss scale {scale}; run again at {again}"
                    ))
                }
                Finished::Rerun { why } => observer.note(&format!("step {step}: {why}; run again")),
            }
        };
        if !keep {
            held.iter_mut().for_each(|s| *s = None);
        }
        steps_run += 1;
        time = time.add(&report.time);
        let rate = (steps_run * global) as f64 / started.elapsed().as_secs_f64().max(1e-9);
        let checkpoint_now = step.is_multiple_of(options.checkpoint_every);
        on_root(collective, || {
            let log = log.as_mut().expect("process 0 holds the log");
            log.append(LogLine {
                step,
                seconds: seconds_before + started.elapsed().as_secs_f64(),
                samples: names_of_group.clone(),
                loss: Terms(report.losses.terms.iter().map(|(n, v)| (n.to_string(), *v)).collect()),
                grad_norm: report.grad_norm,
                lr: report.lr,
                time: report.time,
                loss_scale: report.loss_scale,
                overflows: report.overflows,
            })?;
            if step.is_multiple_of(options.plot_every) {
                plot_log(&folder.plot, log.history())?;
            }
            if checkpoint_now {
                save_checkpoint(trainer.model(), &settings, &folder.checkpoint)?;
            }
            Ok(())
        })?;
        if checkpoint_now {
            saved = step;
        }
        observer.step(&report, rate);
        first.get_or_insert_with(|| report.clone());
        last = Some(report);
        // A stop request or --stop-at ends the run here; a resumed run goes on as if it had not.
        let asked = collective.all_gather_f64(if stop() { 1.0 } else { 0.0 })?.contains(&1.0);
        if step < settings.steps && (asked || options.stop_at == Some(step)) {
            stopped = Some(if asked { Stop::Asked } else { Stop::StopAt });
            break;
        }
    }
    let step = trainer.model().store().step();
    on_root(collective, || {
        if saved != step {
            save_checkpoint(trainer.model(), &settings, &folder.checkpoint)?;
        }
        plot_log(&folder.plot, log.as_ref().expect("process 0 holds the log").history())
    })?;
    collective.barrier()?;
    let seconds = started.elapsed().as_secs_f64();
    Ok(Outcome {
        samples_per_second: (steps_run * global) as f64 / seconds.max(1e-9),
        settings,
        checkpoint: folder.checkpoint.clone(),
        first: first.expect("a run takes at least one step"),
        last: last.expect("a run takes at least one step"),
        steps_run,
        seconds,
        time: time.scale(1.0 / steps_run as f64),
        stopped,
    })
}
