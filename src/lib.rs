//! # depthgraph
//!
//! Editing color+depth (RGB-D) photographs with a typed node graph. This
//! crate is the command-line tool and re-exports the two libraries it glues:
//! [`graph`] (values, documents, the cached scheduler) and [`nodes`] (the
//! algorithms). The binary only parses arguments and prints.

pub use depthgraph_graph as graph;
pub use depthgraph_nodes as nodes;

pub mod backend;
pub mod evaluation;
pub mod fuzzing;
pub mod metrics;
pub mod sweep;

use std::path::{Path, PathBuf};

use depthgraph_graph::prelude::*;

/// Failures of loading a pipeline file.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The file could not be read (the message includes the cause; it is
    /// not also the error's source, so it prints once).
    #[error("{path}: {error}")]
    Io {
        /// The pipeline file.
        path: PathBuf,
        /// Why it could not be read.
        error: std::io::Error,
    },
    #[error("{0}")]
    Check(CheckErrors),
}

/// Reads a pipeline file and applies `--set` overrides; checks nothing else.
pub fn read_document(path: &Path, sets: &[String]) -> Result<Document, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|error| LoadError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    let mut doc = Document::parse(&text, &path.display().to_string())
        .map_err(|e| LoadError::Check(CheckErrors(e)))?;
    let mut errors = Vec::new();
    for s in sets {
        if let Err(e) = doc.apply_set(s) {
            errors.push(e);
        }
    }
    if errors.is_empty() {
        Ok(doc)
    } else {
        Err(LoadError::Check(CheckErrors(errors)))
    }
}

/// Reads, overrides and checks a pipeline against the full registry.
pub fn load_pipeline(
    path: &Path,
    sets: &[String],
    reg: &Registry,
) -> Result<(Document, Pipeline), LoadError> {
    let doc = read_document(path, sets)?;
    let p = Pipeline::check(&doc, reg).map_err(|e| LoadError::Check(CheckErrors(e)))?;
    Ok((doc, p))
}

/// The default persistent cache directory: `$DEPTHGRAPH_CACHE_DIR`, else
/// `$XDG_CACHE_HOME/depthgraph`, else `~/.cache/depthgraph`, else `.depthgraph-cache`.
pub fn default_cache_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("DEPTHGRAPH_CACHE_DIR") {
        return PathBuf::from(d);
    }
    if let Some(d) = std::env::var_os("XDG_CACHE_HOME") {
        return PathBuf::from(d).join("depthgraph");
    }
    if let Some(h) = std::env::var_os("HOME") {
        return PathBuf::from(h).join(".cache").join("depthgraph");
    }
    PathBuf::from(".depthgraph-cache")
}
