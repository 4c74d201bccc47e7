//! A terrain as a heightfield: heights sampled on a regular grid in the world's x–y plane and the
//! exact ground truth of the surface they define: `height_at(x, y)`, `normal_at(x, y)` and the
//! nearest intersection of a ray. ROS-free; other crates (benches, validators) use it directly.
//!
//! Surface: bilinear interpolation between the four samples around a point (each grid cell is a
//! bilinear patch `h(u, v) = a + b·u + c·v + e·u·v`, u, v ∈ [0, 1] across the cell). The surface is
//! continuous, so 8-bit heightmaps whose neighbouring samples differ by one grey level become
//! gentle slopes instead of 3.9 mm stairs; a real step (many levels between two samples) stays a
//! steep ramp one cell wide. Everything the camera renders and every ground-truth query is this same
//! surface, computed in closed form (the ray–patch intersection is a quadratic in the ray parameter),
//! so rendered points lie on the ground truth up to the camera's noise.
//!
//! Grid: sample `(column i, row j)` is at `x = origin.x + i·resolution`, `y = origin.y +
//! j·resolution` (rows along +y); heights are metres in the world frame (z up). NaN samples are
//! holes: a cell with a NaN corner has no surface (rays pass through, queries return `None`).
//! Outside the grid there is no surface.

use nalgebra::Vector3;

use super::rock::{Hit, Ray, T_MIN};

/// Why a heightfield cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HeightfieldError {
    #[error("a heightfield needs at least 2 × 2 samples, got {columns} × {rows}")]
    TooSmall { columns: usize, rows: usize },
    #[error("{columns} × {rows} samples need {expected} heights, got {got}")]
    WrongLength { columns: usize, rows: usize, expected: usize, got: usize },
    #[error("resolution {0} m must be positive and finite")]
    Resolution(f64),
    #[error("origin ({0}, {1}) must be finite")]
    Origin(f64, f64),
    #[error("height at column {column}, row {row} is infinite ({value})")]
    Infinite { column: usize, row: usize, value: f32 },
    #[error("no grid cell has four valid (non-NaN) corners: the heightfield has no surface")]
    NoSurface,
}

/// Heights on a regular grid with a bilinear surface between them (see the module docs).
#[derive(Clone, PartialEq)]
pub struct Heightfield {
    columns: usize,
    rows: usize,
    resolution_m: f64,
    origin_m: [f64; 2],
    heights_m: Vec<f32>,
    /// Lowest and highest valid sample (m).
    z_range_m: [f64; 2],
}

impl std::fmt::Debug for Heightfield {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Heightfield")
            .field("columns", &self.columns)
            .field("rows", &self.rows)
            .field("resolution_m", &self.resolution_m)
            .field("origin_m", &self.origin_m)
            .field("z_range_m", &self.z_range_m)
            .finish_non_exhaustive()
    }
}

/// Grid-space position: cell indices and the position inside the cell.
#[derive(Debug, Clone, Copy)]
struct CellPoint {
    column: usize,
    row: usize,
    u: f64,
    v: f64,
}

/// Bilinear coefficients of one cell: `h(u, v) = a + b·u + c·v + e·u·v`.
#[derive(Debug, Clone, Copy)]
struct Patch {
    a: f64,
    b: f64,
    c: f64,
    e: f64,
    min: f64,
    max: f64,
}

impl Heightfield {
    /// Builds a heightfield of `columns × rows` samples (row-major, row `j` at `y = origin.y +
    /// j·resolution`); NaN heights are holes.
    pub fn new(columns: usize, rows: usize, resolution_m: f64, origin_m: [f64; 2], heights_m: Vec<f32>) -> Result<Self, HeightfieldError> {
        if columns < 2 || rows < 2 {
            return Err(HeightfieldError::TooSmall { columns, rows });
        }
        let expected = columns.checked_mul(rows).unwrap_or(usize::MAX);
        if heights_m.len() != expected {
            return Err(HeightfieldError::WrongLength { columns, rows, expected, got: heights_m.len() });
        }
        if !(resolution_m.is_finite() && resolution_m > 0.0) {
            return Err(HeightfieldError::Resolution(resolution_m));
        }
        if !(origin_m[0].is_finite() && origin_m[1].is_finite()) {
            return Err(HeightfieldError::Origin(origin_m[0], origin_m[1]));
        }
        if let Some(index) = heights_m.iter().position(|h| h.is_infinite()) {
            let value = heights_m.get(index).copied().unwrap_or(f32::INFINITY);
            return Err(HeightfieldError::Infinite { column: index % columns, row: index / columns, value });
        }
        let mut field = Self { columns, rows, resolution_m, origin_m, heights_m, z_range_m: [0.0, 0.0] };
        let mut range = [f64::INFINITY, f64::NEG_INFINITY];
        let mut any_cell = false;
        for row in 0..rows - 1 {
            for column in 0..columns - 1 {
                if let Some(patch) = field.patch(column, row) {
                    any_cell = true;
                    range = [range[0].min(patch.min), range[1].max(patch.max)];
                }
            }
        }
        if !any_cell {
            return Err(HeightfieldError::NoSurface);
        }
        field.z_range_m = range;
        Ok(field)
    }

