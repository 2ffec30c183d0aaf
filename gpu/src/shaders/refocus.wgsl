// Refocus on the device ("realistic depth blur", Sec. 2.3): for each
// aperture view, a forward warp with a z-buffer, the far-prior hole fill,
// and the running average, all on the device; the views' decisions (points,
// active tiles, sources) come from the CPU's plan, unchanged.
//
// The views run in batches (`B.count` views from `B.k0`, each with its own
// z-buffer and view slot): one dispatch warps, gathers or fills every view
// of the batch, and the accumulation adds the batch's views to each pixel
// in view order, so the sum is the same as one view per dispatch.
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
    // view slots allocated (the largest batch)
    slots: u32,
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
    // to the host's 64-byte stride
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

// The views of one batch: k0 .. k0 + count.
struct Batch {
    k0: u32,
    count: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> G: Globals;
@group(0) @binding(1) var<uniform> B: Batch;
// (key index, depth bits, bits of m = 1/u - 1/z, pixel index) per source:
// the active pixels (key index = pixel), then the background layer's
// entries (key index n + k)
@group(0) @binding(2) var<storage, read> src: array<vec4<u32>>;
// raw linear color, 3 floats per pixel (sanitised here like the CPU's sane())
@group(0) @binding(3) var<storage, read> color: array<f32>;
// (1/z, active flag) per pixel
@group(0) @binding(4) var<storage, read> pix: array<vec2<f32>>;
// per view slot b, from 2 n b: [0, n) depth bits of the nearest arrival;
// [n, 2n) its source index
@group(0) @binding(5) var<storage, read_write> zbuf: array<atomic<u32>>;
// per view slot b, from 2 n b: [0, n) (r, g, b, 1/z) of the warped view;
// [n, 2n).x its certainty
@group(0) @binding(6) var<storage, read_write> view: array<vec4<f32>>;
// [0, n): running sum of the views; [n, 2n): its compensation (Kahan)
@group(0) @binding(7) var<storage, read_write> acc: array<vec4<f32>>;
// holes filled per view
@group(0) @binding(8) var<storage, read_write> holes: array<atomic<u32>>;
// the result, 3 floats per pixel
@group(0) @binding(9) var<storage, read_write> out_rgb: array<f32>;
// (r, g, b, 1/z) of the background layer's entry k
@group(0) @binding(10) var<storage, read> layer: array<vec4<f32>>;
// every view's parameters
@group(0) @binding(11) var<storage, read> views: array<ViewParams>;

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

// Where view slot b's arrays start in `zbuf` and `view` (2 n entries a slot).
fn slot(b: u32) -> u32 {
    return 2u * n_px() * b;
}

// The target pixel of source s in view v, or EMPTY when it leaves the image.
fn warp_target(s: vec4<u32>, v: ViewParams) -> u32 {
    let i = s.w;
    let m = bitcast<f32>(s.z);
    let x = f32(i % G.w);
    let y = f32(i / G.w);
    let tx = round_away(x + v.dx * m + v.gx);
    let ty = round_away(y + v.dy * m + v.gy);
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
    for (var b = 0u; b < G.slots; b = b + 1u) {
        atomicStore(&zbuf[slot(b) + t], EMPTY);
        atomicStore(&zbuf[slot(b) + n_px() + t], EMPTY);
    }
    acc[t] = vec4<f32>(0.0);
    acc[n_px() + t] = vec4<f32>(0.0);
}

// One invocation per (view of the batch, source).
@compute @workgroup_size(256)
fn warp_depth(@builtin(global_invocation_id) gid: vec3<u32>) {
    let id = src_id(gid);
    if (id >= G.n_src * B.count) {
        return;
    }
    let b = id / G.n_src;
    let s = src[id % G.n_src];
    let t = warp_target(s, views[B.k0 + b]);
    if (t != EMPTY) {
        atomicMin(&zbuf[slot(b) + t], s.y);
    }
}

@compute @workgroup_size(256)
fn warp_index(@builtin(global_invocation_id) gid: vec3<u32>) {
    let id = src_id(gid);
    if (id >= G.n_src * B.count) {
        return;
    }
    let b = id / G.n_src;
    let s = src[id % G.n_src];
    let t = warp_target(s, views[B.k0 + b]);
    if (t != EMPTY && atomicLoad(&zbuf[slot(b) + t]) == s.y) {
        atomicMin(&zbuf[slot(b) + n_px() + t], s.x);
    }
}

// A (view of the batch, pixel) invocation: whether it has one, the view
// b within the batch, the pixel t and where b's slot starts.
struct SlotPixel {
    valid: bool,
    b: u32,
    t: u32,
    o: u32,
}

fn slot_pixel(gid: vec3<u32>) -> SlotPixel {
    let id = src_id(gid);
    let n = n_px();
    let b = id / n;
    return SlotPixel(id < n * B.count, b, id % n, slot(b));
}

// The winners of the z-buffer become the view; the z-buffer is reset for
// the next batch. One invocation per (view of the batch, pixel).
@compute @workgroup_size(256)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>) {
    let q = slot_pixel(gid);
    if (!q.valid) {
        return;
    }
    let n = n_px();
    let t = q.t;
    let o = q.o;
    let i = atomicLoad(&zbuf[o + n + t]);
    atomicStore(&zbuf[o + t], EMPTY);
    atomicStore(&zbuf[o + n + t], EMPTY);
    if (i == EMPTY) {
        view[o + t] = vec4<f32>(0.0);
        view[o + n + t] = vec4<f32>(0.0);
    } else if (i >= n) {
        view[o + t] = layer[i - n];
        view[o + n + t] = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    } else {
        view[o + t] = vec4<f32>(src_color(i), pix[i].x);
        view[o + n + t] = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    }
}

