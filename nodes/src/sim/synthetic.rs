//! `SyntheticScene`: an analytic, ray-cast scene with **exact** ground truth.
//!
//! The scene is made of planes, yawed boxes, spheres and vertical cylinders,
//! all given in the camera frame (`x` right, `y` down, `z` forward; the camera
//! sits at the origin looking along `+z`). One ray is cast through every pixel
//! centre, so depth, normals, albedo and object ids are exact there; the color
//! is a simple linear HDR shading:
//!
//! `color = albedo * (sun * max(0, n . l) * shadow + ambient) + emission`
//!
//! where `shadow` is 0 or 1 from one shadow ray towards the sun. Small bright
//! emitters (spheres with an emission) give the highlights that the depth-blur
//! paper's bokeh needs ("realistic depth blur", Sec. 4); the presets cover the
//! depth ranges and thin structures the editing and hole-filling stages of the
//! 3-D editing paper are exercised on.
//!
//! Everything here is deterministic: the same scene and options give the same
//! bits whatever the number of threads.

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::camera::lens::{Aperture, ApertureShape, LensEffects, ThinLens, effective_f_number};

depthgraph_graph::param_choice! {
    /// The built-in scenes (the `preset` parameter).
    pub enum ScenePreset {
        /// Objects on a table before a wall.
        Tabletop = "tabletop",
        /// A corridor receding from the camera.
        Corridor = "corridor",
        /// Thin structures in front of a far background.
        Thin = "thin",
    }
}

/// Radiance (brightest channel) of the preset emitters before
/// [`Scene::scale_emission`]; the default of the `emitter_radiance` parameter.
pub const DEFAULT_EMITTER_RADIANCE: f32 = 40.0;

/// Smallest ray parameter accepted as a hit (rejects self-intersections at
/// the ray origin).
const T_MIN: f64 = 1e-9;
/// Shadow rays start this far (metres) off the surface along its normal.
const SHADOW_OFFSET_M: f64 = 1e-6;
/// Ray direction components (or squared lengths) below this are treated as
/// zero: the guard of every division by a direction component.
const DIR_EPS: f64 = 1e-12;
/// Checker lattices are shifted by this fraction of a period, so surfaces at
/// round coordinates (a floor at `y = 0.4` with a 0.1 m checker) do not lie on
/// a cell boundary, where rounding would make the pattern flicker.
const LATTICE_SHIFT: f64 = 0.2371;
/// Rows rendered between two progress reports / cancellation checks.
const BAND_ROWS: usize = 16;

/// Surface reflectance as a function of the 3-D hit point (a solid texture).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Texture {
    /// One linear RGB albedo.
    Solid(Rgb),
    /// A 3-D checkerboard of cubes of side `period_m` metres alternating
    /// between `a` and `b`. A non-positive or non-finite period gives `a`.
    Checker {
        /// Linear RGB albedo of half of the cubes; also the whole texture when
        /// the period is not positive and finite.
        a: Rgb,
        /// Linear RGB albedo of the other half of the cubes.
        b: Rgb,
        /// Side of one cube in metres.
        period_m: f64,
    },
    /// A smooth pattern `a + (b - a) * s` with
    /// `s = 1/2 + (sin(kx) + sin(ky + 1.3) + sin(kz + 2.1)) / 6`,
    /// `k = 2 pi / period_m`. A non-positive or non-finite period gives `a`.
    Waves {
        /// Linear RGB albedo at `s = 0`; also the whole texture when the
        /// period is not positive and finite.
        a: Rgb,
        /// Linear RGB albedo at `s = 1`.
        b: Rgb,
        /// Period of each sine in metres.
        period_m: f64,
    },
}

impl Texture {
    /// Albedo at point `p` (camera frame, metres).
    pub fn eval(&self, p: DVec3) -> Rgb {
        match *self {
            Texture::Solid(c) => c,
            Texture::Checker { a, b, period_m } => {
                // Guard of the division by the period.
                if !(period_m.is_finite() && period_m > 0.0) {
                    return a;
                }
                let q = p / period_m + DVec3::splat(LATTICE_SHIFT);
                let parity = (q.x.floor() + q.y.floor() + q.z.floor()).rem_euclid(2.0);
                if parity < 0.5 { a } else { b }
            }
            Texture::Waves { a, b, period_m } => {
                // Guard of the division by the period.
                if !(period_m.is_finite() && period_m > 0.0) {
                    return a;
                }
                let k = std::f64::consts::TAU / period_m;
                let s =
                    0.5 + ((k * p.x).sin() + (k * p.y + 1.3).sin() + (k * p.z + 2.1).sin()) / 6.0;
                let s = s as f32;
                [
                    a[0] + (b[0] - a[0]) * s,
                    a[1] + (b[1] - a[1]) * s,
                    a[2] + (b[2] - a[2]) * s,
                ]
            }
        }
    }
}

/// The shape of an object, in the camera frame (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Primitive {
    /// Infinite plane through `point` with the given `normal` (any length; a
    /// zero normal makes the plane invisible). Planes are two-sided.
    Plane {
        /// Any point of the plane (metres).
        point: DVec3,
        /// Normal of the plane; it is normalised before use.
        normal: DVec3,
    },
    /// Box centred at `center` with `half_extents` (absolute values are used),
    /// turned by `yaw_rad` about the vertical (`y`) axis through its centre:
    /// a local point `(x, y, z)` is at `center + (x cos + z sin, y, -x sin + z cos)`.
    Box {
        /// Centre of the box (metres).
        center: DVec3,
        /// Half of the box's size along its local `x`, `y` and `z` axes
        /// (metres).
        half_extents: DVec3,
        /// Turn about the vertical axis through the centre, in radians.
        yaw_rad: f64,
    },
    /// Sphere; a non-positive radius makes it invisible.
    Sphere {
        /// Centre of the sphere (metres).
        center: DVec3,
        /// Radius in metres.
        radius: f64,
    },
    /// Closed vertical cylinder standing on `center_base` (the centre of its
    /// bottom disc) and rising `height` metres upwards, i.e. towards `-y`;
    /// non-positive radius or height make it invisible.
    Cylinder {
        /// Centre of the bottom disc (metres); its `y` is the largest `y` of
        /// the cylinder.
        center_base: DVec3,
        /// Radius in metres.
        radius: f64,
        /// Height in metres, measured from `center_base` towards `-y`.
        height: f64,
    },
}

/// True for a finite, strictly positive size.
fn positive(x: f64) -> bool {
    x.is_finite() && x > 0.0
}

/// Roots of `a t^2 + 2 b t + c = 0` in ascending order, computed in the
/// cancellation-free form; `None` without real roots. Requires `a > 0`.
fn quadratic(a: f64, b: f64, c: f64) -> Option<(f64, f64)> {
    let disc = b * b - a * c;
    if disc < 0.0 || a <= 0.0 {
        return None;
    }
    let q = -(b + b.signum() * disc.sqrt());
    // Guard: q == 0 only when b == 0 and disc == 0 (a ray grazing a surface at
    // its origin); treat as a miss.
    if q == 0.0 {
        return None;
    }
    let (t0, t1) = (q / a, c / q);
    Some(if t0 < t1 { (t0, t1) } else { (t1, t0) })
}

/// Rotates a camera-frame vector into a box's local frame (inverse yaw).
fn yaw_to_local(v: DVec3, yaw: f64) -> DVec3 {
    let (s, c) = yaw.sin_cos();
    DVec3::new(c * v.x - s * v.z, v.y, s * v.x + c * v.z)
}

/// Rotates a box-local vector into the camera frame.
fn yaw_to_world(v: DVec3, yaw: f64) -> DVec3 {
    let (s, c) = yaw.sin_cos();
    DVec3::new(c * v.x + s * v.z, v.y, -s * v.x + c * v.z)
}

/// Slab test of a ray against an axis-aligned box `[-h, h]`; returns the
/// first parameter above [`T_MIN`] and the outward unit normal there.
fn box_local_hit(o: DVec3, d: DVec3, h: DVec3) -> Option<(f64, DVec3)> {
    let mut t_near = f64::NEG_INFINITY;
    let mut t_far = f64::INFINITY;
    let mut n_near = DVec3::ZERO;
    let mut n_far = DVec3::ZERO;
    for axis in 0..3 {
        let (oa, da, ha) = (o[axis], d[axis], h[axis]);
        let mut e = DVec3::ZERO;
        e[axis] = 1.0;
        if da.abs() < DIR_EPS {
            // Parallel to this slab: inside it or a miss.
            if oa.abs() > ha {
                return None;
            }
            continue;
        }
        // Guard: |da| >= DIR_EPS.
        let t1 = (-ha - oa) / da;
        let t2 = (ha - oa) / da;
        let (ta, tb, sign) = if t1 < t2 {
            (t1, t2, -1.0)
        } else {
            (t2, t1, 1.0)
        };
        if ta > t_near {
            t_near = ta;
            n_near = e * sign;
        }
        if tb < t_far {
            t_far = tb;
            n_far = -e * sign;
        }
    }
    if t_near > t_far || !t_near.is_finite() || !t_far.is_finite() {
        return None;
    }
    if t_near > T_MIN {
        Some((t_near, n_near))
    } else if t_far > T_MIN {
        Some((t_far, n_far))
    } else {
        None
    }
}

