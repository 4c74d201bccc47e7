//! The hand-made-feature baseline of CNN III-E: per region the seven terrain features of the
//! quadruped foot-cost literature (standard deviation of the heights, maximum and minimum relative to
//! the centre, mean slope in x and y, mean curvature in x and y) on three centred windows of the
//! region's depth (10 × 10, 30 × 30, 50 × 50 of the 60 × 60 region), plus the camera tilt: 22 values.
//! A linear SVM (hinge loss, L2 regularisation, solved by dual coordinate descent, Hsieh et al.
//! ICML 2008) classifies, and a ridge regression on the positives gives (x, y).

use nalgebra::{DMatrix, DVector};
use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::error::FootholdError;
use crate::samples::SampleSet;
use crate::train::Prediction;

/// Window sides of the three scales at a 60 px region (CNN III-E), scaled with the region side.
pub const SCALES: [usize; 3] = [10, 30, 50];
/// 7 features × 3 scales + tilt.
pub const FEATURES: usize = 22;

/// The 22 features of one region input (its first channel, `side × side`) and tilt channel θ/90°.
pub fn features(depth: &[f32], side: usize, tilt_over_90: f32) -> [f64; FEATURES] {
    let mut out = [0.0; FEATURES];
    let at = |a: usize, b: usize| f64::from(depth[b * side + a]);
    let c = side / 2;
    let centre = (at(c - 1, c - 1) + at(c, c - 1) + at(c - 1, c) + at(c, c)) / 4.0;
    for (s, &scale) in SCALES.iter().enumerate() {
        let w = (scale * side / 60).clamp(3, side);
        let lo = c - w / 2;
        let hi = lo + w;
        let (mut sum, mut sq, mut max, mut min) = (0.0, 0.0, f64::NEG_INFINITY, f64::INFINITY);
        let (mut sx, mut sy, mut cx, mut cy) = (0.0, 0.0, 0.0, 0.0);
        for b in lo..hi {
            for a in lo..hi {
                let z = at(a, b);
                sum += z;
                sq += z * z;
                max = max.max(z);
                min = min.min(z);
                if a + 1 < hi {
                    sx += at(a + 1, b) - z;
                }
                if b + 1 < hi {
                    sy += at(a, b + 1) - z;
                }
                if a > lo && a + 1 < hi {
                    cx += at(a + 1, b) - 2.0 * z + at(a - 1, b);
                }
                if b > lo && b + 1 < hi {
                    cy += at(a, b + 1) - 2.0 * z + at(a, b - 1);
                }
            }
        }
        let n = (w * w) as f64;
        let mean = sum / n;
        let std = (sq / n - mean * mean).max(0.0).sqrt();
        let diffs = (w * (w - 1)) as f64;
        let seconds = (w * (w - 2)) as f64;
        let f = &mut out[7 * s..7 * s + 7];
        f.copy_from_slice(&[std, max - centre, min - centre, sx / diffs, sy / diffs, cx / seconds, cy / seconds]);
    }
    out[FEATURES - 1] = f64::from(tilt_over_90);
    out
}

/// Parameters of the SVM fit.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SvmConfig {
    /// C of the soft margin.
    pub c: f64,
    pub epochs: usize,
    /// Ridge regularisation of the (x, y) regression.
    pub ridge: f64,
    pub seed: u64,
    /// Leave the tilt feature out (zero).
    pub no_tilt: bool,
}

impl Default for SvmConfig {
    fn default() -> Self {
        Self { c: 1.0, epochs: 30, ridge: 1e-3, seed: 1, no_tilt: false }
    }
}

/// A fitted linear SVM with its feature standardisation and the (x, y) regression.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LinearSvm {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    /// Weights of the standardised features, then the bias.
    pub w: Vec<f64>,
    /// Ridge coefficients (standardised features, then bias) for x and for y.
    pub rx: Vec<f64>,
    pub ry: Vec<f64>,
    pub no_tilt: bool,
}

fn set_features(set: &SampleSet, no_tilt: bool) -> Vec<[f64; FEATURES]> {
    let s = set.regions.out_px;
    (0..set.len())
        .map(|i| {
            let mut f = features(&set.input(i)[..s * s], s, set.side[i][2]);
            if no_tilt {
                f[FEATURES - 1] = 0.0;
            }
            f
        })
        .collect()
}

