//! A little-endian byte writer and a reader that checks every length
//! against the bytes left before allocating, for values the disk cache
//! keeps (a truncated or corrupt file reads as `None`, never a panic or a
//! huge allocation).

use glam::DVec3;

/// Appends values to a byte buffer (little-endian, lengths as `u64`): the
/// encoding of the disk cache ([`codec`](crate::codec)) and of extension
/// values.
#[derive(Debug, Default)]
pub struct ByteWriter(pub Vec<u8>);

impl ByteWriter {
    /// One byte.
    pub fn u8(&mut self, x: u8) {
        self.0.push(x);
    }
    /// A length, then the UTF-8 bytes.
    pub fn str(&mut self, s: &str) {
        self.usize(s.len());
        self.0.extend_from_slice(s.as_bytes());
    }
    /// A length, then the `u32`s.
    pub fn u32s(&mut self, xs: &[u32]) {
        self.usize(xs.len());
        for x in xs {
            self.0.extend_from_slice(&x.to_le_bytes());
        }
    }
    /// A `u64`.
    pub fn u64(&mut self, x: u64) {
        self.0.extend_from_slice(&x.to_le_bytes());
    }
    /// A `usize` as `u64`.
    pub fn usize(&mut self, x: usize) {
        self.u64(x as u64);
    }
    /// An `f64` by its bits.
    pub fn f64(&mut self, x: f64) {
        self.0.extend_from_slice(&x.to_le_bytes());
    }
    /// A `bool` as one byte.
    pub fn bool(&mut self, x: bool) {
        self.0.push(u8::from(x));
    }
    /// A length, then the `f32`s.
    pub fn f32s(&mut self, xs: &[f32]) {
        self.usize(xs.len());
        self.0.reserve(xs.len() * 4);
        for x in xs {
            self.0.extend_from_slice(&x.to_le_bytes());
        }
    }
    /// A vector: its three components.
    pub fn vec3(&mut self, v: DVec3) {
        for x in v.to_array() {
            self.f64(x);
        }
    }
    /// A length, then `f(self, item)` for each item.
    pub fn seq<T>(&mut self, items: &[T], mut f: impl FnMut(&mut Self, &T)) {
        self.usize(items.len());
        for x in items {
            f(self, x);
        }
    }
    /// `false`, or `true` and `f(self, value)`.
    pub fn opt<T>(&mut self, v: &Option<T>, f: impl FnOnce(&mut Self, &T)) {
        self.bool(v.is_some());
        if let Some(x) = v {
            f(self, x);
        }
    }
}

/// Reads what a [`ByteWriter`] wrote.
#[derive(Debug)]
pub struct ByteReader<'a> {
    bytes: &'a [u8],
}

impl<'a> ByteReader<'a> {
    /// A reader over `bytes`.
    pub fn new(bytes: &'a [u8]) -> Self {
        Self { bytes }
    }
    /// Whether every byte was read.
    pub fn is_done(&self) -> bool {
        self.bytes.is_empty()
    }
    /// The next `n` bytes as they are.
    pub fn bytes(&mut self, n: usize) -> Option<&'a [u8]> {
        if n > self.bytes.len() {
            return None;
        }
        let (head, rest) = self.bytes.split_at(n);
        self.bytes = rest;
        Some(head)
    }
    /// One byte.
    pub fn u8(&mut self) -> Option<u8> {
        self.take::<1>().map(|[b]| b)
    }
    /// A length, then that many UTF-8 bytes.
    pub fn string(&mut self) -> Option<String> {
        let n = self.usize()?;
        String::from_utf8(self.bytes(n)?.to_vec()).ok()
    }
    /// A length, then that many `u32`s.
    pub fn u32s(&mut self) -> Option<Vec<u32>> {
        let n = self.usize()?;
        let b = self.bytes(n.checked_mul(4)?)?;
        Some(
            b.chunks_exact(4)
                .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        )
    }
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let (head, rest) = self.bytes.split_first_chunk::<N>()?;
        self.bytes = rest;
        Some(*head)
    }
    /// A `u64`.
    pub fn u64(&mut self) -> Option<u64> {
        self.take::<8>().map(u64::from_le_bytes)
    }
    /// A `usize` (fails when it does not fit).
    pub fn usize(&mut self) -> Option<usize> {
        usize::try_from(self.u64()?).ok()
    }
    /// An `f64`.
    pub fn f64(&mut self) -> Option<f64> {
        self.take::<8>().map(f64::from_le_bytes)
    }
    /// A `bool` (only 0 and 1 are valid).
    pub fn bool(&mut self) -> Option<bool> {
        match self.u8()? {
            0 => Some(false),
            1 => Some(true),
            _ => None,
        }
    }
    /// A length, then that many `f32`s (as [`ByteWriter::f32s`] writes).
    pub fn f32s(&mut self) -> Option<Vec<f32>> {
        let n = self.usize()?;
        let head = self.bytes(n.checked_mul(4)?)?;
        Some(
            head.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        )
    }
    /// A vector.
    pub fn vec3(&mut self) -> Option<DVec3> {
        Some(DVec3::new(self.f64()?, self.f64()?, self.f64()?))
    }
    /// A sequence whose items take at least `min_item_bytes` each: the
    /// length is checked against the bytes left before anything is
    /// allocated.
    pub fn seq<T>(
        &mut self,
        min_item_bytes: usize,
        mut f: impl FnMut(&mut Self) -> Option<T>,
    ) -> Option<Vec<T>> {
        let n = self.usize()?;
        if n.checked_mul(min_item_bytes.max(1))? > self.bytes.len() {
            return None;
        }
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(f(self)?);
        }
        Some(out)
    }
    /// What [`ByteWriter::opt`] wrote.
    pub fn opt<T>(&mut self, f: impl FnOnce(&mut Self) -> Option<T>) -> Option<Option<T>> {
        if self.bool()? {
            f(self).map(Some)
        } else {
            Some(None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_refusals() {
        let mut w = ByteWriter::default();
        w.u64(7);
        w.f64(-0.5);
        w.bool(true);
        w.vec3(DVec3::new(1.0, 2.0, 3.0));
        w.seq(&[1.5f64, 2.5], |w, x| w.f64(*x));
        w.opt(&Some(3usize), |w, x| w.usize(*x));
        let b = w.0;
        let mut r = ByteReader::new(&b);
        assert_eq!(r.u64(), Some(7));
        assert_eq!(r.f64(), Some(-0.5));
        assert_eq!(r.bool(), Some(true));
        assert_eq!(r.vec3(), Some(DVec3::new(1.0, 2.0, 3.0)));
        assert_eq!(r.seq(8, |r| r.f64()), Some(vec![1.5, 2.5]));
        assert_eq!(r.opt(|r| r.usize()), Some(Some(3)));
        assert!(r.is_done());
        // a huge length is refused before allocating; a bad bool is refused
        let mut w = ByteWriter::default();
        w.u64(u64::MAX / 2);
        assert!(ByteReader::new(&w.0).seq(8, |r| r.f64()).is_none());
        assert!(ByteReader::new(&[2]).bool().is_none());
        assert!(ByteReader::new(&[1, 2, 3]).u64().is_none());
    }
}
