//! The shape checks of node inputs, one copy each: an image that must have
//! the size its intrinsics describe, an image that must have another's
//! size. Errors name the port and say what was expected.

use depthgraph_graph::prelude::*;

/// The intrinsics `k` on input `k_port` must be usable (finite, positive
/// focal lengths, a finite principal point) and describe an image of
/// `dims`, the size of `what` (e.g. "depth map", or the name of a port).
pub fn fits_intrinsics(
    k_port: &str,
    k: &Intrinsics,
    what: &str,
    dims: (usize, usize),
) -> Result<(), NodeError> {
    sane_intrinsics(k_port, k)?;
    if (k.width, k.height) != dims {
        return Err(NodeError::input(
            k_port,
            format!(
                "describe a {}x{} image but the {what} is {}x{}; give the Camera node the image's size",
                k.width, k.height, dims.0, dims.1
            ),
        ));
    }
    Ok(())
}

/// An image a node is about to make, `w` x `h` from `what` (a port or a
/// parameter), must fit the run's pixel budget (`--max-pixels`, as input
/// files do): a camera of 65536 x 65536 would otherwise allocate tens of
/// GiB and abort the process.
pub fn output_fits(ctx: &EvalCtx, what: &str, w: usize, h: usize) -> Result<(), NodeError> {
    match w.checked_mul(h) {
        Some(n) if n <= ctx.max_pixels => Ok(()),
        _ => Err(NodeError::input(
            what,
            format!(
                "asks for a {w}x{h} image, more than the run's {} pixels (--max-pixels)",
                ctx.max_pixels
            ),
        )),
    }
}

/// [`output_fits`] for a size a parameter (`param`) asks for: the error
/// is the parameter's (a usage error), not the input's.
pub fn output_fits_param(ctx: &EvalCtx, param: &str, w: usize, h: usize) -> Result<(), NodeError> {
    output_fits(ctx, param, w, h).map_err(|e| match e {
        NodeError::Input { message, .. } => NodeError::param(param, message),
        other => other,
    })
}

/// The intrinsics `k` on input `k_port` must be usable: finite, positive
/// focal lengths and a finite principal point.
pub fn sane_intrinsics(k_port: &str, k: &Intrinsics) -> Result<(), NodeError> {
    if k.is_sane() {
        return Ok(());
    }
    Err(NodeError::input(
        k_port,
        "expected finite, positive focal lengths and a finite principal point",
    ))
}

/// Parameter `name` must be finite and within `[lo, hi]`: for callers that
/// build a parameter struct in Rust (the pipeline checks the same range
/// before a node runs).
pub fn param_within(name: &str, v: f64, lo: f64, hi: f64) -> Result<(), NodeError> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(NodeError::param(
            name,
            format!("{v} is outside {lo}..={hi}"),
        ))
    }
}

/// The image on `port` (`what`, e.g. "a guide image") must have the size
/// `want` of the `of` image (e.g. "the depth map").
pub fn same_size(
    port: &str,
    what: &str,
    dims: (usize, usize),
    of: &str,
    want: (usize, usize),
) -> Result<(), NodeError> {
    if dims == want {
        return Ok(());
    }
    Err(NodeError::input(
        port,
        format!(
            "is {}x{} but {of} is {}x{}; expected {what} of {of}'s size",
            dims.0, dims.1, want.0, want.1
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mismatches_name_the_port_and_both_sizes() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            width: 640,
            height: 480,
        };
        assert!(fits_intrinsics("intrinsics", &k, "depth map", (640, 480)).is_ok());
        let e = fits_intrinsics("intrinsics", &k, "depth map", (320, 240))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("intrinsics") && e.contains("depth map is 320x240"),
            "{e}"
        );
        assert!(e.contains("640x480"), "{e}");
        let bad = Intrinsics { fx: f64::NAN, ..k };
        let e = fits_intrinsics("k_src", &bad, "depth map", (640, 480))
            .unwrap_err()
            .to_string();
        assert!(e.contains("k_src") && e.contains("finite"), "{e}");
        let e = same_size("color", "a guide image", (2, 2), "the depth map", (3, 3))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("color") && e.contains("2x2") && e.contains("3x3"),
            "{e}"
        );
        assert!(same_size("c", "x", (3, 3), "y", (3, 3)).is_ok());
    }
}
