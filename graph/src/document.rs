//! The pipeline document: what a RON file says, with positions, before any
//! checking against the registry.
//!
//! ```ron
//! (
//!     version: 1,
//!     nodes: {
//!         "scene": (kind: "SyntheticScene", params: (preset: "tabletop")),
//!         "save":  (kind: "SaveColor", params: (path: "color.png"),
//!                   inputs: (color: "scene.color")),
//!     },
//!     outputs: ["save"],
//!     // optional, written by the editor, ignored by the CLI:
//!     layout: { "scene": (10.0, 20.0) },
//! )
//! ```

use std::collections::BTreeMap;
use std::fmt;

use crate::error::{CheckError, Location};
use crate::frames::{expand, has_placeholder, is_whole_placeholder};
use crate::params::quote;
use crate::ron_text::{self, Pos, RonValue, Spanned};

/// The newest document format this build reads and writes.
pub const FORMAT_VERSION: u32 = 1;

/// A parsed pipeline file.
#[derive(Debug, Clone, PartialEq)]
pub struct Document {
    /// Name used in messages (usually the path).
    pub file: String,
    /// Format version the file declares, or [`FORMAT_VERSION`] when it declares none.
    pub version: u32,
    /// Nodes in file order.
    pub nodes: Vec<NodeDecl>,
    /// Requested outputs: `"node"` (all its outputs) or `"node.port"`.
    /// Empty means every sink.
    pub outputs: Vec<Spanned<String>>,
    /// Editor positions by node name; the CLI ignores them.
    pub layout: BTreeMap<String, [f64; 2]>,
    /// The frames `depthgraph batch` runs when given no `--frames`
    /// (`frames: "0..30"`), checked as a [`FrameSelection`](crate::frames::FrameSelection).
    pub frames: Option<String>,
    /// Notices from reading (e.g. a migrated older format).
    pub notices: Vec<String>,
    /// The file's comments, each kept with its element ([`CommentAnchor`]),
    /// so that [`Document::to_ron`] (the editor's Save) writes them back there.
    pub comments: BTreeMap<CommentAnchor, KeptComments>,
}

/// The comments kept with one element: those on lines of their own before
/// it, and those after code on its own line (written back at the end of
/// its line).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeptComments {
    /// On lines of their own before the element.
    pub before: Vec<String>,
    /// After the element, on its line.
    pub after: Vec<String>,
}

/// The element a comment of the file is kept with. A comment on a line of
/// its own belongs to the element written after it (one after the last
/// element, to [`End`](Self::End)); one after code on its line, to the
/// last element that starts on that line (else to the next element, on
/// the line above it). Comments inside a value (between a list's items)
/// move before the next element; comments of a node, parameter or wire
/// that is removed go with it ([`Document::drop_stale_comments`]).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub enum CommentAnchor {
    /// Before the document's opening parenthesis (the file's header).
    Header,
    /// Before a top-level field: `version`, `nodes`, `outputs`, `frames`,
    /// `layout`.
    Field(String),
    /// Before a node's entry.
    Node(String),
    /// Before a node's `kind`.
    Kind(String),
    /// Before a parameter of a node: (node, parameter).
    Param(String, String),
    /// Before an input of a node: (node, input).
    Input(String, String),
    /// After the last element, before the closing parenthesis.
    End,
}

/// Each comment with the element it is kept with ([`CommentAnchor`]):
/// `root` is where the document's parenthesis opens, `fields` its
/// top-level fields.
fn attach_comments(
    comments: Vec<ron_text::Comment>,
    root: Pos,
    fields: &[(Spanned<String>, Spanned<RonValue>)],
    nodes: &[NodeDecl],
) -> BTreeMap<CommentAnchor, KeptComments> {
    let at = |p: Pos| (p.line, p.col);
    let mut anchors: Vec<((usize, usize), CommentAnchor)> = fields
        .iter()
        .map(|(k, _)| (at(k.pos), CommentAnchor::Field(k.value.clone())))
        .collect();
    for n in nodes {
        let name = &n.name.value;
        anchors.push((at(n.name.pos), CommentAnchor::Node(name.clone())));
        anchors.push((at(n.kind.pos), CommentAnchor::Kind(name.clone())));
        for (k, _) in &n.params {
            anchors.push((
                at(k.pos),
                CommentAnchor::Param(name.clone(), k.value.clone()),
            ));
        }
        for (k, _) in &n.inputs {
            anchors.push((
                at(k.pos),
                CommentAnchor::Input(name.clone(), k.value.clone()),
            ));
        }
    }
    anchors.sort_by_key(|a| a.0);
    let mut out: BTreeMap<CommentAnchor, KeptComments> = BTreeMap::new();
    for c in comments {
        let here = at(c.pos);
        if here < at(root) {
            out.entry(CommentAnchor::Header)
                .or_default()
                .before
                .push(c.text);
            continue;
        }
        // after code: the last element starting on its line, before it
        let on_line = (!c.own_line)
            .then(|| {
                anchors
                    .iter()
                    .rev()
                    .find(|(p, _)| p.0 == here.0 && p.1 < here.1)
            })
            .flatten();
        if let Some((_, a)) = on_line {
            out.entry(a.clone()).or_default().after.push(c.text);
            continue;
        }
        let anchor = anchors
            .iter()
            .find(|(p, _)| if c.own_line { *p > here } else { p.0 > here.0 })
            .map_or(CommentAnchor::End, |(_, a)| a.clone());
        out.entry(anchor).or_default().before.push(c.text);
    }
    out
}

