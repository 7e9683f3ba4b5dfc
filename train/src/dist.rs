//! Data-parallel training across processes: what a trainer needs from a collective (sums,
//! a broadcast, an agreement check), the ranks' shares of a step, and the module-level helpers
//! that turn a model's gradients into one flat buffer in a fixed parameter order and back.
//!
//! The collective itself is the app's (MPI behind the `mpi` feature); this crate sees only the
//! [`Collective`] trait, and [`Solo`] (one process) is the identity, so a one-rank run takes the
//! same code path as before data parallelism existed and stays bit-identical to it.
//!
//! How a step stays equal to one process's step on the whole batch: every rank draws the step's
//! samples from the same generator (the draw is cheap next to the forward pass, and keeps every
//! rank's generator in step), packs and runs only its share, weights each mean in its loss by
//! its share of that mean's items, and the gradients are summed over ranks ([`reduce_grads`]).

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use model::error::{Error, Result};
use std::ops::Range;

/// The operations a data-parallel trainer needs. Every rank calls the same operations in the same
/// order with buffers of the same length; `what` names the operation in errors (a rank that
/// stops or hangs makes the others fail with it, never wait forever).
pub trait Collective {
    /// This process's rank, `0..size`.
    fn rank(&self) -> usize;
    /// The number of ranks.
    fn size(&self) -> usize;
    /// Element-wise sum over ranks, in place.
    fn sum_f32(&self, what: &str, buf: &mut [f32]) -> Result<()>;
    /// Element-wise sum over ranks, in place.
    fn sum_f64(&self, what: &str, buf: &mut [f64]) -> Result<()>;
    /// Rank 0's `buf` on every rank.
    fn broadcast_f32(&self, what: &str, buf: &mut [f32]) -> Result<()>;
    /// The smallest and largest `value` over ranks.
    fn min_max(&self, what: &str, value: u64) -> Result<(u64, u64)>;

    /// Whether this rank writes logs, checkpoints and models (rank 0).
    fn is_root(&self) -> bool {
        self.rank() == 0
    }
}

/// One process: every operation is the identity.
#[derive(Clone, Copy, Debug, Default)]
pub struct Solo;

impl Collective for Solo {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn sum_f32(&self, _: &str, _: &mut [f32]) -> Result<()> {
        Ok(())
    }
    fn sum_f64(&self, _: &str, _: &mut [f64]) -> Result<()> {
        Ok(())
    }
    fn broadcast_f32(&self, _: &str, _: &mut [f32]) -> Result<()> {
        Ok(())
    }
    fn min_max(&self, _: &str, value: u64) -> Result<(u64, u64)> {
        Ok((value, value))
    }
}

/// The items `rank` of `size` takes of `n`: contiguous blocks in rank order, sizes differing by at
/// most one (so concatenating the ranks' results in rank order gives the whole batch's order).
pub fn share(n: usize, rank: usize, size: usize) -> Range<usize> {
    n * rank / size..n * (rank + 1) / size
}

/// The factor that turns a mean over this rank's `local` items into its part of the mean over all
/// ranks' `global` items (exactly 1 on one rank; 0 where this rank has none).
pub fn part(local: usize, global: usize) -> f32 {
    if local == global { 1.0 } else { local as f32 / global.max(1) as f32 }
}

/// Sums `counts` over ranks (item counts are exact in f64).
pub fn global_counts(c: &dyn Collective, what: &str, counts: &[usize]) -> Result<Vec<usize>> {
    let mut buf: Vec<f64> = counts.iter().map(|&n| n as f64).collect();
    c.sum_f64(what, &mut buf)?;
    Ok(buf.into_iter().map(|x| x.round() as usize).collect())
}

/// The float parameters of a module in visiting order (the order every rank agrees on): id and
/// element count.
struct Layout {
    params: Vec<(ParamId, usize)>,
}

impl ModuleVisitor for Layout {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.params.push((param.id, param.val().dims().iter().product()));
    }
}

fn layout<M: Module>(m: &M) -> Vec<(ParamId, usize)> {
    let mut l = Layout { params: Vec::new() };
    m.visit(&mut l);
    l.params
}

/// Gradients in one flat buffer, in the order they are pushed: per parameter a presence flag,
/// then its values (zeros where this rank has no gradient for it).
#[derive(Default)]
struct Packed {
    flat: Vec<f32>,
    device: Option<Device>,
}

impl Packed {
    /// Appends one parameter's gradient (`n` values).
    fn push<const D: usize>(&mut self, grad: Option<Tensor<D>>, n: usize) {
        match grad {
            Some(g) => {
                self.device.get_or_insert_with(|| g.device());
                self.flat.push(1.0);
                self.flat.extend(g.into_data().convert::<f32>().to_vec::<f32>().expect("f32 gradient"));
            }
            None => {
                self.flat.push(0.0);
                self.flat.resize(self.flat.len() + n, 0.0);
            }
        }
    }

