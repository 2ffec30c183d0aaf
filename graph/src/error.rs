//! Errors with a location a person can act on.

use std::fmt;
use std::path::PathBuf;

use crate::ron_text::Pos;
use crate::value::ShapeError;
use crate::value::ValueType;

/// Where in which text something is at fault.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// A path, or `--set node.param=value` for an override.
    pub file: String,
    /// Line, from 1.
    pub line: usize,
    /// Column, from 1, counted in chars.
    pub col: usize,
}

impl Location {
    /// The location of `pos` in `file`.
    pub fn new(file: &str, pos: Pos) -> Self {
        Self {
            file: file.to_string(),
            line: pos.line,
            col: pos.col,
        }
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file, self.line, self.col)
    }
}

fn did_you_mean(s: &Option<String>) -> String {
    s.as_ref()
        .map(|s| format!(" (did you mean `{s}`?)"))
        .unwrap_or_default()
}

/// A problem found while reading or checking a pipeline.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckError {
    /// The text is not valid RON.
    #[error("{loc}: syntax error: {message}")]
    Syntax {
        /// Where the error is.
        loc: Location,
        /// The parser's message.
        message: String,
    },
    /// Valid RON that is not a pipeline document (wrong shape, unknown field,
    /// unsupported version, malformed reference...).
    #[error("{loc}: {message}")]
    Format {
        /// Where the offending value is written.
        loc: Location,
        /// What is wrong.
        message: String,
    },
    /// A node's kind is not registered.
    #[error(
        "{loc}: node `{node}`: unknown node kind `{kind}`{}",
        did_you_mean(suggestion)
    )]
    UnknownKind {
        /// Where the kind is written.
        loc: Location,
        /// The node's name.
        node: String,
        /// The unknown kind.
        kind: String,
        /// The closest registered kind, if one is close.
        suggestion: Option<String>,
    },
    /// A reference names a node the document does not have.
    #[error("{loc}: no node named `{name}`{}", did_you_mean(suggestion))]
    UnknownNode {
        /// Where the reference is written.
        loc: Location,
        /// The node name referenced.
        name: String,
        /// The closest node name, if one is close.
        suggestion: Option<String>,
    },
    /// A wire or input names a port the node does not have.
    #[error("{loc}: node `{node}` ({kind}) has no {direction} port `{port}`{}; it has: {}", did_you_mean(suggestion), available.join(", "))]
    UnknownPort {
        /// Where the port is referenced.
        loc: Location,
        /// The node that lacks the port.
        node: String,
        /// Its kind.
        kind: String,
        /// "input" or "output".
        direction: &'static str,
        /// The port name given.
        port: String,
        /// The closest port in that direction, if one is close.
        suggestion: Option<String>,
        /// Every port the node has in that direction.
        available: Vec<String>,
    },
    /// A node is given a parameter its kind does not declare.
    #[error(
        "{loc}: node `{node}` ({kind}) has no parameter `{param}`{}",
        did_you_mean(suggestion)
    )]
    UnknownParam {
        /// Where the parameter name is written.
        loc: Location,
        /// The node's name.
        node: String,
        /// Its kind.
        kind: String,
        /// The parameter name given.
        param: String,
        /// The closest declared parameter, if one is close.
        suggestion: Option<String>,
    },
    /// A parameter value of the wrong type or out of range.
    #[error("{loc}: node `{node}` parameter `{param}`: {message}")]
    BadParam {
        /// Where the value is written.
        loc: Location,
        /// The node's name.
        node: String,
        /// The parameter.
        param: String,
        /// What is wrong with the value.
        message: String,
    },
    /// A wire whose source type cannot feed the input it is connected to.
    #[error(
        "{loc}: node `{node}` input `{port}` expects {expected}, but `{source_ref}` is {found}"
    )]
    TypeMismatch {
        /// Where the source reference is written.
        loc: Location,
        /// The consuming node.
        node: String,
        /// Its input port.
        port: String,
        /// The type the input takes.
        expected: ValueType,
        /// The type the source output produces.
        found: ValueType,
        /// The source as written (`"node.port"`).
        source_ref: String,
    },
    /// A required input is not connected.
    #[error("{loc}: node `{node}` ({kind}) needs input `{port}` ({ty}), which is not connected")]
    MissingInput {
        /// Where the node's name is written.
        loc: Location,
        /// The node's name.
        node: String,
        /// Its kind.
        kind: String,
        /// The unconnected input port.
        port: String,
        /// The type it takes.
        ty: ValueType,
    },
    /// The wires form a cycle.
    #[error("{loc}: cycle: {}", path.join(" -> "))]
    Cycle {
        /// Where the cycle's first node (in file order) is declared.
        loc: Location,
        /// Names of the nodes along the cycle.
        path: Vec<String>,
    },
}

