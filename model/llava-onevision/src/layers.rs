//! The building blocks of the port: `burn::nn` layers loaded from (or initialised for) a
//! checkpoint, the activations the configs name, and softmax attention.

use super::VlmError;
use super::config::Act;
use super::cpu;
use super::cpu::convert::widened;
pub use super::host::in_dtype;
use super::host::{HostTensor, HostValues};
use super::weights::WeightStore;
use base::Rng;
use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, RmsNorm};
use burn::tensor::{DType, Device, Tensor, TensorData, activation};

/// A `torch.nn.Linear` of the checkpoint (`prefix.weight` `[out, in]`, `prefix.bias`), as a
/// `burn::nn::Linear` (`weight` `[in, out]`).
pub fn load_linear(w: &WeightStore, prefix: &str, d_in: usize, d_out: usize, bias: bool) -> Result<Linear, VlmError> {
    Ok(Linear {
        weight: Param::from_tensor(w.hold(w.linear_weight(&format!("{prefix}.weight"), d_in, d_out)?)),
        bias: if bias { Some(Param::from_tensor(w.hold(w.tensor(&format!("{prefix}.bias"), [d_out])?))) } else { None },
    })
}

/// `l` with its weight and bias held in f16.
pub fn half_linear(l: Linear) -> Linear {
    Linear {
        weight: Param::from_tensor(in_dtype(l.weight.val(), DType::F16)),
        bias: l.bias.map(|b| Param::from_tensor(in_dtype(b.val(), DType::F16))),
    }
}

/// `l(x)`, also for a layer held in another precision than `x` (f16 weights, f32 activations).
/// CPU inference (flex, ndarray) runs it in [`host_product`]: the weights read where they lie, in
/// f32 or f16, `x` kept in f32. Elsewhere (training, wgpu) `x` is rounded to the weights'
/// precision for burn's matmul and the result returned in `x`'s.
pub fn linear<const D: usize>(l: &Linear, x: Tensor<D>) -> Tensor<D> {
    let bias = l.bias.as_ref().map(|b| b.val());
    let w = l.weight.val();
    let x = match host_product(x, &w, bias.as_ref()) {
        Ok(y) => return y,
        Err(x) => x,
    };
    in_precision(w.dtype(), x, |x| l.forward(x))
}

/// Weights (elements) up to which [`host_product`] widens f16 weights to f32 for a product of many
/// rows (512 MB in f32: every layer of the 7B model but its 152k-row `lm_head`).
const WIDEN_LIMIT: usize = 1 << 27;

/// `x w (+ bias)` through [`cpu::product`], reading `x`, `w` and `bias` where the CPU backend holds
/// them ([`HostTensor`]: f32 or f16 on flex, f32 on ndarray; no copy) and writing the result once,
/// when `x` is f32 at CPU inference and `w` `[k, n]` is row-major or the transposed view of a
/// row-major `[n, k]` (f16 weights of more than [`WIDEN_LIMIT`] elements only for a few rows);
/// `Err(x)` otherwise.
// the input comes back by value (moved, not copied) when this path does not apply
#[allow(clippy::result_large_err)]
pub fn host_product<const D: usize>(
    x: Tensor<D>,
    w: &Tensor<2>,
    bias: Option<&Tensor<1>>,
) -> Result<Tensor<D>, Tensor<D>> {
    use cpu::matvec::{Held, Order};
    let dims = x.dims();
    let (k, rows) = (dims[D - 1], dims[..D - 1].iter().product::<usize>());
    if !on_host(&x) {
        return Err(x);
    }
    let Some(wt) = HostTensor::of(w) else { return Err(x) };
    let n = w.dims()[1];
    let order = match wt.strides()[..] {
        _ if w.dims()[0] != k => return Err(x),
        [s, 1] if s == n as isize => Order::InOut,
        [1, s] if s == k as isize => Order::OutIn,
        _ => return Err(x),
    };
    let held = match wt.values() {
        Some(HostValues::F32(v)) if v.len() >= k * n => Held::F32(&v[..k * n]),
        Some(HostValues::F16(v)) if v.len() >= k * n && (rows <= cpu::product::FEW_ROWS || k * n <= WIDEN_LIMIT) => {
            Held::F16(&v[..k * n])
        }
        _ => return Err(x),
    };
    let bias_held = bias.and_then(HostTensor::of);
    let bias = match (bias, bias_held.as_ref().and_then(|b| b.contiguous(n))) {
        (None, _) => None,
        (Some(_), Some(HostValues::F32(b))) => Some(std::borrow::Cow::Borrowed(b)),
        (Some(_), Some(HostValues::F16(b))) => Some(std::borrow::Cow::Owned(widened(b))),
        (Some(_), None) => return Err(x),
    };
    let device = x.device();
    let x_held = HostTensor::of(&x);
    let out = match x_held.as_ref().and_then(|h| h.contiguous(rows * k)) {
        Some(HostValues::F32(xs)) => cpu::product::product(xs, held, order, rows, k, n, bias.as_deref()),
        _ => cpu::product::product(&host_vec(x), held, order, rows, k, n, bias.as_deref()),
    };
    let mut shape = dims;
    shape[D - 1] = n;
    Ok(Tensor::from_data(TensorData::new(out, shape), &device))
}