impl LinearSvm {
    /// Fits the classifier and the regression on a set.
    pub fn fit(set: &SampleSet, config: &SvmConfig) -> Result<Self, FootholdError> {
        if set.is_empty() {
            return Err(FootholdError::Empty("no samples to fit the SVM on".into()));
        }
        let raw = set_features(set, config.no_tilt);
        let n = raw.len() as f64;
        let mean: Vec<f64> = (0..FEATURES).map(|j| raw.iter().map(|f| f[j]).sum::<f64>() / n).collect();
        let std: Vec<f64> = (0..FEATURES)
            .map(|j| (raw.iter().map(|f| (f[j] - mean[j]).powi(2)).sum::<f64>() / n).sqrt())
            .map(|s| if s > 1e-12 { s } else { 1.0 })
            .collect();
        let x: Vec<Vec<f64>> = raw.iter().map(|f| standardise(f, &mean, &std)).collect();
        let y: Vec<f64> = set.targets.iter().map(|t| if t.is_some() { 1.0 } else { -1.0 }).collect();
        // Dual coordinate descent for min ½|w|² + C Σ max(0, 1 − y wᵀx) (bias as a constant feature).
        let d = FEATURES + 1;
        let mut w = vec![0.0; d];
        let mut alpha = vec![0.0; x.len()];
        let q: Vec<f64> = x.iter().map(|xi| xi.iter().map(|v| v * v).sum::<f64>()).collect();
        let mut order: Vec<usize> = (0..x.len()).collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(config.seed);
        for _ in 0..config.epochs {
            order.shuffle(&mut rng);
            for &i in &order {
                let g = y[i] * dot(&w, &x[i]) - 1.0;
                let old = alpha[i];
                let new = (old - g / q[i]).clamp(0.0, config.c);
                if new != old {
                    let delta = (new - old) * y[i];
                    w.iter_mut().zip(&x[i]).for_each(|(wj, xj)| *wj += delta * xj);
                    alpha[i] = new;
                }
            }
        }
        // Ridge regression of (x, y) on the positives.
        let positives: Vec<usize> = (0..x.len()).filter(|&i| set.targets[i].is_some()).collect();
        let (rx, ry) = if positives.is_empty() {
            (vec![0.0; d], vec![0.0; d])
        } else {
            let a = DMatrix::from_fn(positives.len(), d, |r, c| x[positives[r]][c]);
            let mut ata = a.transpose() * &a;
            for k in 0..d {
                ata[(k, k)] += config.ridge * positives.len() as f64;
            }
            let target = |pick: fn((f32, f32)) -> f32| {
                DVector::from_iterator(positives.len(), positives.iter().map(|&i| set.targets[i].map_or(0.5, |t| f64::from(pick(t)))))
            };
            let solve = |b: DVector<f64>| -> Result<Vec<f64>, FootholdError> {
                let rhs = a.transpose() * b;
                ata.clone()
                    .cholesky()
                    .map(|c| c.solve(&rhs).iter().copied().collect())
                    .ok_or_else(|| FootholdError::Config("ridge system not positive definite".into()))
            };
            (solve(target(|t| t.0))?, solve(target(|t| t.1))?)
        };
        Ok(Self { mean, std, w, rx, ry, no_tilt: config.no_tilt })
    }

    /// Decision value and (x, y) of one feature vector; p is a logistic squashing of the margin
    /// (the sign is the SVM's class).
    pub fn predict_features(&self, raw: &[f64; FEATURES]) -> Prediction {
        let mut raw = *raw;
        if self.no_tilt {
            raw[FEATURES - 1] = 0.0;
        }
        let x = standardise(&raw, &self.mean, &self.std);
        let margin = dot(&self.w, &x);
        Prediction {
            p: (1.0 / (1.0 + (-2.0 * margin).exp())) as f32,
            x: dot(&self.rx, &x).clamp(0.0, 1.0) as f32,
            y: dot(&self.ry, &x).clamp(0.0, 1.0) as f32,
        }
    }

    /// Predictions for every sample of a set.
    pub fn predict(&self, set: &SampleSet) -> Vec<Prediction> {
        set_features(set, self.no_tilt).iter().map(|f| self.predict_features(f)).collect()
    }
}

fn standardise(f: &[f64; FEATURES], mean: &[f64], std: &[f64]) -> Vec<f64> {
    f.iter().zip(mean).zip(std).map(|((v, m), s)| (v - m) / s).chain(std::iter::once(1.0)).collect()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::regions::RegionConfig;
    use crate::samples::SampleMeta;

    #[test]
    fn features_of_a_ramp_and_a_bump() {
        let side = 60;
        let ramp: Vec<f32> = (0..side * side).map(|i| 0.01 * (i % side) as f32).collect();
        let f = features(&ramp, side, 0.5);
        // Slope x = 0.01 per cell at every scale, no slope in y, no curvature.
        for s in 0..3 {
            assert!((f[7 * s + 3] - 0.01).abs() < 1e-6 && f[7 * s + 4].abs() < 1e-9 && f[7 * s + 5].abs() < 1e-6, "{f:?}");
        }
        // Max/min relative to the centre over the 10 px window: 0.25..0.34 around 0.295.
        assert!((f[1] - 0.045).abs() < 1e-5 && (f[2] + 0.045).abs() < 1e-5, "{} {}", f[1], f[2]);
        assert_eq!(f[21], 0.5);
        let bump: Vec<f32> =
            (0..side * side).map(|i| -(((i % side) as f32 - 30.0).powi(2) + ((i / side) as f32 - 30.0).powi(2)) * 1e-4).collect();
        let f = features(&bump, side, 0.5);
        assert!(f[5] < 0.0 && f[6] < 0.0, "a cap curves down: {f:?}");
    }

    #[test]
    fn the_svm_separates_separable_classes() {
        let regions = RegionConfig { out_px: 60, ..RegionConfig::default() };
        let mut set = SampleSet::new(regions);
        for i in 0..40 {
            let positive = i % 2 == 0;
            let slope = if positive { 0.0 } else { 0.02 } + 0.001 * (i % 5) as f32;
            set.inputs.extend((0..3600).map(|k| slope * (k % 60) as f32));
            set.side.push([0.7, 0.7, 0.5]);
            set.targets.push(positive.then_some((0.3 + 0.01 * (i % 5) as f32, 0.5)));
            set.meta.push(SampleMeta {
                scene: "s".into(),
                frame: i,
                u: 0.0,
                v: 0.0,
                size_px: 60,
                depth_m: 0.5,
                tilt_deg: 45.0,
                augmented: false,
            });
        }
        let svm = LinearSvm::fit(&set, &SvmConfig::default()).unwrap();
        let predictions = svm.predict(&set);
        let errors = predictions.iter().zip(&set.targets).filter(|(p, t)| (p.p >= 0.5) != t.is_some()).count();
        assert_eq!(errors, 0);
        assert!(LinearSvm::fit(&SampleSet::new(set.regions.clone()), &SvmConfig::default()).is_err());
    }
}
