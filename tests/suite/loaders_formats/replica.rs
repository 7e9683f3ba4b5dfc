//! Replica: poses, depth and 16- and 8-bit instance labels.

use super::*;
use model::data::replica;

/// Camera-to-world of frame `i`: a rotation by `0.3 i` about world y, centre `(i, -0.5, 2)`.
fn replica_c2w(i: usize) -> [[f64; 4]; 4] {
    let (s, c) = (0.3 * i as f64).sin_cos();
    [[c, 0.0, s, i as f64], [0.0, 1.0, 0.0, -0.5], [-s, 0.0, c, 2.0], [0.0, 0.0, 0.0, 1.0]]
}

/// 16-bit instance labels of frame `i`: 0 in the top row, then ids that first appear in the order
/// 1000, 42, 7 over the sequence.
fn replica_labels(i: usize) -> Vec<u16> {
    let pal: [&[u16]; 4] = [&[1000, 42], &[42, 1000], &[7, 1000], &[42]];
    (0..W * H).map(|p| if p < W { 0 } else { pal[i][(p as usize) % pal[i].len()] }).collect()
}

pub(crate) fn replica_dir(tag: &str, frames: usize) -> Scratch {
    let dir = temp_dir(tag);
    let mut traj = String::new();
    for i in 0..frames {
        let m = replica_c2w(i);
        let vals: Vec<String> = m.iter().flatten().map(|v| format!("{v:.17e}")).collect();
        traj += &vals.join(" ");
        traj += "\n";
        write_rgb(&dir.join(format!("rgb/rgb_{i}.png")), W, H, &gradient(i as f32 / 8.0, W, H)).unwrap();
        let mm: Vec<u16> = (0..W * H).map(|p| 1000 + 250 * i as u16 + p as u16).collect();
        write_gray16(&dir.join(format!("depth/depth_{i}.png")), W, H, &mm).unwrap();
        write_gray16(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, &replica_labels(i))
            .unwrap();
    }
    std::fs::write(dir.join("traj_w_c.txt"), traj).unwrap();
    dir
}

