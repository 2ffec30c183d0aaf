// Feather on the device (3d-editing Sec. III.C): the separable Gaussian of
// depthgraph_nodes::select::feather, the horizontal pass over every pixel,
// the vertical pass only where the CPU's plan marks a boundary within reach;
// elsewhere the cleaned mask stays bit for bit. Sums are compensated f32.

struct Params {
    w: u32,
    h: u32,
    // kernel radius: taps -r..=r
    r: u32,
    // 1: fade inwards only (min with the mask)
    inside: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
// the cleaned mask (the plan's), 0..1
@group(0) @binding(1) var<storage, read> mask: array<f32>;
// the 2r + 1 normalised taps
@group(0) @binding(2) var<storage, read> taps: array<f32>;
// 1 where the vertical pass runs
@group(0) @binding(3) var<storage, read> near: array<u32>;
@group(0) @binding(4) var<storage, read_write> horiz: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_mask: array<f32>;

@compute @workgroup_size(8, 8)
fn horizontal(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let row = gid.y * P.w;
    var acc = vec2<f32>(0.0, 0.0);
    let r = i32(P.r);
    for (var k = -r; k <= r; k = k + 1) {
        let xx = u32(clamp(i32(gid.x) + k, 0, i32(P.w) - 1));
        acc = kahan_add(acc, taps[u32(k + r)] * mask[row + xx]);
    }
    horiz[row + gid.x] = acc.x;
}

@compute @workgroup_size(8, 8)
fn vertical(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.w || gid.y >= P.h) {
        return;
    }
    let i = gid.y * P.w + gid.x;
    if (near[i] == 0u) {
        out_mask[i] = mask[i];
        return;
    }
    var acc = vec2<f32>(0.0, 0.0);
    let r = i32(P.r);
    for (var k = -r; k <= r; k = k + 1) {
        let yy = u32(clamp(i32(gid.y) + k, 0, i32(P.h) - 1));
        acc = kahan_add(acc, taps[u32(k + r)] * horiz[yy * P.w + gid.x]);
    }
    let b = clamp(acc.x, 0.0, 1.0);
    if (P.inside != 0u) {
        out_mask[i] = min(b, mask[i]);
    } else {
        out_mask[i] = b;
    }
}
