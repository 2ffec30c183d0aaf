//! HDR merge accuracy and time (Debevec & Malik 1997):
//! `cargo bench --bench hdr_memorial` regenerates `docs/hdr.md`.
//!
//! 1. **Memorial church**: the 16 exposures of Debevec's own series
//!    (`../shared/data/hdr_debevec_memorial/memorial/`, pure-blue borders
//!    masked) are merged with a recovered response and compared with
//!    Debevec's `memorial.hdr` by the RMS of `ln(ours) - ln(ref)` after
//!    removing the mean offset (one per channel: a recovered response fixes
//!    radiance only up to one factor per channel; the one-factor variant is
//!    shown too). `memorial.hdr` is Debevec's result, not ground truth.
//! 2. **3 exposures at 640x480**: the synthetic tabletop through
//!    `SimulateBracket` (stops -2, 0, +2, gamma 2.2): time of the merge and of
//!    the recovery, and the same log error against the exact radiance.
//!
//! OpenCV's `CalibrateDebevec` + `MergeDebevec` run on the same images in the
//! same run through `benches/peers/opencv_hdr.py` (set `DEPTHGRAPH_PEERS=0`
//! to skip; `DEPTHGRAPH_PEER_DIR` keeps the exchanged files).
//!
//! 3. **Few exposures**: subsets of the memorial series (2, 3 and 5
//!    exposures) against all 16, each method against its own 16-exposure
//!    result, in stops.
//!
//! `memorial.hdr` starts with a `VIEW=` line before `#?RADIANCE`, which the
//! `image` crate's RGBE decoder (0.25) refuses; it is read with `LoadColor`'s
//! own Radiance reader.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthgraph::evaluation::shared_data_dir;
use depthgraph::graph::prelude::*;
use depthgraph::nodes::camera::hdr::{
    LoadBracketParams, Merged, PolynomialParams, ResponseCurve, ResponseParams, load_bracket,
    mean_stops_apart, merge_hdr, recover_polynomial, recover_response, seen_well,
};
use depthgraph::nodes::sim::sensor::{BracketParams, simulate_bracket};
use depthgraph::nodes::sim::synthetic::{RenderOptions, Scene, render};

/// Median wall time in ms of `repeats` calls, and the last result.
fn median_ms<T>(repeats: usize, mut f: impl FnMut() -> T) -> (Option<T>, f64) {
    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        out = Some(f());
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    (out, times[times.len() / 2])
}

// ------------------------------------------------------------------ RGBE

/// Reads a Radiance RGBE file with the library's reader (`LoadColor`'s).
fn read_rgbe(path: &Path) -> Result<ColorImage, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let r = depthgraph::nodes::io::radiance::decode_rgbe(
        &bytes,
        path,
        &depthgraph::nodes::io::Limits::default(),
    )
    .map_err(|e| e.to_string())?;
    Ok(r.image)
}

// ------------------------------------------------------------------ metric

/// Log-radiance error after removing the mean offset.
#[derive(Debug, Clone, Copy)]
struct LogError {
    /// RMS of `ln(a) - ln(b) - offset_c`, one offset per channel.
    rms_channel: f64,
    /// RMS with one offset for all channels.
    rms_global: f64,
    /// Fraction of pixel-channels within 10 % after the per-channel offsets.
    within_10: f64,
    /// Least-squares slope of `ln(a)` on `ln(b)` (channels centred and pooled):
    /// 1 when the two agree up to a factor; below 1 when `a` spans a smaller
    /// range of radiance than `b`.
    slope: f64,
    pixels: usize,
}

fn positive(px: &[f32; 3]) -> bool {
    px.iter().all(|v| v.is_finite() && *v > 0.0)
}

