//! Partial occlusion at depth edges: a second, background layer behind the
//! foreground edges of an RGB-D image, for [`crate::camera::refocus`].
//!
//! # Why a second layer
//!
//! A lens of finite aperture sees around what is in front: a pixel on a
//! blurred foreground edge receives, through part of the aperture, light
//! from the background behind that edge (the blurred edge becomes a
//! semi-transparent veil over the background), and a blurred background
//! shows through the gaps around thin in-focus structures. One depth layer
//! has nothing behind its foreground. `Refocus` renders the image from
//! points `s` of the aperture; in the view from `s` a pixel of inverse depth
//! `v` moves by `C s (1/u - v)` (see [`crate::camera::lens`]), so against a
//! farther pixel of inverse depth `v_b` a foreground pixel moves by
//! `C |s| (v - v_b)` more: the background behind the foreground is revealed
//! up to
//!
//! `reach(v, v_b) = C e (v - v_b)`  pixels  (`e` = the aperture's extent,
//! 1/2 for a disc)
//!
//! inside the foreground's edge. The depth-blur paper fills what a view
//! reveals by inpainting from the background ("holes that occur due to a
//! changed viewpoint are most probably to be filled extending the adjacent
//! background", Sec. 2.3, with eq. 5's weights scaled by the squared depth).
//! Done per view (the per-view fill of `Refocus`) every view invents its own
//! background, streaked along its own direction. This module inpaints it
//! once, before any view: the layer holds, for every foreground pixel within
//! `reach` of a farther surface, a colour and a depth inpainted from that
//! surface's side only, and every view warps it with the image through the
//! same z-buffer, where the foreground covers it except where it has moved
//! away. Every view then sees the same background behind an edge, as a real
//! lens does.
//!
//! # The inpainting
//!
//! For a pixel `p` (inverse depth `v_p`) the layer marches [`DIRECTIONS`]
//! directions outward to the first pixel `q` that is farther by more than
//! the relative threshold `fill_h` (as `Refocus`'s hole fill:
//! `(v_p - v_q) / (v_p + v_q) > fill_h`), passing over nearer or equal
//! pixels. A `q` found within `reach(v_p, v_q) + 1` pixels is a background
//! sample, weighted with the far-depth prior of eq. 5 and by inverse
//! distance, `w = (v_far / v_q)^2 / d`, where `d` is the distance marched
//! and `v_far` the smallest inverse depth among the samples (the farthest
//! background dominates). The layer's colour and inverse depth are the
//! weighted means (f64). A pixel without a sample has no layer entry.
//! Inverse-distance weights interpolate between the two sides of a thin
//! structure linearly (`(L/a + R/b) / (1/a + 1/b)` is the linear
//! interpolation at distances `a` and `b`), so a smooth background is
//! continued behind it; `1/d^2` and uniform weights measured worse (the
//! `refocus` bench's partial-occlusion table and the two-plane test in
//! `refocus`).
//!
//! # Texture behind the edge ([`LayerParams::texture`])
//!
//! Interpolation continues a smooth background but not a textured one: a
//! checker behind a thin pole comes out as a grey smear. With `texture`
//! on, the layer's colour is copied from elsewhere in the background along
//! one of the background's **dominant patch offsets**, after He and Sun,
//! "Statistics of Patch Offsets for Image Completion" (ECCV 2012): a
//! regular or repeating texture matches itself under a few offsets (its
//! periods), and those are the ones that continue it across a gap.
//!
//! 1. *Statistics*: at up to [`OFFSET_SAMPLES`] background pixels next to
//!    the foreground (the samples the march found), the offset `o`
//!    (`|o|_∞` from [`MIN_OFFSET`] to [`OFFSET_RADIUS`]) whose
//!    `(2·STAT_PATCH+1)²` patch of clamped luminance matches best (mean
//!    squared difference over the pixels of the same depth band in both
//!    patches, at least half the patch) is counted; the [`OFFSETS`] most
//!    counted offsets are kept (each at least twice).
//! 2. *Choice*: each layer pixel `p` of inverse depth `v` takes the offset
//!    whose source `p + o` is background of the same band (not a layer
//!    pixel, `v` and `v_q` not `farther` from each other) and whose
//!    neighbourhood (radius [`MATCH_RADIUS`]) matches `p`'s known
//!    background best (clamped colour, mean squared difference over at
//!    least [`MIN_MATCHED`] pixels known around both), and copies its
//!    colour where that mismatch is below [`TEXTURE_GAIN`] times the
//!    spread of `p`'s known background about its mean (a texture the
//!    offset continues), each channel kept within the range of `p`'s known
//!    background (as it is, not clamped): a glint or an emitter matches as
//!    white in clamped colours but is not the texture, and copied behind an
//!    edge it would blur into a bright ghost. A pixel with no such offset keeps the
//!    interpolated colour, as does a smooth background;
//!    the depth stays the interpolated one either way (a plane is
//!    continued exactly by interpolation).

