//! The eframe application: an egui-snarl canvas, a parameter side panel, a
//! preview pane, a check-error panel and Save / Undo / Redo.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use depthgraph_graph::params::{ParamKind, ParamValue};
use depthgraph_graph::prelude::{Status, Trace, Value, ValueType};
use eframe::egui::{self, Color32, ColorImage, TextureHandle, TextureOptions};
use egui_snarl::ui::{PinInfo, SnarlStyle, SnarlViewer};
use egui_snarl::{InPin, InPinId, NodeId, OutPin, OutPinId, Snarl};

use crate::eval::{Evaluator, NodeProgress};
use crate::model::EditorModel;
use crate::preview::{self, DepthLegend, ImageFrame};
use crate::{focus, placement};

/// Pin colour of a value type.
pub fn type_color(ty: ValueType) -> Color32 {
    match ty {
        ValueType::Color => Color32::from_rgb(230, 120, 60),
        ValueType::Depth => Color32::from_rgb(70, 140, 230),
        ValueType::Mask => Color32::from_rgb(220, 220, 220),
        ValueType::Confidence => Color32::from_rgb(160, 200, 120),
        ValueType::Normals => Color32::from_rgb(170, 110, 220),
        ValueType::Labels => Color32::from_rgb(230, 200, 60),
        ValueType::Intrinsics => Color32::from_rgb(120, 120, 120),
        ValueType::PointCloud => Color32::from_rgb(60, 200, 200),
        ValueType::Mesh => Color32::from_rgb(40, 170, 120),
        ValueType::ExposureStack => Color32::from_rgb(230, 90, 160),
        ValueType::Vpls => Color32::from_rgb(255, 170, 60),
        ValueType::Scalar => Color32::from_rgb(250, 250, 120),
        ValueType::File => Color32::from_rgb(150, 150, 190),
        ValueType::Extension(_) => Color32::from_rgb(200, 200, 200),
    }
}

/// Edit buffers of the parameter panel (text that is not yet a valid value).
#[derive(Default)]
pub struct PanelState {
    pub edits: BTreeMap<String, String>,
    pub error: Option<String>,
    /// The file browser open for a path parameter: "node.param" and the folder shown.
    pub browse: Option<(String, PathBuf)>,
    /// Nodes whose sliders update on release (slow nodes).
    pub on_release: std::collections::BTreeSet<String>,
    /// A slider being dragged on such a node: "node.param" and the value shown.
    pub dragging: BTreeMap<String, f64>,
}

/// The entries of `dir` for the file browser: folders first, then files,
/// each sorted by name; hidden entries left out. Unreadable folders give
/// the error text.
pub fn list_dir(dir: &Path) -> Result<Vec<(String, bool)>, String> {
    let rd = std::fs::read_dir(dir).map_err(|e| format!("cannot list {}: {e}", dir.display()))?;
    let mut entries: Vec<(String, bool)> = rd
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            (!name.starts_with('.')).then(|| (name, e.path().is_dir()))
        })
        .collect();
    entries.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    Ok(entries)
}

/// The file browser of a path parameter (a window): navigate folders,
/// click a file to pick it. Returns the picked path.
fn file_browser(ui: &mut egui::Ui, state: &mut PanelState) -> Option<String> {
    let (key, dir) = state.browse.clone()?;
    let mut open = true;
    let mut picked = None;
    let mut go = None;
    egui::Window::new(format!("choose {key}"))
        .open(&mut open)
        .default_size([360.0, 420.0])
        .show(ui.ctx(), |ui| {
            ui.label(dir.display().to_string());
            if ui.button("..").clicked() {
                go = Some(dir.join(".."));
            }
            egui::ScrollArea::vertical().show(ui, |ui| match list_dir(&dir) {
                Ok(entries) => {
                    for (name, is_dir) in entries {
                        let text = if is_dir {
                            format!("{name}/")
                        } else {
                            name.clone()
                        };
                        if ui.selectable_label(false, text).clicked() {
                            if is_dir {
                                go = Some(dir.join(&name));
                            } else {
                                picked = Some(dir.join(&name).display().to_string());
                            }
                        }
                    }
                }
                Err(e) => {
                    ui.colored_label(Color32::RED, e);
                }
            });
        });
    if let Some(d) = go {
        state.browse = Some((key, d));
    }
    if picked.is_some() || !open {
        state.browse = None;
    }
    picked
}

/// Parameter widgets of `node`, generated from its kind's schema, under its
/// kind's documentation. Changes go through [`EditorModel::set_param`]; a
/// refusal is kept in `state.error`.
pub fn param_panel(ui: &mut egui::Ui, model: &mut EditorModel, node: &str, state: &mut PanelState) {
    let imp = match model.node_impl(node) {
        Ok(i) => i,
        Err(e) => {
            ui.colored_label(Color32::RED, e);
            return;
        }
    };
    let schema = imp.schema();
    ui.heading(node);
    ui.label(format!("kind: {}", schema.kind));
    let (first, rest) = schema.doc.split_once('\n').unwrap_or((schema.doc, ""));
    if !first.is_empty() {
        ui.add(egui::Label::new(egui::RichText::new(first).small()).wrap());
    }
    if !rest.trim().is_empty() {
        egui::CollapsingHeader::new("more about this node")
            .id_salt(("doc", node))
            .show(ui, |ui| {
                ui.add(egui::Label::new(egui::RichText::new(rest.trim()).small()).wrap());
            });
    }
    let mut release = state.on_release.contains(node);
    if ui
        .checkbox(&mut release, "update on release")
        .on_hover_text(
            "sliders of this node re-run it when let go, not while dragged (for slow nodes)",
        )
        .changed()
    {
        if release {
            state.on_release.insert(node.to_string());
        } else {
            state.on_release.remove(node);
        }
    }
    ui.separator();
    for spec in &schema.params {
        param_row(ui, model, node, spec, state, "panel");
    }
    if let Some(e) = &state.error {
        ui.colored_label(Color32::RED, e);
    }
}

