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

use std::any::Any;
use std::fmt;
use std::marker::PhantomData;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

/// Marker types that tell images of the same pixel type apart (the second
/// parameter of [`Image`]): a depth map is not a mask, though both hold one
/// `f32` per pixel. Constructors are generic in the tag, so the tag comes
/// from the type the caller asks for; turning one kind into another is an
/// explicit [`Image::retag`].
pub mod tag {
    /// An image with no further meaning (color, labels, scratch buffers).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub struct Plain;
    /// Depth in metres, `0` = no measurement.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub struct Depth;
    /// Selection or alpha in `[0, 1]`.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub struct Mask;
    /// Confidence in `[0, 1]`.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub struct Confidence;
    /// Unit normals in the camera frame.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    pub struct Normals;
}

/// A row-major 2-D grid of pixels of type `T`; `K` (a [`tag`]) says what
/// the pixels mean.
pub struct Image<T, K = tag::Plain> {
    width: usize,
    height: usize,
    data: Vec<T>,
    kind: PhantomData<K>,
}

impl<T: Clone, K> Clone for Image<T, K> {
    fn clone(&self) -> Self {
        Self {
            width: self.width,
            height: self.height,
            data: self.data.clone(),
            kind: PhantomData,
        }
    }
}

impl<T: PartialEq, K> PartialEq for Image<T, K> {
    fn eq(&self, o: &Self) -> bool {
        self.width == o.width && self.height == o.height && self.data == o.data
    }
}

impl<T, K> fmt::Debug for Image<T, K> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Image({}x{})", self.width, self.height)
    }
}

/// Error for an image whose buffer does not match its dimensions.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("image buffer holds {found} pixels, expected {width}x{height} = {expected}")]
pub struct ShapeError {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Pixels needed, `width * height`.
    pub expected: usize,
    /// Pixels the buffer holds.
    pub found: usize,
}

impl<T: Clone, K> Image<T, K> {
    /// An image filled with one value.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
            kind: PhantomData,
        }
    }
}

impl<T, K> Image<T, K> {
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
            kind: PhantomData,
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
            kind: PhantomData,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// `(width, height)`.
    pub fn dims(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.data.len()
    }
    /// True for an image without pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
    /// The pixels, row-major.
    pub fn as_slice(&self) -> &[T] {
        &self.data
    }
    /// The pixels, row-major, writable.
    pub fn as_mut_slice(&mut self) -> &mut [T] {
        &mut self.data
    }
    /// The pixel buffer, row-major.
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }
    /// Pixel at `(x, y)`; panics when out of bounds (an internal bug, not user input).
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> &T {
        &self.data[y * self.width + x]
    }
    /// Mutable pixel at `(x, y)`; panics when out of bounds (an internal bug).
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
    /// Applies `f` to every pixel; the result's kind is the one the caller asks for.
    pub fn map<U, K2>(&self, f: impl Fn(&T) -> U) -> Image<U, K2> {
        Image {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(f).collect(),
            kind: PhantomData,
        }
    }
    /// Applies `f` to every pixel, keeping the pixel type and the kind (a
    /// depth map stays a depth map).
    pub fn map_same(&self, f: impl Fn(&T) -> T) -> Self {
        self.map(f)
    }
    /// The same pixels with another meaning: the one explicit way to turn,
    /// say, a mask into a confidence.
    pub fn retag<K2>(self) -> Image<T, K2> {
        Image {
            width: self.width,
            height: self.height,
            data: self.data,
            kind: PhantomData,
        }
    }
    /// Same dimensions as `other`.
    pub fn same_dims<U, K2>(&self, other: &Image<U, K2>) -> bool {
        self.width == other.width && self.height == other.height
    }
}

/// Linear RGB, scene-referred.
pub type Rgb = [f32; 3];

/// Linear RGB image (see the module conventions).
pub type ColorImage = Image<Rgb>;

