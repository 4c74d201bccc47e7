//! The patch as the step executor stores and compares it: the paper's minimal parameters (surface and
//! boundary type, boundary params `d`, curvatures `k`, exponential-map rotation `r`, centre `c`;
//! J Table 1, eq. 3–5) with the pose expressed in `base_link` (J 6.3: "patches are stored relative to
//! the robot"). Conversions to/from the mapper's representation live at the ROS boundary.

use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Surface types (names.md order and YAML names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceType {
    EllipticParaboloid = 0,
    HyperbolicParaboloid = 1,
    CylindricParaboloid = 2,
    CircularParaboloid = 3,
    Plane = 4,
    Sphere = 5,
    CircularCylinder = 6,
}

/// Boundary types (names.md order and YAML names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoundaryType {
    Ellipse = 0,
    Circle = 1,
    #[serde(rename = "rect")]
    Rectangle = 2,
    #[serde(rename = "quad")]
    Quadrilateral = 3,
}

impl SurfaceType {
    /// From the Patch.msg constant.
    pub fn from_u8(value: u8) -> Option<Self> {
        use SurfaceType::*;
        [EllipticParaboloid, HyperbolicParaboloid, CylindricParaboloid, CircularParaboloid, Plane, Sphere, CircularCylinder]
            .get(usize::from(value))
            .copied()
    }
}

impl BoundaryType {
    /// From the Patch.msg constant.
    pub fn from_u8(value: u8) -> Option<Self> {
        use BoundaryType::*;
        [Ellipse, Circle, Rectangle, Quadrilateral].get(usize::from(value)).copied()
    }

    /// Number of boundary parameters (IROS Table I / Patch.msg: d_e, d_r = 2; d_c = 1; d_q = 5).
    pub fn param_count(self) -> usize {
        match self {
            BoundaryType::Ellipse | BoundaryType::Rectangle => 2,
            BoundaryType::Circle => 1,
            BoundaryType::Quadrilateral => 5,
        }
    }
}

/// A bounded curved patch with its pose in some frame (here: `base_link`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PatchGeometry {
    pub surface: SurfaceType,
    pub boundary: BoundaryType,
    /// Boundary parameters d (m).
    pub d: Vec<f64>,
    /// Curvatures k (1/m): [κx, κy] for paraboloids, [κ] for sphere/cylinder, [] for planes.
    pub k: Vec<f64>,
    /// Exponential-map rotation r (J eq. 4).
    pub r: [f64; 3],
    /// Centre c (m).
    pub c: [f64; 3],
}

/// Validation failure of a patch, naming the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct PatchError {
    pub field: &'static str,
    pub message: String,
}

impl PatchGeometry {
    /// Check parameter counts and finiteness.
    pub fn validate(&self) -> Result<(), PatchError> {
        let expected_d = self.boundary.param_count();
        if self.d.len() != expected_d {
            return Err(PatchError { field: "d", message: format!("{:?} needs {expected_d} values, got {}", self.boundary, self.d.len()) });
        }
        if self.k.len() > 2 {
            return Err(PatchError { field: "k", message: format!("at most 2 curvatures, got {}", self.k.len()) });
        }
        let checks: [(&'static str, &[f64]); 4] = [("d", &self.d), ("k", &self.k), ("r", &self.r), ("c", &self.c)];
        for (field, values) in checks {
            if values.iter().any(|v| !v.is_finite()) {
                return Err(PatchError { field, message: "values must be finite".into() });
            }
        }
        Ok(())
    }

    /// Rotation R(r) of the patch's local frame (J eq. 4, Rodrigues).
    pub fn rotation(&self) -> Rotation3<f64> {
        Rotation3::from_scaled_axis(Vector3::from(self.r))
    }

    /// `frame_from_patch` as an isometry.
    pub fn pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(Vector3::from(self.c)), UnitQuaternion::from_rotation_matrix(&self.rotation()))
    }

    /// Unit normal (local z axis) in the patch's frame.
    pub fn normal(&self) -> Vector3<f64> {
        self.rotation() * Vector3::z()
    }

    /// The same patch expressed in another frame: `target_from_source · patch_in_source`.
    pub fn transformed(&self, target_from_source: &Isometry3<f64>) -> Self {
        let rotation = target_from_source.rotation.to_rotation_matrix() * self.rotation();
        let centre = target_from_source * nalgebra::Point3::from(self.c);
        Self { r: rotation.scaled_axis().into(), c: centre.coords.into(), ..self.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_names_match_names_md() {
        let patch = PatchGeometry {
            surface: SurfaceType::CircularCylinder,
            boundary: BoundaryType::Rectangle,
            d: vec![0.03, 0.02],
            k: vec![10.0],
            r: [0.0, 0.0, 0.0],
            c: [0.1, 0.0, -0.28],
        };
        let text = serde_yaml_ng::to_string(&patch).unwrap();
        assert!(text.contains("surface: circular_cylinder") && text.contains("boundary: rect"), "{text}");
        assert_eq!(SurfaceType::from_u8(4), Some(SurfaceType::Plane));
        assert_eq!(BoundaryType::from_u8(3), Some(BoundaryType::Quadrilateral));
        assert_eq!(BoundaryType::from_u8(4), None);
    }

    #[test]
    fn transform_moves_centre_and_normal() {
        let patch = PatchGeometry {
            surface: SurfaceType::Plane,
            boundary: BoundaryType::Circle,
            d: vec![0.02],
            k: vec![],
            r: [0.0, 0.0, 0.0],
            c: [1.0, 0.0, 0.0],
        };
        let quarter_about_x = Isometry3::new(Vector3::new(0.0, 0.0, 1.0), Vector3::new(std::f64::consts::FRAC_PI_2, 0.0, 0.0));
        let moved = patch.transformed(&quarter_about_x);
        assert!((Vector3::from(moved.c) - Vector3::new(1.0, 0.0, 1.0)).norm() < 1e-12);
        assert!((moved.normal() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn validate_names_field() {
        let mut patch = PatchGeometry {
            surface: SurfaceType::Plane,
            boundary: BoundaryType::Ellipse,
            d: vec![0.02],
            k: vec![],
            r: [0.0; 3],
            c: [0.0; 3],
        };
        assert_eq!(patch.validate().unwrap_err().field, "d");
        patch.d = vec![0.02, f64::NAN];
        assert_eq!(patch.validate().unwrap_err().field, "d");
        patch.d = vec![0.02, 0.01];
        patch.c[1] = f64::INFINITY;
        assert_eq!(patch.validate().unwrap_err().field, "c");
    }
}
