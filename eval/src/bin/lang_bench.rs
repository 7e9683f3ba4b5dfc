//! `lang-bench`: ChatSplat's speed against error on a trained scene.
//!
//! * token fidelity on held-out views: L1 / cosine of (i) ChatSplat tokens and (ii) the paper's
//!   LLaVA-OV baseline, teacher(rendered RGB), against teacher(ground-truth image); the same per
//!   object with the ground-truth masks;
//! * LLM agreement: KL(P(next token | teacher(GT)) || P(next token | tokens)) over a question set;
//! * speed: views/s (render + encode) and objects/s (identity render, crop, mask, encode) against
//!   the baseline (render RGB + vision tower);
//! * sweeps: language channels {8, 16, 32, 64}, Gaussians kept by language contribution, and the
//!   ablations without the scaling adjustment and without the lifting network; a PNG plot.
//!
//! cargo run --release -p eval --bin lang-bench -- --run RUN [--vlm DIR] [--backend ndarray|wgpu]
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData, activation};
use clap::Parser;
use eval::harness::{ModelArgs, TokenFidelity};
use model::Result;
use model::chat::ChatSession;
use model::data::View;
use model::language::{Encoder, FrozenEncoder, LanguageConfig, object_image};
use model::run::{GeometryRun, LanguageRun};
use model::scene::LanguageScene;
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use scoring::plot::{Chart, Series};
use std::path::PathBuf;
use std::time::Instant;
use train::language::{LanguageTrainConfig, fit};
use train::teacher::{ExtractOptions, TeacherSet};

#[derive(Parser)]
#[command(name = "lang-bench", about = "ChatSplat: token fidelity, LLM agreement and speed against error")]
struct Args {
    /// Geometry run with a trained language run.
    #[arg(long)]
    run: PathBuf,
    /// Language run (default: RUN/language).
    #[arg(long)]
    language: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    /// Output directory for sweep runs, bench.json and the plot (default: RUN/bench).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Iterations per sweep/ablation field (0: no sweep).
    #[arg(long, default_value_t = 300)]
    sweep_iters: usize,
    /// Timed repetitions for speed.
    #[arg(long, default_value_t = 3)]
    reps: usize,
    /// Also time an encoder of the real size (D = 1152, 32 -> 128 -> 1152, 14x14 patches) on a
    /// random map: what a LLaVA-OneVision field costs per view here.
    #[arg(long)]
    full_size: bool,
}

const QUESTIONS: [&str; 3] =
    ["Describe this image.", "What objects are on the table?", "What colour is the largest object?"];

#[derive(Default, Clone, Copy, Debug, serde::Serialize)]
struct Fidelity {
    view: TokenFidelity,
    view_baseline: TokenFidelity,
    object: TokenFidelity,
    object_baseline: TokenFidelity,
    kl: f64,
    kl_baseline: f64,
    kl_n: usize,
}

fn image_of(v: &View) -> RgbImage {
    RgbImage::from_f32(v.camera.width as usize, v.camera.height as usize, &v.rgb)
}

fn tokens_host(vlm: &LlavaOnevision, img: &RgbImage) -> Vec<f32> {
    host(vlm.teacher_tokens(img))
}

fn next_token_probs(vlm: &LlavaOnevision, tokens: &[f32], q: &str) -> Result<Vec<f64>> {
    let d = vlm.cfg.vision.hidden_size;
    let t = Tensor::<2>::from_data(TensorData::new(tokens.to_vec(), [tokens.len() / d, d]), &vlm.device());
    let embeds = vlm.prompt_embeds(q, &[vlm.token_embeds(t)])?;
    let logits = vlm.logits(embeds);
    let [n, v] = logits.dims();
    Ok(host(activation::softmax(logits.narrow(0, n - 1, 1).reshape([v]), 0)).into_iter().map(|p| p as f64).collect())
}

fn kl(p: &[f64], q: &[f64]) -> f64 {
    p.iter().zip(q).filter(|(a, _)| **a > 0.0).map(|(a, b)| a * (a / b.max(1e-30)).ln()).sum()
}