impl Primitive {
    /// First intersection with parameter `t > T_MIN` along `o + t d`, with the
    /// outward unit normal there. `d` must be non-zero.
    fn hit(&self, o: DVec3, d: DVec3) -> Option<(f64, DVec3)> {
        match *self {
            Primitive::Plane { point, normal } => {
                let n = normal.normalize_or_zero();
                let denom = n.dot(d);
                // Guard of the division: a ray parallel to the plane misses it
                // (this also covers a zero normal).
                if denom.abs() < DIR_EPS {
                    return None;
                }
                let t = n.dot(point - o) / denom;
                (t > T_MIN && t.is_finite()).then_some((t, n))
            }
            Primitive::Sphere { center, radius } => {
                if !positive(radius) {
                    return None;
                }
                let oc = o - center;
                let (t0, t1) = quadratic(d.dot(d), oc.dot(d), oc.dot(oc) - radius * radius)?;
                let t = if t0 > T_MIN {
                    t0
                } else if t1 > T_MIN {
                    t1
                } else {
                    return None;
                };
                // Guard: radius > 0 (checked above).
                Some((t, (o + d * t - center) / radius))
            }
            Primitive::Box {
                center,
                half_extents,
                yaw_rad,
            } => {
                let h = half_extents.abs();
                if !h.is_finite() || !yaw_rad.is_finite() {
                    return None;
                }
                let lo = yaw_to_local(o - center, yaw_rad);
                let ld = yaw_to_local(d, yaw_rad);
                let (t, n) = box_local_hit(lo, ld, h)?;
                Some((t, yaw_to_world(n, yaw_rad)))
            }
            Primitive::Cylinder {
                center_base,
                radius,
                height,
            } => {
                if !positive(radius) || !positive(height) {
                    return None;
                }
                let top = center_base.y - height;
                let bottom = center_base.y;
                let ox = o.x - center_base.x;
                let oz = o.z - center_base.z;
                let mut best: Option<(f64, DVec3)> = None;
                let mut offer = |t: f64, n: DVec3| {
                    if t > T_MIN && t.is_finite() && best.is_none_or(|(bt, _)| t < bt) {
                        best = Some((t, n));
                    }
                };
                // Lateral surface.
                let a = d.x * d.x + d.z * d.z;
                let lateral = if a > DIR_EPS * DIR_EPS {
                    quadratic(a, ox * d.x + oz * d.z, ox * ox + oz * oz - radius * radius)
                } else {
                    None
                };
                if let Some((t0, t1)) = lateral {
                    for t in [t0, t1] {
                        let y = o.y + t * d.y;
                        if t > T_MIN && (top..=bottom).contains(&y) {
                            // Guard: radius > 0 (checked above).
                            let n =
                                DVec3::new((ox + t * d.x) / radius, 0.0, (oz + t * d.z) / radius);
                            offer(t, n);
                            break;
                        }
                    }
                }
                // Caps. Guard of the division: a ray parallel to the caps
                // cannot hit them.
                if d.y.abs() >= DIR_EPS {
                    for (y_cap, ny) in [(top, -1.0), (bottom, 1.0)] {
                        let t = (y_cap - o.y) / d.y;
                        let x = ox + t * d.x;
                        let z = oz + t * d.z;
                        if x * x + z * z <= radius * radius {
                            offer(t, DVec3::new(0.0, ny, 0.0));
                        }
                    }
                }
                best
            }
        }
    }

    /// Signed Euclidean distance from `p` to the surface (negative inside
    /// solids; for planes, positive on the side the normal points to).
    /// `f64::INFINITY` for a degenerate primitive (zero normal, non-positive
    /// size).
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        match *self {
            Primitive::Plane { point, normal } => {
                let n = normal.normalize_or_zero();
                if n == DVec3::ZERO {
                    return f64::INFINITY;
                }
                n.dot(p - point)
            }
            Primitive::Sphere { center, radius } => {
                if !positive(radius) {
                    return f64::INFINITY;
                }
                (p - center).length() - radius
            }
            Primitive::Box {
                center,
                half_extents,
                yaw_rad,
            } => {
                let q = yaw_to_local(p - center, yaw_rad).abs() - half_extents.abs();
                q.max(DVec3::ZERO).length() + q.max_element().min(0.0)
            }
            Primitive::Cylinder {
                center_base,
                radius,
                height,
            } => {
                if !positive(radius) || !positive(height) {
                    return f64::INFINITY;
                }
                let dx = p.x - center_base.x;
                let dz = p.z - center_base.z;
                let radial = (dx * dx + dz * dz).sqrt() - radius;
                let axial = (p.y - (center_base.y - 0.5 * height)).abs() - 0.5 * height;
                radial.max(axial).min(0.0) + radial.max(0.0).hypot(axial.max(0.0))
            }
        }
    }
}

/// One object of a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Object {
    /// Id written to the `ids` image; `>= 1` (0 means "nothing").
    pub id: u32,
    /// Geometry.
    pub primitive: Primitive,
    /// Reflectance.
    pub albedo: Texture,
    /// Emitted linear RGB radiance (`[0, 0, 0]` for ordinary surfaces).
    pub emission: Rgb,
    /// Whether the object blocks sunlight. Enclosing geometry (walls and
    /// ceilings of the corridor, which would otherwise shade everything since
    /// planes are infinite) sets this to `false`, like a skylight.
    pub casts_shadow: bool,
    /// Where the texture's origin is in the camera frame (0 for the presets;
    /// [`Scene::move_camera`] moves it with the object).
    pub texture_origin: DVec3,
}

/// Lighting: a directional sun with hard shadows and a constant ambient sky.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Unit vector from the scene towards the sun, camera frame
    /// (see [`sun_direction`]).
    pub sun_direction: DVec3,
    /// Radiance of the sun term (linear RGB).
    pub sun_radiance: Rgb,
    /// Ambient (sky) irradiance term, unshadowed.
    pub ambient: Rgb,
    /// Color of rays that hit nothing.
    pub background: Rgb,
}

/// Unit vector towards a sun at `elevation_deg` above the horizontal plane
/// (up is `-y`) and `azimuth_deg` about the vertical axis: azimuth 0 puts the
/// sun behind the camera (light travelling along `+z`), positive azimuths
/// move it to the camera's right (`+x`).
///
/// ```
/// use depthgraph_nodes::sim::synthetic::sun_direction;
/// let up = sun_direction(90.0, 0.0);
/// assert!((up.y + 1.0).abs() < 1e-12);
/// let right = sun_direction(0.0, 90.0);
/// assert!((right.x - 1.0).abs() < 1e-12);
/// ```
pub fn sun_direction(elevation_deg: f64, azimuth_deg: f64) -> DVec3 {
    let (se, ce) = elevation_deg.to_radians().sin_cos();
    let (sa, ca) = azimuth_deg.to_radians().sin_cos();
    DVec3::new(ce * sa, -se, -ce * ca)
}

/// A ray-surface intersection.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter: `point = origin + t * dir`.
    pub t: f64,
    /// Hit point, camera frame.
    pub point: DVec3,
    /// Unit surface normal, flipped to face the ray's origin (`n . dir <= 0`).
    pub normal: DVec3,
    /// Id of the object hit (`>= 1` for well-formed scenes).
    pub object_id: u32,
    /// Albedo at the hit point.
    pub albedo: Rgb,
    /// Emission of the object hit.
    pub emission: Rgb,
}

/// An analytic scene seen by a pinhole camera at the origin.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// The objects; ids should be distinct and `>= 1`.
    pub objects: Vec<Object>,
    /// Sun and sky.
    pub light: Light,
    /// The camera (at the origin, looking along `+z`).
    pub camera: Intrinsics,
}

/// Kinect-like intrinsics for a `width` x `height` image:
/// `fx = fy = 525 * width / 640`, principal point at the image centre (so
/// pixel centres are at integer + 0.5).
pub fn kinect_like_intrinsics(width: usize, height: usize) -> Intrinsics {
    let f = 525.0 * width as f64 / 640.0;
    Intrinsics {
        fx: f,
        fy: f,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        width,
        height,
    }
}

pub(crate) fn solid(id: u32, primitive: Primitive, albedo: Texture) -> Object {
    Object {
        id,
        primitive,
        albedo,
        emission: [0.0; 3],
        casts_shadow: true,
        texture_origin: DVec3::ZERO,
    }
}

fn enclosing(id: u32, primitive: Primitive, albedo: Texture) -> Object {
    Object {
        casts_shadow: false,
        ..solid(id, primitive, albedo)
    }
}

pub(crate) fn plane(point: [f64; 3], normal: [f64; 3]) -> Primitive {
    Primitive::Plane {
        point: DVec3::from_array(point),
        normal: DVec3::from_array(normal),
    }
}

fn boxed(center: [f64; 3], half: [f64; 3], yaw_rad: f64) -> Primitive {
    Primitive::Box {
        center: DVec3::from_array(center),
        half_extents: DVec3::from_array(half),
        yaw_rad,
    }
}

fn cylinder(base: [f64; 3], radius: f64, height: f64) -> Primitive {
    Primitive::Cylinder {
        center_base: DVec3::from_array(base),
        radius,
        height,
    }
}

fn sphere(center: [f64; 3], radius: f64) -> Primitive {
    Primitive::Sphere {
        center: DVec3::from_array(center),
        radius,
    }
}

/// A small spherical emitter of the given tint (brightest channel 1), scaled
/// to [`DEFAULT_EMITTER_RADIANCE`].
fn emitter(id: u32, center: [f64; 3], radius: f64, tint: Rgb) -> Object {
    let r = DEFAULT_EMITTER_RADIANCE;
    Object {
        id,
        primitive: sphere(center, radius),
        albedo: Texture::Solid([0.9, 0.9, 0.9]),
        emission: [tint[0] * r, tint[1] * r, tint[2] * r],
        casts_shadow: false,
        texture_origin: DVec3::ZERO,
    }
}

