//! PCD point clouds (Point Cloud Library format, v0.7 and older headers): the `x`, `y`, `z` of
//! every point from `DATA ascii`, `binary` (records of all fields, little endian) or
//! `binary_compressed` (u32 compressed size, u32 raw size, then an LZF block holding the fields one
//! after the other, each as `POINTS` values). Field types F (4, 8 bytes), I and U (1, 2, 4, 8).

use super::lzf;
use super::point_cloud::{header_line, CloudError, PointSink, ScalarType};

#[derive(Debug, Clone)]
struct Field {
    name: String,
    kind: ScalarType,
    count: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    Binary,
    BinaryCompressed,
}

/// Parses a PCD file's bytes into points (`x`, `y`, `z` in the file's units, assumed metres).
/// Points with a non-finite coordinate are an error naming the point unless `drop_non_finite`.
pub fn parse_pcd(bytes: &[u8], drop_non_finite: bool) -> Result<Vec<[f64; 3]>, CloudError> {
    let mut fields: Vec<Field> = Vec::new();
    let (mut sizes, mut types, mut counts): (Vec<usize>, Vec<char>, Vec<usize>) = (Vec::new(), Vec::new(), Vec::new());
    let (mut width, mut height, mut points): (Option<usize>, Option<usize>, Option<usize>) = (None, None, None);
    let mut offset = 0;
    let mut line_number = 0;
    let encoding = loop {
        let line = header_line(bytes, &mut offset, &mut line_number, "a DATA line")?;
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let header = |reason: String| CloudError::Header { line: line_number, reason };
        let mut words = line.split_whitespace();
        let key = words.next().unwrap_or("").to_ascii_uppercase();
        let values: Vec<&str> = words.collect();
        let numbers = |values: &[&str]| -> Result<Vec<usize>, CloudError> {
            values.iter().map(|v| v.parse::<usize>().map_err(|_| header(format!("{key}: {v:?} is not a non-negative integer")))).collect()
        };
        let single = |values: &[&str]| -> Result<usize, CloudError> {
            match numbers(values)?.as_slice() {
                [n] => Ok(*n),
                _ => Err(header(format!("{key} needs one value"))),
            }
        };
        match key.as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" | "COLUMNS" => {
                fields = values.iter().map(|name| Field { name: (*name).to_string(), kind: ScalarType::U8, count: 1 }).collect();
            }
            "SIZE" => sizes = numbers(&values)?,
            "TYPE" => {
                types = values.iter().map(|t| t.chars().next().unwrap_or('?').to_ascii_uppercase()).collect();
            }
            "COUNT" => counts = numbers(&values)?,
            "WIDTH" => width = Some(single(&values)?),
            "HEIGHT" => height = Some(single(&values)?),
            "POINTS" => points = Some(single(&values)?),
            "DATA" => {
                break match values.first().map(|v| v.to_ascii_lowercase()).as_deref() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary") => Encoding::Binary,
                    Some("binary_compressed") => Encoding::BinaryCompressed,
                    other => return Err(header(format!("DATA {other:?} is not ascii, binary or binary_compressed"))),
                };
            }
            _ => return Err(header(format!("unknown header key {key:?} (is this a PCD file?)"))),
        }
    };
    if fields.is_empty() {
        return Err(CloudError::Header { line: line_number, reason: "no FIELDS line before DATA".into() });
    }
    if counts.is_empty() {
        counts = vec![1; fields.len()];
    }
    if sizes.len() != fields.len() || types.len() != fields.len() || counts.len() != fields.len() {
        return Err(CloudError::Header {
            line: line_number,
            reason: format!("{} FIELDS but {} SIZE, {} TYPE, {} COUNT values", fields.len(), sizes.len(), types.len(), counts.len()),
        });
    }
    for (i, field) in fields.iter_mut().enumerate() {
        let (size, kind, count) =
            (sizes.get(i).copied().unwrap_or(0), types.get(i).copied().unwrap_or('?'), counts.get(i).copied().unwrap_or(1));
        field.kind = ScalarType::from_pcd(kind, size)
            .ok_or_else(|| CloudError::Unsupported(format!("field {:?}: TYPE {kind} SIZE {size}", field.name)))?;
        field.count = count;
    }
    let n = match (points, width, height) {
        (Some(p), _, _) => p,
        (None, Some(w), Some(h)) => w.saturating_mul(h),
        _ => return Err(CloudError::Header { line: line_number, reason: "neither POINTS nor WIDTH and HEIGHT given".into() }),
    };
    if let (Some(w), Some(h)) = (width, height) {
        if w.saturating_mul(h) != n {
            return Err(CloudError::Header { line: line_number, reason: format!("WIDTH × HEIGHT = {w} × {h} but POINTS = {n}") });
        }
    }
    // Where x, y, z are: (field index, value offset within a record).
    let mut record_size = 0;
    let mut axes = [None; 3];
    let mut value_index = 0;
    for (i, field) in fields.iter().enumerate() {
        if let Some(axis) = ["x", "y", "z"].iter().position(|a| *a == field.name) {
            if field.count != 1 {
                return Err(CloudError::Unsupported(format!("field {:?} with COUNT {}", field.name, field.count)));
            }
            axes[axis] = Some((i, record_size, value_index));
        }
        record_size += field.kind.size() * field.count;
        value_index += field.count;
    }
    let [Some(x), Some(y), Some(z)] = axes else {
        return Err(CloudError::Header { line: line_number, reason: "FIELDS lacks x, y or z".into() });
    };
    let data = bytes.get(offset..).unwrap_or(&[]);
    let mut cloud = PointSink::new(n, drop_non_finite);
    match encoding {
        Encoding::Ascii => {
            let text = std::str::from_utf8(data).map_err(|_| CloudError::Ascii { line: line_number + 1, reason: "not text".into() })?;
            let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
            for index in 0..n {
                let Some((k, line)) = lines.next() else {
                    return Err(CloudError::Truncated { what: format!("ascii data: {index} of {n} points present") });
                };
                let tokens: Vec<&str> = line.split_whitespace().collect();
                if tokens.len() != value_index {
                    return Err(CloudError::Ascii {
                        line: line_number + 1 + k,
                        reason: format!("{} values, {value_index} expected", tokens.len()),
                    });
                }
                let value = |(_, _, v): (usize, usize, usize)| -> Result<f64, CloudError> {
                    let token = tokens.get(v).copied().unwrap_or("");
                    token
                        .parse::<f64>()
                        .map_err(|_| CloudError::Ascii { line: line_number + 1 + k, reason: format!("{token:?} is not a number") })
                };
                cloud.push(index, [value(x)?, value(y)?, value(z)?])?;
            }
        }
        Encoding::Binary => {
            let needed = n.saturating_mul(record_size);
            if data.len() < needed {
                return Err(CloudError::Truncated { what: format!("binary data: {needed} bytes expected, {} present", data.len()) });
            }
            for index in 0..n {
                let record = data.get(index * record_size..(index + 1) * record_size).unwrap_or(&[]);
                let value = |(i, at, _): (usize, usize, usize)| fields.get(i).map_or(f64::NAN, |f| f.kind.read_le(record, at));
                cloud.push(index, [value(x), value(y), value(z)])?;
            }
        }
        Encoding::BinaryCompressed => {
            let word = |at: usize| data.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
            let (Some(compressed), Some(raw)) = (word(0), word(4)) else {
                return Err(CloudError::Truncated { what: "binary_compressed data: the two size words are missing".into() });
            };
            let block = data.get(8..8 + compressed).ok_or_else(|| CloudError::Truncated {
                what: format!("binary_compressed data: {compressed} compressed bytes announced, {} present", data.len().saturating_sub(8)),
            })?;
            let needed = n.saturating_mul(record_size);
            if raw != needed {
                return Err(CloudError::Truncated { what: format!("binary_compressed data: {raw} raw bytes announced, {needed} needed") });
            }
            let raw = lzf::decompress(block, raw)?;
            // Field-major: field f's values start at n × (bytes of the fields before it).
            let field_start = |i: usize| -> usize { fields.iter().take(i).map(|f| f.kind.size() * f.count).sum::<usize>() * n };
            let starts = [field_start(x.0), field_start(y.0), field_start(z.0)];
            for index in 0..n {
                let value = |axis: usize, (i, _, _): (usize, usize, usize)| {
                    fields.get(i).map_or(f64::NAN, |f| f.kind.read_le(&raw, starts.get(axis).copied().unwrap_or(0) + index * f.kind.size()))
                };
                cloud.push(index, [value(0, x), value(1, y), value(2, z)])?;
            }
        }
    }
    Ok(cloud.into_points())
}