    /// Samples along x.
    pub fn columns(&self) -> usize {
        self.columns
    }

    /// Samples along y.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Grid spacing (m).
    pub fn resolution_m(&self) -> f64 {
        self.resolution_m
    }

    /// World `(x, y)` of sample (0, 0).
    pub fn origin_m(&self) -> [f64; 2] {
        self.origin_m
    }

    /// The samples, row-major (row 0 first), NaN = hole.
    pub fn heights_m(&self) -> &[f32] {
        &self.heights_m
    }

    /// Height sample at `(column, row)` (NaN for a hole), `None` outside the grid.
    pub fn sample(&self, column: usize, row: usize) -> Option<f32> {
        if column >= self.columns || row >= self.rows {
            return None;
        }
        self.heights_m.get(row * self.columns + column).copied()
    }

    /// Lowest and highest height of the surface (m).
    pub fn z_range_m(&self) -> [f64; 2] {
        self.z_range_m
    }

    /// World extent `[[x_min, y_min], [x_max, y_max]]` of the grid.
    pub fn extent_m(&self) -> [[f64; 2]; 2] {
        let [x0, y0] = self.origin_m;
        [[x0, y0], [x0 + (self.columns - 1) as f64 * self.resolution_m, y0 + (self.rows - 1) as f64 * self.resolution_m]]
    }

    /// Centre `(x, y)` of the grid.
    pub fn centre_m(&self) -> [f64; 2] {
        let [[x0, y0], [x1, y1]] = self.extent_m();
        [(x0 + x1) / 2.0, (y0 + y1) / 2.0]
    }

