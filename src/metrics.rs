//! Error metrics between two values of the same type (what `sweep` plots).

use depthgraph_graph::prelude::*;
use serde::Serialize;

/// Which error to report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Metric {
    /// Root mean square error.
    Rmse,
    /// Mean absolute error.
    Mae,
    /// Peak signal-to-noise ratio in dB (peak = largest reference value, at least 1e-12).
    Psnr,
    /// Color only: PSNR in dB of the display-referred images (clamped to
    /// [0, 1], sRGB encoded, peak 1), see [`display_psnr`].
    DisplayPsnr,
    /// Color only: mean SSIM of the display luma, see [`display_ssim`].
    Ssim,
}

/// An error measurement and the share of reference samples it covers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Measurement {
    pub value: f64,
    /// Samples compared.
    pub count: usize,
    /// Reference samples that had no counterpart (a hole in the result where
    /// the reference has a measurement).
    pub missing: usize,
}

impl Metric {
    /// The name `--metric` takes (`display-psnr`), for tables, CSV and plots.
    pub fn name(self) -> &'static str {
        match self {
            Metric::Rmse => "rmse",
            Metric::Mae => "mae",
            Metric::Psnr => "psnr",
            Metric::DisplayPsnr => "display-psnr",
            Metric::Ssim => "ssim",
        }
    }
}

/// Why two values cannot be compared.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    #[error("cannot compare {0} with {1}")]
    Types(ValueType, ValueType),
    #[error("cannot compare a {0}x{1} image with a {2}x{3} one")]
    Dims(usize, usize, usize, usize),
    #[error("{0} values cannot be compared numerically")]
    Unsupported(ValueType),
    #[error("--metric {metric} compares colour images only, not {found} values")]
    ColourOnly {
        /// The metric's name.
        metric: &'static str,
        /// What it was given.
        found: ValueType,
    },
    #[error("no sample to compare (the reference has no valid pixel)")]
    Empty,
}

/// Compares `result` with `reference`. For depth, only pixels valid in the
/// reference count; result holes there are counted as `missing` and left out
/// of the error. Sums are accumulated in f64.
pub fn compare(
    result: &Value,
    reference: &Value,
    metric: Metric,
) -> Result<Measurement, MetricError> {
    if matches!(metric, Metric::DisplayPsnr | Metric::Ssim) {
        return match (result, reference) {
            (Value::Color(a), Value::Color(b)) => {
                let value = if metric == Metric::Ssim {
                    display_ssim(a, b)?
                } else {
                    display_psnr(a, b)?
                };
                Ok(Measurement {
                    value,
                    count: a.len(),
                    missing: 0,
                })
            }
            (Value::Color(_), b) => Err(MetricError::Types(ValueType::Color, b.value_type())),
            (a, _) => Err(MetricError::ColourOnly {
                metric: metric.name(),
                found: a.value_type(),
            }),
        };
    }
    let mut acc = Acc::default();
    match (result, reference) {
        (Value::Depth(a), Value::Depth(b)) => {
            dims(a.dims(), b.dims())?;
            for (x, r) in a.as_slice().iter().zip(b.as_slice()) {
                if !DepthMap::is_valid(*r) {
                    continue;
                }
                if !DepthMap::is_valid(*x) {
                    acc.missing += 1;
                    continue;
                }
                acc.add(*x as f64, *r as f64);
            }
        }
        (Value::Color(_), Value::Color(_))
        | (Value::Normals(_), Value::Normals(_))
        | (Value::Mask(_) | Value::Confidence(_), Value::Mask(_) | Value::Confidence(_)) => {
            // every sample alike; `samples` is Some for these kinds
            let (Some(a), Some(b)) = (result.samples(), reference.samples()) else {
                return Err(MetricError::Unsupported(result.value_type()));
            };
            dims((a.width, a.height), (b.width, b.height))?;
            for (x, r) in a.samples.iter().zip(b.samples) {
                acc.add(*x as f64, *r as f64);
            }
        }
        (Value::Scalar(a), Value::Scalar(b)) => acc.add(*a, *b),
        (a, b) if a.value_type() != b.value_type() => {
            return Err(MetricError::Types(a.value_type(), b.value_type()));
        }
        (a, _) => return Err(MetricError::Unsupported(a.value_type())),
    }
    acc.finish(metric)
}

fn dims(a: (usize, usize), b: (usize, usize)) -> Result<(), MetricError> {
    if a == b {
        Ok(())
    } else {
        Err(MetricError::Dims(a.0, a.1, b.0, b.1))
    }
}

