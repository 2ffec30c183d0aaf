//! Binary encoding of node outputs for the on-disk cache.
//!
//! Little-endian, versioned, with lengths checked against the remaining
//! bytes before anything is allocated, so a truncated or corrupt cache file
//! is a miss, never a panic or a huge allocation. Every entry ends with the
//! blake3 hash of all its bytes before it: a flipped bit anywhere (a pixel,
//! a float, a name) is a miss too, never a result served as another one.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use crate::bytes::{ByteReader, ByteWriter};
use crate::node::Outputs;
use crate::value::{
    ExposureStack, ExtensionDecoder, Image, Intrinsics, Mesh, PointCloud, Value, Vpl,
};

const MAGIC: &[u8; 8] = b"DGCACHE5";

/// Bytes of the checksum that ends every entry (blake3).
const CHECKSUM_LEN: usize = 32;

/// The codec's version as it appears in entry file names
/// ([`DiskCache`](crate::cache::DiskCache) keeps `<key>.dg5.bin`): workers
/// of another depthgraph version sharing a store never read, overwrite or
/// evict each other's entries.
pub const VERSION_TAG: &str = "dg5";

/// Encodes outputs (values, the pass-through reason and the report).
pub fn encode(out: &Outputs) -> Vec<u8> {
    let mut w = ByteWriter(Vec::with_capacity(out.bytes() + 64));
    w.0.extend_from_slice(MAGIC);
    w.str(out.passthrough.as_deref().unwrap_or(""));
    w.u8(out.passthrough.is_some() as u8);
    w.str(out.report.as_deref().unwrap_or(""));
    w.u8(out.report.is_some() as u8);
    let origin = out.origin.clone().unwrap_or_default();
    w.str(&origin.backend);
    w.str(origin.adapter.as_deref().unwrap_or(""));
    w.u8(origin.adapter.is_some() as u8);
    w.str(origin.note.as_deref().unwrap_or(""));
    w.u8(origin.note.is_some() as u8);
    w.usize(out.values.len());
    for (k, v) in &out.values {
        w.str(k);
        put_value(&mut w, v);
    }
    let sum = blake3::hash(&w.0);
    w.0.extend_from_slice(sum.as_bytes());
    w.0
}

/// Decoders of extension values by type name.
pub type Decoders = BTreeMap<&'static str, ExtensionDecoder>;

/// Decodes what [`encode`] wrote; `None` for anything malformed or whose
/// bytes fail the entry's checksum, and for an extension value without a
/// decoder in `decoders` or whose bytes fail their own checksum.
pub fn decode(bytes: &[u8], decoders: &Decoders) -> Option<Outputs> {
    // the whole entry's checksum first: nothing damaged is decoded
    let body_len = bytes.len().checked_sub(CHECKSUM_LEN)?;
    let (bytes, sum) = bytes.split_at(body_len);
    if blake3::hash(bytes).as_bytes() != sum {
        return None;
    }
    let mut r = Reader {
        r: ByteReader::new(bytes),
        decoders,
    };
    if r.take(8)? != MAGIC {
        return None;
    }
    // Only the one encoding `encode` writes is accepted (a flag is 0 or 1,
    // an absent string is empty, keys strictly increase): an entry decodes
    // to outputs that encode back to the same bytes, so a damaged entry
    // cannot pass for another one.
    let reason = r.string()?;
    let has_reason = r.r.bool()?;
    let report = r.string()?;
    let has_report = r.r.bool()?;
    let backend = r.string()?;
    let adapter = r.string()?;
    let has_adapter = r.r.bool()?;
    let note = r.string()?;
    let has_note = r.r.bool()?;
    if (!has_reason && !reason.is_empty())
        || (!has_report && !report.is_empty())
        || (!has_adapter && !adapter.is_empty())
        || (!has_note && !note.is_empty())
        || (backend.is_empty() && (has_adapter || has_note))
    {
        return None;
    }
    let n = r.u64()? as usize;
    let mut values = BTreeMap::new();
    for _ in 0..n {
        let k = r.string()?;
        if values
            .last_key_value()
            .is_some_and(|(last, _): (&String, _)| *last >= k)
        {
            return None;
        }
        let v = r.value()?;
        values.insert(k, v);
    }
    if !r.r.is_done() {
        return None;
    }
    Some(Outputs {
        values,
        passthrough: has_reason.then_some(reason),
        report: has_report.then_some(report),
        origin: (!backend.is_empty()).then(|| crate::node::Origin {
            backend,
            adapter: has_adapter.then_some(adapter),
            note: has_note.then_some(note),
        }),
        transfers: Default::default(),
    })
}

