//! The light an object surface receives from the environment's VPLs in an
//! object move (3d-editing §IV.A, eq. 5 on the object's side, split as in
//! [`crate::relight::scene_cached`]): at each object surface,
//!
//! `E^{s+t} = Σ_k Φ_k max(0, n·ω_k) V^t_k V^o_k` and
//! `E^o = Σ_k Φ_k max(0, n·ω_k) V^o_k`,
//!
//! the light with the scene's and the object's own shadows, and with the
//! object's shadows alone (the capture side of the object's shading when
//! the capture map is the target's). [`relight_moved`](crate::relight::scene_cached::relight_moved)
//! builds an [`ObjectLightPlan`] (the maps, the biases, which maps share a
//! frame) and hands it, with a list of surfaces, to an evaluator:
//! [`evaluate`] here, or a device's.
//!
//! A device decides, per surface and VPL, the two visibilities
//! ([`Seen`]) and leaves the sums to the host ([`sums_from_decisions`]),
//! which adds the same f64 terms in the same order as [`evaluate`]: where
//! every decision is the CPU's, the sums are the CPU's bit for bit. A
//! decision the device's f32 arithmetic cannot settle is the host's
//! ([`Seen::Ask`]: [`ObjectLightPlan::seen`] for that VPL).

use depthgraph_graph::prelude::*;
use glam::DVec3;
use rayon::prelude::*;

use crate::relight::contact::{ContactParams, occluded as contact_occluded};
use crate::relight::direct::{DirectLight, slope};
use crate::relight::ism::ShadowMap;
use crate::relight::shading::Surf;

/// One VPL as the object's light reads it: the direct term's
/// [`DirectLight`], with [`DirectLight::bias_object`] the object map's
/// bias constant for the object's own surfaces (its splats' margin
/// included), and `group` `usize::MAX` where the object shadows nothing.
pub type ObjectLight = DirectLight;

/// The photo's depth, for the contact march of the scene's test
/// ([`crate::relight::contact`]).
#[derive(Debug, Clone, Copy)]
pub struct Contact<'a> {
    /// The target photo's depth.
    pub depth: &'a DepthMap,
    /// Its intrinsics.
    pub k: &'a Intrinsics,
    /// The march's parameters.
    pub params: ContactParams,
}

/// Everything the object's light of one move reads.
#[derive(Debug, Clone)]
pub struct ObjectLightPlan<'a> {
    /// Per VPL, in the order every surface sums them.
    pub lights: Vec<ObjectLight>,
    /// Per group: the object alone's map.
    pub object_maps: &'a [Option<ShadowMap>],
    /// Per VPL: the scene's map (`None`: the scene occludes nothing).
    pub scene_maps: &'a [Option<ShadowMap>],
    /// The contact march where the scene's occluder lies within the bias
    /// of the surface (`None`: the map's test alone).
    pub contact: Option<Contact<'a>>,
    /// The object's centre (a device's origin for its f32 coordinates).
    pub centre: DVec3,
}

/// One surface's two sums.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ObjectLightSum {
    /// `E^{s+t}`: the VPLs neither the object nor the scene blocks.
    pub est: [f64; 3],
    /// `E^o`: the VPLs the object does not block.
    pub ecap: [f64; 3],
}

/// A device's decision for one surface and VPL (two bits each).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Seen {
    /// Facing away, or the object blocks it: no term.
    Dark = 0,
    /// The object lets it through, the scene blocks it: `E^o` only.
    ObjectOnly = 1,
    /// The host's call: a test the device could not settle.
    Ask = 2,
    /// Neither blocks it: both sums.
    Both = 3,
}

impl Seen {
    /// The decision of two bits (the low two of `bits`).
    pub fn from_bits(bits: u32) -> Self {
        match bits & 3 {
            0 => Seen::Dark,
            1 => Seen::ObjectOnly,
            2 => Seen::Ask,
            _ => Seen::Both,
        }
    }
}

/// Surfaces per chunk of [`evaluate`]: VPL-major inside a chunk (one pair
/// of maps in cache at a time). 64, not more: the fine lattice's and the
/// exact rest's lists are a few hundred surfaces, and larger chunks left
/// one of the two threads idle on them.
const CHUNK: usize = 64;

