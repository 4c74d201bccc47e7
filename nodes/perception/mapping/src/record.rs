//! The JSON record of one patch, the same in every output of the `patch_mapper` CLIs (`fit`, `map`,
//! `replay`): the SPL's [`Patch`] in its JSON form (surface, boundary, curvatures, boundary
//! parameters, rotation, centre, minimal parameters, covariance, residual, point count) and J 3.3's
//! verdict on it.
//!
//! A CLI line flattens this record next to its own context fields (frame, timestamp, seed cell,
//! map id, ...), so every patch line parses into a [`PatchRecord`].

use patchwalk_spl::patch::Patch;
use patchwalk_spl::validate::Validation;
use serde::{Deserialize, Serialize};

use crate::mapper::Verdict;

/// One patch and what validation (J 3.3) said about it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatchRecord {
    /// The patch (the SPL's JSON form of [`Patch`]).
    #[serde(flatten)]
    pub patch: Patch,
    /// Whether the patch passed every validation test (J 3.3's residual, coverage and curvature,
    /// the foothold tests tilt and edge).
    pub valid: bool,
    /// The verdict name ([`Verdict::name`]): `valid`, `residual`, `coverage`, `curvature` (the
    /// first failed test in J's order), `tilt`, `edge` or `fit_failed`.
    pub verdict: String,
    /// One line per failed test (or the fit error); empty for a valid patch.
    pub failures: Vec<String>,
}

impl PatchRecord {
    /// A patch with the verdict of its validation.
    pub fn validated(patch: Patch, validation: &Validation) -> Self {
        let verdict = Verdict::from_validation(validation);
        Self { patch, valid: verdict.is_valid(), verdict: verdict.name().to_string(), failures: validation.failures() }
    }

    /// A patch with a verdict the mapper reached (and the validation it came from, if any).
    pub fn with_verdict(patch: Patch, verdict: &Verdict, validation: Option<&Validation>) -> Self {
        let failures = match verdict {
            Verdict::FitFailed(why) => vec![why.clone()],
            _ => validation.map(Validation::failures).unwrap_or_default(),
        };
        Self { patch, valid: verdict.is_valid(), verdict: verdict.name().to_string(), failures }
    }

    /// A patch of the patch map (valid by construction).
    pub fn mapped(patch: Patch) -> Self {
        Self { patch, valid: true, verdict: Verdict::Valid { id: 0 }.name().to_string(), failures: Vec::new() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Vector2, Vector3};
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};
    use patchwalk_spl::validate::{validate_patch, ValidateConfig};

    fn disc() -> Patch {
        Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![0.05], Vector2::zeros(), Vector3::zeros(), Vector3::new(0.0, 0.0, 1.0))
            .unwrap()
    }

    #[test]
    fn record_round_trips_through_json_with_the_patch_fields_flat() {
        let record = PatchRecord::mapped(disc());
        let text = serde_json::to_string(&record).unwrap();
        let value: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(value["surface"], "plane");
        assert_eq!(value["valid"], true);
        assert_eq!(value["verdict"], "valid");
        assert_eq!(serde_json::from_str::<PatchRecord>(&text).unwrap(), record);
    }

    #[test]
    fn a_failed_validation_names_its_test() {
        // No points near the patch: the coverage test fails.
        let far: Vec<Vector3<f64>> = (0..50).map(|i| Vector3::new(1.0 + f64::from(i) * 1e-3, 0.0, 1.0)).collect();
        let validation = validate_patch(&disc(), &far, &ValidateConfig::default());
        let record = PatchRecord::validated(disc(), &validation);
        assert!(!record.valid);
        assert_ne!(record.verdict, "valid");
        assert!(!record.failures.is_empty());
        let fit_failed = PatchRecord::with_verdict(disc(), &Verdict::FitFailed("degenerate".into()), None);
        assert_eq!(
            (fit_failed.valid, fit_failed.verdict.as_str(), fit_failed.failures),
            (false, "fit_failed", vec!["degenerate".to_string()])
        );
    }
}
