//! The lighting of a photo estimated from its own shading: an environment
//! map for `VplSample` and `Relight` when no capture of the scene's light
//! exists (3d-editing §VI names "estimating reflectance model and lighting
//! environment" as its future work).
//!
//! # Model and its assumptions
//!
//! - Surfaces are **Lambertian**: pixel `i` of albedo `a` and normal `n_i`
//!   shows `I_i = a E(n_i)`, `E` the irradiance.
//! - Albedo is **piecewise constant** over the regions of
//!   [`albedo_regions`]: within a region every change of brightness is
//!   shading.
//! - The irradiance is a low-frequency part, spherical harmonics of order 2
//!   ([`sh`]: nine radiance coefficients `L_j`, `E = Σ L_j Â_l Y_j(n)`), plus
//!   optionally one **dominant directional light** `d` of irradiance `s`
//!   (sun, lamp), seen or not by each pixel according to the depth map:
//!   `E(n_i) = Σ_j L_j Â_l Y_j(n_i) + s max(0, n_i·d) V_i(d)`.
//! - Light the photo's own surfaces bounce onto each other is **not** part
//!   of the map (with [`EstimateParams::bounce`], the default): it is known
//!   from the pixels, `B_i` of [`super::bounce`], in the photo's units, and
//!   `Relight` bounces the map's light off the same surfaces again. The
//!   irradiance is then `S E(n_i) + B_i`, `S` the light's absolute scale,
//!   and `E` counts the sky only where the photo's surfaces do not cover it
//!   (`φ_i` less the covered part of [`super::bounce::Gathered`]). Light
//!   bounced by what the photo does not show stays in the low-frequency
//!   part.
//!
//! # The fit
//!
//! Writing `φ_i` for the vector of the basis terms (and the light's) at
//! sample `i`, `E_i = φ_i·θ`. The unknown albedo of region `r` drops out of
//! the ratio of a sample to its region's mean, `I_i / Ī_r = E_i / Ē_r`,
//! which is **linear** in `θ`: `(y_i φ̄_r - φ_i)·θ = 0` with
//! `y_i = I_i / Ī_r` and `φ̄_r` the region's mean of `φ`. With the bounce,
//! `I_i / Ī_r = (S E_i + B_i) / (S Ē_r + B̄_r)` gives
//! `(y_i φ̄_r - φ_i)·θ = β (B_i - y_i B̄_r)`, `β = 1/S`, linear for a given
//! `β`; `β` comes from the albedo assumption below, first on the fit
//! without light or bounce (for the search and the robust refit), then
//! from the final fit, settled in three rounds per colour channel. With the mean of `E` over the samples fixed at 1,
//! this is a linear least-squares problem in the other terms,
//! regularised towards an isotropic light (ridge weights per order), solved
//! by Cholesky in f64. A region facing one direction only (a flat wall)
//! gives rows of zero: it carries no information, and neither does it bias
//! the fit.
//!
//! The light's direction is found by search: every direction of a
//! Fibonacci sphere ([`EstimateParams::directions`]), then two finer grids
//! around the best; its visibility `V_i(d)` is a march through the depth
//! map (the cast shadows of what the photo shows), behind each depth pixel
//! as far as [`super::thickness`] estimates the body there is deep (a body
//! as deep as it is wide, at most [`EstimateParams::occluder_thickness_m`]).
//! The samples are sparse and the march coarse, which places a cast
//! shadow's edge to a few pixels and the light to 3-8°; with
//! [`EstimateParams::refine_shadows`] (the default) the edges themselves
//! then move the direction, on a grid of about 320 pixels across
//! ([`super::shadow_edges`]:
//! 0.1-1.3° on the path-traced rooms of docs/lighting.md). A direction whose fit
//! leaves the low-frequency part and the bounce together under
//! `MIN_AMBIENT_SHARE` of the mean irradiance takes no part in the search (a sky darker than black beside
//! a light is the fit trading one for the other). The light is kept when
//! it explains at least [`EstimateParams::min_light_gain`] of what the
//! ambient-only fit leaves and its irradiance is positive, and only when the
//! photo tells its direction: no direction of the coarse search more than
//! 30° from it may explain [`EstimateParams::max_ambiguity`] (85 %) as much
//! or more. A floor and a wall lit by a sun, with nothing casting a shadow,
//! fit a whole arc of directions alike (on the path-traced rooms of
//! docs/lighting.md such rivals explain 94-100 % as much, beside 25-64 %
//! where the photo shows the sun's shadows); a light picked from that arc
//! is invented, and its shadows fall the wrong way. At the chosen
//! direction, iteratively reweighted least squares (Huber weights, scale
//! from the median absolute residual) lowers the pull of specular
//! highlights, textures and shadows the depth map cannot explain. Each
//! colour channel is then fitted with those weights.
//!
//! The albedo scale is not observable (brighter light on darker surfaces
//! looks the same; the bounce is brighter on brighter surfaces, but fitting
//! its weight freely gave median reflectances from 0.05 to 0.86 on rooms
//! of 0.5-0.6): it is fixed by assuming the median reflectance of the
//! sampled surfaces is [`EstimateParams::assumed_albedo`] in every channel
//! (grey world: a scene whose surfaces share a strong hue gives a light
//! tinted by its complement). A Lambertian surface of reflectance `r`
//! shows `I = (r/π) E`, so the albedo `a` of the model above is `r/π`.
//! `Relight` adds the photo's bounce, in the photo's units, to the map's
//! light: the scale matters there.
//!
//! Directions no normal faces get the low-frequency value the fit gives
//! them (the ridge keeps it near the isotropic level), above the camera's
//! horizontal plane. Below it (with [`EstimateParams::bounce`], the
//! default; without it the fit's extrapolation stands for the light the
//! photo's floor bounces, as before) the map holds a ground, a Lambertian plane
//! of reflectance [`EstimateParams::ground_albedo`] under the fitted sky
//! (`ground_radiance`): no photo shows it, since its own floor hides it
//! from every point it shows (and `Relight` bounces that floor's light
//! from the pixels), so the ground lights only an object where it was
//! captured. The fit's extrapolation put a sky's brightness there, which
//! lit the object's underside at its capture as brightly as its top and
//! darkened it in the composite: against the path-traced truth the ground
//! gains 1.6-9.8 dB on the object (docs/lighting.md). A photo with too
//! little shading variation (below [`EstimateParams::min_variation`]: a
//! flat wall) gives the ambient-only estimate, a uniform sky (over the
//! ground), with a
//! confidence near zero, and says so.

use std::f64::consts::PI;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use glam::DVec3;
use rayon::prelude::*;

use crate::kit::color::luminance_f64;
use crate::kit::linalg::cholesky_solve;
use crate::relight::envmap::{SunBlend, paint_sun, pixel_direction};
use crate::relight::lighting::bounce::{BOUNCE_PATCHES, gather, patches};
use crate::relight::lighting::regions::{NO_REGION, RegionParams, albedo_regions};
use crate::relight::lighting::sh::{self, SH_ORDER, SH_TERMS};
use crate::relight::lighting::shadow_edges::{
    EdgeParams, March, Refined, hidden_at, ray_start, refine_direction,
};
use crate::relight::lighting::thickness::occluder_thickness;
use crate::relight::shading::target_surfaces;

node_params! {
    /// Parameters of `EstimateLighting`.
    pub struct EstimateParams {
        /// Width of the output map (its height is half).
        pub width: usize = 128usize, ParamKind::Int { min: 8, max: 4096 };
        /// Pixels sampled for the fit (on a regular grid).
        pub samples: usize = 3000usize, ParamKind::Int { min: 64, max: 1000000 };
        /// Search for a dominant directional light (sun, lamp); off = low-frequency light only.
        pub light: bool = true, ParamKind::Bool;
        /// Directions of the coarse search (Fibonacci sphere); two finer grids refine the best.
        pub directions: usize = 300usize, ParamKind::Int { min: 16, max: 100000 };
        /// Smallest irradiance of the light on a surface facing it, as a fraction of the mean irradiance of the samples, for it to be kept (a broad sky's gradient is not a sun: an overcast room's best "sun" gives 43-61 %, real ones 89-118 %).
        pub min_light_share: f64 = 0.75, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Largest irradiance of the light as a multiple of the mean irradiance of the samples: a brighter one is not believed (the fit let it explain textures with its shadows).
        pub max_light_share: f64 = 3.0, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Refine the light's direction by the edges of the cast shadows, on a grid of about 320 pixels across (shadow_edges): the fit's sparse samples place it to a few degrees.
        pub refine_shadows: bool = true, ParamKind::Bool;
        /// Lowest elevation searched for the light, degrees (light from the horizon or below is rare, and a grazing light's long shadows can be made to match any texture).
        pub min_elevation_deg: f64 = 5.0, ParamKind::Float { min: -90.0, max: 90.0 };
        /// A light is kept only when no direction more than 30° from it (AMBIGUOUS_DEG) explains this share or more of what it explains: else the photo does not tell where the light is (a floor and a wall lit by a sun fit a whole arc of directions alike), and no sun is invented. 1 = off.
        pub max_ambiguity: f64 = 0.85, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Fraction of the ambient-only fit's residual the light must explain to be kept.
        pub min_light_gain: f64 = 0.05, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Below this RMS of relative shading variation the photo is treated as unlit by any direction (ambient only).
        pub min_variation: f64 = 0.02, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Median reflectance (diffuse albedo, 0-1) assumed for the sampled surfaces: fixes the light's scale (a surface of reflectance r under radiance L shows r L).
        pub assumed_albedo: f64 = 0.5, ParamKind::Float { min: 0.01, max: 1.0 };
        /// Angular diameter of the estimated light's disc in the map, degrees.
        pub light_size_deg: f64 = 3.0, ParamKind::Float { min: 0.1, max: 60.0 };
        /// How far shadow rays march through the depth map, metres.
        pub shadow_reach_m: f64 = 3.0, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Largest thickness behind a depth pixel for shadows, metres (each pixel's is estimated: a body as deep as it is wide, thickness.rs).
        pub occluder_thickness_m: f64 = 0.4, ParamKind::Float { min: 0.001, max: 100.0 };
        /// Leave out of the map the light the photo's surfaces bounce onto each other (Relight bounces it again from the same surfaces); off = all of it counts as sky.
        pub bounce: bool = true, ParamKind::Bool;
        /// Reflectance of the ground below the horizon (0-1): the map holds there a Lambertian ground lit by the fitted sky. The photo's own floor hides it from every point the photo shows, so it only lights an object where it was captured; set it to the reflectance of what the object stood on. With bounce off the fit's extrapolation stays there (it stands for the light the photo's floor bounces).
        pub ground_albedo: f64 = 0.1, ParamKind::Float { min: 0.0, max: 1.0 };
    }
}

/// Ridge weight of the order-1 terms, times the total sample weight.
const RIDGE_L1: f64 = 0.02;
/// Ridge weight of the order-2 terms (they extrapolate worst).
const RIDGE_L2: f64 = 0.1;
/// Ridge weight of the light's irradiance.
const RIDGE_LIGHT: f64 = 1e-5;
/// Samples whose ratio to their region's mean is beyond `1 ± this` are
/// left out of the search (highlights, deep unexplained shadows).
const OUTLIER_RATIO: f64 = 2.0;
/// Regions with fewer samples than this are left out.
const MIN_REGION_SAMPLES: usize = 6;
/// Below this spread of the sampled normals (`1 - |mean normal|`, about
/// 10° around their mean) shading cannot tell one light from another.
const MIN_NORMAL_SPREAD: f64 = 0.015;
/// A light found within this many degrees above the search's lowest
/// elevation is pressed against that limit and is not believed.
const GRAZING_MARGIN_DEG: f64 = 2.0;
/// How far (degrees) a rival direction lies from the best for
/// [`EstimateParams::max_ambiguity`]: three times the 10° a found light
/// is meant to lie within. The coarse search's directions lie about 12°
/// apart, so the rivals are its directions beyond this angle.
const AMBIGUOUS_DEG: f64 = 30.0;
/// Marching steps of a shadow ray.
const SHADOW_STEPS: usize = 24;
/// Smallest part of the samples' mean irradiance the low-frequency light
/// must give beside a directional light ([`ambient_share`]). Sunlit and
/// lamp-lit scenes keep a sky or a room that lights their shadows: the
/// fits at the path-traced suns of `docs/lighting.md` leave it 30-50 %.
/// The fits this rule removes left it nothing: they had given the
/// low-frequency part a negative mean (a sky darker than black) for a low
/// light whose cos on the floor mimics the ambient (an overcast room's
/// "sun" at 12°, a sun found 24° off).
const MIN_AMBIENT_SHARE: f64 = 0.1;

/// The estimated directional light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightEstimate {
    /// Unit direction towards the light (camera frame).
    pub direction: DVec3,
    /// Its elevation above the camera's horizontal plane, degrees.
    pub elevation_deg: f64,
    /// Its azimuth in the map convention, degrees (0 behind the camera).
    pub azimuth_deg: f64,
    /// Irradiance on a surface facing it, per channel.
    pub irradiance: [f64; 3],
    /// Fraction of the ambient-only residual it explains.
    pub gain: f64,
}

