// Refocus on the device ("realistic depth blur", Sec. 2.3): for each
// aperture view, a forward warp with a z-buffer, the far-prior hole fill,
// and the running average, all on the device; the views' decisions (points,
// active tiles, sources) come from the CPU's plan, unchanged.
//
// The z-buffer reproduces the CPU's 64-bit key (depth bits, then source
// index) exactly with two 32-bit atomicMin passes: `warp_depth` keeps the
// smallest depth bits per target, `warp_index` the smallest index among the
// sources that reached that depth. Integer atomics are order-independent,
// and every other kernel writes each pixel from one invocation, so the
// result is the same bits on every run.

struct Globals {
    w: u32,
    h: u32,
    n_src: u32,
    // invocations per row of a 1-D dispatch folded into 2-D
    row: u32,
    // gain / n (the average times 2^exposure_stops)
    scale: f32,
    // 2^exposure_stops
    gain: f32,
    fill_h: f32,
    far_prior: u32,
    // the lens barrel (optical vignetting): on, aperture diameters per
    // pixel, squared radius
    barrel: u32,
    per_px: f32,
    radius2: f32,
    _pad: u32,
}

struct ViewParams {
    // the view's shift per unit of 1/u - 1/z, pixels
    dx: f32,
    dy: f32,
    // the hole fill's unit march step
    sx: f32,
    sy: f32,
    // every source's extra shift (spherical aberration's green focus), px
    gx: f32,
    gy: f32,
    // the barrel test's per-view term: s along - per_px centre
    bx: f32,
    by: f32,
    // longitudinal chromatic aberration: red and blue read the view at
    // (x, y) - e_c, pixels (0 without it)
    erx: f32,
    ery: f32,
    ebx: f32,
    eby: f32,
    k: u32,
}

@group(0) @binding(0) var<uniform> G: Globals;
@group(0) @binding(1) var<uniform> V: ViewParams;
// (key index, depth bits, bits of m = 1/u - 1/z, pixel index) per source:
// the active pixels (key index = pixel), then the background layer's
// entries (key index n + k)
@group(0) @binding(2) var<storage, read> src: array<vec4<u32>>;
// raw linear color, 3 floats per pixel (sanitised here like the CPU's sane())
@group(0) @binding(3) var<storage, read> color: array<f32>;
// (1/z, active flag) per pixel
@group(0) @binding(4) var<storage, read> pix: array<vec2<f32>>;
// [0, n): depth bits of the nearest arrival; [n, 2n): its source index
@group(0) @binding(5) var<storage, read_write> zbuf: array<atomic<u32>>;
// [0, n): (r, g, b, 1/z) of the warped view; [n, 2n).x: certainty
@group(0) @binding(6) var<storage, read_write> view: array<vec4<f32>>;
// [0, n): running sum of the views; [n, 2n): its compensation (Kahan)
@group(0) @binding(7) var<storage, read_write> acc: array<vec4<f32>>;
// holes filled per view
@group(0) @binding(8) var<storage, read_write> holes: array<atomic<u32>>;
// the result, 3 floats per pixel
@group(0) @binding(9) var<storage, read_write> out_rgb: array<f32>;
// (r, g, b, 1/z) of the background layer's entry k
@group(0) @binding(10) var<storage, read> layer: array<vec4<f32>>;

const EMPTY: u32 = 0xffffffffu;

fn sane(v: f32) -> f32 {
    if (is_non_finite(v)) {
        return 0.0;
    }
    return max(v, 0.0);
}

fn src_color(i: u32) -> vec3<f32> {
    return vec3<f32>(sane(color[3u * i]), sane(color[3u * i + 1u]), sane(color[3u * i + 2u]));
}

// Rust's f64::round: halves away from zero (v - trunc(v) is exact, so
// 0.49999997 stays 0 and large integers stay put).
fn round_away(v: f32) -> f32 {
    let t = trunc(v);
    return select(t, t + sign(v), abs(v - t) >= 0.5);
}

fn n_px() -> u32 {
    return G.w * G.h;
}

// The target pixel of source s in this view, or EMPTY when it leaves the image.
fn warp_target(s: vec4<u32>) -> u32 {
    let i = s.w;
    let m = bitcast<f32>(s.z);
    let x = f32(i % G.w);
    let y = f32(i / G.w);
    let tx = round_away(x + V.dx * m + V.gx);
    let ty = round_away(y + V.dy * m + V.gy);
    if (tx < 0.0 || ty < 0.0 || tx >= f32(G.w) || ty >= f32(G.h)) {
        return EMPTY;
    }
    return u32(ty) * G.w + u32(tx);
}

fn src_id(gid: vec3<u32>) -> u32 {
    return gid.y * G.row + gid.x;
}

