// PullPush and DualPullPush on the device (3d-editing Sec. III.A-B, eq. 2-4):
// the same pyramid as depthgraph_nodes::depth::pull_push, all levels in one
// set of buffers (level r at offset L.f_off / L.c_off). Pull averages 2x2
// blocks (depth over valid children, weight min(1, sum), color over all
// children); push fills each hole of a level from the four nearest coarse
// pixels with bilinear or dual weights. Every pixel is written by one
// invocation: the same bits on every run.

struct Level {
    // the finer level: size and offset into the level buffers
    fw: u32,
    fh: u32,
    f_off: u32,
    // the coarser level
    cw: u32,
    ch: u32,
    c_off: u32,
    // 1 for the dual weights (eq. 2-4)
    dual: u32,
    // 1: `shadow` says per hole whether it takes the background side; 0:
    // every hole does (`shadow` holds one unused word)
    masked: u32,
    epsilon: f32,
    // intrinsics scale of the finer level (2^-r); the coarser is half
    scale_f: f32,
    kfx: f32,
    kfy: f32,
    kcx: f32,
    kcy: f32,
    // background bias (0 = off; dual weights only): strength and edge slope
    beta: f32,
    edge: f32,
}

@group(0) @binding(0) var<uniform> L: Level;
// input depth (metres, raw) and color (3 floats per pixel, raw)
@group(0) @binding(1) var<storage, read> depth_in: array<f32>;
@group(0) @binding(2) var<storage, read> color_in: array<f32>;
// every level: depth, weight (0 = hole), color
@group(0) @binding(3) var<storage, read_write> lz: array<f32>;
@group(0) @binding(4) var<storage, read_write> lw: array<f32>;
@group(0) @binding(5) var<storage, read_write> lc: array<vec4<f32>>;
// results: depth, then the filled mask
@group(0) @binding(6) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_filled: array<f32>;
// the holes the background side applies to in the push, one word per pixel
// of every level (the CPU's shadow_masks), read when L.masked is 1
@group(0) @binding(8) var<storage, read> shadow: array<u32>;

// The mark of a filled pixel: valid for the next finer level (the CPU's
// f64::MIN_POSITIVE; here the smallest normal f32).
const FILLED: f32 = 1.17549435e-38;

// The far factor of the CPU's pull_push (its module docs): samples
// `spacing` input pixels apart; 1 when beta = 0 or z_max <= 0. It may
// underflow to 0 for a large step: the farthest sample keeps 1.
fn far_factor(z: f32, z_max: f32, spacing: f32) -> f32 {
    return far_factor_b(z, z_max, spacing, L.beta);
}

// far_factor with the strength given (the push's, per hole).
fn far_factor_b(z: f32, z_max: f32, spacing: f32, beta: f32) -> f32 {
    if (beta > 0.0 && z_max > 0.0) {
        let f = 0.5 * (L.kfx + L.kfy);
        let s = (z_max - z) * f / (spacing * z_max);
        return exp(-beta * max(s - L.edge, 0.0));
    }
    return 1.0;
}

fn finite_or_zero(v: f32) -> f32 {
    if (is_non_finite(v)) {
        return 0.0;
    }
    return v;
}

@compute @workgroup_size(8, 8)
fn init(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= L.fw || gid.y >= L.fh) {
        return;
    }
    let i = gid.y * L.fw + gid.x;
    let z = depth_in[i];
    if (is_valid_depth(z)) {
        lz[i] = z;
        lw[i] = 1.0;
    } else {
        lz[i] = 0.0;
        lw[i] = 0.0;
    }
    // the color pyramid exists for the dual weights only
    if (L.dual != 0u) {
        lc[i] = vec4<f32>(finite_or_zero(color_in[3u * i]), finite_or_zero(color_in[3u * i + 1u]), finite_or_zero(color_in[3u * i + 2u]), 0.0);
    }
}

@compute @workgroup_size(8, 8)
fn pull(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= L.cw || gid.y >= L.ch) {
        return;
    }
    var sw = 0.0;
    var sb = 0.0;
    var sd = 0.0;
    var n = 0.0;
    var sc = vec3<f32>(0.0);
    var z_max = 0.0;
    for (var dy = 0u; dy < 2u; dy = dy + 1u) {
        for (var dx = 0u; dx < 2u; dx = dx + 1u) {
            let fx = 2u * gid.x + dx;
            let fy = 2u * gid.y + dy;
            if (fx < L.fw && fy < L.fh && lw[L.f_off + fy * L.fw + fx] > 0.0) {
                z_max = max(z_max, lz[L.f_off + fy * L.fw + fx]);
            }
        }
    }
    for (var dy = 0u; dy < 2u; dy = dy + 1u) {
        for (var dx = 0u; dx < 2u; dx = dx + 1u) {
            let fx = 2u * gid.x + dx;
            let fy = 2u * gid.y + dy;
            if (fx >= L.fw || fy >= L.fh) {
                continue;
            }
            let i = L.f_off + fy * L.fw + fx;
            let wt = lw[i];
            sw = sw + wt;
            // the validity weight stays unbiased; the depth average leans far
            let wb = wt * far_factor(lz[i], z_max, 1.0 / L.scale_f);
            sb = sb + wb;
            sd = sd + wb * lz[i];
            if (L.dual != 0u) {
                sc = sc + lc[i].xyz;
            }
            n = n + 1.0;
        }
    }
    let j = L.c_off + gid.y * L.cw + gid.x;
    // Guard: sw, sb > 0 checked; n >= 1 (every coarse pixel has a child).
    if (sw > 0.0 && sb > 0.0) {
        lz[j] = sd / sb;
        lw[j] = min(sw, 1.0);
    } else {
        lz[j] = 0.0;
        lw[j] = 0.0;
    }
    if (L.dual != 0u) {
        lc[j] = vec4<f32>(sc / n, 0.0);
    }
}


