//! Typed values that flow along the wires of a pipeline.
//!
//! Every value is immutable once produced and shared by [`Arc`], so a cached
//! result can feed many downstream nodes without copies.
//!
//! # Conventions (stated once, used everywhere)
//!
//! - **Color** is linear RGB in `f32`, scene-referred (HDR values above 1 are
//!   allowed). 8-bit files are sRGB-encoded and are linearised on load.
//! - **Depth** is the camera-space `z` coordinate in **metres** (not the
//!   distance along the ray). A pixel with **no measurement** holds `0.0`;
//!   readers must also treat NaN, infinities and negative values as "no
//!   measurement" ([`DepthMap::is_valid`]), and every node in this project
//!   writes `0.0` for holes.
//! - **Mask** and **Confidence** are `f32` in `[0, 1]`.
//! - Images are row-major, `y` down, pixel centres at integer + 0.5.
//! - Camera frame: `x` right, `y` down, `z` forward (OpenCV convention).

use std::fmt;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

/// A row-major 2-D grid of pixels.
#[derive(Clone, PartialEq)]
pub struct Image<T> {
    width: usize,
    height: usize,
    data: Vec<T>,
}

impl<T: fmt::Debug> fmt::Debug for Image<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Image({}x{})", self.width, self.height)
    }
}

/// Error for an image whose buffer does not match its dimensions.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("image buffer holds {found} pixels, expected {width}x{height} = {expected}")]
pub struct ShapeError {
    pub width: usize,
    pub height: usize,
    pub expected: usize,
    pub found: usize,
}

impl<T: Clone> Image<T> {
    /// An image filled with one value.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
        }
    }
}

impl<T> Image<T> {
    /// Wraps a row-major buffer; fails when its length is not `width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Result<Self, ShapeError> {
        let expected = width.saturating_mul(height);
        if data.len() != expected {
            return Err(ShapeError {
                width,
                height,
                expected,
                found: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Builds an image by calling `f(x, y)` for every pixel.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> T) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    /// `(width, height)`.
    pub fn dims(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    pub fn len(&self) -> usize {
        self.data.len()
    }
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
    pub fn as_slice(&self) -> &[T] {
        &self.data
    }
    pub fn as_mut_slice(&mut self) -> &mut [T] {
        &mut self.data
    }
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }
    /// Pixel at `(x, y)`; panics when out of bounds (an internal bug, not user input).
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> &T {
        &self.data[y * self.width + x]
    }
    #[inline]
    pub fn get_mut(&mut self, x: usize, y: usize) -> &mut T {
        &mut self.data[y * self.width + x]
    }
    /// Pixel at `(x, y)` or `None` when outside.
    #[inline]
    pub fn try_get(&self, x: isize, y: isize) -> Option<&T> {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            None
        } else {
            Some(&self.data[y as usize * self.width + x as usize])
        }
    }
    /// One row as a slice.
    pub fn row(&self, y: usize) -> &[T] {
        &self.data[y * self.width..(y + 1) * self.width]
    }
    /// Applies `f` to every pixel.
    pub fn map<U>(&self, f: impl Fn(&T) -> U) -> Image<U> {
        Image {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(f).collect(),
        }
    }
    /// Same dimensions as `other`.
    pub fn same_dims<U>(&self, other: &Image<U>) -> bool {
        self.width == other.width && self.height == other.height
    }
}

/// Linear RGB, scene-referred.
pub type Rgb = [f32; 3];

/// Linear RGB image (see the module conventions).
pub type ColorImage = Image<Rgb>;

/// Depth in metres, `0.0` = no measurement (see the module conventions).
pub type DepthMap = Image<f32>;

/// Per-pixel values in `[0, 1]`: selection masks, alpha.
pub type Mask = Image<f32>;

/// Per-pixel confidence in `[0, 1]`.
pub type Confidence = Image<f32>;

/// Unit normals in the camera frame; `[0, 0, 0]` where unknown.
pub type NormalMap = Image<[f32; 3]>;

/// Integer labels per pixel (object ids); `0` = background / none.
pub type LabelImage = Image<u32>;

impl DepthMap {
    /// True when `z` is a measurement (finite and strictly positive).
    #[inline]
    pub fn is_valid(z: f32) -> bool {
        z.is_finite() && z > 0.0
    }
    /// Number of pixels without a measurement.
    pub fn hole_count(&self) -> usize {
        self.as_slice()
            .iter()
            .filter(|z| !Self::is_valid(**z))
            .count()
    }
}

/// Pinhole camera intrinsics in pixels, for an image of `width` x `height`.
///
/// Projection (3d-editing eq. 1, inverted): `u = fx * x / z + cx`, `v = fy * y / z + cy`
/// with pixel centres at integer + 0.5 when `cx = width / 2`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

impl Intrinsics {
    /// Camera-space point for pixel coordinate `(u, v)` at depth `z` metres.
    #[inline]
    pub fn unproject(&self, u: f64, v: f64, z: f64) -> glam::DVec3 {
        glam::DVec3::new((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z)
    }
    /// Pixel coordinate of a camera-space point; `None` when `z <= 0`.
    #[inline]
    pub fn project(&self, p: glam::DVec3) -> Option<glam::DVec2> {
        if p.z > 0.0 {
            Some(glam::DVec2::new(
                self.fx * p.x / p.z + self.cx,
                self.fy * p.y / p.z + self.cy,
            ))
        } else {
            None
        }
    }
    /// The same camera seen at another resolution (principal point and focal
    /// lengths scaled with the pixel grid).
    pub fn scaled_to(&self, width: usize, height: usize) -> Intrinsics {
        let sx = width as f64 / self.width.max(1) as f64;
        let sy = height as f64 / self.height.max(1) as f64;
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            width,
            height,
        }
    }
    /// True when every focal length is finite and positive.
    pub fn is_sane(&self) -> bool {
        self.fx.is_finite()
            && self.fy.is_finite()
            && self.fx > 0.0
            && self.fy > 0.0
            && self.cx.is_finite()
            && self.cy.is_finite()
    }
}

/// A set of camera-space points (metres) with optional colors and normals.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PointCloud {
    pub positions: Vec<[f32; 3]>,
    /// Empty, or one linear RGB color per point.
    pub colors: Vec<Rgb>,
    /// Empty, or one unit normal per point.
    pub normals: Vec<[f32; 3]>,
}

