//! `Refocus`: thin-lens depth of field by sampling the aperture
//! ("realistic depth blur", Sec. 2.3), and `ReverseMappedDof`, the per-pixel
//! gather blur the paper compares against (its Fig. 5).
//!
//! # Refocus (the paper's method)
//!
//! For each of `n` stratified points `s` of the aperture (see
//! [`Aperture::samples`]) the RGB-D image is re-projected through a pinhole
//! at `s`, sheared so that the focus plane stays put: every pixel moves by
//! `d(s, z) = C s (1/u - 1/z)` (see [`crate::camera::lens`]). The move is a forward
//! warp with a z-buffer (the nearest surface wins; ties go to the lower
//! source index, so the result does not depend on the thread count). Pixels
//! that receive nothing are disocclusions (the new viewpoint sees behind a
//! foreground edge) or cracks; they are inpainted with the non-local weights
//! of eq. 5 and the far-depth prior of Sec. 2.3 ("holes that occur due to a
//! changed viewpoint are most probably to be filled extending the adjacent
//! background... We scale the weight w(i, j) with the corresponding squared
//! depth"). The `n` views are averaged in linear radiance (f64), then
//! multiplied by `2^exposure_stops`: a highlight far above 1 spreads over its
//! circle of confusion before anything clips, so it blooms into the
//! aperture's shape (bokeh).
//!
//! # Only what the scene calls for
//!
//! The circle of confusion (CoC) of every pixel is computed first. If the
//! largest is under half a pixel the node passes the image through (with the
//! exposure applied) and says so. Otherwise only 16x16 tiles that some
//! pixel with a CoC of at least half a pixel can reach are warped; the rest
//! keep their input pixels (a pixel with a CoC under half a pixel moves by
//! less than half a pixel in every view, so it never leaves its own pixel).
//! `samples = 0` (auto) picks the count from the largest CoC: enough that
//! neighbouring samples land at most `2 / quality` pixels apart,
//! `n = ceil(pi/4 (quality * CoC_max / 2)^2)`, within 16 to 1024.

use std::sync::atomic::{AtomicU64, Ordering};

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use rayon::prelude::*;

use crate::camera::frame_border::{Frame, FrameBorder, reach_px};
use crate::camera::lens::{
    Aperture, ApertureShape, Barrel, LensEffects, ThinLens, apply_image_effects, bilinear,
    coc_map_with, effective_f_number, inv_depth,
};
use crate::camera::occlusion::{BackgroundLayer, LayerParams, background_layer};
use crate::camera::view_filter::{MIN_SIGMA_PX, Spacing, close_gaps, sigmas};
use crate::kit::grid::round_to_pixel;

/// Side of the tiles that are skipped when nothing in reach is blurred.
pub const TILE: usize = 16;
/// Smallest and largest sample counts that `samples = 0` (auto) picks.
pub const AUTO_SAMPLES: (usize, usize) = (16, 1024);
/// A CoC below this many pixels is no blur.
pub const MIN_COC_PX: f64 = 0.5;
/// Z-buffer entry of a pixel that received nothing.
const EMPTY: u64 = u64::MAX;

node_params! {
    /// Parameters of the `Refocus` and `ReverseMappedDof` nodes.
    pub struct RefocusParams {
        /// Focal length of the virtual lens in millimetres.
        pub focal_length_mm: f64 = 50.0, ParamKind::Float { min: 1.0, max: 2000.0 };
        /// f-number N: the aperture diameter is focal_length_mm / N.
        pub f_number: f64 = 2.8, ParamKind::Float { min: 0.5, max: 1000.0 };
        /// Aperture diameter in millimetres; > 0 overrides f_number, also beyond f/0.5 (no real lens: a virtual camera's exaggerated blur); 0 = use f_number.
        pub aperture_diameter_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 100000.0 };
        /// Focus distance in metres (`inf` for infinity); must exceed the
        /// focal length.
        pub focus_m: f64 = 2.0, ParamKind::Float { min: 1e-3, max: f64::INFINITY };
        /// Width of the virtual sensor in millimetres, spanning the image
        /// width (36 = full frame).
        pub sensor_width_mm: f64 = 36.0, ParamKind::Float { min: 0.1, max: 1000.0 };
        /// Aperture shape: disc, polygon (`blades` sides), triangle, or mask
        /// (the `aperture` input, values are transmittance).
        pub aperture: ApertureShape = ApertureShape::Disc, ParamKind::Choice(ApertureShape::NAMES);
        /// Number of diaphragm blades of the polygonal aperture.
        pub blades: u32 = 6u32, ParamKind::Int { min: 3, max: 64 };
        /// Rotation of the polygon in degrees (0: a vertex straight up).
        pub rotation_deg: f64 = 0.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Views averaged over the aperture; 0 = auto from the largest circle
        /// of confusion and `quality` (Refocus only).
        pub samples: usize = 0usize, ParamKind::Int { min: 0, max: 16384 };
        /// Auto sample count: neighbouring samples land at most 2 / quality
        /// pixels apart (Refocus only).
        pub quality: f64 = 1.0, ParamKind::Float { min: 0.05, max: 8.0 };
        /// Exposure change in stops applied to the linear result (+1 doubles).
        pub exposure_stops: f64 = 0.0, ParamKind::Float { min: -30.0, max: 30.0 };
        /// Seed of the aperture samples (Refocus only).
        pub seed: u64 = 0u64, ParamKind::Int { min: 0, max: i64::MAX };
        /// Two pixels bounding a hole whose relative inverse-depth difference
        /// `|1/z_a - 1/z_b| / (1/z_a + 1/z_b)` exceeds this are a foreground
        /// and a background: the hole is filled from the background only.
        pub fill_h: f64 = 0.05, ParamKind::Float { min: 1e-4, max: 1.0 };
        /// Fill disocclusions from the background (the far-depth prior of
        /// Sec. 2.3); off blends both sides by distance.
        pub far_prior: bool = true, ParamKind::Bool;
        /// Spherical aberration: the aperture's rim focuses this many dioptres (1/m) nearer than its centre, in between with the squared radius (soft-edged bokeh on one side of the focus, bright-rimmed on the other); 0 = none (Refocus only).
        pub spherical_aberration_d: f64 = 0.0, ParamKind::Float { min: -100.0, max: 100.0 };
        /// With spherical aberration: smooth the gaps it opens between the views (a bright point's bokeh falling apart into dots) by a Gaussian of this many times the spacing it adds at each pixel's depth; 0 = off, no effect on a thin lens (Refocus only).
        pub view_filter: f64 = 0.5, ParamKind::Float { min: 0.0, max: 4.0 };
        /// Longitudinal chromatic aberration: red focuses this many dioptres nearer, blue as many farther; 0 = none (Refocus only).
        pub chromatic_longitudinal_d: f64 = 0.0, ParamKind::Float { min: -100.0, max: 100.0 };
        /// Lateral chromatic aberration: red magnified by 1 + this about the image centre, blue by 1 - this (colour fringes growing toward the edges); 0 = none (Refocus only).
        pub chromatic_lateral: f64 = 0.0, ParamKind::Float { min: -0.25, max: 0.25 };
        /// Optical vignetting: distance in mm of the lens barrel in front of the aperture stop; off the axis it clips the aperture (cat's-eye bokeh, darker corners); 0 = none (Refocus only).
        pub barrel_distance_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 10000.0 };
        /// Diameter of the lens barrel in mm; 0 = the aperture's diameter (Refocus only).
        pub barrel_diameter_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 10000.0 };
        /// Natural vignetting: the image times cos^(4 k) of the field angle, k this value (1 = the physical cos^4 law); 0 = none (Refocus only).
        pub natural_vignetting: f64 = 0.0, ParamKind::Float { min: 0.0, max: 8.0 };
        /// Focus breathing: on, the input's field of view is the lens's at infinity and focusing at u magnifies by u / (u - f); off, the field of view stays the input's at every focus (Refocus only).
        pub focus_breathing: bool = false, ParamKind::Bool;
        /// Partial occlusion: a background layer inpainted once behind foreground edges (from the background side, colour and depth) and warped with the image in every view, so a blurred near edge veils the background and a blurred background shows around thin in-focus structures; off = each view fills what it reveals on its own (Refocus only).
        pub background_layer: bool = false, ParamKind::Bool;
        /// With the background layer: continue the background's texture behind the edges along its dominant patch offsets (a checker, a brick wall continued behind a thin pole) instead of only interpolating its colour; off = interpolation (Refocus only).
        pub background_texture: bool = false, ParamKind::Bool;
        /// Beyond the frame's border: edge = a view's hole there takes the input's own pixel (blurred borders continue their last row outward); reflect = colour mirrored about the border and the depth's planes continued through it, as far as the blur reaches (at most a quarter of the smaller side), rendered with the same lens and cropped away (Refocus only).
        pub frame_border: FrameBorder = FrameBorder::Edge, ParamKind::Choice(FrameBorder::NAMES);
    }
}

impl RefocusParams {
    /// The lens the parameters describe (not yet validated).
    pub fn lens(&self) -> ThinLens {
        ThinLens {
            focal_length_mm: self.focal_length_mm,
            f_number: effective_f_number(
                self.focal_length_mm,
                self.f_number,
                self.aperture_diameter_mm,
            ),
            focus_m: self.focus_m,
            sensor_width_mm: self.sensor_width_mm,
        }
    }

    /// The lens effects the parameters ask for (not yet validated).
    pub fn effects(&self) -> LensEffects {
        LensEffects {
            spherical_d: self.spherical_aberration_d,
            chromatic_longitudinal_d: self.chromatic_longitudinal_d,
            chromatic_lateral: self.chromatic_lateral,
            barrel_distance_mm: self.barrel_distance_mm,
            barrel_diameter_mm: self.barrel_diameter_mm,
            natural_vignetting: self.natural_vignetting,
            focus_breathing: self.focus_breathing,
        }
    }
}

/// What [`refocus`] did, for `explain` and the benchmarks.
#[derive(Debug, Clone, PartialEq)]
pub struct RefocusReport {
    /// Largest circle of confusion, pixels.
    pub max_coc_px: f64,
    /// Views averaged (0 when nothing needed blurring).
    pub samples: usize,
    /// Fraction of the image's pixels that were warped (of the extended
    /// frame's, when `frame_border` extended it).
    pub active_fraction: f64,
    /// Mean fraction of warped pixels that were holes and got inpainted
    /// (of the extended frame's, when `frame_border` extended it).
    pub hole_fraction: f64,
    /// Fraction of the image's pixels with a background layer entry (0 when
    /// `background_layer` is off; of the extended frame's pixels when
    /// `frame_border` extended it).
    pub layer_fraction: f64,
    /// Fraction of the background layer's entries whose colour continues
    /// the background's texture (0 when `background_texture` is off).
    pub layer_textured: f64,
    /// Largest `σ` of the filter that closes the gaps spherical aberration
    /// opens between the views, pixels (0: not applied).
    pub view_filter_px: f64,
    /// Pixels the frame was extended by on each side (`frame_border`
    /// reflect; 0: not extended).
    pub frame_pad_px: usize,
}

/// The sample count `samples = 0` picks for a largest CoC of `max_coc_px`
/// (see the module docs).
pub fn auto_samples(max_coc_px: f64, quality: f64) -> usize {
    let r = 0.5 * quality.max(0.0) * max_coc_px.max(0.0);
    let n = (std::f64::consts::FRAC_PI_4 * r * r).ceil();
    if n.is_finite() {
        (n as usize).clamp(AUTO_SAMPLES.0, AUTO_SAMPLES.1)
    } else {
        AUTO_SAMPLES.1
    }
}

