//! Refocusing accuracy and time against a distributed-ray-traced thin lens:
//! `cargo bench --bench refocus` regenerates `docs/refocus.md` and the
//! images in `docs/refocus/`.
//!
//! The scene is the synthetic tabletop (a near mug and a tall cylinder in
//! front of a wall with small emitters of radiance 40, the bokeh case of the
//! depth-blur paper's Fig. 5). The pinhole render (exact depth, all in
//! focus) is the input; `SyntheticThinLens` renders the same scene through
//! the same lens with many rays per pixel (the ground truth). Errors are on
//! display values (linear clamped to [0, 1], sRGB encoded): PSNR over all
//! channels and SSIM of the luma.
//!
//! Environment: `DEPTHGRAPH_REFOCUS_GT_RAYS` (default 512) rays per pixel of
//! the ground truth; `DEPTHGRAPH_REPEATS` (default 3) timed repeats;
//! `DEPTHGRAPH_REFOCUS_ONLY=speed` (the 640x480 time alone), `=effects`
//! (each lens effect's time beside the effects off, interleaved; only those
//! whose name holds `DEPTHGRAPH_REFOCUS_EFFECT`) or
//! `=occlusion` (the partial-occlusion table alone, images to the temp dir),
//! `=frame` (the frame-border table alone)
//! print one section and leave the docs alone.

mod common;
use common::{env_usize, timed, timed_pair};

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthgraph::graph::prelude::*;
use depthgraph::metrics::{display_psnr, display_ssim};
use depthgraph::nodes::camera::lens::Aperture;
use depthgraph::nodes::camera::refocus::{RefocusParams, refocus, reverse_mapped_dof};
use depthgraph::nodes::kit::color::srgb8;
use depthgraph::nodes::sim::synthetic::{
    RenderOptions, RenderOutput, Scene, ThinLensRender, render, render_thin_lens,
};

fn lens_params(width: usize, focus_m: f64, samples: usize) -> RefocusParams {
    RefocusParams {
        focal_length_mm: 50.0,
        f_number: 1.4,
        focus_m,
        // A full-frame sensor at 640 px: the same blur in pixels at any size.
        sensor_width_mm: 36.0 * width as f64 / 640.0,
        samples,
        ..Default::default()
    }
}

/// The tabletop at 640x480 focused near (f/1.4, 256 samples): its pinhole
/// render, the lens, and the median times (ms) of the reverse-mapped blur
/// and of Refocus in one run.
fn speed_640(repeats: usize) -> (RenderOutput, RefocusParams, f64, f64) {
    let scene = Scene::preset("tabletop", 640, 480).expect("preset");
    let pin = render(&scene, &RenderOptions::default());
    let p = lens_params(640, 0.95, 256);
    let (_, ms_rev) = timed(repeats, || {
        reverse_mapped_dof(&pin.color, &pin.depth, &Aperture::Disc, &p).expect("reverse")
    });
    let (_, ms) = timed(repeats, || {
        refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
    });
    (pin, p, ms_rev, ms)
}

fn save_png(path: &Path, img: &ColorImage) {
    let (w, h) = img.dims();
    let bytes: Vec<u8> = img.as_slice().iter().flat_map(|c| c.map(srgb8)).collect();
    if let Some(dir) = path.parent() {
        let _ = std::fs::create_dir_all(dir);
    }
    if let Err(e) = image::save_buffer(path, &bytes, w as u32, h as u32, image::ColorType::Rgb8) {
        eprintln!("could not write {}: {e}", path.display());
    }
}

fn truth(scene: &Scene, p: &RefocusParams, rays: usize) -> (ColorImage, f64) {
    truth_with(scene, p, rays, false)
}

/// The thin-lens truth, its rays through the pixel centres or, with
/// `pixel_area`, spread over each pixel's square.
fn truth_with(
    scene: &Scene,
    p: &RefocusParams,
    rays: usize,
    pixel_area: bool,
) -> (ColorImage, f64) {
    let t = Instant::now();
    let img = render_thin_lens(
        scene,
        &ThinLensRender {
            lens: p.lens(),
            aperture: Aperture::Disc,
            samples: rays,
            seed: 12345,
            effects: p.effects(),
            pixel_area,
        },
        |_| Ok(()),
    )
    .expect("valid lens");
    (img, t.elapsed().as_secs_f64())
}

