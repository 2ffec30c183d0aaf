//! Tests of the lens effects of `Refocus` ([`crate::camera::lens::LensEffects`]):
//! each against an analytic expectation, and against the ray-traced thin
//! lens with the same effects (`render_thin_lens`).
#![cfg(test)]

use depthgraph_graph::prelude::*;

use crate::camera::lens::{Aperture, LensEffects, ThinLens};
use crate::camera::refocus::{RefocusParams, produced, refocus};
use crate::sim::synthetic::{RenderOptions, Scene, ThinLensRender, render, render_thin_lens};

fn run(c: &ColorImage, d: &DepthMap, p: &RefocusParams) -> ColorImage {
    match refocus(c, d, &Aperture::Disc, p, |_| Ok(())) {
        Ok((out, _)) => out,
        Err(e) => panic!("refocus failed: {e}"),
    }
}

/// Sum of channel `c` along row `y`: for a step from 1 (left) to 0, the
/// edge's position in pixels from the left border.
fn edge_position(img: &ColorImage, y: usize, c: usize) -> f64 {
    img.row(y).iter().map(|p| p[c] as f64).sum()
}

/// A white half-plane left of column `edge`, black right of it, in focus.
fn edge_image(w: usize, h: usize, edge: usize) -> (ColorImage, DepthMap) {
    (
        ColorImage::from_fn(w, h, |x, _| if x < edge { [1.0; 3] } else { [0.0; 3] }),
        DepthMap::filled(w, h, 2.0),
    )
}

#[test]
fn natural_vignetting_is_cos4_of_the_field_angle() {
    let (w, h) = (64, 48);
    let c = ColorImage::filled(w, h, [0.5; 3]);
    let d = DepthMap::filled(w, h, 2.0);
    let p = RefocusParams {
        focus_m: 2.0,
        sensor_width_mm: 36.0,
        natural_vignetting: 1.0,
        ..Default::default()
    };
    let out = run(&c, &d, &p);
    // f_px = 50 mm * 64 / 36 mm
    let f_px = 50.0 * w as f64 / 36.0;
    for (x, y) in [(0usize, 0usize), (31, 23), (63, 10), (5, 40)] {
        let (tx, ty) = (
            (x as f64 + 0.5 - 32.0) / f_px,
            (y as f64 + 0.5 - 24.0) / f_px,
        );
        let cos2 = 1.0 / (1.0 + tx * tx + ty * ty);
        let expected = 0.5 * cos2 * cos2;
        let got = out.get(x, y)[1] as f64;
        assert!(
            (got - expected).abs() < 1e-6,
            "({x}, {y}): {got} vs {expected}"
        );
    }
    // the corner is noticeably darker (cos^4 of about 24 degrees)
    assert!((out.get(0, 0)[0] as f64) < 0.5 * 0.72);
    // the image changed, so it is no pass-through, and explain says why
    let rep = match refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())) {
        Ok((_, r)) => r,
        Err(e) => panic!("{e}"),
    };
    let said = produced(crate::camera::refocus::RefocusOut { color: out }, &p, &rep);
    assert!(said.passthrough.is_none());
    let report = said.report.unwrap_or_default();
    assert!(
        report.contains("vignetting and magnification applied"),
        "{report}"
    );
    assert!(
        report.contains("no chromatic aberration: lateral and longitudinal 0"),
        "{report}"
    );
    assert!(!report.contains("no natural vignetting"), "{report}");
}

#[test]
fn effects_off_pass_through_and_say_so() {
    let (c, d) = edge_image(40, 30, 20);
    let p = RefocusParams {
        focus_m: 2.0,
        ..Default::default()
    };
    let (out, rep) = match refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())) {
        Ok(r) => r,
        Err(e) => panic!("{e}"),
    };
    assert_eq!(out, c);
    let said = produced(crate::camera::refocus::RefocusOut { color: out }, &p, &rep);
    assert!(said.passthrough.is_some());
    let report = said.report.unwrap_or_default();
    for what in [
        "no spherical aberration",
        "no chromatic aberration: lateral and longitudinal 0",
        "no optical vignetting",
        "no natural vignetting",
        "no focus breathing",
    ] {
        assert!(report.contains(what), "{what}: {report}");
    }
}

