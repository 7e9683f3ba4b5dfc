//! A trained ChatSplat scene at inference: frozen Gaussians carrying language features, rendered
//! into feature maps from the token cameras and encoded into tokens; objects picked from the
//! rendered identity. Training (`train::language`) optimises the same [`LanguageScene`].

use crate::ObjectId;
use crate::error::{Error, Result};
use crate::language::{LanguageConfig, LanguageField, ObjectCrop, mask_out};
use crate::run::{GeometryRun, GeometryState, LanguageRun, OpenedLanguage};
use crate::splats::{SplatModel, ViewRender};
use crate::vlm::LlavaOnevision;
use burn::tensor::{Device, Int, Tensor, TensorData};
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::blend::BlendWeights;
use splat_kernels::blend_ext::blend;
use splat_kernels::{Camera, Gaussians};
use std::sync::Arc;

/// Frozen geometry + language field.
pub struct LanguageScene {
    /// Shapes of the field and the token cameras.
    pub cfg: LanguageConfig,
    /// The Gaussians (frozen).
    pub splats: SplatModel,
    /// SH degree and background of RGB renders.
    pub sh_degree: usize,
    pub background: [f32; 3],
    pub field: LanguageField,
    /// Every Gaussian, for RGB renders, when `splats` holds only those the language maps keep
    /// ([`subset`](Self::subset), a compacted run).
    pub display: Option<SplatModel>,
    /// Object crop margin (the teacher's).
    pub margin: f32,
    /// Whether the geometry was trained with instance masks: without them the rendered identity
    /// means nothing and object-level picks are refused.
    pub masks: bool,
}

impl LanguageScene {
    /// Loads a geometry run and a language run trained on it, every Gaussian in the language maps.
    pub fn load(run: &GeometryRun, language: &LanguageRun, device: &Device) -> Result<Self> {
        let (splats, state) = run.load_model(device)?;
        let opened = language.open(run, splats.len(), false, device)?;
        Ok(Self::of(splats, &state, opened))
    }

    /// [`load`](Self::load) for inference: a compacted run ([`model::run::Compaction`]) keeps
    /// only its kept Gaussians for the language maps and picks.
    ///
    /// [`model::run::Compaction`]: crate::run::Compaction
    pub fn open(run: &GeometryRun, language: &LanguageRun, device: &Device) -> Result<Self> {
        let (splats, state) = run.load_model(device)?;
        let opened = language.open(run, splats.len(), true, device)?;
        Ok(Self::of(splats, &state, opened))
    }

    /// The scene of an opened geometry and language run: with a compaction, its language maps
    /// and picks from the kept Gaussians only.
    pub fn of(splats: SplatModel, state: &GeometryState, language: OpenedLanguage) -> Self {
        let scene = Self {
            cfg: language.state.field,
            splats,
            sh_degree: state.sh_degree,
            background: state.background,
            field: language.field,
            display: None,
            margin: language.state.margin,
            masks: state.data.masks,
        };
        match &language.compaction {
            Some(c) => scene.subset(&c.kept),
            None => scene,
        }
    }

    /// The frozen Gaussians carrying `features` (`[N, C]`, on `features`' device, autodiff when
    /// `features` is).
    pub fn gaussians(&self, features: Tensor<2>) -> Gaussians {
        let ad = features.is_autodiff();
        let m = &self.splats;
        let n = m.len();
        let on = |t: Tensor<2>| if ad { t.autodiff() } else { t };
        Gaussians {
            means: on(m.means.val()),
            log_scales: on(m.log_scales.val()),
            quats: on(m.quats.val()),
            opacity_logits: on(m.opacity_logits.val()).reshape([n]),
            features,
        }
    }

    /// Renders `features` `[N, C]` from `cam` over a zero background: `[H, W, C]`.
    pub fn render_map(&self, features: Tensor<2>, cam: &Camera) -> Result<Tensor<3>> {
        let c = features.dims()[1];
        let bg = Tensor::zeros([c], &features.device());
        let opts = SplatOptions { validate: false, ..Default::default() };
        Ok(splat(&self.gaussians(features), cam, bg, &opts)?.features)
    }

    /// The blend weights of the frozen Gaussians seen from `cam`: [`blend_map`](Self::blend_map)
    /// with them is [`render_map`](Self::render_map) for any features, at a fraction of the cost
    /// (`splat_kernels::blend`; what the language stage replays at every step).
    pub fn blend_weights(&self, cam: &Camera) -> Result<BlendWeights> {
        self.splats.blend_weights(cam)
    }