fn log_error(a: &ColorImage, b: &ColorImage, mask: &[bool]) -> Option<LogError> {
    if !a.same_dims(b) || mask.len() != a.len() {
        return None;
    }
    let mut sum = [0.0f64; 3];
    let mut sq = [0.0f64; 3];
    let mut n = 0usize;
    let logs: Vec<([f64; 3], [f64; 3])> = a
        .as_slice()
        .iter()
        .zip(b.as_slice())
        .zip(mask)
        .filter(|((p, q), m)| **m && positive(p) && positive(q))
        .map(|((p, q), _)| (p.map(|v| (v as f64).ln()), q.map(|v| (v as f64).ln())))
        .collect();
    let diffs: Vec<[f64; 3]> = logs
        .iter()
        .map(|(la, lb)| [0, 1, 2].map(|c| la[c] - lb[c]))
        .collect();
    for d in &diffs {
        for c in 0..3 {
            sum[c] += d[c];
            sq[c] += d[c] * d[c];
        }
        n += 1;
    }
    if n == 0 {
        return None;
    }
    let nf = n as f64; // guard: n > 0
    let mean = sum.map(|s| s / nf);
    let var_c: f64 = (0..3).map(|c| sq[c] / nf - mean[c] * mean[c]).sum::<f64>() / 3.0;
    let g = mean.iter().sum::<f64>() / 3.0;
    let var_g: f64 = (0..3).map(|c| sq[c] / nf).sum::<f64>() / 3.0 - g * g;
    let tol = 1.1f64.ln();
    let within = diffs
        .iter()
        .flat_map(|d| (0..3).map(move |c| (d[c] - mean[c]).abs() < tol))
        .filter(|ok| *ok)
        .count() as f64
        / (3.0 * nf);
    // slope of ln a on ln b, per-channel means removed
    let mean_a: [f64; 3] = [0, 1, 2].map(|c| logs.iter().map(|l| l.0[c]).sum::<f64>() / nf);
    let mean_b: [f64; 3] = [0, 1, 2].map(|c| logs.iter().map(|l| l.1[c]).sum::<f64>() / nf);
    let (mut sab, mut sbb) = (0.0f64, 0.0f64);
    for (la, lb) in &logs {
        for c in 0..3 {
            sab += (la[c] - mean_a[c]) * (lb[c] - mean_b[c]);
            sbb += (lb[c] - mean_b[c]).powi(2);
        }
    }
    // guard: a constant reference has no slope
    let slope = if sbb > 0.0 { sab / sbb } else { f64::NAN };
    Some(LogError {
        slope,
        rms_channel: var_c.max(0.0).sqrt(),
        rms_global: var_g.max(0.0).sqrt(),
        within_10: within,
        pixels: n,
    })
}

// ------------------------------------------------------------------ peers

fn peer_dir() -> (Option<PathBuf>, Option<tempfile::TempDir>) {
    let kept = std::env::var_os("DEPTHGRAPH_PEER_DIR").map(PathBuf::from);
    let temp = tempfile::tempdir().ok();
    let dir = match (&kept, &temp) {
        (Some(k), _) => std::fs::create_dir_all(k).ok().map(|_| k.clone()),
        (None, Some(t)) => Some(t.path().to_path_buf()),
        _ => None,
    };
    (dir, temp)
}

fn read_rgb_f32(path: &Path, w: usize, h: usize) -> Option<ColorImage> {
    let b = std::fs::read(path).ok()?;
    let v: Vec<f32> = b
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let px: Vec<[f32; 3]> = v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Image::from_vec(w, h, px).ok()
}

/// Runs the peer script on `case` in `dir`; `Err` says why it did not run.
/// One peer's name, calibration ms, merge ms and output.
type PeerResult = (String, f64, f64, Option<ColorImage>);

/// Runs the OpenCV peers on `case` (inputs already written under `pd`) and
/// reads back their times and outputs; the note names OpenCV's version or
/// why the peers did not run.
fn run_and_read_peers(
    pd: &Path,
    case: &str,
    w: usize,
    h: usize,
) -> (Option<String>, Vec<PeerResult>) {
    let mut out = Vec::new();
    let note = match run_peers(pd, case) {
        Ok(()) => peer_json(pd, case).and_then(|j| {
            for (key, label) in PEER_METHODS {
                out.push((
                    label.to_string(),
                    j["ms"][format!("{key}_calibrate")]
                        .as_f64()
                        .unwrap_or(f64::NAN),
                    j["ms"][format!("{key}_merge")].as_f64().unwrap_or(f64::NAN),
                    read_rgb_f32(&pd.join(format!("{case}.{key}.f32")), w, h),
                ));
            }
            j["opencv"].as_str().map(|v| format!("OpenCV {v}"))
        }),
        Err(e) => Some(format!("OpenCV peers did not run: {e}")),
    };
    (note, out)
}

