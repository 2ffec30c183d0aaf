//! `LoadMask`: a selection mask from a file (another tool's segmentation),
//! usable as `Paste.source_mask` in place of the lasso.
//!
//! An 8- or 16-bit PNG (or any format `LoadColor` reads; grey, or the mean
//! of the colour channels, or the alpha channel when `channel` is
//! `"alpha"`) scaled to `[0, 1]` (255 or 65535 is 1). `"soft"` keeps the
//! values (a matte: feathered edges stay feathered); `"threshold"` makes
//! the mask binary at `threshold`. `invert` swaps object and background.
//! When the optional `like` input is connected (the source photo), the
//! sizes must agree: the error names both.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::{Registry, RegistryError};
use image::DynamicImage;

use super::decode::{Limits, read_file};

node_params! {
    /// Parameters of `LoadMask`.
    pub struct LoadMaskParams {
        /// 8/16-bit PNG (or another image format) holding the mask.
        pub path: String = "", ParamKind::InputPath;
        /// "soft": the values as they are (a matte); "threshold": 1 where the value >= threshold, else 0.
        pub mode: MaskMode = MaskMode::Soft, ParamKind::Choice(MaskMode::NAMES);
        /// The cut of "threshold", in [0, 1].
        pub threshold: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// "value": grey (the mean of the colour channels); "alpha": the alpha channel (1 without one).
        pub channel: MaskChannel = MaskChannel::Value, ParamKind::Choice(MaskChannel::NAMES);
        /// Swap object and background (1 - value).
        pub invert: bool = false, ParamKind::Bool;
    }
}

depthgraph_graph::param_choice! {
    /// How the file's values become the mask (the `mode` parameter).
    pub enum MaskMode {
        /// The values as they are.
        Soft = "soft",
        /// Binary at `threshold`.
        Threshold = "threshold",
    }
}

depthgraph_graph::param_choice! {
    /// Which channel holds the mask (the `channel` parameter).
    pub enum MaskChannel {
        /// Grey, or the mean of the colour channels.
        Value = "value",
        /// The alpha channel.
        Alpha = "alpha",
    }
}

/// Reads the mask of `p` (module docs).
pub fn load_mask(p: &LoadMaskParams) -> Result<Mask, NodeError> {
    load_mask_with(p, &Limits::default())
}

/// [`load_mask`] within the pixel budget `lim` (checked on the header,
/// before the pixels are decoded).
pub fn load_mask_with(p: &LoadMaskParams, lim: &Limits) -> Result<Mask, NodeError> {
    let path = super::given(&p.path)?;
    decode_mask(&read_file(path, lim)?, path, p, lim)
}

/// The mask values of a file the `image` crate reads (PNG, JPEG, TIFF,
/// EXR), before clamping: the mean of the colour channels, or the alpha
/// channel (1 without one). `decode_image` checks the size against `lim`.
fn decoded_mask_values(
    bytes: &[u8],
    path: &Path,
    p: &LoadMaskParams,
    lim: &Limits,
) -> Result<(usize, usize, Vec<f32>), NodeError> {
    let img = super::decode_image(bytes, path, lim)?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let values: Vec<f32> = match p.channel {
        MaskChannel::Value => {
            let rgb = img.to_rgb32f();
            rgb.pixels().map(|q| (q[0] + q[1] + q[2]) / 3.0).collect()
        }
        MaskChannel::Alpha => match &img {
            DynamicImage::ImageLumaA8(_)
            | DynamicImage::ImageLumaA16(_)
            | DynamicImage::ImageRgba8(_)
            | DynamicImage::ImageRgba16(_)
            | DynamicImage::ImageRgba32F(_) => img.to_rgba32f().pixels().map(|q| q[3]).collect(),
            _ => vec![1.0; w * h],
        },
    };
    Ok((w, h, values))
}

