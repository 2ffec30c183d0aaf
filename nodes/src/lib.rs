//! # depthgraph-nodes
//!
//! The stages of depthgraph's two pipelines. Each module is one concept: its
//! algorithm is a plain public function (usable on plain arrays without the
//! graph), with a parameter struct and doc comments citing the paper's
//! equations, and a thin [`Node`](depthgraph_graph::node::Node) adapter
//! registered by the module's `register` function.
//!
//! Adding a node: write `src/<concept>.rs` with the function, its
//! `node_params!` struct and a `register` function, then add one line to
//! [`registry`].

#![warn(missing_docs)]

pub mod camera;
pub mod depth;
pub mod imageops;
pub mod io;
pub mod kit;
pub mod relight;
pub mod select;
pub mod sim;
#[cfg(test)]
pub(crate) mod test_support;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Every node kind of this crate.
pub fn registry() -> Result<Registry, RegistryError> {
    let mut reg = Registry::new();
    for (_, register) in STAGES {
        register(&mut reg)?;
    }
    Ok(reg)
}

/// A module's `register` function.
type Register = fn(&mut Registry) -> Result<(), RegistryError>;

/// The pipeline stages, one per module; [`registry`] registers each.
const STAGES: [(&str, Register); 7] = [
    ("camera", camera::register),
    ("depth", depth::register),
    ("image", imageops::register),
    ("input/output", io::register),
    ("relighting", relight::register),
    ("selection", select::register),
    ("simulation", sim::register),
];

/// The node kinds of each pipeline stage (its module), for a user interface
/// that groups or colours nodes by stage.
pub fn stages() -> Result<Vec<(&'static str, Vec<&'static str>)>, RegistryError> {
    STAGES
        .iter()
        .map(|(name, register)| {
            let mut reg = Registry::new();
            register(&mut reg)?;
            Ok((*name, reg.kinds().collect()))
        })
        .collect()
}

#[cfg(test)]
mod stage_tests {
    #[test]
    fn every_kind_has_exactly_one_stage() {
        let reg = super::registry().expect("registry");
        let stages = super::stages().expect("stages");
        let mut all: Vec<&str> = stages.iter().flat_map(|(_, k)| k.iter().copied()).collect();
        let n = all.len();
        all.sort_unstable();
        all.dedup();
        assert_eq!(all.len(), n, "a kind in two stages");
        let kinds: Vec<&str> = reg.kinds().collect();
        assert_eq!(all, kinds);
        let refocus = stages
            .iter()
            .find(|(_, k)| k.contains(&"Refocus"))
            .map(|(s, _)| *s);
        assert_eq!(refocus, Some("camera"));
    }
}
