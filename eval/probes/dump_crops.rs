//! Writes the tower's object-crop training images with their per-token labels, for
//! `eval/probes/tower_probe.py` (the same crops trained in PyTorch):
//! `cargo run --release -p eval --example dump_crops -- 8000 /tmp/crops.bin`.
//! Each record: the crop as `[3, S, S]` u8 (S = the tower's input side), then per token the
//! (colour, shape, size) classes as u8 (0: no object).
#![allow(deprecated)]
use model::rng::Rng;
use std::io::Write;
use train::vlm::data::{DataSpec, SampleKind};
use train::vlm::{TRAIN_SEEDS, VlmTrainConfig, init_model};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(n), Some(out)) = (args.get(1).and_then(|a| a.parse::<usize>().ok()), args.get(2)) else {
        return Err("usage: dump_crops N OUT".into());
    };
    let cfg = VlmTrainConfig::default();
    let vlm = init_model(&cfg, &burn::tensor::Device::ndarray())?;
    let spec = DataSpec::of(&cfg, &vlm.cfg, &vlm.processor);
    let mut rng = Rng::new(5);
    let mut f = std::io::BufWriter::new(std::fs::File::create(out)?);
    let (mut got, mut seed) = (0, TRAIN_SEEDS);
    while got < n {
        seed =
            if std::env::var("RANDOM_SEEDS").is_ok() { TRAIN_SEEDS + rng.next_u64() % 1_000_000_000 } else { seed + 1 };
        let Some(sample) = spec.sample(SampleKind::Object, seed, &mut rng) else { continue };
        let im = &sample.images[0];
        let px: Vec<u8> = im.pixels.iter().map(|v| ((v * 0.5 + 0.5).clamp(0.0, 1.0) * 255.0).round() as u8).collect();
        f.write_all(&px)?;
        f.write_all(&im.labels.iter().flat_map(|l| [l[0], l[1], l[2]]).collect::<Vec<u8>>())?;
        got += 1;
    }
    f.flush()?;
    Ok(())
}