fn run_peers(dir: &Path, case: &str) -> Result<(), String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peers/opencv_hdr.py");
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(dir)
        .arg(case)
        .status()
    {
        Ok(st) if st.success() => Ok(()),
        Ok(st) => Err(format!("the OpenCV peer failed ({st})")),
        Err(e) => Err(format!("python3 unavailable ({e})")),
    }
}

/// The peer's timings and version for `case`.
fn peer_json(dir: &Path, case: &str) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(dir.join(format!("{case}.peers.json"))).ok()?;
    serde_json::from_str(&text).ok()
}

/// OpenCV variants the peer runs: key, label.
const PEER_METHODS: [(&str, &str); 2] = [
    (
        "opencv_default",
        "OpenCV CalibrateDebevec (default: 70 samples, lambda 10) + MergeDebevec",
    ),
    (
        "opencv_400",
        "OpenCV CalibrateDebevec (400 samples, lambda 31.6 = sqrt 1000) + MergeDebevec",
    ),
];

/// The part of a peer label before " + MergeDebevec".
fn calibration_of(label: &str) -> &str {
    label.split(" + ").next().unwrap_or(label)
}

struct Row {
    method: String,
    response_ms: f64,
    merge_ms: f64,
    err: Option<LogError>,
    /// The same error over the brightest 80 % of the compared pixels.
    err_bright: Option<LogError>,
    /// The same error over the darkest 20 %.
    err_dark: Option<LogError>,
}

/// `mask` without its darkest 20 % (by the reference's green channel).
fn brightest_80(reference: &ColorImage, mask: &[bool]) -> Vec<bool> {
    let mut g: Vec<f32> = reference
        .as_slice()
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(p, _)| p[1])
        .collect();
    if g.is_empty() {
        return mask.to_vec();
    }
    let k = g.len() / 5;
    let thr = *g.select_nth_unstable_by(k, f32::total_cmp).1;
    reference
        .as_slice()
        .iter()
        .zip(mask)
        .map(|(p, m)| *m && p[1] >= thr)
        .collect()
}

fn table(rows: &[Row], what: &str) -> String {
    let mut s = String::from(
        "| method | response ms | merge ms | total ms | RMS ln error, per-channel factor | RMS ln error, one factor | within 10 % | slope of ln on ln ref | RMS ln error, brightest 80 % | RMS ln error, darkest 20 % | pixels |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in rows {
        let (a, b, c, sl, n) = match r.err {
            Some(e) => (
                format!("{:.4}", e.rms_channel),
                format!("{:.4}", e.rms_global),
                format!("{:.1} %", 100.0 * e.within_10),
                format!("{:.3}", e.slope),
                e.pixels.to_string(),
            ),
            None => ("-".into(), "-".into(), "-".into(), "-".into(), "-".into()),
        };
        let _ = writeln!(
            s,
            "| {} | {:.1} | {:.1} | {:.1} | {a} | {b} | {c} | {sl} | {} | {} | {n} |",
            r.method,
            r.response_ms,
            r.merge_ms,
            r.response_ms + r.merge_ms,
            r.err_bright
                .map(|e| format!("{:.4}", e.rms_channel))
                .unwrap_or_else(|| "-".into()),
            r.err_dark
                .map(|e| format!("{:.4}", e.rms_channel))
                .unwrap_or_else(|| "-".into())
        );
    }
    let _ = writeln!(s, "\nErrors against {what}.");
    s
}

// ------------------------------------------------------------------ cases