    /// `features` `[N, C]` blended with kept `weights` over a zero background: `[H, W, C]`.
    pub fn blend_map(&self, features: Tensor<2>, weights: &Arc<BlendWeights>) -> Result<Tensor<3>> {
        Ok(blend(features, weights)?)
    }

    /// The view-level map `[H, W, Cv]` with `field` and the kept weights of the view's token camera
    /// (`blend_weights(&cfg.view_camera(cam))`): [`view_map`](Self::view_map), faster.
    pub fn view_map_kept(&self, field: &LanguageField, weights: &Arc<BlendWeights>) -> Result<Tensor<3>> {
        self.blend_map(field.view_features.val(), weights)
    }

    /// View-level tokens `[T, D]` of [`view_map_kept`](Self::view_map_kept):
    /// [`view_tokens`](Self::view_tokens), faster.
    pub fn view_tokens_kept(&self, field: &LanguageField, weights: &Arc<BlendWeights>) -> Result<Tensor<2>> {
        Ok(field.encoder.forward(self.view_map_kept(field, weights)?))
    }

    /// The masked object-level map `[r, r, Co]` with `field`, the kept weights of an object's crop
    /// camera and its mask: [`object_map`](Self::object_map), faster.
    pub fn object_map_kept(
        &self,
        field: &LanguageField,
        weights: &Arc<BlendWeights>,
        mask: &[f32],
    ) -> Result<Tensor<3>> {
        Ok(cut_out(self.blend_map(field.object_features.val(), weights)?, mask.to_vec()))
    }

    /// Object-level tokens `[T, D]` of [`object_map_kept`](Self::object_map_kept):
    /// [`object_tokens_with`](Self::object_tokens_with), faster.
    pub fn object_tokens_kept(
        &self,
        field: &LanguageField,
        weights: &Arc<BlendWeights>,
        mask: &[f32],
    ) -> Result<Tensor<2>> {
        Ok(field.encoder.forward_level(self.object_map_kept(field, weights, mask)?, true))
    }

    /// The Gaussians RGB renders show: every one ([`display`](Self::display) where the language
    /// maps keep fewer).
    pub fn shown(&self) -> &SplatModel {
        self.display.as_ref().unwrap_or(&self.splats)
    }

    /// RGB, identity and alpha of a view.
    pub fn render(&self, cam: &Camera) -> Result<ViewRender> {
        self.shown().render(cam, self.sh_degree, self.background)
    }

    /// RGB alone of a view `[H * W * 3]`, clamped to 0..=1 (a frame to show; faster than
    /// [`render`](Self::render)).
    pub fn render_rgb(&self, cam: &Camera) -> Result<Vec<f32>> {
        self.shown().render_rgb(cam, self.sh_degree, self.background)
    }

    /// The view-level map `[H, W, Cv]` of a view camera (rendered from its token camera), with
    /// `field` (the scene's own or a copy being trained).
    pub fn view_map(&self, field: &LanguageField, cam: &Camera) -> Result<Tensor<3>> {
        self.render_map(field.view_features.val(), &self.cfg.view_camera(cam))
    }

    /// View-level tokens `[T, D]` of a view camera, with `field` (at inference, a
    /// [`FrozenEncoder`](crate::language::FrozenEncoder) of [`view_map`](Self::view_map) is faster).
    pub fn view_tokens(&self, field: &LanguageField, cam: &Camera) -> Result<Tensor<2>> {
        Ok(field.encoder.forward(self.view_map(field, cam)?))
    }

    /// The tokens the reader takes from the encoder's `tokens` `[T, D]`: the tower's last
    /// `cfg.tower_tail` layers of `vlm` run on them (none where the field learnt the tower's
    /// output, as the paper's).
    pub fn reader_tokens(&self, vlm: &LlavaOnevision, tokens: Tensor<2>) -> Tensor<2> {
        vlm.tower_tail(tokens, self.cfg.tower_tail)
    }

    /// The object crop camera and its `[r, r]` 0/1 mask of object `id`: the rendered identity,
    /// restricted to the crop's box inside the view's frame (as the teacher's image was).
    pub fn object_crop(&self, cam: &Camera, id: ObjectId, bbox: [usize; 4]) -> Result<(Camera, Vec<f32>)> {
        let oc = self.cfg.object_camera(cam, bbox);
        let ids = self.splats.render_ids(&oc)?;
        Ok((oc, crop_mask(cam, &oc, bbox, &ids, id)))
    }

    /// The masked object-level map `[r, r, Co]` through an object's crop camera and its `[r, r]`
    /// mask, with `field`.
    pub fn object_map(&self, field: &LanguageField, oc: &Camera, mask: &[f32]) -> Result<Tensor<3>> {
        Ok(cut_out(self.render_map(field.object_features.val(), oc)?, mask.to_vec()))
    }

