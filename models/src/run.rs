//! The settings of a training run that decide what it computes, beside the model's config:
//! the seed, the length, the batch, the scenes and their order, the learning-rate cooldown.
//! Every checkpoint of the run stores them, so a resumed run takes them from there and repeats
//! the uninterrupted run step for step, whatever the command line of the resumption says.
//!
//! Tests: `tests/training/trainer.rs` and `tests/training/mixed_precision.rs`.

use std::path::Path;

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Precision, Result};

/// What a checkpoint stores of its run (in its config JSON, under `"run"`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunSettings {
    /// Seed of the parameters, of the scene order and of every random draw.
    pub seed: u64,
    /// Total optimiser steps of the run.
    pub steps: u64,
    /// Steps on the same samples before the next ones (see `crate::train::order`).
    pub steps_per_scene: u64,
    /// Steps over which the learning rate comes down at the end of the run (0: none).
    pub cooldown: u64,
    /// Samples per optimiser step, over every micro-batch of every process: the model's
    /// micro-batch times `accumulate` times the processes. A resumed run keeps it. (Runs that
    /// predate the field trained on one sample a step.)
    #[serde(default = "one")]
    pub global_batch: u64,
    /// Micro-batches each process accumulates per step.
    #[serde(default = "one")]
    pub accumulate: u64,
    /// The dataset's scene folders (their names, in name order), which the scene order indexes.
    pub scenes: Vec<String>,
    /// The precision of the products in the training passes: f32, or f16 operands with f32
    /// accumulation, f32 master weights and a dynamic loss scale (runs that predate the field
    /// trained in f32).
    #[serde(default = "f32_precision", with = "precision_name")]
    pub precision: Precision,
}

fn f32_precision() -> Precision {
    Precision::F32
}

/// `Precision` as its name ("f32", "f16") in JSON and metadata.
pub(crate) mod precision_name {
    use serde::{Deserialize, Deserializer, Serializer};
    use velox_engine::Precision;

    pub fn parse(s: &str) -> Option<Precision> {
        [Precision::F32, Precision::F16].into_iter().find(|p| p.name() == s)
    }

    pub fn serialize<S: Serializer>(p: &Precision, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(p.name())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Precision, D::Error> {
        let s = String::deserialize(d)?;
        parse(&s).ok_or_else(|| serde::de::Error::custom(format!("precision {s:?} is not f32 or f16")))
    }
}

/// The settings a command line asks for; `None` where it leaves one out.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RunRequest {
    pub seed: Option<u64>,
    pub steps: Option<u64>,
    pub steps_per_scene: Option<u64>,
    pub cooldown: Option<u64>,
    pub accumulate: Option<u64>,
    pub precision: Option<Precision>,
}

fn one() -> u64 {
    1
}

impl RunSettings {
    pub const DEFAULT_SEED: u64 = 0;
    pub const DEFAULT_STEPS: u64 = 2000;
    pub const DEFAULT_STEPS_PER_SCENE: u64 = 8;
    pub const DEFAULT_COOLDOWN: u64 = 0;
    pub const DEFAULT_ACCUMULATE: u64 = 1;

    /// The settings of a new run: what `request` asks for, the defaults elsewhere; the global
    /// batch is `micro_batch` (the model's) times the accumulated micro-batches times
    /// `processes`.
    pub fn new(
        request: &RunRequest,
        scenes: Vec<String>,
        micro_batch: u64,
        processes: u64,
    ) -> Result<RunSettings> {
        let accumulate = request.accumulate.unwrap_or(Self::DEFAULT_ACCUMULATE);
        let global_batch = micro_batch
            .checked_mul(accumulate)
            .and_then(|b| b.checked_mul(processes))
            .filter(|&b| b > 0)
            .ok_or_else(|| {
                Error::Invalid(format!(
                    "a batch of {micro_batch} samples x {accumulate} micro-batches x {processes} processes \
                     is not a number of samples a step can take"
                ))
            })?;
        Ok(RunSettings {
            seed: request.seed.unwrap_or(Self::DEFAULT_SEED),
            steps: request.steps.unwrap_or(Self::DEFAULT_STEPS),
            steps_per_scene: request.steps_per_scene.unwrap_or(Self::DEFAULT_STEPS_PER_SCENE),
            cooldown: request.cooldown.unwrap_or(Self::DEFAULT_COOLDOWN),
            global_batch,
            accumulate,
            scenes,
            precision: request.precision.unwrap_or(Precision::F32),
        })
    }

