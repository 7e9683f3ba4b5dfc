//! LLaVA-OneVision port: parity with transformers on the tiny fixture in
//! checkpoints/tiny-llava-ov (built by checkpoints/make_tiny_vlm.py), on ndarray and wgpu;
//! preprocessing, chat template and tokenizer against the strings and ids transformers produced;
//! loader errors on broken directories.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

use burn::tensor::{Device, Tensor, TensorData};
use chatsplat_tests::{host, max_abs_diff, temp_dir, wgpu_device};
use model::vlm::cpu::attention as cpu_attention;
use model::vlm::preprocess::{anyres_views, base_view};
use model::vlm::weights::WeightStore;
use model::vlm::{GenerateOptions, LlavaOnevision, PromptLayout, RgbImage, Turn, VlmError, chat_template};
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov")
}

enum Ref {
    F32(Vec<usize>, Vec<f32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
}

fn reference() -> (HashMap<String, Ref>, serde_json::Value) {
    let bytes = std::fs::read(fixture().join("reference.safetensors")).expect("reference.safetensors");
    let st = SafeTensors::deserialize(&bytes).expect("valid reference");
    let mut out = HashMap::new();
    for (name, v) in st.tensors() {
        let d = v.data();
        let r = match v.dtype() {
            Dtype::F32 => Ref::F32(
                v.shape().to_vec(),
                d.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect(),
            ),
            Dtype::I64 => Ref::I64(d.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().unwrap())).collect()),
            Dtype::U8 => Ref::U8(d.to_vec()),
            other => panic!("unexpected dtype {other:?}"),
        };
        out.insert(name, r);
    }
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture().join("reference.json")).unwrap()).unwrap();
    (out, meta)
}

fn f32s<'a>(r: &'a HashMap<String, Ref>, k: &str) -> (&'a [usize], &'a [f32]) {
    match &r[k] {
        Ref::F32(s, v) => (s, v),
        _ => panic!("{k} is not f32"),
    }
}
fn ids(r: &HashMap<String, Ref>, k: &str) -> Vec<u32> {
    match &r[k] {
        Ref::I64(v) => v.iter().map(|&x| x as u32).collect(),
        _ => panic!("{k} is not i64"),
    }
}
fn bytes<'a>(r: &'a HashMap<String, Ref>, k: &str) -> &'a [u8] {
    match &r[k] {
        Ref::U8(v) => v,
        _ => panic!("{k} is not u8"),
    }
}

fn image(name: &str) -> RgbImage {
    model::images::read_rgb_image(&fixture().join(name)).expect("fixture image")
}

/// Views as HF lays out pixel_values: [views, 3, H, W] u8.
fn chw(views: &[RgbImage]) -> Vec<u8> {
    let mut out = Vec::new();
    for v in views {
        for c in 0..3 {
            out.extend(v.data.chunks_exact(3).map(|p| p[c]));
        }
    }
    out
}

#[test]
fn preprocessing_is_bit_exact_with_the_hf_pil_processor() {
    let (r, _) = reference();
    let dev = Device::ndarray();
    let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
    // Single image, 300x700: anyres picks 384x768 -> base view + 2 patches.
    let p = anyres_views(&image("image_wide.png"), &m.processor);
    assert_eq!(p.views.len(), 3);
    let want = bytes(&r, "single_patches_u8");
    let got = chw(&p.views);
    let diff = got.iter().zip(want).filter(|(a, b)| a != b).count();
    assert_eq!(diff, 0, "{diff} of {} anyres pixels differ from transformers", want.len());
    // Two images: each padded to a square with the mean colour, base view only.
    let views: Vec<RgbImage> =
        ["image_a.png", "image_b.png"].iter().map(|n| base_view(&image(n), &m.processor).views.remove(0)).collect();
    let want = bytes(&r, "multi_patches_u8");
    let got = chw(&views);
    let diff = got.iter().zip(want).filter(|(a, b)| a != b).count();
    assert_eq!(diff, 0, "{diff} multi-image pixels differ");
}

#[test]
fn chat_template_and_token_ids_match_transformers() {
    let (r, meta) = reference();
    let q1 = meta["question_single"].as_str().unwrap();
    let q2 = meta["question_multi"].as_str().unwrap();
    let one = chat_template(&[Turn::user(1, q1)], true);
    assert_eq!(one, meta["prompt_single"].as_str().unwrap());
    let two = chat_template(&[Turn::user(2, q2)], true);
    assert_eq!(two, meta["prompt_multi"].as_str().unwrap());
    let follow =
        chat_template(&[Turn::user(1, q1), Turn::assistant("A red sphere."), Turn::user(0, "Where is it?")], true);
    assert_eq!(follow, meta["prompt_followup"].as_str().unwrap());

    let dev = Device::ndarray();
    let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
    let p = m.preprocess(&image("image_wide.png"), false);
    let n = m.num_image_tokens(&p);
    assert_eq!(n as u64, meta["single_num_image_tokens"].as_u64().unwrap());
    let got = m.expand_image_tokens(&m.tokenizer.encode(&one).unwrap(), &[n]).unwrap();
    assert_eq!(got, ids(&r, "single_input_ids"));
    let counts: Vec<usize> =
        ["image_a.png", "image_b.png"].iter().map(|f| m.num_image_tokens(&m.preprocess(&image(f), true))).collect();
    let got = m.expand_image_tokens(&m.tokenizer.encode(&two).unwrap(), &counts).unwrap();
    assert_eq!(got, ids(&r, "multi_input_ids"));
    // A tag/image mismatch is an error, not a silent misalignment.
    assert!(m.expand_image_tokens(&m.tokenizer.encode(&two).unwrap(), &[n]).is_err());
}

fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let err = max_abs_diff(got, want);
    assert!(err <= tol, "{what}: max abs error {err} > {tol}");
    eprintln!("{what}: max abs error {err:.2e}");
}

fn parity(dev: &Device) {
    let (r, _) = reference();
    let m = LlavaOnevision::load(&fixture(), dev).unwrap();
    let p = m.preprocess(&image("image_wide.png"), false);
    let feats = m.vision_features(m.pixels(&p));
    let (shape, want) = f32s(&r, "single_vision_features");
    assert_eq!(feats.dims().to_vec(), shape.to_vec());
    assert_close("vision features", &host(feats.clone()), want, 1e-4);
    let proj = m.projector.forward(feats);
    assert_close("projector", &host(proj.clone()), f32s(&r, "single_projected").1, 1e-4);
    let packed = m.pack(proj, &p);
    assert_close("packed image embeds", &host(packed.clone()), f32s(&r, "single_packed").1, 1e-4);

    let prompt_ids = ids(&r, "single_input_ids");
    let embeds = m.embed_prompt(&prompt_ids, &[packed]).unwrap();
    assert_close("logits", &host(m.logits(embeds.clone())), f32s(&r, "single_logits").1, 1e-4);

    let want_ids = ids(&r, "single_greedy_ids");
    let opts = GenerateOptions { max_new_tokens: want_ids.len(), ignore_stop: true, ..Default::default() };
    let mut streamed = String::new();
    let g = m.generate(embeds, &opts, |s| streamed.push_str(s)).unwrap();
    assert_eq!(g.ids, want_ids, "greedy continuation");
    assert_eq!(streamed, g.text, "streamed pieces add up to the text");
    assert_eq!(g.text, m.tokenizer.decode(&want_ids, true).unwrap());

    // Two images in one prompt: base views + newline each, logits at the end of the prompt.
    let imgs: Vec<Tensor<2>> =
        ["image_a.png", "image_b.png"].iter().map(|f| m.image_embeds(&m.preprocess(&image(f), true))).collect();
    let packed2 = Tensor::cat(imgs.clone(), 0);
    assert_close("multi-image embeds", &host(packed2), f32s(&r, "multi_packed").1, 1e-4);
    let ids2 = ids(&r, "multi_input_ids");
    let logits = m.logits(m.embed_prompt(&ids2, &imgs).unwrap());
    let t = logits.dims()[0];
    assert_close(
        "multi-image logits (last 4)",
        &host(logits.narrow(0, t - 4, 4)),
        f32s(&r, "multi_logits_last").1,
        1e-4,
    );
}

#[test]
fn ndarray_matches_transformers() {
    parity(&Device::ndarray());
}

/// burn-flex: gemm matmuls and its fused (flash) attention, whose tiles the fixture's 729-token
/// views exceed.
#[test]
fn flex_matches_transformers() {
    parity(&Device::flex());
}

#[test]
fn flex_with_f16_weights_stays_within_half_precision_of_transformers() {
    half_parity(&Device::flex());
}

/// Weights held in f16 on `dev` (`LlavaOnevision::load_with(.., half)`): every linear layer and
/// the embeddings are f16 on the device, and the outputs stay within f16 rounding of transformers'
/// f32 ones (relative to each output's scale), with the same greedy continuation.
fn half_parity(dev: &Device) {
    let (r, _) = reference();
    let m = LlavaOnevision::load_with(&fixture(), dev, true).unwrap();
    assert_eq!(m.vision.layers[0].fc1.weight.val().dtype(), burn::tensor::DType::F16);
    assert_eq!(m.llm.embed.weight.val().dtype(), burn::tensor::DType::F16);
    let rel = |what: &str, got: &[f32], want: &[f32], tol: f32| {
        assert_eq!(got.len(), want.len(), "{what}: length");
        let scale = want.iter().fold(1e-6f32, |a, b| a.max(b.abs()));
        let err = max_abs_diff(got, want);
        eprintln!("{what} (f16 weights): max abs error {err:.2e} of scale {scale:.2e}");
        assert!(err <= tol * scale, "{what}: max abs error {err} > {tol} x {scale}");
    };
    let p = m.preprocess(&image("image_wide.png"), false);
    let feats = m.vision_features(m.pixels(&p));
    rel("vision features", &host(feats.clone()), f32s(&r, "single_vision_features").1, 1e-2);
    let packed = m.pack(m.projector.forward(feats), &p);
    let embeds = m.embed_prompt(&ids(&r, "single_input_ids"), &[packed]).unwrap();
    rel("logits", &host(m.logits(embeds.clone())), f32s(&r, "single_logits").1, 1e-2);
    let want_ids = ids(&r, "single_greedy_ids");
    let opts = GenerateOptions { max_new_tokens: want_ids.len(), ignore_stop: true, ..Default::default() };
    assert_eq!(m.generate(embeds, &opts, |_| {}).unwrap().ids, want_ids, "greedy continuation");
}

