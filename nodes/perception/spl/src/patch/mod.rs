//! The 10 bounded curved patch types of IROS Table I: parameters, implicit/explicit forms, boundaries,
//! sampling, distances.
//!
//! A [`Patch`] stores the paper's minimal parameters — boundary `d`, curvatures `k`, exponential-map
//! rotation `r` (with `r_z = 0` for the 5-DoF, rotation-symmetric types) and centre `c` — plus the
//! covariance over exactly the minimal vector `[d, k, r|r_xy, c]` ([`Patch::params`]). Every other view
//! (rotation matrix, normal, pose, sampled points) is derived.
//!
//! Here: the patch and its parameters. The types and their degrees of freedom are in `types`, the
//! derived forms, sampling and distances in `forms`, the prepared query shape ([`PatchShape`],
//! [`PatchQuery`]) in `shape`, and the JSON form `Patch` is serialized through in `json`.

mod forms;
mod json;
mod shape;
mod types;

use json::PatchJson;
use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};
pub use shape::{PatchQuery, PatchShape};
pub use types::{dof, is_5dof, is_valid_combination, BoundaryType, SurfaceType, PATCH_TYPES};

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

impl Patch {
    /// A level disc: a plane with a circular boundary of `radius` m centred at `center`, its
    /// normal +z, with zero covariance (a designed patch, like [`Patch::new`]).
    pub fn level_disc(radius: f64, center: Vector3<f64>) -> Result<Self, PatchError> {
        Self::new(SurfaceType::Plane, BoundaryType::Circle, vec![radius], Vector2::zeros(), Vector3::zeros(), center)
    }

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
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A plane disc of radius 5 cm, 1 m in front of a camera on its optical axis (+z), facing the
    /// camera (a rotation by π about x turns local +z into camera −z).
    pub(crate) fn disc_facing_the_camera() -> Patch {
        Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::zeros(),
            Vector3::new(std::f64::consts::PI, 0.0, 0.0),
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap()
    }

    pub(crate) fn all_types() -> Vec<(SurfaceType, BoundaryType)> {
        PATCH_TYPES.to_vec()
    }

    #[test]
    fn the_ten_types_are_distinct_and_valid() {
        for (i, &(s, b)) in PATCH_TYPES.iter().enumerate() {
            assert!(is_valid_combination(s, b), "{s:?}/{b:?}");
            assert!(PATCH_TYPES[..i].iter().all(|&other| other != (s, b)), "{s:?}/{b:?} twice");
        }
    }

    pub(crate) fn example(surface: SurfaceType, boundary: BoundaryType) -> Patch {
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
}
