//! A patch prepared for many point queries: the surface and boundary in the local frame with the
//! per-patch constants evaluated once ([`PatchShape`]), and with the local frame's rotation
//! ([`PatchQuery`]). Closest points on the bounded surface by Newton steps on the explicit form
//! (eq 13, 23, 27) and projection onto the boundary (eq 17–21): the distances of J eq 15 and the
//! projections of J eq 16.

use super::{BoundaryType, Patch, SurfaceType};
use nalgebra::{Matrix3, Vector2, Vector3};

/// The boundary of the projected patch with its per-patch constants precomputed (eq 17–21).
#[derive(Clone, Copy, Debug, PartialEq)]
enum BoundaryShape {
    /// eq 17 with radii `d_e`.
    Ellipse { dx: f64, dy: f64 },
    /// eq 17 with `d_e = [d_c d_c]`.
    Circle { dc: f64 },
    /// Rectangle (eq 18) or quadrilateral (eq 21): the counter-clockwise vertices, the edge normals
    /// `[v_j − v_i]⊥` of eq 20 and their lengths, and the bounding half-extents.
    Polygon { quad: bool, vertices: [Vector2<f64>; 4], perps: [Vector2<f64>; 4], lengths: [f64; 4], half: Vector2<f64> },
    /// Boundary parameters of the wrong length: nothing is inside.
    Invalid { quad: bool },
}

/// A patch's surface and boundary in its local frame, with everything that does not depend on the
/// query point evaluated once (boundary vertices and edge normals, curvatures): the per-point work
/// of [`PatchShape::closest_point_local`] has no trigonometry and no allocation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatchShape {
    surface: SurfaceType,
    curvatures: Vector2<f64>,
    boundary: BoundaryShape,
}

impl PatchShape {
    /// The shape of `patch`.
    pub fn new(patch: &Patch) -> Self {
        let boundary = match (patch.boundary, patch.boundary_params.as_slice()) {
            (BoundaryType::Ellipse, [dx, dy]) => BoundaryShape::Ellipse { dx: *dx, dy: *dy },
            (BoundaryType::Circle, [dc]) => BoundaryShape::Circle { dc: *dc },
            (b, _) => {
                let quad = b == BoundaryType::Quadrilateral;
                match patch.boundary_vertices() {
                    Some(vertices) => {
                        let mut perps = [Vector2::zeros(); 4];
                        let mut lengths = [0.0; 4];
                        for i in 0..4 {
                            let d = vertices[(i + 1) % 4] - vertices[i];
                            perps[i] = Vector2::new(d.y, -d.x);
                            lengths[i] = perps[i].norm();
                        }
                        let half = vertices
                            .iter()
                            .fold(Vector2::<f64>::zeros(), |acc, p| Vector2::new(acc.x.max(p.x.abs()), acc.y.max(p.y.abs())));
                        BoundaryShape::Polygon { quad, vertices, perps, lengths, half }
                    }
                    None => BoundaryShape::Invalid { quad },
                }
            }
        };
        Self { surface: patch.surface, curvatures: patch.curvatures, boundary }
    }

    /// [`Patch::height`].
    #[inline]
    pub fn height(&self, u: &Vector2<f64>) -> Option<(f64, Vector2<f64>)> {
        explicit_height(self.surface, &self.curvatures, u)
    }

    /// [`Patch::boundary_value`]: `≤ 0` inside (eq 17 for ellipse/circle, eq 19–20 for rectangle/quad).
    #[inline(always)]
    pub fn boundary_value(&self, u: &Vector2<f64>) -> f64 {
        match &self.boundary {
            BoundaryShape::Ellipse { dx, dy } => (u.x / dx).powi(2) + (u.y / dy).powi(2) - 1.0,
            BoundaryShape::Circle { dc } => u.norm_squared() / (dc * dc) - 1.0,
            BoundaryShape::Polygon { vertices, perps, lengths, .. } => (0..4)
                .map(|i| if lengths[i] == 0.0 { f64::NEG_INFINITY } else { (u - vertices[i]).dot(&perps[i]) / lengths[i] })
                .fold(f64::NEG_INFINITY, f64::max),
            BoundaryShape::Invalid { .. } => f64::INFINITY,
        }
    }

    /// Whether `u` lies inside the projected boundary.
    #[inline]
    pub fn contains_uv(&self, u: &Vector2<f64>) -> bool {
        self.boundary_value(u) <= 0.0
    }