fn memorial(data: &Path, peers: Option<&Path>, repeats: usize) -> (String, Option<String>) {
    let dir = data.join("hdr_debevec_memorial").join("memorial");
    let list = dir.join("image_list.txt");
    let mut s =
        String::from("## Memorial church, 16 exposures, 512x768 (Debevec & Malik 1997)\n\n");
    if !list.exists() {
        eprintln!(
            "{} is missing: the memorial comparison is skipped",
            list.display()
        );
        let _ = writeln!(s, "`{}` is missing: no rows.\n", list.display());
        return (s, None);
    }
    let load = |mask: bool| {
        load_bracket(&LoadBracketParams {
            list: list.display().to_string(),
            mask_pure_blue: mask,
            ..Default::default()
        })
    };
    let (stack, load_ms) = median_ms(repeats, || load(true));
    let stack = match stack {
        Some(Ok(st)) => st,
        Some(Err(e)) => {
            eprintln!("memorial: {e}");
            let _ = writeln!(s, "Loading failed: {e}\n");
            return (s, None);
        }
        None => return (s, None),
    };
    let reference = match read_rgbe(&dir.join("memorial.hdr")) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("memorial: {e}");
            let _ = writeln!(s, "Reference unreadable: {e}\n");
            return (s, None);
        }
    };
    let (w, h) = stack.images[0].dims();
    if reference.dims() != (w, h) {
        let _ = writeln!(
            s,
            "Reference is {}x{}, the exposures {w}x{h}: no comparison.\n",
            reference.width(),
            reference.height()
        );
        return (s, None);
    }
    eprintln!(
        "memorial: {} exposures {w}x{h}, loaded in {load_ms:.0} ms",
        stack.images.len()
    );
    let rp = ResponseParams::default();
    let mut outputs: Vec<(String, f64, f64, Option<Merged>)> = Vec::new();
    for (label, st) in [
        (
            format!(
                "depthgraph HdrMerge ({} samples, lambda {}, pure blue masked)",
                rp.samples, rp.lambda
            ),
            Some(stack.clone()),
        ),
        (
            "depthgraph HdrMerge, blue borders not masked".to_string(),
            load(false).ok(),
        ),
    ] {
        let Some(st) = st else { continue };
        let (curve, rec_ms) = median_ms(repeats, || recover_response(&st, &rp));
        let Some(Ok(curve)) = curve else {
            eprintln!("memorial: recovery failed for {label}");
            continue;
        };
        let (merged, merge_ms) = median_ms(repeats, || merge_hdr(&st, &curve));
        outputs.push((label, rec_ms, merge_ms, merged.and_then(Result::ok)));
    }
    // peers on the same files (they have no notion of missing pixels)
    let mut note = None;
    let mut peer_out: Vec<PeerResult> = Vec::new();
    if let Some(pd) = peers {
        let files: Vec<String> = load_list_files(&list)
            .iter()
            .map(|f| f.display().to_string())
            .collect();
        let json = serde_json::json!({ "files": files, "times": stack.times_s }).to_string();
        if std::fs::write(pd.join("memorial.json"), json).is_ok() {
            (note, peer_out) = run_and_read_peers(pd, "memorial", w, h);
        }
    }
    // one pixel set for every method: valid in the reference and every output,
    // and not a fallback pixel of the masked merge
    let mut mask: Vec<bool> = reference.as_slice().iter().map(positive).collect();
    if let Some((_, _, _, Some(m))) = outputs.first() {
        for (k, (px, fb)) in m
            .color
            .as_slice()
            .iter()
            .zip(m.fallback.as_slice())
            .enumerate()
        {
            mask[k] &= positive(px) && *fb == 0.0;
        }
    }
    for img in outputs
        .iter()
        .filter_map(|o| o.3.as_ref().map(|m| &m.color))
        .chain(peer_out.iter().filter_map(|o| o.3.as_ref()))
    {
        for (k, px) in img.as_slice().iter().enumerate() {
            mask[k] &= positive(px);
        }
    }
    let bright = brightest_80(&reference, &mask);
    let dark: Vec<bool> = mask.iter().zip(&bright).map(|(m, b)| *m && !*b).collect();
    let row = |method: &str, response_ms: f64, merge_ms: f64, out: Option<&ColorImage>| Row {
        method: method.to_string(),
        response_ms,
        merge_ms,
        err: out.and_then(|o| log_error(o, &reference, &mask)),
        err_bright: out.and_then(|o| log_error(o, &reference, &bright)),
        err_dark: out.and_then(|o| log_error(o, &reference, &dark)),
    };
    let mut rows = Vec::new();
    for (label, r, m, out) in &outputs {
        rows.push(row(label, *r, *m, out.as_ref().map(|o| &o.color)));
    }
    for (label, r, m, out) in &peer_out {
        rows.push(row(label, *r, *m, out.as_ref()));
    }
    let _ = writeln!(
        s,
        "Loading the 16 PNGs: {load_ms:.0} ms. Pixels compared: valid in `memorial.hdr` and in every \
         output, and not a fallback pixel (saturated or black in every exposure) of the masked merge.\n"
    );
    s.push_str(&table(
        &rows,
        "Debevec's `memorial.hdr` (his own merge of the same scans, not ground truth)",
    ));
    let full16 = outputs
        .first()
        .and_then(|o| o.3.as_ref())
        .map(|m| m.color.clone());
    let cv16 = peer_out.first().and_then(|o| o.3.clone());
    s.push_str(&few_exposures(
        &stack,
        &list,
        full16.as_ref(),
        cv16.as_ref(),
        peers,
    ));
    (s, note)
}

