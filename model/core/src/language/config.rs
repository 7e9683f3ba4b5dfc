//! The shapes of the language field and the token cameras: the cameras that render a feature map
//! covering exactly what the teacher's tokens saw of a view or of an object crop.

use super::crop::ObjectCrop;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use splat_kernels::Camera;

/// Shapes of the language field and its encoder (saved with every run).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LanguageConfig {
    /// Channels of the per-Gaussian view-level features (paper: 32).
    pub view_channels: usize,
    /// Channels of the per-Gaussian object-level features (paper: 32). The encoder is shared by
    /// both levels, so it must equal `view_channels`.
    pub object_channels: usize,
    /// Width of the hidden 1x1 convolution of the lifting network.
    pub hidden: usize,
    /// Use the lifting network. Without it the features live at `dim` channels directly (the
    /// paper's "w/o encoder" ablation; `view_channels` is then ignored and set to `dim`).
    pub lifting: bool,
    /// Learn the scaling adjustment `tokens * a + b`.
    pub scale_shift: bool,
    /// One `(a, b)` per level (view, object) instead of one shared pair. The paper has a single
    /// pair; object crops (mostly black) and whole views have very different token statistics,
    /// and with one pair the view loss rose during training on the synthetic test scene (see
    /// eval/journal/README-reference-2026-11-27.md, "The language stage: `chatsplat train-language`"),
    /// so the default is per level.
    pub scale_shift_per_level: bool,
    /// Teacher token width D (SigLIP hidden size: 1152 for LLaVA-OneVision).
    pub dim: usize,
    /// Token grid side (27 for SigLIP at 384 px with 14 px patches).
    pub grid: usize,
    /// Render pixels per token side: the encoder's non-overlapping convolution kernel (paper: 14).
    /// Smaller values render smaller maps (faster, coarser); 0 = what the views need: one render
    /// pixel per view pixel under a token, at most 14 ([`LanguageConfig::auto_patch`]).
    pub patch: usize,
    /// The teacher's input image side (384) and patch size (14): a token covers the same part of
    /// the picture as the teacher's token did.
    pub teacher_image: usize,
    pub teacher_patch: usize,
    /// One self-attention layer over the token grid after the patch convolution
    /// ([`TokenMixer`](super::TokenMixer); not in the paper, whose encoder is local). Off: on
    /// ten held-out scenes it did not answer better than the field without it (BENCHMARKS.md,
    /// "Where the field's tokens lose count and colours").
    pub token_mixer: bool,
    /// The encoder's tokens are the teacher tower's state before its last `tower_tail` layers,
    /// which run, frozen, on them before the projector (not in the paper: 0). Set from the
    /// teacher index (`chatsplat extract --tower-tail`), never by hand.
    pub tower_tail: usize,
}

impl Default for LanguageConfig {
    fn default() -> Self {
        Self {
            view_channels: 32,
            object_channels: 32,
            hidden: 128,
            lifting: true,
            scale_shift: true,
            scale_shift_per_level: true,
            dim: 1152,
            grid: 27,
            patch: 14,
            teacher_image: 384,
            teacher_patch: 14,
            token_mixer: false,
            tower_tail: 0,
        }
    }
}

impl LanguageConfig {
    /// Checks the shapes fit together.
    pub fn validate(&self) -> Result<()> {
        if self.grid == 0 || self.patch == 0 || self.dim == 0 || self.teacher_patch == 0 {
            return Err(Error::input("language config: grid, patch, dim and teacher_patch must be positive"));
        }
        if self.grid * self.teacher_patch > self.teacher_image {
            return Err(Error::input(format!(
                "language config: a {0}x{0} grid of {1} px patches does not fit a {2} px teacher image",
                self.grid, self.teacher_patch, self.teacher_image
            )));
        }
        if self.lifting && (self.view_channels == 0 || self.hidden == 0) {
            return Err(Error::input("language config: view_channels and hidden must be positive"));
        }
        if self.lifting && self.view_channels != self.object_channels {
            return Err(Error::input(format!(
                "language config: the encoder is shared by both levels, so view_channels ({}) must equal \
                    object_channels ({})",
                self.view_channels, self.object_channels
            )));
        }
        Ok(())
    }

    /// Channels of the per-Gaussian features the encoder reads.
    pub fn feature_channels(&self) -> usize {
        if self.lifting { self.view_channels } else { self.dim }
    }

    /// The patch that renders a `width` x `height` view at about its own resolution: the token
    /// grid covers `grid * teacher_patch / teacher_image` of the view, so a token spans
    /// `max(width, height) * teacher_patch / teacher_image` view pixels (rounded up, 1..=14).
    pub fn auto_patch(&self, width: u32, height: u32) -> usize {
        let span = width.max(height) as f32 * self.teacher_patch as f32 / self.teacher_image as f32;
        (span.ceil() as usize).clamp(1, self.teacher_patch)
    }

    /// Tokens per image.
    pub fn tokens(&self) -> usize {
        self.grid * self.grid
    }

    /// Side of the rendered feature map.
    pub fn map_size(&self) -> usize {
        self.grid * self.patch
    }

    /// Camera that renders the map of a whole view: the teacher squashes the view to a
    /// `teacher_image` square and its tokens cover the top-left `grid * teacher_patch` pixels.
    pub fn view_camera(&self, cam: &Camera) -> Camera {
        let (sx, sy) = (self.teacher_image as f32 / cam.width as f32, self.teacher_image as f32 / cam.height as f32);
        self.scaled(cam, sx, sy, 0.0, 0.0)
    }

    /// Camera that renders the map of the square crop the teacher saw for one object: `bbox` =
    /// `[x0, y0, x1, y1)` in view pixels (box plus margin), padded to a square around its centre,
    /// at least half the view's shorter side ([`ObjectCrop`], the one crop rule).
    pub fn object_camera(&self, cam: &Camera, bbox: [usize; 4]) -> Camera {
        let crop = ObjectCrop::from_box(bbox, cam.width as usize, cam.height as usize);
        let (x0, y0) = crop.origin();
        let s = self.teacher_image as f32 / crop.side as f32;
        self.scaled(cam, s, s, x0, y0)
    }

    fn scaled(&self, cam: &Camera, sx: f32, sy: f32, x0: f32, y0: f32) -> Camera {
        let k = self.map_size() as f32 / (self.grid * self.teacher_patch) as f32;
        let r = self.map_size() as u32;
        Camera {
            fx: cam.fx * sx * k,
            fy: cam.fy * sy * k,
            cx: (cam.cx - x0) * sx * k,
            cy: (cam.cy - y0) * sy * k,
            width: r,
            height: r,
            ..*cam
        }
    }
}
