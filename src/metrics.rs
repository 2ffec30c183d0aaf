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

/// Why two values cannot be compared.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    #[error("cannot compare {0} with {1}")]
    Types(ValueType, ValueType),
    #[error("cannot compare a {0}x{1} image with a {2}x{3} one")]
    Dims(usize, usize, usize, usize),
    #[error("{0} values cannot be compared numerically")]
    Unsupported(ValueType),
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
        (Value::Color(a), Value::Color(b)) | (Value::Normals(a), Value::Normals(b)) => {
            dims(a.dims(), b.dims())?;
            for (x, r) in a.as_slice().iter().zip(b.as_slice()) {
                for c in 0..3 {
                    acc.add(x[c] as f64, r[c] as f64);
                }
            }
        }
        (Value::Mask(a) | Value::Confidence(a), Value::Mask(b) | Value::Confidence(b)) => {
            dims(a.dims(), b.dims())?;
            for (x, r) in a.as_slice().iter().zip(b.as_slice()) {
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
