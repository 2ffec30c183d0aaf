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

/// An error naming both sizes when `estimate` and `truth` differ (pixel by
/// pixel they would pair wrongly).
fn same_size(estimate: &DepthMap, truth: &DepthMap) -> Result<(), String> {
    if estimate.dims() == truth.dims() {
        return Ok(());
    }
    let ((a, b), (c, d)) = (estimate.dims(), truth.dims());
    Err(format!(
        "the estimate is {a}x{b} and the truth {c}x{d}: they cannot be compared"
    ))
}

/// Errors over the pixels where `select(i)` holds and the truth is valid.
/// Unfilled estimates are counted in `unfilled` and as bad pixels, and left
/// out of RMSE/MAE. Sums in f64. An estimate of another size than the truth
/// is an error naming both (pixel by pixel they would pair wrongly).
pub fn depth_errors(
    estimate: &DepthMap,
    truth: &DepthMap,
    select: impl Fn(usize) -> bool,
) -> Result<DepthErrors, String> {
    same_size(estimate, truth)?;
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
    Ok(e)
}

/// How much of an estimate's squared error its worst pixels carry: over
/// the filled pixels where `select(i)` holds and the truth is valid (as
/// [`depth_errors`] counts them), the `share` of pixels with the largest
/// errors (at least one where any pixel is measured).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct WorstShare {
    /// Pixels in the worst share.
    pub worst: usize,
    /// Their part of the summed squared error, in `[0, 1]` (0 when the
    /// error is 0 everywhere).
    pub sse_share: f64,
    /// RMSE of the other pixels, metres (0 when none is left).
    pub rmse_rest_m: f64,
}

/// [`WorstShare`] of `estimate` against `truth` over `select` (same sizes,
/// else an error naming both). Sums in f64.
pub fn worst_share(
    estimate: &DepthMap,
    truth: &DepthMap,
    select: impl Fn(usize) -> bool,
    share: f64,
) -> Result<WorstShare, String> {
    same_size(estimate, truth)?;
    let mut sq: Vec<f64> = estimate
        .as_slice()
        .iter()
        .zip(truth.as_slice())
        .enumerate()
        .filter(|(i, (x, t))| DepthMap::is_valid(**t) && DepthMap::is_valid(**x) && select(*i))
        .map(|(_, (x, t))| (f64::from(*x) - f64::from(*t)).powi(2))
        .collect();
    if sq.is_empty() {
        return Ok(WorstShare::default());
    }
    sq.sort_by(|a, b| b.total_cmp(a));
    let n = sq.len();
    let worst = ((share.clamp(0.0, 1.0) * n as f64).ceil() as usize).clamp(1, n);
    let total: f64 = sq.iter().sum();
    let top: f64 = sq[..worst].iter().sum();
    Ok(WorstShare {
        worst,
        // guard: a zero total error has no share to give
        sse_share: if total > 0.0 { top / total } else { 0.0 },
        // guard: no pixel left, no rest
        rmse_rest_m: if worst < n {
            ((total - top).max(0.0) / (n - worst) as f64).sqrt()
        } else {
            0.0
        },
    })
}

/// The relative depth difference within which a neighbour supports a
/// truth pixel ([`truth_spikes`]).
pub const SPIKE_TOLERANCE: f64 = 0.05;

