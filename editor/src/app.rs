//! The eframe application: an egui-snarl canvas, a parameter side panel, a
//! preview pane, a check-error panel and Save / Undo / Redo.

use std::collections::BTreeMap;
use std::path::PathBuf;

use depthgraph_graph::params::{ParamKind, ParamValue};
use depthgraph_graph::prelude::{Status, Trace, Value, ValueType};
use eframe::egui::{self, Color32, ColorImage, TextureHandle, TextureOptions};
use egui_snarl::ui::{PinInfo, SnarlStyle, SnarlViewer};
use egui_snarl::{InPin, InPinId, NodeId, OutPin, OutPinId, Snarl};

use crate::eval::Evaluator;
use crate::model::EditorModel;

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
        ValueType::Scalar => Color32::from_rgb(250, 250, 120),
        ValueType::File => Color32::from_rgb(150, 150, 190),
    }
}

/// Edit buffers of the parameter panel (text that is not yet a valid value).
#[derive(Default)]
pub struct PanelState {
    pub edits: BTreeMap<String, String>,
    pub error: Option<String>,
}

/// Parameter widgets of `node`, generated from its kind's schema. Changes go
/// through [`EditorModel::set_param`]; a refusal is kept in `state.error`.
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
    ui.separator();
    for spec in &schema.params {
        let name = spec.name;
        let current = match model.param_value(node, name) {
            Ok(v) => v,
            Err(e) => {
                ui.colored_label(Color32::RED, e);
                spec.default.clone()
            }
        };
        let mut new_value: Option<ParamValue> = None;
        let mut new_text: Option<String> = None;
        ui.horizontal(|ui| {
            let label = ui.label(name).on_hover_text(spec.doc);
            match (&spec.kind, &current) {
                (ParamKind::Float { min, max }, ParamValue::Float(x)) => {
                    let mut v = *x;
                    let r = if min.is_finite() && max.is_finite() {
                        ui.add(
                            egui::Slider::new(&mut v, *min..=*max)
                                .logarithmic(*min >= 0.0 && *max / min.max(1e-9) > 1e3),
                        )
                    } else {
                        ui.add(egui::DragValue::new(&mut v).speed(0.01))
                    };
                    if r.labelled_by(label.id).changed() {
                        new_value = Some(ParamValue::Float(v));
                    }
                }
                (ParamKind::Int { min, max }, ParamValue::Int(x)) => {
                    let mut v = *x;
                    let r = if max.saturating_sub(*min) <= 100_000 {
                        ui.add(
                            egui::Slider::new(&mut v, *min..=*max)
                                .logarithmic(*min >= 0 && max.saturating_sub(*min) > 1000),
                        )
                    } else {
                        ui.add(egui::DragValue::new(&mut v).range(*min..=*max))
                    };
                    if r.labelled_by(label.id).changed() {
                        new_value = Some(ParamValue::Int(v));
                    }
                }
                (ParamKind::Bool, ParamValue::Bool(b)) => {
                    let mut v = *b;
                    if ui.checkbox(&mut v, "").labelled_by(label.id).changed() {
                        new_value = Some(ParamValue::Bool(v));
                    }
                }
                (ParamKind::Choice(choices), ParamValue::Text(s)) => {
                    let mut v = s.clone();
                    egui::ComboBox::from_id_salt(("param", node, name))
                        .selected_text(v.clone())
                        .show_ui(ui, |ui| {
                            for c in choices.iter() {
                                ui.selectable_value(&mut v, c.to_string(), *c);
                            }
                        })
                        .response
                        .labelled_by(label.id);
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
                        .labelled_by(label.id)
                        .changed()
                    {
                        new_value = Some(ParamValue::Text(v));
                    }
                }
                _ => {
                    // Points, Floats, Vec3: edited as RON text, applied on Enter.
                    let key = format!("{node}.{name}");
                    let buf = state
                        .edits
                        .entry(key.clone())
                        .or_insert_with(|| current.to_ron());
                    let r = ui.text_edit_singleline(buf).labelled_by(label.id);
                    if r.lost_focus() {
                        new_text = Some(buf.clone());
                        state.edits.remove(&key);
                    }
                }
            }
        });
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
    if let Some(e) = &state.error {
        ui.colored_label(Color32::RED, e);
    }
}

