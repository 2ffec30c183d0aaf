//! # depthgraph
//!
//! Editing color+depth (RGB-D) photographs with a typed node graph. This
//! crate is the command-line tool and re-exports the two libraries it glues:
//! [`graph`] (values, documents, the cached scheduler) and [`nodes`] (the
//! algorithms). The binary only parses arguments and prints.

pub use depthgraph_graph as graph;
pub use depthgraph_nodes as nodes;

pub mod backend;
pub mod batch;
pub mod evaluation;
pub mod fuzzing;
pub mod metrics;
#[cfg(feature = "s3")]
pub mod remote;
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

/// Reads, overrides and checks a pipeline against the full registry; a
/// pipeline that takes a frame index runs frame 0 (with a notice).
pub fn load_pipeline(
    path: &Path,
    sets: &[String],
    reg: &Registry,
) -> Result<(Document, Pipeline), LoadError> {
    load_pipeline_frame(path, sets, None, reg)
}

/// [`load_pipeline`] for frame `frame` of a pipeline with `{frame}`
/// placeholders (`None`: frame 0, with a notice when the pipeline takes
/// one). The returned document is the frame's.
pub fn load_pipeline_frame(
    path: &Path,
    sets: &[String],
    frame: Option<u64>,
    reg: &Registry,
) -> Result<(Document, Pipeline), LoadError> {
    let doc = read_document(path, sets)?;
    let takes_frame = !doc.frame_params().is_empty();
    let mut doc = doc
        .for_frame(frame.unwrap_or(0))
        .map_err(|e| LoadError::Check(CheckErrors(e)))?;
    if takes_frame && frame.is_none() {
        doc.notices.push(
            "this pipeline takes a frame index ({frame}); running frame 0 (choose with --frame N, or run many with `depthgraph batch`)"
                .to_string(),
        );
    }
    let p = Pipeline::check(&doc, reg).map_err(|e| LoadError::Check(CheckErrors(e)))?;
    Ok((doc, p))
}

/// A `--cache-url` that cannot be used: a usage error (a bad URL, a build
/// without the `s3` feature) or a transient one (the store did not answer).
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct CacheUrlError {
    /// What is wrong, naming the URL.
    pub message: String,
    /// Usage or Transient.
    pub kind: FailureKind,
}

/// Opens the shared object-store cache of `--cache-url` (see [`remote`]).
pub fn open_cache_url(
    url: &str,
) -> Result<std::sync::Arc<dyn depthgraph_graph::cache::BlobStore>, CacheUrlError> {
    #[cfg(feature = "s3")]
    {
        remote::open(url).map_err(|e| CacheUrlError {
            kind: match e {
                remote::RemoteError::Url { .. } | remote::RemoteError::Refused { .. } => {
                    FailureKind::Usage
                }
                remote::RemoteError::Unreachable { .. } => FailureKind::Transient,
            },
            message: e.to_string(),
        })
    }
    #[cfg(not(feature = "s3"))]
    {
        Err(CacheUrlError {
            message: format!(
                "--cache-url {url}: this depthgraph was built without the `s3` feature"
            ),
            kind: FailureKind::Usage,
        })
    }
}

/// Checks a `--cache-url` without contacting the store (a Slurm
/// submission: the tasks open it where they run).
pub fn check_cache_url(url: &str) -> Result<(), CacheUrlError> {
    #[cfg(feature = "s3")]
    {
        remote::check_url(url).map_err(|e| CacheUrlError {
            kind: FailureKind::Usage,
            message: e.to_string(),
        })
    }
    #[cfg(not(feature = "s3"))]
    {
        open_cache_url(url).map(|_| ())
    }
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