#[test]
fn lateral_chromatic_aberration_fringes_grow_with_the_distance_from_the_centre() {
    // The edge is 22 px right of the centre (48): red is magnified by 1.05
    // (edge at 48 + 22 * 1.05), blue by 0.95; the fringe is 2 * 0.05 * 22 px.
    let (w, h) = (96, 64);
    let (c, d) = edge_image(w, h, 70);
    let p = RefocusParams {
        focus_m: 2.0,
        chromatic_lateral: 0.05,
        ..Default::default()
    };
    let out = run(&c, &d, &p);
    let y = 20;
    let (r, g, b) = (
        edge_position(&out, y, 0),
        edge_position(&out, y, 1),
        edge_position(&out, y, 2),
    );
    assert!((g - 70.0).abs() < 1e-9, "green stays: {g}");
    assert!((r - (48.0 + 22.0 * 1.05)).abs() < 0.05, "red {r}");
    assert!((b - (48.0 + 22.0 * 0.95)).abs() < 0.05, "blue {b}");
    assert!((r - b - 2.2).abs() < 0.1, "fringe {}", r - b);
    // an edge left of the centre fringes the other way round
    let (c2, _) = edge_image(w, h, 30);
    let out2 = run(&c2, &d, &p);
    let fringe = edge_position(&out2, y, 0) - edge_position(&out2, y, 2);
    assert!((fringe + 2.0 * 0.05 * 18.0).abs() < 0.1, "{fringe}");
}

#[test]
fn focus_breathing_magnifies_by_u_over_u_minus_f() {
    let (w, h) = (96, 64);
    let (c, _) = edge_image(w, h, 70);
    let d = DepthMap::filled(w, h, 1.0);
    let on = RefocusParams {
        focus_m: 1.0,
        focus_breathing: true,
        ..Default::default()
    };
    let out = run(&c, &d, &on);
    let m = 1.0 / (1.0 - 0.05); // u / (u - f), 50 mm at 1 m
    let g = edge_position(&out, 10, 1);
    assert!(
        (g - (48.0 + 22.0 * m)).abs() < 0.05,
        "{g} vs {}",
        48.0 + 22.0 * m
    );
    // off: the field of view stays the input's
    let off = RefocusParams {
        focus_breathing: false,
        ..on
    };
    assert_eq!(run(&c, &d, &off), c);
}

/// Area of the overlap of two discs (radii `r1`, `r2`, centres `d` apart).
fn lens_area(r1: f64, r2: f64, d: f64) -> f64 {
    use std::f64::consts::PI;
    if d >= r1 + r2 {
        return 0.0;
    }
    if d <= (r1 - r2).abs() {
        return PI * r1.min(r2).powi(2);
    }
    let a1 = ((d * d + r1 * r1 - r2 * r2) / (2.0 * d * r1)).acos();
    let a2 = ((d * d + r2 * r2 - r1 * r1) / (2.0 * d * r2)).acos();
    r1 * r1 * (a1 - a1.sin() * a1.cos()) + r2 * r2 * (a2 - a2.sin() * a2.cos())
}