fn flat3(v: &[[f32; 3]]) -> &[f32] {
    v.as_flattened()
}
fn put_image3<K>(w: &mut ByteWriter, img: &Image<[f32; 3], K>) {
    w.u64(img.width() as u64);
    w.u64(img.height() as u64);
    w.f32s(flat3(img.as_slice()));
}
fn put_image1<K>(w: &mut ByteWriter, img: &Image<f32, K>) {
    w.u64(img.width() as u64);
    w.u64(img.height() as u64);
    w.f32s(img.as_slice());
}

fn put_value(w: &mut ByteWriter, v: &Value) {
    match v {
        Value::Color(i) => {
            w.u8(0);
            put_image3(w, i)
        }
        Value::Depth(i) => {
            w.u8(1);
            put_image1(w, i)
        }
        Value::Mask(i) => {
            w.u8(2);
            put_image1(w, i)
        }
        Value::Confidence(i) => {
            w.u8(3);
            put_image1(w, i)
        }
        Value::Normals(i) => {
            w.u8(4);
            put_image3(w, i)
        }
        Value::Labels(i) => {
            w.u8(5);
            w.u64(i.width() as u64);
            w.u64(i.height() as u64);
            w.u32s(i.as_slice());
        }
        Value::Intrinsics(k) => {
            w.u8(6);
            for x in [k.fx, k.fy, k.cx, k.cy] {
                w.f64(x);
            }
            w.u64(k.width as u64);
            w.u64(k.height as u64);
        }
        Value::PointCloud(p) => {
            w.u8(7);
            w.f32s(flat3(&p.positions));
            w.f32s(flat3(&p.colors));
            w.f32s(flat3(&p.normals));
        }
        Value::Mesh(m) => {
            w.u8(8);
            w.f32s(flat3(&m.positions));
            w.f32s(flat3(&m.colors));
            w.f32s(flat3(&m.normals));
            w.u32s(m.triangles.as_flattened());
        }
        Value::ExposureStack(s) => {
            w.u8(9);
            w.u64(s.images.len() as u64);
            for (img, t) in s.images.iter().zip(&s.times_s) {
                w.f64(*t);
                put_image3(w, img);
            }
        }
        Value::Scalar(x) => {
            w.u8(10);
            w.f64(*x);
        }
        Value::File(p) => {
            w.u8(11);
            w.str(&p.to_string_lossy());
        }
        Value::Vpls(v) => {
            w.u8(12);
            w.u64(v.len() as u64);
            for l in v.iter() {
                for x in l.direction.iter().chain(&l.power) {
                    w.0.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        Value::Extension(e) => {
            // `encode` checked `persistable` first; an extension without an
            // encoding never reaches here
            let payload = e.encode().unwrap_or_default();
            w.u8(13);
            w.str(e.type_name());
            w.u64(payload.len() as u64);
            w.0.extend_from_slice(blake3::hash(&payload).as_bytes());
            w.0.extend_from_slice(&payload);
        }
    }
}

/// Whether every value of `out` can be written to disk (extensions may be
/// memory-only).
pub fn persistable(out: &Outputs) -> bool {
    out.values.values().all(|v| match v {
        Value::Extension(e) => e.encode().is_some(),
        _ => true,
    })
}

/// The shared byte reader, with the decoders of extension values.
struct Reader<'a> {
    r: ByteReader<'a>,
    decoders: &'a Decoders,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        self.r.bytes(n)
    }
    fn u8(&mut self) -> Option<u8> {
        self.r.u8()
    }
    fn u64(&mut self) -> Option<u64> {
        self.r.u64()
    }
    fn f64(&mut self) -> Option<f64> {
        self.r.f64()
    }
    fn usize(&mut self) -> Option<usize> {
        self.r.usize()
    }
    fn string(&mut self) -> Option<String> {
        self.r.string()
    }
    fn f32s(&mut self) -> Option<Vec<f32>> {
        self.r.f32s()
    }
    fn u32s(&mut self) -> Option<Vec<u32>> {
        self.r.u32s()
    }
    fn triples(&mut self) -> Option<Vec<[f32; 3]>> {
        let f = self.f32s()?;
        if f.len() % 3 != 0 {
            return None;
        }
        Some(f.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }
    /// An image's size: its pixel count without overflow, and no side 0
    /// unless both are (a 0 x 2^63 image holds no pixel, and its rows
    /// would still be walked).
    fn dims(&mut self) -> Option<(usize, usize)> {
        let (w, h) = (self.usize()?, self.usize()?);
        (w.checked_mul(h).is_some() && (w == 0) == (h == 0)).then_some((w, h))
    }
    fn image3<K>(&mut self) -> Option<Image<[f32; 3], K>> {
        let (w, h) = self.dims()?;
        Image::from_vec(w, h, self.triples()?).ok()
    }
    fn image1<K>(&mut self) -> Option<Image<f32, K>> {
        let (w, h) = self.dims()?;
        Image::from_vec(w, h, self.f32s()?).ok()
    }
    fn value(&mut self) -> Option<Value> {
        Some(match self.u8()? {
            0 => Value::Color(Arc::new(self.image3()?)),
            1 => Value::Depth(Arc::new(self.image1()?)),
            2 => Value::Mask(Arc::new(self.image1()?)),
            3 => Value::Confidence(Arc::new(self.image1()?)),
            4 => Value::Normals(Arc::new(self.image3()?)),
            5 => {
                let (w, h) = self.dims()?;
                Value::Labels(Arc::new(Image::from_vec(w, h, self.u32s()?).ok()?))
            }
            6 => {
                let (fx, fy, cx, cy) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
                let (width, height) = (self.usize()?, self.usize()?);
                Value::Intrinsics(Intrinsics {
                    fx,
                    fy,
                    cx,
                    cy,
                    width,
                    height,
                })
            }
            7 => {
                let positions = self.triples()?;
                let colors = self.triples()?;
                let normals = self.triples()?;
                // colours and normals: none, or one per point
                let per_point = |n: usize| n == 0 || n == positions.len();
                if !(per_point(colors.len()) && per_point(normals.len())) {
                    return None;
                }
                Value::PointCloud(Arc::new(PointCloud {
                    positions,
                    colors,
                    normals,
                }))
            }
            8 => {
                let positions = self.triples()?;
                let colors = self.triples()?;
                let normals = self.triples()?;
                let t = self.u32s()?;
                // whole triangles of vertices that exist; colours and
                // normals none or one per vertex (a damaged or forged entry
                // of a shared store would index out of bounds downstream)
                let per_vertex = |n: usize| n == 0 || n == positions.len();
                if t.len() % 3 != 0
                    || !(per_vertex(colors.len()) && per_vertex(normals.len()))
                    || t.iter().any(|&i| i as usize >= positions.len())
                {
                    return None;
                }
                Value::Mesh(Arc::new(Mesh {
                    positions,
                    colors,
                    normals,
                    triangles: t.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
                }))
            }
            9 => {
                let n = self.usize()?;
                let mut s = ExposureStack::default();
                for _ in 0..n {
                    s.times_s.push(self.f64()?);
                    s.images.push(self.image3()?);
                }
                Value::ExposureStack(Arc::new(s))
            }
            10 => Value::Scalar(self.f64()?),
            11 => Value::File(PathBuf::from(self.string()?)),
            12 => {
                let n = self.usize()?;
                let f = self.take(n.checked_mul(24)?)?;
                let x = |c: &[u8], i: usize| {
                    f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
                };
                Value::Vpls(Arc::new(
                    f.chunks_exact(24)
                        .map(|c| Vpl {
                            direction: [x(c, 0), x(c, 1), x(c, 2)],
                            power: [x(c, 3), x(c, 4), x(c, 5)],
                        })
                        .collect(),
                ))
            }
            13 => {
                let name = self.string()?;
                let n = self.usize()?;
                let sum = self.take(32)?;
                let payload = self.take(n)?;
                if blake3::hash(payload).as_bytes() != sum {
                    return None;
                }
                let decode = self.decoders.get(name.as_str())?;
                let v = decode(payload)?;
                if v.type_name() != name {
                    return None;
                }
                Value::Extension(v)
            }
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_every_kind() {
        let img3 = Image::from_fn(3, 2, |x, y| [x as f32, y as f32, 0.5]);
        let img1 = Image::from_fn(3, 2, |x, y| (x * y) as f32 - 0.25);
        let out = Outputs::new()
            .with("c", Value::Color(Arc::new(img3.clone())))
            .with("d", Value::Depth(Arc::new(img1.clone())))
            .with("m", Value::Mask(Arc::new(img1.clone().retag())))
            .with("n", Value::Normals(Arc::new(img3.clone().retag())))
            .with(
                "l",
                Value::Labels(Arc::new(Image::from_fn(2, 2, |x, _| x as u32))),
            )
            .with(
                "k",
                Value::Intrinsics(Intrinsics {
                    fx: 1.0,
                    fy: 2.0,
                    cx: 3.0,
                    cy: 4.0,
                    width: 5,
                    height: 6,
                }),
            )
            .with(
                "mesh",
                Value::Mesh(Arc::new(Mesh {
                    positions: vec![[0.0, 1.0, 2.0]; 3],
                    colors: vec![],
                    normals: vec![],
                    triangles: vec![[0, 1, 2]],
                })),
            )
            .with(
                "e",
                Value::ExposureStack(Arc::new(ExposureStack {
                    images: vec![img3.clone(), img3],
                    times_s: vec![0.5, 2.0],
                })),
            )
            .with("s", Value::Scalar(-1.5))
            .with("f", Value::File("a/b.png".into()))
            .passthrough("no holes to fill");
        let bytes = encode(&out);
        let back = decode(&bytes, &Decoders::new()).unwrap();
        assert_eq!(back.values, out.values);
        assert_eq!(back.passthrough.as_deref(), Some("no holes to fill"));
    }

    /// Entries whose framing is sound but whose contents could not come
    /// from a node (a damaged or forged entry of a shared store) decode to
    /// nothing: a triangle of a vertex that does not exist, colours for
    /// some points only, an image of no pixels and 2^40 rows.
    #[test]
    fn inconsistent_contents_are_none() {
        let mesh = |triangles: Vec<[u32; 3]>, colors: usize| {
            Outputs::new().with(
                "m",
                Value::Mesh(Arc::new(Mesh {
                    positions: vec![[0.0, 1.0, 2.0]; 3],
                    colors: vec![[0.5; 3]; colors],
                    normals: vec![],
                    triangles,
                })),
            )
        };
        assert!(decode(&encode(&mesh(vec![[0, 1, 2]], 3)), &Decoders::new()).is_some());
        assert!(decode(&encode(&mesh(vec![[0, 1, 3]], 0)), &Decoders::new()).is_none());
        assert!(decode(&encode(&mesh(vec![[0, 1, 2]], 2)), &Decoders::new()).is_none());
        let cloud = Outputs::new().with(
            "p",
            Value::PointCloud(Arc::new(PointCloud {
                positions: vec![[0.0; 3]; 3],
                colors: vec![],
                normals: vec![[0.0, 0.0, 1.0]; 1],
            })),
        );
        assert!(decode(&encode(&cloud), &Decoders::new()).is_none());
        let tall: crate::value::DepthMap = Image::from_vec(0, 1 << 40, vec![]).unwrap();
        let out = Outputs::new().with("d", Value::Depth(Arc::new(tall)));
        assert!(decode(&encode(&out), &Decoders::new()).is_none());
        let empty: crate::value::DepthMap = Image::from_vec(0, 0, vec![]).unwrap();
        let out = Outputs::new().with("d", Value::Depth(Arc::new(empty)));
        assert!(decode(&encode(&out), &Decoders::new()).is_some());
    }

    #[test]
    fn corrupt_input_is_none() {
        let out = Outputs::new().with("d", Value::Scalar(1.0));
        let bytes = encode(&out);
        for cut in 0..bytes.len() {
            assert!(decode(&bytes[..cut], &Decoders::new()).is_none());
        }
        let mut huge = bytes.clone();
        // claim an absurd string length right after the magic
        huge[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode(&huge, &Decoders::new()).is_none());
    }

    #[test]
    fn only_the_canonical_encoding_decodes() {
        let out = Outputs::new()
            .with("a", Value::Scalar(1.0))
            .with("b", Value::Scalar(-0.0));
        let good = encode(&out);
        let back = decode(&good, &Decoders::new()).unwrap();
        assert_eq!(encode(&back), good);
        // the keys swapped: "b" before "a" (each entry: key length, key,
        // type tag 10, the f64)
        let mut swapped = Vec::new();
        let n_at = good.len() - 2 * (8 + 1 + 1 + 8);
        swapped.extend_from_slice(&good[..n_at]);
        let entry = |k: &[u8], bits: u64| {
            let mut e = (1u64).to_le_bytes().to_vec();
            e.extend_from_slice(k);
            e.push(10);
            e.extend_from_slice(&bits.to_le_bytes());
            e
        };
        swapped.extend(entry(b"b", (-0.0f64).to_bits()));
        swapped.extend(entry(b"a", 1.0f64.to_bits()));
        assert_eq!(swapped.len(), good.len());
        assert!(decode(&swapped, &Decoders::new()).is_none());
        // a flag other than 0 or 1
        let mut flag = good.clone();
        // magic (8), empty reason (8), its flag
        flag[16] = 2;
        assert!(decode(&flag, &Decoders::new()).is_none());
    }
}
