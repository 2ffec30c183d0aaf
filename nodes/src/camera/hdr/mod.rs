//! High-dynamic-range radiance maps from exposure brackets (seed paper
//! realistic-depth-blur §2.1; P. Debevec, J. Malik, "Recovering High Dynamic
//! Range Radiance Maps from Photographs", SIGGRAPH 1997).
//!
//! # Model (Debevec & Malik §2.1)
//!
//! A pixel value is `Z_ij = f(E_i Δt_j)` (eq. 1): the camera response `f` of
//! the exposure, radiance `E_i` of pixel `i` times exposure time `Δt_j` of
//! image `j`. With `g = ln f^-1`, `g(Z_ij) = ln E_i + ln Δt_j` (eq. 2).
//!
//! - [`recover_response`] estimates `g` on the 256 levels `z = round(value *
//!   255)` of each channel by minimising the weighted objective (eq. 5, the
//!   weighted form of eq. 3)
//!
//!   `O = Σ_i Σ_j {w(Z_ij) [g(Z_ij) - ln E_i - ln Δt_j]}² + λ Σ_{z=1}^{254} [w(z) g''(z)]²`
//!
//!   with the hat weighting `w(z) = min(z, 255 - z)` (eq. 4, `Z_min = 0`,
//!   `Z_max = 255`) and `g''(z) = g(z-1) - 2 g(z) + g(z+1)`, subject to
//!   `g(128) = 0`. This module's `λ` is relative: the smoothness term is
//!   scaled by the data term's total weight (see [`recover_response`]), so
//!   one value serves 2 exposures and 16 alike. The samples cover every
//!   level each exposure sees, and the solution is made non-decreasing with
//!   straight ends beyond the data, which is what keeps 2-3 exposure
//!   brackets from ending in noise.
//! - [`recover_polynomial`] fits Mitsunaga & Nayar's polynomial inverse
//!   response instead (a handful of coefficients: less data needed).
//! - [`merge_hdr`] evaluates eq. 6 per pixel and channel:
//!   `ln E = Σ_j w_j (g(Z_j) - ln Δt_j) / Σ_j w_j`, the hat weight of eq. 4
//!   times the curve's exposure resolution at `Z_j` (low where the response
//!   is flat: a toe, a shoulder, a black floor), by default one weight per
//!   exposure shared by the channels ([`MergeWeights::Joint`]).
//! - [`align_bracket`] registers handheld brackets first (Ward 2003).
//!
//! `g` is only determined up to an additive constant per channel, so
//! recovered radiance is known up to one unknown factor per channel (a
//! global scale and a white balance, as the paper notes in §2.1). The
//! recovery ties the channels so that the camera's neutral stays neutral
//! ([`recover_response`]; mean `g(128)` over channels is 0), and a known
//! white region can fix the balance instead ([`MergeParams::white`]).
//! Compare recovered radiance with a reference only after fitting the
//! factor. A *given* curve ([`ResponseCurve::gamma`],
//! [`ResponseCurve::linear`]) is absolute: `g(255) = 0`, so the sensor
//! saturates where `E Δt = 1` (the convention of `SimulateBracket`).
//!
//! # Conventions
//!
//! - Stack images hold values in `[0, 1]` *after* the camera response (not
//!   linearised). Finite values outside `[0, 1]` are clipped; NaN and
//!   infinities mean "missing" (weight 0), e.g. the pure-blue borders of
//!   Debevec's memorial series once [`load_bracket`] masks them.
//! - `z = value * 255` is a real number in the merge (so 16-bit and float
//!   inputs keep their precision; `g` is interpolated linearly between levels)
//!   and is rounded to a level for the recovery.
//! - The weights have no floor: a saturated (`z = 255`) or black (`z = 0`)
//!   value says only that the exposure was out of range, and a floor would
//!   let such values pull the estimate. Pixels with no weight at all take the
//!   documented fallback of [`merge_hdr`] instead.
//! - Sums are accumulated in f64; the output is linear RGB f32.

#[cfg(test)]
mod accuracy_tests;
mod align;
mod bracket;
mod compare;
mod curve;
mod merge;
mod polynomial;
mod recover;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

pub use align::{AlignParams, Alignment, align_bracket};
pub use bracket::{
    LoadBracketParams, bracket_entries, load_bracket, load_bracket_with, parse_bracket_list,
};
use bracket::{bracket_files, load_bracket_eval};
pub use compare::{mean_stops_apart, seen_well};
use curve::check_stack;
pub use curve::{LEVELS, ResponseCurve, Z_MID, hat_weight};
pub use merge::{MergeParams, MergeWeights, Merged, merge_hdr, merge_hdr_with};
pub use polynomial::{PolynomialParams, recover_polynomial};
pub use recover::{ResponseParams, recover_response, recover_response_with};

