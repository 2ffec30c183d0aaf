//! `EnvironmentMap`: the light around the scene, as an equirectangular
//! linear-RGB image (3d-editing §IV.A: "When using the environment map as the
//! light source, virtual point lights (VPLs) are assigned into the
//! environment map as the primary light sources").
//!
//! There is no environment-map value type: an environment map is a
//! [`ColorImage`] in linear radiance with the **direction convention** below,
//! which every node of the relighting chain (`VplSample`, `Relight`) assumes.
//!
//! # Direction convention (camera frame: `x` right, `y` down, `z` forward)
//!
//! Pixel `(x, y)` of a `W x H` map looks in the direction with
//!
//! - elevation `e = 90° - 180° (y + 0.5) / H` above the horizontal plane
//!   (up is `-y`): row 0 is the zenith, the last row the nadir;
//! - azimuth `a = 360° (x + 0.5) / W - 180°`,
//!
//! and direction [`direction(e, a)`](direction) `= (cos e sin a, -sin e, -cos e cos a)`,
//! the same as the SyntheticScene sun ([`sun_direction`]): azimuth 0 (the
//! centre column) looks **behind** the camera (`-z`), positive azimuths turn
//! towards the camera's right (`+x`), and the left/right edges (`±180°`)
//! look forward (`+z`, what the camera sees). A sun at the same
//! `(elevation, azimuth)` as a SyntheticScene's lights the scene the same way.
//!
//! Pixel `(x, y)` covers the solid angle
//! `ΔΩ = (2π / W) (π / H) sin θ` with `θ = π (y + 0.5) / H` the polar angle
//! from the zenith (the `sin θ` per row that importance sampling weighs by).
//!
//! # The generated sky
//!
//! Without a file the node makes the project's own sample sky: a uniform
//! `sky_color` above the horizon, a uniform `ground_color` below it, and a
//! sun disc of angular diameter `sun_size_deg` and radiance `sun_radiance`.
//! The sun's energy is kept exactly: the map's integral over the disc,
//! `Σ L ΔΩ`, equals `sun_radiance * Ω_sun` with
//! `Ω_sun = 2π (1 - cos(sun_size / 2))`, also when the disc is smaller than
//! a pixel (then it lands in the pixel holding the sun's direction). A
//! surface facing the sun receives an irradiance of `sun_radiance * Ω_sun`
//! from it; a horizontal surface receives `π * sky` from a uniform sky.
//!
//! Then `yaw_deg` turns the map about the vertical axis (a light at azimuth
//! `a` moves to `a + yaw`, linear interpolation across columns) and the
//! radiance is multiplied by `2^exposure_ev`.

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use glam::DVec3;

pub use crate::sim::synthetic::sun_direction;

node_params! {
    /// Parameters of `EnvironmentMap`.
    pub struct EnvMapParams {
        /// Equirectangular HDR/EXR (or any LoadColor format, linear) file; empty = the generated sky.
        pub path: String = "", ParamKind::InputPath;
        /// Width of the generated map in pixels (ignored for a file).
        pub width: usize = 256usize, ParamKind::Int { min: 2, max: 8192 };
        /// Height of the generated map in pixels (ignored for a file).
        pub height: usize = 128usize, ParamKind::Int { min: 1, max: 4096 };
        /// Sun elevation above the horizon, degrees (as SyntheticScene).
        pub sun_elevation_deg: f64 = 50.0, ParamKind::Float { min: -90.0, max: 90.0 };
        /// Sun azimuth, degrees: 0 = behind the camera, positive = towards its right (as SyntheticScene).
        pub sun_azimuth_deg: f64 = -35.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Angular diameter of the sun disc, degrees (the real sun: 0.53).
        pub sun_size_deg: f64 = 2.0, ParamKind::Float { min: 0.01, max: 90.0 };
        /// Radiance of the sun disc (linear, all channels); its irradiance is this times the disc's solid angle.
        pub sun_radiance: f64 = 2300.0, ParamKind::Float { min: 0.0, max: 1e9 };
        /// Radiance of the sky above the horizon (linear RGB).
        pub sky_color: [f64; 3] = [0.06, 0.07, 0.085], ParamKind::Vec3 { min: 0.0, max: 1e6 };
        /// Radiance below the horizon (linear RGB).
        pub ground_color: [f64; 3] = [0.03, 0.025, 0.02], ParamKind::Vec3 { min: 0.0, max: 1e6 };
        /// Turn the map about the vertical axis, degrees (a light at azimuth a moves to a + yaw).
        pub yaw_deg: f64 = 0.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Multiply the radiance by 2^exposure_ev.
        pub exposure_ev: f64 = 0.0, ParamKind::Float { min: -30.0, max: 30.0 };
    }
}

