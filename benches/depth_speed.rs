//! Depth filters' speed at 640x480 beside OpenCV's, same inputs, same run:
//! `cargo bench --bench depth_speed` regenerates `docs/depth-speed.md`.
//!
//! Frames: a real Kinect frame (TUM fr1_xyz, when `../shared/data` is
//! present) and the synthetic tabletop through `SimulateKinect` (always).
//! Ours: NLMeansDepth (pruning + filter) at its defaults and at OpenCV's
//! window, NLMeansInpaint, JointBilateral r=4 and r=7, DualPullPush. Peers
//! (`benches/peers/opencv_depth_speed.py`, `DEPTHGRAPH_PEERS=0` skips them):
//! `fastNlMeansDenoising` 7/21 on the 8-bit colour and on the 16-bit depth,
//! `ximgproc.jointBilateralFilter` d=9 and d=15, `inpaint` Navier-Stokes.
//! Both sides use 2 threads (rayon's pool here, `cv2.setNumThreads(2)`).
//! The measurement runs in rounds that alternate ours and the peers'
//! (`DEPTHGRAPH_ROUNDS`, default 2); every method keeps the lower of its
//! rounds' medians, so a burst of load on the shared machine during one
//! side's turn does not decide a ratio.
//! `DEPTHGRAPH_DEPTH_ONLY=Inpaint` (any part of a method's name) times only
//! those methods and prints them, without peers or docs.

mod common;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use common::{env_usize, timed, write_peer_frame};
use depthgraph::evaluation::{shared_data_dir, synthetic_scene, tum_scene};
use depthgraph::graph::prelude::*;
use depthgraph::nodes::depth::bilateral::{BilateralParams, joint_bilateral};
use depthgraph::nodes::depth::nlmeans::{
    NLMeansDepthParams, NLMeansInpaintParams, nlmeans_denoise, nlmeans_inpaint,
};
use depthgraph::nodes::depth::pull_push::{PullPushParams, Weights, pull_push};
use depthgraph::nodes::sim::sensor::{KinectParams, simulate_kinect};

/// One frame: colour, depth with the sensor's holes, intrinsics.
struct Frame {
    name: String,
    color: ColorImage,
    depth: DepthMap,
    k: Intrinsics,
}

fn frames(data: &Path) -> (Vec<Frame>, String) {
    let mut out = Vec::new();
    let mut note = String::new();
    if let Some(s) = synthetic_scene("tabletop", 640, 480) {
        let kp = KinectParams {
            seed: 7,
            ..Default::default()
        };
        if let Ok(d) = simulate_kinect(&s.depth, Some(&s.color), &s.intrinsics, &kp) {
            out.push(Frame {
                name: "synthetic tabletop, simulated Kinect".into(),
                color: s.color,
                depth: d,
                k: s.intrinsics,
            });
        }
    }
    match tum_scene(data) {
        Ok(s) => out.push(Frame {
            name: "TUM fr1_xyz (real Kinect)".into(),
            color: s.color,
            depth: s.depth,
            k: s.intrinsics,
        }),
        Err(e) => {
            note = format!("The real frame was not read: {e} (only the synthetic frame is timed).")
        }
    }
    (out, note)
}

