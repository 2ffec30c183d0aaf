//! The light a photo's own surfaces bounce onto each other: the part of
//! each sample's irradiance that the photo shows as the radiance of other
//! visible surfaces, so that the lighting fit ([`super::estimate`]) can
//! leave it out of the environment map.
//!
//! A room lit by a sun passes much of that sun on: in a closed room of
//! albedo `ρ` the total irradiance is the direct one over `1 - ρ`. A fit
//! that calls all of it sky gives a map whose sky is too bright and whose
//! sun is too weak, and `Relight`, which bounces the map's light off the
//! photo's surfaces itself (the VPLs of 3d-editing §IV), would count that
//! light twice. The photo's pixels are outgoing radiance, so the bounce
//! they send is known without knowing any albedo:
//!
//! `B_i = Σ_j L_j cos θ_i cos θ_j A_j / (r_ij² + A_j / π)`,
//!
//! the irradiance at sample `i` (normal `n_i`) from the patches `j` of the
//! photo (radiance `L_j`, area `A_j`, normal `n_j`, at distance `r_ij`),
//! the discrete gather of radiosity (Cohen and Wallace, eq. 2.26 with
//! `E = π B`). The `A_j / π` in the denominator is a patch's own radius
//! squared: it makes each term the on-axis irradiance of a disc of area
//! `A_j` (`π L R² / (r² + R²)`), bounded by `L cos cos π` as `r → 0`,
//! where the point form diverges.
//!
//! The same patches hide the sky in the directions they cover: a map
//! lights a point only past the photo's surfaces, as `Relight`'s scene
//! shadow maps have it. [`gather`] also returns that covered part per
//! spherical-harmonic term, so that the fit's low-frequency light is the
//! sky's alone.
//!
//! # Assumptions
//!
//! - Patches see each other (no visibility test): a surface the photo shows
//!   between two others would cast a shadow in the bounce that is not
//!   subtracted, and a patch behind another counts as well (the sums are
//!   capped at the hemisphere, [`gather`]). The bounce is smooth; this
//!   errs where an occluder is near.
//! - Only the visible surfaces bounce. What lies outside the frame or
//!   behind the camera stays in the fit's low-frequency light.
//! - Surfaces are Lambertian (the radiance a patch shows the camera is the
//!   radiance it sends every way).

use glam::DVec3;
use rayon::prelude::*;

use depthgraph_graph::prelude::*;

use std::f64::consts::PI;

use crate::relight::lighting::sh::{self, SH_TERMS};
use crate::relight::shading::{Surf, pixel_areas};

/// Patches the photo is cut into for the gather (about; square blocks).
pub const BOUNCE_PATCHES: usize = 512;

/// A block of the photo as a light source.
#[derive(Debug, Clone, Copy)]
pub struct Patch {
    /// Area-weighted mean position, metres (camera frame).
    pub pos: DVec3,
    /// Unit normal (of the area-weighted mean normal).
    pub n: DVec3,
    /// Total area, m².
    pub area: f64,
    /// Radiance times area, summed over the block's pixels (linear RGB).
    pub flux: [f64; 3],
}

/// The photo cut into about `count` square blocks, each a [`Patch`] of
/// its pixels with a surface and a finite, non-negative colour. A block
/// whose normals cancel (a corner seen edge-on: mean normal shorter than
/// 0.5) is left out rather than given a normal none of its pixels has.
pub(crate) fn patches(
    color: &ColorImage,
    depth: &DepthMap,
    k: &Intrinsics,
    surfaces: &[Option<Surf>],
    count: usize,
) -> Vec<Patch> {
    let (w, h) = color.dims();
    let areas = pixel_areas(depth, k);
    let valid = surfaces.iter().filter(|s| s.is_some()).count();
    // guard: count >= 1 by max; a side of at least one pixel
    let side = ((valid as f64 / count.max(1) as f64).sqrt().ceil() as usize).max(1);
    let (bw, bh) = (w.div_ceil(side), h.div_ceil(side));
    (0..bw * bh)
        .into_par_iter()
        .filter_map(|b| {
            let (bx, by) = (b % bw, b / bw);
            let mut pos = DVec3::ZERO;
            let mut n = DVec3::ZERO;
            let mut area = 0.0f64;
            let mut flux = [0.0f64; 3];
            for y in by * side..((by + 1) * side).min(h) {
                for x in bx * side..((bx + 1) * side).min(w) {
                    let i = y * w + x;
                    let Some(s) = &surfaces[i] else { continue };
                    let c = color.get(x, y);
                    if !c.iter().all(|v| v.is_finite() && *v >= 0.0) {
                        continue;
                    }
                    let a = areas[i];
                    pos += s.pos * a;
                    n += s.n * a;
                    area += a;
                    for (f, v) in flux.iter_mut().zip(c) {
                        *f += f64::from(*v) * a;
                    }
                }
            }
            // guard: a block without area (holes only) is no patch
            if area <= 0.0 || !area.is_finite() {
                return None;
            }
            let n = n / area;
            (n.length() >= 0.5).then(|| Patch {
                pos: pos / area,
                n: n.normalize(),
                area,
                flux,
            })
        })
        .collect()
}

