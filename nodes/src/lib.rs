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

pub mod bilateral;
pub mod camera;
pub mod composite;
pub mod edges;
pub mod envmap;
pub mod feather;
pub mod hdr;
pub mod imageops;
pub mod io;
pub mod ism;
pub mod lasso;
pub mod lens;
pub mod mesh;
pub mod nlmeans;
pub mod paste;
pub mod pull_push;
pub mod raycast;
pub mod refocus;
pub mod relight;
pub mod relight_reference;
pub mod relight_scene;
pub mod sensor;
pub mod synthetic;
pub mod unproject;
pub mod vpl;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Every node kind of this crate.
pub fn registry() -> Result<Registry, RegistryError> {
    let mut reg = Registry::new();
    camera::register(&mut reg)?;
    io::register(&mut reg)?;
    synthetic::register(&mut reg)?;
    sensor::register(&mut reg)?;
    unproject::register(&mut reg)?;
    bilateral::register(&mut reg)?;
    mesh::register(&mut reg)?;
    pull_push::register(&mut reg)?;
    nlmeans::register(&mut reg)?;
    refocus::register(&mut reg)?;
    imageops::register(&mut reg)?;
    hdr::register(&mut reg)?;
    edges::register(&mut reg)?;
    lasso::register(&mut reg)?;
    paste::register(&mut reg)?;
    feather::register(&mut reg)?;
    composite::register(&mut reg)?;
    envmap::register(&mut reg)?;
    vpl::register(&mut reg)?;
    relight::register(&mut reg)?;
    Ok(reg)
}

/// Helpers shared by the unit tests of the node modules.
#[cfg(test)]
pub(crate) mod test_util {
    /// Runs `f` on a rayon pool of `threads` threads (the tests that a
    /// result does not depend on the thread count).
    pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("a test thread pool")
            .install(f)
    }

    /// What a node's `eval` needs in a test: a fresh cancel token, no
    /// progress, outputs under `.`, no input files.
    pub(crate) struct TestCtx {
        node: &'static str,
        cancel: depthgraph_graph::prelude::CancelToken,
    }

    impl TestCtx {
        pub(crate) fn new(node: &'static str) -> Self {
            Self {
                node,
                cancel: depthgraph_graph::prelude::CancelToken::new(),
            }
        }

        pub(crate) fn ctx(&self) -> depthgraph_graph::prelude::EvalCtx<'_> {
            depthgraph_graph::prelude::EvalCtx {
                node: self.node,
                cancel: &self.cancel,
                progress: None,
                out_dir: std::path::Path::new("."),
                input_files: &[],
            }
        }
    }
}
