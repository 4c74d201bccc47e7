//! LZF (Marc Lehmann's liblzf format), the compression of PCD `binary_compressed` data.
//!
//! A stream is a sequence of chunks, each starting with a control byte `c`:
//! - `c < 32`: a literal run, the next `c + 1` bytes are copied to the output;
//! - else a back reference: length `L = c >> 5` (if `L = 7`, add the next byte), offset
//!   `((c & 31) << 8) + next byte`; `L + 2` bytes are copied from `output_end − offset − 1`
//!   (byte by byte, so the copy may overlap what it writes).
//!
//! [`decompress`] checks every bound and returns an error for any malformed stream; [`compress`]
//! is a greedy hash-chain-free encoder producing valid streams (tests, writing PCD files).

/// Why an LZF stream cannot be decompressed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LzfError {
    #[error("LZF stream ends inside a chunk at byte {at} (needs {needed} more bytes)")]
    Truncated { at: usize, needed: usize },
    #[error("LZF back reference at byte {at} points {offset} bytes back, before the start of the output ({available} bytes so far)")]
    BadReference { at: usize, offset: usize, available: usize },
    #[error("LZF data decompress to more than the {expected} bytes announced")]
    TooLong { expected: usize },
    #[error("LZF data decompress to {got} bytes, {expected} announced")]
    TooShort { expected: usize, got: usize },
}

/// Decompresses `input`, which must expand to exactly `expected_len` bytes.
pub fn decompress(input: &[u8], expected_len: usize) -> Result<Vec<u8>, LzfError> {
    let mut output: Vec<u8> = Vec::with_capacity(expected_len);
    let mut i = 0;
    let byte_at = |i: usize, needed: usize| input.get(i).copied().ok_or(LzfError::Truncated { at: i, needed });
    while i < input.len() {
        let control = usize::from(byte_at(i, 1)?);
        i += 1;
        if control < 32 {
            let run = control + 1;
            let literal = input.get(i..i + run).ok_or(LzfError::Truncated { at: i, needed: i + run - input.len() })?;
            if output.len() + run > expected_len {
                return Err(LzfError::TooLong { expected: expected_len });
            }
            output.extend_from_slice(literal);
            i += run;
        } else {
            let mut length = control >> 5;
            if length == 7 {
                length += usize::from(byte_at(i, 1)?);
                i += 1;
            }
            let offset = ((control & 0x1f) << 8) + usize::from(byte_at(i, 1)?) + 1;
            i += 1;
            let length = length + 2;
            if offset > output.len() {
                return Err(LzfError::BadReference { at: i, offset, available: output.len() });
            }
            if output.len() + length > expected_len {
                return Err(LzfError::TooLong { expected: expected_len });
            }
            let start = output.len() - offset;
            for k in 0..length {
                let byte = output.get(start + k).copied().unwrap_or(0);
                output.push(byte);
            }
        }
    }
    if output.len() != expected_len {
        return Err(LzfError::TooShort { expected: expected_len, got: output.len() });
    }
    Ok(output)
}

/// Longest back reference (bytes) and farthest offset of the format.
const MAX_MATCH: usize = 7 + 255 + 2;
const MAX_OFFSET: usize = 1 << 13;

/// Compresses `input` into an LZF stream (greedy: at each position the last occurrence of the next
/// three bytes is tried as a back reference).
pub fn compress(input: &[u8]) -> Vec<u8> {
    let mut output = Vec::with_capacity(input.len() + input.len() / 32 + 1);
    let mut last_seen = vec![usize::MAX; 1 << 14];
    let hash = |i: usize| -> usize {
        let (a, b, c) =
            (input.get(i).copied().unwrap_or(0), input.get(i + 1).copied().unwrap_or(0), input.get(i + 2).copied().unwrap_or(0));
        ((usize::from(a) << 16 | usize::from(b) << 8 | usize::from(c)).wrapping_mul(2_654_435_761) >> 8) & ((1 << 14) - 1)
    };
    let mut literal_start = 0;
    let mut i = 0;
    let flush = |output: &mut Vec<u8>, from: usize, to: usize| {
        for chunk in input.get(from..to).unwrap_or(&[]).chunks(32) {
            output.push((chunk.len() - 1) as u8);
            output.extend_from_slice(chunk);
        }
    };
    while i + 2 < input.len() {
        let h = hash(i);
        let candidate = last_seen.get(h).copied().unwrap_or(usize::MAX);
        if let Some(slot) = last_seen.get_mut(h) {
            *slot = i;
        }
        let usable = candidate != usize::MAX && i - candidate <= MAX_OFFSET && input.get(candidate..candidate + 3) == input.get(i..i + 3);
        if !usable {
            i += 1;
            continue;
        }
        let mut length = 3;
        while length < MAX_MATCH && i + length < input.len() && input.get(candidate + length) == input.get(i + length) {
            length += 1;
        }
        flush(&mut output, literal_start, i);
        let (offset, code) = (i - candidate - 1, length - 2);
        if code < 7 {
            output.push(((code << 5) | (offset >> 8)) as u8);
        } else {
            output.push(((7 << 5) | (offset >> 8)) as u8);
            output.push((code - 7) as u8);
        }
        output.push((offset & 0xff) as u8);
        i += length;
        literal_start = i;
    }
    flush(&mut output, literal_start, input.len());
    output
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_made_block_decompresses() {
        // "abc" literal, then a back reference of 6 bytes at offset 3 (overlapping: "abcabc").
        let block = [2, b'a', b'b', b'c', (4 << 5), 2];
        assert_eq!(decompress(&block, 9).unwrap(), b"abcabcabc");
        // Long reference: length code 7 + extra byte 3 → 12 bytes, offset 1 ("x" repeated).
        let block = [0, b'x', (7 << 5), 3, 0];
        assert_eq!(decompress(&block, 13).unwrap(), vec![b'x'; 13]);
    }

    #[test]
    fn round_trip_of_own_compressor() {
        let mut data: Vec<u8> = (0..5000u32).flat_map(|i| ((i / 7) as f32 * 0.01).to_le_bytes()).collect();
        data.extend(std::iter::repeat_n(0u8, 1000));
        data.extend((0..300u32).map(|i| (i * 31 % 251) as u8));
        let packed = compress(&data);
        assert!(packed.len() < data.len() / 2, "{} → {}", data.len(), packed.len());
        assert_eq!(decompress(&packed, data.len()).unwrap(), data);
        assert_eq!(decompress(&compress(b"ab"), 2).unwrap(), b"ab");
        assert_eq!(decompress(&compress(&[]), 0).unwrap(), Vec::<u8>::new());
    }

    #[test]
    fn malformed_streams_are_errors() {
        assert_eq!(decompress(&[5, b'a'], 6), Err(LzfError::Truncated { at: 1, needed: 5 }));
        assert_eq!(decompress(&[(1 << 5)], 3), Err(LzfError::Truncated { at: 1, needed: 1 }));
        assert_eq!(decompress(&[0, b'a', (1 << 5), 4], 4), Err(LzfError::BadReference { at: 4, offset: 5, available: 1 }));
        assert_eq!(decompress(&[1, b'a', b'b'], 1), Err(LzfError::TooLong { expected: 1 }));
        assert_eq!(decompress(&[1, b'a', b'b'], 5), Err(LzfError::TooShort { expected: 5, got: 2 }));
    }
}
