//! Refocus: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::parity::color_within;
use depthgraph_gpu::refocus::MIN_PSNR_DB;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::camera::frame_border::FrameBorder;
use depthgraph_nodes::camera::lens::{Aperture, ApertureShape};
use depthgraph_nodes::camera::refocus::{Plan, RefocusParams, plan};

/// A textured background at 4 m, a foreground card at 1 m with a hot
/// highlight, a strip of sky (no depth) and a few broken color samples.
fn scene(w: usize, h: usize) -> (ColorImage, DepthMap) {
    let mut c = ColorImage::from_fn(w, h, |x, y| {
        let t = ((x / 3 + y / 5) % 7) as f32 / 7.0;
        [0.1 + 0.5 * t, 0.3, 0.6 - 0.4 * t]
    });
    let d = DepthMap::from_fn(w, h, |x, y| {
        if y < 4 {
            0.0
        } else if (w / 3..w / 2).contains(&x) && (h / 4..3 * h / 4).contains(&y) {
            1.0
        } else {
            4.0 + 0.002 * x as f32
        }
    });
    *c.get_mut(w / 3 + 2, h / 2) = [80.0, 60.0, 40.0];
    *c.get_mut(5, 9) = [f32::NAN, -3.0, f32::INFINITY];
    (c, d)
}

fn inputs(c: ColorImage, d: DepthMap) -> Inputs {
    let mut i = Inputs::new();
    i.insert("color", Value::Color(Arc::new(c)));
    i.insert("depth", Value::Depth(Arc::new(d)));
    i
}

fn fixed_pixels(c: &ColorImage, d: &DepthMap, p: &RefocusParams) -> Vec<bool> {
    let a = Aperture::from_params(p.aperture, p.blades, p.rotation_deg, None).unwrap();
    match plan(c, d, &a, p).unwrap() {
        Plan::Sharp(..) => vec![true; c.len()],
        Plan::Blur(b) => {
            let fixed: Vec<bool> = b.active.iter().map(|a| !a).collect();
            match &b.frame {
                // the extended frame's flags, cropped as the image is
                Some(f) => {
                    let (pw, ph) = f.padded_dims();
                    f.crop(&Image::<bool>::from_vec(pw, ph, fixed).unwrap())
                        .as_slice()
                        .to_vec()
                }
                None => fixed,
            }
        }
    }
}

fn cases() -> Vec<RefocusParams> {
    let base = RefocusParams {
        focus_m: 1.0,
        f_number: 2.0,
        sensor_width_mm: 6.0,
        samples: 64,
        ..Default::default()
    };
    vec![
        base.clone(),
        RefocusParams {
            focus_m: 4.0,
            aperture: ApertureShape::Polygon,
            blades: 6,
            samples: 96,
            ..base.clone()
        },
        RefocusParams {
            far_prior: false,
            exposure_stops: 1.5,
            samples: 0,
            quality: 0.5,
            ..base.clone()
        },
        RefocusParams {
            focus_m: f64::INFINITY,
            f_number: 1.4,
            samples: 33,
            seed: 5,
            ..base.clone()
        },
    ]
}

#[test]
fn refocus_agrees_with_the_cpu_within_its_stated_bound() {
    // 300 px wide: the fold of the 1-D dispatches and partial tiles are exercised
    let (c, d) = scene(300, 170);
    for p in cases() {
        let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
        assert_eq!(cpu.passthrough, dev.passthrough);
        let (a, b) = (color_of(&cpu, "color"), color_of(&dev, "color"));
        let fixed = fixed_pixels(&c, &d, &p);
        assert!(fixed.iter().any(|f| !f), "the case blurs something");
        let psnr =
            color_within(&a, &b, &fixed, MIN_PSNR_DB).unwrap_or_else(|e| panic!("{p:?}: {e}"));
        eprintln!(
            "focus {} aperture {:?}: PSNR {psnr:.1} dB",
            p.focus_m, p.aperture
        );
        assert_eq!(dev.transfers.downloads, 2, "one result and the hole counts");
    }
}

