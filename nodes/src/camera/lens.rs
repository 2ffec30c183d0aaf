//! The virtual thin-lens camera of the depth-blur paper ("realistic depth
//! blur", Sec. 2.3): the circle of confusion of a depth, and aperture shapes
//! with stratified samples over them.
//!
//! # Units and the circle of confusion
//!
//! The lens has focal length `f` (mm), f-number `N` and is focused at
//! distance `u` (metres, `inf` allowed); its aperture diameter is
//! `A = f / N`. The sensor is `sensor_width_mm` wide and maps onto the image
//! width of `W` pixels, so a pixel is `p = sensor_width_mm / W` mm and the
//! focal length in pixels is `f_px = f / p`. A point at depth `z` is imaged
//! as a blur of diameter (the thin-lens circle of confusion)
//!
//! `coc_px(z) = C * |1/z - 1/u|`,  with  `C = f_px * A * u / (u - f)` (pixel metres),
//!
//! where `u / (u - f)` is the magnification of a lens focused at `u`
//! (1 at infinity). Rendering the image from a point `s` of the aperture
//! (`s` in units of the aperture diameter, `|s| <= 1/2` for a disc) through a
//! pinhole sheared so that the plane at `u` stays fixed moves a pixel of
//! depth `z` by
//!
//! `d(s, z) = C * s * (1/u - 1/z)`  pixels,
//!
//! which is what the paper's per-sample reprojection does (Sec. 2.3: "
//! translating the viewpoint according to the 2D displacement on the lens
//! ... and perturbing the view frustum such that the image coordinates of
//! points at a chosen distance u remain unchanged"). The set of `d(s, z)` over
//! the aperture is the aperture's shape scaled to `coc_px(z)`: this is where
//! bokeh comes from. [`crate::sim::synthetic::render_thin_lens`] traces rays with
//! exactly this lens so the two can be compared.
//!
//! Pixels without a depth measurement (0, negative, NaN) are treated as
//! infinitely far (`1/z = 0`): in the synthetic scenes and in most photos
//! they are the sky.

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use rayon::prelude::*;

use crate::kit::rng::splitmix64;

depthgraph_graph::param_choice! {
    /// The diaphragm's shape (the `aperture` parameter).
    pub enum ApertureShape {
        /// Round.
        Disc = "disc",
        /// A regular polygon of `blades` sides.
        Polygon = "polygon",
        /// A regular triangle.
        Triangle = "triangle",
        /// A custom shape from a Mask input.
        Mask = "mask",
    }
}

/// A thin lens and the sensor it images onto.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThinLens {
    /// Focal length in millimetres.
    pub focal_length_mm: f64,
    /// f-number `N`: the aperture diameter is `focal_length_mm / N`.
    pub f_number: f64,
    /// Focus distance in metres; `f64::INFINITY` focuses at infinity.
    pub focus_m: f64,
    /// Width of the sensor in millimetres; it spans the image width.
    pub sensor_width_mm: f64,
}

/// The f-number of a lens whose aperture is given as a diameter when
/// `aperture_diameter_mm > 0` (`focal_length_mm / aperture_diameter_mm`,
/// which may be below any real lens's f/0.5: a virtual camera's
/// exaggerated blur), else `f_number` as given.
pub fn effective_f_number(focal_length_mm: f64, f_number: f64, aperture_diameter_mm: f64) -> f64 {
    if aperture_diameter_mm > 0.0 && aperture_diameter_mm.is_finite() {
        // guard: the diameter is positive and finite here
        focal_length_mm / aperture_diameter_mm
    } else {
        f_number
    }
}

impl ThinLens {
    /// Checks the lens: positive finite focal length, f-number and sensor
    /// width, and a focus distance beyond the focal length (a thin lens
    /// cannot form a real image of a nearer plane). Errors name the
    /// parameter.
    pub fn validate(&self) -> Result<(), NodeError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.focal_length_mm) {
            return Err(NodeError::param(
                "focal_length_mm",
                format!(
                    "must be a positive number of millimetres, got {}",
                    self.focal_length_mm
                ),
            ));
        }
        if !positive(self.f_number) {
            return Err(NodeError::param(
                "f_number",
                format!("must be positive, got {}", self.f_number),
            ));
        }
        if !positive(self.sensor_width_mm) {
            return Err(NodeError::param(
                "sensor_width_mm",
                format!(
                    "must be a positive number of millimetres, got {}",
                    self.sensor_width_mm
                ),
            ));
        }
        let f_m = self.focal_length_mm * 1e-3;
        if self.focus_m.is_nan() || self.focus_m <= f_m {
            return Err(NodeError::param(
                "focus_m",
                format!(
                    "the focus distance ({} m) must be farther than the focal length ({} mm): \
                     a thin lens cannot focus on a plane nearer than its focal length",
                    self.focus_m, self.focal_length_mm
                ),
            ));
        }
        Ok(())
    }

    /// `1 / u`, 0 when focused at infinity.
    pub fn inv_focus(&self) -> f64 {
        if self.focus_m.is_finite() {
            // Guard: validate() ensures focus_m > focal length > 0.
            1.0 / self.focus_m
        } else {
            0.0
        }
    }

    /// The focal length in pixels of an image `width_px` wide (the sensor
    /// spans the width). Guard: `sensor_width_mm > 0` for a validated lens.
    pub fn f_px(&self, width_px: usize) -> f64 {
        self.focal_length_mm * width_px as f64 / self.sensor_width_mm
    }

    /// The constant `C` (pixel metres) of `coc_px(z) = C |1/z - 1/u|` for
    /// an image `width_px` wide (see the module docs). Call
    /// [`validate`](Self::validate) first.
    pub fn coc_scale(&self, width_px: usize) -> f64 {
        let f_m = self.focal_length_mm * 1e-3;
        // Guards: sensor_width_mm > 0 and f_number > 0 (validate); width 0
        // gives C = 0 (an empty image has no blur).
        let f_px = self.f_px(width_px);
        let aperture_m = f_m / self.f_number;
        // u / (u - f) = 1 / (1 - f/u); f/u < 1 by validate, so the
        // denominator is positive.
        let magnification = 1.0 / (1.0 - f_m * self.inv_focus());
        f_px * aperture_m * magnification
    }
}

