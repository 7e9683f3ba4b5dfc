//! The Rust tower trained on the crops file `dump_crops` writes, in the way of
//! `eval/probes/tower_probe.py` (random batches of 16 of the first 7000 crops, AdamW 1e-3, the
//! per-token shape cross-entropy; `MULTI=1`: the colour, shape and size losses with shape weighted
//! `SW`, default 1), printing the per-token shape accuracy on object tokens every 100 steps:
//! `cargo run --release -p eval --example tower_on_dump -- /tmp/crops.bin 400`
//! (eval/journal/2026-11-24.md, "The tower does not learn shape in burn where the same ViT does in
//! PyTorch").
#![allow(deprecated)]
use burn::module::Module;
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::rng::Rng;
use train::vlm::{VlmTrainConfig, init_model};

#[derive(Module, Debug)]
struct Probe {
    tower: model::vlm::siglip::VisionTower,
    head: burn::nn::Linear,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(file), Some(steps)) = (args.get(1), args.get(2).and_then(|a| a.parse::<usize>().ok())) else {
        return Err("usage: tower_on_dump CROPS STEPS".into());
    };
    let raw = std::fs::read(file)?;
    let (s, g2) = (96usize, 64usize);
    let rec = 3 * s * s + g2 * 3;
    let n = raw.len() / rec;
    let multi = std::env::var("MULTI").is_ok();
    let shape_weight: f32 = std::env::var("SW").ok().and_then(|v| v.parse().ok()).unwrap_or(1.0);
    let cfg = VlmTrainConfig::default();
    let dev = Device::ndarray().autodiff();
    let vlm = init_model(&cfg, &dev)?;
    let mut rng = Rng::new(cfg.seed ^ 0xDA7A);
    let mut m = Probe {
        tower: vlm.vision,
        head: model::vlm::layers::init_linear(&mut rng, 128, if multi { 19 } else { 7 }, true, 0.02, &dev),
    };
    let mut opt = AdamWConfig::new().with_weight_decay(0.01).init();
    let mut accs = Vec::new();
    for step in 0..steps {
        let idx: Vec<usize> = (0..16).map(|_| (rng.next_u64() % 7000.min(n as u64)) as usize).collect();
        let mut px = Vec::new();
        let mut all: [Vec<i64>; 3] = Default::default();
        for &i in &idx {
            let r = &raw[i * rec..(i + 1) * rec];
            px.extend(r[..3 * s * s].iter().map(|&v| v as f32 / 255.0 * 2.0 - 1.0));
            for (k, v) in all.iter_mut().enumerate() {
                v.extend((0..g2).map(|t| r[3 * s * s + t * 3 + k] as i64));
            }
        }
        let x = Tensor::<4>::from_data(TensorData::new(px, [16, 3, s, s]), &dev);
        let logits = m.head.forward(m.tower.forward(x).reshape([16 * g2, 128]));
        let ce = |lg: Tensor<2>, lab: &[i64]| {
            let lab = lab.to_vec();
            let y = Tensor::<1, Int>::from_data(TensorData::new(lab, [16 * g2]), &dev);
            activation::log_softmax(lg, 1).gather(1, y.reshape([16 * g2, 1])).mean().neg()
        };
        let (loss, logits) = if multi {
            let l = (ce(logits.clone().narrow(1, 0, 9), &all[0])
                + ce(logits.clone().narrow(1, 9, 7), &all[1]) * shape_weight
                + ce(logits.clone().narrow(1, 16, 3), &all[2]))
                / 3.0;
            (l, logits.narrow(1, 9, 7))
        } else {
            (ce(logits.clone(), &all[1]), logits)
        };
        let best: Vec<i64> = logits.argmax(1).into_data().convert::<i64>().to_vec().map_err(|e| format!("{e:?}"))?;
        let shape = &all[1];
        let obj: Vec<usize> = (0..16 * g2).filter(|&i| shape[i] > 0).collect();
        accs.push(obj.iter().filter(|&&i| best[i] == shape[i]).count() as f32 / obj.len().max(1) as f32);
        let grads = GradientsParams::from_grads(loss.backward(), &m);
        m = opt.step(1e-3, m, grads);
        if (step + 1) % 100 == 0 {
            let mean: f32 = accs[accs.len() - 50..].iter().sum::<f32>() / 50.0;
            println!("{} train {:.2}", step + 1, mean);
        }
    }
    Ok(())
}