/// The background layer (partial occlusion) on the device: the entries
/// behind the card's edges warp with the image's sources, under the same
/// keys, and the result agrees with the CPU's within the stated bound, at
/// the near and the far focus. The layer changes the result by more than
/// that bound, so the check could fail.
#[test]
fn the_background_layer_agrees_with_the_cpu() {
    let (c, d) = scene(300, 170);
    for base in [cases().remove(0), cases().remove(1)] {
        let p = RefocusParams {
            background_layer: true,
            ..base.clone()
        };
        let a = Aperture::from_params(p.aperture, p.blades, p.rotation_deg, None).unwrap();
        let Plan::Blur(b) = plan(&c, &d, &a, &p).unwrap() else {
            panic!("the case blurs")
        };
        assert!(b.layer.len() > 100, "{} layer entries", b.layer.len());
        let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
        assert_eq!(dev.origin.as_ref().unwrap().backend, "wgpu");
        // explain shows the layer's share alike
        assert!(
            cpu.report
                .as_deref()
                .is_some_and(|r| r.contains("background layer"))
        );
        assert_eq!(cpu.report, dev.report);
        let (x, y) = (color_of(&cpu, "color"), color_of(&dev, "color"));
        let fixed = fixed_pixels(&c, &d, &p);
        let psnr = color_within(&x, &y, &fixed, MIN_PSNR_DB)
            .unwrap_or_else(|e| panic!("focus {}: {e}", p.focus_m));
        eprintln!("layer, focus {}: PSNR {psnr:.1} dB", p.focus_m);
        let off = both("Refocus", &inputs(c.clone(), d.clone()), &base.to_values()).1;
        assert!(
            color_within(&x, &color_of(&off, "color"), &fixed, MIN_PSNR_DB).is_err(),
            "focus {}: the layer changes nothing the check sees",
            p.focus_m
        );
    }
}

#[test]
fn the_refocus_check_fails_on_a_perturbed_result() {
    let (c, d) = scene(120, 90);
    let p = cases().remove(0);
    let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
    let (a, b) = (color_of(&cpu, "color"), color_of(&dev, "color"));
    let fixed = fixed_pixels(&c, &d, &p);
    assert!(color_within(&a, &b, &fixed, MIN_PSNR_DB).is_ok());
    // a faint veil over the active pixels: about 1/255 on the display
    let mut veil = (*b).clone();
    for (px, f) in veil.as_mut_slice().iter_mut().zip(&fixed) {
        if !f {
            px[1] += 0.004;
        }
    }
    assert!(color_within(&a, &veil, &fixed, MIN_PSNR_DB).is_err());
}

/// Refocus of `c` on both backends, focused at 2 m on a wall with a far
/// card (6 m) in its top-left `card` x `card` pixels, f/2 on a 6 mm
/// sensor: the CPU's and the device's colour, and the inactive pixels.
fn card_on_both(
    c: &ColorImage,
    card: usize,
    samples: usize,
    exposure_stops: f64,
) -> (Arc<ColorImage>, Arc<ColorImage>, Vec<bool>) {
    let (w, h) = c.dims();
    let d = DepthMap::from_fn(w, h, |x, y| if x < card && y < card { 6.0 } else { 2.0 });
    let p = RefocusParams {
        focus_m: 2.0,
        f_number: 2.0,
        sensor_width_mm: 6.0,
        samples,
        exposure_stops,
        ..Default::default()
    };
    let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
    let fixed = fixed_pixels(c, &d, &p);
    (color_of(&cpu, "color"), color_of(&dev, "color"), fixed)
}