/// `f(x)` computed in the precision `held` of the weights `f` multiplies by, returned in `x`'s.
pub fn in_precision<const D: usize, const E: usize>(
    held: DType,
    x: Tensor<D>,
    f: impl FnOnce(Tensor<D>) -> Tensor<E>,
) -> Tensor<E> {
    let dtype = x.dtype();
    if held == dtype { f(x) } else { in_dtype(f(in_dtype(x, held)), dtype) }
}

/// A `LayerNorm` of the checkpoint (`prefix.weight`, `prefix.bias`).
pub fn load_layer_norm(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<LayerNorm, VlmError> {
    let mut ln = LayerNormConfig::new(d).with_epsilon(eps).init(w.device());
    ln.gamma = Param::from_tensor(w.tensor(&format!("{prefix}.weight"), [d])?);
    ln.beta = Some(Param::from_tensor(w.tensor(&format!("{prefix}.bias"), [d])?));
    Ok(ln)
}

/// An `RMSNorm` of the checkpoint (`prefix.weight`).
pub fn load_rms_norm(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<RmsNorm, VlmError> {
    Ok(RmsNorm { gamma: Param::from_tensor(w.tensor(&format!("{prefix}.weight"), [d])?), epsilon: eps })
}

/// Values ~ N(0, std²) from `rng`, as a tensor of `shape`.
pub fn normal<const D: usize>(rng: &mut Rng, shape: [usize; D], std: f32, device: &Device) -> Tensor<D> {
    let n: usize = shape.iter().product();
    Tensor::from_data(TensorData::new((0..n).map(|_| std * rng.normal()).collect::<Vec<f32>>(), shape), device)
}

/// A freshly initialised linear layer (weights ~ N(0, std²), zero bias), reproducible from `rng`
/// on every backend.
pub fn init_linear(rng: &mut Rng, d_in: usize, d_out: usize, bias: bool, std: f32, device: &Device) -> Linear {
    Linear {
        weight: Param::from_tensor(normal(rng, [d_in, d_out], std, device)),
        bias: bias.then(|| Param::from_tensor(Tensor::zeros([d_out], device))),
    }
}

/// A LayerNorm starting at the identity (gamma 1, beta 0).
pub fn init_layer_norm(d: usize, eps: f64, device: &Device) -> LayerNorm {
    LayerNormConfig::new(d).with_epsilon(eps).init(device)
}

/// An RMSNorm starting at the identity (gamma 1).
pub fn init_rms_norm(d: usize, eps: f64, device: &Device) -> RmsNorm {
    RmsNorm { gamma: Param::from_tensor(Tensor::ones([d], device)), epsilon: eps }
}

/// Applies an activation.
pub fn act<const D: usize>(a: Act, x: Tensor<D>) -> Tensor<D> {
    if a == Act::GeluTanh && on_host(&x) {
        let (shape, device) = (x.shape(), x.device());
        let mut v = host_vec(x);
        cpu::activation::gelu_tanh_in_place(&mut v);
        return Tensor::from_data(TensorData::new(v, shape), &device);
    }
    match a {
        Act::Gelu => on_cpu_threads(x, D.saturating_sub(2), activation::gelu),
        Act::Silu => on_cpu_threads(x, D.saturating_sub(2), activation::silu),
        Act::GeluTanh => on_cpu_threads(x, D.saturating_sub(2), |x| {
            // 0.5 x (1 + tanh(u)) = x sigmoid(2u), u = sqrt(2/pi) (x + 0.044715 x^3): one
            // transcendental pass instead of pow and tanh (1.5x faster on ndarray, same values to
            // float rounding)
            let inner = (x.clone() * x.clone() * x.clone() * 0.044715 + x.clone())
                * (2.0 * (2.0f64 / std::f64::consts::PI).sqrt());
            x * activation::sigmoid(inner)
        }),
    }
}

/// `act(gate) * up` (Qwen2's MLP), in one pass on the host for SiLU at CPU inference.
pub fn gated<const D: usize>(a: Act, gate: Tensor<D>, up: Tensor<D>) -> Tensor<D> {
    if a == Act::Silu && on_host(&gate) && on_host(&up) && gate.shape() == up.shape() {
        let (shape, device) = (up.shape(), up.device());
        let mut u = host_vec(up);
        cpu::activation::silu_mul_in_place(&host_vec(gate), &mut u);
        return Tensor::from_data(TensorData::new(u, shape), &device);
    }
    act(a, gate) * up
}

/// Whether `device` runs element-wise work on one CPU thread: burn-ndarray's element-wise ops
/// (exp, tanh, softmax, ...) are single-threaded, so at real model size one core idles through
/// the activations and the attention scores. Inference only (the autodiff graph stays on one
/// thread).
fn single_threaded(device: &Device) -> bool {
    !device.is_autodiff() && *device == Device::ndarray()
}

/// Threads to split CPU inference work over (1 elsewhere).
fn cpu_threads(device: &Device) -> usize {
    if single_threaded(device) { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { 1 }
}

/// `f(x)`, computed on ndarray as `f` of `x`'s slices along `dim` on the CPU's threads (then
/// concatenated): `f` must act on each slice independently.
pub fn on_cpu_threads<const D: usize>(
    x: Tensor<D>,
    dim: usize,
    f: impl Fn(Tensor<D>) -> Tensor<D> + Sync,
) -> Tensor<D> {
    let n = x.dims()[dim];
    let parts = cpu_threads(&x.device()).min(n);
    if parts < 2 || x.dims().iter().product::<usize>() < 1 << 16 {
        return f(x);
    }
    let out = on_threads(parts, |i| x.clone().narrow(dim, i * n / parts, (i + 1) * n / parts - i * n / parts), f);
    Tensor::cat(out, dim)
}

/// `run(input(i))` for `i` in `0..parts`, each on its own scoped thread, in order.
fn on_threads<I: Send, O: Send>(parts: usize, input: impl Fn(usize) -> I, run: impl Fn(I) -> O + Sync) -> Vec<O> {
    let run = &run;
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..parts)
            .map(|i| {
                let x = input(i);
                s.spawn(move || run(x))
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("a CPU worker thread panicked")).collect()
    })
}

/// Which keys each query row of [`attention`] sees.
#[derive(Clone, Debug)]
pub enum Mask {
    /// Every key.
    All,
    /// Causal after `past` cached keys: the keys are `past + t`, the query rows `rep` heads of `t`
    /// positions each (`[B, rep * t, d]`, row `h * t + i` at position `i`), and position `i` sees
    /// keys `0..=past + i`.
    Causal { past: usize },
    /// Additive `[Tq, Tk]` (0 or -inf), the same for every batch entry.
    Additive(Box<Tensor<2>>),
}

impl Mask {
    /// The additive `[rows, keys]` form (`None` for [`Mask::All`]).
    pub fn additive(&self, rows: usize, keys: usize, device: &Device) -> Option<Tensor<2>> {
        match self {
            Mask::All => None,
            Mask::Additive(m) => Some((**m).clone()),
            Mask::Causal { past } => {
                let t = keys - past;
                let m: Vec<f32> = (0..rows)
                    .flat_map(|r| (0..keys).map(move |j| if j > past + r % t { f32::NEG_INFINITY } else { 0.0 }))
                    .collect();
                Some(Tensor::from_data(TensorData::new(m, [rows, keys]), device))
            }
        }
    }

    /// The form in which a forward hands this mask to [`attention`] in every layer, for `rows`
    /// query rows against `keys` keys of tensors like `like`, found once for all layers. On the
    /// host a causal mask stays causal ([`attention`] runs it in the host kernel); elsewhere a
    /// decode step (one position after the cache) sees every key and any other causal mask
    /// becomes the additive one, built and uploaded here once instead of in every layer.
    pub fn for_layers<const D: usize>(self, like: &Tensor<D>, rows: usize, keys: usize) -> Mask {
        match self {
            Mask::Causal { .. } if on_host(like) => self,
            Mask::Causal { past } if keys - past == 1 => Mask::All,
            Mask::Causal { .. } => match self.additive(rows, keys, &like.device()) {
                Some(m) => Mask::Additive(Box::new(m)),
                None => Mask::All,
            },
            m => m,
        }
    }
}

/// Whether work on `x` runs in the [`cpu`] kernels (on the host): CPU inference in f32 (burn's
/// autodiff needs its own ops, wgpu keeps the data on its device).
fn on_host<const D: usize>(x: &Tensor<D>) -> bool {
    let device = x.device();
    !device.is_autodiff() && (device == Device::flex() || device == Device::ndarray()) && x.dtype() == DType::F32
}

/// `x`'s values on the host (no copy on flex when `x` is contiguous and not shared).
fn host_vec<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().into_vec::<f32>().expect("f32 activations")
}