impl CheckError {
    /// Where the problem is written.
    pub fn location(&self) -> &Location {
        match self {
            CheckError::Syntax { loc, .. }
            | CheckError::Format { loc, .. }
            | CheckError::UnknownKind { loc, .. }
            | CheckError::UnknownNode { loc, .. }
            | CheckError::UnknownPort { loc, .. }
            | CheckError::UnknownParam { loc, .. }
            | CheckError::BadParam { loc, .. }
            | CheckError::TypeMismatch { loc, .. }
            | CheckError::MissingInput { loc, .. }
            | CheckError::Cycle { loc, .. } => loc,
        }
    }
    /// The node the error concerns, when there is one (the editor marks it).
    pub fn node(&self) -> Option<&str> {
        match self {
            CheckError::UnknownKind { node, .. }
            | CheckError::UnknownPort { node, .. }
            | CheckError::UnknownParam { node, .. }
            | CheckError::BadParam { node, .. }
            | CheckError::TypeMismatch { node, .. }
            | CheckError::MissingInput { node, .. } => Some(node),
            CheckError::Cycle { path, .. } => path.first().map(String::as_str),
            _ => None,
        }
    }
}

/// All the problems of one document, one per line.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckErrors(pub Vec<CheckError>);

impl fmt::Display for CheckErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "error: {e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for CheckErrors {}

/// A failure while running a checked pipeline.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// A node failed; the message is the node's error, printed once (it
    /// is not also returned as the error's source).
    #[error("node `{node}` ({kind}): {error}")]
    Node {
        /// The node's name in the pipeline.
        node: String,
        /// Its kind.
        kind: String,
        /// What went wrong.
        error: NodeError,
    },
    /// A node returned without a value on one of its declared outputs.
    #[error("node `{node}` ({kind}) did not produce its declared output `{port}`")]
    MissingOutput {
        /// The node's name in the pipeline.
        node: String,
        /// Its kind.
        kind: String,
        /// The missing output port.
        port: String,
    },
    /// A node produced a value of another type than its output declares.
    #[error("node `{node}` ({kind}) produced {found} on output `{port}`, declared {expected}")]
    WrongOutputType {
        /// The node's name in the pipeline.
        node: String,
        /// Its kind.
        kind: String,
        /// The output port.
        port: String,
        /// The declared type.
        expected: ValueType,
        /// The type produced.
        found: ValueType,
    },
    /// The run was cancelled through its [`CancelToken`](crate::node::CancelToken).
    #[error("run cancelled")]
    Cancelled,
    /// The worker thread pool could not be built; the message is the pool's error.
    #[error("cannot start worker threads: {0}")]
    Threads(String),
}