/// Few exposures of the memorial series against all 16, each method against
/// its own 16-exposure result (ours against ours, OpenCV against OpenCV).
fn few_exposures(
    stack: &ExposureStack,
    list: &Path,
    full16: Option<&ColorImage>,
    cv16: Option<&ColorImage>,
    peers: Option<&Path>,
) -> String {
    let mut s = String::from(
        "\n## Few exposures of the memorial series against all 16\n\n\
         Mean |log2| difference (stops) from the same method's 16-exposure result, after one factor per \
         channel (the median). Pixels: valid in every one of the 16 exposures and seen by the subset \
         (some exposure of it with every channel in 32..223 of 255). depthgraph: default recovery \
         (`response: \"recover\"`) and the polynomial response (`\"polynomial\"`, degree 4); OpenCV: \
         CalibrateDebevec (defaults) + MergeDebevec.\n\n\
         | exposures (s) | depthgraph recover | depthgraph polynomial | OpenCV | pixels |\n|---|---:|---:|---:|---:|\n",
    );
    let Some(full16) = full16 else {
        s.push_str("\n(no 16-exposure result: no rows)\n");
        return s;
    };
    let files = load_list_files(list);
    let (w, h) = full16.dims();
    for pick in [
        vec![3usize, 5, 7],
        vec![2, 6, 10],
        vec![4, 8, 12],
        vec![5, 7],
        vec![4, 6, 8, 10, 12],
    ] {
        let sub = ExposureStack {
            images: pick.iter().map(|j| stack.images[*j].clone()).collect(),
            times_s: pick.iter().map(|j| stack.times_s[*j]).collect(),
        };
        let ours = recover_response(&sub, &ResponseParams::default())
            .and_then(|c| merge_hdr(&sub, &c))
            .ok();
        let poly = recover_polynomial(&sub, &PolynomialParams::default())
            .and_then(|c| merge_hdr(&sub, &c))
            .ok();
        let case = format!(
            "few{}",
            pick.iter()
                .map(|j| j.to_string())
                .collect::<Vec<_>>()
                .join("_")
        );
        let cv = peers.and_then(|pd| {
            let f: Vec<String> = pick
                .iter()
                .filter_map(|j| files.get(*j))
                .map(|p| p.display().to_string())
                .collect();
            let json = serde_json::json!({ "files": f, "times": sub.times_s }).to_string();
            std::fs::write(pd.join(format!("{case}.json")), json).ok()?;
            run_peers(pd, &case).ok()?;
            read_rgb_f32(&pd.join(format!("{case}.opencv_default.f32")), w, h)
        });
        let seen = seen_well(&sub, 32.0 / 255.0, 223.0 / 255.0);
        let mask: Vec<bool> = (0..full16.len())
            .map(|i| {
                seen[i]
                    && stack
                        .images
                        .iter()
                        .all(|img| img.as_slice()[i][0].is_finite())
            })
            .collect();
        let fmt = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.3}"));
        let a = ours
            .as_ref()
            .and_then(|m| mean_stops_apart(&m.color, full16, &mask));
        let b = poly
            .as_ref()
            .and_then(|m| mean_stops_apart(&m.color, full16, &mask));
        let c = match (&cv, cv16) {
            (Some(x), Some(y)) => mean_stops_apart(x, y, &mask),
            _ => None,
        };
        let times: Vec<String> = sub.times_s.iter().map(|t| format!("{t}")).collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} |",
            times.join(", "),
            fmt(a),
            fmt(b),
            fmt(c),
            mask.iter().filter(|m| **m).count()
        );
    }
    s
}