#[test]
fn wgpu_matches_transformers() {
    let Some(dev) = wgpu_device() else { return };
    parity(&dev);
    // `--half` on wgpu where the adapter's shaders take f16 (Mesa lavapipe's do), in the same
    // process to share its kernels' compilation
    match splat_kernels::cube::f16_on(&dev) {
        Some(true) => half_parity(&dev),
        f16 => {
            eprintln!("wgpu_matches_transformers: f16 weights not checked: the adapter has no f16 shaders ({f16:?})")
        }
    }
}

fn copy_fixture(name: &str) -> chatsplat_tests::Scratch {
    let dir = temp_dir(name);
    std::fs::create_dir_all(&dir).unwrap();
    for e in std::fs::read_dir(fixture()).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dir.join(e.file_name())).unwrap();
    }
    dir
}

#[test]
fn the_prompt_layout_follows_the_models_chat_template() {
    let dev = Device::ndarray();
    let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
    assert_eq!(m.tokenizer.layout, PromptLayout::ImagesFirst, "llava-hf's template renders images first");
    let text_first = PromptLayout::TextFirst.jinja();
    assert_eq!(PromptLayout::of_template(&text_first), PromptLayout::TextFirst);
    assert_eq!(PromptLayout::of_template(&PromptLayout::ImagesFirst.jinja()), PromptLayout::ImagesFirst);
    let dir = copy_fixture("vlm-text-first");
    std::fs::write(dir.join("chat_template.jinja"), &text_first).unwrap();
    let t = LlavaOnevision::load(&dir, &dev).unwrap();
    assert_eq!(t.tokenizer.layout, PromptLayout::TextFirst);
    let prompt = t.tokenizer.prompt(&[Turn::user(2, "Which is red?")], true);
    assert_eq!(prompt, "<|im_start|>user\nWhich is red?<image>\n<image>\n<|im_end|>\n<|im_start|>assistant\n");
    // the image embeddings follow the question's tokens
    let d = t.cfg.text.hidden_size;
    let img = Tensor::<2>::from_data(TensorData::new(vec![7.0f32; 3 * d], [3, d]), &dev);
    let rows = host(t.prompt_embeds("Which is red?", &[img]).unwrap());
    let at: Vec<usize> = (0..rows.len() / d).filter(|&r| rows[r * d..(r + 1) * d].iter().all(|&v| v == 7.0)).collect();
    let before = t.tokenizer.encode("<|im_start|>user\nWhich is red?").unwrap().len();
    assert_eq!(at, (before..before + 3).collect::<Vec<_>>());
    std::fs::remove_dir_all(&dir).ok();
}

fn load_err(dir: &Path) -> String {
    match LlavaOnevision::load(dir, &Device::ndarray()) {
        Ok(_) => panic!("{} loaded but should not", dir.display()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn loader_errors_name_the_file_and_the_problem() {
    let missing = load_err(Path::new("/nonexistent/llava"));
    assert!(missing.contains("/nonexistent/llava") && missing.contains("not a directory"), "{missing}");

    // A truncated shard.
    let dir = copy_fixture("vlm-truncated");
    let shard = dir.join("model-00002-of-00004.safetensors");
    let len = std::fs::metadata(&shard).unwrap().len();
    let f = std::fs::OpenOptions::new().write(true).open(&shard).unwrap();
    f.set_len(len / 2).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("model-00002-of-00004.safetensors") && e.contains("not a valid safetensors"), "{e}");

    // Garbage bytes instead of a header.
    std::fs::write(&shard, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header").unwrap();
    let e = load_err(&dir);
    assert!(e.contains("model-00002-of-00004.safetensors"), "{e}");

    // Unknown architecture.
    let dir = copy_fixture("vlm-arch");
    let cfg = dir.join("config.json");
    let text = std::fs::read_to_string(&cfg)
        .unwrap()
        .replace("LlavaOnevisionForConditionalGeneration", "MllamaForConditionalGeneration")
        .replace("\"llava_onevision\"", "\"mllama\"");
    std::fs::write(&cfg, text).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("config.json") && e.contains("unsupported architecture") && e.contains("Mllama"), "{e}");

    // A config that disagrees with the weights: the tensor is named with both shapes.
    let dir = copy_fixture("vlm-shape");
    let cfg = dir.join("config.json");
    let text = std::fs::read_to_string(&cfg).unwrap().replace("\"intermediate_size\": 64", "\"intermediate_size\": 65");
    std::fs::write(&cfg, text).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("fc1.weight") && e.contains("[64, 32]") && e.contains("[65, 32]"), "{e}");

    // Unsupported options are refused by name.
    let dir = copy_fixture("vlm-rope");
    let cfg = dir.join("config.json");
    let text = std::fs::read_to_string(&cfg).unwrap().replace("\"rope_type\": \"default\"", "\"rope_type\": \"yarn\"");
    std::fs::write(&cfg, text).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("text_config.rope_parameters.rope_type is \"yarn\""), "{e}");

    // Invalid JSON and a missing tokenizer.
    let dir = copy_fixture("vlm-json");
    std::fs::write(dir.join("config.json"), "{ not json").unwrap();
    let e = load_err(&dir);
    assert!(e.contains("config.json") && e.contains("not valid JSON"), "{e}");
    let dir = copy_fixture("vlm-tok");
    std::fs::remove_file(dir.join("tokenizer.json")).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("tokenizer.json") && e.contains("missing"), "{e}");
}

