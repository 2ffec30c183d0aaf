//! Colour: the sRGB transfer functions (IEC 61966-2-1) and Rec. 709
//! luminance, the one copy every node, the editor and the benches use.

use depthgraph_graph::value::Rgb;

/// sRGB electro-optical transfer: encoded value in [0, 1] to linear.
#[inline]
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear to sRGB-encoded value; input clamped to [0, 1] (NaN to 0).
#[inline]
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    if v <= 0.003_130_8 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Linear value to an 8-bit sRGB code (rounded to nearest; clamped, NaN to 0).
#[inline]
pub fn srgb8(v: f32) -> u8 {
    (linear_to_srgb(v) * 255.0).round() as u8
}

/// Linear value to a 16-bit sRGB code (rounded to nearest; clamped, NaN to 0).
#[inline]
pub fn srgb16(v: f32) -> u16 {
    (linear_to_srgb(v) * 65535.0).round() as u16
}

/// Linear RGB to 8-bit sRGB.
#[inline]
pub fn rgb_to_srgb8(c: Rgb) -> [u8; 3] {
    c.map(srgb8)
}

/// Rec. 709 luminance weights `0.2126 R + 0.7152 G + 0.0722 B`, in f64:
/// the one copy of the formula (also for sRGB-encoded or 8-bit values,
/// where it gives luma).
#[inline]
pub fn luminance_f64(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// Rec. 709 luminance of linear RGB, in f64.
#[inline]
pub fn luminance(c: Rgb) -> f64 {
    luminance_f64(c.map(f64::from))
}

/// [`luminance`] of the channels clamped to `>= 0` (NaN and infinities
/// count as 0): the energy of a light, never negative.
#[inline]
pub fn luminance_clamped(c: Rgb) -> f64 {
    luminance_f64(c.map(|v| {
        if v > 0.0 && v.is_finite() {
            v as f64
        } else {
            0.0
        }
    }))
}

/// Mean squared difference of the display values (linear clamped to
/// [0, 1], sRGB-encoded, non-finite as 0) of two equally long pixel lists,
/// over all channels; 0 for empty lists. The one display error measure of
/// the metrics and of the backend parity checks.
pub fn display_mse(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let enc = |v: f32| {
        if v.is_finite() {
            linear_to_srgb(v) as f64
        } else {
            0.0
        }
    };
    let se: f64 = a
        .iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (enc(*x) - enc(*y)).powi(2))
        .sum();
    // Guard: an empty list has no error.
    if a.is_empty() {
        0.0
    } else {
        se / (a.len() * 3) as f64
    }
}

/// [`display_mse`] over the pixels whose `mask` flag is set (0 when none
/// is).
pub fn display_mse_masked(a: &[[f32; 3]], b: &[[f32; 3]], mask: &[bool]) -> f64 {
    let pick = |img: &[[f32; 3]]| -> Vec<[f32; 3]> {
        img.iter()
            .zip(mask)
            .filter(|(_, m)| **m)
            .map(|(c, _)| *c)
            .collect()
    };
    display_mse(&pick(a), &pick(b))
}

/// PSNR in dB (peak 1) of a mean squared error; infinite for 0.
pub fn psnr_of_mse(mse: f64) -> f64 {
    // Guard: mse > 0 in the logarithm.
    if mse > 0.0 {
        -10.0 * mse.log10()
    } else {
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transfer_round_trips_and_luminance_weights_sum_to_one() {
        for i in 0..=255 {
            let v = i as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
        }
        assert_eq!(rgb_to_srgb8([1.0, 0.0, f32::NAN]), [255, 0, 0]);
        assert_eq!(srgb16(1.0), 65535);
        assert!((luminance([1.0; 3]) - 1.0).abs() < 1e-12);
        assert_eq!(luminance_clamped([-1.0, f32::INFINITY, 0.0]), 0.0);
    }
}
