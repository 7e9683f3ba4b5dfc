//! The built-in synthetic scenes and their questions (`chatsplat synth`): deterministic, varied
//! within the rules (1-6 objects, 6 shapes x 8 colours x 2 sizes, no overlap, unique (colour,
//! shape)), depth consistent with the geometry, poses consistent with transforms.json, the same
//! scene as the Gaussian version, and every reference answer true when recomputed from the
//! rendered mask alone.

#![allow(deprecated)]

use burn::tensor::{Device, Tensor};
use chatsplat_tests::temp_dir;
use glam::{Mat4, Quat, Vec3, Vec4};
use model::data::synth::forms::form_of;
use model::data::synth::questions::{
    Kind, ViewFacts, object_follow_ups, object_questions, scene_questions, view_questions,
};
use model::data::synth::raycast::{render_view, render_view_supersampled};
use model::data::synth::scene::{
    CUBE_HALF, CYLINDER_HALF_HEIGHT, CYLINDER_RADIUS, Color, Shape, Size, SynthScene, TORUS_MAJOR, TORUS_MINOR,
};
use model::data::synth::{self, FIRST_OBJECT_ID, SynthOptions};
use model::images::{read_gray16, read_png8};
use model::rng::Rng;
use model::vqa::{Level, load_questions};
use splat_kernels::api::{SplatOptions, splat};
use std::collections::{BTreeMap, BTreeSet};

/// Signed distance of a world point to the surface of object `o` (for the shapes with a simple
/// closed form; `None` for cones and pyramids).
fn surface_distance(o: &model::data::synth::scene::Object, p: Vec3) -> Option<f32> {
    let base = o.center - Vec3::new(0.0, o.shape.centre_height(o.scale), 0.0);
    let q = Quat::from_rotation_y(-o.yaw) * (p - base);
    let s = o.scale;
    Some(match o.shape {
        Shape::Sphere => (q - Vec3::Y * s).length() - s,
        Shape::Cube => {
            let h = CUBE_HALF * s;
            let d = (q - Vec3::Y * h).abs() - Vec3::splat(h);
            d.max(Vec3::ZERO).length() + d.max_element().min(0.0)
        }
        Shape::Cylinder => {
            let (r, hh) = (CYLINDER_RADIUS * s, CYLINDER_HALF_HEIGHT * s);
            let d = glam::Vec2::new(q.x.hypot(q.z) - r, (q.y - hh).abs() - hh);
            d.max(glam::Vec2::ZERO).length() + d.max_element().min(0.0)
        }
        Shape::Torus => (q.x.hypot(q.z) - TORUS_MAJOR * s).hypot(q.y - TORUS_MINOR * s) - TORUS_MINOR * s,
        Shape::Cone | Shape::Pyramid => return None,
    })
}

#[test]
fn scenes_vary_within_the_rules_and_are_deterministic() {
    let (mut counts, mut shapes, mut colors, mut sizes) =
        (BTreeSet::new(), BTreeSet::new(), BTreeSet::new(), BTreeSet::new());
    let (mut tables, mut backgrounds) = (BTreeSet::new(), BTreeSet::new());
    for seed in 0..400 {
        let s = SynthScene::from_seed(seed);
        assert_eq!(s, SynthScene::from_seed(seed), "seed {seed} is not deterministic");
        assert!((1..=6).contains(&s.objects.len()), "seed {seed}: {} objects", s.objects.len());
        counts.insert(s.objects.len());
        tables.insert((s.table.pattern, (s.table.color_a[0] * 100.0) as i32));
        backgrounds.insert(s.background.map(|c| (c * 100.0) as i32));
        let mut pairs = BTreeSet::new();
        for (k, o) in s.objects.iter().enumerate() {
            assert_eq!(o.id, FIRST_OBJECT_ID + k as u16);
            assert!(pairs.insert((o.color, o.shape)), "seed {seed}: two {}s", o.name());
            shapes.insert(o.shape);
            colors.insert(o.color);
            sizes.insert(o.size);
            let fp = o.shape.footprint(o.scale);
            assert!(o.center.x.hypot(o.center.z) + fp <= s.table.half, "seed {seed}: {} off the table", o.name());
            assert!((o.scale / o.size.scale() - 1.0).abs() <= 0.051);
            for p in &s.objects[k + 1..] {
                let d = (o.center.x - p.center.x).hypot(o.center.z - p.center.z);
                assert!(d >= fp + p.shape.footprint(p.scale), "seed {seed}: {} and {} overlap", o.name(), p.name());
            }
        }
    }
    assert_eq!(counts.len(), 6, "object counts {counts:?}");
    assert_eq!(shapes.len(), Shape::ALL.len());
    assert_eq!(colors.len(), Color::ALL.len());
    assert_eq!(sizes.len(), Size::ALL.len());
    assert!(tables.len() >= 6 && backgrounds.len() >= 3, "tables {tables:?}, backgrounds {backgrounds:?}");
}

