//! Training the tabletop LLaVA-OneVision with burn (`chatsplat train-vlm`): a few steps lower the
//! loss equally on ndarray and wgpu; a trained model directory round-trips through the llava-hf
//! loader; packed training batches score answers exactly as single-turn inference does; the
//! supervised hops of a packed batch point at the tokens of the objects the questions name; the
//! committed model (checkpoints/tabletop-llava-ov) answers held-out scenes, from ground-truth
//! images and, end to end, from ChatSplat's tokens.
#![allow(deprecated)]

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData, activation};
use chatsplat_tests::{Scratch, host, max_abs_diff, temp_dir};
use model::vlm::LlavaOnevision;
use train::dist::Solo;
use train::vlm::data::SampleKind;
use train::vlm::forward::forward;
use train::vlm::hops::{HopKind, SINK};
use train::vlm::pack::pack;
use train::vlm::{HEADS_FILE, RunningAccuracy, Shape, Trainer, VlmTrainConfig, eval_samples, save_model, train_from};

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
            text_layers: 3,
            text_heads: 4,
            text_kv_heads: 2,
            text_mlp: 64,
        },
        images_per_step: 4,
        questions_per_sample: 3,
        resolution: 48,
        lr: 3e-3,
        warmup: 1,
        // every head the trainer has, so that the backend-swapped test covers them all
        place_weight: 0.3,
        ..Default::default()
    }
}

