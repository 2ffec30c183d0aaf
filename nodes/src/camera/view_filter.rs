//! The gaps spherical aberration opens between `Refocus`'s views, and the
//! filter that closes them.
//!
//! # The views' spacing
//!
//! Refocus averages `n` views, one per aperture point `s` (aperture
//! diameters, stratified over the aperture's area `A`). A pixel at inverse
//! depth `v` moves by `C s (a + S t)` in view `s` (the per-ray focus of
//! [`crate::camera::lens::LensEffects`]), `a = 1/u - v`, `t = r² = 4|s|²`,
//! `S` the spherical aberration in dioptres. Its point spread function is
//! therefore the `n` points `s` carried through the map
//! `s -> C s (a + S t)`, whose area scale (the Jacobian's determinant of a
//! radial map `s g(|s|)`, `g (g + |s| g')`) is
//!
//! `J(t) = C² |(a + S t)(a + 3 S t)|`.
//!
//! Neighbouring views land `sqrt(J A / n)` pixels apart there. For the
//! thin lens (`S = 0`) that is `C |a| sqrt(A / n)` everywhere on the
//! aperture, the spacing the sample count is chosen for (`samples = 0`
//! picks `n` so that it stays under `2 / quality` pixels at the largest
//! circle of confusion). Spherical aberration stretches the map unevenly:
//! on one side of the focus the rim's views spread up to `(a + S)(a + 3S)
//! / a²` times the area, and a bright point's bokeh falls apart into the
//! views' separate dots (36.1 dB against the ray-traced lens at 256
//! samples, +0.8 D; 38.5 at 1024, 39.0 at 2048, where two renders of the
//! truth itself agree to 39.0 dB: docs/refocus.md).
//!
//! # The filter
//!
//! Each pixel of the averaged views is smoothed by a Gaussian of standard
//! deviation
//!
//! `σ = k sqrt(A / n) C sqrt(max(0, ⟨J⟩ / C² - a²))`,
//!
//! `k` = `view_filter`, `⟨J⟩` the mean of `J` over the views' own points
//! (whatever the aperture's shape), `A` the aperture's area
//! ([`crate::camera::lens::Aperture::area`]), `a` from the pixel's own
//! depth: the spacing the aberration adds to the thin lens's, in the
//! root-mean-square sense. The thin lens gets `σ = 0` at every pixel and
//! the image is returned bit for bit (nothing the sample count already
//! budgets is touched).
//!
//! Where both factors of `J` keep one sign over the aperture (`a S >= 0`,
//! or `|a| >= 3 |S| t_max`), `⟨J⟩/C² - a² = 4 a S ⟨t⟩ + 3 S² ⟨t²⟩`
//! exactly, from two moments of the points; only in the band between (the
//! caustic's side of the focus, `3 |S| t_max` dioptres wide whatever the
//! depths) is the mean of the absolute value tabulated, [`TABLE`]
//! entries, linear between them. A far outlier in the depth map neither
//! widens the table nor gets a filter of its own.
//!
//! The Gaussian is separable, rows then columns, each output pixel with
//! its own `σ`, cut at `2σ` (and at the image's size) and renormalised
//! over the pixels inside the image: no darkening at the border, where, as
//! any renormalised gather, it does not keep the total exactly. Pixels
//! with `σ <` [`MIN_SIGMA_PX`] keep their value. The blurred regions it smooths are
//! already blurred by at least `C |a|` (and `C S` at the focus), many times
//! `σ`, so it removes the dots and little else: on the tabletop at 256
//! samples, `k = 0.5` gives 36.1 -> 38.5 dB at +0.8 D, 39.7 -> 39.9 at
//! -0.8 D, 39.2 -> 40.7 at +0.4 D, 39.3 at -0.4 D either way.

use rayon::prelude::*;

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;

/// A pixel whose filter is narrower than this (pixels) keeps its value.
pub const MIN_SIGMA_PX: f64 = 0.3;

