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

/// The versions of a hot loop (ARCHITECTURE.md, "Vector instructions
/// chosen at run time"): given the signature of `$name`, the names of its
/// two compiled copies and of the `#[inline(always)]` function `$body`
/// that does the work, it writes `$name`, which calls the best copy the
/// CPU runs, `$avx2` (compiled with AVX2) and `$avx512` (with AVX-512 F,
/// not in a fuzzing build: [`avx512`]). Each copy does the body's
/// operations in the same order, so all give the same bits; the tests
/// call the copies by name and compare them with the body.
///
/// Two forms: a method of `&self`, or a free function with one type
/// parameter. Arguments are plain names (`rows: (usize, usize)`).
macro_rules! simd_versions {
    (
        $(#[$m:meta])*
        $vis:vis fn $name:ident(&self $(, $a:ident: $t:ty)* $(,)?) $(-> $r:ty)?;
        avx2: $avx2:ident, avx512: $avx512:ident, body: $body:ident $(,)?
    ) => {
        $(#[$m])*
        $vis fn $name(&self $(, $a: $t)*) $(-> $r)? {
            #[cfg(target_arch = "x86_64")]
            if $crate::kit::cpu::avx512() {
                // SAFETY: the copy needs AVX-512 F and what it implies
                // (AVX2, FMA, F16C), which the CPU was just found to have.
                return unsafe { self.$avx512($($a),*) };
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the copy only needs AVX2, which the CPU was just
                // found to have.
                return unsafe { self.$avx2($($a),*) };
            }
            self.$body($($a),*)
        }

        #[doc = concat!("`", stringify!($body), "` compiled with AVX2.")]
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        $vis unsafe fn $avx2(&self $(, $a: $t)*) $(-> $r)? {
            self.$body($($a),*)
        }

        #[doc = concat!("`", stringify!($body), "` compiled with AVX-512 F.")]
        #[cfg(target_arch = "x86_64")]
        #[cfg_attr(not(fuzzing), target_feature(enable = "avx512f"))]
        $vis unsafe fn $avx512(&self $(, $a: $t)*) $(-> $r)? {
            self.$body($($a),*)
        }
    };
    (
        $(#[$m:meta])*
        $vis:vis fn $name:ident<$g:ident: $bound:path>($($a:ident: $t:ty),* $(,)?) $(-> $r:ty)?;
        avx2: $avx2:ident, avx512: $avx512:ident, body: $body:ident $(,)?
    ) => {
        $(#[$m])*
        $vis fn $name<$g: $bound>($($a: $t),*) $(-> $r)? {
            #[cfg(target_arch = "x86_64")]
            if $crate::kit::cpu::avx512() {
                // SAFETY: the copy needs AVX-512 F and what it implies
                // (AVX2, FMA, F16C), which the CPU was just found to have.
                return unsafe { $avx512($($a),*) };
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the copy only needs AVX2, which the CPU was just
                // found to have.
                return unsafe { $avx2($($a),*) };
            }
            $body($($a),*)
        }

        #[doc = concat!("`", stringify!($body), "` compiled with AVX2.")]
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        $vis unsafe fn $avx2<$g: $bound>($($a: $t),*) $(-> $r)? {
            $body($($a),*)
        }

        #[doc = concat!("`", stringify!($body), "` compiled with AVX-512 F.")]
        #[cfg(target_arch = "x86_64")]
        #[cfg_attr(not(fuzzing), target_feature(enable = "avx512f"))]
        $vis unsafe fn $avx512<$g: $bound>($($a: $t),*) $(-> $r)? {
            $body($($a),*)
        }
    };
}
pub(crate) use simd_versions;
