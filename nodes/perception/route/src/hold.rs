//! Footholds: the planner's input, from any source (CNN predictions, the patch pipeline's valid
//! patches, a file). CNN IV's hold set H: positions projected into 3D in the fixed, gravity-aligned
//! frame (z up), each with a score in [0, 1] (the predictor's probability; 1 for a validated patch).

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::RouteError;

/// One foothold: the sole centre's position in the fixed frame (m) and its score in [0, 1].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Hold {
    /// `[x, y, z]` in the fixed frame (m, z up).
    pub position: [f64; 3],
    /// How sure the source is that this is a foothold, in [0, 1].
    pub score: f64,
}

impl Hold {
    /// A hold at `position` with `score`.
    pub fn new(position: Vector3<f64>, score: f64) -> Self {
        Self { position: [position.x, position.y, position.z], score }
    }

    /// The position as a vector.
    pub fn point(&self) -> Vector3<f64> {
        Vector3::new(self.position[0], self.position[1], self.position[2])
    }
}

/// Checks every hold (finite position, score in [0, 1]) and keeps those scoring at least `min_score`.
pub fn usable_holds(holds: &[Hold], min_score: f64) -> Result<Vec<Hold>, RouteError> {
    if holds.is_empty() {
        return Err(RouteError::NoHolds);
    }
    for (index, hold) in holds.iter().enumerate() {
        let [x, y, z] = hold.position;
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(RouteError::NonFiniteHold { index, x, y, z });
        }
        if !(0.0..=1.0).contains(&hold.score) {
            return Err(RouteError::BadScore { index, score: hold.score });
        }
    }
    let kept: Vec<Hold> = holds.iter().copied().filter(|h| h.score >= min_score).collect();
    if kept.is_empty() {
        return Err(RouteError::NoHoldAboveScore { count: holds.len(), min_score });
    }
    Ok(kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_holds_are_named() {
        assert_eq!(usable_holds(&[], 0.5), Err(RouteError::NoHolds));
        let good = Hold::new(Vector3::new(1.0, 0.0, 0.0), 0.9);
        let nan = Hold { position: [0.0, f64::NAN, 0.0], score: 1.0 };
        assert!(matches!(usable_holds(&[good, nan], 0.5), Err(RouteError::NonFiniteHold { index: 1, .. })));
        let inf = Hold { position: [f64::INFINITY, 0.0, 0.0], score: 1.0 };
        assert!(matches!(usable_holds(&[inf], 0.5), Err(RouteError::NonFiniteHold { index: 0, .. })));
        let score = Hold { position: [0.0; 3], score: 1.5 };
        assert_eq!(usable_holds(&[good, score], 0.5), Err(RouteError::BadScore { index: 1, score: 1.5 }));
        let nan_score = Hold { position: [0.0; 3], score: f64::NAN };
        assert!(matches!(usable_holds(&[nan_score], 0.5), Err(RouteError::BadScore { index: 0, .. })));
        let weak = Hold::new(Vector3::zeros(), 0.2);
        assert_eq!(usable_holds(&[weak], 0.5), Err(RouteError::NoHoldAboveScore { count: 1, min_score: 0.5 }));
        assert_eq!(usable_holds(&[weak, good], 0.5), Ok(vec![good]));
    }

    #[test]
    fn holds_read_from_json() {
        let holds: Vec<Hold> = serde_json::from_str(r#"[{"position": [0.1, 0.2, -0.3], "score": 0.75}]"#).unwrap();
        assert_eq!(holds[0].point(), Vector3::new(0.1, 0.2, -0.3));
        assert_eq!(holds[0].score, 0.75);
    }
}
