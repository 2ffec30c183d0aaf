//! Reading and writing images, depth maps, point clouds and meshes.
//!
//! Loaders refuse absurd dimensions before allocating ([`MAX_SIDE`],
//! [`MAX_PIXELS`]) and turn every decoding failure into an error naming the
//! file. Writers write a temporary file beside the target and rename it into
//! place, so a reader never sees a half-written file, and refuse to write
//! over a file the pipeline reads.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use image::{DynamicImage, ImageFormat};

use crate::kit::color::{srgb8, srgb16};
use crate::kit::colormap::{colormap_depth, depth_range};

mod decode;
pub mod mask;
mod pfm;
mod ply;
mod pnm;
pub mod radiance;
pub mod sequence;
mod write;

pub use decode::{Limits, MAX_PIXELS, MAX_SIDE, Samples};
use decode::{check_dims, decode_err, read_file, srgb8_table, srgb16_table};

pub use pfm::{decode_pfm, read_pfm};
pub use ply::write_ply;
pub use pnm::{Pnm, decode_pnm, read_pnm};
use pnm::{is_pnm, pnm_color};
pub use write::{WriteFailure, write_atomic};

/// The encoding of every EXR depthgraph writes: RLE-compressed scan lines
/// in increasing order, so the same image always gives the same bytes
/// (chunks compressed in parallel are written sorted, never in the order
/// the workers finish).
fn exr_encoding() -> exr::prelude::Encoding {
    use exr::prelude::*;
    Encoding {
        compression: Compression::RLE,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    }
}

/// Writes float channels `(name, samples)` of a `w x h` image as one EXR
/// layer named `layer` ([`exr_encoding`]).
fn write_exr(
    tmp: &Path,
    (w, h): (usize, usize),
    layer: &str,
    channels: Vec<(&str, Vec<f32>)>,
) -> Result<(), WriteFailure> {
    use exr::prelude::*;
    let list: Vec<AnyChannel<FlatSamples>> = channels
        .into_iter()
        .map(|(name, v)| AnyChannel::new(name, FlatSamples::F32(v)))
        .collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::named(layer),
        exr_encoding(),
        AnyChannels::sort(SmallVec::from_vec(list)),
    );
    exr::prelude::Image::from_layer(layer)
        .write()
        .to_file(tmp)?;
    Ok(())
}

// ---------------------------------------------------------------- color

/// An EXR header checked against the pixel budget before a decoder sees
/// the file: every layer's size, the samples of all its channels (a reader
/// allocates every channel of a layer before it reads a block: at most four
/// channels' worth of the budget), and the largest block the header allows
/// (its tile or scan-line block, which a reader allocates for one chunk:
/// at most 16 bytes per pixel of the budget).
fn check_exr_header(bytes: &[u8], path: &Path, lim: &Limits) -> Result<(), NodeError> {
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false)
        .map_err(|e| decode_err(path, e.to_string()))?;
    let mut samples = 0usize;
    for header in &meta.headers {
        let size = header.layer_size;
        check_dims(path, size.width(), size.height(), lim)?;
        samples = samples.saturating_add(size.area().saturating_mul(header.channels.list.len()));
        let block = match header.blocks {
            exr::meta::BlockDescription::Tiles(t) => t.tile_size.area(),
            exr::meta::BlockDescription::ScanLines => header
                .compression
                .scan_lines_per_block()
                .saturating_mul(size.width()),
        }
        .saturating_mul(header.channels.bytes_per_pixel);
        if block > lim.max_pixels.saturating_mul(16) {
            return Err(decode_err(
                path,
                format!(
                    "EXR blocks of {block} bytes; the limit is 16 x {} (--max-pixels)",
                    lim.max_pixels
                ),
            ));
        }
    }
    if samples > lim.max_pixels.saturating_mul(4) {
        return Err(decode_err(
            path,
            format!(
                "EXR holds {samples} samples in its channels; the limit is 4 x {} (--max-pixels)",
                lim.max_pixels
            ),
        ));
    }
    Ok(())
}

/// Decodes an image file's bytes with the `image` crate (format guessed
/// from its magic bytes), its header's dimensions checked against `lim`
/// before any pixel is decoded.
fn decode_image(bytes: &[u8], path: &Path, lim: &Limits) -> Result<DynamicImage, NodeError> {
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|error| NodeError::read(path, error))
    };
    let (w, h) = reader()?
        .into_dimensions()
        .map_err(|e| decode_err(path, e.to_string()))?;
    check_dims(path, w as usize, h as usize, lim)?;
    if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
        check_exr_header(bytes, path, lim)?;
    }
    let mut reader = reader()?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_SIDE as u32);
    limits.max_image_height = Some(MAX_SIDE as u32);
    limits.max_alloc = Some((lim.max_pixels as u64).saturating_mul(16));
    reader.limits(limits);
    reader.decode().map_err(|e| decode_err(path, e.to_string()))
}

depthgraph_graph::param_choice! {
    /// How 8- and 16-bit files are encoded (the `color_space` parameter).
    pub enum ColorSpace {
        /// sRGB-encoded, linearised on load.
        Srgb = "srgb",
        /// Already linear.
        Linear = "linear",
    }
}

node_params! {
    /// Parameters of `LoadColor`.
    pub struct LoadColorParams {
        /// PNG, JPEG, TIFF (8 or 16 bit), EXR or Radiance .hdr file.
        pub path: String = "", ParamKind::InputPath;
        /// Encoding of 8/16-bit files: "srgb" (almost every photo) is linearised; float files are always linear.
        pub color_space: ColorSpace = ColorSpace::Srgb, ParamKind::Choice(ColorSpace::NAMES);
    }
}

/// Reads a color image as linear RGB (alpha is dropped).
///
/// ```no_run
/// use depthgraph_nodes::io::{load_color, ColorSpace};
/// let img = load_color(std::path::Path::new("photo.png"), ColorSpace::Srgb).unwrap();
/// println!("{}x{}", img.width(), img.height());
/// ```
pub fn load_color(path: &Path, color_space: ColorSpace) -> Result<ColorImage, NodeError> {
    load_color_with(path, color_space, &Limits::default())
}

/// [`load_color`] within the pixel budget `lim`.
pub fn load_color_with(
    path: &Path,
    color_space: ColorSpace,
    lim: &Limits,
) -> Result<ColorImage, NodeError> {
    decode_color(&read_file(path, lim)?, path, color_space, lim)
}

/// [`load_color`] of a file's bytes: `path` names the file in errors and
/// its extension picks PNM (`.pgm`/`.ppm`/`.pnm`); other formats are told
/// by their magic bytes. The header is checked against `lim` first.
pub fn decode_color(
    bytes: &[u8],
    path: &Path,
    color_space: ColorSpace,
    lim: &Limits,
) -> Result<ColorImage, NodeError> {
    decode_color_counted(bytes, path, color_space, lim, &mut 0)
}