    /// Object-level tokens `[T, D]` through an object's crop camera and mask, with `field`.
    pub fn object_tokens_with(&self, field: &LanguageField, oc: &Camera, mask: &[f32]) -> Result<Tensor<2>> {
        Ok(field.encoder.forward_level(self.object_map(field, oc, mask)?, true))
    }

    /// An error unless the geometry was trained with instance masks (what object level needs).
    pub fn check_masks(&self) -> Result<()> {
        if self.masks {
            return Ok(());
        }
        Err(Error::input(
            "object level needs instance masks, and this scene's dataset has none: give the capture masks \
             (masks/, Gaussian Grouping's object_mask/, or --masks DIR on train and extract) and train \
             again; view and scene level work without",
        ))
    }

    /// The rendered identity of the view from `cam` (`[H * W]`) and the id under pixel `(x, y)`
    /// (0: the background). A pixel outside the image, or a scene without masks, is an error.
    pub fn identity_at(&self, cam: &Camera, x: usize, y: usize) -> Result<(Vec<ObjectId>, ObjectId)> {
        let (w, h) = (cam.width as usize, cam.height as usize);
        if x >= w || y >= h {
            return Err(Error::input(format!("pixel ({x}, {y}) lies outside the {w}x{h} view")));
        }
        self.check_masks()?;
        let ids = self.splats.render_ids(cam)?;
        let id = ids[y * w + x];
        Ok((ids, id))
    }

    /// The object under pixel `(x, y)` of `cam` and its crop box (from the rendered identity);
    /// `None` for the background (id 0). A pixel outside the image is an error.
    pub fn pick(&self, cam: &Camera, x: usize, y: usize) -> Result<Option<(ObjectId, [usize; 4])>> {
        let (ids, id) = self.identity_at(cam, x, y)?;
        Ok(self.object_box(cam, &ids, id).map(|b| (id, b)))
    }

    /// The crop box of object `id` in the identity `ids` of the view from `cam` (mask box + the
    /// teacher's margin); `None` for the background or an absent object.
    pub fn object_box(&self, cam: &Camera, ids: &[ObjectId], id: ObjectId) -> Option<[usize; 4]> {
        if id == 0 {
            return None;
        }
        crate::language::object_box(ids, cam.width as usize, cam.height as usize, id, self.margin)
    }

    /// The masked object map `[r, r, Co]` of object `id` with crop box `bbox` in the view from
    /// `cam`, with the scene's field. The crop's identity and object features are rendered in one
    /// pass: the same map as [`object_crop`](Self::object_crop) + [`object_map`](Self::object_map),
    /// one render fewer.
    pub fn object_map_in(&self, cam: &Camera, id: ObjectId, bbox: [usize; 4]) -> Result<Tensor<3>> {
        let oc = self.cfg.object_camera(cam, bbox);
        let (ids, map) = self.splats.render_ids_with(&oc, self.field.object_features.val())?;
        Ok(cut_out(map, crop_mask(cam, &oc, bbox, &ids, id)))
    }

    /// The masked object map `[r, r, Co]` of a click at `(x, y)` with the scene's field: `(id,
    /// map)`, `None` when the pixel shows no object ([`pick`](Self::pick) + [`object_map_in`](Self::object_map_in)).
    pub fn object_map_at(&self, cam: &Camera, x: usize, y: usize) -> Result<Option<(ObjectId, Tensor<3>)>> {
        let Some((id, bbox)) = self.pick(cam, x, y)? else { return Ok(None) };
        Ok(Some((id, self.object_map_in(cam, id, bbox)?)))
    }

    /// The scene restricted to Gaussians `keep` (row indices): "model only what a scene needs".
    /// Language maps and picks use those rows; RGB renders keep every Gaussian.
    pub fn subset(&self, keep: &[usize]) -> LanguageScene {
        let dev = self.splats.means.val().device();
        let idx: Vec<i64> = keep.iter().map(|&i| i as i64).collect();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [keep.len()]), &dev);
        let rows = |t: Tensor<2>| t.select(0, idx.clone());
        let mut named = self.field.named();
        for (n, t) in named.iter_mut() {
            if n == "view_features" || n == "object_features" {
                *t = rows(t.clone());
            }
        }
        LanguageScene {
            cfg: self.cfg.clone(),
            splats: self.splats.rows(keep),
            sh_degree: self.sh_degree,
            background: self.background,
            field: LanguageField::from_named(named).expect("the same tensors"),
            display: Some(self.display.clone().unwrap_or_else(|| self.splats.clone())),
            margin: self.margin,
            masks: self.masks,
        }
    }
}