    /// Closest point on the bounded surface to a local-frame point (projected Gauss–Newton over the
    /// explicit parameter `u`, constrained to the boundary). Returns the local closest point.
    pub fn closest_point_local(&self, q_l: &Vector3<f64>) -> Vector3<f64> {
        // One loop per explicit form (eq 13, 23, 27): with the surface a constant, the height's
        // match folds away and the form is inlined into the loop.
        let k = self.curvatures;
        match self.surface {
            SurfaceType::Sphere => self.closest_with(q_l, None, |u| explicit_height(SurfaceType::Sphere, &k, u)),
            SurfaceType::CircularCylinder => self.closest_with(q_l, None, |u| explicit_height(SurfaceType::CircularCylinder, &k, u)),
            _ if k.x == 0.0 && k.y == 0.0 => {
                // z(u) = 0: the first Gauss–Newton step lands on the projection already.
                let u = self.project_to_boundary(&q_l.xy());
                Vector3::new(u.x, u.y, 0.0)
            }
            // ∇²z = diag(κx, κy) (eq 13): Newton steps inside the boundary.
            _ => self.closest_with(q_l, Some(k), |u| Some(paraboloid_height(&k, u))),
        }
    }

    /// [`PatchShape::closest_point_local`] of a curved surface with the explicit form `height`
    /// (`z(u)` and `∂z/∂u`, `None` outside the domain). With the constant diagonal Hessian
    /// `hessian` of `z`, steps are Newton steps on `½‖(u, z(u)) − q‖²` (quadratic convergence)
    /// while they stay strictly inside the boundary and the Hessian `I + g gᵀ + e_z ∇²z` is positive
    /// definite: an interior minimum is a stationary point of both iterations, the same point. From
    /// the first step that would leave the boundary on, projected Gauss–Newton as without `hessian`
    /// (whose fixed point on the boundary depends on the step's metric).
    #[inline(always)]
    fn closest_with(
        &self,
        q_l: &Vector3<f64>,
        hessian: Option<Vector2<f64>>,
        height: impl Fn(&Vector2<f64>) -> Option<(f64, Vector2<f64>)>,
    ) -> Vector3<f64> {
        let q_xy = q_l.xy();
        let mut u = self.project_to_boundary(&q_xy);
        let mut hessian = hessian;
        for _ in 0..12 {
            let Some((z, g)) = height(&u) else { break };
            // residual e = (u − q_xy, z − q_z); J = [I; gᵀ]; JᵀJ = I + g gᵀ has the inverse
            // I − g gᵀ / (1 + gᵀg) (Sherman–Morrison).
            let e_xy = u - q_xy;
            let e_z = z - q_l.z;
            let jte = e_xy + g * e_z;
            let newton =
                hessian.and_then(|h| newton_step(&g, e_z, &h, &jte)).map(|step| u - step).filter(|next| self.boundary_value(next) < 0.0);
            let next = match newton {
                Some(next) => next,
                None => {
                    hessian = None;
                    let step = jte - g * (g.dot(&jte) / (1.0 + g.norm_squared()));
                    self.project_to_boundary(&(u - step))
                }
            };
            let moved_sq = (next - u).norm_squared();
            u = next;
            if moved_sq < 1e-20 {
                break;
            }
        }
        match height(&u) {
            Some((z, _)) => Vector3::new(u.x, u.y, z),
            None => Vector3::new(u.x, u.y, 0.0),
        }
    }