/// Unit direction (camera frame) for elevation `e` and azimuth `a` in radians
/// (see the module docs; [`sun_direction`] in degrees).
#[inline]
pub fn direction(e: f64, a: f64) -> DVec3 {
    let (se, ce) = e.sin_cos();
    let (sa, ca) = a.sin_cos();
    DVec3::new(ce * sa, -se, -ce * ca)
}

/// Direction of the continuous map coordinate `(u, v)` (pixel units, centres
/// at integer + 0.5) of a `w x h` map. Callers guarantee `w, h >= 1`.
#[inline]
pub fn pixel_direction(u: f64, v: f64, w: usize, h: usize) -> DVec3 {
    let e = 0.5 * PI - PI * v / h as f64;
    let a = 2.0 * PI * u / w as f64 - PI;
    direction(e, a)
}

/// Continuous map coordinate `(u, v)` of a direction (need not be unit;
/// the zero vector maps to the zenith).
#[inline]
pub fn direction_to_pixel(d: DVec3, w: usize, h: usize) -> (f64, f64) {
    let d = d.normalize_or_zero();
    let e = (-d.y).clamp(-1.0, 1.0).asin();
    // a from sin a = x / cos e, cos a = -z / cos e (atan2 needs no division)
    let a = d.x.atan2(-d.z);
    let u = (a + PI) / (2.0 * PI) * w as f64;
    let v = (0.5 * PI - e) / PI * h as f64;
    (u.rem_euclid(w as f64), v.clamp(0.0, h as f64))
}

/// Solid angle of one pixel of row `y` of a `w x h` map (module docs).
#[inline]
pub fn pixel_solid_angle(y: usize, w: usize, h: usize) -> f64 {
    let theta = PI * (y as f64 + 0.5) / h as f64;
    (2.0 * PI / w as f64) * (PI / h as f64) * theta.sin()
}

/// The generated sample sky (module docs), `w x h`, before yaw and exposure.
pub fn sample_sky(p: &EnvMapParams) -> Result<ColorImage, NodeError> {
    let (w, h) = (p.width, p.height);
    if w < 2 || h < 1 {
        return Err(NodeError::param(
            "width",
            format!("map is {w}x{h}; need at least 2x1"),
        ));
    }
    let sky = p.sky_color.map(|c| c as f32);
    let ground = p.ground_color.map(|c| c as f32);
    let mut map = Image::from_fn(w, h, |_, y| {
        // horizon at v = h / 2: rows whose centre is above it are sky
        if (y as f64 + 0.5) < 0.5 * h as f64 {
            sky
        } else {
            ground
        }
    });
    let sun = sun_direction(p.sun_elevation_deg, p.sun_azimuth_deg);
    let half = (0.5 * p.sun_size_deg).to_radians();
    let cos_half = half.cos();
    let omega_sun = 2.0 * PI * (1.0 - cos_half);
    let energy = p.sun_radiance * omega_sun;
    if energy <= 0.0 {
        return Ok(map);
    }
    // Coverage of each pixel near the sun by 8x8 sub-samples.
    const SS: usize = 8;
    let mut cover: Vec<(usize, f64)> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            // quick reject: the pixel centre further than half + 2 pixel diagonals
            let c = pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h);
            let pix = 2.0 * PI / w as f64 + PI / h as f64;
            if c.dot(sun) < (half + 2.0 * pix).min(PI).cos() {
                continue;
            }
            let mut n = 0usize;
            for j in 0..SS {
                for i in 0..SS {
                    let u = x as f64 + (i as f64 + 0.5) / SS as f64;
                    let v = y as f64 + (j as f64 + 0.5) / SS as f64;
                    if pixel_direction(u, v, w, h).dot(sun) >= cos_half {
                        n += 1;
                    }
                }
            }
            if n > 0 {
                cover.push((y * w + x, n as f64 / (SS * SS) as f64));
            }
        }
    }
    if cover.is_empty() {
        // the disc is smaller than the sub-sample spacing: one pixel holds it
        let (u, v) = direction_to_pixel(sun, w, h);
        let x = (u.floor() as usize).min(w - 1);
        let y = (v.floor() as usize).min(h - 1);
        cover.push((y * w + x, 1.0));
    }
    // Renormalise so that Σ L ΔΩ over the disc is exactly `energy`.
    let covered: f64 = cover
        .iter()
        .map(|&(i, f)| f * pixel_solid_angle(i / w, w, h))
        .sum();
    // guard: every pixel has ΔΩ > 0 (sin θ > 0 at row centres) and f > 0
    let scale = energy / covered.max(f64::MIN_POSITIVE);
    let data = map.as_mut_slice();
    for (i, f) in cover {
        let add = (f * scale) as f32;
        for c in &mut data[i] {
            *c = (1.0 - f as f32) * *c + add;
        }
    }
    Ok(map)
}