    /// Height (m) of the surface above `(x, y)`; `None` outside the grid or in a hole.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let p = self.locate(x, y)?;
        let patch = self.patch(p.column, p.row)?;
        Some(patch.a + patch.b * p.u + patch.c * p.v + patch.e * p.u * p.v)
    }

    /// Upward unit normal of the surface at `(x, y)`: `(−∂h/∂x, −∂h/∂y, 1)` normalised, the
    /// derivatives of the cell's bilinear patch (on a cell border, the cell at larger x / y).
    pub fn normal_at(&self, x: f64, y: f64) -> Option<Vector3<f64>> {
        let p = self.locate(x, y)?;
        let patch = self.patch(p.column, p.row)?;
        Some(self.patch_normal(&patch, p.u, p.v))
    }

    /// Nearest intersection (ray parameter `t > 1e-6` and upward normal) of a ray with the surface,
    /// seen from above (rays leaving the surface from below are not hits). Exact: the grid cells
    /// the ray crosses are walked in order (2-D DDA) and each bilinear patch is solved in closed form.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let r = self.resolution_m;
        // Grid coordinates: cell (i, j) spans [i, i+1] × [j, j+1].
        let (gx, gy) = ((ray.origin.x - self.origin_m[0]) / r, (ray.origin.y - self.origin_m[1]) / r);
        let (dx, dy) = (ray.direction.x / r, ray.direction.y / r);
        let (oz, dz) = (ray.origin.z, ray.direction.z);
        let (max_x, max_y) = ((self.columns - 1) as f64, (self.rows - 1) as f64);
        // Clip to the bounding box of the surface.
        let mut t0 = T_MIN;
        let mut t1 = f64::INFINITY;
        for (o, d, lo, hi) in [(gx, dx, 0.0, max_x), (gy, dy, 0.0, max_y), (oz, dz, self.z_range_m[0], self.z_range_m[1])] {
            if d.abs() < 1e-300 {
                if o < lo || o > hi {
                    return None;
                }
                continue;
            }
            let (ta, tb) = ((lo - o) / d, (hi - o) / d);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
        if !(t0 <= t1) {
            return None;
        }
        // DDA from the entry point.
        let start_x = gx + dx * t0;
        let start_y = gy + dy * t0;
        let mut column = (start_x.floor().max(0.0) as usize).min(self.columns - 2);
        let mut row = (start_y.floor().max(0.0) as usize).min(self.rows - 2);
        let step_x: isize = if dx > 0.0 { 1 } else { -1 };
        let step_y: isize = if dy > 0.0 { 1 } else { -1 };
        let next_boundary = |cell: usize, step: isize| if step > 0 { (cell + 1) as f64 } else { cell as f64 };
        let delta_x = if dx.abs() > 1e-300 { 1.0 / dx.abs() } else { f64::INFINITY };
        let delta_y = if dy.abs() > 1e-300 { 1.0 / dy.abs() } else { f64::INFINITY };
        let mut t_next_x = if dx.abs() > 1e-300 { (next_boundary(column, step_x) - gx) / dx } else { f64::INFINITY };
        let mut t_next_y = if dy.abs() > 1e-300 { (next_boundary(row, step_y) - gy) / dy } else { f64::INFINITY };
        let mut t_enter = t0;
        loop {
            let t_exit = t_next_x.min(t_next_y).min(t1);
            if let Some(patch) = self.patch(column, row) {
                // Does the ray's height range over [t_enter, t_exit] reach the patch's?
                let (za, zb) = (oz + dz * t_enter, oz + dz * t_exit);
                if za.min(zb) <= patch.max + 1e-9 && za.max(zb) >= patch.min - 1e-9 {
                    if let Some(hit) = self.intersect_patch(&patch, column, row, [gx, gy, oz], [dx, dy, dz], t_enter, t_exit) {
                        return Some(hit);
                    }
                }
            }
            if t_exit >= t1 {
                return None;
            }
            if t_next_x <= t_next_y {
                let next = column as isize + step_x;
                if next < 0 || next as usize > self.columns - 2 {
                    return None;
                }
                column = next as usize;
                t_enter = t_next_x;
                t_next_x += delta_x;
            } else {
                let next = row as isize + step_y;
                if next < 0 || next as usize > self.rows - 2 {
                    return None;
                }
                row = next as usize;
                t_enter = t_next_y;
                t_next_y += delta_y;
            }
        }
    }

    /// First crossing of the ray (grid coordinates `o + t·d`, z in metres) down through the cell's
    /// patch within `[t_enter, t_exit]`.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn intersect_patch(
        &self,
        patch: &Patch,
        column: usize,
        row: usize,
        o: [f64; 3],
        d: [f64; 3],
        t_enter: f64,
        t_exit: f64,
    ) -> Option<Hit> {
        // Cell-local u = u0 + du·t, v = v0 + dv·t; f(t) = z(t) − h(u(t), v(t)) = A t² + B t + C.
        let (u0, v0) = (o[0] - column as f64, o[1] - row as f64);
        let (du, dv, dz) = (d[0], d[1], d[2]);
        let Patch { a, b, c, e, .. } = *patch;
        let qa = -e * du * dv;
        let qb = dz - b * du - c * dv - e * (u0 * dv + v0 * du);
        let qc = o[2] - a - b * u0 - c * v0 - e * u0 * v0;
        let slack = 1e-9 * (1.0 + t_exit.abs());
        let (lo, hi) = (t_enter - slack, t_exit + slack);
        let mut roots = [f64::NAN; 2];
        if qa.abs() < 1e-14 * (qb.abs() + qc.abs() + 1.0) {
            if qb.abs() > 1e-300 {
                roots[0] = -qc / qb;
            }
        } else {
            let discriminant = qb * qb - 4.0 * qa * qc;
            if discriminant < 0.0 {
                return None;
            }
            let q = -0.5 * (qb + qb.signum() * discriminant.sqrt());
            roots = [q / qa, if q.abs() > 1e-300 { qc / q } else { f64::NAN }];
            if roots[1] < roots[0] {
                roots.swap(0, 1);
            }
        }
        for t in roots {
            if !(t >= lo && t <= hi && t > T_MIN) {
                continue;
            }
            // Going down through the surface: f decreasing.
            if 2.0 * qa * t + qb > 0.0 {
                continue;
            }
            let u = (u0 + du * t).clamp(0.0, 1.0);
            let v = (v0 + dv * t).clamp(0.0, 1.0);
            return Some(Hit { t, normal: self.patch_normal(patch, u, v) });
        }
        None
    }

    #[inline]
    fn patch_normal(&self, patch: &Patch, u: f64, v: f64) -> Vector3<f64> {
        let (hu, hv) = (patch.b + patch.e * v, patch.c + patch.e * u);
        Vector3::new(-hu / self.resolution_m, -hv / self.resolution_m, 1.0).normalize()
    }

    /// The cell containing `(x, y)` (the last cell for points on the far border).
    fn locate(&self, x: f64, y: f64) -> Option<CellPoint> {
        let gx = (x - self.origin_m[0]) / self.resolution_m;
        let gy = (y - self.origin_m[1]) / self.resolution_m;
        let (max_x, max_y) = ((self.columns - 1) as f64, (self.rows - 1) as f64);
        if !(gx >= 0.0 && gx <= max_x && gy >= 0.0 && gy <= max_y) {
            return None;
        }
        let column = (gx.floor() as usize).min(self.columns - 2);
        let row = (gy.floor() as usize).min(self.rows - 2);
        Some(CellPoint { column, row, u: gx - column as f64, v: gy - row as f64 })
    }

    /// Bilinear coefficients of cell `(column, row)`; `None` if a corner is a hole.
    #[inline]
    fn patch(&self, column: usize, row: usize) -> Option<Patch> {
        let i = row * self.columns + column;
        let h00 = f64::from(*self.heights_m.get(i)?);
        let h10 = f64::from(*self.heights_m.get(i + 1)?);
        let h01 = f64::from(*self.heights_m.get(i + self.columns)?);
        let h11 = f64::from(*self.heights_m.get(i + self.columns + 1)?);
        if !(h00.is_finite() && h10.is_finite() && h01.is_finite() && h11.is_finite()) {
            return None;
        }
        Some(Patch {
            a: h00,
            b: h10 - h00,
            c: h01 - h00,
            e: h00 - h10 - h01 + h11,
            min: h00.min(h10).min(h01).min(h11),
            max: h00.max(h10).max(h01).max(h11),
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A tilted plane z = 0.1 + 0.2 x − 0.05 y sampled at 5 cm, 21 × 11 samples from (−0.5, −0.25).
    pub(crate) fn tilted_plane() -> Heightfield {
        let (columns, rows, r, origin) = (21, 11, 0.05, [-0.5, -0.25]);
        let heights = (0..rows)
            .flat_map(|j| (0..columns).map(move |i| (origin[0] + i as f64 * r, origin[1] + j as f64 * r)))
            .map(|(x, y)| (0.1 + 0.2 * x - 0.05 * y) as f32)
            .collect();
        Heightfield::new(columns, rows, r, origin, heights).unwrap()
    }

    fn plane_z(x: f64, y: f64) -> f64 {
        0.1 + 0.2 * x - 0.05 * y
    }

    #[test]
    fn plane_queries_are_exact() {
        let field = tilted_plane();
        let expected_normal = Vector3::new(-0.2, 0.05, 1.0).normalize();
        for (x, y) in [(0.0, 0.0), (0.123, -0.2), (-0.5, -0.25), (0.5, 0.25), (0.31, 0.07)] {
            // f32 samples: exact to single precision.
            assert!((field.height_at(x, y).unwrap() - plane_z(x, y)).abs() < 1e-7, "({x}, {y})");
            assert!((field.normal_at(x, y).unwrap() - expected_normal).norm() < 1e-6, "({x}, {y})");
        }
        assert_eq!(field.height_at(0.6, 0.0), None);
        assert_eq!(field.normal_at(0.0, -0.3), None);
        assert_eq!(field.extent_m(), [[-0.5, -0.25], [0.5, 0.25]]);
        // Oblique rays from above land on the plane.
        for (origin, direction) in [
            (Vector3::new(-0.4, 0.2, 1.0), Vector3::new(0.3, -0.2, -1.0)),
            (Vector3::new(0.45, -0.2, 0.5), Vector3::new(-1.0, 0.3, -1.5)),
            (Vector3::new(0.0, 0.0, 0.3), -Vector3::z()),
        ] {
            let ray = Ray { origin, direction };
            let hit = field.intersect(&ray).unwrap();
            let p = ray.at(hit.t);
            assert!((p.z - plane_z(p.x, p.y)).abs() < 1e-7, "{p:?}");
            assert!((hit.normal - expected_normal).norm() < 1e-6);
        }
        // Rays pointing up, or missing the grid, do not hit.
        assert!(field.intersect(&Ray { origin: Vector3::new(0.0, 0.0, 0.5), direction: Vector3::z() }).is_none());
        assert!(field.intersect(&Ray { origin: Vector3::new(2.0, 0.0, 0.5), direction: Vector3::new(1.0, 0.0, -0.1) }).is_none());
        // From below the surface going up: a back face, no hit.
        assert!(field.intersect(&Ray { origin: Vector3::new(0.0, 0.0, -1.0), direction: Vector3::z() }).is_none());
    }

    #[test]
    fn bilinear_saddle_ray_hits_match_height_at() {
        // One cell with corners 0, 1, 1, 0: a saddle h = u + v − 2uv; rays at many angles.
        let field = Heightfield::new(2, 2, 1.0, [0.0, 0.0], vec![0.0, 1.0, 1.0, 0.0]).unwrap();
        assert!((field.height_at(0.5, 0.5).unwrap() - 0.5).abs() < 1e-12);
        assert!((field.height_at(0.25, 0.75).unwrap() - (1.0 - 2.0 * 0.1875)).abs() < 1e-12);
        let mut hits = 0;
        for k in 0..50 {
            let angle = k as f64 * 0.37;
            let ray = Ray { origin: Vector3::new(0.5, 0.5, 2.0), direction: Vector3::new(angle.cos() * 0.3, angle.sin() * 0.3, -1.0) };
            if let Some(hit) = field.intersect(&ray) {
                let p = ray.at(hit.t);
                assert!((p.z - field.height_at(p.x, p.y).unwrap()).abs() < 1e-9, "{p:?}");
                // Numeric normal from the height function.
                let eps = 1e-6;
                let hx = (field.height_at(p.x + eps, p.y).unwrap() - field.height_at(p.x - eps, p.y).unwrap()) / (2.0 * eps);
                let hy = (field.height_at(p.x, p.y + eps).unwrap() - field.height_at(p.x, p.y - eps).unwrap()) / (2.0 * eps);
                assert!((hit.normal - Vector3::new(-hx, -hy, 1.0).normalize()).norm() < 1e-5);
                hits += 1;
            }
        }
        assert_eq!(hits, 50);
    }

    #[test]
    fn holes_have_no_surface_and_bad_grids_are_errors() {
        let mut heights = vec![0.0f32; 9];
        heights[4] = f32::NAN; // centre sample: every cell touches it
        assert_eq!(Heightfield::new(3, 3, 0.1, [0.0, 0.0], heights), Err(HeightfieldError::NoSurface));
        let mut heights = vec![0.0f32; 16];
        heights[0] = f32::NAN; // only cell (0, 0) is a hole
        let field = Heightfield::new(4, 4, 0.1, [0.0, 0.0], heights).unwrap();
        assert_eq!(field.height_at(0.05, 0.05), None);
        assert_eq!(field.height_at(0.15, 0.05), Some(0.0));
        assert!(field.intersect(&Ray { origin: Vector3::new(0.05, 0.05, 1.0), direction: -Vector3::z() }).is_none());
        // A ray through the hole reaches the next cell.
        let hit = field.intersect(&Ray { origin: Vector3::new(0.05, 0.05, 0.1), direction: Vector3::new(1.0, 0.0, -0.5) }).unwrap();
        assert!((hit.t - 0.2).abs() < 1e-12);
        assert!(matches!(Heightfield::new(1, 5, 0.1, [0.0, 0.0], vec![0.0; 5]), Err(HeightfieldError::TooSmall { .. })));
        assert!(matches!(Heightfield::new(2, 2, 0.1, [0.0, 0.0], vec![0.0; 3]), Err(HeightfieldError::WrongLength { .. })));
        assert_eq!(Heightfield::new(2, 2, 0.0, [0.0, 0.0], vec![0.0; 4]), Err(HeightfieldError::Resolution(0.0)));
        assert!(matches!(Heightfield::new(2, 2, 0.1, [f64::NAN, 0.0], vec![0.0; 4]), Err(HeightfieldError::Origin(..))));
        let error = Heightfield::new(2, 2, 0.1, [0.0, 0.0], vec![0.0, 0.0, f32::INFINITY, 0.0]).unwrap_err();
        assert_eq!(error, HeightfieldError::Infinite { column: 0, row: 1, value: f32::INFINITY });
    }

    #[test]
    fn step_seen_from_the_side_hits_the_riser() {
        // A 0.2 m step between x = 0.4 and 0.5 (one cell ramp), seen by a horizontal ray at z = 0.1.
        let columns = 11;
        let heights: Vec<f32> = (0..2).flat_map(|_| (0..columns).map(|i| if i <= 4 { 0.0 } else { 0.2 })).collect();
        let field = Heightfield::new(columns, 2, 0.1, [0.0, 0.0], heights).unwrap();
        let hit = field.intersect(&Ray { origin: Vector3::new(0.05, 0.05, 0.1), direction: Vector3::x() }).unwrap();
        assert!((hit.t - 0.4).abs() < 1e-9, "{}", hit.t);
        // f32 samples: 0.2 is stored as 0.2000000030.
        assert!((hit.normal - Vector3::new(-2.0, 0.0, 1.0).normalize()).norm() < 1e-7);
    }
}