#[test]
fn the_barrel_leaves_a_cats_eye_of_the_right_area_and_orientation() {
    let lens = ThinLens {
        focal_length_mm: 50.0,
        f_number: 2.0,
        focus_m: 2.0,
        sensor_width_mm: 36.0,
    };
    let fx = LensEffects {
        barrel_distance_mm: 30.0,
        ..Default::default()
    };
    let (w, h) = (640, 480);
    let b = match fx.barrel(&lens, w, h) {
        Some(b) => b,
        None => panic!("a barrel at 30 mm"),
    };
    // the barrel is as wide as the aperture: radius 1/2 in aperture units
    assert!((b.radius2 - 0.25).abs() < 1e-12);
    let pts = match Aperture::Disc.samples(20000, 1) {
        Ok(p) => p,
        Err(e) => panic!("{e}"),
    };
    // on the axis nothing is clipped
    assert!(pts.iter().all(|s| b.open(*s, 320.0, 240.0)));
    // toward the top-right corner: the open part is the overlap of the
    // aperture with a disc of radius R / along centred at -per_px d / along
    let (x, y) = (600.0f64, 40.0f64);
    let (dx, dy) = (x - 320.0, y - 240.0);
    let off = b.per_px * (dx * dx + dy * dy).sqrt() / b.along;
    let r2 = b.radius2.sqrt() / b.along;
    let expected = lens_area(0.5, r2, off) / lens_area(0.5, 0.5, 0.0);
    let open: Vec<[f64; 2]> = pts.iter().copied().filter(|s| b.open(*s, x, y)).collect();
    let frac = open.len() as f64 / pts.len() as f64;
    assert!(expected > 0.2 && expected < 0.9, "{expected}");
    assert!((frac - expected).abs() < 0.01, "{frac} vs {expected}");
    // the cat's eye is long across the radius: its spread along the
    // radial direction is the smaller one
    let (ux, uy) = (
        dx / (dx * dx + dy * dy).sqrt(),
        dy / (dx * dx + dy * dy).sqrt(),
    );
    let n = open.len() as f64;
    let mean = open
        .iter()
        .fold([0.0; 2], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
    let (mut radial, mut across) = (0.0, 0.0);
    for p in &open {
        let (qx, qy) = (p[0] - mean[0], p[1] - mean[1]);
        radial += (qx * ux + qy * uy).powi(2) / n;
        across += (qx * uy - qy * ux).powi(2) / n;
    }
    assert!(across > 1.5 * radial, "across {across} radial {radial}");
    // the open part lies toward the centre side (opposite the corner)
    assert!(mean[0] * ux + mean[1] * uy < -0.02, "{mean:?}");
}

#[test]
fn corner_bokeh_is_a_cats_eye_and_in_focus_corners_darken() {
    // A dark wall far behind the focus with a bright point near the corner
    // and one at the centre: the corner's bokeh covers the open fraction of
    // the centre's area; an in-focus grey wall darkens by that fraction.
    let (w, h) = (160, 120);
    let mut c = ColorImage::filled(w, h, [0.0; 3]);
    *c.get_mut(80, 60) = [1.0e4; 3];
    *c.get_mut(140, 18) = [1.0e4; 3];
    let d = DepthMap::filled(w, h, 8.0);
    let p = RefocusParams {
        focus_m: 1.0,
        f_number: 2.0,
        sensor_width_mm: 8.0,
        samples: 1024,
        barrel_distance_mm: 170.0,
        ..Default::default()
    };
    let out = run(&c, &d, &p);
    let count = |x0: usize, y0: usize| {
        let mut n = 0usize;
        for y in y0.saturating_sub(30)..(y0 + 30).min(h) {
            for x in x0.saturating_sub(30)..(x0 + 30).min(w) {
                n += usize::from(out.get(x, y)[0] > 1.0);
            }
        }
        n as f64
    };
    let (centre, corner) = (count(80, 60), count(140, 18));
    let lens = p.lens();
    let b = match p.effects().barrel(&lens, w, h) {
        Some(b) => b,
        None => panic!("barrel"),
    };
    let pts = match Aperture::Disc.samples(4096, 0) {
        Ok(p) => p,
        Err(e) => panic!("{e}"),
    };
    let frac = pts.iter().filter(|s| b.open(**s, 140.5, 18.5)).count() as f64 / 4096.0;
    assert!(frac < 0.8 && frac > 0.2, "{frac}");
    assert!(centre > 200.0, "{centre}");
    assert!(
        (corner / centre - frac).abs() < 0.12,
        "corner {corner} centre {centre} open {frac}"
    );
    // in focus: the grey wall keeps its centre and loses the closed part
    // at the corner
    let grey = ColorImage::filled(w, h, [0.5; 3]);
    let near = DepthMap::filled(w, h, 1.0);
    let sharp = run(&grey, &near, &p);
    assert!((sharp.get(80, 60)[0] - 0.5).abs() < 1e-6);
    let corner_frac = {
        let pts = match Aperture::Disc.samples(256, 0) {
            Ok(p) => p,
            Err(e) => panic!("{e}"),
        };
        pts.iter().filter(|s| b.open(**s, 140.5, 18.5)).count() as f64 / 256.0
    };
    assert!((sharp.get(140, 18)[0] as f64 - 0.5 * corner_frac).abs() < 1e-6);
}

/// Mean of channel `c` of `img` in the ring `r0 <= r < r1` around `(cx, cy)`.
fn ring_mean(img: &ColorImage, cx: f64, cy: f64, r0: f64, r1: f64, c: usize) -> f64 {
    let (mut s, mut n) = (0.0f64, 0.0f64);
    for y in 0..img.height() {
        for x in 0..img.width() {
            let r = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt();
            if r >= r0 && r < r1 {
                s += img.get(x, y)[c] as f64;
                n += 1.0;
            }
        }
    }
    s / n.max(1.0)
}

/// Diameter of a disc-shaped spot of channel `c` from its second moment
/// (`E[r^2] = D^2 / 8` for a uniform disc).
fn spot_diameter(img: &ColorImage, cx: f64, cy: f64, c: usize) -> f64 {
    let (mut m, mut t) = (0.0, 0.0);
    for y in 0..img.height() {
        for x in 0..img.width() {
            let v = img.get(x, y)[c] as f64;
            m += v * ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2));
            t += v;
        }
    }
    (8.0 * m / t).sqrt()
}