/// [`decode_color`], adding to `non_finite` the samples of a float file
/// that were NaN or infinite (read as 0).
fn decode_color_counted(
    bytes: &[u8],
    path: &Path,
    color_space: ColorSpace,
    lim: &Limits,
    non_finite: &mut usize,
) -> Result<ColorImage, NodeError> {
    if is_pnm(path) {
        let pnm = decode_pnm(bytes, path, false, lim)?;
        return pnm_color(pnm, path, color_space == ColorSpace::Srgb);
    }
    // Radiance files are linear radiance whatever `color_space` says
    if radiance::looks_like_rgbe(bytes) || matches!(extension(path).as_str(), "hdr" | "pic") {
        return Ok(radiance::decode_rgbe(bytes, path, lim)?.image);
    }
    let img = decode_image(bytes, path, lim)?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let srgb = color_space == ColorSpace::Srgb;
    let data: Vec<[f32; 3]> = match &img {
        DynamicImage::ImageLuma8(_)
        | DynamicImage::ImageLumaA8(_)
        | DynamicImage::ImageRgb8(_)
        | DynamicImage::ImageRgba8(_) => {
            let t = srgb8_table();
            let conv = |v: u8| {
                if srgb {
                    t[v as usize]
                } else {
                    v as f32 / 255.0
                }
            };
            img.to_rgb8()
                .pixels()
                .map(|p| [conv(p[0]), conv(p[1]), conv(p[2])])
                .collect()
        }
        DynamicImage::ImageLuma16(_)
        | DynamicImage::ImageLumaA16(_)
        | DynamicImage::ImageRgb16(_)
        | DynamicImage::ImageRgba16(_) => {
            let t = srgb16_table();
            let conv = |v: u16| {
                if srgb {
                    t[v as usize]
                } else {
                    v as f32 / 65535.0
                }
            };
            img.to_rgb16()
                .pixels()
                .map(|p| [conv(p[0]), conv(p[1]), conv(p[2])])
                .collect()
        }
        // float files (EXR, TIFF): a NaN or infinite sample is no radiance
        // the nodes could use; it reads as 0, counted
        _ => img
            .to_rgb32f()
            .pixels()
            .map(|p| {
                [p[0], p[1], p[2]].map(|v| {
                    if v.is_finite() {
                        v
                    } else {
                        *non_finite += 1;
                        0.0
                    }
                })
            })
            .collect(),
    };
    Image::from_vec(w, h, data).map_err(|e| decode_err(path, e.to_string()))
}

depthgraph_graph::ports! {
    /// Outputs of `LoadColor`.
    outputs struct LoadColorOut {
        /// linear RGB
        color: ColorImage,
    }
}

/// The path parameter of a load node, refused when empty.
fn given(path: &str) -> Result<&Path, NodeError> {
    if path.is_empty() {
        return Err(NodeError::param(
            "path",
            "no file given; set it with --set <node>.path=FILE",
        ));
    }
    Ok(Path::new(path))
}

fn load_color_eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &LoadColorParams,
) -> Result<Produced<LoadColorOut>, NodeError> {
    let path = given(&p.path)?;
    let lim = Limits::of(ctx);
    let mut non_finite = 0usize;
    let color = decode_color_counted(
        &read_file(path, &lim)?,
        path,
        p.color_space,
        &lim,
        &mut non_finite,
    )?;
    let out = LoadColorOut { color };
    Ok(if non_finite > 0 {
        Produced::reported(
            out,
            format!("{non_finite} samples NaN or infinite in the file, read as 0"),
        )
    } else {
        out.into()
    })
}

// ---------------------------------------------------------------- depth

depthgraph_graph::param_choice! {
    /// What the samples of a depth file are (the `encoding` parameter).
    pub enum DepthEncoding {
        /// Depth, times `scale` to metres.
        Depth = "depth",
        /// Disparity in pixels (with `focal_px`, `baseline_m`, `doffs_px`).
        Disparity = "disparity",
        /// NYU Depth v2 raw Kinect disparity.
        NyuRaw = "nyu_raw",
    }
}

node_params! {
    /// Parameters of `LoadDepth`.
    pub struct LoadDepthParams {
        /// 8/16-bit grey PNG or TIFF, PFM (float), or EXR (float; channel Z, Y or R).
        pub path: String = "", ParamKind::InputPath;
        /// "depth": values are distances along z; "disparity": values are stereo disparities;
        /// "nyu_raw": NYU Depth v2 raw Kinect dump (16-bit PGM whose samples are little-endian raw
        /// disparity): z = 351.3 / (1092.5 - raw) metres, raw >= 1093 or 0 a hole, beyond 10 m (the NYU toolbox's maxDepth) a hole; scale is unused.
        pub encoding: DepthEncoding = DepthEncoding::Depth, ParamKind::Choice(DepthEncoding::NAMES);
        /// Stored units per metre (depth) or per pixel of disparity. 0 = auto: depth 1000 (millimetres)
        /// from integer files, 1 from float files; disparity 1 (pixels) from either. TUM uses 5000;
        /// Middlebury 2003 quarter-size disparity 4.
        pub scale: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e9 };
        /// Disparity only: focal length in pixels at the disparity's resolution.
        pub focal_px: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e7 };
        /// Disparity only: stereo baseline in metres.
        pub baseline_m: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e3 };
        /// Disparity only: offset added to the disparity (Middlebury `doffs`), in pixels.
        pub doffs_px: f64 = 0.0, ParamKind::Float { min: -1e6, max: 1e6 };
    }
}

/// Raw samples and whether the file stored integers.
struct RawDepth {
    samples: Samples,
    integer: bool,
}

fn read_raw_depth(
    bytes: &[u8],
    path: &Path,
    little_endian_16: bool,
    lim: &Limits,
) -> Result<RawDepth, NodeError> {
    if is_pnm(path) {
        let pnm = decode_pnm(bytes, path, little_endian_16, lim)?;
        if pnm.channels != 1 {
            return Err(decode_err(
                path,
                "expected a grey (P5) depth image, found RGB (P6)",
            ));
        }
        return Ok(RawDepth {
            samples: Samples {
                width: pnm.width,
                height: pnm.height,
                values: pnm.samples.iter().map(|v| *v as f32).collect(),
            },
            integer: true,
        });
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    match ext.as_str() {
        "pfm" => decode_pfm(bytes, path, lim).map(|s| RawDepth {
            samples: s,
            integer: false,
        }),
        "exr" => read_exr_channel(bytes, path, lim),
        _ => {
            let img = decode_image(bytes, path, lim)?;
            let (w, h) = (img.width() as usize, img.height() as usize);
            let values: Vec<f32> = match &img {
                DynamicImage::ImageLuma8(b) => b.as_raw().iter().map(|v| *v as f32).collect(),
                DynamicImage::ImageLuma16(b) => b.as_raw().iter().map(|v| *v as f32).collect(),
                other => {
                    return Err(decode_err(
                        path,
                        format!(
                            "expected a single-channel (grey) 8 or 16-bit depth image, found {:?}",
                            other.color()
                        ),
                    ));
                }
            };
            Ok(RawDepth {
                samples: Samples {
                    width: w,
                    height: h,
                    values,
                },
                integer: true,
            })
        }
    }
}

fn read_exr_channel(bytes: &[u8], path: &Path, lim: &Limits) -> Result<RawDepth, NodeError> {
    use exr::prelude::*;
    check_exr_header(bytes, path, lim)?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .non_parallel()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| decode_err(path, e.to_string()))?;
    let layer = image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    check_dims(path, w, h, lim)?;
    let channels = &layer.channel_data.list;
    let pick = ["Z", "Y", "R", "depth", "Z.Z"]
        .iter()
        .find_map(|n| channels.iter().find(|c| c.name.to_string() == *n))
        .or_else(|| channels.first())
        .ok_or_else(|| decode_err(path, "EXR layer has no channels"))?;
    let values: Vec<f32> = match &pick.sample_data {
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::U32(v) => v.iter().map(|x| *x as f32).collect(),
    };
    if values.len() != w * h {
        return Err(decode_err(
            path,
            "EXR channel size does not match the layer size",
        ));
    }
    Ok(RawDepth {
        samples: Samples {
            width: w,
            height: h,
            values,
        },
        integer: false,
    })
}