use depthgraph_graph::value::Rgb;
use rayon::prelude::*;

use crate::camera::frame_border::Frame;
use crate::kit::color::luminance_f64;
use crate::kit::grid::round_to_pixel;

/// Directions marched from every candidate pixel (evenly spaced angles).
pub const DIRECTIONS: usize = 16;
/// Largest reach in pixels that the layer extends behind an edge (a bound
/// on the work of a huge circle of confusion; beyond it the per-view fill
/// of `Refocus` takes over).
pub const MAX_REACH_PX: usize = 256;
/// Background pixels whose best offset is counted ([`LayerParams::texture`]).
pub const OFFSET_SAMPLES: usize = 1500;
/// Largest offset searched, pixels (`|o|_∞`).
pub const OFFSET_RADIUS: i64 = 24;
/// Smallest offset searched, pixels (`|o|_∞`): nearer offsets only say that
/// the background is smooth, which interpolation already continues.
pub const MIN_OFFSET: i64 = 3;
/// Half-size of the patches of the offset statistics.
pub const STAT_PATCH: i64 = 2;
/// Dominant offsets kept.
pub const OFFSETS: usize = 12;
/// Radius of the neighbourhood compared when a layer pixel picks its offset.
pub const MATCH_RADIUS: i64 = 4;
/// Fewest pixels known around both ends for an offset to be compared.
pub const MIN_MATCHED: usize = 6;
/// A copy replaces the interpolated colour only where its neighbourhood's
/// mismatch is below this fraction of the known background's spread
/// around its mean there (a texture the offset continues; a smooth
/// background keeps the interpolation).
pub const TEXTURE_GAIN: f64 = 1.0;

/// Inputs of [`background_layer`] besides the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerParams {
    /// `C e` of `reach(v, v_b) = C e (v - v_b)`: pixel metres (the circle of
    /// confusion's scale times the aperture's extent).
    pub reach_scale: f64,
    /// Relative inverse-depth step that separates a foreground from a
    /// background (`Refocus`'s `fill_h`).
    pub fill_h: f64,
    /// Continue the background's texture along its dominant patch offsets
    /// instead of only interpolating its colour (module docs).
    pub texture: bool,
    /// When the image is an input extended past its border (`Refocus`'s
    /// `frame_border`), the extension: the texture's statistics and sources
    /// are the input's own pixels only (a mirror does not continue a
    /// periodic texture; its copies would carry the mirror's flip into the
    /// frame).
    pub frame: Option<Frame>,
}

/// The background layer: the pixels that have something behind them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BackgroundLayer {
    /// Pixel index (`y * w + x`) of each entry, increasing.
    pub pixels: Vec<u32>,
    /// Inpainted linear colour of each entry.
    pub color: Vec<Rgb>,
    /// Inpainted inverse depth of each entry (1/m; 0 = infinitely far).
    pub inv_z: Vec<f64>,
    /// Entries whose colour was copied along a dominant offset
    /// ([`LayerParams::texture`]; 0 without it).
    pub textured: usize,
}

impl BackgroundLayer {
    /// Number of entries.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// True when no pixel has a background entry.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }
}

/// True when `v_b` is a background to `v` (see the module docs).
fn farther(v: f64, v_b: f64, fill_h: f64) -> bool {
    let s = v + v_b;
    // Guard: s > 0 whenever v > v_b >= 0.
    v > v_b && s > 0.0 && (v - v_b) / s > fill_h
}

