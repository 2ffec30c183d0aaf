//! `OcclusionComposite`: blends a pasted layer into the target with a
//! per-pixel depth test (3d-editing §IV: "Occlusion is handled with depth
//! value comparisons [...] If a depth pixel of source object has deeper
//! value than that of target image, it means that the pixel of source object
//! should be occluded by that of target image. Then we select target image
//! color value instead of source image color value in that pixel", and
//! §III.C: the mask "is used as blending weights between source and target
//! images", "blended with the target image in both color and depth layers").
//!
//! Per pixel, with `a` the pasted alpha (clamped to `[0, 1]`, NaN = 0),
//! `z_p` the pasted depth and `z_t` the target's:
//!
//! 1. **Depth test**: `a = 0` when `z_p` is not a measurement (nothing was
//!    pasted there), or when `z_t` is valid and `z_p > z_t * (1 + tolerance_rel)`
//!    (the pasted point is behind the target surface). A target hole hides
//!    nothing: the pasted pixel shows.
//! 2. **Blend**: `color = a C_p + (1 - a) C_t`; `depth = a z_p + (1 - a) z_t`
//!    where `z_t` is valid, `z_p` where it is a hole (and `a > 0`), `z_t`
//!    unchanged where `a = 0`. Pixels with `a = 0` keep the target's values
//!    bit for bit, and `a = 1` gives the pasted values exactly.
//!
//! The output `alpha` is `a` after the depth test: the relighting stage
//! (differential rendering, §IV.A eq. 5) needs exactly where the object is seen.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use rayon::prelude::*;

node_params! {
    /// Parameters of `OcclusionComposite`.
    pub struct CompositeParams {
        /// Relative depth tolerance of the test: the pasted pixel is hidden when
        /// z_pasted > z_target * (1 + tolerance_rel). 0 is the paper's strict
        /// comparison; a little avoids z-fighting where an object rests on a surface.
        pub tolerance_rel: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1.0 };
    }
}

/// Result of [`occlusion_composite`].
#[derive(Debug, Clone, PartialEq)]
pub struct Composite {
    /// Blended colour `a C_p + (1 - a) C_t`, linear RGB.
    pub color: ColorImage,
    /// Blended depth in metres (module docs); 0 where neither layer has a
    /// measurement.
    pub depth: DepthMap,
    /// Alpha after the depth test.
    pub alpha: Mask,
}

/// Checks that an input has the target color's size (both backends).
pub fn same(port: &str, dims: (usize, usize), want: (usize, usize)) -> Result<(), NodeError> {
    if dims != want {
        return Err(NodeError::input(
            port,
            format!(
                "is {}x{} but the target color is {}x{}",
                dims.0, dims.1, want.0, want.1
            ),
        ));
    }
    Ok(())
}

/// One pixel of the composite (see the module docs): target color and
/// depth, pasted color, depth and alpha, tolerance; returns color, depth
/// and the alpha after the depth test.
#[inline]
pub fn pixel(tc: Rgb, tz: f32, pc: Rgb, pz: f32, pa: f32, tol: f64) -> (Rgb, f32, f32) {
    let mut a = if pa.is_nan() { 0.0 } else { pa.clamp(0.0, 1.0) };
    if !DepthMap::is_valid(pz) {
        a = 0.0;
    }
    let t_valid = DepthMap::is_valid(tz);
    if a > 0.0 && t_valid && pz as f64 > tz as f64 * (1.0 + tol) {
        a = 0.0;
    }
    if a <= 0.0 {
        return (tc, tz, 0.0);
    }
    if a >= 1.0 {
        return (pc, pz, 1.0);
    }
    let b = 1.0 - a;
    let color = std::array::from_fn(|c| a * pc[c] + b * tc[c]);
    let depth = if t_valid { a * pz + b * tz } else { pz };
    (color, depth, a)
}

/// Checks the sizes of the five images and the tolerance (both backends).
pub fn check_inputs(
    target_color: &ColorImage,
    target_depth: &DepthMap,
    pasted_color: &ColorImage,
    pasted_depth: &DepthMap,
    pasted_alpha: &Mask,
    p: &CompositeParams,
) -> Result<(), NodeError> {
    let want = target_color.dims();
    same("target_depth", target_depth.dims(), want)?;
    same("pasted_color", pasted_color.dims(), want)?;
    same("pasted_depth", pasted_depth.dims(), want)?;
    same("pasted_alpha", pasted_alpha.dims(), want)?;
    if !(p.tolerance_rel.is_finite() && p.tolerance_rel >= 0.0) {
        return Err(NodeError::param(
            "tolerance_rel",
            format!("{} must be finite and >= 0", p.tolerance_rel),
        ));
    }
    Ok(())
}