/// The answer to a view question recomputed from the rendered ids and depth alone.
fn recompute(
    scene: &SynthScene,
    ids: &[u16],
    depth: &[f32],
    w: usize,
    qa: &model::data::synth::questions::Qa,
) -> String {
    let area = ids.len() as f32;
    let mut px: BTreeMap<u16, Vec<usize>> = BTreeMap::new();
    for (p, &i) in ids.iter().enumerate() {
        if i >= FIRST_OBJECT_ID {
            px.entry(i).or_default().push(p);
        }
    }
    let visible: Vec<&model::data::synth::scene::Object> = px
        .iter()
        .filter(|(_, v)| v.len() as f32 >= model::data::synth::questions::VISIBLE_FRACTION * area)
        .map(|(id, _)| scene.object(*id).unwrap())
        .collect();
    let words = |mut v: Vec<&'static str>, order: &dyn Fn(&str) -> usize| {
        v.sort_by_key(|w| order(w));
        v.dedup();
        if v.is_empty() { "none".to_string() } else { v.join(" ") }
    };
    let color_rank = |w: &str| Color::ALL.iter().position(|c| c.word() == w).unwrap();
    let shape_rank = |w: &str| Shape::ALL.iter().position(|s| s.word() == w).unwrap();
    let q = qa.question.trim_end_matches('?');
    let centroid_x = |o: &model::data::synth::scene::Object| {
        let v = &px[&o.id];
        v.iter().map(|p| (p % w) as f32 + 0.5).sum::<f32>() / v.len() as f32
    };
    let by_name = |name: &str| visible.iter().find(|o| o.name() == name).copied();
    match qa.kind {
        Kind::Count => visible.len().to_string(),
        Kind::Colors => words(visible.iter().map(|o| o.color.word()).collect(), &color_rank),
        Kind::Shapes => words(visible.iter().map(|o| o.shape.word()).collect(), &shape_rank),
        Kind::Objects => {
            let mut v: Vec<_> =
                visible.iter().map(|o| (color_rank(o.color.word()), shape_rank(o.shape.word()))).collect();
            v.sort();
            let names: Vec<String> =
                v.iter().map(|&(c, s)| format!("{} {}", Color::ALL[c].word(), Shape::ALL[s].word())).collect();
            if names.is_empty() { "none".into() } else { names.join(" ") }
        }
        Kind::ColorOf => {
            let shape = q.trim_start_matches("What color is the ");
            let with: Vec<_> = visible.iter().filter(|o| o.shape.word() == shape).collect();
            assert_eq!(with.len(), 1, "{q}: the {shape} must be unique in view");
            with[0].color.word().to_string()
        }
        Kind::ShapeOf => {
            let color = q.trim_start_matches("What shape is the ").trim_end_matches(" object");
            let with: Vec<_> = visible.iter().filter(|o| o.color.word() == color).collect();
            assert_eq!(with.len(), 1, "{q}: the {color} object must be unique in view");
            with[0].shape.word().to_string()
        }
        Kind::Exists => {
            let name = q.trim_start_matches("Is there a ");
            if by_name(name).is_some() { "yes" } else { "no" }.to_string()
        }
        Kind::LeftOf => {
            let rest = q.trim_start_matches("Is the ");
            let (a, b) = rest.split_once(" left of the ").unwrap();
            let (a, b) = (by_name(a).unwrap(), by_name(b).unwrap());
            if centroid_x(a) < centroid_x(b) { "yes" } else { "no" }.to_string()
        }
        Kind::Nearest => {
            // the object whose own pixels come closest to the camera
            let near =
                |o: &model::data::synth::scene::Object| px[&o.id].iter().map(|&p| depth[p]).fold(f32::MAX, f32::min);
            visible.iter().min_by(|a, b| near(a).total_cmp(&near(b))).unwrap().name()
        }
        other => panic!("{other:?} is not a view question"),
    }
}

