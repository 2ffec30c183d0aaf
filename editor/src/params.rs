//! The parameter side panel: a widget for every parameter, generated from
//! the node kind's schema (sliders, checkboxes, choices, text, a file
//! browser for paths), the kind's documentation, and sliders that can
//! update on release.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use depthgraph_graph::params::{ParamKind, ParamValue};
use eframe::egui::{self, Color32};

use crate::model::EditorModel;

/// Edit buffers of the parameter panel (text that is not yet a valid value).
pub struct PanelState {
    /// Text fields being edited, by widget: the text typed so far and the
    /// value's text when the editing began ([`buffered_text`]).
    pub edits: BTreeMap<String, (String, String)>,
    /// The folder that relative output paths are written under (the
    /// file browser picks output files relative to it).
    pub out_dir: PathBuf,
    pub error: Option<String>,
    /// The file browser open for a path parameter: "node.param" and the folder shown.
    pub browse: Option<(String, PathBuf)>,
    /// Nodes whose sliders update on release (slow nodes).
    pub on_release: std::collections::BTreeSet<String>,
    /// A slider being dragged on such a node: "node.param" and the value shown.
    pub dragging: BTreeMap<String, f64>,
}

impl Default for PanelState {
    fn default() -> Self {
        Self {
            edits: BTreeMap::new(),
            out_dir: PathBuf::from("out"),
            error: None,
            browse: None,
            on_release: Default::default(),
            dragging: BTreeMap::new(),
        }
    }
}

/// The text a path parameter gets for a file picked in the browser: an
/// output file under `out_dir` relative to it (the engine joins relative
/// output paths onto that folder), any other output file absolute; an
/// input file as browsed from the working directory, without `./` steps.
pub fn picked_path_text(picked: &Path, output: bool, out_dir: &Path) -> String {
    let plain: PathBuf = picked
        .components()
        .filter(|c| !matches!(c, std::path::Component::CurDir))
        .collect();
    if !output {
        return plain.display().to_string();
    }
    // the folder resolved (it exists: the file was listed in it)
    let absolute = match (plain.parent(), plain.file_name()) {
        (Some(dir), Some(name)) => std::fs::canonicalize(if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        })
        .map(|d| d.join(name))
        .unwrap_or_else(|_| plain.clone()),
        _ => plain.clone(),
    };
    match std::fs::canonicalize(out_dir) {
        Ok(out) => match absolute.strip_prefix(&out) {
            Ok(rel) => rel.display().to_string(),
            Err(_) => absolute.display().to_string(),
        },
        Err(_) => absolute.display().to_string(),
    }
}

/// A one-line text field for a parameter whose text is applied as a
/// whole: what is typed is kept in `state.edits` under `key` and handed
/// back once the field loses focus (Enter, Tab or a click elsewhere; not
/// Escape, which drops it), and only if it differs from the value's text
/// when the editing began. While
/// the field has no focus it shows `current`, so a value changed
/// elsewhere (a drag, a lasso click, undo) is never written back from a
/// stale copy, and a path is not applied (re-running a sink that writes
/// it) at every keystroke.
fn buffered_text(
    ui: &mut egui::Ui,
    state: &mut PanelState,
    key: &str,
    current: String,
    label_id: egui::Id,
) -> Option<String> {
    let id = ui.make_persistent_id(("param-text", key));
    let focused = ui.memory(|m| m.has_focus(id));
    let entry = state
        .edits
        .entry(key.to_string())
        .or_insert_with(|| (current.clone(), current.clone()));
    if !focused && entry.1 != current {
        *entry = (current.clone(), current);
    }
    let r = ui
        .add(egui::TextEdit::singleline(&mut entry.0).id(id))
        .labelled_by(label_id);
    if r.lost_focus() {
        let (text, base) = state.edits.remove(key).unwrap_or_default();
        // Escape leaves the field as it was
        let cancelled = ui.input(|i| i.key_pressed(egui::Key::Escape));
        return (text != base && !cancelled).then_some(text);
    }
    None
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
                let field = format!("{salt}:{key}");
                if let Some(v) = buffered_text(ui, state, &field, s.clone(), label_id) {
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
                let field = format!("{salt}:{key}");
                new_text = buffered_text(ui, state, &field, current.to_ron(), label_id);
            }
        }
    });
    if state.browse.as_ref().is_some_and(|(k, _)| *k == key)
        && let Some(path) = file_browser(ui, state)
    {
        let output = matches!(spec.kind, ParamKind::OutputPath);
        new_value = Some(ParamValue::Text(picked_path_text(
            Path::new(&path),
            output,
            &state.out_dir,
        )));
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
