//! The settings of a training run that decide what it computes, beside the model's config:
//! the seed, the length, the scenes and their order, the learning-rate cooldown. Every
//! checkpoint of the run stores them, so a resumed run takes them from there and repeats the
//! uninterrupted run step for step, whatever the command line of the resumption says.

use std::path::Path;

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

/// What a checkpoint stores of its run (in its config JSON, under `"run"`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunSettings {
    /// Seed of the parameters, of the scene order and of every random draw.
    pub seed: u64,
    /// Total optimiser steps of the run.
    pub steps: u64,
    /// Steps on each scene before the next one.
    pub steps_per_scene: u64,
    /// Steps over which the learning rate comes down at the end of the run (0: none).
    pub cooldown: u64,
    /// The dataset's scene folders (their names, in name order), which the scene order indexes.
    pub scenes: Vec<String>,
}

/// The settings a command line asks for; `None` where it leaves one out.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RunRequest {
    pub seed: Option<u64>,
    pub steps: Option<u64>,
    pub steps_per_scene: Option<u64>,
    pub cooldown: Option<u64>,
}

impl RunSettings {
    pub const DEFAULT_SEED: u64 = 0;
    pub const DEFAULT_STEPS: u64 = 2000;
    pub const DEFAULT_STEPS_PER_SCENE: u64 = 8;
    pub const DEFAULT_COOLDOWN: u64 = 0;

    /// The settings of a new run: what `request` asks for, the defaults elsewhere.
    pub fn new(request: &RunRequest, scenes: Vec<String>) -> RunSettings {
        RunSettings {
            seed: request.seed.unwrap_or(Self::DEFAULT_SEED),
            steps: request.steps.unwrap_or(Self::DEFAULT_STEPS),
            steps_per_scene: request.steps_per_scene.unwrap_or(Self::DEFAULT_STEPS_PER_SCENE),
            cooldown: request.cooldown.unwrap_or(Self::DEFAULT_COOLDOWN),
            scenes,
        }
    }

    /// The settings of a run resumed from `checkpoint`, which stored `self`. The seed, the
    /// steps per scene and the cooldown are the stored ones: a request for other values is
    /// refused, since it would make the rest of the run another run's. A request for another
    /// total of steps lengthens or shortens the run (and moves a cooldown with its end). The
    /// dataset must hold the scenes the run started with.
    pub fn resume(&self, request: &RunRequest, scenes: &[String], checkpoint: &Path) -> Result<RunSettings> {
        let stored = checkpoint.display();
        for (flag, asked, kept) in [
            ("--seed", request.seed, self.seed),
            ("--steps-per-scene", request.steps_per_scene, self.steps_per_scene),
            ("--cooldown", request.cooldown, self.cooldown),
        ] {
            if let Some(asked) = asked.filter(|&a| a != kept) {
                return Err(Error::Invalid(format!(
                    "{flag} {asked} differs from the {kept} the run started with ({stored}): a resumed \
                     run keeps its settings; leave {flag} out, or start a new run in another folder"
                )));
            }
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
        Ok(RunSettings { steps: request.steps.unwrap_or(self.steps), ..self.clone() })
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
        let s =
            RunSettings::new(&RunRequest { seed: Some(4), cooldown: Some(9), ..Default::default() }, vec![]);
        assert_eq!((s.seed, s.steps, s.steps_per_scene, s.cooldown), (4, 2000, 8, 9));
    }

    #[test]
    fn a_resumed_run_keeps_its_settings_and_refuses_others() {
        let path = Path::new("run/checkpoint.safetensors");
        let stored = RunSettings {
            seed: 3,
            steps: 100,
            steps_per_scene: 4,
            cooldown: 10,
            scenes: scenes(&["a", "b"]),
        };
        let ab = scenes(&["a", "b"]);
        // Nothing asked: the stored settings.
        assert_eq!(stored.resume(&RunRequest::default(), &ab, path).unwrap(), stored);
        // The same values asked for explicitly, and a longer run.
        let same =
            RunRequest { seed: Some(3), steps: Some(150), steps_per_scene: Some(4), cooldown: Some(10) };
        assert_eq!(stored.resume(&same, &ab, path).unwrap(), RunSettings { steps: 150, ..stored.clone() });
        for (request, flag) in [
            (RunRequest { seed: Some(0), ..Default::default() }, "--seed 0 differs from the 3"),
            (
                RunRequest { steps_per_scene: Some(8), ..Default::default() },
                "--steps-per-scene 8 differs from the 4",
            ),
            (RunRequest { cooldown: Some(0), ..Default::default() }, "--cooldown 0 differs from the 10"),
        ] {
            let e = stored.resume(&request, &ab, path).unwrap_err().to_string();
            assert!(e.contains(flag) && e.contains("run/checkpoint.safetensors"), "{e}");
        }
        for (now, said) in [
            (scenes(&["a"]), "2 then, 1 now: b is gone"),
            (scenes(&["a", "b", "c"]), "2 then, 3 now: c is new"),
            (scenes(&["b", "a"]), "another order"),
        ] {
            let e = stored.resume(&RunRequest::default(), &now, path).unwrap_err().to_string();
            assert!(e.contains(said), "{e}");
        }
    }
}