    /// Sums the buffer over the ranks (one all-reduce); what comes back is read in push order,
    /// averaged over the ranks.
    fn all_reduce(mut self, c: &dyn Collective) -> Result<Unpack> {
        c.sum_f32("the gradient all-reduce", &mut self.flat)?;
        let device =
            self.device.ok_or_else(|| Error::input("data-parallel step: this rank's loss reached no parameter"))?;
        Ok(Unpack { flat: self.flat, at: 0, scale: 1.0 / c.size() as f32, device })
    }
}

/// The summed buffer of [`Packed`], read back parameter by parameter.
struct Unpack {
    flat: Vec<f32>,
    at: usize,
    scale: f32,
    device: Device,
}

impl Unpack {
    /// The next parameter's averaged gradient, `None` when no rank had one.
    fn take<const D: usize>(&mut self, shape: [usize; D]) -> Option<Tensor<D>> {
        let n: usize = shape.iter().product();
        let present = self.flat[self.at] > 0.0;
        let values = &self.flat[self.at + 1..self.at + 1 + n];
        self.at += 1 + n;
        present.then(|| {
            let v: Vec<f32> = values.iter().map(|x| x * self.scale).collect();
            Tensor::from_data(TensorData::new(v, shape), &self.device)
        })
    }
}

/// The gradients of `module` summed over ranks in one flat buffer (module order), then averaged:
/// divided by the number of ranks. Each rank's loss must already be `size` times its share of the
/// whole batch's loss ([`part`] times `size`), so the average is the one-process gradient. A
/// parameter gets a gradient when any rank has one. On one rank `grads` comes back untouched.
pub fn reduce_grads<M: Module>(c: &dyn Collective, module: &M, mut grads: GradientsParams) -> Result<GradientsParams> {
    if c.size() == 1 {
        return Ok(grads);
    }
    struct Pack<'a> {
        grads: &'a mut GradientsParams,
        packed: Packed,
    }
    impl ModuleVisitor for Pack<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let n = param.val().dims().iter().product();
            self.packed.push(self.grads.remove::<D>(param.id), n);
        }
    }
    struct Register {
        sums: Unpack,
        grads: GradientsParams,
    }
    impl ModuleVisitor for Register {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.sums.take(param.val().dims()) {
                self.grads.register::<D>(param.id, g);
            }
        }
    }
    let mut pack = Pack { grads: &mut grads, packed: Packed::default() };
    module.visit(&mut pack);
    let mut register = Register { sums: pack.packed.all_reduce(c)?, grads: GradientsParams::new() };
    module.visit(&mut register);
    Ok(register.grads)
}

/// [`reduce_grads`] for parameters kept as a list of named tensors (the language field): the
/// gradients `grads` (of tensors of `shapes`, `None` where a tensor got none) summed over ranks in
/// one flat buffer in list order, then averaged. On one rank they come back untouched.
pub fn reduce_tensors(
    c: &dyn Collective,
    grads: Vec<Option<Tensor<2>>>,
    shapes: &[[usize; 2]],
) -> Result<Vec<Option<Tensor<2>>>> {
    if c.size() == 1 {
        return Ok(grads);
    }
    let mut packed = Packed::default();
    for (g, s) in grads.into_iter().zip(shapes) {
        packed.push(g, s[0] * s[1]);
    }
    let mut sums = packed.all_reduce(c)?;
    Ok(shapes.iter().map(|s| sums.take(*s)).collect())
}

/// A 64-bit FNV-1a hash of the bits of `values` (chained from `seed`).
pub fn hash_f32(seed: u64, values: &[f32]) -> u64 {
    let mut h = seed;
    for x in values {
        for b in x.to_bits().to_le_bytes() {
            h = (h ^ b as u64).wrapping_mul(0x100_0000_01B3);
        }
    }
    h
}

/// The FNV-1a offset basis, the seed of a fresh [`hash_f32`] chain.
pub const HASH_START: u64 = 0xCBF2_9CE4_8422_2325;

/// Fails when `hash` (of this rank's weights) differs between ranks, naming the step.
pub fn check_hash(c: &dyn Collective, hash: u64, step: usize) -> Result<()> {
    if c.size() == 1 {
        return Ok(());
    }
    let (lo, hi) = c.min_max("the weight checksum", hash)?;
    if lo != hi {
        return Err(Error::input(format!(
            "data-parallel training: the ranks' weights differ after step {step} (checksums {lo:016x} and \
             {hi:016x}); the ranks must run the same build and configuration"
        )));
    }
    Ok(())
}

