//! Regions of (assumed) constant albedo for the lighting estimate.
//!
//! The estimate assumes piecewise-constant albedo (a Retinex-style split:
//! within a region every change of brightness is shading). A region is a
//! 4-connected set of pixels on one smooth surface: neighbours join when
//! both have a depth and a normal, their depths differ by at most
//! [`RegionParams::max_depth_ratio`] (no occlusion edge between them), their
//! normals by at most [`RegionParams::max_crease_deg`] (no crease: a box's
//! faces and a floor meeting a wall are separate regions, since their
//! albedos may differ), and their rg-chromaticities by at most
//! [`RegionParams::max_chroma`] (an albedo edge changes the colour; a
//! shadow edge changes mostly the brightness: the default tolerance keeps a
//! sunlit floor and its skylit shadow together, their chromaticities differ
//! by about 0.05 under a white sun and a blue sky).
//!
//! Colours are compared after a 3x3 mean (noise does not split a surface).
//! A texture of one hue (a two-tone checkerboard) breaks the assumption:
//! its steps are shading the fit cannot explain, and its robust weights
//! reduce their pull. Splitting regions at moderate brightness steps as
//! Retinex does was tried and dropped: under a sun it also cuts the edges
//! of cast shadows, the strongest cue of the light's direction (the
//! estimate's errors on path-traced rooms grew from 4-8° to 5-52°).

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::kit::grid::neighbours4;

/// Label of pixels in no region (no depth, no normal, masked out, black).
pub const NO_REGION: u32 = u32::MAX;

/// Neighbouring depths whose ratio exceeds this lie on two surfaces (an
/// occlusion edge): the regions' default and the runs of
/// [`super::thickness`].
pub const DEPTH_STEP_RATIO: f64 = 1.04;

/// Tolerances of [`albedo_regions`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegionParams {
    /// Largest ratio of neighbouring depths on one surface.
    pub max_depth_ratio: f64,
    /// Largest angle between neighbouring normals, degrees.
    pub max_crease_deg: f64,
    /// Largest L1 difference of rg-chromaticity `(r, g) / (r + g + b)`.
    pub max_chroma: f64,
}

impl Default for RegionParams {
    fn default() -> Self {
        Self {
            max_depth_ratio: DEPTH_STEP_RATIO,
            max_crease_deg: 25.0,
            max_chroma: 0.08,
        }
    }
}

/// rg-chromaticity of a colour; `None` when it is too dark to have one
/// (sum below 1e-6: the guard of the division).
fn chroma(c: Rgb) -> Option<(f64, f64)> {
    let (r, g, b) = (f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
    let s = r + g + b;
    (s.is_finite() && s > 1e-6 && r >= 0.0 && g >= 0.0 && b >= 0.0).then(|| (r / s, g / s))
}

/// The mean colour of each usable pixel's usable 3x3 neighbourhood (the
/// tests of [`albedo_regions`] compare these, so sensor or render noise does
/// not split a surface); unusable pixels keep their colour.
fn box3(color: &ColorImage, usable: &[bool]) -> Vec<Rgb> {
    let (w, h) = color.dims();
    (0..w * h)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            if !usable[i] {
                return *color.get(x, y);
            }
            let mut acc = [0.0f64; 3];
            let mut n = 0.0f64;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    if usable[yy * w + xx] {
                        let c = color.get(xx, yy);
                        for (a, v) in acc.iter_mut().zip(c) {
                            *a += f64::from(*v);
                        }
                        n += 1.0;
                    }
                }
            }
            // guard: n >= 1 (the pixel itself is usable)
            acc.map(|a| (a / n.max(1.0)) as f32)
        })
        .collect()
}

/// Labels `0..count` of the albedo regions (module docs), [`NO_REGION`]
/// elsewhere; `normals[i]` is the unit normal of pixel `i` (`None` for a
/// hole), `usable[i]` says whether the pixel may be used at all.
pub fn albedo_regions(
    color: &ColorImage,
    depth: &DepthMap,
    normals: &[Option<DVec3>],
    usable: &[bool],
    p: &RegionParams,
) -> (Vec<u32>, usize) {
    let (w, h) = color.dims();
    let n = w * h;
    let mut label = vec![NO_REGION; n];
    let cos_crease = p.max_crease_deg.to_radians().cos();
    let smooth = box3(color, usable);
    let chromas: Vec<Option<(f64, f64)>> = smooth.iter().map(|c| chroma(*c)).collect();
    let ok = |i: usize| usable[i] && normals[i].is_some() && chromas[i].is_some();
    let joins = |a: usize, b: usize| -> bool {
        let d = depth.as_slice();
        let (za, zb) = (f64::from(d[a]), f64::from(d[b]));
        // guard: both depths are valid (> 0) for usable pixels
        if !(za > 0.0 && zb > 0.0) || za.max(zb) / za.min(zb) > p.max_depth_ratio {
            return false;
        }
        let (Some(na), Some(nb)) = (normals[a], normals[b]) else {
            return false;
        };
        if na.dot(nb) < cos_crease {
            return false;
        }
        let (Some(ca), Some(cb)) = (chromas[a], chromas[b]) else {
            return false;
        };
        (ca.0 - cb.0).abs() + (ca.1 - cb.1).abs() <= p.max_chroma
    };
    let mut count = 0u32;
    let mut stack = Vec::new();
    for seed in 0..n {
        if label[seed] != NO_REGION || !ok(seed) {
            continue;
        }
        label[seed] = count;
        stack.push(seed);
        while let Some(i) = stack.pop() {
            for j in neighbours4(i, w, h) {
                if label[j] == NO_REGION && ok(j) && joins(i, j) {
                    label[j] = count;
                    stack.push(j);
                }
            }
        }
        count += 1;
    }
    (label, count as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two grey planes meeting at a crease and a red patch on one of them
    /// make three regions; a darker (shadowed) band of the same grey stays
    /// in its plane's region.
    #[test]
    fn creases_and_colours_split_shadows_do_not() {
        let (w, h) = (40, 20);
        let color = ColorImage::from_fn(w, h, |x, y| {
            if (3..13).contains(&x) && (3..13).contains(&y) {
                [0.6, 0.1, 0.1]
            } else if (15..18).contains(&x) {
                [0.1, 0.1, 0.11] // shadow band, slightly bluer
            } else {
                [0.5, 0.5, 0.5]
            }
        });
        let depth = DepthMap::filled(w, h, 2.0);
        let normals: Vec<Option<DVec3>> = (0..w * h)
            .map(|i| {
                Some(if i % w < 20 {
                    DVec3::NEG_Z
                } else {
                    DVec3::NEG_Y
                })
            })
            .collect();
        let usable = vec![true; w * h];
        let (l, count) =
            albedo_regions(&color, &depth, &normals, &usable, &RegionParams::default());
        // three regions of 10 pixels or more (the 3x3 mean leaves seams of
        // mixed colour round the patch, in regions of their own)
        let mut sizes = vec![0usize; count];
        for v in &l {
            sizes[*v as usize] += 1;
        }
        assert_eq!(sizes.iter().filter(|n| **n >= 10).count(), 3, "{sizes:?}");
        assert_eq!(l[0], l[16]); // shadow band joins its plane
        assert_ne!(l[0], l[7 * w + 7]); // the red patch
        assert_ne!(l[0], l[30]); // across the crease
    }
}
