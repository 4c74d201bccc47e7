//! Scores of CNN III-D/E: the classification error (share of regions whose "a foothold exists"
//! decision at p ≥ 0.5 disagrees with the label) and the regression error (mean distance between the
//! predicted and the labelled foothold, in pixels of the 60 × 60 region as CNN Tables I–II, over the
//! true positives).

use crate::train::Prediction;

/// Counts and sums behind the two errors.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Scores {
    pub samples: usize,
    pub positives: usize,
    pub true_positives: usize,
    pub false_positives: usize,
    pub false_negatives: usize,
    regression_sum_px: f64,
}

impl Scores {
    /// Adds one region: its prediction (`None`: the method said "no foothold") against its label.
    pub fn add(&mut self, predicted: Option<(f64, f64)>, target: Option<(f64, f64)>, region_px: f64) {
        self.samples += 1;
        match (predicted, target) {
            (Some((x, y)), Some((tx, ty))) => {
                self.positives += 1;
                self.true_positives += 1;
                self.regression_sum_px += ((x - tx).powi(2) + (y - ty).powi(2)).sqrt() * region_px;
            }
            (None, Some(_)) => {
                self.positives += 1;
                self.false_negatives += 1;
            }
            (Some(_), None) => self.false_positives += 1,
            (None, None) => {}
        }
    }

    /// Scores predictions against targets at threshold 0.5.
    pub fn of(predictions: &[Prediction], targets: &[Option<(f32, f32)>], region_px: f64) -> Scores {
        let mut scores = Scores::default();
        for (p, t) in predictions.iter().zip(targets) {
            let predicted = (p.p >= 0.5).then(|| (f64::from(p.x), f64::from(p.y)));
            scores.add(predicted, t.map(|(x, y)| (f64::from(x), f64::from(y))), region_px);
        }
        scores
    }

    /// Adds another set of counts.
    pub fn merge(&mut self, other: &Scores) {
        self.samples += other.samples;
        self.positives += other.positives;
        self.true_positives += other.true_positives;
        self.false_positives += other.false_positives;
        self.false_negatives += other.false_negatives;
        self.regression_sum_px += other.regression_sum_px;
    }

    /// Share of misclassified regions (0..1).
    pub fn classification_error(&self) -> f64 {
        (self.false_positives + self.false_negatives) as f64 / self.samples.max(1) as f64
    }

    /// Mean regression error over the true positives (region pixels), NaN without any.
    pub fn regression_px(&self) -> f64 {
        if self.true_positives == 0 {
            f64::NAN
        } else {
            self.regression_sum_px / self.true_positives as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_count_both_kinds_and_regress_over_true_positives() {
        let predictions = [
            Prediction { p: 0.9, x: 0.5, y: 0.5 },
            Prediction { p: 0.2, x: 0.5, y: 0.5 },
            Prediction { p: 0.7, x: 0.1, y: 0.1 },
            Prediction { p: 0.1, x: 0.0, y: 0.0 },
        ];
        let targets = [Some((0.5, 0.6)), Some((0.4, 0.4)), None, None];
        let s = Scores::of(&predictions, &targets, 60.0);
        assert_eq!((s.true_positives, s.false_negatives, s.false_positives, s.positives), (1, 1, 1, 2));
        assert!((s.classification_error() - 0.5).abs() < 1e-12);
        assert!((s.regression_px() - 6.0).abs() < 1e-4, "{}", s.regression_px());
        assert!(Scores::default().regression_px().is_nan());
    }
}