/// Writes the comments kept before `anchor`, each on its own line at
/// `indent` spaces (a block comment's later lines as written); with
/// `all`, those after it too (an element not written).
fn put_comments(
    s: &mut String,
    comments: &BTreeMap<CommentAnchor, KeptComments>,
    anchor: &CommentAnchor,
    indent: usize,
    all: bool,
) {
    let Some(k) = comments.get(anchor) else {
        return;
    };
    let after = if all { &k.after[..] } else { &[] };
    for c in k.before.iter().chain(after) {
        s.push_str(&" ".repeat(indent));
        s.push_str(c);
        s.push('\n');
    }
}

/// Writes the line of element `anchor` (`text` at `indent` spaces) with
/// its comments: those before it on lines of their own, those after it at
/// the end of its line.
fn put_line(
    s: &mut String,
    comments: &BTreeMap<CommentAnchor, KeptComments>,
    anchor: &CommentAnchor,
    indent: usize,
    text: &str,
) {
    put_comments(s, comments, anchor, indent, false);
    s.push_str(&" ".repeat(indent));
    s.push_str(text);
    for c in comments.get(anchor).map_or(&[][..], |k| &k.after[..]) {
        s.push(' ');
        s.push_str(c);
    }
    s.push('\n');
}

/// One node of a document.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeDecl {
    /// The node's name (its key in `nodes`), with its position.
    pub name: Spanned<String>,
    /// The kind as written, with its position.
    pub kind: Spanned<String>,
    /// Parameter values as written, converted when checked against the schema.
    pub params: Vec<(Spanned<String>, Spanned<RonValue>)>,
    /// Input port -> `"node.port"` reference.
    pub inputs: Vec<(Spanned<String>, Spanned<String>)>,
    /// File the values came from (`--set` overrides have their own).
    pub param_files: BTreeMap<String, String>,
}

impl NodeDecl {
    /// A node `name` of kind `kind`, with no parameters or inputs, at `Pos::default()`.
    pub fn new(name: &str, kind: &str) -> Self {
        Self {
            name: Spanned {
                pos: Pos::default(),
                value: name.to_string(),
            },
            kind: Spanned {
                pos: Pos::default(),
                value: kind.to_string(),
            },
            params: Vec::new(),
            inputs: Vec::new(),
            param_files: BTreeMap::new(),
        }
    }
}

/// A reference `node.port` split in two.
pub fn split_ref(r: &str) -> Option<(&str, &str)> {
    let (n, p) = r.rsplit_once('.')?;
    if n.is_empty() || p.is_empty() {
        None
    } else {
        Some((n, p))
    }
}

