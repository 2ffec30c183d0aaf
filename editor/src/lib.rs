//! # depthgraph-editor
//!
//! An egui node-graph editor for depthgraph pipelines. [`model`] is the
//! window-free logic (edits, undo, save), [`eval`] runs pipelines on a
//! background thread, [`preview`] turns values into
//! pictures, [`app`] is the eframe user interface.

pub mod app;
pub mod eval;
pub mod model;
pub mod preview;

pub use eval::{EvalOutcome, Evaluator};
pub use model::EditorModel;
