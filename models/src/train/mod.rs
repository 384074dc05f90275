//! Training: what a model implements to be trained ([`Trainable`]), and the trainer every
//! model shares ([`trainer`]).
//!
//! A training step over a batch of samples: the trainer zeroes the gradients, calls
//! [`Trainable::accumulate`] on each micro-batch with the weight that makes the gradients the
//! mean over the whole batch, sums the gradients over the processes of a distributed run, then
//! steps the optimiser (AdamW with the model's learning rate and clipping).

pub mod collective;
pub mod distributed;
pub mod log;
mod mpi;
pub mod order;
pub mod plot;
pub mod source;
pub mod trainer;

use velox_engine::ops::adamw::AdamWConfig;
use velox_engine::rng::Rng;
use velox_engine::Result;

use crate::params::ParamStore;

/// The loss terms of a micro-batch: `(name, value)` pairs, the total first. Each value is the
/// sum over the micro-batch's samples of that term times the weight it was accumulated with,
/// so the terms of a step's micro-batches (and processes) add up to the batch means.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Losses {
    pub terms: Vec<(&'static str, f64)>,
}

impl Losses {
    /// The total loss (the first term), 0 when there is none.
    pub fn total(&self) -> f64 {
        self.terms.first().map_or(0.0, |t| t.1)
    }

    /// Adds `other`'s terms into these (same names in the same order; these may be empty).
    pub fn add(&mut self, other: &Losses) {
        if self.terms.is_empty() {
            self.terms = other.terms.clone();
        } else {
            for (a, b) in self.terms.iter_mut().zip(&other.terms) {
                a.1 += b.1;
            }
        }
    }
}

/// Seconds a model's forward and backward passes took.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PassSeconds {
    pub forward: f64,
    pub backward: f64,
    /// Host seconds from the start of each recording to its submission
    /// ([`velox_engine::Finished::host_seconds`]), summed.
    pub host: f64,
    /// A pass went untimed ([`PassTimer`] on a device without timestamps): the split is not
    /// reported.
    pub untimed: bool,
}

/// The GPU time of a micro-batch's forward and backward passes recorded as one recording (no
/// host wait between them), from timestamps: [`PassTimer::start`] before the forward pass,
/// [`PassTimer::backward`] between the two, [`PassTimer::end`] after the backward pass. On a
/// device without timestamps the split goes unreported (the trainer reports the passes' sum).
pub(crate) struct PassTimer([Option<usize>; 3]);

impl PassTimer {
    pub fn start(rec: &mut velox_engine::Recorder) -> PassTimer {
        PassTimer([rec.timestamp(), None, None])
    }

    pub fn backward(&mut self, rec: &mut velox_engine::Recorder) {
        self.0[1] = rec.timestamp();
    }

    pub fn end(&mut self, rec: &mut velox_engine::Recorder) {
        self.0[2] = rec.timestamp();
    }

    /// Adds the two passes' times in the submitted recording (`finished`) to `into`.
    pub fn add(&self, finished: &velox_engine::Finished, into: &mut PassSeconds) {
        let t = &finished.timestamps_ns;
        into.host += finished.host_seconds;
        match self.0 {
            [Some(a), Some(b), Some(c)] if c < t.len() => {
                into.forward += (t[b] - t[a]) / 1e9;
                into.backward += (t[c] - t[b]) / 1e9;
            }
            _ => into.untimed = true,
        }
    }
}

/// What the trainer reads from a model's config to optimise it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Optimisation {
    /// The peak of the Vaswani ("noam") schedule, reached after `warmup` steps.
    pub peak_lr: f64,
    pub warmup: u64,
    /// The global gradient norm the update clips to, if any.
    pub max_grad_norm: Option<f64>,
    pub adamw: AdamWConfig,
    /// Samples a micro-batch holds (the config's `batch`).
    pub batch: usize,
}

impl Optimisation {
    /// The scheduled learning rate of optimiser step `step` (counted from 1), before any
    /// cooldown the run adds.
    pub fn learning_rate(&self, step: u64) -> f64 {
        crate::schedule::noam(self.peak_lr, self.warmup, step)
    }
}

/// A model the trainer can train.
pub trait Trainable {
    /// One training sample (the autoencoder's: a scene).
    type Sample;