type Method = (&'static str, fn(&Frame) -> DepthMap);

fn methods() -> Vec<Method> {
    fn or_input(r: Result<DepthMap, NodeError>, f: &Frame) -> DepthMap {
        r.unwrap_or_else(|e| {
            eprintln!("{}: {e}", f.name);
            f.depth.clone()
        })
    }
    vec![
        ("NLMeansDepth (defaults: 11x11 window, 5x5 patch)", |f| {
            or_input(
                nlmeans_denoise(&f.depth, None, &f.color, &NLMeansDepthParams::default())
                    .map(|r| r.0),
                f,
            )
        }),
        ("NLMeansDepth at OpenCV's window (21x21, 7x7)", |f| {
            let p = NLMeansDepthParams {
                search_radius: 10,
                patch_radius: 3,
                ..Default::default()
            };
            or_input(
                nlmeans_denoise(&f.depth, None, &f.color, &p).map(|r| r.0),
                f,
            )
        }),
        ("NLMeansInpaint (defaults)", |f| {
            or_input(
                nlmeans_inpaint(&f.depth, None, &f.color, &NLMeansInpaintParams::default())
                    .map(|r| r.0),
                f,
            )
        }),
        ("JointBilateral r=4 (9x9)", |f| {
            let p = BilateralParams {
                radius: 4,
                ..Default::default()
            };
            or_input(joint_bilateral(&f.depth, &f.color, &p), f)
        }),
        ("JointBilateral r=7 (15x15)", |f| {
            let p = BilateralParams {
                radius: 7,
                ..Default::default()
            };
            or_input(joint_bilateral(&f.depth, &f.color, &p), f)
        }),
        ("DualPullPush (defaults)", |f| {
            or_input(
                pull_push(
                    &f.depth,
                    &PullPushParams::default(),
                    Weights::Dual {
                        color: &f.color,
                        k: &f.k,
                    },
                )
                .map(|r| r.depth),
                f,
            )
        }),
    ]
}

/// The peers' labels, keyed as the script writes them, and the row of ours
/// each is compared with.
const PEERS: [(&str, &str, &[usize]); 6] = [
    (
        "fastnlm_gray",
        "OpenCV fastNlMeansDenoising 7/21, 8-bit grey",
        &[0, 1],
    ),
    (
        "fastnlm_color",
        "OpenCV fastNlMeansDenoising 7/21, 8-bit colour",
        &[0, 1],
    ),
    (
        "fastnlm_depth16",
        "OpenCV fastNlMeansDenoising 7/21, 16-bit depth (NORM_L1)",
        &[0, 1],
    ),
    ("inpaint_ns", "OpenCV inpaint Navier-Stokes (r=5)", &[2, 5]),
    ("jbf9", "OpenCV jointBilateralFilter d=9", &[3]),
    ("jbf15", "OpenCV jointBilateralFilter d=15", &[4]),
];

fn write_peer_inputs(dir: &Path, case: &str, f: &Frame, repeats: usize) -> std::io::Result<()> {
    let (w, h) = f.depth.dims();
    std::fs::write(
        dir.join(format!("{case}.json")),
        format!("{{\"width\": {w}, \"height\": {h}, \"repeats\": {repeats}}}"),
    )?;
    write_peer_frame(dir, case, &f.depth, &f.color)
}

fn run_peers(dir: &Path) -> Result<(), String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peers/opencv_depth_speed.py");
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(dir)
        .status()
    {
        Ok(st) if st.success() => Ok(()),
        Ok(st) => Err(format!("the OpenCV script failed ({st})")),
        Err(e) => Err(format!("python3 could not run: {e}")),
    }
}

fn main() {
    let repeats = env_usize("DEPTHGRAPH_REPEATS", 5);
    let data = shared_data_dir();
    let (frames, data_note) = frames(&data);
    let peers_on = std::env::var("DEPTHGRAPH_PEERS").map_or(true, |v| v != "0");
    let temp = tempfile::tempdir().ok();
    // DEPTHGRAPH_DEPTH_ONLY: only the methods whose name contains it,
    // timed and printed (no peers, the docs untouched)
    let only = std::env::var("DEPTHGRAPH_DEPTH_ONLY").ok();
    if let Some(o) = &only {
        for f in &frames {
            for (name, m) in methods()
                .into_iter()
                .filter(|(n, _)| n.contains(o.as_str()))
            {
                let _ = m(f);
                let (_, ms) = timed(repeats, || m(f));
                println!("{}: {name}: {ms:.1} ms", f.name);
            }
        }
        return;
    }
    // Rounds alternate ours and the peers'; each method keeps the lower of
    // its rounds' medians (the round the machine disturbed least), both
    // sides alike.
    let rounds = env_usize("DEPTHGRAPH_ROUNDS", 2).max(1);
    for (fi, f) in frames.iter().enumerate() {
        if let Some(t) = &temp
            && let Err(e) = write_peer_inputs(t.path(), &format!("frame{fi}"), f, repeats)
        {
            eprintln!("cannot write the peers' inputs: {e}");
        }
    }
    let mut ours: Vec<Vec<f64>> = vec![vec![f64::INFINITY; methods().len()]; frames.len()];
    let mut peer_ms: Vec<Option<serde_json::Value>> = vec![None; frames.len()];
    let mut peer_note = "OpenCV peers skipped (DEPTHGRAPH_PEERS=0)".to_string();
    for round in 0..rounds {
        for (f, row) in frames.iter().zip(ours.iter_mut()) {
            for ((name, m), best) in methods().into_iter().zip(row.iter_mut()) {
                // one untimed run first (allocations, the thread pool)
                let _ = m(f);
                let (_, ms) = timed(repeats, || m(f));
                eprintln!("round {round}: {}: {name}: {ms:.1} ms", f.name);
                *best = best.min(ms);
            }
        }
        if let (true, Some(t)) = (peers_on, &temp) {
            match run_peers(t.path()) {
                Ok(()) => {
                    peer_note = String::new();
                    for (fi, slot) in peer_ms.iter_mut().enumerate() {
                        let p = t.path().join(format!("frame{fi}.peers.json"));
                        let new: Option<serde_json::Value> = std::fs::read_to_string(p)
                            .ok()
                            .and_then(|s| serde_json::from_str(&s).ok());
                        *slot = lower_times(slot.take(), new);
                        if let (true, Some(j)) = (peer_note.is_empty(), slot.as_ref()) {
                            peer_note = format!("OpenCV {}", j["opencv"].as_str().unwrap_or("?"));
                        }
                    }
                }
                // a round that failed after one that ran keeps its times
                Err(e) if peer_ms.iter().all(Option::is_none) => {
                    peer_note = format!("OpenCV peers did not run: {e}")
                }
                Err(e) => eprintln!("round {round}: OpenCV peers did not run: {e}"),
            }
        }
    }
    let md = report(
        &frames,
        &ours,
        &peer_ms,
        &peer_note,
        &data_note,
        (repeats, rounds),
    );
    let out = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("docs/depth-speed.md");
    match std::fs::write(&out, &md) {
        Ok(()) => eprintln!("wrote {}", out.display()),
        Err(e) => eprintln!("cannot write {}: {e}", out.display()),
    }
    println!("{md}");
}

