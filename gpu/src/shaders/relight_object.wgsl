// Relight, scene-cached move: the object's received light
// (nodes/src/relight/object_light.rs), one invocation per object surface.
// The device decides, for every VPL in order, the two visibilities of
//
//   E^{s+t} = sum_k Phi_k max(0, n.w_k) V^t_k V^o_k,
//   E^o     = sum_k Phi_k max(0, n.w_k) V^o_k,
//
// and writes them as two bits per VPL (0: facing away or the object
// blocks it, 1: the scene blocks it, 3: both let it through, 2: the host
// decides); the host adds the f64 terms, so the sums are the CPU's where
// every decision is. Where the scene's occluder lies within the bias, the
// contact march against the photo's depth decides
// (nodes/src/relight/contact.rs), here too. Every test whose f32 value
// lies within its rounding bound of the threshold makes the decision the
// host's (2).

struct Params {
    count: u32,
    // invocations per row of the 2-D dispatch
    row: u32,
    // VPLs, and the words of two-bit decisions per surface
    lights: u32,
    words: u32,
    // 1: the contact march is on
    contact: u32,
    // the photo's depth: width, height; the march's steps at most
    width: u32,
    height: u32,
    max_steps: u32,
    // the photo's intrinsics
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    // the march's thickness, metres
    thickness: f32,
    _p1: f32,
    _p2: f32,
    _p3: f32,
}

struct Surface {
    pos: vec3<f32>,       // relative to the origin
    _p0: f32,
    n: vec3<f32>,
    _p1: f32,
    at: vec3<f32>,        // camera space (the march's start)
    _p2: f32,
}

// The march's error bounds are tighter than REL's: positions and light
// coordinates carry a few half-ulp roundings of metre-sized terms (f32
// ulp <= 1.2e-7 relative), bounded here by about two ulps of each term.
// REL's 16 ulps would send a march in twenty to the host: its sample
// points move a pixel coordinate by fx / z times their error.
const TIGHT: f32 = 2.5e-7;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> surfaces: array<Surface>;
@group(0) @binding(2) var<storage, read> lights: array<Light>;
@group(0) @binding(3) var<storage, read> maps: array<Map>;
@group(0) @binding(4) var<storage, read> texels: array<f32>;
@group(0) @binding(5) var<storage, read> stexels: array<f32>;
// the photo's depth, row by row (one word when the march is off)
@group(0) @binding(6) var<storage, read> depth: array<f32>;
// per surface: `words` words of decisions (VPL j in bits 2 (j % 16) of
// word j / 16)
@group(0) @binding(7) var<storage, read_write> out: array<u32>;

// The cell of a map's axis holding coordinate `u` in texels (-1 outside:
// the CPU's `!(u >= 0)` and `x >= res`).
fn cell(u: f32, res: u32) -> i32 {
    if (!(u >= 0.0)) {
        return -1;
    }
    let f = floor(u);
    if (f >= f32(res)) {
        return -1;
    }
    return i32(f);
}

// The cells the f64 coordinate may fall in: those of `u` minus and plus
// its rounding bound (the same cell, or two neighbours).
fn axis_span(l: f32, o: f32, inv: f32, res: u32, mag: f32) -> vec2<i32> {
    let u = (l - o) * inv;
    let e = REL * (inv * (mag + abs(o)) + abs(u) + 1.0);
    // a bound of a texel or more could skip a cell between the two: unsure
    if (e >= 0.5) {
        unsure = true;
    }
    return vec2<i32>(cell(u - e, res), cell(u + e, res));
}

// The least and the largest occluder of the texels the point may look up
// (EMPTY outside the map or on an empty texel).
fn occluder_span(m: Map, lc: vec3<f32>, mag: f32) -> vec2<f32> {
    let xs = axis_span(lc.x, m.u0, m.inv_texel, m.res, mag);
    let ys = axis_span(lc.y, m.v0, m.inv_texel, m.res, mag);
    var lo = 3.0e38;
    var hi = -3.0e38;
    for (var a = 0u; a < 2u; a = a + 1u) {
        for (var b = 0u; b < 2u; b = b + 1u) {
            let x = xs[a];
            let y = ys[b];
            var t = EMPTY;
            if (x >= 0 && y >= 0) {
                t = texel_of(m, u32(y) * m.res + u32(x));
            }
            lo = min(lo, t);
            hi = max(hi, t);
        }
    }
    return vec2<f32>(lo, hi);
}

