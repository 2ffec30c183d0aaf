//! `Feather`: Gaussian softening of an object mask's boundary (3d-editing
//! §III.C, last paragraph: "Since the boundary of the source object usually
//! is not continuous with the target image, Gaussian filtering to the source
//! object mask is applied. In the composition process, the source object
//! mask is used as blending weights").
//!
//! The mask is blurred with a separable Gaussian of standard deviation
//! `sigma_px`, truncated at `r = ceil(3 sigma)` and normalised to sum 1
//! (weights in `f64`). Borders are replicated, so an object cut by the image
//! frame stays opaque along the frame instead of fading into it.
//!
//! Only pixels **near the boundary** change: a pixel whose `(2r+1)^2` window
//! holds no boundary pixel (a pixel with a 4-neighbour of another value) lies
//! in a uniform region and keeps its value exactly, so the interior stays
//! exactly 1 and the far exterior exactly 0 (a truncated, rounded kernel
//! would otherwise leave values like 0.99999994).
//!
//! Two modes:
//! - `"inside"` (default): `alpha' = min(alpha, blur(alpha))`: the feather
//!   fades inwards and nothing outside the selection becomes visible. This is
//!   what compositing a pasted layer needs: outside the pasted object there
//!   is no pasted color or depth to blend in.
//! - `"centered"`: `alpha' = blur(alpha)`, the plain Gaussian filtering of
//!   the paper; the feather straddles the boundary.
//!
//! Inputs outside `[0, 1]` are clamped and NaN is 0; the output is in `[0, 1]`.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

depthgraph_graph::param_choice! {
    /// How the mask is feathered (the `mode` parameter).
    pub enum FeatherMode {
        /// Fade inwards only (min of mask and blur): nothing leaks outside.
        Inside = "inside",
        /// Plain blur across the boundary.
        Centered = "centered",
    }
}

node_params! {
    /// Parameters of `Feather`.
    pub struct FeatherParams {
        /// Standard deviation of the Gaussian in pixels; 0 passes the mask through.
        pub sigma_px: f64 = 2.0, ParamKind::Float { min: 0.0, max: 100.0 };
        /// "inside": fade inwards only (min of mask and blur); "centered": plain blur.
        pub mode: FeatherMode = FeatherMode::Inside, ParamKind::Choice(FeatherMode::NAMES);
    }
}

#[inline]
fn clean(v: f32) -> f32 {
    if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) }
}

/// Whether each pixel has a boundary pixel within `r` (Chebyshev distance):
/// sliding-window counts of the boundary indicator along rows, then columns
/// (exact integer sums, O(1) per pixel whatever `r`). Requires `w, h >= 1`.
fn near_boundary(m: &[f32], w: usize, h: usize, r: usize) -> (Vec<bool>, bool) {
    let boundary: Vec<u32> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let v = m[i];
            let differs = (x > 0 && m[i - 1] != v)
                || (x + 1 < w && m[i + 1] != v)
                || (y > 0 && m[i - w] != v)
                || (y + 1 < h && m[i + w] != v);
            u32::from(differs)
        })
        .collect();
    let any = boundary.par_iter().any(|b| *b > 0);
    // Row pass: sliding sum over [x - r, x + r].
    let mut rows = vec![0u32; w * h];
    rows.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let b = &boundary[y * w..(y + 1) * w];
        let mut acc: u32 = b[..=r.min(w - 1)].iter().sum();
        for x in 0..w {
            out[x] = acc;
            if x + r + 1 < w {
                acc += b[x + r + 1];
            }
            if x >= r {
                acc -= b[x - r];
            }
        }
    });
    // Column pass: sliding sums of whole rows over [y - r, y + r].
    let mut near = vec![false; w * h];
    let mut acc = vec![0u32; w];
    for row in rows.chunks(w).take(r.min(h - 1) + 1) {
        for (a, v) in acc.iter_mut().zip(row) {
            *a += v;
        }
    }
    for y in 0..h {
        for (n, a) in near[y * w..(y + 1) * w].iter_mut().zip(&acc) {
            *n = *a > 0;
        }
        if y + r + 1 < h {
            for (a, v) in acc.iter_mut().zip(&rows[(y + r + 1) * w..(y + r + 2) * w]) {
                *a += v;
            }
        }
        if y >= r {
            for (a, v) in acc.iter_mut().zip(&rows[(y - r) * w..(y - r + 1) * w]) {
                *a -= v;
            }
        }
    }
    (near, any)
}