impl ObjectLightPlan<'_> {
    /// VPL `j`'s object map.
    #[inline]
    fn object_map(&self, j: usize) -> Option<&ShadowMap> {
        self.object_maps
            .get(self.lights[j].group)
            .and_then(Option::as_ref)
    }

    /// VPL `j`'s scene map.
    #[inline]
    fn scene_map(&self, j: usize) -> Option<&ShadowMap> {
        self.scene_maps.get(j).and_then(Option::as_ref)
    }

    /// The scene's visibility of `s` along VPL `j`: the map's, except
    /// where its occluder lies within the bias of the surface (a wall a
    /// few centimetres away): there the photo's depth decides (the
    /// contact march, when on). `occ` and `z` in the map's light
    /// coordinates; the march reaches the map's occluder (`occ - z` along
    /// `d`) and a texel beyond it (the texel's extent across `d`).
    #[inline]
    fn scene_sees(&self, occ: f64, z: f64, bias: f64, texel: f64, s: &Surf, d: DVec3) -> bool {
        if occ.is_nan() || occ <= z {
            return true;
        }
        if occ > z + bias {
            return false;
        }
        let reach = (occ - z + texel).min(bias);
        match &self.contact {
            Some(c) => !contact_occluded(c.depth, c.k, s.pos, d, reach, &c.params),
            None => true,
        }
    }

    /// `(V^o, V^t)` of `s` for VPL `j` with `cos = n·ω_j > 0`: the
    /// object's own shadow, and the scene's where the object lets the
    /// light through (its light counts only then; `false` otherwise).
    #[inline]
    pub fn seen(&self, j: usize, s: &Surf, cos: f64) -> (bool, bool) {
        let l = &self.lights[j];
        let (sm, omap) = (self.scene_map(j), self.object_map(j));
        match (sm, omap) {
            (Some(a), Some(b)) if l.shared => {
                // the slope (a square root, a division) only where a
                // texel holds an occluder
                let lc = a.light_coords(s.pos);
                let (oo, os) = (f64::from(b.occluder_lc(lc)), f64::from(a.occluder_lc(lc)));
                if oo == f64::NEG_INFINITY && os == f64::NEG_INFINITY {
                    return (true, true);
                }
                let sl = slope(cos);
                let vo = oo.is_nan() || oo <= lc.z + l.bias_object * sl;
                (
                    vo,
                    vo && self.scene_sees(os, lc.z, l.bias_scene * sl, a.texel_m, s, l.dir),
                )
            }
            _ => {
                let sl = slope(cos);
                let vo = omap.is_none_or(|m| m.visible(s.pos, l.bias_object * sl));
                (
                    vo,
                    vo && sm.is_none_or(|m| {
                        let lc = m.light_coords(s.pos);
                        let os = f64::from(m.occluder_lc(lc));
                        self.scene_sees(os, lc.z, l.bias_scene * sl, m.texel_m, s, l.dir)
                    }),
                )
            }
        }
    }
}

/// Adds VPL `l`'s term `Φ cos` to the sums its visibilities admit.
#[inline(always)]
fn add(sum: &mut ObjectLightSum, l: &ObjectLight, cos: f64, vo: bool, vt: bool) {
    if !vo {
        return;
    }
    for ch in 0..3 {
        let e = l.power[ch] * cos;
        sum.ecap[ch] += e;
        if vt {
            sum.est[ch] += e;
        }
    }
}

/// The sums of every surface of `surfs` (in parallel, chunks of surfaces
/// VPL-major inside; every surface sums its VPLs in order).
pub fn evaluate(plan: &ObjectLightPlan, surfs: &[Surf]) -> Vec<ObjectLightSum> {
    surfs
        .par_chunks(CHUNK)
        .flat_map_iter(|chunk| {
            let mut acc = vec![ObjectLightSum::default(); chunk.len()];
            for (j, l) in plan.lights.iter().enumerate() {
                for (s, sum) in chunk.iter().zip(acc.iter_mut()) {
                    let cos = s.n.dot(l.dir);
                    if cos <= 0.0 {
                        continue;
                    }
                    let (vo, vt) = plan.seen(j, s, cos);
                    add(sum, l, cos, vo, vt);
                }
            }
            acc
        })
        .collect()
}

/// The CPU's sums at one surface (the bits [`evaluate`] gives it).
pub fn evaluate_surface(plan: &ObjectLightPlan, s: &Surf) -> ObjectLightSum {
    sums_from_seen(plan, s, |j, cos| plan.seen(j, s, cos))
}

/// The sums at `s` from a decision per VPL: `decide(j, cos)` gives
/// `(V^o, V^t)` for VPL `j` facing the surface (`cos > 0`). The terms and
/// their order are [`evaluate`]'s.
pub fn sums_from_seen(
    plan: &ObjectLightPlan,
    s: &Surf,
    mut decide: impl FnMut(usize, f64) -> (bool, bool),
) -> ObjectLightSum {
    let mut sum = ObjectLightSum::default();
    for (j, l) in plan.lights.iter().enumerate() {
        let cos = s.n.dot(l.dir);
        if cos <= 0.0 {
            continue;
        }
        let (vo, vt) = decide(j, cos);
        add(&mut sum, l, cos, vo, vt);
    }
    sum
}

