//! Every kind of pipeline error, with the line and column it points at.

use std::path::Path;
use std::process::Command;

use depthgraph::graph::prelude::*;

fn check(text: &str, sets: &[&str]) -> Vec<CheckError> {
    let reg = depthgraph::nodes::registry().unwrap();
    let mut doc = match Document::parse(text, "t.ron") {
        Ok(d) => d,
        Err(e) => return e,
    };
    let mut errs = Vec::new();
    for s in sets {
        if let Err(e) = doc.apply_set(s) {
            errs.push(e);
        }
    }
    if !errs.is_empty() {
        return errs;
    }
    match Pipeline::check(&doc, &reg) {
        Ok(_) => Vec::new(),
        Err(e) => e,
    }
}

fn one(text: &str) -> CheckError {
    let e = check(text, &[]);
    assert_eq!(e.len(), 1, "expected one error, got {e:#?}");
    e.into_iter().next().unwrap()
}

fn at(e: &CheckError) -> (usize, usize) {
    (e.location().line, e.location().col)
}

const HEAD: &str = "(\n    version: 1,\n    nodes: {\n";

#[test]
fn syntax_error_has_line_and_column() {
    let e = one("(\n    version: 1,\n    nodes: {\n        \"a\": (kind: \"Camera\",\n    },\n)");
    assert!(matches!(e, CheckError::Syntax { .. }), "{e}");
    assert_eq!(e.location().line, 5, "{e}");
    assert!(e.to_string().starts_with("t.ron:5:"), "{e}");
}

#[test]
fn unknown_kind_suggests_the_closest() {
    let e = one(&format!(
        "{HEAD}        \"cam\": (kind: \"Camra\"),\n    }},\n)"
    ));
    assert_eq!(at(&e), (4, 23));
    assert_eq!(
        e.to_string(),
        "t.ron:4:23: node `cam`: unknown node kind `Camra` (did you mean `Camera`?)"
    );
}

#[test]
fn unknown_parameter_suggests_the_closest() {
    let e = one(&format!(
        "{HEAD}        \"cam\": (kind: \"Camera\", params: (widht: 320)),\n    }},\n)"
    ));
    assert_eq!(at(&e), (4, 42));
    assert!(
        e.to_string()
            .contains("no parameter `widht` (did you mean `width`?)"),
        "{e}"
    );
}

#[test]
fn parameter_out_of_range_names_the_range() {
    let e = one(&format!(
        "{HEAD}        \"cam\": (kind: \"Camera\", params: (width: 0)),\n    }},\n)"
    ));
    assert_eq!(at(&e), (4, 49));
    assert!(
        e.to_string().contains("value 0 is outside [1, 65536]"),
        "{e}"
    );
    let e = one(&format!(
        "{HEAD}        \"cam\": (kind: \"Camera\", params: (preset: \"kinect2\")),\n    }},\n)"
    ));
    assert!(e.to_string().contains("\"kinect2\" is not one of"), "{e}");
    let e = one(&format!(
        "{HEAD}        \"cam\": (kind: \"Camera\", params: (width: 3.5)),\n    }},\n)"
    ));
    assert!(
        e.to_string()
            .contains("expected an integer, found the float 3.5"),
        "{e}"
    );
}

#[test]
fn unknown_ports_on_both_ends() {
    let text = format!(
        "{HEAD}        \"cam\": (kind: \"Camera\"),\n        \"e\": (kind: \"Exposure\", inputs: (colour: \"cam.intrinsics\")),\n    }},\n)"
    );
    let errs = check(&text, &[]);
    let port = errs
        .iter()
        .find(|e| matches!(e, CheckError::UnknownPort { .. }))
        .unwrap();
    assert_eq!(at(port), (5, 42));
    assert!(
        port.to_string()
            .contains("no input port `colour` (did you mean `color`?)"),
        "{port}"
    );
    // the required input is then missing, reported at the node name
    let missing = errs
        .iter()
        .find(|e| matches!(e, CheckError::MissingInput { .. }))
        .unwrap();
    assert_eq!(at(missing), (5, 9));

    let text = format!(
        "{HEAD}        \"cam\": (kind: \"Camera\"),\n        \"u\": (kind: \"DepthPreview\", inputs: (depth: \"cam.intrinsic\")),\n    }},\n)"
    );
    let e = one(&text);
    assert_eq!(at(&e), (5, 53));
    assert!(
        e.to_string()
            .contains("no output port `intrinsic` (did you mean `intrinsics`?)"),
        "{e}"
    );
}

