//! Patch validation: J 3.3's residual (eq 15), coverage (eq 16–17) and curvature tests, and three
//! foothold tests beyond them: tilt against gravity, edges/folds under the foot disc, and the disc
//! seen by the camera. Every rejection names the failed test, the measured value and its threshold.
//! One test per file: [`residual`], [`coverage`], [`curvature`], [`tilt`], [`edge`], [`visibility`].
//!
//! [`validate_patch`] runs J's tests and the edge test on the neighbourhood alone;
//! [`validate_foothold`] also takes gravity (the tilt test) and the points of the foot disc's
//! column (the edge test), as the mapper has them. [`ValidateConfig::j33`] is J 3.3 as written.

pub mod coverage;
pub mod curvature;
pub mod edge;
pub mod residual;
pub mod tilt;
pub mod visibility;

pub use coverage::{coverage_bad_cells, coverage_cell_size, coverage_cells, CoverageCell, SampledBall};
pub use curvature::principal_curvature_range;
pub use edge::{disc_offset, FootColumn};
pub use residual::residual;
pub use tilt::tilt_deg;
pub use visibility::{DiscView, PixelView};

use crate::patch::{Patch, PatchQuery};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Validation thresholds (J 3.3's defaults are the paper's values; the coverage counting and the
/// foothold tests say why they differ).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ValidateConfig {
    /// Residual threshold T_r (m) on the RMS Euclidean distance (J 3.3.1: 0.01 m).
    pub residual_threshold: f64,
    /// Coverage cell pitch w_c (m) (J 3.3.2: 0.01 m).
    pub cell_size: f64,
    /// Inside-count factor ζ_i of T_i = ζ_i N_e (J eq 17: 0.8).
    pub zeta_inside: f64,
    /// Outside-count factor ζ_o of T_o = ζ_o N_e (J eq 17: 0.2).
    pub zeta_outside: f64,
    /// Bad-cell limit T_p as a fraction of N_p (J 3.3.2: 0.3).
    pub bad_cell_fraction: f64,
    /// Minimum curvature κ_min,t (m⁻¹) (J 3.3.3 / \[10\]: −13.6).
    pub curvature_min: f64,
    /// Maximum curvature κ_max,t (m⁻¹) (J 3.3.3 / \[10\]: 19.7).
    pub curvature_max: f64,
    /// Sub-samples per cell side for the cell ∩ boundary area A_i (approximation of the exact
    /// intersection area; 4 → 16 samples per cell).
    pub area_subsamples: usize,
    /// Least expected points per full cell, N_e of J eq 17. J's w_c = 0.01 m presumes dense data
    /// (a 640×480 frame puts tens of points in a 1 cm cell); on sparser data (a 5 mm birds-eye
    /// raycast gives about 4) the integer counts of a regular pixel grid alias against the cell
    /// grid and half the cells of a perfect fit come out "bad". The cell then grows to
    /// `w = max(w_c, √(A·N_min/N))` so that N_e ≥ N_min. 0 keeps w_c as it is.
    pub min_points_per_cell: f64,
    /// Counting tolerance k of J eq 16 in standard deviations: a cell is bad when
    /// `n_in < A_i/w² · T_i − k·√(A_i/w² · N_e)` or `n_out > (1 − A_i/w²) · T_o + k·√((1 − A_i/w²) · N_e)`.
    /// J's thresholds compare counts with their expectation; the counts of a correct fit scatter
    /// about it by ≈ √expected (Poisson; ±1 point per cell side on a regular pixel grid), which
    /// J's dense data (N_e ≫ 10) makes negligible and a sparse birds-eye raycast (N_e ≈ 8) does not.
    /// 0 is J's test as written.
    pub count_tolerance_sigmas: f64,
    /// Tilt limit θ_max (degrees) of the patch normal from gravity's up ([`tilt`]: 20°, the slope
    /// where the RPBP's plastic sole slides, μ ≈ 0.45, with 20 % of μ kept in reserve). 180 or more
    /// switches the test off.
    pub tilt_max_deg: f64,
    /// Edge/fold limit (m) on how far the terrain inside the foot disc lies off the patch surface
    /// ([`edge`]: 0.02 m). Infinite switches the test off.
    pub edge_max_offset_m: f64,
    /// Quantile of the disc points' distances that is compared with `edge_max_offset_m` (0.98: 2 %
    /// of the points may be stray pixels; 1 is J 3.3.1's `ρ_alt = max ‖q − p‖`).
    pub edge_quantile: f64,
    /// Half height (m) of the foot disc's column about the patch plane: points further along the
    /// normal are not part of the foothold ([`edge`]: 0.25 m, more than a stair riser).
    pub edge_column_height_m: f64,
    /// Largest share of the foot disc's pixels (those whose ray enters the fitted patch inside its
    /// boundary) that did not measure its surface: no depth, or depth more than `edge_max_offset_m`
    /// behind or in front of it ([`visibility`]). Infinite (the default) switches the test off;
    /// [`visibility::SUGGESTED_UNSEEN_MAX_FRACTION`] (0.02) switches it on.
    pub unseen_max_fraction: f64,
    /// Largest share of the foot disc's pixels that see through it or into a hole bordered by terrain
    /// off its plane (the open-rim test, [`visibility`]). Infinite (the default) switches the test
    /// off; [`visibility::SUGGESTED_OPEN_RIM_MAX_FRACTION`] (0.01) switches it on.
    pub open_rim_max_fraction: f64,
    /// Largest share of the foot disc's area whose image falls outside the camera's image (or behind
    /// it) when the caller knows the camera ([`Foothold::out_of_view`], [`visibility`]): the rest of
    /// the foot was not seen, and neither is the terrain that the edge test would find there.
    /// 0.02 by default (a rim segment about 0.1 r deep, 5 mm of a 5 cm foot); infinite switches it off.
    pub out_of_view_max_fraction: f64,
    /// Judge coverage only where the patch surface lies inside the ball the points were gathered
    /// from, when the caller gives it ([`Foothold::sampled`], [`coverage`]'s module doc). False is
    /// J eq 16–17 as written over the whole boundary.
    pub coverage_within_sampled_ball: bool,
}

