#![allow(deprecated)] // the teacher test runs on burn-ndarray (deprecated in burn 0.22)
//! `load_any` on every format, masks from other tools, mask PNG layouts and the teacher stage.

use super::colmap::{colmap_dir, write_distorted_colmap};
use super::llff::llff_dir;
use super::replica::replica_dir;
use super::*;
use model::data::{colmap, llff};

#[test]
fn load_any_detects_each_format() {
    let o = opts(1, 0);
    let (c, _) = colmap_dir("any-colmap", true);
    assert_eq!(load_any(&c, &o).unwrap().train.len(), 5);
    let l = llff_dir("any-llff");
    // LLFF scenes usually also carry a (distorted) COLMAP model: poses_bounds.npy wins.
    write_distorted_colmap(&l.join("sparse/0"));
    let ds = load_any(&l, &o).unwrap();
    assert_eq!(ds.train.len(), 3);
    assert_eq!(ds.train[0].camera.fx, 10.0);
    let r = replica_dir("any-replica", 2);
    assert_eq!(load_any(&r, &o).unwrap().train[1].depth.as_ref().unwrap().len(), 48);
    let n = temp_dir("any-nerfstudio");
    let so = model::data::synth::SynthOptions { views: 3, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&n, &so, |_, _| {}).unwrap();
    assert_eq!(load_any(&n, &o).unwrap().train.len(), 3);
    let empty = temp_dir("any-empty");
    std::fs::create_dir_all(&empty).unwrap();
    expect_err(
        load_any(&empty, &o),
        &[
            "no known scene format",
            "transforms.json",
            "transforms_train.json",
            "poses_bounds.npy",
            "sparse/",
            "traj_w_c.txt",
        ],
    );
    expect_err(load_any(&empty.join("nope"), &o), &["nope: not a directory"]);
}

/// The teacher stage reads every format through the same detection as `train` (not only
/// nerfstudio): tokens of every training view of a COLMAP and an LLFF capture, and the teacher
/// directory reloads its dataset.
#[test]
fn teacher_tokens_are_extracted_from_colmap_and_llff_captures() {
    let dev = burn::tensor::Device::ndarray();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov");
    let vlm = model::vlm::LlavaOnevision::load(&fixture, &dev).unwrap();
    for (tag, dir) in [("colmap", colmap_dir("teacher-colmap", true).0), ("llff", llff_dir("teacher-llff"))] {
        let out = temp_dir(&format!("teacher-{tag}-out"));
        let teacher = model::run::TeacherDir::new(&out);
        let sum = train::teacher::extract(&vlm, &dir, &teacher, &Default::default(), |_| {}, |_, _| {}).unwrap();
        let set = train::teacher::TeacherSet::open(&out).unwrap();
        let ds = set.dataset().unwrap();
        assert!(!ds.train.is_empty(), "{tag}");
        assert_eq!(sum.written, ds.train.len(), "{tag}: one token file per training view");
        assert_eq!(set.views.len(), ds.train.len(), "{tag}");
        let (g, d) = (set.index.grid, set.index.dim);
        for v in 0..ds.train.len() {
            let t = set.tokens(v, None).unwrap();
            assert_eq!(t.len(), g * g * d, "{tag} view {v}");
            assert!(t.iter().any(|x| *x != 0.0), "{tag} view {v}: tokens of a real image");
        }
        assert_eq!(set.index.fingerprint, ds.fingerprint(), "{tag}: the index records the dataset");
        std::fs::remove_dir_all(&out).ok();
    }
}