impl Document {
    /// Reads a document from RON text; `file` names it in messages.
    pub fn parse(text: &str, file: &str) -> Result<Document, Vec<CheckError>> {
        let loc = |pos: Pos| Location::new(file, pos);
        let (root, comments) = ron_text::parse_with_comments(text).map_err(|e| {
            vec![if e.valid_ron {
                CheckError::Format {
                    loc: loc(e.pos),
                    message: e.message,
                }
            } else {
                CheckError::Syntax {
                    loc: loc(e.pos),
                    message: e.message,
                }
            }]
        })?;
        let mut errors = Vec::new();
        let mut doc = Document {
            file: file.to_string(),
            version: FORMAT_VERSION,
            nodes: Vec::new(),
            outputs: Vec::new(),
            layout: BTreeMap::new(),
            frames: None,
            notices: Vec::new(),
            comments: BTreeMap::new(),
        };
        let shape = |pos: Pos, what: &str, found: &RonValue| CheckError::Format {
            loc: loc(pos),
            message: format!("expected {what}, found {}", found.describe()),
        };
        let RonValue::Struct { fields, .. } = &root.value else {
            return Err(vec![shape(
                root.pos,
                "a pipeline `(version: 1, nodes: {...}, outputs: [...])`",
                &root.value,
            )]);
        };
        let mut saw_version = false;
        errors.extend(repeated_fields(fields, "the pipeline", file));
        for (key, val) in fields {
            match key.value.as_str() {
                "version" => {
                    saw_version = true;
                    match val.value {
                        RonValue::Int(v) if v >= 1 && v <= FORMAT_VERSION as i64 => {
                            doc.version = v as u32
                        }
                        RonValue::Int(v) if v > FORMAT_VERSION as i64 => errors.push(CheckError::Format {
                            loc: loc(val.pos),
                            message: format!(
                                "format version {v} was written by a newer depthgraph; this one reads up to {FORMAT_VERSION}"
                            ),
                        }),
                        _ => errors.push(CheckError::Format {
                            loc: loc(val.pos),
                            message: format!("expected a format version from 1 to {FORMAT_VERSION}"),
                        }),
                    }
                }
                "nodes" => {
                    let RonValue::Map(entries) = &val.value else {
                        errors.push(shape(
                            val.pos,
                            "a map of nodes `{\"name\": (kind: ...)}`",
                            &val.value,
                        ));
                        continue;
                    };
                    for (k, v) in entries {
                        match parse_node(k, v, file) {
                            Ok(n) => {
                                if let Some(prev) =
                                    doc.nodes.iter().find(|p| p.name.value == n.name.value)
                                {
                                    errors.push(CheckError::Format {
                                        loc: loc(n.name.pos),
                                        message: format!(
                                            "node `{}` is declared twice (first at line {})",
                                            n.name.value, prev.name.pos.line
                                        ),
                                    });
                                } else {
                                    doc.nodes.push(n);
                                }
                            }
                            Err(mut e) => errors.append(&mut e),
                        }
                    }
                }
                "outputs" => match &val.value {
                    RonValue::List(items) => {
                        for it in items {
                            match &it.value {
                                RonValue::Str(s) => doc.outputs.push(Spanned {
                                    pos: it.pos,
                                    value: s.clone(),
                                }),
                                other => errors.push(shape(
                                    it.pos,
                                    "a string \"node\" or \"node.port\"",
                                    other,
                                )),
                            }
                        }
                    }
                    other => errors.push(shape(val.pos, "a list of outputs", other)),
                },
                "layout" => match &val.value {
                    RonValue::Map(entries) => {
                        for (k, v) in entries {
                            let pos = match &v.value {
                                RonValue::Tuple { items, .. } | RonValue::List(items)
                                    if items.len() == 2 =>
                                {
                                    match (num(&items[0].value), num(&items[1].value)) {
                                        (Some(x), Some(y)) => Some([x, y]),
                                        _ => None,
                                    }
                                }
                                _ => None,
                            };
                            match (&k.value, pos) {
                                (RonValue::Str(name), Some(p)) => {
                                    doc.layout.insert(name.clone(), p);
                                }
                                _ => errors.push(CheckError::Format {
                                    loc: loc(k.pos),
                                    message: "layout entries are `\"node\": (x, y)`".into(),
                                }),
                            }
                        }
                    }
                    other => errors.push(shape(val.pos, "a map of node positions", other)),
                },
                "frames" => match &val.value {
                    RonValue::Str(f) => match crate::frames::FrameSelection::parse(f) {
                        Ok(_) => doc.frames = Some(f.clone()),
                        Err(e) => errors.push(CheckError::Format {
                            loc: loc(val.pos),
                            message: e.to_string(),
                        }),
                    },
                    other => errors.push(shape(val.pos, "frames as text, e.g. \"0..30\"", other)),
                },
                other => {
                    let suggestion = crate::registry::closest(
                        other,
                        ["version", "nodes", "outputs", "layout", "frames"],
                    );
                    errors.push(CheckError::Format {
                        loc: loc(key.pos),
                        message: format!(
                            "unknown field `{other}`; a pipeline has `version`, `nodes`, `outputs`, `frames` and `layout`{}",
                            suggestion.map(|s| format!(" (did you mean `{s}`?)")).unwrap_or_default()
                        ),
                    });
                }
            }
        }
        if !saw_version {
            doc.notices.push(format!(
                "{file}: no `version` field; read as format version {FORMAT_VERSION}"
            ));
        }
        doc.comments = attach_comments(comments, root.pos, fields, &doc.nodes);
        if errors.is_empty() {
            Ok(doc)
        } else {
            Err(errors)
        }
    }

