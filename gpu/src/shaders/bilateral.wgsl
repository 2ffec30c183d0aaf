// JointBilateral on the device (3d-editing Sec. III.B): the same weight as
// depthgraph_nodes::depth::bilateral,
//   w(p, q) = 2^-(space + color_coef |C'(p) - C'(q)|^2 + depth_coef(p) (D(q) - D(p))^2),
// exponents in base 2, weights below 2^-24 dropped, holes neither give nor
// receive weight. One invocation per output pixel, a fixed loop order, no
// atomics: the result is the same bits on every run.

struct Params {
    w: u32,
    h: u32,
    r: u32,
    _pad0: u32,
    // log2(e) / (2 sigma_space^2)
    space_coef: f32,
    // log2(e) / (2 sigma_color^2)
    color_coef: f32,
    // log2(e) / (2 sigma_depth_rel^2), divided by z^2 per centre
    depth_scale: f32,
    _pad1: f32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> depth: array<f32>;
// gamma-2 encoded color, 4 floats per pixel (written by `encode`)
@group(0) @binding(2) var<storage, read> enc: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> out_depth: array<f32>;

const CUTOFF_LOG2: f32 = 24.0;
const DEPTH_COEF_MIN: f32 = 1.17549435e-38;
const DEPTH_COEF_MAX: f32 = 1.0e30;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let x = i32(gid.x);
    let y = i32(gid.y);
    let i = gid.y * P.w + gid.x;
    let zc = depth[i];
    if (!is_valid_depth(zc)) {
        out_depth[i] = 0.0;
        return;
    }
    let cc = enc[i].xyz;
    // Guard: zc > 0, so zc^2 >= 0; an underflow to 0 or an overflow of the
    // quotient is clamped like the CPU's f64 clamp.
    let zz = zc * zc;
    var dcoef = DEPTH_COEF_MAX;
    if (zz > 0.0) {
        dcoef = clamp(P.depth_scale / zz, DEPTH_COEF_MIN, DEPTH_COEF_MAX);
    }
    var sw = vec2<f32>(0.0, 0.0);
    var swd = vec2<f32>(0.0, 0.0);
    let r = i32(P.r);
    let y0 = max(y - r, 0);
    let y1 = min(y + r, i32(P.h) - 1);
    let x0 = max(x - r, 0);
    let x1 = min(x + r, i32(P.w) - 1);
    for (var ny = y0; ny <= y1; ny = ny + 1) {
        let dy = ny - y;
        let row = u32(ny) * P.w;
        for (var nx = x0; nx <= x1; nx = nx + 1) {
            let j = row + u32(nx);
            let zn = depth[j];
            if (!is_valid_depth(zn)) {
                continue;
            }
            let dx = nx - x;
            let dc = enc[j].xyz - cc;
            let dz = zn - zc;
            let e = f32(dx * dx + dy * dy) * P.space_coef + P.color_coef * dot(dc, dc) + dcoef * (dz * dz);
            if (e < CUTOFF_LOG2) {
                let wgt = exp2(-e);
                sw = kahan_add(sw, wgt);
                swd = kahan_add(swd, wgt * dz);
            }
        }
    }
    // Guard: the centre is valid with exponent 0, so sw >= 1.
    let v = zc + swd.x / max(sw.x, 1.0);
    if (is_valid_depth(v)) {
        out_depth[i] = v;
    } else {
        out_depth[i] = zc;
    }
}