/// The image files a list names (for the peer), in order.
fn load_list_files(list: &Path) -> Vec<PathBuf> {
    let text = std::fs::read_to_string(list).unwrap_or_default();
    depthgraph::nodes::camera::hdr::parse_bracket_list(&text, list)
        .map(|v| v.into_iter().map(|e| e.0).collect())
        .unwrap_or_default()
}

fn speed(peers: Option<&Path>, repeats: usize) -> (String, f64, Option<String>) {
    let (w, h) = (640, 480);
    let mut s = String::from(
        "\n## 3 exposures at 640x480 (synthetic tabletop, stops -2, 0, +2, gamma 2.2)\n\n",
    );
    let Some(scene) = Scene::preset("tabletop", w, h) else {
        return (s, f64::NAN, None);
    };
    let truth = render(&scene, &RenderOptions::default()).color;
    let bp = BracketParams {
        stops: vec![-2.0, 0.0, 2.0],
        seed: 1,
        ..Default::default()
    };
    let stack = match simulate_bracket(&truth, &bp) {
        Ok(st) => st,
        Err(e) => {
            let _ = writeln!(s, "Simulation failed: {e}");
            return (s, f64::NAN, None);
        }
    };
    let rp = ResponseParams::default();
    let (curve, rec_ms) = median_ms(repeats, || recover_response(&stack, &rp));
    let Some(Ok(curve)) = curve else {
        let _ = writeln!(s, "Recovery failed.");
        return (s, f64::NAN, None);
    };
    let (merged, merge_ms) = median_ms(repeats, || merge_hdr(&stack, &curve));
    let gamma = ResponseCurve::gamma(bp.gamma);
    let (given, given_ms) = median_ms(repeats, || merge_hdr(&stack, &gamma));
    let mut note = None;
    let mut peer_out = Vec::new();
    if let Some(pd) = peers {
        let mut ok = true;
        for (j, img) in stack.images.iter().enumerate() {
            let bytes: Vec<u8> = img
                .as_slice()
                .iter()
                .flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
                .collect();
            ok &= std::fs::write(pd.join(format!("speed.{j}.u8")), bytes).is_ok();
        }
        let json =
            serde_json::json!({ "width": w, "height": h, "times": stack.times_s }).to_string();
        ok &= std::fs::write(pd.join("speed.json"), json).is_ok();
        if ok {
            (note, peer_out) = run_and_read_peers(pd, "speed", w, h);
        }
    }
    // pixels: lit (truth > 0), valid in every output, and not saturated or
    // black in all three exposures
    let mut mask: Vec<bool> = truth.as_slice().iter().map(positive).collect();
    if let Some(Ok(m)) = &merged {
        for (k, fb) in m.fallback.as_slice().iter().enumerate() {
            mask[k] &= *fb == 0.0;
        }
    }
    let ours =
        [&merged, &given].map(|m| m.as_ref().and_then(|m| m.as_ref().ok()).map(|m| &m.color));
    for img in ours
        .iter()
        .flatten()
        .copied()
        .chain(peer_out.iter().filter_map(|o| o.3.as_ref()))
    {
        for (k, px) in img.as_slice().iter().enumerate() {
            mask[k] &= positive(px);
        }
    }
    let bright = brightest_80(&truth, &mask);
    let dark: Vec<bool> = mask.iter().zip(&bright).map(|(m, b)| *m && !*b).collect();
    let row = |method: String, response_ms: f64, merge_ms: f64, out: Option<&ColorImage>| Row {
        method,
        response_ms,
        merge_ms,
        err: out.and_then(|o| log_error(o, &truth, &mask)),
        err_bright: out.and_then(|o| log_error(o, &truth, &bright)),
        err_dark: out.and_then(|o| log_error(o, &truth, &dark)),
    };
    let mut rows = vec![
        row(
            format!(
                "depthgraph HdrMerge, recovered ({} samples, lambda {})",
                rp.samples, rp.lambda
            ),
            rec_ms,
            merge_ms,
            ours[0],
        ),
        row(
            "depthgraph HdrMerge, given gamma 2.2 (no recovery)".into(),
            0.0,
            given_ms,
            ours[1],
        ),
    ];
    let mut ratios = Vec::new();
    for (label, r, m, out) in &peer_out {
        if *m > 0.0 {
            ratios.push((label.clone(), merge_ms / m)); // guard: m > 0
        }
        rows.push(row(label.clone(), *r, *m, out.as_ref()));
    }
    s.push_str(&table(&rows, "the exact synthetic radiance"));
    for (label, ratio) in &ratios {
        let _ = writeln!(
            s,
            "\n**Merge time, depthgraph / OpenCV MergeDebevec with the curve of {}: {ratio:.2}** (below 1: depthgraph is faster).",
            calibration_of(label)
        );
    }
    let ratio = ratios.first().map_or(f64::NAN, |r| r.1);
    (s, ratio, note)
}

