//! The fill light of an object move: the scene's own bounce at a target
//! surface and the part of it the object's closed volume blocks
//! ([`crate::relight::shading`]'s `scene_fill`; module docs of
//! [`crate::relight::paired`], "Shadows with their fill light"), over the
//! scene's secondary VPLs `(q, n_q, Φ)`:
//!
//! `F = Σ_q Φ_q max(0, n·v) max(0, -n_q·v) / (r² max(r², r²_min))`, `v = q - x`,
//!
//! and `F_blocked`, the same sum over the VPLs whose segment to `x` passes
//! through the object's volume. [`relight_moved`](crate::relight::scene_cached::relight_moved)
//! hands a [`FillPlan`] and a list of surfaces to an evaluator:
//! [`evaluate`] here, or a device's, which decides per surface and VPL
//! whether it faces the surface and whether the volume blocks it
//! ([`FillSeen`]) and leaves the f64 sums to the host
//! ([`sums_from_decisions`]: the CPU's terms in the CPU's order, so the
//! CPU's bits wherever every decision is the CPU's).

use glam::DVec3;
use rayon::prelude::*;

use crate::relight::closure::ObjectVolume;
use crate::relight::shading::Surf;

/// Everything the fill light of one move reads.
#[derive(Debug, Clone, Copy)]
pub struct FillPlan<'a> {
    /// The scene's secondary VPLs: position, unit normal, flux per channel.
    pub vpls: &'a [(DVec3, DVec3, [f64; 3])],
    /// The clamp of `1 / r²` (metres²).
    pub r2_min: f64,
    /// The object's closed volume.
    pub volume: &'a ObjectVolume<'a>,
}

/// A surface's fill: `F` per channel, then `F_blocked` per channel.
pub type FillSum = [f64; 6];

/// A device's decision for one surface and VPL (two bits each).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FillSeen {
    /// The VPL and the surface do not face each other: no term.
    Away = 0,
    /// Not blocked (a term where the host finds that they face).
    Lit = 1,
    /// The host's call: a test the device could not settle.
    Ask = 2,
    /// Blocked by the object's volume (a term where the host finds that
    /// they face).
    Blocked = 3,
}

impl FillSeen {
    /// The decision of two bits (the low two of `bits`).
    pub fn from_bits(bits: u32) -> Self {
        match bits & 3 {
            0 => FillSeen::Away,
            1 => FillSeen::Lit,
            2 => FillSeen::Ask,
            _ => FillSeen::Blocked,
        }
    }
}

/// VPL `(q, n_q, Φ)`'s term at `s`: the geometry factor `g` (`None` where
/// they do not face each other).
#[inline]
fn geometry(s: &Surf, q: DVec3, nq: DVec3, r2_min: f64) -> Option<f64> {
    let v = q - s.pos;
    let r2 = v.length_squared();
    let (cr, cq) = (s.n.dot(v), -nq.dot(v));
    if r2 < 1e-18 || cr <= 0.0 || cq <= 0.0 {
        return None;
    }
    // guard: r2 >= 1e-18 > 0 and r2_min >= 0
    Some(cr * cq / (r2 * r2.max(r2_min)))
}

/// The sums at `s` with `hidden(j)` saying whether the volume blocks VPL
/// `j` (asked only of the VPLs facing `s`).
fn sums_with(plan: &FillPlan, s: &Surf, mut hidden: impl FnMut(usize) -> bool) -> FillSum {
    let (mut all, mut blocked) = ([0.0f64; 3], [0.0f64; 3]);
    for (j, (q, nq, l)) in plan.vpls.iter().enumerate() {
        let Some(g) = geometry(s, *q, *nq, plan.r2_min) else {
            continue;
        };
        let hid = hidden(j);
        for ch in 0..3 {
            all[ch] += l[ch] * g;
            if hid {
                blocked[ch] += l[ch] * g;
            }
        }
    }
    [all[0], all[1], all[2], blocked[0], blocked[1], blocked[2]]
}

/// The CPU's fill at one surface.
pub fn evaluate_surface(plan: &FillPlan, s: &Surf) -> FillSum {
    sums_with(plan, s, |j| plan.volume.blocks(s.pos, plan.vpls[j].0))
}

/// The CPU's fill at every surface of `surfs` (in parallel).
pub fn evaluate(plan: &FillPlan, surfs: &[Surf]) -> Vec<FillSum> {
    surfs
        .par_iter()
        .map(|s| evaluate_surface(plan, s))
        .collect()
}

/// The sums at `s` from a device's decisions `seen(j)`: the host's own
/// test where the device asks for it ([`FillSeen::Ask`]). The terms and
/// their order are [`evaluate_surface`]'s (the host decides which VPLs
/// face the surface; one the device calls away is asked of the volume
/// should the host's geometry disagree).
pub fn sums_from_decisions(plan: &FillPlan, s: &Surf, seen: impl Fn(usize) -> FillSeen) -> FillSum {
    sums_with(plan, s, |j| match seen(j) {
        FillSeen::Lit => false,
        FillSeen::Blocked => true,
        FillSeen::Away | FillSeen::Ask => plan.volume.blocks(s.pos, plan.vpls[j].0),
    })
}

/// The scene's own bounce at a target surface `(x, n)` from the secondary
/// VPLs read off the photo, and the part of it the object's closed volume
/// blocks (module docs): both with the clamped `1 / max(r², r2_min)` of
/// the bounce. [`evaluate_surface`] of one surface, as two triples.
pub(crate) fn scene_fill(
    x: DVec3,
    n: DVec3,
    vpls: &[(DVec3, DVec3, [f64; 3])],
    r2_min: f64,
    volume: &ObjectVolume,
) -> ([f64; 3], [f64; 3]) {
    let plan = FillPlan {
        vpls,
        r2_min,
        volume,
    };
    let f = evaluate_surface(&plan, &Surf { pos: x, n });
    ([f[0], f[1], f[2]], [f[3], f[4], f[5]])
}
