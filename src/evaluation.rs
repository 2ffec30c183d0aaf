//! Accuracy measures for depth completion against ground truth, and the
//! scenes they are measured on (synthetic presets and, when present, the
//! Middlebury captures in `../shared/data`).

use std::path::{Path, PathBuf};

use depthgraph_graph::prelude::*;
use serde::Serialize;

/// Errors of a depth estimate against the truth over a set of pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct DepthErrors {
    /// Root mean square error, metres.
    pub rmse_m: f64,
    /// Mean absolute error, metres.
    pub mae_m: f64,
    /// Share of pixels whose error exceeds 1% of the true depth.
    pub bad_rate: f64,
    /// Pixels measured.
    pub count: usize,
    /// Pixels of the set that the estimate left without a value.
    pub unfilled: usize,
}

/// Errors over the pixels where `select(i)` holds and the truth is valid.
/// Unfilled estimates are counted in `unfilled` and as bad pixels, and left
/// out of RMSE/MAE. Sums in f64.
pub fn depth_errors(
    estimate: &DepthMap,
    truth: &DepthMap,
    select: impl Fn(usize) -> bool,
) -> DepthErrors {
    let mut e = DepthErrors::default();
    let (mut sq, mut abs, mut bad) = (0.0f64, 0.0f64, 0usize);
    for (i, (x, t)) in estimate.as_slice().iter().zip(truth.as_slice()).enumerate() {
        if !DepthMap::is_valid(*t) || !select(i) {
            continue;
        }
        if !DepthMap::is_valid(*x) {
            e.unfilled += 1;
            bad += 1;
            continue;
        }
        let d = (*x as f64 - *t as f64).abs();
        sq += d * d;
        abs += d;
        if d > 0.01 * *t as f64 {
            bad += 1;
        }
        e.count += 1;
    }
    // guard: empty sets report zeros with count 0
    if e.count > 0 {
        e.rmse_m = (sq / e.count as f64).sqrt();
        e.mae_m = abs / e.count as f64;
    }
    let all = e.count + e.unfilled;
    if all > 0 {
        e.bad_rate = bad as f64 / all as f64;
    }
    e
}

/// A depth scene with ground truth.
#[derive(Debug, Clone)]
pub struct TruthScene {
    pub name: String,
    pub color: ColorImage,
    pub depth: DepthMap,
    pub intrinsics: Intrinsics,
}

/// The shared data folder: `$DEPTHGRAPH_DATA`, else `../shared/data` beside the workspace.
pub fn shared_data_dir() -> PathBuf {
    std::env::var_os("DEPTHGRAPH_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"))
}

/// How Middlebury 2005 stores disparity (its SOURCE.txt): 8-bit values of the
/// full-size disparity, `Z[m] = 0.160 * 3740 / (value + 200)`. Also what
/// the full-size Park 2011 benchmark (made from the same scenes) uses.
pub fn middlebury2005_disparity() -> depthgraph_nodes::io::LoadDepthParams {
    depthgraph_nodes::io::LoadDepthParams {
        encoding: depthgraph_nodes::io::DepthEncoding::Disparity,
        scale: 1.0,
        focal_px: 3740.0,
        baseline_m: 0.160,
        doffs_px: 200.0,
        ..Default::default()
    }
}

/// The camera of a full-size Park 2011 scene (made from Middlebury 2005):
/// f = 3740 px, the principal point at the image centre.
pub fn park2011_intrinsics(width: usize, height: usize) -> Intrinsics {
    Intrinsics {
        fx: 3740.0,
        fy: 3740.0,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        width,
        height,
    }
}