fn main() {
    let rays = env_usize("DEPTHGRAPH_REFOCUS_GT_RAYS", 512);
    let repeats = env_usize("DEPTHGRAPH_REPEATS", 3);
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let img_dir = root.join("docs/refocus");
    let mut doc = String::new();
    if std::env::var("DEPTHGRAPH_REFOCUS_ONLY").as_deref() == Ok("speed") {
        // The 640x480, 256-sample time alone (effects off), beside the
        // reverse-mapped blur in the same run.
        let (_, _, ms_rev, ms) = speed_640(repeats);
        println!("Refocus 640x480, 256 samples: {ms:.0} ms; reverse-mapped {ms_rev:.0} ms");
        return;
    }
    if std::env::var("DEPTHGRAPH_REFOCUS_ONLY").as_deref() == Ok("effects") {
        let only = std::env::var("DEPTHGRAPH_REFOCUS_EFFECT").unwrap_or_default();
        for (name, ms_off, ms, ratio, sum) in effect_times(repeats, &only) {
            println!(
                "{name}: {ms:.0} ms, off {ms_off:.0} ms, ratio {ratio:.2}, checksum {sum:016x}"
            );
        }
        return;
    }
    if std::env::var("DEPTHGRAPH_REFOCUS_ONLY").as_deref() == Ok("area") {
        area_pixels(&mut doc, repeats, rays);
        println!("{doc}");
        return;
    }
    if std::env::var("DEPTHGRAPH_REFOCUS_ONLY").as_deref() == Ok("frame") {
        frame_border(&mut doc, repeats, rays);
        println!("{doc}");
        return;
    }
    if std::env::var("DEPTHGRAPH_REFOCUS_ONLY").as_deref() == Ok("occlusion") {
        // One section alone, printed, docs untouched (for tuning).
        partial_occlusion(&mut doc, repeats, rays, &std::env::temp_dir());
        println!("{doc}");
        return;
    }
    let threads = rayon::current_num_threads();
    writeln!(
        doc,
        "# Refocusing: accuracy and time\n\n\
         Generated by `cargo bench --bench refocus` ({threads} threads). Scene: the synthetic tabletop \
         (SyntheticScene preset `tabletop`), a 50 mm f/1.4 lens on a full-frame sensor (36 mm spanning 640 px), \
         disc aperture. Input: the pinhole render (color + exact depth). Ground truth: `SyntheticThinLens`, \
         {rays} rays per pixel through the same lens. Errors on display values (clamped to [0, 1], sRGB): \
         PSNR (dB, higher is better) and SSIM of the luma.\n"
    )
    .ok();

    // ------------------------------------------------------------ Fig. 5
    let (w, h) = (320, 240);
    let scene = Scene::preset("tabletop", w, h).expect("preset");
    let pin: RenderOutput = render(&scene, &RenderOptions::default());
    writeln!(
        doc,
        "## Focus near, middle and far ({w}x{h}; the paper's Fig. 5 comparison)\n\n\
         | focus | max CoC (px) | method | PSNR | PSNR inside | SSIM | time (ms) |\n|---|---|---|---|---|---|---|"
    )
    .ok();
    let inside = interior(w, h, FRAME_BORDER_PX);
    let mut near_truth = None;
    for (label, focus) in [("near", 0.95), ("middle", 1.6), ("far", 2.8)] {
        let p = lens_params(w, focus, 256);
        let (gt, gt_s) = truth(&scene, &p, rays);
        eprintln!("truth {label}: {gt_s:.1} s");
        let ((ours, rep), ms_ours) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
        });
        let (rev, ms_rev) = timed(repeats, || {
            reverse_mapped_dof(&pin.color, &pin.depth, &Aperture::Disc, &p).expect("reverse")
        });
        for (name, img, ms) in [
            ("pinhole input (no blur)", &pin.color, 0.0),
            ("reverse-mapped z-buffer DoF", &rev, ms_rev),
            ("Refocus, 256 samples (Sec. 2.3)", &ours, ms_ours),
        ] {
            writeln!(
                doc,
                "| {label} ({focus} m) | {:.1} | {name} | {:.2} | {:.2} | {:.4} | {ms:.0} |",
                rep.max_coc_px,
                display_psnr(img, &gt).unwrap_or(f64::NAN),
                masked_psnr(img, &gt, &inside),
                display_ssim(img, &gt).unwrap_or(f64::NAN),
            )
            .ok();
        }
        save_png(&img_dir.join(format!("truth_{label}.png")), &gt);
        save_png(&img_dir.join(format!("refocus_{label}.png")), &ours);
        save_png(&img_dir.join(format!("reverse_{label}.png")), &rev);
        if label == "near" {
            save_png(&img_dir.join("pinhole.png"), &pin.color);
            near_truth = Some((gt, p));
        }
        writeln!(
            doc,
            "| | | ground truth render time | | | | {:.0} |",
            gt_s * 1e3
        )
        .ok();
    }
    writeln!(
        doc,
        "\nImages (focus near): [truth](refocus/truth_near.png), [Refocus](refocus/refocus_near.png), \
         [reverse-mapped](refocus/reverse_near.png), [pinhole input](refocus/pinhole.png); \
         middle and far likewise.\n\n\
         **PSNR inside**: the same without the frame's outer {FRAME_BORDER_PX} pixels. Near the frame's \
         edge the truth's rays reach what lies beyond the frame, which the input does not hold; each \
         view fills what its shift uncovers there from the image's own edge, and those \
         {FRAME_BORDER_PX} pixels (5 % of the image) carry a third to a half of the squared error.\n"
    )
    .ok();

    // ------------------------------------------------------------ samples
    if let Some((gt, p)) = near_truth {
        writeln!(
            doc,
            "## Error against time: samples (focus near, {w}x{h})\n\n\
             | samples | PSNR | SSIM | time (ms) |\n|---|---|---|---|"
        )
        .ok();
        let settings: Vec<(String, usize, f64)> = [16, 64, 256, 576, 1024]
            .iter()
            .map(|&n| (n.to_string(), n, 1.0))
            .chain([
                ("auto (quality 1)".to_string(), 0, 1.0),
                ("auto (quality 2)".to_string(), 0, 2.0),
            ])
            .collect();
        for (label, n, q) in settings {
            let p = RefocusParams {
                samples: n,
                quality: q,
                ..p.clone()
            };
            let ((img, rep), ms) = timed(repeats, || {
                refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
            });
            writeln!(
                doc,
                "| {label} ({} used) | {:.2} | {:.4} | {ms:.0} |",
                rep.samples,
                display_psnr(&img, &gt).unwrap_or(f64::NAN),
                display_ssim(&img, &gt).unwrap_or(f64::NAN)
            )
            .ok();
        }
        writeln!(
            doc,
            "\nThe ground truth itself carries Monte Carlo noise from {rays} rays per pixel, \
             which bounds the PSNR any method can reach.\n"
        )
        .ok();
    }

    // ------------------------------------------------------------ speed
    writeln!(
        doc,
        "## Speed at 640x480 (focus near, f/1.4, max CoC about 47 px)\n\n\
         | method | time (ms) | ratio to reverse-mapped |\n|---|---|---|"
    )
    .ok();
    let (pin, p, ms_rev, ms_256) = speed_640(repeats);
    writeln!(doc, "| reverse-mapped z-buffer DoF | {ms_rev:.0} | 1.00 |").ok();
    writeln!(
        doc,
        "| Refocus, 256 samples | {ms_256:.0} | {:.2} |\n",
        ms_256 / ms_rev
    )
    .ok();
    writeln!(
        doc,
        "### Time against samples (640x480)\n\n| samples | time (ms) | ms per sample |\n|---|---|---|"
    )
    .ok();
    for n in [16, 64, 256, 1024] {
        let p = RefocusParams {
            samples: n,
            ..p.clone()
        };
        let (_, ms) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
        });
        writeln!(doc, "| {n} | {ms:.0} | {:.2} |", ms / n as f64).ok();
    }
    writeln!(
        doc,
        "\n### Time against image size (64 samples, the same lens: blur in pixels grows with the size)\n\n\
         | size | megapixels | max CoC (px) | time (ms) | ms per MP |\n|---|---|---|---|---|"
    )
    .ok();
    for (w, h) in [(320, 240), (640, 480), (1280, 960), (2048, 1536)] {
        let scene = Scene::preset("tabletop", w, h).expect("preset");
        let pin = render(&scene, &RenderOptions::default());
        let p = RefocusParams {
            sensor_width_mm: 36.0,
            samples: 64,
            ..lens_params(w, 0.95, 64)
        };
        let ((_, rep), ms) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
        });
        let mp = (w * h) as f64 / 1e6;
        writeln!(
            doc,
            "| {w}x{h} | {mp:.2} | {:.0} | {ms:.0} | {:.0} |",
            rep.max_coc_px,
            ms / mp
        )
        .ok();
    }

    // ------------------------------------------------------------ lens effects
    lens_effects(&mut doc, repeats, rays, &img_dir);

    // ------------------------------------------------------------ occlusion
    partial_occlusion(&mut doc, repeats, rays, &img_dir);

    // ------------------------------------------------------------ pixel area
    area_pixels(&mut doc, repeats, rays);

    // ------------------------------------------------------------ frame border
    frame_border(&mut doc, repeats, rays);

    // ------------------------------------------------------------ shapes
    writeln!(doc, "\n## Bokeh shapes\n").ok();
    let scene = Scene::preset("tabletop", 320, 240).expect("preset");
    let pin = render(&scene, &RenderOptions::default());
    for (name, ap) in [
        ("disc", Aperture::Disc),
        (
            "hexagon",
            Aperture::Polygon {
                blades: 6,
                rotation_deg: 0.0,
            },
        ),
        (
            "triangle",
            Aperture::Polygon {
                blades: 3,
                rotation_deg: 0.0,
            },
        ),
    ] {
        let p = lens_params(320, 0.95, 576);
        if let Ok((img, _)) = refocus(&pin.color, &pin.depth, &ap, &p, |_| Ok(())) {
            save_png(&img_dir.join(format!("bokeh_{name}.png")), &img);
            write!(doc, "[{name}](refocus/bokeh_{name}.png) ").ok();
        }
    }
    writeln!(doc, "(focus near, 576 samples).").ok();

    let out = root.join("docs/refocus.md");
    match std::fs::write(&out, &doc) {
        Ok(()) => eprintln!("wrote {}", out.display()),
        Err(e) => eprintln!("could not write {}: {e}", out.display()),
    }
    println!("{doc}");
}