// Marks the decision the host's when `margin` lies within `err` of 0.
fn doubt_if(margin: f32, err: f32) {
    if (abs(margin) <= err) {
        unsure = true;
    }
}

// The photo's surface at the pixel of camera-space point `s` (`e` bounds
// its error): (z, u, v), z = -1 off the image or on a hole (contact.rs
// `surface`: the projection, its floor, the bounds, the sample's validity).
fn surface_at(s: vec3<f32>, e: f32) -> vec3<f32> {
    doubt_if(s.z, e);
    if (s.z <= 0.0) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    let iz = 1.0 / s.z;
    let px = P.fx * s.x * iz + P.cx;
    let py = P.fy * s.y * iz + P.cy;
    // the point's error through the projection, and the projection's own
    // rounding (a few ulps of the coordinate and the principal point)
    let eu = 2.0 * P.fx * e * (1.0 + abs(s.x) * iz) * iz + REL * (abs(px) + abs(P.cx) + 1.0);
    let ev = 2.0 * P.fy * e * (1.0 + abs(s.y) * iz) * iz + REL * (abs(py) + abs(P.cy) + 1.0);
    // off the image whatever the rounding (a long march leaves it far
    // behind): none
    if (px + eu < 0.0 || py + ev < 0.0 || px - eu >= f32(P.width) || py - ev >= f32(P.height)) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    // the pixel's edges (0 and the image's side among them)
    doubt_if(px - round(px), eu);
    doubt_if(py - round(py), ev);
    if (!(px >= 0.0 && py >= 0.0)) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    let u = floor(px);
    let v = floor(py);
    if (u >= f32(P.width) || v >= f32(P.height)) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    let z = depth[u32(v) * P.width + u32(u)];
    if (!is_valid_depth(z)) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    return vec3<f32>(z, u, v);
}

// The depths of two neighbours within 10 % of each other (contact.rs: the
// ratio test; `hi / lo` rounds within an ulp of the f64 quotient).
fn within_ratio(a: f32, b: f32, lim: f32) -> bool {
    let r = max(a, b) / min(a, b);
    doubt_if(r - lim, 4.0 * REL * lim);
    return r <= lim;
}

// How much the surface's depth changes to its four neighbours on it
// (contact.rs `slack`; the differences of depths within 10 % are exact).
fn slack_at(q: vec3<f32>) -> f32 {
    var m = 0.0;
    let u = i32(q.y);
    let v = i32(q.z);
    for (var k = 0; k < 4; k = k + 1) {
        var du = 0;
        var dv = 0;
        if (k == 0) { du = -1; }
        if (k == 1) { du = 1; }
        if (k == 2) { dv = -1; }
        if (k == 3) { dv = 1; }
        let uu = u + du;
        let vv = v + dv;
        if (uu < 0 || vv < 0 || uu >= i32(P.width) || vv >= i32(P.height)) {
            continue;
        }
        let zz = depth[u32(vv) * P.width + u32(uu)];
        if (is_valid_depth(zz) && within_ratio(zz, q.x, 1.1)) {
            m = max(m, abs(zz - q.x));
        }
    }
    return m;
}

// Whether a sample at depth `sz` (error `e`) lies behind the photo's
// surface `q` by more than the footprint `f` and the pixel's slack.
fn behind(sz: f32, q: vec3<f32>, f: f32, e: f32) -> bool {
    let m1 = (sz - f) - q.x;
    let err = e + REL * (abs(sz) + f + q.x);
    doubt_if(m1, err);
    if (m1 <= 0.0) {
        return false;
    }
    let sl = slack_at(q);
    let m2 = m1 - sl;
    doubt_if(m2, err + 4.0 * REL * sl);
    return m2 > 0.0;
}

