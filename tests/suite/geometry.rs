//! The geometry stage on a tiny built-in synthetic scene: training raises PSNR and learns the
//! identity masks, checkpoint/resume reproduces the run exactly, densification keeps burn Adam's
//! moments aligned with their Gaussians, `.ply` export/import round-trips bit-exactly.
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use chatsplat_tests::{host, temp_dir};
use model::data::nerfstudio::{Dataset, LoadOptions, load};
use model::run::GeometryRun;
use model::splats::{SplatModel, SplatParams};
use train::geometry::{GeometryConfig, GeometryTrainer, data_ref, ssim, view_at};

/// The tensors of a model in name order, on the host.
fn rows(m: &SplatModel) -> Vec<Vec<f32>> {
    m.tensors().into_named().into_iter().map(|(_, t)| host(t)).collect()
}

fn tiny_scene(tag: &str, views: usize) -> Dataset {
    let dir = temp_dir(tag);
    let opts = model::data::synth::SynthOptions { views, width: 48, height: 40, ..Default::default() };
    model::data::synth::write_dataset(&dir, &opts, |_, _| {}).unwrap();
    load(&dir, &LoadOptions { holdout_every: 8, ..Default::default() }).unwrap()
}

fn cfg(iters: usize) -> GeometryConfig {
    GeometryConfig {
        iters,
        init_per_view: 400,
        densify_from: 30,
        densify_every: 30,
        densify_until: 1000,
        opacity_reset_every: 0,
        sh_degree_every: 60,
        checkpoint_every: 0,
        max_gaussians: 5000,
        ..Default::default()
    }
}

fn train(t: &mut GeometryTrainer, ds: &Dataset, iters: usize) {
    for _ in 0..iters {
        let v = &ds.train[view_at(t.iter, ds.train.len(), t.cfg.seed)];
        t.step(v).unwrap();
    }
}

#[test]
fn ssim_is_one_for_equal_images_and_drops_with_noise() {
    let dev = Device::ndarray();
    let mut r = model::rng::Rng::new(3);
    let a: Vec<f32> = (0..32 * 24 * 3).map(|_| r.f()).collect();
    let noisy: Vec<f32> = a.iter().map(|v| (v + 0.8 * (r.f() - 0.5)).clamp(0.0, 1.0)).collect();
    let t = |v: &Vec<f32>| Tensor::<3>::from_data(TensorData::new(v.clone(), [24, 32, 3]), &dev);
    let same = host(ssim(t(&a), t(&a)))[0];
    let diff = host(ssim(t(&a), t(&noisy)))[0];
    assert!((same - 1.0).abs() < 1e-5, "{same}");
    assert!(diff < 0.95 && diff > 0.0, "{diff}");
}

#[test]
fn short_training_raises_psnr_and_learns_identity() {
    let ds = tiny_scene("geo-train", 10);
    let dev = Device::ndarray();
    let mut t = GeometryTrainer::new(&ds, cfg(150), &dev).unwrap();
    let before = t.evaluate(&ds.train).unwrap();
    let n0 = t.model.len();
    train(&mut t, &ds, 150);
    let after = t.evaluate(&ds.train).unwrap();
    let held = t.evaluate(&ds.test).unwrap();
    eprintln!(
        "PSNR {:.2} -> {:.2} dB (held-out {:.2}), mIoU {:?} -> {:?}, N {n0} -> {}",
        before.psnr,
        after.psnr,
        held.psnr,
        before.miou,
        after.miou,
        t.model.len()
    );
    // Deterministic run (CPU path): measured 15.54 -> 19.67 dB (held-out 18.08), mIoU 0.11 -> 0.78
    // (with the 50° cameras' smaller objects: 14.65 -> 18.62, mIoU 0.14 -> 0.83; objects that fill
    // more of the frame leave more for 10 views and 150 iterations to get right on a novel view).
    assert!(after.psnr > before.psnr + 3.0, "PSNR {} -> {}", before.psnr, after.psnr);
    assert!(after.miou.unwrap() > 0.6, "mIoU {:?}", after.miou);
    assert!(held.psnr > before.psnr + 2.0, "held-out PSNR {} -> {}", before.psnr, held.psnr);
    assert_ne!(t.model.len(), n0, "densification changed the Gaussian count");
    // Object masks come from the identity channels alone: the same ids as the full render's.
    for v in &ds.test {
        let full = t.render(&v.camera).unwrap().ids;
        assert!(full.iter().any(|&i| i != 0), "an object is in view");
        assert_eq!(t.model.render_ids(&v.camera).unwrap(), full);
    }
}