/// The widget of one parameter (`salt` tells apart two widgets of the same
/// parameter in one frame, e.g. the side panel's and the preview's).
pub fn param_row(
    ui: &mut egui::Ui,
    model: &mut EditorModel,
    node: &str,
    spec: &depthgraph_graph::params::ParamSpec,
    state: &mut PanelState,
    salt: &str,
) {
    let name = spec.name;
    let current = match model.param_value(node, name) {
        Ok(v) => v,
        Err(e) => {
            ui.colored_label(Color32::RED, e);
            spec.default.clone()
        }
    };
    let on_release = state.on_release.contains(node);
    let key = format!("{node}.{name}");
    let mut new_value: Option<ParamValue> = None;
    let mut new_text: Option<String> = None;
    ui.horizontal(|ui| {
        // A checkbox carries its own name (clickable); others get a label.
        let label_id = if matches!(spec.kind, ParamKind::Bool) {
            egui::Id::NULL
        } else {
            ui.label(name).on_hover_text(spec.doc).id
        };
        match (&spec.kind, &current) {
            (ParamKind::Float { min, max }, ParamValue::Float(x)) => {
                let mut v = state.dragging.get(&key).copied().unwrap_or(*x);
                let r = if min.is_finite() && max.is_finite() {
                    ui.add(
                        egui::Slider::new(&mut v, *min..=*max)
                            .logarithmic(*min >= 0.0 && *max / min.max(1e-9) > 1e3),
                    )
                } else {
                    ui.add(egui::DragValue::new(&mut v).speed(0.01))
                };
                let r = r.labelled_by(label_id);
                if let Some(v) = released(state, &key, on_release, &r, v) {
                    new_value = Some(ParamValue::Float(v));
                }
            }
            (ParamKind::Int { min, max }, ParamValue::Int(x)) => {
                let mut v = state.dragging.get(&key).map_or(*x, |f| f.round() as i64);
                let r = if max.saturating_sub(*min) <= 100_000 {
                    ui.add(
                        egui::Slider::new(&mut v, *min..=*max)
                            .logarithmic(*min >= 0 && max.saturating_sub(*min) > 1000),
                    )
                } else {
                    ui.add(egui::DragValue::new(&mut v).range(*min..=*max))
                };
                let r = r.labelled_by(label_id);
                if let Some(v) = released(state, &key, on_release, &r, v as f64) {
                    new_value = Some(ParamValue::Int(v.round() as i64));
                }
            }
            (ParamKind::Bool, ParamValue::Bool(b)) => {
                let mut v = *b;
                if ui.checkbox(&mut v, name).on_hover_text(spec.doc).changed() {
                    new_value = Some(ParamValue::Bool(v));
                }
            }
            (ParamKind::Choice(choices), ParamValue::Text(s)) => {
                let mut v = s.clone();
                egui::ComboBox::from_id_salt(("param", salt, node, name))
                    .selected_text(v.clone())
                    .show_ui(ui, |ui| {
                        for c in choices.iter() {
                            ui.selectable_value(&mut v, c.to_string(), *c);
                        }
                    })
                    .response
                    .labelled_by(label_id);
                if v != *s {
                    new_value = Some(ParamValue::Text(v));
                }
            }
            (
                ParamKind::Text | ParamKind::InputPath | ParamKind::OutputPath,
                ParamValue::Text(s),
            ) => {
                let mut v = s.clone();
                if ui
                    .text_edit_singleline(&mut v)
                    .labelled_by(label_id)
                    .changed()
                {
                    new_value = Some(ParamValue::Text(v));
                }
                if matches!(spec.kind, ParamKind::InputPath | ParamKind::OutputPath)
                    && ui.button("…").on_hover_text("choose a file").clicked()
                {
                    // Start in the folder of the current value (or the working directory).
                    let start = Path::new(s.as_str())
                        .parent()
                        .filter(|p| p.is_dir())
                        .map(Path::to_path_buf)
                        .unwrap_or_else(|| PathBuf::from("."));
                    state.browse = Some((key.clone(), start));
                }
            }
            _ => {
                // Points, Floats, Vec3: edited as RON text, applied on Enter.
                let buf = state
                    .edits
                    .entry(key.clone())
                    .or_insert_with(|| current.to_ron());
                let r = ui.text_edit_singleline(buf).labelled_by(label_id);
                if r.lost_focus() {
                    new_text = Some(buf.clone());
                    state.edits.remove(&key);
                }
            }
        }
    });
    if state.browse.as_ref().is_some_and(|(k, _)| *k == key) {
        if let Some(path) = file_browser(ui, state) {
            new_value = Some(ParamValue::Text(path));
        }
    }
    let result = match (new_value, new_text) {
        (Some(v), _) => Some(model.set_param(node, name, v)),
        (None, Some(t)) => Some(model.set_param_text(node, name, &t)),
        _ => None,
    };
    match result {
        Some(Err(e)) => state.error = Some(e),
        Some(Ok(())) => state.error = None,
        None => {}
    }
}

/// The value a slider hands to the document this frame: every change, or
/// with `on_release` only when the drag ends (the value shown meanwhile is
/// kept in `state.dragging`); a click or a key changes it at once.
fn released(
    state: &mut PanelState,
    key: &str,
    on_release: bool,
    r: &egui::Response,
    v: f64,
) -> Option<f64> {
    if !on_release {
        return r.changed().then_some(v);
    }
    if r.drag_stopped() {
        state.dragging.remove(key);
        return Some(v);
    }
    if r.dragged() {
        state.dragging.insert(key.to_string(), v);
        return None;
    }
    state.dragging.remove(key);
    r.changed().then_some(v)
}

/// What the canvas asks the app to do after drawing.
#[derive(Default)]
struct CanvasActions {
    select: Option<String>,
    message: Option<String>,
    /// A node's cancel button was pressed.
    cancel: bool,
}

/// The header colour of a pipeline stage (dark enough for light text).
pub fn stage_color(stage: &str) -> Color32 {
    match stage {
        "input/output" => Color32::from_rgb(70, 70, 90),
        "simulation" => Color32::from_rgb(60, 90, 60),
        "camera" => Color32::from_rgb(110, 70, 40),
        "depth" => Color32::from_rgb(40, 70, 120),
        "image" => Color32::from_rgb(90, 90, 50),
        "selection" => Color32::from_rgb(110, 50, 90),
        "relighting" => Color32::from_rgb(120, 90, 20),
        _ => Color32::from_rgb(70, 70, 70),
    }
}

/// The smallest canvas zoom: node titles (14 pt text) stay at least 12 px
/// high; a graph larger than the window is scrolled instead.
pub const MIN_CANVAS_SCALE: f32 = 12.0 / 14.0;

struct GraphViewer<'a> {
    model: &'a mut EditorModel,
    trace: Option<&'a Trace>,
    selected: Option<&'a str>,
    /// Check errors, by the node they concern (`None`: the whole file).
    errors: &'a [(Option<String>, String)],
    /// Filter text of the add-node menu.
    search: &'a mut String,
    /// Nodes of the run in flight that started and have not finished.
    running: &'a BTreeMap<String, NodeProgress>,
    /// Each node's time when it last ran (ms).
    last_ms: &'a BTreeMap<String, f64>,
    /// Nodes that were running when the run was cancelled.
    cancelled: &'a std::collections::BTreeSet<String>,
    /// The pipeline stage of each node kind.
    stages: &'a BTreeMap<String, &'static str>,
    actions: CanvasActions,
}

impl GraphViewer<'_> {
    fn ports(&self, node: &str, output: bool) -> Vec<(&'static str, ValueType)> {
        match self.model.node_impl(node) {
            Ok(imp) => {
                let s = imp.schema();
                let list = if output { &s.outputs } else { &s.inputs };
                list.iter().map(|p| (p.name, p.ty)).collect()
            }
            Err(_) => Vec::new(),
        }
    }

    /// Draws port `index` of `node` (its name, a pin coloured by its type).
    fn pin(&self, ui: &mut egui::Ui, node: &str, output: bool, index: usize) -> PinInfo {
        match self.ports(node, output).get(index) {
            Some((port, ty)) => {
                ui.label(*port);
                PinInfo::circle().with_fill(type_color(*ty))
            }
            None => PinInfo::circle(),
        }
    }

    fn report(&mut self, r: Result<(), String>) {
        if let Err(e) = r {
            self.actions.message = Some(e);
        }
    }
}

