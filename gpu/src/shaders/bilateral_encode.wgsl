// The color planes JointBilateral compares (first pass of bilateral.wgsl).

struct Dims {
    w: u32,
    h: u32,
}

@group(0) @binding(0) var<uniform> D: Dims;
@group(0) @binding(1) var<storage, read> rgb: array<f32>;
@group(0) @binding(2) var<storage, read_write> enc_out: array<vec4<f32>>;

// The gamma-2 encoding of the color distance: sqrt of linear RGB clamped to
// [0, 1], NaN as 0 (bilateral::encode on the CPU).
fn encode1(v: f32) -> f32 {
    if (is_nan(v) || !(v > 0.0)) {
        return 0.0;
    }
    return sqrt(min(v, 1.0));
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= D.w || gid.y >= D.h) {
        return;
    }
    let i = gid.y * D.w + gid.x;
    enc_out[i] = vec4<f32>(encode1(rgb[3u * i]), encode1(rgb[3u * i + 1u]), encode1(rgb[3u * i + 2u]), 0.0);
}
