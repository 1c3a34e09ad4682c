//! msgpack-numpy as `openpi_client.msgpack_numpy` writes and reads it.
//!
//! - A numpy array is a map of four entries whose keys are msgpack **bin**: `__ndarray__` →
//!   `true`, `data` → bin (the array's bytes in C order), `dtype` → str (numpy's typestr, e.g.
//!   `<f4`, `|u1`), `shape` → array of unsigned integers. A numpy scalar is `__npgeneric__` →
//!   `true`, `data` → the native value, `dtype` → str.
//! - Every other map is a plain map; top-level keys are msgpack str.
//!
//! Decoding borrows from the message (an image is never copied) and is bounded: at most
//! [`Limits::max_items`] values and [`Limits::max_depth`] levels, every length checked against
//! the bytes left, an array's bytes against its dtype and shape. Marker keys are accepted as
//! bin or str (SGLang accepts both); they are written as bin.

use std::fmt;

/// Decoding limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Values in the whole message (map entries count twice, an array's bytes once).
    pub max_items: usize,
    /// Nesting depth.
    pub max_depth: usize,
    /// Dimensions of an ndarray.
    pub max_ndim: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_items: 65_536,
            max_depth: 16,
            max_ndim: 8,
        }
    }
}

/// A message that is not msgpack-numpy, or exceeds the limits.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("the message ends inside a value (at byte {0})")]
    Truncated(usize),
    #[error("{0} bytes follow the message's value")]
    Trailing(usize),
    #[error("byte 0x{0:02x} at {1} is not a msgpack type chunkrt reads (ext types are not)")]
    Unsupported(u8, usize),
    #[error("more than {0} values in the message")]
    TooManyItems(usize),
    #[error("nested deeper than {0} levels")]
    TooDeep(usize),
    #[error("a str is not UTF-8 (at byte {0})")]
    Utf8(usize),
    #[error("ndarray: {0}")]
    NdArray(String),
}

/// Element type of an ndarray (numpy's typestr kinds chunkrt reads).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F16,
    F32,
    F64,
    Bool,
}

impl DType {
    /// From numpy's typestr (`<f4`, `|u1`, `=i8`, ...); big-endian arrays are refused.
    pub fn parse(s: &str) -> Option<Self> {
        let (order, rest) = match s.as_bytes().first()? {
            b'<' | b'|' | b'=' => (true, &s[1..]),
            b'>' => (false, &s[1..]),
            _ => (true, s),
        };
        let t = match rest {
            "u1" => DType::U8,
            "i1" => DType::I8,
            "u2" => DType::U16,
            "i2" => DType::I16,
            "u4" => DType::U32,
            "i4" => DType::I32,
            "u8" => DType::U64,
            "i8" => DType::I64,
            "f2" => DType::F16,
            "f4" => DType::F32,
            "f8" => DType::F64,
            "b1" => DType::Bool,
            _ => return None,
        };
        // a big-endian multi-byte array would need swapping; numpy writes little-endian here
        (order || t.size() == 1).then_some(t)
    }

    /// numpy's typestr on a little-endian machine.
    pub fn typestr(self) -> &'static str {
        match self {
            DType::U8 => "|u1",
            DType::I8 => "|i1",
            DType::U16 => "<u2",
            DType::I16 => "<i2",
            DType::U32 => "<u4",
            DType::I32 => "<i4",
            DType::U64 => "<u8",
            DType::I64 => "<i8",
            DType::F16 => "<f2",
            DType::F32 => "<f4",
            DType::F64 => "<f8",
            DType::Bool => "|b1",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::U8 | DType::I8 | DType::Bool => 1,
            DType::U16 | DType::I16 | DType::F16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::U64 | DType::I64 | DType::F64 => 8,
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.typestr())
    }
}

/// A numpy array borrowed from a message.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray<'a> {
    /// Element type.
    pub dtype: DType,
    /// Shape (C order).
    pub shape: Vec<usize>,
    /// The elements' bytes, little-endian, `shape.product() * dtype.size()` of them.
    pub data: &'a [u8],
}

