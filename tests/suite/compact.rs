//! Model only what a scene needs (issue 38, section 2): `train-language` compacts its run by
//! default (`train::compact`): the fewest Gaussians, by language contribution, whose training
//! views' token L1 stays within a tolerance, written to `compact.json`; inference renders language
//! maps from those alone and RGB from every Gaussian; training on makes the compaction stale.
#![allow(deprecated)]

use super::language_hard_cases::{Case, cfg};
use burn::tensor::Device;
use chatsplat_tests::host;
use model::scene::LanguageScene;
use train::compact::FRACTIONS;

#[test]
fn a_compacted_run_keeps_its_top_contributors_for_language_and_every_gaussian_for_rgb() {
    let case = Case::new("compact", |_| {});
    let (geometry, language) = (case.geometry(), case.language());
    let dev = Device::ndarray();

    // a tolerance no fraction can miss: every candidate is scored and the smallest kept
    let s = case.train(train::language::LanguageTrainConfig { compact_tolerance: 100.0, ..cfg(20) }).unwrap();
    let c = s.compaction.expect("compacted");
    let n = c.gaussians;
    let smallest = FRACTIONS[FRACTIONS.len() - 1];
    assert_eq!(c.kept.len(), (n as f64 * smallest).ceil() as usize);
    assert_eq!(c.candidates.len(), FRACTIONS.len(), "every fraction scored");
    assert!(c.kept.windows(2).all(|w| w[0] < w[1]));
    let contribution = language.read_contribution().unwrap();
    let least_kept = c.kept.iter().map(|&i| contribution[i]).fold(f32::INFINITY, f32::min);
    let dropped = (0..n).filter(|i| c.kept.binary_search(i).is_err());
    assert!(dropped.map(|i| contribution[i]).all(|x| x <= least_kept), "the kept rows are the top contributors");
    assert_eq!(language.read_compaction(n).unwrap().as_ref(), Some(&c), "compact.json holds what was chosen");
    assert!((c.token_l1_full.0 - s.after.0).abs() < 1e-6, "the whole field's L1 is the run's final one");

    // inference: language maps from the kept rows, RGB from every Gaussian
    let full = LanguageScene::load(&geometry, &language, &dev).unwrap();
    let open = LanguageScene::open(&geometry, &language, &dev).unwrap();
    assert_eq!((full.splats.len(), open.splats.len(), open.field.len()), (n, c.kept.len(), c.kept.len()));
    let cam = geometry.read_cameras().unwrap().all()[0];
    assert_eq!(open.render(&cam).unwrap().rgb, full.render(&cam).unwrap().rgb, "RGB keeps every Gaussian");
    let sub = full.subset(&c.kept);
    let (a, b) = (host(open.view_tokens(&open.field, &cam).unwrap()), host(sub.view_tokens(&sub.field, &cam).unwrap()));
    assert_eq!(a, b, "the opened run's tokens are those of its kept rows");
    let all = host(full.view_tokens(&full.field, &cam).unwrap());
    assert_ne!(a, all, "a tenth of the Gaussians renders other maps");

    // a compaction made for another geometry is refused, naming the file
    let text = std::fs::read_to_string(language.compaction()).unwrap();
    std::fs::write(language.compaction(), text.replacen(&format!("\"gaussians\": {n}"), "\"gaussians\": 7", 1))
        .unwrap();
    let err = LanguageScene::open(&geometry, &language, &dev).err().expect("refused").to_string();
    assert!(err.contains("compact.json") && err.contains("7 Gaussians"), "{err}");

    // training on makes it stale: gone before the first step, rewritten only if asked for
    let resumed = case.train_on(train::language::LanguageTrainConfig { compact_tolerance: 0.0, ..cfg(25) }, true);
    assert!(resumed.unwrap().compaction.is_none(), "no compaction asked for");
    assert!(!language.compaction().exists(), "a stale compaction stays");
}
