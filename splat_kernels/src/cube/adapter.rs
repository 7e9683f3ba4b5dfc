//! The wgpu adapter, brought up once per process, and whether the op's kernels can run on it.
//!
//! burn picks the adapter (Vulkan first, then DX12, then OpenGL; a GPU before a software
//! rasterizer). What the kernels need of it, and what this module records to decide:
//!
//! * **Subgroup operations** for the plane-summed backward ([`crate::GradReduce::Plane`]): wgpu's
//!   `SUBGROUP` feature. OpenGL has none; a shader that uses them does not compile there, so the
//!   op takes the atomic path and refuses a forced plane path by name ([`subgroups_or_refuse`]).
//! * **A software rasterizer** (Mesa's llvmpipe behind lavapipe or OpenGL, SwiftShader) ends
//!   every loop of an invocation after 65,535 iterations in all. Through Vulkan, lavapipe adds
//!   floats atomically in one instruction and the backward stays far below the limit on the
//!   scenes a CPU can train; through OpenGL it has no float atomic add, every gradient add is a
//!   compare-and-swap loop, and even the tests' tiny scenes pass the limit. Such an adapter is
//!   refused ([`device`]) with its name, its graphics API and what to install instead.
//!
//! Everything in chatsplat that runs on wgpu gets its device from [`device`], so the record is
//! the adapter's own (burn's `Device::wgpu` would bring up the same adapter, unrecorded).

use burn::backend::ops::FloatTensorOps;
use burn::backend::wgpu::CubeBackend;
use burn::tensor::wgpu::wgpu;
use burn::tensor::{Device, TensorData};
use cubecl::features::{AtomicUsage, Plane};
use cubecl::ir::FloatKind;
use cubecl::prelude::*;
use std::sync::OnceLock;

/// The adapter chatsplat runs wgpu work on, and what it offers the op.
#[derive(Clone, Debug)]
pub struct Adapter {
    /// The burn device on it.
    pub device: Device,
    /// The adapter's name (`NVIDIA H100 80GB HBM3`, `llvmpipe (LLVM 15.0.6, 256 bits)`).
    pub name: String,
    /// Its graphics API.
    pub api: wgpu::Backend,
    /// Whether it is a software rasterizer on the CPU.
    pub software: bool,
    /// Whether its shaders have subgroup (plane) operations.
    pub subgroups: bool,
    /// Whether it adds floats atomically in one instruction.
    pub native_float_add: bool,
}

impl Adapter {
    /// `` `llvmpipe (LLVM 15.0.6, 256 bits)` through Vulkan (software) ``.
    pub fn describe(&self) -> String {
        format!("`{}` through {}{}", self.name, api_name(self.api), if self.software { " (software)" } else { "" })
    }

    /// Why the op cannot run on this adapter, or `None` where it can.
    fn refusal(&self) -> Option<String> {
        (self.software && !self.native_float_add).then(|| {
            format!(
                "the only wgpu adapter is `{}` through {}, a software rasterizer without a native float atomic \
                 add: the splatting backward's compare-and-swap loops would pass its limit of 65,535 loop iterations \
                 per shader invocation. Install Mesa's Vulkan driver (`apt-get install mesa-vulkan-drivers \
                 libvulkan1`) to run wgpu on the CPU through lavapipe, use a GPU, or use `--backend flex` or \
                 `--backend ndarray`",
                self.name,
                api_name(self.api)
            )
        })
    }
}

/// The graphics API's usual name.
pub fn api_name(api: wgpu::Backend) -> &'static str {
    match api {
        wgpu::Backend::Vulkan => "Vulkan",
        wgpu::Backend::Metal => "Metal",
        wgpu::Backend::Dx12 => "DirectX 12",
        wgpu::Backend::Gl => "OpenGL",
        wgpu::Backend::BrowserWebGpu => "WebGPU",
        wgpu::Backend::Noop => "no API",
    }
}

static ADAPTER: OnceLock<Result<Adapter, String>> = OnceLock::new();

/// The adapter, brought up on first use (then the same for the whole process): `Err` with the
/// reason where there is none or where the op cannot run on it.
pub fn adapter() -> Result<&'static Adapter, String> {
    ADAPTER.get_or_init(bring_up).as_ref().map_err(Clone::clone)
}

/// The wgpu device, or why there is none the op can run on (a sentence naming the adapter and its
/// graphics API, and what to do).
pub fn device() -> Result<Device, String> {
    adapter().map(|a| a.device.clone())
}