/// The lens effects beyond the thin lens: one setting each.
fn effect_cases(base: &RefocusParams) -> Vec<(&'static str, RefocusParams)> {
    vec![
        (
            "spherical aberration, 0.8 D",
            RefocusParams {
                spherical_aberration_d: 0.8,
                ..base.clone()
            },
        ),
        (
            "spherical aberration, -0.8 D",
            RefocusParams {
                spherical_aberration_d: -0.8,
                ..base.clone()
            },
        ),
        (
            "spherical aberration, 0.8 D, view filter off",
            RefocusParams {
                spherical_aberration_d: 0.8,
                view_filter: 0.0,
                ..base.clone()
            },
        ),
        (
            "longitudinal chromatic, 0.3 D",
            RefocusParams {
                chromatic_longitudinal_d: 0.3,
                ..base.clone()
            },
        ),
        (
            "lateral chromatic, 0.01",
            RefocusParams {
                chromatic_lateral: 0.01,
                ..base.clone()
            },
        ),
        (
            "optical vignetting, barrel 60 mm ahead",
            RefocusParams {
                barrel_distance_mm: 60.0,
                ..base.clone()
            },
        ),
        (
            "natural vignetting (cos^4)",
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
        (
            "all of them",
            RefocusParams {
                spherical_aberration_d: 0.8,
                chromatic_longitudinal_d: 0.3,
                chromatic_lateral: 0.01,
                barrel_distance_mm: 60.0,
                natural_vignetting: 1.0,
                focus_breathing: true,
                ..base.clone()
            },
        ),
    ]
}

/// Each lens effect's 640x480, 256-sample time, interleaved with the
/// effects off (`timed_pair`): name, off (ms), on (ms), their ratio and a
/// checksum of the image (a speed-up that keeps the output keeps it).
fn effect_times(repeats: usize, only: &str) -> Vec<(&'static str, f64, f64, f64, u64)> {
    let big = Scene::preset("tabletop", 640, 480).expect("preset");
    let pin = render(&big, &RenderOptions::default());
    let base = lens_params(640, 0.95, 256);
    let run = |p: &RefocusParams| {
        refocus(&pin.color, &pin.depth, &Aperture::Disc, p, |_| Ok(())).expect("refocus")
    };
    effect_cases(&base)
        .into_iter()
        .filter(|(name, _)| name.contains(only))
        .map(|(name, p)| {
            let ((img, _), off, on, ratio) = timed_pair(repeats, || run(&base), || run(&p));
            (name, off, on, ratio, checksum(&img))
        })
        .collect()
}

/// FNV-1a over the image's f32 bits.
fn checksum(img: &ColorImage) -> u64 {
    img.as_slice()
        .iter()
        .flatten()
        .flat_map(|v| v.to_bits().to_le_bytes())
        .fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
        })
}

