//! The direct term of an object move (3d-editing §IV.A, eq. 5 split as in
//! [`crate::relight::scene_cached`]): at each target pixel whose cone
//! towards the object meets a VPL,
//!
//! `ΔE_direct = Σ_k Φ_k max(0, n·ω_k) V^t_k (1 - V^o_k)`,
//!
//! the light the object takes away, summed over the VPLs of the pixel's
//! tile in the tile's order. [`relight_moved`](crate::relight::scene_cached::relight_moved)
//! builds a [`DirectPlan`] (every discrete choice made on the CPU: which
//! tiles, which VPLs, in which order, which maps share a frame) and hands
//! it to an evaluator: [`evaluate`] here, or the device's. Both sum each
//! pixel's terms in the plan's order; [`evaluate_pixel`] gives the CPU's
//! bits for one pixel (a device recomputes with it the pixels whose
//! decisions its f32 arithmetic cannot settle).

use glam::DVec3;
use rayon::prelude::*;

use crate::relight::ism::ShadowMap;

/// One target pixel of the direct term: its surface and its cone towards
/// the object (the directions whose ray passes within the object's reach).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirectPixel {
    /// Pixel index `y * width + x`.
    pub index: usize,
    /// Surface point, camera space, metres.
    pub pos: DVec3,
    /// Unit normal.
    pub n: DVec3,
    /// The cone's axis (unit, towards the object; zero when `all`).
    pub cone_axis: DVec3,
    /// The cone holds `d` when `d·axis >= cone_cos_min`.
    pub cone_cos_min: f64,
    /// The pixel lies within the object's reach: every direction counts.
    pub cone_all: bool,
}

impl DirectPixel {
    /// Whether the cone holds the unit direction `d`.
    #[inline]
    pub fn sees(&self, d: DVec3) -> bool {
        self.cone_all || d.dot(self.cone_axis) >= self.cone_cos_min
    }
}

/// The pixels of one tile and the VPLs its cone meets, sorted by object
/// map group and then by index (every pixel sums in this order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DirectTile {
    /// The tile's pixels that have a target surface.
    pub pixels: Vec<DirectPixel>,
    /// VPL indices, grouped by [`DirectLight::group`].
    pub vpls: Vec<usize>,
}

/// One VPL as the direct term reads it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirectLight {
    /// Unit direction towards the light.
    pub dir: DVec3,
    /// Power per channel.
    pub power: [f64; 3],
    /// Its object map, an index into [`DirectPlan::object_maps`].
    pub group: usize,
    /// Bias constant of its object map for a scene surface (times the
    /// slope factor [`slope`]).
    pub bias_object: f64,
    /// Bias constant of its scene map (times the slope factor).
    pub bias_scene: f64,
    /// Its scene map has its object map's frame (one transform serves both).
    pub shared: bool,
}

/// Everything the direct term of one move reads.
#[derive(Debug, Clone)]
pub struct DirectPlan<'a> {
    /// The tiles with at least one pixel to evaluate, in the move's order.
    pub tiles: Vec<DirectTile>,
    /// Per VPL (indices of [`DirectTile::vpls`]).
    pub lights: Vec<DirectLight>,
    /// Per group: the object alone's map.
    pub object_maps: &'a [Option<ShadowMap>],
    /// Per VPL: the scene's map (`None`: the scene occludes nothing).
    pub scene_maps: &'a [Option<ShadowMap>],
    /// The object's centre (a device's origin for its f32 coordinates).
    pub centre: DVec3,
}

/// The direct term at one pixel: what the object takes away, and whether
/// it takes anything.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DirectSum {
    /// `Σ Φ_k cos_k` over the VPLs the object blocks and the scene does not.
    pub de: [f64; 3],
    /// At least one VPL was blocked.
    pub hit: bool,
}

/// The slope factor of the ISM bias, `1 + min(tan θ, 10)` with
/// `cos θ = n·ω > 0` (module docs of [`crate::relight::ism`]).
#[inline]
pub fn slope(cos: f64) -> f64 {
    let c = cos.max(1e-6);
    // guard: c >= 1e-6
    1.0 + ((1.0 - c * c).max(0.0).sqrt() / c).min(10.0)
}

