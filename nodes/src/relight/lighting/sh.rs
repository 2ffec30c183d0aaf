//! Real spherical harmonics of order 2 and the irradiance they give a
//! Lambertian surface (Ramamoorthi & Hanrahan, "An Efficient Representation
//! for Irradiance Environment Maps", SIGGRAPH 2001).
//!
//! Radiance `L(ω) = Σ L_lm Y_lm(ω)` gives the irradiance
//! `E(n) = Σ Â_l L_lm Y_lm(n)` (their eq. 7-8) with the clamped-cosine
//! coefficients `Â_0 = π`, `Â_1 = 2π/3`, `Â_2 = π/4` (eq. 9); the nine
//! terms of order ≤ 2 carry the irradiance of any map to within a few
//! percent (their §2.3). Directions are unit vectors of the camera frame
//! (`x` right, `y` down, `z` forward), the frame of the environment maps.

use std::f64::consts::PI;

use depthgraph_graph::prelude::*;
use glam::DVec3;

use crate::relight::envmap::{pixel_direction, pixel_solid_angle};

/// Number of coefficients of order ≤ 2.
pub const SH_TERMS: usize = 9;

/// Order `l` of each coefficient.
pub const SH_ORDER: [usize; SH_TERMS] = [0, 1, 1, 1, 2, 2, 2, 2, 2];

/// `Â_l` of each coefficient (module docs).
pub const CLAMPED_COSINE: [f64; 3] = [PI, 2.0 * PI / 3.0, PI / 4.0];

/// The nine real basis functions at unit direction `d` (the normalised
/// real SH of Ramamoorthi & Hanrahan's eq. 3, in the order
/// `Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22` with their `x, y, z`
/// taken as the camera frame's).
#[inline]
pub fn basis(d: DVec3) -> [f64; SH_TERMS] {
    let (x, y, z) = (d.x, d.y, d.z);
    [
        0.282_095,
        0.488_603 * y,
        0.488_603 * z,
        0.488_603 * x,
        1.092_548 * x * y,
        1.092_548 * y * z,
        0.315_392 * (3.0 * z * z - 1.0),
        1.092_548 * x * z,
        0.546_274 * (x * x - y * y),
    ]
}

/// The irradiance basis at normal `n`: `Â_l Y_lm(n)`, so that
/// `E(n) = Σ_j L_j irradiance_basis(n)_j` for radiance coefficients `L_j`.
#[inline]
pub fn irradiance_basis(n: DVec3) -> [f64; SH_TERMS] {
    let mut b = basis(n);
    for (v, l) in b.iter_mut().zip(SH_ORDER) {
        *v *= CLAMPED_COSINE[l];
    }
    b
}

/// Radiance coefficients of an environment map (per channel), by summing
/// `L(ω) Y(ω) ΔΩ` over its pixels (f64 sums; the map's direction
/// convention of [`crate::relight::envmap`]).
pub fn project_map(map: &ColorImage) -> [[f64; SH_TERMS]; 3] {
    let (w, h) = map.dims();
    let mut out = [[0.0; SH_TERMS]; 3];
    for y in 0..h {
        let d_omega = pixel_solid_angle(y, w, h);
        for x in 0..w {
            let c = map.get(x, y);
            let b = basis(pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h));
            for (ch, o) in out.iter_mut().enumerate() {
                let l = f64::from(c[ch]);
                if !l.is_finite() {
                    continue;
                }
                for (oj, bj) in o.iter_mut().zip(b) {
                    *oj += l * bj * d_omega;
                }
            }
        }
    }
    out
}

/// Irradiance at normal `n` of radiance coefficients `l`.
#[inline]
pub fn irradiance(l: &[f64; SH_TERMS], n: DVec3) -> f64 {
    irradiance_basis(n).iter().zip(l).map(|(b, c)| b * c).sum()
}

/// Radiance in direction `d` of coefficients `l`.
#[inline]
pub fn radiance(l: &[f64; SH_TERMS], d: DVec3) -> f64 {
    basis(d).iter().zip(l).map(|(b, c)| b * c).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A constant map of radiance 1 gives irradiance π on every normal; a
    /// map bright only above the horizon gives a horizontal floor about π
    /// and a ceiling about 0 (the order-2 truncation leaves a few percent).
    #[test]
    fn irradiance_of_known_maps() {
        let (w, h) = (128, 64);
        let ones = ColorImage::filled(w, h, [1.0f32; 3]);
        let l = project_map(&ones);
        for n in [DVec3::X, DVec3::NEG_Y, DVec3::new(0.6, 0.0, 0.8)] {
            let e = irradiance(&l[0], n);
            assert!((e - PI).abs() < 0.01, "{e}");
        }
        let sky = ColorImage::from_fn(w, h, |_, y| if y < h / 2 { [1.0f32; 3] } else { [0.0; 3] });
        let l = project_map(&sky);
        let up = irradiance(&l[1], DVec3::NEG_Y);
        let down = irradiance(&l[1], DVec3::Y);
        let side = irradiance(&l[1], DVec3::X);
        assert!((up - PI).abs() < 0.1 * PI, "up {up}");
        assert!(down.abs() < 0.1 * PI, "down {down}");
        assert!((side - 0.5 * PI).abs() < 0.02 * PI, "side {side}");
    }
}