@compute @workgroup_size(256)
fn clear(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px()) {
        return;
    }
    atomicStore(&zbuf[t], EMPTY);
    atomicStore(&zbuf[n_px() + t], EMPTY);
    acc[t] = vec4<f32>(0.0);
    acc[n_px() + t] = vec4<f32>(0.0);
}

@compute @workgroup_size(256)
fn warp_depth(@builtin(global_invocation_id) gid: vec3<u32>) {
    let id = src_id(gid);
    if (id >= G.n_src) {
        return;
    }
    let s = src[id];
    let t = warp_target(s);
    if (t != EMPTY) {
        atomicMin(&zbuf[t], s.y);
    }
}

@compute @workgroup_size(256)
fn warp_index(@builtin(global_invocation_id) gid: vec3<u32>) {
    let id = src_id(gid);
    if (id >= G.n_src) {
        return;
    }
    let s = src[id];
    let t = warp_target(s);
    if (t != EMPTY && atomicLoad(&zbuf[t]) == s.y) {
        atomicMin(&zbuf[n_px() + t], s.x);
    }
}

// The winners of the z-buffer become the view; the z-buffer is reset for
// the next view.
@compute @workgroup_size(256)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px()) {
        return;
    }
    let n = n_px();
    let i = atomicLoad(&zbuf[n + t]);
    atomicStore(&zbuf[t], EMPTY);
    atomicStore(&zbuf[n + t], EMPTY);
    if (i == EMPTY) {
        view[t] = vec4<f32>(0.0);
        view[n + t] = vec4<f32>(0.0);
    } else if (i >= n) {
        view[t] = layer[i - n];
        view[n + t] = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    } else {
        view[t] = vec4<f32>(src_color(i), pix[i].x);
        view[n + t] = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    }
}

struct Hit {
    found: bool,
    j: u32,
    dist: f32,
}

// The first known pixel from t along (sx, sy), not t itself.
fn march(t: u32, sx: f32, sy: f32) -> Hit {
    let x = f32(t % G.w);
    let y = f32(t / G.w);
    // The step's major component is 1, so the march leaves the image
    // within max(w, h) steps; the bound only makes that explicit.
    let steps = max(G.w, G.h) + 1u;
    for (var n = 1u; n <= steps; n = n + 1u) {
        let k = f32(n);
        let px = round_away(x + k * sx);
        let py = round_away(y + k * sy);
        if (px < 0.0 || py < 0.0 || px >= f32(G.w) || py >= f32(G.h)) {
            break;
        }
        let j = u32(py) * G.w + u32(px);
        if (view[n_px() + j].x > 0.0) {
            return Hit(true, j, k);
        }
    }
    return Hit(false, 0u, 0.0);
}

// The fill of hole t (the CPU's fill_one): the far end along the view's
// shift, or both ends of a crack blended with the far prior's weights.
fn fill(t: u32) -> vec3<f32> {
    let a = march(t, V.sx, V.sy);
    let b = march(t, -V.sx, -V.sy);
    var use_a = a.found;
    var use_b = b.found;
    if (!use_a && !use_b) {
        return vec3<f32>(0.0);
    }
    if (use_a && use_b) {
        let va = view[a.j].w;
        let vb = view[b.j].w;
        let s = va + vb;
        var rel = 0.0;
        // Guard: two sky ends (s = 0) are the same depth.
        if (s > 0.0) {
            rel = abs(va - vb) / s;
        }
        if (G.far_prior != 0u && rel > G.fill_h) {
            if (vb < va) {
                use_a = false;
            } else {
                use_b = false;
            }
        }
    }
    var v_far = 3.4e38;
    if (use_a) {
        v_far = min(v_far, view[a.j].w);
    }
    if (use_b) {
        v_far = min(v_far, view[b.j].w);
    }
    var wsum = 0.0;
    var csum = vec3<f32>(0.0);
    for (var e = 0u; e < 2u; e = e + 1u) {
        var h = a;
        var used = use_a;
        if (e == 1u) {
            h = b;
            used = use_b;
        }
        if (!used) {
            continue;
        }
        let zeta = view[n_px() + h.j].x;
        let vj = view[h.j].w;
        var wt = 0.0;
        if (G.far_prior != 0u) {
            // (v_far / v_j)^2 in [0, 1]; the sky (v = 0) is as far as it gets.
            var prior = 1.0;
            if (vj > 0.0) {
                let q = v_far / vj;
                prior = q * q;
            }
            wt = zeta * prior;
        } else {
            // Guard: dist >= 1 (the march starts one step out).
            wt = zeta / h.dist;
        }
        wsum = wsum + wt;
        csum = csum + wt * view[h.j].xyz;
    }
    if (wsum > 0.0 && !is_non_finite(wsum)) {
        return csum / wsum;
    }
    // Unreachable (every end has certainty 1 and the farthest prior 1);
    // the CPU's fallback all the same: the first end's color.
    if (use_a) {
        return view[a.j].xyz;
    }
    return view[b.j].xyz;
}