/// Why `OcclusionComposite` passes the target through, when nothing is
/// pasted (both backends); `None` when something is.
pub fn nothing_pasted(alpha: &Mask) -> Option<&'static str> {
    alpha
        .as_slice()
        .iter()
        .all(|a| a.is_nan() || *a <= 0.0)
        .then_some("nothing pasted: the pasted alpha is 0 everywhere")
}

/// Composites the pasted layer over the target (3d-editing §IV and §III.C);
/// see the module docs. All five images must have one size.
pub fn occlusion_composite(
    target_color: &ColorImage,
    target_depth: &DepthMap,
    pasted_color: &ColorImage,
    pasted_depth: &DepthMap,
    pasted_alpha: &Mask,
    p: &CompositeParams,
) -> Result<Composite, NodeError> {
    check_inputs(
        target_color,
        target_depth,
        pasted_color,
        pasted_depth,
        pasted_alpha,
        p,
    )?;
    let (w, h) = target_color.dims();
    let px: Vec<(Rgb, f32, f32)> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            pixel(
                target_color.as_slice()[i],
                target_depth.as_slice()[i],
                pasted_color.as_slice()[i],
                pasted_depth.as_slice()[i],
                pasted_alpha.as_slice()[i],
                p.tolerance_rel,
            )
        })
        .collect();
    let mut color = Vec::with_capacity(w * h);
    let mut depth = Vec::with_capacity(w * h);
    let mut alpha = Vec::with_capacity(w * h);
    for (c, z, a) in px {
        color.push(c);
        depth.push(z);
        alpha.push(a);
    }
    Ok(Composite {
        color: Image::from_vec(w, h, color)?,
        depth: Image::from_vec(w, h, depth)?,
        alpha: Image::from_vec(w, h, alpha)?,
    })
}