/// A scene whose blur reaches only part of the image: a small far card
/// behind an in-focus wall, exposed by a fractional stop (the inactive
/// pixels are the input times 2^0.7, which must be the CPU's bits).
#[test]
fn inactive_pixels_are_bit_identical_at_a_fractional_exposure() {
    let (w, h) = (160, 120);
    let c = ColorImage::from_fn(w, h, |x, y| {
        [0.013 * (x % 17) as f32, 0.7, 0.001 * y as f32 + 0.3]
    });
    let (a, b, fixed) = card_on_both(&c, 24, 32, 0.7);
    let n_fixed = fixed.iter().filter(|f| **f).count();
    assert!(
        n_fixed > 1000 && n_fixed < c.len(),
        "{n_fixed} inactive pixels"
    );
    color_within(&a, &b, &fixed, MIN_PSNR_DB).unwrap();
    // and the check sees one inactive pixel off by one ulp
    let t = fixed.iter().position(|f| *f).unwrap();
    let mut ulp = (*b).clone();
    let v = &mut ulp.as_mut_slice()[t][0];
    *v = f32::from_bits(v.to_bits() + 1);
    let e = color_within(&a, &ulp, &fixed, MIN_PSNR_DB).unwrap_err();
    assert!(e.contains("inactive"), "{e}");
}

/// A finite colour at the largest exposure gain stays finite on the device
/// as on the CPU (f32's largest value where the product passes it), blurred
/// pixels and inactive ones alike.
#[test]
fn a_bright_colour_at_the_largest_exposure_stays_finite_on_the_device() {
    let (w, h) = (96, 72);
    let c = ColorImage::from_fn(w, h, |x, y| {
        if (x + y) % 7 == 0 {
            [1e30; 3]
        } else {
            [0.5; 3]
        }
    });
    let (a, b, fixed) = card_on_both(&c, 16, 16, 30.0);
    assert!(fixed.iter().any(|f| *f) && fixed.iter().any(|f| !*f));
    for img in [&a, &b] {
        assert!(img.as_slice().iter().flatten().all(|v| v.is_finite()));
        assert!(img.as_slice().iter().flatten().any(|v| *v == f32::MAX));
    }
    // the inactive pixels: the CPU's bits
    for (t, f) in fixed.iter().enumerate() {
        if *f {
            assert_eq!(a.as_slice()[t], b.as_slice()[t], "pixel {t}");
        }
    }
}

#[test]
fn a_sharp_scene_passes_through_alike() {
    let c = ColorImage::filled(16, 16, [0.5; 3]);
    let d = DepthMap::filled(16, 16, 2.0);
    let p = RefocusParams {
        focus_m: 2.0,
        exposure_stops: 1.0,
        ..Default::default()
    };
    let (cpu, dev) = both("Refocus", &inputs(c, d), &p.to_values());
    assert_eq!(cpu.passthrough, dev.passthrough);
    assert!(dev.passthrough.is_some());
    assert_eq!(*color_of(&cpu, "color"), *color_of(&dev, "color"));
}

/// A problem larger than the device may bind runs on the CPU: the same
/// result, and the outputs name the CPU and why.
#[test]
fn too_large_for_the_device_runs_on_the_cpu_and_says_so() {
    let small = depthgraph_gpu::GpuContext::new(&depthgraph_gpu::AdapterRequest {
        max_buffer_mb: Some(1),
        ..Default::default()
    })
    .unwrap();
    let cpu_reg = depthgraph_nodes::registry().unwrap();
    let mut dev = depthgraph_nodes::registry().unwrap();
    depthgraph_gpu::install(&mut dev, &small).unwrap();
    // 300x170: the views need 32 B per pixel, over 1 MiB
    let (c, d) = scene(300, 170);
    let p = cases().remove(0);
    let i = inputs(c, d);
    let a = eval_on(&cpu_reg, "Refocus", &i, &p.to_values()).unwrap();
    let b = eval_on(&dev, "Refocus", &i, &p.to_values()).unwrap();
    assert_eq!(*color_of(&a, "color"), *color_of(&b, "color"));
    let origin = b.origin.unwrap();
    assert_eq!(origin.backend, "cpu");
    let note = origin.note.unwrap();
    assert!(note.contains("MiB") && note.contains("CPU"), "{note}");
    // a small problem still runs on that device
    let (c, d) = scene(40, 30);
    let b = eval_on(&dev, "Refocus", &inputs(c, d), &p.to_values()).unwrap();
    assert_eq!(b.origin.unwrap().backend, "wgpu");
}