/// Isolated spikes of a ground truth: valid pixels none of whose valid
/// 8-neighbours lies within [`SPIKE_TOLERANCE`] of their depth (true where
/// one is). A plane keeps its depth along a line of the image (its line of
/// equal depth), so however slanted it is, one of the eight neighbours lies
/// near that line and within a few per cent; a one-pixel wire has two along
/// it. A pixel with none
/// is an error of the truth's own measurement: Middlebury's structured-light
/// disparity holds a few (Dolls: one pixel at 2.86 m amid a doll at
/// 1.63 m), and a hole filler cannot be asked to find them. The accuracy
/// bench leaves them out of every method's score alike; a pixel without
/// any valid neighbour (nothing to compare) is no spike.
pub fn truth_spikes(truth: &DepthMap) -> Vec<bool> {
    let (w, h) = truth.dims();
    let t = truth.as_slice();
    (0..w * h)
        .map(|i| {
            let z = t[i];
            if !DepthMap::is_valid(z) {
                return false;
            }
            let (x, y) = (i % w, i / w);
            let (mut neighbours, mut supported) = (0usize, false);
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let zn = t[ny * w + nx];
                    if (nx, ny) == (x, y) || !DepthMap::is_valid(zn) {
                        continue;
                    }
                    neighbours += 1;
                    // guard: z > 0 (valid)
                    supported |=
                        (f64::from(zn) - f64::from(z)).abs() <= SPIKE_TOLERANCE * f64::from(z);
                }
            }
            neighbours > 0 && !supported
        })
        .collect()
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

/// Why a scene of `dir` is left out: its folder is missing, or what its
/// colour or depth file said (a damaged file is not "not found").
fn load_failure(
    dir: &Path,
    color: Option<depthgraph_graph::error::NodeError>,
    depth: Option<depthgraph_graph::error::NodeError>,
) -> String {
    if !dir.exists() {
        return format!("{} (not found)", dir.display());
    }
    let why: Vec<String> = color
        .into_iter()
        .chain(depth)
        .map(|e| e.to_string())
        .collect();
    format!("{} ({})", dir.display(), why.join("; "))
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
            (c, d) => missing.push(load_failure(&dir, c.err(), d.err())),
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
        (c, d) => missing.push(load_failure(&dir, c.err(), d.err())),
    }
    (scenes, missing)
}

/// The TUM RGB-D fr1_xyz frame (its SOURCE.txt: 16-bit depth, 5000 units
/// per metre, registered to the colour by the OpenNI driver; TUM's published
/// fr1 intrinsics). Its "truth" is the measured depth itself, holes and
/// noise included: a filler is scored on holes punched into it
/// ([`punch_holes`]), where the sensor did measure.
pub fn tum_scene(data: &Path) -> Result<TruthScene, String> {
    use depthgraph_nodes::io::{ColorSpace, LoadDepthParams, load_color, load_depth};
    let dir = data.join("tum_rgbd/fr1_xyz");
    let color = load_color(&dir.join("rgb/1305031102.175304.png"), ColorSpace::Srgb)
        .map_err(|e| format!("{} (not read: {e})", dir.display()))?;
    let depth = load_depth(
        &dir.join("depth/1305031102.160407.png"),
        &LoadDepthParams {
            scale: 5000.0,
            ..Default::default()
        },
    )
    .map_err(|e| format!("{} (not read: {e})", dir.display()))?;
    if color.dims() != depth.dims() {
        return Err(format!(
            "{}: colour {:?} and depth {:?} differ in size",
            dir.display(),
            color.dims(),
            depth.dims()
        ));
    }
    let (w, h) = depth.dims();
    Ok(TruthScene {
        name: "TUM fr1_xyz (real Kinect), punched holes".into(),
        color,
        depth,
        intrinsics: Intrinsics {
            fx: 517.3,
            fy: 516.5,
            cx: 318.6,
            cy: 255.3,
            width: w,
            height: h,
        },
    })
}

/// Parameters of [`punch_holes`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PunchParams {
    /// Share of the valid pixels to remove (stops at the first disk that
    /// reaches it).
    pub fraction: f64,
    /// Smallest disk radius, pixels (radii are drawn uniformly in
    /// `min_radius..=max_radius`, each at most the image's larger side).
    pub min_radius: usize,
    /// Largest disk radius, pixels.
    pub max_radius: usize,
    /// Seed of the centres and radii (SplitMix64).
    pub seed: u64,
}

impl Default for PunchParams {
    fn default() -> Self {
        Self {
            fraction: 0.08,
            min_radius: 2,
            max_radius: 10,
            seed: 7,
        }
    }
}