/// Per-channel sign of the chromatic aberrations: red focuses (and is
/// magnified) one way, blue the other, green is the reference.
pub const CHANNEL_SIGN: [f64; 3] = [1.0, 0.0, -1.0];

/// What a real lens adds to the perfect thin lens (the depth-blur paper's
/// future work: "include several other optical effects of real cameras (e.g.
/// spherical and chromatic aberrations)"). Every effect is off at its zero
/// value and then costs nothing. The model, shared by `Refocus` and the
/// ray-traced truth ([`crate::sim::synthetic::render_thin_lens`]):
///
/// - **Focus per aperture point and channel.** The ray from aperture point
///   `s` (aperture diameters, radius `r = 2|s|`, 1 at a disc's rim) in
///   channel `c` focuses at inverse distance
///   `1/u_c(s) = 1/u + S r^2 + k_c L`  (dioptres),
///   with `S` = `spherical_d` (spherical aberration: the focus moves with the
///   radius on the aperture), `L` = `chromatic_longitudinal_d` (longitudinal
///   chromatic aberration) and `k = (+1, 0, -1)` for red, green, blue
///   ([`CHANNEL_SIGN`]). A point at inverse depth `v` then moves by
///   `C s (1/u_c(s) - v)` pixels (the module docs' `d(s, z)` with the
///   per-ray focus), so `S` and `L` add a constant shift per view and
///   channel: `C s (S r^2 + k_c L)`.
/// - **Optical vignetting.** A lens barrel (a circular opening of diameter
///   `B` = `barrel_diameter_mm`, the aperture's diameter `A` when 0) sits
///   `l` = `barrel_distance_mm` in front of the stop. The ray from `s`
///   towards the focus point of the image point `x` crosses it at
///   `s (1 - l/u) + (l / A) t(x)` aperture diameters, `t(x) = (x - centre) /
///   f_px` (the field angle's tangent, from the virtual lens); the ray passes
///   when that lies within `B / 2A`. Off the axis the open part of the
///   aperture is the lens-shaped overlap of two discs: cat's-eye bokeh,
///   long across the radius, and corners darker by the closed fraction.
/// - **Natural vignetting.** Irradiance falls off as `cos^4` of the field
///   angle: the image is multiplied by `(1 + |t(x)|^2)^(-2 k)`, `k` =
///   `natural_vignetting` (1 is the physical law).
/// - **Magnification per channel and focus breathing.** Channel `c` is
///   magnified about the image centre by `M_c = b (1 + k_c m)`, `m` =
///   `chromatic_lateral` (lateral chromatic aberration), `b = u / (u - f)`
///   with `focus_breathing` (a lens that focuses by moving away from the
///   sensor: the input's field of view is the lens's at infinity and
///   focusing nearer narrows it) and `b = 1` without (the field of view stays
///   the input's at every focus distance, today's model). The value at output
///   pixel `x` is the unmagnified image at `centre + (x - centre) / M_c`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LensEffects {
    /// `S`: inverse focus shift at the aperture's rim, dioptres (1/m);
    /// positive: the rim focuses nearer (under-corrected, like a simple lens).
    pub spherical_d: f64,
    /// `L`: red focuses at `1/u + L`, blue at `1/u - L`, dioptres.
    pub chromatic_longitudinal_d: f64,
    /// `m`: red is magnified by `1 + m`, blue by `1 - m`.
    pub chromatic_lateral: f64,
    /// `l`: distance of the barrel in front of the stop, mm; 0 = no optical
    /// vignetting.
    pub barrel_distance_mm: f64,
    /// `B`: the barrel's diameter, mm; 0 = the aperture's diameter.
    pub barrel_diameter_mm: f64,
    /// `k` of the `cos^(4k)` falloff; 0 = none, 1 = physical.
    pub natural_vignetting: f64,
    /// Field of view narrowing as the focus comes nearer (see above).
    pub focus_breathing: bool,
}

/// The barrel clip of [`LensEffects`] for one image: whether the ray from an
/// aperture point to an image point passes the barrel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Barrel {
    /// Image centre, continuous pixel coordinates.
    pub centre: [f64; 2],
    /// `1 - l/u`: the aperture point's weight where the ray crosses.
    pub along: f64,
    /// `l / (A f_px)`: aperture diameters per pixel off the centre.
    pub per_px: f64,
    /// Squared radius of the barrel in aperture diameters, `(B / 2A)^2`.
    pub radius2: f64,
}

