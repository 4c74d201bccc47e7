//! The planning graph's vertices (CNN IV: "a 60 × 80 grid corresponding to pixels of a downsampled
//! RGB-D image … each vertex contains the coordinates of a pixel back-projected into 3D space using
//! the estimated depth"). A depth image is cut into rows × cols blocks; each block's vertex is its
//! centre pixel back-projected at the median of its valid depths (at least a quarter of the block
//! valid), then moved into the fixed frame. Blocks without enough depth have no vertex.

use nalgebra::{Isometry3, Vector3};

use crate::error::RouteError;

/// CNN IV's grid: 60 rows × 80 columns.
pub const CNN_ROWS: usize = 60;
pub const CNN_COLS: usize = 80;

/// Pinhole intrinsics of the depth image (pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    /// Projects a point in the camera's optical frame (z forward) to pixel coordinates.
    pub fn project(&self, p: &Vector3<f64>) -> Option<(f64, f64)> {
        (p.z > 1e-6).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }
}

/// A rows × cols grid of terrain points in the fixed frame, with each vertex's source pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct TerrainGrid {
    pub rows: usize,
    pub cols: usize,
    /// Row-major; `None` where the block had no depth.
    pub points: Vec<Option<Vector3<f64>>>,
    /// Row-major pixel coordinates (u, v) of each vertex in the source image (for pictures).
    pub pixels: Vec<(f64, f64)>,
}

impl TerrainGrid {
    /// A grid from points given directly (row-major, `rows * cols` of them), e.g. a heightfield's
    /// top view; the pixels are the (column, row) indices.
    pub fn from_points(rows: usize, cols: usize, points: Vec<Option<Vector3<f64>>>) -> Result<Self, RouteError> {
        if rows == 0 || cols == 0 || points.len() != rows * cols {
            return Err(RouteError::Grid(format!("{} points for a {rows} × {cols} grid", points.len())));
        }
        for p in points.iter().flatten() {
            if !p.iter().all(|c| c.is_finite()) {
                return Err(RouteError::Grid(format!("non-finite point [{}, {}, {}]", p.x, p.y, p.z)));
            }
        }
        let pixels = (0..rows * cols).map(|i| ((i % cols) as f64, (i / cols) as f64)).collect();
        Ok(Self { rows, cols, points, pixels })
    }

    /// Back-projects a depth image (metres, row-major, NaN or ≤ 0 = no depth) onto a rows × cols grid
    /// and moves the points into the fixed frame with `fixed_from_camera`.
    pub fn from_depth(
        width: usize,
        height: usize,
        depth_m: &[f32],
        intrinsics: &Pinhole,
        fixed_from_camera: &Isometry3<f64>,
        rows: usize,
        cols: usize,
    ) -> Result<Self, RouteError> {
        if depth_m.len() != width * height {
            return Err(RouteError::Grid(format!("{} depths for a {width} × {height} image", depth_m.len())));
        }
        if rows == 0 || cols == 0 || rows > height || cols > width {
            return Err(RouteError::Grid(format!("a {rows} × {cols} grid does not fit a {width} × {height} image")));
        }
        let mut points = Vec::with_capacity(rows * cols);
        let mut pixels = Vec::with_capacity(rows * cols);
        let mut block = Vec::new();
        for r in 0..rows {
            let (v0, v1) = (r * height / rows, (r + 1) * height / rows);
            for c in 0..cols {
                let (u0, u1) = (c * width / cols, (c + 1) * width / cols);
                block.clear();
                for v in v0..v1 {
                    for u in u0..u1 {
                        let d = depth_m[v * width + u];
                        if d.is_finite() && d > 0.0 {
                            block.push(d);
                        }
                    }
                }
                let u = 0.5 * (u0 + u1) as f64 - 0.5;
                let v = 0.5 * (v0 + v1) as f64 - 0.5;
                pixels.push((u, v));
                let area = (u1 - u0) * (v1 - v0);
                if block.is_empty() || block.len() * 4 < area {
                    points.push(None);
                    continue;
                }
                block.sort_by(f32::total_cmp);
                let z = f64::from(block[block.len() / 2]);
                let camera = Vector3::new((u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z);
                points.push(Some(fixed_from_camera.transform_vector(&camera) + fixed_from_camera.translation.vector));
            }
        }
        Ok(Self { rows, cols, points, pixels })
    }

    /// The point of row `r`, column `c`.
    pub fn at(&self, r: usize, c: usize) -> Option<Vector3<f64>> {
        self.points.get(r * self.cols + c).copied().flatten()
    }

    /// Number of vertices with a point.
    pub fn valid(&self) -> usize {
        self.points.iter().filter(|p| p.is_some()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera 1 m above a floor looking straight down: every vertex lands on z = 0 under its pixel.
    #[test]
    fn depth_back_projects_onto_the_floor() {
        let (w, h) = (80, 60);
        let k = Pinhole { fx: 50.0, fy: 50.0, cx: 39.5, cy: 29.5 };
        let mut depth = vec![1.0f32; w * h];
        // One block with too little depth: 3 of its 16 pixels valid.
        for v in 0..4 {
            for u in 0..4 {
                depth[v * w + u] = if v == 0 && u < 3 { 1.0 } else { f32::NAN };
            }
        }
        // Fixed frame z up; camera at z = 1 looking down (optical z = −fixed z, optical y = −fixed x).
        let rotation = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(0.0, -1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0));
        let fixed_from_camera =
            Isometry3::from_parts(nalgebra::Translation3::new(0.0, 0.0, 1.0), nalgebra::UnitQuaternion::from_rotation_matrix(&rotation));
        let grid = TerrainGrid::from_depth(w, h, &depth, &k, &fixed_from_camera, 15, 20).unwrap();
        assert_eq!((grid.rows, grid.cols), (15, 20));
        assert_eq!(grid.at(0, 0), None);
        assert_eq!(grid.valid(), 299);
        let p = grid.at(7, 10).unwrap();
        assert!(p.z.abs() < 1e-12, "{p:?}");
        let (u, v) = grid.pixels[7 * 20 + 10];
        assert_eq!((u, v), (41.5, 29.5));
        assert!((p.y - (-(u - 39.5) / 50.0)).abs() < 1e-12 && (p.x - (-(v - 29.5) / 50.0)).abs() < 1e-12, "{p:?}");
    }

    #[test]
    fn bad_sizes_are_errors() {
        let k = Pinhole { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0 };
        let id = Isometry3::identity();
        assert!(matches!(TerrainGrid::from_depth(4, 4, &[1.0; 15], &k, &id, 2, 2), Err(RouteError::Grid(_))));
        assert!(matches!(TerrainGrid::from_depth(4, 4, &[1.0; 16], &k, &id, 8, 2), Err(RouteError::Grid(_))));
        assert!(matches!(TerrainGrid::from_points(2, 2, vec![None; 3]), Err(RouteError::Grid(_))));
        assert!(matches!(TerrainGrid::from_points(1, 1, vec![Some(Vector3::new(f64::NAN, 0.0, 0.0))]), Err(RouteError::Grid(_))));
    }
}
