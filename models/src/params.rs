//! The parameter store: every parameter of a model in one f32 buffer, with a gradient buffer and
//! the AdamW moments `m` and `v` laid out the same way, so that zeroing the gradients, taking
//! their global norm and the AdamW step are one or two dispatches over flat buffers whatever the
//! number of tensors.
//!
//! Each parameter is a named [`Tensor::view`] at an offset aligned to the device's storage
//! offset alignment, so a layer binds its weights and gradients like any other tensor. Tensors
//! that get weight decay come first in the buffer and those that do not (norm gains, biases)
//! after them, so the AdamW kernel needs only the length of the decayed prefix.
//!
//! A model declares its parameters once, in its constructor, which takes them from a
//! [`Params`]: [`build`] runs the constructor twice, first declaring (each [`Params::param`]
//! registers a name, shape and initialisation and returns a stand-in of that shape; the model
//! made of stand-ins is dropped unused), then, once the store is built, binding (each call
//! returns the store's views, checked against the declared shape). So the names, shapes and
//! order are written in one place, and a model cannot ask for a parameter it did not declare.
//!
//! ```ignore
//! let (layer, store) = build(&gpu, seed, |p| {
//!     let w = p.param("enc.w", &[64, 32], Init::Xavier)?; // two or more dims: decayed
//!     let b = p.param("enc.b", &[32], Init::Zeros)?;      // one dim: not decayed
//!     Linear::new(w, Some(b))
//! })?;
//! ```
//!
//! Tests: `tests/training/train_primitives.rs` (the store's layout, steps and norms),
//! `tests/models/slips.rs` (every model's weight-decay layout) and `tests/data/fuzz.rs`.

use std::collections::HashMap;

use velox_engine::ops::adamw::{adamw, AdamWConfig, AdamWStep, AdamWTensors};
use velox_engine::ops::cast::cast_into;
use velox_engine::ops::fill::fill;
use velox_engine::ops::norm::{check_finite_values, chunk_len, global_norm_into, veto_if_over, NormScratch};
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Gpu, Precision, Readback, Recorder, Result, Tensor};

use crate::layers::Param;
use velox_engine::Limit;

/// How a parameter starts. Random rules draw from [`Rng`] seeded by the store's seed and the
/// parameter's name, so a parameter's initial values do not depend on which others exist.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Init {
    Zeros,
    Ones,
    Constant(f32),
    /// Normal with mean 0 and this standard deviation.
    Normal {
        std: f64,
    },
    /// Uniform in [lo, hi).
    Uniform {
        lo: f64,
        hi: f64,
    },
    /// Glorot and Bengio's rule for linear weights: uniform in [-a, a) with
    /// a = sqrt(6 / (fan_in + fan_out)), where fan_in + fan_out is the sum of the last two
    /// dimensions (a [.., rows, cols] tensor is a stack of rows x cols matrices; the sum is the
    /// same whichever way round the weight is stored). A 1-D tensor of length n counts as an
    /// n-input, one-output map (n + 1).
    Xavier,
    /// He et al.'s rule for weights followed by a ReLU-like activation: normal with std
    /// sqrt(2 / fan_in). The fan-in is given because only the layer knows which dimension is
    /// its input.
    Kaiming {
        fan_in: usize,
    },
}

impl Init {
    fn fill(self, out: &mut [f32], shape: &[usize], rng: &mut Rng) {
        match self {
            Init::Zeros => out.fill(0.0),
            Init::Ones => out.fill(1.0),
            Init::Constant(c) => out.fill(c),
            Init::Normal { std } => out.iter_mut().for_each(|x| *x = (rng.normal() * std) as f32),
            Init::Uniform { lo, hi } => out.iter_mut().for_each(|x| *x = rng.range(lo, hi) as f32),
            Init::Xavier => {
                let fans = match shape {
                    [] => 2,
                    [n] => n + 1,
                    [.., r, c] => r + c,
                };
                let a = (6.0 / fans.max(1) as f64).sqrt();
                out.iter_mut().for_each(|x| *x = rng.range(-a, a) as f32);
            }
            Init::Kaiming { fan_in } => {
                let std = (2.0 / fan_in.max(1) as f64).sqrt();
                out.iter_mut().for_each(|x| *x = (rng.normal() * std) as f32);
            }
        }
    }

