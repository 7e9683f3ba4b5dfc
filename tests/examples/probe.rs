use burn::tensor::{Device, DeviceKind};
use chatsplat_tests::*;
use splat_kernels::api::{SplatOptions, splat};
fn main() {
    let wgpu = Device::wgpu(DeviceKind::DefaultDevice);
    let cam = front_camera(97, 61, 70.0);
    let scene = random_scene(150, 16, &cam, 41);
    for dev in [wgpu.clone(), Device::ndarray(), wgpu] {
        let t0 = std::time::Instant::now();
        let (g, bg) = scene.gaussians(&dev);
        let out = splat(&g, &cam, bg, &SplatOptions::default()).unwrap();
        let f = host(out.features);
        let s: f32 = f.iter().sum();
        println!("{:?}: sum {s} first {:?} in {:?}", dev, &f[3000..3004], t0.elapsed());
    }
}