/// The image-wide lens effects (magnification per channel, breathing,
/// natural vignetting) run on the host after the device's views: the same
/// result within the bound. Spherical aberration (every source's extra
/// shift in the warp), longitudinal chromatic aberration (each view's
/// channels read apart) and the barrel (a per-view clip of the
/// accumulation) run on the device, alone and together with the
/// background layer, within the bound too; each changes the result by
/// more than it.
#[test]
fn lens_effects_agree_with_the_cpu() {
    let (c, d) = scene(120, 90);
    let image_wide = RefocusParams {
        chromatic_lateral: 0.02,
        natural_vignetting: 1.0,
        focus_breathing: true,
        ..cases().remove(0)
    };
    let (cpu, dev) = both(
        "Refocus",
        &inputs(c.clone(), d.clone()),
        &image_wide.to_values(),
    );
    let (a, b) = (color_of(&cpu, "color"), color_of(&dev, "color"));
    // resampling mixes moved and unmoved pixels: none is held to its bits
    let none = vec![false; c.len()];
    color_within(&a, &b, &none, MIN_PSNR_DB).unwrap();
    assert_eq!(dev.origin.as_ref().unwrap().backend, "wgpu");
    // without the effects the device result differs (so the check can fail)
    let plain = both(
        "Refocus",
        &inputs(c.clone(), d.clone()),
        &cases()[0].to_values(),
    )
    .1;
    assert!(color_within(&a, &color_of(&plain, "color"), &none, MIN_PSNR_DB).is_err());
    for p in [
        RefocusParams {
            spherical_aberration_d: 0.5,
            ..cases().remove(0)
        },
        RefocusParams {
            spherical_aberration_d: -0.8,
            ..cases().remove(1)
        },
        RefocusParams {
            barrel_distance_mm: 40.0,
            ..cases().remove(0)
        },
        RefocusParams {
            barrel_distance_mm: 60.0,
            background_layer: true,
            ..cases().remove(1)
        },
        RefocusParams {
            chromatic_longitudinal_d: 0.3,
            ..cases().remove(0)
        },
        RefocusParams {
            chromatic_longitudinal_d: -0.5,
            spherical_aberration_d: 0.3,
            barrel_distance_mm: 40.0,
            background_layer: true,
            ..cases().remove(1)
        },
    ] {
        let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
        assert_eq!(dev.origin.as_ref().unwrap().backend, "wgpu");
        // what explain shows: the effects left off, the layer's share
        assert!(cpu.report.is_some());
        assert_eq!(cpu.report, dev.report);
        let (x, y) = (color_of(&cpu, "color"), color_of(&dev, "color"));
        let fixed = fixed_pixels(&c, &d, &p);
        let psnr =
            color_within(&x, &y, &fixed, MIN_PSNR_DB).unwrap_or_else(|e| panic!("{p:?}: {e}"));
        eprintln!(
            "spherical {} longitudinal chromatic {} barrel {} mm: PSNR {psnr:.1} dB",
            p.spherical_aberration_d, p.chromatic_longitudinal_d, p.barrel_distance_mm
        );
        let without = RefocusParams {
            spherical_aberration_d: 0.0,
            chromatic_longitudinal_d: 0.0,
            barrel_distance_mm: 0.0,
            ..p.clone()
        };
        let off = both(
            "Refocus",
            &inputs(c.clone(), d.clone()),
            &without.to_values(),
        )
        .1;
        assert!(
            color_within(&x, &color_of(&off, "color"), &fixed, MIN_PSNR_DB).is_err(),
            "{p:?}: the effect changes nothing the check sees"
        );
    }
}

