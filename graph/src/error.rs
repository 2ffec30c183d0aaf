//! Errors with a location a person can act on.

use std::fmt;

use crate::node::NodeError;
use crate::ron_text::Pos;
use crate::value::ValueType;

/// Where in which text something is at fault.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// A path, or `--set node.param=value` for an override.
    pub file: String,
    pub line: usize,
    pub col: usize,
}

impl Location {
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
    #[error("{loc}: syntax error: {message}")]
    Syntax { loc: Location, message: String },
    #[error("{loc}: {message}")]
    Format { loc: Location, message: String },
    #[error(
        "{loc}: node `{node}`: unknown node kind `{kind}`{}",
        did_you_mean(suggestion)
    )]
    UnknownKind {
        loc: Location,
        node: String,
        kind: String,
        suggestion: Option<String>,
    },
    #[error("{loc}: no node named `{name}`{}", did_you_mean(suggestion))]
    UnknownNode {
        loc: Location,
        name: String,
        suggestion: Option<String>,
    },
    #[error("{loc}: node `{node}` ({kind}) has no {direction} port `{port}`{}; it has: {}", did_you_mean(suggestion), available.join(", "))]
    UnknownPort {
        loc: Location,
        node: String,
        kind: String,
        /// "input" or "output".
        direction: &'static str,
        port: String,
        suggestion: Option<String>,
        available: Vec<String>,
    },
    #[error(
        "{loc}: node `{node}` ({kind}) has no parameter `{param}`{}",
        did_you_mean(suggestion)
    )]
    UnknownParam {
        loc: Location,
        node: String,
        kind: String,
        param: String,
        suggestion: Option<String>,
    },
    #[error("{loc}: node `{node}` parameter `{param}`: {message}")]
    BadParam {
        loc: Location,
        node: String,
        param: String,
        message: String,
    },
    #[error(
        "{loc}: node `{node}` input `{port}` expects {expected}, but `{source_ref}` is {found}"
    )]
    TypeMismatch {
        loc: Location,
        node: String,
        port: String,
        expected: ValueType,
        found: ValueType,
        source_ref: String,
    },
    #[error("{loc}: node `{node}` ({kind}) needs input `{port}` ({ty}), which is not connected")]
    MissingInput {
        loc: Location,
        node: String,
        kind: String,
        port: String,
        ty: ValueType,
    },
    #[error("{loc}: cycle: {}", path.join(" -> "))]
    Cycle { loc: Location, path: Vec<String> },
}

impl CheckError {
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
    #[error("node `{node}` ({kind}): {source}")]
    Node {
        node: String,
        kind: String,
        #[source]
        source: NodeError,
    },
    #[error("node `{node}` ({kind}) did not produce its declared output `{port}`")]
    MissingOutput {
        node: String,
        kind: String,
        port: String,
    },
    #[error("node `{node}` ({kind}) produced {found} on output `{port}`, declared {expected}")]
    WrongOutputType {
        node: String,
        kind: String,
        port: String,
        expected: ValueType,
        found: ValueType,
    },
    #[error("run cancelled")]
    Cancelled,
    #[error("cannot start worker threads: {0}")]
    Threads(String),
}
