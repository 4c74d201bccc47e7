//! `terrain_sim` binary: publishes simulated depth, CameraInfo and IMU like the real sensors.
fn main() -> std::process::ExitCode {
    eprintln!("terrain_sim: not available yet");
    std::process::ExitCode::FAILURE
}
