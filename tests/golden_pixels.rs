//! Every pipeline in `graphs/` gives the same pixels as recorded: each
//! output port of every non-sink node is hashed (dimensions and the bits of
//! every sample) and compared with `tests/golden/pixels.txt`.
//!
//! Each line also holds the count, sum and sum of magnitudes of the
//! value's numbers: where the bits differ but those agree to 1e-6 (another
//! machine's libm rounding a last place differently) the test says so and
//! passes; any other difference fails it.
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

/// A value's decoded content: a hash of every bit, and the count, sum and
/// sum of magnitudes of its numbers, to tell a real change from bits that
/// differ in the last place (another machine's libm).
struct Print {
    h: blake3::Hasher,
    n: u64,
    sum: f64,
    abs: f64,
}

impl Print {
    fn new(tag: &str) -> Self {
        let mut h = blake3::Hasher::new();
        h.update(tag.as_bytes());
        Self {
            h,
            n: 0,
            sum: 0.0,
            abs: 0.0,
        }
    }
    fn num(&mut self, x: f64) {
        if x.is_finite() {
            self.n += 1;
            self.sum += x;
            self.abs += x.abs();
        }
    }
    fn f32s(&mut self, xs: &[f32]) {
        for x in xs {
            self.h.update(&x.to_bits().to_le_bytes());
            self.num(*x as f64);
        }
    }
    fn f64(&mut self, x: f64) {
        self.h.update(&x.to_bits().to_le_bytes());
        self.num(x);
    }
    fn int(&mut self, x: u64) {
        self.h.update(&x.to_le_bytes());
        self.num(x as f64);
    }
    fn dims(&mut self, w: usize, h: usize) {
        self.int(w as u64);
        self.int(h as u64);
    }
    fn line(self) -> String {
        let hex = self.h.finalize().to_hex();
        format!("{}\t{}\t{:e}\t{:e}", &hex[..32], self.n, self.sum, self.abs)
    }
}

/// The fingerprint of a value (see [`Print`]). The tag is the value's type
/// name, so it does not depend on how `Value` represents it in memory.
fn print_value(v: &Value) -> String {
    let mut p = Print::new(v.value_type().name());
    if let Some(img) = v.samples() {
        // every image kind of f32 samples alike: dimensions, then the samples
        p.dims(img.width, img.height);
        p.f32s(img.samples);
        return p.line();
    }
    match v {
        Value::Labels(i) => {
            p.dims(i.width(), i.height());
            for x in i.as_slice() {
                p.int(*x as u64);
            }
        }
        Value::Scalar(x) => p.f64(*x),
        // images were fingerprinted above
        Value::Color(_)
        | Value::Normals(_)
        | Value::Depth(_)
        | Value::Mask(_)
        | Value::Confidence(_)
        | Value::File(_)
        | Value::Extension(_) => {}
        Value::Intrinsics(k) => {
            for x in [k.fx, k.fy, k.cx, k.cy] {
                p.f64(x);
            }
            p.dims(k.width, k.height);
        }
        Value::PointCloud(c) => {
            for part in [&c.positions, &c.colors, &c.normals] {
                p.int(part.len() as u64);
                p.f32s(part.as_flattened());
            }
        }
        Value::Mesh(m) => {
            for part in [&m.positions, &m.colors, &m.normals] {
                p.int(part.len() as u64);
                p.f32s(part.as_flattened());
            }
            for t in m.triangles.as_flattened() {
                p.int(*t as u64);
            }
        }
        Value::Vpls(ls) => {
            let dirs: Vec<[f32; 3]> = ls.iter().map(|l| l.direction).collect();
            let power: Vec<[f32; 3]> = ls.iter().map(|l| l.power).collect();
            for part in [&dirs, &power] {
                p.int(part.len() as u64);
                p.f32s(part.as_flattened());
            }
        }
        Value::ExposureStack(s) => {
            for (i, t) in s.images.iter().zip(&s.times_s) {
                p.f64(*t);
                p.dims(i.width(), i.height());
                p.f32s(i.as_slice().as_flattened());
            }
        }
    }
    p.line()
}

/// Whether two fingerprints agree: the same bits, or the same count and
/// sums within 1e-6 relative (bits that differ in the last place).
fn agree(want: &str, got: &str) -> bool {
    if want == got {
        return true;
    }
    let parse = |s: &str| -> Option<(String, u64, f64, f64)> {
        let f: Vec<&str> = s.split('\t').collect();
        Some((
            f.first()?.to_string(),
            f.get(1)?.parse().ok()?,
            f.get(2)?.parse().ok()?,
            f.get(3)?.parse().ok()?,
        ))
    };
    match (parse(want), parse(got)) {
        (Some((_, n0, s0, a0)), Some((_, n1, s1, a1))) => {
            let tol = 1e-6 * (a0 + 1.0);
            n0 == n1 && (s0 - s1).abs() <= tol && (a0 - a1).abs() <= tol
        }
        _ => false,
    }
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
        .map(|(port, v)| (format!("{name} {port}"), print_value(v)))
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
        let text: String = now.iter().map(|(k, v)| format!("{k}\t{v}\n")).collect();
        std::fs::create_dir_all(golden_file.parent().unwrap()).unwrap();
        std::fs::write(&golden_file, text).unwrap();
        return;
    }
    let golden: BTreeMap<String, String> = std::fs::read_to_string(&golden_file)
        .unwrap()
        .lines()
        .filter_map(|l| l.split_once('\t'))
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
            Some(got) if agree(want, got) => {
                eprintln!("{k}: bits differ from the record, values agree to 1e-6: {want} -> {got}")
            }
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

/// The comparison passes last-place noise and fails a real change.
#[test]
fn fingerprints_tell_noise_from_change() {
    let a = "00ff\t4\t1e1\t1e1";
    assert!(agree(a, a));
    assert!(agree(a, "11aa\t4\t1.000000000001e1\t1e1"));
    assert!(!agree(a, "11aa\t4\t1.001e1\t1e1"));
    assert!(!agree(a, "11aa\t5\t1e1\t1e1"));
    assert!(!agree(a, "garbage"));
}