/// Token fidelity (and, with `questions`, LLM agreement) of `scene` on `views`.
fn fidelity(
    scene: &LanguageScene,
    vlm: &LlavaOnevision,
    views: &[View],
    with_baseline: bool,
    questions: bool,
) -> Result<Fidelity> {
    let d = vlm.cfg.vision.hidden_size;
    let mut f = Fidelity::default();
    let opts = ExtractOptions::default();
    for v in views {
        let gt_img = image_of(v);
        let gt = tokens_host(vlm, &gt_img);
        let cs = host(scene.reader_tokens(vlm, scene.view_tokens(&scene.field, &v.camera)?));
        f.view.add(&cs, &gt, d);
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let base_img = with_baseline
            .then(|| {
                scene
                    .render(&v.camera)
                    .map(|r| RgbImage::from_f32(w, h, &r.rgb.iter().map(|x| x.clamp(0.0, 1.0)).collect::<Vec<_>>()))
            })
            .transpose()?;
        let base = base_img.as_ref().map(|b| tokens_host(vlm, b));
        if let Some(b) = &base {
            f.view_baseline.add(b, &gt, d);
        }
        if questions {
            for q in QUESTIONS {
                let p = next_token_probs(vlm, &gt, q)?;
                f.kl += kl(&p, &next_token_probs(vlm, &cs, q)?);
                if let Some(b) = &base {
                    f.kl_baseline += kl(&p, &next_token_probs(vlm, b, q)?);
                }
                f.kl_n += 1;
            }
        }
        let Some(ids) = &v.instance_ids else { continue };
        for id in opts.objects(ids) {
            let Some((obj, crop)) = object_image(&gt_img, ids, id, scene.margin) else { continue };
            let gt_o = tokens_host(vlm, &obj);
            let (oc, mask) = scene.object_crop(&v.camera, id, crop.bbox)?;
            let tokens = scene.reader_tokens(vlm, scene.object_tokens_with(&scene.field, &oc, &mask)?);
            f.object.add(&host(tokens), &gt_o, d);
            if let Some(b) = &base_img {
                let (bo, _) = object_image(b, ids, id, scene.margin).expect("same mask");
                f.object_baseline.add(&tokens_host(vlm, &bo), &gt_o, d);
            }
        }
    }
    let k = f.kl_n.max(1) as f64;
    Ok(Fidelity {
        view: f.view.mean(),
        view_baseline: f.view_baseline.mean(),
        object: f.object.mean(),
        object_baseline: f.object_baseline.mean(),
        kl: f.kl / k,
        kl_baseline: f.kl_baseline / k,
        kl_n: f.kl_n,
    })
}

#[derive(Default, Clone, Copy, Debug, serde::Serialize)]
struct Speed {
    views_per_s: f64,
    objects_per_s: f64,
    baseline_views_per_s: f64,
    baseline_objects_per_s: f64,
}

/// A pixel inside each GT object of `v` (for timed clicks).
fn clicks(v: &View) -> Vec<(usize, usize)> {
    let Some(ids) = &v.instance_ids else { return vec![] };
    let w = v.camera.width as usize;
    ExtractOptions::default()
        .objects(ids)
        .into_iter()
        .filter_map(|id| {
            let px: Vec<usize> = (0..ids.len()).filter(|&p| ids[p] == id).collect();
            px.get(px.len() / 2).map(|&p| (p % w, p / w))
        })
        .collect()
}

