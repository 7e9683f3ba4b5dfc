//! The encoder's token mixer (`LanguageConfig::token_mixer`): a fresh one is the identity, a
//! trained one reaches across the grid (the plain encoder does not), burn-autodiff's gradients
//! match central differences, the frozen encoder and the export keep it, and the language stage
//! trains it at its own learning rate.
#![allow(deprecated)]

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use chatsplat_tests::{host, temp_dir};
use model::language::field::ParamGroup;
use model::language::{Encoder, FrozenEncoder, LanguageConfig, LanguageField, TokenMixer};
use model::rng::Rng;
use std::collections::BTreeMap;
use train::language::LanguageTrainer;

fn tensor(rows: usize, cols: usize, scale: f32, seed: u64, dev: &Device) -> Tensor<2> {
    let mut r = Rng::new(seed);
    Tensor::from_data(
        TensorData::new((0..rows * cols).map(|_| scale * r.normal()).collect::<Vec<f32>>(), [rows, cols]),
        dev,
    )
}

fn map(side: usize, c: usize, seed: u64, dev: &Device) -> Tensor<3> {
    tensor(side * side, c, 1.0, seed, dev).reshape([side, side, c])
}

/// The export test's small encoder, with or without a mixer.
fn cfg(token_mixer: bool) -> LanguageConfig {
    LanguageConfig { token_mixer, ..crate::language::small_encoder_cfg() }
}

/// An encoder with a mixer whose output projection is not zero (a trained one's stand-in).
fn mixing_encoder(dev: &Device) -> Encoder {
    let mut enc = Encoder::new(&cfg(true), 3, dev);
    enc.mixer.as_mut().unwrap().out = Param::from_tensor(tensor(6, 6, 0.5, 17, dev));
    enc
}

#[test]
fn a_fresh_mixer_is_the_identity_and_a_trained_one_reaches_across_the_grid() {
    let dev = Device::ndarray();
    let (plain, fresh) = (Encoder::new(&cfg(false), 3, &dev), Encoder::new(&cfg(true), 3, &dev));
    let m = map(6, 3, 1, &dev);
    assert_eq!(host(plain.forward(m.clone())), host(fresh.forward(m.clone())), "a fresh mixer changed the tokens");
    // change the pixels under token 0 only (the top-left 2x2 patch)
    let mut v = host(m.clone());
    for (y, x) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
        for c in 0..3 {
            v[(y * 6 + x) * 3 + c] += 1.5;
        }
    }
    let moved = Tensor::<3>::from_data(TensorData::new(v, [6, 6, 3]), &dev);
    let changed = |enc: &Encoder| {
        let (a, b) = (host(enc.forward(m.clone())), host(enc.forward(moved.clone())));
        (0..9).filter(|t| (0..6).any(|c| (a[t * 6 + c] - b[t * 6 + c]).abs() > 1e-6)).collect::<Vec<_>>()
    };
    assert_eq!(changed(&plain), vec![0], "the plain encoder is local: only the token over the patch moves");
    assert_eq!(changed(&mixing_encoder(&dev)), (0..9).collect::<Vec<_>>(), "the mixer reaches every token");
}

#[test]
fn mixer_gradients_match_central_differences() {
    let dev = Device::ndarray();
    let (t, d) = (5, 4);
    let base: [Tensor<2>; 5] = [
        tensor(t, d, 0.3, 1, &dev),
        tensor(d, d, 0.6, 2, &dev),
        tensor(d, d, 0.6, 3, &dev),
        tensor(d, d, 0.6, 4, &dev),
        tensor(d, d, 0.6, 5, &dev),
    ];
    let x = tensor(t, d, 1.0, 6, &dev);
    let weights = tensor(t, d, 1.0, 7, &dev);
    // loss(params, x) = sum(weights * mixer(x)) in f64 on the host
    let loss = |p: &[Vec<f32>; 5], x: &[f32]| -> f64 {
        let shapes = [[t, d], [d, d], [d, d], [d, d], [d, d]];
        let ts = std::array::from_fn(|i| Tensor::<2>::from_data(TensorData::new(p[i].clone(), shapes[i]), &dev));
        let m = TokenMixer::from_tensors(ts).unwrap();
        let y = host(m.forward(Tensor::from_data(TensorData::new(x.to_vec(), [t, d]), &dev)));
        y.iter().zip(host(weights.clone())).map(|(a, w)| *a as f64 * w as f64).sum()
    };
    let leaves: [Tensor<2>; 5] = std::array::from_fn(|i| base[i].clone().autodiff().require_grad());
    let xl = x.clone().autodiff().require_grad();
    let mixer = TokenMixer::from_tensors(leaves.clone()).unwrap();
    let g = (mixer.forward(xl.clone()) * weights.clone().autodiff()).sum().backward();
    let mut grads: Vec<Vec<f32>> = leaves.iter().map(|l| host(l.grad(&g).expect("a gradient"))).collect();
    grads.push(host(xl.grad(&g).expect("a gradient for the input")));
    let p0: [Vec<f32>; 5] = std::array::from_fn(|i| host(base[i].clone()));
    let x0 = host(x);
    let names = ["pos", "q", "k", "v", "o", "input"];
    let h = 1e-2f32;
    for (which, name) in names.iter().enumerate() {
        let n = grads[which].len();
        for idx in [0, n / 3, n / 2, n - 1] {
            let at = |s: f32| {
                let (mut p, mut x) = (p0.clone(), x0.clone());
                if which < 5 {
                    p[which][idx] += s
                } else {
                    x[idx] += s
                }
                loss(&p, &x)
            };
            let fd = (at(h) - at(-h)) / (2.0 * h as f64);
            let ad = grads[which][idx] as f64;
            assert!(
                (fd - ad).abs() <= 2e-2 * fd.abs().max(ad.abs()).max(0.1),
                "{name}[{idx}]: autodiff {ad} vs central difference {fd}"
            );
        }
        assert!(grads[which].iter().any(|g| g.abs() > 1e-4), "{name}: the gradient is all zero");
    }
}

