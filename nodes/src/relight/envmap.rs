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
//!
//! # A tilted camera
//!
//! The map is captured level (row 0 against gravity); a photo's camera is
//! often pitched and rolled. `pitch_deg` and `roll_deg` give its
//! orientation (e.g. from the camera's gravity reading) and the map is
//! resampled into the camera's frame ([`orient`]), so a level map lights a
//! tilted photo correctly: a sun at elevation `e` behind a camera looking
//! up by `p` sits at elevation `e + p` in the camera's frame.

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use glam::{DMat3, DVec3};

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
        /// The photo's camera pitch, degrees (positive = looking up): the level map is turned into the camera's frame.
        pub pitch_deg: f64 = 0.0, ParamKind::Float { min: -90.0, max: 90.0 };
        /// The photo's camera roll about its view axis, degrees (positive = its right side down).
        pub roll_deg: f64 = 0.0, ParamKind::Float { min: -180.0, max: 180.0 };
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
        // horizon at v = h / 2: each row takes sky and ground by the share
        // of its height above and below it (whole rows for an even h; the
        // middle row of an odd h is half of each, so a 1-row map is not
        // all ground)
        let above = (0.5 * h as f64 - y as f64).clamp(0.0, 1.0) as f32;
        std::array::from_fn(|ch| above * sky[ch] + (1.0 - above) * ground[ch])
    });
    let sun = sun_direction(p.sun_elevation_deg, p.sun_azimuth_deg);
    let omega = sun_solid_angle(p.sun_size_deg);
    let energy = p.sun_radiance * omega;
    paint_sun(&mut map, sun, p.sun_size_deg, [energy; 3], SunBlend::Cover);
    Ok(map)
}

/// Solid angle (sr) of a sun disc of angular diameter `size_deg`:
/// `2π (1 - cos(size / 2))`.
pub fn sun_solid_angle(size_deg: f64) -> f64 {
    2.0 * PI * (1.0 - (0.5 * size_deg).to_radians().cos())
}

/// How [`paint_sun`] combines the disc with what the map holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SunBlend {
    /// The disc covers the sky behind it (a pixel partly covered keeps the
    /// rest of its sky).
    Cover,
    /// The disc's radiance is added to the map's.
    Add,
}