#[derive(Default)]
struct Acc {
    sq: f64,
    abs: f64,
    peak: f64,
    count: usize,
    missing: usize,
}

impl Acc {
    fn add(&mut self, x: f64, r: f64) {
        let d = x - r;
        // Non-finite results are the worst possible answer, not skipped.
        let d = if d.is_finite() { d } else { f64::INFINITY };
        self.sq += d * d;
        self.abs += d.abs();
        if r.is_finite() {
            self.peak = self.peak.max(r.abs());
        }
        self.count += 1;
    }
    fn finish(self, metric: Metric) -> Result<Measurement, MetricError> {
        if self.count == 0 {
            return Err(MetricError::Empty);
        }
        // guard: count > 0 checked above
        let n = self.count as f64;
        let mse = self.sq / n;
        let value = match metric {
            Metric::Rmse => mse.sqrt(),
            Metric::Mae => self.abs / n,
            Metric::Psnr => {
                // guard: a zero error is reported as +inf dB; the peak is at least 1e-12
                let peak = self.peak.max(1e-12);
                if mse == 0.0 {
                    f64::INFINITY
                } else {
                    10.0 * (peak * peak / mse).log10()
                }
            }
            // Handled by `compare` before accumulating; unreachable here.
            Metric::DisplayPsnr | Metric::Ssim => f64::NAN,
        };
        Ok(Measurement {
            value,
            count: self.count,
            missing: self.missing,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    fn depth(v: Vec<f32>) -> Value {
        Value::Depth(Arc::new(Image::from_vec(v.len(), 1, v).unwrap()))
    }

    #[test]
    fn rmse_mae_psnr_on_known_values() {
        let a = depth(vec![1.0, 2.0, 0.0, 4.0]);
        let b = depth(vec![1.0, 3.0, 3.0, 0.0]);
        let m = compare(&a, &b, Metric::Rmse).unwrap();
        // compared: (1,1), (2,3); missing: pixel 2; pixel 3 not in the reference
        assert_eq!((m.count, m.missing), (2, 1));
        assert!((m.value - (0.5f64).sqrt()).abs() < 1e-12);
        assert!((compare(&a, &b, Metric::Mae).unwrap().value - 0.5).abs() < 1e-12);
        let p = compare(&a, &b, Metric::Psnr).unwrap().value;
        assert!((p - 10.0 * (9.0f64 / 0.5).log10()).abs() < 1e-9);
        assert_eq!(compare(&b, &b, Metric::Psnr).unwrap().value, f64::INFINITY);
    }

    /// The colour-only metrics say so on depth (they said depth cannot be
    /// compared numerically, though rmse compares it), and a colour result
    /// against another type names both.
    #[test]
    fn colour_only_metrics_say_what_they_take() {
        let d = depth(vec![1.0, 2.0]);
        for m in [Metric::Ssim, Metric::DisplayPsnr] {
            let e = compare(&d, &d, m).unwrap_err().to_string();
            assert!(
                e.contains(m.name()) && e.contains("colour images only"),
                "{e}"
            );
        }
        let c = Value::Color(Arc::new(Image::from_vec(2, 1, vec![[0.5; 3]; 2]).unwrap()));
        assert_eq!(
            compare(&c, &d, Metric::Ssim).unwrap_err(),
            MetricError::Types(ValueType::Color, ValueType::Depth)
        );
    }

    #[test]
    fn mismatches_are_errors() {
        let a = depth(vec![1.0, 2.0]);
        let b = depth(vec![1.0]);
        assert!(matches!(
            compare(&a, &b, Metric::Rmse),
            Err(MetricError::Dims(..))
        ));
        assert!(matches!(
            compare(&a, &Value::Scalar(1.0), Metric::Rmse),
            Err(MetricError::Types(..))
        ));
        assert_eq!(
            compare(&depth(vec![1.0]), &depth(vec![0.0]), Metric::Rmse),
            Err(MetricError::Empty)
        );
    }
}

/// Display-referred luma of a linear image: each channel clamped to
/// `[0, 1]` and sRGB-encoded (what a viewer sees), then Rec. 709 weights.
pub fn display_luma(img: &ColorImage) -> Vec<f64> {
    use depthgraph_nodes::kit::color::linear_to_srgb;
    img.as_slice()
        .iter()
        .map(|c| {
            let e = c.map(|v| {
                if v.is_finite() {
                    linear_to_srgb(v) as f64
                } else {
                    0.0
                }
            });
            depthgraph_nodes::kit::color::luminance_f64(e)
        })
        .collect()
}

/// PSNR in dB between the display-referred (clamped, sRGB-encoded) versions
/// of two linear color images, all channels, peak 1. Identical images give
/// `f64::INFINITY`.
pub fn display_psnr(a: &ColorImage, b: &ColorImage) -> Result<f64, MetricError> {
    use depthgraph_nodes::kit::color::{display_mse, psnr_of_mse};
    dims(a.dims(), b.dims())?;
    if a.is_empty() {
        return Err(MetricError::Empty);
    }
    Ok(psnr_of_mse(display_mse(a.as_slice(), b.as_slice())))
}

/// Mean SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5,
/// `K1 = 0.01`, `K2 = 0.03`, dynamic range 1) of the display luma of two
/// linear color images; windows are clipped at the borders.
pub fn display_ssim(a: &ColorImage, b: &ColorImage) -> Result<f64, MetricError> {
    dims(a.dims(), b.dims())?;
    if a.is_empty() {
        return Err(MetricError::Empty);
    }
    let (w, h) = a.dims();
    let (la, lb) = (display_luma(a), display_luma(b));
    let g: Vec<f64> = (-5..=5)
        .map(|i: i32| (-(i * i) as f64 / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    // Separable Gaussian blur with renormalisation at clipped borders.
    let blur = |img: &[f64]| -> Vec<f64> {
        let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
            (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as i64, (i / w) as i64);
                    let (mut s, mut n) = (0.0, 0.0);
                    for (k, gk) in g.iter().enumerate() {
                        let o = k as i64 - 5;
                        let (qx, qy) = if horizontal { (x + o, y) } else { (x, y + o) };
                        if qx >= 0 && qy >= 0 && qx < w as i64 && qy < h as i64 {
                            s += gk * src[qy as usize * w + qx as usize];
                            n += gk;
                        }
                    }
                    // Guard: the centre tap (weight 1) is always inside.
                    s / n
                })
                .collect()
        };
        pass(&pass(img, true), false)
    };
    let prod = |p: &[f64], q: &[f64]| -> Vec<f64> { p.iter().zip(q).map(|(x, y)| x * y).collect() };
    let (ma, mb) = (blur(&la), blur(&lb));
    let (saa, sbb, sab) = (
        blur(&prod(&la, &la)),
        blur(&prod(&lb, &lb)),
        blur(&prod(&la, &lb)),
    );
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let total: f64 = (0..w * h)
        .map(|i| {
            let (mu_a, mu_b) = (ma[i], mb[i]);
            let va = saa[i] - mu_a * mu_a;
            let vb = sbb[i] - mu_b * mu_b;
            let cov = sab[i] - mu_a * mu_b;
            // Guard: c1, c2 > 0 keep the denominator positive.
            ((2.0 * mu_a * mu_b + c1) * (2.0 * cov + c2))
                / ((mu_a * mu_a + mu_b * mu_b + c1) * (va + vb + c2))
        })
        .sum();
    Ok(total / (w * h) as f64)
}

#[cfg(test)]
mod display_tests {
    use super::*;

    #[test]
    fn psnr_and_ssim_rank_a_blur_below_the_original() {
        let a = ColorImage::from_fn(40, 30, |x, y| {
            let v = if (x / 4 + y / 4) % 2 == 0 { 0.8 } else { 0.1 };
            [v, v, v]
        });
        assert_eq!(display_psnr(&a, &a).unwrap(), f64::INFINITY);
        assert!((display_ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
        let blurred = ColorImage::from_fn(40, 30, |x, y| {
            let mut s = [0.0f32; 3];
            for dx in -1i64..=1 {
                let xx = (x as i64 + dx).clamp(0, 39) as usize;
                for (acc, v) in s.iter_mut().zip(a.get(xx, y)) {
                    *acc += v / 3.0;
                }
            }
            s
        });
        let p = display_psnr(&blurred, &a).unwrap();
        let s = display_ssim(&blurred, &a).unwrap();
        assert!(p.is_finite() && p > 5.0 && p < 40.0, "{p}");
        assert!(s > 0.3 && s < 0.99, "{s}");
        // Values above 1 are clipped like a display: 5 and 9 look the same.
        let hot = ColorImage::filled(8, 8, [5.0; 3]);
        let hotter = ColorImage::filled(8, 8, [9.0; 3]);
        assert_eq!(display_psnr(&hot, &hotter).unwrap(), f64::INFINITY);
        assert!(display_psnr(&hot, &ColorImage::filled(9, 8, [0.0; 3])).is_err());
    }
}
