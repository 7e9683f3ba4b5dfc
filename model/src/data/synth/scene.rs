//! The synthetic tabletop's content: the table and the objects a seed places on it. Everything
//! else in [`super`] (the ray caster, the Gaussian version, the questions) draws from this.

use crate::rng::Rng;
use glam::Vec3;

/// One object of the tabletop.
#[derive(Clone, Debug, PartialEq)]
pub struct Primitive {
    pub name: &'static str,
    pub shape: &'static str,
    pub color: [f32; 3],
    pub center: Vec3,
    pub size: f32,
}

/// Half side of the square table top (the table spans [-TABLE_HALF, TABLE_HALF] in x and z).
pub const TABLE_HALF: f32 = 2.0;

/// Wood-like stripes of the table top at (x, z).
pub fn table_color(x: f32, z: f32) -> [f32; 3] {
    let stripe = 0.5 + 0.5 * (x * 9.0 + (z * 2.0).sin()).sin();
    [0.55 + 0.12 * stripe, 0.38 + 0.08 * stripe, 0.22 + 0.05 * stripe]
}

/// The objects placed by `seed` (positions and sizes jitter with the seed).
pub fn tabletop_objects(seed: u64) -> Vec<Primitive> {
    let mut r = Rng::new(seed ^ 0x5EED);
    let base = [
        ("red ball", "sphere", [0.85, 0.12, 0.10]),
        ("blue box", "box", [0.15, 0.30, 0.85]),
        ("green cylinder", "cylinder", [0.15, 0.70, 0.25]),
        ("yellow cone", "cone", [0.95, 0.80, 0.10]),
        ("purple ball", "sphere", [0.55, 0.20, 0.70]),
    ];
    base.iter()
        .enumerate()
        .map(|(k, &(name, shape, color))| {
            let ang = k as f32 / base.len() as f32 * std::f32::consts::TAU + r.range(-0.3, 0.3);
            let rad = if k == 0 { 0.0 } else { r.range(0.9, 1.3) };
            let size = r.range(0.28, 0.42);
            Primitive { name, shape, color, center: Vec3::new(rad * ang.cos(), size, rad * ang.sin()), size }
        })
        .collect()
}
