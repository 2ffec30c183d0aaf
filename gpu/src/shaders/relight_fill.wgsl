// Relight, scene-cached move: the fill light at target surfaces
// (nodes/src/relight/fill.rs), one invocation per surface. For every
// secondary VPL (q, n_q) in order the device decides whether it and the
// surface face each other and whether the segment between them passes
// through the object's closed volume (closure.rs `ObjectVolume::blocks`:
// its chord through the ball, eight points of it, each inside when it lies
// between the front and the back depth at its pixel), and writes two bits
// per VPL (0: they do not face, 1: lit, 3: blocked, 2: the host decides);
// the host decides whether they face and adds the f64 terms. Positions are relative to the ball's centre (the
// host subtracts it in f64), metres; every
// test whose f32 value lies within its rounding bound of the threshold
// leaves the decision to the host.

struct Params {
    count: u32,
    // invocations per row of the 2-D dispatch
    row: u32,
    // VPLs, and the words of two-bit decisions per surface
    vpls: u32,
    words: u32,
    // the volume's depth maps: width, height
    width: u32,
    height: u32,
    _p0: u32,
    _p1: u32,
    // the camera
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    // the ball holding the volume (camera space)
    centre: vec3<f32>,
    radius: f32,
}

struct Surface {
    pos: vec3<f32>,       // relative to the ball's centre
    _p0: f32,
    n: vec3<f32>,
    _p1: f32,
}