/// What [`gather`] finds at a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gathered {
    /// `B`, the irradiance the patches send (linear RGB).
    pub irradiance: [f64; 3],
    /// The sky the patches hide, per spherical-harmonic radiance term:
    /// `Σ_j Y_k(u_ij) cos θ_i ω_ij` (`u_ij` the unit direction to patch
    /// `j`, `ω_ij = cos θ_j A_j / (r_ij² + A_j / π)` its solid angle), so
    /// that a map of radiance coefficients `L_k` lights the point with
    /// `Σ_k L_k (Â_l Y_k(n) - covered_k)` past the photo's surfaces.
    pub covered: [f64; SH_TERMS],
    /// `Σ_j cos θ_i ω_ij`, the projected solid angle the patches cover
    /// (at most π: see [`gather`]).
    pub projected: f64,
}

/// `B` of the module docs at points `pos` with unit normals `n`, and the
/// sky the patches hide there ([`Gathered`]). Patches are not tested for
/// visibility, so two at different depths in one direction would both
/// count: where their projected solid angle exceeds the hemisphere's `π`,
/// both sums are scaled down to `π` (guard). Sums in f64 over at most a
/// few thousand terms.
pub fn gather(points: &[(DVec3, DVec3)], patches: &[Patch]) -> Vec<Gathered> {
    points
        .par_iter()
        .map(|(x, nx)| {
            let mut e = [0.0f64; 3];
            let mut covered = [0.0f64; SH_TERMS];
            let mut projected = 0.0f64;
            for p in patches {
                let d = p.pos - *x;
                let r2 = d.length_squared();
                // guard: a patch at the point itself has no direction
                if r2 <= 1e-12 {
                    continue;
                }
                let r = r2.sqrt();
                let u = d / r;
                let cos_i = nx.dot(u);
                let cos_j = -p.n.dot(u);
                if cos_i <= 0.0 || cos_j <= 0.0 {
                    continue;
                }
                // guard: r² + A/π > 0 (r² > 0 above)
                let g = cos_i * cos_j / (r2 + p.area / PI);
                for (a, f) in e.iter_mut().zip(&p.flux) {
                    *a += g * f;
                }
                let w = g * p.area; // cos θ_i ω_ij
                for (c, y) in covered.iter_mut().zip(sh::basis(u)) {
                    *c += w * y;
                }
                projected += w;
            }
            if projected > PI {
                // guard: projected > π > 0
                let f = PI / projected;
                e.iter_mut().for_each(|v| *v *= f);
                covered.iter_mut().for_each(|v| *v *= f);
                projected = PI;
            }
            Gathered {
                irradiance: e,
                covered,
                projected,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A large square of uniform radiance `L` facing a point at distance
    /// `d` on its axis gives `π L sin²α` (α its half-angle as seen from the
    /// point; the disc's `π L R²/(d² + R²)` for a disc): the gather over
    /// fine patches within 2 %.
    #[test]
    fn a_facing_square_gives_its_form_factor() {
        let (l, d, half) = (0.7, 1.0, 3.0);
        let steps = 120;
        let cell = 2.0 * half / steps as f64;
        let mut ps = Vec::new();
        for i in 0..steps {
            for j in 0..steps {
                let x = -half + (i as f64 + 0.5) * cell;
                let y = -half + (j as f64 + 0.5) * cell;
                ps.push(Patch {
                    pos: DVec3::new(x, y, d),
                    n: DVec3::new(0.0, 0.0, -1.0),
                    area: cell * cell,
                    flux: [l * cell * cell; 3],
                });
            }
        }
        let g = gather(&[(DVec3::ZERO, DVec3::Z)], &ps)[0];
        let e = g.irradiance;
        // exact for a square of side 2a at distance d (Hottel's crossed
        // form factor of a point to a square: 4 × the corner rectangle)
        let a = half / d;
        let f = 4.0 / (2.0 * std::f64::consts::PI)
            * (a / (1.0 + a * a).sqrt() * (a / (1.0 + a * a).sqrt()).atan()
                + a / (1.0 + a * a).sqrt() * (a / (1.0 + a * a).sqrt()).atan());
        let exact = std::f64::consts::PI * l * f;
        assert!((e[0] - exact).abs() < 0.02 * exact, "{} vs {exact}", e[0]);
        // a point facing away receives nothing
        let back = gather(&[(DVec3::ZERO, -DVec3::Z)], &ps)[0];
        assert_eq!(back.irradiance, [0.0; 3]);
        assert_eq!(back.projected, 0.0);
        // it hides the sky it covers: π f of the projected solid angle,
        // and an isotropic sky's order-0 term by the same part
        assert!((g.projected - std::f64::consts::PI * f).abs() < 0.02 * g.projected);
        let y0 = sh::basis(DVec3::Z)[0];
        assert!((g.covered[0] - y0 * g.projected).abs() < 1e-9);
    }
}
