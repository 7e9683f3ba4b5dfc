//! Inria-layout .ply: bit-exact round trip, foreign layouts, clear errors on malformed files.

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use model::{GaussianCloud, ply};

fn sample() -> GaussianCloud {
    let (mut cloud, _) = model::data::synth::gaussians::tabletop(3, 8);
    cloud.rest_per_gaussian = 9;
    cloud.sh_rest = (0..cloud.len() * 9).map(|k| (k as f32).sin() * 1e-3).collect();
    let n = cloud.len();
    cloud.extra.insert("identity".into(), (16, (0..n * 16).map(|k| k as f32 * 0.25 - 7.0).collect()));
    cloud
}

#[test]
fn round_trip_is_bit_exact() {
    let cloud = sample();
    let path = chatsplat_tests::temp_dir("rt.ply");
    ply::write(&path, &cloud).unwrap();
    let back = ply::read(&path).unwrap();
    assert_eq!(back, cloud);
    // Denormals, negative zero and extreme values survive too.
    let mut odd = cloud.clone();
    odd.means[0] = [f32::MIN_POSITIVE / 8.0, -0.0, f32::MAX];
    ply::write(&path, &odd).unwrap();
    let back = ply::read(&path).unwrap();
    assert_eq!(back.means[0].map(f32::to_bits), odd.means[0].map(f32::to_bits));
    std::fs::remove_file(&path).ok();
}

/// The Inria properties every Gaussian needs, as a header block.
const GAUSSIAN_PROPS: &str = "property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n\
    property float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\n\
    property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n";

#[test]
fn ascii_and_big_endian_files_load_and_point_clouds_are_refused() {
    let ascii = format!(
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 2\nproperty float x\n\
        property float y\nproperty float z\n{GAUSSIAN_PROPS}property uchar red\nend_header\n\
        1 2 3 0.1 0.2 0.3 2 -3 -3 -3 0 1 0 0 255\n4 5 6 0 0 0 -1 -2 -2 -2 1 0 0 0 0\n"
    );
    let c = ply::parse(ascii.as_bytes(), "hand.ply").unwrap();
    assert_eq!(c.means, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    assert_eq!(c.quats[0], [0.0, 1.0, 0.0, 0.0]);
    assert_eq!(c.opacity_logits, vec![2.0, -1.0]);
    assert_eq!(c.extra["red"], (1, vec![255.0, 0.0]));
    let mut be = format!(
        "ply\nformat binary_big_endian 1.0\nelement vertex 1\nproperty double x\nproperty float y\n\
        property float z\n{GAUSSIAN_PROPS}end_header\n"
    )
    .into_bytes();
    be.extend_from_slice(&2.5f64.to_be_bytes());
    for v in [-1.0f32, 7.0, 0.0, 0.0, 0.0, 1.0, -2.0, -2.0, -2.0, 1.0, 0.0, 0.0, 0.0] {
        be.extend_from_slice(&v.to_be_bytes());
    }
    assert_eq!(ply::parse(&be, "be.ply").unwrap().means, vec![[2.5, -1.0, 7.0]]);
    // a point cloud (positions and colours only) is not rendered with made-up Gaussians
    let cloud = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
        property float z\nproperty uchar red\nend_header\n1 2 3 255\n";
    let e = ply::parse(cloud, "cloud.ply").unwrap_err().to_string();
    assert!(
        e.starts_with("cloud.ply: ") && e.contains("lacks the `f_dc_0` property") && e.contains("point cloud"),
        "{e}"
    );
    // one Gaussian property missing (opacity) is refused by name
    let no_opacity = ascii.replace("property float opacity\n", "");
    let e = ply::parse(no_opacity.as_bytes(), "hand.ply").unwrap_err().to_string();
    assert!(e.contains("lacks the `opacity` property"), "{e}");
}

#[test]
fn malformed_files_give_errors_naming_the_file_and_the_problem() {
    let cases: [(&[u8], &str); 5] = [
        (b"hello", "not a PLY file"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
            property float z\nend_header\n\x00\x00",
            "lacks the `f_dc_0` property",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
            end_header\n",
            "lacks the `z` property",
        ),
        (b"ply\nformat weird 1.0\nelement vertex 1\nend_header\n", "unsupported PLY format"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
            end_header\n1 2 3\n4 5\n",
            "lacks the `f_dc_0` property",
        ),
    ];
    for (bytes, want) in cases {
        let e = ply::parse(bytes, "scene.ply").unwrap_err().to_string();
        let msg = e.to_string();
        assert!(msg.starts_with("scene.ply: ") && msg.contains(want), "{msg}");
    }
}

/// One object's Gaussians taken out of a model, and the model without them: each Gaussian's
/// identity class (the classifier on its own identity feature) picks it, and `retain` keeps every
/// attribute row of the kept Gaussians, extra channels and higher SH bands included.
#[test]
fn an_objects_gaussians_are_taken_out_by_their_identity_class() {
    let mut cloud = sample();
    let n = cloud.len();
    // identity one-hot in channel i % 3; the classifier reads class k from channel k (k = 0: background)
    let identity: Vec<f32> = (0..n).flat_map(|i| (0..16).map(move |c| if c == i % 3 { 1.0 } else { 0.0 })).collect();
    cloud.extra.insert("identity".into(), (16, identity));
    cloud.extra.insert("lang".into(), (2, (0..n).flat_map(|i| [i as f32, -(i as f32)]).collect()));
    let mut classifier = vec![0.0f32; 16 * 3 + 3];
    for k in 0..3 {
        classifier[k * 3 + k] = 10.0;
    }
    let device = burn::tensor::Device::ndarray();
    let model = model::splats::SplatModel::from_cloud(&cloud, Some(&classifier), 3, &device);
    let classes = model.gaussian_classes();
    assert_eq!(classes, (0..n).map(|i| (i % 3) as u16).collect::<Vec<_>>());
    for keep_object in [true, false] {
        let keep: Vec<bool> = classes.iter().map(|&c| (c == 1) == keep_object).collect();
        let picked: Vec<usize> = (0..n).filter(|&i| keep[i]).collect();
        let mut part = cloud.clone();
        part.retain(&keep);
        assert_eq!(part.len(), picked.len());
        assert_eq!(part.means, picked.iter().map(|&i| cloud.means[i]).collect::<Vec<_>>());
        assert_eq!(part.opacity_logits, picked.iter().map(|&i| cloud.opacity_logits[i]).collect::<Vec<_>>());
        let rest: Vec<f32> = picked.iter().flat_map(|&i| cloud.sh_rest[i * 9..(i + 1) * 9].to_vec()).collect();
        assert_eq!(part.sh_rest, rest);
        let lang: Vec<f32> = picked.iter().flat_map(|&i| [i as f32, -(i as f32)]).collect();
        assert_eq!(part.extra["lang"].1, lang);
        let of_part = model::splats::SplatModel::from_cloud(&part, Some(&classifier), 3, &device).gaussian_classes();
        assert!(of_part.iter().all(|&c| (c == 1) == keep_object), "{of_part:?}");
    }
}