// ---------------------------------------------------------------------------
// Nodes
// ---------------------------------------------------------------------------

depthgraph_graph::param_choice! {
    /// Where the response curve comes from (the `response` parameter).
    pub enum ResponseSource {
        /// Estimated from the stack (eq. 5).
        Recover = "recover",
        /// A polynomial inverse response fitted to the stack (Mitsunaga & Nayar 1999).
        Polynomial = "polynomial",
        /// A known gamma camera (the curve of SimulateBracket).
        Gamma = "gamma",
        /// A linear camera.
        Linear = "linear",
    }
}

depthgraph_graph::param_choice! {
    /// How exposures are weighted in the merge (the `weights` parameter).
    pub enum WeightChoice {
        /// One weight per exposure, the mean of the channels' weights.
        Joint = "joint",
        /// Each channel its own weight.
        Channel = "channel",
    }
}

node_params! {
    /// Parameters of `HdrMerge`.
    pub struct HdrMergeParams {
        /// "recover": estimate g from the stack (eq. 5); "polynomial": fit a polynomial inverse
        /// response (Mitsunaga & Nayar; fewer unknowns, for brackets with little data); "gamma": a
        /// known gamma camera (the curve of SimulateBracket); "linear": a linear camera. A
        /// connected `curve` input overrides it.
        pub response: ResponseSource = ResponseSource::Recover, ParamKind::Choice(ResponseSource::NAMES);
        /// Gamma of the "gamma" response (see SimulateBracket).
        pub gamma: f64 = 2.2, ParamKind::Float { min: 1.0, max: 5.0 };
        /// "recover", "polynomial": pixels sampled per channel over the radiance range (flat
        /// regions preferred), on top of up to two pixels at every level of every exposure.
        pub samples: usize = 400usize, ParamKind::Int { min: 2, max: 100_000 };
        /// "recover": relative smoothness (the smoothness term of eq. 5 weighs lambda times the
        /// data term's mean weight per level, whatever the number of samples and exposures).
        pub lambda: f64 = 1e5, ParamKind::Float { min: 1e-6, max: 1e9 };
        /// "polynomial": degree of the inverse response polynomial.
        pub degree: usize = 4usize, ParamKind::Int { min: 1, max: 8 };
        /// "joint": one weight per exposure shared by the channels (an exposure is trusted as a
        /// whole; keeps hues steady); "channel": each channel its own weight. Weights are eq. 4's
        /// hat times the curve's exposure resolution at the level (low on a toe or shoulder).
        pub weights: WeightChoice = WeightChoice::Joint, ParamKind::Choice(WeightChoice::NAMES);
        /// A neutral (white or grey) region [x0, y0, x1, y1] in pixels (half-open): the channels
        /// are scaled so that its mean radiance is neutral. Empty: the camera's own balance.
        pub white: Vec<f64> = Vec::<f64>::new(), ParamKind::Floats { min: 0.0, max: 1e6 };
    }
}

impl HdrMergeParams {
    /// The recovery part of the parameters.
    pub fn response_params(&self) -> ResponseParams {
        ResponseParams {
            samples: self.samples,
            lambda: self.lambda,
        }
    }

    /// The merge part of the parameters; errors name a malformed `white`.
    pub fn merge_params(&self) -> Result<MergeParams, NodeError> {
        let white = match self.white.as_slice() {
            [] => None,
            [x0, y0, x1, y1] => {
                let px = |v: f64| -> Result<usize, NodeError> {
                    if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v <= 1e9 {
                        Ok(v as usize)
                    } else {
                        Err(NodeError::param(
                            "white",
                            format!("{v} is not a pixel coordinate (a whole number >= 0)"),
                        ))
                    }
                };
                Some([px(*x0)?, px(*y0)?, px(*x1)?, px(*y1)?])
            }
            other => {
                return Err(NodeError::param(
                    "white",
                    format!(
                        "holds {} numbers; expected none or four: [x0, y0, x1, y1]",
                        other.len()
                    ),
                ));
            }
        };
        Ok(MergeParams {
            weights: match self.weights {
                WeightChoice::Joint => MergeWeights::Joint,
                WeightChoice::Channel => MergeWeights::Channel,
            },
            white,
        })
    }
}