    fn check(self, name: &str) -> Result<()> {
        let bad = match self {
            Init::Normal { std } => !(std.is_finite() && std >= 0.0),
            Init::Uniform { lo, hi } => !(lo.is_finite() && hi.is_finite() && lo <= hi),
            Init::Constant(c) => !c.is_finite(),
            Init::Kaiming { fan_in } => fan_in == 0,
            _ => false,
        };
        if bad {
            return Err(Error::Invalid(format!("parameter {name:?}: bad initialisation {self:?}")));
        }
        Ok(())
    }
}

/// One registered parameter: where it lives in the flat buffers and how it started.
#[derive(Clone, Debug)]
pub struct ParamInfo {
    pub name: String,
    pub shape: Vec<usize>,
    /// Element offset in the flat buffers (a multiple of the view alignment).
    pub offset: usize,
    pub numel: usize,
    pub decay: bool,
    pub init: Init,
}

/// Collects parameters before the flat buffers are sized and allocated.
#[derive(Default)]
pub struct ParamBuilder {
    specs: Vec<ParamInfo>,
    index: HashMap<String, usize>,
}

impl ParamBuilder {
    /// Registers a parameter. Tensors of two or more dimensions (weight matrices, embeddings)
    /// get weight decay; vectors and scalars (norm gains, biases) do not. Use
    /// [`ParamBuilder::add_with_decay`] to choose.
    pub fn add(&mut self, name: &str, shape: &[usize], init: Init) -> Result<()> {
        self.add_with_decay(name, shape, init, shape.len() >= 2)
    }

    /// Registers a parameter with an explicit weight decay choice.
    pub fn add_with_decay(&mut self, name: &str, shape: &[usize], init: Init, decay: bool) -> Result<()> {
        if name.is_empty() {
            return Err(Error::Invalid("a parameter needs a name".into()));
        }
        if self.index.contains_key(name) {
            return Err(Error::Invalid(format!("parameter {name:?} is registered twice")));
        }
        init.check(name)?;
        let numel = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(|| {
            Error::too_large(Limit::Memory, format!("parameter {name:?} of shape {shape:?}"))
        })?;
        self.index.insert(name.to_string(), self.specs.len());
        self.specs.push(ParamInfo {
            name: name.to_string(),
            shape: shape.to_vec(),
            offset: 0,
            numel,
            decay,
            init,
        });
        Ok(())
    }

    /// The parameters registered so far, in order (offsets are set by [`ParamBuilder::build`]).
    pub fn infos(&self) -> &[ParamInfo] {
        &self.specs
    }

    /// Values of every parameter registered so far (nothing is allocated).
    pub fn num_parameters(&self) -> usize {
        self.specs.iter().map(|p| p.numel).sum()
    }

    /// Values of the parameters registered so far whose names start with `prefix`.
    pub fn num_parameters_under(&self, prefix: &str) -> usize {
        self.specs.iter().filter(|p| p.name.starts_with(prefix)).map(|p| p.numel).sum()
    }

    /// Allocates the flat buffers on `gpu` and initialises the parameters on the host with
    /// `seed`; gradients and moments start at zero and the step counter at 0.
    pub fn build(self, gpu: &Gpu, seed: u64) -> Result<ParamStore> {
        let ParamBuilder { mut specs, index } = self;
        let align = chunk_align(gpu);
        // Decayed tensors first, each group in registration order.
        let mut order: Vec<usize> = (0..specs.len()).collect();
        order.sort_by_key(|&i| !specs[i].decay);
        let mut end = 0usize;
        let mut decay_len = 0usize;
        for &i in &order {
            let start = end.next_multiple_of(align);
            specs[i].offset = start;
            end = start.checked_add(specs[i].numel).ok_or_else(|| {
                Error::too_large(Limit::Memory, format!("parameters past {start} elements"))
            })?;
            if specs[i].decay {
                decay_len = end;
            }
        }
        let total = end;
        let mut host = vec![0f32; total];
        for s in &specs {
            let mut rng = Rng::new(seed ^ name_hash(&s.name));
            s.init.fill(&mut host[s.offset..s.offset + s.numel], &s.shape, &mut rng);
        }
        let params = Tensor::from_slice(gpu, &[total], &host)?;
        drop(host);
        let grads = Tensor::empty(gpu, &[total], DType::F32)?;
        let m = Tensor::empty(gpu, &[total], DType::F32)?;
        let v = Tensor::empty(gpu, &[total], DType::F32)?;
        let mut rec = gpu.recorder()?;
        for t in [&grads, &m, &v] {
            fill_flat(&mut rec, t, 0.0)?;
        }
        rec.submit()?;
        let views = specs
            .iter()
            .map(|s| Ok((params.view(s.offset, &s.shape)?, grads.view(s.offset, &s.shape)?)))
            .collect::<Result<Vec<_>>>()?;
        let half = Tensor::empty(gpu, &[total], DType::F16)?;
        let half_views = specs.iter().map(|s| half.view(s.offset, &s.shape)).collect::<Result<Vec<_>>>()?;
        let norm = NormScratch::new(gpu, total)?;
        let store = ParamStore {
            specs,
            index,
            views,
            params,
            grads,
            m,
            v,
            decay_len,
            norm,
            norm_read: None,
            step: 0,
            half,
            half_views,
            training: Precision::F32,
            loss_scale: LossScale::default(),
            zero_pending: std::sync::atomic::AtomicBool::new(false),
            update_pending: None,
            update_recorded: false,
            vetoes: Vec::new(),
        };
        let mut rec = gpu.recorder()?;
        store.sync_half(&mut rec)?;
        rec.submit()?;
        Ok(store)
    }
}