fn main() {
    // cargo bench passes --bench; accept and ignore harness flags
    let repeats = 5;
    let peers_on = std::env::var("DEPTHGRAPH_PEERS")
        .map(|v| v != "0")
        .unwrap_or(true);
    let (dir, _temp) = peer_dir();
    let peers = if peers_on { dir.as_deref() } else { None };
    let data = shared_data_dir();
    let (mem, note_a) = memorial(&data, peers, repeats);
    let (spd, ratio, note_b) = speed(peers, repeats);
    let peer_note = if !peers_on {
        "OpenCV peers skipped (DEPTHGRAPH_PEERS=0)".to_string()
    } else {
        note_a
            .or(note_b)
            .unwrap_or_else(|| "OpenCV peers did not run".into())
    };
    let mut md = String::from("# HDR merge (Debevec & Malik 1997)\n\n");
    let _ = writeln!(
        md,
        "Regenerate with `cargo bench --bench hdr_memorial` (this file is overwritten). \
         Error: RMS over pixels and channels of `ln(ours) - ln(ref)` minus its mean (per channel, \
         since a recovered response fixes radiance only up to one factor per channel; the \
         one-factor column removes a single offset); the brightest-80 % column leaves out the \
         darkest fifth of the compared pixels (by the reference), the darkest-20 % column is that \
         fifth alone; slope: least-squares slope of \
         `ln(ours)` on `ln(ref)`, 1 when both span the same range of radiance. OpenCV has no \
         notion of missing pixels and sees the memorial's blue borders as they are. Times: median \
         of {repeats} runs (OpenCV: after one untimed run), release build, \
         same machine and run for every method; response = curve recovery (`recover_response`, \
         `CalibrateDebevec`), merge = eq. 6 (`merge_hdr`, `MergeDebevec`). {peer_note}.\n"
    );
    md.push_str(&mem);
    md.push_str(&spd);
    let out = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("docs/hdr.md");
    match std::fs::write(&out, &md) {
        Ok(()) => eprintln!("wrote {}", out.display()),
        Err(e) => eprintln!("cannot write {}: {e}", out.display()),
    }
    if ratio.is_finite() {
        eprintln!("merge time ratio depthgraph / OpenCV at 640x480 x3: {ratio:.2}");
    }
    println!("{md}");
}