/// Moves the gradients of `part`'s parameters (a sub-module) out of `grads` into their own set.
pub fn take_grads<M: Module>(grads: &mut GradientsParams, part: &M) -> GradientsParams {
    struct Take<'a> {
        from: &'a mut GradientsParams,
        to: GradientsParams,
    }
    impl ModuleVisitor for Take<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.from.remove::<D>(param.id) {
                self.to.register::<D>(param.id, g);
            }
        }
    }
    let mut t = Take { from: grads, to: GradientsParams::new() };
    part.visit(&mut t);
    t.to
}

/// Sets every float parameter to rank 0's value (one flat broadcast in module order).
pub fn broadcast_params<M: Module>(c: &dyn Collective, module: M) -> Result<M> {
    if c.size() == 1 {
        return Ok(module);
    }
    let mut flat = flat_params(&module);
    c.broadcast_f32("the broadcast of rank 0's weights", &mut flat)?;
    set_flat_params(module, &flat)
}

/// Every float parameter's values, in module order, in one buffer.
pub fn flat_params<M: Module>(module: &M) -> Vec<f32> {
    struct Gather<'a>(&'a mut Vec<f32>);
    impl ModuleVisitor for Gather<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.extend(param.val().into_data().convert::<f32>().to_vec::<f32>().expect("f32 parameter"));
        }
    }
    let mut flat = Vec::new();
    module.visit(&mut Gather(&mut flat));
    flat
}

/// `module` with its float parameters set from `flat` (module order, as [`flat_params`] gives);
/// `flat` must hold exactly their values.
pub fn set_flat_params<M: Module>(module: M, flat: &[f32]) -> Result<M> {
    let total: usize = layout(&module).iter().map(|(_, n)| n).sum();
    if total != flat.len() {
        return Err(Error::input(format!("{} weights for a model of {total}", flat.len())));
    }
    struct Scatter<'a> {
        flat: &'a [f32],
        at: usize,
    }
    impl ModuleMapper for Scatter<'_> {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            param.map(|t| {
                let shape = t.dims();
                let n: usize = shape.iter().product();
                let v = self.flat[self.at..self.at + n].to_vec();
                self.at += n;
                let fresh = Tensor::from_data(TensorData::new(v, shape), &t.device());
                if t.is_require_grad() { fresh.require_grad() } else { fresh }
            })
        }
    }
    Ok(module.map(&mut Scatter { flat, at: 0 }))
}

/// The float parameters' ids in module order (what an optimizer's state is keyed by).
pub fn param_ids<M: Module>(module: &M) -> Vec<u64> {
    layout(module).iter().map(|(id, _)| id.val()).collect()
}

/// `module` with its float parameters' ids set to `ids` (module order), so that an optimizer
/// state saved with those ids applies to it.
pub fn set_param_ids<M: Module>(module: M, ids: &[u64]) -> Result<M> {
    let n = layout(&module).len();
    if n != ids.len() {
        return Err(Error::input(format!("{} parameter ids for a model of {n} parameters", ids.len())));
    }
    struct Ids<'a> {
        ids: &'a [u64],
        at: usize,
    }
    impl ModuleMapper for Ids<'_> {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let (_, value, mapper) = param.consume();
            let id = ParamId::from(self.ids[self.at]);
            self.at += 1;
            Param::from_mapped_value(id, value, mapper)
        }
    }
    Ok(module.map(&mut Ids { ids, at: 0 }))
}

/// A 64-bit FNV-1a hash of every float parameter's bits, in module order: equal on every rank
/// exactly when the ranks hold the same weights.
pub fn param_hash<M: Module>(module: &M) -> u64 {
    struct Hash(u64);
    impl ModuleVisitor for Hash {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let v = param.val().into_data().convert::<f32>().to_vec::<f32>().expect("f32 parameter");
            self.0 = hash_f32(self.0, &v);
        }
    }
    let mut h = Hash(HASH_START);
    module.visit(&mut h);
    h.0
}

/// Fails when the ranks' weights differ (their hashes disagree), naming the step.
pub fn check_in_step<M: Module>(c: &dyn Collective, module: &M, step: usize) -> Result<()> {
    if c.size() == 1 {
        return Ok(());
    }
    check_hash(c, param_hash(module), step)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_cover_every_item_once_in_rank_order() {
        for n in [1, 2, 5, 16, 17] {
            for size in 1..=n.min(6) {
                let all: Vec<usize> = (0..size).flat_map(|r| share(n, r, size)).collect();
                assert_eq!(all, (0..n).collect::<Vec<_>>(), "n {n} size {size}");
                assert!((0..size).all(|r| !share(n, r, size).is_empty()));
            }
        }
    }

    #[test]
    fn parts_of_a_mean_add_up_to_the_mean() {
        let items = [3usize, 5, 0, 8];
        let global: usize = items.iter().sum();
        let total: f32 = items.iter().map(|&n| part(n, global)).sum();
        assert!((total - 1.0).abs() < 1e-6);
        assert_eq!(part(7, 7), 1.0);
        assert_eq!(part(0, 9), 0.0);
    }
}