#[test]
fn weights_convert_bf16_f16_and_reject_other_dtypes() {
    let dir = temp_dir("vlm-dtypes");
    std::fs::create_dir_all(&dir).unwrap();
    let vals = [1.5f32, -0.25, 3.0e-3, 65504.0];
    let f32b: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    let f16b: Vec<u8> = vals.iter().flat_map(|v| half::f16::from_f32(*v).to_le_bytes()).collect();
    let bf16b: Vec<u8> = vals.iter().flat_map(|v| half::bf16::from_f32(*v).to_le_bytes()).collect();
    let i32b: Vec<u8> = [1i32, 2, 3, 4].iter().flat_map(|v| v.to_le_bytes()).collect();
    let views = vec![
        ("a", safetensors::tensor::TensorView::new(Dtype::F32, vec![2, 2], &f32b).unwrap()),
        ("b", safetensors::tensor::TensorView::new(Dtype::F16, vec![2, 2], &f16b).unwrap()),
        ("c", safetensors::tensor::TensorView::new(Dtype::BF16, vec![4], &bf16b).unwrap()),
        ("d", safetensors::tensor::TensorView::new(Dtype::I32, vec![4], &i32b).unwrap()),
    ];
    safetensors::serialize_to_file(views, None, &dir.join("model.safetensors")).unwrap();
    let w = WeightStore::open(&dir, &Device::ndarray()).unwrap();
    assert_eq!(w.host("a", &[2, 2]).unwrap(), vals);
    let b = w.host("b", &[2, 2]).unwrap();
    for (g, v) in b.iter().zip(vals) {
        assert!((g - v).abs() <= v.abs() * 1e-3, "f16 {g} vs {v}");
    }
    let c = w.host("c", &[4]).unwrap();
    for (g, v) in c.iter().zip(vals) {
        assert!((g - v).abs() <= v.abs() * 8e-3, "bf16 {g} vs {v}");
    }
    let e = w.host("d", &[4]).unwrap_err().to_string();
    assert!(e.contains("dtype I32"), "{e}");
    let e = w.host("a", &[4]).unwrap_err().to_string();
    assert!(e.contains("[2, 2]") && e.contains("[4]"), "{e}");
    let e = w.host("zzz", &[1]).unwrap_err();
    assert!(matches!(e, VlmError::Weights { .. }) && e.to_string().contains("zzz is missing"));
    // The transformers-5 key layout resolves to the same tensors.
    let _ = TensorData::new(vec![0f32], [1]);
}

#[test]
fn object_images_keep_only_the_object_cropped_with_a_margin_and_squared() {
    use model::language::object_image;
    let (w, h) = (40, 20);
    let data: Vec<u8> = (0..w * h * 3).map(|i| (i % 251) as u8 + 1).collect();
    let img = RgbImage::new(w, h, data);
    let mut ids = vec![0u16; w * h];
    for y in 5..15 {
        for x in 10..30 {
            ids[y * w + x] = if (x + y) % 7 == 0 { 3 } else { 2 };
        }
    }
    let (obj, crop) = object_image(&img, &ids, 2, 0.1).unwrap();
    let bbox = crop.bbox;
    // box 10..30 x 5..15 grown by 2 and 1 pixels; squared to the longer side.
    assert_eq!(bbox, [8, 4, 32, 16]);
    assert_eq!((obj.width, obj.height), (24, 24));
    let oy = (24 - 12) / 2;
    for y in 0..24 {
        for x in 0..24 {
            let px = &obj.data[(y * 24 + x) * 3..(y * 24 + x) * 3 + 3];
            let (sx, sy) = (x + 8, y as isize - oy as isize + 4);
            let inside = sy >= 0 && (sy as usize) < h && ids[sy as usize * w + sx] == 2;
            if inside {
                let s = (sy as usize * w + sx) * 3;
                assert_eq!(px, &img.data[s..s + 3], "object pixel ({x},{y})");
            } else {
                assert_eq!(px, [0, 0, 0], "blanked pixel ({x},{y})");
            }
        }
    }
    assert!(object_image(&img, &ids, 9, 0.1).is_none());
}

