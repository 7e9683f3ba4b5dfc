//! LLFF: hand-encoded `poses_bounds.npy` files, axes, intrinsics, downscale and errors.

use super::*;
use model::data::llff;

/// A `.npy` file of `rows` with the given dtype (`<f8` / `<f4`), shape text and format version.
fn npy(rows: &[Vec<f64>], descr: &str, shape: &str, version: u8) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    let pre = if version == 1 { 10 } else { 12 };
    while (pre + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY".to_vec();
    b.extend([version, 0]);
    if version == 1 {
        b.extend((header.len() as u16).to_le_bytes());
    } else {
        b.extend((header.len() as u32).to_le_bytes());
    }
    b.extend(header.as_bytes());
    for v in rows.iter().flatten() {
        if descr == "<f4" {
            b.extend((*v as f32).to_le_bytes());
        } else {
            b.extend(v.to_le_bytes());
        }
    }
    b
}

/// An LLFF row: 3x5 `[R | t | (h, w, f)]` with `R` given by its columns (down, right, back).
fn llff_row(cols: [[f64; 3]; 3], t: [f64; 3], hwf: [f64; 3], near: f64, far: f64) -> Vec<f64> {
    let mut r = vec![];
    for i in 0..3 {
        r.extend([cols[0][i], cols[1][i], cols[2][i], t[i], hwf[i]]);
    }
    r.extend([near, far]);
    r
}

/// Three views: an identity LLFF rotation at the origin, the same rotation at (1, 2, 3), and a
/// camera turned 90 degrees about world x. `(h, w, f) = (12, 16, 20)` while the images are 8x6,
/// so the loaded focal length is 20 * 8 / 16 = 10.
fn llff_rows() -> Vec<Vec<f64>> {
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    // down = x, right = -z, back = y
    let turned = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
    let hwf = [12.0, 16.0, 20.0];
    vec![
        llff_row(id, [0.0; 3], hwf, 1.0, 10.0),
        llff_row(id, [1.0, 2.0, 3.0], hwf, 1.0, 10.0),
        llff_row(turned, [0.0; 3], hwf, 0.5, 5.0),
    ]
}

pub(crate) fn llff_dir(tag: &str) -> Scratch {
    let dir = temp_dir(tag);
    for (i, n) in ["a.png", "b.jpg.png", "c.png"].iter().enumerate() {
        write_rgb(&dir.join("images").join(n), W, H, &gradient(i as f32 / 4.0, W, H)).unwrap();
    }
    std::fs::write(dir.join("images/notes.txt"), "not an image").unwrap();
    std::fs::write(dir.join("poses_bounds.npy"), npy(&llff_rows(), "<f8", "(3, 17)", 1)).unwrap();
    dir
}

