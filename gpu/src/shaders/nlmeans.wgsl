// One NL-means pass of NLMeansInpaint on the device (realistic-depth-blur
// eq. 1, 3, 5): for every target pixel, every candidate of the (2R+1)^2
// search window inside the image, the patch distance (the average of the
// nested box means of depthgraph_nodes' PatchKernel, patch pixels at clamped
// coordinates, per-pixel distances capped), the discontinuity term and the
// far prior, accumulated with the running-maximum trick of the CPU's Acc.
// One invocation per target, candidates in the CPU's order (dy, then dx):
// the same bits on every run.

struct Params {
    k: Patch,
    // 1 / z_ref of the far prior; 0 when off
    inv_ref: f32,
    far: u32,
    // background side: strength (0 = off) and edge step
    beta: f32,
    tau: f32,
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

// The capped distance of patch pixels p and q (colour, and depth where both
// have confidence), for `patch_distance`.
fn pixel_distance(p: u32, q: u32) -> f32 {
    let dg = guide[p].xyz - guide[q].xyz;
    var d = dot(dg, dg) * P.k.inv_hc2;
    let cc = zc[p].y * zc[q].y;
    if (cc > 0.0) {
        // cc dz^2 / h^2 as the square of a capped root, so no product
        // overflows (the cap leaves it unchanged)
        let dz = zc[p].x - zc[q].x;
        let t = min(abs(dz) * sqrt(cc * P.k.inv_hd2), sqrt(P.k.cap));
        d = d + t * t;
    }
    return min(d, P.k.cap);
}

// The largest source depth (confidence > 0) of the search window of (x, y)
// inside the image, 0 when it holds none: the CPU's window_max.
fn window_max(x: i32, y: i32) -> f32 {
    let big_r = i32(P.k.search);
    var m = 0.0;
    for (var yj = max(y - big_r, 0); yj <= min(y + big_r, i32(P.k.h) - 1); yj = yj + 1) {
        for (var xj = max(x - big_r, 0); xj <= min(x + big_r, i32(P.k.w) - 1); xj = xj + 1) {
            let q = zc[u32(yj) * P.k.w + u32(xj)];
            if (q.y > 0.0) {
                m = max(m, q.x);
            }
        }
    }
    return m;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.k.w || gid.y >= P.k.h) {
        return;
    }
    let x = i32(gid.x);
    let y = i32(gid.y);
    let i = gid.y * P.k.w + gid.x;
    if (targets[i] == 0u) {
        result[i] = vec4<f32>(0.0);
        return;
    }
    var acc = acc_empty();
    let big_r = i32(P.k.search);
    let zi = zc[i];
    var z_max = 0.0;
    if (P.beta > 0.0) {
        z_max = window_max(x, y);
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
            let dist = patch_distance(x, y, dx, dy);
            // the CPU's DepthKernel
            let j = u32(yj) * P.k.w + u32(xj);
            let cj = zc[j].y;
            if (cj <= 0.0) {
                add(&acc, -dist, 0.0, 0.0, 0.0);
                continue;
            }
            let zj = zc[j].x;
            var xi = 0.0;
            if (zi.y > 0.0) {
                // bounded (1e36) instead of overflowing: its weight is 0 either way
                let t = min(abs(zi.x - zj) * sqrt(P.k.inv_hd2), 1e18);
                xi = t * t;
            }
            // the log of the CPU's prior factor
            var lp = 0.0;
            if (P.far != 0u) {
                // (z_j / z_ref)^2; z_j > 0 (a source), so the log is finite
                lp = 2.0 * log(zj * P.inv_ref);
            }
            if (P.beta > 0.0 && z_max > 0.0) {
                // in [-beta, 0]; 0 for the farthest source of the window
                lp = lp - P.beta * max((z_max - zj) / z_max - P.tau, 0.0);
            }
            add(&acc, -(dist + xi), cj, lp, zj);
        }
    }
    result[i] = finish(acc);
}