fn check_inputs(color: &ColorImage, depth: &DepthMap) -> Result<(), NodeError> {
    if !color.same_dims(depth) {
        return Err(NodeError::input(
            "depth",
            format!(
                "is {}x{} but the color image is {}x{}; refocusing needs one depth per pixel \
                 (upsample the depth to the color camera first)",
                depth.width(),
                depth.height(),
                color.width(),
                color.height()
            ),
        ));
    }
    Ok(())
}

/// Linear color with non-finite channels replaced by 0 and negatives
/// clamped to 0 (radiance is never negative).
#[inline]
/// `v` (a finite, exposed colour value) as f32, held within f32's range:
/// a finite input times `2^exposure_stops` (up to 2^30) can pass f32's
/// largest value, which `as` turns into +inf.
pub fn exposed_f32(v: f64) -> f32 {
    v.clamp(-f64::from(f32::MAX), f64::from(f32::MAX)) as f32
}

fn sane(c: Rgb) -> Rgb {
    c.map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
}

/// Tiles (in a `tw x th` grid) that a pixel with a CoC of at least half a
/// pixel can reach, as a per-pixel flag. The grid's lines pass through
/// pixel `(origin, origin)` (0: the image's corner).
fn active_pixels(coc: &Image<f32>, extent: f64, origin: usize) -> (Vec<bool>, usize) {
    let (w, h) = coc.dims();
    // pixel x lies in tile (x + shift) / TILE
    let shift = (TILE - origin % TILE) % TILE;
    let (tw, th) = ((w + shift).div_ceil(TILE), (h + shift).div_ceil(TILE));
    // each row of tiles in parallel
    let mut tile_max = vec![0.0f32; tw * th];
    tile_max
        .par_chunks_mut(tw.max(1))
        .enumerate()
        .for_each(|(ty, tiles)| {
            for y in (ty * TILE).saturating_sub(shift)..((ty + 1) * TILE - shift).min(h) {
                for (x, &c) in coc.row(y).iter().enumerate() {
                    let t = &mut tiles[(x + shift) / TILE];
                    *t = t.max(c);
                }
            }
        });
    let mut active_tile = vec![false; tw * th];
    for ty in 0..th {
        for tx in 0..tw {
            let c = tile_max[ty * tw + tx] as f64;
            if c < MIN_COC_PX {
                continue;
            }
            // A pixel moves at most extent * coc pixels (plus rounding);
            // no further than the frame (a huge or infinite circle of
            // confusion reaches every tile, and `ty + reach` cannot overflow)
            let reach = ((extent * c + 1.0) / TILE as f64)
                .ceil()
                .min(tw.max(th) as f64) as usize;
            for y in ty.saturating_sub(reach)..(ty + reach + 1).min(th) {
                for x in tx.saturating_sub(reach)..(tx + reach + 1).min(tw) {
                    active_tile[y * tw + x] = true;
                }
            }
        }
    }
    let flags: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|i| active_tile[((i / w + shift) / TILE) * tw + (i % w + shift) / TILE])
        .collect();
    let count = flags.par_iter().filter(|f| **f).count();
    (flags, count)
}

/// What [`refocus`] decides before rendering any view: the discrete
/// decisions (pass-through, sample count and points, active tiles, which
/// pixels move) that every backend takes from here, so they decide alike.
#[derive(Debug, Clone)]
pub enum Plan {
    /// No circle of confusion reaches half a pixel: the exposed input.
    Sharp(ColorImage, RefocusReport),
    /// Views to render and average.
    Blur(Box<BlurPlan>),
}

/// The views of a blurred [`Plan`].
#[derive(Debug, Clone)]
pub struct BlurPlan {
    /// Image width.
    pub w: usize,
    /// Image height.
    pub h: usize,
    /// Aperture points (diameter units), one view each.
    pub points: Vec<[f64; 2]>,
    /// Pixels some blurred pixel can reach (the others keep the input).
    pub active: Vec<bool>,
    /// Number of active pixels (at least 1).
    pub n_active: usize,
    /// `C` of `coc = C |1/z - 1/u|`, pixel metres.
    pub c_scale: f64,
    /// `1/u`, the focus distance's inverse (0 at infinity).
    pub inv_u: f64,
    /// `1/z` per pixel (0: no measurement, infinitely far).
    pub src_inv_z: Vec<f64>,
    /// Sanitised linear color per pixel (non-finite as 0, negatives clamped).
    pub src_color: Vec<Rgb>,
    /// Active pixels as (index, z-buffer key): the key's high half is the
    /// depth's f32 bits (+inf for the sky), its low half the index.
    pub sources: Vec<(u32, u64)>,
    /// `2^exposure_stops`.
    pub gain: f64,
    /// Largest circle of confusion, pixels (with the blur the lens effects
    /// add to every pixel).
    pub max_coc: f64,
    /// The lens (for the image-wide effects after the views).
    pub lens: ThinLens,
    /// The lens effects beyond the thin lens.
    pub effects: LensEffects,
    /// The barrel clip of optical vignetting, if on.
    pub barrel: Option<Barrel>,
    /// The background layer behind foreground edges (empty when
    /// `background_layer` is off or nothing is behind anything). Its entry
    /// `k` takes part in the z-buffer as source index `w * h + k`.
    pub layer: BackgroundLayer,
    /// Per pixel, the `σ` (pixels) of the filter that closes the gaps
    /// spherical aberration opens between the views
    /// ([`crate::camera::view_filter`]); empty when no pixel's reaches
    /// [`MIN_SIGMA_PX`] (the thin lens, `view_filter = 0`).
    pub view_sigma: Vec<f64>,
    /// With `frame_border` reflect: how the input was extended (`w x h`
    /// above and every per-pixel list are the extended frame's; the
    /// finished image is cropped back to the input's frame).
    pub frame: Option<Frame>,
}

/// The z-buffer key of a source of inverse depth `v` and index `i`: the
/// high half the depth's f32 bits (positive floats order like their bits;
/// +inf for the sky, `v = 0`), the low half the index. The device backend
/// keys its warp with the same bits.
pub fn zkey(v: f64, i: usize) -> u64 {
    // Guard: v > 0 in the division.
    let z = if v > 0.0 {
        (1.0 / v) as f32
    } else {
        f32::INFINITY
    };
    ((z.to_bits() as u64) << 32) | i as u64
}

impl BlurPlan {
    /// The shift of view `s` in pixels per unit of `1/u - 1/z`.
    pub fn shift(&self, s: [f64; 2]) -> [f64; 2] {
        [self.c_scale * s[0], self.c_scale * s[1]]
    }

    /// Whether [`BlurPlan::finish_image`] changes the averaged views.
    pub fn finishes(&self) -> bool {
        self.effects.in_image(&self.lens)
            || self.barrel.is_some()
            || !self.view_sigma.is_empty()
            || self.frame.is_some()
    }

    /// What both backends do to the averaged views: the gaps spherical
    /// aberration opens between them closed
    /// ([`crate::camera::view_filter`]), the barrel's share of the pixels
    /// no view moves (optical vignetting without blur), then the
    /// image-wide lens effects (magnification per channel, breathing,
    /// natural vignetting), and the crop back to the input's frame when it
    /// was extended.
    pub fn finish_image(
        &self,
        out: ColorImage,
        aperture: &Aperture,
        p: &RefocusParams,
    ) -> Result<ColorImage, NodeError> {
        let mut out = close_gaps(out, &self.view_sigma);
        if let Some(b) = &self.barrel {
            let more;
            let pts = if self.points.len() >= FRACTION_SAMPLES {
                &self.points
            } else {
                more = aperture.samples(FRACTION_SAMPLES, p.seed)?;
                &more
            };
            darken_by_barrel(&mut out, b, pts, Some(&self.active));
        }
        let out = apply_image_effects(out, &self.effects, &self.lens);
        Ok(match &self.frame {
            Some(frame) => frame.crop(&out),
            None => out,
        })
    }

    /// The green channel's extra shift of view `s` (spherical
    /// aberration; +0 without it): every source moves by it in the warp.
    pub fn green_shift(&self, s: [f64; 2]) -> [f64; 2] {
        let [dx, dy] = self.shift(s);
        let off = self.effects.focus_offset(s, 1);
        [dx * off, dy * off]
    }

    /// Where each channel of view `s` reads the view that green's focus
    /// warped (longitudinal chromatic aberration): at `(x, y) - e_c`, `e_c`
    /// the view's shift times channel `c`'s focus offset less green's
    /// (zero without the effect, and always for green).
    pub fn channel_offsets(&self, s: [f64; 2]) -> [[f64; 2]; 3] {
        let [dx, dy] = self.shift(s);
        let off_g = self.effects.focus_offset(s, 1);
        std::array::from_fn(|c| {
            let d = self.effects.focus_offset(s, c) - off_g;
            [dx * d, dy * d]
        })
    }

    /// The unit march step of the hole fill along a view's shift (the major
    /// axis has length 1); a zero shift (nothing moved) falls back to x.
    pub fn fill_step(dir: [f64; 2]) -> [f64; 2] {
        let m = dir[0].abs().max(dir[1].abs());
        if m > 0.0 && m.is_finite() {
            // Guard: m > 0 checked.
            [dir[0] / m, dir[1] / m]
        } else {
            [1.0, 0.0]
        }
    }

    /// The report of rendering this plan with `holes_total` hole pixels
    /// filled over all views.
    pub fn report(&self, holes_total: usize) -> RefocusReport {
        let (w, h) = (self.w, self.h);
        RefocusReport {
            max_coc_px: self.max_coc,
            samples: self.points.len(),
            // Guards: w * h > 0 (empty images are Sharp), n_active > 0
            // because the pixel with the largest CoC is active.
            active_fraction: self.n_active as f64 / (w * h).max(1) as f64,
            hole_fraction: holes_total as f64
                / (self.n_active.max(1) * self.points.len().max(1)) as f64,
            layer_fraction: self.layer.len() as f64 / (w * h).max(1) as f64,
            // Guard: max(1) keeps an empty layer at 0.
            layer_textured: self.layer.textured as f64 / self.layer.len().max(1) as f64,
            view_filter_px: self.view_sigma.iter().copied().fold(0.0, f64::max),
            frame_pad_px: self.frame.map_or(0, |f| f.pad),
        }
    }
}

/// The decisions of [`refocus`] (see [`Plan`]).
pub fn plan(
    color: &ColorImage,
    depth: &DepthMap,
    aperture: &Aperture,
    p: &RefocusParams,
) -> Result<Plan, NodeError> {
    check_inputs(color, depth)?;
    let lens = p.lens();
    lens.validate()?;
    let fx = p.effects();
    fx.validate()?;
    let (w, h) = color.dims();
    // The input's C (an extended frame keeps it, so its views shift alike).
    let c_scale = lens.coc_scale(w);
    // The per-ray focus offsets (spherical, longitudinal chromatic) blur
    // every pixel by up to C max|S r^2 + k_c L| more.
    let extra = c_scale * fx.max_focus_offset(aperture.extent());
    let blur_map = |depth: &DepthMap| -> Image<f32> {
        let coc = coc_map_with(depth, c_scale, lens.inv_focus());
        if extra > 0.0 {
            coc.map(|&c| (c as f64 + extra) as f32)
        } else {
            coc
        }
    };
    let coc = blur_map(depth);
    let max_coc = coc
        .as_slice()
        .par_iter()
        .fold(|| 0.0f64, |m, &c| m.max(c as f64))
        .reduce(|| 0.0, f64::max);
    let frame = match p.frame_border {
        FrameBorder::Edge => None,
        FrameBorder::Reflect => {
            // (a frame with no blur reads beyond it only through a channel's
            // minification)
            let blur = if max_coc >= MIN_COC_PX { max_coc } else { 0.0 };
            // (reach_px takes a disc's reach, half the circle: a mask
            // reaches its extent's share of it)
            let blur = blur * 2.0 * aperture.extent();
            Frame::new(w, h, reach_px(blur, &fx, &lens, w, h))
        }
    };
    let Some(frame) = frame else {
        return plan_frame(
            color,
            depth,
            coc,
            max_coc,
            aperture,
            p,
            Lens { lens, c_scale, fx },
            None,
        );
    };
    // The extended frame: the widened sensor keeps the pixel pitch (for
    // the image-wide effects and the barrel), the blur keeps the input's C,
    // so its circles of confusion are those of its depth (the largest stays
    // the input's: it decides the sample count alike).
    let wide = Lens {
        lens: frame.lens(&lens),
        c_scale,
        fx,
    };
    let depth = frame.extend_depth(depth, p.fill_h);
    let coc = blur_map(&depth);
    let plan = plan_frame(
        &frame.extend(color),
        &depth,
        coc,
        max_coc,
        aperture,
        p,
        wide,
        Some(frame),
    )?;
    Ok(match plan {
        Plan::Sharp(out, report) => Plan::Sharp(frame.crop(&out), report),
        Plan::Blur(mut b) => {
            b.frame = Some(frame);
            Plan::Blur(b)
        }
    })
}