// Whether the ray from this view's aperture point to pixel t passes the
// lens barrel (always without one).
fn barrel_open(t: u32) -> bool {
    if (G.barrel == 0u) {
        return true;
    }
    let px = V.bx + G.per_px * (f32(t % G.w) + 0.5);
    let py = V.by + G.per_px * (f32(t / G.w) + 0.5);
    return px * px + py * py <= G.radius2;
}

// Adds view colour c to pixel t's running sum (compensated, see
// common.wgsl's bound).
fn accumulate(t: u32, c: vec3<f32>) {
    let s = acc[t].xyz;
    let comp = acc[n_px() + t].xyz;
    let y = c - comp;
    let sum = s + y;
    acc[n_px() + t] = vec4<f32>((sum - s) - y, 0.0);
    acc[t] = vec4<f32>(sum, 0.0);
}

// Longitudinal chromatic aberration (the CPU's split path), first kernel:
// every active hole's fill written into the view's colour. Its certainty
// stays 0, and the fills read only certain pixels, so no fill sees another.
@compute @workgroup_size(256)
fn fill_store(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px() || pix[t].y == 0.0 || view[n_px() + t].x > 0.0) {
        return;
    }
    atomicAdd(&holes[V.k], 1u);
    view[t] = vec4<f32>(fill(t), view[t].w);
}

// The colour a channel reads at pixel j of the filled view: the input at
// pixels no view moves (they hold it in every view).
fn view_rgb(j: u32) -> vec3<f32> {
    if (pix[j].y == 0.0) {
        return src_color(j);
    }
    return view[j].xyz;
}

// The filled view at (x, y) - e, bilinear, edges clamped (the CPU's
// lens::bilinear).
fn read_at(x: u32, y: u32, e: vec2<f32>) -> vec3<f32> {
    let fx = clamp(f32(x) - e.x, 0.0, f32(G.w - 1u));
    let fy = clamp(f32(y) - e.y, 0.0, f32(G.h - 1u));
    let x0 = u32(floor(fx));
    let y0 = u32(floor(fy));
    let x1 = min(x0 + 1u, G.w - 1u);
    let y1 = min(y0 + 1u, G.h - 1u);
    let ax = fx - f32(x0);
    let ay = fy - f32(y0);
    let top = view_rgb(y0 * G.w + x0) * (1.0 - ax) + view_rgb(y0 * G.w + x1) * ax;
    let bottom = view_rgb(y1 * G.w + x0) * (1.0 - ax) + view_rgb(y1 * G.w + x1) * ax;
    return top * (1.0 - ay) + bottom * ay;
}

// Second kernel: each active pixel the barrel passes adds green from the
// view at its place and red and blue from their offsets.
@compute @workgroup_size(256)
fn accumulate_split(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px() || pix[t].y == 0.0 || !barrel_open(t)) {
        return;
    }
    let x = t % G.w;
    let y = t / G.w;
    let here = view[t].xyz;
    var r = here.x;
    var b = here.z;
    let er = vec2<f32>(V.erx, V.ery);
    let eb = vec2<f32>(V.ebx, V.eby);
    if (any(er != vec2<f32>(0.0))) {
        r = read_at(x, y, er).x;
    }
    if (any(eb != vec2<f32>(0.0))) {
        b = read_at(x, y, eb).z;
    }
    accumulate(t, vec3<f32>(r, here.y, b));
}

@compute @workgroup_size(256)
fn fill_accumulate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px() || pix[t].y == 0.0) {
        return;
    }
    let warped = view[n_px() + t].x > 0.0;
    if (!warped) {
        atomicAdd(&holes[V.k], 1u);
    }
    // the barrel blocks this view's ray: the pixel gets nothing from it
    if (!barrel_open(t)) {
        return;
    }
    var c: vec3<f32>;
    if (warped) {
        c = view[t].xyz;
    } else {
        c = fill(t);
    }
    accumulate(t, c);
}

@compute @workgroup_size(256)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px()) {
        return;
    }
    var c: vec3<f32>;
    if (pix[t].y != 0.0) {
        c = acc[t].xyz * G.scale;
    } else {
        c = src_color(t) * G.gain;
    }
    out_rgb[3u * t] = c.x;
    out_rgb[3u * t + 1u] = c.y;
    out_rgb[3u * t + 2u] = c.z;
}
