//! The Surface Patch Library: bounded curved surface patches with quantified uncertainty (IROS;
//! Vona & Kanoulas), as a library with no ROS, camera or mapping code in it.
//!
//! - [`patch`]: the 10 patch types of IROS Table I (5 surfaces × their boundaries), minimal
//!   parameters and covariance, implicit/explicit forms, sampling, distances.
//! - [`geometry`]: exponential/log maps, their Jacobians, 5-DoF rotations, pose chains with
//!   covariance (IROS II).
//! - [`sensor`]: range-sensor error models (J eq 2, Murray–Little) giving each point its covariance.
//! - [`fit`]: the WLM fit of IROS IV with boundary, classification and Σ; [`fit::neighbourhood`]:
//!   one neighbourhood as J 3.2.1 step 13 fits it.
//! - [`validate`]: J 3.3's residual, coverage and curvature tests, and the foothold tests tilt
//!   (against gravity) and edge (the terrain in the foot disc's column).
//! - [`transform`]: a patch moved by a rigid transform with its covariance.
//! - [`fuse`]: two observations of one patch fused with their covariances (information-form Kalman
//!   update in the tangent space of the pose), the Mahalanobis association gate.
//! - [`points_io`]: point files (`x y z` text, PCD ASCII/binary).
//!
//! Fitting a patch to points, in five lines:
//!
//! ```
//! use nalgebra::Vector3;
//! use patchwalk_spl::fit::neighbourhood::{fit_neighbourhood, NeighbourhoodFit};
//!
//! let points: Vec<Vector3<f64>> = (0..400).map(|i| Vector3::new(f64::from(i % 20) * 0.004 - 0.04, f64::from(i / 20) * 0.004 - 0.04, 1.0)).collect();
//! let patch = fit_neighbourhood(&points, &points, &NeighbourhoodFit::default()).unwrap();
//! assert_eq!(patch.surface, patchwalk_spl::patch::SurfaceType::Plane);
//! ```

pub mod fit;
pub mod fuse;
pub mod fuse_views;
pub mod geometry;
pub mod patch;
pub mod points_io;
pub mod sensor;
pub mod transform;
pub mod validate;