#[test]
fn teacher_extraction_writes_f16_tokens_and_resumes() {
    use model::run::TeacherDir;
    use train::teacher::{ExtractOptions, extract, read_tokens};
    let view_file = TeacherDir::view_file_name;
    let data = temp_dir("vlm-extract");
    let opts = model::data::synth::SynthOptions { views: 3, width: 64, height: 48, ..Default::default() };
    model::data::synth::write_dataset(&data, &opts, |_, _| {}).unwrap();
    let dev = Device::ndarray();
    let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
    let out = data.join("teacher");
    let teacher = TeacherDir::new(&out);
    let eo = ExtractOptions { min_object_pixels: 16, tower_tail: 0, ..Default::default() };
    let mut planned = 0;
    let s = extract(&m, &data, &teacher, &eo, |p| planned = p.views.len(), |_, _| {}).unwrap();
    assert_eq!((s.written, s.skipped), (planned, 0));
    assert!(planned >= 2 && s.images > planned, "{s:?}: objects must be encoded too");
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("teacher.json")).unwrap()).unwrap();
    let v0 = &index["views"][0];
    let objects: Vec<u64> = v0["objects"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap()).collect();
    assert!(!objects.is_empty());
    // The stored view tokens are the tower's output for that image, rounded to f16.
    let ds = model::data::nerfstudio::load(&data, &eo.load).unwrap();
    let img = RgbImage::from_f32(64, 48, &ds.train[0].rgb);
    let want = host(m.teacher_tokens(&img));
    let (shape, got) = read_tokens(&out.join(view_file(0)), "view").unwrap();
    assert_eq!(shape, vec![27, 27, 32]);
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() <= w.abs() * 1e-3 + 1e-4, "f16 token {g} vs {w}");
    }
    for id in &objects {
        let (shape, t) = read_tokens(&out.join(view_file(0)), &format!("object_{id}")).unwrap();
        assert_eq!(shape, vec![27, 27, 32]);
        assert!(max_abs_diff(&t, &got) > 1e-3, "object {id} tokens must differ from the view's");
    }
    // Resume: a deleted and a truncated file are redone, the rest skipped.
    std::fs::remove_file(out.join(view_file(0))).unwrap();
    let f1 = out.join(view_file(1));
    let len = std::fs::metadata(&f1).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&f1).unwrap().set_len(len / 3).unwrap();
    let s = extract(&m, &data, &teacher, &eo, |_| {}, |_, _| {}).unwrap();
    assert_eq!((s.written, s.skipped), (2, planned - 2));
    let (_, again) = read_tokens(&out.join(view_file(0)), "view").unwrap();
    assert_eq!(again, got, "extraction is deterministic");
    // Another downscale: every view is redone (complete files of the old setting are not kept)
    // and the index says what the tokens are; the same setting again skips everything.
    let half = ExtractOptions { load: model::data::LoadOptions { downscale: 2, ..Default::default() }, ..eo.clone() };
    let s = extract(&m, &data, &teacher, &half, |_| {}, |_, _| {}).unwrap();
    assert_eq!((s.written, s.skipped), (planned, 0));
    assert_eq!(teacher.read_index().unwrap().downscale, 2);
    let (_, small) = read_tokens(&out.join(view_file(0)), "view").unwrap();
    assert!(max_abs_diff(&small, &got) > 1e-3, "downscale-2 tokens replace the full-size ones");
    let s = extract(&m, &data, &teacher, &half, |_| {}, |_, _| {}).unwrap();
    assert_eq!((s.written, s.skipped), (0, planned));
    // Tokens taken before the tower's last layers (`--tower-tail`): the tower's last k layers
    // on them give its output, for every k; another tail redoes every view and the index says
    // which; one longer than the tower is refused, naming the model.
    let layers = m.tower_layers();
    assert!(layers >= 1);
    for k in 0..=layers {
        let before = m.teacher_tokens_before_tail(&img, k);
        let done = host(m.tower_tail(before.clone(), k));
        assert!(max_abs_diff(&done, &want) < 1e-5, "tail {k}: {}", max_abs_diff(&done, &want));
        if k > 0 {
            assert!(max_abs_diff(&host(before), &want) > 1e-3, "tail {k}: the state before must differ");
        }
    }
    let tail = ExtractOptions { tower_tail: 1, ..eo.clone() };
    let s = extract(&m, &data, &teacher, &tail, |_| {}, |_, _| {}).unwrap();
    assert_eq!((s.written, s.skipped), (planned, 0));
    assert_eq!(teacher.read_index().unwrap().tower_tail, 1);
    let (_, early) = read_tokens(&out.join(view_file(0)), "view").unwrap();
    let early_want = host(m.teacher_tokens_before_tail(&img, 1));
    for (g, w) in early.iter().zip(&early_want) {
        assert!((g - w).abs() <= w.abs() * 1e-3 + 1e-4, "f16 token {g} vs {w}");
    }
    let long = ExtractOptions { tower_tail: layers + 1, ..eo.clone() };
    let e = extract(&m, &data, &teacher, &long, |_| {}, |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("tower tail") && e.contains(&m.dir.display().to_string()), "{e}");
    // A dataset path that does not exist is a clear error.
    let e = extract(&m, Path::new("/nonexistent/scene"), &teacher, &eo, |_| {}, |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("/nonexistent/scene"), "{e}");
}