impl Default for ValidateConfig {
    fn default() -> Self {
        Self {
            residual_threshold: 0.01,
            cell_size: 0.01,
            zeta_inside: 0.8,
            zeta_outside: 0.2,
            bad_cell_fraction: 0.3,
            curvature_min: -13.6,
            curvature_max: 19.7,
            area_subsamples: 4,
            min_points_per_cell: 8.0,
            count_tolerance_sigmas: 1.0,
            tilt_max_deg: tilt::DEFAULT_TILT_MAX_DEG,
            edge_max_offset_m: 0.02,
            edge_quantile: 0.98,
            edge_column_height_m: 0.25,
            unseen_max_fraction: f64::INFINITY,
            open_rim_max_fraction: f64::INFINITY,
            out_of_view_max_fraction: visibility::DEFAULT_OUT_OF_VIEW_MAX_FRACTION,
            coverage_within_sampled_ball: true,
        }
    }
}

impl ValidateConfig {
    /// J 3.3 as written: fixed w_c cells over the whole boundary, J eq 16's counts without
    /// tolerance, no tilt or edge test.
    pub fn j33() -> Self {
        Self {
            min_points_per_cell: 0.0,
            coverage_within_sampled_ball: false,
            count_tolerance_sigmas: 0.0,
            tilt_max_deg: f64::INFINITY,
            edge_max_offset_m: f64::INFINITY,
            unseen_max_fraction: f64::INFINITY,
            open_rim_max_fraction: f64::INFINITY,
            out_of_view_max_fraction: f64::INFINITY,
            ..Self::default()
        }
    }