@compute @workgroup_size(8, 8)
fn push(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= L.fw || gid.y >= L.fh) {
        return;
    }
    let x = gid.x;
    let y = gid.y;
    let i = L.f_off + y * L.fw + x;
    if (lw[i] > 0.0) {
        return;
    }
    // beta of this hole: the background side for the shadows only
    let beta = select(0.0, L.beta, L.masked == 0u || shadow[i] != 0u);
    // coarse coordinates of the fine pixel centre (exact in f32)
    let cxf = (f32(x) + 0.5) * 0.5 - 0.5;
    let cyf = (f32(y) + 0.5) * 0.5 - 0.5;
    let x0 = min(u32(max(floor(cxf), 0.0)), L.cw - 1u);
    let y0 = min(u32(max(floor(cyf), 0.0)), L.ch - 1u);
    let x1 = min(x0 + 1u, L.cw - 1u);
    let y1 = min(y0 + 1u, L.ch - 1u);
    let fx = clamp(cxf - f32(x0), 0.0, 1.0);
    let fy = clamp(cyf - f32(y0), 0.0, 1.0);
    var nx = array<u32, 4>(x0, x1, x0, x1);
    var ny = array<u32, 4>(y0, y0, y1, y1);
    var nw = array<f32, 4>((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy);
    var z_max = 0.0;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let j = L.c_off + ny[k] * L.cw + nx[k];
        if (lw[j] > 0.0) {
            z_max = max(z_max, lz[j]);
        }
    }
    var bw = 0.0;
    var bd = 0.0;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let j = L.c_off + ny[k] * L.cw + nx[k];
        if (lw[j] > 0.0) {
            let wb = nw[k] * far_factor_b(lz[j], z_max, 2.0 / L.scale_f, beta);
            bw = bw + wb;
            bd = bd + wb * lz[j];
        }
    }
    if (bw <= 0.0) {
        // the bilinear weights can all vanish on a border: plain mean
        var n = 0.0;
        var s = 0.0;
        for (var k = 0u; k < 4u; k = k + 1u) {
            let j = L.c_off + ny[k] * L.cw + nx[k];
            if (lw[j] > 0.0) {
                let f = far_factor_b(lz[j], z_max, 2.0 / L.scale_f, beta);
                n = n + f;
                s = s + f * lz[j];
            }
        }
        if (n == 0.0) {
            return; // no data here: stays a hole
        }
        bw = n;
        bd = s;
    }
    // Guard: bw > 0 ensured above.
    let z_est = bd / bw;
    var value = z_est;
    if (L.dual != 0u) {
        // Pixel centres in input-resolution pixels (exact: scales are powers
        // of two). X_i - X_j = a_i (z_i - z_j) + (a_i - a_j) z_j with
        // a = (u - c) / f, which avoids the cancellation of subtracting two
        // nearly equal unprojected points in f32.
        let ui = vec2<f32>(f32(x) + 0.5, f32(y) + 0.5) / L.scale_f;
        let f = vec2<f32>(L.kfx, L.kfy);
        let ai = (ui - vec2<f32>(L.kcx, L.kcy)) / f;
        let ci = lc[i].xyz;
        var sw = 0.0;
        var sd = 0.0;
        for (var k = 0u; k < 4u; k = k + 1u) {
            let j = L.c_off + ny[k] * L.cw + nx[k];
            if (lw[j] <= 0.0) {
                continue;
            }
            let uj = vec2<f32>(f32(nx[k]) + 0.5, f32(ny[k]) + 0.5) / (0.5 * L.scale_f);
            let dz = z_est - lz[j];
            let dxy = ai * dz + (ui - uj) / f * lz[j];
            // eq. 2 and 3; epsilon > 0
            let wd = 1.0 / (L.epsilon + length(vec3<f32>(dxy, dz)));
            let wc = 1.0 / (L.epsilon + distance(ci, lc[j].xyz));
            let wf = far_factor_b(lz[j], z_max, 2.0 / L.scale_f, beta);
            sw = sw + wd * wc * wf;
            sd = sd + wd * wc * wf * lz[j];
        }
        // Guard: at least one valid neighbour and every weight > 0; a weight
        // is at most 1 / epsilon^2, which f32 holds for epsilon >= 1e-19.
        if (sw > 0.0 && !is_non_finite(sw) && !is_non_finite(sd)) {
            value = sd / sw;
        }
    }
    lz[i] = value;
    lw[i] = FILLED;
}

@compute @workgroup_size(8, 8)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= L.fw || gid.y >= L.fh) {
        return;
    }
    let i = gid.y * L.fw + gid.x;
    let z0 = depth_in[i];
    if (is_valid_depth(z0)) {
        out_depth[i] = z0;
        out_filled[i] = 0.0;
    } else if (lw[i] > 0.0) {
        out_depth[i] = lz[i];
        out_filled[i] = 1.0;
    } else {
        out_depth[i] = 0.0;
        out_filled[i] = 0.0;
    }
}
