//! Speed of 3D copy and paste (3d-editing §III.C, §IV) at 640x480:
//! `cargo bench --bench copy_paste` regenerates `docs/copy-paste.md`
//! (the timing table; the real-data section of that file is kept as is,
//! everything from the line `<!-- real-data -->` on).
//!
//! Source: the synthetic tabletop; the checkered sphere is selected with 10
//! stored clicks (those of `graphs/copy_paste.ron`, doubled for 640x480).
//! Target: the synthetic corridor. Stages, each timed as the median of
//! `DEPTHGRAPH_REPEATS` (default 5) runs on the previous stage's output:
//! EdgeDetect, Lasso (snap + live wire + fill), Paste, Feather,
//! OcclusionComposite; the total is the sum of the medians.
//!
//! Peers in the same run: a straight-line polygon through the same clicks
//! (no snapping, no live wire: what the lasso costs and what it buys, IoU
//! against the exact object ids), and OpenCV through
//! `benches/peers/opencv_select.py` (3x3 Sobel on the color, Canny,
//! seamlessClone) on the same 8-bit image; `DEPTHGRAPH_PEERS=0` skips it.

mod common;
use common::timed;

use std::fmt::Write as _;
use std::path::Path;

use depthgraph::graph::prelude::*;
use depthgraph::nodes::kit::color::srgb8;
use depthgraph::nodes::select::composite::{CompositeParams, occlusion_composite};
use depthgraph::nodes::select::edges::{EdgeParams, detect_edges};
use depthgraph::nodes::select::feather::{FeatherParams, feather};
use depthgraph::nodes::select::lasso::{LassoParams, fill_polygon, iou, lasso};
use depthgraph::nodes::select::paste::{PasteParams, paste};
use depthgraph::nodes::sim::synthetic::{RenderOptions, Scene, render};

const MARK: &str = "<!-- real-data -->";