/// Minimum of `v` over a `(2r+1)^2` square around every pixel (separable).
fn window_min(v: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let rows: Vec<f64> = v
        .par_chunks(w)
        .flat_map_iter(|row| {
            (0..w).map(move |x| {
                row[x.saturating_sub(r)..(x + r + 1).min(w)]
                    .iter()
                    .fold(f64::INFINITY, |m, &a| m.min(a))
            })
        })
        .collect();
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            (y.saturating_sub(r)..(y + r + 1).min(h))
                .fold(f64::INFINITY, |m, yy| m.min(rows[yy * w + x]))
        })
        .collect()
}

/// The background layer of an image (see the module docs), for the pixels
/// whose `want` flag is set. `color` and `inv_z` are `w * h` long, row by
/// row; inverse depths are finite and `>= 0`.
pub fn background_layer(
    w: usize,
    h: usize,
    color: &[Rgb],
    inv_z: &[f64],
    want: &[bool],
    p: &LayerParams,
) -> BackgroundLayer {
    let n = w * h;
    if n == 0 || color.len() != n || inv_z.len() != n || want.len() != n {
        return BackgroundLayer::default();
    }
    let (v_min, v_max) = inv_z.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
        (lo.min(v), hi.max(v))
    });
    let span = p.reach_scale * (v_max - v_min);
    if span.is_nan() || span < 0.5 || !p.reach_scale.is_finite() {
        // No edge can reveal half a pixel (or the scale is unusable).
        return BackgroundLayer::default();
    }
    // (the cast saturates at usize::MAX for a huge or infinite span: the
    // + 1 must not overflow)
    let r = (span.ceil() as usize).saturating_add(1).min(MAX_REACH_PX);
    // Candidates: some pixel within the window is a background and the
    // step reveals at least half a pixel.
    let near_min = window_min(inv_z, w, h, r);
    let dirs: Vec<[f64; 2]> = (0..DIRECTIONS)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / DIRECTIONS as f64;
            let (c, s) = (a.cos(), a.sin());
            // Unit step along the major axis (a DDA); max(|c|, |s|) >= 1/sqrt 2.
            let m = c.abs().max(s.abs());
            [c / m, s / m]
        })
        .collect();
    let entries: Vec<(u32, Rgb, f64, Option<u32>)> = (0..n)
        .into_par_iter()
        .filter(|&i| {
            want[i]
                && farther(inv_z[i], near_min[i], p.fill_h)
                && p.reach_scale * (inv_z[i] - near_min[i]) >= 0.5
        })
        .filter_map(|i| {
            let v = inv_z[i];
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            // A background at inverse depth >= 0 is revealed at most this far.
            let limit = (p.reach_scale * v + 1.0).min(r as f64 + 1.0);
            let mut samples: Vec<(usize, f64)> = Vec::with_capacity(DIRECTIONS);
            for d in &dirs {
                let len = (d[0] * d[0] + d[1] * d[1]).sqrt();
                let mut k = 1.0;
                while k * len <= limit {
                    let (Some(qx), Some(qy)) = (
                        round_to_pixel(x + k * d[0], w),
                        round_to_pixel(y + k * d[1], h),
                    ) else {
                        break;
                    };
                    let q = qy * w + qx;
                    if farther(v, inv_z[q], p.fill_h) {
                        let dist = k * len;
                        if dist <= p.reach_scale * (v - inv_z[q]) + 1.0 {
                            samples.push((q, dist));
                        }
                        break;
                    }
                    k += 1.0;
                }
            }
            if samples.is_empty() {
                return None;
            }
            let v_far = samples
                .iter()
                .map(|&(q, _)| inv_z[q])
                .fold(f64::INFINITY, f64::min);
            let (mut ws, mut cs, mut zs) = (0.0f64, [0.0f64; 3], 0.0f64);
            for &(q, dist) in &samples {
                let vq = inv_z[q];
                // Guards: dist >= 1 (the march starts a step out); vq > 0 in
                // the division, and the sky (vq = 0) is as far as it gets.
                let prior = if vq > 0.0 { (v_far / vq).powi(2) } else { 1.0 };
                let wt = prior / dist;
                ws += wt;
                for (a, c) in cs.iter_mut().zip(color[q]) {
                    *a += wt * c as f64;
                }
                zs += wt * vq;
            }
            // Guard: the farthest sample has prior 1 and dist <= limit, so
            // ws >= 1 / limit > 0; a non-finite sum keeps no entry.
            if !(ws > 0.0 && ws.is_finite()) {
                return None;
            }
            // the nearest sample: a background pixel next to the edge
            let nearest = samples
                .iter()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|&(q, _)| q as u32);
            Some((i as u32, cs.map(|a| (a / ws) as f32), zs / ws, nearest))
        })
        .collect();
    let mut layer = BackgroundLayer {
        pixels: Vec::with_capacity(entries.len()),
        color: Vec::with_capacity(entries.len()),
        inv_z: Vec::with_capacity(entries.len()),
        textured: 0,
    };
    let mut ring: Vec<u32> = Vec::new();
    for (i, c, v, q) in entries {
        layer.pixels.push(i);
        layer.color.push(c);
        layer.inv_z.push(v);
        ring.extend(q);
    }
    if p.texture && !layer.is_empty() {
        ring.sort_unstable();
        ring.dedup();
        if let Some(f) = &p.frame {
            ring.retain(|&i| f.holds(i as usize));
        }
        continue_texture(w, h, color, inv_z, &ring, p, &mut layer);
    }
    layer
}