    /// The parameters, their gradients and the optimiser's moments.
    fn store(&self) -> &ParamStore;
    fn store_mut(&mut self) -> &mut ParamStore;

    /// What a checkpoint stores to rebuild the model: `{"model": kind, "config": ...}`.
    fn describe(&self) -> serde_json::Value;

    /// How the model is optimised: its config's learning rate schedule, clipping, AdamW and
    /// micro-batch.
    fn optimisation(&self) -> Optimisation;

    /// Records and runs the forward and backward passes of a micro-batch and adds `weight`
    /// times the gradient of the sum of its samples' losses into the store's gradients (which
    /// the trainer zeroed at the start of the step). `rngs` holds one generator per sample,
    /// drawn from the seed, the step and the sample's place in the step's batch, so a sample
    /// draws the same randomness whatever batch it is in. Returns the samples' loss terms
    /// summed, times `weight`. The pass's last recording should end with
    /// [`ParamStore::record_update`] (the step's update, where the trainer asked for it with
    /// this micro-batch), which saves the update a submission of its own.
    fn accumulate(&mut self, samples: &[&Self::Sample], rngs: &mut [Rng], weight: f64) -> Result<Losses>;

    /// The seconds the forward and the backward passes of the micro-batches accumulated since
    /// the last call took, for a model that measures them: the trainer then reports the two
    /// in its time split. `None` (the default): the trainer reports their sum as one compute
    /// figure.
    fn take_pass_seconds(&mut self) -> Option<PassSeconds> {
        None
    }

    /// Whether the micro-batch just run outgrew work the model sized ahead of counts the device
    /// made in the same recording (the autoencoder's tile lists, sized from earlier steps), and
    /// must run again: its losses and gradients are wrong and the update, where its recording
    /// held it, was vetoed on the device ([`ParamStore::veto_update_if_over`]). The model has
    /// grown the room; the trainer runs the whole step again with the same draws. Returns what
    /// outgrew what, for the log; taking it clears it. `None` (the default) for a model that
    /// sizes nothing ahead.
    fn take_rerun(&mut self) -> Option<String> {
        None
    }

    /// Whether [`Trainable::record_ahead`] can record the next micro-batch now, before the
    /// one on the device has finished. `false` (the default) for a model that has no such
    /// recording, or whose next recording depends on what the one running will tell (the
    /// autoencoder's first step sizes its tile lists by its counts).
    fn records_ahead(&self) -> bool {
        false
    }

    /// Records a micro-batch's passes as [`Trainable::accumulate`] would, in one recording
    /// (update included, where asked for), without submitting it: the trainer records a step
    /// while the step before runs, submits it once that step has finished, and then calls
    /// the returned finish with the recording's report. Called only where
    /// [`Trainable::records_ahead`] says so. The finish must leave unchanged whatever the next
    /// recording depends on, unless it asks for a rerun (the recording ahead is then made
    /// again).
    fn record_ahead(
        &mut self,
        _samples: &[&Self::Sample],
        _rngs: &mut [Rng],
        _weight: f64,
    ) -> Result<Ahead<Self>> {
        Err(velox_engine::Error::Invalid(format!(
            "{} records no pass ahead",
            self.describe()["model"].as_str().unwrap_or("this model")
        )))
    }
}

/// How a recorded pass ([`Trainable::record_ahead`]) is finished once it has run: it reads
/// the pass's results and returns its losses, as [`Trainable::accumulate`] does.
pub type Finish<M> = Box<dyn FnOnce(&mut M, &velox_engine::Finished) -> Result<Losses>>;

/// A micro-batch's passes recorded and not yet submitted ([`Trainable::record_ahead`]).
pub struct Ahead<M: ?Sized> {
    pub rec: velox_engine::Recorder,
    pub finish: Finish<M>,
}