impl Scene {
    /// A named preset (see [`ScenePreset`]) seen with [`kinect_like_intrinsics`]
    /// at `width` x `height`; `None` for an unknown name.
    ///
    /// - `"tabletop"`: table plane 0.4 m below the camera, back wall at
    ///   2.8 m, a yawed box, a checkered sphere, a tall cylinder, a near mug
    ///   and five small emitters; depth about 0.85 to 2.8 m.
    /// - `"corridor"`: floor, ceiling, side walls and an end wall at 25 m,
    ///   crates from 1.4 to 15 m, emitters at 17 to 24.5 m.
    /// - `"thin"`: poles of radius 2 to 15 mm, a 8 mm bar, two 8 mm slabs and
    ///   two emitters in front of a finely checkered wall at 2 m.
    ///
    /// Every preset is closed (every camera ray hits something).
    pub fn preset(name: &str, width: usize, height: usize) -> Option<Scene> {
        ScenePreset::from_name(name).map(|p| Scene::of(p, width, height))
    }

    /// The built-in scene `preset`, seen by a Kinect-like camera of
    /// `width` x `height` pixels.
    pub fn of(preset: ScenePreset, width: usize, height: usize) -> Scene {
        let camera = kinect_like_intrinsics(width, height);
        let (objects, light) = match preset {
            ScenePreset::Tabletop => tabletop(),
            ScenePreset::Corridor => corridor(),
            ScenePreset::Thin => thin(),
        };
        Scene {
            objects,
            light,
            camera,
        }
    }

    /// The object with id `id`, if any (the first one when ids repeat).
    pub fn object(&self, id: u32) -> Option<&Object> {
        self.objects.iter().find(|o| o.id == id)
    }

    /// Moves the camera to `position` (metres, in the preset's camera frame;
    /// the camera keeps looking along `+z`) by moving every object by
    /// `-position`: a second camera of a rig, e.g. a ToF camera beside the
    /// color camera. Texture patterns move with their objects.
    pub fn move_camera(&mut self, position: DVec3) {
        for o in &mut self.objects {
            match &mut o.primitive {
                Primitive::Plane { point, .. } => *point -= position,
                Primitive::Box { center, .. } => *center -= position,
                Primitive::Sphere { center, .. } => *center -= position,
                Primitive::Cylinder { center_base, .. } => *center_base -= position,
            }
            o.texture_origin -= position;
        }
    }

    /// Multiplies every object's emission by `factor` (the node uses
    /// `emitter_radiance / DEFAULT_EMITTER_RADIANCE`).
    pub fn scale_emission(&mut self, factor: f32) {
        for o in &mut self.objects {
            for c in &mut o.emission {
                *c *= factor;
            }
        }
    }

    /// Nearest intersection of the ray `origin + t dir`, `t > 0` (`dir` need
    /// not be unit; a zero or non-finite `dir` hits nothing). Ties go to the
    /// object listed first.
    ///
    /// ```
    /// use depthgraph_nodes::sim::synthetic::Scene;
    /// use glam::DVec3;
    /// let scene = Scene::preset("tabletop", 64, 48).unwrap();
    /// let hit = scene.intersect(DVec3::ZERO, DVec3::new(0.0, -0.2, 1.0)).unwrap();
    /// assert!((hit.point.z - 2.8).abs() < 1e-9); // the back wall
    /// ```
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<Hit> {
        // Guard for every primitive's divisions by direction terms.
        if !dir.is_finite() || !origin.is_finite() || dir.length_squared() < DIR_EPS * DIR_EPS {
            return None;
        }
        let mut best: Option<(f64, DVec3, &Object)> = None;
        for obj in &self.objects {
            if let Some((t, n)) = obj.primitive.hit(origin, dir)
                && best.is_none_or(|(bt, _, _)| t < bt)
            {
                best = Some((t, n, obj));
            }
        }
        let (t, n, obj) = best?;
        let point = origin + dir * t;
        let normal = if n.dot(dir) > 0.0 { -n } else { n };
        Some(Hit {
            t,
            point,
            normal,
            object_id: obj.id,
            albedo: obj.albedo.eval(point - obj.texture_origin),
            emission: obj.emission,
        })
    }

    /// Signed distance from `point` to the surface of object `object_id`
    /// (see [`Primitive::signed_distance`]); `None` for an unknown id.
    pub fn signed_distance(&self, object_id: u32, point: DVec3) -> Option<f64> {
        self.object(object_id)
            .map(|o| o.primitive.signed_distance(point))
    }

    /// True when a shadow-casting object lies along `origin + t dir`, `t > 0`.
    fn occluded(&self, origin: DVec3, dir: DVec3) -> bool {
        self.objects
            .iter()
            .filter(|o| o.casts_shadow)
            .any(|o| o.primitive.hit(origin, dir).is_some())
    }

    /// Radiance leaving `hit` towards the camera:
    /// `albedo * (sun * max(0, n . l) * shadow + ambient) + emission`.
    pub fn shade(&self, hit: &Hit) -> Rgb {
        let l = self.light.sun_direction.normalize_or_zero();
        let n_dot_l = hit.normal.dot(l);
        let lit = if n_dot_l > 0.0 && !self.occluded(hit.point + hit.normal * SHADOW_OFFSET_M, l) {
            n_dot_l as f32
        } else {
            0.0
        };
        let (sun, amb) = (self.light.sun_radiance, self.light.ambient);
        std::array::from_fn(|c| hit.albedo[c] * (sun[c] * lit + amb[c]) + hit.emission[c])
    }

    /// Color of the ray, the background when it hits nothing.
    fn radiance(&self, dir: DVec3) -> Rgb {
        self.radiance_from(DVec3::ZERO, dir)
    }

    /// Color of the ray from `origin` along `dir`, the background when it
    /// hits nothing.
    fn radiance_from(&self, origin: DVec3, dir: DVec3) -> Rgb {
        match self.intersect(origin, dir) {
            Some(hit) => self.shade(&hit),
            None => self.light.background,
        }
    }