/// Turns the map about the vertical axis by `yaw_deg` (a light at azimuth
/// `a` moves to `a + yaw`) with linear interpolation across columns, and
/// multiplies it by `2^exposure_ev`. Non-finite and negative radiances
/// become 0 (a light source cannot be negative).
pub fn rotate_and_expose(map: &ColorImage, yaw_deg: f64, exposure_ev: f64) -> ColorImage {
    let (w, h) = map.dims();
    let gain = 2f64.powf(exposure_ev) as f32;
    let shift = yaw_deg / 360.0 * w as f64;
    let clean = |v: f32| {
        if v.is_finite() && v > 0.0 {
            v * gain
        } else {
            0.0
        }
    };
    if shift.rem_euclid(w.max(1) as f64) == 0.0 {
        return map.map(|p| p.map(clean));
    }
    Image::from_fn(w, h, |x, y| {
        let src = (x as f64 - shift).rem_euclid(w as f64);
        let x0 = src.floor() as usize % w;
        let x1 = (x0 + 1) % w;
        let t = (src - src.floor()) as f32;
        let (a, b) = (map.get(x0, y), map.get(x1, y));
        let px: Rgb = std::array::from_fn(|c| clean((1.0 - t) * a[c] + t * b[c]));
        px
    })
}

/// The environment map the parameters describe: the file (linear) or the
/// generated sky, then yaw and exposure.
pub fn environment_map(p: &EnvMapParams) -> Result<ColorImage, NodeError> {
    let base = if p.path.is_empty() {
        sample_sky(p)?
    } else {
        crate::io::load_color(Path::new(&p.path), crate::io::ColorSpace::Linear)?
    };
    Ok(rotate_and_expose(&base, p.yaw_deg, p.exposure_ev))
}

depthgraph_graph::ports! {
    /// Outputs of `EnvironmentMap`.
    outputs struct EnvMapOut {
        /// equirectangular linear radiance (see the envmap module docs for directions)
        map: ColorImage,
    }
}

fn eval(_: &EvalCtx, _: NoInputs, p: &EnvMapParams) -> Result<Produced<EnvMapOut>, NodeError> {
    Ok(EnvMapOut {
        map: environment_map(p)?,
    }
    .into())
}