struct Hit {
    found: bool,
    // the pixel's index within its view slot
    j: u32,
    dist: f32,
}

// The first known pixel of slot o's view from t along (sx, sy), not t itself.
fn march(o: u32, t: u32, sx: f32, sy: f32) -> Hit {
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
        if (view[o + n_px() + j].x > 0.0) {
            return Hit(true, j, k);
        }
    }
    return Hit(false, 0u, 0.0);
}

// The fill of hole t in slot o's view v (the CPU's fill_one): the far end
// along the view's shift, or both ends of a crack blended with the far
// prior's weights.
fn fill(o: u32, t: u32, v: ViewParams) -> vec3<f32> {
    let a = march(o, t, v.sx, v.sy);
    let b = march(o, t, -v.sx, -v.sy);
    var use_a = a.found;
    var use_b = b.found;
    // both ways leave the frame: the input's own colour (the CPU's fill_one)
    if (!use_a && !use_b) {
        return src_color(t);
    }
    if (use_a && use_b) {
        let va = view[o + a.j].w;
        let vb = view[o + b.j].w;
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
        v_far = min(v_far, view[o + a.j].w);
    }
    if (use_b) {
        v_far = min(v_far, view[o + b.j].w);
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
        let zeta = view[o + n_px() + h.j].x;
        let vj = view[o + h.j].w;
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
        csum = csum + wt * view[o + h.j].xyz;
    }
    if (wsum > 0.0 && !is_non_finite(wsum)) {
        return csum / wsum;
    }
    // Unreachable (every end has certainty 1 and the farthest prior 1);
    // the CPU's fallback all the same: the first end's color.
    if (use_a) {
        return view[o + a.j].xyz;
    }
    return view[o + b.j].xyz;
}

