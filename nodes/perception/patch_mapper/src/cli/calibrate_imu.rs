//! `patch_mapper calibrate-imu <dataset>`: IMU→camera rotation by orthogonal Procrustes on frames of a
//! dominant horizontal plane (J 2.2); prints the rotation and the residual angles.

use std::path::PathBuf;

use anyhow::Context;
use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::dataset::Dataset;

/// Arguments of `patch_mapper calibrate-imu`.
#[derive(clap::Args, Debug)]
pub struct CalibrateImuArgs {
    /// Dataset with depth frames and accelerometer data (TUM layout) whose dominant plane is horizontal.
    pub dataset: PathBuf,
    /// Use every n-th frame.
    #[arg(long, default_value_t = 1)]
    pub frame_stride: usize,
    /// RANSAC plane inlier distance (m).
    #[arg(long, default_value_t = CalibrationConfig::default().plane_inlier_m)]
    pub plane_inlier_m: f64,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: CalibrateImuArgs) -> anyhow::Result<()> {
    let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let config =
        CalibrationConfig { frame_stride: args.frame_stride.max(1), plane_inlier_m: args.plane_inlier_m, ..CalibrationConfig::default() };
    let calibration = calibrate_dataset(&dataset, &config)?;
    let q = calibration.camera_from_imu;
    let matrix = q.to_rotation_matrix().into_inner();
    let (roll, pitch, yaw) = q.euler_angles();
    if args.json {
        let value = serde_json::json!({
            "camera_from_imu": { "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w },
            "matrix_row_major": matrix.transpose().as_slice(),
            "rms_residual_deg": calibration.rms_residual_deg,
            "max_residual_deg": calibration.max_residual_deg,
            "singular_values": calibration.singular_values,
            "pairs": calibration.pairs,
        });
        println!("{}", serde_json::to_string_pretty(&value)?);
        return Ok(());
    }
    println!("camera_from_imu from {} frame pairs (plane normal ↔ accelerometer gravity):", calibration.pairs);
    println!("  quaternion (x y z w): {:.5} {:.5} {:.5} {:.5}", q.i, q.j, q.k, q.w);
    println!("  angle {:.2} deg about axis {:?}", q.angle().to_degrees(), q.axis().map(|a| [a.x, a.y, a.z]));
    println!("  roll/pitch/yaw (deg): {:.2} {:.2} {:.2}", roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees());
    for r in 0..3 {
        println!("  [{:8.5} {:8.5} {:8.5}]", matrix[(r, 0)], matrix[(r, 1)], matrix[(r, 2)]);
    }
    println!("  residual angle: RMS {:.2} deg, max {:.2} deg", calibration.rms_residual_deg, calibration.max_residual_deg);
    let [s0, s1, s2] = calibration.singular_values;
    println!("  singular values {s0:.3} {s1:.3} {s2:.3}");
    if s1 < 0.05 * s0 {
        println!(
            "  note: the gravity directions span ~one axis (camera barely tilted), so the rotation about gravity \
             is unobservable; only the gravity direction mapping is reliable"
        );
    }
    Ok(())
}