/// Where a model's constructor takes its parameters from: a pass that declares them or one that
/// binds a built store's (see the module docs and [`build`]).
pub struct Params<'a> {
    mode: Mode<'a>,
}

enum Mode<'a> {
    Declare { builder: ParamBuilder, gpu: Gpu, scratch: Option<(Tensor, Tensor)> },
    Bind(&'a ParamStore),
}

impl Params<'static> {
    /// A declaring pass: parameters are registered, and stand-ins handed out. A stand-in is a
    /// view of one scratch buffer as large as the largest parameter so far (f32, and f16 for
    /// the half copy); the model built of them is only for dropping.
    pub fn declaring(gpu: &Gpu) -> Params<'static> {
        Params { mode: Mode::Declare { builder: ParamBuilder::default(), gpu: gpu.clone(), scratch: None } }
    }
}

impl<'a> Params<'a> {
    /// A binding pass over a built store.
    pub fn binding(store: &'a ParamStore) -> Params<'a> {
        Params { mode: Mode::Bind(store) }
    }

    /// The device the model lives on.
    pub fn gpu(&self) -> &Gpu {
        match &self.mode {
            Mode::Declare { gpu, .. } => gpu,
            Mode::Bind(store) => store.params.gpu(),
        }
    }

    /// The parameter `name` of `shape`, initialised by `init`; decayed when it has two or more
    /// dimensions (see [`ParamBuilder::add`]).
    pub fn param(&mut self, name: &str, shape: &[usize], init: Init) -> Result<Param> {
        self.param_with_decay(name, shape, init, shape.len() >= 2)
    }

    /// [`Params::param`] with an explicit weight decay choice.
    pub fn param_with_decay(
        &mut self,
        name: &str,
        shape: &[usize],
        init: Init,
        decay: bool,
    ) -> Result<Param> {
        match &mut self.mode {
            Mode::Declare { builder, gpu, scratch } => {
                builder.add_with_decay(name, shape, init, decay)?;
                let numel = builder.specs.last().map_or(0, |s| s.numel);
                if scratch.as_ref().is_none_or(|(v, _)| v.numel() < numel) {
                    let n = numel.max(1);
                    *scratch =
                        Some((Tensor::empty(gpu, &[n], DType::F32)?, Tensor::empty(gpu, &[n], DType::F16)?));
                }
                let (value, half) = scratch.as_ref().expect("the scratch was just made");
                let p = Param::from_tensors(value.view(0, shape)?, value.view(0, shape)?)?;
                Ok(Param { half: Some(half.view(0, shape)?), ..p })
            }
            Mode::Bind(store) => {
                let info = &store.specs[store.find(name)?];
                if info.shape != shape || info.decay != decay {
                    return Err(Error::Shape(format!(
                        "parameter {name:?} is bound as {shape:?} (decay {decay}) but was declared as {:?} \
                         (decay {})",
                        info.shape, info.decay
                    )));
                }
                Param::from_store(store, name)
            }
        }
    }

    /// The parameters `names`, all of one shape, as one stacked parameter where they lie one
    /// after another in the store ([`ParamStore::stacked`]); `None` while declaring.
    pub fn stacked<S: AsRef<str>>(&self, names: &[S]) -> Result<Option<Param>> {
        match &self.mode {
            Mode::Declare { .. } => Ok(None),
            Mode::Bind(store) => store.stacked(names),
        }
    }

    /// The declarations of a declaring pass.
    pub fn into_builder(self) -> Result<ParamBuilder> {
        match self.mode {
            Mode::Declare { builder, .. } => Ok(builder),
            Mode::Bind(_) => Err(Error::Invalid("a binding pass declares nothing".into())),
        }
    }
}

/// The parameters `make` declares (by running it over a declaring [`Params`]), without
/// allocating them: for counts and layouts.
pub fn declare<T>(gpu: &Gpu, make: impl FnOnce(&mut Params) -> Result<T>) -> Result<ParamBuilder> {
    let mut p = Params::declaring(gpu);
    drop(make(&mut p)?);
    p.into_builder()
}

/// A model and its store: `make` declares the parameters, the store is built and initialised
/// with `seed`, and `make` runs again over the store to bind them.
pub fn build<T>(
    gpu: &Gpu,
    seed: u64,
    mut make: impl FnMut(&mut Params) -> Result<T>,
) -> Result<(T, ParamStore)> {
    let store = declare(gpu, &mut make)?.build(gpu, seed)?;
    let model = make(&mut Params::binding(&store))?;
    Ok((model, store))
}

/// Every parameter of a model in one buffer, with gradients and AdamW moments alongside.
pub struct ParamStore {
    specs: Vec<ParamInfo>,
    index: HashMap<String, usize>,
    views: Vec<(Tensor, Tensor)>,
    params: Tensor,
    grads: Tensor,
    m: Tensor,
    v: Tensor,
    decay_len: usize,
    norm: NormScratch,
    /// The norm's result as the last recording of [`ParamStore::record_grad_norm`] reads it
    /// back (with that recording: no copy and wait of its own on a GPU).
    norm_read: Option<Readback>,
    step: u64,
    /// An f16 copy of `params` at the same offsets, for the f16 inference path; it follows
    /// `params` only through [`ParamStore::sync_half`].
    half: Tensor,
    half_views: Vec<Tensor>,
    /// The precision of the training passes ([`ParamStore::recorder`]); f16 reads the f16
    /// copies, which the trainer refreshes after every step.
    training: Precision,
    /// The loss scale of f16 training.
    loss_scale: LossScale,
    /// Set by [`ParamStore::zero_grads_first`]: the next [`ParamStore::recorder`] records the
    /// zeroing of the gradients first.
    zero_pending: std::sync::atomic::AtomicBool,
    /// The optimiser step the step's last pass records at its end ([`ParamStore::update_last`]),
    /// and whether it has been recorded.
    update_pending: Option<Update>,
    update_recorded: bool,
    /// Counts made on the device this step, each with the limit it must stay within for the
    /// next recorded update to go ahead ([`ParamStore::veto_update_if_over`]).
    vetoes: Vec<(Tensor, u32)>,
}

/// What a recorded pass leaves in the store for the host to read once it has run, and the
/// step counter it advanced: taken out while another pass is recorded ahead of it
/// ([`ParamStore::take_pass_state`]), and put back to finish it.
pub struct PassState {
    zero_pending: bool,
    update_pending: Option<Update>,
    update_recorded: bool,
    vetoes: Vec<(Tensor, u32)>,
    norm_read: Option<Readback>,
    step: u64,
}

/// An AdamW step over the whole store, as [`ParamStore::adamw_step_scaled`] records it, then
/// the f16 copies refreshed from the updated masters where the passes read them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Update {
    pub adamw: AdamWConfig,
    pub lr: f64,
    pub max_norm: Option<f64>,
    pub loss_scale: f64,
    pub sync_half: bool,
}

