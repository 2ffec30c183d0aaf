//! Atomic writes: every file goes to a temporary sibling first and is
//! renamed into place, so a crash never leaves a partial file.

use std::fs;
use std::path::{Path, PathBuf};

use depthgraph_graph::prelude::*;

/// Writes `bytes` produced by `write` to `path` atomically: a temporary file
/// in the same directory, flushed, then renamed over the target.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<PathBuf, NodeError> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    fs::create_dir_all(&parent).map_err(|source| NodeError::Io {
        path: parent.clone(),
        error: source,
    })?;
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    let tmp = parent.join(format!(".{name}.{}.tmp", std::process::id()));
    if let Err(message) = write(&tmp) {
        let _ = fs::remove_file(&tmp);
        return Err(NodeError::Encode {
            path: path.to_path_buf(),
            message,
        });
    }
    fs::rename(&tmp, path).map_err(|source| {
        let _ = fs::remove_file(&tmp);
        NodeError::Io {
            path: path.to_path_buf(),
            error: source,
        }
    })?;
    Ok(path.to_path_buf())
}