/// The same depth band: neither inverse depth is a background to the other.
fn same_band(a: f64, b: f64, fill_h: f64) -> bool {
    !farther(a, b, fill_h) && !farther(b, a, fill_h)
}

/// A colour for patch comparisons: clamped to the display range, so a
/// bright emitter weighs no more than white.
fn clamped(c: Rgb) -> [f64; 3] {
    c.map(|v| f64::from(v).clamp(0.0, 1.0))
}

/// The dominant offsets of the background around `ring` (module docs, step
/// 1), most counted first; `known[i]`: pixel `i` is not a layer pixel.
fn dominant_offsets(
    w: usize,
    h: usize,
    lum: &[f64],
    inv_z: &[f64],
    known: &[bool],
    ring: &[u32],
    fill_h: f64,
) -> Vec<[i64; 2]> {
    let (wi, hi) = (w as i64, h as i64);
    let step = ring.len().div_ceil(OFFSET_SAMPLES).max(1);
    let side = 2 * OFFSET_RADIUS + 1;
    let best: Vec<Option<usize>> = ring
        .par_iter()
        .step_by(step)
        .map(|&q| {
            let q = q as usize;
            let (qx, qy) = ((q % w) as i64, (q / w) as i64);
            let vq = inv_z[q];
            // the patch's pixels of q's band
            let patch: Vec<(i64, i64, f64)> = (-STAT_PATCH..=STAT_PATCH)
                .flat_map(|dy| (-STAT_PATCH..=STAT_PATCH).map(move |dx| (dx, dy)))
                .filter_map(|(dx, dy)| {
                    let (x, y) = (qx + dx, qy + dy);
                    if x < 0 || y < 0 || x >= wi || y >= hi {
                        return None;
                    }
                    let i = (y * wi + x) as usize;
                    (known[i] && same_band(vq, inv_z[i], fill_h)).then_some((dx, dy, lum[i]))
                })
                .collect();
            let need = (2 * STAT_PATCH + 1).pow(2) as usize / 2;
            if patch.len() < need {
                return None;
            }
            let mut best: Option<(f64, usize)> = None;
            for oy in -OFFSET_RADIUS..=OFFSET_RADIUS {
                for ox in -OFFSET_RADIUS..=OFFSET_RADIUS {
                    if ox.abs().max(oy.abs()) < MIN_OFFSET {
                        continue;
                    }
                    let (mut sum, mut m) = (0.0f64, 0usize);
                    for &(dx, dy, l) in &patch {
                        let (x, y) = (qx + ox + dx, qy + oy + dy);
                        if x < 0 || y < 0 || x >= wi || y >= hi {
                            continue;
                        }
                        let i = (y * wi + x) as usize;
                        if known[i] && same_band(vq, inv_z[i], fill_h) {
                            sum += (lum[i] - l).powi(2);
                            m += 1;
                        }
                    }
                    if m < need {
                        continue;
                    }
                    // Guard: m >= need >= 1.
                    let e = sum / m as f64;
                    if best.is_none_or(|(b, _)| e < b) {
                        best = Some((
                            e,
                            ((oy + OFFSET_RADIUS) * side + ox + OFFSET_RADIUS) as usize,
                        ));
                    }
                }
            }
            best.map(|(_, k)| k)
        })
        .collect();
    let mut count = vec![0usize; (side * side) as usize];
    for k in best.into_iter().flatten() {
        count[k] += 1;
    }
    let mut ranked: Vec<(usize, usize)> = count
        .into_iter()
        .enumerate()
        .filter(|&(_, c)| c >= 2)
        .map(|(k, c)| (c, k))
        .collect();
    // most counted first; ties by the offset's index (deterministic)
    ranked.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    ranked
        .into_iter()
        .take(OFFSETS)
        .map(|(_, k)| {
            let k = k as i64;
            [k % side - OFFSET_RADIUS, k / side - OFFSET_RADIUS]
        })
        .collect()
}