    /// Nearest point of the projected boundary region to `u` (identity inside; radial for ellipses,
    /// which is exact for circles and close for mildly eccentric ellipses).
    #[inline(always)]
    fn project_to_boundary(&self, u: &Vector2<f64>) -> Vector2<f64> {
        let mut u = *u;
        // Keep spheres/cylinders inside their domain κ² uᵀu < 1.
        let k = self.curvatures;
        match self.surface {
            SurfaceType::Sphere if k.x != 0.0 => {
                let lim = 0.999_999 / k.x.abs();
                let n = u.norm();
                if n > lim {
                    u *= lim / n;
                }
            }
            SurfaceType::CircularCylinder if k.y != 0.0 => {
                let lim = 0.999_999 / k.y.abs();
                u.y = u.y.clamp(-lim, lim);
            }
            _ => {}
        }
        let value = self.boundary_value(&u);
        if value <= 0.0 {
            return u;
        }
        match &self.boundary {
            BoundaryShape::Ellipse { .. } | BoundaryShape::Circle { .. } => u / (value + 1.0).sqrt(),
            BoundaryShape::Polygon { quad: false, half, .. } => Vector2::new(u.x.clamp(-half.x, half.x), u.y.clamp(-half.y, half.y)),
            BoundaryShape::Polygon { quad: true, vertices, .. } => (0..4)
                .map(|i| closest_on_segment(&u, &vertices[i], &vertices[(i + 1) % 4]))
                .min_by(|a, b| (a - u).norm_squared().total_cmp(&(b - u).norm_squared()))
                .unwrap_or(u),
            BoundaryShape::Invalid { quad: true } => u,
            BoundaryShape::Invalid { quad: false } => Vector2::zeros(),
        }
    }
}

/// A patch prepared for many point queries (J eq 15 distances, eq 16 projections): the rotation of
/// the local frame and the [`PatchShape`] are evaluated once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatchQuery {
    rot_t: Matrix3<f64>,
    center: Vector3<f64>,
    shape: PatchShape,
}

impl PatchQuery {
    /// The query form of `patch`.
    pub fn new(patch: &Patch) -> Self {
        Self { rot_t: patch.rotation_matrix().transpose(), center: patch.center, shape: PatchShape::new(patch) }
    }

    /// The local surface and boundary.
    pub fn shape(&self) -> &PatchShape {
        &self.shape
    }

    /// `X_r`: a world point in the patch frame (eq 4), as [`Patch::to_local`].
    #[inline]
    pub fn to_local(&self, point_in_world: &Vector3<f64>) -> Vector3<f64> {
        self.rot_t * (point_in_world - self.center)
    }

    /// Euclidean distance from a local-frame point to the bounded patch surface.
    #[inline]
    pub fn distance_local(&self, q_l: &Vector3<f64>) -> f64 {
        (self.shape.closest_point_local(q_l) - q_l).norm()
    }

    /// [`Patch::distance`].
    #[inline]
    pub fn distance(&self, point_in_world: &Vector3<f64>) -> f64 {
        self.distance_local(&self.to_local(point_in_world))
    }

    /// Where the ray `origin + t·direction` (world frame, any `direction` length) enters the bounded
    /// surface from its front (the side its normal faces): the parameter `t > 0`, or `None` when the
    /// ray meets the surface from behind, misses the boundary or runs parallel to the tangent plane.
    /// Newton steps on the explicit form `z = h(u)` (eq 13, 23, 27) from the tangent plane's crossing.
    pub fn ray_entry(&self, origin: &Vector3<f64>, direction: &Vector3<f64>) -> Option<f64> {
        self.ray_entry_local(&self.to_local(origin), &self.direction_to_local(direction))
    }

    /// A world direction in the patch frame (rotation only).
    #[inline]
    pub fn direction_to_local(&self, direction_in_world: &Vector3<f64>) -> Vector3<f64> {
        self.rot_t * direction_in_world
    }

