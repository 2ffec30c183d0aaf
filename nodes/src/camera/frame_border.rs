//! What `Refocus` takes beyond the frame's border.
//!
//! A lens gathers light from a circle of confusion around every pixel, so
//! near the frame's border the true image holds scene content that lies
//! outside the input: each aperture view of Refocus moves the image by up
//! to the blur's radius, and the strip it uncovers at the border has no
//! source. With [`FrameBorder::Edge`] (the default, and the behaviour
//! before this option) the view's hole fill takes the input's own pixel
//! there, so a blurred border continues its last row or column outward:
//! streaks that a real lens does not draw. [`FrameBorder::Reflect`]
//! extends the input by as many pixels as a view can read ([`reach_px`]):
//! its colour mirrored about the border (the border pixel once,
//! `..., 2, 1, 0, 1, 2, ...`, as image filters commonly do), its depth's
//! planes continued through the border ([`Frame::extend_depth`]: a mirror
//! would fold a slanted floor back); it renders the extended frame with
//! the same lens (the sensor widened with the frame, so the pixel pitch,
//! the image centre and every lens effect stay where they were) and crops
//! the result back.
//!
//! The extension is a guess about unseen content: right where the scene
//! continues smoothly past the border (a wall, a floor, a table), wrong
//! where an object is cut by the border (its mirror image blurs in).
//! Measured against ray-traced thin-lens truth in `docs/refocus.md`.

use depthgraph_graph::value::{DepthMap, Image};
use rayon::prelude::*;

use crate::camera::lens::{LensEffects, ThinLens};

depthgraph_graph::param_choice! {
    /// What Refocus takes beyond the frame's border (the `frame_border`
    /// parameter).
    pub enum FrameBorder {
        /// The border pixel: a view's hole at the border takes the input's
        /// own colour (blurred borders continue their last row outward).
        Edge = "edge",
        /// Colour mirrored about the border and the depth's planes
        /// continued through it, as far as a view reads, rendered and
        /// cropped away.
        Reflect = "reflect",
    }
}

/// The widest extension, as a share of the input's smaller side: the
/// extended frame holds at most `(1 + 2 * 0.25)^2 = 2.25` times the input's
/// pixels.
pub const MAX_PAD_SHARE: f64 = 0.25;

/// How a frame was extended: `pad` pixels on every side of a `w x h`
/// input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Frame {
    /// Pixels added on each side.
    pub pad: usize,
    /// The input's width.
    pub w: usize,
    /// The input's height.
    pub h: usize,
}

impl Frame {
    /// The extended frame's width and height.
    pub fn padded_dims(&self) -> (usize, usize) {
        (self.w + 2 * self.pad, self.h + 2 * self.pad)
    }

    /// Whether pixel `i` of the extended frame is one of the input's.
    pub fn holds(&self, i: usize) -> bool {
        let (pw, _) = self.padded_dims();
        let (x, y) = (i % pw.max(1), i / pw.max(1));
        (self.pad..self.pad + self.w).contains(&x) && (self.pad..self.pad + self.h).contains(&y)
    }

    /// The lens of the extended frame: the sensor widened in proportion,
    /// so the pixel pitch (and with it every circle of confusion, the
    /// image centre and the field angle of every input pixel) is the
    /// input's.
    pub fn lens(&self, lens: &ThinLens) -> ThinLens {
        // Guard: w >= 1 (a frame is only made for a non-empty input).
        let widen = (self.w + 2 * self.pad) as f64 / self.w.max(1) as f64;
        ThinLens {
            sensor_width_mm: lens.sensor_width_mm * widen,
            ..*lens
        }
    }

    /// The frame to extend a `w x h` input by `reach` pixels, or `None`
    /// when nothing reaches past the border. It extends by at most
    /// [`MAX_PAD_SHARE`] of the smaller side (the mirror repeats no pixel,
    /// and a blur wider than that would multiply the pixels, and the
    /// memory, to mirror content ever farther from what the input shows);
    /// a view reading farther meets the edge behaviour there.
    pub fn new(w: usize, h: usize, reach: usize) -> Option<Self> {
        let cap = (w.min(h) as f64 * MAX_PAD_SHARE) as usize;
        let pad = reach.min(cap).min(w.min(h).saturating_sub(1));
        (pad > 0).then_some(Self { pad, w, h })
    }

