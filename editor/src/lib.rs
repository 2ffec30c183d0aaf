//! # depthgraph-editor
//!
//! An egui node-graph editor for depthgraph pipelines. [`model`] is the
//! window-free logic (edits, undo, save), [`layout`] places a graph without
//! a saved layout, [`eval`] runs pipelines on a background thread,
//! [`preview`] turns values into pictures, [`placement`] and [`focus`] are
//! the arithmetic of dragging the pasted object and clicking to focus;
//! [`canvas`] (the graph), [`params`] (the parameter panel) and [`app`] (the
//! window, its preview pane and gestures) are the egui user interface.

pub mod app;
pub mod canvas;
pub mod eval;
pub mod focus;
pub mod layout;
pub mod model;
pub mod params;
pub mod placement;
pub mod preview;

pub use eval::{EvalOutcome, Evaluator};
pub use model::EditorModel;