fn point_scene(w: usize, h: usize) -> (ColorImage, DepthMap) {
    let mut c = ColorImage::filled(w, h, [0.0; 3]);
    *c.get_mut(w / 2, h / 2) = [1.0e4; 3];
    (c, DepthMap::filled(w, h, 8.0))
}

#[test]
fn spherical_aberration_softens_bokeh_on_one_side_and_rims_it_on_the_other() {
    let (w, h) = (96, 96);
    let (c, d) = point_scene(w, h);
    let base = RefocusParams {
        focus_m: 1.0,
        f_number: 2.0,
        sensor_width_mm: 3.0,
        samples: 2048,
        ..Default::default()
    };
    // behind the focus: a = 1/u - 1/z = 0.875 dioptres
    let a = 1.0 - 1.0 / 8.0;
    let cscale = base.lens().coc_scale(w);
    let profile = |s: f64| {
        let p = RefocusParams {
            spherical_aberration_d: s,
            ..base.clone()
        };
        let out = run(&c, &d, &p);
        // the spot's radius: the rim ray moves by C r (a + S r^2) / 2 at r = 1
        let radius = 0.5 * cscale * (a + s);
        let inner = ring_mean(&out, 48.0, 48.0, 0.0, 0.4 * radius, 0);
        let outer = ring_mean(&out, 48.0, 48.0, 0.6 * radius, 0.9 * radius, 0);
        (inner / outer, spot_diameter(&out, 48.0, 48.0, 0), radius)
    };
    let (flat, _, _) = profile(0.0);
    let (soft, _, _) = profile(0.4);
    let (rim, _, _) = profile(-0.4);
    assert!((flat - 1.0).abs() < 0.1, "no aberration: even disc {flat}");
    assert!(soft > 1.3, "same sign as the defocus: bright centre {soft}");
    assert!(rim < 0.75, "opposite sign: bright rim {rim}");
    // the energy stays where the thin lens puts it (same total)
    let total = |s: f64| {
        let p = RefocusParams {
            spherical_aberration_d: s,
            ..base.clone()
        };
        run(&c, &d, &p)
            .as_slice()
            .iter()
            .map(|p| p[0] as f64)
            .sum::<f64>()
    };
    assert!((total(0.4) - 1.0e4).abs() < 1.0);
}

#[test]
fn longitudinal_chromatic_aberration_gives_each_channel_its_own_focus() {
    let (w, h) = (96, 96);
    let (c, d) = point_scene(w, h);
    let l = 0.3;
    let p = RefocusParams {
        focus_m: 1.0,
        f_number: 2.0,
        sensor_width_mm: 3.0,
        samples: 1024,
        chromatic_longitudinal_d: l,
        ..Default::default()
    };
    let out = run(&c, &d, &p);
    let a = 1.0 - 1.0 / 8.0;
    let cscale = p.lens().coc_scale(w);
    for (ch, k) in [(0usize, 1.0), (1, 0.0), (2, -1.0)] {
        let expected = cscale * (a + k * l);
        let got = spot_diameter(&out, 48.0, 48.0, ch);
        assert!(
            (got - expected).abs() < 0.05 * expected,
            "channel {ch}: {got} vs {expected}"
        );
    }
}