/// Depth in metres, `0.0` = no measurement (see the module conventions).
pub type DepthMap = Image<f32, tag::Depth>;

/// Per-pixel values in `[0, 1]`: selection masks, alpha.
pub type Mask = Image<f32, tag::Mask>;

/// Per-pixel confidence in `[0, 1]`.
pub type Confidence = Image<f32, tag::Confidence>;

/// Unit normals in the camera frame; `[0, 0, 0]` where unknown.
pub type NormalMap = Image<[f32; 3], tag::Normals>;

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
    /// The map with every hole written as `0` (the one spelling of a hole
    /// a node outputs): `d` itself when it already is, else a copy whose
    /// negative, NaN and infinite samples are 0.
    pub fn canonical_holes(d: &Arc<Self>) -> Arc<Self> {
        // +0.0 by its bits: -0.0 is rewritten too
        if d.as_slice()
            .iter()
            .all(|z| Self::is_valid(*z) || z.to_bits() == 0)
        {
            return Arc::clone(d);
        }
        let mut c = (**d).clone();
        for z in c.as_mut_slice() {
            if !Self::is_valid(*z) {
                *z = 0.0;
            }
        }
        Arc::new(c)
    }
}

/// Pinhole camera intrinsics in pixels, for an image of `width` x `height`.
///
/// Projection (3d-editing eq. 1, inverted): `u = fx * x / z + cx`, `v = fy * y / z + cy`
/// with pixel centres at integer + 0.5 when `cx = width / 2`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along `x`, in pixels.
    pub fx: f64,
    /// Focal length along `y`, in pixels.
    pub fy: f64,
    /// Principal point `x`, in pixels.
    pub cx: f64,
    /// Principal point `y`, in pixels.
    pub cy: f64,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
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
    /// Point positions in camera space, metres.
    pub positions: Vec<[f32; 3]>,
    /// Empty, or one linear RGB color per point.
    pub colors: Vec<Rgb>,
    /// Empty, or one unit normal per point.
    pub normals: Vec<[f32; 3]>,
}

/// An indexed triangle mesh in camera space (metres).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    /// Vertex positions in camera space, metres.
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

/// One directional virtual point light (instant radiosity, 3d-editing
/// §IV.A): light arriving from `direction` with irradiance `power`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vpl {
    /// Unit direction towards the light, camera frame.
    pub direction: [f32; 3],
    /// Irradiance at normal incidence, linear RGB.
    pub power: Rgb,
}

/// A set of directional VPLs, as `VplSample` draws them from an environment map.
pub type VplSet = Vec<Vpl>;

/// A value of a kind defined outside this crate (by a node crate): its
/// type name, its size for the cache budgets and, where it can be kept on
/// disk, its encoding. Adding such a kind touches only the crate that
/// defines it: implement this trait and, for the disk cache, register a
/// decoder with [`Registry::register_value`](crate::registry::Registry::register_value).
pub trait Extension: Any + Send + Sync + fmt::Debug {
    /// Name shown in port types and errors; also the key of its decoder.
    fn type_name(&self) -> &'static str;
    /// Approximate heap size in bytes.
    fn bytes(&self) -> usize;
    /// The bytes the registered decoder reads back, or `None` when the
    /// value is kept in memory only.
    fn encode(&self) -> Option<Vec<u8>>;
    /// `self` as [`Any`], to downcast to the concrete type.
    fn as_any(&self) -> &dyn Any;
}

/// Reads back what [`Extension::encode`] wrote; `None` for malformed bytes.
pub type ExtensionDecoder = fn(&[u8]) -> Option<Arc<dyn Extension>>;