#[test]
fn sampling_follows_temperature_and_top_p() {
    use model::rng::Rng;
    use model::vlm::generate::pick;
    let logits = [0.0f32, 3f32.ln(), -1e9, 0.5];
    let greedy = GenerateOptions::default();
    let mut rng = Rng::new(1);
    assert_eq!(pick(&logits, &greedy, &mut rng), 1);
    // A tiny nucleus keeps only the top token.
    let nucleus = GenerateOptions { temperature: 1.0, top_p: 1e-6, ..Default::default() };
    assert!((0..100).all(|_| pick(&logits, &nucleus, &mut rng) == 1));
    // Temperature 1 over {0, ln 3} (+ a third option): frequencies follow the softmax.
    let two = [0.0f32, 3f32.ln()];
    let t1 = GenerateOptions { temperature: 1.0, ..Default::default() };
    let n = 4000;
    let ones = (0..n).filter(|_| pick(&two, &t1, &mut rng) == 1).count();
    let f = ones as f64 / n as f64;
    assert!((f - 0.75).abs() < 0.03, "P(token 1) = {f}, expected 0.75");
    // A high temperature flattens it, a low one sharpens it.
    let hot = GenerateOptions { temperature: 100.0, ..Default::default() };
    let f_hot = (0..n).filter(|_| pick(&two, &hot, &mut rng) == 1).count() as f64 / n as f64;
    assert!((f_hot - 0.5).abs() < 0.04, "{f_hot}");
    // top_p = 0.7 over {0.25, 0.75}: only the 0.75 token survives.
    let p7 = GenerateOptions { temperature: 1.0, top_p: 0.7, ..Default::default() };
    assert!((0..200).all(|_| pick(&two, &p7, &mut rng) == 1));
    // Same seed, same draws.
    let draw = |seed| {
        let mut r = Rng::new(seed);
        (0..50).map(|_| pick(&logits, &t1, &mut r)).collect::<Vec<_>>()
    };
    assert_eq!(draw(5), draw(5));
}

#[test]
fn parameter_count_formula_matches_the_checkpoint() {
    // Every tensor the port uses, counted from the files, equals LlavaConfig::parameter_counts.
    let dev = Device::ndarray();
    let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
    let mut used = 0usize;
    for e in std::fs::read_dir(fixture()).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        if !(name.starts_with("model-") && name.ends_with(".safetensors")) {
            continue;
        }
        let bytes = std::fs::read(&p).unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        for (n, v) in st.tensors() {
            if n.contains("post_layernorm") || n.contains(".head.") {
                continue; // SigLIP's final norm and pooling head are not used by LLaVA
            }
            used += v.shape().iter().product::<usize>();
        }
    }
    assert_eq!(m.cfg.parameter_counts().total(), used);
    // The published models come out at their advertised sizes.
    let p05 = model::vlm::LlavaConfig::onevision_0_5b().parameter_counts();
    let p7 = model::vlm::LlavaConfig::onevision_7b().parameter_counts();
    assert!((0.85e9..0.95e9).contains(&(p05.total() as f64)), "{p05:?}");
    assert!((7.9e9..8.1e9).contains(&(p7.total() as f64)), "{p7:?}");
}

/// A model drawn in f16 layer by layer (how `vlm-bench --random 7b --half` holds the 7B model in
/// 15 GB instead of 30) has exactly the weights of the f32 model halved afterwards, held in f16.
#[test]
fn drawing_a_model_in_f16_gives_the_halved_f32_model() {
    let dev = Device::flex();
    let fixture = LlavaOnevision::load(&fixture(), &dev).unwrap();
    let draw = |half: bool| {
        let (cfg, processor, tokenizer) = (fixture.cfg.clone(), fixture.processor.clone(), fixture.tokenizer.clone());
        LlavaOnevision::init_with(cfg, processor, tokenizer, 7, &dev, half)
    };
    let (halved, drawn) = (draw(false).half(), draw(true));
    for m in [&halved, &drawn] {
        assert_eq!(m.llm.layers[1].down.weight.val().dtype(), burn::tensor::DType::F16);
        assert_eq!(m.llm.embed.weight.val().dtype(), burn::tensor::DType::F16);
        assert_eq!(m.vision.layers[0].fc1.weight.val().dtype(), burn::tensor::DType::F16);
    }
    let (a, b) = (halved.export().tensors, drawn.export().tensors);
    assert_eq!(a.len(), b.len());
    for ((name, shape, x), (name_b, shape_b, y)) in a.iter().zip(&b) {
        assert_eq!((name, shape), (name_b, shape_b));
        assert!(x == y, "{name}: the weights differ");
    }
    // and they are not the seed's f32 weights merely copied: halving rounded them
    let f32_model = draw(false).export().tensors;
    let q = |t: &[(String, Vec<usize>, Vec<f32>)]| {
        t.iter().find(|e| e.0.ends_with("layers.0.self_attn.q_proj.weight")).unwrap().2.clone()
    };
    assert_ne!(q(&f32_model), q(&b));
    assert!(max_abs_diff(&q(&f32_model), &q(&b)) < 1e-3);
}

