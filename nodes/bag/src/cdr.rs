//! OMG CDR (XCDR1, "plain CDR") as ROS 2 puts it on the wire and rosbag2 stores it: a 4-byte
//! encapsulation header (`00 01 00 00` little endian, `00 00 00 00` big endian), then every
//! primitive aligned to its own size (8 for `float64`) counted from the end of that header.
//! Strings are a `uint32` length including the terminating NUL, then the bytes and the NUL;
//! sequences a `uint32` element count, then the elements; fixed arrays only their elements.

/// What was wrong with a CDR payload.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CdrError {
    #[error("payload of {0} bytes is shorter than the 4-byte CDR encapsulation header")]
    NoHeader(usize),
    #[error("encapsulation {0:#04x}{1:02x} is not plain CDR (00 00 big endian or 00 01 little endian)")]
    Encapsulation(u8, u8),
    #[error("payload ends at byte {len} while reading {what} ({needed} more bytes needed)")]
    Truncated { what: &'static str, len: usize, needed: usize },
    #[error("{what}: length {count} exceeds the {remaining} bytes left in the payload")]
    Length { what: &'static str, count: usize, remaining: usize },
    #[error("{what} is not valid UTF-8 or lacks its terminating NUL")]
    String { what: &'static str },
}

/// Reads a CDR payload field by field.
pub struct CdrReader<'a> {
    /// The payload after the encapsulation header.
    body: &'a [u8],
    pos: usize,
    little_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Starts reading `payload` (encapsulation header included).
    pub fn new(payload: &'a [u8]) -> Result<Self, CdrError> {
        let [first, second, _, _, ..] = payload else {
            return Err(CdrError::NoHeader(payload.len()));
        };
        let little_endian = match (*first, *second) {
            (0, 1) => true,
            (0, 0) => false,
            (a, b) => return Err(CdrError::Encapsulation(a, b)),
        };
        Ok(Self { body: &payload[4..], pos: 0, little_endian })
    }

    fn take(&mut self, size: usize, align: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let start = self.pos.div_ceil(align) * align;
        let end = start.checked_add(size).filter(|end| *end <= self.body.len()).ok_or(CdrError::Truncated {
            what,
            len: self.body.len() + 4,
            needed: start.saturating_add(size).saturating_sub(self.body.len()),
        })?;
        self.pos = end;
        Ok(&self.body[start..end])
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CdrError> {
        let bytes = self.take(N, N, what)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        if self.little_endian != cfg!(target_endian = "little") {
            out.reverse();
        }
        Ok(out)
    }

    pub fn u8(&mut self, what: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(1, 1, what)?[0])
    }

    pub fn bool(&mut self, what: &'static str) -> Result<bool, CdrError> {
        Ok(self.u8(what)? != 0)
    }

    pub fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_ne_bytes(self.array(what)?))
    }

    pub fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_ne_bytes(self.array(what)?))
    }

    pub fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        Ok(f64::from_ne_bytes(self.array(what)?))
    }

    pub fn f64_array<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N], CdrError> {
        let mut out = [0.0; N];
        for value in &mut out {
            *value = self.f64(what)?;
        }
        Ok(out)
    }

    /// A sequence length, checked against what is left (each element takes at least `min_element_size` bytes).
    pub fn sequence_len(&mut self, what: &'static str, min_element_size: usize) -> Result<usize, CdrError> {
        let count = self.u32(what)? as usize;
        let remaining = self.body.len() - self.pos;
        if count.saturating_mul(min_element_size) > remaining {
            return Err(CdrError::Length { what, count, remaining });
        }
        Ok(count)
    }

    pub fn f64_sequence(&mut self, what: &'static str) -> Result<Vec<f64>, CdrError> {
        let count = self.sequence_len(what, 8)?;
        (0..count).map(|_| self.f64(what)).collect()
    }

    pub fn bytes(&mut self, what: &'static str) -> Result<Vec<u8>, CdrError> {
        let count = self.sequence_len(what, 1)?;
        Ok(self.take(count, 1, what)?.to_vec())
    }

    pub fn string(&mut self, what: &'static str) -> Result<String, CdrError> {
        let count = self.sequence_len(what, 1)?;
        let bytes = self.take(count, 1, what)?;
        // Length 0 (no NUL) is what some writers send for an empty string.
        let text = match bytes.split_last() {
            None => &[][..],
            Some((0, text)) => text,
            Some(_) => return Err(CdrError::String { what }),
        };
        String::from_utf8(text.to_vec()).map_err(|_| CdrError::String { what })
    }
}