/// The type of a port or value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ValueType {
    /// Linear RGB image.
    Color,
    /// Depth map, metres.
    Depth,
    /// Mask in `[0, 1]`.
    Mask,
    /// Confidence in `[0, 1]`.
    Confidence,
    /// Unit normals.
    Normals,
    /// Integer labels.
    Labels,
    /// Pinhole intrinsics.
    Intrinsics,
    /// Camera-space points.
    PointCloud,
    /// Camera-space triangle mesh.
    Mesh,
    /// LDR exposures and their times.
    ExposureStack,
    /// Directional virtual point lights.
    Vpls,
    /// A number.
    Scalar,
    /// A file that a sink node wrote.
    File,
    /// A kind defined by a node crate ([`Extension`]), by its type name.
    Extension(&'static str),
}

impl ValueType {
    /// Every built-in type (extensions are not listed).
    pub const ALL: [ValueType; 13] = [
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
        ValueType::Vpls,
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
            ValueType::Vpls => "Vpls",
            ValueType::Scalar => "Scalar",
            ValueType::File => "File",
            ValueType::Extension(name) => name,
        }
    }

    /// Whether a value of type `self` may feed a port of type `to`: the
    /// same type, or Mask and Confidence (both in `[0, 1]`; the input
    /// getters retag one as the other).
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