/// Softmax attention: `q` `[B, Tq, d]`, `k`/`v` `[B, Tk, d]`, keys seen as `mask` says. CPU
/// inference runs the hand-written [`cpu::attention`] kernel (causal blocks stop at the diagonal);
/// training and wgpu run burn's ops.
pub fn attention(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, mask: &Mask) -> Tensor<3> {
    let (causal_past, host) = match mask {
        Mask::All => (None, on_host(&q)),
        Mask::Causal { past } => (Some(*past), on_host(&q)),
        Mask::Additive(_) => (None, false),
    };
    let [_, rows, _] = q.dims();
    let keys = k.dims()[1];
    if host && rows > 0 {
        // every call, decode steps included: the few-rows path ([`cpu::attention::FEW_ROWS`]) runs
        // `matvec`'s vector kernels and reads a flex KV cache in place (a flex decode step at a 2k
        // context: 11.3-11.7 tokens/s against 10.1 through flex's fused kernel; ndarray, whose
        // cache is copied per call: 9.3-9.4 against 7.9 through burn's ops)
        return attention_on_host(q, k, v, causal_past);
    }
    // a decode step sees every key
    let m = match mask {
        Mask::Causal { past } if keys - past == 1 => None,
        m => m.additive(rows, keys, &q.device()),
    };
    attention_probs(q, k, v, m).0
}