/// Supersampling blends edge pixels only, and each blended pixel is the box filter of a view
/// rendered `s` times finer (whose pixel centres are the sub-rays): the plain twin as oracle.
#[test]
fn supersampled_views_blend_edge_pixels_as_a_finer_render_averaged() {
    let (s, side) = (3usize, 64u32);
    let mut rng = Rng::new(5);
    let mut blended = 0;
    for seed in [3u64, 11, 29] {
        let scene = SynthScene::from_seed(seed);
        let cam = synth::random_camera(&mut rng, 50.0, side, side);
        let plain = render_view(&cam, &scene);
        assert!(render_view_supersampled(&cam, &scene, 1).rgb == plain.rgb, "s = 1 is the plain render");
        let ss = render_view_supersampled(&cam, &scene, s);
        assert!(ss.ids == plain.ids && ss.depth == plain.depth, "ids and depths are the centre ray's");
        let mut fine = cam;
        (fine.fx, fine.fy, fine.cx, fine.cy) =
            (cam.fx * s as f32, cam.fy * s as f32, cam.cx * s as f32, cam.cy * s as f32);
        (fine.width, fine.height) = (side * s as u32, side * s as u32);
        let f = render_view(&fine, &scene);
        let (w, fw) = (side as usize, side as usize * s);
        for y in 0..w {
            for x in 0..w {
                let o = y * w + x;
                let id = plain.ids[o];
                let edge =
                    [(x > 0, o.wrapping_sub(1)), (x + 1 < w, o + 1), (y > 0, o.wrapping_sub(w)), (y + 1 < w, o + w)]
                        .iter()
                        .any(|&(inside, n)| inside && plain.ids[n] != id);
                for k in 0..3 {
                    let want = if edge {
                        let mut sum = 0.0;
                        for j in 0..s {
                            for i in 0..s {
                                sum += f.rgb[((y * s + j) * fw + x * s + i) * 3 + k];
                            }
                        }
                        sum / (s * s) as f32
                    } else {
                        plain.rgb[o * 3 + k]
                    };
                    assert!(
                        (ss.rgb[o * 3 + k] - want).abs() < 2e-3,
                        "seed {seed} pixel ({x}, {y}) channel {k}: {} vs {want} (plain {}, edge {edge})",
                        ss.rgb[o * 3 + k],
                        plain.rgb[o * 3 + k]
                    );
                }
                blended += (edge && (0..3).any(|k| (ss.rgb[o * 3 + k] - plain.rgb[o * 3 + k]).abs() > 0.02)) as usize;
            }
        }
    }
    assert!(blended > 50, "only {blended} edge pixels changed colour");
}