// Whether the ray from view v's aperture point to pixel t passes the lens
// barrel (always without one).
fn barrel_open(t: u32, v: ViewParams) -> bool {
    if (G.barrel == 0u) {
        return true;
    }
    let px = v.bx + G.per_px * (f32(t % G.w) + 0.5);
    let py = v.by + G.per_px * (f32(t / G.w) + 0.5);
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
// every active hole's fill written into its view's colour, one invocation
// per (view of the batch, pixel). Its certainty stays 0, and the fills read
// only certain pixels, so no fill sees another.
@compute @workgroup_size(256)
fn fill_store(@builtin(global_invocation_id) gid: vec3<u32>) {
    let q = slot_pixel(gid);
    if (!q.valid) {
        return;
    }
    let t = q.t;
    let o = q.o;
    if (pix[t].y == 0.0 || view[o + n_px() + t].x > 0.0) {
        return;
    }
    let v = views[B.k0 + q.b];
    atomicAdd(&holes[v.k], 1u);
    view[o + t] = vec4<f32>(fill(o, t, v), view[o + t].w);
}

// The colour a channel reads at pixel j of slot o's filled view: the input
// at pixels no view moves (they hold it in every view).
fn view_rgb(o: u32, j: u32) -> vec3<f32> {
    if (pix[j].y == 0.0) {
        return src_color(j);
    }
    return view[o + j].xyz;
}

// Slot o's filled view at (x, y) - e, bilinear, edges clamped (the CPU's
// lens::bilinear).
fn read_at(o: u32, x: u32, y: u32, e: vec2<f32>) -> vec3<f32> {
    let fx = clamp(f32(x) - e.x, 0.0, f32(G.w - 1u));
    let fy = clamp(f32(y) - e.y, 0.0, f32(G.h - 1u));
    let x0 = u32(floor(fx));
    let y0 = u32(floor(fy));
    let x1 = min(x0 + 1u, G.w - 1u);
    let y1 = min(y0 + 1u, G.h - 1u);
    let ax = fx - f32(x0);
    let ay = fy - f32(y0);
    let top = view_rgb(o, y0 * G.w + x0) * (1.0 - ax) + view_rgb(o, y0 * G.w + x1) * ax;
    let bottom = view_rgb(o, y1 * G.w + x0) * (1.0 - ax) + view_rgb(o, y1 * G.w + x1) * ax;
    return top * (1.0 - ay) + bottom * ay;
}

// Second kernel: each active pixel adds, view by view in order, green from
// the view at its place and red and blue from their offsets, for every
// view whose ray the barrel passes.
@compute @workgroup_size(256)
fn accumulate_split(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px() || pix[t].y == 0.0) {
        return;
    }
    let x = t % G.w;
    let y = t / G.w;
    for (var b = 0u; b < B.count; b = b + 1u) {
        let v = views[B.k0 + b];
        if (!barrel_open(t, v)) {
            continue;
        }
        let o = slot(b);
        let here = view[o + t].xyz;
        var r = here.x;
        var bl = here.z;
        let er = vec2<f32>(v.erx, v.ery);
        let eb = vec2<f32>(v.ebx, v.eby);
        if (any(er != vec2<f32>(0.0))) {
            r = read_at(o, x, y, er).x;
        }
        if (any(eb != vec2<f32>(0.0))) {
            bl = read_at(o, x, y, eb).z;
        }
        accumulate(t, vec3<f32>(r, here.y, bl));
    }
}

// Each active pixel, view by view in order: its warped colour or its fill,
// added to the running sum where the barrel passes the view's ray.
@compute @workgroup_size(256)
fn fill_accumulate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = src_id(gid);
    if (t >= n_px() || pix[t].y == 0.0) {
        return;
    }
    for (var b = 0u; b < B.count; b = b + 1u) {
        let v = views[B.k0 + b];
        let o = slot(b);
        let warped = view[o + n_px() + t].x > 0.0;
        if (!warped) {
            atomicAdd(&holes[v.k], 1u);
        }
        // the barrel blocks this view's ray: the pixel gets nothing from it
        if (!barrel_open(t, v)) {
            continue;
        }
        var c: vec3<f32>;
        if (warped) {
            c = view[o + t].xyz;
        } else {
            c = fill(o, t, v);
        }
        accumulate(t, c);
    }
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
    // held within f32's range, as the CPU's exposed_f32 (a bright input
    // times 2^exposure_stops can pass it)
    c = min(c, vec3<f32>(0x1.fffffep+127f));
    out_rgb[3u * t] = c.x;
    out_rgb[3u * t + 1u] = c.y;
    out_rgb[3u * t + 2u] = c.z;
}