    /// The settings of a run resumed from `checkpoint`, which stored `self`, and notes for the
    /// user. The seed, the steps per scene, the cooldown and the global batch are the stored
    /// ones: a request for other values is refused, since it would make the rest of the run
    /// another run's. A request for another total of steps lengthens or shortens the run (and
    /// moves a cooldown with its end). The dataset must hold the scenes the run started with.
    ///
    /// On another number of processes, the global batch is kept by accumulating another number
    /// of micro-batches of `micro_batch` samples per process (with a note: the samples are the
    /// same, their gradients are summed in another order), and refused where it does not split
    /// that way.
    pub fn resume(
        &self,
        request: &RunRequest,
        scenes: &[String],
        checkpoint: &Path,
        micro_batch: u64,
        processes: u64,
    ) -> Result<(RunSettings, Vec<String>)> {
        let stored = checkpoint.display();
        for (setting, asked, kept) in [
            ("seed", request.seed, self.seed),
            ("steps_per_scene", request.steps_per_scene, self.steps_per_scene),
            ("cooldown", request.cooldown, self.cooldown),
        ] {
            if let Some(asked) = asked.filter(|&a| a != kept) {
                return Err(Error::setting(
                    setting,
                    format!(
                        "{{{setting}}} {asked} differs from the {kept} the run started with ({stored}): a \
                         resumed run keeps its settings; leave {{{setting}}} out, or start a new run in \
                         another folder"
                    ),
                ));
            }
        }
        if let Some(asked) = request.precision.filter(|&p| p != self.precision) {
            return Err(Error::setting(
                "precision",
                format!(
                    "{{precision}} {} differs from the {} the run started with ({stored}): a resumed run \
                     keeps its settings; leave {{precision}} out, or start a new run in another folder",
                    asked.name(),
                    self.precision.name()
                ),
            ));
        }
        if scenes != self.scenes.as_slice() {
            let gone = self.scenes.iter().find(|s| !scenes.contains(s));
            let new = scenes.iter().find(|s| !self.scenes.contains(s));
            let which = match (gone, new) {
                (Some(g), _) => format!("{g} is gone"),
                (None, Some(n)) => format!("{n} is new"),
                (None, None) => "the names are the same, in another order".into(),
            };
            return Err(Error::Invalid(format!(
                "the dataset's scenes are not the ones the run started with ({} then, {} now: {which}); \
                 resuming {stored} needs the same scenes to repeat the run's scene order",
                self.scenes.len(),
                scenes.len()
            )));
        }
        let mut notes = Vec::new();
        let g = self.global_batch;
        let per_micro_batch = micro_batch.saturating_mul(processes).max(1);
        if !g.is_multiple_of(per_micro_batch) {
            return Err(Error::Invalid(format!(
                "the run ({stored}) takes {g} samples a step, which do not split into micro-batches of \
                 {micro_batch} on {processes} process(es): resume it on a number of processes that \
                 divides {}",
                g / micro_batch.max(1)
            )));
        }
        let accumulate = g / per_micro_batch;
        if let Some(asked) = request.accumulate.filter(|&a| a != accumulate) {
            return Err(Error::setting(
                "accumulate",
                format!(
                    "{{accumulate}} {asked} makes a batch of {} samples a step ({micro_batch} a micro-batch \
                     on {processes} process(es)), and the run ({stored}) takes {g}: a resumed run keeps its \
                     batch; leave {{accumulate}} out, or start a new run in another folder",
                    asked.saturating_mul(per_micro_batch)
                ),
            ));
        }
        if accumulate != self.accumulate {
            notes.push(format!(
                "the run's batch of {g} samples a step is kept on {processes} process(es) by accumulating \
                 {accumulate} micro-batch(es) of {micro_batch} (it accumulated {} before): the same samples, \
                 their gradients summed in another order",
                self.accumulate
            ));
        }
        let steps = request.steps.unwrap_or(self.steps);
        if steps != self.steps && self.cooldown > 0 {
            notes.push(format!(
                "the run now ends at step {steps} instead of {}, and its cooldown of {} steps moves with the end",
                self.steps, self.cooldown
            ));
        }
        Ok((RunSettings { steps, accumulate, ..self.clone() }, notes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scenes(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_new_run_takes_the_request_and_the_defaults() {
        let request =
            RunRequest { seed: Some(4), cooldown: Some(9), accumulate: Some(3), ..Default::default() };
        let s = RunSettings::new(&request, vec![], 2, 5).unwrap();
        assert_eq!((s.seed, s.steps, s.steps_per_scene, s.cooldown), (4, 2000, 8, 9));
        assert_eq!((s.global_batch, s.accumulate), (30, 3));
        let s = RunSettings::new(&RunRequest::default(), vec![], 1, 1).unwrap();
        assert_eq!((s.global_batch, s.accumulate), (1, 1));
        let huge = RunRequest { accumulate: Some(u64::MAX), ..Default::default() };
        assert!(RunSettings::new(&huge, vec![], 2, 1).is_err());
    }

    #[test]
    fn a_resumed_run_keeps_its_batch_on_another_number_of_processes_or_refuses() {
        let path = Path::new("run/checkpoint.safetensors");
        let ab = scenes(&["a", "b"]);
        // 12 samples a step: 2 a micro-batch x 3 micro-batches x 2 processes.
        let stored =
            RunSettings::new(&RunRequest { accumulate: Some(3), ..Default::default() }, ab.clone(), 2, 2)
                .unwrap();
        assert_eq!(stored.global_batch, 12);
        let (same, notes) = stored.resume(&RunRequest::default(), &ab, path, 2, 2).unwrap();
        assert_eq!((same, notes.len()), (stored.clone(), 0));
        // On 3 processes: 2 micro-batches each, with a note.
        let (on3, notes) = stored.resume(&RunRequest::default(), &ab, path, 2, 3).unwrap();
        assert_eq!((on3.global_batch, on3.accumulate), (12, 2));
        assert!(notes[0].contains("kept on 3 process(es) by accumulating 2"), "{notes:?}");
        // --accumulate that keeps the batch is accepted; one that changes it is not.
        let keep = RunRequest { accumulate: Some(2), ..Default::default() };
        assert_eq!(stored.resume(&keep, &ab, path, 2, 3).unwrap().0.accumulate, 2);
        let e = stored.resume(&keep, &ab, path, 2, 2).unwrap_err().to_string();
        assert!(e.contains("`accumulate` 2 makes a batch of 8") && e.contains("takes 12"), "{e}");
        // 12 samples do not split over 5 processes.
        let e = stored.resume(&RunRequest::default(), &ab, path, 2, 5).unwrap_err().to_string();
        assert!(e.contains("do not split into micro-batches of 2 on 5") && e.contains("divides 6"), "{e}");
    }

    #[test]
    fn a_resumed_run_keeps_its_settings_and_refuses_others() {
        let path = Path::new("run/checkpoint.safetensors");
        let stored = RunSettings {
            seed: 3,
            steps: 100,
            steps_per_scene: 4,
            cooldown: 10,
            global_batch: 1,
            accumulate: 1,
            scenes: scenes(&["a", "b"]),
            precision: Precision::F16,
        };
        let ab = scenes(&["a", "b"]);
        let resume = |request: &RunRequest, now: &[String]| stored.resume(request, now, path, 1, 1);
        // Nothing asked: the stored settings.
        assert_eq!(resume(&RunRequest::default(), &ab).unwrap(), (stored.clone(), vec![]));
        // The same values asked for explicitly, and a longer run, whose cooldown moves (a note).
        let same = RunRequest {
            seed: Some(3),
            steps: Some(150),
            steps_per_scene: Some(4),
            cooldown: Some(10),
            accumulate: Some(1),
            precision: Some(Precision::F16),
        };
        let (longer, notes) = resume(&same, &ab).unwrap();
        assert_eq!(longer, RunSettings { steps: 150, ..stored.clone() });
        assert!(notes[0].contains("now ends at step 150 instead of 100"), "{notes:?}");
        for (request, flag) in [
            (RunRequest { seed: Some(0), ..Default::default() }, "`seed` 0 differs from the 3"),
            (
                RunRequest { steps_per_scene: Some(8), ..Default::default() },
                "`steps_per_scene` 8 differs from the 4",
            ),
            (RunRequest { cooldown: Some(0), ..Default::default() }, "`cooldown` 0 differs from the 10"),
            (
                RunRequest { precision: Some(Precision::F32), ..Default::default() },
                "`precision` f32 differs from the f16",
            ),
        ] {
            let e = resume(&request, &ab).unwrap_err().to_string();
            assert!(e.contains(flag) && e.contains("run/checkpoint.safetensors"), "{e}");
        }
        for (now, said) in [
            (scenes(&["a"]), "2 then, 1 now: b is gone"),
            (scenes(&["a", "b", "c"]), "2 then, 3 now: c is new"),
            (scenes(&["b", "a"]), "another order"),
        ] {
            let e = resume(&RunRequest::default(), &now).unwrap_err().to_string();
            assert!(e.contains(said), "{e}");
        }
    }
}
