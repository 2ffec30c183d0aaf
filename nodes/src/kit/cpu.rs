//! What the CPU can run: the checks before a call of code compiled for
//! more instructions than x86-64's baseline (ARCHITECTURE.md, "Vector
//! instructions chosen at run time").

/// Whether the CPU runs code compiled with `target_feature(enable =
/// "avx512f")`, which also enables AVX2, FMA and F16C: all four are checked
/// (a virtual machine may hide some of them).
///
/// Always false in a fuzzing build (`cfg(fuzzing)`, set by cargo-fuzz):
/// LLVM's instruction selection fails on the AVX-512 loops when they are
/// compiled with sanitizer-coverage instrumentation ("Cannot select ...
/// insert_subvector v16i1" on rustc 1.97.0-nightly of 2026-05-19), so
/// those builds compile the AVX-512 versions without the target feature
/// and never call them.
#[cfg(target_arch = "x86_64")]
pub fn avx512() -> bool {
    !cfg!(fuzzing)
        && std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("f16c")
}
