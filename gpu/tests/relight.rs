//! Relight: the device's direct term and object light of a scene-cached
//! move against the CPU's, on the path-traced rooms of
//! `sim::relight_truth`, and the whole node on both backends.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::parity::{direct_within, display_psnr, fill_equal, object_light_equal};
use depthgraph_gpu::relight::{
    DE_TOL, DeviceSums, DirectStats, FillStats, MAX_MARCH_STEPS, ObjectLightStats,
    object_light as object_light_dev,
};
use depthgraph_gpu::session::Session;
use depthgraph_gpu::{AdapterRequest, GpuContext};
use depthgraph_graph::prelude::*;
use depthgraph_nodes::relight::contact::ContactParams;
use depthgraph_nodes::relight::direct::{DirectPlan, DirectSum, evaluate};
use depthgraph_nodes::relight::fill::{
    FillPlan, FillSeen, FillSum, evaluate as evaluate_fill,
    sums_from_decisions as fill_from_decisions,
};
use depthgraph_nodes::relight::object_light::{
    Contact, ObjectLightPlan, ObjectLightSum, evaluate as evaluate_light, sums_from_seen,
};
use depthgraph_nodes::relight::scene_cached::{MoveSums, RelightScene, relight_moved_with};
use depthgraph_nodes::relight::shading::{RelightParams, Surf};
use depthgraph_nodes::relight::vpl::Vpl;
use depthgraph_nodes::sim::pathtrace::PathTraceParams;
use depthgraph_nodes::sim::relight_truth::{RelightCase, Room, Sky, relight_case};

fn case(room: Room, sky: Option<Sky>) -> RelightCase {
    let quick = PathTraceParams {
        samples: 1,
        bounces: 1,
        seed: 1,
    };
    relight_case(room, sky, 160, 120, 64, &quick).unwrap()
}

fn total_power(vpls: &[Vpl]) -> [f64; 3] {
    let mut t = [0.0f64; 3];
    for v in vpls {
        for (ch, x) in t.iter_mut().enumerate() {
            *x += f64::from(v.power[ch]).abs();
        }
    }
    t
}

/// What the device said to a march longer than it takes (surfaces, or why not).
type Marched = Result<usize, NodeError>;

/// An object light on another depth: the CPU's, the device's, and whether
/// the depth changed the CPU's.
type OtherDepth = (Vec<ObjectLightSum>, Vec<ObjectLightSum>, bool);

/// Both backends' sums of one move: the CPU's go on (the move is the
/// CPU's), the device's are kept beside them; with a perturbed copy of
/// the first object light in which a surface loses one lit VPL.
struct Both<'s, 'a> {
    dev: DeviceSums<'s, 'a>,
    direct: Option<(Vec<DirectSum>, Vec<DirectSum>)>,
    light: Vec<(Vec<ObjectLightSum>, Vec<ObjectLightSum>)>,
    perturbed: Option<Vec<ObjectLightSum>>,
    /// Decisions the contact march turned from lit to blocked.
    marched: usize,
    /// VPLs of the object light's plan.
    lights: usize,
    fill: Vec<(Vec<FillSum>, Vec<FillSum>)>,
    /// Surfaces times VPLs of the fill's batches.
    fill_decisions: usize,
    /// A partly blocked surface's fill, and what a device that saw every
    /// VPL lit would give.
    fill_perturbed: Option<(FillSum, FillSum)>,
    /// When set: the direct term again with one object map's VPLs left
    /// without a map (group `usize::MAX`; the first such group that
    /// changes the CPU's sums), on both (CPU, device).
    cut: Option<Option<(Vec<DirectSum>, Vec<DirectSum>)>>,
    /// When set: the first object light again on a session of this
    /// context with a march of more steps than the device takes, and what
    /// the device said.
    long_march: Option<(Arc<GpuContext>, Option<Marched>)>,
    /// When set: the first marching object light again on another depth
    /// (the photo's, 10 % nearer) after the photo's is on the device: both
    /// backends' sums, and whether the depth changed the CPU's.
    other_depth: Option<Option<OtherDepth>>,
}

impl MoveSums for Both<'_, '_> {
    fn begin_move(&mut self) {
        self.dev.begin_move();
    }