#[test]
fn checkpoint_resume_gives_the_same_parameters() {
    let ds = tiny_scene("geo-resume", 6);
    let dev = Device::ndarray();
    let run_dir = temp_dir("geo-resume-run");
    let run = GeometryRun::new(&run_dir);
    let data = data_ref(&ds, std::path::Path::new("scene"), &LoadOptions::default(), &run);
    let mut a = GeometryTrainer::new(&ds, cfg(80), &dev).unwrap();
    train(&mut a, &ds, 25);
    a.save(&run, &data).unwrap();
    train(&mut a, &ds, 15); // crosses a densification step (iteration 30)
    let (mut b, stored) = GeometryTrainer::load(&run, &dev).unwrap();
    assert_eq!(b.iter, 25);
    assert_eq!(stored, data);
    train(&mut b, &ds, 15);
    assert_eq!(a.model.len(), b.model.len());
    assert_eq!(rows(&a.model), rows(&b.model), "resumed run diverged");
    // A damaged checkpoint is a clear error, not a panic.
    let ck = run.checkpoint();
    let len = std::fs::metadata(&ck).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&ck).unwrap().set_len(len / 2).unwrap();
    let e = GeometryTrainer::load(&run, &dev).err().unwrap().to_string();
    assert!(e.contains("checkpoint.safetensors"), "{e}");
}

#[test]
fn densification_keeps_adam_moments_aligned() {
    let ds = tiny_scene("geo-densify", 4);
    let dev = Device::ndarray();
    let mut c = cfg(100);
    c.densify_from = 10_000; // only the explicit call below densifies
    let mut t = GeometryTrainer::new(&ds, c, &dev).unwrap();
    train(&mut t, &ds, 5);
    let n = t.model.len();
    let names = &SplatParams::<()>::NAMES[..7];
    let before: Vec<Vec<f32>> = rows(&t.model)[..7].to_vec();
    // Parameters that got gradients have Adam state (sh_rest is unused at SH degree 0).
    let tracked: Vec<usize> = (0..7).filter(|&p| t.states.get(names[p]).is_some()).collect();
    assert!(tracked.contains(&0) && tracked.contains(&3) && tracked.contains(&6), "{tracked:?}");
    let moment = |t: &GeometryTrainer, p: usize| -> Vec<f32> {
        t.states.get(names[p]).map(|s| host(s.momentum.moment_1.clone())).unwrap_or_default()
    };
    let m1: Vec<Vec<f32>> = (0..7).map(|p| moment(&t, p)).collect();
    // Gaussian 0: large gradient + small -> clone; 1: large gradient + big -> split; 2: transparent -> pruned.
    t.screen.norm_sum = vec![0.0; n];
    t.screen.count = vec![1; n];
    t.screen.norm_sum[0] = 1.0;
    t.screen.norm_sum[1] = 1.0;
    let mut tensors = t.model.tensors();
    let mut ls = before[1].clone();
    ls[0..3].copy_from_slice(&[-9.0; 3]);
    ls[3..6].copy_from_slice(&[2.0; 3]);
    tensors.log_scales = Tensor::from_data(TensorData::new(ls.clone(), [n, 3]), &dev);
    let mut op = before[3].clone();
    op[2] = -20.0;
    tensors.opacity_logits = Tensor::from_data(TensorData::new(op, [n, 1]), &dev);
    t.model = SplatModel::from_tensors(tensors);
    t.densify(false);
    let m = t.model.len();
    assert_eq!(m, n + 1, "clone adds one, split replaces one by two, prune removes one");
    let after: Vec<Vec<f32>> = rows(&t.model)[..7].to_vec();
    let m1_after: Vec<Vec<f32>> = (0..7).map(|p| moment(&t, p)).collect();
    // Output order: kept 0, clone of 0, split children of 1 (x2), then 3.. kept (2 pruned).
    for p in 0..7 {
        let w = SplatParams::<()>::row_width(names[p]);
        assert_eq!(after[p].len(), m * w);
        assert_eq!(&after[p][4 * w..], &before[p][3 * w..]);
        if !tracked.contains(&p) {
            continue;
        }
        assert_eq!(m1_after[p].len(), m * w, "moments of {p} follow the Gaussian count");
        assert_eq!(&m1_after[p][..w], &m1[p][..w], "kept Gaussian 0 keeps its moments");
        assert!(m1_after[p][w..4 * w].iter().all(|v| *v == 0.0), "new Gaussians start with zero moments");
        assert_eq!(&m1_after[p][4 * w..], &m1[p][3 * w..], "the rest keep theirs, shifted past the pruned one");
    }
    assert_eq!(&after[0][3..6], &before[0][0..3], "the clone sits on its source");
    let shrunk = 2.0 - 1.6f32.ln();
    assert!((after[1][6] - shrunk).abs() < 1e-6 && (after[1][9] - shrunk).abs() < 1e-6, "split children shrink by 1.6");
    assert_ne!(&after[0][6..9], &after[0][9..12], "split children are sampled apart");
}

