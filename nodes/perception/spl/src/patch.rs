//! The 10 bounded curved patch types of IROS Table I: parameters, implicit/explicit forms, boundaries,
//! sampling, distances.
//!
//! A [`Patch`] stores the paper's minimal parameters — boundary `d`, curvatures `k`, exponential-map
//! rotation `r` (with `r_z = 0` for the 5-DoF, rotation-symmetric types) and centre `c` — plus the
//! covariance over exactly the minimal vector `[d, k, r|r_xy, c]` ([`Patch::params`]). Every other view
//! (rotation matrix, normal, pose, sampled points) is derived.

use crate::geometry::{exp_map, Pose};
use nalgebra::{DMatrix, DVector, Isometry3, Matrix3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// Surface type (numbering fixed across the project: the surface constants of `msgs/msg/Patch.msg`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceType {
    /// Two curvatures of equal sign (10 DoF with ellipse boundary).
    EllipticParaboloid = 0,
    /// Two curvatures of opposite sign (10 DoF with ellipse boundary).
    HyperbolicParaboloid = 1,
    /// One non-zero curvature `k = [0 κ]` (9 DoF with rectangle boundary).
    CylindricParaboloid = 2,
    /// Equal curvatures `k = [κ κ]` (7 DoF with circle boundary).
    CircularParaboloid = 3,
    /// Zero curvature (6–11 DoF depending on the boundary).
    Plane = 4,
    /// Spherical cap with curvature κ (7 DoF with circle boundary).
    Sphere = 5,
    /// Circular half-cylinder, axis along local x (9 DoF with rectangle boundary).
    CircularCylinder = 6,
}

/// Boundary type in the local xy plane (numbering fixed across the project).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum BoundaryType {
    /// Axis-aligned ellipse with radii `d_e = [d_x d_y]` (eq 17).
    #[serde(rename = "ellipse")]
    Ellipse = 0,
    /// Circle with radius `d_c` (eq 17 with `d_e = [d_c d_c]`).
    #[serde(rename = "circle")]
    Circle = 1,
    /// Axis-aligned rectangle with half-widths `d_r = [d_x d_y]` (eq 18–19).
    #[serde(rename = "rect")]
    Rectangle = 2,
    /// Convex quadrilateral `d_q = [d_1 d_2 d_3 d_4 γ]` (eq 19, 21).
    #[serde(rename = "quad")]
    Quadrilateral = 3,
}

impl SurfaceType {
    /// All surface types in their fixed order.
    pub const ALL: [SurfaceType; 7] = [
        SurfaceType::EllipticParaboloid,
        SurfaceType::HyperbolicParaboloid,
        SurfaceType::CylindricParaboloid,
        SurfaceType::CircularParaboloid,
        SurfaceType::Plane,
        SurfaceType::Sphere,
        SurfaceType::CircularCylinder,
    ];

    /// JSON/CLI name.
    pub fn name(self) -> &'static str {
        match self {
            SurfaceType::EllipticParaboloid => "elliptic_paraboloid",
            SurfaceType::HyperbolicParaboloid => "hyperbolic_paraboloid",
            SurfaceType::CylindricParaboloid => "cylindric_paraboloid",
            SurfaceType::CircularParaboloid => "circular_paraboloid",
            SurfaceType::Plane => "plane",
            SurfaceType::Sphere => "sphere",
            SurfaceType::CircularCylinder => "circular_cylinder",
        }
    }

    /// Parse a JSON/CLI name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The boundary implied by a non-planar surface (IROS Table I); `None` for planes.
    pub fn implied_boundary(self) -> Option<BoundaryType> {
        match self {
            SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => Some(BoundaryType::Ellipse),
            SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => Some(BoundaryType::Rectangle),
            SurfaceType::CircularParaboloid | SurfaceType::Sphere => Some(BoundaryType::Circle),
            SurfaceType::Plane => None,
        }
    }

    /// Number of curvature parameters in the minimal vector.
    pub fn num_curvatures(self) -> usize {
        match self {
            SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => 2,
            SurfaceType::Plane => 0,
            _ => 1,
        }
    }
}

impl BoundaryType {
    /// All boundary types in their fixed order.
    pub const ALL: [BoundaryType; 4] = [BoundaryType::Ellipse, BoundaryType::Circle, BoundaryType::Rectangle, BoundaryType::Quadrilateral];