/// The `tabletop` preset's wall at 2.8 m alone (a smooth wave texture): no
/// occlusion and no detail finer than a pixel, so what differs from the
/// ray-traced truth is the lens model. (With the preset's emitters, a
/// pixel or less wide in the pinhole image that Refocus starts from, every
/// setting loses 2-6 dB to that aliasing, the thin lens without effects
/// too; the bokeh's shape is tested analytically above.)
fn wall_scene(w: usize, h: usize) -> Scene {
    let Some(mut scene) = Scene::preset("tabletop", w, h) else {
        panic!("the tabletop preset exists");
    };
    scene.objects.retain(|o| o.id == 2);
    scene
}

/// Display PSNR (linear clamped to [0, 1]) over the pixels where `keep(x, y)`.
fn psnr_where(a: &ColorImage, b: &ColorImage, keep: impl Fn(usize, usize) -> bool) -> f64 {
    let (w, h) = a.dims();
    let (mut s, mut n) = (0.0f64, 0usize);
    for y in 0..h {
        for x in (0..w).filter(|&x| keep(x, y)) {
            for c in 0..3 {
                let (p, q) = (a.get(x, y)[c], b.get(x, y)[c]);
                s += (p.clamp(0.0, 1.0) as f64 - q.clamp(0.0, 1.0) as f64).powi(2);
                n += 1;
            }
        }
    }
    let mse = s / n.max(1) as f64;
    10.0 * (1.0 / mse.max(1e-20)).log10()
}

/// Display PSNR over the pixels at least `margin` from the border: a
/// single image cannot know what lies beyond its frame, which the lens's
/// rays see.
fn display_psnr(a: &ColorImage, b: &ColorImage, margin: usize) -> f64 {
    let (w, h) = a.dims();
    psnr_where(a, b, |x, y| {
        x >= margin && y >= margin && x + margin < w && y + margin < h
    })
}

/// Display PSNR over the pixels less than `band` from the border.
fn border_psnr(a: &ColorImage, b: &ColorImage, band: usize) -> f64 {
    let (w, h) = a.dims();
    psnr_where(a, b, |x, y| {
        x < band || y < band || x + band >= w || y + band >= h
    })
}

/// `scene` through the lens and the lens effects of `p`, 256 rays a
/// pixel through a disc aperture (seed 5).
fn ray_traced(scene: &Scene, p: &RefocusParams) -> ColorImage {
    let opts = ThinLensRender {
        lens: p.lens(),
        aperture: Aperture::Disc,
        samples: 256,
        seed: 5,
        effects: p.effects(),
        pixel_area: false,
    };
    match render_thin_lens(scene, &opts, |_| Ok(())) {
        Ok(t) => t,
        Err(e) => panic!("{p:?}: {e}"),
    }
}