/// What [`estimate_lighting`] returns.
#[derive(Debug, Clone)]
pub struct LightingEstimate {
    /// Equirectangular radiance (`width x width/2`, envmap convention).
    pub map: ColorImage,
    /// The low-frequency part's radiance coefficients per channel (the
    /// fit: above the horizon the map is their radiance, below it the
    /// ground of [`EstimateParams::ground_albedo`]).
    pub sh: [[f64; SH_TERMS]; 3],
    /// The dominant light, when one was found.
    pub light: Option<LightEstimate>,
    /// Mean radiance of the low-frequency part per channel.
    pub ambient: [f64; 3],
    /// In `[0, 1]`: how much of the shading variation the model explains,
    /// times how much variation there was to explain.
    pub confidence: f64,
    /// RMS relative shading variation within regions.
    pub variation: f64,
    /// Samples used and regions they fell in.
    pub samples: usize,
    /// Regions with samples.
    pub regions: usize,
    /// One line for `explain`.
    pub report: String,
}

/// Inputs of [`estimate_lighting`].
#[derive(Debug, Clone, Copy)]
pub struct EstimateInputs<'a> {
    /// The photo, linear radiance.
    pub color: &'a ColorImage,
    /// Its depth, metres.
    pub depth: &'a DepthMap,
    /// Its camera.
    pub k: &'a Intrinsics,
    /// Normals, else from the depth.
    pub normals: Option<&'a NormalMap>,
    /// Surfaces to trust (>= 0.5), else all.
    pub mask: Option<&'a Mask>,
}

/// One sampled pixel.
#[derive(Debug, Clone, Copy)]
struct Sample {
    pos: DVec3,
    n: DVec3,
    /// Linear RGB and luminance.
    rgbl: [f64; 4],
    region: usize,
    /// The irradiance basis at `n`.
    phi: [f64; SH_TERMS],
    /// The irradiance the photo's surfaces bounce here ([`bounce`]), linear
    /// RGB and luminance, in the photo's units; 0 with `bounce` off.
    bounce: [f64; 4],
}

impl Sample {
    /// The low-frequency light's irradiance here, `φ·θ`.
    fn ambient(&self, theta: &[f64; SH_TERMS]) -> f64 {
        self.phi.iter().zip(theta).map(|(p, t)| p * t).sum()
    }
}

/// Per-region means of the intensities (each channel and luminance).
fn region_means(samples: &[Sample], regions: usize) -> Vec<[f64; 4]> {
    let mut sum = vec![[0.0f64; 4]; regions];
    let mut cnt = vec![0usize; regions];
    for s in samples {
        for (a, v) in sum[s.region].iter_mut().zip(&s.rgbl) {
            *a += v;
        }
        cnt[s.region] += 1;
    }
    sum.iter()
        .zip(&cnt)
        // guard: regions without samples were removed before
        .map(|(s, n)| s.map(|v| v / (*n).max(1) as f64))
        .collect()
}

/// How shadow rays march ([`lit`]).
#[derive(Debug, Clone, Copy)]
struct Shadow<'a> {
    /// How far, metres.
    reach: f64,
    /// The steps' geometric growth ([`shadow_ratio`]).
    ratio: f64,
    /// Thickness behind each depth pixel, metres ([`occluder_thickness`]).
    thickness: &'a [f32],
}

/// `V_i(d)`: whether the depth map leaves the ray from `pos` towards `d`
/// open (module docs: a march of [`SHADOW_STEPS`] geometric steps up to
/// `reach` metres; a point behind a depth pixel by less than its thickness
/// is in shadow; a ray leaving the frame or going behind the camera is
/// open).
fn lit(depth: &DepthMap, k: &Intrinsics, pos: DVec3, n: DVec3, d: DVec3, sh: Shadow) -> bool {
    let Shadow {
        reach,
        ratio,
        thickness,
    } = sh;
    let start = ray_start(pos, n, FIT_SLACK);
    let t0 = SHADOW_T0;
    if reach <= t0 {
        return true;
    }
    let mut t = t0;
    for _ in 0..SHADOW_STEPS {
        let q = start + d * t;
        let Some(px) = k.project(q) else {
            return true;
        };
        match hidden_at(depth, thickness, px, q.z, FIT_SLACK) {
            None => return true,
            Some(true) => return false,
            Some(false) => {}
        }
        t *= ratio;
    }
    true
}

/// The fit's shadow rays start this far from their surface and a depth
/// pixel hides a point behind it by more than this: 1 cm + 1 % of the
/// depth (a depth camera's noise; the refinement's finer march allows
/// [`March::FINE_SLACK`]).
const FIT_SLACK: (f64, f64) = (0.01, 0.01);

/// Rounds of the refinement by the cast shadows' edges, each within
/// [`EdgeParams::radius_deg`] of where the last stopped: the fit's sparse
/// samples on a depth camera's noisy depth left the light up to 11° off.
const REFINE_ROUNDS: usize = 3;

/// First step of a shadow ray, metres.
const SHADOW_T0: f64 = 0.02;

/// The geometric growth of a shadow ray's steps to `reach` (> [`SHADOW_T0`]),
/// [`lit`]'s `ratio`.
fn shadow_ratio(reach: f64) -> f64 {
    // guard: reach > t0 > 0 where called
    (reach / SHADOW_T0).powf(1.0 / (SHADOW_STEPS - 1) as f64)
}

/// Unit directions of a Fibonacci sphere.
fn fibonacci_sphere(n: usize) -> Vec<DVec3> {
    let golden = PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            // guard: n >= 1 where called
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let a = golden * i as f64;
            DVec3::new(r * a.cos(), y, r * a.sin())
        })
        .collect()
}

/// A solved fit: the radiance coefficients, the light's irradiance (0
/// without one), the weighted residual and each sample's residual.
#[derive(Debug, Clone)]
struct Fit {
    theta: [f64; SH_TERMS],
    light: f64,
    /// The bounce's weight `β` of its design (0 without).
    beta: f64,
    rss: f64,
    resid: Vec<f64>,
}

/// The part of the samples' weighted mean irradiance that the fit's
/// low-frequency light and the photo's bounce give:
/// `Σ w_i (φ_i·θ + β B_i) / Σ w_i (φ_i·θ + β B_i + s col_i)` (`col` the
/// light's column, `s` its irradiance, `β B_i` the bounce in the fit's
/// units); 1 without a light, 0 when the weights or the mean vanish
/// (guard).
fn ambient_share(samples: &[Sample], f: &Fit, col: &[f64], wts: &[f64]) -> f64 {
    let (mut amb, mut all) = (0.0f64, 0.0f64);
    for ((s, c), w) in samples.iter().zip(col).zip(wts) {
        let a = s.ambient(&f.theta) + f.beta * s.bounce[3];
        amb += w * a;
        all += w * (a + f.light * c);
    }
    // guard: a mean irradiance that is not positive gives no share
    if all > 0.0 && all.is_finite() {
        amb / all
    } else {
        0.0
    }
}

/// The share of the ambient-only fit's cost `amb_cost` that a fit of cost
/// `cost` removes, `1 - cost / amb_cost`; `None` without a finite,
/// positive ambient cost (nothing to compare with).
fn gain_over(cost: f64, amb_cost: f64) -> Option<f64> {
    // guard: amb_cost > 0 and finite
    (amb_cost > 0.0 && amb_cost.is_finite()).then(|| 1.0 - cost / amb_cost)
}

/// How well the best rival of the coarse search's best direction `best`
/// (of cost `best_cost`) does: among the `scored` directions (direction,
/// Huber cost) more than [`AMBIGUOUS_DEG`] from `best`, the largest gain
/// ([`gain_over`] the ambient-only cost `amb_cost`) as a share of the
/// best's gain, and that rival. `None` when the best explains nothing (a
/// gain of 0 or less, or no finite ambient cost: the share has no meaning)
/// or no direction lies that far.
fn ambiguity_of(
    scored: &[(DVec3, f64)],
    (best, best_cost): (DVec3, f64),
    amb_cost: f64,
) -> Option<(f64, DVec3)> {
    let g_best = gain_over(best_cost, amb_cost)?;
    // (a NaN gain fails the test too)
    if g_best.is_nan() || g_best <= 0.0 {
        return None;
    }
    let (rival, cost) = scored
        .iter()
        .filter(|(d, _)| angle_deg(*d, best) > AMBIGUOUS_DEG)
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    // guard: g_best > 0
    Some((gain_over(*cost, amb_cost)? / g_best, *rival))
}

/// Huber's loss of residuals `r` with weights `w` at scale `k`
/// (quadratic within `k`, linear beyond: what the search minimises, so a
/// texture the model cannot explain pulls less than a shadow it can).
fn huber_cost(r: &[f64], w: &[f64], k: f64) -> f64 {
    r.iter()
        .zip(w)
        .map(|(r, w)| {
            let a = r.abs();
            w * if a <= k {
                0.5 * a * a
            } else {
                k * (a - 0.5 * k)
            }
        })
        .sum()
}

/// The scale of Huber's loss for residuals `r`: twice 1.4826 × their
/// median absolute value, at least 0.02 (2 % of the mean irradiance).
fn huber_scale(r: &[f64]) -> f64 {
    let mut a: Vec<f64> = r.iter().map(|v| v.abs()).collect();
    a.sort_by(|x, y| x.total_cmp(y));
    let med = a.get(a.len() / 2).copied().unwrap_or(0.0);
    2.0 * (1.4826 * med).max(0.01)
}

/// The part of the ratio system (module docs) that does not depend on the
/// light: for channel `ch` (0-2, 3 = luminance) and weights `wts`, each
/// sample's ratio `y_i = I_i / Ī_r` (`None` in a black region), its
/// low-frequency row `y_i φ̄_r - φ_i` and its bounce term
/// `b_i = β (B_i - y_i B̄_r)` (module docs; 0 without bounce), and their
/// weighted normal matrix and `Σ w a b`, so that each direction the search
/// tries adds only the light's column.
/// How the ratio system holds the photo's bounce (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
enum BounceTerm {
    /// No bounce term (`bounce` off, or a flat photo).
    Off,
    /// `β` given: the bounce terms are the right-hand side.
    Fixed(f64),
}

