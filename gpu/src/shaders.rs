//! The WGSL sources, each prefixed with `common.wgsl` (and the NL-means
//! kernels with `nlmeans_acc.wgsl`, the running sums they share; the
//! relighting kernels with `relight_maps.wgsl`, their shadow-map lookups).

const COMMON: &str = include_str!("shaders/common.wgsl");
const NLMEANS_ACC: &str = include_str!("shaders/nlmeans_acc.wgsl");
const RELIGHT_MAPS: &str = include_str!("shaders/relight_maps.wgsl");

/// A kernel's source and entry point.
#[derive(Debug, Clone, Copy)]
pub struct Kernel {
    /// Pipeline-cache name.
    pub name: &'static str,
    /// The file's WGSL (without the common prefix).
    pub body: &'static str,
    /// Entry point.
    pub entry: &'static str,
    /// Shared WGSL between the common helpers and the body (or nothing).
    pub shared: &'static str,
}

impl Kernel {
    /// The full source: the common helpers, the shared part, then the body.
    pub fn source(&self) -> String {
        format!("{COMMON}\n{}\n{}", self.shared, self.body)
    }
}

macro_rules! kernel {
    ($name:ident, $file:literal, $entry:literal) => {
        kernel!($name, $file, $entry, "");
    };
    ($name:ident, $file:literal, $entry:literal, $shared:expr) => {
        #[doc = concat!("`", $file, "`, entry `", $entry, "`.")]
        pub const $name: Kernel = Kernel {
            name: concat!($file, "::", $entry),
            body: include_str!(concat!("shaders/", $file)),
            entry: $entry,
            shared: $shared,
        };
    };
}

kernel!(BILATERAL_ENCODE, "bilateral_encode.wgsl", "main");
kernel!(BILATERAL, "bilateral.wgsl", "main");
kernel!(REFOCUS_CLEAR, "refocus.wgsl", "clear");
kernel!(REFOCUS_WARP_DEPTH, "refocus.wgsl", "warp_depth");
kernel!(REFOCUS_WARP_INDEX, "refocus.wgsl", "warp_index");
kernel!(REFOCUS_GATHER, "refocus.wgsl", "gather");
kernel!(REFOCUS_FILL, "refocus.wgsl", "fill_accumulate");
kernel!(REFOCUS_FILL_STORE, "refocus.wgsl", "fill_store");
kernel!(REFOCUS_ACCUMULATE_SPLIT, "refocus.wgsl", "accumulate_split");
kernel!(REFOCUS_FINISH, "refocus.wgsl", "finish");
kernel!(PULL_PUSH_INIT, "pull_push.wgsl", "init");
kernel!(PULL_PUSH_PULL, "pull_push.wgsl", "pull");
kernel!(PULL_PUSH_PUSH, "pull_push.wgsl", "push");
kernel!(PULL_PUSH_FINISH, "pull_push.wgsl", "finish");
kernel!(FEATHER_HORIZONTAL, "feather.wgsl", "horizontal");
kernel!(FEATHER_VERTICAL, "feather.wgsl", "vertical");
kernel!(EDGES, "edges.wgsl", "main");
kernel!(COMPOSITE, "composite.wgsl", "main");
kernel!(NLMEANS, "nlmeans.wgsl", "main", NLMEANS_ACC);
kernel!(RELIGHT_DIRECT, "relight_direct.wgsl", "main", RELIGHT_MAPS);
kernel!(RELIGHT_OBJECT, "relight_object.wgsl", "main", RELIGHT_MAPS);
kernel!(RELIGHT_FILL, "relight_fill.wgsl", "main");
kernel!(
    NLMEANS_UPSAMPLE,
    "nlmeans_upsample.wgsl",
    "main",
    NLMEANS_ACC
);

/// Every kernel (the test that compiles them all reads this list).
pub const ALL: &[Kernel] = &[
    BILATERAL_ENCODE,
    BILATERAL,
    REFOCUS_CLEAR,
    REFOCUS_WARP_DEPTH,
    REFOCUS_WARP_INDEX,
    REFOCUS_GATHER,
    REFOCUS_FILL,
    REFOCUS_FILL_STORE,
    REFOCUS_ACCUMULATE_SPLIT,
    REFOCUS_FINISH,
    PULL_PUSH_INIT,
    PULL_PUSH_PULL,
    PULL_PUSH_PUSH,
    PULL_PUSH_FINISH,
    FEATHER_HORIZONTAL,
    FEATHER_VERTICAL,
    EDGES,
    COMPOSITE,
    NLMEANS,
    NLMEANS_UPSAMPLE,
    RELIGHT_DIRECT,
    RELIGHT_OBJECT,
    RELIGHT_FILL,
];
