//! Range-sensor point covariances: Murray–Little pointing/disparity model (J eq 2) and the constant /
//! linear / quadratic range models (thesis ch. 3.1).
//!
//! Points are given in the sensor (camera optical) frame: x right, y down, z forward, origin at the
//! centre of projection. The covariances are 3×3 in the same frame.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// Parameters of the Murray–Little pointing/disparity model (J eq 2).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StereoErrorParams {
    /// Pointing error σp (px, standard deviation; E holds σp²). Kinect: 0.35 px (J 2.1, from
    /// Konolige–Mihelich).
    pub sigma_pointing_px: f64,
    /// Disparity matching error σm (px, standard deviation; E holds σm²). Kinect: 0.17 px (J 2.1).
    pub sigma_disparity_px: f64,
    /// Stereo baseline b (m). Kinect IR projector–camera baseline: 0.075 m (Konolige–Mihelich).
    pub baseline_m: f64,
    /// Focal length f_x (px). Kinect IR camera: 580 px (Konolige–Mihelich).
    pub focal_px: f64,
}

impl Default for StereoErrorParams {
    /// The Kinect values of J 2.1 / IROS IV-B.
    fn default() -> Self {
        Self { sigma_pointing_px: 0.35, sigma_disparity_px: 0.17, baseline_m: 0.075, focal_px: 580.0 }
    }
}

/// Range-sensor error model (thesis ch. 3.1, J eq 2).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum ErrorModel {
    /// Constant range uncertainty σ (m) along the measurement ray, none in pointing.
    Constant { sigma_m: f64 },
    /// Range uncertainty `a·ρ` growing linearly with the range ρ, none in pointing.
    Linear { factor: f64 },
    /// Range uncertainty `a·ρ²` growing quadratically with the range ρ, none in pointing.
    Quadratic { factor: f64 },
    /// Murray–Little pointing/disparity stereo model (J eq 2).
    MurrayLittle(StereoErrorParams),
}

impl Default for ErrorModel {
    fn default() -> Self {
        ErrorModel::MurrayLittle(StereoErrorParams::default())
    }
}

/// Errors of the error models.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SensorError {
    /// The point is at or behind the sensor (z ≤ 0 for the stereo model, or at the origin).
    #[error("point {0:?} is not in front of the sensor")]
    BehindSensor([f64; 3]),
    /// A negative or non-finite model parameter.
    #[error("invalid error-model parameter: {0}")]
    InvalidParameter(&'static str),
}

impl ErrorModel {
    /// Covariance (3×3, sensor frame) of a point measured at `point_in_sensor`.
    pub fn covariance(&self, point_in_sensor: &Vector3<f64>) -> Result<Matrix3<f64>, SensorError> {
        let range = point_in_sensor.norm();
        if !range.is_finite() || range <= 0.0 {
            return Err(SensorError::BehindSensor([point_in_sensor.x, point_in_sensor.y, point_in_sensor.z]));
        }
        let ray = point_in_sensor / range;
        let along_ray = |sigma: f64| ray * ray.transpose() * (sigma * sigma);
        match *self {
            ErrorModel::Constant { sigma_m } => {
                check(sigma_m, "sigma_m")?;
                Ok(along_ray(sigma_m))
            }
            ErrorModel::Linear { factor } => {
                check(factor, "factor")?;
                Ok(along_ray(factor * range))
            }
            ErrorModel::Quadratic { factor } => {
                check(factor, "factor")?;
                Ok(along_ray(factor * range * range))
            }
            ErrorModel::MurrayLittle(p) => murray_little(point_in_sensor, &p),
        }
    }
}

fn check(v: f64, name: &'static str) -> Result<(), SensorError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(SensorError::InvalidParameter(name))
    }
}