depthgraph_graph::ports! {
    /// Inputs of `OcclusionComposite`.
    inputs struct CompositeIn {
        /// linear RGB of the target
        target_color: Arc<ColorImage>,
        /// metres; holes hide nothing
        target_depth: Arc<DepthMap>,
        /// Paste.color
        pasted_color: Arc<ColorImage>,
        /// Paste.depth (0 where nothing was pasted)
        pasted_depth: Arc<DepthMap>,
        /// Paste.mask, usually feathered
        pasted_alpha: Arc<Mask>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `OcclusionComposite`.
    outputs struct CompositeOut {
        /// the composite, linear RGB
        color: Arc<ColorImage>,
        /// the composite depth, metres
        depth: Arc<DepthMap>,
        /// pasted alpha after the depth test
        alpha: Mask,
    }
}

/// The target passed through when nothing is pasted (both backends).
pub fn passthrough(i: &CompositeIn) -> Result<Option<Produced<CompositeOut>>, NodeError> {
    let (tc, td, pa) = (&i.target_color, &i.target_depth, &i.pasted_alpha);
    let Some(why) = nothing_pasted(pa) else {
        return Ok(None);
    };
    same("target_depth", td.dims(), tc.dims())?;
    same("pasted_alpha", pa.dims(), tc.dims())?;
    let out = CompositeOut {
        color: tc.clone(),
        depth: DepthMap::canonical_holes(td),
        alpha: Mask::filled(tc.width(), tc.height(), 0.0),
    };
    Ok(Some(Produced::passthrough(out, why)))
}

fn eval(
    _: &EvalCtx,
    i: CompositeIn,
    p: &CompositeParams,
) -> Result<Produced<CompositeOut>, NodeError> {
    let (tc, td, pa) = (&i.target_color, &i.target_depth, &i.pasted_alpha);
    if let Some(out) = passthrough(&i)? {
        return Ok(out);
    }
    let r = occlusion_composite(tc, td, &i.pasted_color, &i.pasted_depth, pa, p)?;
    Ok(CompositeOut {
        color: Arc::new(r.color),
        depth: DepthMap::canonical_holes(&Arc::new(r.depth)),
        alpha: r.alpha,
    }
    .into())
}

/// Registers `OcclusionComposite`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "OcclusionComposite",
        1,
        "Blends a pasted layer into the target by alpha in color and depth, after a per-pixel depth test \
         (3d-editing §IV): pasted pixels behind the target surface keep the target.\nOutputs the alpha after the \
         test for the relighting stage.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::synthetic::{RenderOptions, Scene, render};

    /// A square in the tabletop at 2 m, partly behind the red box (id 3, at
    /// 1.4-1.8 m): hidden exactly on the box's pixels, counted from the
    /// scene's object ids and the square's analytic footprint (no depth
    /// comparison involved).
    #[test]
    fn an_object_behind_the_box_is_hidden_exactly_where_the_box_is() {
        let tgt = render(
            &Scene::preset("tabletop", 200, 150).unwrap(),
            &RenderOptions::default(),
        );
        let k = tgt.intrinsics;
        let (w, h) = (200, 150);
        let footprint = |x: usize, y: usize| {
            let dx = (x as f64 + 0.5 - k.cx) / k.fx;
            let dy = (y as f64 + 0.5 - k.cy) / k.fy;
            (-0.3..=-0.05).contains(&dx) && (-0.15..=0.15).contains(&dy)
        };
        let green = [0.1f32, 0.9, 0.2];
        let pc = Image::from_fn(w, h, |x, y| if footprint(x, y) { green } else { [0.0; 3] });
        let pd = Image::from_fn(w, h, |x, y| if footprint(x, y) { 2.0f32 } else { 0.0 });
        let pa = Image::from_fn(w, h, |x, y| if footprint(x, y) { 1.0f32 } else { 0.0 });
        let r = occlusion_composite(
            &tgt.color,
            &tgt.depth,
            &pc,
            &pd,
            &pa,
            &CompositeParams::default(),
        )
        .unwrap();
        let (mut hidden, mut shown) = (0, 0);
        for y in 0..h {
            for x in 0..w {
                let (c, z, a) = (*r.color.get(x, y), *r.depth.get(x, y), *r.alpha.get(x, y));
                let behind_box = footprint(x, y) && *tgt.ids.get(x, y) == 3;
                if behind_box {
                    hidden += 1;
                    assert_eq!(a, 0.0, "({x},{y})");
                    assert_eq!(c, *tgt.color.get(x, y));
                    assert_eq!(z, *tgt.depth.get(x, y));
                } else if footprint(x, y) {
                    shown += 1;
                    assert_eq!((c, z, a), (green, 2.0, 1.0), "({x},{y})");
                } else {
                    assert_eq!((c, z, a), (*tgt.color.get(x, y), *tgt.depth.get(x, y), 0.0));
                }
            }
        }
        assert!(hidden > 50 && shown > 200, "hidden {hidden}, shown {shown}");
        let seen = r.alpha.as_slice().iter().filter(|a| **a == 1.0).count();
        assert_eq!(seen, shown);
    }

    /// The same through the real chain: a flat 0.3 m square pasted (Paste) to
    /// 2 m behind the box of a 200x150 tabletop from a 160x120 source, feathered
    /// inwards, composited: exactly the pasted pixels that show the box (ids)
    /// are hidden, all others keep the pasted alpha.
    #[test]
    fn paste_feather_composite_hides_the_object_behind_the_box() {
        use crate::select::feather::{FeatherParams, feather};
        use crate::select::paste::{PasteParams, paste};
        let tgt = render(
            &Scene::preset("tabletop", 200, 150).unwrap(),
            &RenderOptions::default(),
        );
        let ks = crate::sim::synthetic::kinect_like_intrinsics(160, 120);
        let depth = Image::filled(160, 120, 1.0f32);
        let color = Image::filled(160, 120, [0.1f32, 0.9, 0.2]);
        let mask = Image::from_fn(160, 120, |x, y| {
            if (60..100).contains(&x) && (40..80).contains(&y) {
                1.0f32
            } else {
                0.0
            }
        });
        let p = PasteParams {
            translation_m: [-0.4, 0.2, 1.0],
            auto_scale: false,
            ..Default::default()
        };
        let pasted = paste(&color, &depth, &mask, &ks, &tgt.depth, &tgt.intrinsics, &p).unwrap();
        let (alpha, _) = feather(&pasted.alpha, &FeatherParams::default()).unwrap();
        let r = occlusion_composite(
            &tgt.color,
            &tgt.depth,
            &pasted.color,
            &pasted.depth,
            &alpha,
            &CompositeParams::default(),
        )
        .unwrap();
        let mut hidden = 0;
        for i in 0..r.alpha.len() {
            let a = alpha.as_slice()[i];
            if a > 0.0 && tgt.ids.as_slice()[i] == 3 {
                hidden += 1;
                assert_eq!(r.alpha.as_slice()[i], 0.0, "pixel {i}");
                assert_eq!(r.color.as_slice()[i], tgt.color.as_slice()[i]);
            } else {
                assert_eq!(r.alpha.as_slice()[i], a, "pixel {i}");
            }
        }
        let pasted_px = alpha.as_slice().iter().filter(|a| **a > 0.0).count();
        assert!(
            hidden > 100 && pasted_px > hidden + 100,
            "{hidden} of {pasted_px}"
        );
    }

    #[test]
    fn blending_alpha_range_holes_and_nan() {
        let tc = Image::filled(6, 1, [0.2f32, 0.4, 0.8]);
        let td = Image::from_vec(6, 1, vec![2.0f32, 2.0, 0.0, 2.0, 2.0, 1.0]).unwrap();
        let pc = Image::filled(6, 1, [1.0f32, 0.0, 0.0]);
        let pd = Image::from_vec(6, 1, vec![1.0f32, 1.0, 1.0, 0.0, 1.0, 1.5]).unwrap();
        let pa = Image::from_vec(6, 1, vec![0.25f32, f32::NAN, 0.5, 1.0, 7.0, 1.0]).unwrap();
        let r = occlusion_composite(&tc, &td, &pc, &pd, &pa, &CompositeParams::default()).unwrap();
        // 0: a quarter blend in color and depth
        assert_eq!(*r.alpha.get(0, 0), 0.25);
        assert!((r.color.get(0, 0)[0] - (0.25 + 0.75 * 0.2)).abs() < 1e-6);
        assert!((r.depth.get(0, 0) - (0.25 + 0.75 * 2.0)).abs() < 1e-6);
        // 1: NaN alpha is 0: target unchanged
        assert_eq!(
            (*r.alpha.get(1, 0), *r.color.get(1, 0)),
            (0.0, [0.2, 0.4, 0.8])
        );
        // 2: a target hole hides nothing; the depth is the pasted one
        assert_eq!(*r.alpha.get(2, 0), 0.5);
        assert_eq!(*r.depth.get(2, 0), 1.0);
        // 3: nothing pasted there (no pasted depth): alpha 0
        assert_eq!(*r.alpha.get(3, 0), 0.0);
        // 4: alpha above 1 is clamped
        assert_eq!(*r.alpha.get(4, 0), 1.0);
        assert_eq!(*r.color.get(4, 0), [1.0, 0.0, 0.0]);
        // 5: behind the target: hidden; with a tolerance of 60 % it shows
        assert_eq!(*r.alpha.get(5, 0), 0.0);
        let t = occlusion_composite(
            &tc,
            &td,
            &pc,
            &pd,
            &pa,
            &CompositeParams { tolerance_rel: 0.6 },
        )
        .unwrap();
        assert_eq!(*t.alpha.get(5, 0), 1.0);
        for a in r.alpha.as_slice() {
            assert!((0.0..=1.0).contains(a));
        }
    }

    #[test]
    fn sizes_are_checked_and_nothing_pasted_passes_through() {
        let tc = Image::filled(4, 3, [0.5f32; 3]);
        let td = Image::filled(4, 3, 1.0f32);
        let e = occlusion_composite(
            &tc,
            &td,
            &tc,
            &td,
            &Image::filled(3, 3, 1.0f32),
            &CompositeParams::default(),
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("pasted_alpha") && e.to_string().contains("3x3"),
            "{e}"
        );
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let mut inputs = Inputs::new();
        inputs.insert("target_color", Value::from(tc.clone()));
        inputs.insert("target_depth", Value::from(td.clone()));
        inputs.insert("pasted_color", Value::from(tc.clone()));
        inputs.insert("pasted_depth", Value::from(td.clone()));
        inputs.insert(
            "pasted_alpha",
            Value::Mask(Arc::new(Image::filled(4, 3, 0.0f32))),
        );
        let test_ctx = crate::test_support::TestCtx::new("composite");
        let ctx = test_ctx.ctx();
        let out = reg
            .get("OcclusionComposite")
            .unwrap()
            .eval(&ctx, &inputs, &CompositeParams::default().to_values())
            .unwrap();
        assert!(out.passthrough.unwrap().contains("nothing pasted"));
    }
}