/// [`load_mask`] of a file's bytes (`path` names it in errors; `p.path`
/// is not read).
pub fn decode_mask(
    bytes: &[u8],
    path: &Path,
    p: &LoadMaskParams,
    lim: &Limits,
) -> Result<Mask, NodeError> {
    // PGM/PPM (a segmentation tool's usual output) and Radiance files, as
    // LoadColor reads them: their samples over maxval, or the radiance;
    // neither has an alpha channel (alpha: every pixel 1)
    let plain = if super::is_pnm(path) {
        let pnm = super::decode_pnm(bytes, path, false, lim)?;
        // guard: maxval >= 1 (checked by the decoder), channels >= 1
        let max = pnm.maxval.max(1) as f32;
        let c = pnm.channels.max(1);
        let v: Vec<f32> = pnm
            .samples
            .chunks_exact(c)
            .map(|q| q.iter().map(|s| *s as f32 / max).sum::<f32>() / c as f32)
            .collect();
        Some((pnm.width, pnm.height, v))
    } else if super::radiance::looks_like_rgbe(bytes)
        || matches!(super::extension(path).as_str(), "hdr" | "pic")
    {
        let img = super::radiance::decode_rgbe(bytes, path, lim)?.image;
        let (w, h) = img.dims();
        let v = img
            .as_slice()
            .iter()
            .map(|q| (q[0] + q[1] + q[2]) / 3.0)
            .collect();
        Some((w, h, v))
    } else {
        None
    };
    let (w, h, values) = match plain {
        Some((w, h, v)) => {
            let v = match p.channel {
                MaskChannel::Value => v,
                MaskChannel::Alpha => vec![1.0; w * h],
            };
            (w, h, v)
        }
        None => decoded_mask_values(bytes, path, p, lim)?,
    };
    let t = p.threshold as f32;
    let mask = values
        .into_iter()
        .map(|v| {
            let v = if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            };
            let v = if p.invert { 1.0 - v } else { v };
            match p.mode {
                MaskMode::Soft => v,
                MaskMode::Threshold => {
                    if v >= t {
                        1.0
                    } else {
                        0.0
                    }
                }
            }
        })
        .collect();
    Ok(Image::from_vec(w, h, mask)?)
}