#[test]
fn view_answers_are_true_by_construction() {
    let mut per_kind: BTreeMap<&str, usize> = BTreeMap::new();
    let mut rng = Rng::new(1);
    let mut ambiguous = 0;
    for seed in 100..160 {
        let scene = SynthScene::from_seed(seed);
        for _ in 0..3 {
            let cam = synth::random_camera(&mut rng, 50.0, 96, 96);
            let v = render_view(&cam, &scene);
            let facts = ViewFacts::of(&scene, &v.ids, &v.depth, 96, 96);
            let qas = view_questions(&scene, &facts, &mut rng);
            if facts.ambiguous {
                assert!(qas.is_empty(), "no question about a view with a sliver of an object");
                ambiguous += 1;
                continue;
            }
            for qa in &qas {
                assert_eq!(qa.kind.level(), Level::View);
                // every question takes a form the page and `chat` offer (synth::forms)
                assert!(form_of(Level::View, &qa.question).is_some(), "no form for {}", qa.question);
                let want = recompute(&scene, &v.ids, &v.depth, 96, qa);
                assert_eq!(qa.answer, want, "seed {seed}: {}", qa.question);
                *per_kind.entry(qa.kind.as_str()).or_default() += 1;
            }
            let count = qas.iter().find(|q| q.kind == Kind::Count).unwrap();
            let distinct: BTreeSet<u16> = v.ids.iter().copied().filter(|&i| i >= FIRST_OBJECT_ID).collect();
            assert_eq!(count.answer, distinct.len().to_string(), "seed {seed}: the count is the objects in the mask");
        }
    }
    eprintln!("checked {per_kind:?}; {ambiguous} ambiguous views skipped");
    for k in ["count", "colors", "shapes", "color_of", "shape_of", "exists", "left_of", "nearest"] {
        assert!(per_kind.get(k).copied().unwrap_or(0) >= 10, "too few {k} questions: {per_kind:?}");
    }
    let yes_no: Vec<usize> = ["exists"].iter().map(|k| per_kind[k]).collect();
    assert!(yes_no[0] > 40);
}

#[test]
fn object_and_scene_answers_describe_the_scene() {
    let scene = SynthScene::from_seed(3);
    for o in &scene.objects {
        let qs = object_questions(o);
        let get = |k: Kind| qs.iter().find(|q| q.kind == k).unwrap().answer.clone();
        assert_eq!(get(Kind::Name), format!("{} {}", o.color.word(), o.shape.word()));
        assert_eq!(
            (get(Kind::Color), get(Kind::Shape), get(Kind::Size)),
            (o.color.word().into(), o.shape.word().into(), o.size.word().into())
        );
    }
    let qs = scene_questions(&scene);
    for (level, qa) in scene.objects.iter().flat_map(|o| object_questions(o).into_iter().map(|q| (Level::Object, q))) {
        assert!(form_of(level, &qa.question).is_some(), "no form for {}", qa.question);
    }
    for qa in &qs {
        assert!(form_of(Level::Scene, &qa.question).is_some(), "no form for {}", qa.question);
    }
    let total = qs.iter().find(|q| q.kind == Kind::Total).unwrap();
    assert_eq!(total.answer, scene.objects.len().to_string());
    let by_color: usize =
        qs.iter().filter(|q| q.kind == Kind::CountColor).map(|q| q.answer.parse::<usize>().unwrap()).sum();
    let by_shape: usize =
        qs.iter().filter(|q| q.kind == Kind::CountShape).map(|q| q.answer.parse::<usize>().unwrap()).sum();
    assert_eq!((by_color, by_shape), (scene.objects.len(), scene.objects.len()));
    let list = &qs.iter().find(|q| q.kind == Kind::List).unwrap().answer;
    assert_eq!(list.split(' ').count(), 2 * scene.objects.len());
}