#[test]
fn ply_export_import_round_trips_bit_exactly() {
    let ds = tiny_scene("geo-ply", 3);
    let dev = Device::ndarray();
    let mut t = GeometryTrainer::new(&ds, cfg(10), &dev).unwrap();
    train(&mut t, &ds, 3);
    let (cloud, cls) = t.model.to_cloud();
    let path = temp_dir("geo-ply-out.ply");
    model::ply::write(&path, &cloud).unwrap();
    let back = model::ply::read(&path).unwrap();
    assert_eq!(back, cloud);
    let m2 = SplatModel::from_cloud(&back, Some(&cls), t.model.num_classes(), &dev);
    assert_eq!(rows(&t.model), rows(&m2));
}

#[test]
fn colmap_points_initialise_the_gaussians() {
    use model::data::colmap::SparsePoints;
    use train::geometry::{SceneExtent, initial_cloud};
    let ds = tiny_scene("geo-init", 3);
    let pts = SparsePoints { xyz: vec![[0.1, 0.2, 0.3], [-1.0, 0.5, 2.0]], rgb: vec![[255, 0, 0], [0, 128, 255]] };
    let cams: Vec<_> = ds.train.iter().map(|v| &v.camera).collect();
    let c = initial_cloud(&ds.train, Some(&pts), &SceneExtent::from_cameras(&cams), &cfg(1));
    assert_eq!(c.means, pts.xyz);
    let rgb = c.colors();
    assert!((rgb[0][0] - 1.0).abs() < 1e-5 && rgb[0][1].abs() < 1e-5 && (rgb[1][1] - 128.0 / 255.0).abs() < 1e-5);
    // Without points, the synthetic scene's depth maps are back-projected onto its surfaces:
    // every initial point lies inside the table's footprint (x, z within the table half-size) or above it.
    let d = initial_cloud(&ds.train, None, &SceneExtent::from_cameras(&cams), &cfg(1));
    assert!(d.len() > 100);
    let half = model::data::synth::scene::SynthScene::from_seed(model::data::synth::DEFAULT_SEED).table.half;
    let inside =
        d.means.iter().filter(|m| m[0].abs() <= half * 1.05 + 0.05 && m[2].abs() <= half * 1.05 + 0.05).count();
    assert!(inside as f32 > 0.95 * d.len() as f32, "{inside} of {} depth points on the table", d.len());
}

#[test]
fn wgpu_training_lowers_the_loss() {
    let Some(dev) = chatsplat_tests::wgpu_device() else { return };
    let ds = tiny_scene("geo-wgpu", 4);
    let mut c = cfg(40);
    c.densify_from = 20;
    c.densify_every = 20;
    let mut t = GeometryTrainer::new(&ds, c, &dev).unwrap();
    let before = t.evaluate(&ds.train).unwrap();
    train(&mut t, &ds, 40);
    let after = t.evaluate(&ds.train).unwrap();
    eprintln!("wgpu PSNR {:.2} -> {:.2}", before.psnr, after.psnr);
    assert!(after.psnr > before.psnr + 1.0, "PSNR {} -> {}", before.psnr, after.psnr);
}
