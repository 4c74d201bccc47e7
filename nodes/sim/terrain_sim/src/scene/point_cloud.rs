//! A point cloud as a terrain: its points gridded into a [`Heightfield`] that the camera renders and
//! whose bilinear surface is the ground truth.
//!
//! Why a heightfield rather than splatting the points: the terrain then has one exact surface for
//! rendering *and* for `height_at` / `normal_at` / ray queries (splats would leave the ground truth
//! ambiguous between overlapping discs, and gaps between splats would look like holes at close
//! range); it is also what elevation-mapping stacks build from such clouds. The cost is that a
//! heightfield is 2.5-D: overhangs collapse to their top.
//!
//! Gridding: each point goes to its nearest grid sample (grid aligned to multiples of the resolution
//! in the world frame); a sample's height is the highest of its points ([`CellHeight::Max`], the top a
//! foot would stand on and what a camera looking down sees; walls fold into their top edge) or their
//! mean ([`CellHeight::Mean`], for noisy scans of flat ground). Samples with no point are filled by
//! the mean of their valid 8-neighbours when at least three exist, `fill_passes` times, which closes
//! the gaps of a sparse scan without extrapolating past its border; what remains empty is a hole.

use serde::{Deserialize, Serialize};

use super::heightfield::{Heightfield, HeightfieldError};
use super::lzf::LzfError;

/// Why a point cloud file cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    #[error("header line {line}: {reason}")]
    Header { line: usize, reason: String },
    #[error("unsupported: {0}")]
    Unsupported(String),
    #[error("truncated {what}")]
    Truncated { what: String },
    #[error("line {line}: {reason}")]
    Ascii { line: usize, reason: String },
    #[error("point {point} has a non-finite coordinate {value:?}")]
    NonFinite { point: usize, value: [f64; 3] },
    #[error("compressed data: {0}")]
    Lzf(#[from] LzfError),
    #[error("the cloud has no points")]
    Empty,
    #[error("the cloud spans {columns} × {rows} samples at {resolution_m} m, more than the {max} allowed (raise the resolution)")]
    TooLarge { columns: usize, rows: usize, resolution_m: f64, max: usize },
    #[error(transparent)]
    Heightfield(#[from] HeightfieldError),
}

/// The next line of a text header that starts at `*offset`, trimmed; `offset` moves past it and
/// `line_number` counts it. `missing` names what a header that ends first lacks.
pub(super) fn header_line<'a>(bytes: &'a [u8], offset: &mut usize, line_number: &mut usize, missing: &str) -> Result<&'a str, CloudError> {
    *line_number += 1;
    let line = *line_number;
    let Some(end) = bytes.get(*offset..).and_then(|rest| rest.iter().position(|&b| b == b'\n')) else {
        return Err(CloudError::Header { line, reason: format!("the header ends before {missing}") });
    };
    let text = std::str::from_utf8(bytes.get(*offset..*offset + end).unwrap_or(&[]))
        .map_err(|_| CloudError::Header { line, reason: "not text".into() })?
        .trim();
    *offset += end + 1;
    Ok(text)
}

/// The points of a cloud file in file order, as its reader finds them: a point with a non-finite
/// coordinate is skipped when `drop_non_finite`, and an error naming it otherwise.
pub(super) struct PointSink {
    points: Vec<[f64; 3]>,
    drop_non_finite: bool,
}

impl PointSink {
    pub(super) fn new(capacity: usize, drop_non_finite: bool) -> Self {
        Self { points: Vec::with_capacity(capacity), drop_non_finite }
    }

    /// Point number `index` of the file.
    pub(super) fn push(&mut self, index: usize, p: [f64; 3]) -> Result<(), CloudError> {
        if p.iter().all(|c| c.is_finite()) {
            self.points.push(p);
        } else if !self.drop_non_finite {
            return Err(CloudError::NonFinite { point: index, value: p });
        }
        Ok(())
    }

    pub(super) fn into_points(self) -> Vec<[f64; 3]> {
        self.points
    }
}