/// Runs the OpenCV peer on `color`; (note, sobel ms, canny ms, seamlessClone ms).
fn opencv_peer(color: &ColorImage) -> (String, Option<[f64; 3]>) {
    if std::env::var("DEPTHGRAPH_PEERS").is_ok_and(|v| v == "0") {
        return ("OpenCV peer skipped (DEPTHGRAPH_PEERS=0)".into(), None);
    }
    let Ok(dir) = tempfile::tempdir() else {
        return ("OpenCV peer did not run (no temporary folder)".into(), None);
    };
    let (w, h) = color.dims();
    let rgb: Vec<u8> = color.as_slice().iter().flat_map(|c| c.map(srgb8)).collect();
    let written = std::fs::write(dir.path().join("color.u8"), rgb).and_then(|_| {
        std::fs::write(
            dir.path().join("meta.json"),
            format!("{{\"width\": {w}, \"height\": {h}}}"),
        )
    });
    if written.is_err() {
        return (
            "OpenCV peer did not run (could not write its input)".into(),
            None,
        );
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peers/opencv_select.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(dir.path())
        .output();
    let Ok(out) = out else {
        return ("OpenCV peer did not run (python3 unavailable)".into(), None);
    };
    let text = String::from_utf8_lossy(&out.stdout);
    let json = text
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str::<serde_json::Value>(l).ok());
    match json {
        Some(j) if out.status.success() => {
            let g = |k: &str| j[k].as_f64().unwrap_or(f64::NAN);
            (
                format!("OpenCV {}", j["opencv"].as_str().unwrap_or("?")),
                Some([g("sobel"), g("canny"), g("seamless_clone")]),
            )
        }
        _ => (
            format!(
                "OpenCV peer failed: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ),
            None,
        ),
    }
}

fn main() {
    let repeats = std::env::var("DEPTHGRAPH_REPEATS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5usize);
    let (w, h) = (640, 480);
    let src_scene = Scene::preset("tabletop", w, h).expect("preset tabletop");
    let tgt_scene = Scene::preset("corridor", w, h).expect("preset corridor");
    let src = render(&src_scene, &RenderOptions::default());
    let tgt = render(&tgt_scene, &RenderOptions::default());
    // graphs/copy_paste.ron's clicks around the checkered sphere, at 640x480
    let clicks: Vec<[f64; 2]> = [
        (254.5, 176.2),
        (237.3, 192.2),
        (217.1, 205.1),
        (197.1, 192.0),
        (179.9, 176.9),
        (185.3, 154.8),
        (192.8, 132.6),
        (216.0, 126.7),
        (236.5, 136.1),
        (255.1, 151.3),
    ]
    .iter()
    .map(|&(x, y)| [x * 2.0, y * 2.0])
    .collect();
    let gt = src.ids.map(|v| if *v == 4 { 1.0f32 } else { 0.0 });

    let ep = EdgeParams::default();
    let (edges, t_edges) = timed(repeats, || {
        detect_edges(&src.color, &src.depth, &ep).expect("edges")
    });
    let lp = LassoParams {
        clicks: clicks.clone(),
        ..Default::default()
    };
    let (sel, t_lasso) = timed(repeats, || lasso(&edges.strength, &lp).expect("lasso"));
    let pp = PasteParams {
        target_pixel: vec![[w as f64 * 0.5, h as f64 * 0.7]],
        depth_offset_m: -0.5,
        ..Default::default()
    };
    let (pasted, t_paste) = timed(repeats, || {
        paste(
            &src.color,
            &src.depth,
            &sel.mask,
            &src.intrinsics,
            &tgt.depth,
            &tgt.intrinsics,
            &pp,
        )
        .expect("paste")
    });
    let fp = FeatherParams {
        sigma_px: 3.0,
        ..Default::default()
    };
    let ((alpha, _), t_feather) = timed(repeats, || feather(&pasted.alpha, &fp).expect("feather"));
    let cp = CompositeParams::default();
    let (comp, t_comp) = timed(repeats, || {
        occlusion_composite(
            &tgt.color,
            &tgt.depth,
            &pasted.color,
            &pasted.depth,
            &alpha,
            &cp,
        )
        .expect("composite")
    });
    let total = t_edges + t_lasso + t_paste + t_feather + t_comp;
    let seen = comp.alpha.as_slice().iter().filter(|a| **a > 0.0).count();
    let lasso_iou = iou(&sel.mask, &gt);

    // Peer 1: the straight-line polygon through the raw clicks.
    let raw: Vec<[usize; 2]> = clicks
        .iter()
        .map(|c| [c[0].max(0.0) as usize, c[1].max(0.0) as usize])
        .collect();
    let (poly, t_poly) = timed(repeats, || fill_polygon(w, h, &raw));
    let poly_iou = iou(&poly, &gt);
    // Peer 2: OpenCV on the same color.
    let (cv_note, cv) = opencv_peer(&src.color);

    let threads = rayon::current_num_threads();
    let mut doc = String::new();
    writeln!(
        doc,
        "# 3D copy and paste: speed and real data\n\n\
         ## Speed (synthetic, {w}x{h})\n\n\
         Generated by `cargo bench --bench copy_paste` \
         (release, {threads} rayon threads, median of {repeats} runs per stage). Source: SyntheticScene \
         `tabletop`, the checkered sphere selected with the 10 clicks of `graphs/copy_paste.ron` (doubled \
         for 640x480); target: SyntheticScene `corridor`, the sphere placed on the ray of pixel \
         ({:.0}, {:.0}), 0.5 m in front of the surface, auto-scaled (scale {:.3}); Feather sigma 3 px \
         \"inside\"; OcclusionComposite with the strict depth test. Lasso IoU against the exact object \
         ids: {lasso_iou:.4}; pasted pixels visible in the composite: {seen}.\n\n\
         | stage | time (ms) |\n|---|---|\n\
         | EdgeDetect (color + depth) | {t_edges:.2} |\n\
         | Lasso (10 clicks: snap, live wire, fill) | {t_lasso:.2} |\n\
         | Paste (object, suggested scale, mesh warp) | {t_paste:.2} |\n\
         | Feather | {t_feather:.2} |\n\
         | OcclusionComposite | {t_comp:.2} |\n\
         | **total** | **{total:.2}** (target < 50) |\n",
        pp.target_pixel[0][0],
        pp.target_pixel[0][1],
        pasted.scale,
    )
    .ok();
    writeln!(
        doc,
        "### Peers, same run\n\n\
         | peer | time (ms) | ours (ms) | ratio ours / peer | note |\n|---|---|---|---|---|\n\
         | straight polygon through the same 10 clicks (fill only) | {t_poly:.2} | {t_lasso:.2} | {:.1} | \
         IoU {poly_iou:.4} vs the lasso's {lasso_iou:.4} |",
        t_lasso / t_poly.max(1e-9) // guard: a zero time would divide by 0
    )
    .ok();
    match cv {
        Some([sobel, canny, clone]) => {
            writeln!(
                doc,
                "| {cv_note} `cv2.Sobel` x, y on 3 float channels + magnitude | {sobel:.2} | {t_edges:.2} | {:.1} | \
                 ours also has the depth term |\n\
                 | {cv_note} `cv2.Canny` on grey | {canny:.2} | {t_edges:.2} | {:.1} | color only, thinned binary edges |\n\
                 | {cv_note} `cv2.seamlessClone` (NORMAL_CLONE, one ellipse) | {clone:.2} | {:.2} | {:.1} | \
                 2D paste + Poisson blend vs our Paste + Feather + OcclusionComposite |",
                t_edges / sobel.max(1e-9), // guard: as above
                t_edges / canny.max(1e-9),
                t_paste + t_feather + t_comp,
                (t_paste + t_feather + t_comp) / clone.max(1e-9),
            )
            .ok();
        }
        None => {
            writeln!(doc, "\n{cv_note}.").ok();
        }
    }
    writeln!(doc).ok();
    eprintln!("{doc}");

    // Keep the hand-written real-data section.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/copy-paste.md");
    let tail = std::fs::read_to_string(&path)
        .ok()
        .and_then(|old| old.find(MARK).map(|i| old[i..].to_string()))
        .unwrap_or_else(|| format!("{MARK}\n"));
    doc.push_str(&tail);
    if let Err(e) = std::fs::write(&path, doc) {
        eprintln!("could not write {}: {e}", path.display());
    }
    let data = depthgraph::evaluation::shared_data_dir();
    if !data.join("tum_rgbd/fr1_xyz").is_dir() {
        eprintln!(
            "note: {} has no tum_rgbd/fr1_xyz; the real-data runs in docs/copy-paste.md cannot be repeated here",
            data.display()
        );
    }
}