    fn fill(&mut self, plan: &FillPlan, surfs: &[Surf]) -> Result<Vec<FillSum>, NodeError> {
        let cpu = evaluate_fill(plan, surfs);
        let dev = self.dev.fill(plan, surfs)?;
        self.fill_decisions += surfs.len() * plan.vpls.len();
        // a perturbed device: every VPL of a partly blocked surface lit
        if self.fill_perturbed.is_none()
            && let Some(k) = cpu.iter().position(|f| f[3] > 0.0)
        {
            let bad = fill_from_decisions(plan, &surfs[k], |_| FillSeen::Lit);
            self.fill_perturbed = Some((cpu[k], bad));
        }
        self.fill.push((cpu.clone(), dev));
        Ok(cpu)
    }

    fn direct(&mut self, plan: &DirectPlan) -> Result<Vec<DirectSum>, NodeError> {
        let cpu = evaluate(plan);
        let dev = self.dev.direct(plan)?;
        if let Some(slot) = &mut self.cut {
            // the first group the tiles read whose VPLs, left without a
            // map, change the CPU's sums
            let cut_group = |g: usize| {
                let mut cut = plan.clone();
                for l in &mut cut.lights {
                    if l.group == g {
                        l.group = usize::MAX;
                    }
                }
                cut
            };
            let found = plan
                .tiles
                .iter()
                .flat_map(|t| &t.vpls)
                .map(|&j| cut_group(plan.lights[j].group))
                .map(|cut| {
                    let sums = evaluate(&cut);
                    (cut, sums)
                })
                .find(|(_, sums)| *sums != cpu);
            if let Some((cut, cpu_cut)) = found {
                *slot = Some((cpu_cut, self.dev.direct(&cut)?));
            }
        }
        self.direct = Some((cpu.clone(), dev));
        Ok(cpu)
    }

    fn object_light(
        &mut self,
        plan: &ObjectLightPlan,
        surfs: &[Surf],
    ) -> Result<Vec<ObjectLightSum>, NodeError> {
        let cpu = evaluate_light(plan, surfs);
        let dev = self.dev.object_light(plan, surfs)?;
        if let Some(slot @ None) = &mut self.other_depth
            && let Some(c) = &plan.contact
        {
            let nearer: DepthMap = c.depth.map(|z| if *z > 0.0 { 0.9 * *z } else { *z });
            let mut other = plan.clone();
            other.contact = Some(Contact {
                depth: &nearer,
                ..*c
            });
            let cpu2 = evaluate_light(&other, surfs);
            let dev2 = self.dev.object_light(&other, surfs)?;
            let changed = cpu2 != cpu;
            *slot = Some((cpu2, dev2, changed));
        }
        if let Some((ctx, slot @ None)) = &mut self.long_march
            && let Some(c) = &plan.contact
        {
            let mut long = plan.clone();
            long.contact = Some(Contact {
                params: ContactParams {
                    max_steps: MAX_MARCH_STEPS as usize + 1,
                    ..c.params
                },
                ..*c
            });
            let mut s = Session::new(ctx);
            let mut stats = ObjectLightStats::default();
            *slot = Some(object_light_dev(&mut s, &long, surfs, &mut stats).map(|v| v.len()));
        }
        self.lights = plan.lights.len();
        let unmarched = ObjectLightPlan {
            contact: None,
            ..plan.clone()
        };
        for q in surfs {
            for (j, l) in plan.lights.iter().enumerate() {
                let cos = q.n.dot(l.dir);
                if cos > 0.0 && plan.seen(j, q, cos) != unmarched.seen(j, q, cos) {
                    self.marched += 1;
                }
            }
        }
        if self.perturbed.is_none() {
            // the first surface a VPL lights: that VPL taken away
            let lit = surfs.iter().enumerate().find_map(|(k, q)| {
                (0..plan.lights.len()).find_map(|j| {
                    let cos = q.n.dot(plan.lights[j].dir);
                    (cos > 0.0 && plan.seen(j, q, cos).1).then_some((k, j))
                })
            });
            if let Some((k, lost)) = lit {
                let mut bad = dev.clone();
                bad[k] = sums_from_seen(plan, &surfs[k], |j, cos| {
                    if j == lost {
                        (true, false)
                    } else {
                        plan.seen(j, &surfs[k], cos)
                    }
                });
                self.perturbed = Some(bad);
            }
        }
        self.light.push((cpu.clone(), dev));
        Ok(cpu)
    }
}