#[test]
fn type_mismatch_names_both_types() {
    let text = format!(
        "{HEAD}        \"cam\": (kind: \"Camera\"),\n        \"e\": (kind: \"Exposure\", inputs: (color: \"cam.intrinsics\")),\n    }},\n)"
    );
    let e = one(&text);
    assert_eq!(at(&e), (5, 49));
    assert_eq!(
        e.to_string(),
        "t.ron:5:49: node `e` input `color` expects Color, but `cam.intrinsics` is Intrinsics"
    );
}

#[test]
fn missing_required_input() {
    let e = one(&format!(
        "{HEAD}        \"e\": (kind: \"Exposure\"),\n    }},\n)"
    ));
    assert_eq!(at(&e), (4, 9));
    assert!(
        e.to_string()
            .contains("needs input `color` (Color), which is not connected"),
        "{e}"
    );
}

#[test]
fn cycle_names_the_nodes_on_it() {
    let text = format!(
        "{HEAD}        \"a\": (kind: \"Exposure\", inputs: (color: \"b.color\")),\n        \"b\": (kind: \"Exposure\", inputs: (color: \"a.color\")),\n    }},\n)"
    );
    let e = one(&text);
    assert_eq!(at(&e), (4, 9));
    assert!(e.to_string().ends_with("cycle: a -> b -> a"), "{e}");
}

#[test]
fn unknown_node_reference_suggests_a_name() {
    let text = format!(
        "{HEAD}        \"scene_a\": (kind: \"Camera\"),\n    }},\n    outputs: [\"scene_b.intrinsics\"],\n)"
    );
    let e = one(&text);
    assert_eq!(at(&e), (6, 15));
    assert!(e.to_string().contains("did you mean `scene_a`?"), "{e}");
}

#[test]
fn set_values_are_checked_like_the_file() {
    let text = format!("{HEAD}        \"cam\": (kind: \"Camera\"),\n    }},\n)");
    let e = check(&text, &["cam.width=abc"]);
    assert_eq!(e.len(), 1);
    assert_eq!(
        e[0].to_string(),
        "--set cam.width=abc:1:11: node `cam` parameter `width`: expected integer, found a string"
    );
    let e = check(&text, &["cam.width=99999999"]);
    assert!(e[0].to_string().contains("outside [1, 65536]"), "{}", e[0]);
    let e = check(&text, &["cam.wdth=4"]);
    assert!(
        e[0].to_string().contains("did you mean `width`?"),
        "{}",
        e[0]
    );
    assert!(check(&text, &["cam.width=320", "cam.preset=tum_fr1"]).is_empty());
}

#[test]
fn all_errors_are_reported_at_once() {
    let text = format!(
        "{HEAD}        \"a\": (kind: \"Nope\"),\n        \"b\": (kind: \"Camera\", params: (width: -1, fx: \"x\")),\n    }},\n)"
    );
    assert_eq!(check(&text, &[]).len(), 3);
}

#[test]
fn cli_check_exits_nonzero_with_locations() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.ron");
    std::fs::write(
        &file,
        format!("{HEAD}        \"e\": (kind: \"Exposure\", params: (stops: 99.0)),\n    }},\n)"),
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_depthgraph"))
        .arg("check")
        .arg(&file)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    let want = format!(
        "{}:4:49: node `e` parameter `stops`: value 99 is outside [-30, 30]",
        file.display()
    );
    assert!(err.contains(&want), "{err}");
    assert!(err.contains("needs input `color`"), "{err}");
}

#[test]
fn shipped_graphs_check_clean() {
    let reg = depthgraph::nodes::registry().unwrap();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "ron") {
            depthgraph::load_pipeline(&path, &[], &reg)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            n += 1;
        }
    }
    assert!(n >= 1, "no pipeline in graphs/");
}
