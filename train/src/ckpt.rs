//! burn Adam states of named rank-2 parameters, stored beside their parameter in a checkpoint
//! (`adam.{name}.m1` / `.m2`, the step count in the run's `state.json`). Both trainers key their
//! optimizer state by parameter name, so adding a parameter cannot shift another's state.

use burn::optim::{Adam, AdamState, AdaptiveMomentumState, Optimizer};
use burn::tensor::{Device, Tensor, TensorData};
use model::error::{Error, Result};
use model::io::{Named, NamedMap};
use model::splats::host;
use std::collections::BTreeMap;
use std::path::Path;

/// Checks a stored run's progress against itself before it is resumed: its iteration cannot be
/// past the total its own `config.json` asked for, and no parameter can have taken more Adam
/// steps than there were iterations. Either means `state` was edited or comes from another run
/// (resuming it would train nothing, or the wrong amount, and exit as if all was well).
pub fn check_progress(state: &Path, iter: usize, total: usize, times: &BTreeMap<String, usize>) -> Result<()> {
    if iter > total {
        return Err(Error::invalid(
            state,
            format!(
                "iteration {iter} is past the {total} iterations the run's config.json asks for: the state does \
                 not belong to this run (start it again without --resume)"
            ),
        ));
    }
    if let Some((name, t)) = times.iter().find(|(_, t)| **t > iter) {
        return Err(Error::invalid(
            state,
            format!("{name} has taken {t} optimizer steps by iteration {iter}: the state does not belong to this run"),
        ));
    }
    Ok(())
}

/// Says so when a resumed run is already at or past the total asked for now (nothing is trained).
pub fn warn_if_done(dir: &Path, at: usize, asked: usize) {
    if at >= asked {
        model::error::warn(format!(
            "{}: the run is already at iteration {at} and {asked} are asked for: nothing more is trained",
            dir.display()
        ));
    }
}

/// Adam states by parameter name.
#[derive(Clone, Default)]
pub struct AdamStates {
    states: BTreeMap<String, AdamState<2>>,
}

impl AdamStates {
    /// One Adam step of parameter `name` with learning rate `lr`: returns the new value and keeps
    /// the new state.
    pub fn step(&mut self, adam: &Adam, name: &str, lr: f64, param: Tensor<2>, grad: Tensor<2>) -> Tensor<2> {
        let (t, s) = adam.step(lr, param, grad, self.states.remove(name));
        if let Some(s) = s {
            self.states.insert(name.to_string(), s);
        }
        t
    }

    /// Replaces the moments of `name` by `f(moment)` (densification moves rows), keeping the
    /// step count. Nothing happens when `name` has no state yet.
    pub fn remap(&mut self, name: &str, mut f: impl FnMut(Tensor<2>) -> Tensor<2>) {
        if let Some(s) = self.states.remove(name) {
            let m = s.momentum;
            let mut state = AdaptiveMomentumState::new(m.time, f(m.moment_1), f(m.moment_2));
            state.max_moment_2 = m.max_moment_2.map(&mut f);
            self.states.insert(name.to_string(), AdamState::new(state));
        }
    }

    /// The state of parameter `name`, if it has one yet.
    pub fn get(&self, name: &str) -> Option<&AdamState<2>> {
        self.states.get(name)
    }

    /// Step count of each parameter with a state.
    pub fn times(&self) -> BTreeMap<String, usize> {
        self.states.iter().map(|(n, s)| (n.clone(), s.momentum.time)).collect()
    }

    /// The moments as checkpoint tensors.
    pub fn tensors(&self) -> Named {
        let mut out = Vec::new();
        for (name, s) in &self.states {
            let shape = s.momentum.moment_1.dims().to_vec();
            out.push((format!("adam.{name}.m1"), shape.clone(), host(s.momentum.moment_1.clone())));
            out.push((format!("adam.{name}.m2"), shape, host(s.momentum.moment_2.clone())));
        }
        out
    }

    /// Rebuilds the states listed in `times` from the checkpoint `tensors` (read from `path`),
    /// removing their moments. A state whose moments are missing or mis-shaped is an error.
    pub fn take(times: &BTreeMap<String, usize>, tensors: &mut NamedMap, path: &Path, device: &Device) -> Result<Self> {
        let mut states = BTreeMap::new();
        for (name, &time) in times {
            let mut moment = |k: &str| {
                let key = format!("adam.{name}.{k}");
                tensors.remove(&key).ok_or_else(|| Error::invalid(path, format!("tensor {key} is missing")))
            };
            let ((s1, v1), (s2, v2)) = (moment("m1")?, moment("m2")?);
            if s1.len() != 2 || s1 != s2 {
                return Err(Error::invalid(path, format!("Adam moments of {name} have shapes {s1:?} / {s2:?}")));
            }
            let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [s1[0], s1[1]]), device);
            states.insert(name.clone(), AdamState::new(AdaptiveMomentumState::new(time, t(v1), t(v2))));
        }
        Ok(Self { states })
    }
}