depthgraph_graph::ports! {
    /// Inputs of `HdrMerge`.
    inputs struct HdrMergeIn {
        /// exposures with their times
        stack: Arc<ExposureStack>,
        /// a 256x1 response curve (another HdrMerge's `curve`); overrides `response`
        curve: Option<Arc<ColorImage>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `HdrMerge`.
    outputs struct HdrMergeOut {
        /// linear radiance
        color: ColorImage,
        /// 256x1: exp g(z) per channel, the relative exposure giving level z
        curve: ColorImage,
        /// 1 where a channel was saturated, black or missing in every exposure
        fallback: Mask,
        /// min(1, sum of weights / one mid-level exposure) of the least supported channel; 0 at
        /// fallback pixels
        confidence: Confidence,
    }
}

fn hdr_merge_eval(
    ctx: &EvalCtx,
    i: HdrMergeIn,
    p: &HdrMergeParams,
) -> Result<Produced<HdrMergeOut>, NodeError> {
    let stack = &i.stack;
    let (w, h) = check_stack(stack)?;
    let merge_params = p.merge_params()?;
    let curve = match &i.curve {
        Some(img) => ResponseCurve::from_image(img, "curve")?,
        None => match p.response {
            ResponseSource::Gamma => ResponseCurve::gamma(p.gamma),
            ResponseSource::Linear => ResponseCurve::linear(),
            ResponseSource::Recover | ResponseSource::Polynomial => {
                if stack.images.len() == 1 {
                    let out = HdrMergeOut {
                        color: stack.images[0].clone(),
                        curve: ResponseCurve::linear().to_image(),
                        fallback: Mask::filled(w, h, 0.0),
                        confidence: Confidence::filled(w, h, 0.0),
                    };
                    return Ok(Produced::passthrough(
                        out,
                        "a single exposure: no response can be recovered from one image, so it is passed \
                         through unchanged (not linearised); set response to \"gamma\" or \"linear\", or \
                         connect a `curve`, to merge it",
                    ));
                }
                if p.response == ResponseSource::Polynomial {
                    recover_polynomial(
                        stack,
                        &PolynomialParams {
                            degree: p.degree,
                            samples: p.samples,
                        },
                    )?
                } else {
                    recover_response_with(stack, &p.response_params(), |f| {
                        ctx.progress(0.5 * f);
                        ctx.check_cancelled()
                    })?
                }
            }
        },
    };
    ctx.check_cancelled()?;
    let merged = merge_hdr_with(stack, &curve, &merge_params)?;
    ctx.progress(1.0);
    Ok(HdrMergeOut {
        color: merged.color,
        curve: curve.to_image(),
        fallback: merged.fallback,
        confidence: merged.confidence,
    }
    .into())
}

node_params! {
    /// Parameters of `AlignBracket`.
    pub struct AlignBracketParams {
        /// Largest translation searched between neighbouring exposures, in pixels (the pyramid
        /// stops while its coarsest image has 8 pixels per side, so a 120-pixel-high image reaches
        /// 15).
        pub max_shift: usize = 32usize, ParamKind::Int { min: 1, max: 4096 };
        /// Pixels within this many 8-bit levels of an exposure's median are left out of the
        /// comparison (they flip with noise).
        pub tolerance: f64 = 4.0, ParamKind::Float { min: 0.0, max: 64.0 };
    }
}

depthgraph_graph::ports! {
    /// Inputs of `AlignBracket`.
    inputs struct AlignBracketIn {
        /// exposures with their times
        stack: Arc<ExposureStack>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `AlignBracket`.
    outputs struct AlignBracketOut {
        /// the exposures moved onto the one of median time; uncovered pixels missing (NaN)
        exposures: ExposureStack,
        /// 1 where every aligned exposure has a value
        covered: Mask,
    }
}

fn align_bracket_eval(
    ctx: &EvalCtx,
    i: AlignBracketIn,
    p: &AlignBracketParams,
) -> Result<Produced<AlignBracketOut>, NodeError> {
    ctx.check_cancelled()?;
    let a = align_bracket(
        &i.stack,
        &AlignParams {
            max_shift: p.max_shift,
            tolerance: p.tolerance,
        },
    )?;
    Ok(AlignBracketOut {
        exposures: a.stack,
        covered: a.covered,
    }
    .into())
}

node_params! {
    /// Parameters of `SaveResponse`.
    pub struct SaveResponseParams {
        /// Output `.csv` file (columns z, g_r, g_g, g_b with g = ln exposure). Relative paths go
        /// under `--out`.
        pub path: String = "response.csv", ParamKind::OutputPath;
    }
}

/// Writes a response curve as CSV: a header `z,g_r,g_g,g_b`, then one line
/// per level with `g(z) = ln(E Δt)`.
pub fn save_response(curve: &ResponseCurve, path: &Path) -> Result<PathBuf, NodeError> {
    let mut text = String::from("z,g_r,g_g,g_b\n");
    for z in 0..LEVELS {
        let _ = writeln!(
            text,
            "{z},{},{},{}",
            curve.g[0][z], curve.g[1][z], curve.g[2][z]
        );
    }
    crate::io::write_atomic(path, |tmp| std::fs::write(tmp, text.as_bytes()))
}

depthgraph_graph::ports! {
    /// Inputs of `SaveResponse`.
    inputs struct SaveResponseIn {
        /// 256x1 response curve
        curve: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SaveResponse`.
    outputs struct SaveResponseOut {
        /// the file written
        file: PathBuf,
    }
}

fn save_response_eval(
    ctx: &EvalCtx,
    i: SaveResponseIn,
    p: &SaveResponseParams,
) -> Result<Produced<SaveResponseOut>, NodeError> {
    let curve = ResponseCurve::from_image(&i.curve, "curve")?;
    let path = ctx.output_path(&p.path)?;
    Ok(SaveResponseOut {
        file: save_response(&curve, &path)?,
    }
    .into())
}

/// Registers `LoadBracket`, `HdrMerge` and `SaveResponse`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(
        PortedNode::new(
            "LoadBracket",
            1,
            "Reads an exposure bracket (images + exposure times) without linearising it.\n\
             From a list file (`filename exposure_time_s` per line, as Debevec's memorial image_list.txt) \
             or from files + times_s; optional pure-blue masking.",
            load_bracket_eval,
        )
        .reads(bracket_files),
    )?;
    reg.register(PortedNode::new(
        "AlignBracket",
        1,
        "Aligns a handheld exposure bracket (Ward 2003): median threshold bitmaps compared by XOR \
         on an image pyramid give each exposure's translation onto the one of median time.",
        align_bracket_eval,
    ))?;
    reg.register(PortedNode::new(
        "HdrMerge",
        4,
        "Merges an exposure bracket into linear radiance (Debevec & Malik 1997, eq. 5-6).\n\
         Recovers the response curve g by least squares with smoothness (or a polynomial, or uses a \
         gamma/linear or connected curve), then averages g(Z) - ln dt with hat weights times the curve's \
         resolution at each level. A recovered \
         curve gives radiance up to one factor per channel, tied so that neutral stays neutral.",
        hdr_merge_eval,
    ))?;
    reg.register(
        PortedNode::new(
            "SaveResponse",
            1,
            "Writes a response curve (HdrMerge's `curve`) as CSV: z, g_r, g_g, g_b.",
            save_response_eval,
        )
        .sink(),
    )
}

//TESTS
#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::response::inverse_response;
    use crate::sim::sensor::{BracketParams, simulate_bracket};
    use crate::sim::synthetic::{RenderOptions, Scene, render};

    /// Radiance 1e-3..1e2: a log ramp (different per channel) above the
    /// tabletop scene's color.
    fn hdr_scene() -> ColorImage {
        let (w, h) = (64, 48);
        let scene = Scene::preset("tabletop", w, 24).unwrap();
        let tab = render(&scene, &RenderOptions::default()).color;
        Image::from_fn(w, h, |x, y| {
            if y < 24 {
                let t = (x as f64 + (y % 8) as f64 / 8.0) / w as f64;
                let e = |off: f64| (10f64.powf(-3.0 + 5.0 * (t * 0.9 + off)) as f32).min(100.0);
                [e(0.1), e(0.05), e(0.0)]
            } else {
                *tab.get(x, y - 24)
            }
        })
    }

    fn bracket(gamma: f64) -> BracketParams {
        BracketParams {
            stops: vec![-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0],
            gamma,
            ..Default::default()
        }
    }

    /// Mean and 95th percentile of |E / (s E_true) - 1| over pixels whose
    /// true radiance some exposure sees well (0.05 < E t < 0.9 for some t),
    /// with one fitted factor `s` per channel (1 when `fit` is false).
    fn rel_errors(out: &ColorImage, truth: &ColorImage, times: &[f64], fit: bool) -> (f64, f64) {
        let seen = |e: f64| times.iter().any(|t| (0.05..0.9).contains(&(e * t)));
        let mut errs = Vec::new();
        for c in 0..3 {
            let pairs: Vec<(f64, f64)> = out
                .as_slice()
                .iter()
                .zip(truth.as_slice())
                .map(|(o, t)| (o[c] as f64, t[c] as f64))
                .filter(|(_, t)| *t > 0.0 && seen(*t))
                .collect();
            let s = if fit {
                let mean: f64 =
                    pairs.iter().map(|(o, t)| (o / t).ln()).sum::<f64>() / pairs.len() as f64;
                mean.exp()
            } else {
                1.0
            };
            errs.extend(pairs.iter().map(|(o, t)| (o / (s * t) - 1.0).abs()));
        }
        errs.sort_by(f64::total_cmp);
        let mean = errs.iter().sum::<f64>() / errs.len() as f64;
        (mean, errs[errs.len() * 95 / 100])
    }

    #[test]
    fn recovered_curve_matches_the_simulated_gamma_up_to_a_constant() {
        // default noise (0.2% of saturation): the darkest levels are noise, not response
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let curve = recover_response(&stack, &ResponseParams::default()).unwrap();
        let truth: Vec<f64> = (0..LEVELS)
            .map(|z| (inverse_response(z as f32 / 255.0, 2.2) as f64).ln())
            .collect();
        // below level 40 the gamma curve bends faster than the default
        // smoothness lets the recovery follow (-0.06 in ln at level 30)
        let range = 40..246;
        let mid: f64 = (0..3).map(|c| curve.g[c][Z_MID]).sum();
        assert!(mid.abs() < 1e-12, "mean g(128) over channels is 0: {mid}");
        // one offset for all three channels: they share one response, and the
        // tie must keep them together (a neutral surface stays neutral)
        let off = (0..3)
            .flat_map(|c| range.clone().map(move |z| (c, z)))
            .map(|(c, z)| curve.g[c][z] - truth[z])
            .sum::<f64>()
            / (3 * range.len()) as f64;
        for c in 0..3 {
            let worst = range
                .clone()
                .map(|z| (curve.g[c][z] - truth[z] - off).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 0.06,
                "channel {c}: max |g - g_true - offset| = {worst}"
            );
            for z in 1..LEVELS {
                assert!(
                    curve.g[c][z] >= curve.g[c][z - 1],
                    "g must not decrease at {z}"
                );
                if range.contains(&z) {
                    assert!(curve.g[c][z] > curve.g[c][z - 1], "g must increase at {z}");
                }
            }
        }
    }

    #[test]
    fn merged_radiance_is_within_a_few_percent_and_a_given_gamma_is_closer() {
        let truth = hdr_scene();
        let run = |noise_sigma: f64, curve: Option<ResponseCurve>| {
            let p = BracketParams {
                noise_sigma,
                ..bracket(2.2)
            };
            let stack = simulate_bracket(&truth, &p).unwrap();
            let fit = curve.is_none();
            let curve = curve
                .unwrap_or_else(|| recover_response(&stack, &ResponseParams::default()).unwrap());
            let m = merge_hdr(&stack, &curve).unwrap();
            rel_errors(&m.color, &truth, &stack.times_s, fit)
        };
        let gamma = || Some(ResponseCurve::gamma(2.2));
        // with noise: a few % after one fitted factor per channel; the known
        // curve is absolute (no factor fitted)
        let (mean_r, p95_r) = run(0.0005, None);
        assert!(
            mean_r < 0.02 && p95_r < 0.05,
            "recovered: mean {mean_r}, p95 {p95_r}"
        );
        let (mean_g, p95_g) = run(0.0005, gamma());
        assert!(
            mean_g < 0.02 && p95_g < 0.05,
            "given: mean {mean_g}, p95 {p95_g}"
        );
        // without noise only the curve differs: the known one is closer
        let (clean_r, clean_r95) = run(0.0, None);
        let (clean_g, clean_g95) = run(0.0, gamma());
        assert!(
            clean_g < clean_r && clean_g95 < clean_r95,
            "given {clean_g} vs recovered {clean_r}"
        );
        // a wrong curve is far worse, even after fitting the factor
        let (mean_w, _) = run(0.0005, Some(ResponseCurve::linear()));
        assert!(
            mean_w > 3.0 * mean_r,
            "linear {mean_w} vs recovered {mean_r}"
        );
    }

    #[test]
    fn sixteen_bit_values_merge_closer_than_eight_bit() {
        let truth = hdr_scene();
        let g = ResponseCurve::gamma(2.2);
        let err = |bits: u32| {
            let p = BracketParams {
                noise_sigma: 0.0,
                bits,
                ..bracket(2.2)
            };
            let stack = simulate_bracket(&truth, &p).unwrap();
            let m = merge_hdr(&stack, &g).unwrap();
            rel_errors(&m.color, &truth, &stack.times_s, false)
        };
        let (e8, e16) = (err(8), err(16));
        assert!(e16.0 < 0.5 * e8.0, "16-bit {e16:?} vs 8-bit {e8:?}");
    }

    fn eval_node(
        stack: ExposureStack,
        p: &HdrMergeParams,
        curve: Option<ColorImage>,
    ) -> Result<Outputs, NodeError> {
        let cancel = CancelToken::new();
        let ctx = EvalCtx {
            node: "merge",
            cancel: &cancel,
            progress: None,
            out_dir: Path::new("."),
            input_files: &[],
            derivations: None,
            max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
        };
        let mut inputs = Inputs::new();
        inputs.insert("stack", stack.into());
        if let Some(c) = curve {
            inputs.insert("curve", c.into());
        }
        let mut reg = Registry::new();
        register(&mut reg).expect("registers");
        let node = reg.get("HdrMerge").expect("registered");
        node.eval(&ctx, &inputs, &p.to_values())
    }

    #[test]
    fn single_exposure_passes_through_with_a_reason() {
        let stack = simulate_bracket(
            &hdr_scene(),
            &BracketParams {
                stops: vec![0.0],
                ..Default::default()
            },
        )
        .unwrap();
        let out = eval_node(stack.clone(), &HdrMergeParams::default(), None).unwrap();
        assert!(
            out.passthrough
                .as_deref()
                .unwrap_or("")
                .contains("single exposure")
        );
        assert_eq!(
            out.values["color"],
            Value::Color(Arc::new(stack.images[0].clone()))
        );
        // with a given curve one exposure is linearised, not passed through
        let p = HdrMergeParams {
            response: ResponseSource::Gamma,
            ..Default::default()
        };
        let out = eval_node(stack.clone(), &p, None).unwrap();
        assert!(out.passthrough.is_none());
        assert_ne!(
            out.values["color"],
            Value::Color(Arc::new(stack.images[0].clone()))
        );
    }

    #[test]
    fn equal_times_cannot_recover_but_merge_with_a_given_curve() {
        let mut stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        stack.images.truncate(3);
        stack.times_s = vec![0.5; 3];
        let e = recover_response(&stack, &ResponseParams::default()).unwrap_err();
        assert!(e.to_string().contains("same time"), "{e}");
        let e = eval_node(stack.clone(), &HdrMergeParams::default(), None).unwrap_err();
        assert!(e.to_string().contains("stack"), "{e}");
        // a connected curve (another merge's output) makes it work
        let curve = ResponseCurve::gamma(2.2).to_image();
        let out = eval_node(stack, &HdrMergeParams::default(), Some(curve)).unwrap();
        let Value::Color(c) = &out.values["color"] else {
            panic!("color output")
        };
        assert!(
            c.as_slice()
                .iter()
                .flatten()
                .all(|v| v.is_finite() && *v >= 0.0)
        );
    }

    #[test]
    fn all_saturated_and_all_black_stacks_give_finite_documented_values() {
        let times = vec![0.25, 1.0, 4.0];
        let g = ResponseCurve::gamma(2.2);
        for (v, want) in [
            (1.0f32, 1.0 / 0.25),           // g(255) = 0, shortest time
            (0.0, (g.g[0][0].exp()) / 4.0), // g(0), longest time
            // a float file's clipped values, a hair inside the range: the
            // same (they were neither used nor counted as clipped: E = 0)
            (1.0 - f32::EPSILON / 2.0, 1.0 / 0.25),
            (1e-7, (g.g[0][0].exp()) / 4.0),
        ] {
            let stack = ExposureStack {
                images: vec![Image::filled(5, 4, [v; 3]); 3],
                times_s: times.clone(),
            };
            let m = merge_hdr(&stack, &g).unwrap();
            for px in m.color.as_slice() {
                for e in px {
                    assert!(e.is_finite());
                    assert!((*e as f64 / want - 1.0).abs() < 1e-5, "{e} vs {want}");
                }
            }
            assert!(m.fallback.as_slice().iter().all(|f| *f == 1.0));
            let e = recover_response(&stack, &ResponseParams::default()).unwrap_err();
            assert!(e.to_string().contains("well exposed"), "{e}");
        }
        // the black estimate lies below the first level's, the saturated one above the last
        assert!(g.g[0][0] < g.g[0][1]);
    }

    #[test]
    fn nan_values_are_ignored() {
        let truth = hdr_scene();
        let stack = simulate_bracket(&truth, &bracket(2.2)).unwrap();
        let (w, h) = stack.images[0].dims();
        let mut holes = stack.clone();
        // exposure 3 misses a block; pixel (0, 0) is missing everywhere
        for y in 10..20 {
            for x in 5..30 {
                *holes.images[3].get_mut(x, y) = [f32::NAN; 3];
            }
        }
        for img in &mut holes.images {
            *img.get_mut(0, 0) = [f32::NAN, 0.5, f32::INFINITY];
        }
        let g = ResponseCurve::gamma(2.2);
        let merged = merge_hdr(&holes, &g).unwrap();
        let without3 = ExposureStack {
            images: [&stack.images[..3], &stack.images[4..]].concat(),
            times_s: [&stack.times_s[..3], &stack.times_s[4..]].concat(),
        };
        let ref3 = merge_hdr(&without3, &g).unwrap();
        let full = merge_hdr(&stack, &g).unwrap();
        for y in 0..h {
            for x in 0..w {
                let got = merged.color.get(x, y);
                assert!(got.iter().all(|v| v.is_finite()));
                if (x, y) == (0, 0) {
                    continue;
                }
                let want = if (10..20).contains(&y) && (5..30).contains(&x) {
                    ref3.color.get(x, y)
                } else {
                    full.color.get(x, y)
                };
                assert_eq!(got, want, "({x}, {y})");
            }
        }
        let px = merged.color.get(0, 0);
        assert_eq!((px[0], px[2]), (0.0, 0.0), "missing everywhere is 0");
        assert!(px[1] > 0.0);
        assert_eq!(*merged.fallback.get(0, 0), 1.0);
        // recovery also ignores them and still works
        assert!(recover_response(&holes, &ResponseParams::default()).is_ok());
    }

    #[test]
    fn bad_stacks_are_named_errors() {
        let img = Image::filled(3, 2, [0.5f32; 3]);
        let cases = [
            (ExposureStack::default(), "no exposure"),
            (
                ExposureStack {
                    images: vec![img.clone(), img.clone()],
                    times_s: vec![1.0],
                },
                "2 images but 1",
            ),
            (
                ExposureStack {
                    images: vec![img.clone(), Image::filled(2, 2, [0.5; 3])],
                    times_s: vec![1.0, 2.0],
                },
                "image 1 is 2x2",
            ),
            (
                ExposureStack {
                    images: vec![img.clone(), img.clone()],
                    times_s: vec![1.0, 0.0],
                },
                "positive",
            ),
        ];
        for (stack, want) in cases {
            let e = merge_hdr(&stack, &ResponseCurve::linear()).unwrap_err();
            assert!(
                e.to_string().contains(want) && e.to_string().contains("stack"),
                "{e}"
            );
        }
        let e = ResponseCurve::from_image(&img, "curve").unwrap_err();
        assert!(e.to_string().contains("256x1"), "{e}");
        let mut bad = ResponseCurve::linear().to_image();
        bad.get_mut(3, 0)[1] = -1.0;
        assert!(ResponseCurve::from_image(&bad, "curve").is_err());
        // a curve saved as a 16-bit PNG: every value above 1 clipped (a
        // recovered curve, g(128) = 0, is above 1 over its top half)
        let g = recover_response(
            &simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap(),
            &ResponseParams::default(),
        )
        .unwrap();
        assert!(ResponseCurve::from_image(&g.to_image(), "curve").is_ok());
        let mut clipped = g.to_image();
        for px in clipped.as_mut_slice() {
            *px = px.map(|v| (v.min(1.0) * 65535.0).round() / 65535.0);
        }
        let e = ResponseCurve::from_image(&clipped, "curve").unwrap_err();
        assert!(
            e.to_string().contains("clips values above 1") && e.to_string().contains("EXR"),
            "{e}"
        );
    }

    #[test]
    fn curve_image_round_trips_and_csv_has_256_rows() {
        let g = ResponseCurve::gamma(2.2);
        let back = ResponseCurve::from_image(&g.to_image(), "curve").unwrap();
        for c in 0..3 {
            for z in 0..LEVELS {
                assert!((back.g[c][z] - g.g[c][z]).abs() < 1e-6);
            }
        }
        assert_eq!(g.g[0][255], 0.0);
        assert!((g.eval(1, 127.5) - 0.5 * (g.g[1][127] + g.g[1][128])).abs() < 1e-12);
        let dir = tempfile::tempdir().unwrap();
        let path = save_response(&g, &dir.path().join("r.csv")).unwrap();
        let text = std::fs::read_to_string(path).unwrap();
        assert_eq!(text.lines().count(), 257);
        assert!(text.starts_with("z,g_r,g_g,g_b\n0,"));
    }

    #[test]
    fn thread_count_does_not_change_bits() {
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let run = |n| {
            crate::test_support::with_threads(n, || {
                let g = recover_response(&stack, &ResponseParams::default()).unwrap();
                merge_hdr(&stack, &g).unwrap()
            })
        };
        assert_eq!(run(1), run(3));
    }

    fn write_png(path: &Path, w: u32, h: u32, px: impl Fn(u32, u32) -> [u8; 3]) {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb(px(x, y)))
            .save(path)
            .unwrap();
    }

    #[test]
    fn load_bracket_reads_a_list_without_linearising_and_masks_blue() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("set");
        std::fs::create_dir(&sub).unwrap();
        for (i, v) in [40u8, 128, 230].iter().enumerate() {
            write_png(&sub.join(format!("e{i}.png")), 4, 3, |x, _| {
                if x == 3 { [0, 0, 255] } else { [*v, *v, *v] }
            });
        }
        let list = sub.join("list.txt");
        std::fs::write(
            &list,
            "# Filename exposure 1/shutter\ne0.png 0.25 4 8\n\n  e1.png   1  1 # mid\ne2.png 4\n",
        )
        .unwrap();
        let p = LoadBracketParams {
            list: list.display().to_string(),
            mask_pure_blue: true,
            ..Default::default()
        };
        let s = load_bracket(&p).unwrap();
        assert_eq!(s.times_s, vec![0.25, 1.0, 4.0]);
        assert_eq!(s.images[1].get(0, 0)[0], 128.0 / 255.0, "not linearised");
        assert!(s.images[2].get(3, 1).iter().all(|v| v.is_nan()));
        let files = bracket_files(&p);
        assert_eq!(files.len(), 4, "the list and its three images: {files:?}");
        let unmasked = load_bracket(&LoadBracketParams {
            mask_pure_blue: false,
            ..p.clone()
        })
        .unwrap();
        assert_eq!(*unmasked.images[0].get(3, 0), [0.0, 0.0, 1.0]);

        // files + times
        let names: Vec<String> = (0..3)
            .map(|i| sub.join(format!("e{i}.png")).display().to_string())
            .collect();
        let q = LoadBracketParams {
            files: names.join(", "),
            times_s: vec![1.0, 2.0, 4.0],
            ..Default::default()
        };
        assert_eq!(load_bracket(&q).unwrap().images.len(), 3);

        // errors name the file or parameter and what was expected
        let e = load_bracket(&LoadBracketParams {
            times_s: vec![1.0, 2.0],
            ..q.clone()
        })
        .unwrap_err();
        assert!(
            e.to_string().contains("times_s") && e.to_string().contains("2 times for the 3 files"),
            "{e}"
        );
        let e = load_bracket(&LoadBracketParams {
            times_s: vec![1.0, 0.0, 4.0],
            ..q.clone()
        })
        .unwrap_err();
        assert!(
            e.to_string().contains("e1.png") && e.to_string().contains("positive"),
            "{e}"
        );
        write_png(&sub.join("small.png"), 2, 2, |_, _| [1, 2, 3]);
        std::fs::write(&list, "e0.png 1\nsmall.png 2\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(
            e.to_string().contains("small.png") && e.to_string().contains("same size"),
            "{e}"
        );
        std::fs::write(&list, "e0.png 1\nmissing.png 2\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(e.to_string().contains("missing.png"), "{e}");
        std::fs::write(&list, "e0.png 1\ne1.png fast\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(
            e.to_string().contains("line 2") && e.to_string().contains("list.txt"),
            "{e}"
        );
        // the columns after the time: equal apertures, gains and filters
        // read (the memorial list's form: 1/shutter f/stop gain ND, or
        // without 1/shutter); a differing one is refused, naming it
        let dir_of = |list: &str| parse_bracket_list(list, Path::new("l/list.txt"));
        let same = "# name exposure 1/shutter f/stop gain ND\na.png 2 0.5 8 0 0\nb.png 1 1 8 0 0\n";
        assert_eq!(dir_of(same).unwrap().len(), 2);
        for (list, what) in [
            ("a.png 2 0.5 8 0 0\nb.png 1 1 4 0 0\n", "f-stop is 4"),
            ("a.png 2 0.5 8 0 0\nb.png 1 1 8 6 0\n", "gain is 6"),
            ("a.png 2 0.5 8 0 0\nb.png 1 1 8 0 1\n", "ND filter is 1"),
            ("a.png 2 8 0 0\nb.png 1 4 0 0\n", "f-stop is 4"),
            ("a.png 2 8 0 0\nb.png 1 8 6 0\n", "gain is 6"),
        ] {
            let e = dir_of(list).unwrap_err().to_string();
            assert!(e.contains(what) && e.contains("line 2"), "{e}");
        }
        // times inverted (1/shutter read as seconds): the longest exposure
        // is the darkest, refused naming the list
        std::fs::write(&list, "e0.png 4\ne1.png 1\ne2.png 0.25\n").unwrap();
        let e = load_bracket(&p).unwrap_err().to_string();
        assert!(e.contains("list") && e.contains("opposite"), "{e}");
        std::fs::write(&list, "e0.png 0.25\ne1.png 1\ne2.png 4\n").unwrap();
        assert!(load_bracket(&p).is_ok());
        std::fs::write(&list, "e0.png -1\n").unwrap();
        assert!(
            load_bracket(&p)
                .unwrap_err()
                .to_string()
                .contains("positive")
        );
        std::fs::write(&list, "# nothing\n").unwrap();
        assert!(
            load_bracket(&p)
                .unwrap_err()
                .to_string()
                .contains("no exposure")
        );
        let e = load_bracket(&LoadBracketParams::default()).unwrap_err();
        assert!(e.to_string().contains("list"), "{e}");
        let e = load_bracket(&LoadBracketParams {
            files: "a.png".into(),
            ..p.clone()
        })
        .unwrap_err();
        assert!(e.to_string().contains("not both"), "{e}");
    }

    #[test]
    fn nodes_produce_their_declared_types() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let out = eval_node(stack, &HdrMergeParams::default(), None).unwrap();
        let node = reg.get("HdrMerge").unwrap();
        for port in &node.schema().outputs {
            assert_eq!(out.values[port.name].value_type(), port.ty, "{}", port.name);
        }
        assert_eq!(out.values["curve"].image_dims(), Some((256, 1)));
    }
}
