//! The graph canvas (egui-snarl): node titles, ports coloured by type,
//! headers coloured by pipeline stage, each node's status, progress bar,
//! cancel button and last time, wiring and the add-node menu.

use std::collections::BTreeMap;

use depthgraph_graph::prelude::{Status, Trace, ValueType};
use eframe::egui::{self, Color32};
use egui_snarl::ui::{PinInfo, SnarlViewer};
use egui_snarl::{InPin, NodeId, OutPin, Snarl};

use crate::eval::NodeProgress;
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
        ValueType::Vpls => Color32::from_rgb(255, 170, 60),
        ValueType::Scalar => Color32::from_rgb(250, 250, 120),
        ValueType::File => Color32::from_rgb(150, 150, 190),
        ValueType::Extension(_) => Color32::from_rgb(200, 200, 200),
    }
}

/// What the canvas asks the app to do after drawing.
#[derive(Default)]
pub(crate) struct CanvasActions {
    pub(crate) select: Option<String>,
    pub(crate) message: Option<String>,
    /// A node's cancel button was pressed.
    pub(crate) cancel: bool,
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

pub(crate) struct GraphViewer<'a> {
    pub(crate) model: &'a mut EditorModel,
    pub(crate) trace: Option<&'a Trace>,
    pub(crate) selected: Option<&'a str>,
    /// Check errors, by the node they concern (`None`: the whole file).
    pub(crate) errors: &'a [(Option<String>, String)],
    /// Filter text of the add-node menu.
    pub(crate) search: &'a mut String,
    /// Nodes of the run in flight that started and have not finished.
    pub(crate) running: &'a BTreeMap<String, NodeProgress>,
    /// Each node's time when it last ran (ms).
    pub(crate) last_ms: &'a BTreeMap<String, f64>,
    /// Nodes that were running when the run was cancelled.
    pub(crate) cancelled: &'a std::collections::BTreeSet<String>,
    /// The pipeline stage of each node kind.
    pub(crate) stages: &'a BTreeMap<String, &'static str>,
    pub(crate) actions: CanvasActions,
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
        if let Some((ip, _)) = self.ports(&dst, false).get(pin.id.input).copied()
            && self.model.input_source(&dst, ip).is_some()
        {
            let r = self.model.disconnect(&dst, ip);
            self.report(r);
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