/// What both backends gave for one move, and what the device did.
struct Sums {
    direct: (Vec<DirectSum>, Vec<DirectSum>),
    light: Vec<(Vec<ObjectLightSum>, Vec<ObjectLightSum>)>,
    perturbed: Option<Vec<ObjectLightSum>>,
    marched: usize,
    lights: usize,
    fill: Vec<(Vec<FillSum>, Vec<FillSum>)>,
    fill_stats: FillStats,
    fill_decisions: usize,
    fill_perturbed: Option<(FillSum, FillSum)>,
    direct_stats: DirectStats,
    light_stats: ObjectLightStats,
    cut: Option<(Vec<DirectSum>, Vec<DirectSum>)>,
    long_march: Option<Marched>,
    other_depth: Option<OtherDepth>,
}

/// What [`both_sums_captured`] does beside the move.
#[derive(Debug, Clone, Copy, Default)]
struct Extra {
    /// The direct term again with one group's VPLs without a map.
    cut: bool,
    /// The first object light again with a march longer than the device's.
    long_march: bool,
    /// The first marching object light again on another depth.
    other_depth: bool,
}

/// Both backends' sums of one move on a given device context.
fn both_sums_on(ctx: &Arc<GpuContext>, c: &RelightCase, vpls: &[Vpl]) -> Sums {
    both_sums_with(ctx, c, vpls, &RelightParams::default())
}

/// [`both_sums_on`] with parameters `p`.
fn both_sums_with(ctx: &Arc<GpuContext>, c: &RelightCase, vpls: &[Vpl], p: &RelightParams) -> Sums {
    both_sums_captured(ctx, c, vpls, p, None, Extra::default())
}

/// [`both_sums_with`] with the capture map's VPLs `capture`.
fn both_sums_captured(
    ctx: &Arc<GpuContext>,
    c: &RelightCase,
    vpls: &[Vpl],
    p: &RelightParams,
    capture: Option<&[Vpl]>,
    extra: Extra,
) -> Sums {
    let p = p.clone();
    let mut inp = c.inputs();
    inp.capture_vpls = capture;
    let scene = RelightScene::new(&inp.scene(), vpls, &p).unwrap();
    let mut s = Session::new(ctx);
    let mut both = Both {
        dev: DeviceSums::new(&mut s),
        direct: None,
        light: Vec::new(),
        perturbed: None,
        marched: 0,
        lights: 0,
        fill: Vec::new(),
        fill_decisions: 0,
        fill_perturbed: None,
        cut: extra.cut.then_some(None),
        long_march: extra.long_march.then(|| (ctx.clone(), None)),
        other_depth: extra.other_depth.then_some(None),
    };
    relight_moved_with(&scene, &inp, &p, &mut both)
        .unwrap()
        .unwrap();
    Sums {
        direct: both.direct.unwrap(),
        light: both.light,
        perturbed: both.perturbed,
        marched: both.marched,
        lights: both.lights,
        fill: both.fill,
        fill_stats: both.dev.fill,
        fill_decisions: both.fill_decisions,
        fill_perturbed: both.fill_perturbed,
        direct_stats: both.dev.direct,
        light_stats: both.dev.object,
        cut: both.cut.flatten(),
        long_march: both.long_march.and_then(|(_, r)| r),
        other_depth: both.other_depth.flatten(),
    }
}

/// The CPU's and the device's direct terms of one move (the same plan),
/// and what the device did.
fn both_direct(c: &RelightCase, vpls: &[Vpl]) -> (Vec<DirectSum>, Vec<DirectSum>, DirectStats) {
    both_direct_on(&gpu(), c, vpls)
}

/// [`both_direct`] on a given device context.
fn both_direct_on(
    ctx: &Arc<GpuContext>,
    c: &RelightCase,
    vpls: &[Vpl],
) -> (Vec<DirectSum>, Vec<DirectSum>, DirectStats) {
    let s = both_sums_on(ctx, c, vpls);
    (s.direct.0, s.direct.1, s.direct_stats)
}

/// Surfaces the device's object light lights (some `E^{s+t}` > 0).
fn lit_surfaces(sums: &Sums) -> usize {
    sums.light
        .iter()
        .flat_map(|(_, d)| d)
        .filter(|l| l.est.iter().any(|&e| e > 0.0))
        .count()
}