/// The lens of a plan, the input's `C` and the lens effects (validated).
struct Lens {
    lens: ThinLens,
    c_scale: f64,
    fx: LensEffects,
}

/// [`plan`] of a frame (the input's, or the input extended by `frame`)
/// whose circles of confusion are `coc` (with the lens effects' extra blur),
/// the largest `max_coc`.
#[allow(clippy::too_many_arguments)]
fn plan_frame(
    color: &ColorImage,
    depth: &DepthMap,
    coc: Image<f32>,
    max_coc: f64,
    aperture: &Aperture,
    p: &RefocusParams,
    Lens { lens, c_scale, fx }: Lens,
    frame: Option<Frame>,
) -> Result<Plan, NodeError> {
    let (w, h) = color.dims();
    let inv_u = lens.inv_focus();
    let gain = 2f64.powf(p.exposure_stops);
    let frame_pad_px = frame.map_or(0, |f| f.pad);
    let exposed = |c: Rgb| sane(c).map(|v| exposed_f32(v as f64 * gain));
    let barrel = fx.barrel(&lens, w, h);
    if max_coc < MIN_COC_PX || color.is_empty() {
        let mut out = color.map(|&c| exposed(c));
        if let Some(b) = &barrel {
            let pts = aperture.samples(FRACTION_SAMPLES, p.seed)?;
            darken_by_barrel(&mut out, b, &pts, None);
        }
        return Ok(Plan::Sharp(
            apply_image_effects(out, &fx, &lens),
            RefocusReport {
                max_coc_px: max_coc,
                samples: 0,
                active_fraction: 0.0,
                hole_fraction: 0.0,
                layer_fraction: 0.0,
                layer_textured: 0.0,
                view_filter_px: 0.0,
                frame_pad_px,
            },
        ));
    }
    let n = if p.samples == 0 {
        auto_samples(max_coc, p.quality)
    } else {
        p.samples
    };
    let points = aperture.samples(n, p.seed)?;
    // (tiles anchored at the input's corner: its pixels get the tiles, and
    // the flags, they get without an extension)
    let (active, n_active) = active_pixels(&coc, aperture.extent(), frame.map_or(0, |f| f.pad));
    // (per-pixel maps in parallel: rayon's collect keeps the order)
    let src_inv_z: Vec<f64> = depth.as_slice().par_iter().map(|&z| inv_depth(z)).collect();
    let src_color: Vec<Rgb> = color.as_slice().par_iter().map(|&c| sane(c)).collect();
    // Sources that can move: active pixels only (see active_pixels), with
    // the high half of their z-buffer key computed once: depth bits (positive
    // floats order like their bits; +inf for the sky) then the source index.
    // (in parallel: rayon's collect keeps the order)
    let sources: Vec<(u32, u64)> = (0..active.len())
        .into_par_iter()
        .filter(|&i| active[i])
        .map(|i| (i as u32, zkey(src_inv_z[i], i)))
        .collect();
    let layer = if p.background_layer {
        background_layer(
            w,
            h,
            &src_color,
            &src_inv_z,
            &active,
            &LayerParams {
                reach_scale: c_scale * aperture.extent(),
                fill_h: p.fill_h,
                texture: p.background_texture,
                frame,
            },
        )
    } else {
        BackgroundLayer::default()
    };
    let view_sigma = {
        let sp = Spacing {
            points: &points,
            c_scale,
            inv_u,
            area: aperture.area(),
            spherical_d: fx.spherical_d,
            k: p.view_filter,
        };
        // empty, without a pass over the pixels, when the filter is off
        let s = sigmas(&sp, &src_inv_z);
        if s.iter().any(|v| *v >= MIN_SIGMA_PX) {
            s
        } else {
            Vec::new()
        }
    };
    Ok(Plan::Blur(Box::new(BlurPlan {
        w,
        h,
        points,
        active,
        n_active,
        c_scale,
        inv_u,
        src_inv_z,
        src_color,
        sources,
        gain,
        max_coc,
        lens,
        effects: fx,
        barrel,
        layer,
        view_sigma,
        frame: None,
    })))
}

/// Aperture points for the open fraction of a pixel that no view moves
/// (optical vignetting without blur): at least this many.
pub const FRACTION_SAMPLES: usize = 256;

/// Multiplies every pixel of `image` (every pixel whose `only` flag is
/// false, when given) by the fraction of `points` whose ray passes the
/// barrel: what optical vignetting leaves of a pixel that does not move.
pub fn darken_by_barrel(
    image: &mut ColorImage,
    barrel: &Barrel,
    points: &[[f64; 2]],
    only: Option<&[bool]>,
) {
    let w = image.width();
    // Guard: an empty point set leaves the image as is.
    if points.is_empty() {
        return;
    }
    let inv_n = 1.0 / points.len() as f64;
    image
        .as_mut_slice()
        .par_iter_mut()
        .enumerate()
        .for_each(|(t, px)| {
            if only.is_some_and(|a| a[t]) {
                return;
            }
            let (x, y) = ((t % w) as f64 + 0.5, (t / w) as f64 + 0.5);
            let open = points.iter().filter(|s| barrel.open(**s, x, y)).count();
            if open != points.len() {
                let f = open as f64 * inv_n;
                *px = px.map(|v| (v as f64 * f) as f32);
            }
        });
}

/// Why `Refocus` passed its input through (`report.samples == 0`); both
/// backends say it in these words.
pub fn sharp_reason(p: &RefocusParams, report: &RefocusReport) -> String {
    let what = if p.exposure_stops == 0.0 {
        "image passed through".to_string()
    } else {
        format!("only the exposure ({:+} stops) applied", p.exposure_stops)
    };
    format!(
        "circle of confusion below {MIN_COC_PX} px everywhere (largest {:.3} px): {what}",
        report.max_coc_px
    )
}