#[test]
fn training_lowers_the_loss_equally_on_ndarray_and_wgpu() {
    let cfg = tiny_config();
    let run = |dev: &Device| {
        let mut t = Trainer::new(&cfg, dev).unwrap();
        (0..5).map(|_| t.step(&Solo).unwrap().answer).collect::<Vec<f32>>()
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
fn the_tower_phase_and_the_full_phase_each_warm_up_then_decay_to_their_floor() {
    let cfg = VlmTrainConfig {
        steps: 300,
        tower_steps: 100,
        warmup: 10,
        lr: 1e-3,
        min_lr: 1e-4,
        tower_lr: 2e-3,
        tower_min_lr: 2e-4,
        ..Default::default()
    };
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9;
    assert!(close(cfg.lr_at(0), 2e-4), "tower warm-up starts at peak / warmup: {}", cfg.lr_at(0));
    assert!(close(cfg.lr_at(9), 2e-3), "tower peak after the warm-up: {}", cfg.lr_at(9));
    assert!(cfg.lr_at(50) < 2e-3 && cfg.lr_at(50) > 2e-4, "tower decays: {}", cfg.lr_at(50));
    assert!((cfg.lr_at(99) - 2e-4).abs() < 1e-6, "tower phase ends near its floor: {}", cfg.lr_at(99));
    assert!(close(cfg.lr_at(100), 1e-4), "the full phase warms up again: {}", cfg.lr_at(100));
    assert!(close(cfg.lr_at(109), 1e-3), "full peak: {}", cfg.lr_at(109));
    assert!((cfg.lr_at(299) - 1e-4).abs() < 1e-6, "full phase ends near min_lr: {}", cfg.lr_at(299));
    // no tower floor: the tower phase stays at its peak, as the committed model was trained
    let constant = VlmTrainConfig { tower_min_lr: 0.0, ..cfg.clone() };
    assert!(close(constant.lr_at(99), 2e-3), "constant tower phase: {}", constant.lr_at(99));
    assert!(close(constant.lr_at(150), cfg.lr_at(150)), "the full phase does not depend on it");
}

#[test]
fn after_its_phase_the_tower_learns_at_tower_lr_scale_times_the_rate() {
    let dev = Device::ndarray();
    // one tower step, then a full step; a frozen tower (scale 0) against one that learns (scale 1)
    let run = |scale: f64| {
        let cfg = VlmTrainConfig { steps: 4, tower_steps: 1, tower_images: 2, tower_lr_scale: scale, ..tiny_config() };
        let mut t = Trainer::new(&cfg, &dev).unwrap();
        t.step(&Solo).unwrap();
        let vision = |t: &Trainer| host(t.model.vlm.vision.patch.weight.val());
        let llm = |t: &Trainer| host(t.model.vlm.llm.layers[0].q.weight.val());
        let (v0, l0) = (vision(&t), llm(&t));
        t.step(&Solo).unwrap();
        (max_abs_diff(&v0, &vision(&t)), max_abs_diff(&l0, &llm(&t)))
    };
    let (frozen_vision, frozen_llm) = run(0.0);
    let (vision, llm) = run(1.0);
    eprintln!(
        "full-phase weight changes: scale 0 vision {frozen_vision} llm {frozen_llm}; scale 1 vision {vision} llm {llm}"
    );
    assert_eq!(frozen_vision, 0.0, "scale 0 keeps the tower as its phase left it");
    assert!(vision > 1e-4, "scale 1 trains the tower: {vision}");
    let alike = (frozen_llm - llm).abs() <= 1e-6 * llm.max(1.0);
    assert!(frozen_llm > 1e-4 && alike, "the LLM's step does not depend on it: {frozen_llm} vs {llm}");
}

#[test]
fn a_stage_chain_trains_its_base_first_or_reads_it_from_a_model_trained_with_it() {
    let dev = Device::ndarray();
    let base = VlmTrainConfig { steps: 2, eval_every: 0, eval_seeds: 1, ..tiny_config() };
    let stage = VlmTrainConfig { seed: 4, lr: 1e-3, base: Some(Box::new(base.clone())), ..base.clone() };
    // one command: the base stage trains into out/base, then the stage starts from its weights
    let whole = temp_dir("vlm-stages-whole");
    let mut seen = Vec::new();
    train_from(&stage, &whole, None, &dev, &Solo, false, |l| seen.push((l.step, l.steps))).unwrap();
    assert_eq!(seen, [(1, 2), (2, 2), (1, 2), (2, 2)], "progress sees both stages' steps");
    assert!(whole.join("base/model.safetensors").is_file(), "the base stage's model is kept");
    // the same stage from the base's model read back: the same weights, bit for bit
    let again = temp_dir("vlm-stages-again");
    train_from(&stage, &again, Some(&whole.join("base")), &dev, &Solo, false, |_| {}).unwrap();
    assert!(!again.join("base").exists(), "the base stage is read, not trained again");
    let weights = |d: &std::path::Path| std::fs::read(d.join("model.safetensors")).unwrap();
    assert!(weights(&whole) == weights(&again), "reading the base gives the chain's own result");
    assert!(weights(&whole) != weights(&whole.join("base")), "the stage trained on from its base");
    // a model trained with this very configuration, or with none of its stages, is refused
    // before anything is trained
    let refused = temp_dir("vlm-stages-refused");
    let e = train_from(&stage, &refused, Some(&whole), &dev, &Solo, false, |_| {}).unwrap_err().to_string();
    assert!(e.contains("train_config.json") && e.contains("this very configuration"), "{e}");
    let other = VlmTrainConfig { seed: 5, ..stage.clone() };
    let e = train_from(&other, &refused, Some(&whole), &dev, &Solo, false, |_| {}).unwrap_err().to_string();
    assert!(e.contains("train_config.json") && e.contains("none of this configuration's stages"), "{e}");
    assert!(!refused.join("base").exists(), "nothing trained: {e}");
    // edge supersampling out of range is refused, naming the key
    for supersample in [0, 9] {
        let e = VlmTrainConfig { supersample, ..base.clone() }.validate().unwrap_err().to_string();
        assert!(e.contains("supersample"), "{e}");
    }
    // and a base of another shape is refused by validation
    let mut wide = base.clone();
    wide.model.text_width = 64;
    let e = VlmTrainConfig { base: Some(Box::new(wide)), ..base }.validate().unwrap_err().to_string();
    assert!(e.contains("base.model"), "{e}");
}

#[test]
fn a_stage_with_carry_heads_starts_from_the_heads_its_base_stage_wrote() {
    let dev = Device::ndarray();
    // a base whose tower phase teaches the auxiliary head to read the tower
    let base =
        VlmTrainConfig { steps: 24, tower_steps: 20, tower_images: 4, eval_every: 0, eval_seeds: 1, ..tiny_config() };
    let out = temp_dir("vlm-heads-base");
    train_from(&base, &out, None, &dev, &Solo, false, |_| {}).unwrap();
    assert!(out.join(HEADS_FILE).is_file(), "every stage keeps its heads beside its model");
    let stage = |carry_heads: bool| VlmTrainConfig {
        seed: 4,
        steps: 2,
        tower_steps: 0,
        carry_heads,
        base: Some(Box::new(base.clone())),
        ..base.clone()
    };
    // the auxiliary loss of the stage's first step (taken before its update)
    let first_aux = |carry_heads: bool, name: &str| {
        let mut aux = Vec::new();
        train_from(&stage(carry_heads), &temp_dir(name), Some(&out), &dev, &Solo, false, |l| aux.push(l.aux_loss))
            .map(|_| aux[0])
    };
    let (fresh, carried) =
        (first_aux(false, "vlm-heads-fresh").unwrap(), first_aux(true, "vlm-heads-carried").unwrap());
    eprintln!("first auxiliary loss of the next stage: fresh heads {fresh}, carried heads {carried}");
    assert!(carried < 0.7 * fresh, "the carried head already reads the tower: {carried} vs fresh {fresh}");
    // a base without its heads is refused, naming the file
    std::fs::remove_file(out.join(HEADS_FILE)).unwrap();
    let e = first_aux(true, "vlm-heads-missing").unwrap_err().to_string();
    assert!(e.contains(HEADS_FILE) && e.contains("carry_heads"), "{e}");
    assert!(first_aux(false, "vlm-heads-fresh-again").is_ok(), "fresh heads need no file");
    // and a first stage has no heads to carry
    let e = VlmTrainConfig { carry_heads: true, ..base }.validate().unwrap_err().to_string();
    assert!(e.contains("carry_heads"), "{e}");
}

#[test]
fn a_run_stopped_midway_resumes_from_its_checkpoint_to_the_same_weights() {
    let dev = Device::ndarray();
    let cfg = VlmTrainConfig {
        steps: 6,
        tower_steps: 2,
        tower_images: 4,
        tower_lr_scale: 0.5,
        checkpoint_every: 3,
        eval_every: 0,
        eval_seeds: 1,
        ..tiny_config()
    };
    let whole = temp_dir("vlm-resume-whole");
    train_from(&cfg, &whole, None, &dev, &Solo, false, |_| {}).unwrap();
    assert!(!train::vlm::checkpoint::exists(&whole), "a finished stage keeps no checkpoint");
    // stopped during step 4 (its last checkpoint is step 3's): a panic where progress is reported
    let stopped = temp_dir("vlm-resume-stopped");
    let run = std::panic::AssertUnwindSafe(|| {
        train_from(&cfg, &stopped, None, &dev, &Solo, false, |l| assert!(l.step < 4, "stopped")).unwrap()
    });
    assert!(std::panic::catch_unwind(run).is_err());
    assert!(train::vlm::checkpoint::exists(&stopped) && !stopped.join("model.safetensors").exists());
    let mut steps = Vec::new();
    train_from(&cfg, &stopped, None, &dev, &Solo, true, |l| steps.push(l.step)).unwrap();
    assert_eq!(steps, [4, 5, 6], "it goes on after the checkpoint");
    let read = |d: &std::path::Path, f: &str| std::fs::read(d.join(f)).unwrap();
    assert!(read(&whole, "model.safetensors") == read(&stopped, "model.safetensors"), "the same weights, bit for bit");
    let losses = |d: &std::path::Path| -> Vec<(u64, f64)> {
        let v: serde_json::Value = serde_json::from_slice(&read(d, "training_log.json")).unwrap();
        v.as_array()
            .unwrap()
            .iter()
            .map(|l| (l["step"].as_u64().unwrap(), l["answer_loss"].as_f64().unwrap()))
            .collect()
    };
    assert_eq!(losses(&whole), losses(&stopped), "the log goes on where it stopped");
    // a finished run resumes to nothing; nothing to resume is an error naming the folder
    let mut more = 0;
    train_from(&cfg, &stopped, None, &dev, &Solo, true, |_| more += 1).unwrap();
    assert_eq!(more, 0);
    let empty = temp_dir("vlm-resume-empty");
    let e = train_from(&cfg, &empty, None, &dev, &Solo, true, |_| {}).unwrap_err().to_string();
    assert!(e.contains("vlm-resume-empty") && e.contains("nothing") || e.contains("no train-vlm run"), "{e}");
}

#[test]
fn kind_weights_make_a_kind_that_lags_picked_more_often() {
    use model::data::synth::questions::Kind;
    let cfg = tiny_config();
    let spec = train::vlm::data::DataSpec::new(
        &train::vlm::init_model(&cfg, &Device::ndarray()).unwrap().cfg,
        &cfg.processor(),
        cfg.resolution,
        cfg.margin,
    );
    let running = RunningAccuracy::default();
    let share = |weights: &[(Kind, f32)]| {
        let cfg = VlmTrainConfig { kind_weights: weights.iter().copied().collect(), ..cfg.clone() };
        let (mut rng, mut left_of, mut all) = (model::rng::Rng::new(5), 0, 0);
        for seed in 0..40 {
            let Some(s) = spec.sample(SampleKind::View, 20_000 + seed, &mut rng) else { continue };
            let picked = train::vlm::data::pick_questions(&s.qas, 3, |k| cfg.question_weight(k, &running), &mut rng);
            left_of += picked.iter().filter(|q| q.kind == Kind::LeftOf).count();
            all += picked.len();
        }
        left_of as f64 / all.max(1) as f64
    };
    let (plain, weighted) = (share(&[]), share(&[(Kind::LeftOf, 4.0)]));
    eprintln!("left_of share of picked view questions: {plain:.3} plain, {weighted:.3} weighted 4x");
    assert!(plain > 0.02 && weighted > 2.0 * plain, "plain {plain:.3}, weighted {weighted:.3}");
}

/// `small_views` draws views without a small object again: the share of a step's views with an
/// object under `SMALL_OBJECT` pixels goes from about half (96-px renders) to nearly all.
#[test]
fn small_views_fills_a_step_with_views_of_a_small_object() {
    let share = |small_views: f32| {
        let cfg = VlmTrainConfig { small_views, mix: [1.0, 0.0, 0.0], images_per_step: 48, ..Default::default() };
        cfg.validate().unwrap();
        let spec = train::vlm::data::DataSpec::of(&cfg, &cfg.llava_config(64), &cfg.processor());
        let samples = train::vlm::step_samples(&cfg, &spec, &RunningAccuracy::default(), &mut model::rng::Rng::new(7));
        let small = samples.iter().filter(|(s, _)| s.smallest.is_some_and(|px| px < train::vlm::SMALL_OBJECT)).count();
        small as f64 / samples.len() as f64
    };
    let (off, on) = (share(0.0), share(0.9));
    eprintln!("views with a small object: {off:.2} as drawn, {on:.2} with small_views 0.9");
    assert!(on > 0.85 && on > off + 0.2, "{on:.2} with the knob, {off:.2} without");
    let bad = VlmTrainConfig { small_views: 1.0, ..Default::default() };
    assert!(bad.validate().unwrap_err().to_string().contains("small_views"));
}

/// With `two_turn`, second turns are tracked apart from single questions: a kind its single
/// questions get right but its follow-ups do not still needs drawing, and of a sample's follow-ups
/// the ones of such a kind are drawn most (a step of object samples: "What size is it?"). Scene
/// samples stay single-turn.
#[test]
fn second_turns_are_drawn_by_what_their_own_accuracy_still_needs() {
    use model::data::synth::questions::Kind;
    let mut running = RunningAccuracy::default();
    for _ in 0..200 {
        for k in [Kind::Name, Kind::Color, Kind::Shape, Kind::Size] {
            running.add(k, true);
        }
        running.add_second(Kind::Color, true);
        running.add_second(Kind::Shape, true);
    }
    let cfg = VlmTrainConfig { two_turn: 1.0, mix: [0.0, 1.0, 0.0], images_per_step: 48, ..Default::default() };
    cfg.validate().unwrap();
    let alone = VlmTrainConfig { two_turn: 0.0, ..cfg.clone() };
    assert!((alone.need(Kind::Size, &running) - alone.need(Kind::Color, &running)).abs() < 1e-6);
    assert!(cfg.need(Kind::Size, &running) > 10.0 * cfg.need(Kind::Color, &running));
    let spec = train::vlm::data::DataSpec::of(&cfg, &cfg.llava_config(64), &cfg.processor());
    let size_share = |running: &RunningAccuracy| {
        let samples = train::vlm::step_samples(&cfg, &spec, running, &mut model::rng::Rng::new(9));
        let follow_ups: Vec<_> = samples
            .iter()
            .flat_map(|(_, qs)| qs)
            .filter(|q| q.follows.is_some() && q.question.ends_with("it?"))
            .collect();
        let size = follow_ups.iter().filter(|q| q.kind == Kind::Size).count();
        assert!(follow_ups.len() > 20, "{} follow-ups drawn", follow_ups.len());
        size as f64 / follow_ups.len() as f64
    };
    let (fresh, needed) = (size_share(&RunningAccuracy::default()), size_share(&running));
    eprintln!(
        "size follow-ups: {fresh:.2} of the follow-ups drawn afresh, {needed:.2} once colour and shape are right"
    );
    assert!((0.15..0.5).contains(&fresh) && needed > 0.7, "{fresh:.2} afresh, {needed:.2} when needed");
    let scenes = VlmTrainConfig { mix: [0.0, 0.0, 1.0], images_per_step: 8, ..cfg.clone() };
    let drawn = train::vlm::step_samples(&scenes, &spec, &running, &mut model::rng::Rng::new(9));
    let asked: Vec<_> = drawn.iter().flat_map(|(s, qs)| qs.iter().map(move |q| (s.kind, q))).collect();
    assert!(!asked.is_empty());
    for (kind, q) in asked {
        assert!(kind == SampleKind::Scene && q.follows.is_none(), "{kind:?}: {} asked as a second turn", q.question);
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

/// The LLM's input embeddings of each of `sample`'s images, through the vision tower.
fn image_embeds(vlm: &LlavaOnevision, sample: &train::vlm::data::Sample, dev: &Device) -> Vec<Tensor<2>> {
    let (g2, dv) = (vlm.cfg.vision.tokens(), vlm.cfg.vision.hidden_size);
    let s = vlm.cfg.vision.image_size;
    sample
        .images
        .iter()
        .map(|img| {
            let px = Tensor::<4>::from_data(TensorData::new(img.pixels.clone(), [1, 3, s, s]), dev);
            vlm.token_embeds(vlm.vision.forward(px).reshape([g2, dv]))
        })
        .collect()
}

#[test]
fn packed_batches_score_answers_as_single_turn_inference_does() {
    let dev = Device::ndarray();
    let cfg = tiny_config();
    let t = Trainer::new(&cfg, &dev).unwrap();
    let m = t.model.valid();
    let samples = eval_samples(t.spec(), 77..79, 1, 1);
    for kind in SampleKind::ALL {
        let batch: Vec<_> = samples
            .iter()
            .filter(|x| x.kind == kind)
            .map(|x| (x.clone(), x.qas.iter().take(3).cloned().collect::<Vec<_>>()))
            .collect();
        assert!(batch.len() == 2 && batch.iter().all(|b| !b.1.is_empty()), "{kind:?} samples");
        let p = pack(&m.vlm, &batch).unwrap();
        let packed = host(forward(&m, &p, None, None, false, None, &dev).unwrap().log_probs);
        let vocab = m.vlm.cfg.text.vocab_size;
        let mut q = 0;
        for (sample, qas) in &batch {
            let embeds = image_embeds(&m.vlm, sample, &dev);
            for qa in qas {
                let e = m.vlm.prompt_embeds(&qa.question, &embeds).unwrap();
                let n = e.dims()[0];
                let last = activation::log_softmax(m.vlm.logits(e).narrow(0, n - 1, 1), 1);
                let want = host(last);
                let row = p.questions[q].1.start;
                let got = &packed[row * vocab..(row + 1) * vocab];
                let err = max_abs_diff(got, &want);
                assert!(err < 1e-4, "{kind:?} {:?}: first answer token log-probs differ by {err}", qa.kind);
                q += 1;
            }
        }
        assert_eq!(q, p.questions.len());
    }
}

/// A tiny model trained two steps into `base` of a fresh temporary directory named `name`: its
/// configuration and that directory (later stages start from `DIR/base`; removed when dropped).
fn two_step_base(name: &str, dev: &Device) -> (VlmTrainConfig, Scratch) {
    let base = VlmTrainConfig { steps: 2, eval_every: 0, eval_seeds: 1, ..tiny_config() };
    let out = temp_dir(name);
    train_from(&base, &out.join("base"), None, dev, &Solo, false, |_| {}).unwrap();
    (base, out)
}

/// The flat weights of the models in `out`'s folders `dirs` (of one shape; the first two differ).
fn three_models(out: &std::path::Path, dirs: [&str; 3], dev: &Device) -> [Vec<f32>; 3] {
    let m = dirs.map(|d| train::dist::flat_params(&LlavaOnevision::load(&out.join(d), dev).unwrap()));
    assert!(m[0].len() == m[1].len() && m[1].len() == m[2].len() && m[0].len() > 10_000);
    let apart = m[0].iter().zip(&m[1]).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(apart > 1e-4, "{} and {} hold the same weights ({apart})", dirs[0], dirs[1]);
    m
}

/// Every weight of `got` is `want` of the same weight of `a` and `b`, to f32 rounding.
fn assert_made_of(a: &[f32], b: &[f32], got: &[f32], want: impl Fn(f32, f32) -> f32) {
    for ((x, y), z) in a.iter().zip(b).zip(got) {
        let w = want(*x, *y);
        assert!((z - w).abs() <= 1e-6 * (1.0 + w.abs()), "{z} against {w}, made of {x} and {y}");
    }
}

/// `keep_base` ends a stage with every weight moved that share back to its base stage's: the model
/// it saves is the blend of the base and the same stage trained without it.
#[test]
fn keep_base_ends_a_stage_blended_with_its_start() {
    let dev = Device::ndarray();
    let (base, out) = two_step_base("vlm-keep-base", &dev);
    let plain = VlmTrainConfig { seed: 5, base: Some(Box::new(base.clone())), ..base.clone() };
    let kept = VlmTrainConfig { keep_base: 0.25, ..plain.clone() };
    for (c, dir) in [(&plain, "plain"), (&kept, "kept")] {
        train_from(c, &out.join(dir), Some(&out.join("base")), &dev, &Solo, false, |_| {}).unwrap();
    }
    let [b, p, k] = three_models(&out, ["base", "plain", "kept"], &dev);
    assert_made_of(&b, &p, &k, |x, y| 0.25 * x + 0.75 * y);
    let bad = |c: VlmTrainConfig| c.validate().unwrap_err().to_string();
    assert!(bad(VlmTrainConfig { keep_base: 1.0, ..kept.clone() }).contains("keep_base"));
    assert!(bad(VlmTrainConfig { keep_base: 0.5, ..base }).contains("needs a base stage"));
}

/// `soup` ends a stage with the mean of its own run and one run per further seed (each kept in
/// `OUT/soup-seed<N>`, the stage with that seed): the saved model is the average of the stage
/// trained alone and its other run.
#[test]
fn a_soup_stage_ends_with_the_mean_of_its_runs() {
    let dev = Device::ndarray();
    let (base, out) = two_step_base("vlm-soup", &dev);
    let stage = VlmTrainConfig { seed: 5, base: Some(Box::new(base.clone())), ..base.clone() };
    let souped = VlmTrainConfig { soup: vec![6], ..stage.clone() };
    for (c, dir) in [(&stage, "alone"), (&souped, "soup")] {
        train_from(c, &out.join(dir), Some(&out.join("base")), &dev, &Solo, false, |_| {}).unwrap();
    }
    let member: VlmTrainConfig = model::io::read_config(&out.join("soup/soup-seed6/train_config.json")).unwrap();
    assert_eq!(member, VlmTrainConfig { seed: 6, ..stage.clone() }, "the other run is the stage with its seed");
    let [a, b, s] = three_models(&out, ["alone", "soup/soup-seed6", "soup"], &dev);
    assert_made_of(&a, &b, &s, |x, y| ((f64::from(x) + f64::from(y)) / 2.0) as f32);
    // a run stopped after its soup's other run resumes from it (that run is not trained again)
    let member = out.join("resumed/soup-seed6");
    std::fs::create_dir_all(&member).unwrap();
    for f in std::fs::read_dir(out.join("soup/soup-seed6")).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, member.join(f.file_name().unwrap())).unwrap();
    }
    std::fs::write(member.join("model.safetensors"), std::fs::read(out.join("alone/model.safetensors")).unwrap())
        .unwrap();
    train_from(&souped, &out.join("resumed"), Some(&out.join("base")), &dev, &Solo, true, |_| {}).unwrap();
    let resumed = train::dist::flat_params(&LlavaOnevision::load(&out.join("resumed"), &dev).unwrap());
    assert_eq!(resumed, a, "the mean of the seed-5 run and the seed-5 weights put in the other run's place");
    let bad = |soup: Vec<u64>| VlmTrainConfig { soup, ..stage.clone() }.validate().unwrap_err().to_string();
    assert!(bad(vec![5]).contains("soup"), "the stage's own seed");
    assert!(bad(vec![6, 6]).contains("soup"), "a seed twice");
}

/// `frozen` parts end a stage exactly as its base stage left them, while the rest learns; a part
/// the model does not have is refused, naming it.
#[test]
fn frozen_parts_end_a_stage_as_they_started() {
    use train::dist::flat_params as flat;
    let dev = Device::ndarray();
    let (base, out) = two_step_base("vlm-frozen", &dev);
    let frozen = vec!["projector".to_string(), "layer.0".to_string()];
    let stage = VlmTrainConfig { seed: 5, frozen, base: Some(Box::new(base.clone())), ..base.clone() };
    train_from(&stage, &out.join("stage"), Some(&out.join("base")), &dev, &Solo, false, |_| {}).unwrap();
    let load = |d: &str| LlavaOnevision::load(&out.join(d), &dev).unwrap();
    let (b, s) = (load("base"), load("stage"));
    let moved = |x: Vec<f32>, y: Vec<f32>| x.iter().zip(&y).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
    assert_eq!(flat(&s.projector), flat(&b.projector), "the projector is frozen");
    assert_eq!(host(s.image_newline.val()), host(b.image_newline.val()), "the image newline goes with it");
    assert_eq!(flat(&s.llm.layers[0]), flat(&b.llm.layers[0]), "layer 0 is frozen");
    let learnt = moved(flat(&s.llm.layers[1]), flat(&b.llm.layers[1]));
    assert!(learnt > 1e-4, "layer 1 is not frozen and should have moved ({learnt})");
    assert!(moved(flat(&s.llm.embed), flat(&b.llm.embed)) > 1e-4, "the embeddings are not frozen");
    let bad =
        |part: &str| VlmTrainConfig { frozen: vec![part.into()], ..stage.clone() }.validate().unwrap_err().to_string();
    let layers = base.model.text_layers;
    assert!(bad(&format!("layer.{layers}")).contains(&format!("\"layer.{layers}\" is not a part")));
    assert!(bad("vision").contains("frozen"), "the tower has tower_lr_scale");
}

#[test]
fn a_two_turn_stage_grows_the_vocabulary_and_scores_second_turns_as_a_conversation_does() {
    use model::vlm::Exchange;
    let dev = Device::ndarray();
    let (base, out) = two_step_base("vlm-two-turn", &dev);
    let single = LlavaOnevision::load(&out.join("base"), &dev).unwrap();
    assert!(single.tokenizer.id("it").is_none() && !single.converses(), "a single-turn model");
    // "it" is added after every word the model had, its row a copy of "this"
    let grown = train::vlm::conversing(single.clone()).unwrap();
    let (old, it) = (single.cfg.text.vocab_size, grown.tokenizer.id("it").unwrap() as usize);
    assert_eq!((grown.cfg.text.vocab_size, it), (old + 1, old));
    let (w0, w1) = (host(single.llm.embed.weight.val()), host(grown.llm.embed.weight.val()));
    let d = w0.len() / old;
    assert_eq!(&w1[..old * d], &w0[..], "every earlier row is kept");
    let this = single.tokenizer.id("this").unwrap() as usize;
    assert_eq!(&w1[old * d..], &w0[this * d..(this + 1) * d], "\"it\" starts as \"this\"");
    // a two-turn stage trains on from the base and holds conversations
    let stage = VlmTrainConfig { seed: 4, two_turn: 1.0, base: Some(Box::new(base.clone())), ..base.clone() };
    let mut evals = Vec::new();
    let stage_cfg = VlmTrainConfig { eval_every: 2, ..stage.clone() };
    train_from(&stage_cfg, &out, None, &dev, &Solo, false, |l| evals.extend(l.eval.clone())).unwrap();
    let two = LlavaOnevision::load(&out, &dev).unwrap();
    assert!(two.converses() && two.tokenizer.id("it") == Some(old as u32), "the stage's model converses");
    let acc = evals.last().expect("evaluated");
    let follow = acc.follow_up_line().expect("held-out follow-ups are scored");
    assert!(follow.contains("follow_color") && follow.contains("follow_size"), "{follow}");
    let bad = VlmTrainConfig { two_turn: 1.5, ..stage }.validate().unwrap_err().to_string();
    assert!(bad.contains("two_turn"), "{bad}");
    // a packed second turn scores its answer exactly as the conversation's prompt does
    let t = Trainer::starting_from(&base, grown, &dev).unwrap();
    let m = t.model.valid();
    let samples = eval_samples(t.spec(), 77..80, 2, 1);
    let mut asked = 0;
    for kind in [SampleKind::View, SampleKind::Object] {
        let batch: Vec<_> = samples
            .iter()
            .filter(|x| x.kind == kind)
            .map(|x| {
                let mut qas: Vec<_> = x.follow_ups().iter().take(2).map(|f| f.qa(&x.qas)).collect();
                qas.push(x.qas[0].clone()); // a single question beside them
                (x.clone(), qas)
            })
            .collect();
        let p = pack(&m.vlm, &batch).unwrap();
        let packed = host(forward(&m, &p, None, None, false, None, &dev).unwrap().log_probs);
        let vocab = m.vlm.cfg.text.vocab_size;
        let mut q = 0;
        for (sample, qas) in &batch {
            let embeds = image_embeds(&m.vlm, sample, &dev);
            for qa in qas {
                let earlier: Vec<Exchange> = qa
                    .follows
                    .iter()
                    .map(|e| Exchange { question: e.question.clone(), answer: e.answer.clone() })
                    .collect();
                asked += earlier.len();
                let counts: Vec<usize> = embeds.iter().map(|e| e.dims()[0]).collect();
                let ids = m.vlm.conversation_ids(&earlier, &qa.question, &counts).unwrap();
                let e = m.vlm.embed_prompt(&ids, &embeds).unwrap();
                let n = e.dims()[0];
                let want = host(activation::log_softmax(m.vlm.logits(e).narrow(0, n - 1, 1), 1));
                let row = p.questions[q].1.start;
                let err = max_abs_diff(&packed[row * vocab..(row + 1) * vocab], &want);
                assert!(err < 1e-4, "{kind:?} {:?} (after {earlier:?}): log-probs differ by {err}", qa.question);
                q += 1;
            }
        }
    }
    assert!(asked >= 4, "second turns of both levels were checked ({asked})");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn the_places_of_left_of_questions_agree_with_their_answers() {
    use model::data::synth::questions::Kind;
    let dev = Device::ndarray();
    let t = Trainer::new(&tiny_config(), &dev).unwrap();
    let m = t.model.valid();
    let grid = m.vlm.cfg.vision.grid() as i64;
    let samples = eval_samples(t.spec(), 90..110, 1, 0);
    let batch: Vec<_> =
        samples.iter().filter(|x| x.kind == SampleKind::View).map(|x| (x.clone(), x.qas.clone())).collect();
    let p = pack(&m.vlm, &batch).unwrap();
    let qas: Vec<_> = batch.iter().flat_map(|(_, qas)| qas.iter()).collect();
    assert_eq!(qas.len(), p.slots.len(), "one slot row per question");
    let (mut agree, mut differ, mut asked) = (0, 0, 0);
    for (qa, (_, slots)) in qas.iter().zip(&p.slots) {
        let [x1, x2] = [slots[4], slots[5]];
        assert!((0..=grid).contains(&x1) && (0..=grid).contains(&x2), "places within the grid: {slots:?}");
        if qa.kind != Kind::LeftOf {
            continue;
        }
        asked += 1;
        // both objects are in the view (the generator asks about seen objects only)
        assert!(x1 > 0 && x2 > 0, "{}: places {x1} {x2}", qa.question);
        if x1 != x2 {
            differ += 1;
            agree += usize::from((x1 < x2) == (qa.answer == "yes"));
        }
    }
    eprintln!("left_of: {asked} asked, {differ} in different columns, {agree} of those agree with the answer");
    assert!(differ >= 10, "enough left_of questions with objects in different columns ({differ})");
    assert!(agree as f64 >= 0.9 * differ as f64, "places agree with the answers ({agree} of {differ})");
}

#[test]
fn supervised_hops_point_at_the_objects_the_questions_name() {
    use model::data::synth::questions::Kind;
    use model::data::synth::scene::{Color, Shape};
    let dev = Device::ndarray();
    let t = Trainer::new(&tiny_config(), &dev).unwrap();
    let m = t.model.valid();
    let samples = eval_samples(t.spec(), 90..96, 1, 0);
    let batch: Vec<_> =
        samples.iter().filter(|x| x.kind == SampleKind::View).map(|x| (x.clone(), x.qas.clone())).collect();
    let p = pack(&m.vlm, &batch).unwrap();
    let g2 = m.vlm.cfg.vision.tokens();
    // the object a position of a row shows: its (colour, shape) label, for image token positions
    let shows = |b: usize, pos: usize| -> Option<(u8, u8)> {
        let i = pos.checked_sub(p.head).filter(|&i| i < g2)?;
        let l = batch[b].0.images[0].labels[i];
        (l[0] > 0).then_some((l[0], l[1]))
    };
    let (mut yes, mut no) = (0, 0);
    let mut q = 0;
    for (b, (_, qas)) in batch.iter().enumerate() {
        for qa in qas {
            let first = p.targets[p.questions[q].1.start].0 - b * p.t;
            q += 1;
            if qa.kind != Kind::Exists {
                continue;
            }
            let w: Vec<&str> = qa.question.trim_end_matches('?').split(' ').collect();
            let c = Color::ALL.iter().position(|c| c.word() == w[w.len() - 2]).unwrap() as u8 + 1;
            let sh = Shape::ALL.iter().position(|s| s.word() == w[w.len() - 1]).unwrap() as u8 + 1;
            let find: Vec<_> =
                p.hops[b].iter().filter(|h| h.kind == HopKind::Find && h.query == first && h.head == 0).collect();
            assert_eq!(find.len(), 1, "{}", qa.question);
            if qa.answer == "yes" {
                yes += 1;
                assert!(find[0].targets.iter().all(|&j| shows(b, j) == Some((c, sh))), "{}", qa.question);
            } else {
                no += 1;
                assert_eq!(find[0].targets, vec![SINK], "{}: nothing to find", qa.question);
            }
            // the words hop gathers exactly the colour and shape words of the question
            let words = p.hops[b].iter().find(|h| h.kind == HopKind::Words && h.query == first).unwrap();
            let named: Vec<i64> = words.targets.iter().map(|&j| p.ids[b * p.t + j]).collect();
            let want = m.vlm.tokenizer.encode(&format!("{} {}", w[w.len() - 2], w[w.len() - 1])).unwrap();
            assert_eq!(named, want.iter().map(|&i| i as i64).collect::<Vec<_>>());
        }
    }
    assert!(yes > 0 && no > 0, "both answers asked ({yes} yes, {no} no)");
    // dedupe: every object token looks at earlier tokens of its own object, or the sink
    for (b, hops) in p.hops.iter().enumerate() {
        for h in hops.iter().filter(|h| h.kind == HopKind::Dedupe) {
            let me = shows(b, h.query).expect("an object token");
            assert!(h.targets == vec![SINK] || h.targets.iter().all(|&j| j < h.query && shows(b, j) == Some(me)));
        }
    }
}

/// Exact match the committed model must keep on ground-truth images of two held-out seeds. The
/// eighth model (the seventh with a two-turn soup stage; issue 65) scores [`COMMITTED_MEASURED`]
/// on single questions (156 of 168, measured 2026-12-06 on ndarray) and [`FOLLOW_UPS_MEASURED`]
/// on follow-ups (45 of 48); each floor sits three answers below, so no single answer flipped by another
/// CPU's rounding fails the test. (The seventh model: 159 of 168 single questions, floor 0.93, and
/// no follow-ups.)
const COMMITTED_FLOOR: f64 = 0.91;
const COMMITTED_MEASURED: f64 = 0.929;
const FOLLOW_UPS_FLOOR: f64 = 0.87;
const FOLLOW_UPS_MEASURED: f64 = 0.938;

#[test]
fn the_committed_model_answers_questions_on_held_out_scenes() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tabletop-llava-ov");
    let cfg = model::io::read_config::<VlmTrainConfig>(&dir.join("train_config.json")).unwrap();
    let dev = Device::ndarray();
    let vlm = LlavaOnevision::load(&dir, &dev).unwrap();
    let seeds = train::vlm::EVAL_SEEDS + 500..train::vlm::EVAL_SEEDS + 502;
    let acc = train::vlm::evaluate_model(vlm, seeds, (2, 2), &cfg, &dev).unwrap();
    let n: usize = acc.by_kind.values().map(|v| v.1).sum();
    let all = acc.level(None);
    eprintln!(
        "committed model on 2 held-out seeds ({n} questions, {all:.3} right): {}\n  {}",
        acc.summary(),
        acc.by_kind_line()
    );
    assert!(n >= 40, "two seeds ask every kind of question ({n} asked)");
    // every view question, and nothing else, is filed under the size of its smallest object
    let filed: usize = acc.view_by_smallest.iter().flat_map(|m| m.values()).map(|v| v.1).sum();
    let view_kinds = |k: &String| {
        model::data::synth::questions::Kind::ALL
            .iter()
            .any(|c| c.as_str() == k && c.level() == model::question_file::Level::View)
    };
    let asked: usize = acc.by_kind.iter().filter(|(k, _)| view_kinds(k)).map(|(_, v)| v.1).sum();
    assert_eq!(filed, asked, "view questions filed by size ({} buckets)", acc.view_by_smallest.len());
    assert!(
        all >= COMMITTED_FLOOR,
        "exact match {all:.3} < {COMMITTED_FLOOR} (measured {COMMITTED_MEASURED} when committed)"
    );
    // it converses: every follow-up is asked after the question it follows
    assert!(cfg.two_turn > 0.0, "the built-in model's last stage trained second turns");
    let (right, asked) = acc.follow_ups();
    let follow = right as f64 / asked.max(1) as f64;
    eprintln!("  follow-ups: {}", acc.follow_up_line().unwrap_or_default());
    assert!(asked >= 20, "two seeds ask follow-ups ({asked} asked)");
    assert!(
        follow >= FOLLOW_UPS_FLOOR,
        "follow-ups {follow:.3} < {FOLLOW_UPS_FLOOR} (measured {FOLLOW_UPS_MEASURED} when committed)"
    );
}

/// The size buckets of `--evaluate`'s breakdown: a view question goes under the smallest object
/// its view sees, bounds exclusive above; other questions only under their kind.
#[test]
fn view_questions_are_filed_under_their_smallest_object() {
    use model::data::synth::questions::Kind;
    use train::vlm::{Accuracy, SMALLEST_BUCKETS};
    let mut a = Accuracy::default();
    let [b0, b1, b2] = SMALLEST_BUCKETS;
    a.add_sized(Kind::Shapes, true, Some(28));
    a.add_sized(Kind::Shapes, false, Some(b0 - 1));
    a.add_sized(Kind::Shapes, true, Some(b0));
    a.add_sized(Kind::Count, false, Some(b1));
    a.add_sized(Kind::Count, true, Some(b2 + 1000));
    a.add_sized(Kind::Name, false, None);
    assert_eq!(a.by_kind["shapes"], (2, 3));
    assert_eq!(a.by_kind["name"], (0, 1));
    let got: Vec<Vec<(&str, (usize, usize))>> =
        a.view_by_smallest.iter().map(|m| m.iter().map(|(k, v)| (k.as_str(), *v)).collect()).collect();
    assert_eq!(
        got,
        vec![vec![("shapes", (1, 2))], vec![("shapes", (1, 1))], vec![("count", (0, 1))], vec![("count", (1, 1))]]
    );
    let lines = a.smallest_lines();
    assert_eq!(lines[0], format!("smallest seen object 0-{} px: view 50% of 2, shapes 50% of 2", b0 - 1));
    assert!(lines[3].starts_with(&format!("smallest seen object >= {b2} px: view 100% of 1")), "{}", lines[3]);
}

/// ChatSplat with the committed model as teacher and reader, end to end on one small held-out
/// scene: synth -> geometry -> teacher tokens -> language field (the shared fixture, also what the
/// viewer's tests serve) -> every question of the scene answered from the ground-truth images and
/// from ChatSplat's tokens (the paper's comparison in miniature; `vqa-bench` runs it at full size).
#[test]
fn chatsplat_tokens_answer_a_held_out_scene_nearly_as_well_as_ground_truth_images() {
    use model::data::{LoadOptions, load_any};
    use model::run::GeometryRun;
    use scoring::compare::{Source, summary_json, table, three_ways};
    let dev = Device::ndarray();
    let scene = chatsplat_tests::fixture::tabletop(std::path::Path::new(env!("CARGO_TARGET_TMPDIR")));
    let vlm_dir = chatsplat_tests::fixture::builtin_model();
    let ds = load_any(&scene.data, &LoadOptions::default()).unwrap();
    let run = GeometryRun::new(&scene.run);
    let session = model::chat::ChatSession::open(&run, None, &vlm_dir, &dev).unwrap();
    let path = scene.data.join("questions.json");
    let qf = model::vqa::load_questions(&path).unwrap();
    // the three ways `chatsplat demo` prints
    let rows = three_ways(&session, &qf, &ds).unwrap();
    let printed = table(&rows);
    eprintln!("{printed}");
    assert_eq!(rows.iter().map(|(s, _)| *s).collect::<Vec<_>>(), Source::ALL);
    assert!(printed.contains("(b) VLM on the rendered RGB") && printed.contains("as fast as rendering"), "{printed}");
    let score = |source| {
        let t = &rows.iter().find(|(s, _)| *s == source).unwrap().1.tally;
        let (right, n): (usize, usize) = t.by_level.values().fold((0, 0), |(r, n), v| (r + v.0, n + v.1));
        (right, n)
    };
    let json = summary_json(&rows, (&path, &qf));
    for source in Source::ALL {
        let key = serde_json::to_value(source).unwrap();
        let answers = json["comparison"][key.as_str().unwrap()]["answers"].as_array().unwrap().clone();
        let right = answers.iter().filter(|a| a["right"] == true).count();
        assert_eq!((right, answers.len()), score(source), "{source:?}: the JSON's answers are the tally's");
    }
    let rate = |(r, n): (usize, usize)| r as f64 / n.max(1) as f64;
    let (gt, cs) = (rate(score(Source::GroundTruth)), rate(score(Source::ChatSplat)));
    eprintln!("{} questions: ground-truth images {gt:.3}, ChatSplat tokens {cs:.3}", qf.questions.len());
    assert!(cs >= E2E_FLOOR, "ChatSplat exact match {cs:.3} < {E2E_FLOOR} (ground truth {gt:.3})");
    assert!(cs >= gt - E2E_GAP, "ChatSplat {cs:.3} more than {E2E_GAP} below ground-truth images {gt:.3}");
}

/// Floors of the end-to-end test: with the language stage's cosine decay and slower encoder
/// (2026-11-25), 75 questions, ground-truth images 0.933, ChatSplat tokens 0.947 (dev profile,
/// ndarray; with the paper's constant rates 0.933 and 0.867; with the smaller objects and an
/// earlier model 0.821 and 0.791, and 0.567 after 60 language iterations: the view tokens of small
/// objects sharpen late, eval/journal/2026-11-25.md, "The paper's comparison with the fourth
/// model"). With the seventh model and the encoder's rates scaled by fan-in (2026-12-01, dev
/// profile): ground-truth images 0.987, ChatSplat tokens 1.000.
const E2E_FLOOR: f64 = 0.85;
const E2E_GAP: f64 = 0.05;

/// The stage a resumed or `--base-model` chain starts at (what its progress bar names): stages
/// `--base-model` holds and, with `--resume`, those already finished under `out` are skipped.
#[test]
fn stages_done_counts_the_stages_a_run_skips() {
    use train::vlm::stages_done;
    let inner = VlmTrainConfig { steps: 3, ..tiny_config() };
    let mid = VlmTrainConfig { steps: 4, base: Some(Box::new(inner.clone())), ..tiny_config() };
    let outer = VlmTrainConfig { steps: 5, base: Some(Box::new(mid.clone())), ..tiny_config() };
    let finish = |dir: &std::path::Path, c: &VlmTrainConfig| {
        std::fs::create_dir_all(dir).unwrap();
        model::io::write_json(&dir.join("train_config.json"), c).unwrap();
        std::fs::write(dir.join("model.safetensors"), b"").unwrap();
    };
    let out = temp_dir("stages-done");
    assert_eq!(stages_done(&outer, &out, None, true), 0);
    finish(&out.join("base").join("base"), &inner);
    assert_eq!(stages_done(&outer, &out, None, true), 1, "the innermost stage is done");
    assert_eq!(stages_done(&outer, &out, None, false), 0, "without --resume every stage trains again");
    finish(&out.join("base"), &mid);
    assert_eq!(stages_done(&outer, &out, None, true), 2);
    // a finished folder of another configuration does not count
    let other = temp_dir("stages-done-other");
    finish(&other.join("base"), &VlmTrainConfig { steps: 9, ..mid.clone() });
    assert_eq!(stages_done(&outer, &other, None, true), 0);
    // --base-model holding the innermost stage
    let base = temp_dir("stages-done-base");
    finish(&base, &inner);
    assert_eq!(stages_done(&outer, &other, Some(&base), false), 1);
}
