// The first pass of NLMeansUpsample on the device (realistic-depth-blur
// eq. 4): for every high-resolution pixel i, every candidate j of the
// (2R+1)^2 search window that holds a placed low-resolution sample s(j),
// the weight (1 - alpha) w(i_low, s(j)) + alpha w_u(i, j), summed in the
// log domain (neither term underflows alone), times the spatial falloff
// exp(-|i - j|^2 spatial) when `spatial` > 0:
//
// - w_u: the colour patch distance of NL-means (nested box means of the
//   capped per-pixel guide distances, patch pixels at clamped coordinates);
// - w: the low-resolution depth patch distance (mean over the low patch of
//   c_a c_b dz^2, clamped coordinates) plus the discontinuity term at the
//   centres, over h_depth^2.
//
// One invocation per pixel, candidates in the CPU's order (dy, then dx):
// the same bits on every run. Sums in f32 (the box sums compensated);
// depths above 1e18 m or subnormal never get here (the runner sends such
// jobs to the CPU), so no square overflows.

struct Params {
    k: Patch,
    lw: u32,
    lh: u32,
    low_patch: u32,
    // 1 when alpha > 0 (the colour term exists), 1 when alpha < 1 (the depth term)
    has_color: u32,
    has_depth: u32,
    inv_low_area: f32,
    // ln(alpha), ln(1 - alpha) where the terms exist
    ln_alpha: f32,
    ln_one_minus_alpha: f32,
    // the spatial falloff 1 / (2 sigma^2), pixels^-2 (0: none)
    spatial: f32,
    // to a multiple of 16 bytes
    pad0: f32,
    pad1: f32,
    pad2: f32,
}

const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> P: Params;
// high-resolution guide features, 4 floats per pixel
@group(0) @binding(1) var<storage, read> guide: array<vec4<f32>>;
// low-resolution (depth, confidence)
@group(0) @binding(2) var<storage, read> low: array<vec2<f32>>;
// per high-resolution pixel, its placed low-resolution sample or NONE
@group(0) @binding(3) var<storage, read> sample_at: array<u32>;
// low-resolution column of each high-resolution column, then row of each
// row (w + h entries), NONE outside
@group(0) @binding(4) var<storage, read> lo_axis: array<u32>;
// (estimate, confidence, found, 0) per pixel
@group(0) @binding(5) var<storage, read_write> result: array<vec4<f32>>;

// -ln w(a, b) of two low-resolution pixels (the CPU's low_distance).
fn low_distance(a: u32, b: u32) -> f32 {
    let ax = i32(a % P.lw);
    let ay = i32(a / P.lw);
    let bx = i32(b % P.lw);
    let by = i32(b / P.lw);
    let r = i32(P.low_patch);
    var s = vec2<f32>(0.0);
    for (var ky = -r; ky <= r; ky = ky + 1) {
        let ra = clampi(ay + ky, P.lh) * P.lw;
        let rb = clampi(by + ky, P.lh) * P.lw;
        for (var kx = -r; kx <= r; kx = kx + 1) {
            let pa = low[ra + clampi(ax + kx, P.lw)];
            let pb = low[rb + clampi(bx + kx, P.lw)];
            let cc = pa.y * pb.y;
            if (cc > 0.0) {
                let dz = pa.x - pb.x;
                s = kahan_add(s, cc * dz * dz);
            }
        }
    }
    var dist = s.x * P.inv_low_area * P.k.inv_hd2;
    let ca = low[a];
    let cb = low[b];
    if (ca.y > 0.0 && cb.y > 0.0) {
        let dz = ca.x - cb.x;
        dist = dist + dz * dz * P.k.inv_hd2;
    }
    return dist;
}