    /// The checks a configuration must pass (a node refuses a parameter set that fails them), naming
    /// the key.
    pub fn check(&self) -> Result<(), String> {
        let positive =
            |name: &str, v: f64| if v.is_nan() || v <= 0.0 { Err(format!("validate.{name} must be positive, got {v}")) } else { Ok(()) };
        positive("residual_threshold", self.residual_threshold)?;
        positive("cell_size", self.cell_size)?;
        positive("tilt_max_deg", self.tilt_max_deg)?;
        positive("edge_max_offset_m", self.edge_max_offset_m)?;
        positive("edge_column_height_m", self.edge_column_height_m)?;
        positive("unseen_max_fraction", self.unseen_max_fraction)?;
        positive("open_rim_max_fraction", self.open_rim_max_fraction)?;
        positive("out_of_view_max_fraction", self.out_of_view_max_fraction)?;
        if !(0.0..=1.0).contains(&self.edge_quantile) || self.edge_quantile == 0.0 {
            return Err(format!("validate.edge_quantile must be in (0, 1], got {}", self.edge_quantile));
        }
        if self.min_points_per_cell.is_nan() || self.min_points_per_cell < 0.0 {
            return Err(format!("validate.min_points_per_cell must be 0 or more, got {}", self.min_points_per_cell));
        }
        Ok(())
    }
}

/// What the foothold tests need beyond the fitted neighbourhood.
#[derive(Clone, Copy, Debug, Default)]
pub struct Foothold<'a> {
    /// Gravity's up in the points' frame (any length); `None`: no tilt test.
    pub up: Option<Vector3<f64>>,
    /// The points of the foot disc's column (see [`edge`]); `None`: the neighbourhood itself.
    pub column: Option<&'a [Vector3<f64>]>,
    /// The ball the neighbourhood was gathered from (the seed and r), for the coverage test (the
    /// boundary beyond it is judged on `column`); `None`: the points are taken to cover the whole
    /// boundary.
    pub sampled: Option<SampledBall>,
    /// What the pixels over the foot disc measured (see [`visibility`]); `None`: no visibility test.
    pub view: Option<DiscView>,
    /// Share of the foot disc's area outside the camera's image ([`visibility::out_of_view_fraction`]);
    /// `None`: the camera is not known, no out-of-view test.
    pub out_of_view: Option<f64>,
}

/// One test's outcome: the measured value against its threshold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TestResult {
    /// Whether the test passed.
    pub passed: bool,
    /// The measured value.
    pub value: f64,
    /// The threshold it was compared with.
    pub threshold: f64,
}

impl TestResult {
    /// A test that passes when `value` does not exceed `threshold`.
    pub fn at_most(value: f64, threshold: f64) -> Self {
        Self { passed: value <= threshold, value, threshold }
    }
}

/// Result of [`validate_patch`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// RMS Euclidean point-to-patch distance (m) vs T_r (J eq 15).
    pub residual: TestResult,
    /// Number of bad coverage cells vs T_p (J eq 16–17).
    pub coverage: TestResult,
    /// Minimum principal curvature (m⁻¹) vs κ_min,t (passes if value ≥ threshold).
    pub curvature_min: TestResult,
    /// Maximum principal curvature (m⁻¹) vs κ_max,t (passes if value ≤ threshold).
    pub curvature_max: TestResult,
    /// Tilt of the normal from up (degrees) vs θ_max ([`tilt`]); `None` without gravity.
    pub tilt: Option<TestResult>,
    /// Quantile distance (m) of the foot disc's terrain off the surface vs its limit ([`edge`]).
    pub edge: Option<TestResult>,
    /// Share of the foot disc's pixels that did not measure its surface vs its limit ([`visibility`]).
    #[serde(default)]
    pub unseen: Option<TestResult>,
    /// Share of the foot disc's pixels that see through it or into a hole bordered by terrain off its
    /// plane vs its limit (the open-rim test, [`visibility`]).
    #[serde(default)]
    pub open_rim: Option<TestResult>,
    /// Share of the foot disc's area outside the camera's image vs its limit ([`visibility`]).
    #[serde(default)]
    pub out_of_view: Option<TestResult>,
}

impl Validation {
    /// Whether the patch passed every test.
    pub fn is_valid(&self) -> bool {
        self.residual.passed
            && self.coverage.passed
            && self.curvature_ok()
            && self.tilt_ok()
            && self.edge_ok()
            && self.unseen_ok()
            && self.open_rim_ok()
            && self.in_view_ok()
    }

    /// Whether the tilt test passed (or was not run).
    pub fn tilt_ok(&self) -> bool {
        self.tilt.is_none_or(|t| t.passed)
    }

