//! A Monte-Carlo path tracer: the **physical** ground truth of relighting.
//!
//! It renders the analytic scenes of [`crate::sim::synthetic`] (planes,
//! boxes, spheres, cylinders; their textures as diffuse albedo) lit **only**
//! by an equirectangular environment map in the convention of
//! [`crate::relight::envmap`]; the scene's own sun and ambient terms are
//! ignored, every object blocks light and every surface is Lambertian. It
//! solves the rendering equation
//! `L(x, ωo) = ∫ ρ(x)/π L(x', -ωi) cos θi dωi` (Kajiya 1986) with
//! `bounces` diffuse interreflections, so a floor lit by the sun lights the
//! underside of an object above it, and a shadow keeps the light the scene
//! bounces into it: everything the relighting model only approximates.
//!
//! # Estimator
//!
//! One ray through each pixel centre (no antialiasing: the object's
//! coverage is exactly that of a depth map rendered with the same ray),
//! `samples` paths per pixel. At every diffuse vertex, next-event
//! estimation draws a direction from the map (pixel chosen with probability
//! `∝ mean(L) ΔΩ`, uniform inside it; the pdf in solid angle is
//! `mean(L_pixel) / Σ mean(L) ΔΩ`) and casts a shadow ray; the path
//! continues in a cosine-distributed direction (`pdf = cos/π`, throughput
//! `× ρ`) and, when it escapes, adds the map's radiance. The two strategies
//! are combined with the power heuristic (Veach 1997), so a small bright
//! sun and a broad sky are both sampled well. Paths stop after `bounces`
//! interreflections (no Russian roulette: the estimate of the truncated sum
//! is unbiased and its truncation is documented by the count).
//!
//! Sums are in f64. The map's `ΔΩ` is the exact solid angle of a pixel
//! ([`band_solid_angle`]); the VPL sampler's midpoint rule
//! ([`pixel_solid_angle`]) differs from it by less than `(π/h)²/24`
//! relative, so the map carries the same energy here as in
//! [`crate::relight::vpl`] to 0.1 % at `h >= 32`.
//!
//! Each pixel draws from its own generator
//! ([`SplitMix64::for_pixel`]): the image does not depend on the thread
//! count, and two seeds give independent estimates (the convergence check of
//! [`display_psnr`](crate::kit::color::psnr_of_mse) between them).

use std::f64::consts::PI;

use depthgraph_graph::prelude::*;
use glam::DVec3;
use rayon::prelude::*;

use crate::kit::rng::SplitMix64;
#[cfg(doc)]
use crate::relight::envmap::pixel_solid_angle;
use crate::relight::envmap::{direction_to_pixel, pixel_direction};
use crate::sim::synthetic::Scene;

/// Parameters of [`path_trace`].
#[derive(Debug, Clone, PartialEq)]
pub struct PathTraceParams {
    /// Paths per pixel.
    pub samples: usize,
    /// Diffuse interreflections after the first hit (3 or more for the
    /// relighting truth: sun → floor → object → camera is two).
    pub bounces: usize,
    /// Seed of every pixel's generator.
    pub seed: u64,
}

impl Default for PathTraceParams {
    fn default() -> Self {
        Self {
            samples: 64,
            bounces: 4,
            seed: 1,
        }
    }
}

/// Surfaces start their rays this far (metres) off along their normal.
const RAY_OFFSET_M: f64 = 1e-6;

/// The exact solid angle of a pixel of row `y` of a `w x h` map:
/// `(2π / w) (cos θ0 - cos θ1)` over its band of polar angles (within
/// `(π/h)²/24` of [`pixel_solid_angle`], the VPL sampler's midpoint rule).
pub fn band_solid_angle(y: usize, w: usize, h: usize) -> f64 {
    let (t0, t1) = (PI * y as f64 / h as f64, PI * (y + 1) as f64 / h as f64);
    2.0 * PI / w as f64 * (t0.cos() - t1.cos())
}

/// The environment map as a light to sample: a 2-D CDF over its pixels.
#[derive(Debug, Clone)]
pub struct EnvLight {
    w: usize,
    h: usize,
    radiance: Vec<[f64; 3]>,
    /// Per row, the cumulative `mean(L) ΔΩ` of its pixels.
    col_cdf: Vec<f64>,
    row_cdf: Vec<f64>,
    total: f64,
}