// ln(exp(a) + exp(b)) of two exponents, each one present or not.
fn log_add_exp(a: f32, has_a: bool, b: f32, has_b: bool) -> vec2<f32> {
    if (!has_a && !has_b) {
        return vec2<f32>(0.0, 0.0);
    }
    if (!has_b) {
        return vec2<f32>(a, 1.0);
    }
    if (!has_a) {
        return vec2<f32>(b, 1.0);
    }
    let hi = max(a, b);
    let lo = min(a, b);
    return vec2<f32>(hi + log(1.0 + exp(lo - hi)), 1.0);
}

// The capped colour distance of patch pixels p and q, for `patch_distance`.
fn pixel_distance(p: u32, q: u32) -> f32 {
    let dg = guide[p].xyz - guide[q].xyz;
    return min(dot(dg, dg) * P.k.inv_hc2, P.k.cap);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.k.w || gid.y >= P.k.h) {
        return;
    }
    let x = i32(gid.x);
    let y = i32(gid.y);
    let i = gid.y * P.k.w + gid.x;
    var acc = acc_empty();
    let big_r = i32(P.k.search);
    let lx = lo_axis[gid.x];
    let ly = lo_axis[P.k.w + gid.y];
    let centre_low = lx != NONE && ly != NONE;
    // The falloff relative to the nearest source's: a shift common to all
    // of the pixel's candidates (their ratios are unchanged), so that the
    // candidates that carry the weight add small terms to their exponent.
    // Unshifted, `d^2 spatial` reaches 1e6 (the cap) where f32 keeps 1/16:
    // the colour and depth terms of tied nearest samples would be lost.
    var d2_min = 0;
    if (P.spatial > 0.0) {
        d2_min = 2 * big_r * big_r + 1;
        for (var dy = -big_r; dy <= big_r; dy = dy + 1) {
            let yj = y + dy;
            if (yj < 0 || yj >= i32(P.k.h)) {
                continue;
            }
            for (var dx = -big_r; dx <= big_r; dx = dx + 1) {
                let xj = x + dx;
                if (xj < 0 || xj >= i32(P.k.w)) {
                    continue;
                }
                let s = sample_at[u32(yj) * P.k.w + u32(xj)];
                // the sources (confidence > 0): the weights of eq. 4
                if (s != NONE && low[s].y > 0.0) {
                    d2_min = min(d2_min, dx * dx + dy * dy);
                }
            }
        }
    }
    for (var dy = -big_r; dy <= big_r; dy = dy + 1) {
        let yj = y + dy;
        if (yj < 0 || yj >= i32(P.k.h)) {
            continue;
        }
        for (var dx = -big_r; dx <= big_r; dx = dx + 1) {
            let xj = x + dx;
            if (xj < 0 || xj >= i32(P.k.w)) {
                continue;
            }
            let j = u32(yj) * P.k.w + u32(xj);
            let s = sample_at[j];
            if (s == NONE) {
                continue;
            }
            // the colour term: box sums of the capped guide distances
            var color = 0.0;
            if (P.has_color != 0u) {
                let dist = patch_distance(x, y, dx, dy);
                color = P.ln_alpha - dist;
            }
            // the depth term
            var depth = 0.0;
            let has_depth = P.has_depth != 0u && centre_low;
            if (has_depth) {
                depth = P.ln_one_minus_alpha - low_distance(ly * P.lw + lx, s);
            }
            let e = log_add_exp(color, P.has_color != 0u, depth, has_depth);
            if (e.y == 0.0) {
                continue; // both terms absent: weighs nothing
            }
            // the Gaussian falloff with the distance from i to j, relative
            // to the nearest sample's (integers exact in f32:
            // dx^2 + dy^2 <= 2 * 30^2)
            var ln_w = e.x;
            if (P.spatial > 0.0) {
                ln_w = ln_w - f32(dx * dx + dy * dy - d2_min) * P.spatial;
            }
            let zs = low[s];
            add(&acc, ln_w, zs.y, 0.0, zs.x);
        }
    }
    result[i] = finish(acc);
}