/// Dynamic loss scaling for f16 training (Micikevicius et al., "Mixed Precision Training"):
/// the loss, and so every gradient, is multiplied by `scale` so that small gradients survive
/// the rounding to f16 (whose smallest normal is 6.1e-5); the optimiser divides it out. A step
/// whose gradients overflow (NaN or Inf) is skipped and redone at half the scale; after
/// [`LossScale::GROWTH_INTERVAL`] good steps in a row the scale doubles. Powers of two only, so
/// scaling is exact wherever it neither overflows nor underflows.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossScale {
    pub scale: f64,
    /// Good steps since the scale last changed.
    pub good_steps: u64,
}

impl Default for LossScale {
    fn default() -> Self {
        LossScale { scale: LossScale::INITIAL, good_steps: 0 }
    }
}

impl LossScale {
    /// 2^16, as PyTorch's gradient scaler starts.
    pub const INITIAL: f64 = 65536.0;
    pub const GROWTH_INTERVAL: u64 = 1000;
    /// 2^24: a scale past this gains nothing (f16's range spans 2^-24 to 2^16).
    pub const MAX: f64 = 16_777_216.0;
    /// 2^-24: gradients that overflow f16 even at this scale are broken, not small.
    pub const MIN: f64 = 1.0 / 16_777_216.0;

