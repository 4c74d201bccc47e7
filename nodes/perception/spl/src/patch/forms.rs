//! What a patch's parameters describe: its local frame and pose (IROS II, III), the implicit form
//! (eq 37–38) and the explicit height form (eq 13, 23, 27), the boundary (eq 17–21) with its area and
//! extents, uniform samples of the bounded surface, and Euclidean distances to it.

use super::shape::explicit_height;
use super::{BoundaryType, Patch, PatchQuery, PatchShape};
use crate::geometry::{exp_map, Pose};
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;

impl Patch {
    /// Rotation matrix `R(r)` whose columns are the local axes in the world frame.
    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        exp_map(&self.rotation)
    }

    /// Outward surface normal at the centre: the local z axis in the world frame.
    pub fn normal(&self) -> Vector3<f64> {
        self.rotation_matrix().column(2).into_owned()
    }

    /// The pose `(r, c)` of the local frame.
    pub fn pose(&self) -> Pose {
        Pose::new(self.rotation, self.center)
    }

    /// `world_from_patch` as an isometry.
    pub fn world_from_patch(&self) -> Isometry3<f64> {
        let rot = nalgebra::Rotation3::from_matrix_unchecked(self.rotation_matrix());
        Isometry3::from_parts(Translation3::from(self.center), UnitQuaternion::from_rotation_matrix(&rot))
    }

    /// `X_r`: a world point in the patch frame (eq 4).
    pub fn to_local(&self, point_in_world: &Vector3<f64>) -> Vector3<f64> {
        self.rotation_matrix().transpose() * (point_in_world - self.center)
    }

    /// Implicit form in the local frame (eq 12, 22, 26 = eq 37): zero on the surface.
    pub fn implicit_local(&self, q_l: &Vector3<f64>) -> f64 {
        let k = self.k3();
        k.x * q_l.x * q_l.x + k.y * q_l.y * q_l.y + k.z * q_l.z * q_l.z - 2.0 * q_l.z
    }

    /// Implicit form in the world frame (eq 14, 24, 28).
    pub fn implicit_world(&self, point_in_world: &Vector3<f64>) -> f64 {
        self.implicit_local(&self.to_local(point_in_world))
    }

    /// Height `z(u)` of the explicit form and its gradient `∂z/∂u` (eq 13, 23, 27). `None` outside
    /// the domain of spheres/cylinders (`κ² uᵀu > 1`).
    pub fn height(&self, u: &Vector2<f64>) -> Option<(f64, Vector2<f64>)> {
        explicit_height(self.surface, &self.curvatures, u)
    }

    /// Explicit form in the local frame: the surface point above `u` (eq 13, 23, 27).
    pub fn explicit_local(&self, u: &Vector2<f64>) -> Option<Vector3<f64>> {
        self.height(u).map(|(z, _)| Vector3::new(u.x, u.y, z))
    }

    /// Explicit form in the world frame (eq 15, 25, 29).
    pub fn explicit_world(&self, u: &Vector2<f64>) -> Option<Vector3<f64>> {
        self.explicit_local(u).map(|q| self.rotation_matrix() * q + self.center)
    }

    /// Vertices of a rectangle (eq 18) or quadrilateral (eq 21) boundary, counter-clockwise.
    pub fn boundary_vertices(&self) -> Option<[Vector2<f64>; 4]> {
        let d = &self.boundary_params;
        match (self.boundary, d.as_slice()) {
            (BoundaryType::Rectangle, [dx, dy]) => {
                let v1 = Vector2::new(*dx, *dy);
                let v2 = Vector2::new(-dx, *dy);
                Some([v1, v2, -v1, -v2])
            }
            (BoundaryType::Quadrilateral, [d1, d2, d3, d4, g]) => {
                let phi = [*g, std::f64::consts::PI - g, std::f64::consts::PI + g, -g];
                let ds = [*d1, *d2, *d3, *d4];
                Some(std::array::from_fn(|i| Vector2::new(phi[i].cos(), phi[i].sin()) * ds[i]))
            }
            _ => None,
        }
    }

    /// Boundary function in the local xy plane: `≤ 0` inside (eq 17 for ellipse/circle, eq 19–20 for
    /// rectangle/quad).
    pub fn boundary_value(&self, u: &Vector2<f64>) -> f64 {
        self.shape().boundary_value(u)
    }

    /// Whether `u` lies inside the projected boundary.
    pub fn contains_uv(&self, u: &Vector2<f64>) -> bool {
        self.boundary_value(u) <= 0.0
    }

    /// Point-in-patch test: the projection `u = Π_xy X_r(q)` (eq 16) lies inside the boundary.
    pub fn contains_point(&self, point_in_world: &Vector3<f64>) -> bool {
        let q = self.to_local(point_in_world);
        self.contains_uv(&q.xy())
    }

    /// Area of the projected boundary `A_p` (J eq 17).
    pub fn boundary_area(&self) -> f64 {
        match (self.boundary, self.boundary_params.as_slice()) {
            (BoundaryType::Ellipse, [dx, dy]) => std::f64::consts::PI * dx * dy,
            (BoundaryType::Circle, [dc]) => std::f64::consts::PI * dc * dc,
            _ => match self.boundary_vertices() {
                Some(v) => 0.5 * (0..4).map(|i| v[i].perp(&v[(i + 1) % 4])).sum::<f64>().abs(),
                None => 0.0,
            },
        }
    }

    /// Half-extents of the axis-aligned bounding box of the projected boundary.
    pub fn boundary_half_extents(&self) -> Vector2<f64> {
        match (self.boundary, self.boundary_params.as_slice()) {
            (BoundaryType::Ellipse, [dx, dy]) => Vector2::new(*dx, *dy),
            (BoundaryType::Circle, [dc]) => Vector2::new(*dc, *dc),
            _ => match self.boundary_vertices() {
                Some(v) => v.iter().fold(Vector2::zeros(), |acc, p| Vector2::new(acc.x.max(p.x.abs()), acc.y.max(p.y.abs()))),
                None => Vector2::zeros(),
            },
        }
    }

    /// A point `u` drawn uniformly from the projected boundary (rejection sampling).
    pub fn sample_uv<R: Rng + ?Sized>(&self, rng: &mut R) -> Vector2<f64> {
        let h = self.boundary_half_extents();
        if h.x <= 0.0 || h.y <= 0.0 {
            return Vector2::zeros();
        }
        for _ in 0..1000 {
            let u = Vector2::new(rng.random_range(-h.x..=h.x), rng.random_range(-h.y..=h.y));
            if self.contains_uv(&u) {
                return u;
            }
        }
        Vector2::zeros()
    }

    /// `n` world points on the bounded patch, uniform in the projected boundary.
    pub fn sample_points<R: Rng + ?Sized>(&self, rng: &mut R, n: usize) -> Vec<Vector3<f64>> {
        let mut out = Vec::with_capacity(n);
        let mut guard = 0;
        while out.len() < n && guard < 100 * n + 100 {
            guard += 1;
            let u = self.sample_uv(rng);
            if let Some(p) = self.explicit_world(&u) {
                out.push(p);
            }
        }
        out
    }

    /// Closest point on the bounded surface to a local-frame point (projected Gauss–Newton over the
    /// explicit parameter `u`, constrained to the boundary). Returns the local closest point.
    pub fn closest_point_local(&self, q_l: &Vector3<f64>) -> Vector3<f64> {
        self.shape().closest_point_local(q_l)
    }

    /// Euclidean distance from a world point to the bounded patch surface (J eq 15's `‖q − p‖`).
    /// For many points use [`PatchQuery`], which evaluates the rotation and the boundary once.
    pub fn distance(&self, point_in_world: &Vector3<f64>) -> f64 {
        PatchQuery::new(self).distance(point_in_world)
    }

    /// The local-frame surface and boundary in closed form (for repeated queries).
    pub fn shape(&self) -> PatchShape {
        PatchShape::new(self)
    }
}
