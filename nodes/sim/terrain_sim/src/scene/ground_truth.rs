//! A terrain's ground truth on disk, next to a dataset, so benches in other crates can re-load the
//! exact surface the simulator rendered: the heightfield's samples as raw little-endian 32-bit floats
//! (`terrain_heights.f32`, row-major, NaN = hole) and a JSON descriptor (`terrain.json`) with the
//! frame, grid size, resolution and origin. [`read_ground_truth`] gives back a [`Heightfield`]
//! bit-identical to the one written, so `height_at`, `normal_at` and ray intersection match the
//! simulator's exactly.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::heightfield::{Heightfield, HeightfieldError};

/// File name of the descriptor [`write_ground_truth`] writes.
pub const DESCRIPTOR_FILE: &str = "terrain.json";
/// File name of the samples [`write_ground_truth`] writes.
pub const HEIGHTS_FILE: &str = "terrain_heights.f32";
/// `format` value of the descriptor.
pub const FORMAT: &str = "patchwalk_heightfield";

/// Errors writing or reading a ground-truth heightfield.
#[derive(Debug, thiserror::Error)]
pub enum GroundTruthError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a heightfield descriptor: {reason}")]
    Descriptor { path: PathBuf, reason: String },
    #[error("{path}: {expected} bytes expected ({columns} × {rows} float32), the file has {got}")]
    Size { path: PathBuf, expected: u64, got: u64, columns: usize, rows: usize },
    #[error("{path}: {source}")]
    Heightfield { path: PathBuf, source: HeightfieldError },
}

/// The descriptor (`terrain.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundTruthDescriptor {
    /// Always [`FORMAT`].
    pub format: String,
    pub version: u32,
    /// Frame of the heights and the grid: the simulator's `world` (gravity aligned, z up, metres).
    pub frame: String,
    /// Samples along x and y.
    pub columns: usize,
    pub rows: usize,
    /// Grid spacing (m).
    pub resolution_m: f64,
    /// World `(x, y)` of sample (0, 0).
    pub origin_m: [f64; 2],
    /// Lowest and highest height (m).
    pub z_range_m: [f64; 2],
    /// Samples file, relative to the descriptor.
    pub heights_file: String,
    /// `float32_le`.
    pub dtype: String,
    /// How samples map to the world.
    pub layout: String,
    /// Surface between samples: `bilinear`.
    pub surface: String,
    /// Where the terrain came from (file and parameters), free text.
    pub source: String,
}

/// Paths [`write_ground_truth`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GroundTruthFiles {
    pub descriptor: PathBuf,
    pub heights: PathBuf,
}

/// Writes `field` into `dir` as [`DESCRIPTOR_FILE`] + [`HEIGHTS_FILE`] (the directory must exist).
pub fn write_ground_truth(field: &Heightfield, dir: &Path, source: &str) -> Result<GroundTruthFiles, GroundTruthError> {
    let heights = dir.join(HEIGHTS_FILE);
    let descriptor = dir.join(DESCRIPTOR_FILE);
    let bytes: Vec<u8> = field.heights_m().iter().flat_map(|h| h.to_le_bytes()).collect();
    std::fs::write(&heights, bytes).map_err(|source| GroundTruthError::Io { path: heights.clone(), source })?;
    let meta = GroundTruthDescriptor {
        format: FORMAT.into(),
        version: 1,
        frame: "world".into(),
        columns: field.columns(),
        rows: field.rows(),
        resolution_m: field.resolution_m(),
        origin_m: field.origin_m(),
        z_range_m: field.z_range_m(),
        heights_file: HEIGHTS_FILE.into(),
        dtype: "float32_le".into(),
        layout:
            "row-major, row 0 first; sample (i, j) at x = origin_m[0] + i*resolution_m, y = origin_m[1] + j*resolution_m; z up; NaN = hole"
                .into(),
        surface: "bilinear".into(),
        source: source.into(),
    };
    let text = serde_json::to_string_pretty(&meta)
        .map_err(|error| GroundTruthError::Descriptor { path: descriptor.clone(), reason: error.to_string() })?;
    std::fs::write(&descriptor, text).map_err(|source| GroundTruthError::Io { path: descriptor.clone(), source })?;
    Ok(GroundTruthFiles { descriptor, heights })
}