/// The peers' times of two rounds, each method at the lower (`ms` keys of
/// the script's JSON); either alone when the other is missing.
fn lower_times(
    a: Option<serde_json::Value>,
    b: Option<serde_json::Value>,
) -> Option<serde_json::Value> {
    match (a, b) {
        (Some(mut a), Some(b)) => {
            if let (Some(am), Some(bm)) = (a["ms"].as_object_mut(), b["ms"].as_object()) {
                for (k, v) in bm {
                    let lower = match (am.get(k).and_then(|x| x.as_f64()), v.as_f64()) {
                        (Some(x), Some(y)) => x.min(y),
                        (None, Some(y)) => y,
                        _ => continue,
                    };
                    am.insert(k.clone(), serde_json::json!(lower));
                }
            }
            Some(a)
        }
        (a, b) => a.or(b),
    }
}

fn report(
    frames: &[Frame],
    ours: &[Vec<f64>],
    peers: &[Option<serde_json::Value>],
    peer_note: &str,
    data_note: &str,
    (repeats, rounds): (usize, usize),
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Depth filters: speed beside OpenCV\n");
    let _ = writeln!(
        s,
        "Regenerate with `cargo bench --bench depth_speed` (this file is overwritten). \
         640x480, release build; each time is the lower of {rounds} rounds' medians of \
         {repeats} runs (after one untimed run), the rounds alternating ours and the peers' \
         (`DEPTHGRAPH_ROUNDS`): the round the shared machine disturbed least; 2 threads on \
         both sides (rayon; `cv2.setNumThreads(2)`), the same inputs in the same run. \
         {peer_note}. {data_note}\n\n\
         Ratio = ours / the peer's time (below 1: ours is faster). The colour peer of \
         NLMeansDepth compares 3-channel 7x7 patches over a 21x21 window on the 8-bit colour; \
         ours compares the 3-channel guide and the depth over its own window; the row at OpenCV's \
         window is the like-for-like one.\n"
    );
    for (fi, f) in frames.iter().enumerate() {
        let _ = writeln!(
            s,
            "## {} ({} holes of {})\n",
            f.name,
            f.depth.hole_count(),
            f.depth.len()
        );
        let _ = writeln!(s, "| ours | ms | peer | peer ms | ratio |");
        let _ = writeln!(s, "|---|---:|---|---:|---:|");
        for (mi, (name, _)) in methods().iter().enumerate() {
            let ms = ours[fi][mi];
            let mut any = false;
            for (key, label, rows) in PEERS {
                if !rows.contains(&mi) {
                    continue;
                }
                let Some(p) = peers[fi].as_ref().and_then(|j| j["ms"][key].as_f64()) else {
                    continue;
                };
                any = true;
                let _ = writeln!(
                    s,
                    "| {name} | {ms:.1} | {label} | {p:.1} | {:.2}x |",
                    ms / p
                );
            }
            if !any {
                let _ = writeln!(s, "| {name} | {ms:.1} | | | |");
            }
        }
        s.push('\n');
    }
    s
}