    /// JSON/CLI name.
    pub fn name(self) -> &'static str {
        match self {
            BoundaryType::Ellipse => "ellipse",
            BoundaryType::Circle => "circle",
            BoundaryType::Rectangle => "rect",
            BoundaryType::Quadrilateral => "quad",
        }
    }

    /// Parse a JSON/CLI name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|b| b.name() == name)
    }

    /// Number of boundary parameters `d`.
    pub fn num_params(self) -> usize {
        match self {
            BoundaryType::Ellipse | BoundaryType::Rectangle => 2,
            BoundaryType::Circle => 1,
            BoundaryType::Quadrilateral => 5,
        }
    }
}

/// Errors building or reading a patch.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PatchError {
    /// The surface/boundary pair is not one of the 10 types of IROS Table I.
    #[error("surface {surface:?} cannot have boundary {boundary:?} (IROS Table I)")]
    InvalidCombination { surface: SurfaceType, boundary: BoundaryType },
    /// A parameter vector of the wrong length.
    #[error("{what}: expected {expected} values, got {got}")]
    WrongLength { what: &'static str, expected: usize, got: usize },
    /// A non-finite or out-of-range parameter.
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
}

/// A bounded curved patch (IROS III) with quantified uncertainty.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(into = "PatchJson", try_from = "PatchJson")]
pub struct Patch {
    /// Surface type.
    pub surface: SurfaceType,
    /// Boundary type.
    pub boundary: BoundaryType,
    /// Boundary parameters `d` (ellipse/rect: 2, circle: 1, quad: 5 = `[d1 d2 d3 d4 γ]`).
    pub boundary_params: Vec<f64>,
    /// Curvatures `[κ_x κ_y]` (derived full form: `[0 κ]` for cylindric/cylinder, `[κ κ]` for
    /// circular/sphere, zeros for planes).
    pub curvatures: Vector2<f64>,
    /// Orientation vector `r` of the local frame (`r_z = 0` for 5-DoF types).
    pub rotation: Vector3<f64>,
    /// Centre `c` (symmetry point / apex) in the world frame.
    pub center: Vector3<f64>,
    /// Covariance (p × p) over [`Patch::params`].
    pub covariance: DMatrix<f64>,
    /// RMS point-to-surface distance of the points the patch was fitted to (m; first-order
    /// Euclidean distance), 0 for designed patches.
    pub residual: f64,
    /// Number of points the patch was fitted to (0 for designed patches).
    pub num_points: usize,
}

/// Whether `(surface, boundary)` is one of the 10 patch types of IROS Table I.
pub fn is_valid_combination(surface: SurfaceType, boundary: BoundaryType) -> bool {
    match surface.implied_boundary() {
        Some(b) => b == boundary,
        None => true,
    }
}

/// Whether the type has revolute symmetry and the 5-DoF pose `(r_xy, c)` (eq 6).
pub fn is_5dof(surface: SurfaceType, boundary: BoundaryType) -> bool {
    boundary == BoundaryType::Circle && matches!(surface, SurfaceType::CircularParaboloid | SurfaceType::Plane | SurfaceType::Sphere)
}

/// Degrees of freedom of a patch type (IROS Table I).
pub fn dof(surface: SurfaceType, boundary: BoundaryType) -> usize {
    boundary.num_params() + surface.num_curvatures() + if is_5dof(surface, boundary) { 2 } else { 3 } + 3
}