impl NdArray<'_> {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    /// True when it has no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Element `i` as f64 (any numeric dtype; bool as 0 / 1). None past the end.
    pub fn get_f64(&self, i: usize) -> Option<f64> {
        let s = self.dtype.size();
        let b = self.data.get(i * s..(i + 1) * s)?;
        let mut a8 = [0u8; 8];
        a8[..s].copy_from_slice(b);
        Some(match self.dtype {
            DType::U8 => b[0] as f64,
            DType::I8 => b[0] as i8 as f64,
            DType::Bool => (b[0] != 0) as u8 as f64,
            DType::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            DType::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            DType::F16 => f16_to_f64(u16::from_le_bytes([b[0], b[1]])),
            DType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DType::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DType::U64 => u64::from_le_bytes(a8) as f64,
            DType::I64 => i64::from_le_bytes(a8) as f64,
            DType::F64 => f64::from_le_bytes(a8),
        })
    }

    /// Every element as f64.
    pub fn to_f64(&self) -> Vec<f64> {
        (0..self.len()).filter_map(|i| self.get_f64(i)).collect()
    }
}

fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    sign * match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// A decoded msgpack-numpy value, borrowing strings, bytes and array data from the message.
#[derive(Debug, Clone, PartialEq)]
pub enum Value<'a> {
    Nil,
    Bool(bool),
    Int(i64),
    UInt(u64),
    Float(f64),
    Str(&'a str),
    Bin(&'a [u8]),
    Array(Vec<Value<'a>>),
    Map(Vec<(Value<'a>, Value<'a>)>),
    NdArray(NdArray<'a>),
}

impl<'a> Value<'a> {
    /// The entry under the str (or bin) key `key` of a map.
    pub fn get(&self, key: &str) -> Option<&Value<'a>> {
        match self {
            Value::Map(m) => m
                .iter()
                .find(|(k, _)| k.key_str() == Some(key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    /// A str, or a bin that is UTF-8 (a map key as either).
    pub fn key_str(&self) -> Option<&'a str> {
        match self {
            Value::Str(s) => Some(s),
            Value::Bin(b) => std::str::from_utf8(b).ok(),
            _ => None,
        }
    }

    /// A number as f64.
    pub fn as_f64(&self) -> Option<f64> {
        match *self {
            Value::Int(i) => Some(i as f64),
            Value::UInt(u) => Some(u as f64),
            Value::Float(f) => Some(f),
            Value::NdArray(ref a) if a.shape.is_empty() => a.get_f64(0),
            _ => None,
        }
    }

    /// An integer that fits u64.
    pub fn as_u64(&self) -> Option<u64> {
        match *self {
            Value::Int(i) => u64::try_from(i).ok(),
            Value::UInt(u) => Some(u),
            _ => None,
        }
    }

    /// What kind of value this is, for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Value::Nil => "nil",
            Value::Bool(_) => "a bool",
            Value::Int(_) | Value::UInt(_) => "an integer",
            Value::Float(_) => "a float",
            Value::Str(_) => "a str",
            Value::Bin(_) => "bytes",
            Value::Array(_) => "a list",
            Value::Map(_) => "a map",
            Value::NdArray(_) => "an ndarray",
        }
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    items: usize,
    limits: Limits,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.buf.len())
            .ok_or(DecodeError::Truncated(self.pos))?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn be(&mut self, n: usize) -> Result<u64, DecodeError> {
        Ok(self
            .take(n)?
            .iter()
            .fold(0u64, |acc, &b| (acc << 8) | b as u64))
    }

    fn count(&mut self, n: usize) -> Result<(), DecodeError> {
        self.items = self.items.saturating_add(n);
        if self.items > self.limits.max_items {
            return Err(DecodeError::TooManyItems(self.limits.max_items));
        }
        Ok(())
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>, DecodeError> {
        if depth > self.limits.max_depth {
            return Err(DecodeError::TooDeep(self.limits.max_depth));
        }
        self.count(1)?;
        let at = self.pos;
        let m = self.take(1)?[0];
        let v = match m {
            0x00..=0x7f => Value::UInt(m as u64),
            0xe0..=0xff => Value::Int(m as i8 as i64),
            0x80..=0x8f => return self.map((m & 0x0f) as usize, depth),
            0x90..=0x9f => return self.array((m & 0x0f) as usize, depth),
            0xa0..=0xbf => self.str((m & 0x1f) as usize)?,
            0xc0 => Value::Nil,
            0xc2 => Value::Bool(false),
            0xc3 => Value::Bool(true),
            0xc4..=0xc6 => {
                let n = self.be(1 << (m - 0xc4))? as usize;
                Value::Bin(self.take(n)?)
            }
            0xca => Value::Float(f32::from_bits(self.be(4)? as u32) as f64),
            0xcb => Value::Float(f64::from_bits(self.be(8)?)),
            0xcc..=0xcf => Value::UInt(self.be(1 << (m - 0xcc))?),
            0xd0 => Value::Int(self.be(1)? as u8 as i8 as i64),
            0xd1 => Value::Int(self.be(2)? as u16 as i16 as i64),
            0xd2 => Value::Int(self.be(4)? as u32 as i32 as i64),
            0xd3 => Value::Int(self.be(8)? as i64),
            0xd9..=0xdb => {
                let n = self.be(1 << (m - 0xd9))? as usize;
                self.str(n)?
            }
            0xdc | 0xdd => {
                let n = self.be(2 << (m - 0xdc))? as usize;
                return self.array(n, depth);
            }
            0xde | 0xdf => {
                let n = self.be(2 << (m - 0xde))? as usize;
                return self.map(n, depth);
            }
            other => return Err(DecodeError::Unsupported(other, at)),
        };
        Ok(v)
    }

    fn str(&mut self, n: usize) -> Result<Value<'a>, DecodeError> {
        let at = self.pos;
        let b = self.take(n)?;
        std::str::from_utf8(b)
            .map(Value::Str)
            .map_err(|_| DecodeError::Utf8(at))
    }

    fn array(&mut self, n: usize, depth: usize) -> Result<Value<'a>, DecodeError> {
        // every element takes at least a byte: a length beyond the bytes left is a lie
        if n > self.buf.len() - self.pos {
            return Err(DecodeError::Truncated(self.pos));
        }
        self.count(n)?;
        let mut v = Vec::with_capacity(n);
        for _ in 0..n {
            v.push(self.value(depth + 1)?);
        }
        Ok(Value::Array(v))
    }

    fn map(&mut self, n: usize, depth: usize) -> Result<Value<'a>, DecodeError> {
        if n.saturating_mul(2) > self.buf.len() - self.pos {
            return Err(DecodeError::Truncated(self.pos));
        }
        self.count(n)?;
        let mut m = Vec::with_capacity(n);
        for _ in 0..n {
            let k = self.value(depth + 1)?;
            let v = self.value(depth + 1)?;
            m.push((k, v));
        }
        if is_marked(&m, "__ndarray__") {
            return ndarray(m, self.limits.max_ndim).map(Value::NdArray);
        }
        if is_marked(&m, "__npgeneric__") {
            return Ok(m
                .into_iter()
                .find(|(k, _)| k.key_str() == Some("data"))
                .map(|(_, v)| v)
                .unwrap_or(Value::Nil));
        }
        Ok(Value::Map(m))
    }
}

fn is_marked(m: &[(Value<'_>, Value<'_>)], marker: &str) -> bool {
    m.iter().any(|(k, v)| {
        k.key_str() == Some(marker) && matches!(v, Value::Bool(true) | Value::UInt(1))
    })
}

fn ndarray<'a>(
    m: Vec<(Value<'a>, Value<'a>)>,
    max_ndim: usize,
) -> Result<NdArray<'a>, DecodeError> {
    let bad = |s: String| DecodeError::NdArray(s);
    let (mut data, mut dtype, mut shape) = (None, None, None);
    for (k, v) in m {
        match (k.key_str(), v) {
            (Some("data"), Value::Bin(b)) => data = Some(b),
            (Some("dtype"), v) => {
                let s = v
                    .key_str()
                    .ok_or_else(|| bad("'dtype' is not a str".into()))?;
                dtype = Some(
                    DType::parse(s)
                        .ok_or_else(|| bad(format!("dtype {s:?} is not one chunkrt reads")))?,
                );
            }
            (Some("shape"), Value::Array(dims)) => {
                if dims.len() > max_ndim {
                    return Err(bad(format!(
                        "{} dimensions (at most {max_ndim})",
                        dims.len()
                    )));
                }
                shape = Some(
                    dims.iter()
                        .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
                        .collect::<Option<Vec<usize>>>()
                        .ok_or_else(|| bad("'shape' holds a non-integer".into()))?,
                );
            }
            _ => {}
        }
    }
    let data = data.ok_or_else(|| bad("no bin 'data'".into()))?;
    let dtype = dtype.ok_or_else(|| bad("no 'dtype'".into()))?;
    let shape = shape.ok_or_else(|| bad("no list 'shape'".into()))?;
    let want = shape
        .iter()
        .try_fold(dtype.size(), |acc, &d| acc.checked_mul(d));
    if want != Some(data.len()) {
        return Err(bad(format!(
            "shape {shape:?} of {dtype} needs {} bytes, 'data' has {}",
            want.map_or("too many".to_string(), |w| w.to_string()),
            data.len()
        )));
    }
    Ok(NdArray { dtype, shape, data })
}

