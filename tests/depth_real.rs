//! Depth upsampling on real data (Park et al. 2011, `../shared/data`):
//! where the data is missing the test says so on stderr and checks nothing
//! else.

use depthgraph::evaluation::{
    depth_errors, middlebury2005_disparity, park2011_intrinsics, shared_data_dir,
};
use depthgraph::nodes::depth::nlmeans::{NLMeansUpsampleParams, nlmeans_upsample};
use depthgraph::nodes::io::{ColorSpace, load_color, load_depth};

/// Books at x8 (the noisy 1/8 depth): the stepped upsampling beats one
/// step at the full factor and a bilinear interpolation by a wide margin
/// (measured in the bench: 18.3 mm against 37.2 and 31.2).
#[test]
fn stepped_upsampling_wins_at_x8_on_park_books() {
    let dir = shared_data_dir().join("park2011_depth_sr/books_big");
    let p = middlebury2005_disparity();
    let (Ok(color), Ok(truth), Ok(low)) = (
        load_color(&dir.join("books_big_color.png"), ColorSpace::Srgb),
        load_depth(&dir.join("_gth/books_big.png"), &p),
        load_depth(&dir.join("depth_3_n.png"), &p),
    ) else {
        eprintln!(
            "{} is missing: the Park 2011 upsampling test checked nothing",
            dir.display()
        );
        return;
    };
    let (w, h) = truth.dims();
    let low_k = park2011_intrinsics(w, h).scaled_to(low.width(), low.height());
    let rmse = |max_step_factor: f64| {
        let p = NLMeansUpsampleParams {
            max_step_factor,
            ..Default::default()
        };
        let d = nlmeans_upsample(&low, &low_k, &color, &p).unwrap().0;
        depth_errors(&d, &truth, |_| true).rmse_m
    };
    let (steps, one) = (rmse(4.0), rmse(0.0));
    assert!(steps < 0.7 * one, "steps {steps} one step {one}");
    assert!(steps < 0.025, "steps {steps}");
}