/// Gaussian Grouping's layout: instance-id PNGs in `object_mask/` beside `images/` (what SAM +
/// DEVA write) are the capture's masks when there is no `masks/`, for COLMAP and LLFF alike.
#[test]
fn gaussian_grouping_object_masks_are_read() {
    let (dir, _) = colmap_dir("colmap-grouping", true);
    let (with_masks, _) = colmap::load(&dir, &opts(1, 0)).unwrap();
    std::fs::rename(dir.join("masks"), dir.join("object_mask")).unwrap();
    let (grouping, _) = colmap::load(&dir, &opts(1, 0)).unwrap();
    assert!(grouping.train[0].instance_ids.is_some(), "object_mask/img_a.png is read");
    for (a, b) in with_masks.train.iter().zip(&grouping.train) {
        assert_eq!(a.instance_ids, b.instance_ids);
    }
    let dir = llff_dir("llff-grouping");
    let ids = |k: u32| -> Vec<u8> { (0..W * H).map(|i| ((i + k) % 3) as u8).collect() };
    for (k, n) in ["a.png", "b.jpg.png", "c.png"].iter().enumerate() {
        write_gray8(&dir.join("object_mask").join(n), W, H, &ids(k as u32)).unwrap();
    }
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    let b = ds.train.iter().find(|v| v.image_path.ends_with("b.jpg.png")).unwrap();
    assert_eq!(b.instance_ids, Some(chatsplat_tests::wide(&ids(1))));
    assert!(ds.train.iter().all(|v| v.instance_ids.is_some()));
    // an empty object_mask/ (SAM + DEVA not run yet) loads without masks, with a warning
    std::fs::remove_dir_all(dir.join("object_mask")).unwrap();
    std::fs::create_dir_all(dir.join("object_mask")).unwrap();
    let before = model::error::warnings();
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    assert!(ds.train.iter().all(|v| v.instance_ids.is_none()));
    assert!(model::error::warnings() > before, "an empty mask folder is warned about");
}

#[test]
fn masks_from_another_tool_replace_any_formats_own() {
    // Replica (own 16-bit labels) and LLFF (no masks): `--masks DIR` gives both the same ids.
    for (tag, dir, images) in [
        ("masks-replica", replica_dir("masks-replica-data", 2), vec!["rgb_0", "rgb_1"]),
        ("masks-llff", llff_dir("masks-llff-data"), vec!["a", "b.jpg", "c"]),
    ] {
        let masks = temp_dir(tag);
        let ids = |i: usize| -> Vec<u8> { (0..W * H).map(|p| ((p as usize + i) % 7) as u8).collect() };
        for (i, stem) in images.iter().enumerate() {
            write_gray8(&masks.join(format!("{stem}.png")), W, H, &ids(i)).unwrap();
        }
        let with = |k: u32| LoadOptions { masks: Some(masks.to_path_buf()), ..opts(k, 0) };
        let ds = load_any(&dir, &with(1)).unwrap();
        assert_eq!(ds.train.len(), images.len(), "{tag}");
        for (i, v) in ds.train.iter().enumerate() {
            assert_eq!(v.instance_ids.as_ref().unwrap(), &chatsplat_tests::wide(&ids(i)), "{tag} view {i}");
        }
        // downscaled by nearest sample, like the format's own masks
        let half = load_any(&dir, &with(2)).unwrap();
        let got = half.train[1].instance_ids.as_ref().unwrap();
        assert_eq!(got, &(0..12).map(|j| ids(1)[(j / 4) * 16 + (j % 4) * 2] as u16).collect::<Vec<_>>(), "{tag}");
        // a mask of the wrong size, a missing mask, a folder that is not there: errors naming the file
        write_gray8(&masks.join(format!("{}.png", images[1])), W - 2, H, &vec![0; ((W - 2) * H) as usize]).unwrap();
        expect_err(load_any(&dir, &with(1)), &[&format!("{}.png", images[1]), "is 6x6 but its image"]);
        std::fs::remove_file(masks.join(format!("{}.png", images[0]))).unwrap();
        expect_err(load_any(&dir, &with(1)), &[&format!("{}.png", images[0]), "is missing: every image needs a mask"]);
        let gone = LoadOptions { masks: Some(masks.join("nope")), ..opts(1, 0) };
        expect_err(load_any(&dir, &gone), &["nope", "is not a directory"]);
        std::fs::remove_dir_all(&dir).ok();
        std::fs::remove_dir_all(&masks).ok();
    }
}

