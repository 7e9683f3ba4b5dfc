//! `encoder-probe`: can ChatSplat's encoder carry "how many" at all? The
//! encoder is local: a per-pixel lifting network, a non-overlapping patch convolution and a
//! per-token scale/shift, so a token sees its own patch only, while the teacher's tokens come out
//! of global attention. Here the field is left out: the encoder reads the ground-truth pixels of a
//! view (RGB as a 3-channel map) and is fitted to the teacher's tokens of the training views of
//! each scene (view level, L1, as the language stage does). Then count and colours are asked on
//! the training and the held-out views from the teacher's tokens and from the encoder's. With
//! `--mix` the encoder has its token mixer (`model::language::TokenMixer`: one self-attention
//! layer over the token grid, learned positions, residual, zero-initialised output) between the
//! patch convolution and the scale/shift: the same fit with global reach.
//!
//! cargo run --release -p eval --bin encoder-probe -- --seeds 5 --first-seed 30000 [--mix]
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use clap::Parser;
use eval::harness::{HeldOutSeeds, ModelArgs};
use eval::probe::{Region, count_answer, regions, token_l1, view_truth};
use model::Result;
use model::chat::answer;
use model::data::synth::scene::SynthScene;
use model::data::synth::{SynthOptions, write_dataset};
use model::data::{LoadOptions, View, load_any};
use model::language::{Encoder, LanguageConfig};
use model::rng::Rng;
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use scoring::compare::{exact, greedy};
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "encoder-probe", about = "Whether the local encoder on true pixels keeps count on new views")]
struct Args {
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    held_out: HeldOutSeeds,
    #[arg(long, default_value_t = 48)]
    views: usize,
    /// Adam steps per scene (one training view per step).
    #[arg(long, default_value_t = 1500)]
    iters: usize,
    #[arg(long, default_value_t = 0.002)]
    lr: f64,
    /// Add one self-attention token-mixing block after the patch convolution.
    #[arg(long)]
    mix: bool,
    /// Fit one encoder on the training views of every scene (default: one per scene, as ChatSplat).
    #[arg(long)]
    pooled: bool,
    #[arg(long, default_value = "out/encoder-probe")]
    out: PathBuf,
}

eval::bench_main!("encoder-probe", probe);

struct Sample {
    map: Vec<f32>,
    teacher: Vec<f32>,
    held_out: bool,
    count: usize,
    colors: String,
    edge: Vec<bool>,
    scene: usize,
}

fn tokens(enc_names: &[String], p: &BTreeMap<String, Tensor<2>>, map: Tensor<3>) -> Result<Tensor<2>> {
    let enc = Encoder::from_named(enc_names.iter().map(|n| (n.clone(), p[n].clone())).collect())?;
    Ok(enc.forward_level(map, false))
}

