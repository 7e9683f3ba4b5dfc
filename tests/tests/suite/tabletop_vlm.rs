//! Training the tabletop LLaVA-OneVision with burn (`chatsplat train-vlm`): a few steps lower the
//! loss equally on ndarray and wgpu; a trained model directory round-trips through the llava-hf
//! loader; packed training batches (either prompt layout) score answers exactly as single-turn
//! inference does.
#![allow(deprecated)]

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData, activation};
use chatsplat_tests::{host, max_abs_diff, temp_dir};
use model::vlm::{LlavaOnevision, PromptLayout};
use train::vlm::batch::{forward, named_objects, pack};
use train::vlm::data::SampleKind;
use train::vlm::{Shape, Trainer, VlmTrainConfig, eval_samples, save_model};

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

#[test]
fn packed_batches_score_answers_as_single_turn_inference_does() {
    let dev = Device::ndarray();
    for layout in [PromptLayout::ImagesFirst, PromptLayout::TextFirst] {
        let cfg = VlmTrainConfig { text_first: layout == PromptLayout::TextFirst, ..tiny_config() };
        let t = Trainer::new(&cfg, &dev).unwrap();
        let m = t.model.valid();
        assert_eq!(m.vlm.tokenizer.layout, layout);
        let samples = eval_samples(t.spec(), 77..79, 1, 1);
        let (s, g2, dv) = (cfg.model.image_size, m.vlm.cfg.vision.tokens(), cfg.model.vision_width);
        for kind in SampleKind::ALL {
            let batch: Vec<_> = samples
                .iter()
                .filter(|x| x.kind == kind)
                .map(|x| (x.clone(), x.qas.iter().take(3).cloned().collect::<Vec<_>>()))
                .collect();
            assert!(batch.len() == 2 && batch.iter().all(|b| !b.1.is_empty()), "{kind:?} samples");
            let p = pack(&m.vlm, &batch).unwrap();
            let packed = host(forward(&m, &p, None, None, &dev).log_probs);
            let vocab = m.vlm.cfg.text.vocab_size;
            let mut q = 0;
            for (sample, qas) in &batch {
                let embeds: Vec<Tensor<2>> = sample
                    .images
                    .iter()
                    .map(|img| {
                        let px = Tensor::<4>::from_data(TensorData::new(img.pixels.clone(), [1, 3, s, s]), &dev);
                        m.vlm.token_embeds(m.vlm.vision.forward(px).reshape([g2, dv]))
                    })
                    .collect();
                for qa in qas {
                    let e = m.vlm.prompt_embeds(&qa.question, &embeds).unwrap();
                    let n = e.dims()[0];
                    let last = activation::log_softmax(m.vlm.logits(e).narrow(0, n - 1, 1), 1);
                    let want = host(last);
                    let row = p.questions[q].1.start;
                    let got = &packed[row * vocab..(row + 1) * vocab];
                    let err = max_abs_diff(got, &want);
                    assert!(
                        err < 1e-4,
                        "{layout:?} {kind:?} {:?}: first answer token log-probs differ by {err}",
                        qa.kind
                    );
                    q += 1;
                }
            }
            assert_eq!(q, p.questions.len());
        }
    }
}

#[test]
fn questions_name_the_objects_the_relevance_loss_looks_for() {
    // (colour, shape) classes, 1-based in Color::ALL / Shape::ALL order as in the token labels
    let (red, blue) = (1, 6);
    let (cube, cone, torus) = (2, 4, 6);
    assert_eq!(named_objects("Is there a red cube?"), [(red, cube)]);
    assert_eq!(named_objects("Is the red cube left of the blue torus?"), [(red, cube), (blue, torus)]);
    assert_eq!(named_objects("What color is the cone?"), [(0, cone)]);
    assert_eq!(named_objects("What shape is the red object?"), [(red, 0)]);
    assert_eq!(named_objects("How many cubes are in the scene?"), [(0, cube)]);
    assert_eq!(named_objects("How many blue objects are in the scene?"), [(blue, 0)]);
    assert!(named_objects("How many objects are there?").is_empty());
    // text first, the relevance targets of a batch mark exactly the tokens labelled with what
    // the question names
    let dev = Device::ndarray();
    let cfg = VlmTrainConfig { text_first: true, ..tiny_config() };
    let t = Trainer::new(&cfg, &dev).unwrap();
    let m = t.model.valid();
    let samples = eval_samples(t.spec(), 90..96, 1, 0);
    let batch: Vec<_> =
        samples.iter().filter(|x| x.kind == SampleKind::View).map(|x| (x.clone(), x.qas.clone())).collect();
    let p = pack(&m.vlm, &batch).unwrap();
    let hits = p.relevance.iter().filter(|r| r.1 == 1.0).count();
    assert!(hits > 0 && hits < p.relevance.len(), "{hits} of {} tokens relevant", p.relevance.len());
    let g2 = m.vlm.cfg.vision.tokens();
    let (mut row, mut want) = (0, 0);
    for (s, qas) in &batch {
        let labels = &s.images[0].labels;
        for qa in qas {
            let named = named_objects(&qa.question);
            if !named.is_empty() {
                want += labels
                    .iter()
                    .filter(|l| {
                        l[0] > 0 && named.iter().any(|&(c, sh)| (c == 0 || c == l[0]) && (sh == 0 || sh == l[1]))
                    })
                    .count();
            }
            row += 1;
        }
    }
    assert_eq!(row, p.rows);
    assert_eq!(hits, want);
    assert_eq!(p.relevance.len() % g2, 0);
}
