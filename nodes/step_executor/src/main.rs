//! `step_executor` binary: the ROS 2 execution node and the simulated servo bus.
fn main() -> std::process::ExitCode {
    eprintln!("step_executor: not available yet");
    std::process::ExitCode::FAILURE
}