fn probe(a: &Args) -> Result<()> {
    let device: Device = a.model.device()?;
    let vlm_dir = a.model.vlm_dir()?;
    let vlm = LlavaOnevision::load(&vlm_dir, &device)?;
    let (d, p) = (vlm.cfg.vision.hidden_size, vlm.cfg.vision.patch_size);
    let side = vlm.cfg.vision.image_size;
    let grid = side / p;
    let cfg = LanguageConfig {
        view_channels: 3,
        object_channels: 3,
        dim: d,
        grid,
        patch: p,
        teacher_image: side,
        teacher_patch: p,
        scale_shift_per_level: false,
        token_mixer: a.mix,
        ..Default::default()
    };
    let mut samples = Vec::new();
    for (si, seed) in a.held_out.range().enumerate() {
        let data = a.out.join(format!("seed{seed}"));
        let opts = SynthOptions { seed, views: a.views, width: side as u32, height: side as u32, ..Default::default() };
        write_dataset(&data, &opts, |_, _| {})?;
        let scene: SynthScene = model::io::read_json(&data.join("scene.json"))?;
        let ds = load_any(&data, &LoadOptions::default())?;
        let split = ds.train.iter().map(|v| (v, false)).chain(ds.test.iter().map(|v| (v, true)));
        for (v, held_out) in split {
            if let Some(s) = sample(&vlm, &scene, v, held_out, si, p)? {
                samples.push(s);
            }
        }
        eprint!("\rencoder-probe: {} views", samples.len());
    }
    eprintln!();
    let ad = device.clone().autodiff();
    let t = grid * grid;
    let fresh = |seed: u64| Encoder::new(&cfg, seed, &device).named();
    let enc_names: Vec<String> = Encoder::new(&cfg, 0, &device).named().into_iter().map(|(n, _)| n).collect();
    let groups: Vec<Vec<usize>> = if a.pooled {
        vec![(0..a.held_out.seeds as usize).collect()]
    } else {
        (0..a.held_out.seeds as usize).map(|s| vec![s]).collect()
    };
    let mut predicted: Vec<Option<Vec<f32>>> = vec![None; samples.len()];
    let adam = burn::optim::AdamConfig::new().with_epsilon(1e-15).build();
    for (gi, g) in groups.iter().enumerate() {
        let train: Vec<usize> =
            (0..samples.len()).filter(|&i| !samples[i].held_out && g.contains(&samples[i].scene)).collect();
        let mut params = fresh(gi as u64);
        let mut states = train::adam_state::AdamStates::default();
        let mut rng = Rng::new(gi as u64 + 7);
        let mut avg = 0.0;
        for it in 0..a.iters {
            let s = &samples[train[(rng.next_u64() % train.len() as u64) as usize]];
            let leaves: Vec<(String, Tensor<2>)> =
                params.iter().map(|(n, x)| (n.clone(), x.clone().autodiff().require_grad())).collect();
            let pm: BTreeMap<String, Tensor<2>> = leaves.iter().cloned().collect();
            let map = Tensor::<3>::from_data(TensorData::new(s.map.clone(), [side, side, 3]), &ad);
            let target = Tensor::<2>::from_data(TensorData::new(s.teacher.clone(), [t, d]), &ad);
            let loss = (tokens(&enc_names, &pm, map)? - target).abs().mean();
            avg = 0.98 * avg + 0.02 * host(loss.clone())[0] as f64;
            let grads = loss.backward();
            let lr = a.lr * 0.5 * (1.0 + (std::f64::consts::PI * it as f64 / a.iters as f64).cos());
            params = leaves
                .iter()
                .zip(params)
                .map(|((n, leaf), (_, value))| match leaf.grad(&grads) {
                    Some(g) => (n.clone(), states.step(&adam, n, lr, value, g)),
                    None => (n.clone(), value),
                })
                .collect();
            if it % 100 == 0 || it + 1 == a.iters {
                eprint!("\rencoder-probe: group {gi} step {it} L1 {avg:.3}   ");
            }
        }
        eprintln!();
        let pm: BTreeMap<String, Tensor<2>> = params.into_iter().collect();
        for (i, s) in samples.iter().enumerate() {
            if g.contains(&s.scene) {
                let map = Tensor::<3>::from_data(TensorData::new(s.map.clone(), [side, side, 3]), &device);
                predicted[i] = Some(host(tokens(&enc_names, &pm, map)?));
            }
        }
    }
    // ask
    let opts = greedy();
    // [train, held] x [teacher, encoder]: (count right, colours right, asked, under, l1 sum, l1 n, edge l1 sum, n)
    let mut tally = [[[0f64; 8]; 2]; 2];
    for (i, s) in samples.iter().enumerate() {
        let enc = predicted[i].clone().expect("every scene was fitted");
        for (src, toks) in [&s.teacher, &enc].into_iter().enumerate() {
            let x = Tensor::<2>::from_data(TensorData::new(toks.clone(), [t, d]), &device);
            let count = answer(&vlm, std::slice::from_ref(&x), "How many objects are there?", &opts, |_| {})?;
            let cols = answer(&vlm, &[x], "What colors are there?", &opts, |_| {})?;
            let e = &mut tally[s.held_out as usize][src];
            e[0] += exact(&count.text, &s.count.to_string()) as u8 as f64;
            e[1] += exact(&cols.text, &s.colors) as u8 as f64;
            e[2] += 1.0;
            if let Some(n) = count_answer(&count.text) {
                e[3] += (n < s.count as i64) as u8 as f64;
            }
            for (k, edge) in s.edge.iter().enumerate() {
                let l = token_l1(toks, &s.teacher, k, d);
                e[4] += l;
                e[5] += 1.0;
                if *edge {
                    e[6] += l;
                    e[7] += 1.0;
                }
            }
        }
        eprint!("\rencoder-probe: asked {}/{}", i + 1, samples.len());
    }
    eprintln!();
    println!(
        "encoder-probe: {} scenes from {}, {} iters, lr {}, mix {}, pooled {}",
        a.held_out.seeds, a.held_out.first_seed, a.iters, a.lr, a.mix, a.pooled
    );
    println!("| views | tokens | asked | count right % | under | colours right % | token L1 | edge L1 |");
    println!("|---|---|---|---|---|---|---|---|");
    for (h, name) in ["training", "held out"].iter().enumerate() {
        for (src, sname) in ["teacher", "encoder on pixels"].iter().enumerate() {
            let e = &tally[h][src];
            println!(
                "| {name} | {sname} | {} | {:.1} | {} | {:.1} | {:.3} | {:.3} |",
                e[2],
                100.0 * e[0] / e[2].max(1.0),
                e[3],
                100.0 * e[1] / e[2].max(1.0),
                e[4] / e[5].max(1.0),
                e[6] / e[7].max(1.0)
            );
        }
    }
    Ok(())
}

/// One unambiguous view: its map (the pixels), the teacher's tokens, the true answers, and which
/// tokens are edges (one object and background, or two objects).
fn sample(
    vlm: &LlavaOnevision,
    scene: &SynthScene,
    v: &View,
    held_out: bool,
    si: usize,
    p: usize,
) -> Result<Option<Sample>> {
    let Some(ids) = v.instance_ids.as_ref() else { return Ok(None) };
    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
    let Some((count, colors)) = view_truth(scene, ids, w, h) else { return Ok(None) };
    let teacher = host(vlm.teacher_tokens(&RgbImage::from_f32(w, h, &v.rgb)));
    let edge = regions(ids, w, h, p).into_iter().map(Region::is_boundary).collect();
    Ok(Some(Sample { map: v.rgb.clone(), teacher, held_out, count, colors, edge, scene: si }))
}