struct Design<'a> {
    samples: &'a [Sample],
    /// The bounce's weight `β` (0 without).
    beta: f64,
    wts: &'a [f64],
    regions: usize,
    y: Vec<Option<f64>>,
    rows: Vec<[f64; SH_TERMS]>,
    /// The bounce terms `b_i`, and whether any is not 0.
    b: Vec<f64>,
    has_b: bool,
    /// `Σ w a b` over the low-frequency rows.
    g_sh: [f64; SH_TERMS],
    /// `Σ w a aᵀ` over the low-frequency rows (row-major, lower triangle).
    m_sh: [f64; SH_TERMS * SH_TERMS],
    /// Weighted mean of `φ`.
    c_sh: [f64; SH_TERMS],
    wsum: f64,
}

impl<'a> Design<'a> {
    fn new(
        samples: &'a [Sample],
        means: &[[f64; 4]],
        ch: usize,
        wts: &'a [f64],
        regions: usize,
        bounce: BounceTerm,
    ) -> Self {
        let beta = match bounce {
            BounceTerm::Fixed(b) => b,
            _ => 0.0,
        };
        let mut fbar = vec![[0.0f64; SH_TERMS]; regions];
        let mut bbar = vec![0.0f64; regions];
        let mut cnt = vec![0usize; regions];
        for s in samples {
            for (a, b) in fbar[s.region].iter_mut().zip(&s.phi) {
                *a += b;
            }
            bbar[s.region] += s.bounce[ch];
            cnt[s.region] += 1;
        }
        for ((fb, bb), n) in fbar.iter_mut().zip(bbar.iter_mut()).zip(&cnt) {
            // guard: every region kept has samples
            let inv = 1.0 / (*n).max(1) as f64;
            fb.iter_mut().for_each(|v| *v *= inv);
            *bb *= inv;
        }
        let y: Vec<Option<f64>> = samples
            .iter()
            .map(|s| {
                let mean = means[s.region][ch];
                // guard: a black region carries no ratio
                (mean > 1e-12).then(|| s.rgbl[ch] / mean)
            })
            .collect();
        let rows: Vec<[f64; SH_TERMS]> = samples
            .iter()
            .zip(&y)
            .map(|(s, y)| {
                let y = y.unwrap_or(0.0);
                std::array::from_fn(|j| y * fbar[s.region][j] - s.phi[j])
            })
            .collect();
        let b: Vec<f64> = samples
            .iter()
            .zip(&y)
            .map(|(s, y)| match y {
                Some(y) if beta != 0.0 => beta * (s.bounce[ch] - y * bbar[s.region]),
                _ => 0.0,
            })
            .collect();
        let has_b = b.iter().any(|v| *v != 0.0);

        let mut m_sh = [0.0; SH_TERMS * SH_TERMS];
        let mut c_sh = [0.0; SH_TERMS];
        let mut g_sh = [0.0; SH_TERMS];
        let mut wsum = 0.0;
        for (((s, row), bi), (y, w)) in samples.iter().zip(&rows).zip(&b).zip(y.iter().zip(wts)) {
            if *w <= 0.0 || y.is_none() {
                continue;
            }
            for p in 0..SH_TERMS {
                for q in 0..=p {
                    m_sh[p * SH_TERMS + q] += w * row[p] * row[q];
                }
                c_sh[p] += w * s.phi[p];
                g_sh[p] += w * row[p] * bi;
            }
            wsum += w;
        }
        Self {
            samples,
            beta,
            wts,
            regions,
            y,
            rows,
            b,
            has_b,
            g_sh,
            m_sh,
            c_sh,
            wsum,
        }
    }

    /// Solves the ratio system with the light's column `col` (`None` =
    /// ambient only).
    ///
    /// With `a_i = y_i φ̄_r - φ_i` the rows and `b_i` the bounce terms, it
    /// minimises `Σ w_i (a_i·θ - b_i)² + Σ_j λ_j θ_j²` under `c·θ = 1`, `c`
    /// the weighted mean of `φ` (the mean irradiance over the samples is 1:
    /// no solution can shrink the residual by dimming the light
    /// everywhere): with `M = Σ w a aᵀ + diag(λ)` and `g = Σ w a b`,
    /// `θ = M⁻¹g + ν M⁻¹c`, `ν = (1 - cᵀM⁻¹g) / (cᵀ M⁻¹ c)` (without
    /// bounce `g = 0` and `θ = M⁻¹c / (cᵀ M⁻¹ c)`). The ridge `λ` is
    /// [`RIDGE_L1`], [`RIDGE_L2`] or [`RIDGE_LIGHT`] times the total
    /// weight, and 1e-9 of it on `L_00` (which keeps `M` positive definite
    /// when the photo has no variation at all).
    fn solve(&self, col: Option<&[f64]>) -> Option<Fit> {
        if self.wsum <= 0.0 {
            return None;
        }
        let m = SH_TERMS + usize::from(col.is_some());
        let mut a = vec![0.0f64; m * m];
        for p in 0..SH_TERMS {
            for q in 0..=p {
                a[p * m + q] = self.m_sh[p * SH_TERMS + q];
            }
        }
        let mut c = vec![0.0f64; m];
        c[..SH_TERMS].copy_from_slice(&self.c_sh);
        let mut g = vec![0.0f64; m];
        g[..SH_TERMS].copy_from_slice(&self.g_sh);
        // the light's rows: y_i mean_r(col) - col_i
        let light_rows: Option<Vec<f64>> = col.map(|col| {
            let mut sum = vec![0.0f64; self.regions];
            let mut cnt = vec![0usize; self.regions];
            for (s, v) in self.samples.iter().zip(col) {
                sum[s.region] += v;
                cnt[s.region] += 1;
            }
            self.samples
                .iter()
                .zip(col)
                .zip(&self.y)
                // guard: every region kept has samples
                .map(|((s, v), y)| {
                    y.unwrap_or(0.0) * sum[s.region] / cnt[s.region].max(1) as f64 - v
                })
                .collect()
        });
        if let (Some(lr), Some(col)) = (&light_rows, col) {
            let l = SH_TERMS;
            for (i, (row, r)) in self.rows.iter().zip(lr).enumerate() {
                let w = self.wts[i];
                if w <= 0.0 || self.y[i].is_none() {
                    continue;
                }
                for (q, rq) in row.iter().enumerate() {
                    a[l * m + q] += w * r * rq;
                }
                a[l * m + l] += w * r * r;
                c[l] += w * col[i];
                g[l] += w * r * self.b[i];
            }
            c[l] /= self.wsum; // guard: wsum > 0 checked above
        }
        for cp in c.iter_mut().take(SH_TERMS) {
            *cp /= self.wsum; // guard: wsum > 0 checked above
        }
        for p in 0..m {
            let ridge = match p {
                0 => 1e-9,
                p if p < SH_TERMS && SH_ORDER[p] == 1 => RIDGE_L1,
                p if p < SH_TERMS => RIDGE_L2,
                _ => RIDGE_LIGHT,
            };
            a[p * m + p] += ridge * self.wsum;
        }
        let a_b = self.has_b.then(|| a.clone());
        let mut z = c.clone();
        cholesky_solve(&mut a, m, &mut z).ok()?;
        let cz: f64 = c.iter().zip(&z).map(|(u, v)| u * v).sum();
        if !(cz > 0.0 && cz.is_finite()) {
            return None; // guard: cᵀM⁻¹c > 0 for a positive definite M and c ≠ 0
        }
        let x: Vec<f64> = match a_b {
            None => z.iter().map(|v| v / cz).collect(),
            Some(mut a_b) => {
                let mut zg = g;
                cholesky_solve(&mut a_b, m, &mut zg).ok()?;
                let cg: f64 = c.iter().zip(&zg).map(|(u, v)| u * v).sum();
                // guard: cz > 0 checked above
                let nu = (1.0 - cg) / cz;
                zg.iter().zip(&z).map(|(u, v)| u + nu * v).collect()
            }
        };
        let light = if col.is_some() { x[SH_TERMS] } else { 0.0 };
        let beta = self.beta;
        let mut rss = 0.0;
        let resid: Vec<f64> = self
            .rows
            .iter()
            .enumerate()
            .map(|(i, row)| {
                if self.y[i].is_none() {
                    return 0.0;
                }
                let mut r: f64 = row.iter().zip(&x).map(|(u, v)| u * v).sum();
                if let Some(lr) = &light_rows {
                    r += lr[i] * light;
                }
                r -= self.b[i];

                rss += self.wts[i].max(0.0) * r * r;
                r
            })
            .collect();
        let mut theta = [0.0; SH_TERMS];
        theta.copy_from_slice(&x[..SH_TERMS]);
        Some(Fit {
            theta,
            light,
            beta,
            rss,
            resid,
        })
    }
}

/// Per sample of a region with positive irradiance, in channel `ch`:
/// its region's mean intensity `Ī_r`, the fit's mean irradiance `ē_r`
/// there (`e_i = φ_i·θ + s col_i`) and the mean bounce `B̄_r`.
fn albedo_terms(
    samples: &[Sample],
    means: &[[f64; 4]],
    ch: usize,
    f: &Fit,
    col: Option<&[f64]>,
    regions: usize,
) -> Vec<(f64, f64, f64)> {
    let mut ebar = vec![0.0f64; regions];
    let mut bbar = vec![0.0f64; regions];
    let mut cnt = vec![0usize; regions];
    for (i, s) in samples.iter().enumerate() {
        ebar[s.region] += s.ambient(&f.theta) + col.map_or(0.0, |c| f.light * c[i]);
        bbar[s.region] += s.bounce[ch];
        cnt[s.region] += 1;
    }
    // guard: n >= 1; a region with no positive irradiance has no albedo
    samples
        .iter()
        .filter_map(|s| {
            let n = cnt[s.region].max(1) as f64;
            let e = ebar[s.region] / n;
            (e > 1e-12).then(|| (means[s.region][ch], e, bbar[s.region] / n))
        })
        .collect()
}

/// The median of `v` (upper middle), `None` when empty.
fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    Some(*v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1)
}

/// The median albedo `ρ = Ī_r / (S ē_r + B̄_r)` of [`albedo_terms`] at
/// scale `sc > 0`.
fn median_albedo(terms: &[(f64, f64, f64)], sc: f64) -> Option<f64> {
    // guard: sc > 0, e > 1e-12 and b >= 0 (radiance gathered)
    median(terms.iter().map(|(m, e, b)| m / (sc * e + b)).collect())
}

/// Lowest absolute scale [`absolute_scale`] gives with a bounce, as a
/// fraction of the scale without: the photo's bounce alone cannot be more
/// than three quarters of what the light gives a surface of the assumed
/// albedo (else the bounce, gathered without shadows, is too bright).
const MIN_BOUNCE_SCALE: f64 = 0.25;