/// Scalar types of PCD fields and PLY properties.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl ScalarType {
    /// PCD `TYPE` letter and `SIZE`.
    pub fn from_pcd(kind: char, size: usize) -> Option<Self> {
        Some(match (kind, size) {
            ('I', 1) => Self::I8,
            ('U', 1) => Self::U8,
            ('I', 2) => Self::I16,
            ('U', 2) => Self::U16,
            ('I', 4) => Self::I32,
            ('U', 4) => Self::U32,
            ('I', 8) => Self::I64,
            ('U', 8) => Self::U64,
            ('F', 4) => Self::F32,
            ('F', 8) => Self::F64,
            _ => return None,
        })
    }

    /// PLY property type name.
    pub fn from_ply(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    pub fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::I64 | Self::U64 | Self::F64 => 8,
        }
    }

    /// The little-endian value at `bytes[at..]` (NaN if out of bounds; callers check lengths first).
    pub fn read_le(self, bytes: &[u8], at: usize) -> f64 {
        let Some(b) = bytes.get(at..at + self.size()) else {
            return f64::NAN;
        };
        let mut word = [0u8; 8];
        if let Some(head) = word.get_mut(..b.len()) {
            head.copy_from_slice(b);
        }
        match self {
            Self::I8 => f64::from(word[0] as i8),
            Self::U8 => f64::from(word[0]),
            Self::I16 => f64::from(i16::from_le_bytes([word[0], word[1]])),
            Self::U16 => f64::from(u16::from_le_bytes([word[0], word[1]])),
            Self::I32 => f64::from(i32::from_le_bytes([word[0], word[1], word[2], word[3]])),
            Self::U32 => f64::from(u32::from_le_bytes([word[0], word[1], word[2], word[3]])),
            Self::I64 => i64::from_le_bytes(word) as f64,
            Self::U64 => u64::from_le_bytes(word) as f64,
            Self::F32 => f64::from(f32::from_le_bytes([word[0], word[1], word[2], word[3]])),
            Self::F64 => f64::from_le_bytes(word),
        }
    }
}

/// Which height a grid sample takes from the points nearest to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CellHeight {
    /// The highest point (the top surface).
    #[default]
    Max,
    /// The mean of the points.
    Mean,
}

/// Largest grid [`grid_points`] builds (samples), ≈ 64 MB of f32.
pub const MAX_SAMPLES: usize = 16_000_000;