/// Refocuses `color` (linear radiance) with its per-pixel `depth` through
/// the thin lens and aperture of `p` (Sec. 2.3; see the module docs).
///
/// ```
/// use depthgraph_nodes::camera::refocus::{refocus, RefocusParams};
/// use depthgraph_nodes::camera::lens::Aperture;
/// use depthgraph_graph::value::{ColorImage, DepthMap};
/// // A bright dot on a dark wall at 4 m, focused at 1 m: the dot spreads.
/// let mut c = ColorImage::filled(48, 48, [0.0; 3]);
/// *c.get_mut(24, 24) = [100.0; 3];
/// let d = DepthMap::filled(48, 48, 4.0);
/// let p = RefocusParams {
///     focus_m: 1.0, f_number: 2.0, samples: 256, sensor_width_mm: 4.0, ..Default::default()
/// };
/// let (out, report) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
/// assert!(report.max_coc_px > 10.0);
/// assert!(out.get(24, 24)[0] < 10.0 && out.get(28, 24)[0] > 0.1);
/// ```
pub fn refocus(
    color: &ColorImage,
    depth: &DepthMap,
    aperture: &Aperture,
    p: &RefocusParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(ColorImage, RefocusReport), NodeError> {
    let plan = match plan(color, depth, aperture, p)? {
        Plan::Sharp(out, report) => return Ok((out, report)),
        Plan::Blur(b) => *b,
    };
    let BlurPlan {
        w,
        h,
        ref points,
        ref active,
        c_scale,
        ref src_inv_z,
        ref src_color,
        ref sources,
        ..
    } = plan;
    let inv_u = plan.inv_u;
    let layer = &plan.layer;
    // What every view's warp reads, computed once.
    let warp: Vec<WarpSource> = sources
        .par_iter()
        .map(|&(i, key)| WarpSource::new(i as usize, w, inv_u - src_inv_z[i as usize], key))
        .chain(layer.pixels.par_iter().enumerate().map(|(k, &i)| {
            let v = layer.inv_z[k];
            WarpSource::new(i as usize, w, inv_u - v, zkey(v, w * h + k))
        }))
        .collect();
    let named = Sources {
        n: w * h,
        src_color,
        src_inv_z,
        layer,
    };
    let fx = plan.effects;
    let split = fx.channels_split();
    let mut acc = vec![[0.0f64; 3]; if split { 0 } else { w * h }];
    let mut holes_total = 0usize;
    // The view's colour is copied out only when the channels read their
    // neighbours (longitudinal chromatic aberration); otherwise the winning
    // keys are the view. (Spherical aberration moves the whole view in the
    // warp; the barrel only masks the accumulation.)
    let barrel = plan.barrel;
    let mut zbuf: Vec<AtomicU64> = (0..w * h).map(|_| AtomicU64::new(EMPTY)).collect();
    // The split view and its sums are held per channel (planes: a
    // channel's shifted read is a row of one plane). Pixels no view moves
    // hold the input in every view (no source reaches them): written once,
    // so a shifted read needs no test.
    let planes = if split { w * h } else { 0 };
    let mut view_planes: [Vec<f32>; 3] =
        std::array::from_fn(|c| src_color[..planes].iter().map(|v| v[c]).collect());
    let mut acc_planes: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; planes]);
    let mut keys = vec![EMPTY; if split { 0 } else { w * h }];
    for (k, s) in points.iter().enumerate() {
        let dx = c_scale * s[0];
        let dy = c_scale * s[1];
        // The lens effects' focus offset of green moves the whole view, in
        // the warp (exact, and +0 when off: the same bits); red and blue
        // move by their difference from green, in the accumulation.
        let [gx, gy] = plan.green_shift(*s);
        let move_by = [dx, dy, gx, gy];
        // (The z-buffer is EMPTY here: it starts so and the pass after the
        // warp resets every entry.)
        // Forward warp with a z-buffer (nearest depth wins, then the lower
        // source index).
        // The background layer's entries take part alike: their keys are
        // farther than the foreground above them.
        warp.par_chunks(4096).for_each(|chunk| {
            for src in chunk {
                if let Some(t) = src.target(w, h, move_by) {
                    // (a plain read first: a source that loses takes no
                    // locked instruction; the minimum is the same)
                    let slot = &zbuf[t];
                    if src.key < slot.load(Ordering::Relaxed) {
                        slot.fetch_min(src.key, Ordering::Relaxed);
                    }
                }
            }
        });
        // The barrel passes the ray from aperture point s to pixel t.
        let open = |t: usize| {
            barrel.is_none_or(|b| b.open(*s, (t % w) as f64 + 0.5, (t / w) as f64 + 0.5))
        };
        let step = BlurPlan::fill_step([dx, dy]);
        // Pixels per parallel task of the passes over the view.
        const CHUNK: usize = 4096;
        if !split {
            // Take the winning keys (resetting the z-buffer), list the holes
            // and accumulate every active pixel that is not a hole; then the
            // holes' share, after their fill. The same sums in the same
            // order as copying the view out first, with a third of the
            // memory traffic.
            let holes: Vec<usize> = keys
                .par_chunks_mut(CHUNK)
                .zip(zbuf.par_chunks_mut(CHUNK))
                .zip(acc.par_chunks_mut(CHUNK))
                .enumerate()
                .flat_map_iter(|(c, ((ks, zs), accs))| {
                    let mut holes = Vec::new();
                    let pixels = ks.iter_mut().zip(zs).zip(accs);
                    for (j, ((k, z), a)) in pixels.enumerate() {
                        let t = c * CHUNK + j;
                        // (exclusive here: a plain read and write, no locked swap)
                        let key = std::mem::replace(z.get_mut(), EMPTY);
                        *k = key;
                        if !active[t] {
                            continue;
                        }
                        if key == EMPTY {
                            holes.push(t);
                            continue;
                        }
                        if !open(t) {
                            continue;
                        }
                        let c = named.color((key & 0xffff_ffff) as usize);
                        for (a, v) in a.iter_mut().zip(c) {
                            *a += v as f64;
                        }
                    }
                    holes
                })
                .collect();
            holes_total += holes.len();
            let keyed = Keyed {
                keys: &keys,
                sources: &named,
            };
            let open_holes: Vec<usize> = holes.into_iter().filter(|&t| open(t)).collect();
            let fills: Vec<Rgb> = open_holes
                .par_iter()
                .map(|&t| fill_one(&keyed, w, h, t, step, p))
                .collect();
            for (&t, c) in open_holes.iter().zip(fills) {
                for (a, v) in acc[t].iter_mut().zip(c) {
                    *a += v as f64;
                }
            }
        } else {
            // Copy the winners' colour into the view and list the holes;
            // fill them (every hole: a channel's read may reach one the
            // barrel closes), reading the z-buffer, which the accumulation
            // below resets.
            let [vr, vg, vb] = &mut view_planes;
            let holes: Vec<usize> = vr
                .par_chunks_mut(CHUNK)
                .zip(vg.par_chunks_mut(CHUNK))
                .zip(vb.par_chunks_mut(CHUNK))
                .enumerate()
                .flat_map_iter(|(c, ((rs, gs), bs))| {
                    let mut holes = Vec::new();
                    for (j, ((r, g), b)) in rs.iter_mut().zip(gs).zip(bs).enumerate() {
                        let t = c * CHUNK + j;
                        if !active[t] {
                            continue;
                        }
                        let key = zbuf[t].load(Ordering::Relaxed);
                        if key == EMPTY {
                            holes.push(t);
                            continue;
                        }
                        [*r, *g, *b] = named.color((key & 0xffff_ffff) as usize);
                    }
                    holes
                })
                .collect();
            holes_total += holes.len();
            let zview = Keyed {
                keys: &zbuf,
                sources: &named,
            };
            let fills: Vec<Rgb> = holes
                .par_iter()
                .map(|&t| fill_one(&zview, w, h, t, step, p))
                .collect();
            for (&t, c) in holes.iter().zip(fills) {
                for (plane, v) in view_planes.iter_mut().zip(c) {
                    plane[t] = v;
                }
            }
            let e = plan.channel_offsets(*s);
            let zbuf = &zbuf;
            let view = &view_planes;
            let [ar, ag, ab] = &mut acc_planes;
            ar.par_chunks_mut(w)
                .zip(ag.par_chunks_mut(w))
                .zip(ab.par_chunks_mut(w))
                .enumerate()
                .for_each(|(y, ((r, g), b))| {
                    for z in &zbuf[y * w..(y + 1) * w] {
                        z.store(EMPTY, Ordering::Relaxed);
                    }
                    // the barrel's test once per pixel, for the three channels
                    let open_row: Vec<bool> = match barrel {
                        None => Vec::new(),
                        Some(_) => (0..w).map(|x| open(y * w + x)).collect(),
                    };
                    for (c, a) in [r, g, b].into_iter().enumerate() {
                        let shift = ShiftedRead { w, h, e: e[c] };
                        match barrel {
                            None => shift.add_row(a, &view[c], y, |_| true),
                            Some(_) => shift.add_row(a, &view[c], y, |x| open_row[x]),
                        }
                    }
                });
        }
        if k % 8 == 7 {
            // Guard: points is non-empty inside the loop.
            on_progress((k + 1) as f32 / points.len() as f32)?;
        }
    }
    // Guard: n >= 1 (auto >= 16, explicit >= 1 since 0 means auto).
    let gain = plan.gain;
    let inv_n = gain / points.len() as f64;
    let data: Vec<Rgb> = (0..w * h)
        .map(|t| {
            if active[t] {
                let sum = if split {
                    std::array::from_fn(|c| acc_planes[c][t])
                } else {
                    acc[t]
                };
                sum.map(|v| exposed_f32(v * inv_n))
            } else {
                src_color[t].map(|v| exposed_f32(v as f64 * gain))
            }
        })
        .collect();
    let out = plan.finish_image(Image::from_vec(w, h, data)?, aperture, p)?;
    Ok((out, plan.report(holes_total)))
}

/// One channel of a split view read at `(x, y) - e` (longitudinal chromatic
/// aberration): bilinear, edges clamped.
struct ShiftedRead {
    w: usize,
    h: usize,
    e: [f64; 2],
}

impl ShiftedRead {
    /// Adds row `y` of `plane` read at the offset to `acc` where `open`
    /// holds. Inside the frame the four taps are at a fixed offset with
    /// the same weights for every pixel (a loop over slices the compiler
    /// vectorizes); the pixels whose taps leave the frame take
    /// [`bilinear`]'s clamped read. An unshifted channel is added as it is.
    fn add_row(&self, acc: &mut [f64], plane: &[f32], y: usize, open: impl Fn(usize) -> bool) {
        let (w, h) = (self.w, self.h);
        let row = &plane[y * w..(y + 1) * w];
        if self.e == [0.0, 0.0] {
            for (x, (a, v)) in acc.iter_mut().zip(row).enumerate() {
                if open(x) {
                    *a += *v as f64;
                }
            }
            return;
        }
        let (qx, qy) = (-self.e[0], -self.e[1]);
        let (fx0, fy0) = (qx.floor(), qy.floor());
        let (ox, oy, ax, ay) = (fx0 as isize, fy0 as isize, qx - fx0, qy - fy0);
        let y0 = y as isize + oy;
        // x with x + ox >= 0 and x + ox + 1 < w, when row y0 and y0 + 1 exist
        let (lo, hi) = if y0 >= 0 && y0 + 1 < h as isize {
            let lo = (-ox).clamp(0, w as isize) as usize;
            let hi = (w as isize - 1 - ox).clamp(lo as isize, w as isize) as usize;
            (lo, hi)
        } else {
            (0, 0)
        };
        let clamped = |x: usize| {
            bilinear(w, h, x as f64 - self.e[0], y as f64 - self.e[1], |j| {
                plane[j]
            })
        };
        for x in (0..lo).chain(hi..w) {
            if open(x) {
                acc[x] += clamped(x);
            }
        }
        if lo < hi {
            let y0 = y0 as usize;
            // (lo + ox >= 0 and hi + ox + 1 <= w by the range above)
            let start = (lo as isize + ox) as usize;
            let n = hi - lo;
            let r0 = &plane[y0 * w + start..y0 * w + start + n + 1];
            let r1 = &plane[(y0 + 1) * w + start..(y0 + 1) * w + start + n + 1];
            let (bx, by) = (1.0 - ax, 1.0 - ay);
            for (i, a) in acc[lo..hi].iter_mut().enumerate() {
                if open(lo + i) {
                    let v = |r: &[f32], k: usize| r[k] as f64;
                    *a += (v(r0, i) * bx + v(r0, i + 1) * ax) * by
                        + (v(r1, i) * bx + v(r1, i + 1) * ax) * ay;
                }
            }
        }
    }
}

/// A source pixel of the forward warp with what every view needs of it:
/// its position (exact in f32: images are under 2^24 pixels a side), its
/// `m = 1/u - 1/z` and its z-buffer key (24 bytes, the same memory as the
/// index, key and depth the warp read before, and no division per view).
struct WarpSource {
    x: f32,
    y: f32,
    m: f64,
    key: u64,
}

impl WarpSource {
    fn new(i: usize, w: usize, m: f64, key: u64) -> WarpSource {
        WarpSource {
            x: (i % w) as f32,
            y: (i / w) as f32,
            m,
            key,
        }
    }

    /// Where a view puts the pixel: `(x, y) + m (dx, dy) + (gx, gy)`
    /// rounded, for `move_by = [dx, dy, gx, gy]`; `None` off the image.
    #[inline]
    fn target(&self, w: usize, h: usize, move_by: [f64; 4]) -> Option<usize> {
        let [dx, dy, gx, gy] = move_by;
        let tx = round_to_pixel(self.x as f64 + dx * self.m + gx, w)?;
        let ty = round_to_pixel(self.y as f64 + dy * self.m + gy, h)?;
        Some(ty * w + tx)
    }
}

/// What the hole fill reads of one view: the pixels some source landed on
/// (before any hole is filled).
trait Warped: Sync {
    /// True when a source landed on pixel `j`.
    fn is_warped(&self, j: usize) -> bool;
    /// Colour, inverse depth and certainty of a warped pixel `j`.
    fn warped(&self, j: usize) -> (Rgb, f32, f32);
    /// Inverse depth of a warped pixel `j`.
    fn inv_z(&self, j: usize) -> f32 {
        self.warped(j).1
    }
    /// The (sanitised) input colour at pixel `t`.
    fn input(&self, t: usize) -> Rgb;
}

/// A view held as its z-buffer's winning keys only (the keys taken out, or
/// the z-buffer itself before its reset): the colour and depth are read
/// from the source the key names, exactly as a gather would copy them.
struct Keyed<'a, K> {
    keys: &'a [K],
    sources: &'a Sources<'a>,
}

/// A winning key as held: taken out of the z-buffer, or still in it.
trait Key: Sync {
    fn key(&self) -> u64;
}

impl Key for u64 {
    fn key(&self) -> u64 {
        *self
    }
}

impl Key for AtomicU64 {
    fn key(&self) -> u64 {
        self.load(Ordering::Relaxed)
    }
}

/// The sources a z-buffer key can name: the image's pixels, then the
/// background layer's entries from index `n = w * h`.
struct Sources<'a> {
    n: usize,
    src_color: &'a [Rgb],
    src_inv_z: &'a [f64],
    layer: &'a BackgroundLayer,
}

impl Sources<'_> {
    /// Colour of source `i` (a layer entry at `n + k`).
    #[inline]
    fn color(&self, i: usize) -> Rgb {
        if i < self.n {
            self.src_color[i]
        } else {
            self.layer.color[i - self.n]
        }
    }

    /// Colour and inverse depth of source `i` (a layer entry at `n + k`).
    fn source(&self, i: usize) -> (Rgb, f32) {
        let inv_z = if i < self.n {
            self.src_inv_z[i]
        } else {
            self.layer.inv_z[i - self.n]
        };
        (self.color(i), inv_z as f32)
    }
}

