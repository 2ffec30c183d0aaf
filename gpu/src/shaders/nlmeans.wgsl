// One NL-means pass of NLMeansInpaint on the device (realistic-depth-blur
// eq. 1, 3, 5): for every target pixel, every candidate of the (2R+1)^2
// search window inside the image, the patch distance (the average of the
// nested box means of depthgraph_nodes' PatchKernel, patch pixels at clamped
// coordinates, per-pixel distances capped), the discontinuity term and the
// far prior, accumulated with the running-maximum trick of the CPU's Acc.
// One invocation per target, candidates in the CPU's order (dy, then dx):
// the same bits on every run.

struct Params {
    w: u32,
    h: u32,
    search: u32,
    patch_r: u32,
    // radii of the (up to three) nested boxes, and how many
    r0: u32,
    r1: u32,
    r2: u32,
    n_boxes: u32,
    coef0: f32,
    coef1: f32,
    coef2: f32,
    cap: f32,
    inv_hc2: f32,
    inv_hd2: f32,
    // 1 / z_ref of the far prior; 0 when off
    inv_ref: f32,
    far: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
// guide features, 4 floats per pixel
@group(0) @binding(1) var<storage, read> guide: array<vec4<f32>>;
// (depth, confidence) per pixel
@group(0) @binding(2) var<storage, read> zc: array<vec2<f32>>;
// 1 for the targets
@group(0) @binding(3) var<storage, read> targets: array<u32>;
// (estimate, confidence, found, 0) per pixel
@group(0) @binding(4) var<storage, read_write> result: array<vec4<f32>>;

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

fn add(a: ptr<function, Acc>, e: f32, conf: f32, prior: f32, v: f32) {
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
    if (!(*a).has_w) {
        (*a).has_w = true;
        (*a).mw = e;
    } else if (e > (*a).mw) {
        let k = exp((*a).mw - e);
        (*a).w = (*a).w * k;
        (*a).wv = (*a).wv * k;
        (*a).mw = e;
    }
    var rel = s;
    if ((*a).mw != (*a).ms) {
        rel = exp(e - (*a).mw);
    }
    let wgt = rel * conf * prior;
    if (wgt > 0.0) {
        (*a).w = (*a).w + wgt;
        (*a).wv = (*a).wv + wgt * v;
        (*a).lo = min((*a).lo, v);
        (*a).hi = max((*a).hi, v);
    }
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let x = i32(gid.x);
    let y = i32(gid.y);
    let i = gid.y * P.w + gid.x;
    if (targets[i] == 0u) {
        result[i] = vec4<f32>(0.0);
        return;
    }
    var acc = Acc(false, 0.0, 0.0, 0.0, false, 0.0, 0.0, 0.0, 3.4e38, -3.4e38);
    let big_r = i32(P.search);
    let r = i32(P.patch_r);
    let zi = zc[i];
    for (var dy = -big_r; dy <= big_r; dy = dy + 1) {
        let yj = y + dy;
        if (yj < 0 || yj >= i32(P.h)) {
            continue;
        }
        for (var dx = -big_r; dx <= big_r; dx = dx + 1) {
            let xj = x + dx;
            if (xj < 0 || xj >= i32(P.w)) {
                continue;
            }
            // box sums of the capped per-pixel distances (compensated)
            var b0 = vec2<f32>(0.0);
            var b1 = vec2<f32>(0.0);
            var b2 = vec2<f32>(0.0);
            for (var v = -r; v <= r; v = v + 1) {
                let py = clampi(y + v, P.h);
                let qy = clampi(y + v + dy, P.h);
                for (var u = -r; u <= r; u = u + 1) {
                    let p = py * P.w + clampi(x + u, P.w);
                    let q = qy * P.w + clampi(x + u + dx, P.w);
                    let dg = guide[p].xyz - guide[q].xyz;
                    var d = dot(dg, dg) * P.inv_hc2;
                    let cc = zc[p].y * zc[q].y;
                    if (cc > 0.0) {
                        // cc dz^2 / h^2 as the square of a capped root, so
                        // no product overflows (the cap leaves it unchanged)
                        let dz = zc[p].x - zc[q].x;
                        let t = min(abs(dz) * sqrt(cc * P.inv_hd2), sqrt(P.cap));
                        d = d + t * t;
                    }
                    d = min(d, P.cap);
                    let m = u32(max(abs(u), abs(v)));
                    if (m <= P.r0) {
                        b0 = kahan_add(b0, d);
                    }
                    if (P.n_boxes > 1u && m <= P.r1) {
                        b1 = kahan_add(b1, d);
                    }
                    if (P.n_boxes > 2u && m <= P.r2) {
                        b2 = kahan_add(b2, d);
                    }
                }
            }
            var dist = P.coef0 * max(b0.x, 0.0);
            if (P.n_boxes > 1u) {
                dist = dist + P.coef1 * max(b1.x, 0.0);
            }
            if (P.n_boxes > 2u) {
                dist = dist + P.coef2 * max(b2.x, 0.0);
            }
            // the CPU's DepthKernel
            let j = u32(yj) * P.w + u32(xj);
            let cj = zc[j].y;
            if (cj <= 0.0) {
                add(&acc, -dist, 0.0, 1.0, 0.0);
                continue;
            }
            let zj = zc[j].x;
            var xi = 0.0;
            if (zi.y > 0.0) {
                // bounded (1e36) instead of overflowing: its weight is 0 either way
                let t = min(abs(zi.x - zj) * sqrt(P.inv_hd2), 1e18);
                xi = t * t;
            }
            var prior = 1.0;
            if (P.far != 0u) {
                let q = zj * P.inv_ref;
                prior = q * q;
            }
            add(&acc, -(dist + xi), cj, prior, zj);
        }
    }
    // the CPU's Acc::finish
    if (!(acc.w > 0.0) || is_non_finite(acc.w)) {
        result[i] = vec4<f32>(0.0);
        return;
    }
    let est = min(max(acc.wv / acc.w, acc.lo), acc.hi);
    if (!is_valid_depth(est)) {
        result[i] = vec4<f32>(0.0);
        return;
    }
    var conf = 0.0;
    if (acc.sim > 0.0) {
        conf = acc.sim_conf / acc.sim;
    }
    result[i] = vec4<f32>(est, clamp(conf, SMALLEST_NORMAL, 1.0), 1.0, 0.0);
}