/// The sampling weight of a radiance: its mean over channels (positive
/// whenever one channel is; non-finite and negative values count as 0).
fn weight(l: [f64; 3]) -> f64 {
    l.iter().sum::<f64>() / 3.0
}

impl EnvLight {
    /// The light of `map` (module docs of [`crate::relight::envmap`]).
    /// Errors when the map is empty or a value is negative or not finite.
    pub fn new(map: &ColorImage) -> Result<Self, NodeError> {
        let (w, h) = map.dims();
        if w == 0 || h == 0 {
            return Err(NodeError::input("env", "an empty environment map"));
        }
        if let Some(v) = map
            .as_slice()
            .iter()
            .flatten()
            .find(|v| !(v.is_finite() && **v >= 0.0))
        {
            return Err(NodeError::input(
                "env",
                format!("radiance must be finite and >= 0, found {v}"),
            ));
        }
        let radiance: Vec<[f64; 3]> = map.as_slice().iter().map(|c| c.map(f64::from)).collect();
        let mut col_cdf = vec![0.0; w * h];
        let mut row_cdf = vec![0.0; h];
        let mut total = 0.0;
        for y in 0..h {
            let d_omega = band_solid_angle(y, w, h);
            let mut acc = 0.0;
            for x in 0..w {
                acc += weight(radiance[y * w + x]) * d_omega;
                col_cdf[y * w + x] = acc;
            }
            total += acc;
            row_cdf[y] = total;
        }
        Ok(Self {
            w,
            h,
            radiance,
            col_cdf,
            row_cdf,
            total,
        })
    }

    fn pixel_of(&self, d: DVec3) -> usize {
        let (u, v) = direction_to_pixel(d, self.w, self.h);
        let x = (u as usize).min(self.w - 1);
        let y = (v as usize).min(self.h - 1);
        y * self.w + x
    }

    /// Radiance arriving from direction `d` (towards the map), piecewise
    /// constant over the map's pixels.
    pub fn radiance(&self, d: DVec3) -> [f64; 3] {
        self.radiance[self.pixel_of(d)]
    }

    /// Solid-angle pdf of [`sample`](Self::sample) drawing `d`; 0 for a
    /// black map.
    pub fn pdf(&self, d: DVec3) -> f64 {
        // guard: total > 0 before dividing
        if self.total > 0.0 {
            weight(self.radiance[self.pixel_of(d)]) / self.total
        } else {
            0.0
        }
    }

    /// A direction drawn `∝ mean(L)` over the sphere from two uniform
    /// numbers, with its radiance and pdf; `None` for a black map.
    pub fn sample(&self, u1: f64, u2: f64, u3: f64, u4: f64) -> Option<(DVec3, [f64; 3], f64)> {
        if !(self.total > 0.0 && self.total.is_finite()) {
            return None;
        }
        let y = self
            .row_cdf
            .partition_point(|&c| c <= u1 * self.total)
            .min(self.h - 1);
        let row = &self.col_cdf[y * self.w..(y + 1) * self.w];
        let x = row
            .partition_point(|&c| c <= u2 * row[self.w - 1])
            .min(self.w - 1);
        let l = self.radiance[y * self.w + x];
        let pdf = weight(l) / self.total;
        if pdf <= 0.0 {
            return None;
        }
        // uniform in solid angle inside the pixel: cos θ uniform over its band
        let (c0, c1) = (
            (PI * y as f64 / self.h as f64).cos(),
            (PI * (y + 1) as f64 / self.h as f64).cos(),
        );
        let theta = (c0 + u4 * (c1 - c0)).clamp(-1.0, 1.0).acos();
        let d = pixel_direction(x as f64 + u3, theta / PI * self.h as f64, self.w, self.h);
        Some((d, l, pdf))
    }
}

/// A unit direction around `n` with pdf `cos/π` from two uniform numbers.
fn cosine_direction(n: DVec3, u1: f64, u2: f64) -> DVec3 {
    let (t, b) = n.any_orthonormal_pair();
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let z = (1.0 - u1).max(0.0).sqrt();
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * z).normalize()
}