/// [`attention`] through [`cpu::attention::attend_in`]: `q` is read to the host and the result
/// written back (7 MB each way for a 2k-token prompt at 0.5B, against 14 GFLOP); keys and values
/// are read where burn-flex holds them (a KV cache in place, see [`HostBlocks`]).
fn attention_on_host(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, causal_past: Option<usize>) -> Tensor<3> {
    let [groups, rows, d] = q.dims();
    let [_, keys, dv] = v.dims();
    let (t, rep) = match causal_past {
        Some(past) => (keys - past, rows / (keys - past)),
        None => (rows, 1),
    };
    let device = q.device();
    let (kh, k_stride) = HostBlocks::of(k.clone());
    let (vh, v_stride) = HostBlocks::of(v.clone());
    // both read in place with the same room per group, or both as compact copies
    let (kh, vh, cap) = if k_stride / d == v_stride / dv && k_stride % d == 0 && v_stride % dv == 0 {
        (kh, vh, k_stride / d)
    } else {
        (HostBlocks::Copy(host_vec(k)), HostBlocks::Copy(host_vec(v)), keys)
    };
    let mut out = vec![0f32; groups * rows * dv];
    let shape = cpu::attention::Shape { groups, rep, t, keys, d, dv };
    let scale = 1.0 / (d as f32).sqrt();
    cpu::attention::attend_in(&host_vec(q), kh.values(), vh.values(), shape, cap, scale, causal_past, &mut out);
    Tensor::from_data(TensorData::new(out, [groups, rows, dv]), &device)
}

/// A `[G, N, W]` f32 tensor's values on the host, each of its `G` blocks of `N x W` contiguous:
/// borrowed where the CPU backend holds them ([`HostTensor`], no copy; on flex the blocks may lie
/// apart, as in a KV cache with room to grow) or else a compact copy.
enum HostBlocks {
    Held(HostTensor),
    Copy(Vec<f32>),
}

impl HostBlocks {
    /// The values and the distance (in elements) from one block's start to the next.
    fn of(t: Tensor<3>) -> (Self, usize) {
        let [_, n, w] = t.dims();
        if let Some(h) = HostTensor::of(&t)
            && let [s0, s1, 1] = h.strides()[..]
            && s1 == w as isize
            && s0 >= (n * w) as isize
            && matches!(h.values(), Some(HostValues::F32(_)))
        {
            return (HostBlocks::Held(h), s0 as usize);
        }
        (HostBlocks::Copy(host_vec(t)), n * w)
    }

    /// From the first block's first value to the end of the storage.
    fn values(&self) -> &[f32] {
        match self {
            HostBlocks::Held(h) => match h.values() {
                Some(HostValues::F32(v)) => v,
                _ => unreachable!("HostBlocks::of holds only f32 values it can read"),
            },
            HostBlocks::Copy(v) => v,
        }
    }
}

/// [`attention`] on one thread, also returning the attention weights `[B, Tq, Tk]`.
pub fn attention_probs(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, mask: Option<Tensor<2>>) -> (Tensor<3>, Tensor<3>) {
    let d = q.dims()[2];
    let scores = q.matmul(k.swap_dims(1, 2)) * (1.0 / (d as f64).sqrt());
    let scores = match mask {
        Some(m) => scores + m.unsqueeze_dim::<3>(0),
        None => scores,
    };
    let probs = activation::softmax(scores, 2);
    (probs.clone().matmul(v), probs)
}