    /// Whether this is a scale training can have: a power of two from [`LossScale::MIN`] to
    /// [`LossScale::MAX`].
    pub fn valid(&self) -> bool {
        let s = self.scale;
        s.is_finite() && (LossScale::MIN..=LossScale::MAX).contains(&s) && s.log2().fract() == 0.0
    }

    /// After a step whose gradients overflowed: halves the scale; fails below [`LossScale::MIN`].
    pub fn overflowed(&mut self) -> Result<()> {
        if self.scale / 2.0 < LossScale::MIN {
            return Err(Error::Invalid(format!(
                "the gradients are NaN or Inf even with the loss scaled by {:e}: not an f16 overflow",
                self.scale
            )));
        }
        *self = LossScale { scale: self.scale / 2.0, good_steps: 0 };
        Ok(())
    }

    /// After a good step: counts it, and doubles the scale after a run of them.
    pub fn good(&mut self) {
        self.good_steps += 1;
        if self.good_steps >= LossScale::GROWTH_INTERVAL && self.scale * 2.0 <= LossScale::MAX {
            *self = LossScale { scale: self.scale * 2.0, good_steps: 0 };
        }
    }
}

impl ParamStore {
    pub fn builder() -> ParamBuilder {
        ParamBuilder::default()
    }

    /// The parameter called `name`.
    pub fn param(&self, name: &str) -> Result<&Tensor> {
        Ok(&self.views[self.find(name)?].0)
    }

    /// The f16 copy of the parameter called `name` (as of the last [`ParamStore::sync_half`]).
    pub fn param_half(&self, name: &str) -> Result<&Tensor> {
        Ok(&self.half_views[self.find(name)?])
    }

    /// Records the rounding of every parameter to its f16 copy: one pass over the store. The
    /// f16 path reads those copies, so call this after the parameters change (a checkpoint
    /// loaded, a training step) and before an f16 forward pass.
    pub fn sync_half(&self, rec: &mut Recorder) -> Result<()> {
        let n = self.params.numel();
        let align = chunk_align(rec.gpu());
        let chunk = (chunk_len(rec.gpu()) / align * align).max(align);
        for start in (0..n).step_by(chunk) {
            let len = chunk.min(n - start);
            cast_into(rec, &self.params.view(start, &[len])?, &self.half.view(start, &[len])?)?;
        }
        Ok(())
    }

    /// The precision of training passes.
    pub fn training_precision(&self) -> Precision {
        self.training
    }

    /// Sets the precision of training passes; for f16, rounds the parameters to their f16
    /// copies now (in a recording of its own).
    pub fn set_training_precision(&mut self, precision: Precision) -> Result<()> {
        if precision == Precision::F16 {
            let mut rec = self.params.gpu().recorder()?;
            self.sync_half(&mut rec)?;
            rec.submit()?;
        }
        self.training = precision;
        Ok(())
    }

    /// A recorder for a training pass: in the training precision, so that the layers' products
    /// read f16 operands in f16 training.
    pub fn recorder(&self) -> Result<Recorder> {
        let mut rec = self.params.gpu().recorder()?;
        rec.set_precision(self.training);
        if self.zero_pending.swap(false, std::sync::atomic::Ordering::Relaxed) {
            self.zero_grads(&mut rec)?;
        }
        Ok(rec)
    }

    /// Has the next training recording ([`ParamStore::recorder`]) zero the gradients before
    /// anything else it records: a step's first pass then needs no submit of its own for it.
    /// Every model's passes start from that recorder; [`ParamStore::settle_zero`] zeroes them
    /// at once where none was made (a step that ran no micro-batch).
    pub fn zero_grads_first(&mut self) {
        self.zero_pending.store(true, std::sync::atomic::Ordering::Relaxed);
        self.vetoes.clear();
    }

    /// Has the next recorded update skipped on the device when `count[0]` (u32, made by the
    /// step's recordings) exceeds `limit`: for a pass that sized work ahead of a count it
    /// records with the update, and learns the count only after the submission. A vetoed
    /// step leaves the parameters, the moments and the step counter as they were (its
    /// [`ParamStore::grad_norm`] fails, as for an overflow); the caller runs it again.
    pub fn veto_update_if_over(&mut self, count: &Tensor, limit: u32) {
        self.vetoes.push((count.clone(), limit));
    }

    /// Asks the step's last pass to record `update` at the end of its recording
    /// ([`ParamStore::record_update`]), so that the update needs no submission of its own: one
    /// host wait a step fewer. The trainer asks where nothing comes between the last pass and
    /// the update (one process, the last micro-batch); it records the update itself when the
    /// pass did not ([`ParamStore::take_update`]).
    pub fn update_last(&mut self, update: Update) {
        self.update_pending = Some(update);
        self.update_recorded = false;
    }

