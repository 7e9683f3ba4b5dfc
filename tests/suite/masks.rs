//! Masks matched across views (issue 84): a geometry run trained without masks, the synthetic
//! scene's true masks corrupted as segmenters err (ids shuffled per view, splits, merges, missing
//! masks, fragments, moved edges), matched through the Gaussians' blend weights, scored by
//! consistent instance mIoU; the order of the views changes nothing.
#![allow(deprecated)]

use burn::tensor::Device;
use chatsplat_tests::temp_dir;
use model::data::nerfstudio::{LoadOptions, load};
use train::geometry::{GeometryConfig, GeometryTrainer, view_at};
use train::masks::ownership::ViewOwners;
use train::masks::{LabelMap, MatchOptions, corrupt, greedy, identity, match_masks, render_labels, score};

fn truth_of(v: &model::data::View) -> LabelMap {
    LabelMap::of_view(v).expect("synthetic masks")
}

#[test]
fn corrupted_masks_are_matched_into_one_id_per_object_whatever_the_view_order() {
    let dev = Device::ndarray();
    let mut report = Vec::new();
    for seed in [11u64, 12] {
        let dir = temp_dir(&format!("masks-{seed}"));
        let opts = model::data::synth::SynthOptions { seed, views: 12, width: 64, height: 56, ..Default::default() };
        model::data::synth::write_dataset(&dir, &opts, |_, _| {}).unwrap();
        let ds = load(&dir, &LoadOptions { holdout_every: 0, ..Default::default() }).unwrap();
        let truth: Vec<LabelMap> = ds.train.iter().map(truth_of).collect();
        // geometry without masks: the identity field learns nothing, the Gaussians are what count
        let mut bare = ds.clone();
        bare.train.iter_mut().for_each(|v| v.instance_ids = None);
        let cfg = GeometryConfig {
            iters: 300,
            init_per_view: 400,
            densify_from: 50,
            densify_every: 50,
            densify_until: 1000,
            opacity_reset_every: 0,
            checkpoint_every: 0,
            max_gaussians: 6000,
            ..Default::default()
        };
        let mut t = GeometryTrainer::new(&bare, cfg, &dev).unwrap();
        for _ in 0..300 {
            let v = &bare.train[view_at(t.iter, bare.train.len(), t.cfg.seed)];
            t.step(v).unwrap();
        }
        let weights: Vec<_> = ds.train.iter().map(|v| t.model.blend_weights(&v.camera).unwrap()).collect();
        // the true masks with their ids shuffled per view: every object found
        let none = corrupt::Errors { edge_px: 0, missing: 0.0, merged: 0.0, split: 0.0, fragments: 0 };
        let shuffled = corrupt::corrupt(&truth, &none, seed);
        let clean = score::consistency(&truth, &match_masks(&weights, &shuffled, &MatchOptions::default()).views);
        let noisy = corrupt::corrupt(&truth, &corrupt::Errors::default(), seed);
        let before = score::consistency(&truth, &noisy);
        let m = match_masks(&weights, &noisy, &MatchOptions::default());
        let after = score::consistency(&truth, &m.views);
        // Gaga's greedy recipe on the same masks and the same ownership
        let owners: Vec<ViewOwners> = weights.iter().zip(&noisy).map(|(w, n)| ViewOwners::of(w, n, 0.5)).collect();
        let g = greedy::greedy(&owners, weights[0].gaussians);
        let greedy_views: Vec<LabelMap> = weights.iter().map(|w| render_labels(w, &g)).collect();
        let baseline = score::consistency(&truth, &greedy_views);
        // the views in reverse: the same objects, the same masks
        let (rw, rn): (Vec<_>, Vec<_>) = weights.iter().cloned().zip(noisy.iter().cloned()).rev().unzip();
        let r = match_masks(&rw, &rn, &MatchOptions::default());
        let back: Vec<LabelMap> = r.views.into_iter().rev().collect();
        let reversed = score::consistency(&truth, &back);
        eprintln!(
            "seed {seed}: {} true objects; ids shuffled: matched {:.3} ({} objects); corrupted mIoU {:.3} ({} ids) \
             -> matched {:.3} ({} objects, confidence {:?}); views reversed {:.3}; greedy baseline {:.3} ({} objects)",
            after.true_objects,
            clean.miou,
            clean.predicted_objects,
            before.miou,
            before.predicted_objects,
            after.miou,
            after.predicted_objects,
            m.objects.iter().map(|o| (o.confidence * 100.0).round() / 100.0).collect::<Vec<_>>(),
            reversed.miou,
            baseline.miou,
            baseline.predicted_objects
        );
        // identity on the frozen geometry from the matched masks: each Gaussian's vote, then
        // cross-entropy on the identity alone
        let views_ids: Vec<(splat_kernels::Camera, Vec<u16>)> =
            ds.train.iter().zip(&m.views).map(|(v, l)| (v.camera, l.ids.clone())).collect();
        let labels = identity::vote_labels(&weights, &m.views);
        let agree = labels.iter().zip(&m.gaussian_labels).filter(|(a, b)| a == b).count() as f32 / labels.len() as f32;
        let voted = identity::from_labels(&t.model, &labels, 7);
        let rendered = |model: &model::splats::SplatModel| -> Vec<LabelMap> {
            ds.train
                .iter()
                .map(|v| {
                    let ids = model.render_ids(&v.camera).unwrap();
                    LabelMap { ids, ..truth_of(v) }
                })
                .collect()
        };
        let by_vote = score::consistency(&m.views, &rendered(&voted));
        // ids past a byte: the same objects numbered from 300 render the same pixels (a class per
        // id up to the largest; the ids between carry no Gaussian and never win)
        let past = |i: u16| if i == 0 { 0 } else { i + 300 };
        let wide = identity::from_labels(&t.model, &labels.iter().map(|&l| past(l)).collect::<Vec<_>>(), 7);
        let shifted: Vec<LabelMap> = rendered(&voted).iter().map(|m| m.map(past)).collect();
        let wide_views = rendered(&wide);
        assert!(wide_views.iter().flat_map(|m| m.labels()).all(|l| l > 300), "an id wrapped or was lost");
        assert_eq!(wide_views, shifted, "ids past 255 render other pixels than the same objects numbered from 1");
        let lrs = train::masks::identity_run::IdentityOptions::default().lrs;
        let refined = identity::refine(voted, &views_ids, 60, lrs, 7, |_, _| {}).unwrap();
        let by_ce = score::consistency(&m.views, &rendered(&refined.model));
        let (first, last) = refined.first_and_last();
        let geometry_kept = ["means", "log_scales", "quats", "opacity_logits", "sh_dc"].iter().all(|name| {
            let (a, b) = (t.model.tensors().into_named(), refined.model.tensors().into_named());
            let find = |x: &[(&str, burn::tensor::Tensor<2>)]| {
                model::splats::host(x.iter().find(|(n, _)| n == name).unwrap().1.clone())
            };
            find(&a) == find(&b)
        });
        eprintln!(
            "seed {seed}: identity from the matched masks: {:.3} of Gaussians voted as matched; rendered vs matched \
             masks: vote {:.3}, after 60 steps {:.3} (cross-entropy {:.3} -> {:.3})",
            agree, by_vote.miou, by_ce.miou, first, last
        );
        assert!(geometry_kept, "the identity step moved the geometry");
        assert!(agree > 0.9, "the vote on the matched masks disagrees with the matching: {agree}");
        assert!(by_vote.miou > 0.8 && by_ce.miou >= by_vote.miou - 0.02, "{by_vote:?} -> {by_ce:?}");
        assert!(last < first, "cross-entropy {first} -> {last}");
        report.push((clean, before, after, reversed, baseline, m.gaussian_labels == r.gaussian_labels));
    }
    // measured 2026-12-07 (64x56 views, 300 iterations): ids shuffled 0.912 / 0.964 with 5 of 5
    // and 2 of 2 objects; corrupted 0.063 / 0.091 -> 0.843 / 0.955 (5 of 5, 2 of 2 objects);
    // greedy 0.358 / 0.931
    for (clean, before, after, reversed, greedy, same) in report {
        assert_eq!(clean.predicted_objects, clean.true_objects, "{clean:?}");
        assert!(clean.miou > 0.85, "{clean:?}");
        assert!(same, "the view order changed a Gaussian's object");
        assert!((after.miou - reversed.miou).abs() < 0.01, "{after:?} vs {reversed:?}");
        assert_eq!(after.predicted_objects, after.true_objects, "objects lost or made: {after:?}");
        assert!(after.miou > 0.78 && after.miou > greedy.miou, "{before:?} -> {after:?}; greedy {greedy:?}");
    }
}