/// Holes punched into a measured depth map: disks of random radius at
/// uniformly random centres (SplitMix64, `seed`), over the whole frame, so
/// they fall on surfaces and across depth edges alike, until `fraction` of
/// the valid pixels is gone. The pixels removed are those valid in `depth`
/// and invalid in the result. Deterministic; a map without valid pixels (or
/// `fraction <= 0`) comes back unchanged; at most `64 * pixels` disks are
/// tried, so a fraction near 1 cannot loop forever.
pub fn punch_holes(depth: &DepthMap, p: &PunchParams) -> DepthMap {
    use depthgraph_nodes::kit::rng::SplitMix64;
    let (w, h) = depth.dims();
    let mut out = depth.clone();
    let valid = depth
        .as_slice()
        .iter()
        .filter(|z| DepthMap::is_valid(**z))
        .count();
    let target = (p.fraction.clamp(0.0, 1.0) * valid as f64).ceil() as usize;
    if target == 0 || w == 0 || h == 0 {
        return out;
    }
    // radii beyond the image's larger side change nothing (and stay far from overflow)
    let side = w.max(h);
    let (r0, r1) = (
        p.min_radius.min(p.max_radius).min(side),
        p.max_radius.max(p.min_radius).min(side),
    );
    let mut rng = SplitMix64(p.seed);
    let mut removed = 0usize;
    let mut tries = 0usize;
    while removed < target && tries < 64 * w * h {
        tries += 1;
        let cx = rng.below(w) as isize;
        let cy = rng.below(h) as isize;
        let r = (r0 + rng.below(r1 - r0 + 1)) as isize;
        for y in (cy - r).max(0)..=(cy + r).min(h as isize - 1) {
            for x in (cx - r).max(0)..=(cx + r).min(w as isize - 1) {
                if (x - cx).pow(2) + (y - cy).pow(2) > r * r {
                    continue;
                }
                let i = y as usize * w + x as usize;
                let z = &mut out.as_mut_slice()[i];
                if DepthMap::is_valid(*z) {
                    *z = 0.0;
                    removed += 1;
                }
            }
        }
    }
    out
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
    fn a_truth_spike_is_a_pixel_no_neighbour_supports() {
        // a plane sloping along x, a one-pixel spike, a one-pixel-wide
        // wire (column 5, rows 0..5) nearer than the plane, a hole
        let (w, h) = (8, 5);
        let mut d: Vec<f32> = (0..w * h).map(|i| 1.0 + 0.02 * (i % w) as f32).collect();
        d[2 * w + 2] = 2.9;
        for y in 0..h {
            d[y * w + 5] = 0.6;
        }
        d[w + 7] = 0.0;
        let truth = Image::from_vec(w, h, d).unwrap();
        let spikes = truth_spikes(&truth);
        let found: Vec<usize> = (0..w * h).filter(|&i| spikes[i]).collect();
        assert_eq!(found, vec![2 * w + 2], "only the spike");
        // a lone valid pixel has nothing to compare: no spike
        let lone = Image::from_vec(3, 1, vec![0.0f32, 1.0, 0.0]).unwrap();
        assert_eq!(truth_spikes(&lone), vec![false; 3]);
    }

    #[test]
    fn the_worst_share_is_the_largest_errors_part() {
        // errors 0.3, 0.1, 0.1, 0.1 and an unfilled pixel and a hole in the truth
        let truth = Image::from_vec(6, 1, vec![1.0f32, 1.0, 1.0, 1.0, 1.0, 0.0]).unwrap();
        let est = Image::from_vec(6, 1, vec![1.3f32, 1.1, 0.9, 1.1, 0.0, 2.0]).unwrap();
        let w = worst_share(&est, &truth, |_| true, 0.25).unwrap();
        assert_eq!(w.worst, 1);
        assert!((w.sse_share - 0.09 / 0.12).abs() < 1e-6, "{w:?}");
        assert!((w.rmse_rest_m - 0.1).abs() < 1e-6, "{w:?}");
        // at least one pixel; none selected gives zeros; sizes must match
        assert_eq!(worst_share(&est, &truth, |_| true, 0.0).unwrap().worst, 1);
        assert_eq!(
            worst_share(&est, &truth, |_| false, 0.5).unwrap(),
            WorstShare::default()
        );
        let all = worst_share(&est, &truth, |_| true, 1.0).unwrap();
        assert_eq!((all.worst, all.rmse_rest_m), (4, 0.0));
        let small = Image::from_vec(1, 1, vec![1.0f32]).unwrap();
        assert!(worst_share(&small, &truth, |_| true, 0.5).is_err());
    }

    #[test]
    fn errors_on_known_values() {
        let truth = Image::from_vec(5, 1, vec![1.0f32, 2.0, 2.0, 0.0, 4.0]).unwrap();
        let est = Image::from_vec(5, 1, vec![1.0f32, 2.1, 0.0, 5.0, 4.02]).unwrap();
        let e = depth_errors(&est, &truth, |_| true).unwrap();
        assert_eq!((e.count, e.unfilled), (3, 1));
        assert!(
            (e.rmse_m - ((0.01f64 + 0.0004) / 3.0).sqrt()).abs() < 1e-6,
            "{e:?}"
        );
        assert!((e.mae_m - 0.12 / 3.0).abs() < 1e-6);
        // bad: 2.1 vs 2 (5%), the unfilled pixel; 4.02 vs 4 is 0.5%: good
        assert!((e.bad_rate - 0.5).abs() < 1e-12);
        let none = depth_errors(&est, &truth, |_| false).unwrap();
        // another size is an error naming both
        let small = DepthMap::filled(1, 1, 1.0);
        let e = depth_errors(&small, &truth, |_| true).unwrap_err();
        assert!(e.contains("1x1"), "{e}");
        assert_eq!(none.count, 0);
        assert_eq!(none.rmse_m, 0.0);
    }

    #[test]
    fn synthetic_truth_is_hole_free_on_tabletop() {
        let s = synthetic_scene("tabletop", 64, 48).unwrap();
        assert_eq!(s.depth.hole_count(), 0);
        assert!(synthetic_scene("nope", 8, 8).is_none());
    }

    /// Punching removes at least the asked share of the valid pixels and at
    /// most one disk more, touches only valid pixels (original holes stay,
    /// kept pixels keep their value), and is the same for the same seed.
    #[test]
    fn punched_holes_remove_the_asked_share_and_nothing_else() {
        let (w, h) = (120usize, 90usize);
        // a ramp with a band of original holes
        let z: Vec<f32> = (0..w * h)
            .map(|i| {
                if (i / w) % 30 < 3 {
                    0.0
                } else {
                    1.0 + (i % w) as f32 * 0.01
                }
            })
            .collect();
        let d = Image::from_vec(w, h, z).unwrap();
        let valid = w * h - d.hole_count();
        let p = PunchParams {
            fraction: 0.1,
            ..Default::default()
        };
        let out = punch_holes(&d, &p);
        let removed = out.hole_count() - d.hole_count();
        let disk = (2 * p.max_radius + 1).pow(2);
        assert!(removed as f64 >= 0.1 * valid as f64, "{removed} of {valid}");
        assert!(
            (removed as f64) < 0.1 * valid as f64 + disk as f64,
            "{removed}"
        );
        for (a, b) in d.as_slice().iter().zip(out.as_slice()) {
            assert!(*b == *a || (*b == 0.0 && DepthMap::is_valid(*a)));
        }
        assert_eq!(punch_holes(&d, &p).as_slice(), out.as_slice());
        let other = punch_holes(&d, &PunchParams { seed: 8, ..p });
        assert_ne!(other.as_slice(), out.as_slice());
        // nothing valid: unchanged
        let empty = Image::from_vec(4, 4, vec![0.0f32; 16]).unwrap();
        assert_eq!(punch_holes(&empty, &p).as_slice(), empty.as_slice());
    }
}