fn lens_effects(doc: &mut String, repeats: usize, gt_rays: usize, out_dir: &Path) {
    writeln!(
        doc,
        "\n## Lens effects (`Refocus` parameters; each off at 0)\n\n\
         The model (`LensEffects` in `nodes/src/camera/lens.rs`) is shared by `Refocus` and `SyntheticThinLens`, \
         which traces every ray through it. Accuracy: 320x240, focus near, against the truth rendered with the same \
         effect ({gt_rays} rays per pixel); the row \"thin lens\" is Refocus without the effect against that same truth. \
         Spherical aberration spreads the views apart unevenly; `view_filter` (0.5, the default; nothing on a thin lens) \
         smooths the gaps it adds (`nodes/src/camera/view_filter.rs`), the row \"view filter off\" shows it off. \
         Time: 640x480, 256 samples, each effect timed alternately with the effects off (the off row: the median of those), ratio of the two medians.\n\n\
         | effect | PSNR | PSNR without the effect | time (ms) | ratio to off |\n|---|---|---|---|---|"
    )
    .ok();
    let (w, h) = (320, 240);
    let scene = Scene::preset("tabletop", w, h).expect("preset");
    let pin = render(&scene, &RenderOptions::default());
    let base = lens_params(w, 0.95, 256);
    let times = effect_times(repeats, "");
    let ms_off = common::median(times.iter().map(|t| t.1).collect());
    writeln!(doc, "| off (the thin lens) | | | {ms_off:.0} | 1.00 |").ok();
    for ((name, p), (_, _, ms, ratio, _)) in effect_cases(&base).into_iter().zip(times) {
        let (gt, _) = truth(&scene, &p, gt_rays);
        let (ours, _) =
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus");
        let (plain, _) =
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &base, |_| Ok(())).expect("refocus");
        writeln!(
            doc,
            "| {name} | {:.2} | {:.2} | {ms:.0} | {ratio:.2} |",
            display_psnr(&ours, &gt).unwrap_or(f64::NAN),
            display_psnr(&plain, &gt).unwrap_or(f64::NAN),
        )
        .ok();
    }
    // bokeh grids: far points at the centre, edges and corners
    writeln!(
        doc,
        "\nBokeh grids (bright points on a black wall at 8 m, focus 1 m, 320x240, 4096 samples): \
         [thin lens](refocus/bokeh_off.png)"
    )
    .ok();
    let (gw, gh) = (320, 240);
    let mut grid = ColorImage::filled(gw, gh, [0.0; 3]);
    for gy in [24, gh / 2, gh - 24] {
        for gx in [24, gw / 2, gw - 24] {
            *grid.get_mut(gx, gy) = [400.0; 3];
        }
    }
    let wall = DepthMap::filled(gw, gh, 8.0);
    let gbase = RefocusParams {
        focus_m: 1.0,
        f_number: 2.0,
        sensor_width_mm: 12.0,
        samples: 4096,
        ..Default::default()
    };
    let shot = |p: &RefocusParams| {
        refocus(&grid, &wall, &Aperture::Disc, p, |_| Ok(()))
            .expect("refocus")
            .0
    };
    save_png(&out_dir.join("bokeh_off.png"), &shot(&gbase));
    let grid_cases = [
        (
            "spherical, +0.5 D (soft)",
            "bokeh_spherical_soft",
            RefocusParams {
                spherical_aberration_d: 0.5,
                ..gbase.clone()
            },
        ),
        (
            "spherical, -0.5 D (bright rim)",
            "bokeh_spherical_rim",
            RefocusParams {
                spherical_aberration_d: -0.5,
                ..gbase.clone()
            },
        ),
        (
            "longitudinal chromatic, 0.5 D",
            "bokeh_chromatic_longitudinal",
            RefocusParams {
                chromatic_longitudinal_d: 0.5,
                ..gbase.clone()
            },
        ),
        (
            "lateral chromatic, 0.03",
            "bokeh_chromatic_lateral",
            RefocusParams {
                chromatic_lateral: 0.03,
                ..gbase.clone()
            },
        ),
        (
            "optical vignetting (cat's eye)",
            "bokeh_cats_eye",
            RefocusParams {
                barrel_distance_mm: 60.0,
                ..gbase.clone()
            },
        ),
        (
            "natural vignetting",
            "bokeh_natural_vignetting",
            RefocusParams {
                natural_vignetting: 1.0,
                ..gbase.clone()
            },
        ),
    ];
    for (name, file, p) in grid_cases {
        save_png(&out_dir.join(format!("{file}.png")), &shot(&p));
        write!(doc, ", [{name}](refocus/{file}.png)").ok();
    }
    writeln!(doc).ok();
}

