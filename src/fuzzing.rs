//! The bodies of the fuzz targets in `fuzz/` (cargo-fuzz, nightly), kept
//! here so that plain `cargo test` on stable replays the seed corpora and
//! every minimized crash input (`fuzz/regressions/<target>/`) through the
//! same code (`tests/fuzz_regressions.rs`).
//!
//! Each function takes arbitrary bytes and panics only when a property
//! fails; an error for bad input is the expected outcome, never a panic.

use std::path::Path;

use depthgraph_graph::codec;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::io::{self, ColorSpace, Limits};

/// The pixel budget of the loader targets: large enough for every seed,
/// small enough that no input can make a target hold more than a few
/// hundred MiB.
pub const FUZZ_MAX_PIXELS: usize = 1 << 20;

/// The body of one fuzz target.
pub type Target = fn(&[u8]);

/// The targets by name, as `fuzz/fuzz_targets/<name>.rs` calls them.
pub const TARGETS: &[(&str, Target)] = &[
    ("ron_document", ron_document),
    ("set_override", set_override),
    ("cache_codec", cache_codec),
    ("load_png", load_png),
    ("load_pfm", load_pfm),
    ("load_pnm", load_pnm),
    ("load_exr", load_exr),
    ("load_hdr", load_hdr),
    ("load_nyu_raw", load_nyu_raw),
    ("exposure_list", exposure_list),
];

/// Line and column of every error lie inside the text (a column may point
/// one past the end of its line, where something was expected).
fn check_location(text: &str, loc: &depthgraph_graph::error::Location) {
    let lines: Vec<&str> = text.split('\n').collect();
    assert!(
        loc.line >= 1 && loc.line <= lines.len().max(1),
        "line {} outside the text's {} lines",
        loc.line,
        lines.len()
    );
    let len = lines.get(loc.line - 1).map_or(0, |l| l.chars().count());
    assert!(
        loc.col >= 1 && loc.col <= len + 1,
        "column {} outside line {} of {} chars",
        loc.col,
        loc.line,
        len
    );
}

/// A pipeline document: if the `ron` crate accepts the text, ours reports
/// no syntax error; every error's position lies inside the text.
pub fn ron_document(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let ron_ok = ron::from_str::<ron::Value>(text).is_ok();
    match Document::parse(text, "fuzz.ron") {
        Ok(_) => {}
        Err(errors) => {
            assert!(!errors.is_empty(), "an error without errors");
            for e in &errors {
                if ron_ok {
                    assert!(
                        !matches!(e, CheckError::Syntax { .. }),
                        "ron accepts the text, we report {e}"
                    );
                }
                check_location(text, e.location());
            }
        }
    }
}

const SET_BASE: &str = r#"(
    version: 1,
    nodes: {
        "scene": (kind: "SyntheticScene", params: (preset: "tabletop", width: 32, height: 24)),
        "smooth": (
            kind: "JointBilateral",
            inputs: (depth: "scene.depth", color: "scene.color"),
        ),
        "blur": (
            kind: "Refocus",
            inputs: (color: "scene.color", depth: "smooth.depth", intrinsics: "scene.intrinsics"),
        ),
    },
    outputs: ["blur"],
)"#;

/// The canonical bytes of every node's parameters: what the Merkle key
/// hashes.
fn param_bytes(p: &Pipeline) -> Vec<u8> {
    let mut out = Vec::new();
    for n in &p.nodes {
        for (k, v) in &n.params {
            out.extend_from_slice(k.as_bytes());
            v.canonical_bytes(&mut out);
        }
    }
    out
}

/// A `--set` override: text, then a checked value, then canonical bytes.
/// Applying an accepted override twice gives the same bytes; writing the
/// checked value back as RON and applying that gives the same bytes again
/// (NaN and -0.0 included: floats are keyed by their bits).
pub fn set_override(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    // built once per fuzzing process (this is the harness, not a node):
    // the target then runs thousands of times a second
    static FIXTURE: std::sync::OnceLock<Option<(Registry, Document)>> = std::sync::OnceLock::new();
    let fixture = FIXTURE.get_or_init(|| {
        let reg = depthgraph_nodes::registry().ok()?;
        let base = Document::parse(SET_BASE, "base.ron").ok()?;
        Some((reg, base))
    });
    let Some((reg, base)) = fixture else {
        panic!("the registry or the base pipeline cannot be built");
    };
    let checked = |set: &str| -> Option<Pipeline> {
        let mut doc = base.clone();
        match doc.apply_set(set) {
            Ok(()) => {}
            Err(e) => {
                // an override is one line, whatever it holds: its column
                // counts every char of `node.param=value`
                let loc = e.location();
                let n = set.chars().count();
                assert!(
                    loc.line == 1 && loc.col >= 1 && loc.col <= n + 1,
                    "`{set}`: error at {loc} outside its {n} chars"
                );
                return None;
            }
        }
        Pipeline::check(&doc, reg).ok()
    };
    let Some(first) = checked(text) else {
        return;
    };
    let Some(again) = checked(text) else {
        panic!("accepted once, refused the second time");
    };
    let bytes = param_bytes(&first);
    assert_eq!(bytes, param_bytes(&again), "one text, two keys");
    // the value written back as RON keys alike
    let Some((target, _)) = text.split_once('=') else {
        return;
    };
    let Some((node, param)) = target.trim().split_once('.') else {
        return;
    };
    let Some(pn) = first.nodes.iter().find(|n| n.name == node.trim()) else {
        return;
    };
    let Some(v) = pn.params.get(param.trim()) else {
        return;
    };
    let round = format!("{}={}", target.trim(), v.to_ron());
    let Some(back) = checked(&round) else {
        panic!("`{round}` (the checked value written back) is refused");
    };
    assert_eq!(
        bytes,
        param_bytes(&back),
        "`{text}` and its canonical form `{round}` key differently"
    );
}

