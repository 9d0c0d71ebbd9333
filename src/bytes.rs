//! Little-endian binary encoding shared by the stored formats: signatures
//! ([`crate::signature::Signature::to_bytes`]), re-ranking payloads
//! ([`crate::rerank::GwPayload::to_bytes`]), the evaluation cache, and the shards' messages
//! ([`crate::queue::shard`]). Each format keeps its own
//! layout and error messages; this module only reads and writes the primitive values, checking
//! every length against the input (no allocation sized by an untrusted count before the bytes
//! are known to be there).
//!
//! Why by hand: the formats are a few fixed fields and long f64/f32 arrays; a serialisation
//! crate would add a dependency and a layout of its own for what is a dozen lines.

/// Appends `v` (2 bytes, little endian).
pub(crate) fn put_u16(w: &mut Vec<u8>, v: u16) {
    w.extend_from_slice(&v.to_le_bytes());
}

/// Appends `v` (4 bytes, little endian).
pub(crate) fn put_u32(w: &mut Vec<u8>, v: u32) {
    w.extend_from_slice(&v.to_le_bytes());
}

/// Appends `v` (8 bytes, little endian).
pub(crate) fn put_u64(w: &mut Vec<u8>, v: u64) {
    w.extend_from_slice(&v.to_le_bytes());
}

/// Appends `v` (8 bytes, little endian, exact bits).
pub(crate) fn put_f64(w: &mut Vec<u8>, v: f64) {
    w.extend_from_slice(&v.to_le_bytes());
}

/// Appends the values of `v` (4 bytes each, little endian).
pub(crate) fn put_f32s(w: &mut Vec<u8>, v: &[f32]) {
    for x in v {
        w.extend_from_slice(&x.to_le_bytes());
    }
}

/// Appends the values of `v` (8 bytes each, little endian).
pub(crate) fn put_f64s(w: &mut Vec<u8>, v: &[f64]) {
    for x in v {
        put_f64(w, *x);
    }
}

/// A cursor over encoded bytes; every read is `None` when the input is too short.
pub(crate) struct ByteReader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> ByteReader<'a> {
    /// A reader at the start of `b`.
    pub(crate) fn new(b: &'a [u8]) -> Self {
        Self { b, pos: 0 }
    }

    /// True when every byte was read.
    pub(crate) fn at_end(&self) -> bool {
        self.pos == self.b.len()
    }

    /// The next `n` bytes.
    pub(crate) fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let s = self.b.get(self.pos..end)?;
        self.pos = end;
        Some(s)
    }

    /// The number of bytes not read yet.
    pub(crate) fn remaining(&self) -> usize {
        self.b.len() - self.pos
    }

    /// One byte.
    pub(crate) fn u8(&mut self) -> Option<u8> {
        Some(self.take(1)?[0])
    }

    /// A little-endian `u16`.
    pub(crate) fn u16(&mut self) -> Option<u16> {
        Some(u16::from_le_bytes(self.take(2)?.try_into().ok()?))
    }

    /// A little-endian `u32`.
    pub(crate) fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }

    /// A little-endian `u64`.
    pub(crate) fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }

    /// A little-endian `f64`.
    pub(crate) fn f64(&mut self) -> Option<f64> {
        Some(f64::from_bits(self.u64()?))
    }

    /// `n` little-endian `f64`s.
    pub(crate) fn f64s(&mut self, n: usize) -> Option<Vec<f64>> {
        let raw = self.take(n.checked_mul(8)?)?;
        Some(
            raw.chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect(),
        )
    }

    /// `n` little-endian `f32`s.
    pub(crate) fn f32s(&mut self, n: usize) -> Option<Vec<f32>> {
        let raw = self.take(n.checked_mul(4)?)?;
        Some(
            raw.chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect(),
        )
    }

    /// `n` little-endian `u32`s.
    pub(crate) fn u32s(&mut self, n: usize) -> Option<Vec<u32>> {
        let raw = self.take(n.checked_mul(4)?)?;
        Some(
            raw.chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_short_input() {
        let mut w = Vec::new();
        put_u64(&mut w, 7);
        put_f64(&mut w, -0.5);
        put_f64s(&mut w, &[1.0, f64::MIN_POSITIVE]);
        put_f32s(&mut w, &[2.5]);
        let mut r = ByteReader::new(&w);
        assert_eq!(r.u64(), Some(7));
        assert_eq!(r.f64(), Some(-0.5));
        assert_eq!(r.f64s(2), Some(vec![1.0, f64::MIN_POSITIVE]));
        assert!(!r.at_end());
        assert_eq!(r.f32s(1), Some(vec![2.5]));
        assert!(r.at_end());
        assert_eq!(r.u64(), None);
        let mut w = Vec::new();
        put_u16(&mut w, 0xBEEF);
        put_u32(&mut w, 0xDEAD_BEEF);
        w.push(9);
        let mut r = ByteReader::new(&w);
        assert_eq!(r.remaining(), 7);
        assert_eq!(r.u16(), Some(0xBEEF));
        assert_eq!(r.u32(), Some(0xDEAD_BEEF));
        assert_eq!(r.remaining(), 1);
        assert_eq!(r.u16(), None, "short input");
        assert_eq!(r.u8(), Some(9));
        assert_eq!((r.u8(), r.remaining()), (None, 0));
        let mut w = Vec::new();
        put_u64(&mut w, 7);
        put_f64(&mut w, -0.5);
        let mut r = ByteReader::new(&w[..5]);
        assert_eq!(r.f64s(usize::MAX), None, "overflowing count");
        assert_eq!(r.u64(), None, "short input");
        assert_eq!(r.take(5).map(|s| s.len()), Some(5));
    }
}