/// Entries of the table of `⟨J⟩` over the caustic's band of `a` (module
/// docs).
pub const TABLE: usize = 1024;

/// What the filter needs to know of the views (module docs).
#[derive(Debug, Clone, Copy)]
pub struct Spacing<'a> {
    /// The views' aperture points, aperture diameters.
    pub points: &'a [[f64; 2]],
    /// `C` of `coc = C |1/z - 1/u|`, pixel metres.
    pub c_scale: f64,
    /// `1/u`.
    pub inv_u: f64,
    /// The aperture's area, square aperture diameters
    /// ([`crate::camera::lens::Aperture::area`]).
    pub area: f64,
    /// `S`, dioptres.
    pub spherical_d: f64,
    /// `k`, times the added spacing; 0 = off.
    pub k: f64,
}

/// `⟨|(a + S t)(a + 3 S t)|⟩ - a²` over the points' `t = 4|s|²`.
fn added(a: f64, s: f64, ts: &[f64]) -> f64 {
    // guard: ts is not empty (callers check)
    ts.iter()
        .map(|t| ((a + s * t) * (a + 3.0 * s * t)).abs())
        .sum::<f64>()
        / ts.len() as f64
        - a * a
}

/// The filter's `σ` (pixels) at every pixel of inverse depths `inv_z`
/// (module docs); empty (no allocation, no pass over the pixels) when the
/// filter or the aberration is off: the thin lens's path.
pub fn sigmas(sp: &Spacing, inv_z: &[f64]) -> Vec<f64> {
    let n = sp.points.len();
    let s = sp.spherical_d;
    let on = sp.k > 0.0 && s != 0.0 && n > 0;
    let scale = sp.k * (sp.area / n.max(1) as f64).sqrt() * sp.c_scale;
    if !on || !scale.is_finite() || !s.is_finite() {
        return Vec::new();
    }
    let ts: Vec<f64> = sp
        .points
        .iter()
        .map(|p| 4.0 * (p[0] * p[0] + p[1] * p[1]))
        .collect();
    // guard: n >= 1 (on)
    let m1 = ts.iter().sum::<f64>() / n as f64;
    let m2 = ts.iter().map(|t| t * t).sum::<f64>() / n as f64;
    let t_max = ts.iter().copied().fold(0.0f64, f64::max);
    // the band where a and a + 3 S t change sign: a between 0 and
    // -3 S t_max; the table spans it, TABLE entries, ends included
    let (b0, b1) = if s > 0.0 {
        (-3.0 * s * t_max, 0.0)
    } else {
        (0.0, -3.0 * s * t_max)
    };
    // guard: TABLE - 1 > 0
    let step = (b1 - b0) / (TABLE - 1) as f64;
    let table: Vec<f64> = (0..TABLE)
        .into_par_iter()
        .map(|i| added(b0 + step * i as f64, s, &ts))
        .collect();
    inv_z
        .par_iter()
        .map(|v| {
            let a = sp.inv_u - v;
            if !a.is_finite() {
                return 0.0;
            }
            let f = if a > b0 && a < b1 && step > 0.0 {
                // guard: step > 0
                let x = (a - b0) / step;
                let i = (x.floor() as usize).min(TABLE - 2);
                let w = x - i as f64;
                table[i] * (1.0 - w) + table[i + 1] * w
            } else {
                // both factors keep a's sign: the mean of the product
                4.0 * a * s * m1 + 3.0 * s * s * m2
            };
            let sigma = scale * f.max(0.0).sqrt();
            if sigma.is_finite() { sigma } else { 0.0 }
        })
        .collect()
}