// Whether the ray from `x` (camera space, error `ex`) along `d` meets the
// photo's surface within `t_max` (error `et`): contact.rs `occluded`, its
// tests in f32 with their rounding bounds (any in doubt: `unsure`).
fn occluded(x: vec3<f32>, ex: f32, d: vec3<f32>, t_max: f32, et: f32) -> bool {
    let f = abs(x.z) / P.fx;
    doubt_if(t_max, et);
    doubt_if(f, 4.0 * REL * abs(x.z) / P.fx + ex / P.fx);
    if (t_max <= 0.0 || f <= 0.0) {
        return false;
    }
    // about two footprints apart
    let q = 0.5 * t_max / f;
    let most = max(P.max_steps, 1u);
    var steps = most;
    if (q <= f32(most) + 1.0) {
        let eq = 0.5 * (et + REL * t_max) / f + REL * q + 0.5 * t_max * ex / (f * f * P.fx);
        doubt_if(q - round(q), eq);
        steps = u32(clamp(ceil(q), 1.0, f32(most)));
    }
    // the last sample in front of the photo's surface (z < 0: none)
    var in_front = vec3<f32>(-1.0, 0.0, 0.0);
    for (var i = 1u; i <= steps; i = i + 1u) {
        let t = t_max * f32(i) / f32(steps);
        let s = x + d * t;
        let es = ex + et + 4.0 * TIGHT * (length(x) + t);
        let q = surface_at(s, es);
        if (q.x < 0.0) {
            in_front = vec3<f32>(-1.0, 0.0, 0.0);
            continue;
        }
        if (behind(s.z, q, f, es)) {
            // inside the surface when close behind it, or when the ray
            // just crossed it
            let mc = P.thickness - (s.z - q.x);
            doubt_if(mc, es + REL * (P.thickness + abs(s.z) + q.x));
            if (mc > 0.0) {
                return true;
            }
            var prev = in_front;
            if (i == 1u) {
                prev = surface_at(x, ex);
                if (prev.x >= 0.0 && behind(x.z, prev, f, ex)) {
                    prev = vec3<f32>(-1.0, 0.0, 0.0);
                }
            }
            if (prev.x >= 0.0) {
                let n = u32(clamp(max(abs(q.y - prev.y), abs(q.z - prev.z)), 1.0, 16.0));
                // 1.1^n by at most 16 products (within 1.5e-6 of the f64
                // power, inside the ratio's band; `pow` may be off by more)
                var lim = 1.0;
                for (var m = 0u; m < n; m = m + 1u) {
                    lim = lim * 1.1;
                }
                if (within_ratio(prev.x, q.x, lim)) {
                    return true;
                }
            }
            in_front = vec3<f32>(-1.0, 0.0, 0.0);
        } else {
            in_front = q;
        }
    }
    return false;
}

// Whether an object occluder `t` (light coordinate; EMPTY: none) blocks the
// light at depth `z` with bias `bo` (within `eb` of the CPU's).
fn object_blocks(t: f32, m: Map, z: f32, bo: f32, eb: f32, mag: f32) -> bool {
    if (t <= EMPTY) {
        return false;
    }
    let d = (t - m.z0) - (z + bo);
    if (near_zero(d, abs(t) + abs(m.z0) + 4.0 * mag + 16.0 * bo) || abs(d) <= eb) {
        unsure = true;
    }
    return d > 0.0;
}

// The scene's occluder `t` at depth `z` with bias `bs` (within `eb` of the
// CPU's), as the CPU's test sees it: its distance beyond the surface (<= 0:
// in front, lit; > bs: blocked; between: the contact march's), and that
// distance's error (the roundings of z0, t - z0 and the light coordinate:
// about an ulp of each term).
fn scene_gap(t: f32, m: Map, z: f32, bs: f32, eb: f32, mag: f32) -> vec2<f32> {
    if (t <= EMPTY) {
        return vec2<f32>(-1.0, 0.0);
    }
    let scale = abs(t) + abs(m.z0) + 4.0 * mag;
    let d1 = (t - m.z0) - z;
    if (near_zero(d1, scale)) {
        unsure = true;
    }
    if (d1 > 0.0 && (near_zero(d1 - bs, scale + 16.0 * bs) || abs(d1 - bs) <= eb)) {
        unsure = true;
    }
    return vec2<f32>(d1, TIGHT * scale);
}

