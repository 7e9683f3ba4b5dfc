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

/// Adam's settings for [`AdamStates::step_on_host`] (burn's `Adam` keeps its own private).
#[derive(Clone, Copy, Debug)]
pub struct HostAdam {
    pub betas: [f32; 2],
    pub epsilon: f32,
}

impl HostAdam {
    /// burn's `AdamConfig` defaults (betas 0.9 / 0.999) with `epsilon`; [`config`](Self::config)
    /// is the same optimizer as burn builds it.
    pub fn new(epsilon: f32) -> Self {
        Self { betas: [0.9, 0.999], epsilon }
    }

    /// The burn Adam of the same settings.
    pub fn config(&self) -> burn::optim::AdamConfig {
        burn::optim::AdamConfig::new().with_beta_1(self.betas[0]).with_beta_2(self.betas[1]).with_epsilon(self.epsilon)
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

    /// [`step`](Self::step) in one pass over host memory, for a CPU device: burn's Adam
    /// (no weight decay, no AMSGrad, the moments of `betas`, `epsilon`) makes a dozen temporaries
    /// the size of the parameter, each read and written whole (at LLaVA-OneVision's size the patch
    /// convolution's weight alone is 1 GB). The same f32 operations in the same order: the same
    /// values to the bit (a test holds it).
    pub fn step_on_host(
        &mut self,
        adam: &HostAdam,
        name: &str,
        lr: f64,
        param: Tensor<2>,
        grad: Tensor<2>,
    ) -> Tensor<2> {
        let device = param.device();
        let dims = param.dims();
        let vec = |t: Tensor<2>| t.into_data().into_vec::<f32>().expect("an f32 tensor");
        let (mut p, g) = (vec(param), vec(grad));
        let (time, mut m1, mut m2) = match self.states.remove(name) {
            Some(s) => (s.momentum.time + 1, vec(s.momentum.moment_1), vec(s.momentum.moment_2)),
            None => (1, Vec::new(), Vec::new()),
        };
        let fresh = m1.is_empty();
        if fresh {
            (m1, m2) = (vec![0.0; g.len()], vec![0.0; g.len()]);
        }
        let [b1, b2] = adam.betas;
        let (f1, f2) = (1.0 - b1, 1.0 - b2);
        let bc2 = (1.0 - b2.powi(time as i32)).sqrt();
        let combined = bc2 / (1.0 - b1.powi(time as i32));
        let (eps, lr) = (adam.epsilon * bc2, lr as f32);
        use rayon::prelude::*;
        const CHUNK: usize = 1 << 16;
        let update = |p: &mut f32, a: f32, b: f32| *p -= (a * combined) / (b.sqrt() + eps) * lr;
        let chunks = p.par_chunks_mut(CHUNK).zip(m1.par_chunks_mut(CHUNK)).zip(m2.par_chunks_mut(CHUNK));
        // zipped slices without a branch inside: the loops vectorise
        chunks.zip(g.par_chunks(CHUNK)).for_each(|(((p, m1), m2), g)| {
            let each = p.iter_mut().zip(m1.iter_mut()).zip(m2.iter_mut()).zip(g);
            if fresh {
                for (((p, a), b), &g) in each {
                    (*a, *b) = (g * f1, (g * g) * f2);
                    update(p, *a, *b);
                }
            } else {
                for (((p, a), b), &g) in each {
                    (*a, *b) = (*a * b1 + g * f1, *b * b2 + (g * g) * f2);
                    update(p, *a, *b);
                }
            }
        });
        let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, dims), &device);
        self.states.insert(name.to_string(), AdamState::new(AdaptiveMomentumState::new(time, t(m1), t(m2))));
        t(p)
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

    /// Drops the state of `name` (its next step starts from zero moments).
    pub fn forget(&mut self, name: &str) {
        self.states.remove(name);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The host Adam is burn's Adam to the bit, on both CPU backends, over fresh and carried
    /// states, gradients with outliers and zeros, and a learning rate that changes per step.
    #[test]
    #[allow(deprecated)]
    fn the_host_adam_is_burns_adam_to_the_bit() {
        for device in [Device::flex(), Device::ndarray()] {
            let adam = HostAdam::new(1e-15);
            let burn_adam = adam.config().build();
            let (mut burn_states, mut host_states) = (AdamStates::default(), AdamStates::default());
            let dims = [37, 53];
            let n = dims[0] * dims[1];
            let mut rng = model::rng::Rng::new(11);
            let tensor = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, dims), &device);
            let start: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
            let (mut a, mut b) = (tensor(start.clone()), tensor(start));
            for step in 0..4 {
                let g: Vec<f32> = (0..n)
                    .map(|i| match i % 97 {
                        0 => 300.0 * rng.range(-1.0, 1.0),
                        1 => 0.0,
                        _ => rng.range(-1.0, 1.0) * 1e-3,
                    })
                    .collect();
                let lr = 0.05 / (1.0 + step as f64);
                a = burn_states.step(&burn_adam, "w", lr, a, tensor(g.clone()));
                b = host_states.step_on_host(&adam, "w", lr, b, tensor(g));
                let (x, y) = (host(a.clone()), host(b.clone()));
                let differ = x.iter().zip(&y).filter(|(p, q)| p.to_bits() != q.to_bits()).count();
                assert_eq!(differ, 0, "step {step}: {differ} of {n} values differ from burn's Adam");
                let (bs, hs) = (burn_states.get("w").unwrap(), host_states.get("w").unwrap());
                assert_eq!(bs.momentum.time, hs.momentum.time);
                assert_eq!(host(bs.momentum.moment_2.clone()), host(hs.momentum.moment_2.clone()));
            }
            assert_ne!(host(a), vec![0.0; n], "the parameter moved");
        }
    }
}