    /// Records the update [`ParamStore::update_last`] asked for, if any: a model's training
    /// pass calls it at the end of its last recording, after the gradients are complete.
    pub fn record_update(&mut self, rec: &mut Recorder) -> Result<()> {
        if let Some(u) = self.update_pending.take() {
            self.record(rec, &u)?;
            self.update_recorded = true;
        }
        Ok(())
    }

    /// Records `u` into `rec`.
    pub fn record(&mut self, rec: &mut Recorder, u: &Update) -> Result<()> {
        self.adamw_step_scaled(rec, &u.adamw, u.lr, u.max_norm, u.loss_scale)?;
        if u.sync_half {
            self.sync_half(rec)?;
        }
        Ok(())
    }

    /// Whether the last pass recorded the update asked for (it has then been submitted with
    /// that pass); either way nothing is left asked for.
    pub fn take_update(&mut self) -> bool {
        self.update_pending = None;
        std::mem::take(&mut self.update_recorded)
    }

    /// Takes out what the passes recorded since the step began have left for their finish
    /// (and what they have yet to record: the zeroing, the update, the vetoes), leaving the
    /// store as at a step's start with nothing asked for: the trainer records the next step's
    /// pass while this one runs, then puts each state back to finish its pass
    /// ([`ParamStore::restore_pass_state`]). The step counter stays as it is.
    pub fn take_pass_state(&mut self) -> PassState {
        PassState {
            zero_pending: self.zero_pending.swap(false, std::sync::atomic::Ordering::Relaxed),
            update_pending: self.update_pending.take(),
            update_recorded: std::mem::take(&mut self.update_recorded),
            vetoes: std::mem::take(&mut self.vetoes),
            norm_read: self.norm_read.take(),
            step: self.step,
        }
    }

    /// Puts back a state [`ParamStore::take_pass_state`] took, step counter included.
    pub fn restore_pass_state(&mut self, state: PassState) {
        self.zero_pending.store(state.zero_pending, std::sync::atomic::Ordering::Relaxed);
        self.update_pending = state.update_pending;
        self.update_recorded = state.update_recorded;
        self.vetoes = state.vetoes;
        self.norm_read = state.norm_read;
        self.step = state.step;
    }

    /// Zeroes the gradients now if [`ParamStore::zero_grads_first`] asked for it and no
    /// recorder has done it since.
    pub fn settle_zero(&self) -> Result<()> {
        if self.zero_pending.swap(false, std::sync::atomic::Ordering::Relaxed) {
            let mut rec = self.params.gpu().recorder()?;
            self.zero_grads(&mut rec)?;
            rec.submit()?;
        }
        Ok(())
    }

    /// The loss scale of f16 training (its state; f32 training does not use it).
    pub fn loss_scale(&self) -> LossScale {
        self.loss_scale
    }

    pub fn loss_scale_mut(&mut self) -> &mut LossScale {
        &mut self.loss_scale
    }

    /// The parameters `names`, all of one shape `S`, as one parameter `[names.len(), S..]`
    /// (views of the value, gradient and f16 buffers) when they lie one after another in the
    /// buffers; `None` when they do not (padding between them).
    pub fn stacked<S: AsRef<str>>(&self, names: &[S]) -> Result<Option<crate::layers::Param>> {
        let infos = names
            .iter()
            .map(|n| self.find(n.as_ref()).map(|i| &self.specs[i]))
            .collect::<Result<Vec<_>>>()?;
        let Some(first) = infos.first() else {
            return Err(Error::Invalid("a stack of no parameters".into()));
        };
        if infos.iter().any(|i| i.shape != first.shape) {
            let names: Vec<&str> = names.iter().map(AsRef::as_ref).collect();
            return Err(Error::Invalid(format!("parameters {names:?} differ in shape: they do not stack")));
        }
        let consecutive = infos.windows(2).all(|w| w[1].offset == w[0].offset + w[0].numel);
        if !consecutive {
            return Ok(None);
        }
        let shape: Vec<usize> = std::iter::once(infos.len()).chain(first.shape.iter().copied()).collect();
        let value = self.params.view(first.offset, &shape)?;
        let p = crate::layers::Param::from_tensors(value, self.grads.view(first.offset, &shape)?)?;
        Ok(Some(crate::layers::Param { half: Some(self.half.view(first.offset, &shape)?), ..p }))
    }

