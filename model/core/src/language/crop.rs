//! The one crop rule for objects, used by the teacher (the masked object image it encodes) and by
//! the token camera (the feature map the field renders for that object), so that every token
//! covers the same part of the picture in both.
//!
//! Rule: the object's mask bounding box grown by `margin` of its size on every side and clipped
//! to the image (`bbox`), padded to a square centred on it (`side`, the box's corner landing at
//! `offset` inside the square) of at least [`MIN_CROP_FRACTION`] of the view's shorter side, so
//! that an object keeps its apparent size (a small object stays small in its crop; only objects
//! larger than that are zoomed out to fit). The teacher's image keeps the object's pixels, blanks
//! everything else to black, and is resized from the square to the tower's input size.

use crate::ObjectId;
use crate::vlm::RgbImage;

/// The crop square is at least this fraction of the view's shorter side.
pub const MIN_CROP_FRACTION: f32 = 0.5;

/// The default margin (of the mask box's size, each side) of an object's crop: the teacher's,
/// and so the language field's and the object questions'.
pub const CROP_MARGIN: f32 = 0.1;

/// Where an object's crop lies in its view.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObjectCrop {
    /// `[x0, y0, x1, y1)` in view pixels: the mask box plus the margin, clipped to the view.
    pub bbox: [usize; 4],
    /// Side of the square the box is padded to.
    pub side: usize,
    /// Position of the box's top-left corner inside the square.
    pub offset: [usize; 2],
}

impl ObjectCrop {
    /// The crop of object `id` in an `[height, width]` id map, or `None` when it is absent.
    pub fn of(ids: &[ObjectId], width: usize, height: usize, id: ObjectId, margin: f32) -> Option<Self> {
        object_box(ids, width, height, id, margin).map(|b| Self::from_box(b, width, height))
    }

    /// The crop of a stored box in a `width` x `height` view.
    pub fn from_box(bbox: [usize; 4], width: usize, height: usize) -> Self {
        let (cw, ch) = (bbox[2].saturating_sub(bbox[0]).max(1), bbox[3].saturating_sub(bbox[1]).max(1));
        let min_side = (MIN_CROP_FRACTION * width.min(height) as f32).round() as usize;
        let side = cw.max(ch).max(min_side);
        Self { bbox, side, offset: [(side - cw) / 2, (side - ch) / 2] }
    }

    /// The square's top-left corner in view pixels (may lie left of or above the view).
    pub fn origin(&self) -> (f32, f32) {
        (self.bbox[0] as f32 - self.offset[0] as f32, self.bbox[1] as f32 - self.offset[1] as f32)
    }

    /// Whether view pixel `(x, y)` (continuous coordinates) lies inside the box.
    pub fn contains(&self, x: f32, y: f32) -> bool {
        let b = self.bbox.map(|v| v as f32);
        x >= b[0] && y >= b[1] && x < b[2] && y < b[3]
    }

    /// The teacher's image of the object: its pixels of `img` (`ids` the view's id map), black
    /// elsewhere, in the `side x side` square.
    pub fn masked_image(&self, img: &RgbImage, ids: &[ObjectId], id: ObjectId) -> RgbImage {
        let (w, side) = (img.width, self.side);
        let [bx0, by0, bx1, by1] = self.bbox;
        let [ox, oy] = self.offset;
        let mut data = vec![0u8; side * side * 3];
        for y in by0..by1 {
            for x in bx0..bx1 {
                if ids[y * w + x] == id {
                    let d = ((y - by0 + oy) * side + (x - bx0 + ox)) * 3;
                    data[d..d + 3].copy_from_slice(&img.data[(y * w + x) * 3..(y * w + x) * 3 + 3]);
                }
            }
        }
        RgbImage::new(side, side, data)
    }
}

/// The mask's bounding box plus `margin` of its size on every side, clipped to the image, as
/// `[x0, y0, x1, y1)`. `None` when `id` is absent.
pub fn object_box(ids: &[ObjectId], width: usize, height: usize, id: ObjectId, margin: f32) -> Option<[usize; 4]> {
    let (mut x0, mut y0, mut x1, mut y1) = (width, height, 0, 0);
    for y in 0..height {
        for x in 0..width {
            if ids[y * width + x] == id {
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x + 1);
                y1 = y1.max(y + 1);
            }
        }
    }
    if x1 <= x0 {
        return None;
    }
    let mx = ((x1 - x0) as f32 * margin).round() as usize;
    let my = ((y1 - y0) as f32 * margin).round() as usize;
    Some([x0.saturating_sub(mx), y0.saturating_sub(my), (x1 + mx).min(width), (y1 + my).min(height)])
}

/// The masked object image of `id` in `img` and its crop, or `None` when `id` is absent.
pub fn object_image(img: &RgbImage, ids: &[ObjectId], id: ObjectId, margin: f32) -> Option<(RgbImage, ObjectCrop)> {
    let crop = ObjectCrop::of(ids, img.width, img.height, id, margin)?;
    Some((crop.masked_image(img, ids, id), crop))
}

/// Object ids of an id map with at least `min_pixels` pixels, ascending, `ignore` left out
/// (0 = background): the objects a view has tokens for.
pub fn objects_in(ids: &[ObjectId], min_pixels: usize, ignore: &[ObjectId]) -> Vec<ObjectId> {
    pixel_counts(ids).into_iter().filter(|&(i, n)| n >= min_pixels && !ignore.contains(&i)).map(|(i, _)| i).collect()
}

/// How many pixels of an id map each id holds, by id (0 included where present).
pub fn pixel_counts(ids: &[ObjectId]) -> std::collections::BTreeMap<ObjectId, usize> {
    let mut count = std::collections::BTreeMap::new();
    for &i in ids {
        *count.entry(i).or_default() += 1;
    }
    count
}