/// Display PSNR over the pixels flagged in `mask` only (as `display_psnr`).
/// The outer pixels of the frame that "PSNR inside" leaves out.
const FRAME_BORDER_PX: usize = 4;

/// Pixels at least `b` from every side of a `w` x `h` frame.
fn interior(w: usize, h: usize, b: usize) -> Vec<bool> {
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            x >= b && y >= b && x + b < w && y + b < h
        })
        .collect()
}

fn masked_psnr(a: &ColorImage, b: &ColorImage, mask: &[bool]) -> f64 {
    use depthgraph::nodes::kit::color::{display_mse_masked, psnr_of_mse};
    if !mask.iter().any(|m| *m) {
        return f64::NAN;
    }
    psnr_of_mse(display_mse_masked(a.as_slice(), b.as_slice(), mask))
}

/// Pixels within `r` of a depth edge (relative inverse-depth step > 5 %
/// between 4-neighbours): where partial occlusion shows.
fn edge_band(depth: &DepthMap, r: usize) -> Vec<bool> {
    let (w, h) = depth.dims();
    let v: Vec<f64> = depth
        .as_slice()
        .iter()
        .map(|&z| {
            if z > 0.0 && z.is_finite() {
                1.0 / z as f64
            } else {
                0.0
            }
        })
        .collect();
    let step = |a: f64, b: f64| (a - b).abs() > 0.05 * (a + b);
    let mut edge = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if (x + 1 < w && step(v[i], v[i + 1])) || (y + 1 < h && step(v[i], v[i + w])) {
                edge[i] = true;
            }
        }
    }
    let mut band = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            if edge[y * w + x] {
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        band[yy * w + xx] = true;
                    }
                }
            }
        }
    }
    band
}