impl<K: Key> Warped for Keyed<'_, K> {
    fn is_warped(&self, j: usize) -> bool {
        self.keys[j].key() != EMPTY
    }
    fn input(&self, t: usize) -> Rgb {
        self.sources.color(t)
    }
    fn warped(&self, j: usize) -> (Rgb, f32, f32) {
        let (c, v) = self
            .sources
            .source((self.keys[j].key() & 0xffff_ffff) as usize);
        (c, v, 1.0)
    }
}

/// The first known pixel from `t` along `step` (not `t` itself), with its
/// distance in steps.
fn march(view: &impl Warped, w: usize, h: usize, t: usize, step: [f64; 2]) -> Option<(usize, f64)> {
    let (x, y) = ((t % w) as f64, (t / w) as f64);
    let mut k = 1.0;
    loop {
        let px = round_to_pixel(x + k * step[0], w)?;
        let py = round_to_pixel(y + k * step[1], h)?;
        let j = py * w + px;
        if view.is_warped(j) {
            return Some((j, k));
        }
        k += 1.0;
    }
}

/// The fill of one hole pixel `t` of a view with the far-depth prior of Sec. 2.3
/// ("holes that occur due to a changed viewpoint are most probably to be
/// filled extending the adjacent background").
///
/// In a view every pixel moves along the same direction `s` (by an amount
/// that depends on its depth), so a disocclusion is a gap along `s` between
/// a foreground pixel on one side and the background it uncovered on the
/// other. Each hole pixel looks for the first known pixel in both directions
/// along `s` and takes the one of larger depth; two ends of nearly equal
/// depth (relative inverse-depth difference below `fill_h`: a crack inside
/// one surface) are blended with the paper's weights `zeta (z / z_far)^2`.
/// Without `far_prior` the two ends are blended by inverse distance, which is
/// what an isotropic inpainting does and what lets the foreground bleed in.
///
/// Why not the paper's iterative eq. 5 with a squared-depth prior over a
/// search window: a gap wider than the window is filled ring by ring from
/// both sides, so its foreground half is filled from the foreground alone
/// whatever the prior; in our tests that darkened a white wall beside a black
/// bar by 28 % (see the `disocclusion_is_filled_from_the_background` test),
/// this fill by under 5 %. Every hole pixel is computed from the warped view
/// only, so the result does not depend on the thread count. A hole with no
/// known pixel along either direction (the march leaves the frame both
/// ways: the view looks past the input's border) takes the input's own
/// colour there.
fn fill_one(
    view: &impl Warped,
    w: usize,
    h: usize,
    t: usize,
    step: [f64; 2],
    p: &RefocusParams,
) -> Rgb {
    let a = march(view, w, h, t, step);
    let b = march(view, w, h, t, [-step[0], -step[1]]);
    let ends: Vec<(usize, f64)> = match (a, b) {
        // Both directions leave the frame before meeting a warped pixel:
        // the view looks past the input's border there (a pixel near the
        // frame's edge, the view's shift pointing along or out of it).
        // The input's own pixel continues the image (for a plane of one
        // colour, exactly); black would darken the frame's border.
        (None, None) => return view.input(t),
        (Some(e), None) | (None, Some(e)) => vec![e],
        (Some(ea), Some(eb)) => {
            let (va, vb) = (view.inv_z(ea.0) as f64, view.inv_z(eb.0) as f64);
            let s = va + vb;
            // Guard: two sky ends (s = 0) are the same depth.
            let rel = if s > 0.0 { (va - vb).abs() / s } else { 0.0 };
            if p.far_prior && rel > p.fill_h {
                // Keep the farther end (smaller inverse depth; ties to a).
                vec![if vb < va { eb } else { ea }]
            } else {
                vec![ea, eb]
            }
        }
    };
    let v_far = ends
        .iter()
        .map(|e| view.inv_z(e.0) as f64)
        .fold(f64::INFINITY, f64::min);
    let (mut wsum, mut csum) = (0.0f64, [0.0f64; 3]);
    for &(j, dist) in &ends {
        let (cj, vj, zeta) = view.warped(j);
        let (vj, zeta) = (vj as f64, zeta as f64);
        let wt = if p.far_prior {
            // (z_j / z_far)^2 = (v_far / v_j)^2 in [0, 1]; the sky (v = 0)
            // is as far as it gets. Guard: vj > 0 in the division.
            zeta * if vj > 0.0 { (v_far / vj).powi(2) } else { 1.0 }
        } else {
            // Guard: dist >= 1 (march starts one step out).
            zeta / dist
        };
        wsum += wt;
        for (a, c) in csum.iter_mut().zip(cj) {
            *a += wt * c as f64;
        }
    }
    if wsum > 0.0 && wsum.is_finite() {
        // Guard: wsum > 0 checked.
        csum.map(|v| (v / wsum) as f32)
    } else {
        // Every end has certainty > 0 and the prior of the farthest end is 1,
        // so this is unreachable; a defined fallback all the same.
        view.warped(ends[0].0).0
    }
}

/// The reverse-mapped z-buffer depth of field ("realistic depth blur",
/// Sec. 1 and Fig. 5, after Demers' GPU Gems survey): every output pixel is
/// the mean of the input over the aperture shape scaled to its own circle of
/// confusion, with no depth test, so a blurred background leaks over a sharp
/// foreground edge and a sharp background keeps a sharp silhouette of a
/// blurred foreground. It is here so the comparison of Fig. 5 can be
/// reproduced; [`refocus`] is the method to use.
pub fn reverse_mapped_dof(
    color: &ColorImage,
    depth: &DepthMap,
    aperture: &Aperture,
    p: &RefocusParams,
) -> Result<ColorImage, NodeError> {
    check_inputs(color, depth)?;
    let coc = crate::camera::lens::coc_map(depth, &p.lens())?;
    let gain = 2f64.powf(p.exposure_stops);
    let (w, h) = color.dims();
    let src: Vec<Rgb> = color.as_slice().iter().map(|&c| sane(c)).collect();
    // Kernels for the diameters in half-pixel steps that some pixel uses,
    // built once.
    let max_coc = coc.as_slice().iter().fold(0.0f32, |m, &c| m.max(c));
    let max_diam = (w.max(h) as f64 * 2.0).min(max_coc as f64);
    let steps = (max_diam * 2.0).ceil() as usize + 1;
    let index = |c: f64| kernel_step(c, max_diam, steps);
    let used = reverse_kernels_used(coc.as_slice(), max_diam, steps, aperture)?;
    // a mask's footprint: its points (an error when no light passes)
    let mask_points = match aperture {
        Aperture::Mask(_) => Some(aperture.samples(MASK_KERNEL_SAMPLES, 0)?),
        _ => None,
    };
    let kernels: Vec<Vec<(isize, isize)>> = (0..=steps)
        .into_par_iter()
        .map(|s| {
            if used[s] {
                kernel(aperture, mask_points.as_deref(), s as f64 * 0.5)
            } else {
                Vec::new()
            }
        })
        .collect();
    let data: Vec<Rgb> = (0..w * h)
        .into_par_iter()
        .map(|t| {
            let c = coc.as_slice()[t] as f64;
            let (x, y) = ((t % w) as isize, (t / w) as isize);
            if c < MIN_COC_PX {
                return src[t].map(|v| exposed_f32(v as f64 * gain));
            }
            let k = &kernels[index(c)];
            let (mut sum, mut n) = ([0.0f64; 3], 0usize);
            for &(ox, oy) in k {
                let (qx, qy) = (x + ox, y + oy);
                if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                    continue;
                }
                for (a, c) in sum.iter_mut().zip(src[qy as usize * w + qx as usize]) {
                    *a += c as f64;
                }
                n += 1;
            }
            // Guard: every kernel holds (0, 0), which is inside the image.
            let inv = gain / n.max(1) as f64;
            sum.map(|v| exposed_f32(v * inv))
        })
        .collect();
    Ok(Image::from_vec(w, h, data)?)
}

/// The kernel of a circle of confusion `c` (px): its half-pixel step of
/// the diameter, `c` clamped to `max_diam`, at most `steps`.
fn kernel_step(c: f64, max_diam: f64, steps: usize) -> usize {
    ((c.min(max_diam) * 2.0).round() as usize).min(steps)
}

/// Which kernel sizes (half-pixel steps of the diameter, `0..=steps`,
/// diameters clamped to `max_diam`) the circles of confusion `coc` use,
/// for [`reverse_mapped_dof`]; an error naming `f_number` when their
/// reads and kernel tests exceed `MAX_REVERSE_OPS` or the used kernels'
/// offsets `MAX_REVERSE_KERNEL_CELLS`.
fn reverse_kernels_used(
    coc: &[f32],
    max_diam: f64,
    steps: usize,
    aperture: &Aperture,
) -> Result<Vec<bool>, NodeError> {
    let index = |c: f64| kernel_step(c, max_diam, steps);
    let max_coc = coc.iter().fold(0.0f32, |m, &c| m.max(c));
    // The kernel of step `s` holds at most this many offsets.
    let cells = |s: usize| {
        let r = (s as f64 * 0.5 * aperture.extent()).ceil();
        (2.0 * r + 1.0).powi(2)
    };
    let mut used = vec![false; steps + 1];
    let mut reads = 0.0f64;
    for &c in coc {
        let c = c as f64;
        if c >= MIN_COC_PX {
            let s = index(c);
            used[s] = true;
            reads += cells(s);
        }
    }
    // building a mask's kernel tests every offset against its samples
    let per_cell = if matches!(aperture, Aperture::Mask(_)) {
        MASK_KERNEL_SAMPLES as f64
    } else {
        1.0
    };
    let (kernel_cells, build): (f64, f64) = (0..=steps)
        .filter(|&s| used[s])
        .map(|s| (cells(s), cells(s) * per_cell))
        .fold((0.0, 0.0), |(a, b), (c, d)| (a + c, b + d));
    if reads + build > MAX_REVERSE_OPS || kernel_cells > MAX_REVERSE_KERNEL_CELLS {
        return Err(NodeError::param(
            "f_number",
            format!(
                "the reverse-mapped blur's largest circle of confusion is {max_coc:.0} px: its \
                 kernels would take {:.1e} offsets and {:.1e} reads and tests, beyond the {:.0e} \
                 and {:.0e} it allows (a larger f_number or a smaller aperture_diameter_mm, or a focus nearer the scene's depths; Refocus has no such limit)",
                kernel_cells,
                reads + build,
                MAX_REVERSE_KERNEL_CELLS,
                MAX_REVERSE_OPS
            ),
        ));
    }
    Ok(used)
}

/// Aperture samples a mask's kernel tests each offset against.
const MASK_KERNEL_SAMPLES: usize = 4096;

/// The reverse-mapped blur's budget of pixel reads (every pixel's kernel)
/// plus kernel tests (each offset, times a mask's samples): about a
/// minute on two cores. Its kernels grow with the square of the circle of
/// confusion and are read whole at every pixel: a lens that blurs by
/// thousands of pixels would run for hours.
const MAX_REVERSE_OPS: f64 = 1e11;

/// The offsets its kernels may hold together (16 bytes each: 1 GiB).
const MAX_REVERSE_KERNEL_CELLS: f64 = (1u64 << 26) as f64;

/// Pixel offsets inside `aperture` scaled to `diameter` pixels; always
/// includes `(0, 0)`. A mask's footprint is that of its points
/// `mask_points` (given for a mask; an analytic shape tests itself).
fn kernel(
    aperture: &Aperture,
    mask_points: Option<&[[f64; 2]]>,
    diameter: f64,
) -> Vec<(isize, isize)> {
    let r = (diameter * aperture.extent()).ceil() as isize;
    let mut out = vec![(0, 0)];
    if diameter <= 0.0 {
        return out;
    }
    for oy in -r..=r {
        for ox in -r..=r {
            if ox == 0 && oy == 0 {
                continue;
            }
            // Guard: diameter > 0 here.
            let (ux, uy) = (ox as f64 / diameter, oy as f64 / diameter);
            let inside = match mask_points {
                // A mask's (centred) footprint: some sample within half a
                // pixel of the offset.
                Some(pts) => {
                    let tol = 0.5 / diameter;
                    pts.iter()
                        .any(|p| (p[0] - ux).abs() <= tol && (p[1] - uy).abs() <= tol)
                }
                None => aperture.contains(ux, uy),
            };
            if inside {
                out.push((ox, oy));
            }
        }
    }
    out
}