impl Serialize for ValueType {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

/// A value on a wire.
#[derive(Debug, Clone)]
pub enum Value {
    /// Linear RGB image.
    Color(Arc<ColorImage>),
    /// Depth map.
    Depth(Arc<DepthMap>),
    /// Mask in `[0, 1]`.
    Mask(Arc<Mask>),
    /// Confidence in `[0, 1]`.
    Confidence(Arc<Confidence>),
    /// Unit normals.
    Normals(Arc<NormalMap>),
    /// Integer labels.
    Labels(Arc<LabelImage>),
    /// Pinhole intrinsics.
    Intrinsics(Intrinsics),
    /// Camera-space points.
    PointCloud(Arc<PointCloud>),
    /// Camera-space mesh.
    Mesh(Arc<Mesh>),
    /// LDR exposures.
    ExposureStack(Arc<ExposureStack>),
    /// Directional VPLs.
    Vpls(Arc<VplSet>),
    /// A number.
    Scalar(f64),
    /// Path of a file written by a sink.
    File(std::path::PathBuf),
    /// A value of a kind defined by a node crate.
    Extension(Arc<dyn Extension>),
}

impl PartialEq for Value {
    /// Equal contents; extension values are equal only when they are the
    /// same allocation.
    fn eq(&self, o: &Value) -> bool {
        use Value as V;
        match (self, o) {
            (V::Color(a), V::Color(b)) => a == b,
            (V::Depth(a), V::Depth(b)) => a == b,
            (V::Mask(a), V::Mask(b)) => a == b,
            (V::Confidence(a), V::Confidence(b)) => a == b,
            (V::Normals(a), V::Normals(b)) => a == b,
            (V::Labels(a), V::Labels(b)) => a == b,
            (V::Intrinsics(a), V::Intrinsics(b)) => a == b,
            (V::PointCloud(a), V::PointCloud(b)) => a == b,
            (V::Mesh(a), V::Mesh(b)) => a == b,
            (V::ExposureStack(a), V::ExposureStack(b)) => a == b,
            (V::Vpls(a), V::Vpls(b)) => a == b,
            (V::Scalar(a), V::Scalar(b)) => a == b,
            (V::File(a), V::File(b)) => a == b,
            (V::Extension(a), V::Extension(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

impl Value {
    /// The value's type.
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
            Value::Vpls(_) => ValueType::Vpls,
            Value::Scalar(_) => ValueType::Scalar,
            Value::File(_) => ValueType::File,
            Value::Extension(e) => ValueType::Extension(e.type_name()),
        }
    }

    /// Approximate heap size in bytes (what the cache budgets count).
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        match self {
            Value::Color(i) => i.len() * size_of::<Rgb>(),
            Value::Depth(i) => i.len() * 4,
            Value::Mask(i) => i.len() * 4,
            Value::Confidence(i) => i.len() * 4,
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
            Value::Vpls(v) => v.len() * size_of::<Vpl>(),
            Value::Scalar(_) => 8,
            Value::File(p) => p.as_os_str().len(),
            Value::Extension(e) => e.bytes(),
        }
    }

    /// The value as a port of type `to` takes it: a Mask for a Confidence
    /// port and the other way round are retagged (a copy of the pixels);
    /// everything else is returned as it is.
    pub fn converted_to(self, to: ValueType) -> Value {
        match (self, to) {
            (Value::Mask(m), ValueType::Confidence) => {
                Value::Confidence(Arc::new(Arc::unwrap_or_clone(m).retag()))
            }
            (Value::Confidence(c), ValueType::Mask) => {
                Value::Mask(Arc::new(Arc::unwrap_or_clone(c).retag()))
            }
            (v, _) => v,
        }
    }

    /// The samples of an image value of `f32` channels (Color, Normals:
    /// 3; Depth, Mask, Confidence: 1), whatever its kind, for code that
    /// treats pixels alike (metrics, hashes, previews).
    pub fn samples(&self) -> Option<Samples<'_>> {
        let (w, h) = self.image_dims()?;
        let (channels, samples) = match self {
            Value::Color(i) => (3, i.as_slice().as_flattened()),
            Value::Normals(i) => (3, i.as_slice().as_flattened()),
            Value::Depth(i) => (1, i.as_slice()),
            Value::Mask(i) => (1, i.as_slice()),
            Value::Confidence(i) => (1, i.as_slice()),
            _ => return None,
        };
        Some(Samples {
            width: w,
            height: h,
            channels,
            samples,
        })
    }

    /// Pixel dimensions for image-like values.
    pub fn image_dims(&self) -> Option<(usize, usize)> {
        match self {
            Value::Color(i) => Some(i.dims()),
            Value::Depth(i) => Some(i.dims()),
            Value::Mask(i) => Some(i.dims()),
            Value::Confidence(i) => Some(i.dims()),
            Value::Normals(i) => Some(i.dims()),
            Value::Labels(i) => Some(i.dims()),
            Value::ExposureStack(s) => s.images.first().map(|i| i.dims()),
            _ => None,
        }
    }
}

/// A read-only view of an image value's `f32` samples ([`Value::samples`]).
#[derive(Debug, Clone, Copy)]
pub struct Samples<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Samples per pixel.
    pub channels: usize,
    /// Row-major, `channels` per pixel.
    pub samples: &'a [f32],
}

macro_rules! value_from {
    ($($variant:ident : $t:ty),*) => {$(
        impl From<$t> for Value {
            fn from(v: $t) -> Value { Value::$variant(Arc::new(v)) }
        }
        impl From<Arc<$t>> for Value {
            fn from(v: Arc<$t>) -> Value { Value::$variant(v) }
        }
    )*};
}
// Every kind of value converts into `Value` by its own type, so an output
// built as a `Mask` cannot be wrapped as a `Depth` by mistake.
value_from!(
    Color: ColorImage,
    Depth: DepthMap,
    Mask: Mask,
    Confidence: Confidence,
    Normals: NormalMap,
    Labels: LabelImage,
    PointCloud: PointCloud,
    Mesh: Mesh,
    ExposureStack: ExposureStack,
    Vpls: VplSet
);

impl From<Intrinsics> for Value {
    fn from(v: Intrinsics) -> Value {
        Value::Intrinsics(v)
    }
}
impl From<f64> for Value {
    fn from(v: f64) -> Value {
        Value::Scalar(v)
    }
}
impl From<std::path::PathBuf> for Value {
    fn from(v: std::path::PathBuf) -> Value {
        Value::File(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_vec_rejects_wrong_length() {
        let err = Image::<f32>::from_vec(3, 2, vec![0.0f32; 5]).unwrap_err();
        assert_eq!(err.expected, 6);
        assert_eq!(err.found, 5);
        assert!(Image::<f32>::from_vec(3, 2, vec![0.0f32; 6]).is_ok());
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