// The scene's decision of a gap (3: lit, 1: blocked, 4: the march's).
fn gap_code(g: f32, bs: f32) -> u32 {
    if (g <= 0.0) {
        return 3u;
    }
    if (g > bs) {
        return 1u;
    }
    if (P.contact != 0u) {
        return 4u;
    }
    return 3u;
}

// The decision for one VPL facing the surface (`cos > 0`; 2 where a test
// is in doubt). A point near a texel's edge is decided with the texels on
// both sides: in doubt only where they decide differently.
fn decide(l: Light, s: Surface, cos: f32, mag: f32) -> u32 {
    unsure = false;
    let sl = slope(cos);
    // the slope's own error (near normal incidence, far above rounding)
    let se = slope_err(cos);
    // the object's own shadow
    if (l.group != NONE) {
        let om = maps[l.group];
        if (om.res != 0u) {
            let lc = light_coords(om, s.pos);
            let span = occluder_span(om, lc, mag);
            let bo = l.bias_object * sl;
            let eb = l.bias_object * se;
            let blocks = object_blocks(span.y, om, lc.z, bo, eb, mag);
            if (object_blocks(span.x, om, lc.z, bo, eb, mag) != blocks) {
                unsure = true;
            }
            if (unsure) {
                return 2u;
            }
            if (blocks) {
                return 0u;
            }
        }
    }
    // the scene's, where the object lets the light through
    if (l.scene_map == NONE) {
        return 3u;
    }
    let sm = maps[l.scene_map];
    // an empty map occludes nothing (the CPU's `occluder_lc` is -inf)
    if (sm.res == 0u) {
        return 3u;
    }
    let slc = light_coords(sm, s.pos);
    let span = occluder_span(sm, slc, mag);
    let bs = l.bias_scene * sl;
    let es = l.bias_scene * se;
    let hi = scene_gap(span.y, sm, slc.z, bs, es, mag);
    let code = gap_code(hi.x, bs);
    if (gap_code(scene_gap(span.x, sm, slc.z, bs, es, mag).x, bs) != code) {
        unsure = true;
    }
    // two texels within the march's band: its reach is either's
    if (code == 4u && span.x != span.y) {
        unsure = true;
    }
    if (unsure) {
        return 2u;
    }
    if (code != 4u) {
        return code;
    }
    // the march reaches the occluder and a texel beyond it, within the bias
    // (the error of the term the minimum takes, or of both where they
    // are within those errors of each other)
    let texel = 1.0 / sm.inv_texel;
    let reach = hi.x + texel;
    let e_reach = hi.y + 2.0 * TIGHT * (texel + reach);
    let e_bias = es + 2.0 * TIGHT * bs;
    let t_max = min(reach, bs);
    var et = e_reach + e_bias;
    if (reach + e_reach < bs - e_bias) {
        et = e_reach;
    } else if (bs + e_bias < reach - e_reach) {
        et = e_bias;
    }
    let ex = TIGHT * length(s.at);
    let blocked = occluded(s.at, ex, l.dir, t_max, et);
    if (unsure) {
        return 2u;
    }
    if (blocked) {
        return 1u;
    }
    return 3u;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.y * P.row + gid.x;
    if (gid.x >= P.row || k >= P.count) {
        return;
    }
    let s = surfaces[k];
    let mag = length(s.pos);
    let base = k * P.words;
    var word = 0u;
    for (var j = 0u; j < P.lights; j = j + 1u) {
        let l = lights[j];
        let cos = dot(s.n, l.dir);
        var code = 0u;
        if (abs(cos) < 8.0 * REL) {
            // the host computes cos (and skips it where <= 0)
            code = 2u;
        } else if (cos > 0.0) {
            code = decide(l, s, cos, mag);
        }
        word = word | (code << (2u * (j % 16u)));
        if (j % 16u == 15u) {
            out[base + j / 16u] = word;
            word = 0u;
        }
    }
    if (P.lights % 16u != 0u) {
        out[base + P.lights / 16u] = word;
    }
}
