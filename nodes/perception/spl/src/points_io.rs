//! Point files for the CLI: CSV (`x,y,z` or `x,y,z,cxx,cyy,czz,cxy,cyz,cxz`) and PLY (ascii or binary,
//! vertex element with float/double `x, y, z`).

use nalgebra::{Matrix3, Vector3};
use std::path::Path;

/// Points read from a file, with per-point covariances when the file has them.
#[derive(Clone, Debug, PartialEq)]
pub struct PointSet {
    /// The points.
    pub points: Vec<Vector3<f64>>,
    /// Per-point covariances (CSV with 9 columns, or PLY with `cxx … cxz` vertex properties).
    pub covariances: Option<Vec<Matrix3<f64>>>,
}

/// Errors reading point files.
#[derive(Debug, thiserror::Error)]
pub enum PointsError {
    /// The file could not be read.
    #[error("cannot read {path}")]
    Io { path: String, source: std::io::Error },
    /// A malformed CSV line.
    #[error("line {line}: {message}")]
    Csv { line: usize, message: String },
    /// A malformed PLY file.
    #[error("PLY: {0}")]
    Ply(String),
    /// No points in the file.
    #[error("the file contains no points")]
    Empty,
}

/// Read a point file; PLY if it starts with `ply`, CSV otherwise.
pub fn read_points(path: &Path) -> Result<PointSet, PointsError> {
    let bytes = std::fs::read(path).map_err(|source| PointsError::Io { path: path.display().to_string(), source })?;
    if bytes.starts_with(b"ply") {
        parse_ply(&bytes)
    } else {
        parse_csv(&String::from_utf8_lossy(&bytes))
    }
}

fn covariance_from(c: &[f64]) -> Matrix3<f64> {
    // cxx, cyy, czz, cxy, cyz, cxz
    let g = |i: usize| c.get(i).copied().unwrap_or(0.0);
    Matrix3::new(g(0), g(3), g(5), g(3), g(1), g(4), g(5), g(4), g(2))
}

/// Parse CSV text: one point per line, 3 or 9 comma-separated numbers; `#` comments, blank lines
/// and one leading header line are skipped.
pub fn parse_csv(text: &str) -> Result<PointSet, PointsError> {
    let mut points = Vec::new();
    let mut covs = Vec::new();
    let mut columns: Option<usize> = None;
    let mut seen_data = false;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let values: Result<Vec<f64>, _> = fields.iter().map(|f| f.parse::<f64>()).collect();
        let values = match values {
            Ok(v) => v,
            Err(_) if !seen_data && points.is_empty() && columns.is_none() => {
                // Header line.
                columns = Some(fields.len());
                continue;
            }
            Err(e) => return Err(PointsError::Csv { line: i + 1, message: format!("not a number ({e}): {line}") }),
        };
        seen_data = true;
        if values.len() != 3 && values.len() != 9 {
            return Err(PointsError::Csv { line: i + 1, message: format!("expected 3 or 9 values, got {}", values.len()) });
        }
        match columns {
            Some(c) if c != values.len() && !points.is_empty() => {
                return Err(PointsError::Csv {
                    line: i + 1,
                    message: format!("expected {c} values like the previous lines, got {}", values.len()),
                })
            }
            _ => columns = Some(values.len()),
        }
        points.push(Vector3::new(values[0], values[1], values[2]));
        if values.len() == 9 {
            covs.push(covariance_from(values.get(3..).unwrap_or_default()));
        }
    }
    if points.is_empty() {
        return Err(PointsError::Empty);
    }
    let covariances = if covs.len() == points.len() { Some(covs) } else { None };
    Ok(PointSet { points, covariances })
}

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

fn type_size(t: &str) -> Option<usize> {
    match t {
        "char" | "uchar" | "int8" | "uint8" => Some(1),
        "short" | "ushort" | "int16" | "uint16" => Some(2),
        "int" | "uint" | "float" | "int32" | "uint32" | "float32" => Some(4),
        "double" | "float64" => Some(8),
        _ => None,
    }
}

fn read_scalar(bytes: &[u8], t: &str, format: Format) -> Option<f64> {
    macro_rules! rd {
        ($ty:ty, $n:expr) => {{
            let arr: [u8; $n] = bytes.get(..$n)?.try_into().ok()?;
            Some(if format == Format::BinaryLe { <$ty>::from_le_bytes(arr) } else { <$ty>::from_be_bytes(arr) } as f64)
        }};
    }
    match t {
        "char" | "int8" => rd!(i8, 1),
        "uchar" | "uint8" => rd!(u8, 1),
        "short" | "int16" => rd!(i16, 2),
        "ushort" | "uint16" => rd!(u16, 2),
        "int" | "int32" => rd!(i32, 4),
        "uint" | "uint32" => rd!(u32, 4),
        "float" | "float32" => rd!(f32, 4),
        "double" | "float64" => rd!(f64, 8),
        _ => None,
    }
}