impl DirectPlan<'_> {
    /// Pixels over all tiles.
    pub fn pixel_count(&self) -> usize {
        self.tiles.iter().map(|t| t.pixels.len()).sum()
    }

    /// Per tile: the index of its first pixel in the flat list of sums an
    /// evaluator returns (tile after tile).
    pub fn tile_starts(&self) -> Vec<usize> {
        let mut at = 0usize;
        self.tiles
            .iter()
            .map(|t| {
                let start = at;
                at += t.pixels.len();
                start
            })
            .collect()
    }

    /// Whether the object blocks VPL `j` (`l = lights[j]`) at `px`
    /// (`cos = n·ω_j > 0`, inside the pixel's cone) and the scene does not:
    /// `lc` and `occ` are the light coordinates and the occluder in `j`'s
    /// object map.
    #[inline]
    pub fn takes(
        &self,
        j: usize,
        l: &DirectLight,
        px: &DirectPixel,
        cos: f64,
        lc: DVec3,
        occ: f64,
    ) -> bool {
        // in front of the object's occluder whatever the bias (>= 0): lit
        if occ.is_nan() || occ <= lc.z {
            return false;
        }
        let sl = slope(cos);
        if occ <= lc.z + l.bias_object * sl {
            return false;
        }
        match (self.scene_maps.get(j).and_then(Option::as_ref), l.shared) {
            (Some(m), true) => m.visible_lc(lc, l.bias_scene * sl),
            (Some(m), false) => m.visible(px.pos, l.bias_scene * sl),
            (None, _) => true,
        }
    }

    /// The object map of the run of VPLs starting at `j`.
    fn map_of(&self, j: usize) -> Option<&ShadowMap> {
        self.object_maps
            .get(self.lights[j].group)
            .and_then(Option::as_ref)
    }

    /// The lights of one run, copied next to each other (the inner loop
    /// reads them in order for every pixel of the tile).
    fn run_lights(&self, run: &[usize], into: &mut Vec<(usize, DirectLight)>) {
        into.clear();
        into.extend(run.iter().map(|&j| (j, self.lights[j])));
    }

    /// Adds one run's terms (VPLs of one object map, in order) at `px`.
    #[inline(always)]
    fn add_run(
        &self,
        lights: &[(usize, DirectLight)],
        om: &ShadowMap,
        px: &DirectPixel,
        out: &mut DirectSum,
    ) {
        // (light coordinates, occluder) once looked up
        let mut looked: Option<(DVec3, f64)> = None;
        let (n, axis, cos_min, all) = (px.n, px.cone_axis, px.cone_cos_min, px.cone_all);
        let mut de = out.de;
        let mut hit = false;
        for (j, l) in lights {
            let cos = n.dot(l.dir);
            if cos <= 0.0 || !(all || l.dir.dot(axis) >= cos_min) {
                continue;
            }
            let (lc, occ) = *looked.get_or_insert_with(|| {
                let lc = om.light_coords(px.pos);
                (lc, f64::from(om.occluder_lc(lc)))
            });
            if occ == f64::NEG_INFINITY {
                break; // nothing of the object there
            }
            if self.takes(*j, l, px, cos, lc, occ) {
                hit = true;
                for (e, power) in de.iter_mut().zip(l.power) {
                    *e += power * cos;
                }
            }
        }
        out.de = de;
        out.hit |= hit;
    }
}

/// The runs of a tile's VPL list: consecutive VPLs of one object map.
fn runs<'t>(plan: &'t DirectPlan, tile: &'t DirectTile) -> impl Iterator<Item = &'t [usize]> {
    tile.vpls
        .chunk_by(|&a, &b| plan.lights[a].group == plan.lights[b].group)
}

/// The direct term of one tile, VPL-major (one object map in cache at a
/// time); each pixel sums its VPLs in the tile's order.
pub fn evaluate_tile(plan: &DirectPlan, tile: &DirectTile) -> Vec<DirectSum> {
    let mut out = vec![DirectSum::default(); tile.pixels.len()];
    let mut lights = Vec::new();
    for run in runs(plan, tile) {
        let Some(om) = plan.map_of(run[0]) else {
            continue;
        };
        plan.run_lights(run, &mut lights);
        for (px, o) in tile.pixels.iter().zip(out.iter_mut()) {
            plan.add_run(&lights, om, px, o);
        }
    }
    out
}

/// The direct term of pixel `k` of `tile` alone: the bits
/// [`evaluate_tile`] gives it (the same terms in the same order).
pub fn evaluate_pixel(plan: &DirectPlan, tile: &DirectTile, k: usize) -> DirectSum {
    let mut out = DirectSum::default();
    let Some(px) = tile.pixels.get(k) else {
        return out;
    };
    let mut lights = Vec::new();
    for run in runs(plan, tile) {
        if let Some(om) = plan.map_of(run[0]) {
            plan.run_lights(run, &mut lights);
            plan.add_run(&lights, om, px, &mut out);
        }
    }
    out
}

/// The direct term of every pixel of the plan on the CPU, tiles in
/// parallel: one sum per pixel, tile after tile.
pub fn evaluate(plan: &DirectPlan) -> Vec<DirectSum> {
    plan.tiles
        .par_iter()
        .flat_map_iter(|t| evaluate_tile(plan, t))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slope_factor_is_one_facing_the_light_and_capped_at_grazing() {
        assert_eq!(slope(1.0), 1.0);
        // tan 60° = sqrt 3
        assert!((slope(0.5) - (1.0 + 3f64.sqrt())).abs() < 1e-12);
        assert_eq!(slope(0.0), 11.0);
        assert_eq!(slope(-1.0), 11.0);
    }

    #[test]
    fn a_pixel_within_reach_sees_every_direction() {
        let px = DirectPixel {
            index: 0,
            pos: DVec3::ZERO,
            n: DVec3::Z,
            cone_axis: DVec3::ZERO,
            cone_cos_min: -1.0,
            cone_all: true,
        };
        assert!(px.sees(-DVec3::Z));
        let narrow = DirectPixel {
            cone_axis: DVec3::X,
            cone_cos_min: 0.9,
            cone_all: false,
            ..px
        };
        assert!(narrow.sees(DVec3::X));
        assert!(!narrow.sees(DVec3::Y));
    }
}