/// Writes a PNG of raw samples (`bits` per sample, big-endian 16-bit) with an optional palette.
fn raw_png(path: &Path, w: u32, h: u32, color: png::ColorType, bits: png::BitDepth, data: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut enc = png::Encoder::new(std::fs::File::create(path).unwrap(), w, h);
    enc.set_color(color);
    enc.set_depth(bits);
    if color == png::ColorType::Indexed {
        enc.set_palette((0..=255u8).flat_map(|i| [i, 255 - i, i / 2]).collect::<Vec<u8>>());
    }
    enc.write_header().unwrap().write_image_data(data).unwrap();
}

/// Instance masks are read by value whatever the PNG layout tools write (8- or 16-bit gray, a
/// palette's indices, a gray mask saved as RGB), and what cannot be read right is refused, naming
/// the file and a pixel: ids above 4095 (no silent cut or wrap) and colour-coded masks (no
/// silent read of the red channel).
#[test]
fn instance_masks_of_every_png_layout_are_read_by_value_or_refused() {
    use png::{BitDepth, ColorType};
    let (dir, _) = colmap_dir("mask-layouts", true);
    let mask = dir.join("masks/img_a.png");
    let ids: Vec<u8> = (0..W * H).map(|i| (i * 37 % 256) as u8).collect();
    let load_a = || colmap::load(&dir, &opts(1, 0)).map(|(ds, _)| ds.train[0].instance_ids.clone().unwrap());
    // 16-bit gray with ids below 256: the same ids (the high byte alone would make them all 0)
    let wide: Vec<u8> = ids.iter().flat_map(|&v| (v as u16).to_be_bytes()).collect();
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Sixteen, &wide);
    let ids16 = chatsplat_tests::wide(&ids);
    assert_eq!(load_a().unwrap(), ids16);
    // a palette PNG (DEVA): the index is the id, whatever colour the palette gives it
    raw_png(&mask, W, H, ColorType::Indexed, BitDepth::Eight, &ids);
    assert_eq!(load_a().unwrap(), ids16);
    // 4-bit palette, packed two pixels a byte
    let small: Vec<u8> = ids.iter().map(|v| v % 16).collect();
    let packed: Vec<u8> = small.chunks(2).map(|p| (p[0] << 4) | p[1]).collect();
    raw_png(&mask, W, H, ColorType::Indexed, BitDepth::Four, &packed);
    assert_eq!(load_a().unwrap(), chatsplat_tests::wide(&small));
    // a gray mask saved as RGB: read; a colour-coded one: refused
    let rgb: Vec<u8> = ids.iter().flat_map(|&v| [v, v, v]).collect();
    raw_png(&mask, W, H, ColorType::Rgb, BitDepth::Eight, &rgb);
    assert_eq!(load_a().unwrap(), ids16);
    let mut coloured = rgb.clone();
    coloured[3 * 9 + 1] ^= 0x40;
    raw_png(&mask, W, H, ColorType::Rgb, BitDepth::Eight, &coloured);
    expect_err(load_a(), &["img_a.png", "colour-coded mask", "pixel (1, 1)"]);
    // 16-bit ids past 255 are read as they are (no wrap to a byte); past the largest id the
    // identity classifier takes, refused naming the pixel
    let mut big = wide.clone();
    big[2 * 10..2 * 10 + 2].copy_from_slice(&300u16.to_be_bytes());
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Sixteen, &big);
    let mut want = ids16.clone();
    want[10] = 300;
    assert_eq!(load_a().unwrap(), want);
    big[2 * 10..2 * 10 + 2].copy_from_slice(&5000u16.to_be_bytes());
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Sixteen, &big);
    expect_err(load_a(), &["img_a.png", "instance id 5000 at pixel (2, 1)", "above 4095"]);
    // some masks missing: refused, naming the first missing mask
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Eight, &ids);
    std::fs::remove_file(dir.join("masks/img_c.png")).unwrap();
    expect_err(load_a(), &["img_c.png", "is missing", "has masks for 4 of the 5 images"]);
}