/// Reads a heightfield written by [`write_ground_truth`] from its descriptor (or from the directory
/// holding [`DESCRIPTOR_FILE`]).
pub fn read_ground_truth(path: &Path) -> Result<Heightfield, GroundTruthError> {
    Ok(read_ground_truth_with_descriptor(path)?.0)
}

/// [`read_ground_truth`], also returning the descriptor.
pub fn read_ground_truth_with_descriptor(path: &Path) -> Result<(Heightfield, GroundTruthDescriptor), GroundTruthError> {
    let descriptor_path = if path.is_dir() { path.join(DESCRIPTOR_FILE) } else { path.to_path_buf() };
    let text =
        std::fs::read_to_string(&descriptor_path).map_err(|source| GroundTruthError::Io { path: descriptor_path.clone(), source })?;
    let bad = |reason: String| GroundTruthError::Descriptor { path: descriptor_path.clone(), reason };
    let meta: GroundTruthDescriptor = serde_json::from_str(&text).map_err(|error| bad(error.to_string()))?;
    if meta.format != FORMAT || meta.version != 1 {
        return Err(bad(format!("format {:?} version {} (expected {FORMAT:?} version 1)", meta.format, meta.version)));
    }
    if meta.dtype != "float32_le" || meta.surface != "bilinear" {
        return Err(bad(format!("dtype {:?} / surface {:?} (expected float32_le / bilinear)", meta.dtype, meta.surface)));
    }
    let heights_path = descriptor_path.parent().unwrap_or(Path::new(".")).join(&meta.heights_file);
    let bytes = std::fs::read(&heights_path).map_err(|source| GroundTruthError::Io { path: heights_path.clone(), source })?;
    let expected = (meta.columns as u64).saturating_mul(meta.rows as u64).saturating_mul(4);
    if bytes.len() as u64 != expected {
        return Err(GroundTruthError::Size {
            path: heights_path,
            expected,
            got: bytes.len() as u64,
            columns: meta.columns,
            rows: meta.rows,
        });
    }
    let heights = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    let field = Heightfield::new(meta.columns, meta.rows, meta.resolution_m, meta.origin_m, heights)
        .map_err(|source| GroundTruthError::Heightfield { path: heights_path, source })?;
    Ok((field, meta))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::heightfield::tests::tilted_plane;

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let mut heights = tilted_plane().heights_m().to_vec();
        heights[3] = f32::NAN;
        let field = Heightfield::new(21, 11, 0.05, [-0.5, -0.25], heights).unwrap();
        let files = write_ground_truth(&field, dir.path(), "test plane").unwrap();
        assert_eq!(files.descriptor, dir.path().join("terrain.json"));
        let (back, meta) = read_ground_truth_with_descriptor(dir.path()).unwrap();
        assert_eq!(meta.source, "test plane");
        assert_eq!(meta.frame, "world");
        assert_eq!((back.columns(), back.rows(), back.resolution_m(), back.origin_m()), (21, 11, 0.05, [-0.5, -0.25]));
        let same = back.heights_m().iter().zip(field.heights_m()).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same);
        assert_eq!(back.height_at(0.1, 0.1), field.height_at(0.1, 0.1));
    }

    #[test]
    fn damaged_files_are_named_errors() {
        let dir = tempfile::tempdir().unwrap();
        write_ground_truth(&tilted_plane(), dir.path(), "plane").unwrap();
        // Truncated samples.
        let heights = dir.path().join(HEIGHTS_FILE);
        let bytes = std::fs::read(&heights).unwrap();
        std::fs::write(&heights, &bytes[..bytes.len() - 4]).unwrap();
        let error = read_ground_truth(dir.path()).unwrap_err().to_string();
        assert!(error.contains("924 bytes expected") && error.contains("920"), "{error}");
        // Wrong format name.
        let descriptor = dir.path().join(DESCRIPTOR_FILE);
        let text = std::fs::read_to_string(&descriptor).unwrap().replace(FORMAT, "other");
        std::fs::write(&descriptor, text).unwrap();
        let error = read_ground_truth(&descriptor).unwrap_err().to_string();
        assert!(error.contains("not a heightfield descriptor") && error.contains("\"other\""), "{error}");
        assert!(matches!(read_ground_truth(&dir.path().join("missing.json")), Err(GroundTruthError::Io { .. })));
    }
}
