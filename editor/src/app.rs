//! The eframe application: the canvas ([`crate::canvas`]), the parameter
//! side panel ([`crate::params`]), the preview pane with its gestures, a
//! check-error panel and Save / Undo / Redo.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use depthgraph_graph::params::ParamValue;
use depthgraph_graph::prelude::{Status, Trace, Value, ValueType};
use eframe::egui::{self, Color32, ColorImage, TextureHandle, TextureOptions};
use egui_snarl::ui::SnarlStyle;
use egui_snarl::{InPinId, NodeId, OutPinId, Snarl};

use crate::canvas::{CanvasActions, GraphViewer, MIN_CANVAS_SCALE};
pub use crate::canvas::{stage_color, type_color};
use crate::eval::{Evaluator, NodeProgress};
use crate::model::EditorModel;
pub use crate::params::{PanelState, list_dir, param_panel, param_row};
use crate::preview::{self, DepthLegend, ImageFrame};
use crate::{focus, placement};

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
    model.upstream(node).iter().find_map(|n| {
        let imp = model.node_impl(n).ok()?;
        imp.schema().inputs.iter().find_map(|input| {
            let (src, port) = model.input_source(n, input.name)?;
            (model.port_type(&src, &port, true) == Ok(ValueType::Color))
                .then(|| format!("{src}.{port}"))
        })
    })
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
    /// The size in pixels of the picture the texture shows (the texture
    /// itself may be smaller: [`preview::fit_texture`]).
    texture_pixels: [usize; 2],
    /// The document revision of the newest request and of the result shown.
    request_revision: u64,
    shown_revision: Option<u64>,
    /// The `Paste` node a drag on the selected node's preview moves.
    paste: Option<String>,
    /// Where its object is in the latest result (found once per result,
    /// not per frame).
    object: Option<placement::ObjectView>,
    /// The depth ("node.port") under a focus preview (Refocus's input).
    focus_depth: Option<String>,
    /// The placement drag in progress.
    place: Option<PlaceDrag>,
    /// A Ctrl + wheel scale gesture is open: when the wheel last moved.
    wheel_gesture: Option<Instant>,
    /// `path` is a name picked for a new document, not saved yet: the
    /// first Save must not replace a file made there since.
    new_file: bool,
    /// The window was asked to close with unsaved changes: the dialog
    /// asking what to do is open.
    confirm_close: bool,
    /// The user chose to close (saved or discarded): let the window go.
    close_allowed: bool,
    /// The window title last sent (`*` marks unsaved changes).
    title: String,
    /// Whether the document had unsaved changes this frame (found once a
    /// frame: it compares the document's whole text).
    modified: bool,
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
        let panel = PanelState {
            out_dir: out_dir.clone(),
            ..PanelState::default()
        };
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
            panel,
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
            texture_pixels: [0, 0],
            request_revision: 0,
            shown_revision: None,
            paste: None,
            object: None,
            focus_depth: None,
            place: None,
            wheel_gesture: None,
            new_file: false,
            confirm_close: false,
            close_allowed: false,
            title: String::new(),
            modified: false,
        }
    }

    /// Marks `path` as a name picked for a new document: its first Save
    /// writes only a file that does not exist yet.
    pub fn with_new_file(mut self) -> Self {
        self.new_file = true;
        self
    }

    /// The file Save writes.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Saves the document to its file. A new document's first save takes
    /// the next free `untitled-N.ron` beside it when its name was taken
    /// meanwhile (another editor saved there), and says so.
    pub fn save(&mut self) -> Result<String, String> {
        if !self.new_file {
            self.model.save(&self.path)?;
            return Ok(format!("saved {}", self.path.display()));
        }
        let dir = self
            .path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default();
        let first = self.path.clone();
        let names = std::iter::once(first.clone())
            .chain((1..10_000).map(|n| dir.join(format!("untitled-{n}.ron"))));
        for candidate in names {
            if self.model.save_new(&candidate)? {
                self.new_file = false;
                self.path = candidate;
                return Ok(if self.path == first {
                    format!("saved {}", self.path.display())
                } else {
                    format!(
                        "saved as {} ({} was made by another program meanwhile)",
                        self.path.display(),
                        first.display()
                    )
                });
            }
        }
        Err("every name untitled[-N].ron up to N = 9999 is taken".into())
    }

    /// The window was asked to close: true when it may (nothing unsaved,
    /// or the user chose to save or discard); otherwise the dialog asking
    /// what to do with the unsaved changes opens and the window stays.
    pub fn request_close(&mut self) -> bool {
        if self.close_allowed || self.shot.is_some() || !self.model.is_modified() {
            return true;
        }
        self.confirm_close = true;
        false
    }

    /// The dialog of [`EditorApp::request_close`]: save and close, close
    /// without saving, or stay.
    fn close_dialog(&mut self, ctx: &egui::Context) {
        if !self.confirm_close {
            return;
        }
        let mut close = false;
        egui::Window::new("Unsaved changes")
            .collapsible(false)
            .resizable(false)
            .anchor(egui::Align2::CENTER_CENTER, egui::vec2(0.0, 0.0))
            .show(ctx, |ui| {
                ui.label(format!(
                    "{} has changes that are not saved.",
                    self.path.display()
                ));
                ui.horizontal(|ui| {
                    if ui.button("Save and close").clicked() {
                        match self.save() {
                            Ok(m) => {
                                self.message = Some(m);
                                close = true;
                            }
                            Err(e) => {
                                self.message = Some(e);
                                self.confirm_close = false;
                            }
                        }
                    }
                    if ui.button("Close without saving").clicked() {
                        close = true;
                    }
                    if ui.button("Cancel").clicked() {
                        self.confirm_close = false;
                    }
                });
            });
        if close {
            self.confirm_close = false;
            self.close_allowed = true;
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        }
    }

    /// Whether the user chose to close the window (from the dialog).
    pub fn close_allowed(&self) -> bool {
        self.close_allowed
    }

    /// The window title: the file, `*` while changes are unsaved.
    pub fn window_title(&self) -> String {
        self.title_for(self.model.is_modified())
    }

    fn title_for(&self, modified: bool) -> String {
        let mark = if modified { "*" } else { "" };
        format!("depthgraph editor - {}{mark}", self.path.display())
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
                    self.object = match self
                        .paste
                        .as_ref()
                        .and_then(|p| self.values.get(&format!("{p}.mask")))
                    {
                        Some(Value::Mask(m)) => placement::object_view(m),
                        _ => None,
                    };
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
            self.texture_pixels = p.image.size;
            let max_side = ctx.input(|i| i.max_texture_side);
            let image = preview::fit_texture(p.image, max_side);
            self.texture = Some(ctx.load_texture("preview", image, TextureOptions::NEAREST));
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
            // the buttons above work without a picture too
            if clicks_changed && let Some(c) = clicks {
                self.set_clicks(sel, c);
            }
            ui.label(match &self.eval_error {
                Some(_) => "(the run failed: see the message below)",
                None if self.busy() => "(running…)",
                None => "(no image among this node's outputs)",
            });
            return;
        };
        // the picture's own size (its texture may be smaller)
        let pixels = self.texture_pixels;
        let size = egui::vec2(pixels[0] as f32, pixels[1] as f32);
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
                    if resp.clicked()
                        && let Some(px) =
                            resp.interact_pointer_pos().and_then(|p| frame.to_pixel(p))
                    {
                        c.push([(px[0] * 10.0).round() / 10.0, (px[1] * 10.0).round() / 10.0]);
                        clicks_changed = true;
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
                if let Some(pos) = resp.hover_pos()
                    && let Some(px) = frame.to_pixel(pos)
                {
                    let (x, y) = (px[0] as usize, px[1] as usize);
                    if let Some(text) = self
                        .values
                        .get(&value_key)
                        .and_then(|v| preview::describe_pixel(v, x, y))
                    {
                        resp.on_hover_text_at_pointer(text);
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
        if clicks_changed && let Some(c) = clicks {
            self.set_clicks(sel, c);
        }
    }

    /// Sets the lasso `sel`'s clicks (a refusal goes to the message line).
    fn set_clicks(&mut self, sel: &str, clicks: Vec<[f64; 2]>) {
        if let Err(e) = self
            .model
            .set_param(sel, "clicks", ParamValue::Points(clicks))
        {
            self.message = Some(e);
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
        let ring = self
            .object
            .map(|v| (frame.to_screen(v.centroid), v.radius as f32 * s + 12.0));
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
        if resp.hovered()
            && zoom != 1.0
            && let Ok(ParamValue::Float(scale)) = self.model.param_value(&paste, "scale")
        {
            self.model.begin_gesture();
            self.wheel_gesture = Some(Instant::now());
            let v = placement::zoomed_scale(scale, f64::from(zoom));
            if let Err(e) = self.model.set_param(&paste, "scale", ParamValue::Float(v)) {
                self.message = Some(e);
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
        if resp.clicked()
            && let Some(px) = resp.interact_pointer_pos().and_then(|p| frame.to_pixel(p))
        {
            match focus::focus_depth(&depth, to_depth(px), focus::FOCUS_WINDOW_RADIUS) {
                Some(z) => {
                    let z = (z * 1e4).round() / 1e4;
                    match self.model.set_param(sel, "focus_m", ParamValue::Float(z)) {
                        Ok(()) => self.message = Some(format!("focus at {z:.3} m")),
                        Err(e) => self.message = Some(e),
                    }
                }
                None => self.message = Some("no depth under the pointer: focus unchanged".into()),
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
                self.message = Some(match self.save() {
                    Ok(m) | Err(m) => m,
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
            if self.modified {
                ui.label("(unsaved changes)");
            }
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
            if let Err(e) = self.move_pasted(delta)
                && let Some(shot) = self.shot.as_mut()
            {
                finish(shot, Err(format!("--drag: {e}")));
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
        if ctx.input(|i| i.viewport().close_requested()) && !self.request_close() {
            ctx.send_viewport_cmd(egui::ViewportCommand::CancelClose);
        }
        self.modified = self.model.is_modified();
        let title = self.title_for(self.modified);
        if title != self.title {
            ctx.send_viewport_cmd(egui::ViewportCommand::Title(title.clone()));
            self.title = title;
        }
        self.close_dialog(&ctx);
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