    /// Whether the edge test passed (or was not run).
    pub fn edge_ok(&self) -> bool {
        self.edge.is_none_or(|t| t.passed)
    }

    /// Whether the visibility test passed (or was not run).
    pub fn unseen_ok(&self) -> bool {
        self.unseen.is_none_or(|t| t.passed)
    }

    /// Whether the open-rim test passed (or was not run).
    pub fn open_rim_ok(&self) -> bool {
        self.open_rim.is_none_or(|t| t.passed)
    }

    /// Whether the out-of-view test passed (or was not run).
    pub fn in_view_ok(&self) -> bool {
        self.out_of_view.is_none_or(|t| t.passed)
    }

    /// Whether both curvature bounds hold.
    pub fn curvature_ok(&self) -> bool {
        self.curvature_min.passed && self.curvature_max.passed
    }

    /// One line per failed test, naming it and the amount by which it failed.
    pub fn failures(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.residual.passed {
            out.push(format!("residual {:.4} m > {:.4} m", self.residual.value, self.residual.threshold));
        }
        if !self.coverage.passed {
            out.push(format!("coverage: {:.0} bad cells > {:.1} allowed", self.coverage.value, self.coverage.threshold));
        }
        if !self.curvature_min.passed {
            out.push(format!("curvature {:.2} 1/m < {:.2} 1/m", self.curvature_min.value, self.curvature_min.threshold));
        }
        if !self.curvature_max.passed {
            out.push(format!("curvature {:.2} 1/m > {:.2} 1/m", self.curvature_max.value, self.curvature_max.threshold));
        }
        if let Some(t) = self.tilt.filter(|t| !t.passed) {
            out.push(format!("tilt {:.1}° > {:.1}°", t.value, t.threshold));
        }
        if let Some(t) = self.edge.filter(|t| !t.passed) {
            out.push(format!("edge: {:.3} m off the surface inside the foot disc > {:.3} m", t.value, t.threshold));
        }
        if let Some(t) = self.unseen.filter(|t| !t.passed) {
            out.push(format!(
                "unseen: {:.1} % of the foot disc's pixels did not measure its surface > {:.1} %",
                100.0 * t.value,
                100.0 * t.threshold
            ));
        }
        if let Some(t) = self.open_rim.filter(|t| !t.passed) {
            out.push(format!(
                "open_rim: {:.1} % of the foot disc's pixels see through it or into a hole at an edge > {:.1} %",
                100.0 * t.value,
                100.0 * t.threshold
            ));
        }
        if let Some(t) = self.out_of_view.filter(|t| !t.passed) {
            out.push(format!(
                "out_of_view: {:.1} % of the foot disc lies outside the image > {:.1} %",
                100.0 * t.value,
                100.0 * t.threshold
            ));
        }
        out
    }
}

/// Validate a fitted patch against its (full) neighbourhood points: J 3.3 and the edge test on the
/// neighbourhood (no gravity, no tilt test).
pub fn validate_patch(patch: &Patch, neighbourhood: &[Vector3<f64>], config: &ValidateConfig) -> Validation {
    validate_foothold(patch, neighbourhood, &Foothold::default(), config)
}