/// The sums at `s` from a device's decisions `seen(j)`: the host's own
/// decision where the device asks for it ([`Seen::Ask`]). The same bits
/// as [`evaluate_surface`] wherever every decision is the CPU's.
pub fn sums_from_decisions(
    plan: &ObjectLightPlan,
    s: &Surf,
    seen: impl Fn(usize) -> Seen,
) -> ObjectLightSum {
    sums_from_seen(plan, s, |j, cos| match seen(j) {
        Seen::Dark => (false, false),
        Seen::ObjectOnly => (true, false),
        Seen::Both => (true, true),
        Seen::Ask => plan.seen(j, s, cos),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lights() -> Vec<ObjectLight> {
        (0..40)
            .map(|j| {
                let a = j as f64 * 0.37;
                ObjectLight {
                    dir: DVec3::new(a.cos(), 0.8 * (a * 1.3).sin(), a.sin()).normalize(),
                    power: [0.1 + 0.01 * j as f64, 0.2, 0.05 * (j % 3) as f64],
                    group: usize::MAX,
                    bias_object: 0.0,
                    bias_scene: 0.0,
                    shared: false,
                }
            })
            .collect()
    }

    /// The plan of [`lights`] with neither maps nor march.
    fn no_maps() -> ObjectLightPlan<'static> {
        ObjectLightPlan {
            lights: lights(),
            object_maps: &[],
            scene_maps: &[],
            contact: None,
            centre: DVec3::ZERO,
        }
    }

    fn surfaces(n: usize) -> Vec<Surf> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.61;
                Surf {
                    pos: DVec3::new(0.01 * i as f64, 0.0, 2.0),
                    n: DVec3::new(a.sin(), (a * 0.7).cos(), -a.cos()).normalize(),
                }
            })
            .collect()
    }

    #[test]
    fn without_maps_every_facing_vpl_lights_both_sums() {
        let plan = no_maps();
        let surfs = surfaces(150);
        let sums = evaluate(&plan, &surfs);
        assert_eq!(sums.len(), surfs.len());
        let mut lit = 0;
        for (s, sum) in surfs.iter().zip(&sums) {
            let mut want = [0.0f64; 3];
            for l in &plan.lights {
                let cos = s.n.dot(l.dir);
                if cos > 0.0 {
                    for (w, p) in want.iter_mut().zip(l.power) {
                        *w += p * cos;
                    }
                }
            }
            assert_eq!(sum.est, want);
            assert_eq!(sum.ecap, want);
            // the chunked sum is the one-surface sum, bit for bit
            assert_eq!(*sum, evaluate_surface(&plan, s));
            lit += usize::from(want[0] > 0.0);
        }
        assert!(lit > 100, "{lit} lit surfaces");
    }

    #[test]
    fn a_devices_decisions_give_the_sums_they_admit() {
        let plan = no_maps();
        let s = surfaces(7)[5];
        let facing: Vec<usize> = (0..plan.lights.len())
            .filter(|&j| s.n.dot(plan.lights[j].dir) > 0.0)
            .collect();
        assert!(facing.len() >= 4, "{} facing", facing.len());
        let term = |j: usize| {
            let l = &plan.lights[j];
            l.power.map(|p| p * s.n.dot(l.dir))
        };
        // the first facing VPL dark, the second blocked by the scene, the
        // third asked (the host's: no maps, so lit), the rest lit
        let code = |j: usize| match facing.iter().position(|&f| f == j) {
            Some(0) => Seen::Dark,
            Some(1) => Seen::ObjectOnly,
            Some(2) => Seen::Ask,
            _ => Seen::Both,
        };
        let got = sums_from_decisions(&plan, &s, code);
        let all = evaluate_surface(&plan, &s);
        let (a, b) = (term(facing[0]), term(facing[1]));
        for ch in 0..3 {
            let est = all.est[ch] - a[ch] - b[ch];
            let ecap = all.ecap[ch] - a[ch];
            assert!((got.est[ch] - est).abs() <= 1e-12, "{ch}: {got:?}");
            assert!((got.ecap[ch] - ecap).abs() <= 1e-12, "{ch}: {got:?}");
        }
        // every code read back from its two bits
        for c in [Seen::Dark, Seen::ObjectOnly, Seen::Ask, Seen::Both] {
            assert_eq!(Seen::from_bits(c as u32 | 4), c);
        }
    }
}