/// The absolute scale `S` of a fit (module docs), from its
/// [`albedo_terms`] in one channel: the irradiance of the light is `S e_i`
/// (`e_i = φ_i·θ + s col_i`, mean 1), and the albedo of region `r`,
/// `Ī_r / (S ē_r + B̄_r)`, has its median over the samples at `assumed`
/// (`ρ = r / π` for a reflectance `r`). Without
/// bounce `S = median(Ī_r / ē_r) / assumed`; with it, the root of the
/// decreasing median by bisection between [`MIN_BOUNCE_SCALE`] of that and
/// that. `None` when no region has a positive irradiance.
fn absolute_scale(terms: &[(f64, f64, f64)], assumed: f64) -> Option<f64> {
    // guard: assumed >= 0.01 / π (parameter range)
    let s0 = median(terms.iter().map(|(m, e, _)| m / e).collect()).filter(|m| *m > 0.0)? / assumed;
    if terms.iter().all(|t| t.2 == 0.0) {
        return Some(s0);
    }
    let albedo_at = |sc: f64| median_albedo(terms, sc).unwrap_or(0.0);
    let (mut lo, mut hi) = (MIN_BOUNCE_SCALE * s0, s0);
    if albedo_at(lo) <= assumed {
        return Some(lo);
    }
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if albedo_at(mid) > assumed {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(0.5 * (lo + hi))
}

/// The bounce's weight `β = 1/S` of an absolute scale `S`; 0 (no bounce)
/// without a positive, finite scale (guard of the division).
fn bounce_weight(scale: Option<f64>) -> f64 {
    scale
        .filter(|s| *s > 0.0 && s.is_finite())
        .map_or(0.0, |s| 1.0 / s)
}

/// Huber weights of residuals `r` (at [`huber_scale`]).
fn huber(r: &[f64]) -> Vec<f64> {
    let k = huber_scale(r);
    r.iter()
        .map(|v| if v.abs() <= k { 1.0 } else { k / v.abs() })
        .collect()
}

/// Unit direction from elevation and azimuth (degrees) and back.
fn angles(d: DVec3) -> (f64, f64) {
    let e = (-d.y).clamp(-1.0, 1.0).asin().to_degrees();
    let a = d.x.atan2(-d.z).to_degrees();
    (e, a)
}

/// The estimate when the photo holds nothing to fit: a uniform sky whose
/// radiance `L` lights an up-facing surface of the assumed reflectance `r`
/// to the photo's mean colour `I` (`I = r L`: irradiance `π L`, radiance
/// out `r/π` of it), over the ground of [`ground_radiance`] (`ρ L`; with
/// [`EstimateParams::bounce`] on, else uniform everywhere), confidence 0,
/// and why.
fn fallback(color: &ColorImage, p: &EstimateParams, why: &str) -> LightingEstimate {
    let mut sum = [0.0f64; 3];
    let mut n = 0.0f64;
    for c in color.as_slice() {
        if c.iter().all(|v| v.is_finite() && *v >= 0.0) {
            for (a, v) in sum.iter_mut().zip(c) {
                *a += f64::from(*v);
            }
            n += 1.0;
        }
    }
    // guards: n >= 1 by max; assumed_albedo >= 0.01 (max, parameter range)
    let l: [f64; 3] = sum.map(|s| s / n.max(1.0) / p.assumed_albedo.max(0.01));
    let (mw, mh) = (p.width.max(2), (p.width / 2).max(1));
    let mut shc = [[0.0; SH_TERMS]; 3];
    for (c, v) in shc.iter_mut().zip(l) {
        c[0] = v / sh::basis(DVec3::Y)[0];
    }
    let ground = p
        .bounce
        .then(|| ground_radiance(&shc, None, [0.0; 3], p.ground_albedo));
    let map = paint_map(mw, mh, ground, |_| l);
    LightingEstimate {
        map,
        sh: shc,
        light: None,
        ambient: l,
        confidence: 0.0,
        variation: 0.0,
        samples: 0,
        regions: 0,
        report: format!(
            "ambient only, radiance {:.4} from the photo's mean colour: {why}, nothing to estimate the \
             light from; confidence 0",
            luminance_f64(l)
        ),
    }
}

/// Albedo regions of every pixel. When the photo has more than 25 pixels
/// per sample in each of 4 quarter-size grids, the regions are built on
/// every other pixel in x and y (a quarter of the work; the samples are
/// block means at least 10 pixels apart) and each pixel takes the label
/// of its 2x2 block's first pixel, if it is usable itself.
fn region_labels(
    inp: &EstimateInputs,
    normals: &[Option<DVec3>],
    usable: &[bool],
    samples: usize,
) -> Vec<u32> {
    let (w, h) = inp.color.dims();
    let params = RegionParams::default();
    if w * h <= 100 * samples.max(1) || w < 4 || h < 4 {
        return albedo_regions(inp.color, inp.depth, normals, usable, &params).0;
    }
    let (hw, hh) = (w / 2, h / 2);
    let at = |x: usize, y: usize| 2 * y * w + 2 * x;
    let color = ColorImage::from_fn(hw, hh, |x, y| *inp.color.get(2 * x, 2 * y));
    let depth = DepthMap::from_fn(hw, hh, |x, y| *inp.depth.get(2 * x, 2 * y));
    let n2: Vec<Option<DVec3>> = (0..hw * hh).map(|i| normals[at(i % hw, i / hw)]).collect();
    let u2: Vec<bool> = (0..hw * hh).map(|i| usable[at(i % hw, i / hw)]).collect();
    let (half, _) = albedo_regions(&color, &depth, &n2, &u2, &params);
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let (bx, by) = ((x / 2).min(hw - 1), (y / 2).min(hh - 1));
            if usable[i] && normals[i].is_some() {
                half[by * hw + bx]
            } else {
                NO_REGION
            }
        })
        .collect()
}

/// A map radiance as f32: negative and NaN give 0, beyond f32's range
/// saturates at `f32::MAX` (a photo near f32's largest values over an
/// albedo below 1 would give infinity).
fn radiance_f32(v: f64) -> f32 {
    if v > 0.0 {
        v.min(f64::from(f32::MAX)) as f32
    } else {
        0.0
    }
}

/// Whether map direction `d` lies below the camera's horizontal plane
/// (`y` is down in the camera frame; the elevations of
/// [`LightEstimate`] are measured from the same plane).
fn below_horizon(d: DVec3) -> bool {
    d.y > 0.0
}

/// The `w x h` map: radiance `sky(d)` in every direction `d`, or `ground`
/// below the horizon when there is one (with [`EstimateParams::bounce`]);
/// values beyond f32 saturate ([`radiance_f32`]).
fn paint_map(
    w: usize,
    h: usize,
    ground: Option<[f64; 3]>,
    sky: impl Fn(DVec3) -> [f64; 3],
) -> ColorImage {
    ColorImage::from_fn(w, h, |x, y| {
        let d = pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h);
        match ground {
            Some(g) if below_horizon(d) => g,
            _ => sky(d),
        }
        .map(radiance_f32)
    })
}

/// Radiance of the map's ground, per channel: a Lambertian plane of
/// reflectance `rho` under the fitted sky, `L_g = rho E_up / π`, with
/// `E_up` the irradiance of a surface facing up: the low-frequency part's
/// (`Σ L_j Â_l Y_j(up)`, which integrates only the hemisphere above, the
/// part painted as sky) plus the light's `s max(0, up·d)`.
///
/// The photo cannot show the map below its horizon: its own floor hides it
/// from every point it shows, and the light that floor bounces reaches
/// `Relight` from the pixels. Below the horizon the fit would extrapolate
/// the sky (an isotropic order-2 fit puts a sky's brightness there), which
/// lit an object's underside where it was captured as brightly as its top
/// and made the relit object too dark; the ground is what the object stood
/// on there, [`EstimateParams::ground_albedo`].
fn ground_radiance(
    shc: &[[f64; SH_TERMS]; 3],
    light: Option<DVec3>,
    light_irr: [f64; 3],
    rho: f64,
) -> [f64; 3] {
    let up = DVec3::NEG_Y;
    let facing = light.map_or(0.0, |d| d.dot(up).max(0.0));
    std::array::from_fn(|ch| {
        let e_up = (sh::irradiance(&shc[ch], up) + light_irr[ch] * facing).max(0.0);
        rho.max(0.0) * e_up / PI // guard: π is a constant
    })
}