    /// Forgets the comments kept with elements that no longer exist (a
    /// removed node, its parameters, a removed wire), so that an element
    /// added later under the same name does not inherit them.
    pub fn drop_stale_comments(&mut self) {
        let nodes = &self.nodes;
        let find = |n: &str| nodes.iter().find(|d| d.name.value == n);
        self.comments.retain(|anchor, _| match anchor {
            CommentAnchor::Node(n) | CommentAnchor::Kind(n) => find(n).is_some(),
            CommentAnchor::Param(n, k) => {
                find(n).is_some_and(|d| d.params.iter().any(|(p, _)| p.value == *k))
            }
            CommentAnchor::Input(n, k) => {
                find(n).is_some_and(|d| d.inputs.iter().any(|(p, _)| p.value == *k))
            }
            CommentAnchor::Header | CommentAnchor::Field(_) | CommentAnchor::End => true,
        });
    }

    /// Finds a node by name.
    pub fn node(&self, name: &str) -> Option<&NodeDecl> {
        self.nodes.iter().find(|n| n.name.value == name)
    }
    /// Finds a node by name, for editing.
    pub fn node_mut(&mut self, name: &str) -> Option<&mut NodeDecl> {
        self.nodes.iter_mut().find(|n| n.name.value == name)
    }

    /// Applies `node.param=value` (value in RON syntax; a bare word is read as
    /// text). The value is checked later, exactly like one written in the file.
    pub fn apply_set(&mut self, assignment: &str) -> Result<(), CheckError> {
        let file = format!("--set {assignment}");
        let at = |col: usize| Location::new(&file, Pos { line: 1, col });
        let Some((target, value_text)) = assignment.split_once('=') else {
            return Err(CheckError::Format {
                loc: at(1),
                message: "expected `node.param=value`".into(),
            });
        };
        let Some((node, param)) = split_ref(target.trim()) else {
            return Err(CheckError::Format {
                loc: at(1),
                message: format!("expected `node.param` before `=`, found `{target}`"),
            });
        };
        let value_col = target.chars().count() + 2;
        let value_text = value_text.trim();
        let parsed = match ron_text::parse(value_text) {
            Ok(v) => v.value,
            // A number the reader cannot hold (an integer past 64 bits)
            // is that, not text (it was then "expected integer, found a
            // string").
            Err(e)
                if value_text
                    .trim_start_matches(['-', '+'])
                    .starts_with(|c: char| c.is_ascii_digit())
                    && value_text.parse::<f64>().is_ok() =>
            {
                return Err(CheckError::Format {
                    loc: at(value_col),
                    message: format!("`{value_text}` is out of range: {}", e.message),
                });
            }
            // A bare word or a path is text.
            Err(_) if !value_text.is_empty() => RonValue::Str(value_text.to_string()),
            Err(e) => {
                return Err(CheckError::Syntax {
                    loc: at(value_col + e.pos.col - 1),
                    message: e.message,
                });
            }
        };
        let parsed = match parsed {
            RonValue::Ident(s) if s != "None" => RonValue::Str(s),
            other => other,
        };
        let names: Vec<String> = self.nodes.iter().map(|n| n.name.value.clone()).collect();
        let Some(decl) = self.node_mut(node) else {
            let suggestion = crate::registry::closest(node, names.iter().map(String::as_str));
            return Err(CheckError::UnknownNode {
                loc: at(1),
                name: node.to_string(),
                suggestion: suggestion.map(str::to_string),
            });
        };
        let spanned_value = Spanned {
            pos: Pos {
                line: 1,
                col: value_col,
            },
            value: parsed,
        };
        decl.param_files.insert(param.to_string(), file.clone());
        if let Some(slot) = decl.params.iter_mut().find(|(k, _)| k.value == param) {
            slot.0.pos = Pos {
                line: 1,
                col: 1 + node.len() + 1,
            };
            slot.1 = spanned_value;
        } else {
            decl.params.push((
                Spanned {
                    pos: Pos {
                        line: 1,
                        col: 1 + node.len() + 1,
                    },
                    value: param.to_string(),
                },
                spanned_value,
            ));
        }
        Ok(())
    }