impl<M: 'static> Ahead<M> {
    /// Submits the recording, waits for it and finishes it: [`Trainable::accumulate`] of a
    /// model that records ahead.
    pub fn run(self, model: &mut M) -> Result<Losses> {
        let finished = self.rec.submit()?;
        (self.finish)(model, &finished)
    }

    /// A pass whose one loss term (`loss`, one f32) comes back with its recording: finishing
    /// it adds the passes' times (`timer`) to the model's (`seconds`) and reads the loss,
    /// which must be finite.
    pub(crate) fn one_loss(
        rec: velox_engine::Recorder,
        timer: PassTimer,
        loss: velox_engine::Readback,
        seconds: fn(&mut M) -> &mut PassSeconds,
    ) -> Ahead<M> {
        let finish: Finish<M> = Box::new(move |model, finished| {
            timer.add(finished, seconds(model));
            let total = loss.read::<f32>()?[0] as f64;
            if !total.is_finite() {
                return Err(velox_engine::Error::Invalid(format!("the loss became non-finite ({total})")));
            }
            Ok(Losses { terms: vec![("total", total)] })
        });
        Ahead { rec, finish }
    }
}

/// Fails unless a micro-batch of `samples` scenes has one random generator each (and at
/// least one scene).
pub(crate) fn check_micro_batch(samples: usize, rngs: usize) -> velox_engine::Result<()> {
    if samples == 0 || samples != rngs {
        return Err(velox_engine::Error::Invalid(format!(
            "a micro-batch needs one generator per scene: {samples} scenes, {rngs} generators"
        )));
    }
    Ok(())
}

/// Implements [`Trainable`] for a Velox model: a struct with the fields `cfg` (its config,
/// holding `peak_lr`, `warmup`, `max_grad_norm` and `batch`), `store`, `adamw` and
/// `pass_seconds`, and inherent `accumulate` and `record_pass` (what
/// [`Trainable::record_ahead`] does; `accumulate` runs it: [`Ahead::run`]); its checkpoints
/// describe it as `{"model": MODEL_KIND, "config": cfg}` (the `MODEL_KIND` of the model's
/// module). The extra methods given after the sample type say at least
/// [`Trainable::records_ahead`].
macro_rules! trainable {
    ($model:ty, $sample:ty $(; $($more:tt)*)?) => {
        impl $crate::train::Trainable for $model {
            type Sample = $sample;

            fn store(&self) -> &$crate::params::ParamStore {
                &self.store
            }

            fn store_mut(&mut self) -> &mut $crate::params::ParamStore {
                &mut self.store
            }

            fn describe(&self) -> serde_json::Value {
                serde_json::json!({ "model": MODEL_KIND, "config": self.cfg })
            }

            fn optimisation(&self) -> $crate::train::Optimisation {
                $crate::train::Optimisation {
                    peak_lr: self.cfg.peak_lr,
                    warmup: self.cfg.warmup,
                    max_grad_norm: Some(self.cfg.max_grad_norm),
                    adamw: self.adamw,
                    batch: self.cfg.batch,
                }
            }

            fn accumulate(
                &mut self,
                samples: &[&$sample],
                rngs: &mut [velox_engine::rng::Rng],
                weight: f64,
            ) -> velox_engine::Result<$crate::train::Losses> {
                <$model>::accumulate(self, samples, rngs, weight)
            }

            fn record_ahead(
                &mut self,
                samples: &[&$sample],
                rngs: &mut [velox_engine::rng::Rng],
                weight: f64,
            ) -> velox_engine::Result<$crate::train::Ahead<Self>> {
                <$model>::record_pass(self, samples, rngs, weight)
            }

            fn take_pass_seconds(&mut self) -> Option<$crate::train::PassSeconds> {
                let p = std::mem::take(&mut self.pass_seconds);
                (!p.untimed).then_some(p)
            }

            $($($more)*)?
        }
    };
}
pub(crate) use trainable;

/// `check_encoder` for a model downstream of the encoder (a struct with `cfg`, whose
/// `encoder_hash` names the autoencoder of its tokens), and its [`crate::Model`] by
/// `crate::model::model!`. `$what` names it in messages.
macro_rules! token_model_files {
    ($model:ty, $config:ty, $what:literal) => {
        impl $model {
            /// Fails unless `autoencoder` (a checkpoint file) is the one whose tokens the model
            /// learned, when it recorded one.
            pub fn check_encoder(&self, autoencoder: &std::path::Path) -> velox_engine::Result<()> {
                $crate::velox::tokens::check_encoder(self.cfg.encoder_hash.as_deref(), autoencoder, $what)
            }
        }
        $crate::model::model!($model, $config, $what);
    };
}
pub(crate) use token_model_files;