/// Every object light of the move the same bits on both; the surfaces.
fn light_equal(light: &[(Vec<ObjectLightSum>, Vec<ObjectLightSum>)]) -> Result<usize, String> {
    let mut n = 0;
    for (cpu, dev) in light {
        n += object_light_equal(cpu, dev)?;
    }
    Ok(n)
}

#[test]
fn the_object_light_on_the_device_is_the_cpus_bit_for_bit() {
    for (room, sky) in [
        (Room::Open, None),
        (Room::NearWall, None),
        (Room::Occluded, Some(Sky::Overcast)),
    ] {
        let c = case(room, sky);
        let vpls = c.vpls(256);
        let sums = both_sums_on(&gpu(), &c, &vpls);
        let n = light_equal(&sums.light).unwrap_or_else(|e| panic!("{}: {e}", c.name));
        let st = sums.light_stats;
        let decisions = n * vpls.len();
        eprintln!(
            "{}: {} calls, {n} surfaces, {} of {decisions} decisions left to the host, \
             {} blocked by the contact march",
            c.name,
            sums.light.len(),
            st.asked,
            sums.marched
        );
        // beside the wall the march blocks light the maps let through: the
        // device's marches decide those sums
        if room == Room::NearWall {
            assert!(sums.marched >= 100, "{}: {} marched", c.name, sums.marched);
        }
        // the lattices ask for the object's surfaces (nodes, then the rest)
        assert!(n >= 50, "{}: {n} surfaces", c.name);
        assert_eq!(st.surfaces, n, "{}", c.name);
        // the device settles nearly every decision itself (its contact
        // marches included), and the lit surfaces are lit by it
        assert!(
            st.asked * 50 <= decisions,
            "{}: {} of {decisions} decisions left to the host",
            c.name,
            st.asked
        );
        let lit = lit_surfaces(&sums);
        assert!(lit * 2 >= n, "{}: {lit} of {n} surfaces lit", c.name);
    }
}

/// A VPL count that leaves the last word of decisions partly filled, and
/// the march switched off (the scene's band then lit, as on the CPU).
#[test]
fn the_object_light_without_the_march_and_with_a_partial_word_is_the_cpus() {
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(250);
    let p = RelightParams {
        contact: false,
        ..RelightParams::default()
    };
    let sums = both_sums_with(&gpu(), &c, &vpls, &p);
    assert!(!sums.lights.is_multiple_of(16), "{} VPLs", sums.lights);
    let n = light_equal(&sums.light).unwrap();
    assert!(n >= 50, "{n} surfaces");
    assert_eq!(sums.marched, 0);
    let lit = lit_surfaces(&sums);
    assert!(lit * 2 >= n, "{lit} of {n} surfaces lit");
}

/// With a capture map the object's capture side (`E_cap` over the capture
/// VPLs, the object's maps in their directions, no scene) is the object
/// light's fourth call: the CPU's bits too, on its own maps.
#[test]
fn the_capture_side_on_the_device_is_the_cpus_bit_for_bit() {
    let c = case(Room::Open, None);
    let vpls = c.vpls(128);
    let other = case(Room::NearWall, Some(Sky::Overcast));
    let capture = other.vpls(100);
    let sums = both_sums_captured(
        &gpu(),
        &c,
        &vpls,
        &RelightParams::default(),
        Some(&capture),
        Extra::default(),
    );
    assert_eq!(sums.light.len(), 4, "{} calls", sums.light.len());
    let n = light_equal(&sums.light).unwrap();
    let (cpu, _) = &sums.light[3];
    let lit = cpu
        .iter()
        .filter(|l| l.ecap.iter().any(|&e| e > 0.0))
        .count();
    assert!(
        lit * 2 >= cpu.len(),
        "{lit} of {} capture surfaces lit",
        cpu.len()
    );
    assert!(n > cpu.len(), "{n} surfaces in all");
}

