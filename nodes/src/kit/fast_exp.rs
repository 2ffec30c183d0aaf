//! `exp(x)` for `x <= 0` without a libm call, branch-free so that loops
//! over it vectorise (the weights of the NL-means passes): [`exp_neg`] in
//! f64, [`exp_neg_f32`] in f32 (twice the lanes, half the polynomial).

/// `x` below this gives 0: `exp(-708)` is about `3.3e-308`, the last value
/// before the subnormal range, so every non-zero result is a normal number
/// with the full relative precision.
pub const EXP_NEG_MIN: f64 = -708.0;

/// `exp(x)` for `x <= 0` with relative error below `1e-12`.
///
/// `x log2(e) = k + f` with `k` the nearest integer (found by adding
/// `1.5 * 2^52`, which leaves `k` in the low mantissa bits) and
/// `|f| <= 1/2`; `2^f = exp(u)`, `|u| <= ln(2) / 2`, from its degree-11
/// Taylor polynomial (truncation below `0.347^12 / 12! = 6e-15`), and `2^k`
/// built in the exponent bits. Exactly 1 at 0 (`k = 0`, `u = 0`). `x` below
/// [`EXP_NEG_MIN`] (and `-inf`) gives 0, NaN gives NaN, `x > 0` is treated
/// as 0 (the callers' exponents are never positive). Only float
/// arithmetic, integer adds and shifts, and selects: no branch, no
/// float-to-int cast.
#[inline(always)]
pub fn exp_neg(x: f64) -> f64 {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52
    let xc = x.clamp(EXP_NEG_MIN, 0.0);
    let y = xc * std::f64::consts::LOG2_E;
    let t = y + MAGIC;
    let k = t - MAGIC; // round(y), exact
    let u = (y - k) * std::f64::consts::LN_2;
    let mut p = 1.0 / 39_916_800.0; // 1 / 11!
    p = p * u + 1.0 / 3_628_800.0;
    p = p * u + 1.0 / 362_880.0;
    p = p * u + 1.0 / 40_320.0;
    p = p * u + 1.0 / 5_040.0;
    p = p * u + 1.0 / 720.0;
    p = p * u + 1.0 / 120.0;
    p = p * u + 1.0 / 24.0;
    p = p * u + 1.0 / 6.0;
    p = p * u + 0.5;
    p = p * u + 1.0;
    p = p * u + 1.0;
    // k in [-1022, 0]: the biased exponent 1023 + k is in [1, 1023].
    let k_int = t.to_bits().wrapping_sub(MAGIC.to_bits());
    let scale = f64::from_bits(1023u64.wrapping_add(k_int) << 52);
    let v = p * scale;
    if x < EXP_NEG_MIN { 0.0 } else { v }
}

/// `x` below this gives 0 in [`exp_neg_f32`]: `exp(-87)` is about
/// `1.65e-38`, just above f32's smallest normal value (`1.18e-38`, at
/// about `exp(-87.34)`), so every non-zero result is a normal number.
pub const EXP_NEG_MIN_F32: f32 = -87.0;

/// `exp(x)` for `x <= 0` in f32 with relative error below `5e-7` (about 4
/// units in the last place).
///
/// The reduction of [`exp_neg`] in f32: `k` the integer nearest to
/// `x log2(e)` (found by adding `1.5 * 2^23`) and `u = x - k ln(2)`,
/// `|u| <= ln(2) / 2` (ln(2) split in two so that `u` carries no rounding
/// of the product); then the degree-6 Taylor
/// polynomial of `exp(u)` (truncation below `0.347^7 / 7! = 1.2e-7`, the
/// rest is rounding of the f32 steps) and `2^k` built in the exponent
/// bits. Exactly 1 at 0. `x` below [`EXP_NEG_MIN_F32`] (and `-inf`) gives
/// 0, NaN gives NaN, `x > 0` is treated as 0. No branch, no float-to-int
/// cast.
#[inline(always)]
pub fn exp_neg_f32(x: f32) -> f32 {
    exp_f32_within(x, 0.0)
}

/// The largest `x` [`exp_f32`] takes: `exp(88)` is about `1.65e38`, below
/// f32's largest value (`3.4e38`).
pub const EXP_MAX_F32: f32 = 88.0;

/// `exp(x)` in f32 for `x` in `[EXP_NEG_MIN_F32, EXP_MAX_F32]` with the
/// relative error of [`exp_neg_f32`] (the same reduction: `|u| <= ln(2) /
/// 2` on both sides of 0, `2^k` for `k` up to 127 in the exponent bits);
/// below that range 0, above it `exp(88)`, NaN gives NaN. For sums kept
/// relative to a reference exponent above their terms' (the NL-means
/// rows' shift), whose ratios are what counts.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    exp_f32_within(x, EXP_MAX_F32)
}

