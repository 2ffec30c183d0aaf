//! Depth upsampling on real data (Park et al. 2011, `../shared/data`):
//! where the data is missing the test says so on stderr and checks nothing
//! else.

use depthgraph::evaluation::{
    depth_errors, middlebury2005_disparity, park2011_intrinsics, shared_data_dir,
};
use depthgraph::nodes::depth::nlmeans::{NLMeansUpsampleParams, nlmeans_upsample};
use depthgraph::nodes::io::{ColorSpace, load_color, load_depth};

/// Books at x8 (the noisy 1/8 depth): the default (steps, spatial falloff)
/// beats eq. 4 as published in one step at the full factor by a wide
/// margin, and eq. 4 in the same steps without the falloff (measured in
/// the bench: 17.8 mm against 37.2 and 18.2; bilinear 31.2, joint
/// bilateral upsampling 19.6).
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
    let rmse = |max_step_factor: f64, spatial_sigma: f64| {
        let p = NLMeansUpsampleParams {
            max_step_factor,
            spatial_sigma,
            ..Default::default()
        };
        let d = nlmeans_upsample(&low, &low_k, &color, &p).unwrap().0;
        depth_errors(&d, &truth, |_| true).unwrap().rmse_m
    };
    let d = NLMeansUpsampleParams::default();
    let steps = rmse(d.max_step_factor, d.spatial_sigma);
    let (one, plain_steps) = (rmse(0.0, 0.0), rmse(4.0, 0.0));
    assert!(steps < 0.7 * one, "steps {steps} one step {one}");
    assert!(
        steps < 0.99 * plain_steps,
        "steps {steps}, without the falloff {plain_steps}"
    );
    assert!(steps < 0.019, "steps {steps}");
}