/// Errors a node reports. The scheduler adds the node's name and kind
/// ([`RunError::Node`]). Every message names what it is about (port,
/// parameter or file) and is complete by itself: no variant also returns
/// its cause as [`source`](std::error::Error::source), so a printer that
/// walks the chain prints each part once.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// An input is missing, mistyped or unusable.
    #[error("input `{port}`: {message}")]
    Input {
        /// The input port.
        port: String,
        /// What is wrong with it.
        message: String,
    },
    /// A parameter value that the schema's range admits but the node cannot use.
    #[error("parameter `{param}`: {message}")]
    Param {
        /// The parameter.
        param: String,
        /// What is wrong with it.
        message: String,
    },
    /// An input file could not be read (missing, unreadable, a
    /// directory): the input's fault, exit code 65, unless the operating
    /// system calls it transient (75).
    #[error("{path}: {error}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        error: std::io::Error,
    },
    /// A file could not be written (or another I/O operation failed).
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        error: std::io::Error,
    },
    /// A file was read but its contents are not what the node expects.
    #[error("{path}: cannot decode: {message}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// What was expected and found.
        message: String,
    },
    /// A result could not be encoded into a file.
    #[error("{path}: cannot encode: {message}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// A sink was asked to write over a file the pipeline reads.
    #[error("{path}: refusing to write over a file this pipeline reads")]
    WouldOverwriteInput {
        /// The file.
        path: PathBuf,
    },
    /// A buffer whose length does not match its image's dimensions (an
    /// internal inconsistency, reported instead of a panic).
    #[error("{0}")]
    Shape(#[from] ShapeError),
    /// The compute device failed (out of device memory, a lost device, a
    /// kernel the driver rejected); the CPU backend (`--backend cpu`) runs
    /// the same node without it.
    #[error("{adapter}: {message}")]
    Device {
        /// The adapter that failed.
        adapter: String,
        /// What failed.
        message: String,
    },
    /// Anything else about the inputs, with its explanation.
    #[error("{0}")]
    Invalid(String),
    /// An internal inconsistency (a bug to report, exit code 70): a backend
    /// that returned results of another size than asked, a buffer that
    /// does not match its image.
    #[error("internal error: {0}")]
    Internal(String),
    /// The run was cancelled.
    #[error("cancelled")]
    Cancelled,
}

impl NodeError {
    /// An error of input `port`.
    pub fn input(port: &str, message: impl Into<String>) -> Self {
        NodeError::Input {
            port: port.to_string(),
            message: message.into(),
        }
    }
    /// An error of parameter `param`.
    pub fn param(param: &str, message: impl Into<String>) -> Self {
        NodeError::Param {
            param: param.to_string(),
            message: message.into(),
        }
    }
    /// An error reading the input file `path`.
    pub fn read(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        NodeError::Read {
            path: path.into(),
            error,
        }
    }
    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        NodeError::Io {
            path: path.into(),
            error,
        }
    }
    /// A decoding error of `path`.
    pub fn decode(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        NodeError::Decode {
            path: path.into(),
            message: message.into(),
        }
    }
    /// An encoding error of `path`.
    pub fn encode(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        NodeError::Encode {
            path: path.into(),
            message: message.into(),
        }
    }
}

/// What kind of failure an error is, so a caller can decide what to do next
/// (a batch runner retries only [`FailureKind::Transient`] ones). Each kind
/// has one process exit code, from BSD's `sysexits.h`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FailureKind {
    /// A bad command line, a pipeline that fails its check, a parameter a
    /// node cannot use, a sink told to overwrite an input. Exit code 2.
    Usage,
    /// Bad input data: a missing, unreadable, corrupt or out-of-range input
    /// file, or inputs a node cannot use. Permanent: a retry fails alike.
    /// Exit code 65 (`EX_DATAERR`).
    Data,
    /// The requested compute device does not exist. Exit code 69
    /// (`EX_UNAVAILABLE`).
    Unavailable,
    /// An internal inconsistency (a bug to report). Exit code 70
    /// (`EX_SOFTWARE`).
    Internal,
    /// An input/output error that is not the input's fault: a full disk,
    /// a read-only or missing output directory, a file that cannot be
    /// encoded. Exit code 74 (`EX_IOERR`).
    Io,
    /// A failure a retry may not meet again: a lost or out-of-memory
    /// device, an interrupted or timed-out operation, a cancelled run, no
    /// threads to be had. Exit code 75 (`EX_TEMPFAIL`).
    Transient,
}

impl FailureKind {
    /// The process exit code of this kind of failure.
    pub const fn exit_code(self) -> u8 {
        match self {
            FailureKind::Usage => 2,
            FailureKind::Data => 65,
            FailureKind::Unavailable => 69,
            FailureKind::Internal => 70,
            FailureKind::Io => 74,
            FailureKind::Transient => 75,
        }
    }

    /// The kind of an operating-system error met writing a file (or
    /// anything but reading an input): interrupted, busy or timed-out
    /// operations are transient; the rest (permissions, a full or
    /// read-only disk, a path through a non-directory) is I/O.
    pub fn of_io(e: &std::io::Error) -> Self {
        if Self::transient(e) {
            FailureKind::Transient
        } else {
            FailureKind::Io
        }
    }

