//! What a seed places on the table: 1-6 objects drawn from 6 shapes x 8 named colours x 2 sizes,
//! placed without overlap, every (colour, shape) pair at most once (so "the red cube" names one
//! object in the whole scene), on a table whose colour and pattern, and under a background and a
//! light, that also vary with the seed. Everything else in [`super`] (the ray caster, the Gaussian
//! version, the questions) draws from a [`SynthScene`].
//!
//! World frame: y up, the table top at y = 0, objects standing on it.

use crate::ObjectId;
use base::rng::Rng;
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// The shapes objects are made of.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    Sphere,
    Cube,
    Cylinder,
    Cone,
    Pyramid,
    Torus,
}

impl Shape {
    pub const ALL: [Shape; 6] =
        [Shape::Sphere, Shape::Cube, Shape::Cylinder, Shape::Cone, Shape::Pyramid, Shape::Torus];

    /// The word questions and answers use.
    pub fn word(self) -> &'static str {
        match self {
            Shape::Sphere => "sphere",
            Shape::Cube => "cube",
            Shape::Cylinder => "cylinder",
            Shape::Cone => "cone",
            Shape::Pyramid => "pyramid",
            Shape::Torus => "torus",
        }
    }

    /// Plural, for counting questions.
    pub fn plural(self) -> &'static str {
        match self {
            Shape::Sphere => "spheres",
            Shape::Cube => "cubes",
            Shape::Cylinder => "cylinders",
            Shape::Cone => "cones",
            Shape::Pyramid => "pyramids",
            Shape::Torus => "tori",
        }
    }

    /// Largest horizontal distance from the object's axis at scale `s` (any yaw).
    pub fn footprint(self, s: f32) -> f32 {
        s * match self {
            Shape::Sphere => 1.0,
            Shape::Cube => CUBE_HALF * std::f32::consts::SQRT_2,
            Shape::Cylinder => CYLINDER_RADIUS,
            Shape::Cone => CONE_RADIUS,
            Shape::Pyramid => PYRAMID_HALF * std::f32::consts::SQRT_2,
            Shape::Torus => TORUS_MAJOR + TORUS_MINOR,
        }
    }

    /// Height of the object's centre above the table at scale `s` (the centre of its bounding box).
    pub fn centre_height(self, s: f32) -> f32 {
        s * match self {
            Shape::Sphere => 1.0,
            Shape::Cube => CUBE_HALF,
            Shape::Cylinder => CYLINDER_HALF_HEIGHT,
            Shape::Cone => CONE_HEIGHT / 2.0,
            Shape::Pyramid => PYRAMID_HEIGHT / 2.0,
            Shape::Torus => TORUS_MINOR,
        }
    }
}

/// Shape proportions, in units of the object's scale `s`.
pub const CUBE_HALF: f32 = 0.8;
pub const CYLINDER_RADIUS: f32 = 0.75;
pub const CYLINDER_HALF_HEIGHT: f32 = 0.8;
pub const CONE_RADIUS: f32 = 0.85;
pub const CONE_HEIGHT: f32 = 1.9;
pub const PYRAMID_HALF: f32 = 0.85;
pub const PYRAMID_HEIGHT: f32 = 1.6;
pub const TORUS_MAJOR: f32 = 0.72;
pub const TORUS_MINOR: f32 = 0.3;

/// The named colours objects come in (none of them the table's or the background's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Color {
    Red,
    Orange,
    Yellow,
    Green,
    Cyan,
    Blue,
    Purple,
    Pink,
}

impl Color {
    pub const ALL: [Color; 8] =
        [Color::Red, Color::Orange, Color::Yellow, Color::Green, Color::Cyan, Color::Blue, Color::Purple, Color::Pink];

    pub fn word(self) -> &'static str {
        match self {
            Color::Red => "red",
            Color::Orange => "orange",
            Color::Yellow => "yellow",
            Color::Green => "green",
            Color::Cyan => "cyan",
            Color::Blue => "blue",
            Color::Purple => "purple",
            Color::Pink => "pink",
        }
    }

    /// Albedo in [0, 1].
    pub fn rgb(self) -> [f32; 3] {
        match self {
            Color::Red => [0.86, 0.10, 0.09],
            Color::Orange => [0.96, 0.50, 0.08],
            Color::Yellow => [0.95, 0.86, 0.12],
            Color::Green => [0.16, 0.70, 0.22],
            Color::Cyan => [0.12, 0.78, 0.84],
            Color::Blue => [0.14, 0.26, 0.88],
            Color::Purple => [0.52, 0.20, 0.74],
            Color::Pink => [0.97, 0.52, 0.72],
        }
    }
}

/// The two sizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Size {
    Small,
    Large,
}

impl Size {
    pub const ALL: [Size; 2] = [Size::Small, Size::Large];

    pub fn word(self) -> &'static str {
        match self {
            Size::Small => "small",
            Size::Large => "large",
        }
    }

    /// The object scale `s` of this size (the large one is 2.5 times the small one: apparent
    /// sizes stay apart from every camera distance the datasets use).
    pub fn scale(self) -> f32 {
        match self {
            Size::Small => 0.19,
            Size::Large => 0.40,
        }
    }
}