/// Linear → sRGB byte, clamped.
fn srgb_byte(x: f32) -> u8 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let s = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// A blue → green → yellow colormap of `t` in [0, 1].
fn colormap(t: f32) -> [u8; 3] {
    let stops = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    let t = t.clamp(0.0, 1.0) * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f32;
    let mut out = [0u8; 3];
    for (c, o) in out.iter_mut().enumerate() {
        *o = (stops[i][c] * (1.0 - f) + stops[i + 1][c] * f) as u8;
    }
    out
}

/// An 8-bit preview of an image value: Color as sRGB, Depth colormapped
/// (holes black), masks and confidences as grey. `None` for other values.
pub fn preview_image(v: &Value) -> Option<ColorImage> {
    match v {
        Value::Color(img) => {
            let (w, h) = img.dims();
            let mut rgba = Vec::with_capacity(w * h * 4);
            for p in img.as_slice() {
                rgba.extend_from_slice(&[srgb_byte(p[0]), srgb_byte(p[1]), srgb_byte(p[2]), 255]);
            }
            Some(ColorImage::from_rgba_unmultiplied([w, h], &rgba))
        }
        Value::Depth(img) => {
            let (w, h) = img.dims();
            let valid = img.as_slice().iter().filter(|z| z.is_finite() && **z > 0.0);
            let (lo, hi) = valid.fold((f32::INFINITY, 0.0f32), |(lo, hi), z| {
                (lo.min(*z), hi.max(*z))
            });
            let span = if hi > lo { hi - lo } else { 1.0 };
            let mut rgba = Vec::with_capacity(w * h * 4);
            for z in img.as_slice() {
                if z.is_finite() && *z > 0.0 {
                    let [r, g, b] = colormap((z - lo) / span);
                    rgba.extend_from_slice(&[r, g, b, 255]);
                } else {
                    rgba.extend_from_slice(&[0, 0, 0, 255]);
                }
            }
            Some(ColorImage::from_rgba_unmultiplied([w, h], &rgba))
        }
        Value::Mask(img) | Value::Confidence(img) => {
            let (w, h) = img.dims();
            let mut rgba = Vec::with_capacity(w * h * 4);
            for x in img.as_slice() {
                let g = (x.clamp(0.0, 1.0) * 255.0) as u8;
                rgba.extend_from_slice(&[g, g, g, 255]);
            }
            Some(ColorImage::from_rgba_unmultiplied([w, h], &rgba))
        }
        _ => None,
    }
}

/// What the canvas asks the app to do after drawing.
#[derive(Default)]
struct CanvasActions {
    select: Option<String>,
    message: Option<String>,
}