/// Parse a PLY file whose first element is `vertex` with scalar properties including `x, y, z`.
pub fn parse_ply(bytes: &[u8]) -> Result<PointSet, PointsError> {
    let header_end = bytes.windows(10).position(|w| w == b"end_header").ok_or_else(|| PointsError::Ply("missing end_header".into()))?;
    let header = String::from_utf8_lossy(bytes.get(..header_end).unwrap_or_default()).to_string();
    let after = header_end + "end_header".len();
    let body_start = bytes
        .get(after..)
        .and_then(|rest| rest.iter().position(|b| *b == b'\n'))
        .map(|p| after + p + 1)
        .ok_or_else(|| PointsError::Ply("missing newline after end_header".into()))?;
    let mut format = None;
    let mut count = None;
    let mut props: Vec<(String, String)> = Vec::new();
    let mut in_vertex = false;
    let mut first_element = true;
    for line in header.lines().map(str::trim) {
        let parts: Vec<&str> = line.split_whitespace().collect();
        match parts.as_slice() {
            ["format", "ascii", ..] => format = Some(Format::Ascii),
            ["format", "binary_little_endian", ..] => format = Some(Format::BinaryLe),
            ["format", "binary_big_endian", ..] => format = Some(Format::BinaryBe),
            ["element", name, n] => {
                if *name == "vertex" {
                    if !first_element {
                        return Err(PointsError::Ply("the vertex element must come first".into()));
                    }
                    count = Some(n.parse::<usize>().map_err(|_| PointsError::Ply(format!("bad vertex count {n}")))?);
                    in_vertex = true;
                } else {
                    in_vertex = false;
                }
                first_element = false;
            }
            ["property", "list", ..] if in_vertex => return Err(PointsError::Ply("list properties in vertex are not supported".into())),
            ["property", ty, name] if in_vertex => {
                if type_size(ty).is_none() {
                    return Err(PointsError::Ply(format!("unknown property type {ty}")));
                }
                props.push((ty.to_string(), name.to_string()));
            }
            _ => {}
        }
    }
    let format = format.ok_or_else(|| PointsError::Ply("missing format line".into()))?;
    let count = count.ok_or_else(|| PointsError::Ply("no vertex element".into()))?;
    let index = |n: &str| props.iter().position(|(_, p)| p == n);
    let (Some(ix), Some(iy), Some(iz)) = (index("x"), index("y"), index("z")) else {
        return Err(PointsError::Ply("vertex needs x, y, z properties".into()));
    };
    let cov_idx: Option<Vec<usize>> = ["cxx", "cyy", "czz", "cxy", "cyz", "cxz"].iter().map(|n| index(n)).collect();
    let mut rows: Vec<Vec<f64>> = Vec::with_capacity(count.min(10_000_000));
    let body = bytes.get(body_start..).unwrap_or_default();
    match format {
        Format::Ascii => {
            let text = String::from_utf8_lossy(body);
            for line in text.lines().filter(|l| !l.trim().is_empty()).take(count) {
                let vals: Result<Vec<f64>, _> = line.split_whitespace().map(str::parse::<f64>).collect();
                let vals = vals.map_err(|e| PointsError::Ply(format!("bad vertex line '{line}': {e}")))?;
                if vals.len() < props.len() {
                    return Err(PointsError::Ply(format!("vertex line has {} values, expected {}", vals.len(), props.len())));
                }
                rows.push(vals);
            }
        }
        Format::BinaryLe | Format::BinaryBe => {
            let stride: usize = props.iter().filter_map(|(t, _)| type_size(t)).sum();
            for v in 0..count {
                let mut off = v * stride;
                let mut vals = Vec::with_capacity(props.len());
                for (t, _) in &props {
                    let s = type_size(t).unwrap_or(0);
                    let value =
                        body.get(off..).and_then(|b| read_scalar(b, t, format)).ok_or_else(|| PointsError::Ply("file truncated".into()))?;
                    vals.push(value);
                    off += s;
                }
                rows.push(vals);
            }
        }
    }
    if rows.len() < count {
        return Err(PointsError::Ply(format!("expected {count} vertices, found {}", rows.len())));
    }
    if rows.is_empty() {
        return Err(PointsError::Empty);
    }
    let get = |r: &Vec<f64>, i: usize| r.get(i).copied().unwrap_or(f64::NAN);
    let points = rows.iter().map(|r| Vector3::new(get(r, ix), get(r, iy), get(r, iz))).collect();
    let covariances =
        cov_idx.map(|idx| rows.iter().map(|r| covariance_from(&idx.iter().map(|&i| get(r, i)).collect::<Vec<_>>())).collect());
    Ok(PointSet { points, covariances })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_with_header_comments_and_covariances() {
        let text = "# points\nx,y,z\n0,0,1\n0.1, 0.2 ,1.1\n";
        let p = parse_csv(text).unwrap();
        assert_eq!(p.points.len(), 2);
        assert!(p.covariances.is_none());
        let text9 = "1,2,3,1e-6,2e-6,3e-6,1e-7,2e-7,3e-7\n";
        let p = parse_csv(text9).unwrap();
        let c = p.covariances.unwrap()[0];
        assert_eq!((c[(0, 1)], c[(1, 2)], c[(0, 2)], c[(2, 2)]), (1e-7, 2e-7, 3e-7, 3e-6));
        assert!(matches!(parse_csv("1,2\n"), Err(PointsError::Csv { line: 1, .. })));
        assert!(matches!(parse_csv("1,2,3\n1,2,x\n"), Err(PointsError::Csv { line: 2, .. })));
        assert!(matches!(parse_csv("# nothing\n"), Err(PointsError::Empty)));
    }

    #[test]
    fn ply_ascii_and_binary() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n0 0 1 255\n0.5 0.25 2 0\n";
        let p = parse_ply(ascii).unwrap();
        assert_eq!(p.points, vec![Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.5, 0.25, 2.0)]);
        let mut bin =
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty float z\nend_header\n"
                .to_vec();
        for (x, y, z) in [(1.0f64, 2.0f64, 3.0f32), (-1.0, 0.5, 0.25)] {
            bin.extend(x.to_le_bytes());
            bin.extend(y.to_le_bytes());
            bin.extend(z.to_le_bytes());
        }
        let p = parse_ply(&bin).unwrap();
        assert_eq!(p.points[1], Vector3::new(-1.0, 0.5, 0.25));
        assert!(parse_ply(&bin[..bin.len() - 3]).is_err());
        assert!(parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n").is_err());
    }
}