    /// The kind of an operating-system error met reading an input file:
    /// transient as in [`FailureKind::of_io`], else the input's fault
    /// (missing, unreadable, a directory).
    pub fn of_read(e: &std::io::Error) -> Self {
        if Self::transient(e) {
            FailureKind::Transient
        } else {
            FailureKind::Data
        }
    }

    fn transient(e: &std::io::Error) -> bool {
        use std::io::ErrorKind as K;
        matches!(
            e.kind(),
            K::Interrupted
                | K::WouldBlock
                | K::TimedOut
                | K::ResourceBusy
                | K::ConnectionReset
                | K::ConnectionAborted
                | K::ConnectionRefused
                | K::NotConnected
                | K::OutOfMemory
        )
    }
}

impl NodeError {
    /// What kind of failure this is ([`FailureKind`]).
    pub fn kind(&self) -> FailureKind {
        match self {
            NodeError::Input { .. } | NodeError::Decode { .. } | NodeError::Invalid(_) => {
                FailureKind::Data
            }
            NodeError::Param { .. } | NodeError::WouldOverwriteInput { .. } => FailureKind::Usage,
            NodeError::Read { error, .. } => FailureKind::of_read(error),
            NodeError::Io { error, .. } => FailureKind::of_io(error),
            NodeError::Encode { .. } => FailureKind::Io,
            NodeError::Shape(_) | NodeError::Internal(_) => FailureKind::Internal,
            NodeError::Device { .. } | NodeError::Cancelled => FailureKind::Transient,
        }
    }
}

impl RunError {
    /// What kind of failure this is ([`FailureKind`]).
    pub fn kind(&self) -> FailureKind {
        match self {
            RunError::Node { error, .. } => error.kind(),
            RunError::MissingOutput { .. } | RunError::WrongOutputType { .. } => {
                FailureKind::Internal
            }
            RunError::Cancelled | RunError::Threads(_) => FailureKind::Transient,
        }
    }
}

#[cfg(test)]
mod failure_kind_tests {
    use super::*;

    #[test]
    fn every_node_error_maps_to_its_documented_code() {
        let io = |k| NodeError::io("f", std::io::Error::from(k));
        let read = |k| NodeError::read("f", std::io::Error::from(k));
        use std::io::ErrorKind as K;
        let cases: Vec<(NodeError, u8)> = vec![
            (NodeError::input("depth", "x"), 65),
            (NodeError::decode("f", "x"), 65),
            (NodeError::Invalid("x".into()), 65),
            (NodeError::param("radius", "x"), 2),
            (NodeError::WouldOverwriteInput { path: "f".into() }, 2),
            (read(K::NotFound), 65),
            (read(K::PermissionDenied), 65),
            (read(K::IsADirectory), 65),
            (read(K::TimedOut), 75),
            (io(K::NotFound), 74),
            (io(K::PermissionDenied), 74),
            (io(K::StorageFull), 74),
            (io(K::NotADirectory), 74),
            (io(K::Interrupted), 75),
            (io(K::TimedOut), 75),
            (NodeError::encode("f", "x"), 74),
            (NodeError::Internal("x".into()), 70),
            (
                NodeError::Shape(ShapeError {
                    width: 2,
                    height: 2,
                    expected: 4,
                    found: 3,
                }),
                70,
            ),
            (
                NodeError::Device {
                    adapter: "a".into(),
                    message: "lost".into(),
                },
                75,
            ),
            (NodeError::Cancelled, 75),
        ];
        for (e, code) in cases {
            assert_eq!(e.kind().exit_code(), code, "{e}");
        }
        let wrapped = RunError::Node {
            node: "n".into(),
            kind: "K".into(),
            error: NodeError::decode("f", "x"),
        };
        assert_eq!(wrapped.kind().exit_code(), 65);
        assert_eq!(RunError::Cancelled.kind().exit_code(), 75);
        assert_eq!(
            RunError::MissingOutput {
                node: "n".into(),
                kind: "K".into(),
                port: "p".into()
            }
            .kind()
            .exit_code(),
            70
        );
    }
}