/// The focus settings of the first table and the thin scene's (preset,
/// label, focus in metres, background layer and texture on).
const FOCUS_CASES: [(&str, &str, f64, bool); 5] = [
    ("tabletop", "tabletop, near", 0.95, false),
    ("tabletop", "tabletop, middle", 1.6, false),
    ("tabletop", "tabletop, far", 2.8, false),
    ("thin", "thin, on the poles", 1.2, true),
    ("thin", "thin, on the wall", 2.0, true),
];

/// The focus settings of the first table and the thin scene's with pixels
/// that integrate their square, as a sensor's do: the input is the 4x4 supersampled pinhole
/// render (its depth still from the pixel centre, as a depth camera gives
/// one depth a pixel) and the truth's rays spread over each pixel.
fn area_pixels(doc: &mut String, repeats: usize, rays: usize) {
    let (w, h) = (320, 240);
    writeln!(
        doc,
        "\n## Pixels that integrate their area\n\n\
         The tables above sample every pixel at its centre, in the input and in the truth: the \
         input then aliases fine texture (the floor's grid, the checker) that no refocusing can \
         undo, and the truth keeps what a lens blurs continuously. A sensor pixel integrates its \
         square: here the input is the pinhole render with 4x4 samples a pixel (colour only; the \
         depth stays the centre's, one depth a pixel as a depth camera gives) and the truth's \
         {rays} rays a pixel are spread over its square (`ThinLensRender::pixel_area`). {w}x{h}, \
         50 mm f/1.4, Refocus with 256 samples (the thin scene with the background layer and its \
         texture, the table above's best). \"edges\": within 8 px of a depth edge.\n\n\
         | scene, focus | PSNR | PSNR at edges | PSNR inside | SSIM | PSNR, centre samples (tables above) | time (ms) |\n\
         |---|---|---|---|---|---|---|"
    )
    .ok();
    let inside = interior(w, h, FRAME_BORDER_PX);
    for (preset, label, focus, layer) in FOCUS_CASES {
        let scene = Scene::preset(preset, w, h).expect("preset");
        let area = render(&scene, &RenderOptions { supersample: 4 });
        let centre = render(&scene, &RenderOptions::default());
        let band = edge_band(&area.depth, 8);
        let p = RefocusParams {
            background_layer: layer,
            background_texture: layer,
            ..lens_params(w, focus, 256)
        };
        let (gt, gt_s) = truth_with(&scene, &p, rays, true);
        let (gt_centre, _) = truth(&scene, &p, rays);
        eprintln!("area truth {label}: {gt_s:.1} s");
        let ((ours, _), ms) = timed(repeats, || {
            refocus(&area.color, &area.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
        });
        let (centred, _) = refocus(
            &centre.color,
            &centre.depth,
            &Aperture::Disc,
            &p,
            |_| Ok(()),
        )
        .expect("refocus");
        writeln!(
            doc,
            "| {label} ({focus} m) | {:.2} | {:.2} | {:.2} | {:.4} | {:.2} | {ms:.0} |",
            display_psnr(&ours, &gt).unwrap_or(f64::NAN),
            masked_psnr(&ours, &gt, &band),
            masked_psnr(&ours, &gt, &inside),
            display_ssim(&ours, &gt).unwrap_or(f64::NAN),
            display_psnr(&centred, &gt_centre).unwrap_or(f64::NAN),
        )
        .ok();
    }
    writeln!(
        doc,
        "\nA pixel that straddles a depth edge mixes the colours of both sides but keeps one depth, \
         the centre's: its share of the other side is blurred with the wrong circle of confusion. \
         That costs most at the small bright emitters when the background is blurred (focus near), \
         where part of an emitter's light is spread over the wall's larger disc."
    )
    .ok();
}

/// Partial occlusion (issue 23, item 3): the background layer against the
/// per-view fill and the reverse-mapped gather, on thin in-focus structures
/// before a blurred wall and blurred near edges over a sharp background.
fn partial_occlusion(doc: &mut String, repeats: usize, rays: usize, out_dir: &Path) {
    let (w, h) = (320, 240);
    writeln!(
        doc,
        "\n## Partial occlusion: the background layer\n\n\
         `background_layer = true` inpaints, once, what lies behind every foreground edge as far as \
         some view reveals it (from the background side, colour and depth) and warps it with the \
         image in every view; off, each view fills what it reveals on its own. {w}x{h}, 50 mm f/1.4, \
         256 samples, truth {rays} rays per pixel. \"edges\": PSNR over the pixels within 8 px of a \
         depth edge, where partial occlusion shows.\n\n\
         | scene, focus | method | PSNR | PSNR at edges | PSNR inside | SSIM | time (ms) |\n|---|---|---|---|---|---|---|"
    )
    .ok();
    let inside = interior(w, h, FRAME_BORDER_PX);
    let cases = [
        (
            "thin",
            "thin, focus on the poles (1.2 m): blurred wall behind sharp poles",
            "thin_near",
            1.2,
        ),
        (
            "thin",
            "thin, focus on the wall (2 m): blurred poles over a sharp checker",
            "thin_far",
            2.0,
        ),
        (
            "tabletop",
            "tabletop, focus near (0.95 m)",
            "tabletop_near",
            0.95,
        ),
        (
            "tabletop",
            "tabletop, focus far (2.8 m): blurred mug over a sharp wall",
            "tabletop_far",
            2.8,
        ),
    ];
    for (preset, label, file, focus) in cases {
        let scene = Scene::preset(preset, w, h).expect("preset");
        let pin = render(&scene, &RenderOptions::default());
        let p = lens_params(w, focus, 256);
        let (gt, gt_s) = truth(&scene, &p, rays);
        eprintln!("truth {file}: {gt_s:.1} s");
        let band = edge_band(&pin.depth, 8);
        let (rev, ms_rev) = timed(repeats, || {
            reverse_mapped_dof(&pin.color, &pin.depth, &Aperture::Disc, &p).expect("reverse")
        });
        let ((off, _), ms_off) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &p, |_| Ok(())).expect("refocus")
        });
        let on_p = RefocusParams {
            background_layer: true,
            ..p.clone()
        };
        let ((on, _), ms_on) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &on_p, |_| Ok(())).expect("refocus")
        });
        let tex_p = RefocusParams {
            background_texture: true,
            ..on_p.clone()
        };
        let ((tex, _), ms_tex) = timed(repeats, || {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, &tex_p, |_| Ok(())).expect("refocus")
        });
        for (name, img, ms) in [
            ("reverse-mapped z-buffer DoF", &rev, ms_rev),
            ("Refocus, per-view fill (layer off)", &off, ms_off),
            ("Refocus, background layer", &on, ms_on),
            ("Refocus, background layer + texture", &tex, ms_tex),
        ] {
            writeln!(
                doc,
                "| {label} | {name} | {:.2} | {:.2} | {:.2} | {:.4} | {ms:.0} |",
                display_psnr(img, &gt).unwrap_or(f64::NAN),
                masked_psnr(img, &gt, &band),
                masked_psnr(img, &gt, &inside),
                display_ssim(img, &gt).unwrap_or(f64::NAN),
            )
            .ok();
        }
        if preset == "thin" {
            save_png(&out_dir.join(format!("occlusion_{file}_truth.png")), &gt);
            save_png(&out_dir.join(format!("occlusion_{file}_off.png")), &off);
            save_png(&out_dir.join(format!("occlusion_{file}_layer.png")), &on);
            save_png(&out_dir.join(format!("occlusion_{file}_texture.png")), &tex);
        }
        if std::env::var_os("DEPTHGRAPH_REFOCUS_ONLY").is_some() {
            // Tuning: display error maps, x8.
            let diff = |a: &ColorImage| {
                let (w, h) = a.dims();
                let srgb = |v: f32| {
                    let v = v.clamp(0.0, 1.0);
                    if v <= 0.003_130_8 {
                        12.92 * v
                    } else {
                        1.055 * v.powf(1.0 / 2.4) - 0.055
                    }
                };
                let d: Vec<[f32; 3]> = a
                    .as_slice()
                    .iter()
                    .zip(gt.as_slice())
                    .map(|(x, y)| {
                        let e = (0..3)
                            .map(|c| (srgb(x[c]) - srgb(y[c])).abs())
                            .fold(0.0, f32::max);
                        let e = (8.0 * e).min(1.0);
                        // back to linear so save_png shows e
                        let lin = if e <= 0.04045 {
                            e / 12.92
                        } else {
                            ((e + 0.055) / 1.055).powf(2.4)
                        };
                        [lin; 3]
                    })
                    .collect();
                ColorImage::from_vec(w, h, d).expect("dims")
            };
            save_png(
                &out_dir.join(format!("occlusion_{file}_off_err.png")),
                &diff(&off),
            );
            save_png(
                &out_dir.join(format!("occlusion_{file}_layer_err.png")),
                &diff(&on),
            );
            save_png(
                &out_dir.join(format!("occlusion_{file}_rev_err.png")),
                &diff(&rev),
            );
            save_png(
                &out_dir.join(format!("occlusion_{file}_texture_err.png")),
                &diff(&tex),
            );
        }
    }
    writeln!(
        doc,
        "\nImages: [truth](refocus/occlusion_thin_near_truth.png), [layer off](refocus/occlusion_thin_near_off.png), \
         [background layer](refocus/occlusion_thin_near_layer.png), \
         [with texture](refocus/occlusion_thin_near_texture.png) (thin, focus on the poles); \
         `occlusion_thin_far_*.png` likewise."
    )
    .ok();
}