/// Writes a little-endian CDR payload (encapsulation header included).
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        Self::with_capacity(64)
    }

    pub fn with_capacity(capacity: usize) -> Self {
        let mut buf = Vec::with_capacity(capacity + 4);
        buf.extend_from_slice(&[0, 1, 0, 0]);
        Self { buf }
    }

    fn align(&mut self, align: usize) {
        let body = self.buf.len() - 4;
        let padded = body.div_ceil(align) * align;
        self.buf.resize(padded + 4, 0);
    }

    pub fn u8(&mut self, value: u8) {
        self.buf.push(value);
    }

    pub fn bool(&mut self, value: bool) {
        self.buf.push(u8::from(value));
    }

    pub fn u32(&mut self, value: u32) {
        self.align(4);
        self.buf.extend_from_slice(&value.to_le_bytes());
    }

    pub fn i32(&mut self, value: i32) {
        self.align(4);
        self.buf.extend_from_slice(&value.to_le_bytes());
    }

    pub fn f64(&mut self, value: f64) {
        self.align(8);
        self.buf.extend_from_slice(&value.to_le_bytes());
    }

    pub fn f64_slice(&mut self, values: &[f64]) {
        for value in values {
            self.f64(*value);
        }
    }

    /// A sequence length (ROS sequences are at most `u32::MAX` long; longer ones are cut there).
    pub fn sequence_len(&mut self, len: usize) {
        self.u32(u32::try_from(len).unwrap_or(u32::MAX));
    }

    pub fn f64_sequence(&mut self, values: &[f64]) {
        self.sequence_len(values.len());
        self.f64_slice(values);
    }

    pub fn bytes(&mut self, bytes: &[u8]) {
        self.sequence_len(bytes.len());
        self.buf.extend_from_slice(bytes);
    }

    pub fn string(&mut self, text: &str) {
        self.sequence_len(text.len() + 1);
        self.buf.extend_from_slice(text.as_bytes());
        self.buf.push(0);
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn primitives_are_aligned_from_the_end_of_the_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.u32(9);
        let bytes = w.finish();
        // header | u8 | 7 padding | f64 | len 3 | "ab\0" | 1 padding | u32
        assert_eq!(&bytes[..5], &[0, 1, 0, 0, 7]);
        assert_eq!(&bytes[12..20], &1.5f64.to_le_bytes());
        assert_eq!(&bytes[20..27], &[3, 0, 0, 0, b'a', b'b', 0]);
        assert_eq!(&bytes[28..32], &9u32.to_le_bytes());
        let mut r = CdrReader::new(&bytes).unwrap();
        assert_eq!(r.u8("a").unwrap(), 7);
        assert_eq!(r.f64("b").unwrap(), 1.5);
        assert_eq!(r.string("c").unwrap(), "ab");
        assert_eq!(r.u32("d").unwrap(), 9);
        assert!(matches!(r.u8("e"), Err(CdrError::Truncated { what: "e", .. })));
    }

    #[test]
    fn big_endian_payloads_read() {
        let bytes = [0, 0, 0, 0, 0, 0, 0, 5, 0, 0, 0, 2, b'x', 0];
        let mut r = CdrReader::new(&bytes).unwrap();
        assert_eq!(r.u32("n").unwrap(), 5);
        assert_eq!(r.string("s").unwrap(), "x");
    }

    #[test]
    fn bad_headers_lengths_and_strings_are_errors() {
        assert_eq!(CdrReader::new(&[0, 1]).err(), Some(CdrError::NoHeader(2)));
        assert_eq!(CdrReader::new(&[0, 7, 0, 0]).err(), Some(CdrError::Encapsulation(0, 7)));
        // A sequence claiming 1000 doubles in 8 bytes.
        let mut w = CdrWriter::new();
        w.u32(1000);
        w.f64(1.0);
        let bytes = w.finish();
        let mut r = CdrReader::new(&bytes).unwrap();
        assert!(matches!(r.f64_sequence("d"), Err(CdrError::Length { what: "d", count: 1000, .. })));
        // A string without its NUL.
        let bytes = [0, 1, 0, 0, 2, 0, 0, 0, b'a', b'b'];
        assert_eq!(CdrReader::new(&bytes).unwrap().string("s").err(), Some(CdrError::String { what: "s" }));
        // An empty string sent without a NUL.
        let bytes = [0, 1, 0, 0, 0, 0, 0, 0];
        assert_eq!(CdrReader::new(&bytes).unwrap().string("s").unwrap(), "");
    }
}