/// An indexed triangle mesh in camera space (metres).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Empty, or one linear RGB color per vertex.
    pub colors: Vec<Rgb>,
    /// Empty, or one unit normal per vertex.
    pub normals: Vec<[f32; 3]>,
    /// Counter-clockwise as seen from the camera.
    pub triangles: Vec<[u32; 3]>,
}

/// Low-dynamic-range exposures of one scene, as a camera stores them.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExposureStack {
    /// Pixel values in `[0, 1]` after the camera response (not linear).
    pub images: Vec<ColorImage>,
    /// Exposure time of each image in seconds.
    pub times_s: Vec<f64>,
}

/// The type of a port or value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum ValueType {
    Color,
    Depth,
    Mask,
    Confidence,
    Normals,
    Labels,
    Intrinsics,
    PointCloud,
    Mesh,
    ExposureStack,
    Scalar,
    /// A file that a sink node wrote.
    File,
}

impl ValueType {
    pub const ALL: [ValueType; 12] = [
        ValueType::Color,
        ValueType::Depth,
        ValueType::Mask,
        ValueType::Confidence,
        ValueType::Normals,
        ValueType::Labels,
        ValueType::Intrinsics,
        ValueType::PointCloud,
        ValueType::Mesh,
        ValueType::ExposureStack,
        ValueType::Scalar,
        ValueType::File,
    ];

    /// Name as written in documentation and error messages.
    pub fn name(self) -> &'static str {
        match self {
            ValueType::Color => "Color",
            ValueType::Depth => "Depth",
            ValueType::Mask => "Mask",
            ValueType::Confidence => "Confidence",
            ValueType::Normals => "Normals",
            ValueType::Labels => "Labels",
            ValueType::Intrinsics => "Intrinsics",
            ValueType::PointCloud => "PointCloud",
            ValueType::Mesh => "Mesh",
            ValueType::ExposureStack => "ExposureStack",
            ValueType::Scalar => "Scalar",
            ValueType::File => "File",
        }
    }

    /// Whether a value of type `self` may feed a port of type `to`.
    /// Mask and Confidence share a representation and convert freely.
    pub fn connects_to(self, to: ValueType) -> bool {
        self == to
            || matches!(
                (self, to),
                (ValueType::Mask, ValueType::Confidence) | (ValueType::Confidence, ValueType::Mask)
            )
    }
}

