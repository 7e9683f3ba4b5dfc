//! Every numeric constant of the splatting op, in one place.
//!
//! The values follow the original 3D Gaussian Splatting rasterizer (Kerbl et al. 2023) unless a
//! line says otherwise. [`RasterConfig`] carries the ones a caller may change (tests use a smooth
//! variant for finite-difference checks); the rest are fixed.

/// Side of a square screen tile in pixels. Gaussians are binned into 16x16 tiles.
pub const TILE_SIZE: u32 = 16;
/// Pixels per tile (`TILE_SIZE^2`), also the workgroup size of the wgpu raster kernels.
pub const TILE_PIXELS: u32 = TILE_SIZE * TILE_SIZE;

/// Low-pass dilation added to the diagonal of every 2D covariance (pixels^2): a screen-space
/// Gaussian is never thinner than about one pixel ("0.3 px dilation" of 3DGS).
pub const LOW_PASS: f32 = 0.3;

/// The perspective Jacobian is evaluated at the projected centre clamped to
/// `FRUSTUM_CLAMP * tan(fov/2)` (3DGS: 1.3), which keeps far-off-axis Gaussians from exploding.
pub const FRUSTUM_CLAMP: f32 = 1.3;

/// Rotations whose quaternion norm is below this are treated as the identity rotation, with a zero
/// gradient (documented policy for zero and denormal quaternions).
pub const QUAT_MIN_NORM: f32 = 1e-12;

/// Log-scales are clamped into this range before `exp` (zero gradient outside), so that finite
/// but absurd inputs cannot overflow the covariance in f32.
pub const LOG_SCALE_MIN: f32 = -30.0;
/// See [`LOG_SCALE_MIN`]. `exp(20)` is about 4.9e8 world units.
pub const LOG_SCALE_MAX: f32 = 20.0;

/// Default near plane (camera-space depth); Gaussians whose centre is nearer are culled.
pub const DEFAULT_NEAR: f32 = 0.01;
/// Default far plane; Gaussians whose centre is farther are culled.
pub const DEFAULT_FAR: f32 = 1e10;

/// Id written into the top-contributor map where no Gaussian contributes.
pub const EMPTY_ID: i32 = -1;

/// Tunable thresholds of the compositor.
///
/// `Default` gives the 3DGS values. [`RasterConfig::smooth`] removes every threshold so that the
/// rendered image is a smooth function of the inputs (used by the finite-difference tests).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterConfig {
    /// Upper clamp of a single Gaussian's alpha (3DGS: 0.99).
    pub alpha_max: f32,
    /// Contributions with alpha below this are skipped (3DGS: 1/255).
    pub alpha_min: f32,
    /// Compositing stops before the transmittance would fall below this (3DGS: 1e-4).
    pub t_min: f32,
    /// A Gaussian is binned to the tiles its `extent`-sigma ellipse bounding square touches (3DGS: 3).
    pub extent: f32,
    /// How the wgpu backward adds per-pixel gradients into each Gaussian's slots (the CPU
    /// backends ignore it).
    pub grad_reduce: GradReduce,
    /// Which atomic add the wgpu backward uses (the CPU backends ignore it).
    pub float_add: FloatAdd,
    /// How the wgpu forward orders each tile's Gaussians (the CPU backends ignore it).
    pub tile_sort: TileSort,
}

/// How the wgpu backward accumulates a tile's per-pixel contributions to one Gaussian's gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum GradReduce {
    /// [`GradReduce::Plane`] where the adapter reports plane (subgroup) operations, else
    /// [`GradReduce::Atomic`]. Real GPUs report them; Mesa lavapipe does not. The environment
    /// variable `CHATSPLAT_WGPU_GRAD_REDUCE=atomic|plane` overrides the choice (to compare them).
    #[default]
    Auto,
    /// Every pixel adds its contribution with its own atomic: up to 256 at once on one slot.
    Atomic,
    /// The pixels of a plane (subgroup) sum their contributions first; one atomic per plane.
    /// Needs an adapter with subgroup support (the shader does not compile without it).
    Plane,
}

/// How the wgpu backward adds a float into a Gaussian's gradient slot.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum FloatAdd {
    /// [`FloatAdd::Native`] where the adapter has float atomic add (NVIDIA and AMD through Vulkan's
    /// `shaderBufferFloat32AtomicAdd`), else [`FloatAdd::Cas`]. The environment variable
    /// `CHATSPLAT_WGPU_FLOAT_ADD=native|cas` overrides the choice (to compare them).
    #[default]
    Auto,
    /// The hardware's atomic float add: one instruction per add.
    Native,
    /// A compare-and-swap loop on the float's bits: runs everywhere, slower under contention.
    Cas,
}

/// How the wgpu forward puts each tile's Gaussians in (depth, id) order. Both give the same lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum TileSort {
    /// [`TileSort::Radix`]. The environment variable `CHATSPLAT_WGPU_SORT=radix|bitonic`
    /// overrides the choice (to compare them).
    #[default]
    Auto,
    /// The Gaussians sorted once by depth, then every tile entry by tile: two global, stable
    /// radix sorts (what gsplat and Brush do), work in proportion to the entries.
    Radix,
    /// A bitonic sort of each tile's list by a workgroup, in global memory: n log² n per tile, and a
    /// tile's workgroup waits on its longest list.
    Bitonic,
}

impl Default for RasterConfig {
    fn default() -> Self {
        Self {
            alpha_max: 0.99,
            alpha_min: 1.0 / 255.0,
            t_min: 1e-4,
            extent: 3.0,
            grad_reduce: GradReduce::Auto,
            float_add: FloatAdd::Auto,
            tile_sort: TileSort::Auto,
        }
    }
}

impl RasterConfig {
    /// No alpha skip, no early stop and an 8-sigma footprint: the output is smooth in every input
    /// as long as no alpha reaches `alpha_max` and no Gaussian changes tiles.
    pub fn smooth() -> Self {
        Self { alpha_max: 0.99, alpha_min: 0.0, t_min: 0.0, extent: 8.0, ..Self::default() }
    }
}