/// One pass of the separable Gaussian: along rows (`along_x`) or columns,
/// each pixel with its own `sigma` (module docs); `w, h >= 1` (the
/// caller's check).
fn pass(src: &[Rgb], w: usize, h: usize, sigma: &[f64], along_x: bool) -> Vec<Rgb> {
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let sg = sigma[i];
            if sg.is_nan() || sg < MIN_SIGMA_PX {
                return src[i];
            }
            let (x, y) = (i % w, i / w);
            let (pos, len) = if along_x { (x, w) } else { (y, h) };
            // at most the row's or column's length (an inf sigma too)
            let r = (2.0 * sg).ceil().min((len - 1) as f64) as usize;
            // guard: sg >= MIN_SIGMA_PX > 0
            let inv = 0.5 / (sg * sg);
            let at = |q: usize| {
                if along_x {
                    src[y * w + q]
                } else {
                    src[q * w + x]
                }
            };
            let (mut acc, mut wsum) = (at(pos).map(f64::from), 1.0f64);
            // exp(-d² inv) by its ratios: w_d = w_{d-1} g^(2d-1), g = exp(-inv)
            let g = (-inv).exp();
            let (mut wt, mut ratio) = (1.0f64, g);
            for d in 1..=r {
                wt *= ratio;
                ratio *= g * g;
                for q in [pos.checked_sub(d), Some(pos + d).filter(|q| *q < len)]
                    .into_iter()
                    .flatten()
                {
                    for (c, v) in acc.iter_mut().zip(at(q)) {
                        *c += wt * f64::from(v);
                    }
                    wsum += wt;
                }
            }
            // guard: wsum >= 1 (the centre's own weight)
            acc.map(|v| (v / wsum) as f32)
        })
        .collect()
}