/// NYU Depth v2 raw disparity to metres: `z = NYU_RAW_FB / (NYU_RAW_DOFFS - raw)`
/// (NYU toolbox `depth_rel2depth_abs`, Open3D `CreateFromNYUFormat`).
const NYU_RAW_FB: f64 = 351.3;
const NYU_RAW_DOFFS: f64 = 1092.5;
/// Raw values at or above this are no measurement (2047 is the Kinect's "none").
const NYU_RAW_INVALID: f64 = 1093.0;
/// The farthest depth a raw value means, metres: the toolbox's `maxDepth`.
/// Raw values near `NYU_RAW_DOFFS` give any depth (1092 gives 702 m); the
/// toolbox clamps them to 10 m, here they are holes (no reading that far),
/// so they stretch no range and enter no fill.
const NYU_RAW_MAX_M: f64 = 10.0;

/// Reads a depth map in metres (0 = no measurement) from a file.
///
/// Depth: `z = raw / scale`. Disparity: `z = baseline_m * focal_px / (raw / scale + doffs_px)`
/// (Middlebury's `Z = baseline * f / (d + doffs)`). NYU raw: `z = 351.3 / (1092.5 - raw)`
/// with little-endian PGM samples. Raw zeros in integer files, non-finite
/// values, and non-positive results are holes. Binary PGM (P5) is read as well.
pub fn load_depth(path: &Path, p: &LoadDepthParams) -> Result<DepthMap, NodeError> {
    load_depth_with(path, p, &Limits::default())
}

/// [`load_depth`] within the pixel budget `lim`.
pub fn load_depth_with(
    path: &Path,
    p: &LoadDepthParams,
    lim: &Limits,
) -> Result<DepthMap, NodeError> {
    // the parameters are checked before the file is read
    check_depth_params(path, p)?;
    decode_depth(&read_file(path, lim)?, path, p, lim)
}

fn check_depth_params(path: &Path, p: &LoadDepthParams) -> Result<(), NodeError> {
    let nyu = p.encoding == DepthEncoding::NyuRaw;
    if nyu && !is_pnm(path) {
        return Err(NodeError::param(
            "encoding",
            format!(
                "\"nyu_raw\" reads the NYU raw PGM dump; {} is not a .pgm",
                path.display()
            ),
        ));
    }
    Ok(())
}

/// [`load_depth`] of a file's bytes: `path` names the file in errors and
/// its extension picks the format (`.pgm`, `.pfm`, `.exr`, else by magic
/// bytes). The header is checked against `lim` before pixels are decoded.
pub fn decode_depth(
    bytes: &[u8],
    path: &Path,
    p: &LoadDepthParams,
    lim: &Limits,
) -> Result<DepthMap, NodeError> {
    check_depth_params(path, p)?;
    let nyu = p.encoding == DepthEncoding::NyuRaw;
    let raw = read_raw_depth(bytes, path, nyu, lim)?;
    let disparity = p.encoding == DepthEncoding::Disparity;
    // auto: millimetres for integer depth; pixels for disparity (no
    // integer disparity format stores thousandths of a pixel)
    let scale = if p.scale > 0.0 {
        p.scale
    } else if raw.integer && !disparity {
        1000.0
    } else {
        1.0
    };
    if disparity && (p.focal_px <= 0.0 || p.baseline_m <= 0.0) {
        return Err(NodeError::param(
            if p.focal_px <= 0.0 {
                "focal_px"
            } else {
                "baseline_m"
            },
            "disparity files need focal_px and baseline_m (both > 0) to give metres",
        ));
    }
    let fb = p.focal_px * p.baseline_m;
    let values: Vec<f32> = raw
        .samples
        .values
        .iter()
        .map(|&v| {
            if !v.is_finite() || (raw.integer && v == 0.0) {
                return 0.0;
            }
            let z = if nyu {
                // NYU toolbox: z = 351.3 / (1092.5 - raw); raw >= 1093 (2047 included) is no measurement
                let d = NYU_RAW_DOFFS - v as f64;
                // guard: d > 0.5 for every raw < 1093 that gets here
                if v as f64 >= NYU_RAW_INVALID || NYU_RAW_FB / d > NYU_RAW_MAX_M {
                    0.0
                } else {
                    NYU_RAW_FB / d
                }
            } else if disparity {
                let v = v as f64 / scale;
                let d = v + p.doffs_px;
                // guard: a non-positive disparity has no finite depth
                if d <= 0.0 { 0.0 } else { fb / d }
            } else {
                v as f64 / scale
            };
            // (finite in f32: a depth beyond f32's range, e.g. from a
            // disparity of 1e-38, is no measurement either)
            let z = z as f32;
            if z.is_finite() && z > 0.0 { z } else { 0.0 }
        })
        .collect();
    Image::from_vec(raw.samples.width, raw.samples.height, values)
        .map_err(|e| decode_err(path, e.to_string()))
}

depthgraph_graph::ports! {
    /// Outputs of `LoadDepth`.
    outputs struct LoadDepthOut {
        /// metres, 0 = no measurement
        depth: DepthMap,
        /// fraction of pixels without a measurement
        hole_fraction: f64,
    }
}

fn load_depth_eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &LoadDepthParams,
) -> Result<Produced<LoadDepthOut>, NodeError> {
    let depth = load_depth_with(given(&p.path)?, p, &Limits::of(ctx))?;
    // guard: images have at least one pixel (check_dims), max(1) for safety
    let hole_fraction = depth.hole_count() as f64 / depth.len().max(1) as f64;
    Ok(LoadDepthOut {
        depth,
        hole_fraction,
    }
    .into())
}

// ---------------------------------------------------------------- writing

fn write_dynamic(tmp: &Path, img: DynamicImage, fmt: ImageFormat) -> Result<(), WriteFailure> {
    let f = fs::File::create(tmp)?;
    let mut w = BufWriter::new(f);
    img.write_to(&mut w, fmt)?;
    Ok(w.flush()?)
}

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

depthgraph_graph::param_choice! {
    /// Bits per channel of a written PNG (the `bits` parameter).
    pub enum PngBits {
        /// 8-bit sRGB.
        Eight = "8",
        /// 16-bit sRGB.
        Sixteen = "16",
    }
}

node_params! {
    /// Parameters of `SaveColor`.
    pub struct SaveColorParams {
        /// Output file; `.png` (sRGB, 8 or 16 bit), `.exr` (linear float) or `.hdr` (Radiance RGBE, linear). Relative paths go under `--out`.
        pub path: String = "color.png", ParamKind::OutputPath;
        /// PNG bit depth.
        pub bits: PngBits = PngBits::Eight, ParamKind::Choice(PngBits::NAMES);
        /// Exposure adjustment in stops applied before encoding (PNG clips at 1 after it).
        pub exposure_stops: f64 = 0.0, ParamKind::Float { min: -30.0, max: 30.0 };
    }
}