#[test]
fn the_frozen_encoder_and_the_export_keep_the_mixer() {
    let dev = Device::ndarray();
    let enc = mixing_encoder(&dev);
    let m = map(6, 3, 2, &dev);
    let want = host(enc.forward_level(m.clone(), true));
    let plain = host(
        Encoder::from_named(enc.named().into_iter().filter(|(n, _)| !n.starts_with("mix.")).collect())
            .unwrap()
            .forward_level(m.clone(), true),
    );
    assert_ne!(want, plain, "the mixer did nothing");
    let got = host(FrozenEncoder::new(enc.clone()).forward_level(m.clone(), true));
    let err = want.iter().zip(&got).fold(0f32, |e, (a, b)| e.max((a - b).abs()));
    assert!(err <= 1e-4, "the frozen encoder differs by {err}");
    let path = temp_dir("mixer-export.safetensors");
    let c = cfg(true);
    let params = model::language::export::write_encoder(&path, &enc, &c, "tiny").unwrap();
    let without = 3 * 5 + 5 + 5 * 6 + 6 + 2 * 2 * 6 * 6 + 6 + 4 * 9 * 6;
    assert_eq!(params, without + 9 * 6 + 4 * 6 * 6, "the mixer's position table and four projections");
    let (back, c2) = model::language::export::read_encoder(&path, &dev).unwrap();
    assert!(c2.token_mixer, "the header says the file has a mixer");
    assert_eq!(host(back.forward_level(m, true)), want, "tokens differ after the export round trip");
    // a mixer with a tensor missing is refused by name
    let broken: Vec<_> = enc.named().into_iter().filter(|(n, _)| n != "mix.k").collect();
    let e = Encoder::from_named(broken).err().unwrap().to_string();
    assert!(e.contains("mixer is incomplete"), "{e}");
    let mut wrong = enc.named();
    wrong.iter_mut().find(|(n, _)| n == "mix.v").unwrap().1 = tensor(6, 5, 1.0, 1, &dev);
    let e = Encoder::from_named(wrong).err().unwrap().to_string();
    assert!(e.contains("mix.v is [6, 5], expected [6, 6]"), "{e}");
}

#[test]
fn the_mixer_is_named_and_grouped_for_its_own_learning_rate() {
    let dev = Device::ndarray();
    let c = cfg(true);
    let field = LanguageField::new(&c, 4, 1, &dev);
    let names: Vec<String> = field.named().into_iter().map(|(n, _)| n).collect();
    assert_eq!(names, LanguageField::names(&c), "names() lists what named() gives");
    let mixer: Vec<&String> = names.iter().filter(|n| ParamGroup::of(n) == ParamGroup::Mixer).collect();
    assert_eq!(mixer, ["encoder.mix.pos", "encoder.mix.q", "encoder.mix.k", "encoder.mix.v", "encoder.mix.o"]);
    assert_eq!(ParamGroup::of("encoder.patch.weight"), ParamGroup::Encoder);
    assert_eq!(ParamGroup::of("view_features"), ParamGroup::Features);
    let back = LanguageField::from_named(field.named()).unwrap();
    assert!(back.encoder.mixer.is_some(), "the mixer survives a save/load by name");
}

/// One Adam step of the language stage (epsilon 1e-15, no warm-up) moves every weight that has
/// a gradient by its group's rate: from a fresh mixer only the output projection has one (the
/// others sit behind it), and it moves by `lr_mixer`, not by the encoder's rate.
#[test]
fn the_language_stage_trains_the_mixer_at_its_own_rate() {
    let case = crate::language_hard_cases::Case::new("mixer", |_| {});
    let dev = Device::ndarray();
    let one_step = |lr_mixer: f64| {
        let mut c = crate::language_hard_cases::cfg(1);
        (c.field.token_mixer, c.warmup_iters, c.lr_mixer) = (true, 0, lr_mixer);
        let mut t = LanguageTrainer::new(&case.geometry(), case.teacher_set(), c, &dev).unwrap();
        let before = t.scene.field.named();
        t.step(0).unwrap();
        let moved = |(n, a): (String, Tensor<2>), b: Tensor<2>| {
            let d = host(a).iter().zip(host(b)).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
            (n, d)
        };
        before.into_iter().zip(t.scene.field.named()).map(|(a, (_, b))| moved(a, b)).collect::<BTreeMap<_, _>>()
    };
    let (off, slow, fast) = (one_step(0.0), one_step(0.001), one_step(0.01));
    for n in ["pos", "q", "k", "v", "o"] {
        let n = format!("encoder.mix.{n}");
        assert_eq!(off[&n], 0.0, "{n} moved at lr_mixer 0");
    }
    for (n, d) in [("pos", 0.0), ("q", 0.0), ("v", 0.0), ("o", 0.001)] {
        let got = slow[&format!("encoder.mix.{n}")];
        assert!((got - d).abs() <= 1e-3 * d + 1e-9, "mix.{n} moved {got}, expected {d}");
    }
    assert!((fast["encoder.mix.o"] - 0.01).abs() <= 1e-5, "mix.o moved {} at lr_mixer 0.01", fast["encoder.mix.o"]);
    let patch = "encoder.patch.weight";
    assert!(off[patch] > 0.0, "the rest of the encoder trains");
    assert_eq!(slow[patch], fast[patch], "the encoder's own rate does not depend on lr_mixer");
}