/// A cache entry from a shared store is untrusted: decoding never panics,
/// and whatever decodes encodes back to the very same bytes.
pub fn cache_codec(data: &[u8]) {
    let decoders = codec::Decoders::new();
    if let Some(out) = codec::decode(data, &decoders) {
        let again = codec::encode(&out);
        assert!(again == data, "decode then encode changed the entry");
    }
}

fn limits() -> Limits {
    Limits {
        max_pixels: FUZZ_MAX_PIXELS,
    }
}

/// A loaded image is within the budget; depth is finite and `>= 0`.
fn check_depth(d: &DepthMap) {
    assert!(d.len() <= FUZZ_MAX_PIXELS && !d.is_empty());
    assert!(
        d.as_slice().iter().all(|z| z.is_finite() && *z >= 0.0),
        "a loaded depth that is not finite or negative"
    );
}

fn check_color(c: &ColorImage) {
    assert!(c.len() <= FUZZ_MAX_PIXELS && !c.is_empty());
}

fn depth_params(encoding: io::DepthEncoding) -> io::LoadDepthParams {
    io::LoadDepthParams {
        encoding,
        ..Default::default()
    }
}

/// Runs the colour and depth loaders on `data` as a file named `name`.
fn load_both(data: &[u8], name: &str) {
    let path = Path::new(name);
    let lim = limits();
    for cs in [ColorSpace::Srgb, ColorSpace::Linear] {
        if let Ok(c) = io::decode_color(data, path, cs, &lim) {
            check_color(&c);
        }
    }
    if let Ok(d) = io::decode_depth(data, path, &depth_params(io::DepthEncoding::Depth), &lim) {
        check_depth(&d);
    }
    let mask = io::mask::LoadMaskParams::default();
    if let Ok(m) = io::mask::decode_mask(data, path, &mask, &lim) {
        assert!(m.as_slice().iter().all(|a| (0.0..=1.0).contains(a)));
    }
}

/// PNG (8/16-bit, grey or colour, any chunk the `image` crate reads).
pub fn load_png(data: &[u8]) {
    load_both(data, "fuzz.png");
}

/// PFM, both byte orders (the sign of the scale).
pub fn load_pfm(data: &[u8]) {
    if let Ok(s) = io::decode_pfm(data, Path::new("fuzz.pfm"), &limits()) {
        assert_eq!(s.values.len(), s.width * s.height);
    }
    load_both(data, "fuzz.pfm");
}

/// Binary PGM/PPM with maxval up to 65535, both 16-bit byte orders.
pub fn load_pnm(data: &[u8]) {
    for little in [false, true] {
        if let Ok(p) = io::decode_pnm(data, Path::new("fuzz.pgm"), little, &limits()) {
            assert_eq!(p.samples.len(), p.width * p.height * p.channels);
        }
    }
    // integer files give colour in [0, 1] whatever their samples claim
    // (samples above maxval are clamped to it)
    for cs in [ColorSpace::Srgb, ColorSpace::Linear] {
        if let Ok(c) = io::decode_color(data, Path::new("fuzz.ppm"), cs, &limits()) {
            assert!(
                c.as_slice()
                    .as_flattened()
                    .iter()
                    .all(|v| (0.0..=1.0).contains(v))
            );
        }
    }
    load_both(data, "fuzz.ppm");
}

/// OpenEXR: f16/f32/u32 channels, any compression the `exr` crate reads.
pub fn load_exr(data: &[u8]) {
    load_both(data, "fuzz.exr");
}

/// Radiance RGBE: any header order, both run-length encodings, every
/// orientation; values finite and non-negative.
pub fn load_hdr(data: &[u8]) {
    if let Ok(r) = io::radiance::decode_rgbe(data, Path::new("fuzz.hdr"), &limits()) {
        check_color(&r.image);
        assert!(r.exposure.is_finite() && r.exposure > 0.0);
        assert!(
            r.image
                .as_slice()
                .as_flattened()
                .iter()
                .all(|v| v.is_finite() && *v >= 0.0),
            "a decoded RGBE value that is negative or not finite"
        );
    }
    load_both(data, "fuzz.hdr");
}

/// NYU Depth v2 raw dumps (little-endian PGM of Kinect disparity).
pub fn load_nyu_raw(data: &[u8]) {
    let p = depth_params(io::DepthEncoding::NyuRaw);
    if let Ok(d) = io::decode_depth(data, Path::new("fuzz.pgm"), &p, &limits()) {
        check_depth(&d);
    }
}

/// An exposure list (`filename exposure_time_s` lines): parsed or refused
/// with the line; every time it returns is finite and positive.
pub fn exposure_list(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(list) = depthgraph_nodes::camera::hdr::parse_bracket_list(text, Path::new("l.txt")) {
        assert!(!list.is_empty());
        assert!(list.iter().all(|(_, t)| t.is_finite() && *t > 0.0));
    }
}
