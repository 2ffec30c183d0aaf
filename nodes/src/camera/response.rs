//! The camera response curve: exposure to pixel value and back, the
//! sRGB-like gamma curve the simulated brackets are made with and that
//! `HdrMerge`'s `"gamma"` response inverts.

/// Toe offset of the response at `gamma = 2.4` (sRGB's 0.055); scaled with
/// `gamma - 1` so that `gamma = 1` is the identity.
const TOE_AT_2_4: f64 = 0.055;

/// The response curve's constants for one gamma: offset `a`, end `x0` of
/// the linear toe and the toe's slope `s`; `None` for `gamma <= 1`
/// (identity).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Curve {
    gamma: f64,
    toe: Option<(f64, f64, f64)>,
}

impl Curve {
    pub(crate) fn new(gamma: f64) -> Self {
        if !(gamma.is_finite() && gamma > 1.0 + 1e-9) {
            return Self { gamma, toe: None };
        }
        let a = TOE_AT_2_4 * (gamma - 1.0) / 1.4;
        // Value and slope continuity at x0; guard: gamma > 1 so 1 - 1/gamma > 0.
        let x0 = (a / ((1.0 + a) * (1.0 - 1.0 / gamma))).powf(gamma);
        let s = (1.0 + a) / gamma * x0.powf(1.0 / gamma - 1.0);
        Self {
            gamma,
            toe: Some((a, x0, s)),
        }
    }

    pub(crate) fn apply(&self, x: f64) -> f64 {
        if x.is_nan() || x <= 0.0 {
            return 0.0;
        }
        if x >= 1.0 {
            return 1.0;
        }
        match self.toe {
            None => x,
            Some((_, x0, s)) if x <= x0 => s * x,
            Some((a, _, _)) => ((1.0 + a) * x.powf(1.0 / self.gamma) - a).min(1.0),
        }
    }

    pub(crate) fn invert(&self, y: f64) -> f64 {
        if y.is_nan() || y <= 0.0 {
            return 0.0;
        }
        if y >= 1.0 {
            return 1.0;
        }
        match self.toe {
            None => y,
            // Guard: s > 0 (x0 > 0, gamma > 1).
            Some((_, x0, s)) if y <= s * x0 => y / s,
            Some((a, _, _)) => ((y + a) / (1.0 + a)).powf(self.gamma).min(1.0),
        }
    }
}

/// The camera response: exposure `x` (1 = saturation) to pixel value in
/// `[0, 1]`. An sRGB-like curve, `(1 + a) x^(1/gamma) - a` above a linear toe
/// `s x` that meets it with the same value and slope; `a = 0.055 (gamma - 1)
/// / 1.4`, so `gamma = 2.4` is sRGB's and `gamma = 1` the identity.
/// Smooth, strictly increasing, `response(0) = 0` and `response(1) = 1`
/// exactly; inputs are clipped to `[0, 1]` (NaN to 0).
///
/// ```
/// use depthgraph_nodes::camera::response::{inverse_response, response};
/// let y = response(0.18, 2.2);
/// assert!(y > 0.42 && y < 0.45);
/// assert!((inverse_response(y, 2.2) - 0.18).abs() < 1e-6);
/// assert_eq!(response(3.0, 2.2), 1.0);
/// ```
pub fn response(x: f32, gamma: f32) -> f32 {
    Curve::new(gamma as f64).apply(x as f64) as f32
}

/// Inverse of [`response`] on `[0, 1]` (values outside are clipped).
pub fn inverse_response(y: f32, gamma: f32) -> f32 {
    Curve::new(gamma as f64).invert(y as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn response_is_monotone_continuous_and_inverted() {
        for gamma in [1.0f32, 1.5, 2.2, 2.4, 5.0] {
            assert_eq!(response(0.0, gamma), 0.0);
            assert_eq!(response(1.0, gamma), 1.0);
            assert_eq!(response(2.0, gamma), 1.0);
            assert_eq!(response(f32::NAN, gamma), 0.0);
            let mut prev = 0.0;
            for i in 1..=1000 {
                let x = i as f32 / 1000.0;
                let y = response(x, gamma);
                assert!(y > prev, "gamma {gamma}: not increasing at {x}");
                prev = y;
                assert!(
                    (inverse_response(y, gamma) - x).abs() <= 2e-6 * x + 1e-9,
                    "gamma {gamma} x {x}"
                );
            }
            // Continuity at the end of the toe.
            let curve = Curve::new(gamma as f64);
            if let Some((_, x0, _)) = curve.toe {
                let below = curve.apply(x0 * (1.0 - 1e-12));
                let above = curve.apply(x0 * (1.0 + 1e-12));
                assert!((above - below).abs() < 1e-9, "gamma {gamma}");
            }
        }
        // gamma 2.4 is sRGB's curve.
        assert!((response(0.5, 2.4) - 0.735_357).abs() < 1e-5);
        assert_eq!(response(0.3, 1.0), 0.3);
    }
}