    /// Writes the document as RON a person can read and edit.
    /// The file's comments are written back with their elements
    /// ([`CommentAnchor`]).
    pub fn to_ron(&self) -> String {
        use CommentAnchor as A;
        let c = &self.comments;
        let field = |f: &str| A::Field(f.to_string());
        let mut s = String::new();
        put_comments(&mut s, c, &A::Header, 0, true);
        s.push_str("(\n");
        put_line(
            &mut s,
            c,
            &field("version"),
            4,
            &format!("version: {},", self.version),
        );
        put_line(&mut s, c, &field("nodes"), 4, "nodes: {");
        for n in &self.nodes {
            let name = &n.name.value;
            put_line(
                &mut s,
                c,
                &A::Node(name.clone()),
                8,
                &format!("{}: (", quote(name)),
            );
            put_line(
                &mut s,
                c,
                &A::Kind(name.clone()),
                12,
                &format!("kind: {},", quote(&n.kind.value)),
            );
            if !n.params.is_empty() {
                s.push_str("            params: (\n");
                for (k, v) in &n.params {
                    put_line(
                        &mut s,
                        c,
                        &A::Param(name.clone(), k.value.clone()),
                        16,
                        &format!("{}: {},", k.value, ron_to_text(&v.value)),
                    );
                }
                s.push_str("            ),\n");
            }
            if !n.inputs.is_empty() {
                s.push_str("            inputs: (\n");
                for (k, v) in &n.inputs {
                    put_line(
                        &mut s,
                        c,
                        &A::Input(name.clone(), k.value.clone()),
                        16,
                        &format!("{}: {},", k.value, quote(&v.value)),
                    );
                }
                s.push_str("            ),\n");
            }
            s.push_str("        ),\n");
        }
        s.push_str("    },\n");
        let outs: Vec<String> = self.outputs.iter().map(|o| quote(&o.value)).collect();
        put_line(
            &mut s,
            c,
            &field("outputs"),
            4,
            &format!("outputs: [{}],", outs.join(", ")),
        );
        if let Some(f) = &self.frames {
            put_line(
                &mut s,
                c,
                &field("frames"),
                4,
                &format!("frames: {},", quote(f)),
            );
        }
        if !self.layout.is_empty() {
            put_line(&mut s, c, &field("layout"), 4, "layout: {");
            for (k, [x, y]) in &self.layout {
                s.push_str(&format!("        {}: ({x:?}, {y:?}),\n", quote(k)));
            }
            s.push_str("    },\n");
        }
        // the comments of a field not written (no frames, an empty
        // layout) and those after the last element
        for f in ["frames", "layout"] {
            let written = match f {
                "frames" => self.frames.is_some(),
                _ => !self.layout.is_empty(),
            };
            if !written {
                put_comments(&mut s, c, &field(f), 4, true);
            }
        }
        put_comments(&mut s, c, &A::End, 4, true);
        s.push_str(")\n");
        s
    }
}

fn num(v: &RonValue) -> Option<f64> {
    match v {
        RonValue::Int(i) => Some(*i as f64),
        RonValue::Float(f) => Some(*f),
        _ => None,
    }
}

/// RON text of a value (inverse of the reader for the subset it reads).
pub fn ron_to_text(v: &RonValue) -> String {
    match v {
        RonValue::Str(s) => quote(s),
        RonValue::Int(i) => i.to_string(),
        RonValue::Float(f) => {
            if f.is_nan() {
                "NaN".into()
            } else if f.is_infinite() {
                if *f > 0.0 {
                    "inf".into()
                } else {
                    "-inf".into()
                }
            } else {
                format!("{f:?}")
            }
        }
        RonValue::Bool(b) => b.to_string(),
        RonValue::Ident(s) => s.clone(),
        RonValue::List(items) => {
            let parts: Vec<String> = items.iter().map(|i| ron_to_text(&i.value)).collect();
            format!("[{}]", parts.join(", "))
        }
        RonValue::Map(entries) => {
            let parts: Vec<String> = entries
                .iter()
                .map(|(k, v)| format!("{}: {}", ron_to_text(&k.value), ron_to_text(&v.value)))
                .collect();
            format!("{{{}}}", parts.join(", "))
        }
        RonValue::Struct { name, fields } => {
            let parts: Vec<String> = fields
                .iter()
                .map(|(k, v)| format!("{}: {}", k.value, ron_to_text(&v.value)))
                .collect();
            format!("{}({})", name.clone().unwrap_or_default(), parts.join(", "))
        }
        RonValue::Tuple { name, items } => {
            let parts: Vec<String> = items.iter().map(|i| ron_to_text(&i.value)).collect();
            format!("{}({})", name.clone().unwrap_or_default(), parts.join(", "))
        }
    }
}