    /// [`PatchQuery::ray_entry`] with the ray's origin `o` and direction `d` in the patch frame.
    pub fn ray_entry_local(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<f64> {
        // The front side is local +z: the ray must come down onto the surface.
        if d.z >= -1e-12 * d.norm() {
            return None;
        }
        let mut t = -o.z / d.z;
        for _ in 0..4 {
            let u = o.xy() + d.xy() * t;
            let (h, dh) = explicit_height(self.shape.surface, &self.shape.curvatures, &u)?;
            // g(t) = z(t) − h(u(t)), g'(t) = d_z − ∇h·d_xy.
            let slope = d.z - dh.dot(&d.xy());
            if slope >= 0.0 {
                return None;
            }
            let step = (o.z + d.z * t - h) / slope;
            t -= step;
            if step.abs() <= 1e-9 * t.abs().max(1.0) {
                break;
            }
        }
        let u = o.xy() + d.xy() * t;
        (t > 0.0 && t.is_finite() && self.shape.contains_uv(&u)).then_some(t)
    }
}

/// Height `z(u)` of the explicit form of `surface` with curvatures `k` and its gradient `∂z/∂u`
/// (eq 13, 23, 27); `None` outside the domain of spheres/cylinders (`κ² uᵀu > 1`).
pub(super) fn explicit_height(surface: SurfaceType, k: &Vector2<f64>, u: &Vector2<f64>) -> Option<(f64, Vector2<f64>)> {
    match surface {
        SurfaceType::Sphere => sphere_height(k.x, u.norm_squared()).map(|(z, dz)| (z, u * dz)),
        SurfaceType::CircularCylinder => sphere_height(k.y, u.y * u.y).map(|(z, dz)| (z, Vector2::new(0.0, u.y * dz))),
        _ => Some(paraboloid_height(k, u)),
    }
}

/// Height and gradient of the paraboloid family (eq 13).
#[inline(always)]
fn paraboloid_height(k: &Vector2<f64>, u: &Vector2<f64>) -> (f64, Vector2<f64>) {
    (0.5 * (k.x * u.x * u.x + k.y * u.y * u.y), Vector2::new(k.x * u.x, k.y * u.y))
}

/// The Newton step `(I + g gᵀ + e_z diag(h))⁻¹ jte` of the closest-point problem on an explicit
/// surface with gradient `g` and diagonal Hessian `h` (eq 13), `None` unless positive definite.
#[inline(always)]
fn newton_step(g: &Vector2<f64>, e_z: f64, h: &Vector2<f64>, jte: &Vector2<f64>) -> Option<Vector2<f64>> {
    let a11 = 1.0 + g.x * g.x + e_z * h.x;
    let a22 = 1.0 + g.y * g.y + e_z * h.y;
    let a12 = g.x * g.y;
    let det = a11 * a22 - a12 * a12;
    if !(a11 > 0.0 && det > 1e-12 * a11 * a22) {
        return None;
    }
    Some(Vector2::new(a22 * jte.x - a12 * jte.y, a11 * jte.y - a12 * jte.x) / det)
}

/// Height of a sphere/circle of curvature κ at squared radius `s = uᵀu` (eq 23) in the stable form
/// `κ s / (1 + √(1 − κ² s))`, and `∂z/∂(u) / u` (so `∂z/∂u = u · dz`).
#[inline(always)]
fn sphere_height(kappa: f64, s: f64) -> Option<(f64, f64)> {
    let arg = 1.0 - kappa * kappa * s;
    if arg < 0.0 {
        return None;
    }
    let root = arg.sqrt();
    let z = kappa * s / (1.0 + root);
    let dz = if root > 1e-12 { kappa / root } else { kappa / 1e-12 };
    Some((z, dz))
}

fn closest_on_segment(u: &Vector2<f64>, a: &Vector2<f64>, b: &Vector2<f64>) -> Vector2<f64> {
    let d = b - a;
    let len2 = d.norm_squared();
    if len2 == 0.0 {
        return *a;
    }
    let t = ((u - a).dot(&d) / len2).clamp(0.0, 1.0);
    a + d * t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::tests::{all_types, example};
    use rand::SeedableRng;

    /// The Newton steps of the paraboloid closest point reach the projected Gauss–Newton result
    /// (inside and on the boundary), for points near and far from the surface.
    #[test]
    fn newton_closest_point_matches_gauss_newton() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        for (s, b) in all_types() {
            if !matches!(
                s,
                SurfaceType::EllipticParaboloid
                    | SurfaceType::HyperbolicParaboloid
                    | SurfaceType::CylindricParaboloid
                    | SurfaceType::CircularParaboloid
            ) {
                continue;
            }
            let shape = example(s, b).shape();
            let k = shape.curvatures;
            for i in 0..400 {
                let u = example(s, b).sample_uv(&mut rng) * (0.5 + 0.002 * i as f64);
                let q_l = Vector3::new(u.x, u.y, paraboloid_height(&k, &u).0 + 0.01 * ((i % 21) as f64 - 10.0) / 10.0);
                let newton = shape.closest_with(&q_l, Some(k), |u| Some(paraboloid_height(&k, u)));
                let gauss_newton = shape.closest_with(&q_l, None, |u| Some(paraboloid_height(&k, u)));
                let (dn, dg) = ((newton - q_l).norm(), (gauss_newton - q_l).norm());
                assert!((dn - dg).abs() <= 1e-12 + 1e-9 * dg, "{s:?} {i}: {dn} vs {dg}");
            }
        }
    }
}