/// The fill light's sums at the composite's pixels: the CPU's bits, the
/// object's volume blocking part of it.
#[test]
fn the_fill_on_the_device_is_the_cpus_bit_for_bit() {
    for (room, sky) in [
        (Room::Open, None),
        (Room::NearWall, None),
        (Room::Occluded, Some(Sky::Overcast)),
    ] {
        let c = case(room, sky);
        let vpls = c.vpls(128);
        let sums = both_sums_on(&gpu(), &c, &vpls);
        let (mut n, mut blocked) = (0usize, 0usize);
        for (k, (cpu, dev)) in sums.fill.iter().enumerate() {
            n += fill_equal(cpu, dev).unwrap_or_else(|e| panic!("{}: batch {k}: {e}", c.name));
            blocked += cpu.iter().filter(|f| f[3] > 0.0).count();
        }
        let (st, all) = (sums.fill_stats, sums.fill_decisions);
        eprintln!(
            "{}: {} batches, {n} surfaces, {blocked} partly blocked, {} of {all} decisions left to the host",
            c.name,
            sums.fill.len(),
            st.asked
        );
        assert!(n >= 50, "{}: {n} surfaces", c.name);
        assert_eq!(st.surfaces, n, "{}", c.name);
        assert!(
            blocked >= 5,
            "{}: {blocked} surfaces partly blocked",
            c.name
        );
        // the volume's tests (the expensive part) stay on the device for
        // at least 95 % of the pairs
        assert!(
            st.asked * 20 <= all,
            "{}: {} of {all} asked",
            c.name,
            st.asked
        );
        // the check fails on a device that misses the volume at one
        // surface, or is one ulp off
        let (k, (cpu, dev)) = sums
            .fill
            .iter()
            .enumerate()
            .find(|(_, (cpu, _))| cpu.iter().any(|f| f[3] > 0.0))
            .expect("a partly blocked surface");
        let at = cpu.iter().position(|f| f[3] > 0.0).unwrap_or(0);
        let (_, lit) = sums.fill_perturbed.expect("a partly blocked surface");
        let mut bad = dev.clone();
        bad[at] = lit;
        assert!(fill_equal(cpu, &bad).is_err(), "{}: batch {k}", c.name);
        let mut bad = dev.clone();
        bad[at][0] = f64::from_bits(bad[at][0].to_bits() + 1);
        assert!(fill_equal(cpu, &bad).is_err(), "{}: batch {k}", c.name);
    }
}

#[test]
fn a_perturbed_object_light_fails_the_check() {
    let c = case(Room::Open, None);
    let vpls = c.vpls(256);
    let sums = both_sums_on(&gpu(), &c, &vpls);
    let (cpu, dev) = &sums.light[0];
    object_light_equal(cpu, dev).unwrap();
    // one surface without one lit VPL's light
    let bad = sums.perturbed.expect("a lit surface");
    assert!(object_light_equal(cpu, &bad).is_err());
    // one ulp off in one channel
    let mut bad = dev.clone();
    bad[0].ecap[2] = f64::from_bits(bad[0].ecap[2].to_bits() + 1);
    assert!(object_light_equal(cpu, &bad).is_err());
}

#[test]
fn the_direct_term_agrees_with_the_cpu_within_its_bound() {
    for (room, sky) in [
        (Room::Open, None),
        (Room::NearWall, None),
        (Room::Occluded, Some(Sky::Overcast)),
    ] {
        let c = case(room, sky);
        let vpls = c.vpls(256);
        let (cpu, dev, stats) = both_direct(&c, &vpls);
        let a = direct_within(&cpu, &dev, total_power(&vpls), DE_TOL)
            .unwrap_or_else(|e| panic!("{}: {e}", c.name));
        eprintln!(
            "{}: {} pixels on the device, {} recomputed, {} shaded, max rel {:.2e}",
            c.name, stats.pixels, stats.recomputed, a.hits, a.max_rel
        );
        // the object shades the room here, and the device settles nearly
        // every pixel itself
        assert!(a.hits >= 50, "{}: {} shaded pixels", c.name, a.hits);
        assert!(stats.pixels >= a.hits, "{}", c.name);
        assert!(
            stats.recomputed * 20 <= stats.pixels,
            "{}: {} of {} recomputed on the host",
            c.name,
            stats.recomputed,
            stats.pixels
        );
    }
}

