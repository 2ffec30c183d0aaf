// EdgeDetect's strength on the device (3d-editing Sec. III.C): the same
// color and depth terms as depthgraph_nodes::select::edges, in the same f32
// order. The binary edges (threshold and thinning) are the CPU's function
// applied to this strength, so they follow it exactly.

struct Params {
    w: u32,
    h: u32,
    // 0: occlusion term, 1: gradient term
    term: u32,
    _pad: u32,
    wc: f32,
    wd: f32,
    inv_cs: f32,
    inv_ds: f32,
    inv_ks: f32,
    kw: f32,
    _pad1: f32,
    _pad2: f32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> depth: array<f32>;
// gamma-2 encoded color (bilateral_encode.wgsl)
@group(0) @binding(2) var<storage, read> enc: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> strength: array<f32>;

// depth, 0 for holes
fn zs(i: u32) -> f32 {
    let z = depth[i];
    if (is_valid_depth(z)) {
        return z;
    }
    return 0.0;
}

// inverse depth, 0 for holes
fn inv(i: u32) -> f32 {
    let z = zs(i);
    if (z > 0.0) {
        return 1.0 / z;
    }
    return 0.0;
}

fn occlusion(x: i32, y: i32) -> vec2<f32> {
    let wp = inv(u32(y) * P.w + u32(x));
    if (wp <= 0.0) {
        return vec2<f32>(0.0, 0.0);
    }
    var best = 0.0;
    var kink = 0.0;
    var axes = array<vec2<i32>, 4>(vec2<i32>(1, 0), vec2<i32>(0, 1), vec2<i32>(1, 1), vec2<i32>(1, -1));
    for (var k = 0; k < 4; k = k + 1) {
        let d = axes[k];
        let a = vec2<i32>(x, y) - d;
        let b = vec2<i32>(x, y) + d;
        if (a.x < 0 || a.y < 0 || b.x < 0 || b.y < 0 || a.x >= i32(P.w) || b.x >= i32(P.w) || a.y >= i32(P.h) || b.y >= i32(P.h)) {
            continue;
        }
        let wa = inv(u32(a.y) * P.w + u32(a.x));
        let wb = inv(u32(b.y) * P.w + u32(b.x));
        if (wa <= 0.0 || wb <= 0.0) {
            continue;
        }
        let dd = -(wa - 2.0 * wp + wb);
        best = max(best, dd);
        kink = max(kink, -dd);
    }
    // Guard: wp > 0 (checked above).
    return vec2<f32>(best / wp, kink / wp);
}

fn zn(xx: u32, yy: u32, zc: f32) -> f32 {
    let v = zs(yy * P.w + xx);
    if (v > 0.0) {
        return v;
    }
    return zc;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let x = gid.x;
    let y = gid.y;
    let ym = select(y - 1u, 0u, y == 0u);
    let yp = min(y + 1u, P.h - 1u);
    let xm = select(x - 1u, 0u, x == 0u);
    let xp = min(x + 1u, P.w - 1u);
    let tl = enc[ym * P.w + xm].xyz;
    let t = enc[ym * P.w + x].xyz;
    let tr = enc[ym * P.w + xp].xyz;
    let l = enc[y * P.w + xm].xyz;
    let r = enc[y * P.w + xp].xyz;
    let bl = enc[yp * P.w + xm].xyz;
    let b = enc[yp * P.w + x].xyz;
    let br = enc[yp * P.w + xp].xyz;
    let gx = ((tr + 2.0 * r + br) - (tl + 2.0 * l + bl)) * 0.125;
    let gy = ((bl + 2.0 * b + br) - (tl + 2.0 * t + tr)) * 0.125;
    var g2 = 0.0;
    for (var c = 0; c < 3; c = c + 1) {
        g2 = g2 + gx[c] * gx[c] + gy[c] * gy[c];
    }
    let cterm = min(sqrt(g2) * P.inv_cs, 1.0);
    var dterm = 0.0;
    if (P.term == 0u) {
        let gk = occlusion(i32(x), i32(y));
        dterm = max(min(gk.x * P.inv_ds, 1.0), P.kw * min(gk.y * P.inv_ks, 1.0));
    } else {
        let zc = zs(y * P.w + x);
        if (zc > 0.0) {
            let ddx = ((zn(xp, ym, zc) + 2.0 * zn(xp, y, zc) + zn(xp, yp, zc)) - (zn(xm, ym, zc) + 2.0 * zn(xm, y, zc) + zn(xm, yp, zc))) * 0.125;
            let ddy = ((zn(xm, yp, zc) + 2.0 * zn(x, yp, zc) + zn(xp, yp, zc)) - (zn(xm, ym, zc) + 2.0 * zn(x, ym, zc) + zn(xp, ym, zc))) * 0.125;
            // Guard: zc > 0 (checked above).
            dterm = min(sqrt(ddx * ddx + ddy * ddy) / zc * P.inv_ds, 1.0);
        }
    }
    strength[y * P.w + x] = clamp(P.wc * cterm + P.wd * dterm, 0.0, 1.0);
}
