//! PLY point clouds (Stanford polygon format): the `x`, `y`, `z` properties of the `vertex` element
//! from `format ascii 1.0` or `binary_little_endian 1.0` files. Elements before `vertex` are
//! skipped (list properties included); faces after it are ignored, so meshes read as their vertices.

use super::point_cloud::{header_line, CloudError, PointSink, ScalarType};

#[derive(Debug, Clone)]
enum Property {
    Scalar { name: String, kind: ScalarType },
    List { count: ScalarType, item: ScalarType },
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// Parses a PLY file's bytes into vertex positions. Non-finite coordinates are an error naming the
/// vertex unless `drop_non_finite`.
pub fn parse_ply(bytes: &[u8], drop_non_finite: bool) -> Result<Vec<[f64; 3]>, CloudError> {
    let mut elements: Vec<Element> = Vec::new();
    let mut binary = None;
    let mut offset = 0;
    let mut line_number = 0;
    loop {
        let line = header_line(bytes, &mut offset, &mut line_number, "end_header")?;
        let header = |reason: String| CloudError::Header { line: line_number, reason };
        if line_number == 1 {
            if line != "ply" {
                return Err(header(format!("starts with {line:?}, not \"ply\"")));
            }
            continue;
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", "ascii", "1.0"] => binary = Some(false),
            ["format", "binary_little_endian", "1.0"] => binary = Some(true),
            ["format", other, ..] => {
                return Err(CloudError::Unsupported(format!("PLY format {other:?} (ascii or binary_little_endian only)")))
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| header(format!("element count {count:?} is not a non-negative integer")))?;
                elements.push(Element { name: (*name).to_string(), count, properties: Vec::new() });
            }
            ["property", "list", count, item, _name] => {
                let element = elements.last_mut().ok_or_else(|| header("property before any element".into()))?;
                let scalar = |t: &str| ScalarType::from_ply(t).ok_or_else(|| CloudError::Unsupported(format!("PLY property type {t:?}")));
                element.properties.push(Property::List { count: scalar(count)?, item: scalar(item)? });
            }
            ["property", kind, name] => {
                let element = elements.last_mut().ok_or_else(|| header("property before any element".into()))?;
                let kind =
                    ScalarType::from_ply(kind).ok_or_else(|| CloudError::Unsupported(format!("PLY property {name:?} of type {kind:?}")))?;
                element.properties.push(Property::Scalar { name: (*name).to_string(), kind });
            }
            ["end_header"] => break,
            _ => return Err(header(format!("cannot read {line:?}"))),
        }
    }
    let binary = binary.ok_or_else(|| CloudError::Header { line: line_number, reason: "no format line".into() })?;
    let vertex_index = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| CloudError::Header { line: line_number, reason: "no vertex element".into() })?;
    let vertex = elements.get(vertex_index).cloned().ok_or(CloudError::Empty)?;
    let mut axes = [None; 3];
    for (i, property) in vertex.properties.iter().enumerate() {
        if let Property::Scalar { name, .. } = property {
            if let Some(axis) = ["x", "y", "z"].iter().position(|a| a == name) {
                axes[axis] = Some(i);
            }
        }
    }
    let [Some(xi), Some(yi), Some(zi)] = axes else {
        return Err(CloudError::Header { line: line_number, reason: "the vertex element lacks x, y or z".into() });
    };
    let data = bytes.get(offset..).unwrap_or(&[]);
    let mut cloud = PointSink::new(vertex.count, drop_non_finite);
    if binary {
        let mut at = 0;
        let truncated = |what: &str| CloudError::Truncated { what: format!("binary data in {what}") };
        let read = |kind: ScalarType, at: &mut usize, what: &str| -> Result<f64, CloudError> {
            let value = kind.read_le(data, *at);
            if data.len() < *at + kind.size() {
                return Err(truncated(what));
            }
            *at += kind.size();
            Ok(value)
        };
        for element in elements.iter().take(vertex_index + 1) {
            let is_vertex = element.name == "vertex";
            for index in 0..element.count {
                let mut values = [f64::NAN; 3];
                for (i, property) in element.properties.iter().enumerate() {
                    let what = format!("element {:?} {index} of {}", element.name, element.count);
                    match property {
                        Property::Scalar { kind, .. } => {
                            let value = read(*kind, &mut at, &what)?;
                            if let Some(axis) = [xi, yi, zi].iter().position(|&a| a == i) {
                                values[axis] = value;
                            }
                        }
                        Property::List { count, item } => {
                            let n = read(*count, &mut at, &what)?;
                            if !(0.0..=1e9).contains(&n) {
                                return Err(CloudError::Unsupported(format!("list length {n} in {what}")));
                            }
                            for _ in 0..n as usize {
                                read(*item, &mut at, &what)?;
                            }
                        }
                    }
                }
                if is_vertex {
                    cloud.push(index, values)?;
                }
            }
        }
    } else {
        let text = std::str::from_utf8(data).map_err(|_| CloudError::Ascii { line: line_number + 1, reason: "not text".into() })?;
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
        // Each element instance is one line; skip those of the elements before `vertex`.
        let skip: usize = elements.iter().take(vertex_index).map(|e| e.count).sum();
        for _ in 0..skip {
            if lines.next().is_none() {
                return Err(CloudError::Truncated { what: "ascii data before the vertices".into() });
            }
        }
        let scalars = vertex.properties.iter().all(|p| matches!(p, Property::Scalar { .. }));
        if !scalars {
            return Err(CloudError::Unsupported("list properties in the vertex element".into()));
        }
        for index in 0..vertex.count {
            let Some((k, line)) = lines.next() else {
                return Err(CloudError::Truncated { what: format!("ascii data: {index} of {} vertices present", vertex.count) });
            };
            let tokens: Vec<&str> = line.split_whitespace().collect();
            if tokens.len() != vertex.properties.len() {
                return Err(CloudError::Ascii {
                    line: line_number + 1 + k,
                    reason: format!("{} values, {} expected", tokens.len(), vertex.properties.len()),
                });
            }
            let value = |i: usize| -> Result<f64, CloudError> {
                let token = tokens.get(i).copied().unwrap_or("");
                token
                    .parse::<f64>()
                    .map_err(|_| CloudError::Ascii { line: line_number + 1 + k, reason: format!("{token:?} is not a number") })
            };
            cloud.push(index, [value(xi)?, value(yi)?, value(zi)?])?;
        }
    }
    Ok(cloud.into_points())
}