/// Writes a linear color image: PNG is sRGB-encoded (values clipped to [0, 1]
/// after `exposure_stops`), EXR keeps linear floats.
pub fn save_color(
    img: &ColorImage,
    path: &Path,
    bits16: bool,
    exposure_stops: f64,
) -> Result<PathBuf, NodeError> {
    let (w, h) = (img.width() as u32, img.height() as u32);
    let gain = 2f32.powf(exposure_stops as f32);
    match extension(path).as_str() {
        "exr" => {
            let plane = |ch: usize| -> Vec<f32> {
                img.as_slice()
                    .iter()
                    .map(|p| if p[ch].is_finite() { p[ch] * gain } else { 0.0 })
                    .collect()
            };
            let channels = vec![("R", plane(0)), ("G", plane(1)), ("B", plane(2))];
            write_atomic(path, |tmp| write_exr(tmp, img.dims(), "color", channels))
        }
        "hdr" | "pic" => {
            let bytes = radiance::encode_rgbe(&Image::from_vec(
                img.width(),
                img.height(),
                img.as_slice().iter().map(|p| p.map(|v| v * gain)).collect(),
            )?);
            write_atomic(path, |tmp| fs::write(tmp, &bytes))
        }
        "png" => {
            if bits16 {
                let data: Vec<u16> = img
                    .as_slice()
                    .iter()
                    .flat_map(|p| p.map(|v| srgb16(v * gain)))
                    .collect();
                let buf = image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_raw(w, h, data)
                    .ok_or_else(|| NodeError::Internal("color buffer size mismatch".into()))?;
                write_atomic(path, |tmp| {
                    write_dynamic(tmp, DynamicImage::ImageRgb16(buf), ImageFormat::Png)
                })
            } else {
                let data: Vec<u8> = img
                    .as_slice()
                    .iter()
                    .flat_map(|p| p.map(|v| srgb8(v * gain)))
                    .collect();
                let buf = image::RgbImage::from_raw(w, h, data)
                    .ok_or_else(|| NodeError::Internal("color buffer size mismatch".into()))?;
                write_atomic(path, |tmp| {
                    write_dynamic(tmp, DynamicImage::ImageRgb8(buf), ImageFormat::Png)
                })
            }
        }
        other => Err(NodeError::param(
            "path",
            format!("cannot write color as `.{other}`; use .png, .exr or .hdr"),
        )),
    }
}

depthgraph_graph::ports! {
    /// Inputs of `SaveColor`.
    inputs struct SaveColorIn {
        /// linear RGB
        color: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// The output of every Save node.
    outputs struct Written {
        /// the file written
        file: PathBuf,
    }
}

fn save_color_eval(
    ctx: &EvalCtx,
    i: SaveColorIn,
    p: &SaveColorParams,
) -> Result<Produced<Written>, NodeError> {
    let path = ctx.output_path(&p.path)?;
    let file = save_color(
        &i.color,
        &path,
        p.bits == PngBits::Sixteen,
        p.exposure_stops,
    )?;
    Ok(Written { file }.into())
}

depthgraph_graph::param_choice! {
    /// How a depth map is written (the `format` parameter of SaveDepth).
    pub enum DepthFormat {
        /// By the file's extension: `.exr` is EXR, `.png` PNG16 (another
        /// extension is an error).
        Auto = "auto",
        /// 16-bit PNG in millimetres.
        Png16 = "png16",
        /// 32-bit float EXR in metres.
        Exr = "exr",
        /// A colour-mapped 8-bit preview.
        Preview = "preview",
    }
}

node_params! {
    /// Parameters of `SaveDepth`.
    pub struct SaveDepthParams {
        /// Output file. Relative paths go under `--out`.
        pub path: String = "depth.png", ParamKind::OutputPath;
        /// "png16" (integer, `scale` units per metre), "exr" (float metres), "preview"
        /// (colormapped 8-bit PNG, holes black), or "auto" (from the extension: .exr or
        /// .png). The file's extension must match: .png for png16 and preview, .exr for exr.
        pub format: DepthFormat = DepthFormat::Auto, ParamKind::Choice(DepthFormat::NAMES);
        /// png16 only: stored units per metre (1000 = millimetres, TUM uses 5000).
        pub scale: f64 = 1000.0, ParamKind::Float { min: 1e-6, max: 1e9 };
        /// preview only: depth mapped to the first color; 0 with max 0 = 2nd percentile of the data.
        pub min_m: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e6 };
        /// preview only: depth mapped to the last color; 0 = 98th percentile of the data.
        pub max_m: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e6 };
    }
}

/// The depths a preview maps to its first and last colours, as
/// `SaveDepthParams` says: `max_m` when set (> 0), else the data's 98th
/// percentile; `min_m` when set or when `max_m` is, else the 2nd
/// percentile. Both set with `max_m <= min_m` is an error naming `max_m`.
fn preview_range(depth: &DepthMap, p: &SaveDepthParams) -> Result<(f32, f32), NodeError> {
    if p.max_m > 0.0 && p.max_m <= p.min_m {
        return Err(NodeError::param(
            "max_m",
            format!("{} m is not beyond min_m ({} m)", p.max_m, p.min_m),
        ));
    }
    let (auto_lo, auto_hi) = depth_range(depth, 0.02, 0.98);
    let hi = if p.max_m > 0.0 {
        p.max_m as f32
    } else {
        auto_hi
    };
    let lo = if p.min_m > 0.0 || p.max_m > 0.0 {
        p.min_m as f32
    } else {
        auto_lo
    };
    // min_m alone, beyond the data's far end: every pixel one colour
    // (a map without a valid pixel, or one depth equal to min_m, maps to
    // the first colour as before: nothing lies beyond what is shown)
    if p.min_m > 0.0 && p.max_m <= 0.0 && hi < lo && depth.hole_count() < depth.len() {
        return Err(NodeError::param(
            "min_m",
            format!(
                "{} m is beyond the depths to show (98th percentile {auto_hi} m): lower it or set max_m",
                p.min_m
            ),
        ));
    }
    Ok((lo, hi))
}

/// Writes a depth map (see [`SaveDepthParams`] for the forms). In png16, depths
/// beyond 65535 units are stored as 65535 and holes as 0; the count of clipped
/// pixels is returned.
pub fn save_depth(
    depth: &DepthMap,
    path: &Path,
    p: &SaveDepthParams,
) -> Result<(PathBuf, usize), NodeError> {
    let (w, h) = (depth.width() as u32, depth.height() as u32);
    let ext = extension(path);
    let format = match p.format {
        DepthFormat::Auto if ext == "exr" => DepthFormat::Exr,
        DepthFormat::Auto => DepthFormat::Png16,
        f => f,
    };
    // the file's name says what it holds (a depth.pfm of PNG bytes is read
    // back by nothing that goes by its extension)
    let wanted = if format == DepthFormat::Exr {
        "exr"
    } else {
        "png"
    };
    if ext != wanted {
        return Err(NodeError::param(
            "path",
            format!(
                "{} would hold {} data: name it .{wanted}, or choose the format its extension asks for (png16 or preview: .png; exr: .exr)",
                path.display(),
                if wanted == "exr" { "OpenEXR" } else { "PNG" },
            ),
        ));
    }
    match format {
        DepthFormat::Exr => {
            let data: Vec<f32> = depth
                .as_slice()
                .iter()
                .map(|z| if DepthMap::is_valid(*z) { *z } else { 0.0 })
                .collect();
            let written = write_atomic(path, |tmp| {
                write_exr(tmp, depth.dims(), "depth_m", vec![("Z", data)])
            })?;
            Ok((written, 0))
        }
        DepthFormat::Png16 => {
            let mut clipped = 0;
            let data: Vec<u16> = depth
                .as_slice()
                .iter()
                .map(|z| {
                    if !DepthMap::is_valid(*z) {
                        return 0;
                    }
                    let v = (*z as f64 * p.scale).round();
                    if v > 65535.0 {
                        clipped += 1;
                        65535
                    } else {
                        v.max(1.0) as u16
                    }
                })
                .collect();
            let buf = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(w, h, data)
                .ok_or_else(|| NodeError::Internal("depth buffer size mismatch".into()))?;
            let written = write_atomic(path, |tmp| {
                write_dynamic(tmp, DynamicImage::ImageLuma16(buf), ImageFormat::Png)
            })?;
            Ok((written, clipped))
        }
        // `Auto` was resolved to Exr or Png16 above
        DepthFormat::Preview | DepthFormat::Auto => {
            let (lo, hi) = preview_range(depth, p)?;
            let rgb = colormap_depth(depth, lo, hi);
            let data: Vec<u8> = rgb.as_slice().iter().flat_map(|p| p.map(srgb8)).collect();
            let buf = image::RgbImage::from_raw(w, h, data)
                .ok_or_else(|| NodeError::Internal("depth buffer size mismatch".into()))?;
            let written = write_atomic(path, |tmp| {
                write_dynamic(tmp, DynamicImage::ImageRgb8(buf), ImageFormat::Png)
            })?;
            Ok((written, 0))
        }
    }
}