/// What [`feather`] decides before blurring (both backends use it): the
/// cleaned mask and, when something is to blur, the normalised kernel and
/// the pixels near a boundary (the only ones that change).
#[derive(Debug, Clone)]
pub enum FeatherPlan {
    /// Nothing to blur (`sigma_px = 0`, an empty mask, or no boundary): the
    /// cleaned mask is the result.
    Unchanged(Mask),
    /// A blur to compute.
    Blur {
        /// The mask clamped to [0, 1], NaN as 0.
        mask: Mask,
        /// Gaussian taps `-r..=r`, summing to 1.
        kernel: Vec<f64>,
        /// Pixels within `r` of a boundary.
        near: Vec<bool>,
        /// Fade inwards only (`inside`) or blur both ways.
        inside: bool,
    },
}

/// The decisions of [`feather`] (see [`FeatherPlan`]).
pub fn plan(mask: &Mask, p: &FeatherParams) -> Result<FeatherPlan, NodeError> {
    let inside = p.mode == FeatherMode::Inside;
    if !(p.sigma_px.is_finite() && p.sigma_px >= 0.0 && p.sigma_px <= 1e4) {
        return Err(NodeError::param(
            "sigma_px",
            format!("{} must be finite and in [0, 10000]", p.sigma_px),
        ));
    }
    let (w, h) = mask.dims();
    let m: Vec<f32> = mask.as_slice().par_iter().map(|v| clean(*v)).collect();
    if p.sigma_px == 0.0 || w == 0 || h == 0 {
        return Ok(FeatherPlan::Unchanged(Image::from_vec(w, h, m)?));
    }
    let r = (3.0 * p.sigma_px).ceil() as usize;
    let (near, any) = near_boundary(&m, w, h, r);
    if !any {
        return Ok(FeatherPlan::Unchanged(Image::from_vec(w, h, m)?));
    }
    // (under about 1e-162 px, 2 sigma^2 underflows to 0: the side taps are
    // exp(-inf) = 0 and the centre, set to 1 rather than exp(-0 / 0) = NaN,
    // leaves the mask as it is)
    let two_s2 = 2.0 * p.sigma_px * p.sigma_px;
    let raw: Vec<f64> = (0..=2 * r)
        .map(|i| {
            let d = i as f64 - r as f64;
            if i == r { 1.0 } else { (-d * d / two_s2).exp() }
        })
        .collect();
    // Guard: the centre tap is exp(0) = 1, so total >= 1.
    let total: f64 = raw.iter().sum();
    let kernel: Vec<f64> = raw.iter().map(|v| v / total).collect();
    Ok(FeatherPlan::Blur {
        mask: Image::from_vec(w, h, m)?,
        kernel,
        near,
        inside,
    })
}

/// Why `Feather` passed its input through, or `None` when it blurred.
pub fn unchanged_reason(p: &FeatherParams) -> &'static str {
    if p.sigma_px == 0.0 {
        "sigma_px is 0"
    } else {
        "the mask has no boundary to feather"
    }
}