impl SnarlViewer<String> for GraphViewer<'_> {
    fn title(&mut self, node: &String) -> String {
        let kind = self
            .model
            .document()
            .node(node)
            .map(|d| d.kind.value.clone())
            .unwrap_or_default();
        format!("{node} ({kind})")
    }

    fn inputs(&mut self, node: &String) -> usize {
        self.ports(node, false).len()
    }

    fn outputs(&mut self, node: &String) -> usize {
        self.ports(node, true).len()
    }

    fn show_input(
        &mut self,
        pin: &InPin,
        ui: &mut egui::Ui,
        snarl: &mut Snarl<String>,
    ) -> impl egui_snarl::ui::SnarlPin + 'static {
        let name = snarl.get_node(pin.id.node).cloned().unwrap_or_default();
        self.pin(ui, &name, false, pin.id.input)
    }

    fn show_output(
        &mut self,
        pin: &OutPin,
        ui: &mut egui::Ui,
        snarl: &mut Snarl<String>,
    ) -> impl egui_snarl::ui::SnarlPin + 'static {
        let name = snarl.get_node(pin.id.node).cloned().unwrap_or_default();
        self.pin(ui, &name, true, pin.id.output)
    }

    fn has_body(&mut self, _node: &String) -> bool {
        true
    }

    fn show_body(
        &mut self,
        node: NodeId,
        _inputs: &[InPin],
        _outputs: &[OutPin],
        ui: &mut egui::Ui,
        snarl: &mut Snarl<String>,
    ) {
        let name = snarl.get_node(node).cloned().unwrap_or_default();
        ui.vertical(|ui| {
            if let Some(p) = self.running.get(&name) {
                let secs = p.started.elapsed().as_secs_f32();
                let bar = egui::ProgressBar::new(p.fraction)
                    .desired_width(150.0)
                    .text(format!("{:.0} % · {secs:.1} s", p.fraction * 100.0));
                // A node that reports nothing but its start gets a moving bar.
                ui.add(if p.fraction <= 0.0 {
                    bar.animate(true)
                } else {
                    bar
                });
                if ui
                    .button("cancel")
                    .on_hover_text("stop the run in flight")
                    .clicked()
                {
                    self.actions.cancel = true;
                }
            } else if self.cancelled.contains(&name) {
                ui.colored_label(Color32::from_rgb(255, 170, 60), "cancelled");
            } else if let Some(rec) = self.trace.and_then(|t| t.get(&name)) {
                let color = match rec.status {
                    Status::Ran => Color32::LIGHT_GREEN,
                    Status::Cached => Color32::LIGHT_BLUE,
                    Status::Passthrough => Color32::YELLOW,
                    Status::NotNeeded => Color32::GRAY,
                };
                ui.add(
                    egui::Label::new(
                        egui::RichText::new(format!("{} {:.1} ms", rec.status.as_str(), rec.ms))
                            .color(color),
                    )
                    .extend(),
                );
                if let Some(reason) = &rec.reason {
                    ui.small(reason.as_str());
                }
            }
            let ran_now = self
                .trace
                .and_then(|t| t.get(&name))
                .is_some_and(|r| matches!(r.status, Status::Ran | Status::Passthrough));
            if let (Some(ms), false) = (self.last_ms.get(&name), ran_now) {
                ui.small(format!("last run {ms:.1} ms"));
            }
            for (_, e) in self
                .errors
                .iter()
                .filter(|(n, _)| n.as_deref() == Some(name.as_str()))
            {
                ui.colored_label(Color32::RED, e.as_str())
                    .on_hover_text(e.as_str());
            }
            let selected = self.selected == Some(name.as_str());
            if ui.selectable_label(selected, "preview").clicked() {
                self.actions.select = Some(name.clone());
            }
        });
    }

    fn connect(&mut self, from: &OutPin, to: &InPin, snarl: &mut Snarl<String>) {
        let (Some(src), Some(dst)) = (
            snarl.get_node(from.id.node).cloned(),
            snarl.get_node(to.id.node).cloned(),
        ) else {
            return;
        };
        let out_port = self.ports(&src, true).get(from.id.output).map(|p| p.0);
        let in_port = self.ports(&dst, false).get(to.id.input).map(|p| p.0);
        if let (Some(op), Some(ip)) = (out_port, in_port) {
            let r = self.model.try_connect(&src, op, &dst, ip);
            self.report(r);
        }
    }

    fn disconnect(&mut self, _from: &OutPin, to: &InPin, snarl: &mut Snarl<String>) {
        self.drop_inputs(to, snarl);
    }

    fn drop_inputs(&mut self, pin: &InPin, snarl: &mut Snarl<String>) {
        let Some(dst) = snarl.get_node(pin.id.node).cloned() else {
            return;
        };
        if let Some((ip, _)) = self.ports(&dst, false).get(pin.id.input).copied() {
            if self.model.input_source(&dst, ip).is_some() {
                let r = self.model.disconnect(&dst, ip);
                self.report(r);
            }
        }
    }

    fn drop_outputs(&mut self, pin: &OutPin, snarl: &mut Snarl<String>) {
        for remote in &pin.remotes {
            let Some(dst) = snarl.get_node(remote.node).cloned() else {
                continue;
            };
            if let Some((ip, _)) = self.ports(&dst, false).get(remote.input).copied() {
                let r = self.model.disconnect(&dst, ip);
                self.report(r);
            }
        }
    }

    fn header_frame(
        &mut self,
        default: egui::Frame,
        node: NodeId,
        _inputs: &[InPin],
        _outputs: &[OutPin],
        snarl: &Snarl<String>,
    ) -> egui::Frame {
        let stage = snarl
            .get_node(node)
            .and_then(|n| self.model.document().node(n))
            .and_then(|d| self.stages.get(&d.kind.value));
        match stage {
            Some(stage) => default.fill(stage_color(stage)),
            None => default,
        }
    }

    fn has_graph_menu(&mut self, _pos: egui::Pos2, _snarl: &mut Snarl<String>) -> bool {
        true
    }

    fn show_graph_menu(&mut self, pos: egui::Pos2, ui: &mut egui::Ui, _snarl: &mut Snarl<String>) {
        ui.label("Add node");
        ui.text_edit_singleline(self.search)
            .on_hover_text("filter the node kinds by name");
        let needle = self.search.to_lowercase();
        let kinds: Vec<&'static str> = self
            .model
            .registry()
            .kinds()
            .filter(|k| k.to_lowercase().contains(&needle))
            .collect();
        egui::ScrollArea::vertical()
            .max_height(300.0)
            .show(ui, |ui| {
                for k in kinds {
                    if ui.button(k).clicked() {
                        match self.model.add_node(k) {
                            Ok(name) => {
                                self.search.clear();
                                self.model
                                    .set_position(&name, [f64::from(pos.x), f64::from(pos.y)]);
                                self.actions.select = Some(name);
                            }
                            Err(e) => self.actions.message = Some(e),
                        }
                        ui.close();
                    }
                }
            });
    }

    fn has_node_menu(&mut self, _node: &String) -> bool {
        true
    }

    fn show_node_menu(
        &mut self,
        node: NodeId,
        _inputs: &[InPin],
        _outputs: &[OutPin],
        ui: &mut egui::Ui,
        snarl: &mut Snarl<String>,
    ) {
        let name = snarl.get_node(node).cloned().unwrap_or_default();
        if ui.button("Remove").clicked() {
            let r = self.model.remove_node(&name);
            self.report(r);
            ui.close();
        }
    }
}

/// Screenshot mode (`depthgraph-editor FILE --screenshot OUT.png`): select a
/// node, wait until its preview is on screen, write the window to a PNG and
/// close. Used by the Xvfb test and for the README's picture.
pub struct AutoShot {
    /// Where the PNG goes.
    pub path: PathBuf,
    /// The node whose preview to show (none: just the canvas).
    pub select: Option<String>,
    /// Give up (and report an error) after this long.
    pub timeout: Duration,
    /// The outcome, filled in before the window closes.
    pub outcome: Arc<Mutex<Option<Result<(), String>>>>,
    /// Move the pasted object of the selected preview by this many image
    /// pixels once it is shown (as a drag does), then wait for the result.
    pub drag: Option<[f64; 2]>,
}

struct ShotState {
    cfg: AutoShot,
    started: Instant,
    ready_frames: u32,
    requested: bool,
    done: bool,
    /// The `drag` has been applied.
    dragged: bool,
}