    /// `img` (the input's size) extended by mirroring about its border.
    pub fn extend<T: Copy, K>(&self, img: &Image<T, K>) -> Image<T, K> {
        let (pw, ph) = self.padded_dims();
        let src = img.as_slice();
        let pad = self.pad as isize;
        Image::from_fn(pw, ph, |x, y| {
            let (sx, sy) = (
                mirror(x as isize - pad, self.w),
                mirror(y as isize - pad, self.h),
            );
            src[sy * self.w + sx]
        })
    }

    /// `depth` (the input's size) extended past its border: the inverse
    /// depth continued through the border pixel, `v = 2 v_b - v_m` with
    /// `v_b` the border pixel's and `v_m` the mirrored pixel's (a point
    /// reflection about the border pixel), first along the columns, then
    /// along the rows of the result (the corners: a plane continued along
    /// both). A plane's inverse depth is affine in the pixel coordinates,
    /// so a floor, a wall or a table seen at an angle continues exactly
    /// where the plain mirror folds it back. Where the line from the border
    /// pixel to the mirrored one crosses a depth step (neighbours whose
    /// `|v_1 - v_2| / (v_1 + v_2)` exceeds `fill_h`, `Refocus`'s split of a
    /// foreground from a background) or a pixel without depth, or where
    /// the continuation would pass infinity (`v <= 0`), the mirrored depth
    /// stays: a point reflection across a step would invent a surface
    /// nearer than either side. Linear in the extended frame's pixels
    /// (each line's first step from either end is found once).
    pub fn extend_depth(&self, depth: &DepthMap, fill_h: f64) -> DepthMap {
        let (pw, ph) = self.padded_dims();
        let src = depth.as_slice();
        let (w, h) = (self.w, self.h);
        // the columns, extended (in parallel)
        let cols: Vec<Vec<f32>> = (0..w)
            .into_par_iter()
            .map(|x| {
                let col: Vec<f32> = (0..h).map(|y| src[y * w + x]).collect();
                continue_line(&col, self.pad, fill_h)
            })
            .collect();
        // then every row of the result (in parallel, in order)
        let data: Vec<f32> = (0..ph)
            .into_par_iter()
            .flat_map_iter(|y| {
                let row: Vec<f32> = cols.iter().map(|c| c[y]).collect();
                continue_line(&row, self.pad, fill_h)
            })
            .collect();
        debug_assert_eq!(data.len(), pw * ph);
        // (the buffer holds pw * ph values by construction)
        Image::from_vec(pw, ph, data).unwrap_or_else(|_| self.extend(depth))
    }

    /// The input's part of an extended image (the inverse of
    /// [`Frame::extend`] on the pixels it kept).
    pub fn crop<T: Copy, K>(&self, img: &Image<T, K>) -> Image<T, K> {
        let (pw, src) = (img.width(), img.as_slice());
        Image::from_fn(self.w, self.h, |x, y| {
            src[(y + self.pad) * pw + x + self.pad]
        })
    }
}