/// A field written twice in one struct of `what` (the pipeline, a node,
/// its `params` or `inputs`): the RON reader keeps both, and which one
/// counts is not for the document to leave open (a `--set` replaced the
/// first while the last was used).
fn repeated_fields(
    fields: &[(Spanned<String>, Spanned<RonValue>)],
    what: &str,
    file: &str,
) -> Vec<CheckError> {
    fields
        .iter()
        .enumerate()
        .filter_map(|(i, (k, _))| {
            let (first, _) = fields[..i].iter().find(|(p, _)| p.value == k.value)?;
            Some(CheckError::Format {
                loc: Location::new(file, k.pos),
                message: format!(
                    "{what}: `{}` is given twice (first at line {}, column {})",
                    k.value, first.pos.line, first.pos.col
                ),
            })
        })
        .collect()
}

fn parse_node(
    key: &Spanned<RonValue>,
    val: &Spanned<RonValue>,
    file: &str,
) -> Result<NodeDecl, Vec<CheckError>> {
    let loc = |pos: Pos| Location::new(file, pos);
    let mut errors = Vec::new();
    let RonValue::Str(name) = &key.value else {
        return Err(vec![CheckError::Format {
            loc: loc(key.pos),
            message: format!("node names are strings, found {}", key.value.describe()),
        }]);
    };
    if name.contains('.') || name.is_empty() {
        errors.push(CheckError::Format {
            loc: loc(key.pos),
            message: format!("node name `{name}` must be non-empty and contain no `.`"),
        });
    }
    let RonValue::Struct { fields, .. } = &val.value else {
        return Err(vec![CheckError::Format {
            loc: loc(val.pos),
            message: format!(
                "node `{name}`: expected `(kind: \"...\", params: (...), inputs: (...))`, found {}",
                val.value.describe()
            ),
        }]);
    };
    let mut decl = NodeDecl::new(name, "");
    decl.name.pos = key.pos;
    let mut saw_kind = false;
    errors.extend(repeated_fields(fields, &format!("node `{name}`"), file));
    for (k, v) in fields {
        match k.value.as_str() {
            "kind" => match &v.value {
                RonValue::Str(s) | RonValue::Ident(s) => {
                    saw_kind = true;
                    decl.kind = Spanned {
                        pos: v.pos,
                        value: s.clone(),
                    };
                }
                other => errors.push(CheckError::Format {
                    loc: loc(v.pos),
                    message: format!("node `{name}`: `kind` is a string, found {}", other.describe()),
                }),
            },
            "params" => match &v.value {
                RonValue::Struct { fields, .. } => {
                    errors.extend(repeated_fields(
                        fields,
                        &format!("node `{name}` params"),
                        file,
                    ));
                    decl.params = fields.clone();
                }
                RonValue::Tuple { items, .. } if items.is_empty() => {}
                other => errors.push(CheckError::Format {
                    loc: loc(v.pos),
                    message: format!(
                        "node `{name}`: `params` is `(name: value, ...)`, found {}",
                        other.describe()
                    ),
                }),
            },
            "inputs" => match &v.value {
                RonValue::Struct { fields, .. } => {
                    errors.extend(repeated_fields(
                        fields,
                        &format!("node `{name}` inputs"),
                        file,
                    ));
                    for (port, src) in fields {
                        match &src.value {
                            RonValue::Str(s) => decl.inputs.push((
                                port.clone(),
                                Spanned {
                                    pos: src.pos,
                                    value: s.clone(),
                                },
                            )),
                            other => errors.push(CheckError::Format {
                                loc: loc(src.pos),
                                message: format!(
                                    "node `{name}` input `{}`: expected \"node.port\", found {}",
                                    port.value,
                                    other.describe()
                                ),
                            }),
                        }
                    }
                }
                RonValue::Tuple { items, .. } if items.is_empty() => {}
                other => errors.push(CheckError::Format {
                    loc: loc(v.pos),
                    message: format!(
                        "node `{name}`: `inputs` is `(port: \"node.port\", ...)`, found {}",
                        other.describe()
                    ),
                }),
            },
            other => errors.push(CheckError::Format {
                loc: loc(k.pos),
                message: format!(
                    "node `{name}`: unknown field `{other}`; a node has `kind`, `params` and `inputs`"
                ),
            }),
        }
    }
    if !saw_kind {
        errors.push(CheckError::Format {
            loc: loc(val.pos),
            message: format!("node `{name}` has no `kind`"),
        });
    }
    if errors.is_empty() {
        Ok(decl)
    } else {
        Err(errors)
    }
}