/// Writes an egui screenshot as an RGBA PNG.
pub fn save_png(image: &ColorImage, path: &Path) -> Result<(), String> {
    let [w, h] = image.size;
    let bytes: Vec<u8> = image.pixels.iter().flat_map(|c| c.to_array()).collect();
    let (w32, h32) = (
        u32::try_from(w).map_err(|_| format!("screenshot {w} px wide is too large"))?,
        u32::try_from(h).map_err(|_| format!("screenshot {h} px high is too large"))?,
    );
    image::save_buffer(path, &bytes, w32, h32, image::ExtendedColorType::Rgba8)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// The first Color output upstream of `node` (breadth first over its
/// inputs), as a "node.port" key: the photograph a mask is drawn over.
pub fn upstream_color(model: &EditorModel, node: &str) -> Option<String> {
    let mut queue = std::collections::VecDeque::from([node.to_string()]);
    let mut seen = std::collections::BTreeSet::new();
    while let Some(n) = queue.pop_front() {
        if !seen.insert(n.clone()) {
            continue;
        }
        let Ok(imp) = model.node_impl(&n) else {
            continue;
        };
        for input in &imp.schema().inputs {
            let Some((src, port)) = model.input_source(&n, input.name) else {
                continue;
            };
            if model.port_type(&src, &port, true) == Ok(ValueType::Color) {
                return Some(format!("{src}.{port}"));
            }
            queue.push_back(src);
        }
    }
    None
}

/// The editor window's state.
pub struct EditorApp {
    pub model: EditorModel,
    path: PathBuf,
    snarl: Snarl<String>,
    synced_revision: Option<u64>,
    selected: Option<String>,
    panel: PanelState,
    evaluator: Option<Evaluator>,
    requested: Option<(u64, Option<String>)>,
    /// When the request in flight was started.
    request_started: Option<Instant>,
    /// Time from the last request to its preview on screen.
    pub last_latency_ms: Option<f64>,
    trace: Option<Trace>,
    values: BTreeMap<String, Value>,
    /// The selected node's output shown in the preview.
    preview_port: Option<String>,
    /// The Color output drawn under the selected node's masks.
    background: Option<String>,
    texture: Option<TextureHandle>,
    legend: Option<DepthLegend>,
    preview_hash: Option<u64>,
    /// Where the preview picture was drawn last frame.
    image_frame: Option<ImageFrame>,
    /// Preview zoom (screen points per pixel); `None` fits the panel.
    zoom: Option<f32>,
    check_errors: Vec<(Option<String>, String)>,
    eval_error: Option<String>,
    message: Option<String>,
    search: String,
    notify_set: bool,
    shot: Option<ShotState>,
    /// Each node kind's pipeline stage (the canvas's header colours).
    stages: BTreeMap<String, &'static str>,
    /// Each node's time when it last ran (ms).
    last_ms: BTreeMap<String, f64>,
    /// Nodes that were running when the last run was cancelled.
    cancelled: std::collections::BTreeSet<String>,
    /// The running nodes of the request in flight (refreshed each frame).
    running: BTreeMap<String, NodeProgress>,
    /// The node whose picture the preview texture shows.
    texture_node: Option<String>,
    /// The document revision of the newest request and of the result shown.
    request_revision: u64,
    shown_revision: Option<u64>,
    /// The `Paste` node a drag on the selected node's preview moves.
    paste: Option<String>,
    /// The depth ("node.port") under a focus preview (Refocus's input).
    focus_depth: Option<String>,
    /// The placement drag in progress.
    place: Option<PlaceDrag>,
    /// A Ctrl + wheel scale gesture is open: when the wheel last moved.
    wheel_gesture: Option<Instant>,
}

/// A drag on the preview that places the pasted object.
#[derive(Debug, Clone, Copy)]
struct PlaceDrag {
    /// Where the pointer was pressed (screen).
    origin: egui::Pos2,
    what: PlaceWhat,
}

#[derive(Debug, Clone, Copy)]
enum PlaceWhat {
    /// Moving the object: `Paste.target_pixel` when the drag began.
    Move { start: [f64; 2] },
    /// Turning it with the ring: `Paste.rotation_deg` when the drag began.
    Rotate { start: [f64; 3] },
}

impl EditorApp {
    /// An editor for `model` (read from `path`); sinks write under `out`
    /// in the working directory, as the CLI's default `--out`.
    pub fn new(model: EditorModel, path: PathBuf) -> Self {
        Self::with_out_dir(model, path, PathBuf::from("out"))
    }

    /// [`EditorApp::new`] with the folder that sinks write under.
    pub fn with_out_dir(model: EditorModel, path: PathBuf, out_dir: PathBuf) -> Self {
        let (evaluator, message) =
            match Evaluator::new(depthgraph_graph::prelude::EngineOptions::default(), out_dir) {
                Ok(e) => (Some(e), None),
                Err(e) => (None, Some(e)),
            };
        Self {
            model,
            path,
            snarl: Snarl::new(),
            synced_revision: None,
            selected: None,
            panel: PanelState::default(),
            evaluator,
            requested: None,
            request_started: None,
            last_latency_ms: None,
            trace: None,
            values: BTreeMap::new(),
            preview_port: None,
            background: None,
            texture: None,
            legend: None,
            preview_hash: None,
            image_frame: None,
            zoom: None,
            check_errors: Vec::new(),
            eval_error: None,
            message,
            search: String::new(),
            notify_set: false,
            shot: None,
            stages: depthgraph_nodes::stages()
                .map(|list| {
                    list.into_iter()
                        .flat_map(|(stage, kinds)| {
                            kinds.into_iter().map(move |k| (k.to_string(), stage))
                        })
                        .collect()
                })
                .unwrap_or_default(),
            last_ms: BTreeMap::new(),
            cancelled: std::collections::BTreeSet::new(),
            running: BTreeMap::new(),
            texture_node: None,
            request_revision: 0,
            shown_revision: None,
            paste: None,
            focus_depth: None,
            place: None,
            wheel_gesture: None,
        }
    }

    /// Runs in screenshot mode (see [`AutoShot`]).
    pub fn with_screenshot(mut self, cfg: AutoShot) -> Self {
        self.selected = cfg.select.clone();
        self.shot = Some(ShotState {
            cfg,
            started: Instant::now(),
            ready_frames: 0,
            requested: false,
            done: false,
            dragged: false,
        });
        self
    }

    /// Rebuilds the canvas from the model (after any structural change).
    fn sync_snarl(&mut self) {
        let mut snarl = Snarl::new();
        let mut ids: BTreeMap<String, NodeId> = BTreeMap::new();
        for name in self.model.node_names() {
            let [x, y] = self
                .model
                .positions()
                .get(&name)
                .copied()
                .unwrap_or([0.0, 0.0]);
            let id = snarl.insert_node(egui::pos2(x as f32, y as f32), name.clone());
            ids.insert(name, id);
        }
        for d in &self.model.document().nodes {
            let Some(&to_id) = ids.get(&d.name.value) else {
                continue;
            };
            let Ok(to_imp) = self.model.node_impl(&d.name.value) else {
                continue;
            };
            for (port, _) in &d.inputs {
                let Some((src, src_port)) = self.model.input_source(&d.name.value, &port.value)
                else {
                    continue;
                };
                let Some(&from_id) = ids.get(&src) else {
                    continue;
                };
                let Ok(from_imp) = self.model.node_impl(&src) else {
                    continue;
                };
                let out_i = from_imp
                    .schema()
                    .outputs
                    .iter()
                    .position(|p| p.name == src_port);
                let in_i = to_imp
                    .schema()
                    .inputs
                    .iter()
                    .position(|p| p.name == port.value);
                if let (Some(o), Some(i)) = (out_i, in_i) {
                    snarl.connect(
                        OutPinId {
                            node: from_id,
                            output: o,
                        },
                        InPinId {
                            node: to_id,
                            input: i,
                        },
                    );
                }
            }
        }
        self.snarl = snarl;
        self.check_errors = match self.model.check() {
            Ok(_) => Vec::new(),
            Err(errs) => errs
                .iter()
                .map(|e| (e.node().map(str::to_string), e.to_string()))
                .collect(),
        };
        self.synced_revision = Some(self.model.revision());
    }

    fn selected_kind(&self) -> Option<String> {
        let sel = self.selected.as_deref()?;
        self.model
            .document()
            .node(sel)
            .map(|d| d.kind.value.clone())
    }

    /// Starts evaluating the selected node when the document or the selection changed.
    fn maybe_evaluate(&mut self, ctx: &egui::Context) {
        let key = (self.model.revision(), self.selected.clone());
        if self.requested.as_ref() == Some(&key) {
            return;
        }
        self.requested = Some(key);
        let Some(sel) = self.selected.clone() else {
            return;
        };
        self.background = upstream_color(&self.model, &sel);
        self.paste = placement::paste_upstream(&self.model, &sel);
        let focus_kind = self
            .selected_kind()
            .is_some_and(|k| focus::FOCUS_KINDS.contains(&k.as_str()));
        self.focus_depth = if focus_kind {
            self.model
                .input_source(&sel, "depth")
                .map(|(n, p)| format!("{n}.{p}"))
        } else {
            None
        };
        let mut targets = vec![sel];
        for key in [&self.background, &self.focus_depth].into_iter().flatten() {
            if let Some((node, _)) = key.split_once('.') {
                targets.push(node.to_string());
            }
        }
        // The pasted object's mask, where a drag can grab it.
        targets.extend(self.paste.clone());
        targets.sort_unstable();
        targets.dedup();
        let gesture = self.model.in_gesture();
        let Some(ev) = self.evaluator.as_mut() else {
            return;
        };
        if !self.notify_set {
            let c = ctx.clone();
            ev.set_notify(move || c.request_repaint());
            self.notify_set = true;
        }
        match self.model.pipeline_for(Some(&targets)) {
            Ok(p) => {
                // A drag lets the run in flight finish (each step is shown)
                // and replaces only the request waiting behind it.
                if gesture {
                    ev.start_queued(p, vec![self.path.clone()]);
                } else {
                    ev.start(p, vec![self.path.clone()]);
                }
                self.cancelled.clear();
                self.request_revision = self.model.revision();
                if self.request_started.is_none() || !gesture {
                    self.request_started = Some(Instant::now());
                }
                ctx.request_repaint();
            }
            Err(errs) => self.eval_error = Some(errs.join("\n")),
        }
    }

    fn poll(&mut self, ctx: &egui::Context) {
        let Some(ev) = self.evaluator.as_mut() else {
            return;
        };
        let outcome = ev.poll();
        let pending = ev.pending();
        let running = ev.running();
        if let Some(outcome) = outcome {
            match outcome.result {
                Ok((trace, values)) => {
                    for rec in &trace.nodes {
                        if rec.status == Status::Ran || rec.status == Status::Passthrough {
                            self.last_ms.insert(rec.node.clone(), rec.ms);
                        }
                    }
                    self.trace = Some(trace);
                    self.values = values;
                    self.eval_error = None;
                    self.cancelled.clear();
                    self.rebuild_preview(ctx);
                    // A drag's intermediate step: the newest is still coming.
                    if !pending {
                        self.shown_revision = Some(self.request_revision);
                        if let Some(t) = self.request_started.take() {
                            self.last_latency_ms = Some(t.elapsed().as_secs_f64() * 1e3);
                        }
                    }
                }
                Err(e) => {
                    self.request_started = None;
                    if outcome.cancelled {
                        self.cancelled = running.keys().cloned().collect();
                        self.eval_error = Some(format!(
                            "run cancelled{}",
                            if self.cancelled.is_empty() {
                                String::new()
                            } else {
                                format!(
                                    " while {} ran",
                                    self.cancelled
                                        .iter()
                                        .cloned()
                                        .collect::<Vec<_>>()
                                        .join(", ")
                                )
                            }
                        ));
                    } else {
                        self.eval_error = Some(e);
                    }
                }
            }
        }
        self.running = if self.request_started.is_some() {
            running
        } else {
            BTreeMap::new()
        };
        if !self.running.is_empty() {
            // Keep the progress bars moving.
            ctx.request_repaint_after(Duration::from_millis(100));
        }
    }

    /// Cancels the run in flight (the nodes it was running say
    /// "cancelled"); false when nothing was running.
    pub fn cancel_run(&mut self) -> bool {
        if !self.busy() {
            return false;
        }
        self.evaluator.as_mut().is_some_and(Evaluator::cancel)
    }

    /// Nodes that were running when the last run was cancelled.
    pub fn cancelled_nodes(&self) -> &std::collections::BTreeSet<String> {
        &self.cancelled
    }

    /// The nodes of the run in flight that have started and not finished.
    pub fn running_nodes(&self) -> &BTreeMap<String, NodeProgress> {
        &self.running
    }

    /// The run's error or cancellation, as shown under the canvas.
    pub fn run_error(&self) -> Option<&str> {
        self.eval_error.as_deref()
    }

    /// Moves the pasted object of the selected node's preview by `delta`
    /// image pixels, as one drag does (one undoable edit): the screenshot
    /// mode's `--drag` and scripts use it.
    pub fn move_pasted(&mut self, delta: [f64; 2]) -> Result<(), String> {
        let sel = self.selected.clone().ok_or("no node is selected")?;
        let paste = placement::paste_upstream(&self.model, &sel)
            .ok_or_else(|| format!("node `{sel}` is not downstream of a Paste"))?;
        let mask = match self.values.get(&format!("{paste}.mask")) {
            Some(Value::Mask(m)) => m.clone(),
            _ => return Err(format!("`{paste}.mask` has not been computed yet")),
        };
        let (w, h) = mask.dims();
        let start = self.placement_start(&paste, &mask)?;
        self.model.begin_gesture();
        let r = self.model.set_param(
            &paste,
            "target_pixel",
            ParamValue::Points(vec![placement::dragged_target(start, delta, [w, h])]),
        );
        self.model.end_gesture();
        r
    }

    /// `Paste.target_pixel` where a move starts: its value, or (when the
    /// object is placed by translation alone) the object's centroid.
    fn placement_start(
        &self,
        paste: &str,
        mask: &depthgraph_graph::prelude::Mask,
    ) -> Result<[f64; 2], String> {
        match self.model.param_value(paste, "target_pixel")? {
            ParamValue::Points(p) if !p.is_empty() => Ok(p[0]),
            _ => placement::object_view(mask)
                .map(|v| v.centroid)
                .ok_or_else(|| format!("`{paste}` placed nothing in the picture")),
        }
    }

    /// The selected node's image outputs (port names), in schema order.
    fn image_ports(&self) -> Vec<&'static str> {
        let Some(sel) = self.selected.as_deref() else {
            return Vec::new();
        };
        let Ok(imp) = self.model.node_impl(sel) else {
            return Vec::new();
        };
        imp.schema()
            .outputs
            .iter()
            .filter(|p| {
                self.values
                    .get(&format!("{sel}.{}", p.name))
                    .is_some_and(|v| v.image_dims().is_some())
            })
            .map(|p| p.name)
            .collect()
    }

    /// Builds the preview texture from the latest values.
    fn rebuild_preview(&mut self, ctx: &egui::Context) {
        self.texture = None;
        self.texture_node = None;
        self.legend = None;
        self.preview_hash = None;
        self.image_frame = None;
        let Some(sel) = self.selected.clone() else {
            return;
        };
        let ports = self.image_ports();
        let port = match &self.preview_port {
            Some(p) if ports.contains(&p.as_str()) => p.clone(),
            _ => match ports.first() {
                Some(p) => p.to_string(),
                None => return,
            },
        };
        let Some(value) = self.values.get(&format!("{sel}.{port}")) else {
            return;
        };
        let background = self
            .background
            .as_ref()
            .and_then(|k| self.values.get(k))
            .filter(|bg| bg.image_dims() == value.image_dims())
            .and_then(preview::picture);
        let lasso = self.selected_kind().as_deref() == Some("Lasso");
        let picture = match (value, background) {
            (Value::Mask(_) | Value::Confidence(_), Some(mut bg)) => {
                let size = value.image_dims().map_or([0, 0], |(w, h)| [w, h]);
                if lasso {
                    preview::overlay_mask(
                        &mut bg.image,
                        self.values
                            .get(&format!("{sel}.mask"))
                            .and_then(|v| match v {
                                Value::Mask(m) => Some(m.as_slice()),
                                _ => None,
                            })
                            .unwrap_or(&[]),
                        size,
                        Color32::from_rgb(40, 120, 255),
                        0.45,
                    );
                    if let Some(Value::Mask(p)) = self.values.get(&format!("{sel}.path")) {
                        preview::overlay_mask(
                            &mut bg.image,
                            p.as_slice(),
                            size,
                            Color32::YELLOW,
                            1.0,
                        );
                    }
                } else {
                    preview::overlay_mask(
                        &mut bg.image,
                        value.samples().map_or(&[][..], |m| m.samples),
                        size,
                        Color32::from_rgb(255, 120, 40),
                        0.6,
                    );
                }
                Some(bg)
            }
            (v, _) => preview::picture(v),
        };
        if let Some(p) = picture {
            self.legend = p.legend;
            let mut h = std::collections::hash_map::DefaultHasher::new();
            std::hash::Hash::hash(&p.image.size, &mut h);
            for c in &p.image.pixels {
                std::hash::Hash::hash(&c.to_array(), &mut h);
            }
            self.preview_hash = Some(std::hash::Hasher::finish(&h));
            self.texture = Some(ctx.load_texture("preview", p.image, TextureOptions::NEAREST));
            self.texture_node = Some(sel.clone());
        }
    }

    /// The preview pane: output choice, zoom, the picture (with hover
    /// values), a depth legend, and lasso clicks for a Lasso node.
    fn preview_pane(&mut self, ui: &mut egui::Ui, sel: &str) {
        ui.strong(format!("preview of {sel}"));
        let ports = self.image_ports();
        let mut rebuild = false;
        ui.horizontal(|ui| {
            if ports.len() > 1 {
                let mut current = self
                    .preview_port
                    .clone()
                    .filter(|p| ports.contains(&p.as_str()))
                    .unwrap_or_else(|| ports[0].to_string());
                let before = current.clone();
                egui::ComboBox::from_id_salt("preview-port")
                    .selected_text(current.clone())
                    .show_ui(ui, |ui| {
                        for p in &ports {
                            ui.selectable_value(&mut current, p.to_string(), *p);
                        }
                    });
                if current != before {
                    self.preview_port = Some(current);
                    rebuild = true;
                }
            }
            let mut fit = self.zoom.is_none();
            if ui.checkbox(&mut fit, "fit").changed() {
                self.zoom = if fit { None } else { Some(1.0) };
            }
            if let Some(z) = self.zoom.as_mut() {
                ui.add(
                    egui::Slider::new(z, 0.125..=16.0)
                        .logarithmic(true)
                        .text("zoom"),
                );
            }
        });
        if rebuild {
            self.rebuild_preview(ui.ctx());
        }
        // One status row, always there, so the picture never moves under
        // the pointer when a run starts or ends.
        ui.horizontal(|ui| {
            ui.set_min_height(22.0);
            if self.busy() {
                ui.add(egui::Spinner::new());
                ui.small("computing… (the previous result is shown dimmed)");
                if ui.small_button("cancel run").clicked() {
                    self.cancel_run();
                }
            } else if self.shown_revision != Some(self.model.revision()) {
                ui.small("not up to date (the last run did not finish)");
                if ui.small_button("run again").clicked() {
                    self.requested = None;
                }
            } else if let Some(ms) = self.last_latency_ms {
                ui.small(format!("result shown {ms:.0} ms after the change"));
            }
        });
        let focus_kind = self.focus_depth.is_some();
        if focus_kind {
            ui.small("Click on the picture to focus there; the circle shows the blur of the pixel under the pointer.");
            if let Ok(imp) = self.model.node_impl(sel) {
                for name in ["focus_m", "f_number", "aperture"] {
                    if let Some(spec) = imp.schema().param(name) {
                        param_row(ui, &mut self.model, sel, spec, &mut self.panel, "preview");
                    }
                }
            }
        }
        if self.paste.is_some() && !focus_kind {
            ui.small("Drag the pasted object to move it, Ctrl + wheel to scale it, drag the ring to turn it.");
        }
        let lasso = self.selected_kind().as_deref() == Some("Lasso");
        let mut clicks = match self.model.param_value(sel, "clicks") {
            Ok(ParamValue::Points(p)) if lasso => Some(p),
            _ => None,
        };
        let mut clicks_changed = false;
        if let Some(c) = clicks.as_mut() {
            ui.small("Click on the picture to add a lasso point; right click removes the last.");
            ui.horizontal(|ui| {
                if ui
                    .add_enabled(!c.is_empty(), egui::Button::new("Remove last click"))
                    .clicked()
                {
                    c.pop();
                    clicks_changed = true;
                }
                if ui
                    .add_enabled(!c.is_empty(), egui::Button::new("Clear clicks"))
                    .clicked()
                {
                    c.clear();
                    clicks_changed = true;
                }
                ui.label(format!("{} clicks", c.len()));
            });
        }
        let Some(tex) = self.texture.clone() else {
            ui.label(match &self.eval_error {
                Some(_) => "(the run failed: see the message below)",
                None if self.busy() => "(running…)",
                None => "(no image among this node's outputs)",
            });
            return;
        };
        let size = tex.size_vec2();
        let pixels = [tex.size()[0], tex.size()[1]];
        let value_key = format!(
            "{sel}.{}",
            self.preview_port
                .clone()
                .filter(|p| ports.contains(&p.as_str()))
                .or_else(|| ports.first().map(|p| p.to_string()))
                .unwrap_or_default()
        );
        // The picture is stale while a new one computes (or it is another
        // node's): shown dimmed.
        let current = self.texture_node.as_deref() == Some(sel);
        let stale = self.busy() || !current || self.shown_revision != Some(self.model.revision());
        let max_height = (ui.available_height() * 0.6).clamp(160.0, 560.0);
        egui::ScrollArea::both()
            .id_salt("preview-scroll")
            .max_height(max_height)
            .auto_shrink([false, true])
            .show(ui, |ui| {
                let scale = match self.zoom {
                    Some(z) => z,
                    // Guard: an empty texture keeps scale 1.
                    None if size.x > 0.0 => (ui.available_width() / size.x).max(0.01),
                    None => 1.0,
                };
                let tint = if stale {
                    Color32::from_gray(110)
                } else {
                    Color32::WHITE
                };
                let resp = ui.add(
                    egui::Image::new((tex.id(), size * scale))
                        .tint(tint)
                        .sense(egui::Sense::click_and_drag()),
                );
                let frame = ImageFrame {
                    rect: resp.rect,
                    size: pixels,
                };
                self.image_frame = Some(frame);
                // Only on this node's own picture (not the previous
                // selection's, still shown while this one computes).
                if current && focus_kind {
                    self.focus_interaction(ui, &resp, frame, sel);
                } else if current && self.paste.is_some() {
                    self.place_interaction(ui, &resp, frame);
                }
                if let Some(c) = clicks.as_mut() {
                    if resp.clicked() {
                        if let Some(px) =
                            resp.interact_pointer_pos().and_then(|p| frame.to_pixel(p))
                        {
                            c.push([(px[0] * 10.0).round() / 10.0, (px[1] * 10.0).round() / 10.0]);
                            clicks_changed = true;
                        }
                    }
                    if resp.secondary_clicked() && c.pop().is_some() {
                        clicks_changed = true;
                    }
                    let painter = ui.painter_at(resp.rect);
                    let pts: Vec<egui::Pos2> = c.iter().map(|p| frame.to_screen(*p)).collect();
                    if pts.len() >= 2 {
                        let mut closed = pts.clone();
                        closed.push(pts[0]);
                        painter.add(egui::Shape::dashed_line(
                            &closed,
                            egui::Stroke::new(1.0, Color32::WHITE),
                            4.0,
                            4.0,
                        ));
                    }
                    for p in &pts {
                        painter.circle(
                            *p,
                            4.0,
                            Color32::RED,
                            egui::Stroke::new(1.0, Color32::WHITE),
                        );
                    }
                }
                if let Some(pos) = resp.hover_pos() {
                    if let Some(px) = frame.to_pixel(pos) {
                        let (x, y) = (px[0] as usize, px[1] as usize);
                        if let Some(text) = self
                            .values
                            .get(&value_key)
                            .and_then(|v| preview::describe_pixel(v, x, y))
                        {
                            resp.on_hover_text_at_pointer(text);
                        }
                    }
                }
            });
        if let Some(l) = self.legend {
            ui.horizontal(|ui| {
                ui.label(format!("{:.2} m", l.near_m));
                let (rect, _) =
                    ui.allocate_exact_size(egui::vec2(160.0, 12.0), egui::Sense::hover());
                let painter = ui.painter_at(rect);
                let n = 32;
                for i in 0..n {
                    let [r, g, b] = preview::colormap((i as f32 + 0.5) / n as f32);
                    let x0 = rect.min.x + rect.width() * i as f32 / n as f32;
                    let x1 = rect.min.x + rect.width() * (i + 1) as f32 / n as f32;
                    painter.rect_filled(
                        egui::Rect::from_min_max(
                            egui::pos2(x0, rect.min.y),
                            egui::pos2(x1, rect.max.y),
                        ),
                        0.0,
                        Color32::from_rgb(r, g, b),
                    );
                }
                ui.label(format!("{:.2} m", l.far_m));
                if l.holes > 0 {
                    ui.label(format!("({} holes, black)", l.holes));
                }
            });
        }
        if clicks_changed {
            if let Some(c) = clicks {
                if let Err(e) = self.model.set_param(sel, "clicks", ParamValue::Points(c)) {
                    self.message = Some(e);
                }
            }
        }
    }

    /// Drag to place on a preview downstream of `Paste` (see
    /// [`placement`]): the ring gizmo, a drag on the object (move) or on
    /// the ring (turn), Ctrl + wheel (scale). Each gesture is one undoable
    /// edit; its steps are evaluated latest-wins.
    fn place_interaction(&mut self, ui: &egui::Ui, resp: &egui::Response, frame: ImageFrame) {
        let Some(paste) = self.paste.clone() else {
            return;
        };
        let mask = match self.values.get(&format!("{paste}.mask")) {
            Some(Value::Mask(m)) if m.dims() == (frame.size[0], frame.size[1]) => m.clone(),
            _ => return,
        };
        let s = frame.scale();
        let view = placement::object_view(&mask);
        let ring = view.map(|v| (frame.to_screen(v.centroid), v.radius as f32 * s + 12.0));
        let rotation = match self.model.param_value(&paste, "rotation_deg") {
            Ok(ParamValue::Vec3(r)) => r,
            _ => [0.0; 3],
        };
        if let Some((c, r)) = ring {
            let painter = ui.painter_at(resp.rect);
            painter.circle_stroke(
                c,
                r,
                egui::Stroke::new(2.0, Color32::from_rgba_unmultiplied(255, 255, 255, 150)),
            );
            let yaw = rotation[0].to_radians() as f32;
            painter.circle_filled(
                c + r * egui::vec2(yaw.sin(), -yaw.cos()),
                5.0,
                Color32::YELLOW,
            );
        }
        if resp.drag_started() {
            let origin = ui.input(|i| i.pointer.press_origin());
            if let Some((origin, px)) = origin.and_then(|o| frame.to_pixel(o).map(|p| (o, p))) {
                let on_ring = ring.is_some_and(|(c, r)| ((origin - c).length() - r).abs() <= 10.0);
                let what = if placement::on_object(&mask, px) {
                    self.placement_start(&paste, &mask)
                        .ok()
                        .map(|start| PlaceWhat::Move { start })
                } else if on_ring {
                    Some(PlaceWhat::Rotate { start: rotation })
                } else {
                    None
                };
                if let Some(what) = what {
                    self.model.begin_gesture();
                    self.place = Some(PlaceDrag { origin, what });
                }
            }
        }
        if let Some(drag) = self.place {
            let pos = resp
                .interact_pointer_pos()
                .or_else(|| ui.input(|i| i.pointer.latest_pos()));
            if let (Some(pos), true) = (pos, resp.dragged() || resp.drag_stopped()) {
                let d = pos - drag.origin;
                let r = match drag.what {
                    PlaceWhat::Move { start } => {
                        // Guard: the frame's scale is > 0 (ImageFrame::scale).
                        let delta = [f64::from(d.x / s), f64::from(d.y / s)];
                        self.model.set_param(
                            &paste,
                            "target_pixel",
                            ParamValue::Points(vec![placement::dragged_target(
                                start, delta, frame.size,
                            )]),
                        )
                    }
                    PlaceWhat::Rotate { start } => self.model.set_param(
                        &paste,
                        "rotation_deg",
                        ParamValue::Vec3(placement::rotated(
                            start,
                            [f64::from(d.x), f64::from(d.y)],
                        )),
                    ),
                };
                if let Err(e) = r {
                    self.message = Some(e);
                }
            }
            if resp.drag_stopped() || !ui.input(|i| i.pointer.any_down()) {
                self.place = None;
            }
        }
        let zoom = ui.input(|i| i.zoom_delta());
        if resp.hovered() && zoom != 1.0 {
            if let Ok(ParamValue::Float(scale)) = self.model.param_value(&paste, "scale") {
                self.model.begin_gesture();
                self.wheel_gesture = Some(Instant::now());
                let v = placement::zoomed_scale(scale, f64::from(zoom));
                if let Err(e) = self.model.set_param(&paste, "scale", ParamValue::Float(v)) {
                    self.message = Some(e);
                }
            }
        }
    }

    /// Ends the placement gestures that are over, whatever is on screen
    /// now: a drag once no button is down, a scale gesture once Ctrl is
    /// released and the wheel has rested for 300 ms (so a pinch without Ctrl
    /// is one step too); and forgets them when the model's gesture was
    /// ended elsewhere (an undo). Called every frame.
    fn end_finished_gestures(&mut self, ctx: &egui::Context) {
        if !self.model.in_gesture() {
            self.place = None;
            self.wheel_gesture = None;
            return;
        }
        let (down, ctrl) = ctx.input(|i| {
            (
                i.pointer.any_down(),
                i.modifiers.ctrl || i.modifiers.command,
            )
        });
        if self.place.is_some() && !down {
            self.place = None;
        }
        if let Some(t) = self.wheel_gesture {
            if ctrl || t.elapsed() < Duration::from_millis(300) {
                ctx.request_repaint_after(Duration::from_millis(100));
            } else {
                self.wheel_gesture = None;
            }
        }
        if self.place.is_none() && self.wheel_gesture.is_none() {
            self.model.end_gesture();
        }
    }

    /// Click to focus on a Refocus / ReverseMappedDof preview (see
    /// [`focus`]): a click sets `focus_m` to the median depth of a small
    /// window under the pointer; hovering draws the pixel's circle of
    /// confusion under the node's lens.
    fn focus_interaction(
        &mut self,
        ui: &egui::Ui,
        resp: &egui::Response,
        frame: ImageFrame,
        sel: &str,
    ) {
        let Some(key) = self.focus_depth.clone() else {
            return;
        };
        let depth = match self.values.get(&key) {
            Some(Value::Depth(d)) => d.clone(),
            _ => return,
        };
        let (dw, dh) = depth.dims();
        // Image pixel -> depth pixel, scaled when the sizes differ. Guard:
        // an empty frame maps to 0.
        let to_depth = |px: [f64; 2]| {
            let sx = if frame.size[0] > 0 {
                dw as f64 / frame.size[0] as f64
            } else {
                0.0
            };
            let sy = if frame.size[1] > 0 {
                dh as f64 / frame.size[1] as f64
            } else {
                0.0
            };
            [px[0] * sx, px[1] * sy]
        };
        if resp.clicked() {
            if let Some(px) = resp.interact_pointer_pos().and_then(|p| frame.to_pixel(p)) {
                match focus::focus_depth(&depth, to_depth(px), focus::FOCUS_WINDOW_RADIUS) {
                    Some(z) => {
                        let z = (z * 1e4).round() / 1e4;
                        match self.model.set_param(sel, "focus_m", ParamValue::Float(z)) {
                            Ok(()) => self.message = Some(format!("focus at {z:.3} m")),
                            Err(e) => self.message = Some(e),
                        }
                    }
                    None => {
                        self.message = Some("no depth under the pointer: focus unchanged".into())
                    }
                }
            }
        }
        if let Some(pos) = resp.hover_pos() {
            let Some(px) = frame.to_pixel(pos) else {
                return;
            };
            let Some(z) = focus::focus_depth(&depth, to_depth(px), 0) else {
                return;
            };
            let Ok(lens) = focus::node_lens(&self.model, sel) else {
                return;
            };
            if let Some(coc) = focus::coc_px(&lens, frame.size[0], z as f32) {
                let painter = ui.painter_at(resp.rect);
                let r = (coc as f32 * frame.scale() * 0.5).max(1.5);
                painter.circle_stroke(pos, r, egui::Stroke::new(1.5, Color32::YELLOW));
                painter.text(
                    pos + egui::vec2(r + 6.0, -r - 6.0),
                    egui::Align2::LEFT_BOTTOM,
                    format!("{z:.2} m · blur {coc:.1} px"),
                    egui::FontId::proportional(13.0),
                    Color32::YELLOW,
                );
            }
        }
    }

    fn toolbar(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            if ui.button("Save").clicked() {
                self.message = Some(match self.model.save(&self.path) {
                    Ok(()) => format!("saved {}", self.path.display()),
                    Err(e) => e,
                });
            }
            if ui
                .add_enabled(self.model.can_undo(), egui::Button::new("Undo"))
                .clicked()
            {
                self.model.undo();
            }
            if ui
                .add_enabled(self.model.can_redo(), egui::Button::new("Redo"))
                .clicked()
            {
                self.model.redo();
            }
            ui.label(self.path.display().to_string());
            if let Some(m) = &self.message {
                ui.label(m.as_str());
            }
        });
    }

    /// Screenshot mode: once the preview is on screen for a few frames, ask
    /// for a screenshot; when it arrives, write it and close.
    fn drive_shot(&mut self, ctx: &egui::Context) {
        // Ready once the selected node's run is back (with or without an
        // image to show: a sink has none) or cannot run.
        let ready = self.selected.is_none()
            || self.evaluator.is_none()
            || (!self.busy() && (self.trace.is_some() || self.eval_error.is_some()));
        let shots: Vec<Arc<ColorImage>> = ctx.input(|i| {
            i.raw
                .events
                .iter()
                .filter_map(|e| match e {
                    egui::Event::Screenshot { image, .. } => Some(image.clone()),
                    _ => None,
                })
                .collect()
        });
        let Some(shot) = self.shot.as_mut() else {
            return;
        };
        if shot.done {
            return;
        }
        let finish = |shot: &mut ShotState, r: Result<(), String>| {
            if let Ok(mut o) = shot.cfg.outcome.lock() {
                *o = Some(r);
            }
            shot.done = true;
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        };
        if let Some(img) = shots.last() {
            let r = save_png(img, &shot.cfg.path);
            finish(shot, r);
            return;
        }
        if shot.started.elapsed() > shot.cfg.timeout {
            let r = Err(format!(
                "no preview after {:.0} s{}",
                shot.cfg.timeout.as_secs_f64(),
                self.eval_error
                    .as_ref()
                    .map(|e| format!(": {e}"))
                    .unwrap_or_default()
            ));
            finish(shot, r);
            return;
        }
        if ready {
            shot.ready_frames += 1;
        }
        let apply_drag = match (shot.cfg.drag, shot.dragged, shot.ready_frames >= 3) {
            (Some(delta), false, true) => {
                shot.dragged = true;
                shot.ready_frames = 0;
                Some(delta)
            }
            _ => None,
        };
        if let Some(delta) = apply_drag {
            if let Err(e) = self.move_pasted(delta) {
                if let Some(shot) = self.shot.as_mut() {
                    finish(shot, Err(format!("--drag: {e}")));
                }
            }
            ctx.request_repaint();
            return;
        }
        let Some(shot) = self.shot.as_mut() else {
            return;
        };
        if shot.ready_frames >= 5 && !shot.requested {
            ctx.send_viewport_cmd(egui::ViewportCommand::Screenshot(egui::UserData::default()));
            shot.requested = true;
        }
        ctx.request_repaint();
    }
}

