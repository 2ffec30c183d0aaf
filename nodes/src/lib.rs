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
    camera::register(&mut reg)?;
    depth::register(&mut reg)?;
    imageops::register(&mut reg)?;
    io::register(&mut reg)?;
    relight::register(&mut reg)?;
    select::register(&mut reg)?;
    sim::register(&mut reg)?;
    Ok(reg)
}