fn bring_up() -> Result<Adapter, String> {
    // a driver that fails to start may panic inside wgpu: its message, not a crash report
    let (device, setup) = match base::panic::quietly(|| Device::wgpu_options().init_with_setup()) {
        Ok(Ok(pair)) => pair,
        Ok(Err(e)) => return Err(format!("no wgpu adapter on this machine ({e})")),
        Err(message) => return Err(format!("no wgpu adapter on this machine ({message})")),
    };
    let info = setup.adapter.get_info();
    let client = cube_client(&device).ok_or("the wgpu device is not a CubeCL device")?;
    let adapter = Adapter {
        device,
        name: info.name.clone(),
        api: info.backend,
        software: info.device_type == wgpu::DeviceType::Cpu,
        subgroups: setup.device.features().contains(wgpu::Features::SUBGROUP),
        native_float_add: native_float_add(&client),
    };
    match adapter.refusal() {
        Some(why) => Err(why),
        None => Ok(adapter),
    }
}

/// Whether the recorded adapter has subgroup operations: panics with a message naming it where
/// it has none, for a caller that forces the plane-summed backward. `true` where no adapter was
/// recorded (a device made outside [`device`]; the shader compiler then says what it lacks).
pub(super) fn subgroups_or_refuse() -> bool {
    match ADAPTER.get() {
        Some(Ok(a)) if !a.subgroups => panic!(
            "the plane-summed backward (GradReduce::Plane) needs subgroup operations, which the wgpu adapter {} \
             does not have: use GradReduce::Auto or Atomic",
            a.describe()
        ),
        _ => true,
    }
}

/// Whether the recorded adapter has subgroup operations (`None` before [`device`] ran or where it
/// failed).
pub fn subgroups() -> Option<bool> {
    match ADAPTER.get() {
        Some(Ok(a)) => Some(a.subgroups),
        _ => None,
    }
}

/// Whether the adapter has a native atomic add on `f32` in storage buffers.
pub fn native_float_add(client: &Client) -> bool {
    let f32_atomic = Type::atomic(ElemType::Float(FloatKind::F32));
    client.properties().atomic_type_usage(f32_atomic).contains(AtomicUsage::Add)
}

/// Whether `device` is a CubeCL (wgpu) adapter with a native atomic float add; `None` for a host
/// device. What [`FloatAdd::Auto`] picks there, and whether [`FloatAdd::Native`] can run.
pub fn native_float_add_on(device: &burn::tensor::Device) -> Option<bool> {
    cube_client(device).map(|c| native_float_add(&c))
}

/// Whether `device` is a CubeCL (wgpu) adapter whose shaders take f16 (wgpu's `SHADER_F16`): what
/// holding a model's weights in f16 there (`--half`) needs. `None` for a host device.
pub fn f16_on(device: &burn::tensor::Device) -> Option<bool> {
    cube_client(device).map(|c| f16_shaders(&c))
}

/// Whether the adapter's shaders take f16.
fn f16_shaders(client: &Client) -> bool {
    client.properties().supports_type(ElemType::Float(FloatKind::F16))
}

/// The CubeCL client behind `device` (through a one-element tensor made there); `None` for a host
/// device.
pub(super) fn cube_client(device: &burn::tensor::Device) -> Option<Client> {
    match device.clone().inner().as_dispatch() {
        burn::backend::DispatchDevice::Cube(d) => {
            Some(CubeBackend::float_from_data(TensorData::new(vec![0.0f32], [1]), d).client)
        }
        _ => None,
    }
}

/// What the CubeCL (wgpu) adapter behind `device` offers the op and the port, on one line: its
/// name, native float atomic add, plane (subgroup) operations and their size, cooperative-matrix
/// (tensor core) configurations, the largest buffer binding and shared memory. `None` for a host
/// device. Benchmarks print it above their figures, so each figure says which path ran.
pub fn adapter_report(device: &burn::tensor::Device) -> Option<String> {
    let client = cube_client(device)?;
    let props = client.properties();
    let hw = &props.hardware;
    let plane = if props.features.plane.contains(Plane::Ops) {
        format!("yes, {}-{} wide", hw.plane_size_min, hw.plane_size_max)
    } else {
        "no".to_string()
    };
    Some(format!(
        "adapter `{}`: native f32 atomic add {}, plane ops {plane}, f16 in shaders {}, cooperative-matrix configs {}, \
         largest binding {} MiB, shared memory {} KiB",
        props.identity.name,
        if native_float_add(&client) { "yes" } else { "no (compare-and-swap loop)" },
        if f16_shaders(&client) { "yes" } else { "no" },
        props.features.matmul.cmma.len(),
        props.memory.max_page_size >> 20,
        hw.max_shared_memory_size >> 10,
    ))
}
