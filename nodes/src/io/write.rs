//! Atomic writes: every file goes to a temporary sibling first, is flushed
//! to the disk, and is renamed into place, so a crash, a full disk or an
//! encoder error never leaves a partial file and never touches an existing
//! file of that name.

use std::fs;
use std::path::{Path, PathBuf};

use depthgraph_graph::prelude::*;

/// Why writing a file failed: the operating system's error (a full or
/// read-only disk: [`NodeError::Io`], exit code 74) or the encoder's
/// ([`NodeError::Encode`]).
#[derive(Debug)]
pub enum WriteFailure {
    /// The operating system refused a write.
    Io(std::io::Error),
    /// The encoder could not encode the value.
    Encode(String),
}

impl From<std::io::Error> for WriteFailure {
    fn from(e: std::io::Error) -> Self {
        WriteFailure::Io(e)
    }
}

impl From<String> for WriteFailure {
    fn from(e: String) -> Self {
        WriteFailure::Encode(e)
    }
}

impl From<image::ImageError> for WriteFailure {
    fn from(e: image::ImageError) -> Self {
        match e {
            image::ImageError::IoError(e) => WriteFailure::Io(e),
            other => WriteFailure::Encode(other.to_string()),
        }
    }
}

impl From<exr::error::Error> for WriteFailure {
    fn from(e: exr::error::Error) -> Self {
        match e {
            exr::error::Error::Io(e) => WriteFailure::Io(e),
            other => WriteFailure::Encode(other.to_string()),
        }
    }
}

/// Writes the file `write` produces to `path` atomically: a temporary file
/// in the same directory, synced to the disk, then renamed over the target.
/// On any failure the temporary file is removed and `path` is untouched.
pub fn write_atomic<E: Into<WriteFailure>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
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
    let tmp = parent.join(format!(
        ".{name}.{}.tmp",
        depthgraph_graph::cache::temp_suffix()
    ));
    let fail = |f: WriteFailure| {
        let _ = fs::remove_file(&tmp);
        match f {
            WriteFailure::Io(error) => NodeError::Io {
                path: path.to_path_buf(),
                error,
            },
            WriteFailure::Encode(message) => NodeError::Encode {
                path: path.to_path_buf(),
                message,
            },
        }
    };
    write(&tmp).map_err(|e| fail(e.into()))?;
    // the data on the disk before the name points at it (a full disk shows
    // here on file systems that allocate late)
    fs::OpenOptions::new()
        .write(true)
        .open(&tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| fail(WriteFailure::Io(e)))?;
    fs::rename(&tmp, path).map_err(|e| fail(WriteFailure::Io(e)))?;
    Ok(path.to_path_buf())
}