/// Every effect against the ray-traced lens with the same effect (display
/// PSNR >= 38 dB), and the thin lens without it is clearly further from
/// that truth (so the check fails when the effect is wrong or missing).
#[test]
fn each_effect_matches_the_ray_traced_lens() {
    let (w, h) = (128, 96);
    let scene = wall_scene(w, h);
    let pin = render(&scene, &RenderOptions::default());
    let base = RefocusParams {
        focus_m: 1.4,
        f_number: 2.8,
        sensor_width_mm: 36.0 * w as f64 / 640.0,
        samples: 256,
        ..Default::default()
    };
    let cases: Vec<(&str, RefocusParams)> = vec![
        (
            "spherical",
            RefocusParams {
                spherical_aberration_d: 0.5,
                ..base.clone()
            },
        ),
        (
            "longitudinal chromatic",
            RefocusParams {
                chromatic_longitudinal_d: 0.4,
                ..base.clone()
            },
        ),
        (
            "lateral chromatic",
            RefocusParams {
                chromatic_lateral: 0.03,
                ..base.clone()
            },
        ),
        (
            "optical vignetting",
            RefocusParams {
                barrel_distance_mm: 25.0,
                ..base.clone()
            },
        ),
        (
            "natural vignetting",
            RefocusParams {
                natural_vignetting: 1.0,
                ..base.clone()
            },
        ),
        (
            "focus breathing",
            RefocusParams {
                focus_breathing: true,
                ..base.clone()
            },
        ),
    ];
    let plain = ray_traced(&scene, &base);
    // beyond the largest blur radius (about 7 px) and the breathing
    let margin = 16;
    let base_db = display_psnr(&run(&pin.color, &pin.depth, &base), &plain, margin);
    eprintln!("no effect: {base_db:.1} dB");
    assert!(base_db >= 38.0, "{base_db}");
    for (name, p) in cases {
        let truth = ray_traced(&scene, &p);
        let ours = run(&pin.color, &pin.depth, &p);
        let without = run(
            &pin.color,
            &pin.depth,
            &RefocusParams {
                focus_m: p.focus_m,
                ..base.clone()
            },
        );
        let (with_db, without_db) = (
            display_psnr(&ours, &truth, margin),
            display_psnr(&without, &truth, margin),
        );
        eprintln!("{name}: {with_db:.1} dB, without the effect {without_db:.1} dB");
        assert!(with_db >= 38.0, "{name}: {with_db:.1} dB");
        assert!(
            with_db > without_db + 3.0,
            "{name}: {with_db:.1} vs {without_db:.1} dB"
        );
    }
}

/// Spherical aberration spreads a bright point's views apart (module docs
/// of `view_filter`): at 64 samples its bokeh is a scatter of dots. The
/// filter brings it at least halfway to the converged bokeh (4096 views,
/// no filter) in RMS without widening it, keeps its energy (the spot lies
/// far from the border), and leaves the thin lens's bits alone.
#[test]
fn the_view_filter_closes_the_gaps_spherical_aberration_opens() {
    let (w, h) = (96, 96);
    let (c, d) = point_scene(w, h);
    let with = |samples: usize, s: f64, k: f64| {
        run(
            &c,
            &d,
            &RefocusParams {
                focus_m: 1.0,
                f_number: 2.0,
                sensor_width_mm: 3.0,
                samples,
                spherical_aberration_d: s,
                view_filter: k,
                ..Default::default()
            },
        )
    };
    let rms = |a: &ColorImage, b: &ColorImage| {
        let s: f64 = a
            .as_slice()
            .iter()
            .zip(b.as_slice())
            .map(|(p, q)| (p[1] as f64 - q[1] as f64).powi(2))
            .sum();
        (s / (w * h) as f64).sqrt()
    };
    let reference = with(4096, 0.8, 0.0);
    let (dots, filtered) = (with(64, 0.8, 0.0), with(64, 0.8, 0.5));
    let (e_dots, e_filtered) = (rms(&dots, &reference), rms(&filtered, &reference));
    eprintln!("RMS to the converged bokeh: {e_dots:.3} unfiltered, {e_filtered:.3} filtered");
    assert!(e_filtered < 0.5 * e_dots, "{e_filtered} vs {e_dots}");
    // and no wider: the spot's diameter within a pixel of the converged one
    let (d_ref, d_filtered) = (
        spot_diameter(&reference, 48.0, 48.0, 1),
        spot_diameter(&filtered, 48.0, 48.0, 1),
    );
    eprintln!("spot diameter: {d_ref:.2} converged, {d_filtered:.2} filtered");
    assert!((d_filtered - d_ref).abs() < 1.0, "{d_filtered} vs {d_ref}");
    let total = |im: &ColorImage| im.as_slice().iter().map(|p| p[1] as f64).sum::<f64>();
    assert!(
        (total(&filtered) - 1.0e4).abs() < 1.0,
        "{}",
        total(&filtered)
    );
    let (thin, thin_off) = (with(64, 0.0, 0.5), with(64, 0.0, 0.0));
    assert_eq!(thin.as_slice(), thin_off.as_slice());
}

