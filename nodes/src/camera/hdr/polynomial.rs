//! A parametric response for brackets with little data: the polynomial
//! inverse response of T. Mitsunaga, S. K. Nayar, "Radiometric Self
//! Calibration", CVPR 1999 (eq. 3-6), with the exposure times taken as known.

use depthgraph_graph::prelude::*;

use super::curve::{CHANNEL, LEVELS, ResponseCurve, Z_MAX, hat_weight, level};
use super::recover::{
    Grid, Solved, check_recovery_input, cholesky_solve, select_samples, solve_channels,
};

/// Highest polynomial degree [`recover_polynomial`] accepts.
pub const MAX_DEGREE: usize = 8;

/// Parameters of [`recover_polynomial`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolynomialParams {
    /// Degree `N` of the inverse response `I(M) = Σ_{n=0}^{N} c_n M^n`
    /// (1 to `MAX_DEGREE`).
    pub degree: usize,
    /// Pixels sampled per channel over the radiance range, on top of the
    /// coverage pass (as [`super::ResponseParams::samples`]).
    pub samples: usize,
}

impl Default for PolynomialParams {
    fn default() -> Self {
        Self {
            degree: 4,
            samples: 400,
        }
    }
}

/// Recovers a polynomial inverse response per channel (Mitsunaga & Nayar
/// 1999). With `M = z / 255` the normalised level, the exposure is
/// `I(M) = Σ_n c_n M^n` with `I(1) = Σ_n c_n = 1` (eq. 3-4). A pixel seen
/// well (`0 < z < 255`) in two exposures `a`, `b` with times `t_a < t_b`
/// (consecutive among the exposures that see it well) gives
/// `I(M_a) - R I(M_b) = 0` with the known ratio `R = t_a / t_b` (eq. 5).
/// Eliminating `c_0 = 1 - Σ_{n≥1} c_n` leaves the linear least-squares
/// problem `Σ_{n≥1} c_n [(M_a^n - 1) - R (M_b^n - 1)] = R - 1` (eq. 6 with
/// the constraint substituted), each row weighted by the hat weight of its
/// worse-exposed value (eq. 4 of Debevec & Malik) over 127.5. The normal
/// equations (`N x N`) are solved by Cholesky in f64 with a ridge of
/// `1e-12` times their mean diagonal against rounding.
///
/// `g(z) = ln I(z / 255)` (`z = 0` read as half a level, like
/// [`ResponseCurve::gamma`]); levels where `I ≤ 0` (a fitted black offset)
/// take the value of the nearest level above. The curve is then shaped like
/// a recovered one (non-decreasing, straight ends beyond the data) and the
/// channels are tied the same way, so the result has the scale conventions
/// of `recover_response`. With few parameters it needs far less data than
/// eq. 5's 256 free levels.
///
/// Errors: those of `recover_response`, a degree outside `1..=8`, or a
/// channel with fewer usable pairs than unknowns.
pub fn recover_polynomial(
    stack: &ExposureStack,
    p: &PolynomialParams,
) -> Result<ResponseCurve, NodeError> {
    check_recovery_input(stack)?;
    if !(1..=MAX_DEGREE).contains(&p.degree) {
        return Err(NodeError::param(
            "degree",
            format!("{} is outside 1..={MAX_DEGREE}", p.degree),
        ));
    }
    solve_channels(stack, |grid, c| fit_channel(stack, grid, c, p), |_| Ok(()))
}

/// Fits channel `c`; returns `g` and the support (pair observations) per
/// level.
fn fit_channel(
    stack: &ExposureStack,
    grid: &Grid,
    c: usize,
    p: &PolynomialParams,
) -> Result<Solved, NodeError> {
    let n = p.degree;
    let idx = select_samples(stack, grid, c, p.samples);
    let mut order: Vec<usize> = (0..stack.images.len()).collect();
    order.sort_by(|a, b| stack.times_s[*a].total_cmp(&stack.times_s[*b]));
    let mut a = vec![0.0f64; n * n];
    let mut b = vec![0.0f64; n];
    let mut support = [0u32; LEVELS];
    let mut rows = 0usize;
    let mut seen: Vec<(f64, f64)> = Vec::with_capacity(order.len());
    let mut row = vec![0.0f64; n];
    for &i in &idx {
        seen.clear();
        for &j in &order {
            if let Some(z) = level(stack.images[j].as_slice()[i][c]) {
                let z = z.round();
                if hat_weight(z) > 0.0 {
                    seen.push((z, stack.times_s[j]));
                }
            }
        }
        for pair in seen.windows(2) {
            let ((za, ta), (zb, tb)) = (pair[0], pair[1]);
            // guard: times are positive (checked), and sorted so tb >= ta
            let r = ta / tb;
            if r >= 1.0 {
                continue; // equal times say nothing about I
            }
            let w = hat_weight(za).min(hat_weight(zb)) / 127.5;
            let (ma, mb) = (za / Z_MAX, zb / Z_MAX);
            let (mut pa, mut pb) = (1.0f64, 1.0f64);
            for v in row.iter_mut() {
                pa *= ma;
                pb *= mb;
                *v = (pa - 1.0) - r * (pb - 1.0);
            }
            let rhs = r - 1.0;
            let w2 = w * w;
            for k in 0..n {
                b[k] += w2 * row[k] * rhs;
                for l in 0..=k {
                    a[k * n + l] += w2 * row[k] * row[l];
                }
            }
            support[za as usize] += 1;
            support[zb as usize] += 1;
            rows += 1;
        }
    }
    if rows < n + 1 {
        return Err(NodeError::input(
            "stack",
            format!(
                "{} channel: only {rows} pixel pairs are well exposed in two exposures; a degree-{n} \
                 polynomial response needs at least {}. Lower `degree`, or use response \"gamma\" or \"linear\"",
                CHANNEL[c],
                n + 1
            ),
        ));
    }
    let mean_diag = ((0..n).map(|k| a[k * n + k]).sum::<f64>() / n as f64).max(f64::MIN_POSITIVE);
    for k in 0..n {
        a[k * n + k] += 1e-12 * mean_diag;
    }
    cholesky_solve(&mut a, n, &mut b).map_err(|j| {
        NodeError::Invalid(format!(
            "{} channel: the polynomial response system is singular (pivot {j}); the exposures do not determine it",
            CHANNEL[c]
        ))
    })?;
    let coef = b;
    let c0 = 1.0 - coef.iter().sum::<f64>();
    let eval = |m: f64| {
        let mut acc = c0;
        let mut pm = 1.0;
        for ck in &coef {
            pm *= m;
            acc += ck * pm;
        }
        acc
    };
    let mut g = [f64::NAN; LEVELS];
    for (z, gz) in g.iter_mut().enumerate() {
        let m = if z == 0 { 0.5 } else { z as f64 } / Z_MAX;
        let i = eval(m);
        if i.is_finite() && i > 0.0 {
            *gz = i.ln();
        }
    }
    // levels with I <= 0 take the nearest positive level above (then below)
    let Some(first) = g.iter().position(|v| v.is_finite()) else {
        return Err(NodeError::Invalid(format!(
            "{} channel: the fitted polynomial response is not positive at any level",
            CHANNEL[c]
        )));
    };
    let mut last = g[first];
    for z in 0..LEVELS {
        if g[z].is_finite() {
            last = g[z];
        } else if z < first {
            g[z] = g[first];
        } else {
            g[z] = last;
        }
    }
    Ok((g, support))
}
