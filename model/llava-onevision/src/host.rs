//! A CPU tensor's values read where its backend holds them, without a copy: the weights a decode
//! step multiplies by ([`super::layers::host_product`]), a KV cache with room to grow
//! ([`super::layers::attention`]), f16 weights widened on the host ([`in_dtype`]).
//! `into_data` would copy a weight first, since its parameter shares the storage.

use super::cpu::convert::{narrowed, widened};
use burn::backend::flex::FlexTensor;
use burn::backend::ndarray::NdArrayTensor;
use burn::backend::{Flex, NdArray};
use burn::tensor::{DType, Device, Tensor, TensorData};

/// A tensor's primitive on a CPU backend at inference, kept so that its values can be borrowed.
pub enum HostTensor {
    /// burn-flex: a storage buffer, a start offset and strides (a view may lie inside it).
    Flex(FlexTensor),
    /// burn-ndarray, f32 (it holds no f16; other element types are not taken).
    Ndarray(NdArrayTensor),
}

/// Borrowed values of a [`HostTensor`], in memory order from its first element.
pub enum HostValues<'a> {
    F32(&'a [f32]),
    F16(&'a [half::f16]),
}

impl HostTensor {
    /// `t`'s primitive when it lies on burn-flex or burn-ndarray (f32) outside autodiff, with
    /// strides that are not negative; `None` elsewhere (wgpu, training).
    pub fn of<const D: usize>(t: &Tensor<D>) -> Option<Self> {
        if t.device().is_autodiff() {
            return None;
        }
        let held = match t.clone().try_into_primitive::<Flex>() {
            Ok(p) => HostTensor::Flex(p),
            Err(_) => match t.clone().try_into_primitive::<NdArray>().ok()? {
                p @ NdArrayTensor::F32(_) => HostTensor::Ndarray(p),
                _ => return None,
            },
        };
        held.strides().iter().all(|&s| s >= 0).then_some(held)
    }

    /// The distance in elements between neighbours along each dimension.
    pub fn strides(&self) -> Vec<isize> {
        match self {
            HostTensor::Flex(p) => p.layout().strides().to_vec(),
            HostTensor::Ndarray(NdArrayTensor::F32(s)) => s.view().strides().to_vec(),
            HostTensor::Ndarray(_) => Vec::new(),
        }
    }

    /// The values from the tensor's first element on, in memory order: on flex to the end of its
    /// storage (so a view with room between its blocks reads in place), on ndarray when its
    /// elements fill one block of memory. `None` for other element types or layouts.
    pub fn values(&self) -> Option<HostValues<'_>> {
        match self {
            HostTensor::Flex(p) => {
                let at = p.layout().start_offset();
                match p.dtype() {
                    DType::F32 => Some(HostValues::F32(&p.storage::<f32>()[at..])),
                    DType::F16 => Some(HostValues::F16(&p.storage::<half::f16>()[at..])),
                    _ => None,
                }
            }
            HostTensor::Ndarray(NdArrayTensor::F32(s)) => s.view().to_slice_memory_order().map(HostValues::F32),
            HostTensor::Ndarray(_) => None,
        }
    }

    /// The first `n` values, when the tensor's `n` elements lie in one contiguous row-major block.
    pub fn contiguous(&self, n: usize) -> Option<HostValues<'_>> {
        let row_major = match self {
            HostTensor::Flex(p) => p.is_contiguous(),
            HostTensor::Ndarray(NdArrayTensor::F32(s)) => s.view().is_standard_layout(),
            HostTensor::Ndarray(_) => false,
        };
        match self.values()? {
            HostValues::F32(v) if row_major && v.len() >= n => Some(HostValues::F32(&v[..n])),
            HostValues::F16(v) if row_major && v.len() >= n => Some(HostValues::F16(&v[..n])),
            _ => None,
        }
    }
}

/// `t` in `dtype` (no op when it already is). f32 <-> f16 on flex is converted on the host with
/// F16C vector instructions: burn-flex's own cast goes element by element through f64 in
/// software, which made the f16-weight vision tower 3x slower than f32 (14.7 s vs 5.2 s per view).
pub fn in_dtype<const D: usize>(t: Tensor<D>, dtype: DType) -> Tensor<D> {
    let from = t.dtype();
    if from == dtype {
        return t;
    }
    let device = t.device();
    let pair = matches!((from, dtype), (DType::F32, DType::F16) | (DType::F16, DType::F32));
    if !pair || device.is_autodiff() || device != Device::flex() {
        return t.cast(dtype);
    }
    let shape = t.shape();
    let n = shape.num_elements();
    // read where flex holds it, or else as data
    let held = HostTensor::of(&t);
    let data = match held.as_ref().and_then(|h| h.contiguous(n)) {
        Some(HostValues::F32(v)) => TensorData::new(narrowed(v), shape),
        Some(HostValues::F16(v)) => TensorData::new(widened(v), shape),
        None => {
            let d = t.into_data();
            match from {
                DType::F32 => TensorData::new(narrowed(d.as_slice::<f32>().expect("f32 data")), shape),
                _ => TensorData::new(widened(d.as_slice::<half::f16>().expect("f16 data")), shape),
            }
        }
    };
    Tensor::from_data(data, (&device, dtype))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn tensor(device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new((0..12).map(|v| v as f32).collect::<Vec<_>>(), [3, 4]), device)
    }

    fn f32s(v: Option<HostValues<'_>>) -> Option<Vec<f32>> {
        match v {
            Some(HostValues::F32(v)) => Some(v.to_vec()),
            _ => None,
        }
    }

    #[test]
    fn values_are_read_in_place_on_both_cpu_backends() {
        for device in [Device::flex(), Device::ndarray()] {
            let t = tensor(&device);
            let h = HostTensor::of(&t).expect("a CPU tensor");
            assert_eq!(h.strides(), [4, 1], "{device:?}");
            assert_eq!(f32s(h.contiguous(12)).expect("row-major"), (0..12).map(|v| v as f32).collect::<Vec<_>>());
            // the transposed view: the same memory, strides swapped, not row-major
            let tt = t.clone().transpose();
            let h = HostTensor::of(&tt).expect("a CPU view");
            assert_eq!(h.strides(), [1, 4], "{device:?}");
            assert_eq!(f32s(h.values()).expect("one block")[..12], (0..12).map(|v| v as f32).collect::<Vec<_>>());
            assert!(h.contiguous(12).is_none(), "{device:?}: a transposed view is not row-major");
            // a narrowed view starts at its first element
            let row = t.narrow(0, 1, 2);
            let h = HostTensor::of(&row).expect("a CPU view");
            assert_eq!(f32s(h.values()).expect("values")[..8], [4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0]);
        }
    }

    #[test]
    fn half_values_on_flex_and_nothing_under_autodiff_or_in_f64() {
        let t = tensor(&Device::flex()).cast(DType::F16);
        let h = HostTensor::of(&t).expect("a flex tensor");
        match h.contiguous(12) {
            Some(HostValues::F16(v)) => assert_eq!(v[11].to_f32(), 11.0),
            _ => panic!("f16 values expected"),
        }
        assert!(HostTensor::of(&tensor(&Device::flex().autodiff())).is_none());
        // burn-ndarray in f64: not taken (the kernels read f32)
        assert!(HostTensor::of(&tensor(&Device::ndarray()).cast(DType::F64)).is_none());
    }
}