impl fmt::Display for ValueType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A value on a wire.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Color(Arc<ColorImage>),
    Depth(Arc<DepthMap>),
    Mask(Arc<Mask>),
    Confidence(Arc<Confidence>),
    Normals(Arc<NormalMap>),
    Labels(Arc<LabelImage>),
    Intrinsics(Intrinsics),
    PointCloud(Arc<PointCloud>),
    Mesh(Arc<Mesh>),
    ExposureStack(Arc<ExposureStack>),
    Scalar(f64),
    /// Path of a file written by a sink.
    File(std::path::PathBuf),
}

impl Value {
    pub fn value_type(&self) -> ValueType {
        match self {
            Value::Color(_) => ValueType::Color,
            Value::Depth(_) => ValueType::Depth,
            Value::Mask(_) => ValueType::Mask,
            Value::Confidence(_) => ValueType::Confidence,
            Value::Normals(_) => ValueType::Normals,
            Value::Labels(_) => ValueType::Labels,
            Value::Intrinsics(_) => ValueType::Intrinsics,
            Value::PointCloud(_) => ValueType::PointCloud,
            Value::Mesh(_) => ValueType::Mesh,
            Value::ExposureStack(_) => ValueType::ExposureStack,
            Value::Scalar(_) => ValueType::Scalar,
            Value::File(_) => ValueType::File,
        }
    }

    /// Approximate heap size in bytes (what the cache budgets count).
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        match self {
            Value::Color(i) => i.len() * size_of::<Rgb>(),
            Value::Depth(i) | Value::Mask(i) | Value::Confidence(i) => i.len() * 4,
            Value::Normals(i) => i.len() * 12,
            Value::Labels(i) => i.len() * 4,
            Value::Intrinsics(_) => size_of::<Intrinsics>(),
            Value::PointCloud(p) => (p.positions.len() + p.colors.len() + p.normals.len()) * 12,
            Value::Mesh(m) => {
                (m.positions.len() + m.colors.len() + m.normals.len() + m.triangles.len()) * 12
            }
            Value::ExposureStack(s) => {
                s.images.iter().map(|i| i.len() * 12).sum::<usize>() + s.times_s.len() * 8
            }
            Value::Scalar(_) => 8,
            Value::File(p) => p.as_os_str().len(),
        }
    }

    /// Pixel dimensions for image-like values.
    pub fn image_dims(&self) -> Option<(usize, usize)> {
        match self {
            Value::Color(i) => Some(i.dims()),
            Value::Depth(i) | Value::Mask(i) | Value::Confidence(i) => Some(i.dims()),
            Value::Normals(i) => Some(i.dims()),
            Value::Labels(i) => Some(i.dims()),
            Value::ExposureStack(s) => s.images.first().map(|i| i.dims()),
            _ => None,
        }
    }
}

macro_rules! value_from {
    ($($variant:ident : $t:ty),*) => {$(
        impl From<$t> for Value {
            fn from(v: $t) -> Value { Value::$variant(Arc::new(v)) }
        }
    )*};
}
value_from!(Color: ColorImage, Labels: LabelImage, PointCloud: PointCloud, Mesh: Mesh, ExposureStack: ExposureStack);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_vec_rejects_wrong_length() {
        let err = Image::from_vec(3, 2, vec![0.0f32; 5]).unwrap_err();
        assert_eq!(err.expected, 6);
        assert_eq!(err.found, 5);
        assert!(Image::from_vec(3, 2, vec![0.0f32; 6]).is_ok());
    }

    #[test]
    fn project_inverts_unproject() {
        let k = Intrinsics {
            fx: 525.0,
            fy: 520.0,
            cx: 319.5,
            cy: 239.5,
            width: 640,
            height: 480,
        };
        let p = k.unproject(100.25, 400.5, 2.5);
        let uv = k.project(p).unwrap();
        assert!((uv.x - 100.25).abs() < 1e-9 && (uv.y - 400.5).abs() < 1e-9);
        assert!(k.project(glam::DVec3::new(1.0, 1.0, 0.0)).is_none());
    }

    #[test]
    fn depth_validity_convention() {
        assert!(DepthMap::is_valid(0.5));
        for z in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert!(!DepthMap::is_valid(z));
        }
        let d = DepthMap::from_vec(2, 2, vec![1.0, 0.0, f32::NAN, 2.0]).unwrap();
        assert_eq!(d.hole_count(), 2);
    }

    #[test]
    fn mask_and_confidence_connect() {
        assert!(ValueType::Mask.connects_to(ValueType::Confidence));
        assert!(!ValueType::Depth.connects_to(ValueType::Mask));
    }
}