/// Registers `EnvironmentMap`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(
        PortedNode::new(
            "EnvironmentMap",
            1,
            "An equirectangular environment map in linear radiance: loaded (EXR/HDR) or the generated sample sky \
             with a sun (3d-editing §IV.A, the light source of the VPLs).\nRow 0 is the zenith; the centre column \
             looks behind the camera (-z), azimuth grows towards +x (the SyntheticScene sun convention).",
            eval,
        )
        .reads(|p: &EnvMapParams| {
            if p.path.is_empty() {
                Vec::new()
            } else {
                vec![PathBuf::from(&p.path)]
            }
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_round_trip_and_match_the_sun_convention() {
        let (w, h) = (64, 32);
        for (y, x) in [(0usize, 0usize), (5, 17), (16, 32), (31, 63)] {
            let d = pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h);
            assert!((d.length() - 1.0).abs() < 1e-12);
            let (u, v) = direction_to_pixel(d, w, h);
            assert!((u - x as f64 - 0.5).abs() < 1e-9 && (v - y as f64 - 0.5).abs() < 1e-9);
        }
        // row 0 looks up (-y), the centre column behind the camera (-z), the edge forward
        assert!(pixel_direction(32.0, 0.0, w, h).y < -0.999);
        assert!(pixel_direction(32.0, 16.0, w, h).z < -0.999);
        assert!(pixel_direction(0.0, 16.0, w, h).z > 0.999);
        assert!(pixel_direction(48.0, 16.0, w, h).x > 0.999);
        let s = sun_direction(35.0, 40.0);
        let d = direction(35f64.to_radians(), 40f64.to_radians());
        assert!((s - d).length() < 1e-12);
        // solid angles sum to 4π
        let total: f64 = (0..h).map(|y| w as f64 * pixel_solid_angle(y, w, h)).sum();
        assert!((total - 4.0 * PI).abs() < 0.02, "{total}");
    }

    #[test]
    fn the_sun_energy_is_exact_and_at_its_direction() {
        for size in [0.05, 2.0, 20.0] {
            let p = EnvMapParams {
                sun_size_deg: size,
                sky_color: [0.0; 3],
                ground_color: [0.0; 3],
                sun_radiance: 1000.0,
                ..Default::default()
            };
            let m = sample_sky(&p).unwrap();
            let (w, h) = m.dims();
            let (mut e, mut best, mut arg) = (0.0f64, 0.0f32, (0, 0));
            for y in 0..h {
                for x in 0..w {
                    let v = m.get(x, y)[0];
                    e += v as f64 * pixel_solid_angle(y, w, h);
                    if v > best {
                        best = v;
                        arg = (x, y);
                    }
                }
            }
            let want = 1000.0 * 2.0 * PI * (1.0 - (0.5 * size).to_radians().cos());
            assert!((e - want).abs() < 1e-4 * want, "size {size}: {e} vs {want}");
            let d = pixel_direction(arg.0 as f64 + 0.5, arg.1 as f64 + 0.5, w, h);
            let s = sun_direction(p.sun_elevation_deg, p.sun_azimuth_deg);
            assert!(d.dot(s) > (3f64 + size).to_radians().cos(), "size {size}");
        }
    }

    #[test]
    fn yaw_moves_the_sun_and_exposure_scales() {
        let p = EnvMapParams {
            sun_size_deg: 0.05,
            sun_azimuth_deg: 0.0,
            ..Default::default()
        };
        let m = sample_sky(&p).unwrap();
        let r = rotate_and_expose(&m, 90.0, 1.0);
        let (w, h) = m.dims();
        let argmax = |img: &ColorImage| {
            (0..w * h)
                .max_by(|&a, &b| img.as_slice()[a][0].total_cmp(&img.as_slice()[b][0]))
                .unwrap_or(0)
        };
        let (i0, i1) = (argmax(&m), argmax(&r));
        assert_eq!(i1 / w, i0 / w);
        assert_eq!((i1 % w + w - i0 % w) % w, w / 4);
        assert_eq!(r.get(0, h - 1)[0], 2.0 * m.get(0, h - 1)[0]);
        // full turn = identity
        assert_eq!(rotate_and_expose(&m, 360.0, 0.0), m);
        // negative / NaN radiance is cleaned to 0
        let bad = Image::from_vec(2, 1, vec![[f32::NAN, -1.0, 2.0], [1.0; 3]]).unwrap();
        assert_eq!(
            rotate_and_expose(&bad, 0.0, 0.0).get(0, 0),
            &[0.0, 0.0, 2.0]
        );
    }

    #[test]
    fn a_missing_file_names_the_path() {
        let p = EnvMapParams {
            path: "/nonexistent/sky.exr".into(),
            ..Default::default()
        };
        let e = environment_map(&p).unwrap_err();
        assert!(e.to_string().contains("sky.exr"), "{e}");
    }
}