/// Views/s and objects/s of `scene`'s tokens as `chat` makes them (through the tower's last
/// layers where the field leaves them to it), and with `baseline` the render-then-tower path's.
fn speed(scene: &LanguageScene, vlm: &LlavaOnevision, baseline: bool, views: &[View], reps: usize) -> Result<Speed> {
    let mut s = Speed::default();
    // inference as `chat` runs it: the encoder frozen once, its fold formed
    let enc = FrozenEncoder::new(scene.field.encoder.clone());
    let view_tokens = |v: &View| -> Result<Tensor<2>> {
        Ok(scene.reader_tokens(vlm, enc.forward_level(scene.view_map(&scene.field, &v.camera)?, false)))
    };
    // warm-up (kernel compilation on wgpu)
    let _ = host(view_tokens(&views[0])?);
    let t0 = Instant::now();
    for _ in 0..reps {
        for v in views {
            let _ = host(view_tokens(v)?);
        }
    }
    s.views_per_s = (reps * views.len()) as f64 / t0.elapsed().as_secs_f64();
    let (mut n, t0) = (0, Instant::now());
    for _ in 0..reps {
        for v in views {
            for (x, y) in clicks(v) {
                if let Some((_, map)) = scene.object_map_at(&v.camera, x, y)? {
                    let _ = host(scene.reader_tokens(vlm, enc.forward_level(map, true)));
                    n += 1;
                }
            }
        }
    }
    s.objects_per_s = n as f64 / t0.elapsed().as_secs_f64().max(1e-9);
    if baseline {
        let t0 = Instant::now();
        for _ in 0..reps {
            for v in views {
                let r = scene.render(&v.camera)?;
                let _ = tokens_host(
                    vlm,
                    &RgbImage::from_f32(
                        v.camera.width as usize,
                        v.camera.height as usize,
                        &r.rgb.iter().map(|x| x.clamp(0.0, 1.0)).collect::<Vec<_>>(),
                    ),
                );
            }
        }
        s.baseline_views_per_s = (reps * views.len()) as f64 / t0.elapsed().as_secs_f64();
        let (mut n, t0) = (0, Instant::now());
        for _ in 0..reps {
            for v in views {
                let Some(ids) = &v.instance_ids else { continue };
                let r = scene.render(&v.camera)?;
                let img = RgbImage::from_f32(
                    v.camera.width as usize,
                    v.camera.height as usize,
                    &r.rgb.iter().map(|x| x.clamp(0.0, 1.0)).collect::<Vec<_>>(),
                );
                for id in ExtractOptions::default().objects(ids) {
                    if let Some((o, _)) = object_image(&img, ids, id, scene.margin) {
                        let _ = tokens_host(vlm, &o);
                        n += 1;
                    }
                }
            }
        }
        s.baseline_objects_per_s = n as f64 / t0.elapsed().as_secs_f64().max(1e-9);
    }
    Ok(s)
}

#[derive(Clone, Debug, serde::Serialize)]
struct Row {
    name: String,
    channels: usize,
    gaussians: usize,
    feature_bytes: usize,
    view_l1: f64,
    view_cos: f64,
    object_l1: f64,
    views_per_s: f64,
    objects_per_s: f64,
    train_s_per_iter: Option<f64>,
}

fn row(
    name: &str,
    scene: &LanguageScene,
    vlm: &LlavaOnevision,
    views: &[View],
    reps: usize,
    train_s: Option<f64>,
) -> Result<Row> {
    let f = fidelity(scene, vlm, views, false, false)?;
    let s = speed(scene, vlm, false, views, reps)?;
    let c = scene.field.view_features.val().dims()[1];
    let r = Row {
        name: name.to_string(),
        channels: c,
        gaussians: scene.field.len(),
        feature_bytes: scene.field.len() * c * 2 * 4,
        view_l1: f.view.l1,
        view_cos: f.view.cos,
        object_l1: f.object.l1,
        views_per_s: s.views_per_s,
        objects_per_s: s.objects_per_s,
        train_s_per_iter: train_s,
    };
    println!(
        "| {} | {} | {} | {:.2} MB | {:.4} | {:.4} | {:.4} | {:.2} | {:.2} | {} |",
        r.name,
        r.channels,
        r.gaussians,
        r.feature_bytes as f64 / 1e6,
        r.view_l1,
        r.view_cos,
        r.object_l1,
        r.views_per_s,
        r.objects_per_s,
        train_s.map(|t| format!("{t:.3}")).unwrap_or_else(|| "-".into())
    );
    Ok(r)
}

eval::bench_main!("lang-bench", bench);