depthgraph_graph::ports! {
    /// Inputs of `Refocus` and `ReverseMappedDof`.
    inputs struct RefocusIn {
        /// linear radiance (HDR), all in focus
        color: Arc<ColorImage>,
        /// metres per color pixel, complete; 0 = infinitely far
        depth: Arc<DepthMap>,
        /// custom aperture shape (transmittance), used with aperture = "mask"
        aperture: Option<Arc<Mask>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Refocus`.
    outputs struct RefocusOut {
        /// refocused linear radiance times 2^exposure_stops
        color: ColorImage,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `ReverseMappedDof`.
    outputs struct ReverseOut {
        /// blurred linear radiance times 2^exposure_stops
        color: ColorImage,
    }
}

fn aperture_of(i: &RefocusIn, p: &RefocusParams) -> Result<Aperture, NodeError> {
    Aperture::from_params(p.aperture, p.blades, p.rotation_deg, i.aperture.as_deref())
}

fn eval_refocus(
    ctx: &EvalCtx,
    i: RefocusIn,
    p: &RefocusParams,
) -> Result<Produced<RefocusOut>, NodeError> {
    let aperture = aperture_of(&i, p)?;
    let (color, report) = refocus(&i.color, &i.depth, &aperture, p, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?;
    Ok(produced(RefocusOut { color }, p, &report))
}

/// `Refocus`'s outputs with what `explain` shows: the pass-through reason
/// when nothing was blurred and no lens effect changed the image, and the
/// lens effects that were off (each costs nothing then). Both backends
/// report in these words.
pub fn produced(
    out: RefocusOut,
    p: &RefocusParams,
    report: &RefocusReport,
) -> Produced<RefocusOut> {
    let (lens, fx) = (p.lens(), p.effects());
    let skipped = fx.skipped(&lens);
    let applied = fx.in_image(&lens) || fx.barrel_distance_mm > 0.0;
    let passthrough = (report.samples == 0 && !applied).then(|| sharp_reason(p, report));
    let mut lines = Vec::new();
    if report.samples == 0 && applied {
        let exposure = if p.exposure_stops != 0.0 {
            format!(" and the exposure ({:+} stops)", p.exposure_stops)
        } else {
            String::new()
        };
        lines.push(format!(
            "no blur (circle of confusion below {MIN_COC_PX} px everywhere, largest {:.3} px): \
             only the lens's vignetting and magnification{exposure} applied",
            report.max_coc_px
        ));
    }
    lines.extend(skipped);
    if report.view_filter_px > 0.0 {
        lines.push(format!(
            "the gaps spherical aberration opens between the {} views smoothed \
             (view_filter {}): a Gaussian of up to {:.2} px",
            report.samples, p.view_filter, report.view_filter_px
        ));
    } else if p.spherical_aberration_d != 0.0 && p.view_filter <= 0.0 && report.samples > 0 {
        lines.push(
            "view_filter 0: the gaps spherical aberration opens between the views are left \
             (a bright point's bokeh may show the views as dots)"
                .to_string(),
        );
    }
    if report.frame_pad_px > 0 {
        lines.push(format!(
            "frame extended by {} px on each side (frame_border reflect: the colour mirrored, \
             the depth's planes continued) and cropped back",
            report.frame_pad_px
        ));
    }
    if p.background_layer && report.samples > 0 {
        lines.push(format!(
            "background layer behind foreground edges: {:.1} % of the pixels",
            100.0 * report.layer_fraction
        ));
        if p.background_texture {
            lines.push(format!(
                "background texture continued along its dominant offsets on {:.1} % of the layer",
                100.0 * report.layer_textured
            ));
        }
    }
    Produced {
        out,
        passthrough,
        report: (!lines.is_empty()).then(|| lines.join("; ")),
    }
}

fn eval_reverse(
    _: &EvalCtx,
    i: RefocusIn,
    p: &RefocusParams,
) -> Result<Produced<ReverseOut>, NodeError> {
    let aperture = aperture_of(&i, p)?;
    Ok(ReverseOut {
        color: reverse_mapped_dof(&i.color, &i.depth, &aperture, p)?,
    }
    .into())
}

/// Registers `Refocus` and `ReverseMappedDof`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Refocus",
        4,
        "Thin-lens depth of field by sampling the aperture (realistic-depth-blur Sec. 2.3): one sheared \
         pinhole view per aperture sample, forward-warped with a z-buffer, disocclusions inpainted with the \
         far-depth prior, averaged in linear radiance, then the exposure. Any aperture shape gives its bokeh.\n\
         Passes through when every circle of confusion is under 0.5 px; skips tiles nothing blurred can reach.",
        eval_refocus,
    ))?;
    reg.register(PortedNode::new(
        "ReverseMappedDof",
        2,
        "The common per-pixel gather blur (reverse-mapped z-buffer DoF) that realistic-depth-blur Fig. 5 \
         compares against: each pixel averages the aperture shape scaled to its own circle of confusion, \
         without a depth test (blurred background leaks over sharp edges). For comparisons; use Refocus.",
        eval_reverse,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The active tiles of a frame extended by `pad` (its extension not
    /// blurred) are the input's own, wherever `pad` puts the grid: the
    /// tiles are anchored at the input's corner.
    #[test]
    fn active_tiles_of_an_extended_frame_are_the_inputs() {
        let (w, h) = (70, 45);
        let coc = Image::<f32>::from_fn(w, h, |x, y| {
            if (30..33).contains(&x) && y == 20 {
                3.0
            } else {
                0.1
            }
        });
        let (flags, n) = active_pixels(&coc, 1.0, 0);
        assert!(n > 0 && n < w * h);
        for pad in [1usize, 3, 7, 9, 16, 21] {
            let f = Frame { pad, w, h };
            let (pw, ph) = f.padded_dims();
            let wide = Image::<f32>::from_fn(pw, ph, |x, y| {
                if f.holds(y * pw + x) {
                    *coc.get(x - pad, y - pad)
                } else {
                    0.0
                }
            });
            let (wf, _) = active_pixels(&wide, 1.0, pad);
            let Ok(wf) = Image::<bool>::from_vec(pw, ph, wf) else {
                panic!("sizes");
            };
            assert_eq!(f.crop(&wf).as_slice(), flags.as_slice(), "pad {pad}");
        }
    }

    /// A 3 mm sensor, so that the small test images get large blurs.
    fn params(focus_m: f64, f_number: f64, samples: usize) -> RefocusParams {
        RefocusParams {
            focus_m,
            f_number,
            samples,
            sensor_width_mm: 3.0,
            ..Default::default()
        }
    }

    #[test]
    fn in_focus_plane_is_unchanged_and_energy_is_kept() {
        // A textured plane exactly at the focus distance stays bit-identical.
        let c = ColorImage::from_fn(40, 30, |x, y| [(x * 7 % 13) as f32, (y % 5) as f32, 1.0]);
        let d = DepthMap::filled(40, 30, 2.0);
        let (out, rep) =
            refocus(&c, &d, &Aperture::Disc, &params(2.0, 1.4, 64), |_| Ok(())).unwrap();
        assert_eq!(rep.samples, 0);
        assert_eq!(out, c);
        // Out of focus, a dot in the middle keeps its energy (no holes on a
        // plane: each view is a shift).
        let mut c = ColorImage::filled(64, 64, [0.0; 3]);
        *c.get_mut(32, 32) = [1000.0, 0.0, 0.0];
        let d = DepthMap::filled(64, 64, 6.0);
        let (out, rep) =
            refocus(&c, &d, &Aperture::Disc, &params(1.0, 2.0, 256), |_| Ok(())).unwrap();
        assert!(
            rep.max_coc_px > 20.0 && rep.max_coc_px < 40.0,
            "{}",
            rep.max_coc_px
        );
        let total: f64 = out.as_slice().iter().map(|p| p[0] as f64).sum();
        assert!((total - 1000.0).abs() < 1e-3, "{total}");
        // A plane of one colour stays that colour to the frame's corners,
        // where a view's holes look past the input (their fill found no
        // warped pixel either way and was black: 179 of these 4096 pixels
        // darkened, a corner to 54 %).
        let flat = ColorImage::filled(64, 64, [0.25, 0.5, 1.0]);
        let (out, _) = refocus(&flat, &d, &Aperture::Disc, &params(1.0, 2.0, 256), |_| {
            Ok(())
        })
        .unwrap();
        for (i, p) in out.as_slice().iter().enumerate() {
            for (v, want) in p.iter().zip([0.25f32, 0.5, 1.0]) {
                assert!((v - want).abs() <= 1e-5 * want, "pixel {i}: {p:?}");
            }
        }
    }

    /// `aperture_diameter_mm` overrides `f_number`: a diameter of f/N
    /// renders as f/N (to rounding), a diameter beyond f/0.5 (no real lens)
    /// gives a circle of confusion in proportion, and 0 leaves the lens as
    /// the f-number says (bit for bit).
    #[test]
    fn an_aperture_diameter_overrides_the_f_number() {
        let mut c = ColorImage::filled(64, 64, [0.0; 3]);
        *c.get_mut(32, 32) = [1000.0, 0.0, 0.0];
        let d = DepthMap::filled(64, 64, 6.0);
        let by_n = params(1.0, 2.0, 64);
        let by_d = RefocusParams {
            aperture_diameter_mm: 25.0, // 50 mm / 2
            ..by_n.clone()
        };
        let run = |p: &RefocusParams| refocus(&c, &d, &Aperture::Disc, p, |_| Ok(())).unwrap();
        let ((a, ra), (b, rb)) = (run(&by_n), run(&by_d));
        assert!((ra.max_coc_px - rb.max_coc_px).abs() < 1e-9 * ra.max_coc_px);
        let diff = a
            .as_slice()
            .iter()
            .zip(b.as_slice())
            .map(|(p, q)| (p[0] - q[0]).abs())
            .fold(0.0f32, f32::max);
        assert!(diff < 1e-3, "{diff}");
        // f/0.25: twice the blur of the widest real f-number, f/0.5
        let wide = RefocusParams {
            aperture_diameter_mm: 200.0,
            samples: 8,
            ..by_n.clone()
        };
        let half = RefocusParams {
            f_number: 0.5,
            samples: 8,
            ..by_n.clone()
        };
        let (rw, rh) = (run(&wide).1, run(&half).1);
        assert!(
            (rw.max_coc_px / rh.max_coc_px - 2.0).abs() < 1e-9,
            "{rw:?} {rh:?}"
        );
        assert_eq!(
            by_n.lens(),
            RefocusParams {
                aperture_diameter_mm: 0.0,
                ..by_n.clone()
            }
            .lens()
        );
        assert_eq!(by_n.lens().f_number, 2.0);
    }

    #[test]
    fn bokeh_takes_the_aperture_shape_and_size() {
        // A bright point far behind the focus plane: its spread is the
        // aperture scaled to the CoC, in every shape.
        let (w, h) = (96, 96);
        let mut c = ColorImage::filled(w, h, [0.0; 3]);
        *c.get_mut(48, 48) = [1.0e4; 3];
        let d = DepthMap::filled(w, h, 8.0);
        let p = params(1.5, 2.0, 1024);
        let coc = crate::camera::lens::coc_map(&d, &p.lens())
            .unwrap()
            .as_slice()[0] as f64;
        for ap in [
            Aperture::Disc,
            Aperture::Polygon {
                blades: 6,
                rotation_deg: 0.0,
            },
            Aperture::Polygon {
                blades: 3,
                rotation_deg: 0.0,
            },
        ] {
            let (out, _) = refocus(&c, &d, &ap, &p, |_| Ok(())).unwrap();
            // Lit pixels vs the shape scaled to the CoC around the point.
            let (mut inside_lit, mut inside, mut outside_lit) = (0, 0, 0);
            for y in 0..h {
                for x in 0..w {
                    let (ux, uy) = ((x as f64 - 48.0) / coc, (y as f64 - 48.0) / coc);
                    // The far point moves by C s (1/u - 1/z): shape as s.
                    let lit = out.get(x, y)[0] > 0.0;
                    // Shrink / grow by about a pixel (scaling about the centre:
                    // 4 / coc moves the apothem of the triangle by 1 px) for
                    // the rounding of the warp.
                    let g = 4.0 / coc;
                    let core = ap.contains(ux * (1.0 + g), uy * (1.0 + g));
                    let hull = ap.contains(ux * (1.0 - g), uy * (1.0 - g));
                    if core {
                        inside += 1;
                        inside_lit += lit as usize;
                    }
                    if !hull && lit {
                        outside_lit += 1;
                    }
                }
            }
            assert!(inside > 100, "{ap:?}: CoC {coc}");
            assert!(
                inside_lit as f64 > 0.95 * inside as f64,
                "{ap:?}: {inside_lit}/{inside}"
            );
            assert_eq!(outside_lit, 0, "{ap:?}");
        }
    }

    #[test]
    fn disocclusion_is_filled_from_the_background() {
        // A near dark bar (1 m) in focus in front of a bright far wall (5 m):
        // the wall blurs (CoC about 20 px), the bar stays sharp, and pixels
        // revealed beside the bar take the wall's color (far prior), not the
        // bar's. A blurred constant wall is itself, so any darkening of a wall
        // pixel is bar color that leaked into a hole.
        let (w, h) = (96, 24);
        let bar = 44..52;
        let c = ColorImage::from_fn(
            w,
            h,
            |x, _| if bar.contains(&x) { [0.0; 3] } else { [1.0; 3] },
        );
        let d = DepthMap::from_fn(w, h, |x, _| if bar.contains(&x) { 1.0 } else { 5.0 });
        let p = params(1.0, 2.8, 128);
        let darkening = |p: &RefocusParams| {
            let (out, rep) = refocus(&c, &d, &Aperture::Disc, p, |_| Ok(())).unwrap();
            assert!(rep.hole_fraction > 0.0);
            for y in 0..h {
                // The bar in focus stays exactly dark.
                for x in bar.clone() {
                    assert_eq!(out.get(x, y)[0], 0.0, "({x}, {y})");
                }
            }
            (0..w)
                .filter(|x| !bar.contains(x))
                .map(|x| 1.0 - out.get(x, h / 2)[0] as f64)
                .fold(0.0f64, f64::max)
        };
        let with_prior = darkening(&p);
        let without = darkening(&RefocusParams {
            far_prior: false,
            ..p.clone()
        });
        assert!(with_prior < 0.05, "{with_prior}");
        assert!(without > 2.0 * with_prior, "{without} vs {with_prior}");
    }

    /// Partial occlusion against an exact two-plane ray trace: a near bar
    /// (1.5 m, 6 px wide) before a far wall (3 m) whose colour is a ramp in
    /// x, focused on the wall, between, on the bar and before it. A ray
    /// from output pixel `t` through aperture point `s` meets the bar's
    /// plane at `t - s_x C (1/u - 1/z_bar)`; where the bar is not, it meets
    /// the wall at `t - s_x C (1/u - 1/z_wall)`: the truth, including the
    /// wall hidden behind the bar.
    #[test]
    fn the_background_layer_shows_the_wall_behind_a_blurred_bar() {
        // Taller than the blur, so the middle row sees an endless bar.
        let (w, h) = (96, 48);
        let bar = 45..51;
        let ramp = |x: f64| [(x / w as f64) as f32, 0.2, (1.0 - x / w as f64) as f32];
        let c = ColorImage::from_fn(w, h, |x, _| {
            if bar.contains(&x) {
                [0.9, 0.1, 0.1]
            } else {
                ramp(x as f64)
            }
        });
        let (z_bar, z_wall) = (1.5f32, 3.0f32);
        let d = DepthMap::from_fn(w, h, |x, _| if bar.contains(&x) { z_bar } else { z_wall });
        let rays = Aperture::Disc.samples(4096, 77).unwrap();
        for focus in [3.0, 2.0, 1.5, 1.2] {
            let p = params(focus, 1.4, 256);
            let lens = p.lens();
            let shift = |z: f32| lens.coc_scale(w) * (lens.inv_focus() - 1.0 / z as f64);
            let (shift_bar, shift_wall) = (shift(z_bar), shift(z_wall));
            let truth: Vec<[f64; 3]> = (0..w)
                .map(|t| {
                    let mut acc = [0.0f64; 3];
                    for s in &rays {
                        let x = t as f64 - s[0] * shift_bar;
                        let on_bar = x >= bar.start as f64 - 0.5 && x < bar.end as f64 - 0.5;
                        let v = if on_bar {
                            [0.9, 0.1, 0.1]
                        } else {
                            ramp(t as f64 - s[0] * shift_wall)
                        };
                        for (a, v) in acc.iter_mut().zip(v) {
                            *a += v as f64;
                        }
                    }
                    acc.map(|a| a / rays.len() as f64)
                })
                .collect();
            // Mean error over the bar and the veil around it (middle row).
            let err = |on: bool| {
                let p = RefocusParams {
                    background_layer: on,
                    ..p.clone()
                };
                let (out, _) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
                let cols = 30..66;
                let n = cols.len() as f64 * 3.0;
                cols.map(|x| {
                    (0..3)
                        .map(|k| (out.get(x, h / 2)[k] as f64 - truth[x][k]).abs())
                        .sum::<f64>()
                })
                .sum::<f64>()
                    / n
            };
            let (off, on) = (err(false), err(true));
            eprintln!(
                "focus {focus} m (bar moves {shift_bar:.1} px, wall {shift_wall:.1} px): \
                 mean abs error per-view fill {off:.5}, background layer {on:.5}"
            );
            assert!(on < 0.0025, "focus {focus}: layer {on}");
            // explain says how much of the image had a background behind it
            // (the bar, 6 of 96 columns, within reach of the wall)
            let on_p = RefocusParams {
                background_layer: true,
                ..p.clone()
            };
            let (out, report) = refocus(&c, &d, &Aperture::Disc, &on_p, |_| Ok(())).unwrap();
            assert!(
                (report.layer_fraction - 6.0 / 96.0).abs() < 1e-9,
                "{}",
                report.layer_fraction
            );
            let note = produced(RefocusOut { color: out }, &on_p, &report).report;
            assert!(
                note.as_deref()
                    .unwrap_or("")
                    .contains("background layer behind foreground edges: 6.2 %"),
                "{note:?}"
            );
            if focus == 3.0 {
                // The wall in focus: its hidden part never moves, both are
                // close; the layer interpolates the ramp across the bar.
                assert!(
                    on <= off,
                    "focus {focus}: layer {on} vs per-view fill {off}"
                );
            } else {
                // A blurred wall: its hidden part is revealed in every view
                // alike with the layer, by each view's own guess without.
                assert!(
                    on < 0.8 * off,
                    "focus {focus}: layer {on} vs per-view fill {off}"
                );
            }
        }
    }

    /// The reverse-mapped blur builds only the kernel sizes some pixel
    /// uses (one pixel 1 cm from a 640x480 camera blurs by the 1280 px cap:
    /// every size up to it took 17 GB), and a blur it cannot afford is an
    /// error naming `f_number` before anything is built.
    #[test]
    fn the_reverse_mapped_blur_builds_only_the_kernels_it_uses() {
        let (w, h) = (640, 480);
        let max_diam = 2.0 * w as f64;
        let steps = (max_diam * 2.0).ceil() as usize + 1;
        let mut coc = vec![0.0f32; w * h];
        coc[0] = 5000.0;
        coc[1] = 3.0;
        let used = reverse_kernels_used(&coc, max_diam, steps, &Aperture::Disc).unwrap();
        let sizes: Vec<usize> = (0..=steps).filter(|&s| used[s]).collect();
        assert_eq!(sizes, vec![6, steps - 1]);
        // every pixel at that blur: 5e11 reads, refused with the parameter's name
        let all = vec![5000.0f32; w * h];
        let e = reverse_kernels_used(&all, max_diam, steps, &Aperture::Disc)
            .unwrap_err()
            .to_string();
        assert!(e.contains("f_number") && e.contains("5000 px"), "{e}");
        // the sharp pixels need none
        assert!(
            reverse_kernels_used(&vec![0.2f32; w * h], max_diam, steps, &Aperture::Disc)
                .unwrap()
                .iter()
                .all(|u| !u)
        );
    }

    /// A finite colour times the largest exposure gain stays finite: f32's
    /// largest value, never +inf, in the blurred and the sharp pixels and
    /// in the reverse-mapped blur.
    #[test]
    fn a_bright_colour_at_the_largest_exposure_stays_finite() {
        let (w, h) = (32, 24);
        let c = ColorImage::from_fn(w, h, |x, _| if x % 5 == 0 { [1e30; 3] } else { [0.5; 3] });
        let d = DepthMap::from_fn(w, h, |x, _| if x < 16 { 1.0 } else { 3.0 });
        let p = RefocusParams {
            exposure_stops: 30.0,
            ..params(1.0, 1.4, 16)
        };
        // blurred, and (a plane in focus) passed through with the gain
        let flat = DepthMap::filled(w, h, 1.0);
        for depth in [&d, &flat] {
            let (out, _) = refocus(&c, depth, &Aperture::Disc, &p, |_| Ok(())).unwrap();
            assert!(out.as_slice().iter().flatten().all(|v| v.is_finite()));
            assert!(out.as_slice().iter().flatten().any(|v| *v == f32::MAX));
            let rev = reverse_mapped_dof(&c, depth, &Aperture::Disc, &p).unwrap();
            assert!(rev.as_slice().iter().flatten().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn thread_count_does_not_change_bits() {
        let (w, h) = (64, 48);
        let c = ColorImage::from_fn(w, h, |x, y| [(x % 9) as f32 * 3.0, (y % 7) as f32, 0.5]);
        let d = DepthMap::from_fn(w, h, |x, y| 0.8 + ((x / 8 + y / 6) % 4) as f32);
        for background_layer in [false, true] {
            let p = RefocusParams {
                background_layer,
                ..params(1.5, 1.8, 48)
            };
            let run = |threads| {
                crate::test_support::with_threads(threads, || {
                    refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap().0
                })
            };
            let (a, b) = (run(1), run(2));
            assert!(
                a.as_slice()
                    .iter()
                    .zip(b.as_slice())
                    .all(|(p, q)| { p.iter().zip(q).all(|(u, v)| u.to_bits() == v.to_bits()) }),
                "background_layer {background_layer}"
            );
        }
    }

    #[test]
    fn hard_inputs_give_finite_outputs() {
        let (w, h) = (24, 16);
        let c = ColorImage::from_fn(w, h, |x, y| match (x + y) % 5 {
            0 => [f32::NAN, 1.0, 1.0],
            1 => [f32::INFINITY, -3.0, 1e30],
            _ => [0.5; 3],
        });
        let d = DepthMap::from_fn(w, h, |x, _| match x % 4 {
            0 => 0.0,
            1 => f32::NAN,
            2 => -2.0,
            _ => 1.0e-3,
        });
        for (focus, n) in [(f64::INFINITY, 0.7), (0.06, 0.7), (2.0, 1000.0), (1e9, 2.0)] {
            let p = params(focus, n, 16);
            let (out, _) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
            assert!(
                out.as_slice()
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite() && *v >= 0.0)
            );
            // The background layer over the same hard depths (1 mm beside
            // the sky: the largest reach there is).
            let layered = RefocusParams {
                background_layer: true,
                ..p.clone()
            };
            let (out, _) = refocus(&c, &d, &Aperture::Disc, &layered, |_| Ok(())).unwrap();
            assert!(
                out.as_slice()
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite() && *v >= 0.0),
                "focus {focus}, f/{n}, with the background layer"
            );
            let rev = reverse_mapped_dof(&c, &d, &Aperture::Disc, &p).unwrap();
            assert!(
                rev.as_slice()
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite() && *v >= 0.0)
            );
        }
        // Focus nearer than the focal length is an error naming focus_m.
        let e = refocus(&c, &d, &Aperture::Disc, &params(0.01, 2.0, 16), |_| Ok(()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("focus_m"), "{e}");
        // A size mismatch names the depth port.
        let small = DepthMap::filled(3, 3, 1.0);
        let e = refocus(&c, &small, &Aperture::Disc, &params(2.0, 2.0, 16), |_| {
            Ok(())
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("depth"), "{e}");
        // A one-pixel aperture mask is nearly a pinhole: the samples lie
        // within 1/14 of the diameter of the centre, so a pixel moves by at
        // most 0.1 * CoC (about 0.8 px here) and a ramp of slope 1 per pixel
        // changes by at most one.
        let mut m = Mask::filled(7, 7, 0.0);
        *m.get_mut(3, 3) = 1.0;
        let c = ColorImage::from_fn(w, h, |x, _| [x as f32; 3]);
        let d = DepthMap::filled(w, h, 1.0);
        let p = params(5.0, 2.0, 32);
        let coc = crate::camera::lens::coc_map(&d, &p.lens())
            .unwrap()
            .as_slice()[0];
        assert!(coc > 5.0, "{coc}");
        let (out, rep) = refocus(&c, &d, &Aperture::Mask(m), &p, |_| Ok(())).unwrap();
        assert_eq!(rep.samples, 32);
        for y in 0..h {
            for x in 2..w - 2 {
                let e = (out.get(x, y)[0] - x as f32).abs();
                assert!(e <= 1.0, "({x}, {y}): {e}");
            }
        }
    }

    /// With nothing to blur but a lens effect on, `explain` names every
    /// change made to the image: the exposure too (it was left out).
    #[test]
    fn a_sharp_image_reports_its_exposure_with_the_lens_effects() {
        let (w, h) = (24, 16);
        let c = ColorImage::from_fn(w, h, |x, _| [x as f32 / 24.0; 3]);
        let p = RefocusParams {
            natural_vignetting: 4.0,
            exposure_stops: 1.0,
            ..params(2.0, 5.0, 32)
        };
        // everything at the focus distance: no blur
        let d = DepthMap::filled(w, h, 2.0);
        let (out, report) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
        assert_eq!(report.samples, 0);
        let note = produced(RefocusOut { color: out }, &p, &report).report;
        let note = note.unwrap_or_default();
        assert!(
            note.contains("vignetting and magnification and the exposure (+1 stops) applied"),
            "{note}"
        );
    }

    /// An aperture mask that lets no light through is an error for the
    /// reverse-mapped blur too (it returned the image unblurred: its
    /// kernels fell back to a test no offset passed).
    #[test]
    fn reverse_mapped_refuses_a_closed_mask() {
        let (w, h) = (24, 16);
        let c = ColorImage::from_fn(w, h, |x, _| [x as f32; 3]);
        let d = DepthMap::filled(w, h, 1.0);
        let p = params(5.0, 2.0, 32);
        let e = reverse_mapped_dof(&c, &d, &Aperture::Mask(Mask::filled(5, 5, 0.0)), &p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no open pixel"), "{e}");
        // an open mask blurs the ramp's ends
        let out = reverse_mapped_dof(&c, &d, &Aperture::Mask(Mask::filled(5, 5, 1.0)), &p).unwrap();
        assert!(out.get(0, 8)[0] > 0.5, "{:?}", out.get(0, 8));
    }

    #[test]
    fn reverse_mapped_darkens_the_wall_beside_a_sharp_bar() {
        // The Fig. 5 artefact: focused on a near dark bar in front of a bright
        // far wall, the gather blur averages the dark bar into the wall next to
        // it (no depth test), while a real lens sees the whole wall there.
        let (w, h) = (96, 20);
        let bar = 44..52;
        let c = ColorImage::from_fn(
            w,
            h,
            |x, _| if bar.contains(&x) { [0.0; 3] } else { [1.0; 3] },
        );
        let d = DepthMap::from_fn(w, h, |x, _| if bar.contains(&x) { 1.0 } else { 5.0 });
        let p = params(1.0, 2.8, 64);
        let rev = reverse_mapped_dof(&c, &d, &Aperture::Disc, &p).unwrap();
        let (refo, _) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
        let x = 41;
        assert!(rev.get(x, 10)[0] < 0.8, "{:?}", rev.get(x, 10));
        assert!(refo.get(x, 10)[0] > 0.95, "{:?}", refo.get(x, 10));
    }

    #[test]
    fn sharp_tiles_out_of_reach_are_skipped_and_untouched() {
        // A 128x64 image in focus except a small far patch at the right: only
        // the tiles the patch's blur can reach are warped.
        let (w, h) = (128, 64);
        let c = ColorImage::from_fn(w, h, |x, y| [(x % 11) as f32, (y % 3) as f32, 2.0]);
        let d = DepthMap::from_fn(w, h, |x, y| {
            if (112..120).contains(&x) && (28..36).contains(&y) {
                3.0
            } else {
                1.0
            }
        });
        let p = params(1.0, 8.0, 32);
        let coc = crate::camera::lens::coc_map(&d, &p.lens()).unwrap();
        let max = coc.as_slice().iter().fold(0.0f32, |m, &v| m.max(v));
        assert!(max > 2.0 && max < 16.0, "{max}");
        let (out, rep) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
        assert!(rep.samples == 32 && rep.active_fraction < 0.5, "{rep:?}");
        for y in 0..h {
            for x in 0..64 {
                assert_eq!(out.get(x, y), c.get(x, y), "({x}, {y})");
            }
        }
        assert_ne!(out, c);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Stability: any depth (including 0, NaN, negative, 1 mm and 1000 m)
        /// and any lens in range give finite, non-negative images whose values
        /// stay within the range of the input radiance (a mean of views of the
        /// input, never an extrapolation), for Refocus and the gather blur.
        #[test]
        fn outputs_are_finite_and_within_the_input_range(
            w in 1usize..20, h in 1usize..20,
            seed in proptest::prelude::any::<u64>(),
            f_number in proptest::prop_oneof![proptest::prelude::Just(0.7), proptest::prelude::Just(2.0), proptest::prelude::Just(1000.0)],
            focus in proptest::prop_oneof![proptest::prelude::Just(0.06), proptest::prelude::Just(1.0), proptest::prelude::Just(f64::INFINITY)],
        ) {
            let mut s = seed;
            let mut next = || { s = crate::kit::rng::splitmix64(s); (s >> 11) as f64 / (1u64 << 53) as f64 };
            let d = DepthMap::from_fn(w, h, |_, _| match (next() * 6.0) as u32 {
                0 => 0.0,
                1 => f32::NAN,
                2 => -1.0,
                3 => 1.0e-3,
                4 => 1000.0,
                _ => (0.2 + 5.0 * next()) as f32,
            });
            let c = ColorImage::from_fn(w, h, |_, _| [(next() * 50.0) as f32, next() as f32, 0.0]);
            let hi = c.as_slice().iter().flatten().fold(0.0f32, |m, v| m.max(*v));
            let p = RefocusParams { focus_m: focus, f_number, samples: 8, sensor_width_mm: 3.0, ..Default::default() };
            let (out, _) = refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())).unwrap();
            let rev = reverse_mapped_dof(&c, &d, &Aperture::Disc, &p).unwrap();
            for v in out.as_slice().iter().chain(rev.as_slice()).flatten() {
                proptest::prop_assert!(v.is_finite() && *v >= 0.0 && *v <= hi * (1.0 + 1e-5), "{} vs {}", v, hi);
            }
        }
    }

    #[test]
    fn auto_samples_grow_with_the_blur() {
        assert_eq!(auto_samples(0.0, 1.0), AUTO_SAMPLES.0);
        assert_eq!(auto_samples(20.0, 1.0), 79);
        assert_eq!(auto_samples(1.0e9, 1.0), AUTO_SAMPLES.1);
        assert!(auto_samples(20.0, 2.0) > auto_samples(20.0, 1.0));
    }
}

#[cfg(test)]
mod ground_truth {
    use super::*;
    use crate::sim::synthetic::{RenderOptions, Scene, ThinLensRender, render, render_thin_lens};

    /// RMSE of display values (linear clamped to [0, 1]), f64 sums.
    fn display_rmse(a: &ColorImage, b: &ColorImage) -> f64 {
        let s: f64 = a
            .as_slice()
            .iter()
            .flatten()
            .zip(b.as_slice().iter().flatten())
            .map(|(x, y)| (x.clamp(0.0, 1.0) as f64 - y.clamp(0.0, 1.0) as f64).powi(2))
            .sum();
        (s / (a.len() * 3) as f64).sqrt()
    }

    #[test]
    fn refocus_beats_reverse_mapping_against_the_thin_lens() {
        // The Fig. 5 comparison on the tabletop (a near mug and a tall
        // cylinder in front of a wall with bright emitters), focused near and
        // far; ground truth by distributed ray tracing through the same lens.
        let (w, h) = (96, 72);
        let scene = Scene::preset("tabletop", w, h).unwrap();
        let pin = render(&scene, &RenderOptions::default());
        for focus_m in [0.95, 2.8] {
            let p = RefocusParams {
                focus_m,
                f_number: 1.4,
                // 36 mm at 640 px: the same blur in pixels as a full frame.
                sensor_width_mm: 36.0 * w as f64 / 640.0,
                samples: 256,
                ..Default::default()
            };
            let gt = render_thin_lens(
                &scene,
                &ThinLensRender {
                    lens: p.lens(),
                    aperture: Aperture::Disc,
                    samples: 256,
                    seed: 9,
                    effects: Default::default(),
                    pixel_area: false,
                },
                |_| Ok(()),
            )
            .unwrap();
            let (ours, rep) =
                refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).unwrap();
            let rev = reverse_mapped_dof(&pin.color, &pin.depth, &Aperture::Disc, &p).unwrap();
            let sharp = display_rmse(&pin.color, &gt);
            let (e_ours, e_rev) = (display_rmse(&ours, &gt), display_rmse(&rev, &gt));
            eprintln!(
                "focus {focus_m} m: max CoC {:.1} px, rmse pinhole {sharp:.4}, refocus {e_ours:.4}, reverse {e_rev:.4}",
                rep.max_coc_px
            );
            assert!(rep.max_coc_px > 3.0);
            assert!(e_ours < e_rev, "focus {focus_m}: {e_ours} vs {e_rev}");
            assert!(
                e_ours < 0.5 * sharp,
                "focus {focus_m}: {e_ours} vs pinhole {sharp}"
            );
        }
    }
}
