//! The preview pane's pictures: image values turned into 8-bit textures
//! (Color as sRGB, Depth colour-mapped with a legend, masks and confidences
//! as grey or tinted over the photograph upstream), and the mapping between
//! screen points and image pixels that zoom and lasso clicks need.

use depthgraph_graph::prelude::Value;
use depthgraph_nodes::kit::color::rgb_to_srgb8;
use eframe::egui::{self, Color32, ColorImage};
use rayon::prelude::*;

/// The depth colormap of `t` in [0, 1] as 8-bit sRGB: the nodes' one
/// ([`depthgraph_nodes::kit::colormap::colormap`]), so a preview and a
/// `DepthPreview` output look alike.
pub fn colormap(t: f32) -> [u8; 3] {
    depthgraph_nodes::kit::color::rgb_to_srgb8(depthgraph_nodes::kit::colormap::colormap(t))
}

/// The depth range a colour-mapped preview spans (metres), for its legend.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthLegend {
    /// Depth shown at the low end of the colormap.
    pub near_m: f32,
    /// Depth shown at the high end.
    pub far_m: f32,
    /// Pixels without depth (shown black).
    pub holes: usize,
}

/// A preview texture's pixels and, for depth, its legend.
pub struct Picture {
    pub image: ColorImage,
    pub legend: Option<DepthLegend>,
}

/// Valid depth range of `z` (finite and > 0), or `None` when all are holes.
pub fn depth_range(z: &[f32]) -> Option<(f32, f32)> {
    let (lo, hi) = z
        .iter()
        .filter(|z| z.is_finite() && **z > 0.0)
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), z| {
            (lo.min(*z), hi.max(*z))
        });
    (lo <= hi).then_some((lo, hi))
}

/// An 8-bit picture of an image value: Color as sRGB, Depth colour-mapped
/// between its nearest and farthest valid depth (holes black), masks and
/// confidences as grey. `None` for values that are not images.
pub fn picture(v: &Value) -> Option<Picture> {
    match v {
        Value::Color(img) => {
            let (w, h) = img.dims();
            Some(Picture {
                image: opaque([w, h], img.as_slice(), |p| rgb_to_srgb8(*p)),
                legend: None,
            })
        }
        Value::Depth(img) => {
            let (w, h) = img.dims();
            let (lo, hi) = depth_range(img.as_slice()).unwrap_or((0.0, 0.0));
            // Guard: a flat (or empty) depth map maps to the low end.
            let span = if hi > lo { hi - lo } else { 1.0 };
            let valid = |z: &f32| z.is_finite() && *z > 0.0;
            let holes = img.as_slice().par_iter().filter(|z| !valid(z)).count();
            let image = opaque([w, h], img.as_slice(), |z| {
                if valid(z) {
                    colormap((z - lo) / span)
                } else {
                    [0, 0, 0]
                }
            });
            Some(Picture {
                image,
                legend: Some(DepthLegend {
                    near_m: lo,
                    far_m: hi,
                    holes,
                }),
            })
        }
        Value::Mask(_) | Value::Confidence(_) => {
            let img = v.samples()?;
            let (w, h) = (img.width, img.height);
            let image = opaque([w, h], img.samples, |x| {
                let g = (if x.is_finite() {
                    x.clamp(0.0, 1.0)
                } else {
                    0.0
                } * 255.0) as u8;
                [g, g, g]
            });
            Some(Picture {
                image,
                legend: None,
            })
        }
        _ => None,
    }
}

/// An opaque picture of `size` whose pixel `i` is `f(&src[i])`, built in
/// parallel (rows of a 640x480 preview cost a few milliseconds each way:
/// the sRGB encoding is a `powf` per channel). `src` holds
/// `size[0] * size[1]` values (the callers' images do).
fn opaque<T: Sync>(size: [usize; 2], src: &[T], f: impl Fn(&T) -> [u8; 3] + Sync) -> ColorImage {
    let pixels: Vec<Color32> = src
        .par_iter()
        .with_min_len(4096)
        .map(|v| {
            let [r, g, b] = f(v);
            Color32::from_rgb(r, g, b)
        })
        .collect();
    ColorImage::new(size, pixels)
}

/// The 8-bit preview of an image value (see [`picture`]).
pub fn preview_image(v: &Value) -> Option<ColorImage> {
    picture(v).map(|p| p.image)
}

