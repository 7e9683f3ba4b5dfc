//! The packed buffers the kernels share, by named offset: the projected Gaussians (`P_*`), the
//! screen-space gradients (`G_*`) and the camera block (`C_*`).

/// Floats per projected Gaussian (`proj`): the fields `P_*`.
pub(super) const PROJ: usize = 8;
/// Projected screen-space centre x, y.
pub(super) const P_MX: usize = 0;
pub(super) const P_MY: usize = 1;
/// Projected conic (inverse 2D covariance) a, b, c.
pub(super) const P_CA: usize = 2;
pub(super) const P_CB: usize = 3;
pub(super) const P_CC: usize = 4;
pub(super) const P_DEPTH: usize = 5;
pub(super) const P_OPACITY: usize = 6;
pub(super) const P_RADIUS: usize = 7;
/// Floats per Gaussian staged in shared memory by the raster kernels: `proj`'s first fields, up
/// to the opacity (the radius stays behind).
pub(super) const STAGED: usize = 7;

/// Per-Gaussian screen-space gradient slots (`g2d`): the fields `G_*`.
pub(super) const G2D: usize = 7;
pub(super) const G_MX: usize = 0;
pub(super) const G_MY: usize = 1;
pub(super) const G_CA: usize = 2;
pub(super) const G_CB: usize = 3;
pub(super) const G_CC: usize = 4;
pub(super) const G_OPACITY: usize = 5;
pub(super) const G_DEPTH: usize = 6;

/// Camera parameter block (`cam`), built by `cam_block`: the fields `C_*`.
pub(super) const CAM: usize = 24;
/// World-to-camera rotation, 9 floats row-major (`C_R + 3 * row + col`).
pub(super) const C_R: usize = 0;
/// World-to-camera translation, 3 floats.
pub(super) const C_T: usize = 9;
pub(super) const C_FX: usize = 12;
pub(super) const C_FY: usize = 13;
pub(super) const C_CX: usize = 14;
pub(super) const C_CY: usize = 15;
/// The clamp limits of the normalised image coordinates x/z and y/z (`Camera::clamp_limits`).
pub(super) const C_LIM_X: usize = 16;
pub(super) const C_LIM_Y: usize = 17;
pub(super) const C_NEAR: usize = 18;
pub(super) const C_FAR: usize = 19;
/// The Gaussian extent in standard deviations (`RasterConfig::extent`).
pub(super) const C_EXTENT: usize = 20;
pub(super) const C_ALPHA_MAX: usize = 21;
pub(super) const C_ALPHA_MIN: usize = 22;
pub(super) const C_T_MIN: usize = 23;

/// The runtime trip count of [`super::raster`]'s loop canary (see `loop_canary`).
pub(super) const CANARY_TRIPS: u32 = 2;