/// Feathers `mask` (3d-editing §III.C); see the module docs. Returns the
/// feathered mask and whether anything changed (`false`: `sigma_px` is 0 or
/// the mask has no boundary).
///
/// ```
/// use depthgraph_graph::value::Image;
/// use depthgraph_nodes::select::feather::{feather, FeatherParams};
/// let m = Image::from_fn(40, 1, |x, _| if x < 20 { 1.0f32 } else { 0.0 });
/// let (f, changed) = feather(&m, &FeatherParams::default()).unwrap();
/// assert!(changed);
/// assert_eq!(*f.get(5, 0), 1.0); // interior, farther than 3 sigma: exactly 1
/// assert!(*f.get(19, 0) > 0.4 && *f.get(19, 0) < 1.0); // the boundary fades
/// assert_eq!(*f.get(20, 0), 0.0); // "inside" mode: nothing outside
/// ```
pub fn feather(mask: &Mask, p: &FeatherParams) -> Result<(Mask, bool), NodeError> {
    let (m, kernel, near, inside) = match plan(mask, p)? {
        FeatherPlan::Unchanged(m) => return Ok((m, false)),
        FeatherPlan::Blur {
            mask,
            kernel,
            near,
            inside,
        } => (mask, kernel, near, inside),
    };
    let (w, h) = m.dims();
    let r = kernel.len() / 2;
    let m = m.as_slice();
    let clampi = |v: isize, n: usize| v.clamp(0, n as isize - 1) as usize;
    // Horizontal pass (all pixels: the vertical pass reads whole columns).
    let mut horiz = vec![0.0f32; w * h];
    horiz.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let row = &m[y * w..(y + 1) * w];
        for (x, o) in out.iter_mut().enumerate() {
            let mut acc = 0.0f64;
            for (k, wt) in kernel.iter().enumerate() {
                let xx = clampi(x as isize + k as isize - r as isize, w);
                acc += wt * row[xx] as f64;
            }
            *o = acc as f32;
        }
    });
    // Vertical pass only where the window holds a boundary.
    let mut out = m.to_vec();
    out.par_chunks_mut(w).enumerate().for_each(|(y, orow)| {
        for (x, o) in orow.iter_mut().enumerate() {
            let i = y * w + x;
            if !near[i] {
                continue;
            }
            let mut acc = 0.0f64;
            for (k, wt) in kernel.iter().enumerate() {
                let yy = clampi(y as isize + k as isize - r as isize, h);
                acc += wt * horiz[yy * w + x] as f64;
            }
            let b = (acc as f32).clamp(0.0, 1.0);
            *o = if inside { b.min(m[i]) } else { b };
        }
    });
    Ok((Image::from_vec(w, h, out)?, true))
}

