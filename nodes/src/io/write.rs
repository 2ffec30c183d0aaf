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
/// A `path` that is a symbolic link stays one: the file it points to is
/// replaced (and returned).
pub fn write_atomic<E: Into<WriteFailure>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<PathBuf, NodeError> {
    // a link stays one: the file it points to is replaced
    let path = &depthgraph_graph::node::follow_links(path).map_err(|error| NodeError::Io {
        path: path.to_path_buf(),
        error,
    })?;
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

#[cfg(test)]
mod tests {
    use super::*;

    fn put(path: &Path, text: &str) -> Result<PathBuf, NodeError> {
        write_atomic(path, |tmp| fs::write(tmp, text))
    }

    #[test]
    fn a_write_replaces_the_file_and_keeps_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.txt");
        put(&p, "one").unwrap();
        assert_eq!(put(&p, "two").unwrap(), p);
        assert_eq!(fs::read_to_string(&p).unwrap(), "two");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
        // a failed write leaves the file as it was
        let e = write_atomic(&p, |_| Err(std::io::Error::other("disk full"))).unwrap_err();
        assert!(e.to_string().contains("a.txt"), "{e}");
        assert_eq!(fs::read_to_string(&p).unwrap(), "two");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[cfg(unix)]
    #[test]
    fn a_symbolic_link_stays_a_link_and_its_target_is_written() {
        use std::os::unix::fs::symlink;
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("sub/real.ron");
        fs::create_dir_all(real.parent().unwrap()).unwrap();
        fs::write(&real, "old").unwrap();
        // a relative link, through a second link
        let link = dir.path().join("link.ron");
        let link2 = dir.path().join("link2.ron");
        symlink("sub/real.ron", &link).unwrap();
        symlink("link.ron", &link2).unwrap();
        assert_eq!(put(&link2, "new").unwrap(), dir.path().join("sub/real.ron"));
        assert!(
            fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert!(
            fs::symlink_metadata(&link2)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert_eq!(fs::read_to_string(&real).unwrap(), "new");
        // a link to nowhere creates its target
        let dangling = dir.path().join("dangling.ron");
        symlink("made.ron", &dangling).unwrap();
        put(&dangling, "made").unwrap();
        assert_eq!(
            fs::read_to_string(dir.path().join("made.ron")).unwrap(),
            "made"
        );
        // a loop is an error naming the path, not a hang
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        symlink("b", &a).unwrap();
        symlink("a", &b).unwrap();
        let e = put(&a, "x").unwrap_err();
        assert!(e.to_string().contains("symbolic links"), "{e}");
    }
}