    /// Direction (with `z = 1`) of the camera ray through continuous pixel
    /// coordinate `(u, v)`. Callers check `camera.is_sane()` (the guard of
    /// the divisions by the focal lengths).
    fn ray(&self, u: f64, v: f64) -> DVec3 {
        let k = &self.camera;
        DVec3::new((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0)
    }
}

fn tabletop() -> (Vec<Object>, Light) {
    let table_y = 0.40;
    let objects = vec![
        solid(
            1,
            plane([0.0, table_y, 0.0], [0.0, -1.0, 0.0]),
            Texture::Checker {
                a: [0.55, 0.38, 0.22],
                b: [0.33, 0.21, 0.12],
                period_m: 0.10,
            },
        ),
        solid(
            2,
            plane([0.0, 0.0, 2.8], [0.0, 0.0, -1.0]),
            Texture::Waves {
                a: [0.75, 0.72, 0.65],
                b: [0.45, 0.50, 0.60],
                period_m: 0.35,
            },
        ),
        solid(
            3,
            boxed([-0.35, table_y - 0.15, 1.6], [0.15, 0.15, 0.15], 0.5),
            Texture::Solid([0.70, 0.15, 0.12]),
        ),
        solid(
            4,
            sphere([0.28, table_y - 0.18, 1.3], 0.18),
            Texture::Checker {
                a: [0.15, 0.25, 0.70],
                b: [0.85, 0.85, 0.85],
                period_m: 0.06,
            },
        ),
        solid(
            5,
            cylinder([0.02, table_y, 2.1], 0.10, 0.55),
            Texture::Solid([0.20, 0.55, 0.25]),
        ),
        solid(
            6,
            cylinder([-0.12, table_y, 0.95], 0.05, 0.10),
            Texture::Solid([0.80, 0.70, 0.20]),
        ),
        emitter(7, [-0.55, -0.30, 2.6], 0.015, [1.0, 0.8, 0.5]),
        emitter(8, [-0.15, -0.38, 2.7], 0.015, [1.0, 0.9, 0.75]),
        emitter(9, [0.35, -0.25, 2.5], 0.015, [0.6, 0.8, 1.0]),
        emitter(10, [0.62, -0.05, 2.65], 0.015, [1.0, 0.6, 0.4]),
        emitter(11, [0.45, 0.12, 1.05], 0.012, [1.0, 0.95, 0.85]),
    ];
    let light = Light {
        sun_direction: sun_direction(50.0, -35.0),
        sun_radiance: [2.2, 2.1, 1.9],
        ambient: [0.18, 0.20, 0.24],
        background: [0.0; 3],
    };
    (objects, light)
}

fn corridor() -> (Vec<Object>, Light) {
    let floor_y = 1.2;
    let objects = vec![
        solid(
            1,
            plane([0.0, floor_y, 0.0], [0.0, -1.0, 0.0]),
            Texture::Checker {
                a: [0.60, 0.60, 0.60],
                b: [0.25, 0.25, 0.28],
                period_m: 0.5,
            },
        ),
        enclosing(
            2,
            plane([0.0, -1.3, 0.0], [0.0, 1.0, 0.0]),
            Texture::Solid([0.80, 0.80, 0.78]),
        ),
        enclosing(
            3,
            plane([-1.5, 0.0, 0.0], [1.0, 0.0, 0.0]),
            Texture::Waves {
                a: [0.70, 0.65, 0.55],
                b: [0.50, 0.45, 0.40],
                period_m: 1.3,
            },
        ),
        enclosing(
            4,
            plane([1.5, 0.0, 0.0], [-1.0, 0.0, 0.0]),
            Texture::Waves {
                a: [0.55, 0.60, 0.70],
                b: [0.40, 0.42, 0.50],
                period_m: 0.9,
            },
        ),
        enclosing(
            5,
            plane([0.0, 0.0, 25.0], [0.0, 0.0, -1.0]),
            Texture::Checker {
                a: [0.70, 0.70, 0.70],
                b: [0.20, 0.20, 0.20],
                period_m: 1.0,
            },
        ),
        solid(
            6,
            boxed([-0.7, floor_y - 0.6, 1.6], [0.2, 0.6, 0.2], 0.3),
            Texture::Solid([0.65, 0.45, 0.25]),
        ),
        solid(
            7,
            boxed([0.75, floor_y - 0.4, 3.5], [0.4, 0.4, 0.3], -0.4),
            Texture::Checker {
                a: [0.70, 0.20, 0.15],
                b: [0.90, 0.80, 0.70],
                period_m: 0.2,
            },
        ),
        solid(
            8,
            boxed([-0.6, floor_y - 0.6, 7.0], [0.35, 0.6, 0.35], 0.8),
            Texture::Solid([0.25, 0.45, 0.65]),
        ),
        solid(
            9,
            boxed([0.9, floor_y - 0.3, 11.0], [0.3, 0.3, 0.3], 0.0),
            Texture::Solid([0.30, 0.60, 0.30]),
        ),
        solid(
            10,
            boxed([-0.2, floor_y - 0.5, 15.0], [0.5, 0.5, 0.5], 0.2),
            Texture::Solid([0.75, 0.70, 0.30]),
        ),
        emitter(11, [-1.0, -1.0, 18.0], 0.06, [1.0, 0.85, 0.6]),
        emitter(12, [0.9, -1.1, 20.0], 0.06, [0.7, 0.85, 1.0]),
        emitter(13, [0.0, -0.9, 23.0], 0.06, [1.0, 0.7, 0.5]),
        emitter(14, [-0.5, 0.2, 24.5], 0.06, [1.0, 1.0, 0.9]),
    ];
    let light = Light {
        sun_direction: sun_direction(60.0, 20.0),
        sun_radiance: [1.5, 1.45, 1.4],
        ambient: [0.25, 0.25, 0.28],
        background: [0.0; 3],
    };
    (objects, light)
}

fn thin() -> (Vec<Object>, Light) {
    let objects = vec![
        solid(
            1,
            plane([0.0, 0.0, 2.0], [0.0, 0.0, -1.0]),
            Texture::Checker {
                a: [0.85, 0.85, 0.80],
                b: [0.15, 0.18, 0.20],
                period_m: 0.04,
            },
        ),
        solid(
            2,
            cylinder([-0.35, 0.6, 1.0], 0.004, 1.2),
            Texture::Solid([0.80, 0.80, 0.80]),
        ),
        solid(
            3,
            cylinder([-0.10, 0.6, 1.3], 0.008, 1.2),
            Texture::Solid([0.70, 0.30, 0.20]),
        ),
        solid(
            4,
            cylinder([0.20, 0.6, 1.6], 0.015, 1.2),
            Texture::Solid([0.20, 0.40, 0.70]),
        ),
        solid(
            5,
            cylinder([0.05, 0.6, 1.2], 0.002, 1.2),
            Texture::Solid([0.90, 0.85, 0.30]),
        ),
        solid(
            6,
            boxed([0.0, -0.15, 1.4], [0.6, 0.004, 0.004], 0.0),
            Texture::Solid([0.60, 0.60, 0.65]),
        ),
        solid(
            7,
            boxed([0.35, 0.1, 1.2], [0.15, 0.2, 0.004], 0.35),
            Texture::Waves {
                a: [0.30, 0.60, 0.30],
                b: [0.80, 0.90, 0.50],
                period_m: 0.08,
            },
        ),
        solid(
            8,
            boxed([-0.25, 0.15, 1.5], [0.004, 0.18, 0.2], 0.15),
            Texture::Solid([0.75, 0.40, 0.60]),
        ),
        emitter(9, [0.5, -0.3, 1.9], 0.01, [1.0, 0.9, 0.7]),
        emitter(10, [-0.45, -0.25, 1.95], 0.01, [0.7, 0.8, 1.0]),
    ];
    let light = Light {
        sun_direction: sun_direction(45.0, -30.0),
        sun_radiance: [2.0, 1.95, 1.85],
        ambient: [0.20, 0.20, 0.22],
        background: [0.0; 3],
    };
    (objects, light)
}

/// Options of [`render`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RenderOptions {
    /// Color samples per pixel along each axis (1 to 4, clamped): `s * s`
    /// stratified samples averaged. Depth, normals, albedo and ids always
    /// come from the single ray through the pixel centre.
    pub supersample: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self { supersample: 1 }
    }
}

/// The images [`render`] produces, all `camera.width` x `camera.height`.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    /// Linear HDR radiance.
    pub color: ColorImage,
    /// Camera-space `z` at the pixel centre (not the ray length); 0 where the
    /// ray hits nothing.
    pub depth: DepthMap,
    /// Unit normals in the camera frame, facing the camera; `[0, 0, 0]` where
    /// nothing is hit.
    pub normals: NormalMap,
    /// Albedo at the pixel centre; `[0, 0, 0]` where nothing is hit.
    pub albedo: ColorImage,
    /// Object ids; 0 where nothing is hit.
    pub ids: LabelImage,
    /// The camera the images were rendered with.
    pub intrinsics: Intrinsics,
}

/// One rendered row.
struct Row {
    color: Vec<Rgb>,
    depth: Vec<f32>,
    normals: Vec<[f32; 3]>,
    albedo: Vec<Rgb>,
    ids: Vec<u32>,
}

fn render_row(scene: &Scene, y: usize, width: usize, ss: usize) -> Row {
    let mut row = Row {
        color: Vec::with_capacity(width),
        depth: Vec::with_capacity(width),
        normals: Vec::with_capacity(width),
        albedo: Vec::with_capacity(width),
        ids: Vec::with_capacity(width),
    };
    let sane = scene.camera.is_sane();
    // Guard of the division: ss >= 1 (clamped by the caller).
    let inv_ss = 1.0 / ss as f64;
    let inv_n = inv_ss * inv_ss;
    for x in 0..width {
        let centre = sane
            .then(|| scene.intersect(DVec3::ZERO, scene.ray(x as f64 + 0.5, y as f64 + 0.5)))
            .flatten();
        let color = if !sane {
            scene.light.background
        } else if ss == 1 {
            centre.map_or(scene.light.background, |h| scene.shade(&h))
        } else {
            let mut acc = [0.0f64; 3];
            for j in 0..ss {
                for i in 0..ss {
                    let u = x as f64 + (i as f64 + 0.5) * inv_ss;
                    let v = y as f64 + (j as f64 + 0.5) * inv_ss;
                    let c = scene.radiance(scene.ray(u, v));
                    for (a, c) in acc.iter_mut().zip(c) {
                        *a += c as f64;
                    }
                }
            }
            acc.map(|a| (a * inv_n) as f32)
        };
        row.color.push(color);
        match centre {
            Some(h) => {
                row.depth.push(h.point.z as f32);
                row.normals.push(h.normal.as_vec3().to_array());
                row.albedo.push(h.albedo);
                row.ids.push(h.object_id);
            }
            None => {
                row.depth.push(0.0);
                row.normals.push([0.0; 3]);
                row.albedo.push([0.0; 3]);
                row.ids.push(0);
            }
        }
    }
    row
}

/// Renders `scene` with one ray through each pixel centre (see the module
/// docs for the shading).
///
/// ```
/// use depthgraph_nodes::sim::synthetic::{render, RenderOptions, Scene};
/// let scene = Scene::preset("tabletop", 32, 24).unwrap();
/// let out = render(&scene, &RenderOptions::default());
/// assert_eq!(out.depth.dims(), (32, 24));
/// assert_eq!(out.depth.hole_count(), 0); // the preset is closed
/// ```
pub fn render(scene: &Scene, opts: &RenderOptions) -> RenderOutput {
    match render_with(scene, opts, |_| Ok::<(), std::convert::Infallible>(())) {
        Ok(out) => out,
        Err(never) => match never {},
    }
}

/// [`render`] that calls `on_progress(fraction)` after every band of rows and
/// stops with its error when it returns one (cancellation).
pub fn render_with<E>(
    scene: &Scene,
    opts: &RenderOptions,
    mut on_progress: impl FnMut(f32) -> Result<(), E>,
) -> Result<RenderOutput, E> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let ss = opts.supersample.clamp(1, 4);
    let mut color = ColorImage::filled(w, h, [0.0; 3]);
    let mut depth = DepthMap::filled(w, h, 0.0);
    let mut normals = NormalMap::filled(w, h, [0.0; 3]);
    let mut albedo = ColorImage::filled(w, h, [0.0; 3]);
    let mut ids = LabelImage::filled(w, h, 0);
    let mut y0 = 0;
    while y0 < h {
        let y1 = (y0 + BAND_ROWS).min(h);
        let rows: Vec<Row> = (y0..y1)
            .into_par_iter()
            .map(|y| render_row(scene, y, w, ss))
            .collect();
        for (y, row) in (y0..y1).zip(rows) {
            let span = y * w..(y + 1) * w;
            color.as_mut_slice()[span.clone()].copy_from_slice(&row.color);
            depth.as_mut_slice()[span.clone()].copy_from_slice(&row.depth);
            normals.as_mut_slice()[span.clone()].copy_from_slice(&row.normals);
            albedo.as_mut_slice()[span.clone()].copy_from_slice(&row.albedo);
            ids.as_mut_slice()[span].copy_from_slice(&row.ids);
        }
        // Guard: h > 0 inside the loop.
        on_progress(y1 as f32 / h as f32)?;
        y0 = y1;
    }
    Ok(RenderOutput {
        color,
        depth,
        normals,
        albedo,
        ids,
        intrinsics: scene.camera,
    })
}

