//! Relight: the device's direct term of a scene-cached move against the
//! CPU's, on the path-traced rooms of `sim::relight_truth`, and the whole
//! node on both backends.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::parity::{direct_within, display_psnr};
use depthgraph_gpu::relight::{DE_TOL, DirectStats, direct};
use depthgraph_gpu::session::Session;
use depthgraph_gpu::{AdapterRequest, GpuContext};
use depthgraph_graph::prelude::*;
use depthgraph_nodes::relight::direct::{DirectSum, evaluate};
use depthgraph_nodes::relight::scene_cached::{RelightScene, relight_moved_with};
use depthgraph_nodes::relight::shading::RelightParams;
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
    let p = RelightParams::default();
    let inp = c.inputs();
    let scene = RelightScene::new(&inp.scene(), vpls, &p).unwrap();
    let mut s = Session::new(ctx);
    let mut stats = DirectStats::default();
    let mut seen = None;
    relight_moved_with(&scene, &inp, &p, &mut |plan| {
        let cpu = evaluate(plan);
        let dev = direct(&mut s, plan, &mut stats)?;
        seen = Some((cpu.clone(), dev));
        Ok(cpu)
    })
    .unwrap()
    .unwrap();
    let (cpu, dev) = seen.unwrap();
    (cpu, dev, stats)
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
    let (cpu, dev, stats) = both_direct_on(&narrow, &c, &vpls);
    // many rows: the plan is far more than 3 x 64 pixels
    assert!(stats.pixels > 20 * 3 * 64, "{} pixels", stats.pixels);
    let (x, y) = narrow.flat_grid(stats.pixels, 64).unwrap();
    assert_eq!(x, 3);
    assert!(y > 20);
    let a = direct_within(&cpu, &dev, total_power(&vpls), DE_TOL).unwrap();
    assert!(a.hits >= 50, "{} shaded pixels", a.hits);
}

#[test]
fn a_perturbed_direct_term_fails_the_check() {
    let c = case(Room::Open, None);
    let vpls = c.vpls(256);
    let (cpu, dev, _) = both_direct(&c, &vpls);
    let total = total_power(&vpls);
    direct_within(&cpu, &dev, total, DE_TOL).unwrap();
    let k = cpu.iter().position(|s| s.hit).unwrap();
    // a sum off by twice the bound
    let mut bad = dev.clone();
    bad[k].de[1] += 2.0 * DE_TOL * (total[1] + cpu[k].de[1]);
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
    // the rendered region is decided alike
    assert_eq!(cpu.values.get("region"), dev.values.get("region"));
    let report = dev.report.clone().unwrap_or_default();
    assert!(report.contains("direct term on the device"), "{report}");
    // a perturbed picture fails the same bound
    let mut worse = (*b).clone();
    for px in worse.as_mut_slice().iter_mut().step_by(7) {
        px[0] += 0.01;
    }
    assert!(display_psnr(&a, &worse).unwrap() < 80.0);
}