impl eframe::App for EditorApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.show(ui);
    }
}

impl EditorApp {
    /// Selects `node` for the parameter panel and the preview.
    pub fn select(&mut self, node: &str) {
        if self.selected.as_deref() != Some(node) {
            self.preview_port = None;
            // A gesture belongs to the preview it began on.
            self.place = None;
            self.wheel_gesture = None;
            self.model.end_gesture();
        }
        self.selected = Some(node.to_string());
    }

    /// The latest run's trace (what ran, what was cached).
    pub fn trace(&self) -> Option<&Trace> {
        self.trace.as_ref()
    }

    /// A fingerprint of the preview picture now shown (`None`: none shown).
    pub fn preview_fingerprint(&self) -> Option<u64> {
        self.preview_hash
    }

    /// Where the preview picture is on screen (after a frame showed it).
    pub fn preview_frame(&self) -> Option<ImageFrame> {
        self.image_frame
    }

    /// A value of the latest run, by "node.port".
    pub fn value(&self, key: &str) -> Option<&Value> {
        self.values.get(key)
    }

    /// True while a requested evaluation has not come back.
    pub fn busy(&self) -> bool {
        self.request_started.is_some()
    }

    /// Draws the whole editor into `ui` (the window's contents).
    pub fn show(&mut self, ui: &mut egui::Ui) {
        let ctx = ui.ctx().clone();
        if self.synced_revision != Some(self.model.revision()) {
            self.sync_snarl();
        }
        self.poll(&ctx);
        egui::Panel::top("toolbar").show(ui, |ui| self.toolbar(ui));
        if !self.check_errors.is_empty() || self.eval_error.is_some() {
            egui::Panel::bottom("errors").show(ui, |ui| {
                if let Some(e) = &self.eval_error {
                    ui.strong("run error");
                    ui.colored_label(Color32::RED, e.as_str());
                }
                if !self.check_errors.is_empty() {
                    ui.strong("check errors");
                    for (_, e) in &self.check_errors {
                        ui.colored_label(Color32::RED, e.as_str());
                    }
                }
            });
        }
        egui::Panel::right("side")
            .min_size(340.0)
            .default_size(520.0)
            .show(ui, |ui| {
                // The picture first (it is what a drag or a click works on),
                // the parameters below it, scrolled.
                let sel = self
                    .selected
                    .clone()
                    .filter(|s| self.model.document().node(s).is_some());
                if let Some(sel) = &sel {
                    self.preview_pane(ui, sel);
                    ui.separator();
                }
                egui::ScrollArea::vertical()
                    .id_salt("side-scroll")
                    .show(ui, |ui| match sel {
                        Some(sel) => {
                            param_panel(ui, &mut self.model, &sel, &mut self.panel);
                        }
                        _ => {
                            ui.label("Click `preview` on a node to edit its parameters.");
                            ui.separator();
                            ui.strong("stages");
                            let mut names: Vec<&str> = self.stages.values().copied().collect();
                            names.sort_unstable();
                            names.dedup();
                            for stage in names {
                                ui.horizontal(|ui| {
                                    let (rect, _) = ui.allocate_exact_size(
                                        egui::vec2(14.0, 14.0),
                                        egui::Sense::hover(),
                                    );
                                    ui.painter().rect_filled(rect, 2.0, stage_color(stage));
                                    ui.label(stage);
                                });
                            }
                        }
                    });
            });
        egui::CentralPanel::default().show(ui, |ui| {
            let mut viewer = GraphViewer {
                model: &mut self.model,
                trace: self.trace.as_ref(),
                selected: self.selected.as_deref(),
                errors: &self.check_errors,
                search: &mut self.search,
                running: &self.running,
                last_ms: &self.last_ms,
                cancelled: &self.cancelled,
                stages: &self.stages,
                actions: CanvasActions::default(),
            };
            let mut style = SnarlStyle::new();
            style.min_scale = Some(MIN_CANVAS_SCALE);
            self.snarl
                .show(&mut viewer, &style, "depthgraph-canvas", ui);
            let actions = viewer.actions;
            if let Some(s) = actions.select {
                self.select(&s);
            }
            if actions.cancel {
                self.cancel_run();
            }
            if let Some(m) = actions.message {
                self.message = Some(m);
            }
        });
        // Positions back into the model (saved in the layout section).
        let moved: Vec<(String, egui::Pos2)> = self
            .snarl
            .nodes_pos_ids()
            .map(|(_, pos, name)| (name.clone(), pos))
            .collect();
        for (name, pos) in moved {
            self.model
                .set_position(&name, [f64::from(pos.x), f64::from(pos.y)]);
        }
        self.end_finished_gestures(&ctx);
        self.maybe_evaluate(&ctx);
        if self.shot.is_some() {
            self.drive_shot(&ctx);
        }
    }
}