/// `frame_border` edge (the default) against reflect on the focus settings
/// of the tables above: the whole frame, the band of the frame's outer
/// pixels where a view reads past the border, and the time of each in the
/// same run.
fn frame_border(doc: &mut String, repeats: usize, rays: usize) {
    use depthgraph::nodes::camera::frame_border::FrameBorder;
    let (w, h) = (320, 240);
    writeln!(
        doc,
        "\n## Beyond the frame's border\n\n\
         A lens's rays near the border see the scene continue past the frame; the input stops \
         there. `frame_border = edge` (the default) fills what a view uncovers at the border with \
         the input's own pixel; `reflect` mirrors the colour about the border and continues the depth's \
         planes through it (`Frame::extend_depth`) by the blur's \
         reach, renders the wider frame with the same pixel pitch and crops it. {w}x{h}, 50 mm \
         f/1.4, 256 samples, truth {rays} rays per pixel; the thin scene with the background layer \
         and its texture. \"band\": the outer {FRAME_BORDER_PX} pixels.\n\n\
         | scene, focus | border | PSNR | PSNR in the band | PSNR inside | time (ms) | ratio to edge |\n\
         |---|---|---|---|---|---|---|"
    )
    .ok();
    let inside = interior(w, h, FRAME_BORDER_PX);
    let band: Vec<bool> = inside.iter().map(|i| !i).collect();
    for (preset, label, focus, layer) in FOCUS_CASES {
        let scene = Scene::preset(preset, w, h).expect("preset");
        let pin = render(&scene, &RenderOptions::default());
        let edge = RefocusParams {
            background_layer: layer,
            background_texture: layer,
            ..lens_params(w, focus, 256)
        };
        let reflect = RefocusParams {
            frame_border: FrameBorder::Reflect,
            ..edge.clone()
        };
        let (gt, gt_s) = truth(&scene, &edge, rays);
        eprintln!("truth {label}: {gt_s:.1} s");
        let run = |p: &RefocusParams| {
            refocus(&pin.color, &pin.depth, &Aperture::Disc, p, |_| Ok(())).expect("refocus")
        };
        // interleaved, so machine load falls on both alike
        let (a, _) = run(&edge);
        let ((b, rep), ms_a, ms_b, ratio) = timed_pair(repeats, || run(&edge), || run(&reflect));
        for (name, img, ms, r) in [
            ("edge".to_string(), &a, ms_a, 1.0),
            (
                format!("reflect ({} px)", rep.frame_pad_px),
                &b,
                ms_b,
                ratio,
            ),
        ] {
            writeln!(
                doc,
                "| {label} ({focus} m) | {name} | {:.2} | {:.2} | {:.2} | {ms:.0} | {r:.2} |",
                display_psnr(img, &gt).unwrap_or(f64::NAN),
                masked_psnr(img, &gt, &band),
                masked_psnr(img, &gt, &inside),
            )
            .ok();
        }
    }
    writeln!(
        doc,
        "\nThe extension is a guess about what lies past the border: right where the scene \
         continues smoothly (a wall, a floor), wrong where the border cuts an object, whose mirror \
         image then blurs in, or where a texture's next stripe begins just past it. The background \
         layer's texture is continued from the input's own pixels only (a mirror flips a periodic \
         texture at the border)."
    )
    .ok();
}
