// Relight, scene-cached move: the direct term at each target pixel
// (nodes/src/relight/direct.rs), one invocation per pixel:
//
//   dE = sum_k Phi_k max(0, n.w_k) V^t_k (1 - V^o_k)
//
// over the VPLs of the pixel's tile, in the tile's order (runs of VPLs
// sharing one object map). Coordinates are relative to an origin near the
// object (the host subtracts it in f64), so f32 keeps their small
// differences. Every discrete test (cos > 0, the cone, the texel a point
// falls in, occluder against receiver) whose f32 value lies within its
// rounding bound of the threshold marks the pixel unsure: the host then
// recomputes it with the CPU's own f64 function. The device writes which
// VPLs the object takes (a bit per place of the tile's list); the host adds
// their f64 terms in the list's order, so the sums are the CPU's bits.

struct Params {
    count: u32,
    // invocations per row of the 2-D dispatch
    row: u32,
    // where the pixels' output offsets start in `list`
    offsets: u32,
    _p2: u32,
}

struct Pixel {
    pos: vec3<f32>,       // relative to the origin
    cos_min: f32,         // < -1.5: every direction (the pixel within reach)
    n: vec3<f32>,
    first: u32,           // the tile's VPL list: [first, last)
    axis: vec3<f32>,
    last: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> pixels: array<Pixel>;
@group(0) @binding(2) var<storage, read> list: array<u32>;
@group(0) @binding(3) var<storage, read> lights: array<Light>;
@group(0) @binding(4) var<storage, read> maps: array<Map>;
@group(0) @binding(5) var<storage, read> texels: array<f32>;
@group(0) @binding(6) var<storage, read> stexels: array<f32>;
// per pixel, at its offset (list[P.offsets + k]): a word per 32 places of
// its tile's VPL list, a bit per place (set: the object takes that VPL's
// light here), then a word of flags (2: unsure)
@group(0) @binding(7) var<storage, read_write> out: array<u32>;


@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.y * P.row + gid.x;
    if (gid.x >= P.row || k >= P.count) {
        return;
    }
    let px = pixels[k];
    unsure = false;
    let mag = length(px.pos);
    let base = list[P.offsets + k];
    let words = (px.last - px.first + 31u) / 32u;
    for (var i = 0u; i <= words; i = i + 1u) {
        out[base + i] = 0u;
    }
    var group = NONE;
    var skip_run = false;
    var looked = false;
    var lc = vec3<f32>(0.0);
    var occ = EMPTY;
    // the word of bits being gathered (places only grow along the list:
    // each word is written once, when the next one starts or at the end)
    var word = 0u;
    var bits = 0u;
    for (var q = px.first; q < px.last; q = q + 1u) {
        let j = list[q];
        let l = lights[j];
        if (l.group != group) {
            group = l.group;
            skip_run = false;
            looked = false;
        }
        if (skip_run) {
            continue;
        }
        // a VPL without an object map: the object shadows nothing there
        // (the CPU skips its run too)
        if (l.group == NONE) {
            skip_run = true;
            continue;
        }
        let m = maps[l.group];
        if (m.res == 0u) {
            skip_run = true;
            continue;
        }
        let cos = dot(px.n, l.dir);
        if (abs(cos) < 8.0 * REL) {
            unsure = true;
        }
        if (cos <= 0.0) {
            continue;
        }
        if (px.cos_min > -1.5) {
            let cc = dot(l.dir, px.axis) - px.cos_min;
            if (abs(cc) < 8.0 * REL) {
                unsure = true;
            }
            if (cc < 0.0) {
                continue;
            }
        }
        if (!looked) {
            looked = true;
            lc = light_coords(m, px.pos);
            occ = lookup(m, lc, mag);
        }
        if (occ <= EMPTY) {
            // nothing of the object there: the rest of the run is lit
            skip_run = true;
            continue;
        }
        // in front of the object's occluder whatever the bias: lit
        let scale = abs(occ) + abs(m.z0) + 4.0 * mag;
        let d1 = (occ - m.z0) - lc.z;
        if (near_zero(d1, scale)) {
            unsure = true;
        }
        if (d1 <= 0.0) {
            continue;
        }
        let sl = slope(cos);
        // the slope's own error (near normal incidence, far above rounding)
        let se = slope_err(cos);
        let bo = l.bias_object * sl;
        let d2 = d1 - bo;
        if (near_zero(d2, scale + 16.0 * bo) || abs(d2) <= l.bias_object * se) {
            unsure = true;
        }
        if (d2 <= 0.0) {
            continue;
        }
        // the scene's own map: its light counts only where it is visible
        var visible = true;
        if (l.scene_map != NONE) {
            let sm = maps[l.scene_map];
            var slc = lc;
            if (l.same_frame == 0u) {
                slc = light_coords(sm, px.pos);
            }
            let so = lookup(sm, slc, mag);
            if (so > EMPTY) {
                let bs = l.bias_scene * sl;
                let d3 = (so - sm.z0) - (slc.z + bs);
                if (near_zero(d3, abs(so) + abs(sm.z0) + 4.0 * mag + 16.0 * bs)
                    || abs(d3) <= l.bias_scene * se) {
                    unsure = true;
                }
                visible = d3 <= 0.0;
            }
        }
        if (visible) {
            let b = q - px.first;
            if (b / 32u != word) {
                out[base + word] = bits;
                word = b / 32u;
                bits = 0u;
            }
            bits = bits | (1u << (b % 32u));
        }
    }
    out[base + word] = bits;
    if (unsure) {
        out[base + words] = 2u;
    }
}
