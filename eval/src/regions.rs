//! Where a token's patch lies relative to the objects of a view, from the ground-truth instance
//! mask: the regions `token-probe` and `encoder-probe` score token error and answers by.

use model::data::synth::FIRST_OBJECT_ID;

/// A patch's place relative to the objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Region {
    /// No object pixel in the patch.
    Background,
    /// One object fills the patch.
    Inside,
    /// One object and background.
    Edge,
    /// Two objects or more.
    Contact,
}

/// Every region, in order.
pub const REGIONS: [Region; 4] = [Region::Background, Region::Inside, Region::Edge, Region::Contact];

impl Region {
    /// Whether the patch holds an object boundary (an edge or a contact).
    pub fn is_boundary(self) -> bool {
        matches!(self, Region::Edge | Region::Contact)
    }
}

/// The region of every patch of a `w`x`h` instance mask `ids` cut in `p`-pixel patches, row-major.
pub fn regions(ids: &[u8], w: usize, h: usize, p: usize) -> Vec<Region> {
    let mut out = Vec::with_capacity((w / p) * (h / p));
    for py in 0..h / p {
        for px in 0..w / p {
            let (mut objects, mut other) = (Vec::new(), false);
            for y in py * p..(py + 1) * p {
                for &i in &ids[y * w + px * p..y * w + (px + 1) * p] {
                    if i >= FIRST_OBJECT_ID {
                        if !objects.contains(&i) {
                            objects.push(i);
                        }
                    } else {
                        other = true;
                    }
                }
            }
            out.push(match (objects.len(), other) {
                (0, _) => Region::Background,
                (1, false) => Region::Inside,
                (1, true) => Region::Edge,
                _ => Region::Contact,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_patch_gets_its_region() {
        let (bg, a, b) = (0u8, FIRST_OBJECT_ID, FIRST_OBJECT_ID + 1);
        // an 8x2 mask in four 2x2 patches: table only, object a only, a beside table, a beside b
        #[rustfmt::skip]
        let ids = [
            bg, bg, a, a, a, bg, a, b,
            bg, 1, a, a, a, bg, a, b,
        ];
        let r = regions(&ids, 8, 2, 2);
        assert_eq!(r, [Region::Background, Region::Inside, Region::Edge, Region::Contact]);
        assert_eq!(r.iter().map(|r| r.is_boundary()).collect::<Vec<_>>(), [false, false, true, true]);
    }
}