/// Paints a sun disc of angular diameter `size_deg` towards `sun` (unit,
/// camera frame) into `map` so that the map's integral over the disc,
/// `Σ L ΔΩ`, is exactly `irradiance` per channel (what a surface facing the
/// sun receives from it), also when the disc is smaller than a pixel (then
/// it lands in the pixel holding the sun's direction). Pixels near the
/// disc's edge are weighted by their coverage (8x8 sub-samples).
pub fn paint_sun(
    map: &mut ColorImage,
    sun: DVec3,
    size_deg: f64,
    irradiance: [f64; 3],
    blend: SunBlend,
) {
    let (w, h) = map.dims();
    if w == 0 || h == 0 || irradiance.iter().all(|e| *e <= 0.0) {
        return;
    }
    let half = (0.5 * size_deg).to_radians();
    let cos_half = half.cos();
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
    // Renormalise so that Σ L ΔΩ over the disc is exactly the irradiance.
    let covered: f64 = cover
        .iter()
        .map(|&(i, f)| f * pixel_solid_angle(i / w, w, h))
        .sum();
    // guard: every pixel has ΔΩ > 0 (sin θ > 0 at row centres) and f > 0
    let scale = irradiance.map(|e| e.max(0.0) / covered.max(f64::MIN_POSITIVE));
    let data = map.as_mut_slice();
    for (i, f) in cover {
        for (c, s) in data[i].iter_mut().zip(scale) {
            let add = (f * s) as f32;
            *c = match blend {
                SunBlend::Cover => (1.0 - f as f32) * *c + add,
                SunBlend::Add => *c + add,
            };
        }
    }
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

/// The camera-to-world rotation of a camera pitched by `pitch_deg`
/// (positive = looking up) and rolled by `roll_deg` about its view axis
/// (positive = its right side down), in the frame of the module docs
/// (`y` down): roll first, then pitch, `R = R_x(pitch) R_z(roll)`.
pub fn camera_to_world(pitch_deg: f64, roll_deg: f64) -> DMat3 {
    let (sp, cp) = pitch_deg.to_radians().sin_cos();
    let (sr, cr) = roll_deg.to_radians().sin_cos();
    let rx = DMat3::from_cols(
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::new(0.0, cp, sp),
        DVec3::new(0.0, -sp, cp),
    );
    let rz = DMat3::from_cols(
        DVec3::new(cr, sr, 0.0),
        DVec3::new(-sr, cr, 0.0),
        DVec3::new(0.0, 0.0, 1.0),
    );
    rx * rz
}

/// A level map (world frame: `-y` against gravity) seen from a camera
/// with the rotation `r` (camera to world): pixel `d` of the result holds
/// the map's radiance from `r d`, bilinear from 3x3 sub-samples per pixel,
/// then scaled per channel so that `Σ L ΔΩ` is the map's (the resampling
/// spreads a small sun over its neighbours but keeps its energy).
pub fn orient(map: &ColorImage, r: DMat3) -> ColorImage {
    let (w, h) = map.dims();
    if w == 0 || h == 0 {
        return map.clone();
    }
    let bilinear = |u: f64, v: f64| -> [f64; 3] {
        let (x, y) = (u - 0.5, (v - 0.5).clamp(0.0, (h - 1) as f64));
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let xi = |k: f64| ((x0 + k).rem_euclid(w as f64) as usize).min(w - 1);
        let yi = |k: f64| ((y0 + k) as usize).min(h - 1);
        let at = |xx: usize, yy: usize| map.get(xx, yy).map(f64::from);
        let (a, b, c, d) = (
            at(xi(0.0), yi(0.0)),
            at(xi(1.0), yi(0.0)),
            at(xi(0.0), yi(1.0)),
            at(xi(1.0), yi(1.0)),
        );
        std::array::from_fn(|ch| {
            (1.0 - fy) * ((1.0 - fx) * a[ch] + fx * b[ch]) + fy * ((1.0 - fx) * c[ch] + fx * d[ch])
        })
    };
    const SS: usize = 3;
    let out: Vec<[f64; 3]> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut acc = [0.0f64; 3];
            for j in 0..SS {
                for k in 0..SS {
                    let u = x as f64 + (k as f64 + 0.5) / SS as f64;
                    let v = y as f64 + (j as f64 + 0.5) / SS as f64;
                    let d = r * pixel_direction(u, v, w, h);
                    let (su, sv) = direction_to_pixel(d, w, h);
                    let l = bilinear(su, sv);
                    for ch in 0..3 {
                        acc[ch] += l[ch];
                    }
                }
            }
            acc.map(|a| a / (SS * SS) as f64)
        })
        .collect();
    let energy = |px: &mut dyn Iterator<Item = (usize, [f64; 3])>| {
        let mut e = [0.0f64; 3];
        for (i, l) in px {
            let d_omega = pixel_solid_angle(i / w, w, h);
            for ch in 0..3 {
                e[ch] += l[ch] * d_omega;
            }
        }
        e
    };
    let before = energy(
        &mut map
            .as_slice()
            .iter()
            .enumerate()
            .map(|(i, l)| (i, l.map(f64::from))),
    );
    let after = energy(&mut out.iter().copied().enumerate());
    // guard: scale only a channel that carries energy after resampling
    let scale: [f64; 3] = std::array::from_fn(|ch| {
        if after[ch] > 0.0 {
            before[ch] / after[ch]
        } else {
            1.0
        }
    });
    let px = out
        .iter()
        .map(|l| std::array::from_fn(|ch| (l[ch] * scale[ch]) as f32))
        .collect();
    Image::from_vec(w, h, px).unwrap_or_else(|_| map.clone())
}

/// The environment map the parameters describe: the file (linear) or the
/// generated sky, then yaw and exposure, then turned into the frame of a
/// pitched or rolled camera ([`orient`]).
pub fn environment_map(p: &EnvMapParams) -> Result<ColorImage, NodeError> {
    environment_map_with(p, &crate::io::Limits::default())
}

/// [`environment_map`] with the file's decoding limits (the node passes
/// its run's `--max-pixels`).
pub fn environment_map_with(
    p: &EnvMapParams,
    lim: &crate::io::Limits,
) -> Result<ColorImage, NodeError> {
    let base = if p.path.is_empty() {
        sample_sky(p)?
    } else {
        crate::io::load_color_with(Path::new(&p.path), crate::io::ColorSpace::Linear, lim)?
    };
    let map = rotate_and_expose(&base, p.yaw_deg, p.exposure_ev);
    if p.pitch_deg == 0.0 && p.roll_deg == 0.0 {
        return Ok(map);
    }
    Ok(orient(&map, camera_to_world(p.pitch_deg, p.roll_deg)))
}

