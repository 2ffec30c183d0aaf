// Shadow maps of the scene-cached relighting, shared by its kernels
// (relight_direct.wgsl, relight_object.wgsl): the lights and maps as the
// host packs them (gpu/src/relight.rs), the texel lookup and the tests'
// rounding allowances. Lookups read `texels` (the object's maps, per move)
// or `stexels` (the scene's, kept on the device with the cached scene),
// which each kernel binds.

struct Light {
    dir: vec3<f32>,
    bias_object: f32,
    power: vec3<f32>,
    bias_scene: f32,
    group: u32,           // its object map (index into maps)
    scene_map: u32,       // its scene map, or NONE
    same_frame: u32,      // the scene map has the object map's frame
    _pad: u32,
}

struct Map {
    eu: vec3<f32>,
    u0: f32,              // window origin, relative to the origin
    ev: vec3<f32>,
    v0: f32,
    dir: vec3<f32>,
    z0: f32,              // origin . dir
    inv_texel: f32,
    res: u32,             // 0: no map
    offset: u32,          // first texel in its pool
    pool: u32,            // 0: `texels`, 1: `stexels`
}

const NONE: u32 = 0xffffffffu;
// An empty texel (the CPU's -inf) is stored as -1e30; at or below: empty.
const EMPTY: f32 = -1.0e30;
// Relative rounding allowance of a test (about 16 f32 ulps).
const REL: f32 = 1.0e-6;

var<private> unsure: bool;

// The texel index along one axis of a map (-1 outside); `mag` bounds the
// magnitude of the point's relative coordinates.
fn axis_index(l: f32, o: f32, inv: f32, res: u32, mag: f32) -> i32 {
    let u = (l - o) * inv;
    let e = REL * (inv * (mag + abs(o)) + abs(u) + 1.0);
    // outside (NaN too, as the CPU's `!(u >= 0)`)
    if (!(u >= 0.0)) {
        if (u > -e) {
            unsure = true;
        }
        return -1;
    }
    let f = floor(u);
    if (u - f < e || (f + 1.0) - u < e) {
        unsure = true;
    }
    if (f >= f32(res)) {
        return -1;
    }
    return i32(f);
}

// The occluder at light coordinates `lc` of map `m` (EMPTY outside).
fn lookup(m: Map, lc: vec3<f32>, mag: f32) -> f32 {
    let x = axis_index(lc.x, m.u0, m.inv_texel, m.res, mag);
    let y = axis_index(lc.y, m.v0, m.inv_texel, m.res, mag);
    if (x < 0 || y < 0) {
        return EMPTY;
    }
    return texel_of(m, u32(y) * m.res + u32(x));
}

// Texel `i` of map `m`, from its pool.
fn texel_of(m: Map, i: u32) -> f32 {
    if (m.pool == 1u) {
        return stexels[m.offset + i];
    }
    return texels[m.offset + i];
}

fn light_coords(m: Map, p: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(dot(p, m.eu), dot(p, m.ev), dot(p, m.dir));
}

// The ISM bias's slope factor 1 + min(tan, 10) (direct.rs `slope`).
fn slope(cos: f32) -> f32 {
    let c = max(cos, 1.0e-6);
    return 1.0 + min(sqrt(max(1.0 - c * c, 0.0)) / c, 10.0);
}

// The f32 cosine's error bound against the f64 one: each component of the
// two unit vectors is rounded by at most half an ulp (6e-8 of itself), so
// the inputs move the dot by at most 1.2e-7; its three products and two
// sums add at most another 1.2e-7. 4e-7 bounds the 2.4e-7.
const COS_ERR: f32 = 4.0e-7;

// A bound on |slope(cos) - slope(cos64)| for |cos - cos64| <= COS_ERR: the
// slope falls with the cosine, steeply near normal incidence (there the
// tangent is a square root of 1 - cos^2, and a cosine off by an ulp moves
// it by up to about 1e-3), so the bound is its change across the cosine's
// error interval, plus its own rounding (a square, a square root, a
// quotient and a sum: five ulps of the slope, 6e-7 of it).
fn slope_err(cos: f32) -> f32 {
    return slope(cos - COS_ERR) - slope(cos + COS_ERR) + 6.0e-7 * slope(cos);
}

// Whether `d` (occluder minus receiver, plus bias) is within the rounding
// of its terms of 0: then the f64 test may go the other way.
fn near_zero(d: f32, scale: f32) -> bool {
    return abs(d) < REL * scale + 1.0e-12;
}

