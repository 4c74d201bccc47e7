//! Bring-your-own terrain: which file to load and how (`scene.terrain` in the config), dispatching
//! on the file's extension to the heightmap reader (`.png`) or a point-cloud reader (`.pcd`,
//! `.ply`) followed by gridding, and the errors naming the file.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::heightfield::Heightfield;
use super::heightmap_png::{decode_heightmap, HeightmapError, HeightmapScale};
use super::pcd::parse_pcd;
use super::ply::parse_ply;
use super::point_cloud::{grid_points, CellHeight, CloudError};

/// A terrain file and how to read it. An empty `path` means the built-in rock scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TerrainConfig {
    /// `.png` heightmap, `.pcd` or `.ply` point cloud (metres, z up); empty = table and rocks.
    pub path: PathBuf,
    /// Heightmaps: distance between pixel centres (m).
    pub metres_per_pixel: f64,
    /// Heightmaps: height of grey level 0 and of the largest level (m).
    pub height_min_m: f64,
    pub height_max_m: f64,
    /// Heightmaps: world `(x, y)` of the bottom-left pixel (m). Point clouds keep their coordinates.
    pub origin_m: [f64; 2],
    /// Heightmaps: alpha 0 = hole (else alpha is ignored).
    pub alpha_is_mask: bool,
    /// Point clouds: grid spacing of the heightfield the points are gridded into (m).
    pub cloud_resolution_m: f64,
    /// Point clouds: a grid sample's height from its points, `max` (top surface) or `mean`.
    pub cloud_cell_height: CellHeight,
    /// Point clouds: passes of filling empty samples from their neighbours.
    pub cloud_fill_passes: usize,
    /// Point clouds: skip points with NaN/inf coordinates instead of rejecting the file.
    pub drop_non_finite: bool,
}

impl Default for TerrainConfig {
    fn default() -> Self {
        let png = HeightmapScale::default();
        Self {
            path: PathBuf::new(),
            metres_per_pixel: png.metres_per_pixel,
            height_min_m: png.height_min_m,
            height_max_m: png.height_max_m,
            origin_m: png.origin_m,
            alpha_is_mask: png.alpha_is_mask,
            cloud_resolution_m: 0.02,
            cloud_cell_height: CellHeight::Max,
            cloud_fill_passes: 2,
            drop_non_finite: false,
        }
    }
}

/// Why a terrain file cannot be loaded (always names the file).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TerrainError {
    #[error("terrain {path}: {reason}")]
    Io { path: PathBuf, reason: String },
    #[error("terrain {path}: {source}")]
    Heightmap { path: PathBuf, source: HeightmapError },
    #[error("terrain {path}: {source}")]
    Cloud { path: PathBuf, source: CloudError },
    #[error("terrain {path}: unknown file type (expected .png, .pcd or .ply)")]
    UnknownKind { path: PathBuf },
}

/// The kinds of terrain file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TerrainKind {
    Heightmap,
    Pcd,
    Ply,
}

impl TerrainConfig {
    /// Whether a terrain file is configured.
    pub fn is_set(&self) -> bool {
        !self.path.as_os_str().is_empty()
    }

    /// The kind of `path`, from its extension.
    pub fn kind(&self) -> Result<TerrainKind, TerrainError> {
        let extension = self.path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("png") => Ok(TerrainKind::Heightmap),
            Some("pcd") => Ok(TerrainKind::Pcd),
            Some("ply") => Ok(TerrainKind::Ply),
            _ => Err(TerrainError::UnknownKind { path: self.path.clone() }),
        }
    }

    /// The heightmap parameters of this config.
    pub fn heightmap_scale(&self) -> HeightmapScale {
        HeightmapScale {
            metres_per_pixel: self.metres_per_pixel,
            height_min_m: self.height_min_m,
            height_max_m: self.height_max_m,
            origin_m: self.origin_m,
            alpha_is_mask: self.alpha_is_mask,
        }
    }

    /// One line saying what was loaded and how (for ground-truth descriptors and logs).
    pub fn describe(&self) -> String {
        match self.kind() {
            Ok(TerrainKind::Heightmap) => format!(
                "heightmap {} at {} m/px, levels → {}..{} m, origin ({}, {}), bilinear",
                self.path.display(),
                self.metres_per_pixel,
                self.height_min_m,
                self.height_max_m,
                self.origin_m[0],
                self.origin_m[1]
            ),
            Ok(_) => format!(
                "point cloud {} gridded at {} m ({:?} per sample, {} fill passes), bilinear",
                self.path.display(),
                self.cloud_resolution_m,
                self.cloud_cell_height,
                self.cloud_fill_passes
            ),
            Err(_) => format!("unknown terrain {}", self.path.display()),
        }
    }

    /// Loads the terrain file into a heightfield.
    pub fn load(&self) -> Result<Heightfield, TerrainError> {
        let kind = self.kind()?;
        let bytes = std::fs::read(&self.path).map_err(|e| TerrainError::Io { path: self.path.clone(), reason: e.to_string() })?;
        self.load_bytes(kind, &bytes)
    }

    /// Loads a terrain from the bytes of a file of `kind` (errors name `path`).
    pub fn load_bytes(&self, kind: TerrainKind, bytes: &[u8]) -> Result<Heightfield, TerrainError> {
        let path = self.path.clone();
        let cloud = |points: Result<Vec<[f64; 3]>, CloudError>, path: &Path| {
            points
                .and_then(|points| grid_points(&points, self.cloud_resolution_m, self.cloud_cell_height, self.cloud_fill_passes))
                .map_err(|source| TerrainError::Cloud { path: path.to_path_buf(), source })
        };
        match kind {
            TerrainKind::Heightmap => {
                decode_heightmap(bytes, &self.heightmap_scale()).map_err(|source| TerrainError::Heightmap { path, source })
            }
            TerrainKind::Pcd => cloud(parse_pcd(bytes, self.drop_non_finite), &path),
            TerrainKind::Ply => cloud(parse_ply(bytes, self.drop_non_finite), &path),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::pcd::write_pcd;
    use crate::scene::ply::write_ply;

    #[test]
    fn files_load_by_extension_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let points: Vec<[f32; 3]> = (0..=20).flat_map(|j| (0..=20).map(move |i| [i as f32 * 0.02, j as f32 * 0.02, 0.05])).collect();
        for (name, bytes) in
            [("a.pcd", write_pcd(&points, "binary_compressed").unwrap()), ("b.PLY", write_ply(&points, "binary_little_endian").unwrap())]
        {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap();
            let config = TerrainConfig { path, ..TerrainConfig::default() };
            let field = config.load().unwrap();
            assert_eq!((field.columns(), field.rows()), (21, 21), "{name}");
            assert!((field.height_at(0.2, 0.2).unwrap() - 0.05).abs() < 1e-6);
            assert!(config.describe().contains("point cloud"));
        }
        let missing = TerrainConfig { path: dir.path().join("none.png"), ..TerrainConfig::default() };
        let error = missing.load().unwrap_err().to_string();
        assert!(error.contains("none.png"), "{error}");
        let unknown = TerrainConfig { path: dir.path().join("x.obj"), ..TerrainConfig::default() };
        assert!(matches!(unknown.load(), Err(TerrainError::UnknownKind { .. })));
        let bad = dir.path().join("bad.pcd");
        std::fs::write(&bad, b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 9\nDATA binary\n\x00").unwrap();
        let error = TerrainConfig { path: bad, ..TerrainConfig::default() }.load().unwrap_err().to_string();
        assert!(error.contains("bad.pcd") && error.contains("truncated"), "{error}");
        assert!(!TerrainConfig::default().is_set());
    }
}