/// The power heuristic's weight of a strategy with pdf `a` against `b`.
fn power(a: f64, b: f64) -> f64 {
    let (a2, b2) = (a * a, b * b);
    // guard: a2 + b2 > 0 unless both are 0 (then the sample has no weight)
    if a2 + b2 > 0.0 { a2 / (a2 + b2) } else { 0.0 }
}

/// Radiance along the camera ray `dir` from the origin (module docs).
fn trace(
    scene: &Scene,
    env: &EnvLight,
    dir: DVec3,
    bounces: usize,
    rng: &mut SplitMix64,
) -> [f64; 3] {
    let mut l = [0.0f64; 3];
    let mut thr = [1.0f64; 3];
    let (mut o, mut d) = (DVec3::ZERO, dir);
    // pdf of the direction just taken by the BSDF (None for the camera ray)
    let mut bsdf_pdf: Option<f64> = None;
    for depth in 0..=bounces {
        let Some(hit) = scene.intersect(o, d) else {
            let le = env.radiance(d.normalize_or_zero());
            let w = bsdf_pdf.map_or(1.0, |pb| power(pb, env.pdf(d.normalize_or_zero())));
            for ch in 0..3 {
                l[ch] += thr[ch] * le[ch] * w;
            }
            break;
        };
        for ch in 0..3 {
            l[ch] += thr[ch] * f64::from(hit.emission[ch]);
        }
        if depth == bounces {
            break;
        }
        let n = hit.normal;
        let x = hit.point + n * RAY_OFFSET_M;
        let rho = hit.albedo.map(|a| f64::from(a.max(0.0)));
        // next event: a direction from the map
        let (u1, u2, u3, u4) = (
            rng.next_f64(),
            rng.next_f64(),
            rng.next_f64(),
            rng.next_f64(),
        );
        if let Some((wi, le, pl)) = env.sample(u1, u2, u3, u4) {
            let cos = n.dot(wi);
            if cos > 0.0 && scene.intersect(x, wi).is_none() {
                // f cos / p_l with f = ρ/π; guard: pl > 0 (sample's contract)
                let wgt = power(pl, cos / PI) * cos / (PI * pl);
                for ch in 0..3 {
                    l[ch] += thr[ch] * rho[ch] * le[ch] * wgt;
                }
            }
        }
        // continue: cosine sampling, f cos / pdf = ρ
        let wi = cosine_direction(n, rng.next_f64(), rng.next_f64());
        bsdf_pdf = Some(n.dot(wi).max(0.0) / PI);
        for ch in 0..3 {
            thr[ch] *= rho[ch];
        }
        if thr.iter().all(|t| *t <= 0.0) {
            break;
        }
        o = x;
        d = wi;
    }
    l
}