impl Patch {
    /// A patch from its parts, with zero covariance (a designed patch). Checks the type pair, the
    /// number of boundary parameters and finiteness; normalises `r_z = 0` for 5-DoF types and the
    /// curvature pattern of the surface type; for 5-DoF types a full `r` is replaced by
    /// `[r_xy(r) 0]` (same normal, eq 8).
    pub fn new(
        surface: SurfaceType,
        boundary: BoundaryType,
        boundary_params: Vec<f64>,
        curvatures: Vector2<f64>,
        rotation: Vector3<f64>,
        center: Vector3<f64>,
    ) -> Result<Self, PatchError> {
        if !is_valid_combination(surface, boundary) {
            return Err(PatchError::InvalidCombination { surface, boundary });
        }
        if boundary_params.len() != boundary.num_params() {
            return Err(PatchError::WrongLength { what: "boundary_params", expected: boundary.num_params(), got: boundary_params.len() });
        }
        let all_finite = boundary_params.iter().chain(curvatures.iter()).chain(rotation.iter()).chain(center.iter()).all(|v| v.is_finite());
        if !all_finite {
            return Err(PatchError::InvalidParameter("non-finite value".into()));
        }
        if boundary_params.iter().any(|&d| d < 0.0) {
            return Err(PatchError::InvalidParameter("negative boundary parameter".into()));
        }
        if boundary == BoundaryType::Quadrilateral {
            let gamma = boundary_params.get(4).copied().unwrap_or(0.0);
            if !(gamma > 0.0 && gamma < std::f64::consts::FRAC_PI_2) {
                return Err(PatchError::InvalidParameter(format!("quad angle γ = {gamma} outside (0, π/2) (eq 21)")));
            }
        }
        let curvatures = match surface {
            SurfaceType::Plane => Vector2::zeros(),
            SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => Vector2::new(0.0, curvatures.y),
            SurfaceType::CircularParaboloid | SurfaceType::Sphere => Vector2::new(curvatures.x, curvatures.x),
            _ => curvatures,
        };
        // 5-DoF types keep only the normal: r → [r_xy(r) 0] (eq 7–8), which preserves R(r) ẑ.
        let rotation = if is_5dof(surface, boundary) {
            if rotation.z == 0.0 {
                rotation
            } else {
                let rxy = crate::geometry::r_xy(&rotation);
                Vector3::new(rxy.x, rxy.y, 0.0)
            }
        } else {
            rotation
        };
        let p = dof(surface, boundary);
        Ok(Self {
            surface,
            boundary,
            boundary_params,
            curvatures,
            rotation,
            center,
            covariance: DMatrix::zeros(p, p),
            residual: 0.0,
            num_points: 0,
        })
    }

    /// A patch from its minimal parameter vector `[d, k, r|r_xy, c]` (IROS Table I order).
    pub fn from_params(surface: SurfaceType, boundary: BoundaryType, params: &[f64]) -> Result<Self, PatchError> {
        if !is_valid_combination(surface, boundary) {
            return Err(PatchError::InvalidCombination { surface, boundary });
        }
        let p = dof(surface, boundary);
        if params.len() != p {
            return Err(PatchError::WrongLength { what: "params", expected: p, got: params.len() });
        }
        let nd = boundary.num_params();
        let nk = surface.num_curvatures();
        let d = params.get(..nd).unwrap_or_default().to_vec();
        let k = params.get(nd..nd + nk).unwrap_or_default();
        let curvatures = match (surface, k) {
            (_, [kx, ky]) => Vector2::new(*kx, *ky),
            (SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder, [kappa]) => Vector2::new(0.0, *kappa),
            (_, [kappa]) => Vector2::new(*kappa, *kappa),
            _ => Vector2::zeros(),
        };
        let rest = params.get(nd + nk..).unwrap_or_default();
        let (rotation, c) = match rest {
            [rx, ry, cx, cy, cz] => (Vector3::new(*rx, *ry, 0.0), Vector3::new(*cx, *cy, *cz)),
            [rx, ry, rz, cx, cy, cz] => (Vector3::new(*rx, *ry, *rz), Vector3::new(*cx, *cy, *cz)),
            _ => return Err(PatchError::WrongLength { what: "pose params", expected: p - nd - nk, got: rest.len() }),
        };
        Self::new(surface, boundary, d, curvatures, rotation, c)
    }

    /// Degrees of freedom `p` (IROS Table I).
    pub fn dof(&self) -> usize {
        dof(self.surface, self.boundary)
    }

    /// Whether the pose is the 5-DoF `(r_xy, c)` (eq 6).
    pub fn is_5dof(&self) -> bool {
        is_5dof(self.surface, self.boundary)
    }

    /// Minimal curvature parameters (`[κx κy]`, `[κ]` or empty).
    pub fn curvature_params(&self) -> Vec<f64> {
        match self.surface.num_curvatures() {
            2 => vec![self.curvatures.x, self.curvatures.y],
            1 => vec![self.curvatures.y],
            _ => Vec::new(),
        }
    }

    /// The minimal parameter vector `[d, k, r|r_xy, c]` (IROS Table I; SPL order).
    pub fn params(&self) -> DVector<f64> {
        let mut v: Vec<f64> = self.boundary_params.clone();
        v.extend(self.curvature_params());
        v.push(self.rotation.x);
        v.push(self.rotation.y);
        if !self.is_5dof() {
            v.push(self.rotation.z);
        }
        v.extend(self.center.iter());
        DVector::from_vec(v)
    }