/// A dispatch wrapped into rows (three workgroups a row here; a real
/// device wraps past 65 535, 4.19 M pixels) reaches every pixel once: the
/// same sums as the CPU's.
#[test]
fn a_direct_term_dispatched_in_rows_agrees_with_the_cpu() {
    let narrow = GpuContext::new(&AdapterRequest {
        max_groups_per_row: Some(3),
        ..Default::default()
    })
    .unwrap();
    let c = case(Room::Open, None);
    let vpls = c.vpls(64);
    let sums = both_sums_on(&narrow, &c, &vpls);
    let ((cpu, dev), stats) = (&sums.direct, sums.direct_stats);
    // many rows: the plan is far more than 3 x 64 pixels
    assert!(stats.pixels > 20 * 3 * 64, "{} pixels", stats.pixels);
    let (x, y) = narrow.flat_grid(stats.pixels, 64).unwrap();
    assert_eq!(x, 3);
    assert!(y > 20);
    let a = direct_within(cpu, dev, total_power(&vpls), DE_TOL).unwrap();
    assert!(a.hits >= 50, "{} shaded pixels", a.hits);
    // the object light's calls too: one of them spans rows
    let largest = sums.light.iter().map(|(c, _)| c.len()).max().unwrap_or(0);
    assert!(largest > 3 * 64, "{largest} surfaces");
    light_equal(&sums.light).unwrap();
}

/// Calls split into many dispatches (at most 37 surfaces each here; a
/// real device splits past 65 536) give the same bits as the CPU: the
/// object's light and the fill, every dispatch of a call in its place.
#[test]
fn decisions_split_into_many_dispatches_are_the_cpus() {
    let split = GpuContext::new(&AdapterRequest {
        max_surfaces_per_dispatch: Some(37),
        ..Default::default()
    })
    .unwrap();
    assert_eq!(split.surfaces_per_dispatch(), 37);
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(128);
    let sums = both_sums_on(&split, &c, &vpls);
    let calls = |lens: Vec<usize>| -> (usize, usize) {
        // (the largest call, the dispatches the calls need at 37 a dispatch)
        let largest = lens.iter().copied().max().unwrap_or(0);
        (largest, lens.iter().map(|n| n.div_ceil(37)).sum())
    };
    let (largest, need) = calls(sums.light.iter().map(|(c, _)| c.len()).collect());
    assert!(largest > 3 * 37, "{largest} surfaces");
    assert_eq!(sums.light_stats.dispatches, need);
    light_equal(&sums.light).unwrap();
    let (largest, need) = calls(sums.fill.iter().map(|(c, _)| c.len()).collect());
    assert!(largest > 3 * 37, "{largest} fill surfaces");
    assert_eq!(sums.fill_stats.dispatches, need);
    for (k, (cpu, dev)) in sums.fill.iter().enumerate() {
        fill_equal(cpu, dev).unwrap_or_else(|e| panic!("batch {k}: {e}"));
    }
    // a device that put one dispatch's sums in another's place fails
    let (cpu, dev) = sums
        .light
        .iter()
        .find(|(c, _)| c.len() > 2 * 37 && c[..37] != c[37..74])
        .expect("a call of two dispatches that differ");
    let mut bad = dev.clone();
    bad[..74].rotate_left(37);
    assert!(object_light_equal(cpu, &bad).is_err());
}

/// VPLs without an object map in a tile's list (group `usize::MAX`: the
/// object shadows nothing there) take nothing on the device either: the
/// CPU's bits, the run skipped. (lavapipe reads zeros past a buffer's end,
/// so there a kernel without the guard passes too; a device that clamps
/// the index would read the last map.)
#[test]
fn a_run_of_vpls_without_an_object_map_takes_nothing_on_the_device() {
    let c = case(Room::Open, None);
    let vpls = c.vpls(64);
    let extra = Extra {
        cut: true,
        ..Extra::default()
    };
    let sums = both_sums_captured(&gpu(), &c, &vpls, &RelightParams::default(), None, extra);
    // a group whose VPLs take light somewhere: leaving it out matters
    let (cpu, dev) = sums.cut.expect("a group that takes light");
    direct_within(&cpu, &dev, total_power(&vpls), DE_TOL).unwrap();
}