#[test]
fn dataset_is_deterministic_complete_and_geometrically_consistent() {
    let opts = SynthOptions { seed: 11, views: 16, width: 64, height: 56, ..Default::default() };
    let (a, b) = (temp_dir("a"), temp_dir("b"));
    let mut calls = 0;
    synth::write_dataset(&a, &opts, |_, _| calls += 1).unwrap();
    synth::write_dataset(&b, &opts, |_, _| {}).unwrap();
    assert_eq!(calls, 16, "progress reported once per view");
    for rel in [
        "transforms.json",
        "scene.json",
        "questions.json",
        "images/frame_0003.png",
        "masks/frame_0003.png",
        "depth/frame_0003.png",
    ] {
        assert_eq!(
            std::fs::read(a.join(rel)).unwrap(),
            std::fs::read(b.join(rel)).unwrap(),
            "{rel} differs between runs"
        );
    }
    let tf: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("transforms.json")).unwrap()).unwrap();
    let scene: SynthScene = serde_json::from_slice(&std::fs::read(a.join("scene.json")).unwrap()).unwrap();
    assert_eq!(scene, SynthScene::from_seed(11));
    let (fx, fy, cx, cy) = (
        tf["fl_x"].as_f64().unwrap() as f32,
        tf["fl_y"].as_f64().unwrap() as f32,
        tf["cx"].as_f64().unwrap() as f32,
        tf["cy"].as_f64().unwrap() as f32,
    );
    let (w, h) = (64usize, 56usize);
    let mut seen = [0usize; 8];
    let mut checked = 0;
    for f in tf["frames"].as_array().unwrap() {
        let m: Vec<Vec<f32>> = f["transform_matrix"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect())
            .collect();
        // OpenGL camera-to-world -> OpenCV world-to-camera.
        let c2w_gl = Mat4::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| m[r][c])));
        let c2w = c2w_gl * Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0));
        let w2c = c2w.inverse();
        // The cameras look at LOOK_AT: it projects to the principal point.
        let p = w2c.transform_point3(synth::LOOK_AT);
        assert!(p.z > 0.0 && (fx * p.x / p.z).abs() < 0.5 && (fy * p.y / p.z).abs() < 0.5);
        let (_, _, ch, ids) = read_png8(&a.join(f["instance_mask_path"].as_str().unwrap())).unwrap();
        assert_eq!(ch, 1);
        let (_, _, depth) = read_gray16(&a.join(f["depth_file_path"].as_str().unwrap())).unwrap();
        let eye = c2w.transform_point3(Vec3::ZERO);
        for o in 0..w * h {
            seen[ids[o] as usize] += 1;
            assert_eq!(ids[o] == 0, depth[o] == 0, "depth present exactly where a surface is");
            let Some(obj) = scene.object(ids[o] as u16) else { continue };
            // Back-project and check the point lies on the object's surface.
            let (x, y) = ((o % w) as f32 + 0.5, (o / w) as f32 + 0.5);
            let z = depth[o] as f32 * synth::DEPTH_SCALE;
            let pw = c2w.transform_point3(Vec3::new((x - cx) / fx * z, (y - cy) / fy * z, z));
            if let Some(d) = surface_distance(obj, pw) {
                // 1 mm depth quantisation along a ray at up to ~70 degrees incidence.
                assert!(d.abs() < 6e-3 * (pw - eye).length().max(1.0), "{} pixel off the surface by {d}", obj.name());
                checked += 1;
            }
        }
    }
    assert!(checked > 50, "too few object pixels checked ({checked})");
    assert!(seen[0] > 0 && seen[1] > 0, "background and table visible");
    for o in &scene.objects {
        assert!(seen[o.id as usize] >= 10, "{} covers only {} pixels over all views", o.name(), seen[o.id as usize]);
    }
    // questions.json: view and object questions on held-out frames, clicks on the object
    let qf = load_questions(&a.join("questions.json")).unwrap();
    let frames = qf.views.clone().unwrap();
    assert_eq!(frames.len(), 16);
    let mut levels = BTreeSet::new();
    let mut follow_kinds = BTreeSet::new();
    for q in &qf.questions {
        levels.insert(q.level);
        // follow-ups included: every question takes a form the page and `chat` offer
        if q.level != Level::Find {
            assert!(form_of(q.level, &q.question).is_some(), "{}: no form for {}", q.id, q.question);
        }
        match q.level {
            Level::View | Level::Object => {
                assert!(synth::held_out(q.view.unwrap()), "{} is not on a held-out view", q.id)
            }
            Level::Scene => {
                let vs = q.views.as_ref().unwrap();
                assert!(vs.iter().all(|&v| !synth::held_out(v)), "scene views are training views");
            }
            Level::Find => {
                // the objects named are exactly those whose name holds every word of the phrase
                let named: Vec<u16> = scene
                    .objects
                    .iter()
                    .filter(|o| q.question.split(' ').all(|w| o.name().split(' ').any(|n| n == w)))
                    .map(|o| o.id)
                    .collect();
                assert_eq!(q.objects.as_ref(), Some(&named), "{}: {}", q.id, q.question);
                let absent = q.kind.as_deref().unwrap().starts_with("find_absent_");
                assert_eq!(absent, named.is_empty(), "{}", q.id);
            }
        }
        if q.level == Level::Object {
            let [x, y] = q.object.unwrap();
            let (_, _, _, ids) = read_png8(&a.join(frames[q.view.unwrap()].replace("images/", "masks/"))).unwrap();
            let id = ids[y as usize * w + x as usize];
            let o = scene.object(id as u16).expect("the click lands on an object");
            let qas = object_questions(o);
            let mut asked: Vec<(String, String)> =
                qas.iter().map(|qa| (qa.question.clone(), qa.answer.clone())).collect();
            if q.follows.is_some() {
                asked = object_follow_ups(&qas).into_iter().map(|f| (f.question, f.answer)).collect();
            }
            assert!(asked.contains(&(q.question.clone(), q.answer.clone())), "{}: {}", q.id, q.question);
        }
        // a follow-up goes on an earlier question's conversation and answers as its twin does
        if let Some(first) = &q.follows {
            let first = qf.questions.iter().find(|p| p.id == *first).expect("it follows a question of the file");
            let twin = qf.questions.iter().find(|p| Some(&p.id) == q.spelled.as_ref()).expect("a twin");
            assert_eq!((first.view, first.object), (q.view, q.object), "{}", q.id);
            assert_eq!(twin.answer, q.answer, "{}", q.id);
            let it = |t: &str| t.split([' ', '?']).any(|w| w == "it");
            assert!(it(&q.question) && !it(&twin.question), "{} / {}", q.question, twin.question);
            follow_kinds.insert(q.kind.clone().unwrap());
        }
    }
    assert_eq!(levels.len(), 4, "view, object, scene and find questions: {levels:?}");
    for kind in ["follow_color", "follow_shape", "follow_size"] {
        assert!(follow_kinds.contains(kind), "no {kind} follow-up: {follow_kinds:?}");
    }
    let finds: Vec<&str> = qf.questions.iter().filter(|q| q.level == Level::Find).map(|q| q.id.as_str()).collect();
    for sort in ["color", "shape", "name"] {
        assert!(finds.iter().any(|id| id.ends_with(&format!("-find_{sort}"))), "no present {sort}: {finds:?}");
        assert!(finds.iter().any(|id| id.ends_with(&format!("-find_absent_{sort}"))), "no absent {sort}: {finds:?}");
    }
    std::fs::remove_dir_all(&a).ok();
    std::fs::remove_dir_all(&b).ok();
}