/// A line of depths extended by `pad` on each end ([`Frame::extend_depth`]):
/// the inverse depth point-reflected about the end pixel while the line
/// from the end inward stays smooth, else mirrored.
fn continue_line(line: &[f32], pad: usize, fill_h: f64) -> Vec<f32> {
    let n = line.len();
    let inv = |z: f32| {
        if DepthMap::is_valid(z) {
            // Guard: a valid depth is finite and > 0.
            1.0 / f64::from(z)
        } else {
            0.0
        }
    };
    // Guard: a + b > 0 when both are.
    let step = |a: f64, b: f64| a <= 0.0 || b <= 0.0 || (a - b).abs() / (a + b) > fill_h;
    // the first index (from each end) whose pixel is across a step from
    // the one before it: mirrored pixels nearer the end than it continue
    let smooth_from = |at: &dyn Fn(usize) -> f64| -> usize {
        (1..n).find(|&k| step(at(k - 1), at(k))).unwrap_or(n)
    };
    let head = smooth_from(&|k| inv(line[k]));
    let tail = smooth_from(&|k| inv(line[n - 1 - k]));
    let extend = |k: usize, end: usize, inner: usize, reach: usize| -> f32 {
        // k >= 1 pixels past the end pixel `end`; `inner` the mirrored one
        let m = line[inner];
        if k >= reach {
            return m;
        }
        let v = 2.0 * inv(line[end]) - inv(m);
        if v > 0.0 {
            // Guard: v > 0 checked.
            (1.0 / v) as f32
        } else {
            m
        }
    };
    let mut out = Vec::with_capacity(n + 2 * pad);
    out.extend(
        (1..=pad)
            .rev()
            .map(|k| extend(k, 0, mirror(-(k as isize), n), head)),
    );
    out.extend_from_slice(line);
    out.extend((1..=pad).map(|k| extend(k, n - 1, mirror((n - 1 + k) as isize, n), tail)));
    out
}

/// Index `i` of a line of `n` pixels mirrored about its ends without
/// repeating them (`-1 -> 1`, `n -> n - 2`); valid for `-(n - 1) <= i <=
/// 2 (n - 1)`, which [`Frame::new`]'s cap keeps.
fn mirror(i: isize, n: usize) -> usize {
    let last = n as isize - 1;
    let j = if i < 0 {
        -i
    } else if i > last {
        2 * last - i
    } else {
        i
    };
    j.clamp(0, last.max(0)) as usize
}