impl Barrel {
    /// True when the ray from aperture point `s` towards continuous image
    /// point `(x, y)` passes the barrel.
    #[inline]
    pub fn open(&self, s: [f64; 2], x: f64, y: f64) -> bool {
        let px = s[0] * self.along + self.per_px * (x - self.centre[0]);
        let py = s[1] * self.along + self.per_px * (y - self.centre[1]);
        px * px + py * py <= self.radius2
    }
}

impl LensEffects {
    /// Checks the effects: finite values, a non-negative barrel and falloff,
    /// magnifications that stay positive. Errors name the parameter.
    pub fn validate(&self) -> Result<(), NodeError> {
        let finite = |name: &str, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(NodeError::param(
                    name,
                    format!("must be a finite number, got {v}"),
                ))
            }
        };
        finite("spherical_aberration_d", self.spherical_d)?;
        finite("chromatic_longitudinal_d", self.chromatic_longitudinal_d)?;
        finite("chromatic_lateral", self.chromatic_lateral)?;
        for (name, v) in [
            ("barrel_distance_mm", self.barrel_distance_mm),
            ("barrel_diameter_mm", self.barrel_diameter_mm),
            ("natural_vignetting", self.natural_vignetting),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(NodeError::param(
                    name,
                    format!("must be zero or a positive number, got {v}"),
                ));
            }
        }
        if self.chromatic_lateral.abs() >= 0.5 {
            return Err(NodeError::param(
                "chromatic_lateral",
                format!(
                    "must lie within (-0.5, 0.5): red and blue are magnified by 1 +- this, got {}",
                    self.chromatic_lateral
                ),
            ));
        }
        Ok(())
    }

    /// True when some effect changes the views themselves (the focus per
    /// aperture point or channel, or the barrel), not only the final image.
    pub fn in_views(&self) -> bool {
        self.spherical_d != 0.0
            || self.chromatic_longitudinal_d != 0.0
            || self.barrel_distance_mm > 0.0
    }

    /// True when the channels focus apart (longitudinal chromatic
    /// aberration): each view's channels are read at their own offsets.
    pub fn channels_split(&self) -> bool {
        self.chromatic_longitudinal_d != 0.0
    }

    /// True when the final image is resampled or darkened (magnification
    /// per channel, breathing, natural vignetting).
    pub fn in_image(&self, lens: &ThinLens) -> bool {
        self.natural_vignetting > 0.0 || (0..3).any(|c| self.magnification(lens, c) != 1.0)
    }

    /// The inverse-focus offset `S r^2 + k_c L` (dioptres) of aperture point
    /// `s` in channel `c` (see the type's docs).
    #[inline]
    pub fn focus_offset(&self, s: [f64; 2], c: usize) -> f64 {
        let r2 = 4.0 * (s[0] * s[0] + s[1] * s[1]);
        self.spherical_d * r2 + CHANNEL_SIGN[c] * self.chromatic_longitudinal_d
    }

    /// The largest `|S r^2 + k_c L|` over an aperture whose points lie
    /// within `extent` aperture diameters of its centre.
    pub fn max_focus_offset(&self, extent: f64) -> f64 {
        let r2 = 4.0 * extent * extent;
        self.spherical_d.abs() * r2 + self.chromatic_longitudinal_d.abs()
    }

    /// `M_c`, the magnification of channel `c` (see the type's docs).
    pub fn magnification(&self, lens: &ThinLens, c: usize) -> f64 {
        let f_m = lens.focal_length_mm * 1e-3;
        // u / (u - f) = 1 / (1 - f/u); f/u < 1 for a validated lens.
        let breathing = if self.focus_breathing {
            1.0 / (1.0 - f_m * lens.inv_focus())
        } else {
            1.0
        };
        breathing * (1.0 + CHANNEL_SIGN[c] * self.chromatic_lateral)
    }

    /// The barrel clip for a `width` x `height` image, `None` without one.
    pub fn barrel(&self, lens: &ThinLens, width: usize, height: usize) -> Option<Barrel> {
        if self.barrel_distance_mm <= 0.0 {
            return None;
        }
        // Guard: f_number > 0 for a validated lens, so A > 0.
        let a_mm = lens.focal_length_mm / lens.f_number;
        let b_mm = if self.barrel_diameter_mm > 0.0 {
            self.barrel_diameter_mm
        } else {
            a_mm
        };
        let f_px = lens.f_px(width).max(f64::MIN_POSITIVE);
        let r = b_mm / (2.0 * a_mm);
        Some(Barrel {
            centre: [width as f64 / 2.0, height as f64 / 2.0],
            along: 1.0 - self.barrel_distance_mm * 1e-3 * lens.inv_focus(),
            // Guard: a_mm > 0 and f_px > 0.
            per_px: self.barrel_distance_mm / (a_mm * f_px),
            radius2: r * r,
        })
    }

    /// The natural vignetting factor `(1 + |t|^2)^(-2k)` at continuous image
    /// point `(x, y)` of a `width` x `height` image.
    pub fn natural_factor(
        &self,
        lens: &ThinLens,
        width: usize,
        height: usize,
        x: f64,
        y: f64,
    ) -> f64 {
        if self.natural_vignetting <= 0.0 {
            return 1.0;
        }
        let f_px = lens.f_px(width).max(f64::MIN_POSITIVE);
        // Guard: f_px > 0.
        let tx = (x - width as f64 / 2.0) / f_px;
        let ty = (y - height as f64 / 2.0) / f_px;
        (1.0 + tx * tx + ty * ty).powf(-2.0 * self.natural_vignetting)
    }

    /// One line per effect that is off, in the words `explain` shows.
    pub fn skipped(&self, lens: &ThinLens) -> Vec<String> {
        let mut out = Vec::new();
        if self.spherical_d == 0.0 {
            out.push("no spherical aberration: spherical_aberration_d 0".to_string());
        }
        if self.chromatic_longitudinal_d == 0.0 && self.chromatic_lateral == 0.0 {
            out.push("no chromatic aberration: lateral and longitudinal 0".to_string());
        }
        if self.barrel_distance_mm <= 0.0 {
            out.push("no optical vignetting: barrel_distance_mm 0".to_string());
        }
        if self.natural_vignetting <= 0.0 {
            out.push("no natural vignetting: natural_vignetting 0".to_string());
        }
        if !self.focus_breathing || self.magnification(lens, 1) == 1.0 {
            out.push("no focus breathing: the field of view stays the input's".to_string());
        }
        out
    }
}