depthgraph_graph::ports! {
    /// Inputs of `Feather`.
    inputs struct FeatherIn {
        /// alpha in [0, 1]
        mask: Arc<Mask>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Feather`.
    outputs struct FeatherOut {
        /// feathered alpha in [0, 1]
        mask: Mask,
    }
}

fn eval(_: &EvalCtx, i: FeatherIn, p: &FeatherParams) -> Result<Produced<FeatherOut>, NodeError> {
    let (mask, changed) = feather(&i.mask, p)?;
    let out = FeatherOut { mask };
    if !changed {
        return Ok(Produced::passthrough(out, unchanged_reason(p)));
    }
    Ok(out.into())
}

/// Registers `Feather`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Feather",
        1,
        "Gaussian feathering of a mask's boundary (3d-editing §III.C); interior stays exactly 1, far exterior 0.\n\
         \"inside\" fades inwards only (nothing outside the object shows), \"centered\" is the plain blur.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disc(w: usize, h: usize, cx: f64, cy: f64, r: f64) -> Mask {
        Image::from_fn(w, h, |x, y| {
            let d = ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2)).sqrt();
            if d <= r { 1.0f32 } else { 0.0 }
        })
    }

    #[test]
    fn interior_stays_one_far_exterior_zero_and_only_the_band_changes() {
        let m = disc(60, 50, 30.0, 25.0, 15.0);
        let sigma = 2.0;
        // the kernel's support is a square of radius r = 6: up to r sqrt 2 away
        // along a diagonal, plus a pixel of slack for the discrete circle
        let band = 6.0 * std::f64::consts::SQRT_2 + 1.0;
        for mode in [FeatherMode::Inside, FeatherMode::Centered] {
            let p = FeatherParams {
                sigma_px: sigma,
                mode,
            };
            let (f, changed) = feather(&m, &p).unwrap();
            assert!(changed);
            for y in 0..50 {
                for x in 0..60 {
                    let d =
                        ((x as f64 + 0.5 - 30.0).powi(2) + (y as f64 + 0.5 - 25.0).powi(2)).sqrt();
                    let v = *f.get(x, y);
                    assert!((0.0..=1.0).contains(&v));
                    if d < 15.0 - band {
                        assert_eq!(v, 1.0, "{mode} interior ({x},{y})");
                    }
                    if d > 15.0 + band {
                        assert_eq!(v, 0.0, "{mode} exterior ({x},{y})");
                    }
                    if mode == FeatherMode::Inside && *m.get(x, y) == 0.0 {
                        assert_eq!(v, 0.0, "inside mode leaks at ({x},{y})");
                    }
                }
            }
            // the boundary is soft
            let edge = *f.get(44, 25);
            assert!(edge > 0.2 && edge < 0.8, "{mode}: {edge}");
        }
        // centered: the fade straddles the boundary
        let (c, _) = feather(
            &m,
            &FeatherParams {
                sigma_px: sigma,
                mode: FeatherMode::Centered,
            },
        )
        .unwrap();
        assert!(*c.get(46, 25) > 0.0 && *c.get(46, 25) < 0.5);
    }

    #[test]
    fn a_mask_cut_by_the_frame_stays_opaque_along_it() {
        // the left 20 columns: only the boundary at x = 19/20 should fade
        let m = Image::from_fn(40, 30, |x, _| if x < 20 { 1.0f32 } else { 0.0 });
        let (f, _) = feather(&m, &FeatherParams::default()).unwrap();
        for y in 0..30 {
            for x in 0..12 {
                assert_eq!(*f.get(x, y), 1.0, "({x},{y})");
            }
            // a straight boundary is the same in every row, borders included
            assert_eq!(*f.get(18, y), *f.get(18, 15));
        }
    }

    #[test]
    fn hard_inputs_and_no_ops() {
        let m = Image::from_fn(9, 9, |x, y| match (x + 2 * y) % 4 {
            0 => f32::NAN,
            1 => 3.0,
            2 => -2.0,
            _ => 0.5,
        });
        for mode in [FeatherMode::Inside, FeatherMode::Centered] {
            let (f, _) = feather(
                &m,
                &FeatherParams {
                    sigma_px: 1.3,
                    mode,
                },
            )
            .unwrap();
            assert!(f.as_slice().iter().all(|v| (0.0..=1.0).contains(v)));
        }
        // sigma 0 and uniform masks pass through (clamped)
        let (f, changed) = feather(
            &m,
            &FeatherParams {
                sigma_px: 0.0,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(!changed);
        assert_eq!(*f.get(1, 0), 1.0);
        let (f, changed) =
            feather(&Image::filled(5, 4, 1.0f32), &FeatherParams::default()).unwrap();
        assert!(!changed && f.as_slice().iter().all(|v| *v == 1.0));
        // a sigma whose square underflows: the mask as it was, not NaN
        let tiny = disc(16, 12, 8.0, 6.0, 4.0);
        for mode in [FeatherMode::Centered, FeatherMode::Inside] {
            let (f, _) = feather(
                &tiny,
                &FeatherParams {
                    sigma_px: 1e-200,
                    mode,
                },
            )
            .unwrap();
            assert_eq!(f.as_slice(), tiny.as_slice(), "{mode:?}");
        }
        // huge sigma on a tiny mask
        let (f, _) = feather(
            &disc(6, 5, 3.0, 2.5, 1.5),
            &FeatherParams {
                sigma_px: 100.0,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(
            f.as_slice()
                .iter()
                .all(|v| v.is_finite() && (0.0..=1.0).contains(v))
        );
        // a name that is no mode is refused with the parameter's name
        let mut bad = FeatherParams::default().to_values();
        bad.insert("mode".into(), ParamValue::Text("outside".into()));
        let e = FeatherParams::from_values(&bad).unwrap_err();
        assert!(e.contains("mode"), "{e}");
    }
}