/// Buffers the pool hands out again hold what their last user left: every
/// kernel clears (or writes) each word it reads back. Here the pool holds
/// only buffers of all ones (two of every size class up to 32 MiB), and the
/// move's three sums are still the CPU's bits.
#[test]
fn buffers_left_dirty_in_the_pool_change_no_sum() {
    // a context of its own: its pool holds nothing else
    let ctx = GpuContext::new(&AdapterRequest::default()).unwrap();
    {
        let mut dirty = Vec::new();
        for class in (8..=25).map(|p| 1u64 << p) {
            for _ in 0..2 {
                let b = ctx.buffer(class, depthgraph_gpu::session::STORAGE).unwrap();
                let ones = vec![0xFFu8; class as usize];
                ctx.queue().write_buffer(b.get(), 0, &ones);
                dirty.push(b);
            }
        }
        ctx.queue().submit([]);
        // dropped: back to the pool, all ones
    }
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(100);
    let sums = both_sums_on(&ctx, &c, &vpls);
    let (cpu, dev) = &sums.direct;
    let a = direct_within(cpu, dev, total_power(&vpls), DE_TOL).unwrap();
    assert!(a.hits >= 50, "{} shaded pixels", a.hits);
    // and the device decided them (a dirty flag word would send every
    // pixel back to the host, which gives the CPU's bits too)
    let st = sums.direct_stats;
    assert!(
        st.recomputed * 20 <= st.pixels,
        "{} of {} recomputed",
        st.recomputed,
        st.pixels
    );
    let st = sums.light_stats;
    assert!(st.asked * 20 <= st.surfaces * sums.lights, "{st:?}");
    light_equal(&sums.light).unwrap();
    for (k, (cpu, dev)) in sums.fill.iter().enumerate() {
        fill_equal(cpu, dev).unwrap_or_else(|e| panic!("batch {k}: {e}"));
    }
}

/// A contact march longer than the device takes (one dispatch must end
/// within a driver's watchdog) is refused before any dispatch: the node
/// then runs on the CPU.
#[test]
fn a_march_longer_than_the_device_takes_is_refused() {
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(64);
    let extra = Extra {
        long_march: true,
        ..Extra::default()
    };
    let sums = both_sums_captured(&gpu(), &c, &vpls, &RelightParams::default(), None, extra);
    match sums.long_march.expect("an object light with the march") {
        Ok(n) => panic!("{n} surfaces marched {} steps", MAX_MARCH_STEPS + 1),
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains(&format!("{} steps", MAX_MARCH_STEPS + 1)),
                "{msg}"
            );
        }
    }
}

/// A plan that marches another depth than the one on the device uploads
/// its own: the CPU's bits on the other depth, which changes the sums.
#[test]
fn a_plan_marching_another_depth_gets_its_own_on_the_device() {
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(128);
    let extra = Extra {
        other_depth: true,
        ..Extra::default()
    };
    let sums = both_sums_captured(&gpu(), &c, &vpls, &RelightParams::default(), None, extra);
    let (cpu, dev, changed) = sums.other_depth.expect("an object light with the march");
    assert!(changed, "a nearer photo changed no march");
    object_light_equal(&cpu, &dev).unwrap();
}

#[test]
fn a_perturbed_direct_term_fails_the_check() {
    let c = case(Room::Open, None);
    let vpls = c.vpls(256);
    let (cpu, dev, _) = both_direct(&c, &vpls);
    let total = total_power(&vpls);
    direct_within(&cpu, &dev, total, DE_TOL).unwrap();
    let k = cpu.iter().position(|s| s.hit).unwrap();
    // a sum one ulp off (the bound is the CPU's bits)
    assert_eq!(DE_TOL, 0.0);
    let mut bad = dev.clone();
    bad[k].de[1] = f64::from_bits(bad[k].de[1].to_bits() + 1);
    assert!(direct_within(&cpu, &bad, total, DE_TOL).is_err());
    // a pixel whose decision differs
    let mut bad = dev;
    bad[k].hit = false;
    assert!(direct_within(&cpu, &bad, total, DE_TOL).is_err());
}