impl Document {
    /// The `(node, parameter)` pairs whose values hold a frame placeholder,
    /// in file order; empty when the pipeline takes no frame index.
    pub fn frame_params(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for n in &self.nodes {
            for (k, v) in &n.params {
                if let RonValue::Str(s) = &v.value
                    && has_placeholder(s)
                {
                    out.push((n.name.value.clone(), k.value.clone()));
                }
            }
        }
        out
    }

    /// The document of frame `frame`: every placeholder replaced; a value
    /// that is exactly one placeholder (`"{frame}"`) becomes the integer, so
    /// number parameters can follow the frame. Errors name the node, the
    /// parameter and its position.
    pub fn for_frame(&self, frame: u64) -> Result<Document, Vec<CheckError>> {
        let mut doc = self.clone();
        let mut errors = Vec::new();
        for n in &mut doc.nodes {
            for (k, v) in &mut n.params {
                let RonValue::Str(s) = &v.value else { continue };
                match expand(s, frame) {
                    Ok(None) => {}
                    Ok(Some(text)) => {
                        let whole = is_whole_placeholder(s);
                        v.value = match (whole, i64::try_from(frame)) {
                            (true, Ok(i)) => RonValue::Int(i),
                            _ => RonValue::Str(text),
                        };
                    }
                    Err(why) => {
                        let file = n
                            .param_files
                            .get(&k.value)
                            .cloned()
                            .unwrap_or_else(|| self.file.clone());
                        errors.push(CheckError::Format {
                            loc: Location::new(&file, v.pos),
                            message: format!(
                                "node `{}`, parameter `{}`: {why}",
                                n.name.value, k.value
                            ),
                        });
                    }
                }
            }
        }
        if errors.is_empty() {
            Ok(doc)
        } else {
            Err(errors)
        }
    }
}