    /// The gradient of the parameter called `name` (same shape, in the flat gradient buffer).
    pub fn grad(&self, name: &str) -> Result<&Tensor> {
        Ok(&self.views[self.find(name)?].1)
    }

    fn find(&self, name: &str) -> Result<usize> {
        self.index.get(name).copied().ok_or_else(|| {
            Error::Invalid(format!("no parameter called {name:?} (the store has {})", self.specs.len()))
        })
    }

    /// (name, parameter, gradient) in registration order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Tensor, &Tensor)> {
        self.specs.iter().zip(&self.views).map(|(s, (p, g))| (s.name.as_str(), p, g))
    }

    /// Where each parameter lives, in registration order.
    pub fn infos(&self) -> &[ParamInfo] {
        &self.specs
    }

    /// Number of parameter tensors.
    pub fn len(&self) -> usize {
        self.specs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.specs.is_empty()
    }

    /// Number of scalar parameters (without alignment padding).
    pub fn num_parameters(&self) -> usize {
        self.specs.iter().map(|s| s.numel).sum()
    }

    /// The flat buffers, `[total]` with padding between tensors (always zero in all four).
    pub fn flat_params(&self) -> &Tensor {
        &self.params
    }
    pub fn flat_grads(&self) -> &Tensor {
        &self.grads
    }
    /// AdamW's first and second moments.
    pub fn moments(&self) -> (&Tensor, &Tensor) {
        (&self.m, &self.v)
    }

    /// Elements `[0, decay_len)` of the flat buffers get weight decay.
    pub fn decay_len(&self) -> usize {
        self.decay_len
    }

    /// AdamW steps taken (0 before the first).
    pub fn step(&self) -> u64 {
        self.step
    }

    pub fn set_step(&mut self, step: u64) {
        self.step = step;
    }

    /// Overwrites one parameter from the host.
    pub fn write_param(&self, name: &str, data: &[f32]) -> Result<()> {
        self.param(name)?.write(data)
    }

    /// Records zeroing every gradient.
    pub fn zero_grads(&self, rec: &mut Recorder) -> Result<()> {
        fill_flat(rec, &self.grads, 0.0)
    }

    /// Records the global norm of all gradients; [`ParamStore::grad_norm`] reads it after submit.
    /// The vetoes asked for ([`ParamStore::veto_update_if_over`]) are recorded onto it before
    /// it is read back, so that the host reads the norm the update saw.
    pub fn record_grad_norm(&mut self, rec: &mut Recorder) -> Result<()> {
        global_norm_into(rec, &self.grads, &self.norm)?;
        for (count, limit) in std::mem::take(&mut self.vetoes) {
            veto_if_over(rec, &count, limit, self.norm.result())?;
        }
        self.norm_read = Some(rec.read_back(self.norm.result())?);
        Ok(())
    }

    /// Records one AdamW step over every parameter: the global gradient norm, then the fused
    /// update, clipped to `max_norm` when given. Advances the step counter; after submit, call
    /// [`ParamStore::grad_norm`] to log the norm and to catch NaN or Inf.
    pub fn adamw_step(
        &mut self,
        rec: &mut Recorder,
        cfg: &AdamWConfig,
        lr: f64,
        max_norm: Option<f64>,
    ) -> Result<()> {
        self.adamw_step_scaled(rec, cfg, lr, max_norm, 1.0)
    }

    /// [`ParamStore::adamw_step`] on gradients that hold `loss_scale` times the true ones (the
    /// gradients of a scaled loss): the update divides it out, clipping included.
    pub fn adamw_step_scaled(
        &mut self,
        rec: &mut Recorder,
        cfg: &AdamWConfig,
        lr: f64,
        max_norm: Option<f64>,
        loss_scale: f64,
    ) -> Result<()> {
        if !(loss_scale.is_finite() && loss_scale > 0.0) {
            return Err(Error::Invalid(format!("adamw: loss scale {loss_scale} is not a positive number")));
        }
        self.record_grad_norm(rec)?;
        let tensors = AdamWTensors {
            params: &self.params,
            grads: &self.grads,
            m: &self.m,
            v: &self.v,
            decay_len: self.decay_len,
            norm: Some(self.norm.result()),
        };
        let step = AdamWStep { lr, step: self.step + 1, grad_scale: 1.0 / loss_scale, max_norm };
        adamw(rec, &tensors, cfg, &step)?;
        self.step += 1;
        Ok(())
    }

    /// The global gradient norm recorded last (after the recording was submitted). A NaN or Inf
    /// norm means the gradients hold NaN or Inf: the AdamW kernel then left everything as it
    /// was, so the step counter goes back by one and the error says what happened.
    pub fn grad_norm(&mut self) -> Result<f32> {
        let values = match &self.norm_read {
            Some(read) => read.read::<f32>()?,
            None => self.norm.result().read::<f32>()?,
        };
        match check_finite_values(&values, "gradients") {
            Ok(n) => Ok(n),
            Err(e) => {
                self.step = self.step.saturating_sub(1);
                Err(e)
            }
        }
    }
}