depthgraph_graph::ports! {
    /// Inputs of `SaveDepth`.
    inputs struct SaveDepthIn {
        /// metres
        depth: Arc<DepthMap>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SaveDepth`.
    outputs struct SaveDepthOut {
        /// the file written
        file: PathBuf,
        /// png16: pixels beyond 65535 units, stored as 65535
        clipped: f64,
    }
}

fn save_depth_eval(
    ctx: &EvalCtx,
    i: SaveDepthIn,
    p: &SaveDepthParams,
) -> Result<Produced<SaveDepthOut>, NodeError> {
    let path = ctx.output_path(&p.path)?;
    let (file, clipped) = save_depth(&i.depth, &path, p)?;
    Ok(SaveDepthOut {
        file,
        clipped: clipped as f64,
    }
    .into())
}

// ---------------------------------------------------------------- PLY

depthgraph_graph::param_choice! {
    /// PLY encoding (the `format` parameter of SavePoints / SaveMesh).
    pub enum PlyFormat {
        /// Little-endian binary.
        Binary = "binary",
        /// Text.
        Ascii = "ascii",
    }
}

node_params! {
    /// Parameters of `SavePointCloud` and `SaveMesh`.
    pub struct SavePlyParams {
        /// Output `.ply` file. Relative paths go under `--out`.
        pub path: String = "points.ply", ParamKind::OutputPath;
        /// "binary" (little-endian, compact) or "ascii" (readable).
        pub format: PlyFormat = PlyFormat::Binary, ParamKind::Choice(PlyFormat::NAMES);
    }
}

depthgraph_graph::ports! {
    /// Inputs of `SavePointCloud`.
    inputs struct SavePointsIn {
        /// camera-space points
        points: Arc<PointCloud>,
    }
}

fn save_points_eval(
    ctx: &EvalCtx,
    i: SavePointsIn,
    p: &SavePlyParams,
) -> Result<Produced<Written>, NodeError> {
    let path = ctx.output_path(&p.path)?;
    let pc = &i.points;
    let ascii = p.format == PlyFormat::Ascii;
    let file = write_ply(&path, &pc.positions, &pc.colors, &pc.normals, &[], ascii)?;
    Ok(Written { file }.into())
}

depthgraph_graph::ports! {
    /// Inputs of `SaveMesh`.
    inputs struct SaveMeshIn {
        /// camera-space triangle mesh
        mesh: Arc<Mesh>,
    }
}

fn save_mesh_eval(
    ctx: &EvalCtx,
    i: SaveMeshIn,
    p: &SavePlyParams,
) -> Result<Produced<Written>, NodeError> {
    let path = ctx.output_path(&p.path)?;
    let m = &i.mesh;
    let ascii = p.format == PlyFormat::Ascii;
    let file = write_ply(
        &path,
        &m.positions,
        &m.colors,
        &m.normals,
        &m.triangles,
        ascii,
    )?;
    Ok(Written { file }.into())
}

/// Registers the loaders and writers.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    mask::register(reg)?;
    reg.register(
        PortedNode::new(
            "LoadColor",
            1,
            "Reads a PNG/JPEG/TIFF (8/16-bit, sRGB linearised), EXR or Radiance .hdr color image as linear RGB.",
            load_color_eval,
        )
        .reads(|p: &LoadColorParams| vec![PathBuf::from(&p.path)]),
    )?;
    reg.register(
        PortedNode::new(
            "LoadDepth",
            2,
            "Reads depth in metres from a 16-bit PNG (with a scale), Middlebury PFM or 8-bit disparity (with focal length, baseline, doffs), or float EXR.",
            load_depth_eval,
        )
        .reads(|p: &LoadDepthParams| vec![PathBuf::from(&p.path)]),
    )?;
    reg.register(
        PortedNode::new(
            "LoadSequence",
            1,
            "Reads one colour + depth frame of a sequence: a TUM RGB-D folder (pairs associated by timestamp), \
             a list file or a glob; `frame: \"{frame}\"` in a pipeline run by `depthgraph batch`.",
            sequence::eval,
        )
        .reads(sequence::files_read)
        .guards(sequence::index_files),
    )?;
    reg.register(
        PortedNode::new(
            "SaveColor",
            1,
            "Writes a color image: PNG (sRGB, 8 or 16 bit), EXR (linear float) or Radiance .hdr (RGBE), atomically.",
            save_color_eval,
        )
        .sink(),
    )?;
    reg.register(
        PortedNode::new(
            "SaveDepth",
            1,
            "Writes depth: 16-bit PNG, float EXR, or a colormapped PNG preview, atomically.",
            save_depth_eval,
        )
        .sink(),
    )?;
    reg.register(
        PortedNode::new(
            "SavePointCloud",
            1,
            "Writes a point cloud (positions, colors, normals) as PLY.",
            save_points_eval,
        )
        .sink(),
    )?;
    reg.register(
        PortedNode::new(
            "SaveMesh",
            1,
            "Writes a triangle mesh as PLY.",
            save_mesh_eval,
        )
        .sink(),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {

    #[test]
    fn pnm_color_and_nyu_raw_depth() {
        let dir = tempfile::tempdir().unwrap();
        // 2x1 P6 8-bit: white, black
        let ppm = dir.path().join("c.ppm");
        let mut b = b"P6\n# comment\n2 1\n255\n".to_vec();
        b.extend_from_slice(&[255, 255, 255, 0, 0, 0]);
        std::fs::write(&ppm, b).unwrap();
        let c = super::load_color(&ppm, ColorSpace::Srgb).unwrap();
        assert_eq!(c.dims(), (2, 1));
        assert!((c.get(0, 0)[0] - 1.0).abs() < 1e-6 && c.get(1, 0)[2] == 0.0);
        // 3x1 P5 16-bit with little-endian raw disparity (the NYU dump): 839, 2047 (none), 0 (none)
        let pgm = dir.path().join("d.pgm");
        let mut b = b"P5\n3 1\n65535\n".to_vec();
        for v in [839u16, 2047, 0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&pgm, b).unwrap();
        let p = super::LoadDepthParams {
            encoding: DepthEncoding::NyuRaw,
            ..Default::default()
        };
        let d = super::load_depth(&pgm, &p).unwrap();
        assert!((*d.get(0, 0) - (351.3 / (1092.5 - 839.0)) as f32).abs() < 1e-5);
        assert_eq!((*d.get(1, 0), *d.get(2, 0)), (0.0, 0.0));
        // raw values whose depth is beyond the toolbox's 10 m are holes
        // (1092 meant 702 m): 1057 is 9.9 m, 1058 10.2 m
        let mut b = b"P5\n2 1\n65535\n".to_vec();
        for v in [1057u16, 1058] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let far = dir.path().join("far.pgm");
        std::fs::write(&far, b).unwrap();
        let d = super::load_depth(&far, &p).unwrap();
        assert!((*d.get(0, 0) - (351.3 / 35.5) as f32).abs() < 1e-5);
        assert_eq!(*d.get(1, 0), 0.0);
        // nyu_raw names the parameter on a non-PGM file; truncated data names the file
        let e = super::load_depth(&dir.path().join("x.png"), &p).unwrap_err();
        assert!(e.to_string().contains("encoding"), "{e}");
        std::fs::write(&pgm, b"P5\n3 1\n65535\n\x01").unwrap();
        let e = super::load_depth(&pgm, &p).unwrap_err();
        assert!(e.to_string().contains("d.pgm"), "{e}");
    }
    use super::*;

    fn depth_params() -> LoadDepthParams {
        LoadDepthParams::default()
    }

    #[test]
    fn srgb_round_trip() {
        for i in 0..=255u8 {
            let lin = srgb8_table()[i as usize];
            assert_eq!(srgb8(lin), i);
        }
        assert_eq!(srgb8(f32::NAN), 0);
    }

    #[test]
    fn color_png_round_trip_8_and_16_bit() {
        let dir = tempfile::tempdir().unwrap();
        let img = Image::from_fn(7, 5, |x, y| [x as f32 / 6.0, y as f32 / 4.0, 0.25]);
        for bits16 in [false, true] {
            let path = dir.path().join(format!("c{bits16}.png"));
            save_color(&img, &path, bits16, 0.0).unwrap();
            let back = load_color(&path, ColorSpace::Srgb).unwrap();
            let tol = if bits16 { 1e-4 } else { 6e-3 };
            for (a, b) in img.as_slice().iter().zip(back.as_slice()) {
                for c in 0..3 {
                    assert!((a[c] - b[c]).abs() < tol, "{a:?} vs {b:?}");
                }
            }
        }
        let exr = dir.path().join("c.exr");
        let hdr = Image::from_fn(4, 3, |x, _| [x as f32 * 10.0, 0.5, 1e-3]);
        save_color(&hdr, &exr, false, 0.0).unwrap();
        assert_eq!(load_color(&exr, ColorSpace::Srgb).unwrap(), hdr);
    }

    #[test]
    fn depth_png16_and_exr_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let d = Image::from_fn(6, 4, |x, y| {
            if x == 2 && y == 1 {
                0.0
            } else {
                0.5 + x as f32 * 0.25 + y as f32
            }
        });
        let png = dir.path().join("d.png");
        save_depth(&d, &png, &SaveDepthParams::default()).unwrap();
        let back = load_depth(&png, &depth_params()).unwrap();
        for (a, b) in d.as_slice().iter().zip(back.as_slice()) {
            assert!((a - b).abs() <= 0.0005 + 1e-6, "{a} vs {b}");
        }
        assert_eq!(*back.get(2, 1), 0.0);
        let exr = dir.path().join("d.exr");
        save_depth(&d, &exr, &SaveDepthParams::default()).unwrap();
        assert_eq!(load_depth(&exr, &depth_params()).unwrap(), d);
    }

    #[test]
    fn png16_clips_far_depth_and_counts_it() {
        let dir = tempfile::tempdir().unwrap();
        let d = Image::from_vec(2, 1, vec![1.0, 100.0]).unwrap();
        let (_, clipped) =
            save_depth(&d, &dir.path().join("c.png"), &SaveDepthParams::default()).unwrap();
        assert_eq!(clipped, 1);
    }

    fn write_pfm(path: &Path, w: usize, h: usize, rows_top_first: &[f32]) {
        let mut bytes = format!("Pf\n{w} {h}\n-1.0\n").into_bytes();
        for y in (0..h).rev() {
            for x in 0..w {
                bytes.extend_from_slice(&rows_top_first[y * w + x].to_le_bytes());
            }
        }
        fs::write(path, bytes).unwrap();
    }

    #[test]
    fn pfm_disparity_to_metres_middlebury_formula() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("disp.pfm");
        // top row: 50 px and +inf (unknown); bottom row 100, 0
        write_pfm(&path, 2, 2, &[50.0, f32::INFINITY, 100.0, 0.0]);
        let p = LoadDepthParams {
            encoding: DepthEncoding::Disparity,
            focal_px: 1870.0,
            baseline_m: 0.160,
            doffs_px: 100.0,
            ..Default::default()
        };
        let d = load_depth(&path, &p).unwrap();
        assert!((d.get(0, 0) - (0.160 * 1870.0 / 150.0) as f32).abs() < 1e-5);
        assert_eq!(*d.get(1, 0), 0.0);
        assert!((d.get(0, 1) - (0.160 * 1870.0 / 200.0) as f32).abs() < 1e-5);
        // disparity 0 with doffs 100 is a valid (far) depth for float files
        assert!((d.get(1, 1) - (0.160 * 1870.0 / 100.0) as f32).abs() < 1e-5);
        let e = load_depth(
            &path,
            &LoadDepthParams {
                encoding: DepthEncoding::Disparity,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("focal_px"), "{e}");
    }

    /// An integer disparity file is in pixels unless `scale` says otherwise
    /// (auto's millimetres are for depth: read as thousandths of a pixel,
    /// Middlebury's 8-bit disparities all came out at about `fb / doffs`).
    #[test]
    fn integer_disparities_are_pixels_by_default() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("disp.png");
        image::GrayImage::from_raw(2, 1, vec![100, 0])
            .unwrap()
            .save(&path)
            .unwrap();
        let p = LoadDepthParams {
            encoding: DepthEncoding::Disparity,
            focal_px: 3740.0,
            baseline_m: 0.160,
            doffs_px: 200.0,
            ..Default::default()
        };
        let d = load_depth(&path, &p).unwrap();
        assert!(
            (d.get(0, 0) - (0.160 * 3740.0 / 300.0) as f32).abs() < 1e-5,
            "{}",
            d.get(0, 0)
        );
        // 0 in an integer file is no measurement
        assert_eq!(*d.get(1, 0), 0.0);
        // an explicit scale still applies (Middlebury 2003 quarter size: 4 per pixel)
        let q = load_depth(&path, &LoadDepthParams { scale: 4.0, ..p }).unwrap();
        assert!((q.get(0, 0) - (0.160 * 3740.0 / 225.0) as f32).abs() < 1e-5);
    }

    /// A depth finite in f64 but beyond f32's range is a hole, never +inf.
    #[test]
    fn a_depth_beyond_f32_is_a_hole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.pfm");
        write_pfm(&path, 2, 1, &[1e-38, 50.0]);
        let disp = LoadDepthParams {
            encoding: DepthEncoding::Disparity,
            focal_px: 1870.0,
            baseline_m: 0.160,
            ..Default::default()
        };
        let d = load_depth(&path, &disp).unwrap();
        assert_eq!(*d.get(0, 0), 0.0, "a disparity of 1e-38 is 3e40 m away");
        assert!((d.get(1, 0) - (0.160 * 1870.0 / 50.0) as f32).abs() < 1e-5);
        write_pfm(&path, 2, 1, &[3e38, 2.0]);
        let depth = LoadDepthParams {
            scale: 0.5,
            ..Default::default()
        };
        let d = load_depth(&path, &depth).unwrap();
        assert_eq!(*d.get(0, 0), 0.0, "3e38 / 0.5 overflows f32");
        assert_eq!(*d.get(1, 0), 4.0);
        assert!(d.as_slice().iter().all(|z| z.is_finite()));
    }

    /// A path that is not a regular file (a FIFO, which a read waits on
    /// for ever, or `/dev/zero`, which never ends) is an error at once, and
    /// so is a file larger than any image within the budget holds.
    #[test]
    fn a_path_that_is_not_a_regular_file_is_an_error_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.png");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo");
        let (tx, rx) = std::sync::mpsc::channel();
        let paths = [
            fifo.clone(),
            PathBuf::from("/dev/zero"),
            dir.path().to_path_buf(),
        ];
        std::thread::spawn(move || {
            for p in paths {
                let d = load_depth(&p, &LoadDepthParams::default()).map(|_| ());
                let c = load_color(&p, ColorSpace::Srgb).map(|_| ());
                let key = depthgraph_graph::key::with_file_contents(
                    depthgraph_graph::key::Key::from_bytes([0; 32]),
                    std::slice::from_ref(&p),
                );
                let _ = tx.send((p, d, c, key));
            }
        });
        for _ in 0..3 {
            // (a regression would wait on the FIFO or read /dev/zero for ever)
            let (p, d, c, _) = rx
                .recv_timeout(std::time::Duration::from_secs(20))
                .expect("every path answers at once");
            let (d, c) = (d.unwrap_err().to_string(), c.unwrap_err().to_string());
            if p.is_dir() {
                assert!(d.contains(&p.display().to_string()), "{d}");
            } else {
                assert!(d.contains("not a regular file"), "{d}");
                assert!(c.contains("not a regular file"), "{c}");
            }
        }
        // more bytes than the budget's pixels hold: refused before reading
        // (a sparse file: nothing is written)
        let big = dir.path().join("big.pfm");
        let f = fs::File::create(&big).unwrap();
        f.set_len(65 << 20).unwrap();
        let e = load_depth_with(&big, &LoadDepthParams::default(), &Limits { max_pixels: 4 })
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("more than an image within the pixel budget"),
            "{e}"
        );
    }

    /// The preview's range follows its parameters' docs: a set `min_m`
    /// holds with the 98th percentile above it, a set `max_m` with 0
    /// below, both as given, neither the data's percentiles; a `max_m`
    /// not beyond `min_m` is an error naming it.
    #[test]
    fn a_previews_range_keeps_what_is_set() {
        let d = DepthMap::from_fn(100, 1, |x, _| 1.0 + x as f32 * 0.1);
        let (alo, ahi) = depth_range(&d, 0.02, 0.98);
        let at = |min_m, max_m| {
            preview_range(
                &d,
                &SaveDepthParams {
                    min_m,
                    max_m,
                    ..Default::default()
                },
            )
        };
        assert_eq!(at(0.0, 0.0).unwrap(), (alo, ahi));
        assert_eq!(at(2.0, 0.0).unwrap(), (2.0, ahi));
        assert_eq!(at(0.0, 5.0).unwrap(), (0.0, 5.0));
        assert_eq!(at(2.0, 5.0).unwrap(), (2.0, 5.0));
        let e = at(5.0, 3.0).unwrap_err().to_string();
        assert!(e.contains("max_m"), "{e}");
        // min_m alone beyond the data's far end: an error, not one colour
        let e = at(20.0, 0.0).unwrap_err().to_string();
        assert!(e.contains("min_m"), "{e}");
        // a map without a valid pixel still previews (all black)
        let empty = DepthMap::filled(4, 1, 0.0);
        let p = SaveDepthParams {
            min_m: 2.0,
            ..Default::default()
        };
        assert!(preview_range(&empty, &p).is_ok());
    }

    /// SaveDepth writes what its file's name says (a .pfm or .tif got PNG
    /// bytes, a .png EXR bytes with format exr) or names the mismatch.
    #[test]
    fn a_depth_file_holds_what_its_extension_says() {
        let dir = tempfile::tempdir().unwrap();
        let d = DepthMap::filled(4, 3, 1.5);
        let save = |name: &str, format| {
            save_depth(
                &d,
                &dir.path().join(name),
                &SaveDepthParams {
                    format,
                    ..Default::default()
                },
            )
        };
        for (name, format) in [
            ("d.pfm", DepthFormat::Auto),
            ("d.tif", DepthFormat::Png16),
            ("d.png", DepthFormat::Exr),
            ("d.exr", DepthFormat::Preview),
        ] {
            let e = save(name, format).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains("path"), "{name}: {e}");
            assert!(!dir.path().join(name).exists());
        }
        for (name, format) in [
            ("a.exr", DepthFormat::Auto),
            ("a.png", DepthFormat::Auto),
            ("b.PNG", DepthFormat::Preview),
            ("c.exr", DepthFormat::Exr),
        ] {
            save(name, format).unwrap();
        }
        let back = load_depth(&dir.path().join("a.exr"), &LoadDepthParams::default()).unwrap();
        assert_eq!(*back.get(1, 1), 1.5);
    }

    /// A float colour file's NaN and infinite samples read as 0, counted
    /// for the node's report; finite ones, negative included, as they are.
    #[test]
    fn non_finite_colour_samples_read_as_zero() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.exr");
        let raw = vec![
            f32::NAN,
            0.5,
            f32::INFINITY,
            0.25,
            -0.125,
            f32::NEG_INFINITY,
        ];
        image::Rgb32FImage::from_raw(2, 1, raw)
            .unwrap()
            .save(&path)
            .unwrap();
        let bytes = fs::read(&path).unwrap();
        let mut n = 0;
        let c = decode_color_counted(
            &bytes,
            &path,
            ColorSpace::Linear,
            &Limits::default(),
            &mut n,
        )
        .unwrap();
        assert_eq!(n, 3);
        assert_eq!(c.as_slice(), &[[0.0, 0.5, 0.0], [0.25, -0.125, 0.0]]);
        assert!(
            load_color(&path, ColorSpace::Srgb)
                .unwrap()
                .as_slice()
                .iter()
                .flatten()
                .all(|v| v.is_finite())
        );
    }

    /// Headers ending in `\r\n` (written on Windows) read their samples
    /// from after the `\n`, not one byte early; a plain `\n` as before.
    #[test]
    fn crlf_headers_of_pfm_and_pgm_read_their_samples() {
        let mut pfm = b"Pf\r\n2 1\r\n-1.0\r\n".to_vec();
        for v in [1.5f32, 2.5] {
            pfm.extend_from_slice(&v.to_le_bytes());
        }
        let s = pfm::decode_pfm(&pfm, Path::new("a.pfm"), &Limits::default()).unwrap();
        assert_eq!(s.values, vec![1.5, 2.5]);
        let mut pgm = b"P5\r\n2 1\r\n255\r\n".to_vec();
        pgm.extend_from_slice(&[10, 20]);
        let p = decode_pnm(&pgm, Path::new("a.pgm"), false, &Limits::default()).unwrap();
        assert_eq!(p.samples, vec![10, 20]);
        // a LF header whose first sample is 10 (a newline byte) stays as it was
        let mut lf = b"P5\n2 1\n255\n".to_vec();
        lf.extend_from_slice(&[10, 20]);
        let p = decode_pnm(&lf, Path::new("b.pgm"), false, &Limits::default()).unwrap();
        assert_eq!(p.samples, vec![10, 20]);
    }

    #[test]
    fn malformed_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let cases: &[(&str, &[u8])] = &[
            ("empty.png", b""),
            ("garbage.png", b"\x89PNG\r\n\x1a\nnot really"),
            ("trunc.pfm", b"Pf\n4 4\n-1.0\n\x00\x00"),
            ("huge.pfm", b"Pf\n100000 100000\n-1.0\n"),
            ("zero.pfm", b"Pf\n0 3\n-1.0\n"),
            ("magic.pfm", b"P5\n1 1\n255\n\x00"),
            ("header.pfm", b"Pf"),
            ("nan.pfm", b"Pf\n1 1\nnan\n\x00\x00\x00\x00"),
            ("inf.pfm", b"Pf\n1 1\n-inf\n\x00\x00\x00\x00"),
            ("zeroscale.pfm", b"Pf\n1 1\n0.0\n\x00\x00\x00\x00"),
            ("bad.exr", b"v/1\x01garbage"),
            ("bad.jpg", b"\xff\xd8\xff\xe0 nonsense"),
        ];
        for (name, bytes) in cases {
            let path = dir.path().join(name);
            fs::write(&path, bytes).unwrap();
            let e = load_depth(&path, &depth_params());
            assert!(e.is_err(), "{name} loaded as depth");
            assert!(
                e.unwrap_err().to_string().contains(name),
                "error must name the file"
            );
            assert!(
                load_color(&path, ColorSpace::Srgb).is_err(),
                "{name} loaded as color"
            );
        }
        // a color PNG is not a depth map
        let rgb = dir.path().join("rgb.png");
        save_color(&Image::filled(2, 2, [0.5, 0.5, 0.5]), &rgb, false, 0.0).unwrap();
        let e = load_depth(&rgb, &depth_params()).unwrap_err();
        assert!(e.to_string().contains("single-channel"), "{e}");
        assert!(load_color(&dir.path().join("missing.png"), ColorSpace::Srgb).is_err());
    }

    #[test]
    fn the_same_image_is_written_as_the_same_bytes() {
        let dir = tempfile::tempdir().unwrap();
        // large enough for many chunks compressed in parallel
        let (w, h) = (300, 257);
        let color = ColorImage::from_fn(w, h, |x, y| {
            let v = ((x * 7 + y * 13) % 97) as f32 / 97.0;
            [v, 1.0 - v, (x ^ y) as f32 / 512.0]
        });
        let depth = DepthMap::from_fn(w, h, |x, y| {
            if (x + y) % 11 == 0 {
                0.0
            } else {
                0.5 + (x * y) as f32 * 1e-4
            }
        });
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap();
        let mut seen: Vec<Vec<u8>> = Vec::new();
        for i in 0..3 {
            let (c, d) = (
                dir.path().join(format!("c{i}.exr")),
                dir.path().join(format!("d{i}.exr")),
            );
            pool.install(|| {
                save_color(&color, &c, false, 0.0).unwrap();
                save_depth(
                    &depth,
                    &d,
                    &SaveDepthParams {
                        path: String::new(),
                        ..Default::default()
                    },
                )
                .unwrap();
            });
            let both = [fs::read(&c).unwrap(), fs::read(&d).unwrap()].concat();
            if let Some(first) = seen.first() {
                assert!(*first == both, "run {i} wrote other bytes");
            }
            seen.push(both);
            // and the pixels come back
            assert_eq!(load_color(&c, ColorSpace::Linear).unwrap(), color);
            assert_eq!(load_depth(&d, &depth_params()).unwrap(), depth);
        }
    }

    #[test]
    fn headers_are_checked_against_the_budget_before_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let exr = dir.path().join("d.exr");
        let depth = DepthMap::from_fn(8, 6, |x, _| 1.0 + x as f32);
        save_depth(
            &depth,
            &exr,
            &SaveDepthParams {
                path: String::new(),
                ..Default::default()
            },
        )
        .unwrap();
        let bytes = fs::read(&exr).unwrap();
        let tight = Limits { max_pixels: 47 };
        let e = decode_depth(&bytes, &exr, &depth_params(), &tight).unwrap_err();
        assert!(
            e.to_string().contains("8x6") && e.to_string().contains("47 pixels"),
            "{e}"
        );
        assert!(decode_depth(&bytes, &exr, &depth_params(), &Limits { max_pixels: 48 }).is_ok());
        // PNG, PNM and PFM alike
        let png = dir.path().join("c.png");
        save_color(&Image::filled(8, 6, [0.5f32; 3]), &png, false, 0.0).unwrap();
        let b = fs::read(&png).unwrap();
        assert!(decode_color(&b, &png, ColorSpace::Srgb, &tight).is_err());
        assert!(decode_color(&b, &png, ColorSpace::Srgb, &Limits { max_pixels: 48 }).is_ok());
        let pgm = b"P5\n8 6\n255\n"
            .iter()
            .copied()
            .chain([7u8; 48])
            .collect::<Vec<u8>>();
        assert!(decode_pnm(&pgm, Path::new("x.pgm"), false, &tight).is_err());
        assert!(decode_pnm(&pgm, Path::new("x.pgm"), false, &Limits { max_pixels: 48 }).is_ok());
        let pfm = b"Pf\n8 6\n-1\n"
            .iter()
            .copied()
            .chain([0u8; 192])
            .collect::<Vec<u8>>();
        assert!(decode_pfm(&pfm, Path::new("x.pfm"), &tight).is_err());
        assert!(decode_pfm(&pfm, Path::new("x.pfm"), &Limits { max_pixels: 48 }).is_ok());
    }

    #[test]
    fn a_failed_write_names_the_file_and_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("file");
        fs::write(&blocker, b"x").unwrap();
        // a directory that cannot exist: its parent is a regular file
        let target = blocker.join("sub").join("c.exr");
        let e = save_color(&Image::filled(2, 2, [0.5f32; 3]), &target, false, 0.0).unwrap_err();
        assert_eq!(e.kind(), FailureKind::Io, "{e}");
        assert!(e.to_string().contains("sub"), "{e}");
        // an I/O error inside the writer is an I/O error, not an encoding one
        let t = dir.path().join("t.png");
        let e = write_atomic(&t, |_| {
            Err(std::io::Error::from(std::io::ErrorKind::StorageFull))
        })
        .unwrap_err();
        assert_eq!(e.kind().exit_code(), 74, "{e}");
        assert!(!t.exists());
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn ply_binary_layout() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.ply");
        let pos = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]];
        write_ply(&path, &pos, &[[1.0; 3]; 3], &[], &[[0, 1, 2]], false).unwrap();
        let bytes = fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&bytes);
        let end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 3") && text.contains("element face 1"));
        // 3 vertices * (12 + 3) bytes + 1 face * (1 + 12)
        assert_eq!(bytes.len() - end, 3 * 15 + 13);
        assert!(write_ply(&path, &pos, &[], &[], &[[0, 1, 5]], false).is_err());
    }

    #[test]
    fn atomic_write_leaves_no_temp_on_failure() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("x.png");
        let r = write_atomic(&target, |tmp| {
            fs::write(tmp, b"partial").unwrap();
            Err(WriteFailure::Encode("boom".into()))
        });
        assert!(r.is_err());
        assert!(!target.exists());
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