/// A thin lens for [`render_thin_lens`]: the ground truth of the depth-blur
/// paper's refocusing (its Sec. 1: "the exact way for computing DoF is to
/// model the light transport ... by casting rays from across the lens").
#[derive(Debug, Clone, PartialEq)]
pub struct ThinLensRender {
    /// The lens: focal length, f-number, focus distance and sensor width.
    pub lens: ThinLens,
    /// Shape of the aperture the rays start from.
    pub aperture: Aperture,
    /// Rays per pixel, spread over the aperture.
    pub samples: usize,
    /// Seed of the per-pixel aperture samples.
    pub seed: u64,
    /// What the lens adds to the thin lens (aberrations, vignetting,
    /// breathing; all off by default), the model of
    /// [`crate::camera::lens::LensEffects`].
    pub effects: LensEffects,
    /// Each ray also starts from its own point of the pixel's square (a
    /// box filter over the pixel, as a sensor pixel integrates light; the
    /// pinhole render's `supersample` is the same filter) instead of the
    /// pixel centre.
    pub pixel_area: bool,
}

/// The R2 sequence's steps (Roberts 2018, from the plastic number): the
/// sub-pixel points of [`render_thin_lens`]'s rays with `pixel_area`, a
/// low-discrepancy sequence rotated per pixel.
const R2_STEP: [f64; 2] = [0.754_877_666_246_692_7, 0.569_840_290_998_053_2];

/// Where ray `i` of a pixel crosses it, in pixels from its corner:
/// `frac(shift + i R2_STEP)` with `pixel_area`, else the centre.
fn ray_offset(pixel_area: bool, shift: [f64; 2], i: usize) -> [f64; 2] {
    if !pixel_area {
        return [0.5, 0.5];
    }
    let i = i as f64;
    [
        (shift[0] + i * R2_STEP[0]).fract(),
        (shift[1] + i * R2_STEP[1]).fract(),
    ]
}

