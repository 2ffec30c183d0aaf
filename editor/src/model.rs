//! The editor's pure-logic model: a [`Document`] with positions, typed
//! edits (parameters, wires, nodes), undo/redo and RON save/load. Nothing
//! here needs a window, so it is tested directly.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use depthgraph_graph::document::{NodeDecl, split_ref};
use depthgraph_graph::pipeline::{OutputRef, convert};
use depthgraph_graph::prelude::*;
use depthgraph_graph::ron_text::{self, Pos, RonValue, Spanned};

pub use crate::layout::COLUMN_WIDTH;

/// What undo/redo restore: the document and the node positions.
#[derive(Debug, Clone, PartialEq)]
struct Snapshot {
    doc: Document,
    positions: BTreeMap<String, [f64; 2]>,
}

/// A document being edited.
pub struct EditorModel {
    doc: Document,
    registry: Arc<Registry>,
    positions: BTreeMap<String, [f64; 2]>,
    undo: Vec<Snapshot>,
    redo: Vec<Snapshot>,
    /// Bumped on every structural or parameter change (the UI resyncs on it).
    revision: u64,
    /// Inside a gesture ([`EditorModel::begin_gesture`]): whether its first
    /// change has recorded the undo step yet.
    gesture: Option<bool>,
    /// The text of the document and positions as last read or saved:
    /// what [`EditorModel::is_modified`] compares with (the text, not the
    /// values with their file positions: a value set back to what the
    /// file says is unchanged).
    saved: String,
}

fn spanned<T>(value: T) -> Spanned<T> {
    Spanned {
        pos: Pos::default(),
        value,
    }
}

impl EditorModel {
    /// A model for `doc`; positions come from its layout section where
    /// present, else from an automatic layered layout.
    pub fn new(doc: Document, registry: Arc<Registry>) -> Self {
        let mut m = Self {
            doc,
            registry,
            positions: BTreeMap::new(),
            undo: Vec::new(),
            redo: Vec::new(),
            revision: 0,
            gesture: None,
            // replaced below, once the positions are known
            saved: String::new(),
        };
        m.positions = m.auto_layout();
        for (name, p) in &m.doc.layout {
            if m.doc.node(name).is_some() {
                m.positions.insert(name.clone(), *p);
            }
        }
        m.saved = m.to_ron();
        m
    }

    /// Whether the document or a node's position changed since it was
    /// read or last saved (an undo back to that state counts as unchanged).
    pub fn is_modified(&self) -> bool {
        self.to_ron() != self.saved
    }

    /// Parses RON text (a pipeline file) into a model.
    pub fn from_text(text: &str, file: &str, registry: Arc<Registry>) -> Result<Self, String> {
        let doc = Document::parse(text, file).map_err(|errs| {
            errs.iter()
                .map(|e| e.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        })?;
        Ok(Self::new(doc, registry))
    }

    /// Reads a pipeline file into a model.
    pub fn load(path: &Path, registry: Arc<Registry>) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        Self::from_text(&text, &path.display().to_string(), registry)
    }

    /// Writes the document (with positions in its layout section) to
    /// `path`, replacing it whole or not at all: the text goes to a
    /// temporary file beside it, is flushed to disk, and is renamed over
    /// it (a full disk or a crash mid-write leaves the old file as it was).
    pub fn save(&mut self, path: &Path) -> Result<(), String> {
        let text = self.to_ron();
        depthgraph_nodes::io::write_atomic(path, |tmp| std::fs::write(tmp, &text))
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        self.saved = text;
        Ok(())
    }