#[test]
fn second_turns_use_only_the_conversation_vocabulary_and_follow_their_first_question() {
    use model::data::synth::questions::{conversation_vocabulary, vocabulary};
    let (words, single) = (conversation_vocabulary(), vocabulary());
    assert_eq!((&words[..single.len()], &words[single.len()..]), (&single[..], &["it".to_string()][..]));
    let known = |text: &str| text.split([' ', '?']).filter(|w| !w.is_empty()).all(|w| words.iter().any(|v| v == w));
    let mut follow_ups = 0;
    for seed in 0..20 {
        let scene = SynthScene::from_seed(seed);
        for o in &scene.objects {
            let qas = object_questions(o);
            for f in object_follow_ups(&qas) {
                let qa = f.qa(&qas);
                let first = qa.follows.as_deref().expect("asked after its first question");
                assert_eq!((qa.kind, first), (qas[f.twin].kind, &qas[f.first]), "{}", qa.question);
                assert_eq!(qa.answer, qas[f.twin].answer, "it answers as its twin");
                assert!(known(&qa.question) && known(&first.question) && known(&first.answer), "{}", qa.question);
                assert!(!qa.question.split([' ', '?']).all(|w| single.iter().any(|v| v == w) || w.is_empty()));
                follow_ups += 1;
            }
        }
    }
    assert!(follow_ups >= 60, "{follow_ups} follow-ups");
}