/// Writes points as a PLY file (`float x y z`), `ascii` or `binary_little_endian` (tests, tools).
pub fn write_ply(points: &[[f32; 3]], format: &str) -> Result<Vec<u8>, CloudError> {
    let mut out =
        format!("ply\nformat {format} 1.0\ncomment terrain_sim\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n", points.len())
            .into_bytes();
    match format {
        "ascii" => {
            for p in points {
                out.extend_from_slice(format!("{} {} {}\n", p[0], p[1], p[2]).as_bytes());
            }
        }
        "binary_little_endian" => out.extend(points.iter().flat_map(|p| p.iter().flat_map(|c| c.to_le_bytes()))),
        other => return Err(CloudError::Unsupported(format!("PLY format {other:?}"))),
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_formats_read_back() {
        let points: Vec<[f32; 3]> = (0..25).map(|i| [i as f32 * 0.5, -(i as f32) * 0.25, 0.125 * (i % 3) as f32]).collect();
        let expected: Vec<[f64; 3]> = points.iter().map(|p| p.map(f64::from)).collect();
        for format in ["ascii", "binary_little_endian"] {
            assert_eq!(parse_ply(&write_ply(&points, format).unwrap(), false).unwrap(), expected, "{format}");
        }
    }

    #[test]
    fn hand_written_meshes_skip_other_elements() {
        // Binary: a "camera" element with a list before the vertices, double z and a colour, faces after.
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement camera 1\nproperty list uchar int ids\n\
element vertex 2\nproperty uchar red\nproperty float x\nproperty float y\nproperty double z\nelement face 1\n\
property list uchar int vertex_indices\nend_header\n"
            .to_vec();
        bytes.push(2);
        bytes.extend(7i32.to_le_bytes().into_iter().chain(8i32.to_le_bytes()));
        for (r, x, y, z) in [(255u8, 1.0f32, 2.0f32, 3.0f64), (0, -1.0, -2.0, -3.5)] {
            bytes.push(r);
            bytes.extend(x.to_le_bytes().into_iter().chain(y.to_le_bytes()).chain(z.to_le_bytes()));
        }
        bytes.extend([3, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(parse_ply(&bytes, false).unwrap(), vec![[1.0, 2.0, 3.0], [-1.0, -2.0, -3.5]]);
        // Ascii: a face element first (skipped by lines), z before x.
        let text = "ply\nformat ascii 1.0\ncomment hand written\nelement face 1\nproperty list uchar int vertex_indices\n\
element vertex 2\nproperty float z\nproperty float x\nproperty float y\nend_header\n3 0 1 1\n0.5 1 2\n-0.5 3 4\n";
        assert_eq!(parse_ply(text.as_bytes(), false).unwrap(), vec![[1.0, 2.0, 0.5], [3.0, 4.0, -0.5]]);
    }

    #[test]
    fn bad_files_are_errors_naming_the_problem() {
        let message = |bytes: &[u8]| parse_ply(bytes, false).unwrap_err().to_string();
        assert!(message(b"VERSION 0.7\n").contains("not \"ply\""));
        assert!(message(b"ply\nformat binary_big_endian 1.0\nend_header\n").contains("binary_big_endian"));
        assert!(message(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n").contains("before end_header"));
        assert!(message(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n").contains("\"half\""));
        assert!(message(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n")
            .contains("lacks x, y or z"));
        let points = [[0.0f32, 1.0, 2.0]; 3];
        let binary = write_ply(&points, "binary_little_endian").unwrap();
        assert!(message(&binary[..binary.len() - 2]).contains("truncated binary data in element \"vertex\" 2 of 3"));
        let ascii = write_ply(&points, "ascii").unwrap();
        assert!(message(&ascii[..ascii.len() - 6]).contains("2 of 3 vertices"), "{}", message(&ascii[..ascii.len() - 6]));
        let nan = write_ply(&[[0.0, f32::NAN, 0.0]], "binary_little_endian").unwrap();
        assert!(message(&nan).contains("point 0 has a non-finite coordinate"));
        assert_eq!(parse_ply(&nan, true).unwrap(), Vec::<[f64; 3]>::new());
    }
}