/// Decodes one message (`msgpack_numpy.unpackb`) within `limits`.
pub fn decode(msg: &[u8], limits: Limits) -> Result<Value<'_>, DecodeError> {
    let mut r = Reader {
        buf: msg,
        pos: 0,
        items: 0,
        limits,
    };
    let v = r.value(0)?;
    if r.pos != msg.len() {
        return Err(DecodeError::Trailing(msg.len() - r.pos));
    }
    Ok(v)
}

/// Writes msgpack-numpy into a byte buffer (`msgpack_numpy.packb`; writing to a `Vec` cannot
/// fail).
#[derive(Debug, Default)]
pub struct Writer {
    /// The bytes written so far.
    pub buf: Vec<u8>,
}

impl Writer {
    /// An empty writer.
    pub fn new() -> Self {
        Self::default()
    }

    /// Empties the buffer, keeping its memory.
    pub fn clear(&mut self) {
        self.buf.clear();
    }

    /// A map header of `n` entries.
    pub fn map(&mut self, n: usize) -> &mut Self {
        let _ = rmp::encode::write_map_len(&mut self.buf, n as u32);
        self
    }

    /// A list header of `n` elements.
    pub fn list(&mut self, n: usize) -> &mut Self {
        let _ = rmp::encode::write_array_len(&mut self.buf, n as u32);
        self
    }