#[test]
fn replica_intrinsics_poses_depth_and_labels() {
    let dir = replica_dir("replica", 4);
    let ds = replica::load(&dir, &opts(1, 0)).unwrap();
    assert_eq!(ds.train.len(), 4);
    for (i, v) in ds.train.iter().enumerate() {
        let c = v.camera;
        // 90 degree hfov: fx = fy = (W/2) / tan(45 deg) = 4; the centre (W/2, H/2) in this
        // project's pixel convention is Semantic-NeRF's ((W-1)/2, (H-1)/2).
        assert!((c.fx - 4.0).abs() < 1e-5 && (c.fy - 4.0).abs() < 1e-5, "f = {} {}", c.fx, c.fy);
        assert_eq!((c.cx, c.cy, c.width, c.height), (4.0, 3.0, W, H));
        // traj_w_c is camera-to-world, OpenCV: its columns are the camera axes and centre.
        let m = replica_c2w(i);
        let [right, down, fwd, centre] = axes(&c);
        let col = |k: usize| [m[0][k] as f32, m[1][k] as f32, m[2][k] as f32];
        for (got, k) in [(right, 0), (down, 1), (fwd, 2), (centre, 3)] {
            assert!(close3(got, col(k), 1e-5), "frame {i} column {k}: {got} vs {:?}", col(k));
        }
        // A camera-space point (0.5, -0.25, 2) projects to (4 + 4 * 0.25, 3 - 4 * 0.125).
        let pc = [0.5, -0.25, 2.0, 1.0];
        let pw: [f64; 3] = std::array::from_fn(|r| (0..4).map(|k| m[r][k] * pc[k]).sum());
        let (u, w) = project(&c, pw);
        assert!((u - 5.0).abs() < 1e-4 && (w - 2.5).abs() < 1e-4, "({u}, {w})");
        // Depth in metres.
        let d = v.depth.as_ref().unwrap();
        assert_eq!(d.len(), 48);
        for p in [0usize, 17, 47] {
            let want = (1000 + 250 * i + p) as f32 / 1000.0;
            assert!((d[p] - want).abs() < 1e-6, "frame {i} pixel {p}: {} vs {want}", d[p]);
        }
        assert!((v.rgb[2] - q8(i as f32 / 8.0)).abs() < 1e-6);
    }
    // 16-bit ids compacted over the sequence in order of first appearance: 1000 -> 1, 42 -> 2,
    // 7 -> 3; 0 stays 0.
    for (i, v) in ds.train.iter().enumerate() {
        let want: Vec<u16> = replica_labels(i)
            .iter()
            .map(|&l| match l {
                0 => 0,
                1000 => 1,
                42 => 2,
                7 => 3,
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(v.instance_ids.as_ref().unwrap(), &want, "frame {i}");
    }
    // Holdout and downscale: intrinsics halved, depth and ids subsampled (top-left of 2x2).
    let s = replica::load(&dir, &opts(2, 2)).unwrap();
    assert_eq!((s.train.len(), s.test.len()), (2, 2));
    assert_eq!(names(&s.test), ["rgb_1.png", "rgb_3.png"]);
    let c = s.train[0].camera;
    assert!((c.fx - 2.0).abs() < 1e-5);
    assert_eq!((c.cx, c.cy, c.width, c.height), (2.0, 1.5, 4, 3));
    let d = s.train[0].depth.as_ref().unwrap();
    assert_eq!(d.len(), 12);
    assert!((d[5] - (1000 + 2 * 8 + 2) as f32 / 1000.0).abs() < 1e-6);
    assert_eq!(s.train[0].instance_ids.as_ref().unwrap()[5], ds.train[0].instance_ids.as_ref().unwrap()[18]);
    // intrinsics.json overrides the default.
    std::fs::write(dir.join("intrinsics.json"), r#"{"fx": 5.5, "fy": 6.0, "cx": 3.25, "cy": 2.75}"#).unwrap();
    let c = replica::load(&dir, &opts(1, 0)).unwrap().train[2].camera;
    assert_eq!([c.fx, c.fy, c.cx, c.cy], [5.5, 6.0, 3.25, 2.75]);
    std::fs::write(dir.join("intrinsics.json"), r#"{"fx": 5.5, "fy": 6.0, "cx": 3.25}"#).unwrap();
    expect_err(replica::load(&dir, &opts(1, 0)), &["intrinsics.json: `cy` is missing"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn replica_8bit_labels_and_errors() {
    let dir = replica_dir("replica-bad", 3);
    let load = || replica::load(&dir, &opts(1, 0));
    // 8-bit labels are used verbatim.
    let ids8: Vec<u8> = (0..48).map(|p| (p * 5) as u8).collect();
    for i in 0..3 {
        write_gray8(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, &ids8).unwrap();
    }
    assert_eq!(load().unwrap().train[1].instance_ids.as_ref().unwrap(), &chatsplat_tests::wide(&ids8));
    // Mixed bit depths.
    write_gray16(&dir.join("semantic_instance/semantic_instance_2.png"), W, H, &replica_labels(0)).unwrap();
    expect_err(load(), &["semantic_instance_2.png: 16-bit labels in a sequence whose earlier labels are 8-bit"]);
    // 16-bit labels: distinct ids accumulate over the sequence.
    let many: Vec<u16> = (0..48).map(|p| 1 + p as u16).collect();
    let more: Vec<u16> = (0..48).map(|p| 100 + 5 * p as u16).collect();
    let lots: Vec<u16> = (0..48).map(|p| 400 + 7 * p as u16).collect();
    for (i, l) in [many, more, lots].iter().enumerate() {
        write_gray16(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, l).unwrap();
    }
    // 144 distinct ids over the sequence fit in 8 bits.
    assert!(load().is_ok());
    let big: Vec<u16> = (0..W * 40).map(|p| 1000 + p as u16).collect();
    write_gray16(&dir.join("semantic_instance/semantic_instance_1.png"), W, 40, &big).unwrap();
    expect_err(load(), &["semantic_instance_1.png: is 8x40 but its image is 8x6"]);
    // 272 distinct non-zero 16-bit ids: dense ids 1..=272 past a byte; more than the identity
    // classifier takes do not fit.
    let d = temp_dir("replica-many");
    std::fs::create_dir_all(d.join("rgb")).unwrap();
    std::fs::write(d.join("traj_w_c.txt"), "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n").unwrap();
    write_rgb(&d.join("rgb/rgb_0.png"), 16, 17, &gradient(0.0, 16, 17)).unwrap();
    let ids: Vec<u16> = (0..16 * 17).map(|p| 60000 - 7 * p as u16).collect();
    write_gray16(&d.join("semantic_instance/semantic_instance_0.png"), 16, 17, &ids).unwrap();
    let dense = replica::load(&d, &opts(1, 0)).unwrap().train[0].instance_ids.clone().unwrap();
    assert_eq!(dense, (1..=16 * 17).collect::<Vec<u16>>());
    write_rgb(&d.join("rgb/rgb_0.png"), 65, 64, &gradient(0.0, 65, 64)).unwrap();
    let ids: Vec<u16> = (0..65 * 64).map(|p| 1 + p as u16).collect();
    write_gray16(&d.join("semantic_instance/semantic_instance_0.png"), 65, 64, &ids).unwrap();
    expect_err(
        replica::load(&d, &opts(1, 0)),
        &["semantic_instance_0.png: more than 4095 distinct non-zero instance ids"],
    );
    std::fs::remove_dir_all(&d).ok();
    // Missing files and a bad trajectory.
    std::fs::remove_dir_all(dir.join("semantic_instance")).unwrap();
    std::fs::remove_file(dir.join("depth/depth_2.png")).unwrap();
    expect_err(load(), &["depth_2.png: depth of frame 2 is missing"]);
    std::fs::remove_dir_all(dir.join("depth")).unwrap();
    assert!(load().unwrap().train[0].depth.is_none());
    std::fs::remove_file(dir.join("rgb/rgb_1.png")).unwrap();
    expect_err(load(), &["rgb_1.png: image of frame 1 is missing", "lists 3 frames"]);
    let traj = dir.join("traj_w_c.txt");
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0 0 1 0 0 0 0 1 0 0 0 0\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 2: 15 numbers, expected 16"]);
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 x 1\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 1: cannot parse `x` as a number"]);
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 2\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 1: not an invertible camera-to-world matrix"]);
    std::fs::remove_file(&traj).unwrap();
    expect_err(load(), &["traj_w_c.txt: cannot read"]);
    std::fs::remove_dir_all(&dir).ok();
}