struct Vpl {
    q: vec3<f32>,         // relative to the ball's centre
    _p0: f32,
    nq: vec3<f32>,
    _p1: f32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> surfaces: array<Surface>;
@group(0) @binding(2) var<storage, read> vpls: array<Vpl>;
@group(0) @binding(3) var<storage, read> front: array<f32>;
@group(0) @binding(4) var<storage, read> back: array<f32>;
// per surface: `words` words of decisions (VPL j in bits 2 (j % 16) of
// word j / 16)
@group(0) @binding(5) var<storage, read_write> out: array<u32>;

// Rounding allowances: REL (about 16 ulps) for sums of a few terms, TIGHT
// (about two ulps) for a rounded input or one operation.
const REL: f32 = 1.0e-6;
const TIGHT: f32 = 2.5e-7;
// Samples along the chord (closure.rs VOLUME_STEPS).
const STEPS: u32 = 8u;

var<private> unsure: bool;

fn doubt_if(margin: f32, err: f32) {
    if (abs(margin) <= err) {
        unsure = true;
    }
}

// Whether `p` (camera space, error `e`) lies inside the volume
// (closure.rs `contains`).
fn contains(p: vec3<f32>, e: f32) -> bool {
    doubt_if(p.z, e);
    if (p.z <= 0.0) {
        return false;
    }
    let iz = 1.0 / p.z;
    let px = P.fx * p.x * iz + P.cx;
    let py = P.fy * p.y * iz + P.cy;
    let eu = 2.0 * P.fx * e * (1.0 + abs(p.x) * iz) * iz + REL * (abs(px) + abs(P.cx) + 1.0);
    let ev = 2.0 * P.fy * e * (1.0 + abs(p.y) * iz) * iz + REL * (abs(py) + abs(P.cy) + 1.0);
    // off the image whatever the rounding
    if (px + eu < 0.0 || py + ev < 0.0 || px - eu >= f32(P.width) || py - ev >= f32(P.height)) {
        return false;
    }
    doubt_if(px - round(px), eu);
    doubt_if(py - round(py), ev);
    if (!(px >= 0.0 && py >= 0.0)) {
        return false;
    }
    let u = floor(px);
    let v = floor(py);
    if (u >= f32(P.width) || v >= f32(P.height)) {
        return false;
    }
    let i = u32(v) * P.width + u32(u);
    let zf = front[i];
    if (!is_valid_depth(zf)) {
        return false;
    }
    let zb = back[i];
    let m1 = p.z - zf;
    doubt_if(m1, e + 2.0 * TIGHT * (abs(p.z) + abs(zf)));
    if (m1 < 0.0) {
        return false;
    }
    let m2 = zb - p.z;
    doubt_if(m2, e + 2.0 * TIGHT * (abs(p.z) + abs(zb)));
    return m2 >= 0.0;
}

// Whether the segment from `a` to `b` (relative to the centre, each within
// `ea` of its f64 value) passes through the volume (closure.rs `blocks`). The CPU finds the chord
// through the ball from its quadratic in t (f64, close to the exact
// values); here the same numbers come from the line's closest approach to
// the centre, in metres, which f32 keeps far better: `tc` along the unit
// direction, the half chord `hc` from the distance `d` of the line, so
// t0 = (tc - hc) / |v|, t1 = (tc + hc) / |v|, and the disc test is h2 =
// R^2 - d^2 > 0.
fn blocks(a: vec3<f32>, b: vec3<f32>, ea: f32) -> bool {
    let v = b - a;
    let len2 = dot(v, v);
    let dv = sqrt(len2);
    let e_v = 2.0 * ea + TIGHT * dv;
    doubt_if(len2, 4.0 * dv * e_v + 1.0e-30);
    if (len2 <= 0.0) {
        return false;
    }
    let u = v / dv;
    let e_u = e_v / dv + 2.0 * TIGHT;
    // relative to the centre already
    let oc = a;
    let loc = length(oc);
    let e_oc = ea;
    let tc = -dot(oc, u);
    let e_tc = e_oc + loc * e_u + 2.0 * TIGHT * loc;
    let perp = oc + tc * u;
    let d = length(perp);
    let e_perp = e_oc + e_tc + abs(tc) * e_u + 2.0 * TIGHT * (loc + abs(tc));
    let r = P.radius;
    let h2 = r * r - dot(perp, perp);
    let e_h2 = 2.0 * d * e_perp + e_perp * e_perp + 2.0 * TIGHT * (r * r + d * d);
    doubt_if(h2, e_h2);
    if (h2 <= 0.0) {
        return false;
    }
    let hc = sqrt(h2);
    let e_hc = e_h2 / hc + TIGHT * hc;
    // t in units of the segment; the error of both ends
    let et = (e_tc + e_hc) / dv + (abs(tc) + hc) / dv * (e_v / dv + 2.0 * TIGHT) + TIGHT;
    let t0 = max((tc - hc) / dv, 0.01);
    let t1 = min((tc + hc) / dv, 0.99);
    doubt_if(t1 - t0, 2.0 * et);
    if (t0 >= t1) {
        return false;
    }
    for (var j = 0u; j < STEPS; j = j + 1u) {
        let t = t0 + (t1 - t0) * (f32(j) + 0.5) / f32(STEPS);
        let p = a + v * t;
        // back to camera space (the centre's own rounding added)
        let ep = ea + dv * et + e_v * t + 2.0 * TIGHT * (length(a) + dv * t + 2.0 * length(P.centre));
        if (contains(P.centre + p, ep)) {
            return true;
        }
    }
    return false;
}

// The decision for VPL `l` at surface `s` (0, 1, 3; 2 where in doubt).
fn decide(s: Surface, l: Vpl) -> u32 {
    unsure = false;
    let ea = TIGHT * (length(s.pos) + length(l.q));
    let v = l.q - s.pos;
    let r2 = dot(v, v);
    // the CPU's 1e-18 floor lies far below what f32 positions resolve
    if (r2 < 1.0e-10) {
        return 2u;
    }
    let dv = sqrt(r2);
    // a dot of a rounded unit normal with v (its rounding and v's)
    let ec = 4.0e-7 * dv + 2.0 * ea + 2.0 * TIGHT * dv;
    let cr = dot(s.n, v);
    let cq = -dot(l.nq, v);
    // Facing away beyond doubt: no term. Otherwise the volume's decision;
    // whether they face is the host's (it computes the term's geometry in
    // f64 and skips what does not face: coplanar pairs, a floor's surfaces
    // and its VPLs, are decided there by the f64 rounding alone).
    if (cr < -ec || cq < -ec) {
        return 0u;
    }
    let hidden = blocks(s.pos, l.q, ea);
    if (unsure) {
        return 2u;
    }
    if (hidden) {
        return 3u;
    }
    return 1u;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.y * P.row + gid.x;
    if (gid.x >= P.row || k >= P.count) {
        return;
    }
    let s = surfaces[k];
    let base = k * P.words;
    var word = 0u;
    for (var j = 0u; j < P.vpls; j = j + 1u) {
        let code = decide(s, vpls[j]);
        word = word | (code << (2u * (j % 16u)));
        if (j % 16u == 15u) {
            out[base + j / 16u] = word;
            word = 0u;
        }
    }
    if (P.vpls % 16u != 0u) {
        out[base + P.vpls / 16u] = word;
    }
}