    /// A str.
    pub fn str(&mut self, s: &str) -> &mut Self {
        let _ = rmp::encode::write_str(&mut self.buf, s);
        self
    }

    /// A float64 (numpy's float64 and Python's float are written this way).
    pub fn f64(&mut self, v: f64) -> &mut Self {
        let _ = rmp::encode::write_f64(&mut self.buf, v);
        self
    }

    /// An integer.
    pub fn int(&mut self, v: i64) -> &mut Self {
        let _ = rmp::encode::write_sint(&mut self.buf, v);
        self
    }

    /// An unsigned integer.
    pub fn uint(&mut self, v: u64) -> &mut Self {
        let _ = rmp::encode::write_uint(&mut self.buf, v);
        self
    }

    /// A bool.
    pub fn bool(&mut self, v: bool) -> &mut Self {
        let _ = rmp::encode::write_bool(&mut self.buf, v);
        self
    }

    /// nil.
    pub fn nil(&mut self) -> &mut Self {
        let _ = rmp::encode::write_nil(&mut self.buf);
        self
    }

    /// An ndarray of `dtype` and `shape` whose bytes `write` appends (exactly
    /// `shape.product() * dtype.size()` of them, little-endian, C order).
    pub fn ndarray_with(
        &mut self,
        dtype: DType,
        shape: &[usize],
        write: impl FnOnce(&mut Vec<u8>),
    ) -> &mut Self {
        let n = shape.iter().product::<usize>() * dtype.size();
        let _ = rmp::encode::write_map_len(&mut self.buf, 4);
        let _ = rmp::encode::write_bin(&mut self.buf, b"__ndarray__");
        let _ = rmp::encode::write_bool(&mut self.buf, true);
        let _ = rmp::encode::write_bin(&mut self.buf, b"data");
        let _ = rmp::encode::write_bin_len(&mut self.buf, n as u32);
        let start = self.buf.len();
        write(&mut self.buf);
        debug_assert_eq!(self.buf.len() - start, n, "ndarray bytes");
        self.buf.resize(start + n, 0);
        let _ = rmp::encode::write_bin(&mut self.buf, b"dtype");
        let _ = rmp::encode::write_str(&mut self.buf, dtype.typestr());
        let _ = rmp::encode::write_bin(&mut self.buf, b"shape");
        let _ = rmp::encode::write_array_len(&mut self.buf, shape.len() as u32);
        for &d in shape {
            let _ = rmp::encode::write_uint(&mut self.buf, d as u64);
        }
        self
    }

