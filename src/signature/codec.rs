//! The binary encoding of a [`Signature`] (`SSG1`, little endian, exact `f64`): what the index
//! stores and the eval cache keeps. A second version ([`Signature::alternate`]) follows the
//! channels as the byte `A` and its own length-prefixed encoding; a signature without one ends
//! after its channels, as every signature stored before there were second versions does.

use super::compute::{ChannelData, ChannelValues, Signature};
use super::distributions::QuantileSketch;
use crate::bytes::{put_f64, put_f64s, put_u64, ByteReader};
use crate::{Error, Result};

const MAGIC: &[u8; 4] = b"SSG1";

impl Signature {
    /// Compact binary encoding (little endian, exact f64), see [`Signature::from_bytes`].
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = Vec::with_capacity(64 + self.channels.len() * 4200);
        w.extend_from_slice(MAGIC);
        put_str(&mut w, &self.spec_key);
        put_u64(&mut w, self.vertices as u64);
        put_f64(&mut w, self.area);
        put_u64(&mut w, self.quadrature_points as u64);
        put_u64(&mut w, self.channels.len() as u64);
        for c in &self.channels {
            put_str(&mut w, &c.name);
            match &c.values {
                ChannelValues::Distribution(s) => {
                    w.push(0);
                    put_f64(&mut w, s.mass);
                    put_f64_array(&mut w, &s.quantiles);
                }
                ChannelValues::Vector(v) => {
                    w.push(1);
                    put_f64_array(&mut w, v);
                }
            }
        }
        if let Some(a) = &self.alternate {
            let inner = a.to_bytes();
            w.push(b'A');
            put_u64(&mut w, inner.len() as u64);
            w.extend_from_slice(&inner);
        }
        w
    }

    /// Decodes [`Signature::to_bytes`]; malformed input is an [`Error::Corrupt`] (these bytes are
    /// only ever read back from a store or cache).
    pub fn from_bytes(b: &[u8]) -> Result<Self> {
        let mut r = Reader(ByteReader::new(b));
        if r.take(4)? != MAGIC {
            return Err(Error::corrupt("signature", None, "bad magic"));
        }
        let spec_key = r.string()?;
        let vertices = r.u64()? as usize;
        let area = r.f64()?;
        let quadrature_points = r.u64()? as usize;
        let nch = r.u64()? as usize;
        if nch > b.len() {
            return Err(Error::corrupt("signature", None, "bad channel count"));
        }
        let mut channels = Vec::with_capacity(nch);
        for _ in 0..nch {
            let name = r.string()?;
            let tag = r.take(1)?[0];
            let values = match tag {
                0 => {
                    let mass = r.f64()?;
                    let quantiles = r.f64s()?;
                    ChannelValues::Distribution(QuantileSketch { mass, quantiles })
                }
                1 => ChannelValues::Vector(r.f64s()?),
                _ => return Err(Error::corrupt("signature", None, "bad channel tag")),
            };
            channels.push(ChannelData { name, values });
        }
        let mut alternate = None;
        if !r.0.at_end() {
            if r.take(1)? != b"A" {
                return Err(Error::corrupt("signature", None, "trailing bytes"));
            }
            let n = r.u64()? as usize;
            let inner = Signature::from_bytes(r.take(n)?)?;
            if inner.alternate.is_some() {
                return Err(Error::corrupt("signature", None, "nested second version"));
            }
            alternate = Some(Box::new(inner));
            if !r.0.at_end() {
                return Err(Error::corrupt("signature", None, "trailing bytes"));
            }
        }
        Ok(Signature {
            spec_key,
            channels,
            vertices,
            area,
            quadrature_points,
            alternate,
        })
    }

    /// The channel called `name`, if any.
    pub fn channel(&self, name: &str) -> Option<&ChannelData> {
        self.channels.iter().find(|c| c.name == name)
    }
}

fn put_str(w: &mut Vec<u8>, s: &str) {
    put_u64(w, s.len() as u64);
    w.extend_from_slice(s.as_bytes());
}

/// A length-prefixed `f64` array.
fn put_f64_array(w: &mut Vec<u8>, v: &[f64]) {
    put_u64(w, v.len() as u64);
    put_f64s(w, v);
}

/// [`ByteReader`] with this format's errors.
struct Reader<'a>(ByteReader<'a>);

fn truncated() -> Error {
    Error::corrupt("signature", None, "truncated")
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        self.0.take(n).ok_or_else(truncated)
    }
    fn u64(&mut self) -> Result<u64> {
        self.0.u64().ok_or_else(truncated)
    }
    fn f64(&mut self) -> Result<f64> {
        self.0.f64().ok_or_else(truncated)
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u64()? as usize;
        let s = self.take(n)?;
        String::from_utf8(s.to_vec()).map_err(|_| Error::corrupt("signature", None, "bad utf-8"))
    }
    /// A length-prefixed `f64` array.
    fn f64s(&mut self) -> Result<Vec<f64>> {
        let n = self.u64()? as usize;
        self.0.f64s(n).ok_or_else(truncated)
    }
}