/// Which form the Qwen2 forward gives its mask once for all layers: on the host a causal mask
/// stays causal (`attention` runs it in the kernel); elsewhere (autodiff, wgpu) a decode step sees
/// every key and a prefill's additive mask is built once, the one `Mask::additive` gives.
#[test]
fn a_forwards_mask_is_resolved_once_for_its_device() {
    use model::vlm::layers::Mask;
    let host = Tensor::<2>::zeros([2, 2], &Device::flex());
    assert!(matches!(Mask::Causal { past: 3 }.for_layers(&host, 7 * 20, 23), Mask::Causal { past: 3 }));
    assert!(matches!(Mask::Causal { past: 3 }.for_layers(&host, 7, 4), Mask::Causal { past: 3 }));
    let ad = Device::flex().autodiff();
    let like = Tensor::<2>::zeros([2, 2], &ad);
    assert!(matches!(Mask::Causal { past: 3 }.for_layers(&like, 7, 4), Mask::All));
    let (rows, keys) = (2 * 5, 8);
    let Mask::Additive(m) = Mask::Causal { past: 3 }.for_layers(&like, rows, keys) else { panic!("additive expected") };
    let want = host_rows(Mask::Causal { past: 3 }.additive(rows, keys, &ad).unwrap());
    assert_eq!(host_rows(*m.clone()), want);
    // row 1 of head 1 (position 1 after 3 cached keys) sees keys 0..=4
    let row = &want[6];
    assert!(row[..5].iter().all(|v| *v == 0.0) && row[5..].iter().all(|v| *v == f32::NEG_INFINITY), "{row:?}");
}

fn host_rows(m: Tensor<2>) -> Vec<Vec<f32>> {
    let [_, keys] = m.dims();
    host(m).chunks(keys).map(<[f32]>::to_vec).collect()
}

/// The plain twin of `cpu_attention::attend`, in f64: every score, softmax over the keys each row
/// may see, the weighted sum of the values.
fn attend_reference(q: &[f32], k: &[f32], v: &[f32], s: cpu_attention::Shape, past: Option<usize>) -> Vec<f32> {
    let rows = s.rep * s.t;
    let mut out = vec![0f32; s.groups * rows * s.dv];
    for g in 0..s.groups {
        for r in 0..rows {
            let seen = past.map_or(s.keys, |p| p + r % s.t + 1);
            let qr = &q[(g * rows + r) * s.d..][..s.d];
            let scores: Vec<f64> = (0..seen)
                .map(|j| {
                    let kj = &k[(g * s.keys + j) * s.d..][..s.d];
                    qr.iter().zip(kj).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>() / (s.d as f64).sqrt()
                })
                .collect();
            let max = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let w: Vec<f64> = scores.iter().map(|x| (x - max).exp()).collect();
            let sum: f64 = w.iter().sum();
            for c in 0..s.dv {
                let o: f64 = (0..seen).map(|j| w[j] * v[(g * s.keys + j) * s.dv + c] as f64).sum();
                out[(g * rows + r) * s.dv + c] = (o / sum) as f32;
            }
        }
    }
    out
}

/// The CPU inference kernel against its f64 twin: a vision-tower-like call over several row
/// blocks, grouped causal prefill, causal after cached keys, one decode row, and scores in the
/// hundreds (a softmax without its max subtracted would overflow); then through `layers::attention`
/// on ndarray and flex against burn's composed softmax with the same mask built as a tensor.
#[test]
fn cpu_attention_matches_an_f64_reference_and_burns_softmax() {
    use cpu_attention::Shape;
    use model::vlm::layers::{Mask, attention, attention_probs};
    let mut rng = model::rng::Rng::new(7);
    let mut draw = |n: usize, amp: f32| (0..n).map(|_| amp * rng.normal()).collect::<Vec<f32>>();
    let cases = [
        ("vision-like: 150 rows in 3 blocks", Shape { groups: 3, rep: 1, t: 150, keys: 150, d: 16, dv: 16 }, None, 1.0),
        ("grouped causal prefill", Shape { groups: 2, rep: 3, t: 70, keys: 70, d: 8, dv: 12 }, Some(0), 1.0),
        ("causal after 67 cached keys", Shape { groups: 2, rep: 2, t: 5, keys: 72, d: 8, dv: 8 }, Some(67), 1.0),
        ("decode: one row", Shape { groups: 2, rep: 7, t: 1, keys: 41, d: 8, dv: 8 }, Some(40), 1.0),
        ("scores in the hundreds", Shape { groups: 1, rep: 2, t: 66, keys: 66, d: 16, dv: 4 }, Some(0), 12.0),
    ];
    for (what, s, past, amp) in cases {
        let rows = s.rep * s.t;
        let (q, k, v) =
            (draw(s.groups * rows * s.d, amp), draw(s.groups * s.keys * s.d, amp), draw(s.groups * s.keys * s.dv, 1.0));
        let mut got = vec![f32::NAN; s.groups * rows * s.dv];
        cpu_attention::attend(&q, &k, &v, s, 1.0 / (s.d as f32).sqrt(), past, &mut got);
        let want = attend_reference(&q, &k, &v, s, past);
        assert!(got.iter().all(|x| x.is_finite()), "{what}: non-finite output");
        assert_close(what, &got, &want, 2e-5);

        let mask = past.map_or(Mask::All, |past| Mask::Causal { past });
        for dev in [Device::ndarray(), Device::flex()] {
            let t3 = |x: &[f32], n: usize, w: usize| {
                Tensor::<3>::from_data(TensorData::new(x.to_vec(), [s.groups, n, w]), &dev)
            };
            let (tq, tk, tv) = (t3(&q, rows, s.d), t3(&k, s.keys, s.d), t3(&v, s.keys, s.dv));
            let fast = host(attention(tq.clone(), tk.clone(), tv.clone(), &mask));
            let composed = host(attention_probs(tq, tk, tv.clone(), mask.additive(rows, s.keys, &dev)).0);
            assert_close(&format!("{what}: layers::attention vs burn's softmax on {dev:?}"), &fast, &composed, 2e-5);
            // keys and values as the first rows of room for 9 more (a KV cache read in place)
            let roomy = |x: Tensor<3>| {
                let [g, n, w] = x.dims();
                Tensor::cat(vec![x, Tensor::<3>::ones([g, 9, w], &dev) * 1e3], 1).narrow(1, 0, n)
            };
            let in_room = host(attention(t3(&q, rows, s.d), roomy(t3(&k, s.keys, s.d)), roomy(tv), &mask));
            assert_close(&format!("{what}: keys and values with room to grow on {dev:?}"), &in_room, &fast, 1e-6);
        }
    }
}