fn bench(a: &Args) -> Result<()> {
    let device: Device = a.model.device()?;
    let vlm_dir = a.model.vlm_dir()?;
    let geometry = GeometryRun::new(&a.run);
    let lang = a.language.as_ref().map(LanguageRun::new).unwrap_or_else(|| geometry.language());
    let out = a.out.clone().unwrap_or_else(|| a.run.join("bench"));
    model::io::create_dir(&out)?;
    // every Gaussian: the rows below keep fractions of them, and the run's compaction among them
    let session = ChatSession::open_full(&geometry, Some(&lang.dir), &vlm_dir, &device)?;
    let teacher_dir = lang.teacher()?.dir;
    let ds = TeacherSet::open(&teacher_dir)?.dataset()?;
    let held: &[View] = if ds.test.is_empty() { &ds.train } else { &ds.test };
    let vlm = &session.vlm;
    let scene = &session.scene;
    println!(
        "# lang-bench: {} ({} Gaussians, {} held-out views {}x{}), teacher {} (D = {}), {:?}",
        a.run.display(),
        scene.field.len(),
        held.len(),
        held[0].camera.width,
        held[0].camera.height,
        vlm_dir.display(),
        vlm.cfg.vision.hidden_size,
        a.model.backend
    );

    let f = fidelity(scene, vlm, held, true, true)?;
    println!("\n## Token fidelity on held-out views (against teacher(ground truth))\n");
    println!("| tokens | view L1 | view cosine | object L1 | object cosine | objects | KL next token (nats) |");
    println!("|---|---|---|---|---|---|---|");
    println!(
        "| ChatSplat (rendered language maps -> encoder) | {:.4} | {:.4} | {:.4} | {:.4} | {} | {:.4} |",
        f.view.l1, f.view.cos, f.object.l1, f.object.cos, f.object.grids, f.kl
    );
    println!(
        "| LLaVA-OV baseline: teacher(rendered RGB) | {:.4} | {:.4} | {:.4} | {:.4} | {} | {:.4} |",
        f.view_baseline.l1,
        f.view_baseline.cos,
        f.object_baseline.l1,
        f.object_baseline.cos,
        f.object_baseline.grids,
        f.kl_baseline
    );
    println!("\n(KL averaged over {} view x question pairs: {:?})", f.kl_n, QUESTIONS);

    let s = speed(scene, vlm, true, held, a.reps)?;
    println!("\n## Speed ({:?}, {} views x {} reps)\n", a.model.backend, held.len(), a.reps);
    println!("| path | views/s | objects/s |");
    println!("|---|---|---|");
    println!(
        "| ChatSplat: render language map + encode (object: identity render, crop camera, mask, encode) | \
            {:.2} | {:.2} |",
        s.views_per_s, s.objects_per_s
    );
    println!(
        "| baseline: render RGB + vision tower (object: + masked crop) | {:.2} | {:.2} |",
        s.baseline_views_per_s, s.baseline_objects_per_s
    );
    println!("| paper (A6000, real LLaVA-OV) ChatSplat / baseline | 72-81 / 9-11 FPS | 289 objects/s |");

    // Render only the tiles of an object's crop vs rendering the whole frame at the same density.
    let (mut t_crop, mut t_full, mut px_crop, mut px_full, mut n_obj) = (0.0, 0.0, 0usize, 0usize, 0);
    for v in held {
        let Some(ids) = &v.instance_ids else { continue };
        for id in ExtractOptions::default().objects(ids) {
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            let Some(bbox) = model::language::object_box(ids, w, h, id, scene.margin) else { continue };
            let oc = scene.cfg.object_camera(&v.camera, bbox);
            let side = (bbox[2] - bbox[0]).max(bbox[3] - bbox[1]) as f32;
            let k = oc.width as f32 / side; // render pixels per view pixel
            let mut full_cam = v.camera;
            full_cam.fx *= k;
            full_cam.fy *= k;
            full_cam.cx *= k;
            full_cam.cy *= k;
            full_cam.width = (w as f32 * k).round() as u32;
            full_cam.height = (h as f32 * k).round() as u32;
            let feats = scene.field.object_features.val();
            let _ = host(scene.render_map(feats.clone(), &oc)?.sum());
            let t0 = Instant::now();
            let _ = host(scene.render_map(feats.clone(), &oc)?.sum());
            t_crop += t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let _ = host(scene.render_map(feats, &full_cam)?.sum());
            t_full += t0.elapsed().as_secs_f64();
            px_crop += (oc.width * oc.height) as usize;
            px_full += (full_cam.width * full_cam.height) as usize;
            n_obj += 1;
        }
    }
    if n_obj > 0 {
        println!(
            "\nObject maps: rendering only the crop's tiles takes {:.2} ms per object ({:.0} kpx) vs {:.2} ms \
                for the whole frame at the same density ({:.0} kpx): {:.1}x faster ({n_obj} objects).",
            1e3 * t_crop / n_obj as f64,
            px_crop as f64 / n_obj as f64 / 1e3,
            1e3 * t_full / n_obj as f64,
            px_full as f64 / n_obj as f64 / 1e3,
            t_full / t_crop.max(1e-12)
        );
    }

    let mut full = None;
    if a.full_size {
        let cfg = LanguageConfig::default();
        let enc = Encoder::new(&cfg, 0, &device);
        let map = Tensor::<3>::random(
            [cfg.map_size(), cfg.map_size(), cfg.view_channels],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let _ = host(enc.forward(map.clone()));
        let t0 = Instant::now();
        let _ = host(enc.forward(map.clone()));
        let train_secs = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let frozen = FrozenEncoder::new(enc);
        let _ = host(frozen.forward_level(map.clone(), false));
        let first_secs = t0.elapsed().as_secs_f64();
        // the median of `--reps` calls: one call moved 13-49 ms between GPU leases
        let mut calls: Vec<f64> = (0..a.reps.max(1))
            .map(|_| {
                let t0 = Instant::now();
                let _ = host(frozen.forward_level(map.clone(), false));
                t0.elapsed().as_secs_f64()
            })
            .collect();
        calls.sort_by(f64::total_cmp);
        let secs = calls[calls.len() / 2];
        println!(
            "\nfull-size encoder (32 -> 128 -> 1152, 14x14 patches, 378x378 map -> 729 x 1152 tokens) on {}: \
                {secs:.3} s per view at inference (median of {} calls, {:.3}-{:.3} s; frozen{}; the first view, \
                freezing included, {first_secs:.3} s), {train_secs:.3} s as training runs it (the fold formed \
                per view)",
            a.model.backend,
            calls.len(),
            calls[0],
            calls[calls.len() - 1],
            if frozen.is_folded() { ": last lifting layer folded into the patch convolution" } else { "" },
        );
        full = Some(serde_json::json!({
            "inference_s_per_view": secs, "inference_calls_s": calls, "first_view_s": first_secs,
            "training_s_per_view": train_secs,
        }));
    }

    let mut rows = Vec::new();
    let header = "| field | channels | Gaussians | feature memory | held-out view L1 | view cosine | object \
        L1 | views/s | objects/s | train s/iter |\n|---|---|---|---|---|---|---|---|---|---|";
    println!("\n## Speed against error\n\n{header}");
    rows.push(row("trained (this run)", scene, vlm, held, a.reps, None)?);
    if let Some(c) = lang.read_compaction(scene.splats.len())? {
        rows.push(row("compacted (compact.json)", &scene.subset(&c.kept), vlm, held, a.reps, None)?);
    }
    // model only what a scene needs: Gaussians ranked by their language contribution
    let contribution = lang.read_contribution()?;
    let base_cfg: LanguageTrainConfig = model::io::read_json(&lang.config())?;
    let used = contribution.iter().filter(|&&c| c > 0.0).count();
    if used == 0 {
        println!(
            "\n(no Gaussian has a language contribution yet: {} holds the run's first checkpoint, before any \
                step; the rows of Gaussians kept by contribution are left out)",
            lang.checkpoint().display()
        );
    }
    for frac in [1.0, 0.5, 0.25, 0.1].into_iter().filter(|_| used > 0) {
        let keep = model::scene::top_contributors(&contribution, ((used as f64 * frac).round() as usize).max(1));
        rows.push(row(
            &format!("kept {:.0}% of contributing", frac * 100.0),
            &scene.subset(&keep),
            vlm,
            held,
            a.reps,
            None,
        )?);
    }
    if a.sweep_iters > 0 {
        let mut variants: Vec<(String, LanguageTrainConfig)> = Vec::new();
        for c in [8, 16, 32, 64] {
            let mut cfg = base_cfg.clone();
            cfg.field.view_channels = c;
            cfg.field.object_channels = c;
            variants.push((format!("channels {c}"), cfg));
        }
        let mut no_ss = base_cfg.clone();
        no_ss.field.scale_shift = false;
        variants.push(("no scale/shift".into(), no_ss));
        let mut no_lift = base_cfg.clone();
        no_lift.field.lifting = false;
        variants.push(("no lifting (features at D)".into(), no_lift));
        for (name, mut cfg) in variants {
            cfg.iters = a.sweep_iters;
            cfg.checkpoint_every = 0;
            let dir = LanguageRun::new(out.join(name.replace([' ', '/', '(', ')', '='], "_")));
            let bar = scoring::progress::Progress::new(name.clone(), "it");
            let resume = dir.checkpoint().is_file();
            let summary = fit(&geometry, &teacher_dir, &dir, cfg, &device, resume, &train::dist::Solo, |p| {
                bar.update_with(p.iter, p.iters, &format!("loss {:.4}", p.step.loss))
            })?;
            let sc = LanguageScene::load(&geometry, &dir, &device)?;
            rows.push(row(&name, &sc, vlm, held, a.reps, Some(summary.seconds_per_iter))?);
        }
    }
    let d = 1152usize;
    let n = scene.field.len();
    println!(
        "\nWithout the lifting network a LLaVA-OneVision field stores D = {d} channels per level: {:.1} MB \
            for these {n} Gaussians (vs {:.1} MB at 32 channels), {:.1} GB for 1M Gaussians, x3 with Adam moments.",
        (n * d * 2 * 4) as f64 / 1e6,
        (n * 32 * 2 * 4) as f64 / 1e6,
        (1_000_000 * d * 2 * 4) as f64 / 1e9
    );

    // the rows by the name's first word, then the teacher on renders
    let groups: [(&str, &[&str], [u8; 3]); 3] = [
        ("channels 8-64", &["channels"], [31, 119, 180]),
        ("Gaussians kept", &["kept", "trained"], [214, 39, 40]),
        ("ablations", &["no "], [44, 160, 44]),
    ];
    let mut series: Vec<Series> = groups
        .iter()
        .map(|(label, prefixes, color)| Series {
            label: label.to_string(),
            points: rows
                .iter()
                .filter(|r| prefixes.iter().any(|p| r.name.starts_with(p)))
                .map(|r| (r.views_per_s, r.view_l1))
                .collect(),
            color: *color,
        })
        .collect();
    series.push(Series {
        label: "LLaVA-OV on render".into(),
        points: vec![(s.baseline_views_per_s, f.view_baseline.l1)],
        color: [120, 120, 120],
    });
    let chart = Chart {
        title: format!("held-out token L1 vs views/s ({:?})", a.model.backend),
        x_label: "views per second (render + encode)".into(),
        y_label: "token L1 vs teacher(GT)".into(),
        log_x: true,
        series,
    };
    let png = out.join("speed_vs_error.png");
    chart.write_png(&png, 900, 600)?;
    let per_object = |t: f64| 1e3 * t / n_obj.max(1) as f64;
    let json = serde_json::json!({
        "fidelity": f, "speed": s, "rows": rows, "full_size_encoder_s_per_view": full,
        "object_crop_ms": per_object(t_crop), "object_full_frame_ms": per_object(t_full),
        "backend": a.model.backend.to_string(),
    });
    model::io::write_json(&out.join("bench.json"), &json)?;
    println!("\nplot -> {}, figures -> {}", png.display(), out.join("bench.json").display());
    Ok(())
}
