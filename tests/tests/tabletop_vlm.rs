//! Training the tabletop LLaVA-OneVision with burn (`chatsplat train-vlm`): a few steps lower the
//! loss equally on ndarray and wgpu; a trained model directory round-trips through the llava-hf
//! loader.
#![allow(deprecated)]

use burn::tensor::Device;
use chatsplat_tests::{host, max_abs_diff, temp_dir};
use model::vlm::LlavaOnevision;
use train::vlm::{Shape, Trainer, VlmTrainConfig, save_model};

fn tiny_config() -> VlmTrainConfig {
    VlmTrainConfig {
        seed: 3,
        model: Shape {
            image_size: 48,
            patch_size: 12,
            vision_width: 32,
            vision_layers: 2,
            vision_heads: 2,
            vision_mlp: 64,
            text_width: 32,
            text_layers: 2,
            text_heads: 2,
            text_kv_heads: 1,
            text_mlp: 64,
        },
        images_per_step: 4,
        questions_per_sample: 3,
        resolution: 48,
        lr: 3e-3,
        warmup: 1,
        ..Default::default()
    }
}

#[test]
fn training_lowers_the_loss_equally_on_ndarray_and_wgpu() {
    let cfg = tiny_config();
    let run = |dev: &Device| {
        let mut t = Trainer::new(&cfg, dev).unwrap();
        (0..5).map(|_| t.step().unwrap().0).collect::<Vec<f32>>()
    };
    let cpu = run(&Device::ndarray());
    eprintln!("ndarray answer losses {cpu:?}");
    assert!(cpu[4] < cpu[0], "the loss falls: {cpu:?}");
    let Some(wgpu) = chatsplat_tests::wgpu_device() else { return };
    let gpu = run(&wgpu);
    eprintln!("wgpu answer losses {gpu:?}");
    for (a, b) in cpu.iter().zip(&gpu) {
        assert!((a - b).abs() <= 1e-3 * a.abs().max(1.0), "ndarray {cpu:?} vs wgpu {gpu:?}");
    }
}

#[test]
fn a_trained_model_directory_round_trips_through_the_loader() {
    let dev = Device::ndarray();
    let cfg = tiny_config();
    let t = Trainer::new(&cfg, &dev).unwrap();
    let trained = burn::module::Module::valid(&t.model);
    let dir = temp_dir("tabletop-vlm-save");
    let params = save_model(&trained.vlm, &dir).unwrap();
    assert!(params > 10_000);
    let back = LlavaOnevision::load(&dir, &dev).unwrap();
    assert_eq!(back.cfg, trained.vlm.cfg);
    let img = model::vlm::RgbImage::new(48, 48, (0..48 * 48 * 3).map(|i| (i * 7 % 251) as u8).collect());
    let logits = |m: &LlavaOnevision| {
        let tokens = m.teacher_tokens(&img);
        let embeds = m.prompt_embeds("How many objects are there?", &[m.token_embeds(tokens)]).unwrap();
        host(m.logits(embeds))
    };
    let (a, b) = (logits(&trained.vlm), logits(&back));
    assert!(max_abs_diff(&a, &b) < 1e-5, "logits differ by {}", max_abs_diff(&a, &b));
    // the word-level tokenizer: every question word is known, answers decode to their words
    let ids = back.tokenizer.encode("Is the red cube left of the blue torus?").unwrap();
    assert!(!ids.contains(&5), "no <unk>: {ids:?}");
    assert_eq!(
        back.tokenizer.decode(&back.tokenizer.encode("small red cube").unwrap(), true).unwrap(),
        "small red cube"
    );
    std::fs::remove_dir_all(&dir).ok();
}
