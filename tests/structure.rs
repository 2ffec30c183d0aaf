//! The code's structure, checked: no import circle between the modules of
//! any crate (test modules aside), and every node kind written in the
//! sources is in the registry.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The module path of a source file under `src`: `a/b.rs` and
/// `a/b/mod.rs` are `a::b`, `lib.rs` is the crate root (empty).
fn module_of(src: &Path, file: &Path) -> String {
    let rel = file.strip_prefix(src).unwrap().with_extension("");
    let mut parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().to_string())
        .collect();
    if matches!(
        parts.last().map(String::as_str),
        Some("mod" | "lib" | "main")
    ) {
        parts.pop();
    }
    parts.join("::")
}

/// The code of a file without comments and without `#[cfg(test)]` items
/// (test modules may import what they like).
fn code_without_tests(text: &str) -> String {
    let mut out = String::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        let t = line.trim_start();
        if t.starts_with("//") {
            continue;
        }
        if t.starts_with("#[cfg(test)]") {
            // skip the next item: up to its matching closing brace or `;`
            let mut depth = 0i32;
            let mut opened = false;
            for l in lines.by_ref() {
                depth += l.matches('{').count() as i32 - l.matches('}').count() as i32;
                opened |= l.contains('{');
                if (opened && depth <= 0) || (!opened && l.trim_end().ends_with(';')) {
                    break;
                }
            }
            continue;
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// `crate::a::b::c` paths in `code`, as their segments (grouped `use`
/// lists name their common prefix).
fn crate_paths(code: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find("crate::") {
        let after = &rest[i + "crate::".len()..];
        let end = after
            .find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
            .unwrap_or(after.len());
        let segs: Vec<String> = after[..end]
            .split("::")
            .filter(|s| !s.is_empty())
            .map(str::to_string)
            .collect();
        if !segs.is_empty() {
            out.push(segs);
        }
        rest = &after[end..];
    }
    out
}

/// Module-level import edges of one crate: file module -> the longest
/// module prefix of each `crate::` path it names (itself and its own
/// children excluded).
fn edges(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let modules: BTreeSet<String> = files.iter().map(|f| module_of(src, f)).collect();
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in &files {
        let from = module_of(src, f);
        let code = code_without_tests(&std::fs::read_to_string(f).unwrap());
        let to_set = g.entry(from.clone()).or_default();
        for segs in crate_paths(&code) {
            let target = (1..=segs.len())
                .rev()
                .map(|n| segs[..n].join("::"))
                .find(|m| modules.contains(m));
            if let Some(t) = target {
                let own_child = t.starts_with(&format!("{from}::")) || from.is_empty();
                if t != from && !own_child {
                    to_set.insert(t);
                }
            }
        }
    }
    g
}

/// A cycle in `g`, if any, as the modules along it.
fn find_cycle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(n.to_string(), 1);
        stack.push(n.to_string());
        for m in g.get(n).into_iter().flatten() {
            match state.get(m.as_str()).copied().unwrap_or(0) {
                1 => {
                    let at = stack.iter().position(|s| s == m).unwrap_or(0);
                    let mut c = stack[at..].to_vec();
                    c.push(m.clone());
                    return Some(c);
                }
                0 => {
                    if let Some(c) = visit(m, g, state, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for n in g.keys() {
        if state.get(n.as_str()).copied().unwrap_or(0) == 0 {
            let mut stack = Vec::new();
            if let Some(c) = visit(n, g, &mut state, &mut stack) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn no_crate_has_an_import_circle() {
    for krate in ["graph/src", "nodes/src", "gpu/src", "editor/src", "src"] {
        let g = edges(&root().join(krate));
        assert!(g.len() > 3, "{krate}: only {} modules found", g.len());
        if let Some(c) = find_cycle(&g) {
            panic!("{krate}: import circle {}", c.join(" -> "));
        }
    }
}

/// The checker itself finds a circle when there is one (and none in a
/// chain), so the test above can fail.
#[test]
fn the_circle_finder_finds_circles() {
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    g.entry("a".into()).or_default().insert("b".into());
    g.entry("b".into()).or_default().insert("c".into());
    assert_eq!(find_cycle(&g), None);
    g.entry("c".into()).or_default().insert("a".into());
    assert_eq!(
        find_cycle(&g),
        Some(vec!["a".into(), "b".into(), "c".into(), "a".into()])
    );
    let code = "use crate::relight::shading::{Cone, Surf};\n#[cfg(test)]\nmod tests {\n    use crate::x::y;\n}\n// crate::z\nfn f() { crate::kit::rng::splitmix64(1); }\n";
    let paths = crate_paths(&code_without_tests(code));
    assert_eq!(
        paths,
        vec![
            vec!["relight".to_string(), "shading".to_string()],
            vec![
                "kit".to_string(),
                "rng".to_string(),
                "splitmix64".to_string()
            ],
        ]
    );
}

/// Every `TypedNode::new("Kind", ..)` and `PortedNode::new("Kind", ..)`
/// in the node sources is registered
/// by `nodes::registry()`, and the registry holds no kind the sources do
/// not define.
#[test]
fn every_node_kind_is_registered() {
    let mut files = Vec::new();
    rust_files(&root().join("nodes/src"), &mut files);
    let mut written = BTreeSet::new();
    for f in files {
        let code = code_without_tests(&std::fs::read_to_string(f).unwrap());
        for ctor in ["TypedNode::new(", "PortedNode::new("] {
            let mut rest = code.as_str();
            while let Some(i) = rest.find(ctor) {
                let after = rest[i + ctor.len()..].trim_start();
                if let Some(body) = after.strip_prefix('"') {
                    let end = body.find('"').unwrap();
                    written.insert(body[..end].to_string());
                }
                rest = &rest[i + 1..];
            }
        }
    }
    let reg = depthgraph::nodes::registry().unwrap();
    let registered: BTreeSet<String> = reg.kinds().map(str::to_string).collect();
    assert!(written.len() > 30, "found only {written:?}");
    assert_eq!(written, registered);
}