struct GraphViewer<'a> {
    model: &'a mut EditorModel,
    trace: Option<&'a Trace>,
    selected: Option<&'a str>,
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
        match self.ports(&name, false).get(pin.id.input) {
            Some((port, ty)) => {
                ui.label(*port);
                PinInfo::circle().with_fill(type_color(*ty))
            }
            None => PinInfo::circle(),
        }
    }

    fn show_output(
        &mut self,
        pin: &OutPin,
        ui: &mut egui::Ui,
        snarl: &mut Snarl<String>,
    ) -> impl egui_snarl::ui::SnarlPin + 'static {
        let name = snarl.get_node(pin.id.node).cloned().unwrap_or_default();
        match self.ports(&name, true).get(pin.id.output) {
            Some((port, ty)) => {
                ui.label(*port);
                PinInfo::circle().with_fill(type_color(*ty))
            }
            None => PinInfo::circle(),
        }
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
            if let Some(rec) = self.trace.and_then(|t| t.get(&name)) {
                let color = match rec.status {
                    Status::Ran => Color32::LIGHT_GREEN,
                    Status::Cached => Color32::LIGHT_BLUE,
                    Status::Passthrough => Color32::YELLOW,
                    Status::NotNeeded => Color32::GRAY,
                };
                ui.colored_label(color, format!("{} {:.1} ms", rec.status.as_str(), rec.ms));
                if let Some(reason) = &rec.reason {
                    ui.small(reason.as_str());
                }
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

    fn has_graph_menu(&mut self, _pos: egui::Pos2, _snarl: &mut Snarl<String>) -> bool {
        true
    }

    fn show_graph_menu(&mut self, pos: egui::Pos2, ui: &mut egui::Ui, _snarl: &mut Snarl<String>) {
        ui.label("Add node");
        let kinds: Vec<&'static str> = self.model.registry().kinds().collect();
        egui::ScrollArea::vertical()
            .max_height(300.0)
            .show(ui, |ui| {
                for k in kinds {
                    if ui.button(k).clicked() {
                        match self.model.add_node(k) {
                            Ok(name) => {
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
    trace: Option<Trace>,
    values: BTreeMap<String, Value>,
    texture: Option<TextureHandle>,
    check_errors: Vec<String>,
    message: Option<String>,
}

impl EditorApp {
    pub fn new(model: EditorModel, path: PathBuf) -> Self {
        let out_dir = path
            .parent()
            .map(|p| p.join("out"))
            .unwrap_or_else(|| PathBuf::from("out"));
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
            trace: None,
            values: BTreeMap::new(),
            texture: None,
            check_errors: Vec::new(),
            message,
        }
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
            Err(errs) => errs.iter().map(|e| e.to_string()).collect(),
        };
        self.synced_revision = Some(self.model.revision());
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
        let Some(ev) = self.evaluator.as_mut() else {
            return;
        };
        match self.model.pipeline_for(Some(std::slice::from_ref(&sel))) {
            Ok(p) => {
                ev.start(p, vec![self.path.clone()]);
                ctx.request_repaint();
            }
            Err(errs) => self.message = Some(errs.join("\n")),
        }
    }

    fn poll(&mut self, ctx: &egui::Context) {
        let Some(ev) = self.evaluator.as_mut() else {
            return;
        };
        match ev.poll() {
            Some(outcome) => match outcome.result {
                Ok((trace, values)) => {
                    self.trace = Some(trace);
                    self.values = values;
                    self.texture = None;
                    if let Some(sel) = &self.selected {
                        let prefix = format!("{sel}.");
                        let img = self
                            .values
                            .iter()
                            .filter(|(k, _)| k.starts_with(&prefix))
                            .find_map(|(_, v)| preview_image(v));
                        if let Some(img) = img {
                            self.texture =
                                Some(ctx.load_texture("preview", img, TextureOptions::LINEAR));
                        }
                    }
                }
                Err(e) => self.message = Some(e),
            },
            None => ctx.request_repaint_after(std::time::Duration::from_millis(50)),
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
}

impl eframe::App for EditorApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        if self.synced_revision != Some(self.model.revision()) {
            self.sync_snarl();
        }
        self.poll(&ctx);
        egui::Panel::top("toolbar").show(ui, |ui| self.toolbar(ui));
        if !self.check_errors.is_empty() {
            egui::Panel::bottom("errors").show(ui, |ui| {
                ui.strong("check errors");
                for e in &self.check_errors {
                    ui.colored_label(Color32::RED, e.as_str());
                }
            });
        }
        egui::Panel::right("side").min_size(300.0).show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| match self.selected.clone() {
                Some(sel) if self.model.document().node(&sel).is_some() => {
                    param_panel(ui, &mut self.model, &sel, &mut self.panel);
                    ui.separator();
                    ui.strong("preview");
                    match &self.texture {
                        Some(t) => {
                            let size = t.size_vec2();
                            let w = ui.available_width().min(size.x.max(1.0));
                            let scale = w / size.x.max(1.0);
                            ui.image((t.id(), size * scale));
                        }
                        None => {
                            ui.label("(no image output yet)");
                        }
                    }
                }
                _ => {
                    ui.label("Click `preview` on a node to edit its parameters.");
                }
            });
        });
        egui::CentralPanel::default().show(ui, |ui| {
            let mut viewer = GraphViewer {
                model: &mut self.model,
                trace: self.trace.as_ref(),
                selected: self.selected.as_deref(),
                actions: CanvasActions::default(),
            };
            self.snarl
                .show(&mut viewer, &SnarlStyle::new(), "depthgraph-canvas", ui);
            let actions = viewer.actions;
            if let Some(s) = actions.select {
                self.selected = Some(s);
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
        self.maybe_evaluate(&ctx);
    }
}