/// Element multiple at which views may start on `gpu`, both the f32 views of the parameters
/// and the f16 views of their copies (hence half the alignment in bytes, at least 2: the f16
/// kernels read whole 32-bit words).
fn chunk_align(gpu: &Gpu) -> usize {
    (gpu.caps().min_storage_buffer_offset_alignment.max(4) as usize).div_ceil(2)
}

/// Fills a flat f32 buffer that may be larger than one storage binding.
fn fill_flat(rec: &mut Recorder, t: &Tensor, value: f64) -> Result<()> {
    let n = t.numel();
    let chunk = chunk_len(t.gpu());
    let flat = t.reshape(&[n])?;
    for start in (0..n).step_by(chunk) {
        fill(rec, &flat.view(start, &[chunk.min(n - start)])?, value)?;
    }
    Ok(())
}

/// FNV-1a: mixes a parameter's name into the store's seed.
fn name_hash(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_loss_scale_halves_on_overflow_and_doubles_after_a_run_of_good_steps() {
        let mut s = LossScale::default();
        assert!(s.valid() && s.scale == 65536.0);
        for _ in 0..LossScale::GROWTH_INTERVAL - 1 {
            s.good();
        }
        assert_eq!(s, LossScale { scale: 65536.0, good_steps: LossScale::GROWTH_INTERVAL - 1 });
        s.good();
        assert_eq!(s, LossScale { scale: 131072.0, good_steps: 0 });
        s.good();
        s.overflowed().unwrap();
        assert_eq!(s, LossScale { scale: 65536.0, good_steps: 0 });
        // Never past the largest scale, never below the smallest.
        let mut top = LossScale { scale: LossScale::MAX, good_steps: 0 };
        (0..LossScale::GROWTH_INTERVAL).for_each(|_| top.good());
        assert_eq!(top.scale, LossScale::MAX);
        let mut bottom = LossScale { scale: LossScale::MIN, good_steps: 0 };
        assert!(bottom.overflowed().unwrap_err().to_string().contains("not an f16 overflow"));
        for bad in [0.0, 3.0, f64::INFINITY, f64::NAN, LossScale::MAX * 2.0, -2.0] {
            assert!(!LossScale { scale: bad, good_steps: 0 }.valid(), "{bad}");
        }
    }

    #[test]
    fn init_rules_have_the_documented_spread() {
        let mut rng = Rng::new(7);
        let mut w = vec![0f32; 200 * 300];
        Init::Xavier.fill(&mut w, &[200, 300], &mut rng);
        let a = (6.0f64 / 500.0).sqrt();
        assert!(w.iter().all(|&x| (x as f64).abs() <= a));
        let var = w.iter().map(|&x| x as f64 * x as f64).sum::<f64>() / w.len() as f64;
        assert!((var / (a * a / 3.0) - 1.0).abs() < 0.03, "xavier variance {var}");
        Init::Kaiming { fan_in: 300 }.fill(&mut w, &[200, 300], &mut rng);
        let var = w.iter().map(|&x| x as f64 * x as f64).sum::<f64>() / w.len() as f64;
        assert!((var / (2.0 / 300.0) - 1.0).abs() < 0.03, "kaiming variance {var}");
        let mut u = vec![0f32; 1000];
        Init::Uniform { lo: -2.0, hi: 3.0 }.fill(&mut u, &[1000], &mut rng);
        assert!(u.iter().all(|&x| (-2.0..3.0).contains(&x)));
    }

    #[test]
    fn registration_errors_name_the_problem() {
        let mut b = ParamStore::builder();
        b.add("w", &[2, 3], Init::Xavier).unwrap();
        assert!(b.add("w", &[2], Init::Zeros).unwrap_err().to_string().contains("twice"));
        assert!(b.add("", &[2], Init::Zeros).is_err());
        assert!(b.add("s", &[2], Init::Normal { std: -1.0 }).unwrap_err().to_string().contains("\"s\""));
    }

    #[test]
    fn name_hash_separates_names() {
        assert_ne!(name_hash("a.w"), name_hash("a.b"));
    }
}