#[test]
fn the_relight_node_on_the_device_gives_the_cpus_picture() {
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(128);
    let mut i = Inputs::new();
    i.insert("photo", Value::Color(Arc::new(c.photo.clone())));
    i.insert("depth", Value::Depth(Arc::new(c.depth.clone())));
    i.insert(
        "pasted_color",
        Value::Color(Arc::new(c.object_color.clone())),
    );
    i.insert(
        "pasted_depth",
        Value::Depth(Arc::new(c.object_depth.clone())),
    );
    i.insert("alpha", Value::Mask(Arc::new(c.alpha.clone())));
    i.insert("intrinsics", Value::Intrinsics(c.k));
    i.insert("vpls", Value::Vpls(Arc::new(vpls)));
    let params = RelightParams::default().to_values();
    let (cpu, dev) = both("Relight", &i, &params);
    let (a, b) = (color_of(&cpu, "color"), color_of(&dev, "color"));
    let psnr = display_psnr(&a, &b).unwrap();
    eprintln!("Relight color: display PSNR {psnr:.1} dB against the CPU");
    assert!(psnr >= 80.0, "{psnr} dB");
    // every sum the device takes part in is the CPU's bits: the picture too
    let bits = |c: &ColorImage| -> Vec<u32> {
        c.as_slice()
            .iter()
            .flat_map(|p| p.map(f32::to_bits))
            .collect()
    };
    assert!(
        bits(&a) == bits(&b),
        "the device's picture differs from the CPU's"
    );
    // the rendered region is decided alike
    assert_eq!(cpu.values.get("region"), dev.values.get("region"));
    let report = dev.report.clone().unwrap_or_default();
    assert!(report.contains("direct term on the device"), "{report}");
    assert!(report.contains("object light on the device"), "{report}");
    // a perturbed picture fails the same bound
    let mut worse = (*b).clone();
    for px in worse.as_mut_slice().iter_mut().step_by(7) {
        px[0] += 0.01;
    }
    assert!(display_psnr(&a, &worse).unwrap() < 80.0);
}

/// The node names the cached scene before each move: the first move
/// uploads the scene's maps and keeps them on the device with the scene,
/// the next finds them there (and the photo's depth with its value); both
/// give the same picture, the CPU's within the node's bound.
#[test]
fn a_second_move_finds_the_scenes_maps_on_the_device() {
    let c = case(Room::NearWall, None);
    let vpls = c.vpls(128);
    let p = RelightParams::default();
    let inp = c.inputs();
    let scene = Arc::new(RelightScene::new(&inp.scene(), &vpls, &p).unwrap());
    let depth = Arc::new(c.depth.clone());
    let inp = depthgraph_nodes::relight::shading::RelightInputs {
        depth: &depth,
        ..inp
    };
    let scene_bytes: usize = scene
        .scene_maps()
        .iter()
        .flatten()
        .map(|m| 4 * m.t.len())
        .sum();
    let depth_bytes = 4 * depth.as_slice().len();
    let ctx = gpu();
    let run = |scene: &Arc<RelightScene>| {
        let mut s = Session::new(&ctx);
        let mut sums = DeviceSums::new(&mut s).with_depth(depth.clone());
        sums.scene(scene);
        let r = relight_moved_with(scene, &inp, &p, &mut sums)
            .unwrap()
            .unwrap();
        (r, s.stats)
    };
    let (first, up1) = run(&scene);
    let (second, up2) = run(&scene);
    eprintln!(
        "uploads: first move {} B, second {} B (scene maps {scene_bytes} B, depth {depth_bytes} B), resident hits {} then {}",
        up1.upload_bytes, up2.upload_bytes, up1.resident_hits, up2.resident_hits
    );
    assert!(scene_bytes > 100_000, "{scene_bytes} B of scene maps");
    assert!(up1.upload_bytes >= scene_bytes + depth_bytes);
    assert!(up2.upload_bytes + scene_bytes + depth_bytes <= up1.upload_bytes);
    assert!(up2.resident_hits >= 2, "{} hits", up2.resident_hits);
    assert_eq!(first.color, second.color);
    let cpu = relight_moved_with(
        &scene,
        &inp,
        &p,
        &mut depthgraph_nodes::relight::scene_cached::CpuSums,
    )
    .unwrap()
    .unwrap();
    let psnr = display_psnr(&Arc::new(cpu.color), &Arc::new(second.color)).unwrap();
    assert!(psnr >= 80.0, "{psnr} dB against the CPU");
    // another scene value (the same maps, another identity) is uploaded
    // again, never read from the first one's buffer
    let other = Arc::new((*scene).clone());
    let (_, up3) = run(&other);
    assert!(up3.upload_bytes >= scene_bytes, "{} B", up3.upload_bytes);
}
