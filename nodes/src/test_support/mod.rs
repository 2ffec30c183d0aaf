//! Fixtures shared by the unit tests of the node modules: thread pools,
//! evaluation contexts, small scenes. No test module imports another's.
#![cfg(test)]

pub(crate) mod relight;
/// A `w x h` camera whose focal length is `w` pixels (about 53° across)
/// with the principal point at the image's centre.
pub(crate) fn square_camera(w: usize, h: usize) -> depthgraph_graph::prelude::Intrinsics {
    depthgraph_graph::prelude::Intrinsics {
        fx: w as f64,
        fy: w as f64,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
        width: w,
        height: h,
    }
}

/// Runs `f` on a rayon pool of `threads` threads (the tests that a
/// result does not depend on the thread count).
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap_or_else(|e| panic!("no test thread pool of {threads} threads: {e}"))
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
            derivations: None,
            max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
        }
    }
}