/// Writes points as a PCD file with fields x y z (F 4) in the given data flavour (tests, tools).
pub fn write_pcd(points: &[[f32; 3]], data: &str) -> Result<Vec<u8>, CloudError> {
    let n = points.len();
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )
    .into_bytes();
    match data {
        "ascii" => {
            for p in points {
                out.extend_from_slice(format!("{} {} {}\n", p[0], p[1], p[2]).as_bytes());
            }
        }
        "binary" => out.extend(points.iter().flat_map(|p| p.iter().flat_map(|c| c.to_le_bytes()))),
        "binary_compressed" => {
            let raw: Vec<u8> =
                (0..3).flat_map(|axis| points.iter().flat_map(move |p| p.get(axis).copied().unwrap_or(0.0).to_le_bytes())).collect();
            let packed = lzf::compress(&raw);
            out.extend_from_slice(&(packed.len() as u32).to_le_bytes());
            out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
            out.extend_from_slice(&packed);
        }
        other => return Err(CloudError::Unsupported(format!("PCD DATA {other:?}"))),
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points() -> Vec<[f32; 3]> {
        (0..40).map(|i| [i as f32 * 0.01, (i % 5) as f32 * 0.02, 0.1 + (i / 5) as f32 * 0.003]).collect()
    }

    fn as_f64(points: &[[f32; 3]]) -> Vec<[f64; 3]> {
        points.iter().map(|p| p.map(f64::from)).collect()
    }

    #[test]
    fn every_data_flavour_reads_back() {
        for flavour in ["ascii", "binary", "binary_compressed"] {
            let bytes = write_pcd(&points(), flavour).unwrap();
            let parsed = parse_pcd(&bytes, false).unwrap();
            if flavour == "ascii" {
                // Printed as the shortest decimal of the f32: the same f32 when read back.
                let as_f32: Vec<[f32; 3]> = parsed.iter().map(|p| p.map(|c| c as f32)).collect();
                assert_eq!(as_f32, points());
            } else {
                assert_eq!(parsed, as_f64(&points()), "{flavour}");
            }
        }
    }

    #[test]
    fn hand_written_files_with_other_fields_and_types() {
        // ascii with an rgb field first and double z, COUNT omitted, comments and blank lines.
        let text = "# hand written\nVERSION .7\nFIELDS rgb x y z\nSIZE 4 4 4 8\nTYPE U F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n\
                    4278190335 1.5 -2 0.25\n\n7 0 0 -1e-3\n";
        assert_eq!(parse_pcd(text.as_bytes(), false).unwrap(), vec![[1.5, -2.0, 0.25], [0.0, 0.0, -1e-3]]);
        // binary with a padding field of COUNT 3 and i16 coordinates (millimetre-like integers).
        let mut bytes =
            b"VERSION 0.7\nFIELDS _ x y z\nSIZE 1 2 2 2\nTYPE U I I I\nCOUNT 3 1 1 1\nWIDTH 1\nHEIGHT 2\nDATA binary\n".to_vec();
        for (x, y, z) in [(1i16, -2i16, 3i16), (-400, 500, 600)] {
            bytes.extend_from_slice(&[9, 9, 9]);
            bytes.extend(x.to_le_bytes().into_iter().chain(y.to_le_bytes()).chain(z.to_le_bytes()));
        }
        assert_eq!(parse_pcd(&bytes, false).unwrap(), vec![[1.0, -2.0, 3.0], [-400.0, 500.0, 600.0]]);
        // binary_compressed with a hand-made LZF block: two points (1, 2, 3), (1, 2, 3) as f32;
        // raw = x x y y z z, each value repeated once → literal of 4 bytes + a back reference of 4.
        let mut raw = Vec::new();
        for v in [1.0f32, 2.0, 3.0] {
            raw.extend_from_slice(&v.to_le_bytes());
            raw.extend_from_slice(&v.to_le_bytes());
        }
        let mut block = Vec::new();
        for v in [1.0f32, 2.0, 3.0] {
            block.push(3);
            block.extend_from_slice(&v.to_le_bytes());
            block.extend_from_slice(&[(2 << 5), 3]); // 4 bytes from 4 back
        }
        let mut bytes = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 2\nDATA binary_compressed\n".to_vec();
        bytes.extend_from_slice(&(block.len() as u32).to_le_bytes());
        bytes.extend_from_slice(&(raw.len() as u32).to_le_bytes());
        bytes.extend_from_slice(&block);
        assert_eq!(parse_pcd(&bytes, false).unwrap(), vec![[1.0, 2.0, 3.0]; 2]);
    }

    #[test]
    fn bad_files_are_errors_naming_the_problem() {
        let message = |bytes: &[u8]| parse_pcd(bytes, false).unwrap_err().to_string();
        assert!(message(b"ply\nformat ascii 1.0\n").contains("unknown header key \"PLY\""));
        assert!(message(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\n").contains("before a DATA line"));
        assert!(message(b"FIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n0 0 0\n").contains("3 FIELDS but 2 SIZE"));
        assert!(message(b"FIELDS x y z\nSIZE 2 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n0 0 0\n").contains("TYPE F SIZE 2"));
        assert!(message(b"FIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA ascii\n0 0\n").contains("lacks x, y or z"));
        assert!(message(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 2\nDATA ascii\n0 0 0\n").contains("1 of 2 points"));
        assert!(message(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n0 zero 0\n").contains("\"zero\" is not a number"));
        assert!(message(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA lzma\n").contains("lzma"));
        let nan = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 2\nDATA ascii\n0 0 0\n1 nan 0\n";
        assert!(message(nan).contains("point 1"), "{}", message(nan));
        assert_eq!(parse_pcd(nan, true).unwrap(), vec![[0.0, 0.0, 0.0]]);
        // Truncated binary and compressed data.
        let bytes = write_pcd(&points(), "binary").unwrap();
        assert!(message(&bytes[..bytes.len() - 1]).contains("479 present"));
        let bytes = write_pcd(&points(), "binary_compressed").unwrap();
        assert!(message(&bytes[..bytes.len() - 3]).contains("compressed bytes announced"));
        let marker = b"DATA binary_compressed\n";
        let data_start = bytes.windows(marker.len()).position(|w| w == marker).unwrap() + marker.len();
        let mut corrupt = bytes.clone();
        corrupt[data_start + 4] ^= 0x01; // raw size word off by one
        assert!(message(&corrupt).contains("raw bytes announced"), "{}", message(&corrupt));
        let mut corrupt = bytes.clone();
        corrupt[data_start + 8] = 0xe0 | 0x1f; // first chunk: a long back reference into nothing
        assert!(parse_pcd(&corrupt, false).is_err());
    }
}