depthgraph_graph::ports! {
    /// Outputs of `EnvironmentMap`.
    outputs struct EnvMapOut {
        /// equirectangular linear radiance (see the envmap module docs for directions)
        map: ColorImage,
    }
}

fn eval(ctx: &EvalCtx, _: NoInputs, p: &EnvMapParams) -> Result<Produced<EnvMapOut>, NodeError> {
    Ok(EnvMapOut {
        map: environment_map_with(p, &crate::io::Limits::of(ctx))?,
    }
    .into())
}

/// Registers `EnvironmentMap`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(
        PortedNode::new(
            "EnvironmentMap",
            2,
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

    /// The horizon row of an odd-height map is half sky, half ground (a
    /// 1-row map was all ground, its sky colour unused); even heights keep
    /// whole rows.
    #[test]
    fn the_horizon_row_of_an_odd_map_is_half_sky() {
        let at = |h: usize| {
            let p = EnvMapParams {
                width: 8,
                height: h,
                sky_color: [1.0, 0.5, 0.25],
                ground_color: [0.0, 0.25, 0.75],
                sun_radiance: 0.0,
                ..Default::default()
            };
            let m = sample_sky(&p).unwrap();
            (0..h).map(|y| m.get(3, y)[1]).collect::<Vec<f32>>()
        };
        assert_eq!(at(1), vec![0.375]);
        assert_eq!(at(3), vec![0.5, 0.375, 0.25]);
        assert_eq!(at(4), vec![0.5, 0.5, 0.25, 0.25]);
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

    /// A level map seen from a camera looking up by 20°: the sun behind
    /// it at elevation 30° sits at 50° in the camera's frame (within a
    /// pixel); a roll of 90° puts a sun straight above onto the camera's
    /// left; the energy is kept.
    #[test]
    fn a_pitched_camera_sees_the_sun_where_it_is() {
        let base = EnvMapParams {
            width: 360,
            height: 180,
            sun_size_deg: 1.0,
            sun_elevation_deg: 30.0,
            sun_azimuth_deg: 0.0,
            ..Default::default()
        };
        let argmax_dir = |img: &ColorImage| {
            let (w, h) = img.dims();
            let i = (0..w * h)
                .max_by(|&a, &b| img.as_slice()[a][0].total_cmp(&img.as_slice()[b][0]))
                .unwrap_or(0);
            pixel_direction((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, w, h)
        };
        let energy = |img: &ColorImage| {
            let (w, h) = img.dims();
            (0..w * h)
                .map(|i| f64::from(img.as_slice()[i][0]) * pixel_solid_angle(i / w, w, h))
                .sum::<f64>()
        };
        let level = environment_map(&base).unwrap();
        let pitched = environment_map(&EnvMapParams {
            pitch_deg: 20.0,
            ..base.clone()
        })
        .unwrap();
        let want = sun_direction(50.0, 0.0);
        let got = argmax_dir(&pitched);
        let err = got.dot(want).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(err < 1.5, "sun at {got}, want {want} ({err:.2}°)");
        // the level map is untouched by zero angles; not so the pitched one
        assert!(argmax_dir(&level).dot(sun_direction(30.0, 0.0)) > 0.9995);
        assert!(got.dot(sun_direction(30.0, 0.0)) < 0.99);
        let (e0, e1) = (energy(&level), energy(&pitched));
        assert!((e1 - e0).abs() < 1e-4 * e0, "{e0} vs {e1}");
        // roll 90° (right side down): the zenith goes to the camera's left (-x)
        let rolled = environment_map(&EnvMapParams {
            sun_elevation_deg: 90.0,
            roll_deg: 90.0,
            ..base.clone()
        })
        .unwrap();
        let d = argmax_dir(&rolled);
        assert!(d.x < -0.99, "{d}");
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

    #[test]
    fn a_map_file_beyond_the_runs_pixel_limit_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sky.png");
        image::RgbImage::from_pixel(64, 32, image::Rgb([200, 180, 160]))
            .save(&path)
            .unwrap();
        let p = EnvMapParams {
            path: path.to_string_lossy().into_owned(),
            ..Default::default()
        };
        let small = crate::io::Limits { max_pixels: 1000 };
        let e = environment_map_with(&p, &small).unwrap_err();
        assert!(
            e.to_string().contains("64x32") && e.to_string().contains("1000 pixels"),
            "{e}"
        );
        let ok = environment_map_with(&p, &crate::io::Limits { max_pixels: 2048 }).unwrap();
        assert_eq!(ok.dims(), (64, 32));
    }
}