/// `image` fitted to textures of at most `max_side` pixels a side (the
/// display's limit; a larger texture aborts the renderer): scaled down by
/// nearest sampling, aspect kept, at least one pixel a side. Images that
/// fit are returned as they are. The preview maps the pointer with the
/// image's own size, not the texture's.
pub fn fit_texture(image: ColorImage, max_side: usize) -> ColorImage {
    let [w, h] = image.size;
    let max_side = max_side.max(1);
    if w <= max_side && h <= max_side {
        return image;
    }
    // guard: w or h > max_side >= 1 here, so the larger side is > 0
    let s = max_side as f64 / w.max(h) as f64;
    let fit = |n: usize| ((n as f64 * s).round() as usize).clamp(1, max_side);
    let (tw, th) = (fit(w), fit(h));
    let pixels = (0..tw * th)
        .map(|i| {
            // the source pixel under the texel's centre; guard: tw, th >= 1
            let sx = (((i % tw) as f64 + 0.5) * w as f64 / tw as f64) as usize;
            let sy = (((i / tw) as f64 + 0.5) * h as f64 / th as f64) as usize;
            image.pixels[sy.min(h - 1) * w + sx.min(w - 1)]
        })
        .collect();
    ColorImage::new([tw, th], pixels)
}

/// Tints `base` by `mask` (values in [0, 1], clamped): each pixel moves
/// towards `tint` by `opacity × mask`. Returns false (and leaves `base`
/// alone) when the sizes differ.
pub fn overlay_mask(
    base: &mut ColorImage,
    mask: &[f32],
    mask_size: [usize; 2],
    tint: Color32,
    opacity: f32,
) -> bool {
    if base.size != mask_size || base.pixels.len() != mask.len() {
        return false;
    }
    let t = [tint.r(), tint.g(), tint.b()];
    for (p, &m) in base.pixels.iter_mut().zip(mask) {
        let a = if m.is_finite() {
            m.clamp(0.0, 1.0)
        } else {
            0.0
        } * opacity.clamp(0.0, 1.0);
        if a <= 0.0 {
            continue;
        }
        let mix = |c: u8, t: u8| (f32::from(c) * (1.0 - a) + f32::from(t) * a + 0.5) as u8;
        *p = Color32::from_rgb(mix(p.r(), t[0]), mix(p.g(), t[1]), mix(p.b(), t[2]));
    }
    true
}

/// Where an image of `size` pixels is drawn on screen (`rect`): converts
/// between screen points and pixel coordinates (pixel centres at
/// integer + 0.5, as the Lasso's clicks are written).
#[derive(Debug, Clone, Copy)]
pub struct ImageFrame {
    pub rect: egui::Rect,
    pub size: [usize; 2],
}

impl ImageFrame {
    /// Screen points per image pixel (guarded: an empty image or rect gives 1).
    pub fn scale(&self) -> f32 {
        let w = self.size[0] as f32;
        if w > 0.0 && self.rect.width() > 0.0 {
            self.rect.width() / w
        } else {
            1.0
        }
    }

    /// The pixel coordinates under a screen point, or `None` outside the image.
    pub fn to_pixel(&self, p: egui::Pos2) -> Option<[f64; 2]> {
        if !self.rect.contains(p) {
            return None;
        }
        let s = self.scale();
        let x = f64::from((p.x - self.rect.min.x) / s);
        let y = f64::from((p.y - self.rect.min.y) / s);
        Some([
            x.clamp(0.0, self.size[0] as f64),
            y.clamp(0.0, self.size[1] as f64),
        ])
    }

    /// The screen point of pixel coordinates.
    pub fn to_screen(&self, px: [f64; 2]) -> egui::Pos2 {
        let s = self.scale();
        egui::pos2(
            self.rect.min.x + px[0] as f32 * s,
            self.rect.min.y + px[1] as f32 * s,
        )
    }
}