/// Path-traces `scene` (its camera, its objects as diffuse surfaces) lit
/// by `env` alone (module docs): linear radiance per pixel.
pub fn path_trace(scene: &Scene, env: &EnvLight, p: &PathTraceParams) -> ColorImage {
    let k = scene.camera;
    let (w, h) = (k.width, k.height);
    let spp = p.samples.max(1);
    let sane = k.is_sane();
    let px: Vec<[f32; 3]> = (0..w * h)
        .into_par_iter()
        .with_min_len(64)
        .map(|i| {
            if !sane {
                return [0.0; 3];
            }
            let (x, y) = (i % w, i / w);
            // guard: sane intrinsics have fx, fy > 0
            let dir = DVec3::new(
                (x as f64 + 0.5 - k.cx) / k.fx,
                (y as f64 + 0.5 - k.cy) / k.fy,
                1.0,
            );
            let mut rng = SplitMix64::for_pixel(p.seed, 0x9A7B, x as u64, y as u64);
            let mut acc = [0.0f64; 3];
            for _ in 0..spp {
                let l = trace(scene, env, dir, p.bounces, &mut rng);
                for ch in 0..3 {
                    acc[ch] += l[ch];
                }
            }
            // guard: spp >= 1
            acc.map(|a| (a / spp as f64) as f32)
        })
        .collect();
    Image::from_vec(w, h, px).unwrap_or_else(|_| Image::filled(w, h, [0.0; 3]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::synthetic::{Object, Primitive, Texture, kinect_like_intrinsics};

    fn floor_only(w: usize, h: usize, albedo: [f32; 3]) -> Scene {
        Scene {
            objects: vec![Object {
                id: 1,
                primitive: Primitive::Plane {
                    point: DVec3::new(0.0, 0.4, 0.0),
                    normal: DVec3::new(0.0, -1.0, 0.0),
                },
                albedo: Texture::Solid(albedo),
                emission: [0.0; 3],
                casts_shadow: true,
                texture_origin: DVec3::ZERO,
            }],
            light: crate::sim::synthetic::Scene::of(
                crate::sim::synthetic::ScenePreset::Tabletop,
                1,
                1,
            )
            .light,
            camera: kinect_like_intrinsics(w, h),
        }
    }

    /// A floor under a uniform sky of radiance `L` receives `π L` and
    /// shows `ρ L`; under a sky plus a sun it shows
    /// `ρ (L + E_sun cos / π)` (the analytic values, within the noise).
    #[test]
    fn a_floor_under_a_uniform_sky_and_a_sun_has_its_analytic_radiance() {
        let (w, h) = (24, 18);
        let rho = [0.5f32, 0.25, 0.8];
        let scene = floor_only(w, h, rho);
        let sky = ColorImage::filled(64, 32, [0.3f32, 0.3, 0.3]);
        let env = EnvLight::new(&sky).unwrap();
        let p = PathTraceParams {
            samples: 16,
            bounces: 3,
            seed: 3,
        };
        let img = path_trace(&scene, &env, &p);
        let (mut n, mut mean) = (0, [0.0f64; 3]);
        for y in 0..h {
            for x in 0..w {
                let c = *img.get(x, y);
                if y as f64 + 0.5 > h as f64 / 2.0 + 1.0 {
                    // floor: ρ L, each pixel within its noise
                    for ch in 0..3 {
                        let want = rho[ch] * 0.3;
                        assert!((c[ch] - want).abs() < 0.2 * want, "{c:?} vs {want}");
                        mean[ch] += f64::from(c[ch]);
                    }
                    n += 1;
                } else if (y as f64 + 0.5) < h as f64 / 2.0 - 1.0 {
                    assert!((c[0] - 0.3).abs() < 1e-6, "sky seen directly: {c:?}");
                }
            }
        }
        assert!(n > 50);
        for ch in 0..3 {
            let (m, want) = (mean[ch] / n as f64, f64::from(rho[ch]) * 0.3);
            assert!((m - want).abs() < 0.01 * want, "mean {m} vs {want}");
        }
        // a sun from the generated sky: E = sun_radiance Ω_sun at elevation 60°
        let ep = crate::relight::envmap::EnvMapParams {
            sun_elevation_deg: 60.0,
            sun_azimuth_deg: 20.0,
            sky_color: [0.0; 3],
            ground_color: [0.0; 3],
            ..Default::default()
        };
        let map = crate::relight::envmap::environment_map(&ep).unwrap();
        let env = EnvLight::new(&map).unwrap();
        let img = path_trace(&scene, &env, &p);
        let omega = 2.0 * PI * (1.0 - (ep.sun_size_deg.to_radians() / 2.0).cos());
        let e = ep.sun_radiance * omega * 60f64.to_radians().sin();
        let c = *img.get(w / 2, h - 2);
        for ch in 0..3 {
            let want = f64::from(rho[ch]) * e / PI;
            let rel = (f64::from(c[ch]) - want).abs() / want;
            assert!(rel < 0.03, "channel {ch}: {} vs {want} ({rel:.4})", c[ch]);
        }
    }

    #[test]
    fn a_bad_map_is_an_error_and_a_black_one_renders_black() {
        let mut m = ColorImage::filled(8, 4, [0.1f32; 3]);
        m.as_mut_slice()[3] = [f32::NAN, 0.0, 0.0];
        assert!(
            EnvLight::new(&m)
                .unwrap_err()
                .to_string()
                .contains("finite")
        );
        let black = EnvLight::new(&ColorImage::filled(8, 4, [0.0f32; 3])).unwrap();
        let img = path_trace(
            &floor_only(8, 6, [0.5; 3]),
            &black,
            &PathTraceParams::default(),
        );
        assert!(img.as_slice().iter().flatten().all(|v| *v == 0.0));
    }
}