    /// `diag(κx, κy, κz)` of the common implicit form (eq 37): paraboloids `κz = 0`, sphere
    /// `[κ κ κ]`, circular cylinder `[0 κ κ]`.
    pub fn k3(&self) -> Vector3<f64> {
        let k = self.curvatures;
        match self.surface {
            SurfaceType::Sphere => Vector3::new(k.x, k.x, k.x),
            SurfaceType::CircularCylinder => Vector3::new(0.0, k.y, k.y),
            _ => Vector3::new(k.x, k.y, 0.0),
        }
    }

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
}

/// Height `z(u)` of the explicit form of `surface` with curvatures `k` and its gradient `∂z/∂u`
/// (eq 13, 23, 27); `None` outside the domain of spheres/cylinders (`κ² uᵀu > 1`).
fn explicit_height(surface: SurfaceType, k: &Vector2<f64>, u: &Vector2<f64>) -> Option<(f64, Vector2<f64>)> {
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

/// JSON form of a patch (the `patch_mapper fit` schema).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PatchJson {
    /// Surface type name.
    pub surface: SurfaceType,
    /// Boundary type name.
    pub boundary: BoundaryType,
    /// `[κx, κy]`.
    pub curvatures: [f64; 2],
    /// Boundary parameters `d`.
    pub boundary_params: Vec<f64>,
    /// Orientation vector `[rx, ry, rz]`.
    pub rotation: [f64; 3],
    /// Centre `[x, y, z]`.
    pub center: [f64; 3],
    /// Minimal parameter vector (derived; ignored when reading).
    #[serde(default)]
    pub params: Vec<f64>,
    /// Covariance rows (p × p over `params`); empty means zero.
    #[serde(default)]
    pub covariance: Vec<Vec<f64>>,
    /// RMS residual of the fit points (m).
    #[serde(default)]
    pub residual: f64,
    /// Number of fit points.
    #[serde(default)]
    pub num_points: usize,
}

impl From<Patch> for PatchJson {
    fn from(p: Patch) -> Self {
        let rows = p.covariance.nrows();
        PatchJson {
            surface: p.surface,
            boundary: p.boundary,
            curvatures: [p.curvatures.x, p.curvatures.y],
            params: p.params().iter().copied().collect(),
            boundary_params: p.boundary_params,
            rotation: [p.rotation.x, p.rotation.y, p.rotation.z],
            center: [p.center.x, p.center.y, p.center.z],
            covariance: (0..rows).map(|i| p.covariance.row(i).iter().copied().collect()).collect(),
            residual: p.residual,
            num_points: p.num_points,
        }
    }
}

impl TryFrom<PatchJson> for Patch {
    type Error = PatchError;

