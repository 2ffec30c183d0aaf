//! Every pipeline in `graphs/` gives the same pixels as recorded: each
//! output port of every non-sink node is hashed (dimensions and the bits of
//! every sample) and compared with `tests/golden/pixels.txt`.
//!
//! A change of result on purpose is recorded by running the test with
//! `DEPTHGRAPH_BLESS=1` and committing the new file together with the
//! version bump of the node whose output changed.
//!
//! `copy_paste_files.ron` reads `../shared/data`; where that is missing its
//! lines are not compared, and the test says so on stderr.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use depthgraph::graph::pipeline::OutputRef;
use depthgraph::graph::prelude::*;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Hashes a value's decoded content. The tag is the value's type name, so
/// the hash does not depend on how `Value` represents it in memory.
fn hash_value(v: &Value) -> String {
    let mut h = blake3::Hasher::new();
    h.update(v.value_type().name().as_bytes());
    let f32s = |h: &mut blake3::Hasher, xs: &[f32]| {
        for x in xs {
            h.update(&x.to_bits().to_le_bytes());
        }
    };
    let dims = |h: &mut blake3::Hasher, w: usize, ht: usize| {
        h.update(&(w as u64).to_le_bytes());
        h.update(&(ht as u64).to_le_bytes());
    };
    match v {
        Value::Color(i) => {
            dims(&mut h, i.width(), i.height());
            f32s(&mut h, i.as_slice().as_flattened());
        }
        Value::Normals(i) => {
            dims(&mut h, i.width(), i.height());
            f32s(&mut h, i.as_slice().as_flattened());
        }
        Value::Depth(i) => {
            dims(&mut h, i.width(), i.height());
            f32s(&mut h, i.as_slice());
        }
        Value::Mask(i) => {
            dims(&mut h, i.width(), i.height());
            f32s(&mut h, i.as_slice());
        }
        Value::Confidence(i) => {
            dims(&mut h, i.width(), i.height());
            f32s(&mut h, i.as_slice());
        }
        Value::Labels(i) => {
            dims(&mut h, i.width(), i.height());
            for x in i.as_slice() {
                h.update(&x.to_le_bytes());
            }
        }
        Value::Scalar(x) => {
            h.update(&x.to_bits().to_le_bytes());
        }
        Value::File(_) => {}
        Value::Intrinsics(k) => {
            for x in [k.fx, k.fy, k.cx, k.cy] {
                h.update(&x.to_bits().to_le_bytes());
            }
            dims(&mut h, k.width, k.height);
        }
        Value::PointCloud(c) => {
            for part in [&c.positions, &c.colors, &c.normals] {
                h.update(&(part.len() as u64).to_le_bytes());
                f32s(&mut h, part.as_flattened());
            }
        }
        Value::Mesh(m) => {
            for part in [&m.positions, &m.colors, &m.normals] {
                h.update(&(part.len() as u64).to_le_bytes());
                f32s(&mut h, part.as_flattened());
            }
            for t in m.triangles.as_flattened() {
                h.update(&t.to_le_bytes());
            }
        }
        Value::Vpls(ls) => {
            let dirs: Vec<[f32; 3]> = ls.iter().map(|l| l.direction).collect();
            let power: Vec<[f32; 3]> = ls.iter().map(|l| l.power).collect();
            for part in [&dirs, &power] {
                h.update(&(part.len() as u64).to_le_bytes());
                f32s(&mut h, part.as_flattened());
            }
        }
        Value::Extension(_) => {}
        Value::ExposureStack(s) => {
            for (i, t) in s.images.iter().zip(&s.times_s) {
                h.update(&t.to_bits().to_le_bytes());
                dims(&mut h, i.width(), i.height());
                f32s(&mut h, i.as_slice().as_flattened());
            }
        }
    }
    h.finalize().to_hex()[..32].to_string()
}

fn hashes_of(file: &Path, reg: &Registry) -> BTreeMap<String, String> {
    let (_doc, mut p) = depthgraph::load_pipeline(file, &[], reg)
        .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    p.outputs = (0..p.nodes.len())
        .filter(|&i| !p.nodes[i].node.schema().sink)
        .map(|node| OutputRef { node, port: None })
        .collect();
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let out = tempfile::tempdir().unwrap();
    let opts = RunOptions {
        out_dir: out.path().to_path_buf(),
        ..RunOptions::default()
    };
    let r = engine
        .run(&p, &opts)
        .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    let name = file.file_name().unwrap().to_string_lossy().to_string();
    r.outputs
        .iter()
        .filter(|(_, v)| !matches!(v, Value::File(_)))
        .map(|(port, v)| (format!("{name} {port}"), hash_value(v)))
        .collect()
}

#[test]
fn every_pipeline_gives_the_recorded_pixels() {
    let reg = depthgraph::nodes::registry().unwrap();
    let have_data = root().join("../shared/data").is_dir();
    let mut files: Vec<PathBuf> = std::fs::read_dir(root().join("graphs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "ron"))
        .collect();
    files.sort();
    // the pipelines resolve their relative paths against the repository root
    std::env::set_current_dir(root()).unwrap();
    let mut now = BTreeMap::new();
    let mut skipped = Vec::new();
    for f in &files {
        let needs_data = std::fs::read_to_string(f)
            .unwrap()
            .contains("\"../shared/data");
        if needs_data && !have_data {
            skipped.push(f.file_name().unwrap().to_string_lossy().to_string());
            continue;
        }
        now.extend(hashes_of(f, &reg));
    }
    assert!(now.len() > 50, "only {} outputs hashed", now.len());
    let golden_file = root().join("tests/golden/pixels.txt");
    if std::env::var_os("DEPTHGRAPH_BLESS").is_some() {
        let text: String = now.iter().map(|(k, v)| format!("{k} {v}\n")).collect();
        std::fs::create_dir_all(golden_file.parent().unwrap()).unwrap();
        std::fs::write(&golden_file, text).unwrap();
        return;
    }
    let golden: BTreeMap<String, String> = std::fs::read_to_string(&golden_file)
        .unwrap()
        .lines()
        .filter_map(|l| l.rsplit_once(' '))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    for s in &skipped {
        eprintln!("../shared/data is missing: {s} is not compared");
    }
    let mut diffs = Vec::new();
    for (k, want) in &golden {
        if skipped.iter().any(|s| k.starts_with(&format!("{s} "))) {
            continue;
        }
        match now.get(k) {
            Some(got) if got == want => {}
            Some(got) => diffs.push(format!("{k}: {want} -> {got}")),
            None => diffs.push(format!("{k}: no longer produced")),
        }
    }
    for k in now.keys() {
        if !golden.contains_key(k) {
            diffs.push(format!("{k}: new output, not recorded"));
        }
    }
    assert!(diffs.is_empty(), "outputs changed:\n{}", diffs.join("\n"));
}
