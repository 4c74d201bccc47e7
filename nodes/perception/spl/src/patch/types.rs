//! The patch types of IROS Table I: the 7 surface types, the 4 boundary types (eq 17–21), which
//! pairs form the 10 patch types, and their degrees of freedom (5-DoF pose `(r_xy, c)` for the
//! revolute-symmetric ones, eq 6). The numbering is fixed across the project: it is the constants
//! of `msgs/msg/Patch.msg`.

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

    /// How many of the boundary parameters are extents (lengths, the first ones): all but a
    /// quadrilateral's angle γ.
    pub fn num_extents(self) -> usize {
        match self {
            BoundaryType::Quadrilateral => 4,
            b => b.num_params(),
        }
    }
}

/// Whether `(surface, boundary)` is one of the 10 patch types of IROS Table I.
pub fn is_valid_combination(surface: SurfaceType, boundary: BoundaryType) -> bool {
    match surface.implied_boundary() {
        Some(b) => b == boundary,
        None => true,
    }
}

/// The 10 patch types (surface, boundary) in the order of IROS Table I.
pub const PATCH_TYPES: [(SurfaceType, BoundaryType); 10] = [
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
];

/// Whether the type has revolute symmetry and the 5-DoF pose `(r_xy, c)` (eq 6).
pub fn is_5dof(surface: SurfaceType, boundary: BoundaryType) -> bool {
    boundary == BoundaryType::Circle && matches!(surface, SurfaceType::CircularParaboloid | SurfaceType::Plane | SurfaceType::Sphere)
}

/// Degrees of freedom of a patch type (IROS Table I).
pub fn dof(surface: SurfaceType, boundary: BoundaryType) -> usize {
    boundary.num_params() + surface.num_curvatures() + if is_5dof(surface, boundary) { 2 } else { 3 } + 3
}