/// A synthetic capture (4 views of 16x12) whose transforms.json is edited by `edit` (given the
/// capture's folder too), loaded with every second view held out.
fn edited_capture(tag: &str, edit: impl Fn(&mut serde_json::Value)) -> model::Result<model::data::Dataset> {
    edited_capture_in(tag, 2, |_, tf| edit(tf))
}

fn edited_capture_in(
    tag: &str,
    holdout_every: usize,
    edit: impl Fn(&Path, &mut serde_json::Value),
) -> model::Result<model::data::Dataset> {
    let dir = temp_dir(tag);
    let o = model::data::synth::SynthOptions { seed: 4, views: 4, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&dir, &o, |_, _| {}).unwrap();
    let path = dir.join("transforms.json");
    let mut tf: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    edit(&dir, &mut tf);
    std::fs::write(&path, tf.to_string()).unwrap();
    load_any(&dir, &LoadOptions { holdout_every, ..Default::default() })
}

/// An edit giving every frame frame 0's `key`.
fn like_frame0(key: &'static str) -> Box<dyn Fn(&mut serde_json::Value)> {
    Box::new(move |tf| {
        let v = tf["frames"][0][key].clone();
        for f in tf["frames"].as_array_mut().unwrap() {
            f[key] = v.clone();
        }
    })
}

/// Captures no reconstruction can come from are refused with the image and the problem; the
/// unedited capture loads.
#[test]
fn degenerate_captures_are_refused() {
    assert_eq!(edited_capture("capture-ok", |_| {}).unwrap().train.len(), 2);
    let frame0 = |tf: &serde_json::Value| tf["frames"][0].clone();
    let cases: Vec<(&str, Box<dyn Fn(&mut serde_json::Value)>, &[&str])> = vec![
        ("focal-mm", Box::new(|tf| tf["fl_x"] = 0.035.into()), &["focal length fx = 0.035", "field of view"]),
        ("focal-huge", Box::new(|tf| tf["fl_y"] = 1e9.into()), &["focal length fy", "field of view"]),
        ("principal-far", Box::new(|tf| tf["cx"] = 400.into()), &["principal point (400", "far outside"]),
        ("same-pose", like_frame0("transform_matrix"), &["all 4 views have the same camera pose"]),
        ("same-file", like_frame0("file_path"), &["is both a training view and a held-out view"]),
        (
            "listed-twice",
            Box::new(move |tf| {
                let f = frame0(tf);
                tf["frames"].as_array_mut().unwrap().insert(1, f);
            }),
            &["is both a training view and a held-out view"],
        ),
        ("depth-scale", Box::new(|tf| tf["depth_unit_scale_factor"] = (-0.001).into()), &["depth_unit_scale_factor"]),
    ];
    for (tag, edit, want) in cases {
        let e = expect_err(edited_capture(tag, edit), want);
        assert!(e.contains(".png") || e.contains("transforms.json"), "{tag}: names no file: {e}");
    }
}

/// nerfstudio's own `mask_path` is a 0/255 validity mask: read as instance ids (one object) only
/// with a warning that says so.
#[test]
fn binary_nerfstudio_masks_are_warned_about() {
    let before = model::error::warnings();
    let ds = edited_capture_in("binary-masks", 0, |dir, tf| {
        for f in tf["frames"].as_array_mut().unwrap() {
            let m = f.as_object_mut().unwrap().remove("instance_mask_path").unwrap();
            let valid: Vec<u8> = (0..16 * 12).map(|i| if i % 16 < 8 { 255 } else { 0 }).collect();
            write_gray8(&dir.join(m.as_str().unwrap()), 16, 12, &valid).unwrap();
            f["mask_path"] = m;
        }
    })
    .unwrap();
    assert!(ds.train.iter().all(|v| v.instance_ids.as_ref().unwrap().contains(&255)));
    assert!(model::error::warnings() > before, "a 0/255 mask_path is warned about");
}
