// The running sums of one NL-means target (the CPU's `Acc` of
// depthgraph_nodes' nlmeans::pass, in f32), shared by `nlmeans.wgsl` and
// `nlmeans_upsample.wgsl` (each kernel's source is common.wgsl, this file,
// then its own), the patch kernel both kernels' uniforms start with
// (`Patch`, the Rust `PatchUniform` of gpu/src/nlmeans.rs), and the patch
// distance of both: each kernel declares its uniform `P` (whose member `k`
// is the `Patch`) and its own `pixel_distance(p, q)`.

// The grid and patch kernel of an NL-means pass.
struct Patch {
    w: u32,
    h: u32,
    search: u32,
    patch_r: u32,
    // radii of the (up to three) nested boxes, and how many
    r0: u32,
    r1: u32,
    r2: u32,
    n_boxes: u32,
    // weight of one pixel of each box
    coef0: f32,
    coef1: f32,
    coef2: f32,
    // per-pixel distances are capped here
    cap: f32,
    inv_hc2: f32,
    inv_hd2: f32,
    _pad0: f32,
    _pad1: f32,
}

const SMALLEST_NORMAL: f32 = 1.17549435e-38;

fn clampi(v: i32, n: u32) -> u32 {
    return u32(clamp(v, 0, i32(n) - 1));
}

// The running sums of one target (the CPU's Acc, in f32).
struct Acc {
    has_s: bool,
    ms: f32,
    sim: f32,
    sim_conf: f32,
    has_w: bool,
    mw: f32,
    w: f32,
    wv: f32,
    lo: f32,
    hi: f32,
}

// Adds a candidate with similarity exp(e), confidence `conf` (0 for a
// hole: it counts only in the confidence), log prior `lp` (<= 0 as the
// callers compute it; the CPU's factor `prior = exp(lp)`) and value `v`.
// The weights of eq. 1 are kept in the log domain: exp(e + ln conf + lp)
// relative to the largest such exponent, so the best source weighs 1 and
// none underflows because its factors did (the CPU's product of the three
// in f64 reaches 1e-308 before f32's 1e-38). The estimate is the same
// ratio; the rounding moves from the product to the sum of exponents, a
// few ulps of |e + ln conf + lp|.
fn add(a: ptr<function, Acc>, e: f32, conf: f32, lp: f32, v: f32) {
    // NaN and -inf weigh nothing (the CPU skips them)
    if (is_non_finite(e)) {
        return;
    }
    if (!(*a).has_s) {
        (*a).has_s = true;
        (*a).ms = e;
    } else if (e > (*a).ms) {
        let k = exp((*a).ms - e);
        (*a).sim = (*a).sim * k;
        (*a).sim_conf = (*a).sim_conf * k;
        (*a).ms = e;
    }
    let s = exp(e - (*a).ms);
    (*a).sim = (*a).sim + s;
    if (conf <= 0.0) {
        return;
    }
    (*a).sim_conf = (*a).sim_conf + s * conf;
    // finite: e is, conf is a positive normal f32 (the device path takes
    // no subnormal confidence), lp is bounded by the callers
    let lw = e + log(conf) + lp;
    if (!(*a).has_w) {
        (*a).has_w = true;
        (*a).mw = lw;
    } else if (lw > (*a).mw) {
        let k = exp((*a).mw - lw);
        (*a).w = (*a).w * k;
        (*a).wv = (*a).wv * k;
        (*a).mw = lw;
    }
    let wgt = exp(lw - (*a).mw);
    if (wgt > 0.0) {
        (*a).w = (*a).w + wgt;
        (*a).wv = (*a).wv + wgt * v;
        (*a).lo = min((*a).lo, v);
        (*a).hi = max((*a).hi, v);
    }
}

fn acc_empty() -> Acc {
    return Acc(false, 0.0, 0.0, 0.0, false, 0.0, 0.0, 0.0, 3.4e38, -3.4e38);
}

// The CPU's Acc::finish: (estimate, confidence, 1, 0), or zeros when no
// source had a positive weight.
fn finish(acc: Acc) -> vec4<f32> {
    if (!(acc.w > 0.0) || is_non_finite(acc.w)) {
        return vec4<f32>(0.0);
    }
    let est = min(max(acc.wv / acc.w, acc.lo), acc.hi);
    if (!is_valid_depth(est)) {
        return vec4<f32>(0.0);
    }
    var conf = 0.0;
    if (acc.sim > 0.0) {
        conf = acc.sim_conf / acc.sim;
    }
    return vec4<f32>(est, clamp(conf, SMALLEST_NORMAL, 1.0), 1.0, 0.0);
}

// The patch distance of target (x, y) and candidate (x + dx, y + dy): the
// average of the nested box means (radii r0..r2, pixel weights coef0..2)
// of the capped per-pixel distances, patch pixels at clamped coordinates,
// each box sum compensated (the CPU's PatchKernel over its box sums).
fn patch_distance(x: i32, y: i32, dx: i32, dy: i32) -> f32 {
    let r = i32(P.k.patch_r);
    var b0 = vec2<f32>(0.0);
    var b1 = vec2<f32>(0.0);
    var b2 = vec2<f32>(0.0);
    for (var v = -r; v <= r; v = v + 1) {
        let py = clampi(y + v, P.k.h);
        let qy = clampi(y + v + dy, P.k.h);
        for (var u = -r; u <= r; u = u + 1) {
            let d = pixel_distance(py * P.k.w + clampi(x + u, P.k.w), qy * P.k.w + clampi(x + u + dx, P.k.w));
            let m = u32(max(abs(u), abs(v)));
            if (m <= P.k.r0) {
                b0 = kahan_add(b0, d);
            }
            if (P.k.n_boxes > 1u && m <= P.k.r1) {
                b1 = kahan_add(b1, d);
            }
            if (P.k.n_boxes > 2u && m <= P.k.r2) {
                b2 = kahan_add(b2, d);
            }
        }
    }
    var dist = P.k.coef0 * max(b0.x, 0.0);
    if (P.k.n_boxes > 1u) {
        dist = dist + P.k.coef1 * max(b1.x, 0.0);
    }
    if (P.k.n_boxes > 2u) {
        dist = dist + P.k.coef2 * max(b2.x, 0.0);
    }
    return dist;
}