/// [`exp_neg_f32`]'s reduction with `x` clamped to `[EXP_NEG_MIN_F32, hi]`
/// (`hi <= EXP_MAX_F32`).
#[inline(always)]
fn exp_f32_within(x: f32, hi: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 * 2^23
    let xc = x.clamp(EXP_NEG_MIN_F32, hi);
    let y = xc * std::f32::consts::LOG2_E;
    let t = y + MAGIC;
    let k = t - MAGIC; // round(y), exact
    // u = x - k ln(2) in two steps (Cody and Waite): k * LN2_HI is exact
    // (|k| <= 126 has 7 bits, LN2_HI 9), so the rounding of x log2(e)
    // (up to 4e-6 at |x| = 87) never reaches u.
    const LN2_HI: f32 = 0.693_359_4; // 355 / 512
    const LN2_LO: f32 = -2.121_944_4e-4; // ln(2) - LN2_HI
    let u = (xc - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 720.0;
    p = p * u + 1.0 / 120.0;
    p = p * u + 1.0 / 24.0;
    p = p * u + 1.0 / 6.0;
    p = p * u + 0.5;
    p = p * u + 1.0;
    p = p * u + 1.0;
    // k in [-126, 127]: the biased exponent 127 + k is in [1, 254].
    let k_int = t.to_bits().wrapping_sub(MAGIC.to_bits());
    let scale = f32::from_bits(127u32.wrapping_add(k_int) << 23);
    let v = p * scale;
    if x < EXP_NEG_MIN_F32 { 0.0 } else { v }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_f32_version_matches_libm_over_the_range() {
        assert_eq!(exp_neg_f32(0.0), 1.0);
        assert_eq!(exp_neg_f32(-0.0), 1.0);
        assert_eq!(exp_neg_f32(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_neg_f32(-87.5), 0.0);
        assert!(exp_neg_f32(f32::NAN).is_nan());
        let mut worst = 0.0f64;
        let n = 400_000;
        for i in 0..=n {
            for x in [
                EXP_NEG_MIN_F32 * i as f32 / n as f32,
                -4.0 * i as f32 / n as f32,
            ] {
                let (a, b) = (exp_neg_f32(x) as f64, (x as f64).exp());
                assert!(a.is_normal() || a == 0.0, "{x}: {a:e}");
                worst = worst.max(((a - b) / b).abs());
            }
        }
        assert!(worst < 5e-7, "relative error {worst:e}");
        // and the bound is not loose by orders of magnitude
        assert!(worst > 5e-8, "relative error {worst:e}");
    }

    #[test]
    fn the_f32_version_above_zero_matches_libm() {
        assert_eq!(exp_f32(0.0), 1.0);
        assert_eq!(exp_f32(200.0), exp_f32(EXP_MAX_F32));
        assert!(exp_f32(EXP_MAX_F32).is_finite());
        assert_eq!(exp_f32(-87.5), 0.0);
        assert!(exp_f32(f32::NAN).is_nan());
        let mut worst = 0.0f64;
        let n = 400_000;
        for i in 0..=n {
            let x = EXP_NEG_MIN_F32 + (EXP_MAX_F32 - EXP_NEG_MIN_F32) * i as f32 / n as f32;
            let (a, b) = (exp_f32(x) as f64, (x as f64).exp());
            assert!(a.is_normal(), "{x}: {a:e}");
            worst = worst.max(((a - b) / b).abs());
            if x <= 0.0 {
                assert_eq!(exp_f32(x), exp_neg_f32(x), "{x}");
            }
        }
        assert!(worst < 5e-7, "relative error {worst:e}");
    }

    #[test]
    fn the_f32_version_is_monotone_at_the_reduction_boundaries() {
        for k in [1.0f32, 10.0, 60.0, 86.0] {
            let x = -(k + 0.5) * std::f32::consts::LN_2;
            let (a, b) = (exp_neg_f32(x + 1e-5), exp_neg_f32(x - 1e-5));
            assert!(a >= b, "{k}: {a} < {b}");
        }
    }

    #[test]
    fn matches_libm_over_the_range() {
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(-0.0), 1.0);
        assert_eq!(exp_neg(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp_neg(-708.5), 0.0);
        assert!(exp_neg(f64::NAN).is_nan());
        let mut worst = 0.0f64;
        let n = 200_000;
        for i in 0..=n {
            let x = EXP_NEG_MIN * i as f64 / n as f64;
            let (a, b) = (exp_neg(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
        }
        // also the small exponents the weights mostly have, densely
        for i in 0..=n {
            let x = -4.0 * i as f64 / n as f64;
            let (a, b) = (exp_neg(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
        }
        assert!(worst < 1e-12, "relative error {worst:e}");
    }

    #[test]
    fn is_monotone_at_the_reduction_boundaries() {
        // around k + 1/2 (the rounding switches k) the value must not jump
        for k in [1.0f64, 10.0, 100.0, 700.0] {
            let x = -(k + 0.5) * std::f64::consts::LN_2;
            let (a, b) = (exp_neg(x + 1e-12), exp_neg(x - 1e-12));
            assert!(a >= b, "{k}: {a} < {b}");
        }
    }
}