/// The averaged views with the gaps between them closed (module docs),
/// `sigma` per pixel from [`sigmas`]. The image itself, bit for bit, when
/// no pixel's `σ` reaches [`MIN_SIGMA_PX`] or `sigma` does not fit the
/// image (empty: the thin lens, `k = 0`).
pub fn close_gaps(image: ColorImage, sigma: &[f64]) -> ColorImage {
    let (w, h) = image.dims();
    if sigma.len() != w * h || w == 0 || h == 0 || sigma.iter().all(|s| *s < MIN_SIGMA_PX) {
        return image;
    }
    let rows = pass(image.as_slice(), w, h, sigma, true);
    let cols = pass(&rows, w, h, sigma, false);
    Image::from_vec(w, h, cols).unwrap_or(image)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disc_points(n: usize) -> Vec<[f64; 2]> {
        // a polar grid over the disc of diameter 1
        let k = (n as f64).sqrt() as usize;
        let mut out = Vec::new();
        for i in 0..k {
            for j in 0..k {
                let r = 0.5 * ((i as f64 + 0.5) / k as f64).sqrt();
                let phi = std::f64::consts::TAU * (j as f64 + 0.5) / k as f64;
                out.push([r * phi.cos(), r * phi.sin()]);
            }
        }
        out
    }

    /// Without aberration the spacing is the thin lens's: σ = 0, and the
    /// image comes back bit for bit; with it, σ matches the closed form of
    /// ⟨J⟩ for a uniform disc, (a + S)², where both factors keep their
    /// sign, and in the caustic's band the direct mean over the points.
    #[test]
    fn the_thin_lens_is_untouched_and_the_aberrations_spacing_is_its_closed_form() {
        let pts = disc_points(4096);
        let inv_z: Vec<f64> = (0..50).map(|i| 0.1 + 0.05 * i as f64).collect();
        let thin = Spacing {
            points: &pts,
            c_scale: 40.0,
            inv_u: 1.0,
            area: std::f64::consts::FRAC_PI_4,
            spherical_d: 0.0,
            k: 0.5,
        };
        assert!(sigmas(&thin, &inv_z).iter().all(|s| *s == 0.0));
        assert!(sigmas(&thin, &inv_z).is_empty());
        let img = Image::from_vec(10, 5, (0..50).map(|i| [i as f32; 3]).collect()).unwrap();
        let same = close_gaps(img.clone(), &sigmas(&thin, &inv_z));
        assert_eq!(same.as_slice(), img.as_slice());
        // S = 0.8: where (a + S t)(a + 3 S t) keeps its sign on [0, 1]
        // (a >= 0), ⟨J⟩ = ∫ a² + 4 a S t + 3 S² t² dt = a² + 2 a S + S²
        let s = 0.8;
        let sp = Spacing {
            spherical_d: s,
            ..thin
        };
        let got = sigmas(&sp, &inv_z);
        let scale = 0.5 * (std::f64::consts::FRAC_PI_4 / pts.len() as f64).sqrt() * 40.0;
        for (v, g) in inv_z.iter().zip(&got) {
            let a = 1.0 - v;
            if a < 0.0 {
                continue;
            }
            let want = scale * (2.0 * a * s + s * s).sqrt();
            assert!((g - want).abs() < 0.01 * want, "a {a}: {g} vs {want}");
        }
        // the other side: a caustic's band (0 < a < 2.4) where the direct
        // mean over the points decides, never negative, not zero throughout
        let neg_sp = Spacing {
            spherical_d: -s,
            ..thin
        };
        let neg = sigmas(&neg_sp, &inv_z);
        assert!(neg.iter().all(|v| *v >= 0.0 && v.is_finite()));
        assert!(neg.iter().any(|v| *v > 0.1), "{neg:?}");
        let ts: Vec<f64> = pts
            .iter()
            .map(|p| 4.0 * (p[0] * p[0] + p[1] * p[1]))
            .collect();
        for (v, g) in inv_z.iter().zip(&neg) {
            let want = added(1.0 - v, -s, &ts).max(0.0);
            let got = (g / scale).powi(2);
            assert!((got - want).abs() < 1e-4, "{v}: {got} vs {want}");
        }
    }

    /// A depth far off the others (a stray near pixel) changes no other
    /// pixel's filter, and gets a finite one itself.
    #[test]
    fn an_outlier_depth_changes_no_other_pixels_filter() {
        let pts = disc_points(1024);
        let sp = Spacing {
            points: &pts,
            c_scale: 40.0,
            inv_u: 1.0,
            area: std::f64::consts::FRAC_PI_4,
            spherical_d: 0.8,
            k: 0.5,
        };
        let inv_z: Vec<f64> = (0..64).map(|i| 0.2 + 0.04 * i as f64).collect();
        let mut with = inv_z.clone();
        with.push(1e14);
        with.push(f64::NAN);
        let (a, b) = (sigmas(&sp, &inv_z), sigmas(&sp, &with));
        assert_eq!(a[..], b[..64]);
        assert!(b[64..].iter().all(|v| v.is_finite() && *v >= 0.0));
    }

    /// A row of isolated dots (the views of one bright point) becomes the
    /// smooth band they sample: the filter's output varies far less along
    /// the row, and keeps the row's total (a Gaussian renormalised inside
    /// the image).
    #[test]
    fn dots_spaced_by_the_views_become_a_band() {
        let (w, h) = (64, 1);
        let mut v = vec![[0.0f32; 3]; w];
        for x in (8..56).step_by(4) {
            v[x] = [1.0; 3];
        }
        let img = Image::from_vec(w, h, v).unwrap();
        let sigma = vec![2.0; w];
        let out = Image::from_vec(w, h, pass(img.as_slice(), w, h, &sigma, true)).unwrap();
        let spread = |im: &ColorImage| {
            let xs: Vec<f64> = (20..44).map(|x| im.get(x, 0)[0] as f64).collect();
            let m = xs.iter().sum::<f64>() / xs.len() as f64;
            (xs.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / xs.len() as f64).sqrt()
        };
        assert!(spread(&out) < 0.05 * spread(&img), "{}", spread(&out));
        let total = |im: &ColorImage| im.as_slice().iter().map(|p| p[0] as f64).sum::<f64>();
        assert!((total(&out) - total(&img)).abs() < 0.02 * total(&img));
    }
}