/// Decoding through the KV cache (room for 5 positions at first, so it grows twice, each token's
/// keys written in place) gives at every position the logits of one forward over the whole
/// sequence, on ndarray and flex (whose decode steps take the few-row products and host attention).
#[test]
fn decoding_through_the_kv_cache_matches_a_full_forward() {
    use model::vlm::qwen2::KvCache;
    let ids: Vec<u32> = (0..14).map(|i| (i * 37 + 5) % 97).collect();
    for dev in [Device::ndarray(), Device::flex()] {
        let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
        let full = host(m.llm.logits(m.llm.forward(m.llm.embed(&ids), &mut KvCache::default())));
        let mut cache = KvCache::with_capacity(5);
        let mut stepped = host(m.llm.logits(m.llm.forward(m.llm.embed(&ids[..3]), &mut cache)));
        for i in 3..ids.len() {
            stepped.extend(host(m.llm.logits(m.llm.forward(m.llm.embed(&ids[i..i + 1]), &mut cache))));
        }
        assert_eq!(cache.len(), ids.len());
        assert_close(&format!("decoded vs full logits on {dev:?}"), &stepped, &full, 1e-4);
    }
}

/// A conversation's follow-up (the earlier question and answer in the chat template, then the new
/// question) prefills only what its cache does not hold, needs no image embeddings, and answers
/// token for token as the whole prompt prefilled afresh; an earlier turn that changed is noticed
/// (the cache serves only up to where the prompts part), on ndarray and flex.
#[test]
fn a_conversations_follow_up_reuses_its_cache_and_answers_as_a_fresh_prompt() {
    use model::vlm::{Exchange, PromptCache};
    use std::ops::ControlFlow;
    for dev in [Device::ndarray(), Device::flex()] {
        let m = LlavaOnevision::load(&fixture(), &dev).unwrap();
        let (t, vd) = (9, m.cfg.vision.hidden_size);
        let grid: Vec<f32> = (0..t * vd).map(|i| (i as f32 * 0.37).sin()).collect();
        let images = vec![m.token_embeds(Tensor::from_data(TensorData::new(grid, [t, vd]), &dev))];
        let counts = [t + 1];
        let opts = GenerateOptions { max_new_tokens: 6, ignore_stop: true, ..Default::default() };
        let go = |ids: &[u32], images: &[Tensor<2>], cache: &mut PromptCache| {
            m.generate_cached(ids, images, cache, &opts, |_| ControlFlow::Continue(())).unwrap()
        };
        let q1 = "What is on the table?";
        let ids1 = m.conversation_ids(&[], q1, &counts).unwrap();
        assert_eq!(ids1.iter().filter(|&&i| i == m.cfg.image_token_id).count(), t + 1);
        let mut cache = PromptCache::default();
        assert!(m.needs_images(&cache, &ids1));
        let a1 = go(&ids1, &images, &mut cache);
        assert_eq!(a1.cached_tokens, 0);
        // every answer token but the last went back through the model
        assert_eq!(cache.len(), ids1.len() + a1.ids.len() - 1);
        let earlier = [Exchange { question: q1.into(), answer: a1.text.clone() }];
        let ids2 = m.conversation_ids(&earlier, "Which object is closest to the camera?", &counts).unwrap();
        assert_eq!(ids2.iter().filter(|&&i| i == m.cfg.image_token_id).count(), t + 1, "the images once");
        assert!(!m.needs_images(&cache, &ids2), "the images are in the cache");
        let a2 = go(&ids2, &[], &mut cache);
        assert!(
            a2.cached_tokens + 2 >= ids1.len() && a2.cached_tokens < ids2.len(),
            "{} of {}",
            a2.cached_tokens,
            ids2.len()
        );
        let fresh = go(&ids2, &images, &mut PromptCache::default());
        assert_eq!((a2.ids.clone(), fresh.cached_tokens), (fresh.ids, 0), "follow-up vs fresh on {dev:?}");
        // the first question edited after its images: the cache serves the images, not what follows
        let edited = [Exchange { question: "What is under the table?".into(), answer: a1.text.clone() }];
        let ids3 = m.conversation_ids(&edited, "Which object is closest to the camera?", &counts).unwrap();
        let a3 = go(&ids3, &[], &mut cache);
        assert!(a3.cached_tokens > t && a3.cached_tokens < ids1.len(), "{} cached", a3.cached_tokens);
        assert_eq!(a3.ids, go(&ids3, &images, &mut PromptCache::default()).ids, "edited vs fresh on {dev:?}");
    }
}