/// The `k` Gaussians with the largest language contribution (ties in index order; `k` clamped
/// to the count), as sorted row indices for [`LanguageScene::subset`]: "model only what a scene
/// needs". `contribution` `[N]`: each Gaussian's accumulated language gradient (the checkpoint's
/// `contribution`), zero for one that never reached a language map.
pub fn top_contributors(contribution: &[f32], k: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..contribution.len()).collect();
    order.sort_by(|&i, &j| contribution[j].total_cmp(&contribution[i]));
    order.truncate(k);
    order.sort_unstable();
    order
}

/// Highlights object `id` in red over a rendered RGB view (the paper's picked-object display):
/// `rgb` `[H, W, 3]`, `ids` `[H, W]`.
pub fn highlight(rgb: &[f32], ids: &[ObjectId], id: ObjectId) -> Vec<f32> {
    let mut out = rgb.to_vec();
    for (p, &i) in ids.iter().enumerate() {
        let c = &mut out[3 * p..3 * p + 3];
        if i == id {
            c[0] = 0.45 * c[0].clamp(0.0, 1.0) + 0.55;
            c[1] *= 0.45;
            c[2] *= 0.45;
        } else {
            for v in c.iter_mut() {
                *v = 0.35 * v.clamp(0.0, 1.0) + 0.2;
            }
        }
    }
    out
}

/// `k` views spread around the scene (farthest-point sampling on camera centres, starting from
/// view 0), for scene-level chat.
pub fn spread_views(cams: &[Camera], k: usize) -> Vec<usize> {
    let centres: Vec<glam::Vec3> = cams.iter().map(|c| c.world_to_cam.inverse().w_axis.truncate()).collect();
    let mut chosen = Vec::new();
    if centres.is_empty() {
        return chosen;
    }
    chosen.push(0);
    let mut dist: Vec<f32> = centres.iter().map(|c| c.distance(centres[0])).collect();
    while chosen.len() < k.min(centres.len()) {
        let (i, _) = dist.iter().enumerate().fold((0, -1.0), |b, (i, &d)| if d > b.1 { (i, d) } else { b });
        chosen.push(i);
        for (j, c) in centres.iter().enumerate() {
            dist[j] = dist[j].min(c.distance(centres[i]));
        }
    }
    chosen
}

/// The `[r, r]` 0/1 mask of object `id` in crop camera `oc` of view `cam`: pixels whose rendered
/// identity `ids` (`[r * r]`, seen from `oc`) is `id` and whose centre, back in view pixels, lies
/// inside the crop of `bbox` (as the teacher's image was cut).
fn crop_mask(cam: &Camera, oc: &Camera, bbox: [usize; 4], ids: &[ObjectId], id: ObjectId) -> Vec<f32> {
    let crop = ObjectCrop::from_box(bbox, cam.width as usize, cam.height as usize);
    let size = oc.width as usize;
    let mut mask = vec![0f32; size * size];
    for y in 0..size {
        for x in 0..size {
            // pixel centre back in view pixels
            let vx = (x as f32 + 0.5 - oc.cx) / oc.fx * cam.fx + cam.cx;
            let vy = (y as f32 + 0.5 - oc.cy) / oc.fy * cam.fy + cam.cy;
            if crop.contains(vx, vy) && ids[y * size + x] == id {
                mask[y * size + x] = 1.0;
            }
        }
    }
    mask
}

/// MaskOut of a square `[r, r, C]` object map by its `[r * r]` 0/1 mask.
fn cut_out(map: Tensor<3>, mask: Vec<f32>) -> Tensor<3> {
    let size = map.dims()[0];
    let mask = Tensor::<2>::from_data(TensorData::new(mask, [size, size]), &map.device());
    mask_out(map, mask)
}

#[cfg(test)]
mod tests {
    use super::top_contributors;

    #[test]
    fn top_contributors_keeps_the_largest_in_row_order() {
        let c = [0.5, 0.0, 2.0, 0.5, 1.0, 0.0];
        assert_eq!(top_contributors(&c, 2), vec![2, 4]);
        // a tie at the cut keeps the lower index
        assert_eq!(top_contributors(&c, 3), vec![0, 2, 4]);
        assert_eq!(top_contributors(&c, 99), vec![0, 1, 2, 3, 4, 5]);
        assert!(top_contributors(&c, 0).is_empty());
        assert!(top_contributors(&[], 3).is_empty());
    }
}
