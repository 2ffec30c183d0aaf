// OcclusionComposite on the device (3d-editing Sec. IV, III.C): the depth
// test and the alpha blend of depthgraph_nodes::select::composite::pixel.
// The CPU tests z_p > z_t (1 + tolerance) in f64; here the product is f32,
// so a pixel whose two sides lie within 1e-6 of each other (or whose alpha
// is subnormal, which a device may flush) is marked with alpha = -1 and
// the host recomputes it with the CPU's function: the alpha after the test
// is the CPU's at every pixel.

struct Params {
    w: u32,
    h: u32,
    // 1 when the tolerance is 0 (the f32 comparison is then exact)
    exact: u32,
    _pad: u32,
    // 1 + tolerance_rel, rounded to f32
    k: f32,
    _pad1: f32,
    _pad2: f32,
    _pad3: f32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> tc: array<f32>;
@group(0) @binding(2) var<storage, read> tz: array<f32>;
@group(0) @binding(3) var<storage, read> pc: array<f32>;
@group(0) @binding(4) var<storage, read> pz: array<f32>;
@group(0) @binding(5) var<storage, read> pa: array<f32>;
// color (3 floats per pixel), then depth and alpha, packed: [0, 3n) color,
// [3n, 4n) depth, [4n, 5n) alpha
@group(0) @binding(6) var<storage, read_write> out_all: array<f32>;

const RECHECK: f32 = -1.0;

fn rgb(buf: u32, i: u32) -> vec3<f32> {
    if (buf == 0u) {
        return vec3<f32>(tc[3u * i], tc[3u * i + 1u], tc[3u * i + 2u]);
    }
    return vec3<f32>(pc[3u * i], pc[3u * i + 1u], pc[3u * i + 2u]);
}

fn put(i: u32, c: vec3<f32>, z: f32, a: f32) {
    let n = P.w * P.h;
    out_all[3u * i] = c.x;
    out_all[3u * i + 1u] = c.y;
    out_all[3u * i + 2u] = c.z;
    out_all[3u * n + i] = z;
    out_all[4u * n + i] = a;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let i = gid.y * P.w + gid.x;
    let ab = bitcast<u32>(pa[i]);
    if ((ab & 0x7fffffffu) != 0u && (ab & 0x7f800000u) == 0u) {
        put(i, vec3<f32>(0.0), 0.0, RECHECK); // subnormal alpha
        return;
    }
    var a = 0.0;
    if (!is_nan(pa[i])) {
        a = clamp(pa[i], 0.0, 1.0);
    }
    let zp = pz[i];
    let zt = tz[i];
    if (!is_valid_depth(zp)) {
        a = 0.0;
    }
    let t_valid = is_valid_depth(zt);
    if (a > 0.0 && t_valid) {
        if (P.exact != 0u) {
            if (zp > zt) {
                a = 0.0;
            }
        } else {
            let lim = zt * P.k;
            if (abs(zp - lim) <= 1e-6 * lim) {
                put(i, vec3<f32>(0.0), 0.0, RECHECK);
                return;
            }
            if (zp > lim) {
                a = 0.0;
            }
        }
    }
    if (a <= 0.0) {
        put(i, rgb(0u, i), zt, 0.0);
        return;
    }
    if (a >= 1.0) {
        put(i, rgb(1u, i), zp, 1.0);
        return;
    }
    let b = 1.0 - a;
    let c = a * rgb(1u, i) + b * rgb(0u, i);
    var z = zp;
    if (t_valid) {
        z = a * zp + b * zt;
    }
    put(i, c, z, a);
}