    /// A uint8 ndarray.
    pub fn u8_array(&mut self, shape: &[usize], data: &[u8]) -> &mut Self {
        self.ndarray_with(DType::U8, shape, |b| b.extend_from_slice(data))
    }

    /// A float32 ndarray from f64 values.
    pub fn f32_array(&mut self, shape: &[usize], data: &[f64]) -> &mut Self {
        self.ndarray_with(DType::F32, shape, |b| {
            for &x in data {
                b.extend_from_slice(&(x as f32).to_le_bytes());
            }
        })
    }

    /// A float64 ndarray.
    pub fn f64_array(&mut self, shape: &[usize], data: &[f64]) -> &mut Self {
        self.ndarray_with(DType::F64, shape, |b| {
            for &x in data {
                b.extend_from_slice(&x.to_le_bytes());
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ndarray_bytes_are_msgpack_numpy_s() {
        // np.array([1.0, 2.0], np.float32) packed by openpi_client.msgpack_numpy (51 bytes)
        let mut w = Writer::new();
        w.f32_array(&[2], &[1.0, 2.0]);
        let mut want = vec![0x84, 0xc4, 0x0b];
        want.extend_from_slice(b"__ndarray__");
        want.push(0xc3);
        want.extend_from_slice(&[0xc4, 0x04]);
        want.extend_from_slice(b"data");
        want.extend_from_slice(&[0xc4, 0x08, 0, 0, 0x80, 0x3f, 0, 0, 0, 0x40]);
        want.extend_from_slice(&[0xc4, 0x05]);
        want.extend_from_slice(b"dtype");
        want.extend_from_slice(&[0xa3, b'<', b'f', b'4']);
        want.extend_from_slice(&[0xc4, 0x05]);
        want.extend_from_slice(b"shape");
        want.extend_from_slice(&[0x91, 0x02]);
        assert_eq!(w.buf, want);
        assert_eq!(w.buf.len(), 51);
        let v = decode(&w.buf, Limits::default()).unwrap();
        let Value::NdArray(a) = v else {
            panic!("not an ndarray: {v:?}")
        };
        assert_eq!(a.to_f64(), vec![1.0, 2.0]);
    }

    #[test]
    fn maps_scalars_and_nesting_round_trip() {
        let mut w = Writer::new();
        w.map(4)
            .str("prompt")
            .str("pick it up")
            .str("images")
            .map(1)
            .str("cam_high")
            .u8_array(&[3, 2, 2], &[7; 12])
            .str("n")
            .int(-5)
            .str("x")
            .f64(0.25);
        let v = decode(&w.buf, Limits::default()).unwrap();
        assert_eq!(v.get("prompt"), Some(&Value::Str("pick it up")));
        let Some(Value::NdArray(img)) = v.get("images").and_then(|m| m.get("cam_high")) else {
            panic!("no image")
        };
        assert_eq!(img.shape, vec![3, 2, 2]);
        assert_eq!(v.get("n").and_then(Value::as_f64), Some(-5.0));
        assert_eq!(v.get("x").and_then(Value::as_f64), Some(0.25));
    }

    #[test]
    fn hostile_messages_are_bounded_errors() {
        let lim = Limits::default();
        // a map claiming 2^32 - 1 entries in six bytes
        assert!(matches!(
            decode(&[0xdf, 0xff, 0xff, 0xff, 0xff, 0x01], lim),
            Err(DecodeError::Truncated(_))
        ));
        // a bin claiming 4 GiB
        assert!(decode(&[0xc6, 0xff, 0xff, 0xff, 0xff], lim).is_err());
        // deep nesting
        let deep = vec![0x91; 100];
        assert!(matches!(decode(&deep, lim), Err(DecodeError::TooDeep(_))));
        // many small items
        let mut many = vec![0xdd, 0x00, 0x01, 0x00, 0x00];
        many.extend(std::iter::repeat_n(0xc0, 65_536));
        assert!(matches!(
            decode(&many, lim),
            Err(DecodeError::TooManyItems(_))
        ));
        // an ndarray whose data disagrees with its shape
        let mut w = Writer::new();
        w.ndarray_with(DType::U8, &[4], |b| b.extend_from_slice(&[1, 2, 3, 4]));
        let at = w.buf.len() - 1;
        w.buf[at] = 5; // shape [5]
        assert!(matches!(decode(&w.buf, lim), Err(DecodeError::NdArray(_))));
        // an ext type, trailing bytes, a bad str
        assert!(decode(&[0xd4, 0x01, 0x00], lim).is_err());
        assert!(matches!(
            decode(&[0xc0, 0xc0], lim),
            Err(DecodeError::Trailing(1))
        ));
        assert!(matches!(
            decode(&[0xa1, 0xff], lim),
            Err(DecodeError::Utf8(_))
        ));
        // every prefix of a valid message is an error, never a panic
        let mut w = Writer::new();
        w.map(2)
            .str("a")
            .f32_array(&[2, 2], &[1.0; 4])
            .str("b")
            .str("c");
        for n in 0..w.buf.len() {
            assert!(decode(&w.buf[..n], lim).is_err(), "prefix {n}");
        }
    }

    #[test]
    fn dtypes_and_scalars() {
        assert_eq!(DType::parse("<f4"), Some(DType::F32));
        assert_eq!(DType::parse("|u1"), Some(DType::U8));
        assert_eq!(DType::parse(">f4"), None);
        assert_eq!(DType::parse("<U3"), None);
        assert_eq!(f16_to_f64(0x3c00), 1.0);
        assert_eq!(f16_to_f64(0xc000), -2.0);
        // np.float32(1.5) as msgpack_numpy writes it: the native value under 'data'
        let mut w = Writer::new();
        w.map(3);
        let _ = rmp::encode::write_bin(&mut w.buf, b"__npgeneric__");
        w.bool(true);
        let _ = rmp::encode::write_bin(&mut w.buf, b"data");
        w.f64(1.5);
        let _ = rmp::encode::write_bin(&mut w.buf, b"dtype");
        w.str("<f4");
        assert_eq!(decode(&w.buf, Limits::default()), Ok(Value::Float(1.5)));
    }
}