depthgraph_graph::ports! {
    /// Inputs of `LoadMask`.
    inputs struct LoadMaskIn {
        /// the image the mask belongs to (its size is checked)
        like: Option<Arc<ColorImage>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `LoadMask`.
    outputs struct LoadMaskOut {
        /// in [0, 1], 1 = the object
        mask: Mask,
        /// fraction of the mask's area (sum of values / pixels)
        coverage: f64,
    }
}

fn eval(
    ctx: &EvalCtx,
    i: LoadMaskIn,
    p: &LoadMaskParams,
) -> Result<Produced<LoadMaskOut>, NodeError> {
    let mask = load_mask_with(p, &Limits::of(ctx))?;
    if let Some(like) = &i.like {
        let (a, b) = (mask.dims(), like.dims());
        if a != b {
            return Err(NodeError::input(
                "like",
                format!(
                    "is {}x{} but the mask {} is {}x{}",
                    b.0, b.1, p.path, a.0, a.1
                ),
            ));
        }
    }
    let sum: f64 = mask.as_slice().iter().map(|v| f64::from(*v)).sum();
    // guard: a decoded image has at least one pixel
    let coverage = sum / mask.len().max(1) as f64;
    Ok(LoadMaskOut { mask, coverage }.into())
}

/// Registers `LoadMask`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(
        PortedNode::new(
            "LoadMask",
            1,
            "Reads a selection mask from an 8/16-bit PNG (another tool's segmentation): soft (a matte) or thresholded, \
             grey or alpha, optionally inverted; usable as Paste.source_mask. Connect `like` (the source photo) to check the size.",
            eval,
        )
        .reads(|p: &LoadMaskParams| vec![PathBuf::from(&p.path)]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every format LoadColor reads gives a mask, as the module docs say:
    /// binary PGM (8- and 16-bit) and PPM over their maxval, Radiance as
    /// its radiance; alpha is 1 for formats without one.
    #[test]
    fn pgm_ppm_and_radiance_masks_read_as_loadcolor_reads_them() {
        let dir = tempfile::tempdir().unwrap();
        let soft = LoadMaskParams::default();
        let read = |name: &str, bytes: Vec<u8>, p: &LoadMaskParams| {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap();
            decode_mask(&std::fs::read(&path).unwrap(), &path, p, &Limits::default()).unwrap()
        };
        let mut pgm = b"P5\n3 1\n255\n".to_vec();
        pgm.extend_from_slice(&[0, 51, 255]);
        assert_eq!(read("m.pgm", pgm, &soft).as_slice(), &[0.0, 0.2, 1.0]);
        let mut pgm16 = b"P5\n2 1\n65535\n".to_vec();
        for v in [65535u16, 0] {
            pgm16.extend_from_slice(&v.to_be_bytes());
        }
        assert_eq!(read("m16.pgm", pgm16, &soft).as_slice(), &[1.0, 0.0]);
        let mut ppm = b"P6\n1 1\n255\n".to_vec();
        ppm.extend_from_slice(&[255, 0, 0]);
        let m = read("m.ppm", ppm.clone(), &soft);
        assert!((m.as_slice()[0] - 1.0 / 3.0).abs() < 1e-6);
        let alpha = LoadMaskParams {
            channel: MaskChannel::Alpha,
            ..Default::default()
        };
        assert_eq!(read("a.ppm", ppm, &alpha).as_slice(), &[1.0]);
        let hdr = ColorImage::from_fn(2, 1, |x, _| if x == 0 { [0.5; 3] } else { [4.0; 3] });
        let m = read("m.hdr", crate::io::radiance::encode_rgbe(&hdr), &soft);
        assert!(
            (m.as_slice()[0] - 0.5).abs() < 1e-2 && m.as_slice()[1] == 1.0,
            "{:?}",
            m.as_slice()
        );
    }

    fn run(p: &LoadMaskParams, like: Option<ColorImage>) -> Result<Outputs, NodeError> {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let node = reg.get("LoadMask").unwrap();
        let test_ctx = crate::test_support::TestCtx::new("mask");
        let mut inputs = Inputs::new();
        if let Some(l) = like {
            inputs.insert("like", Value::from(l));
        }
        node.eval(&test_ctx.ctx(), &inputs, &p.to_values())
    }

    /// 8- and 16-bit PNGs give the same soft mask; threshold and invert
    /// do what they say; a wrong size names both sizes; a missing file
    /// names the file.
    #[test]
    fn masks_from_8_and_16_bit_pngs_and_their_size_check() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (6u32, 4u32);
        let p8 = dir.path().join("m8.png");
        let p16 = dir.path().join("m16.png");
        image::GrayImage::from_fn(w, h, |x, _| image::Luma([(x * 51) as u8]))
            .save(&p8)
            .unwrap();
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, _| {
            image::Luma([(x * 13107) as u16])
        })
        .save(&p16)
        .unwrap();
        let params = |path: &std::path::Path| LoadMaskParams {
            path: path.display().to_string(),
            ..Default::default()
        };
        let m8 = load_mask(&params(&p8)).unwrap();
        let m16 = load_mask(&params(&p16)).unwrap();
        assert_eq!(m8.dims(), (6, 4));
        for (a, b) in m8.as_slice().iter().zip(m16.as_slice()) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
        assert!((m8.get(1, 0) - 0.2).abs() < 1e-6);
        let t = load_mask(&LoadMaskParams {
            mode: MaskMode::Threshold,
            threshold: 0.5,
            invert: true,
            ..params(&p8)
        })
        .unwrap();
        // values 0, .2, .4, .6, .8, 1 inverted: 1, .8, .6, .4, .2, 0
        let row: Vec<f32> = (0..6).map(|x| *t.get(x, 0)).collect();
        assert_eq!(row, vec![1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
        // the size check against the source photo
        let ok = run(&params(&p8), Some(ColorImage::filled(6, 4, [0.0; 3]))).unwrap();
        assert!(matches!(ok.values["mask"], Value::Mask(_)));
        let err = run(&params(&p8), Some(ColorImage::filled(8, 4, [0.0; 3])))
            .unwrap_err()
            .to_string();
        assert!(err.contains("8x4") && err.contains("6x4"), "{err}");
        let missing = run(&params(&dir.path().join("none.png")), None)
            .unwrap_err()
            .to_string();
        assert!(missing.contains("none.png"), "{missing}");
    }
}