/// Bilinear interpolation at pixel-index point `(x, y)` (pixel centres at
/// integers) of the values `at(index)` of a non-empty `w` x `h` image,
/// edges clamped.
pub fn bilinear(w: usize, h: usize, x: f64, y: f64, at: impl Fn(usize) -> f32) -> f64 {
    let x = x.clamp(0.0, w.saturating_sub(1) as f64);
    let y = y.clamp(0.0, h.saturating_sub(1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (x - x0 as f64, y - y0 as f64);
    let v = |i: usize, j: usize| at(j * w + i) as f64;
    (v(x0, y0) * (1.0 - ax) + v(x1, y0) * ax) * (1.0 - ay)
        + (v(x0, y1) * (1.0 - ax) + v(x1, y1) * ax) * ay
}

/// Applies the image-wide effects of [`LensEffects`] to a rendered `image`
/// in place of the unmagnified one: each channel resampled (bilinear, edges
/// clamped) at `centre + (x - centre) / M_c`, then the natural vignetting.
/// Returns the image unchanged (bit for bit) when neither is on.
pub fn apply_image_effects(image: ColorImage, fx: &LensEffects, lens: &ThinLens) -> ColorImage {
    if !fx.in_image(lens) || image.is_empty() {
        return image;
    }
    let (w, h) = image.dims();
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let inv_m: [f64; 3] = std::array::from_fn(|c| {
        // Guard: M_c > 0 (|chromatic_lateral| < 1/2 by validate, breathing >= 1).
        1.0 / fx.magnification(lens, c)
    });
    let src = image.as_slice();
    let resample = (0..3).any(|c| inv_m[c] != 1.0);
    let data: Vec<Rgb> = (0..w * h)
        .into_par_iter()
        .map(|t| {
            let (px, py) = ((t % w) as f64 + 0.5, (t / w) as f64 + 0.5);
            let v = fx.natural_factor(lens, w, h, px, py);
            std::array::from_fn(|c| {
                let raw = if resample && inv_m[c] != 1.0 {
                    let qx = cx + (px - cx) * inv_m[c] - 0.5;
                    let qy = cy + (py - cy) * inv_m[c] - 0.5;
                    bilinear(w, h, qx, qy, |j| src[j][c])
                } else {
                    src[t][c] as f64
                };
                (raw * v) as f32
            })
        })
        .collect();
    Image::from_vec(w, h, data).unwrap_or(image)
}

/// `1 / z` of a depth sample, 0 for no measurement (treated as infinitely
/// far, see the module docs).
#[inline]
pub fn inv_depth(z: f32) -> f64 {
    if DepthMap::is_valid(z) {
        1.0 / z as f64
    } else {
        0.0
    }
}

/// Circle-of-confusion diameter in pixels of every pixel of `depth`:
/// `C |1/z - 1/u|` with `C` = [`ThinLens::coc_scale`].
pub fn coc_map(depth: &DepthMap, lens: &ThinLens) -> Result<Image<f32>, NodeError> {
    lens.validate()?;
    Ok(coc_map_with(
        depth,
        lens.coc_scale(depth.width()),
        lens.inv_focus(),
    ))
}

/// [`coc_map`] with the constant `C` and the focus's inverse `1/u` given
/// (a frame extended past the input's border keeps the input's `C`).
pub fn coc_map_with(depth: &DepthMap, c: f64, inv_u: f64) -> Image<f32> {
    // pixels in parallel (rayon's collect keeps their order)
    let (w, h) = depth.dims();
    let data: Vec<f32> = depth
        .as_slice()
        .par_iter()
        .map(|&z| (c * (inv_depth(z) - inv_u).abs()) as f32)
        .collect();
    // (the buffer holds w * h values by construction)
    Image::from_vec(w, h, data).unwrap_or_else(|_| Image::filled(w, h, 0.0))
}

/// The shape of the aperture, in a frame where the aperture has diameter 1
/// (the disc and polygons are inscribed in the circle of radius 1/2; a
/// mask image spans the square `[-1/2, 1/2]^2` along its longer side).
#[derive(Debug, Clone, PartialEq)]
pub enum Aperture {
    /// A round diaphragm.
    Disc,
    /// A regular polygon of `blades` sides (3 = triangle), rotated by
    /// `rotation_deg` (0: one vertex straight up).
    Polygon {
        /// Number of blades, i.e. sides of the polygon (3 to 64 from
        /// [`Aperture::from_params`]).
        blades: u32,
        /// Rotation in degrees, clockwise in the image (`y` down); 0 puts a
        /// vertex straight up.
        rotation_deg: f64,
    },
    /// A custom diaphragm: each pixel's value is its transmittance in
    /// `[0, 1]` (values outside are clamped, NaN is 0).
    Mask(Mask),
}

impl Aperture {
    /// The aperture the parameters name: a disc, a polygon (with
    /// `blades`), a triangle, or a mask (which needs `mask`).
    pub fn from_params(
        shape: ApertureShape,
        blades: u32,
        rotation_deg: f64,
        mask: Option<&Mask>,
    ) -> Result<Aperture, NodeError> {
        match shape {
            ApertureShape::Disc => Ok(Aperture::Disc),
            ApertureShape::Polygon => {
                if !(3..=64).contains(&blades) {
                    return Err(NodeError::param(
                        "blades",
                        format!("a polygonal aperture needs 3 to 64 blades, got {blades}"),
                    ));
                }
                Ok(Aperture::Polygon {
                    blades,
                    rotation_deg,
                })
            }
            ApertureShape::Triangle => Ok(Aperture::Polygon {
                blades: 3,
                rotation_deg,
            }),
            ApertureShape::Mask => match mask {
                Some(m) => Ok(Aperture::Mask(m.clone())),
                None => Err(NodeError::input(
                    "aperture",
                    "aperture = \"mask\" needs a Mask connected to the `aperture` input",
                )),
            },
        }
    }

    /// Largest distance of an aperture point from the centre, in aperture
    /// diameters: 1/2 for the disc and polygons; for a mask, the farthest
    /// corner of an open pixel from the mask's centre of transmittance
    /// (its points are centred there, [`Aperture::samples`]): up to
    /// `sqrt(2)/2` for a centred shape, up to `sqrt(2)` for a lopsided one
    /// (a blob in one corner, one open pixel in the opposite one).
    pub fn extent(&self) -> f64 {
        match self {
            Aperture::Mask(m) => mask_extent(m),
            _ => 0.5,
        }
    }

    /// The area the aperture's points are spread over, square aperture
    /// diameters: the disc's `π/4`; a regular polygon of `n` blades
    /// inscribed in the circle of radius 1/2, `n sin(2π/n) / 8`; a mask,
    /// its pixels with any transmittance (their side `1 / max(w, h)`).
    pub fn area(&self) -> f64 {
        match self {
            Aperture::Disc => std::f64::consts::FRAC_PI_4,
            Aperture::Polygon { blades, .. } => {
                let n = f64::from((*blades).max(3));
                n * (std::f64::consts::TAU / n).sin() / 8.0
            }
            Aperture::Mask(m) => {
                let (w, h) = m.dims();
                let open = m
                    .as_slice()
                    .iter()
                    .filter(|v| v.is_finite() && **v > 0.0)
                    .count();
                // guard: max(w, h, 1) >= 1
                let side = 1.0 / w.max(h).max(1) as f64;
                open as f64 * side * side
            }
        }
    }

    /// True when `(x, y)` (aperture diameters, `y` down) is open. Only used
    /// for the analytic shapes; masks are sampled from their pixels.
    pub fn contains(&self, x: f64, y: f64) -> bool {
        match self {
            Aperture::Disc => x * x + y * y <= 0.25,
            Aperture::Polygon {
                blades,
                rotation_deg,
            } => {
                let n = (*blades).max(3) as f64;
                let half = std::f64::consts::PI / n;
                // Apothem of the polygon inscribed in the circle of radius 1/2.
                let apothem = 0.5 * half.cos();
                // A vertex straight up (y down, so at angle -pi/2), rotated.
                let first_vertex = -std::f64::consts::FRAC_PI_2 + rotation_deg.to_radians();
                (0..*blades).all(|k| {
                    let normal = first_vertex + half + 2.0 * half * k as f64;
                    x * normal.cos() + y * normal.sin() <= apothem
                })
            }
            Aperture::Mask(m) => {
                let (w, h) = m.dims();
                let side = w.max(h) as f64;
                let px = ((x + 0.5) * side - (side - w as f64) / 2.0).floor();
                let py = ((y + 0.5) * side - (side - h as f64) / 2.0).floor();
                m.try_get(px as isize, py as isize)
                    .is_some_and(|v| v.is_finite() && *v > 0.5)
            }
        }
    }

    /// `n` stratified sample points over the open part of the aperture
    /// (aperture diameters, centre 0), deterministic in `seed` (Sec. 2.3:
    /// "we sample 2D positions s on the lens ... using stratified
    /// sampling").
    ///
    /// Analytic shapes take the points of a Halton (2, 3) sequence, shifted by
    /// a seeded Cranley-Patterson rotation, that fall inside the shape: every
    /// dyadic and triadic box of the square receives its share, which is the
    /// stratification a jittered grid gives without requiring `n` to be a
    /// square. Masks are sampled in proportion to their transmittance: the
    /// open pixels, in scan order, form a cumulative distribution that is cut
    /// into `n` equal strata with one jittered point each (so even a mask
    /// with one open pixel works). Mask points are centred on the mask's
    /// centre of transmittance (the mean of its open pixels' centres,
    /// weighted by transmittance: where a lopsided aperture's mean ray
    /// passes), so that it does not shift the in-focus image, and
    /// [`Aperture::extent`] bounds them exactly.
    ///
    /// ```
    /// use depthgraph_nodes::camera::lens::Aperture;
    /// let s = Aperture::Disc.samples(256, 0).unwrap();
    /// assert_eq!(s.len(), 256);
    /// assert!(s.iter().all(|p| p[0] * p[0] + p[1] * p[1] <= 0.25));
    /// ```
    pub fn samples(&self, n: usize, seed: u64) -> Result<Vec<[f64; 2]>, NodeError> {
        if n == 0 {
            return Ok(Vec::new());
        }
        if n == 1 {
            // One ray: the lens's mean ray, through the centre (a point
            // drawn anywhere else shifted every blurred pixel by up to half
            // its circle of confusion, and blurred nothing). A mask with no
            // open pixel is still refused.
            if let Aperture::Mask(m) = self {
                mask_samples(m, 1, seed)?;
            }
            return Ok(vec![[0.0, 0.0]]);
        }
        match self {
            Aperture::Mask(m) => mask_samples(m, n, seed),
            _ => {
                let r = splitmix64(seed ^ 0x5eed_a9e7);
                let shift = [unit(r), unit(splitmix64(r))];
                let mut out = Vec::with_capacity(n);
                // The analytic shapes cover at least 41% of the square (the
                // triangle), so 16 n + 64 draws are far more than enough; the
                // bound only guards against a logic error looping forever.
                for i in 1..=(16 * n as u64 + 64) {
                    let x = (radical_inverse(i, 2) + shift[0]).fract() - 0.5;
                    let y = (radical_inverse(i, 3) + shift[1]).fract() - 0.5;
                    if self.contains(x, y) {
                        out.push([x, y]);
                        if out.len() == n {
                            return Ok(out);
                        }
                    }
                }
                Err(NodeError::Invalid(format!(
                    "could not place {n} samples in the aperture (only {})",
                    out.len()
                )))
            }
        }
    }
}

/// A `u64` mapped to `[0, 1)`.
fn unit(r: u64) -> f64 {
    (r >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Van der Corput radical inverse of `i` in `base` (>= 2).
fn radical_inverse(mut i: u64, base: u64) -> f64 {
    let inv = 1.0 / base as f64;
    let mut f = inv;
    let mut r = 0.0;
    while i > 0 {
        r += (i % base) as f64 * f;
        i /= base;
        f *= inv;
    }
    r
}

/// A mask's open pixels (index, transmittance in (0, 1]; NaN and values
/// <= 0 are closed) in scan order.
fn mask_open(m: &Mask) -> Vec<(usize, f64)> {
    m.as_slice()
        .iter()
        .enumerate()
        .filter_map(|(i, v)| {
            let t = if v.is_finite() {
                v.clamp(0.0, 1.0) as f64
            } else {
                0.0
            };
            (t > 0.0).then_some((i, t))
        })
        .collect()
}

/// The square a `w x h` mask is centred in: its side in pixels (>= 1 for
/// a mask with a pixel) and the mask's offset in it.
fn mask_square(w: usize, h: usize) -> (f64, f64, f64) {
    let side = w.max(h) as f64;
    (side, (side - w as f64) / 2.0, (side - h as f64) / 2.0)
}

/// A mask's centre of transmittance in aperture diameters (centre of its
/// square 0): the transmittance-weighted mean of its open pixels' centres.
/// `None` when no pixel is open.
fn mask_centre(m: &Mask, open: &[(usize, f64)]) -> Option<[f64; 2]> {
    let (w, h) = m.dims();
    let (side, ox, oy) = mask_square(w, h);
    let total: f64 = open.iter().map(|(_, t)| t).sum();
    if open.is_empty() || total <= 0.0 || side < 1.0 {
        return None;
    }
    let (mut sx, mut sy) = (0.0, 0.0);
    for &(i, t) in open {
        sx += t * ((i % w) as f64 + ox + 0.5);
        sy += t * ((i / w) as f64 + oy + 0.5);
    }
    // guard: total > 0 and side >= 1 (checked above)
    Some([sx / total / side - 0.5, sy / total / side - 0.5])
}

/// [`Aperture::extent`] of a mask: its open pixels' farthest corner from
/// its centre of transmittance (`sqrt(2)/2`, the whole square's, when
/// no pixel is open: sampling such a mask is an error anyway).
fn mask_extent(m: &Mask) -> f64 {
    let open = mask_open(m);
    let Some(c) = mask_centre(m, &open) else {
        return std::f64::consts::FRAC_1_SQRT_2;
    };
    let (w, h) = m.dims();
    let (side, ox, oy) = mask_square(w, h);
    open.iter()
        .map(|&(i, _)| {
            let (x0, y0) = (
                ((i % w) as f64 + ox) / side - 0.5,
                ((i / w) as f64 + oy) / side - 0.5,
            );
            // guard: side >= 1 (a centre exists)
            let (x1, y1) = (x0 + 1.0 / side, y0 + 1.0 / side);
            let dx = (x0 - c[0]).abs().max((x1 - c[0]).abs());
            let dy = (y0 - c[1]).abs().max((y1 - c[1]).abs());
            dx.hypot(dy)
        })
        .fold(0.0, f64::max)
}

fn mask_samples(m: &Mask, n: usize, seed: u64) -> Result<Vec<[f64; 2]>, NodeError> {
    let (w, h) = m.dims();
    let open = mask_open(m);
    let total: f64 = open.iter().map(|(_, t)| t).sum();
    let Some(centre) = mask_centre(m, &open) else {
        return Err(NodeError::input(
            "aperture",
            "the aperture mask has no open pixel (every value is 0): no light passes",
        ));
    };
    let (side, ox, oy) = mask_square(w, h);
    let mut out = Vec::with_capacity(n);
    let mut rng = splitmix64(seed ^ 0x6d61_736b);
    let mut k = 0usize;
    let mut cum = open[0].1;
    for s in 0..n {
        rng = splitmix64(rng);
        // Guard: n > 0 here.
        let target = (s as f64 + unit(rng)) / n as f64 * total;
        while cum < target && k + 1 < open.len() {
            k += 1;
            cum += open[k].1;
        }
        let (i, _) = open[k];
        let (px, py) = ((i % w) as f64, (i / w) as f64);
        rng = splitmix64(rng);
        let jx = unit(rng);
        rng = splitmix64(rng);
        let jy = unit(rng);
        // Guard: side >= 1 (a mask has at least one pixel here).
        out.push([
            (px + ox + jx) / side - 0.5 - centre[0],
            (py + oy + jy) / side - 0.5 - centre[1],
        ]);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lens(f_number: f64, focus_m: f64) -> ThinLens {
        ThinLens {
            focal_length_mm: 50.0,
            f_number,
            focus_m,
            sensor_width_mm: 36.0,
        }
    }

    #[test]
    fn coc_matches_the_thin_lens_formula() {
        // 50 mm f/2 at 2 m on a 36 mm sensor, 640 px: a point at 4 m.
        let l = lens(2.0, 2.0);
        l.validate().unwrap();
        let c = l.coc_scale(640);
        let coc = c * (1.0 / 4.0 - 1.0 / 2.0f64).abs();
        // Thin lens: image distances v = f u / (u - f); blur on the sensor
        // = A |v_u - v_z| / v_z, in mm, then in pixels.
        let f = 50.0;
        let a = f / 2.0;
        let v = |u: f64| f * u / (u - f);
        let blur_mm = a * (v(2000.0) - v(4000.0)).abs() / v(4000.0);
        let expected = blur_mm / (36.0 / 640.0);
        assert!(
            (coc - expected).abs() < 1e-9 * expected,
            "{coc} vs {expected}"
        );
        // In focus: zero.
        let map = coc_map(&DepthMap::filled(2, 1, 2.0), &l).unwrap();
        assert_eq!(map.as_slice(), &[0.0, 0.0]);
    }

    #[test]
    fn infinity_focus_and_invalid_depth_are_finite() {
        let l = lens(1.4, f64::INFINITY);
        l.validate().unwrap();
        let d = DepthMap::from_vec(4, 1, vec![0.0, f32::NAN, -1.0, 1.0]).unwrap();
        let m = coc_map(&d, &l).unwrap();
        // No measurement = infinitely far = in focus at infinity.
        assert_eq!(&m.as_slice()[..3], &[0.0, 0.0, 0.0]);
        let expected = l.coc_scale(4) * 1.0; // 1/z - 1/u = 1 at z = 1 m
        assert!(expected > 0.0 && (m.as_slice()[3] as f64 - expected).abs() < 1e-6 * expected);
    }

    #[test]
    fn impossible_lenses_are_errors_that_name_the_parameter() {
        let near = lens(2.0, 0.01).validate().unwrap_err().to_string();
        assert!(
            near.contains("focus_m") && near.contains("focal length"),
            "{near}"
        );
        let zero = lens(0.0, 2.0).validate().unwrap_err().to_string();
        assert!(zero.contains("f_number"), "{zero}");
        // f/1000 and f/0.7 are fine.
        lens(1000.0, 2.0).validate().unwrap();
        lens(0.7, 2.0).validate().unwrap();
    }

    #[test]
    fn samples_are_inside_uniform_and_deterministic() {
        for ap in [
            Aperture::Disc,
            Aperture::Polygon {
                blades: 6,
                rotation_deg: 15.0,
            },
            Aperture::Polygon {
                blades: 3,
                rotation_deg: 0.0,
            },
        ] {
            let s = ap.samples(1024, 7).unwrap();
            assert_eq!(s.len(), 1024);
            assert!(s.iter().all(|p| ap.contains(p[0], p[1])));
            assert_eq!(s, ap.samples(1024, 7).unwrap());
            assert_ne!(s, ap.samples(1024, 8).unwrap());
            // Uniform over a centred symmetric-enough shape: the mean is near 0
            // for the disc and hexagon (the triangle's centroid is 0 too).
            let m = s.iter().fold([0.0; 2], |a, p| [a[0] + p[0], a[1] + p[1]]);
            assert!(
                m[0].abs() / 1024.0 < 0.01 && m[1].abs() / 1024.0 < 0.01,
                "{ap:?} {m:?}"
            );
            // Stratified: each quadrant of the shape's bounding square gets
            // close to its share (exact shares for the disc: 1/4).
            if ap == Aperture::Disc {
                let q = s.iter().filter(|p| p[0] < 0.0 && p[1] < 0.0).count();
                assert!((246..=266).contains(&q), "{q}");
            }
        }
    }

    #[test]
    fn polygon_has_the_right_area() {
        // Hexagon inscribed in r = 1/2: area 3 sqrt(3)/2 r^2.
        let hex = Aperture::Polygon {
            blades: 6,
            rotation_deg: 0.0,
        };
        let n = 400;
        let inside = (0..n * n)
            .filter(|i| {
                let x = ((i % n) as f64 + 0.5) / n as f64 - 0.5;
                let y = ((i / n) as f64 + 0.5) / n as f64 - 0.5;
                hex.contains(x, y)
            })
            .count() as f64
            / (n * n) as f64;
        let exact = 1.5 * 3f64.sqrt() * 0.25;
        assert!((inside - exact).abs() < 2e-3, "{inside} vs {exact}");
        // The triangle points up: the top vertex is open, the bottom centre edge
        // is at y = +1/4.
        let tri = Aperture::Polygon {
            blades: 3,
            rotation_deg: 0.0,
        };
        assert!(tri.contains(0.0, -0.49));
        assert!(tri.contains(0.0, 0.24) && !tri.contains(0.0, 0.26));
    }

    /// One sample is the lens's centre, for every shape: a single point
    /// drawn off the centre shifted the whole out-of-focus image.
    #[test]
    fn one_sample_is_the_centre() {
        let mut m = Mask::filled(9, 9, 0.0);
        *m.get_mut(0, 0) = 1.0;
        *m.get_mut(8, 3) = 0.5;
        for ap in [
            Aperture::Disc,
            Aperture::Polygon {
                blades: 3,
                rotation_deg: 10.0,
            },
            Aperture::Mask(m),
        ] {
            for seed in [0, 1, 77] {
                assert_eq!(ap.samples(1, seed).unwrap(), vec![[0.0, 0.0]], "{ap:?}");
            }
        }
        assert!(
            Aperture::Mask(Mask::filled(3, 3, 0.0))
                .samples(1, 0)
                .is_err()
        );
    }

    /// A lopsided mask's points reach beyond `sqrt(2)/2` from its centre
    /// of transmittance; `extent` bounds every one of them (it was a
    /// constant, and kernels and active tiles cut such bokeh short).
    #[test]
    fn a_lopsided_masks_extent_bounds_its_points() {
        let mut m = Mask::filled(64, 64, 0.0);
        for y in 0..8 {
            for x in 0..8 {
                *m.get_mut(x, y) = 1.0;
            }
        }
        *m.get_mut(63, 63) = 1.0;
        let ap = Aperture::Mask(m);
        let s = ap.samples(4096, 3).unwrap();
        let far = s.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
        assert!(far > std::f64::consts::FRAC_1_SQRT_2, "{far}");
        assert!(
            far <= ap.extent() && ap.extent() < far + 0.03,
            "{far} {}",
            ap.extent()
        );
        // centred: the points' mean is the centre of transmittance
        let mean = s.iter().fold([0.0; 2], |a, p| [a[0] + p[0], a[1] + p[1]]);
        assert!(
            mean[0].abs() / 4096.0 < 1e-3 && mean[1].abs() / 4096.0 < 1e-3,
            "{mean:?}"
        );
        // a full mask: its square's half diagonal
        let full = Aperture::Mask(Mask::filled(8, 8, 1.0));
        assert!((full.extent() - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-12);
    }

    #[test]
    fn one_pixel_mask_and_empty_mask() {
        let mut m = Mask::filled(5, 5, 0.0);
        *m.get_mut(2, 2) = 1.0;
        let s = Aperture::Mask(m).samples(16, 0).unwrap();
        assert_eq!(s.len(), 16);
        // Centred, within one mask pixel (1/5 of the diameter).
        assert!(s.iter().all(|p| p[0].abs() <= 0.2 && p[1].abs() <= 0.2));
        let e = Aperture::Mask(Mask::filled(3, 3, 0.0))
            .samples(4, 0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("aperture") && e.contains("no open pixel"), "{e}");
        let missing = Aperture::from_params(ApertureShape::Mask, 6, 0.0, None)
            .unwrap_err()
            .to_string();
        assert!(missing.contains("aperture"), "{missing}");
    }
}