/// Angle between two directions in degrees (the error of a found light).
pub fn angle_deg(a: DVec3, b: DVec3) -> f64 {
    a.normalize_or_zero()
        .dot(b.normalize_or_zero())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Estimates the lighting of a photo (module docs).
pub fn estimate_lighting(
    inp: &EstimateInputs,
    p: &EstimateParams,
) -> Result<LightingEstimate, NodeError> {
    estimate_lighting_with(inp, p, &|| Ok(()))
}

/// Directions of the light's coarse search scored between two calls of
/// the cancellation check.
const SEARCH_CHUNK: usize = 64;

/// [`estimate_lighting`] calling `check` (the node's cancellation) between
/// chunks of the light's search, whose cost grows with `directions` times
/// `samples`: an error from it ends the estimate.
pub fn estimate_lighting_with(
    inp: &EstimateInputs,
    p: &EstimateParams,
    check: &dyn Fn() -> Result<(), NodeError>,
) -> Result<LightingEstimate, NodeError> {
    let (w, h) = inp.color.dims();
    crate::kit::checks::fits_intrinsics("intrinsics", inp.k, "color", (w, h))?;
    crate::kit::checks::fits_intrinsics("intrinsics", inp.k, "depth", inp.depth.dims())?;
    if let Some(n) = inp.normals {
        crate::kit::checks::fits_intrinsics("intrinsics", inp.k, "normals", n.dims())?;
    }
    if let Some(m) = inp.mask {
        crate::kit::checks::fits_intrinsics("intrinsics", inp.k, "mask", m.dims())?;
    }
    let k = inp.k;
    // per-pixel normals and usability
    // the given normal where finite and non-zero, else from the depth (as Relight)
    let surfaces = target_surfaces(inp.depth, inp.normals, k);
    let normals: Vec<Option<DVec3>> = surfaces.iter().map(|s| s.as_ref().map(|s| s.n)).collect();
    let usable: Vec<bool> = (0..w * h)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let c = inp.color.get(x, y);
            let trusted = inp.mask.is_none_or(|m| *m.get(x, y) >= 0.5);
            trusted
                && c.iter().all(|v| v.is_finite() && *v >= 0.0)
                && luminance_f64(c.map(f64::from)) > 1e-6
        })
        .collect();
    let labels = region_labels(inp, &normals, &usable, p.samples);
    // samples on a regular grid
    let valid = labels.iter().filter(|l| **l != NO_REGION).count();
    if valid == 0 {
        let why = "no pixel has a depth, a normal and a colour (under the mask)";
        return Ok(fallback(inp.color, p, why));
    }
    // guard: samples >= 64 (parameter range)
    let stride = ((valid as f64 / p.samples.max(1) as f64).sqrt().floor() as usize).max(1);
    let mut raw = Vec::new();
    for y in (stride / 2..h).step_by(stride) {
        for x in (stride / 2..w).step_by(stride) {
            let i = y * w + x;
            if labels[i] == NO_REGION {
                continue;
            }
            let Some(surf) = &surfaces[i] else { continue };
            let n = surf.n;
            // the mean over the sample's block on its region (less noise)
            let mut c = [0.0f64; 3];
            let mut cnt = 0.0f64;
            for yy in y.saturating_sub(stride / 2)..(y + stride - stride / 2).min(h) {
                for xx in x.saturating_sub(stride / 2)..(x + stride - stride / 2).min(w) {
                    if labels[yy * w + xx] == labels[i] {
                        for (a, v) in c.iter_mut().zip(inp.color.get(xx, yy)) {
                            *a += f64::from(*v);
                        }
                        cnt += 1.0;
                    }
                }
            }
            // guard: cnt >= 1 (the sample's own pixel)
            let c = c.map(|v| v / cnt.max(1.0));
            raw.push(Sample {
                pos: surf.pos,
                n,
                rgbl: [c[0], c[1], c[2], luminance_f64(c)],
                region: labels[i] as usize,
                phi: sh::irradiance_basis(n),
                bounce: [0.0; 4],
            });
        }
    }
    // keep regions with enough samples, renumbered
    let max_label = raw.iter().map(|s| s.region + 1).max().unwrap_or(0);
    let mut count = vec![0usize; max_label];
    for s in &raw {
        count[s.region] += 1;
    }
    let mut remap = vec![usize::MAX; max_label];
    let mut regions = 0;
    for (r, c) in count.iter().enumerate() {
        if *c >= MIN_REGION_SAMPLES {
            remap[r] = regions;
            regions += 1;
        }
    }
    let mut samples: Vec<Sample> = raw
        .into_iter()
        .filter(|s| remap[s.region] != usize::MAX)
        .map(|mut s| {
            s.region = remap[s.region];
            s
        })
        .collect();
    if samples.is_empty() {
        let why = format!("no surface region has {MIN_REGION_SAMPLES} samples");
        return Ok(fallback(inp.color, p, &why));
    }
    let means = region_means(&samples, regions);
    // the variation to explain, and the search's weights (outliers out)
    let ratios: Vec<f64> = samples
        .iter()
        .map(|s| {
            let m = means[s.region][3];
            if m > 1e-12 { s.rgbl[3] / m } else { 1.0 } // guard: black region
        })
        .collect();
    let base_w: Vec<f64> = ratios
        .iter()
        .map(|y| {
            if (y - 1.0).abs() <= OUTLIER_RATIO {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let wsum: f64 = base_w.iter().sum();
    let variation = (ratios
        .iter()
        .zip(&base_w)
        .map(|(y, w)| w * (y - 1.0) * (y - 1.0))
        .sum::<f64>()
        / wsum.max(1.0))
    .sqrt();
    // guard: samples is not empty
    let mean_n = samples.iter().map(|s| s.n).sum::<DVec3>() / samples.len() as f64;
    let spread = 1.0 - mean_n.length();
    let flat = variation < p.min_variation || spread < MIN_NORMAL_SPREAD;
    // the photo's own bounce at every sample (not for a flat photo, whose
    // estimate is the isotropic fallback)
    if p.bounce && !flat {
        let emitters = patches(inp.color, inp.depth, k, &surfaces, BOUNCE_PATCHES);
        let points: Vec<(DVec3, DVec3)> = samples.iter().map(|s| (s.pos, s.n)).collect();
        for (s, b) in samples.iter_mut().zip(gather(&points, &emitters)) {
            let e = b.irradiance;
            s.bounce = [e[0], e[1], e[2], luminance_f64(e)];
            // the sky the photo's surfaces hide is not the map's to give
            for (f, c) in s.phi.iter_mut().zip(&b.covered) {
                *f -= c;
            }
        }
    }

    // the bounce's weight in the fit's units, β = 1 / S (module docs), from
    // the fit without light or bounce at the assumed reflectance
    let rho = p.assumed_albedo / PI;
    let mode = if p.bounce && !flat {
        let b0 = Design::new(&samples, &means, 3, &base_w, regions, BounceTerm::Off).solve(None);
        let sc = b0.and_then(|f| {
            absolute_scale(&albedo_terms(&samples, &means, 3, &f, None, regions), rho)
        });
        match bounce_weight(sc) {
            b if b > 0.0 => BounceTerm::Fixed(b),
            _ => BounceTerm::Off,
        }
    } else {
        BounceTerm::Off
    };
    let base = Design::new(&samples, &means, 3, &base_w, regions, mode);
    let amb = base.solve(None);

    // how deep each depth pixel's body is, for the shadow rays (none are
    // marched without the search)
    let thickness = if p.light && !flat {
        occluder_thickness(inp.depth, k, p.occluder_thickness_m)
    } else {
        Vec::new()
    };
    // the march's step growth, once (lit does not march when reach <= t0)
    let shadow = Shadow {
        reach: p.shadow_reach_m,
        ratio: if p.shadow_reach_m > SHADOW_T0 {
            shadow_ratio(p.shadow_reach_m)
        } else {
            1.0
        },
        thickness: &thickness,
    };
    let light_col = |d: DVec3| -> Vec<f64> {
        samples
            .iter()
            .map(|s| {
                let c = s.n.dot(d);
                if c <= 0.0 || !lit(inp.depth, k, s.pos, s.n, d, shadow) {
                    0.0
                } else {
                    c
                }
            })
            .collect()
    };
    // the search compares Huber costs at the ambient-only fit's scale
    let k_search = amb.as_ref().map_or(0.02, |f| huber_scale(&f.resid));
    let amb_cost = amb
        .as_ref()
        .map_or(f64::INFINITY, |f| huber_cost(&f.resid, &base_w, k_search));
    let score = |d: DVec3, design: &Design| -> Option<(Fit, Vec<f64>, f64)> {
        let col = light_col(d);
        let f = design.solve(Some(&col))?;
        let cost = huber_cost(&f.resid, design.wts, k_search);
        // a light that leaves the low-frequency part too little light of
        // its own is the fit trading one for the other (MIN_AMBIENT_SHARE)
        let plausible =
            f.light > 0.0 && ambient_share(&samples, &f, &col, design.wts) >= MIN_AMBIENT_SHARE;
        plausible.then_some((f, col, cost))
    };
    // search for the light
    let mut best: Option<(DVec3, Fit, Vec<f64>, f64)> = None;
    // the search had no direction above its lowest elevation (the report's reason)
    let mut no_direction = false;
    // the best rival's gain over the best's ([`ambiguity_of`])
    let mut ambiguity: Option<(f64, DVec3)> = None;
    if p.light && !flat {
        let min_up = p.min_elevation_deg.to_radians().sin();
        let dirs: Vec<DVec3> = fibonacci_sphere(p.directions.max(1))
            .into_iter()
            .filter(|d| -d.y >= min_up)
            .collect();
        let mut scored: Vec<(DVec3, f64)> = Vec::with_capacity(dirs.len());
        for chunk in dirs.chunks(SEARCH_CHUNK) {
            check()?;
            scored.par_extend(
                chunk
                    .par_iter()
                    .filter_map(|d| score(*d, &base).map(|(_, _, c)| (*d, c))),
            );
        }
        no_direction = dirs.is_empty();
        let coarse = scored.iter().min_by(|a, b| a.1.total_cmp(&b.1)).copied();
        let mut centre = coarse.map(|(d, _)| d);
        let coarse_best = centre;
        ambiguity = coarse.and_then(|b| ambiguity_of(&scored, b, amb_cost));
        // the fine search with the robust weights of the coarse best
        let mut search_w = base_w.clone();
        if let Some(c) = centre
            && let Some((f, _, _)) = score(c, &base)
        {
            let hw = huber(&f.resid);
            search_w = base_w.iter().zip(&hw).map(|(a, b)| a * b).collect();
        }
        // two finer grids about the best: ±1 coarse spacing, then ±1/4 of one
        let coarse = (4.0 * PI / p.directions.max(1) as f64).sqrt();
        let robust = Design::new(&samples, &means, 3, &search_w, regions, mode);
        for step in [coarse / 4.0, coarse / 16.0] {
            let Some(c) = centre else { break };
            let (t1, t2) = c.any_orthonormal_pair();
            let grid: Vec<DVec3> = (-4..=4)
                .flat_map(|i| (-4..=4).map(move |j| (i, j)))
                .map(|(i, j)| (c + t1 * (i as f64 * step) + t2 * (j as f64 * step)).normalize())
                .filter(|d| -d.y >= min_up)
                .collect();
            check()?;
            // (the grid's centre stays when the robust weights keep none)
            centre = grid
                .par_iter()
                .filter_map(|d| score(*d, &robust).map(|(_, _, c)| (*d, c)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(d, _)| d)
                .or(Some(c));
        }
        // the refined direction, else the coarse one (plausible by construction)
        best = [centre, coarse_best]
            .into_iter()
            .flatten()
            .find_map(|d| score(d, &base).map(|(f, col, c)| (d, f, col, c)));
    }
    let gain = best
        .as_ref()
        .and_then(|(_, _, _, c)| gain_over(*c, amb_cost))
        .unwrap_or(0.0);
    // the mean irradiance of the samples in the fit's units: the light's
    // and sky's 1 plus the bounce
    let bounce_mean = |beta: f64, wts: &[f64]| {
        let ws: f64 = wts.iter().sum();
        // guard: no weight gives no bounce
        if ws > 0.0 {
            beta.max(0.0)
                * wts
                    .iter()
                    .zip(&samples)
                    .map(|(w, s)| w * s.bounce[3])
                    .sum::<f64>()
                / ws
        } else {
            0.0
        }
    };
    let share = best.as_ref().map_or(0.0, |(_, f, _, _)| {
        f.light / (1.0 + bounce_mean(f.beta, &base_w)) // guard: 1 + a mean >= 0
    });
    // a light pressed against the search's lower limit is a grazing light
    // the fit uses to explain gradients (ambient occlusion, bounce), not a
    // sun: it is not believed
    let grazing = best
        .as_ref()
        .is_some_and(|(d, _, _, _)| angles(*d).0 < p.min_elevation_deg + GRAZING_MARGIN_DEG);
    // a light the other rules keep, but whose direction a rival 30° away
    // fits about as well (EstimateParams::max_ambiguity)
    let believed = best.is_some()
        && !grazing
        && gain >= p.min_light_gain
        && share >= p.min_light_share
        && share <= p.max_light_share;
    // (1 = off: a rival ties the best at most, a share of exactly 1)
    let ambiguous =
        believed && p.max_ambiguity < 1.0 && ambiguity.is_some_and(|(a, _)| a >= p.max_ambiguity);
    let keep = believed && !ambiguous;
    let (mut dir, mut col) = match (&best, keep) {
        (Some((d, _, col, _)), true) => (Some(*d), Some(col.clone())),
        _ => (None, None),
    };
    // the direction refined by the cast shadows' edges, where the fit there
    // stays plausible
    let mut refined = None;
    if let Some(d) = dir
        && p.refine_shadows
    {
        let march = March {
            t0: SHADOW_T0,
            reach: p.shadow_reach_m,
            thickness: &thickness,
            slack: March::FINE_SLACK,
            // one step per pixel at 320 across, as the labels
            step_px: (w / 320).max(1) as f64,
        };
        let min_up = p.min_elevation_deg.to_radians().sin();
        let edges = EdgeParams::default();
        let refine = |from: DVec3| {
            refine_direction(
                inp.color, inp.depth, k, &surfaces, &labels, from, min_up, march, &edges,
            )
        };
        // further rounds (at most REFINE_ROUNDS in all) from where the last
        // stopped while that lies at the edge of its radius (the fit may be
        // further off)
        let mut found = refine(d);
        let mut from = d;
        for _ in 1..REFINE_ROUNDS {
            let Some(r) = found else { break };
            if angle_deg(from, r.direction) < 0.8 * edges.radius_deg {
                break;
            }
            let Some(next) = refine(r.direction) else {
                break;
            };
            from = r.direction;
            found = Some(Refined {
                disagree_before: r.disagree_before,
                band: r.band,
                ..next
            });
        }
        if let Some(r) = found
            && let Some((_, c, _)) = score(r.direction, &base)
        {
            dir = Some(r.direction);
            col = Some(c);
            refined = Some((r, angle_deg(d, r.direction)));
        }
    }

    // robust refit (luminance), then each channel with its weights
    let robust = |col: Option<&[f64]>| -> (Option<Fit>, Vec<f64>) {
        let mut wts = base_w.clone();
        let mut fit_l = if flat { None } else { base.solve(col) };
        for _ in 0..4 {
            let Some(f) = fit_l else { break };
            let hw = huber(&f.resid);
            wts = base_w.iter().zip(&hw).map(|(a, b)| a * b).collect();
            fit_l = Design::new(&samples, &means, 3, &wts, regions, mode)
                .solve(col)
                .or(Some(f));
        }
        (fit_l, wts)
    };
    let (mut fit_l, mut wts) = robust(col.as_deref());
    // the search's rule (MIN_AMBIENT_SHARE) on the robust fit too: its
    // weights can hand the sky's light to a low light (an overcast room
    // without the bounce: a light at 10° with no sky beside it); the light
    // is dropped and the sky fitted alone
    let mut traded = None;
    if let (Some(f), Some(c)) = (&fit_l, &col) {
        let a = ambient_share(&samples, f, c, &wts);
        if a < MIN_AMBIENT_SHARE {
            traded = Some(a);
            (dir, col) = (None, None);
            (fit_l, wts) = robust(None);
        }
    }
    let isotropic = Fit {
        theta: {
            let mut t = [0.0; SH_TERMS];
            t[0] = 1.0;
            t
        },
        light: 0.0,
        beta: 0.0,
        rss: 0.0,
        resid: Vec::new(),
    };
    let tss: f64 = ratios
        .iter()
        .zip(&wts)
        .map(|(y, w)| w * (y - 1.0) * (y - 1.0))
        .sum();
    let r2 = match &fit_l {
        Some(f) if tss > 0.0 => (1.0 - f.rss / tss).clamp(0.0, 1.0),
        _ => 0.0,
    };
    // the absolute scale of a fit in a channel at that reflectance
    let scale_of = |f: &Fit, ch: usize| {
        absolute_scale(
            &albedo_terms(&samples, &means, ch, f, col.as_deref(), regions),
            rho,
        )
    };
    // the luminance fit's β, settled with its light and weights
    let beta = match (&fit_l, mode) {
        (Some(f), BounceTerm::Fixed(_)) => bounce_weight(scale_of(f, 3)),
        _ => 0.0,
    };
    let mut fits = [isotropic.clone(), isotropic.clone(), isotropic];
    // the absolute scale per channel at that reflectance: the one the last
    // round computed for its fit, else computed once
    let mut scale = [1.0f64; 3];
    for (ch, f) in fits.iter_mut().enumerate() {
        let mut known = None;
        if !flat {
            // each channel's β settles with its fit at the same reflectance
            let mut beta_c = beta;
            for _ in 0..if beta > 0.0 { 3 } else { 1 } {
                let term = if beta_c > 0.0 {
                    BounceTerm::Fixed(beta_c)
                } else {
                    BounceTerm::Off
                };
                if let Some(s) =
                    Design::new(&samples, &means, ch, &wts, regions, term).solve(col.as_deref())
                {
                    *f = s;
                }
                known = None;
                if beta_c > 0.0 {
                    known = scale_of(f, ch);
                    beta_c = bounce_weight(known);
                }
            }
        }
        scale[ch] = known.or_else(|| scale_of(f, ch)).unwrap_or(1.0);
    }
    // the part of the mean irradiance the photo's surfaces bounce (left
    // out of the map), at the luminance fit's weight
    let bounce_part = {
        let m = bounce_mean(beta, &wts);
        m / (1.0 + m) // guard: m >= 0
    };
    let shc: [[f64; SH_TERMS]; 3] = std::array::from_fn(|ch| fits[ch].theta.map(|t| t * scale[ch]));
    let light_irr: [f64; 3] = std::array::from_fn(|ch| (fits[ch].light * scale[ch]).max(0.0));
    // the map
    let (mw, mh) = (p.width.max(2), (p.width / 2).max(1));
    let ground = p
        .bounce
        .then(|| ground_radiance(&shc, dir, light_irr, p.ground_albedo));
    let mut map = paint_map(mw, mh, ground, |d| {
        std::array::from_fn(|ch| sh::radiance(&shc[ch], d))
    });
    let light = dir.map(|d| {
        paint_sun(&mut map, d, p.light_size_deg, light_irr, SunBlend::Add);
        // the disc's radiance saturates as the rest does (radiance_f32)
        for px in map.as_mut_slice() {
            for v in px.iter_mut() {
                *v = radiance_f32(f64::from(*v));
            }
        }
        let (e, a) = angles(d);
        LightEstimate {
            direction: d,
            elevation_deg: e,
            azimuth_deg: a,
            irradiance: light_irr,
            gain,
        }
    });
    let ambient: [f64; 3] =
        std::array::from_fn(|ch| (shc[ch][0] * sh::basis(DVec3::Y)[0]).max(0.0));
    let confidence = if flat {
        0.0
    } else {
        r2 * (variation / 0.1).min(1.0)
    };
    let amb_l = luminance_f64(ambient).max(0.0);
    let report = match (&light, flat) {
        (_, true) => format!(
            "ambient only, radiance {amb_l:.4}: no usable shading variation (RMS {:.1} %, {:.1} % needed; \
             normals spread {:.3}, {MIN_NORMAL_SPREAD} needed: a flat or uniformly lit surface); confidence \
             {confidence:.2}",
            100.0 * variation,
            100.0 * p.min_variation,
            spread
        ),
        (Some(l), false) => format!(
            "light at elevation {:.1}°, azimuth {:.1}°, irradiance {:.3} ({:.0} % of the mean irradiance; \
             {:.0} % of the residual explained); ambient radiance {amb_l:.4}; confidence {confidence:.2} \
             ({} samples, {regions} regions)",
            l.elevation_deg,
            l.azimuth_deg,
            luminance_f64(l.irradiance),
            100.0 * share,
            100.0 * l.gain,
            samples.len()
        ),
        (None, false) if !p.light => format!(
            "ambient only, radiance {amb_l:.4}: the search for a dominant light is off (light = false); \
             confidence {confidence:.2} ({} samples, {regions} regions)",
            samples.len()
        ),
        (None, false) if no_direction => format!(
            "ambient only, radiance {amb_l:.4}: no dominant light (no direction lies above the lowest \
             elevation searched, {:.0}°); confidence {confidence:.2} ({} samples, {regions} regions)",
            p.min_elevation_deg,
            samples.len()
        ),
        (None, false) if best.is_none() => format!(
            "ambient only, radiance {amb_l:.4}: no dominant light (no direction's fit gives the light a \
             positive irradiance and leaves the low-frequency light {:.0} % of the mean irradiance); \
             confidence {confidence:.2} ({} samples, {regions} regions)",
            100.0 * MIN_AMBIENT_SHARE,
            samples.len()
        ),
        (None, false) if traded.is_some() => format!(
            "ambient only, radiance {amb_l:.4}: no dominant light (the robust fit with the best left the \
             low-frequency light {:.0} % of the mean irradiance, {:.0} % needed: the light traded for the \
             sky); confidence {confidence:.2} ({} samples, {regions} regions)",
            100.0 * traded.unwrap_or(0.0).max(0.0),
            100.0 * MIN_AMBIENT_SHARE,
            samples.len()
        ),
        (None, false) if ambiguous && traded.is_none() => {
            let (a, rival) = ambiguity.unwrap_or((0.0, DVec3::Y));
            let (re, ra) = angles(rival);
            format!(
                "ambient only, radiance {amb_l:.4}: no dominant light (a direction more than \
                 {AMBIGUOUS_DEG:.0}° from the best, elevation {re:.0}°, azimuth {ra:.0}°, explains {:.0} % \
                 as much as it, under {:.0} % needed: the photo does not tell where the light is); confidence \
                 {confidence:.2} ({} samples, {regions} regions)",
                100.0 * a,
                100.0 * p.max_ambiguity,
                samples.len()
            )
        }
        (None, false) if grazing => format!(
            "ambient only, radiance {amb_l:.4}: no dominant light (the best lies at the lowest elevation \
             searched, {:.0}°: a grazing light explaining gradients, not believed); confidence {confidence:.2} \
             ({} samples, {regions} regions)",
            p.min_elevation_deg,
            samples.len()
        ),
        (None, false) => format!(
            "ambient only, radiance {amb_l:.4}: no dominant light (the best explains {:.0} % of the residual, \
             {:.0} % needed, and gives {:.0} % of the mean irradiance, {:.0} to {:.0} % believed); \
             confidence {confidence:.2} ({} samples, {regions} regions)",
            100.0 * gain.max(0.0),
            100.0 * p.min_light_gain,
            100.0 * share.max(0.0),
            100.0 * p.min_light_share,
            100.0 * p.max_light_share,
            samples.len()
        ),
    };
    let report = match refined {
        Some((r, moved)) if light.is_some() => format!(
            "{report}; the light moved {moved:.1}° by the cast shadows' edges ({} of {} edge pixels \
             disagreed with it, {} now)",
            r.disagree_before, r.band, r.disagree_after
        ),
        _ => report,
    };
    let report = if bounce_part > 0.0 {
        format!(
            "{report}; the photo's surfaces bounce {:.0} % of the mean irradiance, left out of the map",
            100.0 * bounce_part
        )
    } else {
        report
    };
    Ok(LightingEstimate {
        map,
        sh: shc,
        light,
        ambient,
        confidence,
        variation,
        samples: samples.len(),
        regions,
        report,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::lighting_truth::{LightRoom, light_case};
    use crate::sim::pathtrace::PathTraceParams;
    use crate::sim::relight_truth::{Room, Sky, relight_case};
    use crate::sim::synthetic::{RenderOptions, Scene, ScenePreset, render, sun_direction};

    fn estimate(
        c: &ColorImage,
        d: &DepthMap,
        k: &Intrinsics,
        n: Option<&NormalMap>,
    ) -> LightingEstimate {
        estimate_with(c, d, k, n, &EstimateParams::default())
    }

    fn estimate_with(
        c: &ColorImage,
        d: &DepthMap,
        k: &Intrinsics,
        n: Option<&NormalMap>,
        p: &EstimateParams,
    ) -> LightingEstimate {
        let inp = EstimateInputs {
            color: c,
            depth: d,
            k,
            normals: n,
            mask: None,
        };
        estimate_lighting(&inp, p).unwrap()
    }

    /// The scores of `case` relit with `map` (256 VPLs, scene cached,
    /// default parameters).
    fn relit_scores(
        case: &crate::sim::relight_truth::RelightCase,
        map: &ColorImage,
    ) -> crate::sim::relight_truth::Scores {
        use crate::relight::scene_cached::{RelightScene, relight_moved};
        use crate::relight::shading::RelightParams;
        use crate::relight::vpl::{VplParams, sample_vpls};
        let inp = case.inputs();
        let p = RelightParams::default();
        let vpls = sample_vpls(
            map,
            &VplParams {
                count: 256,
                seed: 1,
                ..Default::default()
            },
        );
        let sc = RelightScene::new(&inp.scene(), &vpls, &p).unwrap();
        crate::sim::relight_truth::score(
            case,
            &relight_moved(&sc, &inp, &p).unwrap().unwrap().color,
        )
    }

    /// The tests' path tracing: 128 paths per pixel, 3 bounces, seed 1.
    const PT: PathTraceParams = PathTraceParams {
        samples: 128,
        bounces: 3,
        seed: 1,
    };

    fn path_traced(room: LightRoom, sky: Sky) -> LightingEstimate {
        let c = light_case(room, sky, 160, 120, 128, &PT).unwrap();
        estimate(&c.photo, &c.depth, &c.k, None)
    }

    /// The SyntheticScene's tabletop (a sun and a uniform ambient term,
    /// cast shadows; textured surfaces): the sun within 10°, at 320x240
    /// and at 640x480 (where the regions are built on every other pixel).
    #[test]
    fn finds_the_sun_of_a_rendered_tabletop() {
        let (e, a) = (35.0, 40.0);
        for (w, h) in [(320, 240), (640, 480)] {
            let mut scene = Scene::of(ScenePreset::Tabletop, w, h);
            scene.light.sun_direction = sun_direction(e, a);
            let out = render(&scene, &RenderOptions::default());
            let est = estimate(&out.color, &out.depth, &scene.camera, Some(&out.normals));
            let l = est
                .light
                .unwrap_or_else(|| panic!("no light: {}", est.report));
            let err = angle_deg(l.direction, sun_direction(e, a));
            assert!(err < 10.0, "{w}x{h}: {err:.1}° off: {}", est.report);
            assert!(est.report.contains("light at elevation"), "{}", est.report);
        }
    }

    /// The light's search asks the cancellation check between chunks of
    /// directions, and a cancelled run ends with its error (the node could
    /// not be cancelled: `directions` x `samples` at their maxima is hours).
    #[test]
    fn the_light_search_can_be_cancelled() {
        let mut scene = Scene::of(ScenePreset::Tabletop, 160, 120);
        scene.light.sun_direction = sun_direction(35.0, 40.0);
        let out = render(&scene, &RenderOptions::default());
        let inp = EstimateInputs {
            color: &out.color,
            depth: &out.depth,
            k: &scene.camera,
            normals: Some(&out.normals),
            mask: None,
        };
        let p = EstimateParams::default();
        let calls = std::cell::Cell::new(0usize);
        let counted = estimate_lighting_with(&inp, &p, &|| {
            calls.set(calls.get() + 1);
            Ok(())
        })
        .unwrap();
        // the coarse search's chunks (the 300 directions' upper part: more
        // than one) and the two finer grids
        assert!(calls.get() >= 4, "{}", calls.get());
        assert_eq!(counted.report, estimate_lighting(&inp, &p).unwrap().report);
        let after = std::cell::Cell::new(0usize);
        let e = estimate_lighting_with(&inp, &p, &|| {
            after.set(after.get() + 1);
            if after.get() > 2 {
                Err(NodeError::Cancelled)
            } else {
                Ok(())
            }
        })
        .map(|_| ())
        .unwrap_err();
        assert!(matches!(e, NodeError::Cancelled), "{e}");
        assert_eq!(after.get(), 3);
    }

    /// Path-traced rooms lit only by a sky with a sun (depth only, normals
    /// from it): the sun within 10° of the truth, and the map's sun carries
    /// most of the light a surface facing it receives.
    #[test]
    fn finds_the_sun_of_path_traced_rooms() {
        for (e, a) in [(50.0, -40.0), (40.0, 70.0), (60.0, -80.0), (30.0, 20.0)] {
            let est = path_traced(
                LightRoom::Objects,
                Sky::Sun {
                    elevation_deg: e,
                    azimuth_deg: a,
                },
            );
            eprintln!("({e}, {a}): {}", est.report);
            let l = est
                .light
                .unwrap_or_else(|| panic!("({e}, {a}): no light: {}", est.report));
            let err = angle_deg(l.direction, sun_direction(e, a));
            assert!(err < 10.0, "({e}, {a}): {err:.1}° off: {}", est.report);
            assert!(est.confidence > 0.5, "{}", est.report);
            // the map's brightest pixel looks towards the light
            let (w, h) = est.map.dims();
            let (mut bi, mut bv) = (0, 0.0f32);
            for (i, c) in est.map.as_slice().iter().enumerate() {
                if c[1] > bv {
                    (bi, bv) = (i, c[1]);
                }
            }
            let d = pixel_direction((bi % w) as f64 + 0.5, (bi / w) as f64 + 0.5, w, h);
            assert!(angle_deg(d, l.direction) < 3.0);
        }
    }

    /// The cast shadows' edges place the sun: on the path-traced rooms of
    /// [`finds_the_sun_of_path_traced_rooms`] within 3° at 160x120 (a
    /// degree at 320x240, docs/lighting.md), and on average less than half
    /// as far off as the fit's sparse samples alone (`refine_shadows =
    /// false`: 3-8°). On the depth a Kinect-like camera measures (noise,
    /// disparity steps, holes) the refinement still lowers the mean error
    /// by a quarter (at 160x120: 5.7° against 10.8°; a light missed counts
    /// 180°).
    #[test]
    fn the_shadows_edges_place_the_sun_to_a_degree() {
        use crate::sim::sensor::{KinectParams, simulate_kinect};
        let (mut worst, mut sum_on, mut sum_off) = (0.0f64, 0.0, 0.0);
        let (mut kinect_on, mut kinect_off) = (0.0f64, 0.0);
        for (e, a) in [(50.0, -40.0), (40.0, 70.0), (60.0, -80.0), (30.0, 20.0)] {
            let sky = Sky::Sun {
                elevation_deg: e,
                azimuth_deg: a,
            };
            let c = light_case(LightRoom::Objects, sky, 160, 120, 128, &PT).unwrap();
            // the same depth as a Kinect-like camera measures it (noise,
            // disparity steps, the projector's shadows)
            let kinect =
                simulate_kinect(&c.depth, Some(&c.photo), &c.k, &KinectParams::default()).unwrap();
            let err = |depth: &DepthMap, refine: bool| {
                let p = EstimateParams {
                    refine_shadows: refine,
                    ..Default::default()
                };
                let est = estimate_with(&c.photo, depth, &c.k, None, &p);
                est.light.map_or((180.0, est.report.clone()), |l| {
                    (angle_deg(l.direction, sun_direction(e, a)), est.report)
                })
            };
            let ((on, report), (off, _)) = (err(&c.depth, true), err(&c.depth, false));
            let ((k_on, _), (k_off, _)) = (err(&kinect, true), err(&kinect, false));
            eprintln!(
                "({e}, {a}): refined {on:.2}°, fit alone {off:.2}°; Kinect-like depth {k_on:.2}°, \
                 {k_off:.2}°: {report}"
            );
            assert!(report.contains("cast shadows' edges"), "{report}");
            worst = worst.max(on);
            sum_on += on;
            sum_off += off;
            kinect_on += k_on;
            kinect_off += k_off;
        }
        eprintln!(
            "Kinect-like depth: mean refined {:.2}, fit alone {:.2}",
            kinect_on / 4.0,
            kinect_off / 4.0
        );
        assert!(
            kinect_on < kinect_off,
            "{kinect_on:.2} against {kinect_off:.2}"
        );
        eprintln!(
            "worst {worst:.2}, mean refined {:.2}, fit alone {:.2}",
            sum_on / 4.0,
            sum_off / 4.0
        );
        assert!(worst < 3.0, "{worst:.2}°");
        assert!(sum_on < 0.5 * sum_off, "{sum_on:.2} against {sum_off:.2}");
    }

    /// The furnished room (a sphere pasted before a sphere, a box and a
    /// cylinder under a sun): relit with the map estimated from the photo,
    /// the object's shadow and bounce come within 3 dB of the true map's
    /// (the bar; with the sun of the fit alone it is 4-6 dB below).
    #[test]
    fn relit_with_the_estimated_sun_the_shadow_is_within_3_db_of_the_true_maps() {
        let case = relight_case(Room::Furnished, None, 320, 240, 128, &PT).unwrap();
        let relit = |map: &ColorImage| relit_scores(&case, map);
        let est = |refine: bool| {
            let p = EstimateParams {
                refine_shadows: refine,
                ..Default::default()
            };
            estimate_with(&case.photo, &case.depth, &case.k, None, &p)
        };
        let t = relit(&case.env);
        let (on, off) = (est(true), est(false));
        let (e, f) = (relit(&on.map), relit(&off.map));
        eprintln!(
            "influence: true map {:.2}, estimated {:.2}, fit alone {:.2}; {}",
            t.influence_db, e.influence_db, f.influence_db, on.report
        );
        assert!(
            e.influence_db >= t.influence_db - 3.0,
            "influence {:.1} dB, true map {:.1}: {}",
            e.influence_db,
            t.influence_db,
            on.report
        );
    }

    /// Without the bounce, the overcast `occluded` room's robust fit hands
    /// the sky to a light at 10° (the search's candidate kept a sky): the
    /// rule of the search holds for the robust fit too, the light is
    /// dropped and the report says why.
    #[test]
    fn a_light_the_robust_fit_trades_for_the_sky_is_dropped() {
        let case = relight_case(Room::Occluded, Some(Sky::Overcast), 320, 240, 128, &PT).unwrap();
        let p = EstimateParams {
            bounce: false,
            ..Default::default()
        };
        let est = estimate_with(&case.photo, &case.depth, &case.k, None, &p);
        eprintln!("{}", est.report);
        assert!(est.light.is_none(), "{}", est.report);
        assert!(est.report.contains("traded for the sky"), "{}", est.report);
        assert!(est.ambient[1] > 0.1, "{:?}", est.ambient);
    }

    /// An overcast sky has no sun: the estimate keeps the low-frequency
    /// light only, brighter above than below.
    #[test]
    fn an_overcast_room_has_no_sun() {
        let est = path_traced(LightRoom::Objects, Sky::Overcast);
        assert!(est.light.is_none(), "{}", est.report);
        let up = sh::irradiance(&est.sh[1], DVec3::NEG_Y);
        let down = sh::irradiance(&est.sh[1], DVec3::Y);
        assert!(up > down, "up {up}, down {down}");
    }

    /// The map's level: the rooms' surfaces have reflectances 0.45-0.6 and
    /// the assumed median is 0.5, so the estimated sky lights an upward
    /// surface about as the true map does (within 30 %; an albedo read as
    /// `r` instead of `r/π` put it at a third). With `bounce` the report
    /// says how much of the irradiance the photo's surfaces gave, without
    /// it not.
    #[test]
    fn the_maps_level_is_the_truths_at_the_rooms_reflectance() {
        let c = light_case(LightRoom::Objects, Sky::Overcast, 160, 120, 128, &PT).unwrap();
        let est = estimate(&c.photo, &c.depth, &c.k, None);
        let truth = sh::project_map(&c.env);
        let up = |l: &[f64; SH_TERMS]| sh::irradiance(l, DVec3::NEG_Y);
        let ratio = up(&est.sh[1]) / up(&truth[1]);
        assert!((0.7..1.3).contains(&ratio), "{ratio}: {}", est.report);
        assert!(est.report.contains("surfaces bounce"), "{}", est.report);
        let inp = EstimateInputs {
            color: &c.photo,
            depth: &c.depth,
            k: &c.k,
            normals: None,
            mask: None,
        };
        let off = EstimateParams {
            bounce: false,
            ..Default::default()
        };
        let est = estimate_lighting(&inp, &off).unwrap();
        assert!(!est.report.contains("bounce"), "{}", est.report);
    }

    /// The object pasted in the open room under an overcast sky, relit with
    /// the estimated map on both sides: the map's ground lights its
    /// underside at its capture as the truth's dim ground does, so the
    /// relit object beats the naive paste by 3 dB (the fit's extrapolated
    /// ground, a sky's brightness below the horizon, gave +1 dB), and the
    /// influence region stays within 3 dB of the true map's.
    #[test]
    fn the_maps_ground_relights_the_objects_underside() {
        let case = relight_case(Room::Open, Some(Sky::Overcast), 160, 120, 128, &PT).unwrap();
        let relit = |map: &ColorImage| relit_scores(&case, map);
        let est = estimate(&case.photo, &case.depth, &case.k, None);
        let (e, t) = (relit(&est.map), relit(&case.env));
        assert!(
            e.object_db >= e.naive_object_db + 3.0,
            "object {:.1} dB, naive {:.1}: {}",
            e.object_db,
            e.naive_object_db,
            est.report
        );
        assert!(
            e.influence_db >= t.influence_db - 3.0,
            "influence {:.1} dB, true map {:.1}",
            e.influence_db,
            t.influence_db
        );
    }

    /// An overcast room whose floor is most of the photo (the relight
    /// truth's `occluded`: a floor, a back wall and a box): a low light,
    /// whose cos is nearly the same over the whole floor, fits the shading
    /// as well as the sky does, with a negative sky beside it; such a fit
    /// takes no part in the search ([`MIN_AMBIENT_SHARE`]; without the
    /// rule it is kept), and the sky stays.
    #[test]
    fn a_light_that_leaves_no_ambient_is_not_believed() {
        let case = relight_case(Room::Occluded, Some(Sky::Overcast), 160, 120, 128, &PT).unwrap();
        let est = estimate(&case.photo, &case.depth, &case.k, None);
        assert!(est.light.is_none(), "{}", est.report);
        assert!(luminance_f64(est.ambient) > 0.0, "{}", est.report);
    }

    /// The rival is the best direction beyond 30°: neighbours within it
    /// do not count, the share is of the gains over the ambient-only cost,
    /// and a best that explains nothing has no share.
    #[test]
    fn the_ambiguity_is_the_best_rivals_share_of_the_gain() {
        let at = |deg: f64| {
            let r = deg.to_radians();
            DVec3::new(r.sin(), -r.cos(), 0.0)
        };
        // the best (cost 0.2), a neighbour at 10° nearly as good, rivals at 40° and 90°
        let scored = [
            (at(0.0), 0.2),
            (at(10.0), 0.21),
            (at(40.0), 0.3),
            (at(90.0), 0.6),
        ];
        let best = (at(0.0), 0.2);
        let (a, rival) = ambiguity_of(&scored, best, 1.0).unwrap();
        assert!((a - 0.7 / 0.8).abs() < 1e-12, "{a}");
        assert!(angle_deg(rival, at(40.0)) < 1e-9);
        // nothing beyond 30°, a best no better than the ambient, no ambient cost
        assert!(ambiguity_of(&scored[..2], best, 1.0).is_none());
        assert!(ambiguity_of(&scored, best, 0.2).is_none());
        assert!(ambiguity_of(&scored, best, f64::INFINITY).is_none());
        assert!(ambiguity_of(&scored, best, 0.0).is_none());
    }

    /// A sun that lights a floor and a wall but casts no shadow the photo
    /// shows (the relight truth's near-wall and coloured-floor rooms: the
    /// object is pasted later): a whole arc of directions fits the shading
    /// alike, and the estimate claims no sun and says why; with the rule
    /// off (`max_ambiguity` 1) it picks one from the arc, tens of degrees
    /// from the truth.
    #[test]
    fn a_light_the_photo_does_not_place_is_not_invented() {
        // the rooms' own suns
        for (room, e, a) in [
            (Room::NearWall, 40.0, 70.0),
            (Room::ColouredFloor, 55.0, -20.0),
        ] {
            let sky = Sky::Sun {
                elevation_deg: e,
                azimuth_deg: a,
            };
            let case = relight_case(room, Some(sky), 160, 120, 128, &PT).unwrap();
            let est = estimate(&case.photo, &case.depth, &case.k, None);
            assert!(est.light.is_none(), "{room:?}: {}", est.report);
            assert!(
                est.report.contains("does not tell where the light is"),
                "{room:?}: {}",
                est.report
            );
            assert!(luminance_f64(est.ambient) > 0.0, "{}", est.report);
            let off = EstimateParams {
                max_ambiguity: 1.0,
                ..Default::default()
            };
            let invented = estimate_with(&case.photo, &case.depth, &case.k, None, &off);
            let l = invented
                .light
                .unwrap_or_else(|| panic!("{room:?}, rule off: {}", invented.report));
            let truth = sun_direction(e, a);
            assert!(
                angle_deg(l.direction, truth) > 20.0,
                "{room:?}: the arc's pick {:.1}° off",
                angle_deg(l.direction, truth)
            );
        }
    }

    /// The report says why no light was kept where the search could keep
    /// none: no direction above the lowest elevation searched (89.9°:
    /// none of the coarse directions), or the search switched off.
    #[test]
    fn the_report_says_why_no_light_was_kept() {
        let c = light_case(
            LightRoom::Objects,
            Sky::Sun {
                elevation_deg: 50.0,
                azimuth_deg: -40.0,
            },
            160,
            120,
            128,
            &PT,
        )
        .unwrap();
        let inp = EstimateInputs {
            color: &c.photo,
            depth: &c.depth,
            k: &c.k,
            normals: None,
            mask: None,
        };
        let high = EstimateParams {
            min_elevation_deg: 89.9,
            ..Default::default()
        };
        let est = estimate_lighting(&inp, &high).unwrap();
        assert!(est.light.is_none(), "{}", est.report);
        assert!(
            est.report.contains("no direction lies above"),
            "{}",
            est.report
        );
        let off = EstimateParams {
            light: false,
            ..Default::default()
        };
        let est = estimate_lighting(&inp, &off).unwrap();
        assert!(est.light.is_none());
        assert!(
            est.report.contains("search for a dominant light is off"),
            "{}",
            est.report
        );
    }

    /// The share of the low-frequency light: all of it without a light,
    /// half where the two give alike, none where the SH part gives nothing.
    #[test]
    fn the_ambient_share_weighs_the_two_parts() {
        let s = |n: DVec3| Sample {
            pos: DVec3::Z,
            n,
            rgbl: [0.5; 4],
            region: 0,
            phi: sh::irradiance_basis(n),
            bounce: [0.25; 4],
        };
        let samples = [s(DVec3::NEG_Y), s(DVec3::NEG_Z)];
        let mut theta = [0.0; SH_TERMS];
        // the DC term alone: E = theta_0 phi_0, the same for every normal
        theta[0] = 1.0 / samples[0].phi[0];
        let fit_b = |light: f64, theta: [f64; SH_TERMS], beta: f64| Fit {
            theta,
            light,
            beta,
            rss: 0.0,
            resid: Vec::new(),
        };
        let fit = |light: f64, theta: [f64; SH_TERMS]| fit_b(light, theta, 0.0);
        let w = [1.0, 1.0];
        let col = [1.0, 1.0];
        assert!((ambient_share(&samples, &fit(0.0, theta), &col, &w) - 1.0).abs() < 1e-12);
        assert!((ambient_share(&samples, &fit(1.0, theta), &col, &w) - 0.5).abs() < 1e-12);
        assert_eq!(
            ambient_share(&samples, &fit(1.0, [0.0; SH_TERMS]), &col, &w),
            0.0
        );
        // a negative sky beside the light: a negative share
        let neg = theta.map(|t| -0.5 * t);
        assert!((ambient_share(&samples, &fit(1.0, neg), &col, &w) + 1.0).abs() < 1e-12);
        // a mean irradiance that is not positive: no share (the guard)
        assert_eq!(ambient_share(&samples, &fit(-1.0, theta), &col, &w), 0.0);
        // no weight: no share (the guard)
        assert_eq!(
            ambient_share(&samples, &fit(1.0, theta), &col, &[0.0, 0.0]),
            0.0
        );
        // the bounce counts with the low-frequency part: β B = 1 beside a
        // sky of 1 and a light of 1 gives 2/3; a sky of 0 beside them 1/2
        assert!(
            (ambient_share(&samples, &fit_b(1.0, theta, 4.0), &col, &w) - 2.0 / 3.0).abs() < 1e-12
        );
        assert!(
            (ambient_share(&samples, &fit_b(1.0, [0.0; SH_TERMS], 4.0), &col, &w) - 0.5).abs()
                < 1e-12
        );
    }

    /// The ground under a light alone at elevation `e` (no sky): `ρ s
    /// sin(e) / π`, the light's irradiance on a horizontal plane; with no
    /// light or a light below the horizon, the sky's part alone.
    #[test]
    fn the_ground_is_lit_by_the_sky_and_the_light() {
        let e = 30f64.to_radians();
        let d = DVec3::new(0.0, -e.sin(), e.cos());
        let g = ground_radiance(&[[0.0; SH_TERMS]; 3], Some(d), [2.0, 1.0, 0.5], 0.2);
        for (ch, s) in [2.0, 1.0, 0.5].into_iter().enumerate() {
            let want = 0.2 * s * e.sin() / PI;
            assert!((g[ch] - want).abs() < 1e-12, "{} {want}", g[ch]);
        }
        let below = ground_radiance(&[[0.0; SH_TERMS]; 3], Some(-d), [2.0; 3], 0.2);
        assert_eq!(below, [0.0; 3]);
        // a uniform sky of radiance 1: irradiance π above, ground ρ
        let mut shc = [[0.0; SH_TERMS]; 3];
        for c in &mut shc {
            c[0] = 1.0 / sh::basis(DVec3::Y)[0];
        }
        let g = ground_radiance(&shc, None, [0.0; 3], 0.3);
        assert!(g.iter().all(|v| (v - 0.3).abs() < 1e-9), "{g:?}");
    }

    /// A flat wall shows no shading variation: ambient only, a uniform sky
    /// over the ground,
    /// confidence 0, and the report says why, under a sun as well.
    #[test]
    fn a_flat_wall_gives_ambient_only_and_says_so() {
        for sky in [
            Sky::Overcast,
            Sky::Sun {
                elevation_deg: 40.0,
                azimuth_deg: 20.0,
            },
        ] {
            let est = path_traced(LightRoom::FlatWall, sky);
            assert!(
                est.light.is_none() && est.confidence < 0.05,
                "{}",
                est.report
            );
            assert!(
                est.report.contains("no usable shading variation"),
                "{}",
                est.report
            );
            // a uniform sky over a ground of reflectance 0.1 under it
            let (w, h) = est.map.dims();
            let (mut sky_px, mut ground_px) = (Vec::new(), Vec::new());
            for y in 0..h {
                for x in 0..w {
                    let d = pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h);
                    let v = est.map.get(x, y)[1];
                    if below_horizon(d) {
                        &mut ground_px
                    } else {
                        &mut sky_px
                    }
                    .push(v);
                }
            }
            let range = |v: &[f32]| {
                v.iter()
                    .fold((f32::MAX, 0.0f32), |(a, b), c| (a.min(*c), b.max(*c)))
            };
            let (lo, hi) = range(&sky_px);
            assert!(hi > 0.0 && (hi - lo) / hi < 1e-3, "isotropic: {lo} to {hi}");
            let (glo, ghi) = range(&ground_px);
            let want = EstimateParams::default().ground_albedo as f32 * hi;
            assert!(
                (glo - want).abs() <= 1e-3 * want && (ghi - want).abs() <= 1e-3 * want,
                "ground {glo} to {ghi}, {want} expected"
            );
        }
    }

    /// No depth: the ambient level of the photo's mean colour, confidence
    /// 0, and the reason; mismatched sizes are errors, not panics.
    #[test]
    fn no_depth_gives_ambient_only_and_bad_sizes_are_errors() {
        let k = crate::sim::synthetic::kinect_like_intrinsics(32, 24);
        let c = ColorImage::filled(32, 24, [0.5f32; 3]);
        let d = DepthMap::filled(32, 24, 0.0);
        let inp = EstimateInputs {
            color: &c,
            depth: &d,
            k: &k,
            normals: None,
            mask: None,
        };
        let est = estimate_lighting(&inp, &EstimateParams::default()).unwrap();
        assert!(
            est.light.is_none() && est.confidence == 0.0,
            "{}",
            est.report
        );
        assert!(
            est.report.contains("no pixel has a depth"),
            "{}",
            est.report
        );
        // a surface of reflectance 0.5 under isotropic radiance L shows 0.5 L
        let l = f64::from(est.map.get(0, 0)[1]);
        assert!((l - 1.0).abs() < 1e-6, "{l}");
        let small = DepthMap::filled(16, 24, 1.0);
        let inp = EstimateInputs {
            depth: &small,
            ..inp
        };
        assert!(estimate_lighting(&inp, &EstimateParams::default()).is_err());
    }
}