/// A short description of the value at pixel `(x, y)` (for hover text).
pub fn describe_pixel(v: &Value, x: usize, y: usize) -> Option<String> {
    let (w, h) = v.image_dims()?;
    if x >= w || y >= h {
        return None;
    }
    Some(match v {
        Value::Color(img) => {
            let p = img.get(x, y);
            format!("({x}, {y}) rgb {:.3} {:.3} {:.3}", p[0], p[1], p[2])
        }
        Value::Depth(img) => {
            let z = *img.get(x, y);
            if z.is_finite() && z > 0.0 {
                format!("({x}, {y}) depth {z:.3} m")
            } else {
                format!("({x}, {y}) no depth")
            }
        }
        Value::Mask(img) => format!("({x}, {y}) {:.3}", img.get(x, y)),
        Value::Confidence(img) => format!("({x}, {y}) {:.3}", img.get(x, y)),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A picture larger than the display's texture limit is shown scaled
    /// down (aspect kept); one that fits is untouched.
    #[test]
    fn pictures_over_the_texture_limit_are_scaled_to_fit() {
        let px = |i: usize| Color32::from_rgb((i % 251) as u8, (i / 251) as u8, 7);
        let big = ColorImage::new([100, 30], (0..3000).map(px).collect());
        let fit = fit_texture(big.clone(), 40);
        assert_eq!(fit.size, [40, 12]);
        // each texel is the source pixel under its centre
        assert_eq!(fit.pixels[0], big.pixels[100 + 1]);
        assert_eq!(fit.pixels[12 * 40 - 1], big.pixels[28 * 100 + 98]);
        let thin = ColorImage::new([1, 9000], vec![Color32::WHITE; 9000]);
        assert_eq!(fit_texture(thin, 8192).size, [1, 8192]);
        let small = fit_texture(big.clone(), 100);
        assert_eq!(small.size, big.size);
        assert_eq!(small.pixels, big.pixels);
    }

    #[test]
    fn overlay_tints_only_inside_the_mask_and_refuses_other_sizes() {
        let mut img = ColorImage::new([2, 1], vec![Color32::from_rgb(0, 0, 0); 2]);
        assert!(overlay_mask(
            &mut img,
            &[1.0, 0.0],
            [2, 1],
            Color32::from_rgb(200, 100, 0),
            0.5
        ));
        assert_eq!(img.pixels[0], Color32::from_rgb(100, 50, 0));
        assert_eq!(img.pixels[1], Color32::from_rgb(0, 0, 0));
        assert!(!overlay_mask(&mut img, &[1.0], [1, 1], Color32::WHITE, 1.0));
        assert_eq!(img.pixels[0], Color32::from_rgb(100, 50, 0));
    }

    #[test]
    fn frame_maps_pixels_and_points_both_ways() {
        let f = ImageFrame {
            rect: egui::Rect::from_min_size(egui::pos2(10.0, 20.0), egui::vec2(200.0, 100.0)),
            size: [100, 50],
        };
        assert_eq!(f.scale(), 2.0);
        assert_eq!(f.to_pixel(egui::pos2(30.0, 40.0)), Some([10.0, 10.0]));
        assert_eq!(f.to_screen([10.0, 10.0]), egui::pos2(30.0, 40.0));
        assert_eq!(f.to_pixel(egui::pos2(5.0, 40.0)), None);
    }

    #[test]
    fn depth_legend_spans_valid_depths_and_counts_holes() {
        let z = depthgraph_graph::prelude::DepthMap::from_vec(3, 1, vec![1.0, f32::NAN, 3.0])
            .expect("3 pixels");
        let p = picture(&Value::Depth(std::sync::Arc::new(z))).expect("depth is an image");
        let legend = p.legend.expect("depth has a legend");
        assert_eq!((legend.near_m, legend.far_m, legend.holes), (1.0, 3.0, 1));
        assert_eq!(p.image.pixels[1], Color32::from_rgb(0, 0, 0));
        assert_ne!(p.image.pixels[0], p.image.pixels[2]);
    }

    /// The pictures are built in parallel; each pixel is still its own
    /// value's encoding, in order (an image large enough to split).
    #[test]
    fn pictures_encode_every_pixel_in_place() {
        use depthgraph_graph::prelude::{ColorImage as Img, DepthMap, Mask};
        use depthgraph_nodes::kit::color::srgb8;
        let (w, h) = (301, 97);
        let c = Img::from_fn(w, h, |x, y| {
            [
                x as f32 / w as f32,
                y as f32 / h as f32,
                ((x * y) % 7) as f32 / 6.0,
            ]
        });
        let p = picture(&Value::Color(std::sync::Arc::new(c.clone()))).expect("colour");
        assert_eq!(p.image.size, [w, h]);
        for (i, px) in p.image.pixels.iter().enumerate() {
            let v = c.as_slice()[i];
            assert_eq!(
                *px,
                Color32::from_rgb(srgb8(v[0]), srgb8(v[1]), srgb8(v[2])),
                "pixel {i}"
            );
        }
        let z = DepthMap::from_fn(w, h, |x, y| {
            if (x + y) % 11 == 0 {
                0.0
            } else {
                1.0 + x as f32
            }
        });
        let p = picture(&Value::Depth(std::sync::Arc::new(z.clone()))).expect("depth");
        let legend = p.legend.expect("legend");
        let holes = z.as_slice().iter().filter(|v| **v <= 0.0).count();
        assert_eq!(legend.holes, holes);
        for (i, px) in p.image.pixels.iter().enumerate() {
            let v = z.as_slice()[i];
            let want = if v > 0.0 {
                let [r, g, b] = colormap((v - legend.near_m) / (legend.far_m - legend.near_m));
                Color32::from_rgb(r, g, b)
            } else {
                Color32::from_rgb(0, 0, 0)
            };
            assert_eq!(*px, want, "depth pixel {i}");
        }
        let m = Mask::from_fn(w, h, |x, _| x as f32 / w as f32);
        let p = picture(&Value::Mask(std::sync::Arc::new(m.clone()))).expect("mask");
        for (i, px) in p.image.pixels.iter().enumerate() {
            let g = (m.as_slice()[i] * 255.0) as u8;
            assert_eq!(*px, Color32::from_rgb(g, g, g), "mask pixel {i}");
        }
    }
}