/// Validate a fitted patch as a foothold: J 3.3 on its neighbourhood, the tilt against
/// `foothold.up`, the edge test on `foothold.column` (the neighbourhood when `None`) and the
/// visibility test on `foothold.view`.
pub fn validate_foothold(patch: &Patch, neighbourhood: &[Vector3<f64>], foothold: &Foothold, config: &ValidateConfig) -> Validation {
    // The points in the patch frame once (eq 4), for both the residual and the coverage grid.
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = neighbourhood.iter().map(|q| query.to_local(q)).collect();
    let rho = residual::residual_local(&query, &local);
    let residual = TestResult { passed: rho <= config.residual_threshold, value: rho, threshold: config.residual_threshold };
    let sampled = foothold
        .sampled
        .filter(|_| config.coverage_within_sampled_ball)
        .map(|ball| SampledBall { centre: query.to_local(&ball.centre), ..ball });
    let column_local: Vec<Vector3<f64>> = match (&sampled, foothold.column) {
        (Some(_), Some(column)) => column.iter().map(|q| query.to_local(q)).collect(),
        _ => Vec::new(),
    };
    let sampled = sampled.as_ref().map(|ball| (ball, column_local.as_slice()));
    let (bad, allowed) = coverage::coverage_bad_cells_local(patch, query.shape(), &local, sampled, config);
    let coverage = TestResult { passed: bad as f64 <= allowed, value: bad as f64, threshold: allowed };
    let (kmin, kmax) = principal_curvature_range(patch);
    let tilt = foothold.up.map(|up| {
        let value = tilt_deg(patch, &up);
        TestResult { passed: value <= config.tilt_max_deg || config.tilt_max_deg >= 180.0, value, threshold: config.tilt_max_deg }
    });
    let edge = (config.edge_max_offset_m < f64::INFINITY).then(|| {
        let (value, _) = disc_offset(patch, foothold.column.unwrap_or(neighbourhood), foothold.up.as_ref(), config);
        TestResult::at_most(value, config.edge_max_offset_m)
    });
    let unseen = foothold
        .view
        .filter(|_| config.unseen_max_fraction < f64::INFINITY)
        .map(|view| TestResult::at_most(view.unseen_fraction(), config.unseen_max_fraction));
    let open_rim = foothold
        .view
        .filter(|_| config.open_rim_max_fraction < f64::INFINITY)
        .map(|view| TestResult::at_most(view.open_fraction(), config.open_rim_max_fraction));
    let out_of_view = foothold
        .out_of_view
        .filter(|_| config.out_of_view_max_fraction < f64::INFINITY)
        .map(|share| TestResult::at_most(share, config.out_of_view_max_fraction));
    Validation {
        residual,
        coverage,
        curvature_min: TestResult { passed: kmin >= config.curvature_min, value: kmin, threshold: config.curvature_min },
        curvature_max: TestResult { passed: kmax <= config.curvature_max, value: kmax, threshold: config.curvature_max },
        tilt,
        edge,
        unseen,
        open_rim,
        out_of_view,
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::patch::{BoundaryType, SurfaceType};
    use nalgebra::Vector2;
    use rand::SeedableRng;

    /// A plane disc of radius `r` at the origin facing +z.
    pub(crate) fn disk(r: f64) -> Patch {
        Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![r], Vector2::zeros(), Vector3::zeros(), Vector3::new(0.0, 0.0, 1.0))
            .unwrap()
    }

    #[test]
    fn good_patch_passes() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let pts = disk(0.1).sample_points(&mut rng, 3000);
        let v = validate_foothold(
            &disk(0.1),
            &pts,
            &Foothold { up: Some(Vector3::z()), column: None, sampled: None, view: None, out_of_view: None },
            &ValidateConfig::default(),
        );
        assert!(v.is_valid(), "{:?}", v.failures());
        assert!(v.residual.value < 1e-9);
        assert!(v.tilt.unwrap().value < 1e-9 && v.edge.unwrap().value < 1e-9);
    }

    #[test]
    fn empty_neighbourhood_is_invalid() {
        let v = validate_patch(&disk(0.1), &[], &ValidateConfig::default());
        assert!(!v.is_valid());
    }

    #[test]
    fn j33_runs_only_j_tests_and_bad_configs_are_refused() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let pts = disk(0.1).sample_points(&mut rng, 3000);
        let v = validate_foothold(
            &disk(0.1),
            &pts,
            &Foothold { up: Some(Vector3::x()), column: None, sampled: None, view: None, out_of_view: None },
            &ValidateConfig::j33(),
        );
        assert!(v.is_valid() && v.edge.is_none() && v.tilt.is_some_and(|t| t.passed && (t.value - 90.0).abs() < 1e-9), "{v:?}");
        assert!(ValidateConfig::default().check().is_ok() && ValidateConfig::j33().check().is_ok());
        let bad = ValidateConfig { edge_quantile: 0.0, ..ValidateConfig::default() };
        assert!(bad.check().unwrap_err().contains("validate.edge_quantile"));
        let bad = ValidateConfig { tilt_max_deg: f64::NAN, ..ValidateConfig::default() };
        assert!(bad.check().unwrap_err().contains("validate.tilt_max_deg"));
    }
}
