//! Which matched objects are surfaces: the ground or table others stand on ("stuff", not
//! "things"). A segmenter masks a table like any object, but a synthetic scene's `scene.json`
//! keeps its table out of every search, and a user searching a capture for "red" does not mean the
//! floor. A capture without labels learns it from its Gaussians: a surface is flat (its centres'
//! least spread is a small part of its second) and at least one other object, smaller than it is
//! wide, lies over its extent.

use glam::DVec3;

/// An object is flat when the spread of its centres across its plane is at most this share of
/// the spread along its second axis.
pub const FLAT: f64 = 0.15;

/// The centre, axes (unit, by spread, largest first) and spreads (standard deviations) of points.
#[derive(Clone, Copy, Debug)]
struct Frame {
    centre: DVec3,
    axes: [DVec3; 3],
    spread: [f64; 3],
}

impl Frame {
    fn of(points: &[DVec3]) -> Option<Self> {
        if points.len() < 4 {
            return None;
        }
        let n = points.len() as f64;
        let centre = points.iter().copied().sum::<DVec3>() / n;
        let mut c = [[0f64; 3]; 3];
        for p in points {
            let d = (*p - centre).to_array();
            for i in 0..3 {
                for j in 0..3 {
                    c[i][j] += d[i] * d[j] / n;
                }
            }
        }
        let (values, vectors) = symmetric_eigen(c);
        let mut order = [0, 1, 2];
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        let axes = order.map(|k| DVec3::new(vectors[0][k], vectors[1][k], vectors[2][k]).normalize());
        Some(Self { centre, axes, spread: order.map(|k| values[k].max(0.0).sqrt()) })
    }

    fn flat(&self) -> bool {
        self.spread[2] <= FLAT * self.spread[1]
    }

    /// Whether `other` lies over this plane's extent (its centre within two spreads along both
    /// in-plane axes) and is smaller than the plane is wide.
    fn carries(&self, other: &Frame) -> bool {
        let d = other.centre - self.centre;
        (0..2).all(|k| d.dot(self.axes[k]).abs() <= 2.0 * self.spread[k]) && other.spread[0] < self.spread[1]
    }
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3x3 matrix, by Jacobi rotations.
fn symmetric_eigen(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        if off < 1e-30 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// The surfaces among the objects `matched` found, from the centres of `model`'s Gaussians.
pub fn of_matched(model: &model::splats::SplatModel, matched: &super::Matched) -> Vec<u16> {
    let means = model::splats::host(model.means.val());
    let centres: Vec<[f32; 3]> = means.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let ids: Vec<u16> = matched.objects.iter().map(|o| o.id).collect();
    surfaces(&centres, &matched.gaussian_labels, &ids)
}

/// The ids among `objects` that are surfaces, given each Gaussian's centre and object label
/// (0 = none), ascending.
pub fn surfaces(centres: &[[f32; 3]], labels: &[u16], objects: &[u16]) -> Vec<u16> {
    // each object's centres, gathered in one pass over the Gaussians
    let mut points: std::collections::BTreeMap<u16, Vec<DVec3>> = objects.iter().map(|&id| (id, Vec::new())).collect();
    for (c, l) in centres.iter().zip(labels) {
        if let Some(p) = points.get_mut(l) {
            p.push(DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64));
        }
    }
    let frames: Vec<(u16, Frame)> = points.iter().filter_map(|(&id, p)| Some((id, Frame::of(p)?))).collect();
    frames
        .iter()
        .filter(|(id, f)| f.flat() && frames.iter().any(|(other, g)| other != id && f.carries(g)))
        .map(|&(id, _)| id)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid of points over `[x0, x1] x [y0, y1] x [z0, z1]`, `n` per side.
    fn block(lo: [f32; 3], hi: [f32; 3], n: usize) -> Vec<[f32; 3]> {
        let at = |k: usize, i: usize| lo[k] + (hi[k] - lo[k]) * i as f32 / (n - 1) as f32;
        (0..n * n * n).map(|i| [at(0, i % n), at(1, i / n % n), at(2, i / (n * n))]).collect()
    }

    fn scene(parts: &[(u16, Vec<[f32; 3]>)]) -> (Vec<[f32; 3]>, Vec<u16>) {
        let centres = parts.iter().flat_map(|(_, p)| p.clone()).collect();
        let labels = parts.iter().flat_map(|(id, p)| vec![*id; p.len()]).collect();
        (centres, labels)
    }

    #[test]
    fn a_table_under_objects_is_a_surface_and_they_are_not() {
        // a tilted table (its plane not along any axis) with a cube and a thin card on it
        let tilt = glam::Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.3, 0.2);
        let turn = |p: Vec<[f32; 3]>| p.into_iter().map(|c| tilt.mul_vec3(c.into()).to_array()).collect::<Vec<_>>();
        let (centres, labels) = scene(&[
            (3, turn(block([-1.0, -1.0, -0.02], [1.0, 1.0, 0.0], 9))),
            (1, turn(block([0.2, 0.2, 0.0], [0.5, 0.5, 0.3], 5))),
            (2, turn(block([-0.6, -0.5, 0.0], [-0.3, -0.2, 0.01], 5))),
        ]);
        assert_eq!(surfaces(&centres, &labels, &[1, 2, 3]), vec![3]);
        // the table alone carries nothing: an object like any other
        let (centres, labels) = scene(&[(3, block([-1.0, -1.0, -0.02], [1.0, 1.0, 0.0], 9))]);
        assert!(surfaces(&centres, &labels, &[3]).is_empty());
        // an object beside the table, not over it, makes it no surface either
        let (centres, labels) = scene(&[
            (3, block([-1.0, -1.0, -0.02], [1.0, 1.0, 0.0], 9)),
            (1, block([3.0, 3.0, 0.0], [3.3, 3.3, 0.3], 5)),
        ]);
        assert!(surfaces(&centres, &labels, &[1, 3]).is_empty());
    }

    #[test]
    fn eigen_of_a_known_matrix() {
        let (values, v) = symmetric_eigen([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 5.0]]);
        let mut sorted = values;
        sorted.sort_by(f64::total_cmp);
        for (got, want) in sorted.iter().zip([1.0, 3.0, 5.0]) {
            assert!((got - want).abs() < 1e-12, "{values:?}");
        }
        // A v = lambda v for each column
        let a = [[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 5.0]];
        for k in 0..3 {
            for i in 0..3 {
                let av: f64 = (0..3).map(|j| a[i][j] * v[j][k]).sum();
                assert!((av - values[k] * v[i][k]).abs() < 1e-12);
            }
        }
    }
}