    /// [`EditorModel::save`] to a file that must not exist yet (a new
    /// document's first save): `Ok(false)`, and nothing written, when
    /// `path` exists (another program made it since the name was picked).
    pub fn save_new(&mut self, path: &Path) -> Result<bool, String> {
        let text = self.to_ron();
        match write_new(path, text.as_bytes()) {
            Ok(()) => {
                self.saved = text;
                Ok(true)
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
            Err(e) => Err(format!("cannot write {}: {e}", path.display())),
        }
    }

    /// The document as RON text, positions in the `layout` section.
    pub fn to_ron(&self) -> String {
        self.document_with_layout().to_ron()
    }

    /// A copy of the document whose layout holds the current positions.
    pub fn document_with_layout(&self) -> Document {
        let mut d = self.doc.clone();
        d.layout = self
            .positions
            .iter()
            .filter(|(k, _)| d.node(k).is_some())
            .map(|(k, v)| (k.clone(), *v))
            .collect();
        d
    }

    pub fn document(&self) -> &Document {
        &self.doc
    }
    pub fn registry(&self) -> &Arc<Registry> {
        &self.registry
    }
    pub fn revision(&self) -> u64 {
        self.revision
    }
    pub fn positions(&self) -> &BTreeMap<String, [f64; 2]> {
        &self.positions
    }
    pub fn node_names(&self) -> Vec<String> {
        self.doc
            .nodes
            .iter()
            .map(|n| n.name.value.clone())
            .collect()
    }

    /// Moves a node (not an undoable step: dragging would flood the stack).
    /// The canvas holds positions in f32: a position equal to the stored
    /// one at that precision keeps the stored value, so a file's `10.3`
    /// is not written back as `10.300000190734863` by a node never moved.
    pub fn set_position(&mut self, node: &str, pos: [f64; 2]) {
        if self.doc.node(node).is_none() {
            return;
        }
        let same = |a: [f64; 2]| a.map(|v| v as f32) == pos.map(|v| v as f32);
        if self.positions.get(node).is_some_and(|p| same(*p)) {
            return;
        }
        self.positions.insert(node.to_string(), pos);
    }

    /// The implementation (and so the schema) of a node's kind.
    pub fn node_impl(&self, node: &str) -> Result<Arc<dyn Node>, String> {
        let decl = self
            .doc
            .node(node)
            .ok_or_else(|| format!("no node `{node}`"))?;
        let kind = &decl.kind.value;
        self.registry
            .get(kind)
            .ok_or_else(|| format!("node `{node}`: unknown kind `{kind}`"))
    }

    /// The current value of a parameter: written in the document, else the default.
    pub fn param_value(&self, node: &str, name: &str) -> Result<ParamValue, String> {
        let imp = self.node_impl(node)?;
        let schema = imp.schema();
        let spec = schema
            .param(name)
            .ok_or_else(|| format!("node `{node}` has no parameter `{name}`"))?;
        let written = self
            .doc
            .node(node)
            .and_then(|d| d.params.iter().find(|(k, _)| k.value == name));
        match written {
            Some((_, v)) => convert(&spec.kind, &v.value)
                .map(|p| spec.kind.coerce(p))
                .map_err(|e| format!("node `{node}` parameter `{name}`: {e}")),
            None => Ok(spec.default.clone()),
        }
    }

    fn snapshot(&self) -> Snapshot {
        Snapshot {
            doc: self.doc.clone(),
            positions: self.positions.clone(),
        }
    }

    /// Records the current state for undo before a change (inside a
    /// gesture only before its first change).
    fn push_undo(&mut self) {
        if self.gesture != Some(true) {
            self.undo.push(self.snapshot());
            self.redo.clear();
        }
        if self.gesture.is_some() {
            self.gesture = Some(true);
        }
        self.revision += 1;
    }

    /// Starts a gesture (a drag of the pasted object, a wheel of scale
    /// steps): every change until [`end_gesture`](Self::end_gesture) is one
    /// undoable edit. A gesture already open stays open.
    pub fn begin_gesture(&mut self) {
        if self.gesture.is_none() {
            self.gesture = Some(false);
        }
    }

    /// Ends the gesture begun by [`begin_gesture`](Self::begin_gesture).
    pub fn end_gesture(&mut self) {
        self.gesture = None;
    }

    /// True between [`begin_gesture`](Self::begin_gesture) and
    /// [`end_gesture`](Self::end_gesture).
    pub fn in_gesture(&self) -> bool {
        self.gesture.is_some()
    }

    /// Sets a parameter, type- and range-checked exactly as a value written in
    /// the file (or given with `--set`) would be.
    pub fn set_param(&mut self, node: &str, name: &str, value: ParamValue) -> Result<(), String> {
        let text = value.to_ron();
        let parsed = ron_text::parse(&text)
            .map_err(|e| format!("node `{node}` parameter `{name}`: {}", e.message))?;
        self.set_param_ron(node, name, parsed.value)
    }

    /// Sets a parameter from text as `--set node.param=TEXT` reads it.
    pub fn set_param_text(&mut self, node: &str, name: &str, text: &str) -> Result<(), String> {
        let text = text.trim();
        let parsed = match ron_text::parse(text) {
            Ok(v) => v.value,
            Err(_) if !text.is_empty() => RonValue::Str(text.to_string()),
            Err(e) => return Err(format!("node `{node}` parameter `{name}`: {}", e.message)),
        };
        let parsed = match parsed {
            RonValue::Ident(s) if s != "None" => RonValue::Str(s),
            other => other,
        };
        self.set_param_ron(node, name, parsed)
    }

    fn set_param_ron(&mut self, node: &str, name: &str, value: RonValue) -> Result<(), String> {
        let imp = self.node_impl(node)?;
        let schema = imp.schema();
        let spec = schema.param(name).ok_or_else(|| {
            let names: Vec<&str> = schema.params.iter().map(|p| p.name).collect();
            format!(
                "node `{node}` ({}) has no parameter `{name}`; it has: {}",
                schema.kind,
                names.join(", ")
            )
        })?;
        let converted = convert(&spec.kind, &value)
            .map(|p| spec.kind.coerce(p))
            .map_err(|e| format!("node `{node}` parameter `{name}`: {e}"))?;
        spec.kind
            .validate(&converted)
            .map_err(|e| format!("node `{node}` parameter `{name}`: {e}"))?;
        // Store the canonical form of the value.
        let stored = ron_text::parse(&converted.to_ron())
            .map(|s| s.value)
            .unwrap_or(value);
        let unchanged = self
            .doc
            .node(node)
            .and_then(|d| d.params.iter().find(|(k, _)| k.value == name))
            .is_some_and(|(_, v)| v.value == stored);
        if unchanged {
            return Ok(());
        }
        self.push_undo();
        if let Some(decl) = self.doc.node_mut(node) {
            decl.param_files.remove(name);
            match decl.params.iter_mut().find(|(k, _)| k.value == name) {
                Some(slot) => slot.1 = spanned(stored),
                None => decl
                    .params
                    .push((spanned(name.to_string()), spanned(stored))),
            }
        }
        Ok(())
    }

    /// The type of `node.port` as an output (`output = true`) or an input.
    pub fn port_type(&self, node: &str, port: &str, output: bool) -> Result<ValueType, String> {
        let imp = self.node_impl(node)?;
        let schema = imp.schema();
        let spec = if output {
            schema.output(port)
        } else {
            schema.input(port)
        };
        spec.map(|p| p.ty).ok_or_else(|| {
            let list = if output {
                &schema.outputs
            } else {
                &schema.inputs
            };
            let names: Vec<&str> = list.iter().map(|p| p.name).collect();
            format!(
                "node `{node}` ({}) has no {} `{port}`; it has: {}",
                schema.kind,
                if output { "output" } else { "input" },
                names.join(", ")
            )
        })
    }

    /// True when `to` is `from` or depends on nothing upstream of... i.e.
    /// when a wire `from -> to` would close a cycle.
    fn reaches(&self, from: &str, to: &str) -> bool {
        // Is `from` downstream of `to` (or equal)? Walk inputs upstream from `from`.
        let mut stack = vec![from.to_string()];
        let mut seen = std::collections::BTreeSet::new();
        while let Some(n) = stack.pop() {
            if n == to {
                return true;
            }
            if !seen.insert(n.clone()) {
                continue;
            }
            if let Some(d) = self.doc.node(&n) {
                for (_, src) in &d.inputs {
                    if let Some((up, _)) = split_ref(&src.value) {
                        stack.push(up.to_string());
                    }
                }
            }
        }
        false
    }

    /// Wires `from_node.from_port` into `to_node.to_port` (replacing what fed
    /// that input), or says why not; the document is unchanged on refusal.
    pub fn try_connect(
        &mut self,
        from_node: &str,
        from_port: &str,
        to_node: &str,
        to_port: &str,
    ) -> Result<(), String> {
        let out_ty = self.port_type(from_node, from_port, true)?;
        let in_ty = self.port_type(to_node, to_port, false)?;
        if !out_ty.connects_to(in_ty) {
            return Err(format!(
                "cannot connect `{from_node}.{from_port}` ({}) to `{to_node}.{to_port}` ({}): \
                 a {} output does not fit a {} input",
                out_ty.name(),
                in_ty.name(),
                out_ty.name(),
                in_ty.name()
            ));
        }
        if self.reaches(from_node, to_node) {
            return Err(format!(
                "cannot connect `{from_node}.{from_port}` to `{to_node}.{to_port}`: \
                 it would make a cycle"
            ));
        }
        let src = format!("{from_node}.{from_port}");
        let already = self
            .doc
            .node(to_node)
            .and_then(|d| d.inputs.iter().find(|(k, _)| k.value == to_port))
            .is_some_and(|(_, v)| v.value == src);
        if already {
            return Ok(());
        }
        self.push_undo();
        if let Some(decl) = self.doc.node_mut(to_node) {
            match decl.inputs.iter_mut().find(|(k, _)| k.value == to_port) {
                Some(slot) => slot.1 = spanned(src),
                None => decl
                    .inputs
                    .push((spanned(to_port.to_string()), spanned(src))),
            }
        }
        Ok(())
    }

    /// Removes the wire feeding `to_node.to_port`.
    pub fn disconnect(&mut self, to_node: &str, to_port: &str) -> Result<(), String> {
        let decl = self
            .doc
            .node(to_node)
            .ok_or_else(|| format!("no node `{to_node}`"))?;
        if !decl.inputs.iter().any(|(k, _)| k.value == to_port) {
            return Err(format!("input `{to_node}.{to_port}` is not connected"));
        }
        self.push_undo();
        if let Some(decl) = self.doc.node_mut(to_node) {
            decl.inputs.retain(|(k, _)| k.value != to_port);
        }
        self.doc.drop_stale_comments();
        Ok(())
    }

    /// `node` and every node upstream of it, each once, breadth first over
    /// the inputs in schema order: where the editor looks for the photograph
    /// under a mask and for the `Paste` a drag moves.
    pub fn upstream(&self, node: &str) -> Vec<String> {
        let mut order = Vec::new();
        let mut seen = std::collections::BTreeSet::new();
        let mut queue = std::collections::VecDeque::from([node.to_string()]);
        while let Some(n) = queue.pop_front() {
            if !seen.insert(n.clone()) {
                continue;
            }
            if let Ok(imp) = self.node_impl(&n) {
                for input in &imp.schema().inputs {
                    if let Some((src, _)) = self.input_source(&n, input.name) {
                        queue.push_back(src);
                    }
                }
                order.push(n);
            }
        }
        order
    }

    /// The source (`"node.port"`) feeding `node.input`, if wired.
    pub fn input_source(&self, node: &str, input: &str) -> Option<(String, String)> {
        let d = self.doc.node(node)?;
        let (_, src) = d.inputs.iter().find(|(k, _)| k.value == input)?;
        split_ref(&src.value).map(|(n, p)| (n.to_string(), p.to_string()))
    }

    /// Adds a node of `kind` with default parameters; returns its new name.
    pub fn add_node(&mut self, kind: &str) -> Result<String, String> {
        if self.registry.get(kind).is_none() {
            let hint = self
                .registry
                .suggest(kind)
                .map(|s| format!(" (did you mean `{s}`?)"))
                .unwrap_or_default();
            return Err(format!("unknown node kind `{kind}`{hint}"));
        }
        let base: String = kind
            .chars()
            .enumerate()
            .flat_map(|(i, c)| {
                let lower = c.to_ascii_lowercase();
                if c.is_ascii_uppercase() && i > 0 {
                    vec!['_', lower]
                } else {
                    vec![lower]
                }
            })
            .collect();
        let mut name = base.clone();
        let mut k = 2;
        while self.doc.node(&name).is_some() {
            name = format!("{base}_{k}");
            k += 1;
        }
        self.push_undo();
        let max_x = self.positions.values().map(|p| p[0]).fold(0.0, f64::max);
        self.doc.nodes.push(NodeDecl::new(&name, kind));
        self.positions
            .insert(name.clone(), [max_x + COLUMN_WIDTH, 0.0]);
        Ok(name)
    }

    /// Removes a node, its wires and its mentions in outputs and layout.
    pub fn remove_node(&mut self, node: &str) -> Result<(), String> {
        if self.doc.node(node).is_none() {
            return Err(format!("no node `{node}`"));
        }
        self.push_undo();
        self.doc.nodes.retain(|n| n.name.value != node);
        for d in &mut self.doc.nodes {
            d.inputs
                .retain(|(_, src)| split_ref(&src.value).is_none_or(|(n, _)| n != node));
        }
        self.doc
            .outputs
            .retain(|o| o.value != node && split_ref(&o.value).is_none_or(|(n, _)| n != node));
        self.doc.layout.remove(node);
        self.positions.remove(node);
        // its comments (and those of the wires to it) go with it: a node
        // added later under its name does not inherit them
        self.doc.drop_stale_comments();
        Ok(())
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }
    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Restores the state before the last change; false when there is none.
    pub fn undo(&mut self) -> bool {
        self.gesture = None;
        match self.undo.pop() {
            Some(s) => {
                let now = self.snapshot();
                self.redo.push(now);
                self.restore(s);
                true
            }
            None => false,
        }
    }

    /// Re-applies the last undone change; false when there is none.
    pub fn redo(&mut self) -> bool {
        self.gesture = None;
        match self.redo.pop() {
            Some(s) => {
                let now = self.snapshot();
                self.undo.push(now);
                self.restore(s);
                true
            }
            None => false,
        }
    }

    fn restore(&mut self, s: Snapshot) {
        self.doc = s.doc;
        self.positions = s.positions;
        self.revision += 1;
    }

    /// Type-checks the document (frame 0 of a pipeline with `{frame}`
    /// placeholders: the editor shows the first frame of a sequence).
    pub fn check(&self) -> Result<Pipeline, Vec<CheckError>> {
        Pipeline::check(&self.doc.for_frame(0)?, &self.registry)
    }

    /// The checked pipeline requesting all outputs of `targets` (node names)
    /// instead of the document's outputs; `None` keeps the document's.
    pub fn pipeline_for(&self, targets: Option<&[String]>) -> Result<Pipeline, Vec<String>> {
        let mut p = self
            .check()
            .map_err(|errs| errs.iter().map(|e| e.to_string()).collect::<Vec<_>>())?;
        if let Some(targets) = targets {
            let mut outs = Vec::new();
            for t in targets {
                match p.index_of(t) {
                    Some(i) => outs.push(OutputRef {
                        node: i,
                        port: None,
                    }),
                    None => return Err(vec![format!("no node `{t}` to evaluate")]),
                }
            }
            p.outputs = outs;
        }
        Ok(p)
    }

    /// The automatic layered layout ([`crate::layout::best_layered`]):
    /// column = longest path from a source, rows ordered and placed to keep
    /// wires short, each node given the height its ports need.
    pub fn auto_layout(&self) -> BTreeMap<String, [f64; 2]> {
        self.layout_with(None)
    }

    /// [`auto_layout`](Self::auto_layout) with explicit layout parameters
    /// (`None`: the best of several, [`crate::layout::best_layered`]).
    pub fn layout_with(
        &self,
        params: Option<&crate::layout::LayoutParams>,
    ) -> BTreeMap<String, [f64; 2]> {
        let names = self.node_names();
        let index: BTreeMap<&str, usize> = names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), i))
            .collect();
        let mut edges = Vec::new();
        for (to, d) in self.doc.nodes.iter().enumerate() {
            for (_, src) in &d.inputs {
                if let Some((up, _)) = split_ref(&src.value)
                    && let Some(&from) = index.get(up)
                    && from != to
                {
                    edges.push((from, to));
                }
            }
        }
        let heights: Vec<f64> = names
            .iter()
            .map(|n| {
                let ports = self.node_impl(n).map_or(1, |imp| {
                    let s = imp.schema();
                    s.inputs.len().max(s.outputs.len())
                });
                crate::layout::node_height(ports)
            })
            .collect();
        let pos = match params {
            Some(p) => crate::layout::layered(names.len(), &edges, &heights, p),
            None => crate::layout::best_layered(names.len(), &edges, &heights),
        };
        names.into_iter().zip(pos).collect()
    }
}

/// Writes `bytes` to a new file `path` (`AlreadyExists` when there is
/// one, which is left untouched); a failed write removes the part written.
fn write_new(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)?;
    let written = f.write_all(bytes).and_then(|()| f.sync_all());
    if written.is_err() {
        drop(f);
        let _ = std::fs::remove_file(path);
    }
    written
}