/// `explain` says whether the views' gaps were smoothed and how wide the
/// filter got, or that they were left; nothing about it on a thin lens.
#[test]
fn explain_reports_the_view_filter() {
    let (c, d) = point_scene(64, 64);
    let said = |s: f64, k: f64| {
        let p = RefocusParams {
            focus_m: 1.0,
            f_number: 2.0,
            sensor_width_mm: 3.0,
            samples: 64,
            spherical_aberration_d: s,
            view_filter: k,
            ..Default::default()
        };
        let (out, rep) = match refocus(&c, &d, &Aperture::Disc, &p, |_| Ok(())) {
            Ok(r) => r,
            Err(e) => panic!("{e}"),
        };
        let text = produced(crate::camera::refocus::RefocusOut { color: out }, &p, &rep)
            .report
            .unwrap_or_default();
        (rep.view_filter_px, text)
    };
    let (px, text) = said(0.8, 0.5);
    assert!(px > 0.3 && px.is_finite(), "{px}");
    assert!(
        text.contains("smoothed (view_filter 0.5): a Gaussian of up to"),
        "{text}"
    );
    let (px, text) = said(0.8, 0.0);
    assert_eq!(px, 0.0);
    assert!(text.contains("view_filter 0: the gaps"), "{text}");
    let (px, text) = said(0.0, 0.5);
    assert_eq!(px, 0.0);
    assert!(!text.contains("view_filter"), "{text}");
}

/// `frame_border` reflect against the ray-traced lens, whose rays see the
/// wall continue past the frame: the border band (where a view reads
/// beyond the input) comes clearly nearer the truth than with the edge
/// behaviour, the pixels no view's read past the border reaches keep
/// their bits, and explain says by how much the frame was extended.
#[test]
fn a_reflected_frame_continues_the_wall_past_the_border() {
    let (w, h) = (128, 96);
    let scene = wall_scene(w, h);
    let pin = render(&scene, &RenderOptions::default());
    let edge = RefocusParams {
        focus_m: 1.0,
        f_number: 1.4,
        sensor_width_mm: 36.0 * w as f64 / 640.0,
        samples: 256,
        ..Default::default()
    };
    let reflect = RefocusParams {
        frame_border: crate::camera::frame_border::FrameBorder::Reflect,
        ..edge.clone()
    };
    let truth = ray_traced(&scene, &edge);
    let go =
        |p: &RefocusParams| match refocus(&pin.color, &pin.depth, &Aperture::Disc, p, |_| Ok(())) {
            Ok(r) => r,
            Err(e) => panic!("{e}"),
        };
    let ((a, rep_a), (b, rep_b)) = (go(&edge), go(&reflect));
    assert_eq!(b.dims(), (w, h));
    assert_eq!(rep_a.frame_pad_px, 0);
    let pad = rep_b.frame_pad_px;
    assert_eq!(
        pad,
        (rep_b.max_coc_px / 2.0).ceil() as usize + 1,
        "{rep_b:?}"
    );
    let band = pad;
    let (db_edge, db_reflect) = (border_psnr(&a, &truth, band), border_psnr(&b, &truth, band));
    eprintln!(
        "border band {band} px: edge {db_edge:.2} dB, reflect {db_reflect:.2} dB; interior {:.2} / {:.2}",
        display_psnr(&a, &truth, band),
        display_psnr(&b, &truth, band)
    );
    assert!(
        db_reflect > db_edge + 3.0,
        "{db_reflect:.2} vs {db_edge:.2}"
    );
    // Pixels farther than twice the reach from the border neither read past
    // it nor are filled from what did (the views' fill marches stay within
    // a reach of the pixel): the same bits.
    let far = 2 * pad;
    for y in far..h - far {
        for x in far..w - far {
            assert_eq!(a.get(x, y), b.get(x, y), "({x}, {y})");
        }
    }
    let text = produced(
        crate::camera::refocus::RefocusOut { color: b },
        &reflect,
        &rep_b,
    )
    .report
    .unwrap_or_default();
    assert!(
        text.contains(&format!("frame extended by {pad} px on each side")),
        "{text}"
    );
}