/// Murray–Little covariance `Σ = J E Jᵀ` (J eq 2) with `E = diag(σp², σp², σm²)`, `d = f b / z`,
/// `(u, v) = f (x, y) / z` the pixel offsets from the principal point and
/// `J = [[b/d, 0, −b u/d²], [0, b/d, −b v/d²], [0, 0, −f b/d²]]`.
///
/// J eq 2 prints E with σp, σm on the diagonal and calls them variances, but gives their values in
/// pixels (IROS IV-B: "σ_pointing = 0.35px, σ_disparity = 0.17px"); we read them as standard deviations,
/// which gives σ_z ≈ 3.9 mm at 1 m for the Kinect (the variance reading would give 9.5 mm, well above
/// published Kinect depth noise).
pub fn murray_little(point_in_sensor: &Vector3<f64>, p: &StereoErrorParams) -> Result<Matrix3<f64>, SensorError> {
    check(p.sigma_pointing_px, "sigma_pointing_px")?;
    check(p.sigma_disparity_px, "sigma_disparity_px")?;
    if !(p.baseline_m > 0.0 && p.focal_px > 0.0) {
        return Err(SensorError::InvalidParameter("baseline_m and focal_px must be positive"));
    }
    let z = point_in_sensor.z;
    if !(z > 0.0 && z.is_finite()) {
        return Err(SensorError::BehindSensor([point_in_sensor.x, point_in_sensor.y, z]));
    }
    let (f, b) = (p.focal_px, p.baseline_m);
    let d = f * b / z;
    let u = f * point_in_sensor.x / z;
    let v = f * point_in_sensor.y / z;
    let jac = Matrix3::new(b / d, 0.0, -b * u / (d * d), 0.0, b / d, -b * v / (d * d), 0.0, 0.0, -f * b / (d * d));
    let e = Matrix3::from_diagonal(&Vector3::new(p.sigma_pointing_px.powi(2), p.sigma_pointing_px.powi(2), p.sigma_disparity_px.powi(2)));
    Ok(jac * e * jac.transpose())
}

/// Covariances for points given in any frame whose axes are those of the sensor, with the sensor at
/// `sensor_origin` (e.g. camera-frame points with origin 0).
pub fn covariances_for(
    points: &[Vector3<f64>],
    sensor_origin: &Vector3<f64>,
    model: &ErrorModel,
) -> Result<Vec<Matrix3<f64>>, SensorError> {
    points.iter().map(|q| model.covariance(&(q - sensor_origin))).collect()
}

/// Draw a noisy measurement of `point_in_sensor` from `N(point, Σ)` (used by tests, benches and the
/// simulator): `Σ = L Lᵀ`, sample `L n` with `n ~ N(0, I)`.
pub fn sample_noise<R: rand::Rng + ?Sized>(rng: &mut R, covariance: &Matrix3<f64>) -> Vector3<f64> {
    use rand_distr::{Distribution, StandardNormal};
    let n = Vector3::new(StandardNormal.sample(rng), StandardNormal.sample(rng), StandardNormal.sample(rng));
    // Eigen-decomposition handles semi-definite (rank-1 range models) covariances.
    let eig = covariance.symmetric_eigen();
    let sqrt = eig.eigenvalues.map(|l| l.max(0.0).sqrt());
    eig.eigenvectors * Matrix3::from_diagonal(&sqrt) * n
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn murray_little_is_elongated_along_the_ray_and_grows_quadratically() {
        let model = ErrorModel::default();
        let q = Vector3::new(0.2, -0.1, 1.0);
        let c1 = model.covariance(&q).unwrap();
        let eig = c1.symmetric_eigen();
        let (imax, _) = eig.eigenvalues.iter().enumerate().fold((0, f64::MIN), |a, (i, &v)| if v > a.1 { (i, v) } else { a });
        let axis = eig.eigenvectors.column(imax).into_owned();
        assert!(axis.normalize().dot(&q.normalize()).abs() > 0.999);
        // Depth std grows with z²: σz(2m)/σz(1m) = 4.
        let c2 = model.covariance(&(q * 2.0)).unwrap();
        assert!(((c2[(2, 2)] / c1[(2, 2)]).sqrt() - 4.0).abs() < 0.05);
        // Known value at 1 m on the axis: σz = z² σm / (f b).
        let c0 = model.covariance(&Vector3::new(0.0, 0.0, 1.0)).unwrap();
        assert!((c0[(2, 2)].sqrt() - 0.17 / (580.0f64 * 0.075)).abs() < 1e-12);
        assert!(model.covariance(&Vector3::new(0.0, 0.0, -1.0)).is_err());
    }

    #[test]
    fn range_models_and_sampling() {
        let q = Vector3::new(0.0, 0.6, 0.8);
        let c = ErrorModel::Linear { factor: 0.01 }.covariance(&q).unwrap();
        assert!(((q.normalize().transpose() * c * q.normalize())[(0, 0)] - 1e-4).abs() < 1e-12);
        let cq = ErrorModel::Quadratic { factor: 0.01 }.covariance(&(q * 2.0)).unwrap();
        assert!((cq.trace() - (0.04f64).powi(2)).abs() < 1e-12);
        assert!(ErrorModel::Constant { sigma_m: -1.0 }.covariance(&q).is_err());
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let n = 20_000;
        let mut acc = Matrix3::zeros();
        let cov = ErrorModel::default().covariance(&Vector3::new(0.1, 0.2, 1.2)).unwrap();
        for _ in 0..n {
            let e = sample_noise(&mut rng, &cov);
            acc += e * e.transpose();
        }
        acc /= n as f64;
        assert!((acc - cov).norm() / cov.norm() < 0.05);
    }
}