#[test]
fn llff_axes_intrinsics_and_split() {
    let dir = llff_dir("llff-axes");
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    assert_eq!(names(&ds.train), ["a.png", "b.jpg.png", "c.png"]);
    let c0 = ds.train[0].camera;
    assert_eq!([c0.fx, c0.fy, c0.cx, c0.cy], [10.0, 10.0, 4.0, 3.0]);
    // Identity LLFF pose: columns [down, right, back] = world x, y, z, so the camera looks
    // down world -z with image-right = +y and image-down = +x.
    let [right, down, fwd, centre] = axes(&c0);
    assert!(close3(fwd, [0.0, 0.0, -1.0], 1e-6), "forward {fwd}");
    assert!(close3(right, [0.0, 1.0, 0.0], 1e-6), "right {right}");
    assert!(close3(down, [1.0, 0.0, 0.0], 1e-6), "down {down}");
    assert!(close3(centre, [0.0; 3], 1e-6));
    // A point straight ahead projects to the principal point; one displaced along +x (down)
    // lands below it: v = f * 0.5 / 5 + cy = 4.
    assert_eq!(project(&c0, [0.0, 0.0, -5.0]), (4.0, 3.0));
    let (u, v) = project(&c0, [0.5, 0.0, -5.0]);
    assert!((u - 4.0).abs() < 1e-5 && (v - 4.0).abs() < 1e-5, "({u}, {v})");
    let (u, v) = project(&c0, [0.0, 0.5, -5.0]);
    assert!((u - 5.0).abs() < 1e-5 && (v - 3.0).abs() < 1e-5, "({u}, {v})");
    // The translation column is the camera centre.
    let [_, _, fwd1, centre1] = axes(&ds.train[1].camera);
    assert!(close3(centre1, [1.0, 2.0, 3.0], 1e-5) && close3(fwd1, [0.0, 0.0, -1.0], 1e-6));
    // back = +y, so forward = -y; right = -z.
    let [right2, _, fwd2, _] = axes(&ds.train[2].camera);
    assert!(close3(fwd2, [0.0, -1.0, 0.0], 1e-6) && close3(right2, [0.0, 0.0, -1.0], 1e-6));
    // Colours.
    for (i, v) in ds.train.iter().enumerate() {
        assert!((v.rgb[2] - q8(i as f32 / 4.0)).abs() < 1e-6 && v.instance_ids.is_none());
    }
    // Holdout: every 3rd view.
    let s = llff::load(&dir, &opts(1, 3)).unwrap();
    assert_eq!((s.train.len(), s.test.len()), (2, 1));
    assert_eq!(names(&s.test), ["c.png"]);
    // '<f4' data and format version 2 load the same cameras.
    std::fs::write(dir.join("poses_bounds.npy"), npy(&llff_rows(), "<f4", "(3, 17)", 2)).unwrap();
    let f4 = llff::load(&dir, &opts(1, 0)).unwrap();
    for (a, b) in f4.train.iter().zip(&ds.train) {
        assert_eq!(a.camera, b.camera);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn llff_downscale_prefers_images_k_and_reads_masks() {
    let dir = llff_dir("llff-down");
    // No images_2: box-filter images/.
    let full = llff::load(&dir, &opts(1, 0)).unwrap();
    let half = llff::load(&dir, &opts(2, 0)).unwrap();
    let (f, h) = (&full.train[0], &half.train[0]);
    assert_eq!((h.camera.width, h.camera.height, h.camera.fx, h.camera.cx, h.camera.cy), (4, 3, 5.0, 2.0, 1.5));
    let want = (f.rgb[0] + f.rgb[3] + f.rgb[24] + f.rgb[27]) / 4.0;
    assert!((h.rgb[0] - want).abs() < 1e-6);
    // images_2 with the right count is used as is: its own colours, f scaled by 4 / 16.
    for (i, n) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        write_rgb(&dir.join("images_2").join(n), 4, 3, &[0.2 * i as f32 + 0.1; 36]).unwrap();
    }
    let pre = llff::load(&dir, &opts(2, 0)).unwrap();
    let c = pre.train[1].camera;
    assert_eq!((c.width, c.height, c.fx, c.cx, c.cy), (4, 3, 5.0, 2.0, 1.5));
    assert!(pre.train[1].image_path.starts_with(dir.join("images_2")));
    assert!((pre.train[1].rgb[0] - q8(0.3)).abs() < 1e-6);
    // With masks (defined on images/), images/ is box-filtered and the masks subsampled.
    let ids: Vec<u8> = (0..48).map(|i| (i % 5) as u8).collect();
    write_gray8(&dir.join("masks/b.jpg.png"), W, H, &ids).unwrap();
    // a mask folder that covers some images only is refused, naming the first missing mask
    expect_err(llff::load(&dir, &opts(2, 0)), &["a.png", "is missing", "has masks for 1 of the 3 images"]);
    for n in ["a.png", "c.png"] {
        write_gray8(&dir.join("masks").join(n), W, H, &[0; 48]).unwrap();
    }
    let m = llff::load(&dir, &opts(2, 0)).unwrap();
    assert!(m.train[1].image_path.starts_with(dir.join("images")));
    let got = m.train[1].instance_ids.as_ref().unwrap();
    assert_eq!(got, &(0..12).map(|i| ids[(i / 4) * 16 + (i % 4) * 2] as u16).collect::<Vec<_>>());
    assert_eq!(m.train[0].instance_ids.as_deref(), Some(&[0u16; 12][..]));
    // images_2 with the wrong count is ignored.
    std::fs::remove_dir_all(dir.join("masks")).unwrap();
    std::fs::remove_file(dir.join("images_2/c.png")).unwrap();
    let ignored = llff::load(&dir, &opts(2, 0)).unwrap();
    assert!(ignored.train[0].image_path.starts_with(dir.join("images")));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn llff_malformed_inputs_give_errors_naming_the_file() {
    let dir = llff_dir("llff-bad");
    let file = dir.join("poses_bounds.npy");
    let load = || llff::load(&dir, &opts(1, 0));
    let rows = llff_rows();
    let good = npy(&rows, "<f8", "(3, 17)", 1);
    let mut bad = good.clone();
    bad[1] = b'X';
    std::fs::write(&file, &bad).unwrap();
    expect_err(load(), &["poses_bounds.npy: not a NumPy .npy file (bad magic)"]);
    std::fs::write(&file, &good[..7]).unwrap();
    expect_err(load(), &["poses_bounds.npy: not a NumPy .npy file"]);
    std::fs::write(&file, &good[..40]).unwrap();
    expect_err(load(), &["poses_bounds.npy: truncated .npy header"]);
    std::fs::write(&file, &good[..good.len() - 8]).unwrap();
    expect_err(load(), &["poses_bounds.npy: holds 400 data bytes but shape (3, 17) of <f8 needs 408"]);
    let short: Vec<Vec<f64>> = rows.iter().map(|r| r[..15].to_vec()).collect();
    std::fs::write(&file, npy(&short, "<f8", "(3, 15)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: shape (3, 15) is not (N, 17)"]);
    std::fs::write(&file, npy(&rows, ">f8", "(3, 17)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: dtype '>f8' is not supported"]);
    let mut nf = rows.clone();
    nf[1][15] = 20.0;
    std::fs::write(&file, npy(&nf, "<f8", "(3, 17)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: row 1: near = 20 and far = 10 must satisfy 0 < near < far"]);
    // Two rows, three images.
    std::fs::write(&file, npy(&rows[..2], "<f8", "(2, 17)", 1)).unwrap();
    expect_err(load(), &["images: holds 3 images but", "poses_bounds.npy has 2 poses"]);
    // An image that is not a rescaled (h, w).
    std::fs::write(&file, &good).unwrap();
    write_rgb(&dir.join("images/c.png"), W, W, &gradient(0.0, W, W)).unwrap();
    expect_err(load(), &["c.png: image is 8x8, which is not a rescaled 16x12"]);
    // Corrupt JPEG.
    std::fs::remove_file(dir.join("images/c.png")).unwrap();
    std::fs::write(dir.join("images/c.jpg"), b"\xff\xd8\xff\xe0 not really").unwrap();
    expect_err(load(), &["c.jpg: cannot decode JPEG"]);
    std::fs::remove_file(&file).unwrap();
    expect_err(load(), &["poses_bounds.npy: cannot read"]);
    std::fs::remove_dir_all(&dir).ok();
}