/// Renders `scene` through a thin lens by distributed ray tracing: for each
/// pixel, `samples` rays start at stratified points `L` of the aperture and
/// pass through the point where the pixel's pinhole ray meets the focus plane
/// `z = u` (parallel to the pinhole ray when focused at infinity); the pixel
/// is their mean radiance (f64 sums). The aperture point `s` (in aperture
/// diameters, see [`crate::camera::lens`]) sits at `L = (s_x C / fx, s_y C / fy, 0)`
/// metres, `C` = [`ThinLens::coc_scale`], so a point at depth `z` is spread
/// over exactly the circle of confusion `C |1/z - 1/u|` pixels that
/// [`crate::camera::refocus::refocus`] uses: the two differ only by what a single
/// RGB-D image cannot know (what hides behind edges). Rays go through pixel
/// centres, like the pinhole render the refocusing starts from, or with
/// [`ThinLensRender::pixel_area`] through points spread over the pixel
/// (like a supersampled pinhole render). Each pixel
/// draws its own aperture samples (seeded by the pixel), so the noise is
/// not correlated across the image.
pub fn render_thin_lens(
    scene: &Scene,
    lens: &ThinLensRender,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<ColorImage, NodeError> {
    lens.lens.validate()?;
    if lens.samples == 0 {
        return Err(NodeError::param("lens_samples", "must be at least 1"));
    }
    let k = scene.camera;
    let (w, h) = (k.width, k.height);
    if !k.is_sane() {
        return Ok(ColorImage::filled(w, h, scene.light.background));
    }
    let c = lens.lens.coc_scale(w);
    let inv_u = lens.lens.inv_focus();
    // Guard: is_sane() ensures fx, fy > 0.
    let (sx, sy) = (c / k.fx, c / k.fy);
    // Guard: samples >= 1 (checked above).
    let inv_n = 1.0 / lens.samples as f64;
    let fx = &lens.effects;
    fx.validate()?;
    let plain = !fx.in_views() && !fx.in_image(&lens.lens);
    let barrel = fx.barrel(&lens.lens, w, h);
    let mag: [f64; 3] = std::array::from_fn(|ch| fx.magnification(&lens.lens, ch));
    // One ray per aperture point serves all three channels unless they
    // focus or magnify differently.
    let per_channel = fx.chromatic_longitudinal_d != 0.0 || mag[0] != mag[1] || mag[2] != mag[1];
    let centre = [w as f64 / 2.0, h as f64 / 2.0];
    // The pixel through the lens with the effects: channel group `chans`
    // seen from output pixel (x, y) (see LensEffects for the model).
    let effect_pixel = |x: usize, y: usize, points: &[[f64; 2]], shift: [f64; 2]| -> Rgb {
        let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
        let mut acc = [0.0f64; 3];
        let groups: &[&[usize]] = if per_channel {
            &[&[0], &[1], &[2]]
        } else {
            &[&[0, 1, 2]]
        };
        for chans in groups {
            let ch = chans[0];
            for (i, s) in points.iter().enumerate() {
                let o = ray_offset(lens.pixel_area, shift, i);
                // Guard: magnifications are positive (validate).
                let qx = centre[0] + (x as f64 + o[0] - centre[0]) / mag[ch];
                let qy = centre[1] + (y as f64 + o[1] - centre[1]) / mag[ch];
                if barrel.is_some_and(|b| !b.open(*s, qx, qy)) {
                    continue;
                }
                let d0 = scene.ray(qx, qy);
                let origin = DVec3::new(s[0] * sx, s[1] * sy, 0.0);
                // Towards the point where this ray focuses: inverse
                // distance 1/u + S r^2 + k_c L (any sign: beyond infinity
                // the rays diverge).
                let inv = inv_u + fx.focus_offset(*s, if per_channel { ch } else { 1 });
                let r = scene.radiance_from(origin, d0 - origin * inv);
                for &c in chans.iter() {
                    acc[c] += r[c] as f64;
                }
            }
        }
        let v = fx.natural_factor(&lens.lens, w, h, px, py);
        acc.map(|a| (a * inv_n * v) as f32)
    };
    let mut color = ColorImage::filled(w, h, [0.0; 3]);
    let mut y0 = 0;
    while y0 < h {
        let y1 = (y0 + BAND_ROWS).min(h);
        let rows: Vec<Result<Vec<Rgb>, NodeError>> = (y0..y1)
            .into_par_iter()
            .map(|y| {
                (0..w)
                    .map(|x| {
                        let pixel_seed = crate::kit::rng::splitmix64(
                            lens.seed ^ ((y * w + x) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
                        );
                        let points = lens.aperture.samples(lens.samples, pixel_seed)?;
                        let r = crate::kit::rng::splitmix64(pixel_seed ^ 0x0ff5_e7a1);
                        let unit = |v: u64| (v >> 11) as f64 / (1u64 << 53) as f64;
                        let shift = [unit(r), unit(crate::kit::rng::splitmix64(r))];
                        if !plain {
                            return Ok(effect_pixel(x, y, &points, shift));
                        }
                        let centre_ray = scene.ray(x as f64 + 0.5, y as f64 + 0.5);
                        let mut acc = [0.0f64; 3];
                        for (i, s) in points.iter().enumerate() {
                            let d0 = if lens.pixel_area {
                                let o = ray_offset(true, shift, i);
                                scene.ray(x as f64 + o[0], y as f64 + o[1])
                            } else {
                                centre_ray
                            };
                            let origin = DVec3::new(s[0] * sx, s[1] * sy, 0.0);
                            let dir = if inv_u > 0.0 {
                                // Guard: inv_u > 0, so 1 / inv_u is the finite focus distance.
                                d0 * (1.0 / inv_u) - origin
                            } else {
                                d0
                            };
                            let r = scene.radiance_from(origin, dir);
                            for (a, v) in acc.iter_mut().zip(r) {
                                *a += v as f64;
                            }
                        }
                        Ok(acc.map(|a| (a * inv_n) as f32))
                    })
                    .collect()
            })
            .collect();
        for (y, row) in (y0..y1).zip(rows) {
            color.as_mut_slice()[y * w..(y + 1) * w].copy_from_slice(&row?);
        }
        // Guard: h > 0 inside the loop.
        on_progress(y1 as f32 / h as f32)?;
        y0 = y1;
    }
    Ok(color)
}

node_params! {
    /// Parameters of the `SyntheticThinLens` node: a scene preset (as
    /// `SyntheticScene`) seen through a thin lens (as `Refocus`).
    pub struct SyntheticThinLensParams {
        /// Which analytic scene (see `SyntheticScene`).
        pub preset: ScenePreset = ScenePreset::Tabletop, ParamKind::Choice(ScenePreset::NAMES);
        /// Image width in pixels.
        pub width: usize = 640usize, ParamKind::Int { min: 1, max: 8192 };
        /// Image height in pixels.
        pub height: usize = 480usize, ParamKind::Int { min: 1, max: 8192 };
        /// Sun elevation above the horizon in degrees.
        pub sun_elevation_deg: f64 = 50.0, ParamKind::Float { min: -90.0, max: 90.0 };
        /// Sun azimuth in degrees.
        pub sun_azimuth_deg: f64 = -35.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Radiance of the brightest channel of the small emitters.
        pub emitter_radiance: f32 = DEFAULT_EMITTER_RADIANCE, ParamKind::Float { min: 0.0, max: 1e6 };
        /// Focal length of the lens in millimetres.
        pub focal_length_mm: f64 = 50.0, ParamKind::Float { min: 1.0, max: 2000.0 };
        /// f-number.
        pub f_number: f64 = 2.8, ParamKind::Float { min: 0.5, max: 1000.0 };
        /// Aperture diameter in millimetres; > 0 overrides f_number (as Refocus), 0 = use f_number.
        pub aperture_diameter_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 100000.0 };
        /// Focus distance in metres (`inf` for infinity).
        pub focus_m: f64 = 2.0, ParamKind::Float { min: 1e-3, max: f64::INFINITY };
        /// Sensor width in millimetres, spanning the image width.
        pub sensor_width_mm: f64 = 36.0, ParamKind::Float { min: 0.1, max: 1000.0 };
        /// Aperture shape (disc, polygon, triangle; a mask needs the Refocus node).
        pub aperture: ApertureShape = ApertureShape::Disc, ParamKind::Choice(&["disc", "polygon", "triangle"]);
        /// Blades of the polygonal aperture.
        pub blades: u32 = 6u32, ParamKind::Int { min: 3, max: 64 };
        /// Rotation of the polygon in degrees.
        pub rotation_deg: f64 = 0.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Rays per pixel across the aperture.
        pub lens_samples: usize = 256usize, ParamKind::Int { min: 1, max: 65536 };
        /// Seed of the aperture samples.
        pub seed: u64 = 0u64, ParamKind::Int { min: 0, max: i64::MAX };
        /// Spherical aberration in dioptres at the aperture's rim (as Refocus).
        pub spherical_aberration_d: f64 = 0.0, ParamKind::Float { min: -100.0, max: 100.0 };
        /// Longitudinal chromatic aberration in dioptres (as Refocus).
        pub chromatic_longitudinal_d: f64 = 0.0, ParamKind::Float { min: -100.0, max: 100.0 };
        /// Lateral chromatic aberration, relative magnification (as Refocus).
        pub chromatic_lateral: f64 = 0.0, ParamKind::Float { min: -0.25, max: 0.25 };
        /// Distance of the lens barrel in front of the stop, mm (as Refocus).
        pub barrel_distance_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 10000.0 };
        /// Diameter of the lens barrel, mm; 0 = the aperture's (as Refocus).
        pub barrel_diameter_mm: f64 = 0.0, ParamKind::Float { min: 0.0, max: 10000.0 };
        /// Natural vignetting exponent k of cos^(4k) (as Refocus).
        pub natural_vignetting: f64 = 0.0, ParamKind::Float { min: 0.0, max: 8.0 };
        /// Focus breathing (as Refocus).
        pub focus_breathing: bool = false, ParamKind::Bool;
        /// Rays spread over each pixel's square (a box filter, as a sensor pixel integrates; pair with SyntheticScene's supersample), not through its centre.
        pub pixel_area: bool = false, ParamKind::Bool;
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SyntheticThinLens`.
    outputs struct ThinLensOut {
        /// linear HDR radiance through the lens
        color: ColorImage,
    }
}

fn eval_thin_lens(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &SyntheticThinLensParams,
) -> Result<Produced<ThinLensOut>, NodeError> {
    let scene = scene_from_params(&SyntheticSceneParams {
        preset: p.preset,
        width: p.width,
        height: p.height,
        supersample: 1,
        sun_elevation_deg: p.sun_elevation_deg,
        sun_azimuth_deg: p.sun_azimuth_deg,
        emitter_radiance: p.emitter_radiance,
        ..Default::default()
    })?;
    let lens = ThinLensRender {
        lens: ThinLens {
            focal_length_mm: p.focal_length_mm,
            f_number: effective_f_number(p.focal_length_mm, p.f_number, p.aperture_diameter_mm),
            focus_m: p.focus_m,
            sensor_width_mm: p.sensor_width_mm,
        },
        aperture: Aperture::from_params(p.aperture, p.blades, p.rotation_deg, None)?,
        samples: p.lens_samples,
        seed: p.seed,
        effects: LensEffects {
            spherical_d: p.spherical_aberration_d,
            chromatic_longitudinal_d: p.chromatic_longitudinal_d,
            chromatic_lateral: p.chromatic_lateral,
            barrel_distance_mm: p.barrel_distance_mm,
            barrel_diameter_mm: p.barrel_diameter_mm,
            natural_vignetting: p.natural_vignetting,
            focus_breathing: p.focus_breathing,
        },
        pixel_area: p.pixel_area,
    };
    let color = render_thin_lens(&scene, &lens, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?;
    Ok(ThinLensOut { color }.into())
}

node_params! {
    /// Parameters of the `SyntheticScene` node.
    pub struct SyntheticSceneParams {
        /// Which analytic scene: "tabletop" (0.85-2.8 m, objects on a table),
        /// "corridor" (1.4-25 m), "thin" (poles, bars and slabs of 2-15 mm).
        pub preset: ScenePreset = ScenePreset::Tabletop, ParamKind::Choice(ScenePreset::NAMES);
        /// Image width in pixels (fx = fy = 525 * width / 640).
        pub width: usize = 640usize, ParamKind::Int { min: 1, max: 8192 };
        /// Image height in pixels.
        pub height: usize = 480usize, ParamKind::Int { min: 1, max: 8192 };
        /// Color samples per pixel along each axis (s * s in all); the ground
        /// truth images always use the pixel centre.
        pub supersample: usize = 1usize, ParamKind::Int { min: 1, max: 4 };
        /// Sun elevation above the horizon in degrees.
        pub sun_elevation_deg: f64 = 50.0, ParamKind::Float { min: -90.0, max: 90.0 };
        /// Sun azimuth in degrees: 0 = behind the camera, positive = towards
        /// the camera's right.
        pub sun_azimuth_deg: f64 = -35.0, ParamKind::Float { min: -360.0, max: 360.0 };
        /// Radiance of the brightest channel of the small emitters (the bokeh
        /// highlights).
        pub emitter_radiance: f32 = DEFAULT_EMITTER_RADIANCE, ParamKind::Float { min: 0.0, max: 1e6 };
        /// Where this camera stands relative to the preset's camera, metres
        /// (x right, y down, z forward): a second camera of a rig, e.g. a
        /// depth camera beside the color camera.
        pub camera_position_m: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -100.0, max: 100.0 };
        /// Frame index of a sequence (`frame: "{frame}"` in a pipeline run by
        /// `depthgraph batch`): the camera stands at
        /// `camera_position_m + frame * dolly_m_per_frame`.
        pub frame: u32 = 0u32, ParamKind::Int { min: 0, max: 10_000_000 };
        /// How far the camera moves per frame, metres (x right, y down,
        /// z forward): a dolly.
        pub dolly_m_per_frame: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -1.0, max: 1.0 };
    }
}

/// The scene the parameters describe (preset, sun, emitter radiance).
///
/// ```
/// use depthgraph_nodes::sim::synthetic::{scene_from_params, SyntheticSceneParams};
/// let p = SyntheticSceneParams { width: 64, height: 48, ..Default::default() };
/// let scene = scene_from_params(&p).unwrap();
/// assert_eq!(scene.camera.fx, 52.5);
/// ```
pub fn scene_from_params(p: &SyntheticSceneParams) -> Result<Scene, NodeError> {
    let mut scene = Scene::of(p.preset, p.width, p.height);
    scene.light.sun_direction = sun_direction(p.sun_elevation_deg, p.sun_azimuth_deg);
    // Guard: DEFAULT_EMITTER_RADIANCE is a non-zero constant.
    scene.scale_emission(p.emitter_radiance / DEFAULT_EMITTER_RADIANCE);
    let dolly = DVec3::from_array(p.dolly_m_per_frame) * f64::from(p.frame);
    scene.move_camera(DVec3::from_array(p.camera_position_m) + dolly);
    Ok(scene)
}

depthgraph_graph::ports! {
    /// Outputs of `SyntheticScene`.
    outputs struct SceneOut {
        /// linear HDR radiance
        color: ColorImage,
        /// exact camera-space z in metres, 0 where nothing is hit
        depth: DepthMap,
        /// unit camera-frame normals facing the camera
        normals: NormalMap,
        /// surface albedo
        albedo: ColorImage,
        /// object ids, 0 where nothing is hit
        ids: LabelImage,
        /// Kinect-like intrinsics of the render
        intrinsics: Intrinsics,
    }
}

fn eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &SyntheticSceneParams,
) -> Result<Produced<SceneOut>, NodeError> {
    let scene = scene_from_params(p)?;
    let opts = RenderOptions {
        supersample: p.supersample,
    };
    let out = render_with(&scene, &opts, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?;
    Ok(SceneOut {
        color: out.color,
        depth: out.depth,
        normals: out.normals,
        albedo: out.albedo,
        ids: out.ids,
        intrinsics: out.intrinsics,
    }
    .into())
}

/// Registers `SyntheticScene` and `SyntheticThinLens`.
pub fn register(reg: &mut Registry) -> Result<(), depthgraph_graph::registry::RegistryError> {
    reg.register(PortedNode::new(
        "SyntheticScene",
        1,
        "Ray-cast analytic scene (tabletop, corridor, thin structures) with exact depth, normals, albedo and ids.\n\
         One ray per pixel centre, so the ground truth is exact there; the color is linear HDR with a sun, \
         hard shadows, ambient light and small bright emitters.",
        eval,
    ))?;
    reg.register(PortedNode::new(
        "SyntheticThinLens",
        1,
        "The SyntheticScene presets seen through a thin lens by distributed ray tracing (many rays per pixel \
         across the aperture): the ground truth that Refocus and ReverseMappedDof are measured against.\n\
         Same lens parameters and circle of confusion as Refocus.",
        eval_thin_lens,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// Unprojects every pixel's depth at its centre and measures the distance
    /// to the surface of the object named by the id image. Returns the worst
    /// distance and the number of pixels with a hit.
    fn gt_residual(scene: &Scene, out: &RenderOutput) -> (f64, usize) {
        let k = out.intrinsics;
        let (w, h) = out.depth.dims();
        let mut worst = 0.0f64;
        let mut hits = 0;
        for v in 0..h {
            for u in 0..w {
                let z = *out.depth.get(u, v);
                let id = *out.ids.get(u, v);
                assert_eq!(DepthMap::is_valid(z), id != 0, "pixel ({u}, {v})");
                if id == 0 {
                    assert_eq!(*out.normals.get(u, v), [0.0; 3]);
                    continue;
                }
                hits += 1;
                let p = k.unproject(u as f64 + 0.5, v as f64 + 0.5, z as f64);
                let d = scene.signed_distance(id, p).unwrap();
                worst = worst.max(d.abs());
                let n = glam::Vec3::from_array(*out.normals.get(u, v)).as_dvec3();
                assert!(
                    (n.length() - 1.0).abs() < 1e-5,
                    "normal not unit at ({u}, {v})"
                );
                assert!(
                    n.dot(p) <= 1e-9,
                    "normal does not face the camera at ({u}, {v})"
                );
            }
        }
        (worst, hits)
    }

    fn all_finite(out: &RenderOutput) -> bool {
        out.color.as_slice().iter().flatten().all(|c| c.is_finite())
            && out
                .albedo
                .as_slice()
                .iter()
                .flatten()
                .all(|c| c.is_finite())
            && out
                .normals
                .as_slice()
                .iter()
                .flatten()
                .all(|c| c.is_finite())
            && out.depth.as_slice().iter().all(|z| z.is_finite())
    }

    fn distinct_ids(out: &RenderOutput) -> usize {
        let mut ids: Vec<u32> = out.ids.as_slice().to_vec();
        ids.sort_unstable();
        ids.dedup();
        ids.len()
    }

    #[test]
    fn ground_truth_lies_on_the_labelled_surface_for_every_preset() {
        for name in ScenePreset::NAMES {
            let scene = Scene::preset(name, 64, 48).unwrap();
            let out = render(&scene, &RenderOptions::default());
            let (worst, hits) = gt_residual(&scene, &out);
            assert!(worst < 1e-4, "{name}: worst surface distance {worst} m");
            assert_eq!(hits, 64 * 48, "{name}: presets are closed");
            assert!(all_finite(&out), "{name}");
        }
    }

    #[test]
    fn thin_preset_at_higher_resolution_is_exact_and_shows_thin_parts() {
        let scene = Scene::preset("thin", 320, 240).unwrap();
        let out = render(&scene, &RenderOptions::default());
        let (worst, _) = gt_residual(&scene, &out);
        assert!(worst < 1e-4, "worst surface distance {worst} m");
        // The wall, the four poles (the 2 mm one is ~0.5 px wide at 320 px and
        // may fall between pixel centres), the bar and both slabs.
        for id in [1, 2, 3, 4, 6, 7, 8] {
            assert!(out.ids.as_slice().contains(&id), "object {id} not visible");
        }
    }

    #[test]
    fn preset_depth_ranges_and_visible_objects() {
        let range = |out: &RenderOutput| {
            let zs = out.depth.as_slice().iter().copied();
            (
                zs.clone().fold(f32::INFINITY, f32::min),
                zs.fold(0.0f32, f32::max),
            )
        };
        let t = render(
            &Scene::preset("tabletop", 160, 120).unwrap(),
            &RenderOptions::default(),
        );
        let (lo, hi) = range(&t);
        assert!(
            lo > 0.8 && lo < 1.0 && (hi - 2.8).abs() < 1e-5,
            "tabletop {lo}..{hi}"
        );
        assert!(
            distinct_ids(&t) >= 7,
            "tabletop shows {} objects",
            distinct_ids(&t)
        );
        let c = render(
            &Scene::preset("corridor", 160, 120).unwrap(),
            &RenderOptions::default(),
        );
        let (lo, hi) = range(&c);
        assert!(lo < 2.0 && (hi - 25.0).abs() < 1e-4, "corridor {lo}..{hi}");
        for id in 5..=10 {
            assert!(
                c.ids.as_slice().contains(&id),
                "corridor object {id} not visible"
            );
        }
    }

    #[test]
    fn depth_is_z_not_ray_length() {
        // Back wall z = 2.8 everywhere it is seen, including off-axis pixels.
        let scene = Scene::preset("tabletop", 64, 48).unwrap();
        let out = render(&scene, &RenderOptions::default());
        let wall: Vec<f32> = (0..out.depth.len())
            .filter(|i| out.ids.as_slice()[*i] == 2)
            .map(|i| out.depth.as_slice()[i])
            .collect();
        assert!(wall.len() > 100);
        assert!(wall.iter().all(|z| (z - 2.8).abs() < 1e-6));
    }

    #[test]
    fn misses_write_zero_depth_id_and_normal() {
        let scene = Scene {
            objects: vec![solid(
                5,
                sphere([0.0, 0.0, 2.0], 0.5),
                Texture::Solid([0.5; 3]),
            )],
            light: Light {
                sun_direction: sun_direction(90.0, 0.0),
                sun_radiance: [1.0; 3],
                ambient: [0.0; 3],
                background: [0.25, 0.5, 0.75],
            },
            camera: kinect_like_intrinsics(64, 48),
        };
        let out = render(&scene, &RenderOptions::default());
        let (worst, hits) = gt_residual(&scene, &out);
        // Depth is stored as f32: ~1e-7 relative.
        assert!(worst < 1e-6, "{worst}");
        assert!(hits > 50 && hits < 64 * 48 - 500, "{hits}");
        assert_eq!(*out.depth.get(0, 0), 0.0);
        assert_eq!(*out.ids.get(0, 0), 0);
        assert_eq!(*out.color.get(0, 0), [0.25, 0.5, 0.75]);
        // Nearest point of the sphere: z = 1.5 on the axis; pixel centres are
        // 0.5 px off axis, so slightly farther.
        let min = out
            .depth
            .as_slice()
            .iter()
            .copied()
            .filter(|z| *z > 0.0)
            .fold(f32::INFINITY, f32::min);
        assert!((min - 1.5).abs() < 1e-3, "{min}");
    }

    #[test]
    fn shading_follows_the_formula_with_hard_shadows() {
        // Floor at y = 1, sphere hovering above it, sun straight overhead.
        let albedo = [0.5, 0.4, 0.3];
        let scene = Scene {
            objects: vec![
                solid(
                    1,
                    plane([0.0, 1.0, 0.0], [0.0, -1.0, 0.0]),
                    Texture::Solid(albedo),
                ),
                solid(2, sphere([0.0, 0.0, 3.0], 0.3), Texture::Solid([1.0; 3])),
            ],
            light: Light {
                sun_direction: sun_direction(90.0, 0.0),
                sun_radiance: [2.0, 2.0, 2.0],
                ambient: [0.1, 0.2, 0.3],
                background: [0.0; 3],
            },
            camera: kinect_like_intrinsics(64, 48),
        };
        // The floor point right below the sphere is in shadow: albedo * ambient.
        let below = scene
            .intersect(DVec3::ZERO, DVec3::new(0.0, 1.0, 3.0))
            .unwrap();
        assert_eq!(below.object_id, 1);
        let c = scene.shade(&below);
        for i in 0..3 {
            assert!((c[i] - albedo[i] * scene.light.ambient[i]).abs() < 1e-6);
        }
        // A floor point far to the side is lit with n . l = 1.
        let lit = scene
            .intersect(DVec3::ZERO, DVec3::new(2.0, 1.0, 3.0))
            .unwrap();
        let c = scene.shade(&lit);
        for i in 0..3 {
            let expected = albedo[i] * (2.0 + scene.light.ambient[i]);
            assert!((c[i] - expected).abs() < 1e-6, "{c:?}");
        }
        // The sphere's side (n . l = 0 at its equator) receives ambient only.
        let side = scene
            .intersect(DVec3::ZERO, DVec3::new(0.3, 0.0, 3.0))
            .unwrap();
        assert_eq!(side.object_id, 2);
        assert!(side.normal.dot(scene.light.sun_direction).abs() < 1e-3);
    }

    #[test]
    fn primitives_hit_where_their_distance_is_zero() {
        let prims = [
            plane([0.0, 0.5, 0.0], [0.0, -2.0, 0.0]),
            sphere([0.1, 0.0, 2.0], 0.4),
            boxed([0.0, 0.0, 2.0], [0.3, 0.2, 0.1], 0.7),
            cylinder([0.0, 0.3, 2.0], 0.2, 0.6),
        ];
        for prim in prims {
            let mut hits = 0;
            for i in 0..21 {
                for j in 0..21 {
                    let d = DVec3::new(-0.2 + 0.02 * i as f64, -0.2 + 0.02 * j as f64, 1.0);
                    if let Some((t, n)) = prim.hit(DVec3::ZERO, d) {
                        hits += 1;
                        let p = d * t;
                        assert!(prim.signed_distance(p).abs() < 1e-9, "{prim:?}");
                        // The outward normal is the distance gradient.
                        let e = 1e-6;
                        let g = DVec3::new(
                            prim.signed_distance(p + DVec3::X * e)
                                - prim.signed_distance(p - DVec3::X * e),
                            prim.signed_distance(p + DVec3::Y * e)
                                - prim.signed_distance(p - DVec3::Y * e),
                            prim.signed_distance(p + DVec3::Z * e)
                                - prim.signed_distance(p - DVec3::Z * e),
                        ) / (2.0 * e);
                        // Edges and corners have no unique gradient; compare
                        // on faces only.
                        if (g.length() - 1.0).abs() < 1e-3 {
                            assert!(g.dot(n) > 0.999, "{prim:?}: normal {n} vs gradient {g}");
                        }
                    }
                }
            }
            assert!(hits > 50, "{prim:?}: only {hits} hits");
        }
    }

    #[test]
    fn degenerate_input_hits_nothing() {
        let scene = Scene::preset("tabletop", 8, 6).unwrap();
        assert!(scene.intersect(DVec3::ZERO, DVec3::ZERO).is_none());
        assert!(
            scene
                .intersect(DVec3::ZERO, DVec3::new(f64::NAN, 0.0, 1.0))
                .is_none()
        );
        // Looking backwards from the origin: everything is in front.
        assert!(
            scene
                .intersect(DVec3::ZERO, DVec3::new(0.0, -0.1, -1.0))
                .is_none()
        );
        let bad = sphere([0.0, 0.0, 2.0], -1.0);
        assert!(bad.hit(DVec3::ZERO, DVec3::Z).is_none());
        let mut broken = scene.clone();
        broken.camera.fx = 0.0;
        let out = render(&broken, &RenderOptions::default());
        assert_eq!(out.depth.hole_count(), 48);
        let empty = Scene::preset("corridor", 0, 0).unwrap();
        assert_eq!(render(&empty, &RenderOptions::default()).depth.len(), 0);
    }

    #[test]
    fn supersampling_changes_color_only() {
        let scene = Scene::preset("tabletop", 64, 48).unwrap();
        let one = render(&scene, &RenderOptions { supersample: 1 });
        let three = render(&scene, &RenderOptions { supersample: 3 });
        assert_eq!(one.depth, three.depth);
        assert_eq!(one.ids, three.ids);
        assert_eq!(one.normals, three.normals);
        assert_ne!(one.color, three.color);
        // The mean color agrees (same scene, finer sampling).
        let mean = |img: &ColorImage| {
            img.as_slice()
                .iter()
                .map(|c| (c[0] + c[1] + c[2]) as f64)
                .sum::<f64>()
                / img.len() as f64
        };
        let (a, b) = (mean(&one.color), mean(&three.color));
        assert!((a - b).abs() < 0.1 * a, "{a} vs {b}");
    }

    #[test]
    fn render_is_independent_of_thread_count() {
        let scene = Scene::preset("corridor", 48, 36).unwrap();
        let opts = RenderOptions { supersample: 2 };
        let run = |threads| crate::test_support::with_threads(threads, || render(&scene, &opts));
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn a_dolly_moves_the_camera_by_frame_times_step() {
        let at = |frame, dolly, pos| {
            let p = SyntheticSceneParams {
                width: 32,
                height: 24,
                frame,
                dolly_m_per_frame: dolly,
                camera_position_m: pos,
                ..Default::default()
            };
            render(&scene_from_params(&p).unwrap(), &RenderOptions::default()).depth
        };
        // frame 5 at 0.1 m forward is the camera 0.5 m forward
        assert_eq!(
            at(5, [0.0, 0.0, 0.1], [0.0; 3]),
            at(0, [0.0; 3], [0.0, 0.0, 0.5])
        );
        assert_eq!(at(0, [0.0, 0.0, 0.1], [0.0; 3]), at(0, [0.0; 3], [0.0; 3]));
        assert_ne!(at(1, [0.0, 0.0, 0.1], [0.0; 3]), at(0, [0.0; 3], [0.0; 3]));
    }

    #[test]
    fn emitters_are_bright_and_scale_with_the_parameter() {
        let p = SyntheticSceneParams {
            emitter_radiance: 10.0,
            ..Default::default()
        };
        let scene = scene_from_params(&p).unwrap();
        let e = scene.object(7).unwrap();
        assert!((e.emission.iter().fold(0.0f32, |m, c| m.max(*c)) - 10.0).abs() < 1e-5);
        // Looking straight at an emitter gives at least its emission.
        let c = DVec3::new(-0.55, -0.30, 2.6);
        let hit = scene.intersect(DVec3::ZERO, c).unwrap();
        assert_eq!(hit.object_id, 7);
        assert!(scene.shade(&hit)[0] >= 10.0);
    }

    #[test]
    fn node_outputs_match_the_schema_and_report_progress() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let node = reg.get("SyntheticScene").unwrap();
        let mut params = SyntheticSceneParams::default().to_values();
        params.insert("width".into(), ParamValue::Int(40));
        params.insert("height".into(), ParamValue::Int(40));
        let seen: Arc<Mutex<Vec<f32>>> = Arc::default();
        let sink = seen.clone();
        let progress: depthgraph_graph::node::ProgressFn = Arc::new(move |_, f| {
            if let Ok(mut v) = sink.lock() {
                v.push(f);
            }
        });
        let cancel = CancelToken::new();
        let ctx = EvalCtx {
            node: "s",
            cancel: &cancel,
            progress: Some(&progress),
            out_dir: std::path::Path::new("."),
            input_files: &[],
            derivations: None,
            max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
        };
        let out = node.eval(&ctx, &Inputs::new(), &params).unwrap();
        for port in &node.schema().outputs {
            let v = &out.values[port.name];
            assert_eq!(v.value_type(), port.ty, "port {}", port.name);
            if let Some(dims) = v.image_dims() {
                assert_eq!(dims, (40, 40));
            }
        }
        let seen = seen.lock().unwrap().clone();
        assert_eq!(seen.len(), 3); // 40 rows in bands of 16
        assert!(seen.windows(2).all(|w| w[0] < w[1]) && seen.last() == Some(&1.0));

        cancel.cancel();
        let ctx = EvalCtx {
            progress: None,
            ..ctx
        };
        assert!(matches!(
            node.eval(&ctx, &Inputs::new(), &params),
            Err(NodeError::Cancelled)
        ));
        let mut bad = SyntheticSceneParams::default().to_values();
        bad.insert("preset".into(), ParamValue::Text("nope".into()));
        assert!(SyntheticSceneParams::from_values(&bad).is_err());
        assert!(Scene::preset("nope", 8, 8).is_none());
    }

    /// With `pixel_area`, a lens too small to blur gives the box-filtered
    /// pinhole image (the supersampled render) rather than the centre
    /// samples: the error against the 4x4 supersampled render is a
    /// fraction of the centre samples' error against it, and without the
    /// flag the rays still give the centre samples (the pinhole render).
    #[test]
    fn thin_lens_rays_over_the_pixel_area_give_the_box_filtered_image() {
        let scene = Scene::preset("tabletop", 64, 48).unwrap();
        let boxed = render(&scene, &RenderOptions { supersample: 4 });
        let centred = render(&scene, &RenderOptions::default());
        let lens = |pixel_area: bool| ThinLensRender {
            lens: ThinLens {
                focal_length_mm: 50.0,
                f_number: 1000.0,
                focus_m: 2.0,
                sensor_width_mm: 36.0 * 64.0 / 640.0,
            },
            aperture: Aperture::Disc,
            samples: 256,
            seed: 3,
            effects: Default::default(),
            pixel_area,
        };
        let area = render_thin_lens(&scene, &lens(true), |_| Ok(())).unwrap();
        let centre = render_thin_lens(&scene, &lens(false), |_| Ok(())).unwrap();
        let mse = |a: &ColorImage, b: &ColorImage| -> f64 {
            a.as_slice()
                .iter()
                .zip(b.as_slice())
                .flat_map(|(p, q)| {
                    p.iter()
                        .zip(q)
                        .map(|(u, v)| (f64::from(*u) - f64::from(*v)).powi(2))
                })
                .sum::<f64>()
                / a.len() as f64
        };
        let (e_area, e_centre) = (mse(&area, &boxed.color), mse(&centre, &boxed.color));
        eprintln!("area {e_area:e}, centre {e_centre:e}");
        assert!(e_centre > 0.0, "the scene has edges a box filter changes");
        assert!(
            e_area < 0.2 * e_centre,
            "area {e_area:e}, centre {e_centre:e}"
        );
        // the centre path: every ray through the centre, as the pinhole
        let to_pinhole = mse(&centre, &centred.color);
        assert!(to_pinhole < 0.05 * e_centre, "{to_pinhole:e}");
    }

    #[test]
    fn thin_lens_render_tends_to_the_pinhole_and_rejects_bad_lenses() {
        let scene = Scene::preset("tabletop", 48, 36).unwrap();
        let pin = render(&scene, &RenderOptions::default());
        let lens = |f_number: f64, focus_m: f64| ThinLensRender {
            lens: ThinLens {
                focal_length_mm: 50.0,
                f_number,
                focus_m,
                sensor_width_mm: 36.0 * 48.0 / 640.0,
            },
            aperture: Aperture::Disc,
            samples: 16,
            seed: 3,
            effects: Default::default(),
            pixel_area: false,
        };
        // f/1000: the aperture is 0.05 mm, every CoC far below a pixel.
        let tiny = render_thin_lens(&scene, &lens(1000.0, 2.0), |_| Ok(())).unwrap();
        let differing = tiny
            .as_slice()
            .iter()
            .zip(pin.color.as_slice())
            .filter(|(a, b)| {
                a.iter()
                    .zip(b.iter())
                    .any(|(x, y)| (x - y).abs() > 1e-3 * (1.0 + y.abs()))
            })
            .count();
        // Only pixels straddling an edge may see the other side.
        assert!(differing < pin.color.len() / 50, "{differing}");
        // Wide open, the picture changes and stays finite.
        let wide = render_thin_lens(&scene, &lens(1.4, 0.95), |_| Ok(())).unwrap();
        assert!(
            wide.as_slice()
                .iter()
                .flatten()
                .all(|v| v.is_finite() && *v >= 0.0)
        );
        assert_ne!(wide, pin.color);
        let e = render_thin_lens(&scene, &lens(2.0, 0.01), |_| Ok(()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("focus_m"), "{e}");
    }
}
