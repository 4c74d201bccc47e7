//! `patch_mapper calibrate-imu` (placeholder until its issue lands).

/// Arguments of `patch_mapper calibrate-imu`.
#[derive(clap::Args, Debug)]
pub struct CalibrateImuArgs {}

pub fn run(_args: CalibrateImuArgs) -> anyhow::Result<()> {
    anyhow::bail!("`calibrate-imu` is not available yet")
}