    fn try_from(j: PatchJson) -> Result<Self, Self::Error> {
        let mut patch = Patch::new(
            j.surface,
            j.boundary,
            j.boundary_params,
            Vector2::new(j.curvatures[0], j.curvatures[1]),
            Vector3::from(j.rotation),
            Vector3::from(j.center),
        )?;
        let p = patch.dof();
        if !j.covariance.is_empty() {
            if j.covariance.len() != p || j.covariance.iter().any(|row| row.len() != p) {
                return Err(PatchError::WrongLength { what: "covariance rows", expected: p, got: j.covariance.len() });
            }
            patch.covariance = DMatrix::from_fn(p, p, |r, c| j.covariance.get(r).and_then(|row| row.get(c)).copied().unwrap_or(0.0));
        }
        patch.residual = j.residual;
        patch.num_points = j.num_points;
        Ok(patch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    pub(crate) fn all_types() -> Vec<(SurfaceType, BoundaryType)> {
        vec![
            (SurfaceType::EllipticParaboloid, BoundaryType::Ellipse),
            (SurfaceType::HyperbolicParaboloid, BoundaryType::Ellipse),
            (SurfaceType::CylindricParaboloid, BoundaryType::Rectangle),
            (SurfaceType::CircularParaboloid, BoundaryType::Circle),
            (SurfaceType::Plane, BoundaryType::Ellipse),
            (SurfaceType::Plane, BoundaryType::Circle),
            (SurfaceType::Plane, BoundaryType::Rectangle),
            (SurfaceType::Plane, BoundaryType::Quadrilateral),
            (SurfaceType::Sphere, BoundaryType::Circle),
            (SurfaceType::CircularCylinder, BoundaryType::Rectangle),
        ]
    }

    fn example(surface: SurfaceType, boundary: BoundaryType) -> Patch {
        let d = match boundary {
            BoundaryType::Ellipse => vec![0.08, 0.05],
            BoundaryType::Circle => vec![0.06],
            BoundaryType::Rectangle => vec![0.07, 0.04],
            BoundaryType::Quadrilateral => vec![0.05, 0.07, 0.06, 0.04, 0.6],
        };
        let k = match surface {
            SurfaceType::HyperbolicParaboloid => Vector2::new(-3.0, 5.0),
            _ => Vector2::new(3.0, 5.0),
        };
        Patch::new(surface, boundary, d, k, Vector3::new(0.3, -0.2, 0.5), Vector3::new(0.1, 0.2, 1.0)).unwrap()
    }

    #[test]
    fn dofs_match_table_one() {
        let expected = [10, 10, 9, 7, 8, 6, 8, 11, 7, 9];
        for ((s, b), e) in all_types().into_iter().zip(expected) {
            assert_eq!(dof(s, b), e, "{s:?} {b:?}");
            let p = example(s, b);
            assert_eq!(p.params().len(), e);
            let back = Patch::from_params(s, b, p.params().as_slice()).unwrap();
            assert_eq!(back, p);
        }
        assert!(Patch::new(
            SurfaceType::Sphere,
            BoundaryType::Rectangle,
            vec![1.0, 1.0],
            Vector2::zeros(),
            Vector3::zeros(),
            Vector3::zeros()
        )
        .is_err());
    }

    #[test]
    fn sampled_points_lie_on_surface_and_inside() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for (s, b) in all_types() {
            let p = example(s, b);
            for q in p.sample_points(&mut rng, 200) {
                assert!(p.implicit_world(&q).abs() < 1e-12, "{s:?}");
                assert!(p.contains_point(&q));
                assert!(p.distance(&q) < 1e-9, "{s:?} {b:?} d {}", p.distance(&q));
            }
        }
    }

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

    #[test]
    fn distance_is_euclidean_to_bounded_surface() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(8);
        for (s, b) in all_types() {
            let p = example(s, b);
            for _ in 0..50 {
                // Offset along the local normal of the explicit surface: distance = offset.
                let u = p.sample_uv(&mut rng) * 0.8;
                let (_, g) = p.height(&u).unwrap();
                let n_l = Vector3::new(-g.x, -g.y, 1.0).normalize();
                let off = 0.003;
                let q_l = p.explicit_local(&u).unwrap() + n_l * off;
                let q_w = p.rotation_matrix() * q_l + p.center;
                assert!((p.distance(&q_w) - off).abs() < 1e-6, "{s:?} {b:?} {}", p.distance(&q_w));
            }
        }
        // Beyond the boundary of a plane: distance to the rim.
        let plane =
            Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![0.1], Vector2::zeros(), Vector3::zeros(), Vector3::zeros()).unwrap();
        assert!((plane.distance(&Vector3::new(0.13, 0.0, 0.04)) - 0.05).abs() < 1e-9);
    }

    #[test]
    fn boundary_area_and_quad_convexity() {
        let q = example(SurfaceType::Plane, BoundaryType::Quadrilateral);
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let h = q.boundary_half_extents();
        let n = 200_000;
        let inside = (0..n).filter(|_| q.contains_uv(&Vector2::new(rng.random_range(-h.x..h.x), rng.random_range(-h.y..h.y)))).count();
        let mc = inside as f64 / n as f64 * 4.0 * h.x * h.y;
        assert!((mc - q.boundary_area()).abs() / q.boundary_area() < 0.01);
    }

    #[test]
    fn json_round_trip() {
        let mut p = example(SurfaceType::CircularCylinder, BoundaryType::Rectangle);
        p.covariance = DMatrix::identity(9, 9) * 1e-4;
        let s = serde_json::to_string(&p).unwrap();
        assert!(s.contains("\"surface\":\"circular_cylinder\"") && s.contains("\"boundary\":\"rect\""));
        let back: Patch = serde_json::from_str(&s).unwrap();
        assert_eq!(back, p);
        let bad = s.replace("\"rect\"", "\"circle\"");
        assert!(serde_json::from_str::<Patch>(&bad).is_err());
    }
}