impl fmt::Display for Document {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_ron())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = r#"(
    version: 1,
    nodes: {
        "a": (kind: "Source", params: (x: 1.5, name: "hi")),
        "b": (kind: "Sink", inputs: (v: "a.out")),
    },
    outputs: ["b"],
    layout: { "a": (1.0, 2.0) },
)"#;

    #[test]
    fn parse_and_round_trip() {
        let d = Document::parse(TEXT, "t.ron").unwrap();
        assert_eq!(d.nodes.len(), 2);
        assert_eq!(d.nodes[1].inputs[0].1.value, "a.out");
        assert_eq!(d.nodes[1].inputs[0].1.pos, Pos { line: 5, col: 41 });
        assert_eq!(d.layout["a"], [1.0, 2.0]);
        let again = Document::parse(&d.to_ron(), "t.ron").unwrap();
        assert_eq!(again.to_ron(), d.to_ron());
        assert_eq!(again.nodes[0].params.len(), 2);
    }

    /// A `--set` number too large for the reader is reported as such, not
    /// read as text (which then failed as "found a string").
    #[test]
    fn a_set_number_out_of_range_says_so() {
        let mut d = Document::parse(TEXT, "t.ron").unwrap();
        let e = d
            .apply_set("a.x=99999999999999999999")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("out of range") && e.contains("99999999999999999999"),
            "{e}"
        );
        // words, paths and numbers that fit are as before
        d.apply_set("a.name=hello").unwrap();
        d.apply_set("a.name=./12.png").unwrap();
        d.apply_set("a.x=12").unwrap();
        d.apply_set("a.x=-1e400").unwrap_or_else(|e| panic!("{e}"));
    }

    /// Written back, a file keeps its comments with the elements they
    /// stood before (the editor's Save rewrote the file without them).
    #[test]
    fn comments_are_written_back_before_their_elements() {
        let text = "// header one\n// header two\n#![enable(implicit_some)]\n(\n    // about the version\n    version: 1,\n    nodes: {\n        // the source\n        \"a\": (\n            kind: \"Source\", // trailing\n            params: (\n                // x is one and a half\n                x: 1.5,\n                list: [1.0, /* inside */ 2.0],\n            ),\n        ),\n        \"b\": (kind: \"Sink\", inputs: (\n            /* the wire */ v: \"a.out\")),\n    },\n    // what runs\n    outputs: [\"b\"],\n    // the end\n)\n";
        let d = Document::parse(text, "t.ron").unwrap();
        let out = d.to_ron();
        let line_of = |needle: &str| {
            out.lines()
                .position(|l| l.contains(needle))
                .unwrap_or_else(|| panic!("`{needle}` lost:\n{out}"))
        };
        // each comment on the line before its element (or in the header)
        assert!(line_of("// header one") < line_of("// header two"));
        let open = out.lines().position(|l| l == "(");
        assert_eq!(Some(line_of("#![enable(implicit_some)]") + 1), open);
        assert_eq!(line_of("// about the version") + 1, line_of("version: 1"));
        assert_eq!(line_of("// the source") + 1, line_of("\"a\": ("));
        // after code on its line: at the end of that element's line
        assert_eq!(line_of("// trailing"), line_of("kind: \"Source\","));
        assert_eq!(line_of("// x is one") + 1, line_of("x: 1.5"));
        // inside a value on one line: at the end of that value's line
        assert_eq!(line_of("/* inside */"), line_of("list: [1.0, 2.0],"));
        assert_eq!(line_of("/* the wire */") + 1, line_of("v: \"a.out\""));
        assert_eq!(line_of("// what runs") + 1, line_of("outputs:"));
        assert_eq!(line_of("// the end") + 2, out.lines().count());
        // and a second round trip changes nothing
        let again = Document::parse(&out, "t.ron").unwrap();
        assert_eq!(again.to_ron(), out);
        assert_eq!(again.comments, d.comments);
        // a node's comments go with it, and stay gone when a node of
        // that name is added again
        let mut gone = d.clone();
        let a = gone.nodes.remove(0);
        assert!(!gone.to_ron().contains("the source"));
        assert!(!gone.to_ron().contains("x is one"));
        gone.drop_stale_comments();
        gone.nodes.push(a);
        assert!(!gone.to_ron().contains("the source"));
        assert!(!gone.to_ron().contains("trailing"));
    }

    /// A field written twice (a parameter, an input, a node's `kind`, a
    /// top-level field) is an error at the second, naming the first: the
    /// RON reader keeps both, and a `--set` replaced the first while the
    /// last one ran.
    #[test]
    fn a_field_given_twice_is_an_error_at_the_second() {
        let text = r#"(
    version: 1,
    nodes: {
        "a": (kind: "Source", params: (x: 2.0, x: 5.0)),
        "b": (kind: "Sink", inputs: (v: "a.out", v: "c.out")),
        "c": (kind: "Source", kind: "Sink"),
    },
    outputs: ["b"],
    outputs: ["a"],
)"#;
        let errs = Document::parse(text, "t.ron").unwrap_err();
        let msgs: Vec<String> = errs.iter().map(|e| e.to_string()).collect();
        let has = |s: &str| msgs.iter().any(|m| m.contains(s));
        assert!(
            has("t.ron:4:48: node `a` params: `x` is given twice (first at line 4, column 40)"),
            "{msgs:?}"
        );
        assert!(has("node `b` inputs: `v` is given twice"), "{msgs:?}");
        assert!(has("node `c`: `kind` is given twice"), "{msgs:?}");
        assert!(has("the pipeline: `outputs` is given twice"), "{msgs:?}");
        assert_eq!(errs.len(), 4, "{msgs:?}");
    }

    #[test]
    fn set_overrides_and_adds() {
        let mut d = Document::parse(TEXT, "t.ron").unwrap();
        d.apply_set("a.x=2").unwrap();
        d.apply_set("a.path=out/x.png").unwrap();
        let a = d.node("a").unwrap();
        assert_eq!(a.params[0].1.value, RonValue::Int(2));
        assert_eq!(a.params[2].1.value, RonValue::Str("out/x.png".into()));
        let e = d.apply_set("aa.x=1").unwrap_err();
        assert!(e.to_string().contains("did you mean `a`"), "{e}");
        assert!(d.apply_set("nodot=1").is_err());
    }

    #[test]
    fn newer_version_is_refused() {
        let e = Document::parse("(version: 99, nodes: {})", "t.ron").unwrap_err();
        assert!(e[0].to_string().contains("newer"), "{}", e[0]);
    }

    #[test]
    fn missing_version_gives_notice() {
        let d = Document::parse("(nodes: {})", "t.ron").unwrap();
        assert_eq!(d.notices.len(), 1);
    }
}