/// Middlebury scenes with ground-truth disparity converted to metres with the
/// calibration given in each SOURCE.txt. Returns the scenes found and a note
/// for each one that is missing.
pub fn middlebury_scenes(data: &Path) -> (Vec<TruthScene>, Vec<String>) {
    use depthgraph_nodes::io::{LoadDepthParams, load_color, load_depth};
    let mut scenes = Vec::new();
    let mut missing = Vec::new();
    // 2005 third-size: Z[m] = 0.160 * 3740 / (value + 200), value = full-size disparity.
    for name in ["Art", "Books", "Dolls", "Moebius"] {
        let dir = data.join("middlebury2005_thirdsize").join(name);
        let p = middlebury2005_disparity();
        match (
            load_color(
                &dir.join("view1.png"),
                depthgraph_nodes::io::ColorSpace::Srgb,
            ),
            load_depth(&dir.join("disp1.png"), &p),
        ) {
            (Ok(color), Ok(depth)) => {
                let (w, h) = depth.dims();
                let intrinsics = Intrinsics {
                    fx: 3740.0 / 3.0,
                    fy: 3740.0 / 3.0,
                    cx: w as f64 / 2.0,
                    cy: h as f64 / 2.0,
                    width: w,
                    height: h,
                };
                scenes.push(TruthScene {
                    name: format!("Middlebury 2005 {name}"),
                    color,
                    depth,
                    intrinsics,
                });
            }
            _ => missing.push(format!("{} (not found)", dir.display())),
        }
    }
    // MiddEval3 ArtL half size: Z[m] = 0.160 * 1870 / (d + 100), PFM, +inf = unknown.
    let dir = data.join("middeval3_half").join("ArtL");
    let p = LoadDepthParams {
        encoding: depthgraph_nodes::io::DepthEncoding::Disparity,
        scale: 1.0,
        focal_px: 1870.0,
        baseline_m: 0.160,
        doffs_px: 100.0,
        ..Default::default()
    };
    match (
        load_color(&dir.join("im0.png"), depthgraph_nodes::io::ColorSpace::Srgb),
        load_depth(&dir.join("disp0GT.pfm"), &p),
    ) {
        (Ok(color), Ok(depth)) => {
            let (w, h) = depth.dims();
            let intrinsics = Intrinsics {
                fx: 1870.0,
                fy: 1870.0,
                cx: 297.0,
                cy: 277.0,
                width: w,
                height: h,
            };
            scenes.push(TruthScene {
                name: "MiddEval3 ArtL (half)".into(),
                color,
                depth,
                intrinsics,
            });
        }
        _ => missing.push(format!("{} (not found)", dir.display())),
    }
    (scenes, missing)
}

/// A synthetic preset rendered with exact ground truth.
pub fn synthetic_scene(preset: &str, width: usize, height: usize) -> Option<TruthScene> {
    use depthgraph_nodes::sim::synthetic::{RenderOptions, Scene, render};
    let scene = Scene::preset(preset, width, height)?;
    let r = render(&scene, &RenderOptions { supersample: 1 });
    Some(TruthScene {
        name: format!("synthetic {preset}"),
        color: r.color,
        depth: r.depth,
        intrinsics: r.intrinsics,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_on_known_values() {
        let truth = Image::from_vec(5, 1, vec![1.0f32, 2.0, 2.0, 0.0, 4.0]).unwrap();
        let est = Image::from_vec(5, 1, vec![1.0f32, 2.1, 0.0, 5.0, 4.02]).unwrap();
        let e = depth_errors(&est, &truth, |_| true);
        assert_eq!((e.count, e.unfilled), (3, 1));
        assert!(
            (e.rmse_m - ((0.01f64 + 0.0004) / 3.0).sqrt()).abs() < 1e-6,
            "{e:?}"
        );
        assert!((e.mae_m - 0.12 / 3.0).abs() < 1e-6);
        // bad: 2.1 vs 2 (5%), the unfilled pixel; 4.02 vs 4 is 0.5%: good
        assert!((e.bad_rate - 0.5).abs() < 1e-12);
        let none = depth_errors(&est, &truth, |_| false);
        assert_eq!(none.count, 0);
        assert_eq!(none.rmse_m, 0.0);
    }

    #[test]
    fn synthetic_truth_is_hole_free_on_tabletop() {
        let s = synthetic_scene("tabletop", 64, 48).unwrap();
        assert_eq!(s.depth.hole_count(), 0);
        assert!(synthetic_scene("nope", 8, 8).is_none());
    }
}