/// Pixels beyond the border that Refocus can read for a largest circle of
/// confusion of `max_coc` pixels (its diameter, with the blur the lens
/// effects add): a view moves a pixel by at most its radius; the one-pixel
/// margin covers the bilinear and march reads next to it. A channel
/// minified about the centre (lateral chromatic aberration, focus
/// breathing's inverse) reads `(1/M - 1)` of the half-diagonal's larger
/// side farther. 0 when nothing moves.
pub fn reach_px(max_coc: f64, fx: &LensEffects, lens: &ThinLens, w: usize, h: usize) -> usize {
    let half = 0.5 * w.max(h) as f64;
    let minify = (0..3)
        .map(|c| {
            let m = fx.magnification(lens, c);
            // Guard: m > 0 for validated effects; a non-positive or
            // non-finite m reads nothing beyond (validate rejects it).
            if m > 0.0 && m.is_finite() {
                (1.0 / m - 1.0).max(0.0)
            } else {
                0.0
            }
        })
        .fold(0.0f64, f64::max);
    let reach = 0.5 * max_coc.max(0.0) + half * minify;
    if reach.is_nan() || reach <= 0.0 {
        return 0;
    }
    if reach.is_infinite() {
        return usize::MAX; // Frame::new caps it
    }
    // (cast saturates; Frame::new caps it at the image's size)
    (reach.ceil() + 1.0) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirror_repeats_no_border_pixel() {
        let got: Vec<usize> = (-3..8).map(|i| mirror(i, 5)).collect();
        assert_eq!(got, vec![3, 2, 1, 0, 1, 2, 3, 4, 3, 2, 1]);
    }

    #[test]
    fn extend_then_crop_is_the_input_and_the_margin_mirrors_it() {
        let img: Image<u32> = Image::from_fn(5, 4, |x, y| (10 * y + x) as u32);
        let f = Frame { pad: 2, w: 5, h: 4 };
        let big = f.extend(&img);
        assert_eq!(big.dims(), (9, 8));
        // the column left of x = 0 is x = 1, the row above y = 0 is y = 1
        assert_eq!(*big.get(1, 2), *img.get(1, 0));
        assert_eq!(*big.get(2, 1), *img.get(0, 1));
        assert_eq!(*big.get(0, 0), *img.get(2, 2));
        assert_eq!(*big.get(8, 7), *img.get(2, 1));
        assert_eq!(f.crop(&big), img);
        // the input's pixels of the extended frame, and no other
        let held: Vec<usize> = (0..9 * 8).filter(|&i| f.holds(i)).collect();
        assert_eq!(held.len(), 5 * 4);
        assert!(f.holds(2 * 9 + 2) && f.holds(5 * 9 + 6));
        assert!(!f.holds(2 * 9 + 1) && !f.holds(6 * 9 + 2) && !f.holds(2 * 9 + 7));
    }

    #[test]
    fn extended_depth_continues_a_plane_and_mirrors_across_a_step() {
        // a slanted plane: inverse depth affine in x and y
        let (w, h) = (12, 9);
        let plane = DepthMap::from_fn(w, h, |x, y| {
            (1.0 / (0.5 + 0.02 * x as f64 + 0.01 * y as f64)) as f32
        });
        let f = Frame { pad: 4, w, h };
        let ext = f.extend_depth(&plane, 0.05);
        for (x, y) in [(0usize, 0usize), (1, 6), (17, 3), (19, 16), (8, 0)] {
            let (ix, iy) = (x as f64 - 4.0, y as f64 - 4.0);
            let want = 1.0 / (0.5 + 0.02 * ix + 0.01 * iy);
            let got = f64::from(*ext.get(x, y));
            assert!(
                (got - want).abs() < 1e-5 * want,
                "({x}, {y}): {got} vs {want}"
            );
        }
        // the input's own pixels keep their bits
        assert_eq!(f.crop(&ext), plane);
        // a step at the border (a near column 0 before a far wall): the
        // mirror, not a surface nearer than both sides
        let step = DepthMap::from_fn(w, h, |x, _| if x == 0 { 1.0 } else { 3.0 });
        let ext = f.extend_depth(&step, 0.05);
        assert_eq!(*ext.get(2, 5), 3.0);
        assert_eq!(*ext.get(3, 5), 3.0);
        // no depth stays no depth
        let holes = DepthMap::filled(w, h, 0.0);
        assert!(
            f.extend_depth(&holes, 0.05)
                .as_slice()
                .iter()
                .all(|z| *z == 0.0)
        );
    }

    #[test]
    fn the_pad_is_capped_at_a_quarter_of_the_smaller_side_and_none_when_nothing_reaches() {
        assert_eq!(Frame::new(100, 80, 50).map(|f| f.pad), Some(20));
        assert_eq!(Frame::new(100, 80, 7).map(|f| f.pad), Some(7));
        assert_eq!(Frame::new(100, 3, 50), None);
        assert_eq!(Frame::new(100, 12, 50).map(|f| f.pad), Some(3));
        assert_eq!(Frame::new(100, 80, 0), None);
    }

    #[test]
    fn the_widened_lens_keeps_the_pixel_pitch() {
        let lens = ThinLens {
            focal_length_mm: 50.0,
            f_number: 2.0,
            focus_m: 2.0,
            sensor_width_mm: 36.0,
        };
        let f = Frame::new(640, 480, 13).unwrap();
        let wide = f.lens(&lens);
        let (pw, _) = f.padded_dims();
        let rel = wide.coc_scale(pw) / lens.coc_scale(640) - 1.0;
        assert!(rel.abs() < 1e-12, "{rel}");
    }

    #[test]
    fn reach_is_the_blur_radius_plus_a_margin_and_grows_with_minification() {
        let lens = ThinLens {
            focal_length_mm: 50.0,
            f_number: 2.0,
            focus_m: 2.0,
            sensor_width_mm: 36.0,
        };
        let none = LensEffects::default();
        assert_eq!(reach_px(0.0, &none, &lens, 640, 480), 0);
        assert_eq!(reach_px(24.0, &none, &lens, 640, 480), 13);
        let lateral = LensEffects {
            chromatic_lateral: 0.01,
            ..LensEffects::default()
        };
        // blue is minified by 1 - 0.01: it reads (1/0.99 - 1) 320 = 3.2 px farther
        assert_eq!(reach_px(24.0, &lateral, &lens, 640, 480), 17);
    }
}