/// One object on the table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Object {
    /// Instance id in the masks (`FIRST_OBJECT_ID`, ...).
    pub id: ObjectId,
    pub shape: Shape,
    pub color: Color,
    pub size: Size,
    /// Centre of the object's bounding box.
    pub center: Vec3,
    /// Scale `s`; the shape's proportions are multiples of it.
    pub scale: f32,
    /// Rotation about the vertical axis (radians; cubes and pyramids show it).
    pub yaw: f32,
}

impl Object {
    /// "red cube": unique in its scene.
    pub fn name(&self) -> String {
        format!("{} {}", self.color.word(), self.shape.word())
    }
}

/// The table top's look.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Table {
    /// Half side of the square top (it spans [-half, half] in x and z).
    pub half: f32,
    pub color_a: [f32; 3],
    pub color_b: [f32; 3],
    /// 0: wood-like stripes, 1: checker, 2: plain.
    pub pattern: u8,
    /// Stripes or squares per unit length.
    pub frequency: f32,
}

impl Table {
    /// Albedo at (x, z).
    pub fn color(&self, x: f32, z: f32) -> [f32; 3] {
        let t = match self.pattern {
            0 => 0.5 + 0.5 * (x * self.frequency * 9.0 + (z * 2.0).sin()).sin(),
            1 => {
                let (i, j) = ((x * self.frequency).floor() as i64, (z * self.frequency).floor() as i64);
                ((i + j).rem_euclid(2)) as f32
            }
            _ => 0.5,
        };
        std::array::from_fn(|k| self.color_a[k] * (1.0 - t) + self.color_b[k] * t)
    }
}

/// Where objects may stand: within this distance of the table's centre.
pub const PLACEMENT_RADIUS: f32 = 0.95;
/// Gap kept between the footprints of two objects.
pub const GAP: f32 = 0.08;

/// A whole synthetic scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthScene {
    pub seed: u64,
    pub table: Table,
    pub background: [f32; 3],
    /// Direction towards the light (unit).
    pub light: Vec3,
    pub objects: Vec<Object>,
}

const TABLE_COLORS: [([f32; 3], [f32; 3]); 4] = [
    ([0.55, 0.38, 0.22], [0.67, 0.46, 0.27]), // oak
    ([0.36, 0.24, 0.15], [0.45, 0.30, 0.19]), // walnut
    ([0.50, 0.50, 0.52], [0.62, 0.62, 0.64]), // grey stone
    ([0.78, 0.70, 0.56], [0.86, 0.79, 0.66]), // beige
];

const BACKGROUNDS: [[f32; 3]; 4] = [[1.0, 1.0, 1.0], [0.90, 0.90, 0.90], [0.86, 0.91, 1.0], [1.0, 0.97, 0.90]];

impl SynthScene {
    /// The scene of `seed`: deterministic, 1 to 6 objects.
    pub fn from_seed(seed: u64) -> Self {
        let mut r = Rng::new(seed ^ 0x5EED_5CE7E);
        let (color_a, color_b) = TABLE_COLORS[(r.next_u64() % TABLE_COLORS.len() as u64) as usize];
        let table = Table {
            half: r.range(1.7, 2.1),
            color_a,
            color_b,
            pattern: (r.next_u64() % 3) as u8,
            frequency: r.range(0.8, 1.6),
        };
        let background = BACKGROUNDS[(r.next_u64() % BACKGROUNDS.len() as u64) as usize];
        let light = Vec3::new(r.range(-0.6, 0.6), 1.0, r.range(-0.6, 0.6)).normalize();
        let want = 1 + (r.next_u64() % 6) as usize;
        let mut objects: Vec<Object> = Vec::with_capacity(want);
        let mut tries = 0;
        while objects.len() < want && tries < 400 {
            tries += 1;
            let shape = Shape::ALL[(r.next_u64() % 6) as usize];
            let color = Color::ALL[(r.next_u64() % 8) as usize];
            let size = Size::ALL[(r.next_u64() % 2) as usize];
            if objects.iter().any(|o| o.shape == shape && o.color == color) {
                continue;
            }
            let s = size.scale() * r.range(0.95, 1.05);
            let rad = PLACEMENT_RADIUS * r.f().sqrt();
            let ang = r.range(0.0, std::f32::consts::TAU);
            let (x, z) = (rad * ang.cos(), rad * ang.sin());
            let fp = shape.footprint(s);
            let clear = objects.iter().all(|o| {
                let d = (o.center.x - x).hypot(o.center.z - z);
                d >= o.shape.footprint(o.scale) + fp + GAP
            });
            if !clear {
                continue;
            }
            objects.push(Object {
                id: super::FIRST_OBJECT_ID + objects.len() as ObjectId,
                shape,
                color,
                size,
                center: Vec3::new(x, shape.centre_height(s), z),
                scale: s,
                yaw: r.range(0.0, std::f32::consts::FRAC_PI_2),
            });
        }
        SynthScene { seed, table, background, light, objects }
    }

    /// The object with mask id `id`.
    pub fn object(&self, id: ObjectId) -> Option<&Object> {
        self.objects.iter().find(|o| o.id == id)
    }
}