/// Grids `points` into a heightfield at `resolution_m` (see the module docs).
pub fn grid_points(points: &[[f64; 3]], resolution_m: f64, cell: CellHeight, fill_passes: usize) -> Result<Heightfield, CloudError> {
    if !(resolution_m.is_finite() && resolution_m > 0.0) {
        return Err(HeightfieldError::Resolution(resolution_m).into());
    }
    if points.is_empty() {
        return Err(CloudError::Empty);
    }
    let index = |v: f64| (v / resolution_m).round();
    let (mut min, mut max) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in points {
        for axis in 0..2 {
            let k = index(p[axis]);
            min[axis] = min[axis].min(k);
            max[axis] = max[axis].max(k);
        }
    }
    // At least 2 × 2 samples.
    let columns = ((max[0] - min[0]) as usize + 1).max(2);
    let rows = ((max[1] - min[1]) as usize + 1).max(2);
    if columns.saturating_mul(rows) > MAX_SAMPLES {
        return Err(CloudError::TooLarge { columns, rows, resolution_m, max: MAX_SAMPLES });
    }
    let mut sum = vec![0.0f64; columns * rows];
    let mut count = vec![0u32; columns * rows];
    let mut top = vec![f64::NEG_INFINITY; columns * rows];
    for p in points {
        let (i, j) = ((index(p[0]) - min[0]) as usize, (index(p[1]) - min[1]) as usize);
        let k = j * columns + i;
        if let (Some(s), Some(c), Some(t)) = (sum.get_mut(k), count.get_mut(k), top.get_mut(k)) {
            *s += p[2];
            *c += 1;
            *t = t.max(p[2]);
        }
    }
    let mut heights: Vec<f32> = (0..columns * rows)
        .map(|k| match (count.get(k).copied().unwrap_or(0), cell) {
            (0, _) => f32::NAN,
            (_, CellHeight::Max) => top.get(k).copied().unwrap_or(f64::NAN) as f32,
            (n, CellHeight::Mean) => (sum.get(k).copied().unwrap_or(f64::NAN) / f64::from(n)) as f32,
        })
        .collect();
    for _ in 0..fill_passes {
        let before = heights.clone();
        let mut changed = false;
        for j in 0..rows {
            for i in 0..columns {
                if before.get(j * columns + i).is_some_and(|h| !h.is_nan()) {
                    continue;
                }
                let (mut total, mut n) = (0.0f64, 0);
                for (di, dj) in [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                    let (ni, nj) = (i as isize + di, j as isize + dj);
                    if ni < 0 || nj < 0 || ni as usize >= columns || nj as usize >= rows {
                        continue;
                    }
                    if let Some(h) = before.get(nj as usize * columns + ni as usize).filter(|h| !h.is_nan()) {
                        total += f64::from(*h);
                        n += 1;
                    }
                }
                if n >= 3 {
                    if let Some(h) = heights.get_mut(j * columns + i) {
                        *h = (total / f64::from(n)) as f32;
                        changed = true;
                    }
                }
            }
        }
        if !changed {
            break;
        }
    }
    Ok(Heightfield::new(columns, rows, resolution_m, [min[0] * resolution_m, min[1] * resolution_m], heights)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gridding_takes_the_top_and_fills_small_gaps() {
        // A 1 m × 0.5 m plane z = 0.1 x at 1 cm spacing, minus one sample, plus a point under the
        // surface at (0.5, 0.25) that Max ignores and Mean averages in.
        let mut points: Vec<[f64; 3]> = Vec::new();
        for j in 0..=50 {
            for i in 0..=100 {
                if (i, j) != (30, 20) {
                    let (x, y) = (i as f64 * 0.01, j as f64 * 0.01);
                    points.push([x, y, 0.1 * x]);
                }
            }
        }
        points.push([0.501, 0.249, -1.0]);
        let field = grid_points(&points, 0.01, CellHeight::Max, 1).unwrap();
        assert_eq!((field.columns(), field.rows()), (101, 51));
        assert!((field.height_at(0.5, 0.25).unwrap() - 0.05).abs() < 1e-6);
        // The missing sample was filled from its neighbours (mean of a plane = the plane).
        assert!((field.height_at(0.3, 0.2).unwrap() - 0.03).abs() < 1e-6);
        assert!((field.normal_at(0.77, 0.1).unwrap() - nalgebra::Vector3::new(-0.1, 0.0, 1.0).normalize()).norm() < 1e-5);
        let mean = grid_points(&points, 0.01, CellHeight::Mean, 0).unwrap();
        assert!((mean.height_at(0.5, 0.25).unwrap() - (0.05 - 1.0) / 2.0).abs() < 1e-6);
        assert_eq!(mean.height_at(0.3, 0.2), None, "no fill pass: a hole");
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert_eq!(grid_points(&[], 0.01, CellHeight::Max, 0), Err(CloudError::Empty));
        assert!(matches!(grid_points(&[[0.0; 3]], -1.0, CellHeight::Max, 0), Err(CloudError::Heightfield(_))));
        assert!(matches!(grid_points(&[[0.0; 3], [1e3, 1e3, 0.0]], 0.01, CellHeight::Max, 0), Err(CloudError::TooLarge { .. })));
        // A single point: 2 × 2 grid with three holes → no surface.
        assert_eq!(grid_points(&[[0.0; 3]], 0.01, CellHeight::Max, 0), Err(CloudError::Heightfield(HeightfieldError::NoSurface)));
        let value = ScalarType::I16.read_le(&[0xff, 0xff], 0);
        assert_eq!(value, -1.0);
        assert!(ScalarType::F64.read_le(&[0; 4], 0).is_nan());
    }
}