/// `frame_border` reflect on the device: the views warp the extended
/// frame's colour (uploaded in place of the input) and the result comes
/// back cropped; it agrees with the CPU's within the stated bound and
/// explain says the same on both, with and without the background layer.
/// The mirrored border changes the result by more than the bound.
#[test]
fn the_reflected_frame_agrees_with_the_cpu() {
    let (c, d) = scene(120, 90);
    let none = vec![false; c.len()];
    for base in [
        cases().remove(0),
        RefocusParams {
            background_layer: true,
            ..cases().remove(1)
        },
    ] {
        let p = RefocusParams {
            frame_border: FrameBorder::Reflect,
            ..base.clone()
        };
        let (cpu, dev) = both("Refocus", &inputs(c.clone(), d.clone()), &p.to_values());
        assert_eq!(dev.origin.as_ref().unwrap().backend, "wgpu");
        assert_eq!(cpu.report, dev.report);
        let said = cpu.report.clone().unwrap_or_default();
        assert!(said.contains("frame extended by"), "{said}");
        let (x, y) = (color_of(&cpu, "color"), color_of(&dev, "color"));
        assert_eq!(y.dims(), c.dims());
        let fixed = fixed_pixels(&c, &d, &p);
        let psnr =
            color_within(&x, &y, &fixed, MIN_PSNR_DB).unwrap_or_else(|e| panic!("{p:?}: {e}"));
        eprintln!("reflected frame, focus {}: PSNR {psnr:.1} dB", p.focus_m);
        let edge = both("Refocus", &inputs(c.clone(), d.clone()), &base.to_values()).1;
        assert!(
            color_within(&y, &color_of(&edge, "color"), &none, MIN_PSNR_DB).is_err(),
            "the mirrored border changes nothing the check sees"
        );
    }
}

/// Views rendered in batches (several per dispatch, each with its own
/// z-buffer and view slot, accumulated in view order) give the bits of one
/// view per dispatch: with the plain path, the background layer, the far
/// prior off, and the per-view lens effects (the split path included),
/// for view counts that leave a partial last batch. The comparison is
/// exact, and it tells a different aperture sampling apart.
#[test]
fn batches_of_views_give_the_bits_of_one_view_per_dispatch() {
    let per_dispatch = |views| {
        let ctx = depthgraph_gpu::GpuContext::new(&depthgraph_gpu::AdapterRequest {
            views_per_dispatch: Some(views),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(ctx.views_per_dispatch(), views);
        let mut reg = depthgraph_nodes::registry().unwrap();
        depthgraph_gpu::install(&mut reg, &ctx).unwrap();
        reg
    };
    let one = per_dispatch(1);
    let batched = [per_dispatch(5), registries().1];
    let (c, d) = scene(120, 90);
    let i = inputs(c, d);
    let mut cases = cases();
    cases.push(RefocusParams {
        background_layer: true,
        samples: 37,
        ..cases[0].clone()
    });
    cases.push(RefocusParams {
        chromatic_longitudinal_d: -0.5,
        spherical_aberration_d: 0.3,
        barrel_distance_mm: 40.0,
        background_layer: true,
        samples: 21,
        ..cases[1].clone()
    });
    for p in &cases {
        let a = eval_on(&one, "Refocus", &i, &p.to_values()).unwrap();
        assert_eq!(a.origin.as_ref().unwrap().backend, "wgpu");
        let bits = |o: &Outputs| -> Vec<[u32; 3]> {
            color_of(o, "color")
                .as_slice()
                .iter()
                .map(|c| c.map(f32::to_bits))
                .collect()
        };
        for reg in &batched {
            let b = eval_on(reg, "Refocus", &i, &p.to_values()).unwrap();
            assert_eq!(b.origin.as_ref().unwrap().backend, "wgpu");
            assert!(bits(&a) == bits(&b), "{p:?}: batched views differ");
            assert_eq!(a.report, b.report, "{p:?}");
        }
        let other = RefocusParams {
            seed: p.seed + 1,
            ..p.clone()
        };
        let o = eval_on(&batched[0], "Refocus", &i, &other.to_values()).unwrap();
        assert!(bits(&a) != bits(&o), "{p:?}: the check tells nothing apart");
    }
}