#[test]
fn gaussian_tabletop_covers_the_same_pixels_as_the_analytic_scene() {
    let o = SynthOptions { seed: 7, views: 4, width: 80, height: 80, ..Default::default() };
    let (cloud, scene) = model::data::synth::gaussians::tabletop(o.seed, 60);
    let device = Device::ndarray();
    let g = cloud.to_gaussians(&device);
    let mut agree = 0usize;
    let mut total = 0usize;
    for i in 0..o.views {
        let cam = synth::view_camera(i, &o);
        let v = render_view(&cam, &scene);
        let out = splat(&g, &cam, Tensor::zeros([3], &device), &SplatOptions::default()).unwrap();
        let alpha = out.alpha.into_data().to_vec::<f32>().unwrap();
        for (a, id) in alpha.iter().zip(&v.ids) {
            agree += ((*a > 0.5) == (*id != 0)) as usize;
            total += 1;
        }
    }
    let frac = agree as f32 / total as f32;
    assert!(frac > 0.93, "coverage agrees on only {:.1}% of pixels", 100.0 * frac);
}

#[test]
fn clicks_land_deep_inside_the_object() {
    // an 11x7 ring of id 5 (4 pixels wide on the left) around a hole of id 0; a 2-pixel bar of id 6
    let (w, h) = (11usize, 7usize);
    let mut ids = vec![0u16; w * h];
    for y in 1..6 {
        for x in 1..10 {
            let ring = !(5..=7).contains(&x) || !(2..=4).contains(&y);
            ids[y * w + x] = if ring { 5 } else { 0 };
        }
    }
    ids[0] = 6;
    ids[1] = 6;
    let [x, y] = synth::click_pixel(&ids, w, 5).expect("id 5 has pixels");
    assert_eq!(ids[y * w + x], 5, "the click is on the object");
    // every neighbour is on the object too: the click is not on an edge pixel (the old rule, the
    // median pixel in reading order, picked (4, 3), next to the hole)
    assert!(interior(&ids, w, x, y), "the click ({x}, {y}) is on the ring's edge");
    // a mask with no interior pixel: its first pixel; an absent id: none
    assert_eq!(synth::click_pixel(&ids, w, 6), Some([0, 0]));
    assert_eq!(synth::click_pixel(&ids, w, 7), None);
    // a rendered view: each click is on its object, and inside it whenever the mask has an interior
    let s = 48usize;
    let opts = SynthOptions { views: 2, width: s as u32, height: s as u32, ..Default::default() };
    let scene = SynthScene::from_seed(opts.seed);
    let v = render_view(&synth::view_camera(0, &opts), &scene);
    for o in &scene.objects {
        let Some([x, y]) = synth::click_pixel(&v.ids, s, o.id) else { continue };
        assert_eq!(v.ids[y * s + x], o.id, "object {} clicked at ({x}, {y}) off its mask", o.id);
        let has_interior = (0..s * s).any(|p| v.ids[p] == o.id && interior(&v.ids, s, p % s, p / s));
        assert!(!has_interior || interior(&v.ids, s, x, y), "object {} clicked on its edge ({x}, {y})", o.id);
    }
}

/// Whether the pixel and its four neighbours (all inside the image) carry the same id.
fn interior(ids: &[u16], w: usize, x: usize, y: usize) -> bool {
    let h = ids.len() / w;
    let id = ids[y * w + x];
    x > 0
        && y > 0
        && x + 1 < w
        && y + 1 < h
        && [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)].iter().all(|&(nx, ny)| ids[ny * w + nx] == id)
}