/// Step 2 of the module docs: every layer pixel's colour copied along the
/// best-matching dominant offset, where one fits (statistics and sources
/// from the input's own pixels, [`LayerParams::frame`]).
fn continue_texture(
    w: usize,
    h: usize,
    color: &[Rgb],
    inv_z: &[f64],
    ring: &[u32],
    p: &LayerParams,
    layer: &mut BackgroundLayer,
) {
    let fill_h = p.fill_h;
    // the input's own pixels (not the extension past its border)
    let mut known: Vec<bool> = match &p.frame {
        Some(f) => (0..w * h).map(|i| f.holds(i)).collect(),
        None => vec![true; w * h],
    };
    for &i in &layer.pixels {
        known[i as usize] = false;
    }
    let lum: Vec<f64> = color
        .par_iter()
        .map(|&c| luminance_f64(clamped(c)))
        .collect();
    let offsets = dominant_offsets(w, h, &lum, inv_z, &known, ring, fill_h);
    if offsets.is_empty() {
        return;
    }
    let (wi, hi) = (w as i64, h as i64);
    let at = |x: i64, y: i64| -> Option<usize> {
        (x >= 0 && y >= 0 && x < wi && y < hi).then(|| (y * wi + x) as usize)
    };
    let copied: Vec<Option<Rgb>> = layer
        .pixels
        .par_iter()
        .zip(layer.inv_z.par_iter())
        .map(|(&i, &v)| {
            let i = i as usize;
            let (px, py) = ((i % w) as i64, (i / w) as i64);
            let band = |j: usize| known[j] && same_band(v, inv_z[j], fill_h);
            // p's known background around it (offset, clamped colour), read
            // once for the spread and for every offset's match
            let near: Vec<(i64, i64, [f64; 3], Rgb)> = (-MATCH_RADIUS..=MATCH_RADIUS)
                .flat_map(|dy| (-MATCH_RADIUS..=MATCH_RADIUS).map(move |dx| (dx, dy)))
                .filter_map(|(dx, dy)| {
                    let a = at(px + dx, py + dy).filter(|&a| band(a))?;
                    Some((dx, dy, clamped(color[a]), color[a]))
                })
                .collect();
            let n0 = near.len();
            if n0 < MIN_MATCHED {
                return None;
            }
            // the range of p's known background, per channel (as it is, not
            // clamped): what the copy may bring (module docs, step 2)
            let mut range = [[f32::INFINITY, f32::NEG_INFINITY]; 3];
            for (_, _, _, c) in &near {
                for k in 0..3 {
                    range[k][0] = range[k][0].min(c[k]);
                    range[k][1] = range[k][1].max(c[k]);
                }
            }
            // the spread of p's known background: what the mean (about what
            // interpolation gives) misses
            let (mut s1, mut s2) = ([0.0f64; 3], 0.0f64);
            for (_, _, c, _) in &near {
                for k in 0..3 {
                    s1[k] += c[k];
                    s2 += c[k] * c[k];
                }
            }
            // Guard: n0 >= MIN_MATCHED >= 1.
            let spread = (s2 - s1.iter().map(|t| t * t).sum::<f64>() / n0 as f64) / n0 as f64;
            let mut best: Option<(f64, usize)> = None;
            for o in &offsets {
                let Some(src) = at(px + o[0], py + o[1]) else {
                    continue;
                };
                if !band(src) {
                    continue;
                }
                let (mut sum, mut m) = (0.0f64, 0usize);
                for (dx, dy, ca, _) in &near {
                    if let Some(b) = at(px + o[0] + dx, py + o[1] + dy).filter(|&b| band(b)) {
                        let cb = clamped(color[b]);
                        sum += (0..3).map(|k| (ca[k] - cb[k]).powi(2)).sum::<f64>();
                        m += 1;
                    }
                }
                if m < MIN_MATCHED {
                    continue;
                }
                // Guard: m >= MIN_MATCHED >= 1.
                let e = sum / m as f64;
                if best.is_none_or(|(b, _)| e < b) {
                    best = Some((e, src));
                }
            }
            // a texture the offset predicts well beyond its mean
            best.filter(|&(e, _)| e < TEXTURE_GAIN * spread)
                .map(|(_, src)| {
                    let c = color[src];
                    // guard: a channel without a finite value nearby keeps the copy's
                    std::array::from_fn(|k| {
                        let [lo, hi] = range[k];
                        if lo <= hi { c[k].max(lo).min(hi) } else { c[k] }
                    })
                })
        })
        .collect();
    for (c, new) in layer.color.iter_mut().zip(copied) {
        if let Some(new) = new {
            *c = new;
            layer.textured += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A near bar (columns 10..14, 1 m) over a far wall (2 m) whose columns
    /// are coloured by their x.
    fn bar_scene(w: usize, h: usize) -> (Vec<Rgb>, Vec<f64>) {
        let mut color = vec![[0.0f32; 3]; w * h];
        let mut inv_z = vec![0.5f64; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if (10..14).contains(&x) {
                    color[i] = [1.0, 0.0, 0.0];
                    inv_z[i] = 1.0;
                } else {
                    color[i] = [0.0, x as f32 / w as f32, 0.5];
                }
            }
        }
        (color, inv_z)
    }

    /// The layer of the bar scene with every pixel wanted.
    fn bar_layer(reach_scale: f64) -> (usize, BackgroundLayer) {
        let (w, h) = (30, 8);
        let (color, inv_z) = bar_scene(w, h);
        let p = LayerParams {
            reach_scale,
            fill_h: 0.05,
            texture: false,
            frame: None,
        };
        (
            w,
            background_layer(w, h, &color, &inv_z, &vec![true; w * h], &p),
        )
    }

    /// A reach past usize (a depth of 1e-19 m under the default lens) is
    /// capped like any large one: `span as usize + 1` overflowed (a panic
    /// in a debug build, an empty layer in release).
    #[test]
    fn an_enormous_reach_is_capped_not_overflowed() {
        let (_, capped) = bar_layer(1e40);
        let (_, large) = bar_layer(1e6);
        assert!(!large.is_empty());
        assert_eq!(capped.pixels, large.pixels);
    }

    #[test]
    fn a_thin_bar_gets_the_background_of_both_sides() {
        // reach = 20 * 0.5 = 10 px: the whole bar is within reach.
        let (w, layer) = bar_layer(20.0);
        let h = 8;
        // Exactly the bar's pixels, each with the wall's depth and no red.
        assert_eq!(layer.len(), 4 * h);
        for (k, &i) in layer.pixels.iter().enumerate() {
            let x = i as usize % w;
            assert!((10..14).contains(&x), "entry at x = {x}");
            assert!((layer.inv_z[k] - 0.5).abs() < 1e-12);
            assert_eq!(layer.color[k][0], 0.0, "foreground colour leaked in");
            // Green lies between the two sides' green (9 / 30 and 14 / 30),
            // nearer the closer side.
            let g = layer.color[k][1] as f64;
            assert!(g > 9.0 / 30.0 - 1e-6 && g < 14.0 / 30.0 + 1e-6, "g = {g}");
            if x == 10 {
                assert!(g < 11.5 / 30.0, "x = 10 should lean left: {g}");
            }
            if x == 13 {
                assert!(g > 11.5 / 30.0, "x = 13 should lean right: {g}");
            }
        }
    }

    #[test]
    fn the_layer_reaches_only_as_far_as_a_view_reveals() {
        let h = 8;
        // reach = 2 * 0.5 = 1 px, + 1 px of rounding: columns 10..14 are at
        // 1 or 2 px from the wall.
        let (w, layer) = bar_layer(2.0);
        let xs: Vec<usize> = layer.pixels.iter().map(|&i| i as usize % w).collect();
        assert!(xs.iter().all(|x| (10..14).contains(x)));
        assert_eq!(layer.len(), 4 * h);
        // reach 0.6 + 1 = 1.6 px: only the bar's edge columns.
        let (w, layer) = bar_layer(1.2);
        let xs: Vec<usize> = layer.pixels.iter().map(|&i| i as usize % w).collect();
        assert_eq!(layer.len(), 2 * h);
        assert!(xs.iter().all(|&x| x == 10 || x == 13));
    }

    /// A grey checker wall (2 m, squares of `period` px) behind a near bar
    /// (columns 20..24, 1 m): the truth behind the bar is the checker.
    fn checker_scene(w: usize, h: usize, period: usize) -> (Vec<Rgb>, Vec<f64>, Vec<Rgb>) {
        let mut color = vec![[0.0f32; 3]; w * h];
        let mut inv_z = vec![0.5f64; w * h];
        let mut truth = vec![[0.0f32; 3]; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let g = if (x / period + y / period).is_multiple_of(2) {
                    0.8
                } else {
                    0.1
                };
                truth[i] = [g; 3];
                if (20..24).contains(&x) {
                    color[i] = [1.0, 0.0, 0.0];
                    inv_z[i] = 1.0;
                } else {
                    color[i] = [g; 3];
                }
            }
        }
        (color, inv_z, truth)
    }

    /// The layer with every pixel wanted, reach scale 20, with or without
    /// the texture.
    fn layer_of(
        w: usize,
        h: usize,
        color: &[Rgb],
        inv_z: &[f64],
        texture: bool,
    ) -> BackgroundLayer {
        let p = LayerParams {
            reach_scale: 20.0,
            fill_h: 0.05,
            texture,
            frame: None,
        };
        background_layer(w, h, color, inv_z, &vec![true; w * h], &p)
    }

    /// A bright emitter in the texture (a lamp's glint on a white square)
    /// matches as white (the patches compare clamped colours), but it is
    /// not the texture: a copy brings no colour outside the range of the
    /// background around the pixel it fills.
    #[test]
    fn texture_copies_no_emitter_behind_a_thin_bar() {
        let (w, h) = (64, 40);
        let (mut color, inv_z, truth) = checker_scene(w, h, 6);
        // a glint at the centre of every bright square
        let mut glints = 0;
        for y in (0..h).filter(|y| y % 6 == 3) {
            for x in (0..w).filter(|x| x % 6 == 3 && !(20..24).contains(x)) {
                let i = y * w + x;
                if truth[i][1] > 0.5 {
                    color[i] = [40.0; 3];
                    glints += 1;
                }
            }
        }
        assert!(glints > 10);
        let tex = layer_of(w, h, &color, &inv_z, true);
        assert!(
            tex.textured * 10 >= tex.len() * 9,
            "{} of {} copied",
            tex.textured,
            tex.len()
        );
        let brightest = tex.color.iter().flatten().fold(0.0f32, |m, v| m.max(*v));
        assert!(
            brightest <= 0.8,
            "a glint copied behind the bar: {brightest}"
        );
        let err = tex
            .pixels
            .iter()
            .zip(&tex.color)
            .map(|(&i, c)| (f64::from(c[1]) - f64::from(truth[i as usize][1])).abs())
            .sum::<f64>()
            / tex.len() as f64;
        assert!(err < 0.05, "the checker continued: mean error {err}");
    }

    #[test]
    fn texture_continues_a_checker_behind_a_thin_bar() {
        let (w, h) = (64, 40);
        let (color, inv_z, truth) = checker_scene(w, h, 6);
        let (plain, tex) = (
            layer_of(w, h, &color, &inv_z, false),
            layer_of(w, h, &color, &inv_z, true),
        );
        assert_eq!(plain.pixels, tex.pixels);
        assert_eq!(plain.inv_z, tex.inv_z, "the depth stays interpolated");
        assert_eq!(plain.textured, 0);
        let err = |l: &BackgroundLayer| -> f64 {
            l.pixels
                .iter()
                .zip(&l.color)
                .map(|(&i, c)| (f64::from(c[1]) - f64::from(truth[i as usize][1])).abs())
                .sum::<f64>()
                / l.len() as f64
        };
        let (e_plain, e_tex) = (err(&plain), err(&tex));
        assert!(
            tex.textured * 10 >= tex.len() * 9,
            "{} of {} copied",
            tex.textured,
            tex.len()
        );
        assert!(e_plain > 0.1, "interpolation smears the checker: {e_plain}");
        assert!(
            e_tex < 0.1 * e_plain,
            "texture {e_tex}, interpolation {e_plain}"
        );
    }

    /// An input extended past its border by a mirror (`frame_border`
    /// reflect): the mirror flips the checker at the border, so copies from
    /// the extension would carry the flip into the frame; with the frame
    /// given, the layer inside the input is continued from the input alone,
    /// as well as without any extension.
    #[test]
    fn an_extended_frame_takes_its_texture_from_the_input_alone() {
        use depthgraph_graph::value::Image;
        // the checker scene's columns 14.. : the bar at 6..10, near the border
        let (w0, h) = (64, 40);
        let (color0, inv_z0, truth0) = checker_scene(w0, h, 6);
        let w = w0 - 14;
        let cols =
            |v: &[Rgb]| -> Vec<Rgb> { (0..w * h).map(|i| v[(i / w) * w0 + 14 + i % w]).collect() };
        let (color, truth) = (cols(&color0), cols(&truth0));
        let inv_z: Vec<f64> = (0..w * h)
            .map(|i| inv_z0[(i / w) * w0 + 14 + i % w])
            .collect();
        let f = Frame { pad: 12, w, h };
        let (Ok(c), Ok(v)) = (
            Image::<Rgb>::from_vec(w, h, color.clone()),
            Image::<f64>::from_vec(w, h, inv_z.clone()),
        ) else {
            panic!("sizes");
        };
        let (c, v) = (f.extend(&c), f.extend(&v));
        let (pw, ph) = f.padded_dims();
        let layer = |frame: Option<Frame>| {
            let p = LayerParams {
                reach_scale: 20.0,
                fill_h: 0.05,
                texture: true,
                frame,
            };
            background_layer(pw, ph, c.as_slice(), v.as_slice(), &vec![true; pw * ph], &p)
        };
        // mean |error| of green over the entries inside the input, each
        // entry's input index given by `at`
        let err = |l: &BackgroundLayer, at: &dyn Fn(usize) -> Option<usize>| -> f64 {
            let e: Vec<f64> = l
                .pixels
                .iter()
                .zip(&l.color)
                .filter_map(|(&i, c)| {
                    let j = at(i as usize)?;
                    Some((f64::from(c[1]) - f64::from(truth[j][1])).abs())
                })
                .collect();
            assert!(!e.is_empty());
            e.iter().sum::<f64>() / e.len() as f64
        };
        let padded = |i: usize| f.holds(i).then(|| (i / pw - f.pad) * w + i % pw - f.pad);
        let reference = err(&layer_of(w, h, &color, &inv_z, true), &|i| Some(i));
        let (given, ignored) = (err(&layer(Some(f)), &padded), err(&layer(None), &padded));
        eprintln!("reference {reference:.4}, frame given {given:.4}, ignored {ignored:.4}");
        assert!(given <= reference + 1e-3, "{given} vs {reference}");
        assert!(ignored > given + 0.01, "{ignored} vs {given}");
    }

    #[test]
    fn texture_keeps_the_interpolation_of_a_smooth_background() {
        // the bar scene's wall changes smoothly with x: nothing to continue
        let (w, h) = (30, 8);
        let (color, inv_z) = bar_scene(w, h);
        let (plain, tex) = (
            layer_of(w, h, &color, &inv_z, false),
            layer_of(w, h, &color, &inv_z, true),
        );
        assert_eq!(tex.textured, 0);
        assert_eq!(plain, tex);
    }

    #[test]
    fn a_flat_image_or_a_tiny_reach_has_no_layer() {
        let (w, h) = (12, 6);
        let color = vec![[0.5f32; 3]; w * h];
        let flat = vec![0.5f64; w * h];
        let want = vec![true; w * h];
        let p = LayerParams {
            reach_scale: 50.0,
            fill_h: 0.05,
            texture: false,
            frame: None,
        };
        assert!(background_layer(w, h, &color, &flat, &want, &p).is_empty());
        let (color, inv_z) = bar_scene(30, 8);
        let p = LayerParams {
            reach_scale: 0.1,
            fill_h: 0.05,
            texture: false,
            frame: None,
        };
        assert!(background_layer(30, 8, &color, &inv_z, &vec![true; 240], &p).is_empty());
        // Mismatched lengths: no layer rather than a panic.
        assert!(background_layer(30, 8, &color, &inv_z[..10], &vec![true; 240], &p).is_empty());
    }
}
